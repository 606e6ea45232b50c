"""``sintel`` layout: MPI Sintel's training tree, what ``torchvision.datasets.Sintel`` reads.

::

    DIR/
      manifest.json
      Sintel/training/
        clean/scene_00000/frame_0001.png ... frame_TTTT.png     8-bit RGB, every frame of sample 0
        final/scene_00000/frame_0001.png ... frame_TTTT.png     8-bit RGB, rgb_final (when exported)
        flow/scene_00000/frame_0001.flo ... (T - 1 files)       flow_fw frame t -> t+1, float32, bit-exact
        occlusions/scene_00000/frame_0001.png ...               occ_fw, 8-bit 0 / 255 (when exported)

One scene per sample, frames numbered from 1 as in Sintel. The ``final`` pass is written when ``rgb_final``
is among the outputs (``--outputs rgb,rgb_final,flow_fw,occ_fw``; flowsynth/renderer/finalpass.py), read by
``torchvision.datasets.Sintel(root=DIR, pass_name="final")`` (or "both"); flow and occlusions are the same
for both passes. ``.flo`` holds the stream's flow, 0 where not ``valid_fw``: the format has no mask.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from flowsynth.io.flo import read_flo, write_flo
from flowsynth.io.layouts import register
from flowsynth.io.layouts.base import Layout
from flowsynth.io.png import read_mask_png, read_rgb_png, write_mask_png, write_rgb_png

__all__ = ["Sintel"]

_TRAIN = "Sintel/training"


@register
class Sintel(Layout):
    """One sample per scene folder ``Sintel/training/{clean,final,flow,occlusions}/scene_NNNNN/``."""

    name = "sintel"
    summary = "Sintel/training/clean/scene_NNNNN/frame_NNNN.png, final/ (with rgb_final), flow/.../*.flo, " \
              "occlusions/, one scene per sample; torchvision.datasets.Sintel(root=DIR)"
    default_outputs = ("rgb", "flow_fw", "occ_fw")
    required_outputs = ("rgb", "flow_fw")
    stored_outputs = default_outputs + ("rgb_final",)
    min_frames = 2
    owned = ("Sintel",)

    def write(self, sample: dict[str, torch.Tensor], index: int, folder: Path) -> dict[str, str]:
        scene = f"scene_{index:05d}"
        rgb, flow = sample["rgb"].numpy(), sample["flow_fw"].numpy()
        parts = {"clean": ("png", "rgb", rgb), "flow": ("flo", "flow_fw", flow)}
        if "rgb_final" in sample:
            parts["final"] = ("png", "rgb_final", sample["rgb_final"].numpy())
        if "occ_fw" in sample:
            parts["occlusions"] = ("png", "occ_fw", sample["occ_fw"].numpy()[:, 0])
        out = {}
        for sub, (ext, key, frames) in parts.items():
            (Path(folder) / _TRAIN / sub / scene).mkdir(parents=True)
            for t, frame in enumerate(frames):
                rel = f"{_TRAIN}/{sub}/{scene}/frame_{t + 1:04d}.{ext}"
                writer = {"rgb": write_rgb_png, "rgb_final": write_rgb_png, "flow_fw": write_flo,
                          "occ_fw": write_mask_png}[key]
                writer(Path(folder) / rel, frame)
                out[rel] = key
        return out

    def read(self, root: Path, files: Sequence[str]) -> dict[str, torch.Tensor]:
        """rgb (T, 3, H, W), flow_fw (T-1, 2, H, W) exact; rgb_final (T, 3, H, W) and occ_fw (T-1, 1, H, W) when
        they were exported."""
        def part(sub: str) -> list[Path]:
            return [root / f for f in sorted(files) if f.startswith(f"{_TRAIN}/{sub}/")]

        out = {"rgb": torch.from_numpy(np.stack([read_rgb_png(p) for p in part("clean")])),
               "flow_fw": torch.from_numpy(np.stack([read_flo(p) for p in part("flow")]))}
        if part("final"):
            out["rgb_final"] = torch.from_numpy(np.stack([read_rgb_png(p) for p in part("final")]))
        if part("occlusions"):
            out["occ_fw"] = torch.from_numpy(np.stack([read_mask_png(p) for p in part("occlusions")])[:, None])
        return out

    def load_hint(self, root: Path) -> str:
        return f"torchvision.datasets.Sintel(root={str(root)!r})  # or flowsynth.datasets.Exported"
