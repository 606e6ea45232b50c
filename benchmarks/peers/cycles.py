"""A full flowsynth sample beside Blender Cycles' 1-spp render passes of the same scene, on one CPU core.

    taskset -c 0 python benchmarks/peers/cycles.py [--quick] [--repeat N] [--blender PATH]

Issue 13 (whole samples): "the full sample is depth, normals, ids, forward and backward flow, occlusion and
direct RGB, 2 frames, 512x384, 20 objects. Goal: at least 5x faster than Cycles on one core."

Scene: ``sample_scene(_common.full_sample_config(), 0, 0)`` (512x384, 2 frames, direct RGB, 20 things and the room,
a static camera; a moving one before issue 41). Its sampling (layout + physics) is timed apart.

- flowsynth: ``render_plan`` of rgb (direct: lights and shadows), depth, normals, instance, flow_fw,
  flow_bw, occ_fw, occ_bw, valid_fw, valid_bw (exact occlusion), ``threads=1``, torch 1 thread, the process
  pinned to one CPU (``pin_single_core``); median of ``--repeat`` calls after one warm-up. Beside it, timed
  round-robin, the same without rgb and only the keys Cycles' passes hold (depth, normals, instance, flow
  fw/bw), so the cost of the shading and of the occlusion masks shows.
- Cycles (only where ``blender`` is on PATH or given with ``--blender``; otherwise the script prints a
  "not installed" row and exits 0): the same triangles (object-frame meshes with one keyframe per frame
  for world_T_obj), camera (K -> focal length, principal point -> shift; OpenCV axes -> Blender's) and
  lights (point -> hard point light of power 4 pi^2 I, directional -> sun of strength pi I, ambient ->
  world colour; materials -> Principled BSDF of the mean base colour, roughness and specular: RGB is an
  approximation, textures are left out), built by ``benchmarks/peers/_cycles_scene.py`` in ``blender -b
  --factory-startup``. Cycles on the CPU, 1 sample, FIXED 1 thread (and the same pinned CPU, inherited),
  passes Combined, Z, Normal, Vector, IndexOB; two light-path settings: "direct" (max_bounces 0: direct
  light with shadows, like flowsynth's mode) and "path" (Cycles' defaults, 12 bounces). Render time is
  taken inside Blender around ``bpy.ops.render.render`` (scene sync + BVH build + render, per frame,
  median of ``--repeat``); Blender's start-up and the scene build are reported apart.

Cycles has no occlusion or validity masks, and its Vector pass (pixel motion to the previous and next
frame) comes from its own evaluation of the keyframed motion; flowsynth's sample holds more. The ratio
is on process CPU time (the work; both run on one pinned core, so wall time also counts other processes).

Sanity check (not a test): on pixels where both hit, the share whose ids agree (Cycles' object index is
set to the flowsynth instance id), Cycles' Z against flowsynth's planar depth (and ray length), the angle
between normals and the end-point error of Cycles' vector pass against flow_fw / flow_bw.

Writes benchmarks/results/cycles.json (or cycles_quick.json) with the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parents[1])]
from _common import (
    FULL_SAMPLE,
    FULL_SAMPLE_OUTPUTS,
    RESULTS_DIR,
    Timer,
    full_sample_config,
    machine_info,
    pin_single_core,
    print_table,
    time_calls,
    time_round_robin,
    write_json,
)

OUTPUTS = list(FULL_SAMPLE_OUTPUTS)
NO_RGB = [k for k in OUTPUTS if k != "rgb"]
PASSES = ["depth", "normals", "instance", "flow_fw", "flow_bw"]  # what Cycles' Z/Normal/IndexOB/Vector hold
W, H, T = FULL_SAMPLE["width"], FULL_SAMPLE["height"], FULL_SAMPLE["num_frames"]
NUM_OBJECTS = FULL_SAMPLE["num_objects"][1]
GOAL = 5.0  # Cycles / flowsynth, on one core
COLUMNS = ["engine", "what", "cpu s", "wall s", "cycles/flowsynth", "goal", "met"]


def _skip(blender: str, name: str) -> None:
    msg = f"SKIPPED: Blender not installed ({blender!r} not found); Cycles comparison not run"
    print(msg)
    print_table([{"engine": "Cycles", "what": "not installed"}], COLUMNS)
    if not (RESULTS_DIR / f"{name}.json").exists():  # a machine without Blender keeps the measured record
        write_json(name, {"machine": machine_info(), "skipped": msg})


def export_scene(scene, path: Path, depth_median: float) -> None:
    """Write what ``_cycles_scene.py`` needs to rebuild ``scene`` in Blender (meshes, poses, camera, lights), as
    JSON: a distribution's Blender may run on a system Python without numpy."""
    import numpy as np

    from flowsynth.appearance import resolve_lights, srgb_to_linear

    d = {"num_frames": scene.num_frames, "width": scene.camera.width, "height": scene.camera.height,
         "K": scene.camera.K.tolist(), "world_T_cam": scene.world_T_cam.tolist(), "fps": scene.fps, "meshes": {},
         "instances": [], "assets": [], "poses": [], "colors": [], "roughness": [], "specular": []}
    for o in scene.objects:
        d["meshes"].setdefault(str(o.asset), (np.asarray(o.mesh.vertices, np.float64).tolist(),
                                              np.asarray(o.mesh.faces, np.int64).tolist()))
        m = o.material
        layer = m if "colors" in m else (m.get("layers") or [{}])[0]
        c = np.asarray(layer.get("colors", [[0.8, 0.8, 0.8]]), np.float64).reshape(-1, 3)
        d["instances"].append(o.instance)
        d["assets"].append(o.asset)
        d["poses"].append(o.poses.tolist())
        d["colors"].append(srgb_to_linear(c).mean(0).tolist())
        d["roughness"].append(float(m.get("roughness", 0.5)))
        d["specular"].append(float(m.get("specular", 0.0)))
    lights = resolve_lights(scene.lights, scene.world_T_cam[0], depth_median)
    d.update(light_kind=[x.kind for x in lights], light_color=[list(x.color) for x in lights],
             light_intensity=[x.intensity for x in lights], light_direction=[list(x.direction) for x in lights],
             light_position=[list(x.position) for x in lights])
    path.write_text(json.dumps(d))


