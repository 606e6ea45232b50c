"""Ground-truth accuracy against run time: occlusion methods, reprojection precision, cost per output.

Scene (built by hand, no sampler): a back wall and 20 objects (icospheres and boxes, random sizes,
rotations, linear and angular velocities) 3-10 m in front of a moving 60 deg camera, OpenCV axes.
The reference is the float64 brute-force oracle of ``tests/oracle.py`` (Moller-Trumbore over every
triangle, visibility rays cast the same way); it shares no code with flowsynth.

1. Occlusion: ``occlusion="exact"`` (visibility rays) vs ``"depth"`` (depth-buffer test): time of a
   frame pair with flow_fw + occ_fw, the occlusion stage's share, and pixels whose occ_fw differs from
   the oracle (all, and off silhouettes as defined in ``oracle.silhouette``).
2. Reprojection precision at world offsets 1 .. 1e5 m (camera and objects shifted together, so the
   true flow does not change): flowsynth's float64 reprojection of the object-local hit point vs a
   world-space float32 pipeline written here (float32 world hit point, i.e. the ``position`` output,
   mapped by float32 matrices obj_T_world[t], world_T_obj[t+1], cam_T_world[t+1] and projected in
   float32). EPE vs the oracle over pixels that see the same instance as the oracle and stay in frame.
3. Cost each output adds to a frame: ``fs.render`` time per frame of a T-frame clip for cumulative
   output sets (depth; +normals; +flow_fw; +occ_fw exact; +motion; +boxes).

Single core, as in ``benchmarks/peers/raycast.py``: thread variables and CPU affinity pinned before numpy
loads, ``torch.set_num_threads(1)``. Run ``python benchmarks/accuracy/accuracy.py [--quick]``. Prints tables;
writes ``benchmarks/results/accuracy.json`` (and ``accuracy_epe.png`` when matplotlib is importable).
"""

from __future__ import annotations

import argparse
import sys
import time
from functools import partial
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parents[1]), str(HERE.parents[1] / "tests")]  # _common, flowsynth, oracle
from _common import RESULTS_DIR, Timer, machine_info, pin_single_core, print_table, write_json

PINNING = pin_single_core()

import numpy as np
import torch
import trimesh
from oracle import pair_truth, pose, silhouette

import flowsynth as fs
from flowsynth.raycast import SceneAccel
from flowsynth.truth import reproject
from flowsynth.raycast import cast_gbuffer, scene_arrays

FOV_DEG = 60.0
NUM_OBJECTS = 20
OFFSETS = (1.0, 1e2, 1e3, 1e4, 1e5)  # world offset of the whole scene [m]
OFFSET_DIR = np.array([1.0, -0.7, 0.5]) / np.linalg.norm([1.0, -0.7, 0.5])
BOX_KEYS = ["box3d_corners", "box2d_amodal", "box2d_visible", "visible_pixels"]
OUTPUT_SETS = [
    ("depth", ["depth"]),
    ("+normals", ["depth", "normals"]),
    ("+flow_fw", ["depth", "normals", "flow_fw"]),
    ("+occ_fw (exact)", ["depth", "normals", "flow_fw", "occ_fw"]),
    ("+motion", ["depth", "normals", "flow_fw", "occ_fw", "motion"]),
    ("+boxes", ["depth", "normals", "flow_fw", "occ_fw", "motion", *BOX_KEYS]),
]


def timeit(fn, repeat: int) -> float:
    """Fastest wall time of ``fn()`` over ``repeat`` calls after one untimed call [s] (the minimum, not
    the median: on a shared machine, load only ever adds time)."""
    return timeit_many({"fn": fn}, repeat)["fn"]


def timeit_many(fns: dict, repeat: int) -> dict:
    """``timeit`` for several functions, called round-robin so that load changes hit all of them alike."""
    for fn in fns.values():
        fn()
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(repeat):
        for key, fn in fns.items():
            with Timer() as tm:
                fn()
            best[key] = min(best[key], tm.wall_s)
    return best


def make_scene(width: int, height: int, num_frames: int, offset: float = 0.0, seed: int = 0) -> fs.Scene:
    """Back wall + NUM_OBJECTS moving icospheres and boxes; everything shifted by ``offset`` [m]."""
    rng = np.random.default_rng(seed)
    shift = pose(t=OFFSET_DIR * offset)
    scene = fs.Scene(fs.Camera.from_fov(width, height, FOV_DEG), num_frames)
    cam_w, cam_v = rng.normal(0, 0.02, 3), rng.normal(0, 0.08, 3)
    scene.set_camera_poses(shift[None] @ np.stack([pose(cam_w * t, cam_v * t) for t in range(num_frames)]))
    T = num_frames
    wall = trimesh.creation.box((40.0, 30.0, 0.2))
    scene.add_object(wall, poses=shift @ pose(t=(0.0, 0.0, 14.0)), category=1)
    half = np.tan(np.radians(FOV_DEG) / 2)
    for k in range(NUM_OBJECTS):
        size = rng.uniform(0.4, 1.2)
        mesh = (trimesh.creation.icosphere(2, radius=size / 2) if k % 2 else
                trimesh.creation.box(size * rng.uniform(0.5, 1.0, 3)))
        z = rng.uniform(3.0, 10.0)
        p0 = np.array([rng.uniform(-0.8, 0.8) * half * z, rng.uniform(-0.6, 0.6) * half * z, z])
        r0, w, v = rng.normal(0, 1.0, 3), rng.normal(0, 0.15, 3), rng.normal(0, 0.15, 3)
        poses = np.stack([shift @ pose(r0 + w * t, p0 + v * t) for t in range(T)])
        scene.add_object(mesh, poses=poses, category=2 + k % 2)
    return scene


