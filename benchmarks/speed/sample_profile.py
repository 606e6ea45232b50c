"""Where a full sample's time goes: py-spy's stacks of the full sample, by stage, by Python function and by kernel.

    py-spy record --native --rate 250 --format raw -o STACKS -- taskset -c 1 python benchmarks/speed/sample_profile.py
    python benchmarks/speed/sample_profile.py --read STACKS
    taskset -c 1 python benchmarks/speed/sample_profile.py --limits

The first command runs the workload under py-spy (https://github.com/benfred/py-spy, a sampling profiler that reads
the Python and the native stack of every thread from outside the process): ``_common.full_sample_config()`` (512x384,
2 frames, 20 objects, direct light, every output of ``FULL_SAMPLE_OUTPUTS``), one thread a launch
(``BouncingThings(threads=1)``, torch on one thread), ``--warmup`` samples (kernels loaded, caches filled) and then
``--samples`` fresh ones inside ``profiled_samples``, the frame that marks what is read; it also times each stage in
process CPU time (results/profile_stages.json), which a busy core does not skew. The second reads the stacks
py-spy wrote (one line a distinct stack, ``frame;frame;... count``), prints the tables and writes them to
results/profile.json with a bar chart, results/profile.png: the share of the profiled samples' stack samples that falls

- in each stage (``STAGES``: the innermost of these functions on the stack names it; physics and scene sampling are
  ``BouncingThings.scene``), inclusive;
- in each kind of work (``classify``): a Warp kernel running, Warp's launch in Python, torch, numpy, Python;
- in each kernel, by its launch site (Warp's CPU kernels are compiled in memory and have no symbols, so the
  innermost Python frame above ``wp.launch`` names the kernel);
- in each Python function, self time (the innermost Python frame of the stack, native frames below it counted to
  it).

``--limits`` measures what the largest costs are read against (``limits``): Embree's rays per second on the same
scenes, primary and shadow rays, and one core's memory bandwidth (results/profile_limits.json).

Shares of the samples py-spy took, not times: on a shared machine the process may wait for the core, which py-spy
also samples (it records stacks at a wall-clock rate), so a share is of the sample's wall time on that core.
"""

from __future__ import annotations

import argparse
import collections
import re
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _common import FULL_SAMPLE, FULL_SAMPLE_OUTPUTS, RESULTS_DIR, machine_info, print_table, pyplot, save_figure, \
    write_json

MARK = "profiled_samples"  # the frame under which the profiled samples run
# (label, what a frame's text must contain): the innermost match on a stack names its stage
STAGES = (("scene (physics, sampling)", "scene (flowsynth/datasets/bouncing.py"),
          ("accel (BVH build, refit)", "SceneAccel"),
          ("primary cast (G-buffer)", "cast_gbuffer ("),
          ("G-buffer outputs", "gbuffer_outputs ("),
          ("flow, validity, occlusion", "flow_outputs ("),
          ("shading (rgb)", "render_rgb ("))
LAUNCH = "launch (warp/_src/context.py"  # Warp's wp.launch
INVOKE = "invoke (warp/_src/context.py"  # where wp.launch calls the kernel: native frames below it are the kernel
PY_FRAME = re.compile(r"^(?P<name>[\w.<>]+) \((?P<file>[^():]+\.py):\d+\)$")
SITE_SKIP = ("flowsynth/parallel.py", "flowsynth/kernels/specialise.py")  # launch helpers, not launchers
NATIVE_LIBS = (("libtorch", "torch (native)"), ("numpy/", "numpy (native)"), ("scipy/", "scipy (native)"),
               ("libpython", "Python runtime (gc, allocation)"))


def profiled_samples(ds, indices: range) -> None:
    """Render sample ``i`` of ``ds`` for each of ``indices`` (the frame py-spy's stacks are read under)."""
    for i in indices:
        ds.sample(i)


