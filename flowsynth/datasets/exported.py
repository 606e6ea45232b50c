"""``Exported``: map-style dataset over a folder written by ``flowsynth export``, in any layout."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch.utils.data import Dataset

from flowsynth.errors import ExportError

__all__ = ["Exported"]


class Exported(Dataset):
    """Samples of an export, with the stream's keys (``BouncingThings.sample``) for what the layout stores.

    The layout named in ``manifest.json`` reads each sample (``flowsynth.io.layouts``). ``native``
    gives back every exported key: float channels bit-exact (EXR float32, JSON of float32 values),
    ``rgb`` within 8-bit quantisation (|error| <= 0.5/255). Other layouts give back what their format
    holds (their module docstrings say what and how exactly). Expected tree (native)::

        root/
          manifest.json
          00000/  meta.json  rgb_0000.png  flow_fw_0000.exr  ...
          00001/  ...

    Args:
        root: export folder (the one holding ``manifest.json``).
        verify: check every file's sha256 against the manifest when reading it.
    """

    def __init__(self, root: str | Path, verify: bool = False) -> None:
        from flowsynth.io import layouts

        self.root = Path(root)
        manifest = self.root / "manifest.json"
        if not manifest.is_file():
            raise ExportError(f"could not find {manifest}; is {self.root} a folder written by `flowsynth export`?")
        self.manifest = json.loads(manifest.read_text())
        name = self.manifest.get("layout")
        if name not in layouts.names():
            raise ExportError(f"{self.root} uses layout {name!r}, which this flowsynth does not know "
                              f"({', '.join(layouts.names())})")
        self.layout = layouts.get(name)
        samples = self.manifest.get("samples", {})
        self.names = sorted(n for n in samples if all((self.root / f).is_file() for f in samples[n]))
        self.verify = verify

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        from flowsynth.sampleio import file_digest

        files = self.manifest["samples"][self.names[i]]
        if self.verify:
            for rel, rec in files.items():
                if file_digest(self.root / rel) != rec["sha256"]:
                    raise ExportError(f"checksum mismatch for {self.root / rel}; the export is corrupted")
        return self.layout.read(self.root, list(files))
