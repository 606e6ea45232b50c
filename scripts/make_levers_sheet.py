"""Regenerate docs/levers.png: the same default samples with issue 38's look levers, one row each.

    PYTHONPATH=. .venv/bin/python scripts/make_levers_sheet.py                # writes docs/levers.png
    PYTHONPATH=. .venv/bin/python scripts/make_levers_sheet.py --out x.png --num 3 --seed 1

Rows: the default config; "leaves" added to the texture families (dead-leaves discs); smooth shading (corner
normals); both. Columns: the first frame of samples 0.. of seed ``--seed`` at 256x192, render_mode "direct" so that
shading shows. A lever changes the materials drawn (leaves) or the shading normals (smooth), never the scene's
geometry or motion. The PNG carries each row's config changes in a tEXt chunk ``flowsynth:rows``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

import flowsynth as fs
from flowsynth.viz import contact_sheet, save_png

LEAVES = ("noise", "value", "cells", "stripes", "checks", "blend", "leaves")
ROWS = {"default": {}, "leaves": {"texture_families": LEAVES}, "smooth": {"smooth_shading": True},
        "leaves+smooth": {"texture_families": LEAVES, "smooth_shading": True}}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "levers.png"))
    p.add_argument("--num", type=int, default=4, help="samples (columns)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    base = fs.BouncingThingsConfig(width=256, height=192, num_frames=2, render_mode="direct")
    tiles = []
    for name, changes in ROWS.items():
        ds = fs.datasets.BouncingThings(dataclasses.replace(base, **changes), outputs=["rgb"], seed=args.seed)
        for i in range(args.num):
            rgb = ds.sample(i)["rgb"][0]
            tiles.append((f"{name} {i}", np.rint(np.clip(rgb.numpy(), 0, 1) * 255).astype(np.uint8).transpose(1, 2, 0)))
    sheet = contact_sheet(tiles, columns=args.num)
    save_png(args.out, sheet, {"flowsynth:rows": json.dumps({k: {f: list(v) if isinstance(v, tuple) else v
                                                                  for f, v in c.items()} for k, c in ROWS.items()})})
    print(f"wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]})")


if __name__ == "__main__":
    main()