def run(samples: int, warmup: int) -> dict:
    """The workload: ``warmup`` samples, then ``samples`` fresh ones under ``profiled_samples``. Also times each stage
    of ``scaling.STAGES`` (and the scene) in process CPU time, a second account of the split that a busy core does
    not skew (py-spy samples wall-clock time). Returns {stage: CPU ms a sample}, the sample's "sample" included."""
    import importlib

    import torch

    import flowsynth as fs
    from _common import Timer, full_sample_config
    from scaling import STAGES as TIMED

    torch.set_num_threads(1)
    ds = fs.datasets.BouncingThings(full_sample_config(), outputs=list(FULL_SAMPLE_OUTPUTS), seed=0, threads=1)
    for i in range(warmup):
        ds.sample(9000 + i)
    cpu: dict = collections.defaultdict(float)

    def timed(fn, label):
        def call(*a, **kw):
            with Timer() as t:
                out = fn(*a, **kw)
            cpu[label] += t.cpu_s
            return out
        return call

    saved = [(importlib.import_module(m), attr) for m, attr, _ in TIMED]
    saved = [(mod, attr, getattr(mod, attr)) for mod, attr in saved]
    for (mod, attr, fn), (_, _, label) in zip(saved, TIMED):
        setattr(mod, attr, timed(fn, label))
    ds.scene = timed(ds.scene, "scene")
    try:
        t = time.perf_counter(), time.process_time()
        profiled_samples(ds, range(5000, 5000 + samples))
        wall, total = time.perf_counter() - t[0], time.process_time() - t[1]
    finally:
        for mod, attr, fn in saved:
            setattr(mod, attr, fn)
    cpu["sample"] = total
    ms = {k: 1000 * v / samples for k, v in cpu.items()}
    ms["rest"] = ms["sample"] - sum(v for k, v in ms.items() if k != "sample")
    print(f"{samples} samples of {FULL_SAMPLE} at one thread: {wall / samples:.3f} s wall, {total / samples:.3f} s CPU "
          f"a sample (CPU / wall {total / wall:.2f}); process CPU ms a sample by stage:")
    print_table([{"stage": k, "cpu_ms": v, "share_%": 100 * v / ms["sample"]} for k, v in ms.items()],
                ["stage", "cpu_ms", "share_%"])
    return ms


