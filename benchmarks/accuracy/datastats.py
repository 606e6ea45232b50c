"""What each preset produces: flowsynth.stats (with the OpenCV DIS check) on N samples per preset.

    python benchmarks/accuracy/datastats.py [--quick] [--num 16]

The default config is measured at 512x384 (the issue-12 targets), chairs at its own 512x384 and things at
its own 960x540; all as frame pairs (num_frames=2) so every preset costs the same number of renders.
Writes results/datastats.json; docs/statistics.md quotes it beside FlyingChairs, FlyingThings3D and Sintel.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common

from _common import machine_info, print_table, write_json

CASES = {"default": {"width": 512, "height": 384}, "chairs": {}, "things": {}}
TARGETS = ("default at 512x384: mean 8-40 px, p90 >= 25 px, zero flow <= 10%, textureless <= 30%, "
           "DIS EPE < zero-flow EPE on room and objects")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--num", type=int, default=None, help="samples per preset (default 4 quick, 16 full)")
    args = p.parse_args()
    import flowsynth as fs
    from flowsynth.stats import dataset_stats

    n = args.num or (4 if args.quick else 16)
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    rows, out = [], {}
    for name, extra in CASES.items():
        cfg = fs.BouncingThingsConfig.preset(name, num_frames=2, **extra)
        st = dataset_stats(cfg, n, seed=0, dis=True)
        out[name] = dict(st, config=cfg.to_dict())
        f, d = st["flow"], st["dis"]
        rows.append({"preset": name, "size": f"{cfg.width}x{cfg.height}", "mean": f["mean"], "p50": f["p50"],
                     "p90": f["p90"], "p99": f["p99"], "zero %": 100 * f["zero_fraction"],
                     "occ %": 100 * st["occluded_fraction"], "oof %": 100 * st["out_of_frame_fraction"],
                     "flat %": 100 * st["textureless_fraction"], "room %": 100 * st["category_share"].get("room", 0),
                     "DIS/zero room": f"{d['room']['dis_epe']:.2f}/{d['room']['zero_epe']:.2f}",
                     "DIS/zero obj": f"{d['objects']['dis_epe']:.2f}/{d['objects']['zero_epe']:.2f}",
                     "s/sample": st["seconds_per_sample"]["mean"]})
    print(f"\nflowsynth.stats over {n} samples per preset (|flow| in px; flat = textureless 8x8 patches). Load: {load}")
    print_table(rows, list(rows[0]))
    print(f"targets: {TARGETS}")
    write_json("datastats", {"machine": machine_info(), "load": load, "samples": n, "presets": out, "table": rows})


if __name__ == "__main__":
    main()
