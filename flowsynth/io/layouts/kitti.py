"""``kitti`` layout: the KITTI 2015 flow benchmark's tree, what ``torchvision.datasets.KittiFlow`` reads.

::

    DIR/
      manifest.json
      KittiFlow/training/
        image_2/000000_10.png  000000_11.png    8-bit RGB, frames t and t+1 of a pair
        flow_occ/000000_10.png                  16-bit flow PNG (flowsynth/io/kitti.py), valid = valid_fw
        flow_noc/000000_10.png                  same, valid = valid_fw and not occ_fw (when occ_fw is exported)

Every consecutive frame pair (t, t+1) of a sample is one KITTI pair: sample i with T frames gives
pairs i * (T - 1) ... (i + 1) * (T - 1) - 1 (6 digits, 0-based, like KITTI). As in KITTI, ``flow_occ``
holds every pixel whose flow is known, occluded ones included, and ``flow_noc`` only those visible in
both frames. Flow is quantised to 1/64 px; a component outside KITTI's range [-512, 511.98] px is
marked invalid rather than clipped.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from flowsynth.io.kitti import KITTI_FLOW_MAX, KITTI_FLOW_MIN, read_kitti_flow, write_kitti_flow
from flowsynth.io.layouts import register
from flowsynth.io.layouts.base import Layout
from flowsynth.io.png import read_rgb_png, write_rgb_png

__all__ = ["Kitti"]

_DIGITS = 6
_TRAIN = "KittiFlow/training"


@register
class Kitti(Layout):
    """Frame pairs as ``KittiFlow/training/image_2/NNNNNN_10.png``, ``_11.png`` and ``flow_occ/NNNNNN_10.png``."""

    name = "kitti"
    summary = "KittiFlow/training/image_2/NNNNNN_10.png, _11.png, flow_occ/ and flow_noc/ 16-bit flow PNGs, " \
              "one per frame pair; torchvision.datasets.KittiFlow(root=DIR)"
    default_outputs = ("rgb", "flow_fw", "valid_fw", "occ_fw")
    required_outputs = ("rgb", "flow_fw", "valid_fw")
    stored_outputs = default_outputs
    min_frames = 2
    pair_digits = _DIGITS
    owned = ("KittiFlow",)

    def write(self, sample: dict[str, torch.Tensor], index: int, folder: Path) -> dict[str, str]:
        rgb, flow = sample["rgb"].numpy(), sample["flow_fw"].numpy()
        in_range = ((flow >= KITTI_FLOW_MIN) & (flow <= KITTI_FLOW_MAX)).all(axis=1)
        valid = sample["valid_fw"].numpy()[:, 0] & in_range
        noc = valid & ~sample["occ_fw"].numpy()[:, 0] if "occ_fw" in sample else None
        root = Path(folder) / _TRAIN
        for sub in ("image_2", "flow_occ") + (("flow_noc",) if noc is not None else ()):
            (root / sub).mkdir(parents=True)
        out = {}
        for t in range(flow.shape[0]):
            stem = f"{index * flow.shape[0] + t:0{_DIGITS}d}"
            write_rgb_png(root / f"image_2/{stem}_10.png", rgb[t])
            write_rgb_png(root / f"image_2/{stem}_11.png", rgb[t + 1])
            write_kitti_flow(root / f"flow_occ/{stem}_10.png", flow[t], valid[t])
            out.update({f"{_TRAIN}/image_2/{stem}_10.png": "rgb", f"{_TRAIN}/image_2/{stem}_11.png": "rgb",
                        f"{_TRAIN}/flow_occ/{stem}_10.png": "flow_fw"})
            if noc is not None:
                write_kitti_flow(root / f"flow_noc/{stem}_10.png", flow[t], noc[t])
                out[f"{_TRAIN}/flow_noc/{stem}_10.png"] = "occ_fw"
        return out

    def read(self, root: Path, files: Sequence[str]) -> dict[str, torch.Tensor]:
        """rgb (T, 3, H, W); flow_fw (T-1, 2, H, W) in 1/64 px steps, 0 where invalid; valid_fw (T-1, 1, H, W)."""
        first = sorted(f for f in files if f.endswith("_10.png") and "/image_2/" in f)
        second = sorted(f for f in files if f.endswith("_11.png"))
        flows = [read_kitti_flow(root / f) for f in sorted(f for f in files if "/flow_occ/" in f)]
        rgb = np.stack([read_rgb_png(root / f) for f in [*first, second[-1]]])
        return {"rgb": torch.from_numpy(rgb), "flow_fw": torch.from_numpy(np.stack([f for f, _ in flows])),
                "valid_fw": torch.from_numpy(np.stack([v for _, v in flows])[:, None])}

    def load_hint(self, root: Path) -> str:
        return f"torchvision.datasets.KittiFlow(root={str(root)!r})  # or flowsynth.datasets.Exported"