def limits(scenes: int) -> dict:
    """The physical limits the profile is read against, on this core: Embree's (embreex) rays per second on the full
    sample's own scenes (indices 5000 on, frame 0; primary rays with closest hit and normals, and the shading's
    shadow rays, an occlusion query from each hit towards each point or directional light) and the memory bandwidth
    of one core (a numpy copy of 256 MiB). Process CPU time for the rays, wall time for the copy; medians."""
    import statistics

    import numpy as np
    import torch
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    import flowsynth as fs
    from _common import full_sample_config

    def cpu_s(fn, n=5):
        fn()
        out = []
        for _ in range(n):
            t = time.process_time()
            fn()
            out.append(time.process_time() - t)
        return statistics.median(out)

    ds = fs.datasets.BouncingThings(full_sample_config(), outputs=["rgb"], seed=0)
    rows = []
    for i in range(5000, 5000 + scenes):
        sc = ds.scene(i)
        # every object at frame 0 merged into one world-space triangle soup, as Embree takes it
        V = np.concatenate([np.asarray(ob.mesh.vertices) @ ob.poses[0][:3, :3].T + ob.poses[0][:3, 3]
                            for ob in sc.objects])
        starts = np.cumsum([0] + [len(ob.mesh.vertices) for ob in sc.objects[:-1]])
        F = np.concatenate([np.asarray(ob.mesh.faces) + s for ob, s in zip(sc.objects, starts)]).astype(np.int32)
        esc = rtcore_scene.EmbreeScene()
        TriangleMesh(esc, V.astype(np.float32), F)
        pose = sc.world_T_cam[0]
        cam_dirs = sc.camera.pixel_rays(torch.float64).reshape(-1, 3).numpy()  # unit, camera frame
        d = np.ascontiguousarray((cam_dirs @ pose[:3, :3].T).astype(np.float32))
        o = np.ascontiguousarray(np.tile(pose[:3, 3], (len(d), 1)).astype(np.float32))
        hit = esc.run(o, d, output=1)
        ok = hit["primID"] >= 0
        x = o + d * hit["tfar"][:, None]
        n = np.asarray(hit["Ng"], np.float32).reshape(-1, 3)
        n *= (-np.sign(np.einsum("ij,ij->i", n, d)) / (np.linalg.norm(n, axis=1) + 1e-20))[:, None]
        so, sd, sl = [], [], []
        for light in sc.lights:
            if light.kind == "point":
                w = np.asarray(light.position, np.float32) - x
                dist = np.linalg.norm(w, axis=1)
                w /= dist[:, None]
            elif light.kind == "directional":
                w = np.tile(-np.asarray(light.direction, np.float32) / np.linalg.norm(light.direction), (len(x), 1))
                dist = np.full(len(x), 1e30, np.float32)
            else:
                continue
            so.append(x[ok] + n[ok] * 1e-3)
            sd.append(w[ok])
            sl.append(dist[ok] * 0.999)
        so, sd, sl = (np.ascontiguousarray(np.concatenate(a).astype(np.float32)) for a in (so, sd, sl))
        primary_s = cpu_s(lambda e=esc, o=o, d=d: e.run(o, d, output=1))
        shadow_s = cpu_s(lambda e=esc, o=so, d=sd, t=sl: e.run(o, d, t, query="OCCLUDED"))
        rows.append({"index": i, "triangles": len(F), "primary_Mrays_s": len(d) / primary_s / 1e6,
                     "shadow_Mrays_s": len(sd) / shadow_s / 1e6, "shadow_rays_per_pixel": len(sd) / len(d)})
    a = np.ones(64 * 2**20, np.float32)
    b = np.empty_like(a)
    copies = []
    for _ in range(7):
        t = time.perf_counter()
        np.copyto(b, a)
        copies.append(time.perf_counter() - t)
    out = {"scenes": rows, **{k: statistics.median(r[k] for r in rows) for k in ("primary_Mrays_s", "shadow_Mrays_s",
                                                                                  "shadow_rays_per_pixel")},
           "copy_GB_s": 2 * a.nbytes / statistics.median(copies) / 1e9}
    print_table(rows, ["index", "triangles", "primary_Mrays_s", "shadow_Mrays_s", "shadow_rays_per_pixel"])
    print(f"median: Embree primary {out['primary_Mrays_s']:.2f} Mrays/s, shadow {out['shadow_Mrays_s']:.2f} Mrays/s; "
          f"one core's copy {out['copy_GB_s']:.1f} GB/s (read + write)")
    return out


def read_stacks(path: Path) -> list[tuple[list[str], int]]:
    """py-spy's raw output: [(frames outermost first, count)], only the stacks under ``MARK``, from it inwards."""
    out = []
    for line in path.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        frames = stack.split(";")
        at = next((k for k, f in enumerate(frames) if f.startswith(MARK + " ")), None)
        if at is not None and count.isdigit():
            out.append((frames[at + 1:], int(count)))
    return out


def _short(frame: str) -> str:
    m = PY_FRAME.match(frame)
    return f"{m['name']} ({m['file'].removeprefix('flowsynth/')})" if m else frame


def classify(frames: list[str]) -> tuple[str, str, str]:
    """(kind, launch site, Python function) of one stack (frames outermost first).

    kind: "kernel" (the innermost Python frame is Warp's ``invoke``: the kernel runs), "Warp launch (Python)" (other
    Python frames below ``wp.launch``: argument packing, module hashing and loading), or for a stack with no launch
    the library of its native leaf (``NATIVE_LIBS``), "Python" (a Python frame is the leaf) or "other native". Launch
    site: the innermost frame above the launch outside ``SITE_SKIP`` (the kernel's launcher), "" without one.
    Function: the innermost Python frame of the stack."""
    py = [k for k, f in enumerate(frames) if PY_FRAME.match(f)]
    func = _short(frames[py[-1]]) if py else "(no Python frame)"
    at = next((k for k, f in enumerate(frames) if f.startswith(LAUNCH)), None)
    if at is not None:
        site = next((_short(frames[k]) for k in reversed(py) if k < at and not any(s in frames[k] for s in SITE_SKIP)),
                    "")
        return ("kernel" if frames[py[-1]].startswith(INVOKE) else "Warp launch (Python)"), site, func
    leaf = frames[-1] if frames else ""
    if py and py[-1] == len(frames) - 1:
        return "Python", "", func
    kind = next((label for key, label in NATIVE_LIBS if key in leaf), "other native (libc, ctypes, ...)")
    return kind, "", func


