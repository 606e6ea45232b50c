"""Per-asset BVH on one CPU core: Warp's constructor and leaf size against build time and primary cast time.

flowsynth casts camera rays against one ``wp.Mesh`` (a triangle BVH) per asset, built once per process by
``flowsynth.accel.asset_mesh`` as ``wp.Mesh(points, indices)``: on the CPU that is Warp's SAH builder with
4 triangles per leaf (warp 1.19, ``Mesh.__init__``; row ``default``). This script builds the same meshes
with every CPU constructor and a range of leaf sizes (``bvh_constructor``, ``bvh_leaf_size``):

- ``sah``: Warp's top-down surface-area-heuristic builder (16 buckets);
- ``median``: Warp's top-down builder splitting at the median centroid;
- ``cubql``: cuBQL's CPU SAH builder, converted to Warp's node layout (experimental in Warp; leaf size is
  cuBQL's ``makeLeafThreshold``);
- ``lbvh`` is GPU-only: on the CPU Warp warns and builds SAH instead, so it is not measured.

Scenes, 640x480 pixels, 60 deg horizontal fov, camera at the origin looking down +z:

- ``single``: one icosphere (radius 1 m, random rotation) 1.5 m in front of the camera, filling the view
  (every ray hits);
- ``30 spheres``: the scene of benchmarks/raycast.py (``make_scene``: 30 icospheres 4-12 m away).

For icospheres of 1280, 5120, 20480 and 81920 faces the script reports the build time of one mesh and the
time of the primary G-buffer kernel (``primary_kernel(want_normals=True, want_points=False)``, launched as
``flowsynth.render.cast_gbuffer`` launches it, into preallocated outputs) with the variant meshes swapped
into a ``SceneAccel``'s ``item_mesh`` array. With at most ``ORDERED_MAX`` instances the camera rays walk the
instances near to far without the top-level BVH, so only the per-asset BVH changes between variants.
Every variant's hits are checked against the default's (same instance per pixel, same distance). The
same cast against a 20-face icosahedron (``floor_ms``) estimates the time that no BVH can save: pixel
rays, the instance walk, the mesh-query setup and the outputs.

Times are medians of process CPU time over round-robin rounds on one pinned core. Run
``python benchmarks/bvh.py [--quick]``: prints tables, writes ``benchmarks/results/bvh.json``,
``bvh_cast_single.png``, ``bvh_cast_30_spheres.png`` (cast time / default's vs leaf size) and
``bvh_build.png`` (build time vs leaf size).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent)]
from _common import machine_info, pin_single_core, plot_curves, print_table, time_round_robin, write_json

PINNING = pin_single_core()

import numpy as np
import torch
import trimesh
from raycast import FOV_DEG, HEIGHT, WIDTH, make_scene
from scipy.spatial.transform import Rotation

from flowsynth.accel import ORDERED_MAX, SceneAccel, pinhole
from flowsynth.camera import Camera
from flowsynth.kernels import wp_runtime
from flowsynth.kernels.raycast import primary_kernel

SUBDIVISIONS = {1280: 3, 5120: 4, 20480: 5, 81920: 6}  # icosphere faces -> subdivisions
FLOOR_SUBDIVISIONS = {20: 0}  # the icosahedron, for the cast time that does not depend on the BVH
CONSTRUCTORS = ("sah", "median", "cubql")
DEFAULT = ("default", None)  # wp.Mesh(points, indices), as flowsynth.accel.asset_mesh builds it
DEFAULT_EQUIVALENT = ("sah", 4)  # what DEFAULT is on the CPU in warp 1.19
SINGLE_DISTANCE = 1.5  # [m]: a unit sphere this close covers the whole 60 deg x 46.8 deg view
DIST_REL_TOL = 1e-5  # float32 ray-triangle distance agreement between BVH variants
FLOOR_REPEAT = 7  # timed rounds of the 20-face cast (cheap; the BVH share is a difference of two times)


def single_scene_poses(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(cam_T_world (1, 4, 4), world_T_obj (1, 1, 4, 4)) of one sphere filling the view."""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    pose[:3, 3] = (0.0, 0.0, SINGLE_DISTANCE)
    return np.eye(4)[None], pose[None, None]


def raycast_scene_poses() -> tuple[np.ndarray, np.ndarray]:
    """(cam_T_world (1, 4, 4), world_T_obj (1, 30, 4, 4)) of benchmarks/raycast.py's scene."""
    scene = make_scene()
    return scene.cam_T_world, np.stack([o.poses for o in scene.objects], 1)


def build_mesh(wp, mesh: trimesh.Trimesh, constructor: str, leaf: int | None):
    points = wp.array(np.asarray(mesh.vertices, np.float32), dtype=wp.vec3)
    indices = wp.array(np.asarray(mesh.faces, np.int32).reshape(-1), dtype=wp.int32)
    if constructor == DEFAULT[0]:
        return lambda: wp.Mesh(points=points, indices=indices)
    return lambda: wp.Mesh(points=points, indices=indices, bvh_constructor=constructor, bvh_leaf_size=leaf)


