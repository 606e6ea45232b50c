"""``webdataset`` layout: POSIX tar shards of many samples each, the format of large-scale PyTorch training.

::

    DIR/
      manifest.json          config, seed, outputs, layout, shard_size, size and sha256 of every shard
      shard-000000.tar       samples 0 .. N-1          (N = --shard-size)
      shard-000001.tar       samples N .. 2N-1
      ...

In a shard, sample i's files sit side by side under the key ``%08d`` (WebDataset's convention: the key is
the member name up to its first dot), members sorted by name::

    00000007.rgb_0000.png  00000007.depth_0000.exr  00000007.flow_fw_0000.exr  ...   images, as ``native``
    00000007.K.npy  00000007.cam_T_world.npy  00000007.object_valid.npy  ...       tensors, numpy .npy
    00000007.index.npy  00000007.seed.npy  00000007.provenance.json                 (a scene record, JSON)
    00000007.camera.json                                                           a lens camera only

Images are the ``native`` layout's files byte for byte (flowsynth/io/sampleio.py: 8-bit sRGB PNG, float32
EXR, 16-bit PNG ids and masks); cameras, object tables, point tracks, index and seed are ``.npy`` arrays
with the stream's dtype and shape; ``provenance.json`` is the stream's provenance string. A lens camera's
model and coefficients sit beside ``K.npy`` in ``camera.json``, ``{"model": ..., "dist": [...]}`` (OpenCV's
order; what ``native`` writes into meta.json as ``camera_model`` and ``camera_dist``); a pinhole sample has no
such member, as a pinhole ``meta.json`` has no such keys. Readers of the sample dict find them in the
provenance's ``camera`` too. The derived
files ``boxes_coco.json`` and ``tapvid.pkl`` of ``native`` are not written (their tensors are).

The tar is deterministic: USTAR headers with mtime 0, uid/gid 0, empty user/group names, mode 0644, and
members in name order; so a shard's bytes depend only on its samples, whatever the engine or workers.

Crash safety and resume (flowsynth/export/exporter.py, flowsynth/io/integrity.py): shard j holds samples
[j N, min((j+1) N, num)) and is one unit of work (``Layout.units``). A worker writes the whole shard under
a staging folder ``DIR/.tmp-*``; the exporter journals the record of each of its samples (all naming the
shard, with its size and sha256) in one write, then renames the shard into place. A shard is complete
when its file passes the check (quick: present with the recorded size; ``--verify``: its sha256) and
the samples recorded with it are exactly the shard's; otherwise, missing, damaged, or written for another
``--num``, it is written again whole. A shard never appears half-written under its final name.

Read it back with ``flowsynth.datasets.Exported(DIR)`` (map-style), ``flowsynth.datasets.Shards(DIR)``
(streaming, shuffled, split by worker and rank), ``webdataset.WebDataset(urls)`` or
``ray.data.read_webdataset(paths)``.
"""

from __future__ import annotations

import io
import itertools
import json
import re
import tarfile
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np
import torch

from flowsynth.errors import ConfigError, ExportError
from flowsynth.options import check_int
from flowsynth.io.atomic import atomic_path
from flowsynth.io.layouts import register
from flowsynth.io.layouts.base import Layout
from flowsynth.io.layouts.native import Native, frame_key

__all__ = ["DEFAULT_SHARD_SIZE", "WebDataset", "decode", "iter_shard", "shard_name"]

DEFAULT_SHARD_SIZE = 256
"""Samples per shard unless ``--shard-size`` says otherwise. A shard is also the unit a worker writes and a
resume rewrites, and the unit a reader splits among workers x ranks: choose num / shard_size >= the
training job's workers x ranks (a choice, not a measurement; WebDataset's guide suggests shards of
100 MB - 1 GB, which is ``flowsynth export --dry-run``'s bytes per sample times the shard size)."""
_SHARD_DIGITS = 6
_KEY_DIGITS = 8
_SHARD = re.compile(r"shard-\d{6}\.tar$")


def shard_name(j: int) -> str:
    """File name of shard ``j``: ``shard-000000.tar``."""
    return f"shard-{j:0{_SHARD_DIGITS}d}.tar"


def _tensor_keys() -> tuple[str, ...]:
    from flowsynth.plan import TRACK_KEYS
    from flowsynth.io.sampleio import META_KEYS

    return META_KEYS + TRACK_KEYS