def scene_poses(scene: fs.Scene) -> tuple[np.ndarray, np.ndarray, list]:
    return scene.world_T_cam, np.stack([o.poses for o in scene.objects], 1), [o.mesh for o in scene.objects]


def bench_occlusion(width: int, height: int, repeat: int) -> list[dict]:
    scene = make_scene(width, height, 2)
    cams, world_T_obj, meshes = scene_poses(scene)
    with Timer() as tm:
        truth = pair_truth(scene.camera.K, width, height, cams, meshes, world_T_obj, 0, 1)
    oracle_s = tm.wall_s
    casts = {}
    inst1 = pair_truth(scene.camera.K, width, height, cams, meshes, world_T_obj, 1, 0, casts=casts,
                       occlusion=False)["instance"]
    sil = silhouette(truth["instance"], inst1, truth["uv"])
    keys = ["flow_fw", "occ_fw"]
    times = timeit_many({"base": partial(fs.render, scene, ["flow_fw"]),
                         "exact": partial(fs.render, scene, keys, occlusion="exact"),
                         "depth": partial(fs.render, scene, keys, occlusion="depth")}, repeat)
    base = times["base"]
    rows = []
    for method in ("exact", "depth"):
        out = fs.render(scene, ["flow_fw", "occ_fw", "instance"], occlusion=method)
        occ = out["occ_fw"][0, 0].numpy()
        same = out["instance"][0, 0].numpy() == truth["instance"]
        wrong = (occ != truth["occ"]) & same & truth["hit"]
        t = times[method]
        rows.append({
            "method": method, "pair_ms": 1e3 * t, "occ_stage_ms": 1e3 * (t - base),
            "hit_px": int(truth["hit"].sum()), "occluded_px": int(truth["occ"].sum()),
            "wrong_px": int(wrong.sum()), "wrong_off_silhouette": int((wrong & ~sil).sum()),
            "false_occluded": int((wrong & occ).sum()), "false_visible": int((wrong & ~occ).sum()),
            "wrong_pct": 100.0 * wrong.sum() / max(int(truth["hit"].sum()), 1),
        })
    rows.append({"method": "oracle (numpy)", "pair_ms": 1e3 * oracle_s})
    return rows


