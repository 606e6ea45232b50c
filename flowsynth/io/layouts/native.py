"""``native`` layout: one folder per sample, every output lossless (file formats in flowsynth/io/sampleio.py).

::

    DIR/
      manifest.json        config, seed, outputs, layout, versions, size and sha256 of every file
      boxes_coco.json      COCO detection file of every sample's visible boxes (when the boxes are exported)
      00000/  rgb_0000.png  depth_0000.exr  flow_fw_0000.exr  instance_0000.png ...  meta.json
      00001/  ...

Read it back with ``flowsynth.datasets.Exported(DIR)``: the stream's keys, float outputs bit-exact.
"""

from __future__ import annotations

import re
import shutil
from collections.abc import Sequence
from pathlib import Path

import torch

from flowsynth.io.layouts import register
from flowsynth.io.layouts.base import Layout

__all__ = ["Native", "frame_key"]

_PER_FRAME = re.compile(r"(.+)_\d{4}\.\w+$")


def frame_key(name: str) -> str | None:
    """The output key of a per-frame or per-pair file ``KEY_TTTT.ext`` (flowsynth/io/sampleio.py's names:
    ``rgb_0000.png`` -> ``rgb``, ``flow_fw_k2_0001.exr`` -> ``flow_fw_k2``); None for any other file (``meta.json``,
    ``tracks.npz``)."""
    m = _PER_FRAME.match(name)
    return m.group(1) if m else None


@register
class Native(Layout):
    """Every requested output of a sample in folder ``NNNNN/`` (5-digit, 0-based index)."""

    name = "native"
    writes_exr = True
    summary = "one folder per sample, every output lossless; read with flowsynth.datasets.Exported"
    # images, flow both ways with occlusion, ids, and what boxes_coco.json needs (io.sampleio.COCO_KEYS)
    default_outputs = ("rgb", "depth", "flow_fw", "flow_bw", "occ_fw", "occ_bw", "instance", "box2d_visible",
                       "visible_pixels", "object_valid", "object_category")

    def write(self, sample: dict[str, torch.Tensor], index: int, folder: Path) -> dict[str, str]:
        from flowsynth.io.sampleio import write_sample

        sub = Path(folder) / f"{index:05d}"
        sub.mkdir()
        out = {}
        for n in write_sample(sample, sub, exr_compression=self.exr_compression):
            out[f"{sub.name}/{n}"] = frame_key(n) or n.rsplit(".", 1)[0]
        return out

    def read(self, root: Path, files: Sequence[str]) -> dict[str, torch.Tensor]:
        from flowsynth.io.sampleio import read_sample

        return read_sample(Path(root) / Path(files[0]).parent)

    def finish(self, root: Path, num: int, cfg) -> list[str]:
        """``boxes_coco.json``: the COCO file of samples 0 .. num - 1 (``flowsynth.io.sampleio.write_coco``), written
        again at the end of every run, a resume included."""
        from flowsynth.io.sampleio import write_coco

        return write_coco(Path(root), [f"{i:05d}" for i in range(num)])

    def clear(self, root: Path) -> None:
        from flowsynth.io.sampleio import COCO_FILE

        (Path(root) / COCO_FILE).unlink(missing_ok=True)
        for p in Path(root).iterdir():
            if p.is_dir() and p.name.isdigit():
                shutil.rmtree(p)