def _member_info(name: str, size: int) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.size, info.mtime, info.mode, info.uid, info.gid, info.uname, info.gname = size, 0, 0o644, 0, 0, "", ""
    return info


@register
class WebDataset(Layout):
    """Samples in tar shards ``shard-NNNNNN.tar`` of ``shard_size`` samples, keyed ``%08d`` (module docstring).

    Args:
        shard_size: samples per shard, >= 1.
        exr_compression: as for every layout.
    """

    name = "webdataset"
    writes_exr = True
    summary = ("tar shards shard-NNNNNN.tar of --shard-size samples, files keyed by the 8-digit index (images "
               "as native, tensors .npy); flowsynth.datasets.Shards, webdataset.WebDataset, ray.data.read_webdataset")
    default_outputs = Native.default_outputs

    def __init__(self, *, shard_size: int = DEFAULT_SHARD_SIZE, exr_compression: str = "zip") -> None:
        super().__init__(exr_compression=exr_compression)
        self.shard_size = check_int("shard_size (--shard-size)", shard_size, 1)
        self._index: dict[tuple[str, int, int], dict[str, list[tuple[str, int, int]]]] = {}

    def options(self) -> dict:
        return {**super().options(), "shard_size": self.shard_size}

    def check(self, cfg, outputs: Sequence[str], num: int) -> None:
        super().check(cfg, outputs, num)
        if num > 10**_KEY_DIGITS or -(-num // self.shard_size) > 10**_SHARD_DIGITS:
            raise ConfigError(f"layout webdataset numbers samples with {_KEY_DIGITS} digits and shards with "
                              f"{_SHARD_DIGITS}; lower --num or raise --shard-size")

    def units(self, num: int) -> list[range]:
        n = self.shard_size
        return [range(j * n, min((j + 1) * n, num)) for j in range(-(-num // n))]

    # -- writing --------------------------------------------------------------------------------------
    def write(self, sample: dict[str, torch.Tensor], index: int, folder: Path) -> dict[str, str]:
        """Sample ``index``'s shard members as loose files ``%08d.NAME`` in ``folder`` (what ``tar -x`` of its
        shard gives for it); :meth:`write_unit` packs them."""
        from flowsynth.io.sampleio import PROVENANCE_KEY, write_sample

        folder, key = Path(folder), f"{index:0{_KEY_DIGITS}d}"
        tensors = _tensor_keys()
        images = {k: v for k, v in sample.items() if k not in tensors and k != PROVENANCE_KEY}
        out: dict[str, str] = {}
        if images:
            with tempfile.TemporaryDirectory(dir=folder, prefix=".images-") as tmp:
                for n in write_sample(images, Path(tmp), exr_compression=self.exr_compression):
                    if n == "meta.json":  # holds only the key list here; the member names say it
                        continue
                    (Path(tmp) / n).replace(folder / f"{key}.{n}")
                    out[f"{key}.{n}"] = frame_key(n)
        for k, v in sample.items():
            if k in tensors:
                buf = io.BytesIO()
                np.save(buf, v.numpy(), allow_pickle=False)
                (folder / f"{key}.{k}.npy").write_bytes(buf.getvalue())
                out[f"{key}.{k}.npy"] = k
        if PROVENANCE_KEY in sample:
            (folder / f"{key}.provenance.json").write_text(sample[PROVENANCE_KEY], encoding="utf-8")
            out[f"{key}.provenance.json"] = "meta"
            cam = json.loads(sample[PROVENANCE_KEY]).get("camera", {})  # a Layers sample has no camera
            if "model" in cam:  # a lens camera (a pinhole's provenance has no model: its shards are unchanged)
                (folder / f"{key}.camera.json").write_text(json.dumps({"model": cam["model"], "dist": cam["dist"]}))
                out[f"{key}.camera.json"] = "meta"
        return out

    def write_unit(self, samples: Iterable[tuple[int, dict[str, torch.Tensor]]], folder: Path) -> dict[str, str]:
        """Write one shard (its samples, in index order) as ``folder/shard-NNNNNN.tar``."""
        folder, samples = Path(folder), iter(samples)
        first = next(samples, None)
        if first is None:
            raise ExportError("a webdataset shard needs at least one sample")
        name = shard_name(first[0] // self.shard_size)
        members = folder / ".members"
        with atomic_path(folder / name) as tmp, tarfile.open(tmp, "w", format=tarfile.USTAR_FORMAT) as tar:
            for index, sample in itertools.chain([first], samples):
                members.mkdir()
                for rel in sorted(self.write(sample, index, members)):
                    data = (members / rel).read_bytes()
                    tar.addfile(_member_info(rel, len(data)), io.BytesIO(data))
                    (members / rel).unlink()
                members.rmdir()
        return {name: "shard"}

    # -- reading --------------------------------------------------------------------------------------
    def read(self, root: Path, files: Sequence[str]) -> dict[str, torch.Tensor]:
        """One sample from its loose member files ``%08d.NAME`` (an extracted shard)."""
        members = {}
        for rel in files:
            members[Path(rel).name.split(".", 1)[1]] = (Path(root) / rel).read_bytes()
        return decode(members)

    def read_sample(self, root: Path, files: Sequence[str], index: int) -> dict[str, torch.Tensor]:
        """Sample ``index`` out of its shard (``files``: the one shard path the manifest records for it)."""
        path = Path(root) / files[0]
        st = path.stat()
        cache = (str(path), st.st_size, st.st_mtime_ns)
        if cache not in self._index:  # key -> its members' data offsets and sizes, from the headers only
            self._index[cache] = _tar_index(path)
        key = f"{index:0{_KEY_DIGITS}d}"
        if key not in self._index[cache]:
            raise ExportError(f"{path} holds no sample {key}; re-run the export command to repair it")
        members = {}
        with open(path, "rb") as f:  # a fresh handle per read: safe in forked DataLoader workers
            for suffix, offset, size in self._index[cache][key]:
                f.seek(offset)
                members[suffix] = f.read(size)
        return decode(members)

    def load_hint(self, root: Path) -> str:
        return (f"flowsynth.datasets.Shards({str(root)!r})  # streaming; or flowsynth.datasets.Exported, "
                "webdataset.WebDataset")

    def clear(self, root: Path) -> None:
        for p in Path(root).iterdir():
            if p.is_file() and _SHARD.match(p.name):
                p.unlink()


def _tar_index(path: Path) -> dict[str, list[tuple[str, int, int]]]:
    out: dict[str, list[tuple[str, int, int]]] = {}
    with tarfile.open(path, "r:") as tar:
        for m in tar:
            if m.isfile():
                key, _, suffix = m.name.partition(".")
                out.setdefault(key, []).append((suffix, m.offset_data, m.size))
    return out


def iter_shard(path: str | Path) -> Iterator[tuple[str, dict[str, bytes]]]:
    """``(key, {member suffix: bytes})`` of each sample of a shard, read front to back in one pass.

    Members of one key must be consecutive (flowsynth writes them sorted); the suffix is the member
    name after the key's dot (``rgb_0000.png``, ``K.npy``).
    """
    key, members = None, {}
    with tarfile.open(path, "r|") as tar:
        for m in tar:
            if not m.isfile():
                continue
            k, _, suffix = m.name.partition(".")
            if k != key and members:
                yield key, members
                members = {}
            key = k
            members[suffix] = tar.extractfile(m).read()
    if members:
        yield key, members


def decode(members: dict[str, bytes]) -> dict[str, torch.Tensor]:
    """A sample dict (the stream's keys, dtypes, shapes) from one key's members ``{suffix: bytes}``."""
    from flowsynth.io.sampleio import PROVENANCE_KEY, read_sample

    out: dict[str, torch.Tensor] = {}
    images = {}
    for suffix, data in members.items():
        if suffix.endswith(".npy"):
            out[suffix[:-4]] = torch.from_numpy(np.load(io.BytesIO(data), allow_pickle=False))
        elif suffix == "provenance.json":
            out[PROVENANCE_KEY] = data.decode("utf-8")
        elif suffix == "camera.json":
            continue  # the lens of the provenance's camera, for readers of the members; no key of its own
        elif frame_key(suffix):
            images[suffix] = data
        else:
            raise ExportError(f"unknown webdataset member suffix {suffix!r}; was this shard written by flowsynth?")
    if images:  # the native layout's reader over the same files
        with tempfile.TemporaryDirectory(prefix="flowsynth-wds-") as tmp:
            for n, data in images.items():
                (Path(tmp) / n).write_bytes(data)
            keys = sorted({frame_key(n) for n in images})
            (Path(tmp) / "meta.json").write_text(json.dumps({"keys": keys}))
            out.update(read_sample(Path(tmp)))
    return out
