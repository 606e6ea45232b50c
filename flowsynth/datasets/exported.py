"""``Exported``: map-style dataset over a folder written by ``flowsynth export`` (native layout)."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch.utils.data import Dataset

from flowsynth.errors import ExportError

__all__ = ["Exported"]


class Exported(Dataset):
    """Samples of a native export, with the same keys as the stream (``BouncingThings.sample``).

    Float channels come back bit-exact (EXR float32, JSON of float32 values); ``rgb`` within 8-bit
    quantisation (|error| <= 0.5/255). Expected tree::

        root/
          manifest.json
          00000/  meta.json  rgb_0000.png  flow_fw_0000.exr  ...
          00001/  ...

    Args:
        root: export folder.
        verify: check every file's sha256 against the manifest when reading it.
    """

    def __init__(self, root: str | Path, verify: bool = False) -> None:
        self.root = Path(root)
        manifest = self.root / "manifest.json"
        if not manifest.is_file():
            raise ExportError(f"could not find {manifest}; is {self.root} a folder written by `flowsynth export`?")
        self.manifest = json.loads(manifest.read_text())
        if self.manifest.get("layout") != "native":
            raise ExportError(f"{self.root} uses layout {self.manifest.get('layout')!r}; Exported reads the native "
                              "layout (read flyingchairs folders with torchvision.datasets.FlyingChairs)")
        self.names = sorted(n for n in self.manifest.get("samples", {}) if (self.root / n).is_dir())
        self.verify = verify

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        from flowsynth.sampleio import file_digest, read_sample

        folder = self.root / self.names[i]
        if self.verify:
            for name, digest in self.manifest["samples"][self.names[i]].items():
                if file_digest(folder / name) != digest:
                    raise ExportError(f"checksum mismatch for {folder / name}; the export is corrupted")
        return read_sample(folder)
