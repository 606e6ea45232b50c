"""``Exported``: map-style dataset over a folder written by ``flowsynth export``, in any layout."""

from __future__ import annotations

from pathlib import Path

import torch
from torch.utils.data import Dataset

from flowsynth.errors import ConfigError, ExportError

__all__ = ["Exported"]


class Exported(Dataset):
    """Samples of an export, with the stream's keys (``BouncingThings.sample``) for what the layout stores.

    The layout named in ``manifest.json`` reads each sample (``flowsynth.io.layouts``). ``native``
    and ``webdataset`` give back every exported key: float channels bit-exact (EXR float32; JSON of
    float32 values or ``.npy``), ``rgb`` within 8-bit quantisation (|error| <= 0.5/255). Other layouts
    give back what their format holds (their module docstrings say what and how exactly). Every
    layout's manifest also records each sample's camera (K, size, lens model and coefficients):
    :meth:`camera`. Expected trees::

        root/                                      native
          manifest.json
          00000/  meta.json  rgb_0000.png  flow_fw_0000.exr  ...
          00001/  ...

        root/                                      webdataset (--shard-size N samples a shard)
          manifest.json
          shard-000000.tar   00000000.rgb_0000.png  00000000.K.npy  ...  00000001.rgb_0000.png  ...
          shard-000001.tar   samples N .. 2N-1

    A ``webdataset`` sample is read out of its shard by seeking to its members (each shard's tar
    headers are read once, when its first sample is asked for); to stream shards in order, shuffled
    and split by worker and rank, use :class:`flowsynth.datasets.Shards` instead.

    Args:
        root: export folder (the one holding ``manifest.json``).
        verify: how the files are checked against the manifest (:mod:`flowsynth.io.integrity`):
            ``"quick"`` (default) when the folder is opened: every file of every recorded sample
            exists with its recorded size; ``"full"``: that, and the sha256 of each file whenever a
            sample is read; ``"none"``: no check. ``True`` / ``False`` mean ``"full"`` / ``"none"``.

    Raises:
        ExportError: no manifest, an unknown layout, or (quick/full) a sample whose files fail the
            check; the message names them and says how to repair (re-run the export command).
        ConfigError: ``verify`` is not one of the above.
    """

    def __init__(self, root: str | Path, verify: str | bool = "quick") -> None:
        from flowsynth.io import VERIFY_MODES, read_manifest, sample_problem
        from flowsynth.io import layouts

        self.root = Path(root)
        self.manifest = read_manifest(self.root)
        name = self.manifest.get("layout")
        if name not in layouts.names():
            raise ExportError(f"{self.root} uses layout {name!r}, which this flowsynth does not know "
                              f"({', '.join(layouts.names())})")
        self.layout = layouts.get(name)
        if isinstance(verify, bool):
            verify = "full" if verify else "none"
        if verify not in VERIFY_MODES:
            raise ConfigError(f"verify must be one of {VERIFY_MODES} (or a bool), got {verify!r}")
        self.verify = verify
        samples = self.manifest.get("samples", {})
        self.names = sorted(samples)
        quick = "none" if verify == "none" else "quick"  # sha256 waits until a sample is read
        bad = [f"{n}: {p}" for n in self.names if (p := sample_problem(self.root, samples[n], quick))]
        if bad:
            raise ExportError(f"{len(bad)} sample(s) of {self.root} do not match its manifest ({'; '.join(bad[:5])}"
                              f"{'; ...' if len(bad) > 5 else ''}); re-run the `flowsynth export` command that "
                              "wrote it to repair them, or pass verify='none' to read what is there")

    def __len__(self) -> int:
        return len(self.names)

    def camera(self, i: int) -> dict | None:
        """Sample ``i``'s camera as the manifest records it for every layout: ``K`` (3x3 list, px), ``width``,
        ``height``, ``model`` ("pinhole", "brown_conrady", "kannala_brandt") and ``dist`` (its coefficients in
        OpenCV's order; [] for a pinhole). The same as the sample's provenance ``camera``, with model and dist
        always present; None for a sample without a camera (an export of ``Layers``).

        Raises ExportError for an export written before cameras were recorded (re-run its export command:
        the resume writes those samples again)."""
        cameras = self.manifest.get("cameras", {})
        if self.names[i] not in cameras:
            raise ExportError(f"{self.root}/manifest.json records no camera for sample {self.names[i]}; re-run "
                              "the `flowsynth export` command that wrote it to record them")
        return cameras[self.names[i]]

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        from flowsynth.io import sample_problem

        files = self.manifest["samples"][self.names[i]]
        if self.verify == "full" and (problem := sample_problem(self.root, files, "full")):
            raise ExportError(f"sample {self.names[i]} of {self.root}: {problem} (sha256 check); the export is "
                              "damaged: re-run `flowsynth export ... --verify` with the same arguments to repair it")
        return self.layout.read_sample(self.root, list(files), int(self.names[i]))
