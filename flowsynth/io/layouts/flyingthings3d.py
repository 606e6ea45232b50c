"""``flyingthings3d`` layout: the folder structure of FlyingThings3D's "subset" release (stereo + flow).

::

    DIR/
      manifest.json
      FlyingThings3D_subset/train/
        image_clean/left/NNNNNNN.png, right/NNNNNNN.png            rgb, rgb_right (8-bit)
        disparity/left/NNNNNNN.pfm, right/NNNNNNN.pfm              disparity, disparity_right [px], float32
        disparity_change/left/into_future/NNNNNNN.pfm              disparity_change [px] (frames 0..T-2)
        disparity_occlusions/left/NNNNNNN.png, right/              disparity_occ[_right], 0 / 255
        flow/left/into_future/NNNNNNN.flo, into_past/NNNNNNN.flo   flow_fw (frames 0..T-2), flow_bw (1..T-1)
        flow_occlusions/left/into_future/NNNNNNN.png, into_past/   occ_fw, occ_bw, 0 / 255

Frame t of sample i is file number NNNNNNN = i * T + t (7 digits, as in the release); a pair file is named
by its source frame (into_future: t -> t+1, into_past: t+1 -> t). Like the release, ``.flo`` and ``.pfm``
have no validity mask: flow and disparity change are 0 where not valid. Disparity is positive (left view
u_L - u_R, docs/conventions.md "Stereo"). Needs ``stereo_baseline > 0``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from flowsynth.errors import ConfigError
from flowsynth.io.flo import read_flo, write_flo
from flowsynth.io.layouts import register
from flowsynth.io.layouts.base import Layout
from flowsynth.io.pfm import read_pfm, write_pfm
from flowsynth.io.png import read_mask_png, read_rgb_png, write_mask_png, write_rgb_png

__all__ = ["FlyingThings3D"]

_ROOT = "FlyingThings3D_subset/train"
# output -> (folder under _ROOT, extension, first frame of the file numbering: 0 per frame / source of a pair)
_FILES = {
    "rgb": ("image_clean/left", "png", 0),
    "rgb_right": ("image_clean/right", "png", 0),
    "disparity": ("disparity/left", "pfm", 0),
    "disparity_right": ("disparity/right", "pfm", 0),
    "disparity_change": ("disparity_change/left/into_future", "pfm", 0),
    "disparity_occ": ("disparity_occlusions/left", "png", 0),
    "disparity_occ_right": ("disparity_occlusions/right", "png", 0),
    "flow_fw": ("flow/left/into_future", "flo", 0),
    "flow_bw": ("flow/left/into_past", "flo", 1),
    "occ_fw": ("flow_occlusions/left/into_future", "png", 0),
    "occ_bw": ("flow_occlusions/left/into_past", "png", 1),
}


@register
class FlyingThings3D(Layout):
    """FlyingThings3D "subset" tree: left/right images, disparity (PFM), disparity change, flow, occlusions."""

    name = "flyingthings3d"
    summary = "FlyingThings3D_subset/train/{image_clean,disparity,disparity_change,flow,...}/left|right/ " \
              "(PFM disparity, .flo flow); needs --stereo-baseline > 0"
    default_outputs = tuple(_FILES)
    required_outputs = ("rgb", "rgb_right", "disparity")
    stored_outputs = default_outputs
    min_frames = 2
    owned = ("FlyingThings3D_subset",)
    pair_digits = 7

    def check(self, cfg, outputs: Sequence[str], num: int) -> None:
        super().check(cfg, outputs, num)
        if cfg.stereo_baseline <= 0:
            raise ConfigError("layout flyingthings3d needs a right camera: set --stereo-baseline > 0 [m] (e.g. 0.1)")
        if num * cfg.num_frames >= 10**7:
            raise ConfigError(f"layout flyingthings3d numbers frames with 7 digits; --num {num} x num_frames "
                              f"{cfg.num_frames} is too many")

    def write(self, sample: dict[str, torch.Tensor], index: int, folder: Path) -> dict[str, str]:
        T = int(sample["rgb"].shape[0])
        out = {}
        for key, (sub, ext, first) in _FILES.items():
            if key not in sample:
                continue
            (Path(folder) / _ROOT / sub).mkdir(parents=True, exist_ok=True)
            for t, frame in enumerate(sample[key].numpy()):
                rel = f"{_ROOT}/{sub}/{index * T + first + t:07d}.{ext}"
                if ext == "png" and key.startswith("rgb"):
                    write_rgb_png(Path(folder) / rel, frame)
                elif ext == "png":
                    write_mask_png(Path(folder) / rel, frame[0])
                elif ext == "pfm":
                    write_pfm(Path(folder) / rel, frame[0])
                else:
                    write_flo(Path(folder) / rel, frame)
                out[rel] = key
        return out

    def read(self, root: Path, files: Sequence[str]) -> dict[str, torch.Tensor]:
        """Every stored key with the stream's shape and dtype (rgb 8-bit; the rest exact)."""
        out = {}
        for key, (sub, ext, _) in _FILES.items():
            paths = [root / f for f in sorted(files) if f.startswith(f"{_ROOT}/{sub}/")]
            if not paths:
                continue
            if ext == "png" and key.startswith("rgb"):
                a = np.stack([read_rgb_png(p) for p in paths])
            elif ext == "png":
                a = np.stack([read_mask_png(p) for p in paths])[:, None]
            elif ext == "pfm":
                a = np.stack([read_pfm(p) for p in paths])[:, None]
            else:
                a = np.stack([read_flo(p) for p in paths])
            out[key] = torch.from_numpy(np.ascontiguousarray(a))
        return out
