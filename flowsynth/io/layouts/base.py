"""``Layout``: what one export layout writes for a sample, how it reads it back, and what it needs.

A layout only writes files; the exporter (:mod:`flowsynth.export`) does the bookkeeping that is the
same for every layout: it gives :meth:`Layout.write` an empty staging folder, hashes what was written
(size and sha256 per file, into ``manifest.json``), then moves the files into the export root with
:func:`os.replace`, so a file under its final name is always whole. Paths are relative to the export
root and use ``/``.

To add a layout, subclass :class:`Layout` in a new module of this package and decorate it with
:func:`flowsynth.io.layouts.register`; the CLI's ``--layout``, :func:`flowsynth.export.export_dataset` and
:class:`flowsynth.datasets.Exported` find it by its ``name``.
"""

from __future__ import annotations

import shutil
from abc import ABC, abstractmethod
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import ClassVar

import torch

from flowsynth.errors import ConfigError
from flowsynth.io.exr import COMPRESSIONS

__all__ = ["EXR_COMPRESSIONS", "Layout"]

EXR_COMPRESSIONS = tuple(COMPRESSIONS)
"""Lossless OpenEXR compressions an export may use for its float32 files (bit-exact round trip)."""


class Layout(ABC):
    """Base class of export layouts. Subclasses set the class attributes and implement ``write`` and ``read``.

    Args:
        exr_compression: compression of the EXR files the layout writes, one of
            :data:`EXR_COMPRESSIONS` (only layouts that write EXR use it).
    """

    name: ClassVar[str]
    """Registry name, the CLI's ``--layout NAME``."""
    summary: ClassVar[str]
    """One line for ``--help``: what the layout is for and who reads it."""
    default_outputs: ClassVar[tuple[str, ...]]
    """Outputs exported when the user names none."""
    required_outputs: ClassVar[tuple[str, ...]] = ()
    """Outputs without which the layout cannot write a sample."""
    stored_outputs: ClassVar[tuple[str, ...] | None] = None
    """Every output the layout can store; None: any. Others are refused, never computed and dropped."""
    min_frames: ClassVar[int] = 1
    """Smallest ``num_frames`` the layout can store."""
    owned: ClassVar[tuple[str, ...]] = ()
    """Top-level entries of the export root that belong to the layout (removed by ``--overwrite``)."""
    writes_exr: ClassVar[bool] = False
    """Whether the layout writes EXR files; one that does not refuses an ``exr_compression`` other than "zip"
    (the default), which it could not honour."""
    pair_digits: ClassVar[int | None] = None
    """Digits of the frame-pair numbers in file names, for layouts that number pairs across the export
    (num * (num_frames - 1) must stay below 10**pair_digits); None: no such limit."""

    def __init__(self, *, exr_compression: str = "zip") -> None:
        if exr_compression not in EXR_COMPRESSIONS:
            raise ConfigError(f"exr_compression must be one of {EXR_COMPRESSIONS}, got {exr_compression!r}")
        if exr_compression != "zip" and not self.writes_exr:
            raise ConfigError(f"layout {self.name} writes no EXR files, so --exr-compression {exr_compression} would "
                              "change nothing; leave it out (or export with --layout native or webdataset)")
        self.exr_compression = exr_compression

    def options(self) -> dict:
        """Settings that change the bytes written; part of the export's identity in the manifest."""
        return {"exr_compression": self.exr_compression}

    def check(self, cfg, outputs: Sequence[str], num: int) -> None:
        """Raise :class:`ConfigError` when ``cfg`` / ``outputs`` / ``num`` cannot be written in this layout.

        Args:
            cfg: the export's ``BouncingThingsConfig``.
            outputs: the resolved output keys (``flowsynth.plan.make_plan(...).outputs``).
            num: number of samples in the export.
        """
        missing = [k for k in self.required_outputs if k not in outputs]
        if missing:
            raise ConfigError(f"layout {self.name} needs the outputs {list(self.required_outputs)}; add "
                              f"{missing} to --outputs")
        dropped = [k for k in outputs if self.stored_outputs is not None and k not in self.stored_outputs]
        if dropped:
            raise ConfigError(f"layout {self.name} stores only the outputs {list(self.stored_outputs)}; remove "
                              f"{dropped} from --outputs (or export them with --layout native)")
        if cfg.num_frames < self.min_frames:
            raise ConfigError(f"layout {self.name} needs num_frames >= {self.min_frames}, got {cfg.num_frames}; "
                              f"raise --num-frames")
        pairs = num * (cfg.num_frames - 1)
        if self.pair_digits is not None and pairs >= 10**self.pair_digits:
            raise ConfigError(f"layout {self.name} numbers pairs with {self.pair_digits} digits; --num {num} with "
                              f"num_frames {cfg.num_frames} makes {pairs} pairs; lower --num or --num-frames")

    @abstractmethod
    def write(self, sample: dict[str, torch.Tensor], index: int, folder: Path) -> dict[str, str]:
        """Write sample ``index`` under the staging ``folder`` (empty; laid out like the export root).

        Args:
            sample: one ``BouncingThings.sample`` dict (CPU tensors, shapes in docs/conventions.md).
            index: the sample's index in the export, 0-based.
            folder: staging root; create sub-folders as needed.

        Returns:
            relative path -> the output it stores (``"rgb"``, ``"flow_fw"``, ...; ``"meta"`` for
            metadata), for every file written; ``--dry-run`` sums sizes by that output.
        """

    @abstractmethod
    def read(self, root: Path, files: Sequence[str]) -> dict[str, torch.Tensor]:
        """Read one sample back from its files (relative paths under ``root``, as in the manifest).

        Returns:
            a sample dict with the stream's keys, shapes and dtypes, for the outputs the layout stores.
        """

    def units(self, num: int) -> list[range]:
        """The export's units of work: sample indices written, recorded and resumed together, in order.

        Default: one sample each. A layout that packs several samples into one file (``webdataset``'s
        shards) returns one range per file; the exporter then writes, journals and resumes whole units.
        """
        return [range(i, i + 1) for i in range(num)]

    def write_unit(self, samples: Iterable[tuple[int, dict[str, torch.Tensor]]], folder: Path) -> dict[str, str]:
        """Write one unit's samples, ``(index, sample)`` pairs made one at a time, under the staging ``folder``.

        Returns relative path -> the output it stores, like :meth:`write`. Default: :meth:`write` each.
        """
        out: dict[str, str] = {}
        for index, sample in samples:
            out.update(self.write(sample, index, folder))
        return out

    def read_sample(self, root: Path, files: Sequence[str], index: int) -> dict[str, torch.Tensor]:
        """Sample ``index`` from its recorded ``files``; what :class:`flowsynth.datasets.Exported` calls.

        Default: :meth:`read` (the files hold this one sample); layouts whose files hold several samples
        pick sample ``index`` out of them.
        """
        return self.read(root, files)

    def finish(self, root: Path, num: int, cfg) -> list[str]:
        """Write index files that cover the whole export (after the last sample); returns their paths."""
        return []

    def load_hint(self, root: Path) -> str:
        """A Python line that loads the export at ``root``, for the CLI's closing message."""
        return f"flowsynth.datasets.Exported({str(root)!r})"

    def clear(self, root: Path) -> None:
        """Remove everything this layout wrote under ``root`` (``--overwrite``)."""
        for name in self.owned:
            p = root / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