def build_times(make, repeat: int) -> float:
    """Median process CPU time of one ``make()`` [s], excluding the destruction of the result."""
    times, keep = [], []
    for _ in range(repeat):
        c0 = time.process_time()
        keep.append(make())
        times.append(time.process_time() - c0)
    return float(np.median(times))


def measure(wp, scene_name: str, faces: int, poses, variants, camera: Camera, repeat: int,
            build_repeat: int) -> list[dict]:
    """Build and cast every (constructor, leaf) variant for one scene and face count."""
    mesh = trimesh.creation.icosphere(subdivisions={**SUBDIVISIONS, **FLOOR_SUBDIVISIONS}[faces], radius=1.0)
    cam_T_world, world_T_obj = poses
    N = world_T_obj.shape[1]
    assert N <= ORDERED_MAX
    accel = SceneAccel([mesh] * N, cam_T_world, world_T_obj)
    shape = (1, camera.height, camera.width)
    dist, item, face = (wp.zeros(shape, dtype=t) for t in (wp.float32, wp.int32, wp.int32))
    point, normal = wp.zeros((1, 1, 1), dtype=wp.vec3), wp.zeros(shape, dtype=wp.vec3)
    kernel = primary_kernel(True, False)
    default_ids = accel.item_mesh
    built, fns, results, build_s = {}, {}, {}, {}
    for key in variants:
        make = build_mesh(wp, mesh, *key)
        built[key] = make()
        build_s[key] = build_times(make, build_repeat) if build_repeat else None
        accel.item_mesh = wp.array(np.full(accel.F * N, built[key].id, np.uint64), dtype=wp.uint64)
        inputs = [accel.instances(), accel.tile_lists(camera), pinhole(camera), 1e9, 0]
        fns[key] = lambda inputs=inputs: wp.launch(kernel, dim=shape[:2], inputs=inputs,
                                                   outputs=[dist, item, face, point, normal])
        fns[key]()
        results[key] = (item.numpy().copy(), dist.numpy().copy())
    accel.item_mesh = default_ids
    times = time_round_robin(fns, repeat=repeat, warmup=0)
    ref_item, ref_dist = results[DEFAULT]
    hit = ref_item >= 0
    rows = []
    for key in variants:
        it, d = results[key]
        rel = np.abs(d[hit] - ref_dist[hit]) / ref_dist[hit]
        t = times[key]
        rows.append({"scene": scene_name, "faces": faces, "constructor": key[0],
                     "leaf": key[1] if key[0] != DEFAULT[0] else DEFAULT_EQUIVALENT[1],
                     "build_ms": None if build_s[key] is None else 1e3 * build_s[key],
                     "cast_ms": 1e3 * t["cpu_s"], "cast_wall_ms": 1e3 * t["wall_s"],
                     "Mrays_s": hit.size / t["cpu_s"] / 1e6,
                     "x_default": times[DEFAULT]["cpu_s"] / t["cpu_s"],
                     "hit_fraction": float(hit.mean()), "item_mismatch": int((it != ref_item).sum()),
                     "dist_over_tol": int((rel > DIST_REL_TOL).sum())})
    return rows


def summaries(rows: list[dict], floor: dict, scenes, leaves) -> tuple[list[dict], list[dict]]:
    """(best variant per scene and mesh, each variant's speed-up over the default across all of them)."""
    best_rows = []
    for scene_name in scenes:
        for faces in SUBDIVISIONS:
            part = {(r["constructor"], r["leaf"]): r for r in rows
                    if r["scene"] == scene_name and r["faces"] == faces}
            default = part[DEFAULT[0], DEFAULT_EQUIVALENT[1]]
            best = min(part.values(), key=lambda r: r["cast_ms"])
            above = floor[scene_name]
            best_rows.append({
                "scene": scene_name, "faces": faces, "floor_ms": above, "default_ms": default["cast_ms"],
                "best": f"{best['constructor']} leaf {best['leaf']}", "best_ms": best["cast_ms"],
                "x_default": best["x_default"],
                "x_default_bvh": (default["cast_ms"] - above) / (best["cast_ms"] - above),
                "same_tree_noise": abs(part[DEFAULT_EQUIVALENT]["x_default"] - 1.0)})
    overall = []
    for c in CONSTRUCTORS:
        for leaf in leaves:
            x = np.array([r["x_default"] for r in rows if r["constructor"] == c and r["leaf"] == leaf])
            build = [r["build_ms"] for r in rows if r["constructor"] == c and r["leaf"] == leaf
                     and r["faces"] == max(SUBDIVISIONS)]
            overall.append({"constructor": c, "leaf": leaf,
                            "x_default_geomean": float(np.exp(np.log(x).mean())),
                            "x_default_min": float(x.min()), "x_default_max": float(x.max()),
                            f"build_ms_{max(SUBDIVISIONS)}": build[0]})
    return best_rows, overall


