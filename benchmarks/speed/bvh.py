"""Per-asset BVH on one CPU core: flowsynth's 4-wide BVH (``flowsynth.raycast.blas``) against Warp's ``wp.Mesh``.

flowsynth casts rays against one BVH per asset, in the asset's object frame. Until 2026-11-24 that was a
``wp.Mesh`` (Warp's CPU SAH builder, 4 triangles a leaf) queried with ``wp.mesh_query_ray``; now it is the
4-wide tree of ``flowsynth.raycast.blas`` queried with ``flowsynth.kernels.blas.blas_closest`` / ``blas_any``. This
script casts the same rays both ways in one kernel that differs only in that query:

- ``wp.Mesh``: ``wp.mesh_query_ray`` / ``wp.mesh_query_ray_anyhit`` on ``wp.Mesh(points, indices)``;
- ``bvh4``: ``blas_closest`` / ``blas_any`` on ``flowsynth.raycast.blas.atlas`` of the same mesh.

Scenes, 640x480 pixels, 60 deg horizontal fov, camera at the origin looking down +z:

- ``single``: one icosphere (radius 1 m, random rotation) 1.5 m in front of the camera, filling the view
  (every ray hits);
- ``30 spheres``: the scene of benchmarks/peers/raycast.py (``raycast_scene``: 30 icospheres 4-12 m away); each ray
  walks the instances near to far (sorted by the distance to their boxes) and stops at the first box beyond
  its best hit, as flowsynth's camera rays do (``flowsynth.kernels.raycast.closest_from_camera``).

For icospheres of 1280, 5120, 20480 and 81920 faces: closest-hit and any-hit cast time of both, their ratio
(``x_wp_mesh`` > 1: bvh4 is faster), hits compared (same hit mask, same instance, distance within 1e-5
relative, any-hit mask equal to the closest-hit mask), and build times: ``wp.Mesh``; bvh4's tree (numpy, once
per shape: ``flowsynth.raycast.blas.topology``); bvh4's per-mesh part (``atlas``: gather and refit; what every new size
of a shape costs).

Times are medians of process CPU time over round-robin rounds on one pinned core. Run
``python benchmarks/speed/bvh.py [--quick]``: prints a table, writes ``benchmarks/results/bvh.json`` and
``bvh_cast.png`` (Mrays/s against faces).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parents[1])]
from _common import (
    RAYCAST_FOV_DEG,
    RAYCAST_HEIGHT,
    RAYCAST_WIDTH,
    Timer,
    machine_info,
    pin_single_core,
    plot_curves,
    print_table,
    raycast_scene,
    time_round_robin,
    write_json,
)

PINNING = pin_single_core()
WIDTH, HEIGHT, FOV_DEG = RAYCAST_WIDTH, RAYCAST_HEIGHT, RAYCAST_FOV_DEG  # raycast.py's camera

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from flowsynth.raycast import SceneAccel, blas, pinhole
from flowsynth.caches import clear_caches
from flowsynth.scene import Camera
from flowsynth.kernels import wp_runtime

wp = wp_runtime()

from flowsynth.kernels.blas import blas_any, blas_closest
from flowsynth.kernels.raycast import box_entry_inv, inverse_dir, pixel_ray, Pinhole

SUBDIVISIONS = {1280: 3, 5120: 4, 20480: 5, 81920: 6}  # icosphere faces -> subdivisions
ENGINES = ("wp.Mesh", "bvh4")
SINGLE_DISTANCE = 1.5  # [m]: a unit sphere this close covers the whole 60 deg x 46.8 deg view
DIST_REL_TOL = 1e-5  # float32 ray-triangle distance agreement between the two


def make_cast(use_bvh4: bool, anyhit: bool):
    """Camera-ray kernel: per pixel, the instances near to far; one mesh query per box the ray enters."""

    @wp.kernel(enable_backward=False, module="unique")
    def cast(cam: Pinhole, order: wp.array[wp.int32], near: wp.array[wp.float32], lowers: wp.array[wp.vec3],
             uppers: wp.array[wp.vec3], obj_T_ref: wp.array[wp.mat44], mesh: wp.array[wp.uint64],
             root: wp.array[wp.int32], bounds: wp.array[wp.vec4], kids: wp.array[wp.vec4i],
             tris: wp.array[wp.vec3], face: wp.array[wp.int32],
             # outputs
             dist: wp.array2d[wp.float32], item_out: wp.array2d[wp.int32]):
        i = wp.tid()
        for j in range(dist.shape[1]):
            d = pixel_ray(i, j, cam)
            inv = inverse_dir(d)
            best_t = wp.float32(1.0e9)
            best = wp.int32(-1)
            for k in range(order.shape[0]):
                item = order[k]
                if near[item] >= best_t:
                    break
                te = box_entry_inv(lowers[item], uppers[item], d, inv)
                if te < 0.0 or te >= best_t:
                    continue
                X = obj_T_ref[item]
                o = wp.vec3(X[0, 3], X[1, 3], X[2, 3])
                dd = wp.transform_vector(X, d)
                if wp.static(anyhit):
                    hit = False
                    if wp.static(use_bvh4):
                        hit = blas_any(bounds, kids, tris, root[item], o, dd, best_t)
                    else:
                        hit = wp.mesh_query_ray_anyhit(mesh[item], o, dd, best_t)
                    if hit:
                        best = item
                        break
                else:
                    if wp.static(use_bvh4):
                        f, t, u, v = blas_closest(bounds, kids, tris, face, root[item], o, dd, best_t)
                        if f >= 0:
                            best_t = t
                            best = item
                    else:
                        q = wp.mesh_query_ray(mesh[item], o, dd, best_t)
                        if q.result and q.t < best_t:
                            best_t = q.t
                            best = item
            dist[i, j] = wp.where(best >= 0, best_t, 0.0)
            item_out[i, j] = best

    return cast


KERNELS = {(b, a): make_cast(b, a) for b in (False, True) for a in (False, True)}


def single_scene_poses(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(cam_T_world (1, 4, 4), world_T_obj (1, 1, 4, 4)) of one sphere filling the view."""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    pose[:3, 3] = (0.0, 0.0, SINGLE_DISTANCE)
    return np.eye(4)[None], pose[None, None]


