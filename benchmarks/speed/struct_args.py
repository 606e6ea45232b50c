"""How to pass the ``Instances`` struct to a kernel: whole, or its fields as separate arguments?

Two questions, each timed in alternating rounds (``time_round_robin(rotate=True)``), process CPU time of a serial
Warp CPU launch (one thread), the ratio of every round reported, not only the medians:

1. ``cast``: one closest-hit ray per pixel of ``raycast_scene()`` (30 icospheres, 640x480) through the top-level BVH
   Variant "whole": the kernel takes ``Instances`` and hands it whole to ``trace_closest`` (flowsynth's traversal,
   which takes the struct since docs/decisions/0021). Variant "fields": the kernel takes the 11 arrays and the BVH
   id as separate arguments and hands them, separately, to ``closest_fields``, the same traversal written here with
   one argument per array (``trace_closest`` as it was until 0021). The two write the same distances (checked bit
   for bit).
2. ``tile``: flowsynth.kernels.raycast.tile_list's docstring says a struct argument of a ``@wp.func`` is copied per
   call, so it takes the ``TileLists`` scalars. Variant "whole": a func that takes ``TileLists`` by value and reads
   its scalars; "fields": ``tile_list`` itself. Each thread computes the list of every pixel of its row for 8
   frames and sums ``start[list]`` (the same sums, checked).

Run: ``nice .venv/bin/python benchmarks/speed/struct_args.py [--rounds 7]``. Writes results/struct_args.json. The
reading and the choice: docs/decisions/0021-instances-struct-convention.md.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common

from _common import machine_info, pin_single_core, print_table, raycast_scene, time_round_robin, write_json

from flowsynth.raycast import SceneAccel, pinhole
from flowsynth.kernels.blas import blas_closest
from flowsynth.kernels.raycast import Instances, Pinhole, TileLists, thin_skip, tile_list, trace_closest

TILE_FRAMES = 8  # frames of the tile-index kernel (one frame's work is too small to time)


@wp.func
def ray_dir(i: wp.int32, j: wp.int32, cam: Pinhole):
    y = (wp.float32(i) - cam.intr[3]) / cam.intr[1]
    x = (wp.float32(j) - cam.intr[2] - cam.skew * y) / cam.intr[0]
    return wp.normalize(wp.vec3(x, y, 1.0))


@wp.func
def closest_whole(inst: Instances, g: wp.int32, d: wp.vec3, max_t: wp.float32):
    return trace_closest(inst, inst.roots[g], wp.vec3(0.0), d, max_t)


@wp.func
def closest_fields(bvh: wp.uint64, root: wp.int32, item_root: wp.array[wp.int32], bb: wp.array[wp.vec4],
                   bk: wp.array[wp.vec4i], bt: wp.array[wp.vec3], bf: wp.array[wp.int32], obj_T_ref: wp.array[wp.mat44],
                   thin: wp.array[wp.int32], obj_lo: wp.array[wp.vec3], obj_hi: wp.array[wp.vec3], d: wp.vec3,
                   max_t: wp.float32):
    """``trace_closest`` with one argument per array (its form until docs/decisions/0021)."""
    best_t = max_t
    best_item = wp.int32(-1)
    best_face = wp.int32(-1)
    best_u = wp.float32(0.0)
    best_v = wp.float32(0.0)
    o = wp.vec3(0.0)
    query = wp.bvh_query_ray(bvh, o, d, root)
    item = wp.int32(0)
    while wp.bvh_query_next(query, item, best_t):
        X = obj_T_ref[item]
        o_obj = wp.transform_point(X, o)
        d_obj = wp.transform_vector(X, d)
        if thin_skip(thin, obj_lo, obj_hi, item, o_obj, d_obj, best_t):
            continue
        face, t, u, v = blas_closest(bb, bk, bt, bf, item_root[item], o_obj, d_obj, best_t)
        if face >= 0:
            best_t = t
            best_item = item
            best_face = face
            best_u = u
            best_v = v
    return best_item, best_t, best_face, best_u, best_v


@wp.kernel(enable_backward=False)
def cast_whole(inst: Instances, cam: Pinhole, max_t: wp.float32, out: wp.array2d[wp.float32]):
    i = wp.tid()
    for j in range(out.shape[1]):
        item, dist, face, bu, bv = closest_whole(inst, 0, ray_dir(i, j, cam), max_t)
        out[i, j] = wp.where(item >= 0, dist, -1.0)


@wp.kernel(enable_backward=False)
def cast_fields(bvh: wp.uint64, roots: wp.array[wp.int32], item_root: wp.array[wp.int32], bb: wp.array[wp.vec4],
                bk: wp.array[wp.vec4i], bt: wp.array[wp.vec3], bf: wp.array[wp.int32], obj_T_ref: wp.array[wp.mat44],
                thin: wp.array[wp.int32], obj_lo: wp.array[wp.vec3], obj_hi: wp.array[wp.vec3], cam: Pinhole,
                max_t: wp.float32, out: wp.array2d[wp.float32]):
    i = wp.tid()
    for j in range(out.shape[1]):
        item, dist, face, bu, bv = closest_fields(bvh, roots[0], item_root, bb, bk, bt, bf, obj_T_ref, thin, obj_lo,
                                                  obj_hi, ray_dir(i, j, cam), max_t)
        out[i, j] = wp.where(item >= 0, dist, -1.0)


@wp.func
def tile_list_whole(tiles: TileLists, f: wp.int32, i: wp.int32, j: wp.int32):
    return (f * tiles.tiles_y + (i >> tiles.tile_shift)) * tiles.tiles_x + (j >> tiles.tile_shift)


@wp.kernel(enable_backward=False)
def tiles_whole(tiles: TileLists, frames: wp.int32, out: wp.array2d[wp.int32]):
    i = wp.tid()
    for j in range(out.shape[1]):
        acc = wp.int32(0)
        for f in range(frames):
            acc += tiles.start[tile_list_whole(tiles, f, i, j)]
        out[i, j] = acc


@wp.kernel(enable_backward=False)
def tiles_fields(tiles: TileLists, frames: wp.int32, out: wp.array2d[wp.int32]):
    i = wp.tid()
    for j in range(out.shape[1]):
        acc = wp.int32(0)
        for f in range(frames):
            acc += tiles.start[tile_list(tiles.tiles_x, tiles.tiles_y, tiles.tile_shift, f, i, j)]
        out[i, j] = acc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=7)
    args = ap.parse_args()
    pin = pin_single_core()  # one CPU (Warp's CPU launches run serially; numpy's threads are not timed)

    scene = raycast_scene()
    world_T_obj = np.stack([o.poses for o in scene.objects], 1)
    accel = SceneAccel([o.mesh for o in scene.objects], scene.cam_T_world, world_T_obj)
    inst, cam = accel.instances(), pinhole(scene.camera)
    H, W = scene.camera.height, scene.camera.width
    max_t = 1.0e9
    a, b = (wp.empty((H, W), dtype=wp.float32) for _ in range(2))
    fields = [inst.bvh, inst.roots, inst.item_root, inst.blas_bounds, inst.blas_kids, inst.blas_tris, inst.blas_face,
              inst.obj_T_ref, inst.thin, inst.obj_lo, inst.obj_hi, cam, max_t]

    tl = TileLists()
    tl.tile_shift = 4
    tl.tiles_x, tl.tiles_y = -(-W // 16), -(-H // 16)
    tl.start = wp.array(np.arange(TILE_FRAMES * tl.tiles_x * tl.tiles_y + 1, dtype=np.int32), dtype=wp.int32)
    tl.items = wp.zeros(1, dtype=wp.int32)
    c, d = (wp.empty((H, W), dtype=wp.int32) for _ in range(2))

    fns = {
        "cast whole": lambda: wp.launch(cast_whole, H, [inst, cam, max_t], [a]),
        "cast fields": lambda: wp.launch(cast_fields, H, fields, [b]),
        "tile whole": lambda: wp.launch(tiles_whole, H, [tl, TILE_FRAMES], [c]),
        "tile fields": lambda: wp.launch(tiles_fields, H, [tl, TILE_FRAMES], [d]),
    }
    times = time_round_robin(fns, repeat=args.rounds, warmup=1, rotate=True)
    assert np.array_equal(a.numpy(), b.numpy()) and (a.numpy() > 0).any(), "the two casts disagree"
    assert np.array_equal(c.numpy(), d.numpy()), "the two tile-index kernels disagree"

    rows, out = [], {}
    for what in ("cast", "tile"):
        w, f = times[f"{what} whole"]["cpu_all_s"], times[f"{what} fields"]["cpu_all_s"]
        ratios = [x / y for x, y in zip(w, f)]
        out[what] = {"whole_cpu_s": w, "fields_cpu_s": f, "ratio_whole_over_fields": ratios}
        rows.append({"kernel": what, "whole s (median)": statistics.median(w),
                     "fields s (median)": statistics.median(f),
                     "ratio median": statistics.median(ratios), "ratio min": min(ratios), "ratio max": max(ratios)})
    print_table(rows, list(rows[0]))
    write_json("struct_args", {"rounds": args.rounds, "pin": pin, "results": out, "machine": machine_info()})


if __name__ == "__main__":
    main()
