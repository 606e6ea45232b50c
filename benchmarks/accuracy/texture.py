"""Texture at pixel scale: textureless 8x8 patches and mean grey of default samples in every render mode,
beside real photographs (scikit-image's chelsea, coffee, astronaut resized to the same size).

    python benchmarks/accuracy/texture.py [--quick] [--samples N]

A patch is textureless when its grey intensity (mean of the sRGB channels, 0..1) has standard deviation
below 0.02: ``flowsynth.stats.textureless_fraction``. Full run: 16 default samples (seed 0, indices 0-15)
at 512x384, every frame of 2-frame clips (texture does not depend on the clip length; 2 frames keep path
tracing affordable). ``--quick``: 4 samples at 256x192. Writes benchmarks/results/texture.json (quick:
texture_quick.json). Needs the ``bench`` extra (scikit-image).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common

from _common import Timer, machine_info, print_table, write_json

MODES = ("flat", "direct", "path")
PHOTOS = ("chelsea", "coffee", "astronaut")


def photo_rows(W: int, H: int) -> list[dict]:
    import numpy as np
    import skimage.data
    from PIL import Image

    from flowsynth.stats import textureless_fraction

    rows = []
    for name in PHOTOS:
        im = Image.fromarray(getattr(skimage.data, name)()).convert("RGB").resize((W, H), Image.BILINEAR)
        rgb = np.asarray(im, np.float32).transpose(2, 0, 1)[None] / 255.0
        rows.append({"source": f"photo: {name}", "textureless": textureless_fraction(rgb),
                     "mean grey": float(rgb.mean()), "s/sample": None})
    return rows


def mode_row(mode: str, W: int, H: int, n: int) -> dict:
    import numpy as np

    import flowsynth as fs
    from flowsynth.stats import textureless_fraction

    cfg = fs.BouncingThingsConfig(width=W, height=H, num_frames=2, render_mode=mode)
    ds = fs.datasets.BouncingThings(cfg, outputs=["rgb"], seed=0)
    flat, grey = [], []
    with Timer() as tm:
        for i in range(n):
            rgb = ds.sample(i)["rgb"]
            flat.append(textureless_fraction(rgb))
            grey.append(float(rgb.mean()))
    return {"source": f"flowsynth default, {mode}", "textureless": float(np.mean(flat)),
            "textureless worst sample": float(np.max(flat)), "mean grey": float(np.mean(grey)),
            "s/sample": tm.wall_s / n}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--samples", type=int, default=None, help="samples per mode (default 16, quick 4)")
    args = p.parse_args()
    W, H = (256, 192) if args.quick else (512, 384)
    n = args.samples or (4 if args.quick else 16)
    rows = [mode_row(mode, W, H, n) for mode in MODES] + photo_rows(W, H)
    print(f"\nTextureless 8x8 patches (grey std < 0.02) at {W}x{H}, {n} samples x 2 frames per mode; "
          f"load average {os.getloadavg()[0]:.2f}")
    print_table(rows, ["source", "textureless", "textureless worst sample", "mean grey", "s/sample"])
    write_json("texture_quick" if args.quick else "texture",
               {"machine": machine_info(["scikit-image"]), "resolution": [W, H], "samples": n, "rows": rows})


if __name__ == "__main__":
    main()