def raycast_scene_poses() -> tuple[np.ndarray, np.ndarray]:
    """(cam_T_world (1, 4, 4), world_T_obj (1, 30, 4, 4)) of benchmarks/peers/raycast.py's scene."""
    scene = raycast_scene()
    return scene.cam_T_world, np.stack([o.poses for o in scene.objects], 1)


def build_mesh(mesh: trimesh.Trimesh):
    points = wp.array(np.asarray(mesh.vertices, np.float32), dtype=wp.vec3)
    indices = wp.array(np.asarray(mesh.faces, np.int32).reshape(-1), dtype=wp.int32)
    return lambda: wp.Mesh(points=points, indices=indices)


def build_times(make, repeat: int) -> float:
    """Median process CPU time of one ``make()`` [s], excluding the destruction of the result."""
    times, keep = [], []
    for _ in range(repeat):
        with Timer() as tm:
            keep.append(make())
        times.append(tm.cpu_s)
    return float(np.median(times))


def measure(scene_name: str, faces: int, poses, camera: Camera, repeat: int, build_repeat: int) -> list[dict]:
    """Closest- and any-hit casts of both engines for one scene and face count."""
    mesh = trimesh.creation.icosphere(subdivisions=SUBDIVISIONS[faces], radius=1.0)
    cam_T_world, world_T_obj = poses
    N = world_T_obj.shape[1]
    builds = {}
    if build_repeat:
        builds["wp_mesh_build_ms"] = 1e3 * build_times(build_mesh(mesh), build_repeat)

        def fresh_topology():
            clear_caches("blas.topology")
            return blas.topology(mesh.vertices, mesh.faces)

        builds["bvh4_tree_build_ms"] = 1e3 * build_times(fresh_topology, build_repeat)
        builds["bvh4_refit_ms"] = 1e3 * build_times(lambda: blas.atlas([mesh]), build_repeat)
    accel = SceneAccel([mesh] * N, cam_T_world, world_T_obj)
    A = accel.blas
    shape = (camera.height, camera.width)
    warp_mesh = build_mesh(mesh)()  # what flowsynth.raycast.accel built per asset until d08ad06
    item_mesh = wp.array(np.full(accel.F * N, warp_mesh.id, np.uint64), dtype=wp.uint64)
    inputs = [pinhole(camera), accel.frame_items, accel.near, accel.lowers, accel.uppers, accel.obj_T_ref,
              item_mesh, accel.item_root, A["bounds"], A["kids"], A["tris"], A["face"]]
    outs = {k: (wp.zeros(shape, dtype=wp.float32), wp.zeros(shape, dtype=wp.int32)) for k in KERNELS}
    fns = {k: (lambda k=k: wp.launch(KERNELS[k], dim=camera.height, inputs=inputs, outputs=list(outs[k])))
           for k in KERNELS}
    for fn in fns.values():
        fn()
    times = time_round_robin(fns, repeat=repeat, warmup=0, rotate=True)
    res = {k: (outs[k][0].numpy(), outs[k][1].numpy()) for k in KERNELS}
    ref_d, ref_i = res[False, False]
    hit = ref_i >= 0
    rows = []
    for anyhit in (False, True):
        d4, i4 = res[True, anyhit]
        dw, iw = res[False, anyhit]
        t4, tw = times[True, anyhit]["cpu_s"], times[False, anyhit]["cpu_s"]
        row = {"scene": scene_name, "faces": faces, "query": "any hit" if anyhit else "closest",
               "wp_mesh_ms": 1e3 * tw, "bvh4_ms": 1e3 * t4, "wp_mesh_Mrays_s": hit.size / tw / 1e6,
               "bvh4_Mrays_s": hit.size / t4 / 1e6, "x_wp_mesh": tw / t4, "hit_fraction": float(hit.mean()),
               "hit_mismatch": int(((i4 >= 0) != (iw >= 0)).sum())}
        if anyhit:
            row["any_vs_closest_mismatch"] = int(((i4 >= 0) != hit).sum())
        else:
            both = hit & (i4 >= 0)
            row["item_mismatch"] = int((i4 != iw).sum())
            row["dist_over_tol"] = int((np.abs(d4[both] - dw[both]) > DIST_REL_TOL * dw[both]).sum())
        rows.append({**row, **builds})
    return rows


