"""Regenerate docs/final_pass.png: clean (top row) against final (bottom row) frames of a few default samples.

    PYTHONPATH=. .venv/bin/python scripts/make_final_sheet.py                 # writes docs/final_pass.png
    PYTHONPATH=. .venv/bin/python scripts/make_final_sheet.py --out x.png --num 3 --seed 1

Each column is the middle frame of one sample of the default BouncingThingsConfig at 256x192 (3 frames), so
the final pass's settings are the defaults (docs/rendering.md, Final pass); a final tile's label says what its
clip drew: depth of field (aperture, focus) or none, the noise levels and the frame's exposure change. The PNG
carries the config in a tEXt chunk ``flowsynth:config``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import flowsynth as fs
from flowsynth.renderer import draw_final
from flowsynth.plan import FinalPass
from flowsynth.viz import contact_sheet, save_png


def _tile(rgb) -> np.ndarray:
    """(3, H, W) float in [0, 1] -> (H, W, 3) uint8."""
    return np.rint(np.clip(rgb.numpy(), 0, 1) * 255).astype(np.uint8).transpose(1, 2, 0)


def _label(draw, t: int) -> str:
    dof = f"A {draw.aperture * 1000:.0f}mm f@{draw.focus:.1f}m" if draw.dof else "no DoF"
    return f"{dof} ev{np.log2(draw.gains[t, 1]):+.2f} a{draw.shot_noise:.4f}"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "final_pass.png"))
    p.add_argument("--num", type=int, default=4, help="samples (columns)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    cfg = fs.BouncingThingsConfig(width=256, height=192, num_frames=3)
    ds = fs.datasets.BouncingThings(cfg, outputs=["rgb", "rgb_final", "depth", "instance"], seed=args.seed)
    fp = FinalPass.from_options({k: v for k, v in cfg.plan_options().items() if k.startswith("final_")})
    clean, final = [], []
    t = cfg.num_frames // 2
    for i in range(args.num):
        s, scene = ds.sample(i), ds.scene(i)
        inst = s["instance"][t, 0].numpy()
        objects = np.array([False] + [not o.background for o in scene.objects])
        draw = draw_final(scene.render_seed, fp, s["depth"][t, 0].numpy().astype(np.float64), objects[inst],
                          cfg.num_frames)
        clean.append((f"clean {i}", _tile(s["rgb"][t])))
        final.append((f"final {i}: {_label(draw, t)}", _tile(s["rgb_final"][t])))
    sheet = contact_sheet(clean + final, columns=args.num)
    save_png(args.out, sheet, {"flowsynth:config": json.dumps(cfg.to_dict(), sort_keys=True)})
    print(f"wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]})")


if __name__ == "__main__":
    main()
