"""How large the motion is: |flow| distributions of flowsynth configs, the 2D baseline and real ground truth.

    python benchmarks/learning/magnitudes.py [--num 12] [--middlebury DIR] [--set FIELD=JSON ...] [--quick]

Real video holds still and slow regions beside fast ones. This script puts side by side, as
histograms of |flow| on log-spaced bins and as shares of Sintel's s0-10 / s10-40 / s40+ partition (the bands the
Sintel benchmark scores separately; the benchmark does not publish each band's pixel share, so the shares here
are measured, never quoted):

- "default": the default config at 512x384 (the size ``flow_px`` is given at), frame pairs, over valid pixels;
- "candidate": the default with ``--set`` fields changed (and ``--flow-px``), when given;
- "chairs2d": the learning benchmark's 2D baseline (``learning.pools.build_arms``' "chairs2d" arm, 64 pairs of seed 0)
  at the judge's 256x192, its motion scaled to the flowsynth pool's mean as the judge does, flow multiplied by
  ``protocol.SCALE`` (the 512x384 scale);
- "middlebury": the ground truth of the pairs under ``--middlebury`` at their own size (420x380 to 640x480,
  about the 512x384 scale), known pixels.

Reports per set the mean, median, p90, p99 and max, the zero-flow share (< 0.1 px), the sub-pixel share (< 1 px)
and the Sintel bands. Writes results/magnitudes.json and the plot results/magnitudes.png.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common and the learning package

from _common import RESULTS_DIR, machine_info, print_table, write_json
from learning.pools import build_arms
from learning.protocol import SCALE
from learning.sets import middlebury_pairs

BINS = (0.0, 0.01) + tuple(float(x) for x in __import__("numpy").geomspace(0.02, 1000.0, 48))
BANDS = ((0.0, 10.0, "s0-10"), (10.0, 40.0, "s10-40"), (40.0, float("inf"), "s40+"))


def flowsynth_magnitudes(cfg, num: int, seed: int = 0):
    """|flow_fw| [px] of every valid pixel of ``num`` samples of ``cfg`` (frame pairs)."""
    import numpy as np
    import torch

    import flowsynth as fs

    ds = fs.datasets.BouncingThings(cfg, outputs=["flow_fw", "valid_fw"], seed=seed)
    out = []
    for i in range(num):
        s = ds.sample(i)
        out.append(torch.linalg.vector_norm(s["flow_fw"][0], dim=0)[s["valid_fw"][0, 0]].numpy())
    return np.concatenate(out).astype(np.float64)


def describe(m) -> dict:
    import numpy as np

    hist, _ = np.histogram(np.clip(m, 0, BINS[-1]), bins=np.array(BINS))
    return {"pixels": int(m.size), "mean": float(m.mean()), "p50": float(np.percentile(m, 50)),
            "p90": float(np.percentile(m, 90)), "p99": float(np.percentile(m, 99)), "max": float(m.max()),
            "zero_share": float((m < 0.1).mean()), "subpixel_share": float((m < 1.0).mean()),
            **{name: float(((m >= lo) & (m < hi)).mean()) for lo, hi, name in BANDS},
            "histogram": (hist / max(m.size, 1)).tolist()}


def plot(sets: dict) -> Path | None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    import numpy as np

    edges = np.array(BINS)
    centres = np.sqrt(np.maximum(edges[1:], 1e-3) * np.maximum(edges[:-1], 1e-3))
    fig, ax = plt.subplots(figsize=(7, 4), dpi=110)
    for name, d in sets.items():
        ax.step(centres, d["histogram"], where="mid", label=f"{name} (mean {d['mean']:.1f}, p50 {d['p50']:.1f})")
    for lo, _, band in BANDS[1:]:
        ax.axvline(lo, color="grey", lw=0.8, ls="--")
        ax.text(lo * 1.05, ax.get_ylim()[1] * 0.9, band, fontsize=8, color="grey")
    ax.set_xscale("log")
    ax.set_xlabel("|flow| [px per frame, 512x384 scale]")
    ax.set_ylabel("share of pixels per bin")
    ax.set_title("flow magnitude distributions (log-spaced bins)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / "magnitudes.png"
    fig.savefig(path)
    plt.close(fig)
    return path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--num", type=int, default=None, help="flowsynth samples per config (default 12; --quick 2)")
    p.add_argument("--middlebury", default=None, metavar="DIR", help="folder of Middlebury pairs (NAME/flow10.flo)")
    p.add_argument("--flow-px", type=lambda v: tuple(float(x) for x in v.split(",")), default=None, metavar="LO,HI",
                   help="the candidate's flow_px")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=JSON", help="a candidate config field")
    args = p.parse_args()
    import numpy as np
    import torch

    import flowsynth as fs

    n = args.num or (2 if args.quick else 12)
    size = (128, 96) if args.quick else (512, 384)
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    base = fs.BouncingThingsConfig(width=size[0], height=size[1], num_frames=2)
    mags = {"default": flowsynth_magnitudes(base, n)}
    overrides = {k: json.loads(v) for k, _, v in (s.partition("=") for s in args.set)}
    if args.flow_px:
        overrides["flow_px"] = list(args.flow_px)
    if overrides:
        mags["candidate"] = flowsynth_magnitudes(fs.BouncingThingsConfig.from_dict(
            {**overrides, "width": size[0], "height": size[1], "num_frames": 2}), n)
    # the 2D baseline as the learning benchmark makes it, at its 256x192, matched to its flowsynth pool's mean there
    chairs = build_arms(["chairs2d"], 0, 0, {}, 64)[0]["chairs2d"]
    mags["chairs2d"] = (torch.linalg.vector_norm(chairs[2], dim=1)[chairs[3][:, 0]].numpy().astype(np.float64)
                        * SCALE)
    mb = middlebury_pairs(args.middlebury)
    if mb:
        mags["middlebury"] = np.concatenate([torch.linalg.vector_norm(v[2][0], dim=0)[v[3][0, 0] > 0.5].numpy()
                                             for v in mb.values()]).astype(np.float64)
    sets = {name: describe(m) for name, m in mags.items()}
    rows = [{"set": name, "pixels": d["pixels"], "mean": d["mean"], "p50": d["p50"], "p90": d["p90"], "p99": d["p99"],
             "zero %": 100 * d["zero_share"], "<1 px %": 100 * d["subpixel_share"],
             **{b: f"{100 * d[b]:.1f}%" for _, _, b in BANDS}} for name, d in sets.items()]
    print(f"\n|flow| [px per frame] at the 512x384 scale ({n} flowsynth samples a config; load {load})")
    print_table(rows, list(rows[0]))
    path = plot(sets)
    if path:
        print(f"plot: {path}")
    write_json("magnitudes" + ("_quick" if args.quick else ""), {
        "machine": machine_info(), "load": load, "samples": n, "size": size, "bins": list(BINS),
        "candidate": {k: list(v) if isinstance(v, tuple) else v for k, v in overrides.items()}, "sets": sets})


if __name__ == "__main__":
    main()