def plot(rows: list[dict], scenes, leaves) -> None:
    for scene_name in scenes:
        series = {}
        for faces in SUBDIVISIONS:
            part = {(r["constructor"], r["leaf"]): r["x_default"] for r in rows
                    if r["scene"] == scene_name and r["faces"] == faces}
            for c in CONSTRUCTORS:
                series[f"{c}, {faces} faces"] = (list(leaves), [1.0 / part[c, leaf] for leaf in leaves])
        plot_curves(f"bvh_cast_{scene_name.replace(' ', '_')}", series, "leaf size [triangles]",
                    "cast time / default's (SAH, leaf 4)", logx=True, logy=False,
                    title=f"Primary cast, {scene_name}, {WIDTH}x{HEIGHT}")
    build = {(r["faces"], r["constructor"], r["leaf"]): r["build_ms"] for r in rows}
    series = {f"{c}, {faces} faces": (list(leaves), [build[faces, c, leaf] for leaf in leaves])
              for faces in SUBDIVISIONS for c in CONSTRUCTORS}
    plot_curves("bvh_build", series, "leaf size [triangles]", "build time [ms] (1 core)",
                title="wp.Mesh build")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="leaf sizes 1, 4, 16, 2 rounds (else 1-16, 5 rounds)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    wp = wp_runtime()
    t_start = time.perf_counter()
    leaves = (1, 4, 16) if args.quick else (1, 2, 4, 8, 16)
    repeat = 2 if args.quick else 5
    build_repeat = 3 if args.quick else 5
    variants = [DEFAULT] + [(c, leaf) for c in CONSTRUCTORS for leaf in leaves]
    camera = Camera.from_fov(WIDTH, HEIGHT, FOV_DEG)
    scenes = {"single": single_scene_poses(), "30 spheres": raycast_scene_poses()}
    measure(wp, "warmup", 20, scenes["single"], [DEFAULT], camera, 1, 0)  # compile / load the kernel
    # the same kernel on a 20-face icosahedron: the part of the cast time that is not BVH traversal
    floor = {name: measure(wp, name, 20, poses, [DEFAULT], camera, FLOOR_REPEAT, 0)[0]["cast_ms"]
             for name, poses in scenes.items()}
    rows = []
    for scene_name, poses in scenes.items():
        for faces in SUBDIVISIONS:
            # build time depends on the mesh only: measured with the first scene
            part = measure(wp, scene_name, faces, poses, variants, camera, repeat,
                           build_repeat if scene_name == "single" else 0)
            rows += part
            print(f"{scene_name}, {faces} faces: default {part[0]['cast_ms']:.1f} ms", flush=True)
    build = {(r["faces"], r["constructor"], r["leaf"]): r["build_ms"]
             for r in rows if r["build_ms"] is not None}
    for r in rows:
        r["build_ms"] = build[r["faces"], r["constructor"], r["leaf"]]
    best_rows, overall = summaries(rows, floor, scenes, leaves)

    info = machine_info()
    print(f"\nPer-asset BVH: build and primary cast (depth + instance + normals kernel), {WIDTH}x{HEIGHT} "
          f"rays, icospheres; medians of {repeat} round-robin rounds of process CPU time; x_default = "
          "default's cast time / this one's (> 1 is faster); build_ms for one mesh; default = "
          f"wp.Mesh(points, indices) = {DEFAULT_EQUIVALENT[0]} leaf {DEFAULT_EQUIVALENT[1]} on the CPU")
    print(f"{info['cpu_model']}, affinity {PINNING['affinity']}, warp {info['warp-lang']}")
    print_table(rows, ["scene", "faces", "constructor", "leaf", "build_ms", "cast_ms", "Mrays_s", "x_default",
                       "hit_fraction", "item_mismatch", "dist_over_tol"])
    print("\nBest variant per scene and mesh. floor_ms: the same cast against a 20-face icosahedron "
          "(time not spent in the BVH); x_default_bvh: speed-up of the part above the floor; "
          "same_tree_noise: "
          f"|x_default - 1| of {DEFAULT_EQUIVALENT[0]} leaf {DEFAULT_EQUIVALENT[1]}, the default's own tree "
          "(timing noise)")
    print_table(best_rows, list(best_rows[0]))
    print(f"\nEach variant over all {len(best_rows)} scene/mesh cases: x_default geometric mean, min, max")
    print_table(overall, list(overall[0]))
    plot(rows, scenes, leaves)
    total = time.perf_counter() - t_start
    path = write_json("bvh", {
        "machine": info, "pinning": PINNING, "loadavg_1_5_15": os.getloadavg(), "quick": args.quick,
        "setup": {"width": WIDTH, "height": HEIGHT, "fov_deg": FOV_DEG, "single_distance_m": SINGLE_DISTANCE,
                  "leaf_sizes": leaves, "constructors": CONSTRUCTORS, "repeat": repeat,
                  "build_repeat": build_repeat,
                  "default": f"wp.Mesh(points, indices) = {DEFAULT_EQUIVALENT} on the CPU",
                  "not_measured": {"lbvh": "GPU only; Warp builds SAH instead on the CPU"}},
        "rows": rows, "best": best_rows, "overall": overall, "floor_ms": floor, "total_s": total})
    print(f"total {total:.1f} s; wrote {path}")


if __name__ == "__main__":
    main()