def tables(stacks: list[tuple[list[str], int]]) -> dict:
    """Shares [%] of the stacks under ``MARK``: by stage, by kind, by kernel launch site and by Python function."""
    total = sum(c for _, c in stacks)
    stage, kind, kernel, func = (collections.Counter() for _ in range(4))
    for frames, c in stacks:
        stage[next((lab for f in reversed(frames) for lab, key in STAGES if key in f), "other")] += c
        k, site, fn = classify(frames)
        kind[k] += c
        if k == "kernel":
            kernel[site] += c
        func[fn] += c

    def rows(counter, key):
        return [{key: k, "share_%": 100 * v / total, "stack_samples": v} for k, v in counter.most_common()]

    return {"stack_samples": total, "stages": rows(stage, "stage"), "kinds": rows(kind, "kind"),
            "kernels": rows(kernel, "kernel"), "functions": rows(func, "function")}


def plot(result: dict, name: str) -> Path | None:
    plt = pyplot()
    if plt is None:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), dpi=110)
    for ax, key, title, n in ((axes[0], "stages", "by stage (inclusive)", 8), (axes[1], "kernels",
                                                                              "by kernel (inclusive)", 10)):
        rows = result[key][:n][::-1]
        ax.barh([r[key[:-1]] for r in rows], [r["share_%"] for r in rows])
        ax.set_xlabel("share of the full sample's stack samples [%]")
        ax.set_title(title)
        ax.tick_params(axis="y", labelsize=8)
    fig.suptitle("Full sample 512x384, 2 frames, 20 objects, direct light; one pinned core (py-spy)")
    fig.tight_layout()
    return save_figure(fig, name)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--samples", type=int, default=16, help="profiled samples (default 16)")
    p.add_argument("--warmup", type=int, default=3, help="samples before them, not read (default 3)")
    p.add_argument("--read", type=Path, default=None, metavar="STACKS",
                   help="read py-spy's raw stacks (--format raw) and write results/profile.json and .png")
    p.add_argument("--limits", action="store_true", help="measure Embree's rays/s on the full sample's scenes and one "
                   "core's memory bandwidth instead; writes results/profile_limits.json (needs embreex)")
    p.add_argument("--note", default="", help="--read: a line for the JSON, how the run was made (cores, load)")
    args = p.parse_args()
    if args.limits:
        write_json("profile_limits", {"machine": machine_info(extra_packages=("embreex",)), **limits(4)})
        return
    if args.read is None:
        write_json("profile_stages", {"machine": machine_info(), "samples": args.samples, "warmup": args.warmup,
                                      "sample": FULL_SAMPLE, "cpu_ms": run(args.samples, args.warmup)})
        return
    result = tables(read_stacks(args.read))
    if not result["stack_samples"]:
        p.error(f"--read {args.read}: no stack under {MARK}; record with py-spy's --format raw")
    for key, n in (("stages", 99), ("kinds", 99), ("kernels", 15), ("functions", 15)):
        print(f"\nBy {key[:-1]}:")
        print_table(result[key][:n], [key[:-1], "share_%", "stack_samples"])
    write_json("profile", {"machine": machine_info(), "note": args.note, "sample": FULL_SAMPLE,
                           "outputs": FULL_SAMPLE_OUTPUTS, **result})
    png = plot(result, "profile")
    print(f"\n{result['stack_samples']} stack samples under {MARK}; {args.note}\nwrote {RESULTS_DIR / 'profile.json'}"
          + (f" and {png}" if png else ""))


if __name__ == "__main__":
    main()
