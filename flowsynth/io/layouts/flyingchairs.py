"""``flyingchairs`` layout: what ``torchvision.datasets.FlyingChairs(root=DIR)`` reads.

::

    DIR/
      manifest.json
      FlyingChairs/
        FlyingChairs_train_val.txt   one line per pair: 1 = train, 2 = val (every 10th pair)
        data/00001_img1.ppm  00001_img2.ppm  00001_flow.flo   (1-based, like the original)

Every consecutive frame pair (t, t+1) of a sample is one FlyingChairs pair: sample i with T frames
gives pairs i * (T - 1) + 1 ... (i + 1) * (T - 1). Images are 8-bit PPM, flow is ``flow_fw`` as
``.flo`` (float32, bit-exact; 0 where not ``valid_fw``: the format has no mask).

``np.loadtxt`` (which FlyingChairs readers use on the split file) turns a one-line file into a 0-d
array that cannot be indexed, so the split file holds at least two lines; a line beyond the last
pair names no pair, and readers only index it up to the number of ``.flo`` files.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from flowsynth.io.flo import read_flo, write_flo
from flowsynth.io.atomic import atomic_write_bytes
from flowsynth.io.layouts import register
from flowsynth.io.layouts.base import Layout
from flowsynth.io.png import read_ppm, write_ppm

__all__ = ["FlyingChairs"]

_DIGITS = 5  # the original's file numbering; readers sort names as strings
_VAL_EVERY = 10  # every 10th pair goes to the val split


@register
class FlyingChairs(Layout):
    """Frame pairs as ``FlyingChairs/data/NNNNN_img1.ppm``, ``_img2.ppm``, ``_flow.flo``."""

    name = "flyingchairs"
    summary = "FlyingChairs/data/NNNNN_img1.ppm, _img2.ppm, _flow.flo, one per frame pair; " \
              "torchvision.datasets.FlyingChairs(root=DIR)"
    default_outputs = ("rgb", "flow_fw")
    required_outputs = ("rgb", "flow_fw")
    stored_outputs = default_outputs
    min_frames = 2
    pair_digits = _DIGITS
    owned = ("FlyingChairs",)

    def write(self, sample: dict[str, torch.Tensor], index: int, folder: Path) -> dict[str, str]:
        rgb, flow = sample["rgb"].numpy(), sample["flow_fw"].numpy()
        data = Path(folder) / "FlyingChairs" / "data"
        data.mkdir(parents=True)
        out = {}
        for t in range(flow.shape[0]):
            stem = f"{index * flow.shape[0] + t + 1:0{_DIGITS}d}"
            write_ppm(data / f"{stem}_img1.ppm", rgb[t])
            write_ppm(data / f"{stem}_img2.ppm", rgb[t + 1])
            write_flo(data / f"{stem}_flow.flo", flow[t])
            out.update({f"FlyingChairs/data/{stem}_img1.ppm": "rgb", f"FlyingChairs/data/{stem}_img2.ppm": "rgb",
                        f"FlyingChairs/data/{stem}_flow.flo": "flow_fw"})
        return out

    def read(self, root: Path, files: Sequence[str]) -> dict[str, torch.Tensor]:
        img1 = sorted(f for f in files if f.endswith("_img1.ppm"))
        img2 = sorted(f for f in files if f.endswith("_img2.ppm"))
        flows = sorted(f for f in files if f.endswith("_flow.flo"))
        rgb = np.stack([read_ppm(root / f) for f in [*img1, img2[-1]]])
        flow = np.stack([read_flo(root / f) for f in flows])
        return {"rgb": torch.from_numpy(rgb), "flow_fw": torch.from_numpy(flow)}

    def finish(self, root: Path, num: int, cfg) -> list[str]:
        pairs = num * (cfg.num_frames - 1)
        lines = ["2" if (k + 1) % _VAL_EVERY == 0 else "1" for k in range(pairs)]
        lines += ["1"] * (2 - len(lines))
        name = "FlyingChairs/FlyingChairs_train_val.txt"
        atomic_write_bytes(Path(root) / name, ("\n".join(lines) + "\n").encode())
        return [name]

    def load_hint(self, root: Path) -> str:
        return f"torchvision.datasets.FlyingChairs(root={str(root)!r})  # or flowsynth.datasets.Exported"