def read_exr(path: str) -> dict:
    """Channels of a Blender multilayer EXR as {"Pass.C": (H, W) float32}, view-layer prefix dropped."""
    import numpy as np
    import OpenEXR

    out = {}
    with OpenEXR.File(path, separate_channels=True) as f:
        for name, ch in f.channels().items():
            out[name.split(".", 1)[1] if name.count(".") >= 2 else name] = np.asarray(ch.pixels, np.float32)
    return out


def run_blender(blender: str, scene_json: Path, out: Path, config: str, repeat: int) -> dict:
    cmd = [blender, "-b", "--factory-startup", "-noaudio", "--python-exit-code", "1", "-P",
           str(HERE / "_cycles_scene.py"), "--", str(scene_json), str(out), config, str(repeat)]
    t_launch, w0 = time.time(), time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    total = time.perf_counter() - w0
    info_path = out / f"cycles_{config}.json"
    if r.returncode != 0 or not info_path.exists():
        raise RuntimeError(f"blender failed (exit {r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    info = json.loads(info_path.read_text())
    info["startup_s"] = info["t_script"] - t_launch
    info["process_wall_s"] = total
    info["render_wall_s"] = sum(statistics.median(f["wall_s"]) for f in info["frames"])
    info["render_cpu_s"] = sum(statistics.median(f["cpu_s"]) for f in info["frames"])
    return info


def compare(sample: dict, scene, frames: list[dict]) -> list[dict]:
    """Loose agreement of Cycles' passes with flowsynth's sample, per frame (pixels both hit)."""
    import numpy as np

    K = scene.camera.K
    jj, ii = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    ray = np.stack([(jj - K[0, 2]) / K[0, 0], (ii - K[1, 2]) / K[1, 1], np.ones_like(jj)])
    ray_len = np.linalg.norm(ray, axis=0)  # distance = depth * ray_len
    rows = []
    for t, fr in enumerate(frames):
        c = read_exr(fr["exr"])
        z, idx = c["Depth.Z"], np.rint(c["IndexOB.X"]).astype(np.int64)
        n_w = np.stack([c["Normal.X"], c["Normal.Y"], c["Normal.Z"]])
        vec = np.stack([c[f"Vector.{k}"] for k in "XYZW"])
        inst = sample["instance"][t, 0].numpy().astype(np.int64)
        depth = sample["depth"][t, 0].numpy().astype(np.float64)
        both = (inst > 0) & (idx > 0)
        either = (inst > 0) | (idx > 0)
        same = both & (inst == idx)
        rel = np.abs(z[same] - depth[same]) / depth[same]
        rel_dist = np.abs(z[same] - depth[same] * ray_len[same]) / (depth[same] * ray_len[same])
        R = scene.cam_T_world[t][:3, :3]
        n_c = np.einsum("ab,bhw->ahw", R, n_w)
        nf = sample["normals"][t].numpy()
        cosang = np.clip(np.abs((n_c * nf).sum(0)[same]) / np.maximum(np.linalg.norm(n_c, axis=0)[same], 1e-12), 0, 1)
        row = {"frame": t, "both hit %": 100 * both.sum() / both.size,
               "ids agree %": 100 * (inst == idx)[either].mean(),
               "Z vs depth med rel": float(np.median(rel)), "Z vs ray length med rel": float(np.median(rel_dist)),
               "normal med deg": float(np.degrees(np.arccos(np.median(cosang))))}
        # Cycles' Vector pass holds (previous - centre, centre - next) in Blender pixels (y up), as measured on
        # this scene (the other signs give an end-point error of twice the flow): flow_fw = (-z, w) at frame 0,
        # flow_bw (frame 1 -> 0) = (x, -y) at frame 1.
        if t == 0:
            key, fc = "fw", np.stack([-vec[2], vec[3]])
        else:
            key, fc = "bw", np.stack([vec[0], -vec[1]])
        ff = sample[f"flow_{key}"][0].numpy()
        ok = same & sample[f"valid_{key}"][0, 0].numpy()
        row["flow"] = key
        row["flow med EPE px"] = float(np.median(np.linalg.norm(fc - ff, axis=0)[ok]))
        row["flow med |f| px"] = float(np.median(np.linalg.norm(ff, axis=0)[ok]))
        rows.append(row)
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="2 repeats instead of 3, no warm scene-sampling time")
    p.add_argument("--repeat", type=int, default=None)
    p.add_argument("--blender", default="blender")
    args = p.parse_args()
    name = "cycles_quick" if args.quick else "cycles"
    repeat = args.repeat or (2 if args.quick else 3)
    blender = shutil.which(args.blender)
    if blender is None:
        _skip(args.blender, name)
        return 0
    pinning = pin_single_core()

    import torch

    torch.set_num_threads(1)
    from flowsynth.plan import make_plan
    from flowsynth.renderer import render_plan
    from flowsynth.scene import sample_scene

    cfg = full_sample_config()
    with Timer() as cold:
        scene = sample_scene(cfg, 0, 0)
    sampling = {"cold_wall_s": cold.wall_s, "cold_cpu_s": cold.cpu_s}
    if not args.quick:
        s = time_calls(lambda: sample_scene(cfg, 0, 0), repeat=1, warmup=0)
        sampling.update(wall_s=s["wall_s"], cpu_s=s["cpu_s"])
    plan = make_plan(OUTPUTS, render_mode="direct", threads=1)
    with Timer() as first:
        sample = render_plan(scene, plan)
    first_s = first.wall_s
    plans = {"full": plan, "no rgb": make_plan(NO_RGB, threads=1), "passes": make_plan(PASSES, threads=1)}
    fs_all = time_round_robin({k: (lambda p=p: render_plan(scene, p)) for k, p in plans.items()}, repeat=repeat,
                              warmup=1)
    fs_t = fs_all["full"]

    rows = [{"engine": "flowsynth", "what": f"full sample ({len(OUTPUTS)} keys, direct rgb)",
             "cpu s": fs_t["cpu_s"], "wall s": fs_t["wall_s"]},
            {"engine": "flowsynth", "what": "without rgb",
             "cpu s": fs_all["no rgb"]["cpu_s"], "wall s": fs_all["no rgb"]["wall_s"]},
            {"engine": "flowsynth", "what": "Cycles' passes only (no rgb, occ, valid)",
             "cpu s": fs_all["passes"]["cpu_s"], "wall s": fs_all["passes"]["wall_s"]},
            {"engine": "flowsynth", "what": "scene sampling " + ("(cold, once)" if args.quick else "(warm, once)"),
             "cpu s": sampling.get("cpu_s", sampling["cold_cpu_s"]),
             "wall s": sampling.get("wall_s", sampling["cold_wall_s"])}]
    cycles, checks = {}, {}
    with tempfile.TemporaryDirectory(prefix="fs_cycles_") as tmp:
        tmp = Path(tmp)
        depth = sample["depth"][0].numpy()
        export_scene(scene, tmp / "scene.json", float(torch.tensor(depth[depth > 0]).median()) if (depth > 0).any()
                     else 1.0)
        for config, label in (("direct", "direct light (0 bounces)"), ("path", "path traced (12 bounces)")):
            info = run_blender(blender, tmp / "scene.json", tmp, config, repeat)
            cycles[config] = info
            ratio = info["render_cpu_s"] / fs_t["cpu_s"]
            rows.append({"engine": f"Cycles {info['blender']}", "what": f"1 spp, {label}",
                         "cpu s": info["render_cpu_s"], "wall s": info["render_wall_s"], "cycles/flowsynth": ratio,
                         "goal": GOAL, "met": "yes" if ratio >= GOAL else "NO"})
            checks[config] = compare(sample, scene, info["frames"])
        info = cycles["direct"]
        rows.append({"engine": "Cycles", "what": "Blender start-up (wall)", "wall s": info["startup_s"]})
        rows.append({"engine": "Cycles", "what": "scene build in bpy (wall)", "wall s": info["build_s"]})
    # The parts of the flowsynth sample beside Cycles' direct render (not the goal: that is the full sample).
    for row in rows[1:3]:
        row["cycles/flowsynth"] = cycles["direct"]["render_cpu_s"] / row["cpu s"]
    load = os.getloadavg()
    print(f"Full sample, {W}x{H}, {T} frames, {NUM_OBJECTS} objects + room, one pinned core "
          f"(affinity {pinning['affinity']}, torch threads 1, Cycles FIXED 1 thread); seconds per 2-frame sample, "
          f"medians of {repeat}; ratio on process CPU time; {os.cpu_count()} cores shared, load average "
          f"{load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}; flowsynth first call {first_s:.2f} s (kernel load)\n"
          f"flowsynth keys: {', '.join(OUTPUTS)}; without rgb: the others; Cycles' passes only: {', '.join(PASSES)}. "
          "Cycles: passes Combined, Z, Normal, Vector, IndexOB; time around bpy.ops.render.render (scene sync, "
          "BVH build, render) per frame; Blender start-up and the scene build in bpy apart. The ratio of the two "
          "partial flowsynth rows is to Cycles' direct render; the goal is for the full sample")
    print_table(rows, COLUMNS)
    print("\nSanity check (not a test): Cycles' passes against flowsynth's sample on pixels both hit")
    crow = [{"cycles": k, **r} for k, rs in checks.items() for r in rs]
    print_table(crow, ["cycles", "frame", "both hit %", "ids agree %", "Z vs depth med rel", "Z vs ray length med rel",
                       "normal med deg", "flow", "flow med EPE px", "flow med |f| px"])
    for c in cycles.values():
        c.pop("t_script", None)
        for f in c["frames"]:
            f.pop("exr", None)
    write_json(name, {"machine": machine_info(), "pinning": pinning, "load_average": load, "resolution": [W, H],
                      "num_frames": T, "outputs": OUTPUTS, "repeat": repeat, "flowsynth": fs_all,
                      "flowsynth_first_s": first_s, "sampling": sampling, "cycles": cycles, "rows": rows,
                      "sanity": crow, "goal": GOAL})
    return 0


if __name__ == "__main__":
    sys.exit(main())