def plot(rows: list[dict], scenes) -> None:
    series = {}
    for scene_name in scenes:
        for query in ("closest", "any hit"):
            part = [r for r in rows if r["scene"] == scene_name and r["query"] == query]
            for eng, key in (("wp.Mesh", "wp_mesh_Mrays_s"), ("bvh4", "bvh4_Mrays_s")):
                series[f"{eng}, {scene_name}, {query}"] = ([r["faces"] for r in part], [r[key] for r in part])
    plot_curves("bvh_cast", series, "faces per mesh", "Mrays/s (1 core)", logx=True, logy=False,
                title=f"Per-asset BVH query, {WIDTH}x{HEIGHT} camera rays")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 rounds (else 7)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    t_start = time.perf_counter()
    repeat = 3 if args.quick else 7
    build_repeat = 3 if args.quick else 5
    camera = Camera.from_fov(WIDTH, HEIGHT, FOV_DEG)
    scenes = {"single": single_scene_poses(), "30 spheres": raycast_scene_poses()}
    rows = []
    for scene_name, poses in scenes.items():
        for faces in SUBDIVISIONS:
            part = measure(scene_name, faces, poses, camera, repeat, build_repeat if scene_name == "single" else 0)
            rows += part
            print(f"{scene_name}, {faces} faces: closest x_wp_mesh {part[0]['x_wp_mesh']:.3f}", flush=True)
    builds = {r["faces"]: {k: v for k, v in r.items() if k.endswith("build_ms") or k.endswith("refit_ms")}
              for r in rows if "wp_mesh_build_ms" in r}
    info = machine_info()
    print(f"\nPer-asset BVH query, {WIDTH}x{HEIGHT} camera rays, icospheres: wp.Mesh (wp.mesh_query_ray) vs "
          f"flowsynth's bvh4 (blas_closest / blas_any), the same kernel otherwise; medians of {repeat} round-robin "
          "rounds of process CPU time; x_wp_mesh = wp.Mesh's time / bvh4's (> 1: bvh4 faster)")
    print(f"{info['cpu_model']}, affinity {PINNING['affinity']}, warp {info['warp-lang']}")
    print_table(rows, ["scene", "faces", "query", "wp_mesh_ms", "bvh4_ms", "wp_mesh_Mrays_s", "bvh4_Mrays_s",
                       "x_wp_mesh", "hit_fraction", "hit_mismatch", "item_mismatch", "dist_over_tol",
                       "any_vs_closest_mismatch"])
    print("\nBuild of one mesh [ms]: wp.Mesh; bvh4 tree (numpy SAH, once per shape); bvh4 refit (per mesh: "
          "gather + refit kernel, what a new size of a cached shape costs)")
    print_table([{"faces": f, **b} for f, b in builds.items()],
                ["faces", "wp_mesh_build_ms", "bvh4_tree_build_ms", "bvh4_refit_ms"])
    plot(rows, scenes)
    total = time.perf_counter() - t_start
    path = write_json("bvh", {
        "machine": info, "pinning": PINNING, "loadavg_1_5_15": os.getloadavg(), "quick": args.quick,
        "setup": {"width": WIDTH, "height": HEIGHT, "fov_deg": FOV_DEG, "single_distance_m": SINGLE_DISTANCE,
                  "repeat": repeat, "build_repeat": build_repeat, "engines": ENGINES},
        "rows": rows, "builds": builds, "total_s": total})
    print(f"total {total:.1f} s; wrote {path}")


if __name__ == "__main__":
    main()