def float32_world_flow(pos: np.ndarray, n: np.ndarray, i: np.ndarray, j: np.ndarray, world_T_obj: np.ndarray,
                       cam_T_world: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Forward flow (P, 2) of a world-space float32 pipeline: float32 world points ``pos`` (P, 3) of
    instances ``n`` at pixels (i, j) of frame 0, float32 matrices, float32 projection."""
    f32 = np.float32
    obj_T_world0 = np.linalg.inv(world_T_obj[0]).astype(f32)[n]
    world_T_obj1 = world_T_obj[1].astype(f32)[n]
    cam1 = cam_T_world[1].astype(f32)
    p = np.einsum("pij,pj->pi", obj_T_world0[:, :3, :3], pos) + obj_T_world0[:, :3, 3]
    xw = np.einsum("pij,pj->pi", world_T_obj1[:, :3, :3], p) + world_T_obj1[:, :3, 3]
    X = xw @ cam1[:3, :3].T + cam1[:3, 3]
    K32 = K.astype(f32)
    u = (K32[0, 0] * X[:, 0] + K32[0, 1] * X[:, 1]) / X[:, 2] + K32[0, 2]
    v = K32[1, 1] * X[:, 1] / X[:, 2] + K32[1, 2]
    return np.stack([u - j.astype(f32), v - i.astype(f32)], 1)


def bench_precision(width: int, height: int, repeat: int) -> list[dict]:
    ref = make_scene(width, height, 2, offset=0.0)
    cams, world_T_obj, meshes = scene_poses(ref)
    truth = pair_truth(ref.camera.K, width, height, cams, meshes, world_T_obj, 0, 1, occlusion=False)
    rows = []
    for offset in OFFSETS:
        scene = make_scene(width, height, 2, offset=offset)
        K = scene.camera.K
        out = fs.render(scene, ["flow_fw", "position", "instance"])
        idx = out["instance"][0, 0].numpy() - 1
        sel = (idx == truth["instance"] - 1) & truth["valid"] & ~truth["oof"]
        i, j = np.nonzero(sel)
        n = idx[i, j]
        flow64 = out["flow_fw"][0].permute(1, 2, 0).numpy().astype(np.float64)[i, j]
        pos = out["position"][0].permute(1, 2, 0).numpy()[i, j]
        _, world_T_obj_s, _ = scene_poses(scene)
        cam_T_world = scene.cam_T_world
        flow32 = float32_world_flow(pos, n, i, j, world_T_obj_s, cam_T_world, K).astype(np.float64)
        # timing: the reprojection step alone, on the same points
        _, cam_T_w, w_T_o = scene_arrays(scene)
        accel = SceneAccel(meshes, cam_T_w, w_T_o)
        gb = cast_gbuffer(accel, scene.camera, want_normals=False, want_points=True)
        p_local = gb.host().point[0, i, j].astype(np.float64)
        M = np.einsum("ij,pjk->pik", cam_T_w[1], w_T_o[1, n])
        t64 = timeit(partial(reproject, p_local, M, K), repeat=repeat)
        t32 = timeit(partial(float32_world_flow, pos, n, i, j, world_T_obj_s, cam_T_world, K), repeat=repeat)
        ref_flow = truth["flow"][i, j]
        for name, flow, t in (("float64 local (flowsynth)", flow64, t64), ("float32 world", flow32, t32)):
            e = np.linalg.norm(flow - ref_flow, axis=1)
            rows.append({"offset_m": offset, "variant": name, "px": len(e), "reproject_ms": 1e3 * t,
                         "epe_mean": float(e.mean()), "epe_max": float(e.max())})
    return rows


def bench_outputs(width: int, height: int, num_frames: int, repeat: int) -> list[dict]:
    scene = make_scene(width, height, num_frames)
    times = timeit_many({label: partial(fs.render, scene, keys, max_objects=NUM_OBJECTS + 1)
                         for label, keys in OUTPUT_SETS}, repeat)
    rows, prev = [], None
    for label, _ in OUTPUT_SETS:
        t = times[label] / num_frames
        rows.append({"outputs": label, "ms_per_frame": 1e3 * t,
                     "added_ms": None if prev is None else 1e3 * (t - prev)})
        prev = t
    return rows


def save_epe_plot(rows: list[dict]) -> Path | None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    fig, ax = plt.subplots(figsize=(5, 3.4))
    for variant in dict.fromkeys(r["variant"] for r in rows):
        rs = [r for r in rows if r["variant"] == variant]
        offsets = [r["offset_m"] for r in rs]
        ax.loglog(offsets, [max(r["epe_mean"], 1e-9) for r in rs], "o-", label=f"{variant}, mean")
        ax.loglog(offsets, [max(r["epe_max"], 1e-9) for r in rs], "x--", label=f"{variant}, max")
    ax.set_xlabel("world offset [m]")
    ax.set_ylabel("EPE vs float64 oracle [px]")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = RESULTS_DIR / "accuracy_epe.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="128x96 images, fewer repeats")
    args = ap.parse_args()
    torch.set_num_threads(1)
    width, height = (128, 96) if args.quick else (256, 192)
    repeat = 3 if args.quick else 7
    num_frames = 3 if args.quick else 5
    t_start = time.perf_counter()
    # compile every kernel variant before timing
    fs.render(make_scene(32, 24, 2), [k for _, ks in OUTPUT_SETS for k in ks] + ["flow_bw", "position"])

    info = machine_info(extra_packages=("kornia",))
    print(f"{info['cpu_model']}, {info['platform']}, {info['cpu_count']} CPUs "
          f"(pinned to {PINNING['affinity']}), python {info['python']}, torch {info['torch']}, "
          f"warp {info['warp-lang']}, kornia {info['kornia']}")
    print(f"{width}x{height}, {NUM_OBJECTS} objects + wall, fastest of {repeat}\n")

    occ = bench_occlusion(width, height, repeat)
    print("1. occlusion: exact (visibility rays) vs depth buffer; wrong = occ_fw != brute-force oracle")
    print_table(occ, ["method", "pair_ms", "occ_stage_ms", "hit_px", "occluded_px", "wrong_px", "wrong_pct",
                      "wrong_off_silhouette", "false_occluded", "false_visible"])

    prec = bench_precision(width, height, repeat)
    print("\n2. reprojection precision vs world offset (EPE vs float64 oracle, in-frame pixels) [px]")
    print_table(prec, ["offset_m", "variant", "px", "reproject_ms", "epe_mean", "epe_max"])

    cost = bench_outputs(width, height, num_frames, repeat)
    print(f"\n3. render time per frame ({num_frames}-frame clip) for cumulative output sets")
    print_table(cost, ["outputs", "ms_per_frame", "added_ms"])

    plot = save_epe_plot(prec)
    total = time.perf_counter() - t_start
    print(f"\ntotal {total:.1f} s" + ("" if plot else "; matplotlib not importable, no plot"))
    path = write_json("accuracy", {
        "machine": info, "pinning": PINNING, "torch_threads": torch.get_num_threads(), "quick": args.quick,
        "width": width, "height": height, "num_objects": NUM_OBJECTS, "repeat": repeat,
        "occlusion": occ, "precision": prec, "output_cost": {"num_frames": num_frames, "rows": cost},
        "plot": plot, "total_s": total,
    })
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
