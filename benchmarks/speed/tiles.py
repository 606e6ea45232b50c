"""Primary cast with per-screen-tile candidate lists against one list per frame (``flowsynth.raycast.tiles.TILE``).

Below ``ORDERED_MAX`` instances a primary ray walks a near-to-far candidate list instead of the top-level
BVH; the list is per TILE x TILE screen tile (the instances whose clipped hull projects onto the tile). A tile as
large as the image is one list per frame, which is the baseline here. Scene: benchmarks/peers/raycast.py's 30
icospheres x 5120 faces at 640x480, one core, one thread, kernel cast with normals (``cast_gbuffer``),
round-robin medians of process CPU time. Hit maps must agree exactly across tile sizes.

Run ``python benchmarks/speed/tiles.py [--quick]``; prints a table and writes ``benchmarks/results/tiles.json``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parents[1])]
from _common import machine_info, pin_single_core, print_table, raycast_scene, time_round_robin, write_json

PINNING = pin_single_core()  # one core and one thread per library, before numpy and Warp load

import numpy as np

from flowsynth.raycast import SceneAccel, cast_gbuffer, scene_arrays, tiles as tiles_mod

TILES = {"one list per frame": 1 << 20, "64 px tiles": 64, "16 px tiles (default)": 16, "8 px tiles": 8}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer rounds")
    args = ap.parse_args()
    default_tile = tiles_mod.TILE
    load_before = os.getloadavg()
    scene = raycast_scene()
    cam = scene.camera
    meshes, cam_T_world, world_T_obj = scene_arrays(scene)
    fns, items = {}, {}
    for name, tile in TILES.items():
        acc = SceneAccel(meshes, cam_T_world, world_T_obj)

        def cast(acc=acc, tile=tile):
            tiles_mod.TILE = tile  # read by tile_lists (cached per accel)
            try:
                return cast_gbuffer(acc, cam, want_normals=True, want_points=False, threads=1)
            finally:
                tiles_mod.TILE = default_tile

        items[name] = cast().item
        fns[name] = cast
    t = time_round_robin(fns, repeat=3 if args.quick else 7, warmup=1)
    rays = cam.width * cam.height
    base = t["one list per frame"]["cpu_s"]
    ref = items["16 px tiles (default)"]
    rows = [{"candidate lists": name, "cpu_ms": 1e3 * t[name]["cpu_s"], "Mrays_s": rays / t[name]["cpu_s"] / 1e6,
             "speedup": base / t[name]["cpu_s"], "hit_map_equal": bool(np.array_equal(items[name], ref))}
            for name in TILES]
    print(f"Primary cast (normals), {cam.width}x{cam.height}, {len(scene.objects)} instances, 1 thread; medians "
          f"of process CPU time; load average {load_before[0]:.2f} -> {os.getloadavg()[0]:.2f}")
    print_table(rows, ["candidate lists", "cpu_ms", "Mrays_s", "speedup", "hit_map_equal"])
    path = write_json("tiles", {"machine": machine_info(), "pinning": PINNING, "rows": rows,
                                "load_before": load_before, "load_after": os.getloadavg()})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
