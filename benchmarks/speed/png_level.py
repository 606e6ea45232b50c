"""zlib level of 16-bit PNG encoding (``flowsynth.io.png.encode_png16``): encode time against file size.

The image is a KITTI-format flow map (u*64 + 2^15, v*64 + 2^15, valid) of one rendered BouncingThings sample
at KITTI's 1242x375, so the numbers reflect flowsynth's own flow. ``flowsynth.io.png.ZLIB_LEVEL`` is chosen
from this table. Run ``python benchmarks/speed/png_level.py [--quick]``; prints a table and writes
``benchmarks/results/png_level.json``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parents[1])]
from _common import machine_info, pin_single_core, print_table, timeit, write_json

PINNING = pin_single_core()

import numpy as np

import flowsynth as fs
from flowsynth.io import KITTI_FLOW_SCALE, ZLIB_LEVEL, encode_png16


def kitti_image(seed: int) -> np.ndarray:
    """(375, 1242, 3) uint16 KITTI flow image of sample 0's first flow pair."""
    cfg = fs.BouncingThingsConfig(width=1242, height=375, num_frames=2, motion="kinematic")
    s = fs.datasets.BouncingThings(cfg, outputs=["flow_fw", "valid_fw"], seed=seed).sample(0)
    flow, ok = s["flow_fw"][0].double().numpy(), s["valid_fw"][0, 0].numpy()
    image = np.zeros((*ok.shape, 3), np.uint16)
    stored = np.rint(np.clip(flow * KITTI_FLOW_SCALE + 2**15, 0, 65535)).astype(np.uint16)
    image[..., 0], image[..., 1], image[..., 2] = stored[0] * ok, stored[1] * ok, ok
    return image


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats")
    args = ap.parse_args()
    repeat = 2 if args.quick else 5
    load_before = os.getloadavg()
    image = kitti_image(0)
    rows = []
    for level in (1, 3, 6, 9):
        size = len(encode_png16(image, level=level))
        t = timeit(lambda lv=level: encode_png16(image, level=lv), repeat=repeat, warmup=0, clock="cpu")
        rows.append({"level": level, "chosen": level == ZLIB_LEVEL, "encode_s": t, "kB": size / 1e3})
    for r in rows:
        r["size_vs_level_1"] = r["kB"] / rows[0]["kB"]
    print(f"encode_png16 of a 1242x375 KITTI flow map, median of {repeat} (process CPU time); load average "
          f"{load_before[0]:.2f} -> {os.getloadavg()[0]:.2f}")
    print_table(rows, ["level", "chosen", "encode_s", "kB", "size_vs_level_1"])
    path = write_json("png_level", {"machine": machine_info(), "pinning": PINNING, "rows": rows,
                                    "load_before": load_before, "load_after": os.getloadavg()})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
