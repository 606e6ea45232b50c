"""``Shards``: a streaming ``IterableDataset`` over the tar shards of a ``webdataset`` export, for training.

What readers of WebDataset shards do (the ``webdataset`` package's ``shardshuffle``, ``split_by_node``,
``split_by_worker`` and ``shuffle``; Ray Data's ``read_webdataset``), with the stream's sample dicts:

1. Shard order: with ``shuffle``, a permutation of the shards drawn from ``(seed, epoch)``; the same on
   every rank and worker, so the split below is a partition. Without, the manifest's (index) order.
2. Split: consumer g = rank * num_workers + worker_id of G = world_size * num_workers takes the shards at
   positions g, g + G, g + 2G, ... of that order. Every sample is read exactly once per epoch across
   workers x ranks. A consumer may get no shard (fewer shards than G) or one more than another; choose
   ``--shard-size`` so that the export has many shards per consumer.
3. Samples: read front to back from each shard in one pass (``tarfile`` streaming mode); with
   ``shuffle``, through a buffer of ``buffer`` samples that yields a random one of them as each new one
   arrives (random draws from ``(seed, epoch, g)``), the rest shuffled at the end.

Rank and world size come from ``rank`` / ``world_size`` when given, else from ``RANK`` and ``WORLD_SIZE`` in the
environment (torchrun's, which every worker inherits), else from ``torch.distributed`` when it is initialised, else
0 and 1 (``flowsynth.datasets.stream.rank_world``); the worker from ``torch.utils.data.get_worker_info()``.

Epochs: each ``iter()`` on the same object (num_workers=0, or persistent workers) starts the next epoch;
with non-persistent workers call ``set_epoch(e)`` before each epoch, as with ``DistributedSampler``.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from flowsynth.datasets.stream import rank_world
from flowsynth.errors import ConfigError, ExportError
from flowsynth.options import check_int
from flowsynth.io import read_manifest

__all__ = ["Shards"]


class Shards(IterableDataset):
    """Samples of ``webdataset`` shards, shard-shuffled, buffer-shuffled, split by worker and by rank.

    Args:
        source: an export folder written with ``--layout webdataset`` (its shards in the manifest's
            order), or a sequence of shard paths.
        shuffle: shuffle shards and samples (seeded, per epoch); False: shard order, samples in order.
        seed: seed of the shuffles; every rank must pass the same.
        buffer: samples held for the sample shuffle (memory: that many samples), >= 1.
        rank, world_size: this process's rank among world_size; None: from ``RANK`` and ``WORLD_SIZE``, else
            ``torch.distributed`` when it is initialised, else 0 of 1. Give both or neither.

    Yields:
        the stream's sample dicts (``BouncingThings.sample`` keys, dtypes and shapes, for the exported
        outputs; ``rgb`` within 8-bit quantisation, other outputs exact).

    Raises:
        ExportError: ``source`` is not a webdataset export, or a listed shard is missing.
        ConfigError: bad ``buffer``, ``rank`` or ``world_size``.
    """

    def __init__(self, source: str | Path | Sequence[str | Path], *, shuffle: bool = True, seed: int = 0,
                 buffer: int = 64, rank: int | None = None, world_size: int | None = None) -> None:
        self.urls = _shard_paths(source)
        buffer = check_int("buffer", buffer, 1)
        if (rank is None) != (world_size is None):
            raise ConfigError("give both rank and world_size, or neither (then RANK and WORLD_SIZE, or "
                              "torch.distributed, say)")
        if world_size is not None:
            world_size = check_int("world_size", world_size, 1)
            rank = check_int("rank", rank, 0, world_size - 1)
        self.shuffle, self.seed, self.buffer = bool(shuffle), check_int("seed", seed, 0), buffer
        self.rank, self.world_size = rank, world_size
        self._epoch = 0
        self._ranks = (0, 1)  # the rank the main process saw when it pickled this stream for a worker

    def __getstate__(self) -> dict:
        if get_worker_info() is None:  # the main process pickles the stream for a spawned worker: its rank now
            self._ranks = rank_world()
        return self.__dict__.copy()

    def set_epoch(self, epoch: int) -> None:
        """Shuffle the next ``iter()`` as epoch ``epoch`` (needed with non-persistent workers)."""
        self._epoch = int(epoch)

    def _consumer(self) -> tuple[int, int]:
        """(g, G): this consumer's position among every rank's workers."""
        rank, world = self.rank, self.world_size
        if rank is None:
            rank, world = rank_world(self._ranks)
        info = get_worker_info()
        wid, nw = (info.id, info.num_workers) if info is not None else (0, 1)
        return rank * nw + wid, world * nw

    def shards(self, epoch: int | None = None) -> list[Path]:
        """The shards this consumer reads in ``epoch`` (default: the next ``iter()``'s), in reading order."""
        epoch = self._epoch if epoch is None else epoch
        order = list(self.urls)
        if self.shuffle:
            order = [order[k] for k in np.random.default_rng([self.seed, epoch]).permutation(len(order))]
        g, G = self._consumer()
        return order[g::G]

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        from flowsynth.io.layouts.webdataset import decode, iter_shard

        if get_worker_info() is not None:
            torch.set_num_threads(1)
        epoch = self._epoch
        self._epoch += 1
        g, _ = self._consumer()
        samples = (decode(members) for url in self.shards(epoch) for _, members in iter_shard(url))
        if not self.shuffle:
            yield from samples
            return
        rng = np.random.default_rng([self.seed, epoch, g])
        held: list = []
        for s in samples:
            if len(held) < self.buffer:
                held.append(s)
                continue
            k = int(rng.integers(len(held)))
            held[k], s = s, held[k]
            yield s
        for k in rng.permutation(len(held)):
            yield held[k]


def _shard_paths(source) -> list[Path]:
    if isinstance(source, (str, Path)) and Path(source).is_dir():
        root = Path(source)
        m = read_manifest(root)
        if m.get("layout") != "webdataset":
            raise ExportError(f"{root} holds a {m.get('layout')!r} export; Shards reads --layout webdataset "
                              "(flowsynth.datasets.Exported reads every layout)")
        names = dict.fromkeys(f for _, files in sorted(m.get("samples", {}).items()) for f in files)
        paths = [root / n for n in names]
    else:
        paths = [Path(p) for p in ([source] if isinstance(source, (str, Path)) else source)]
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise ExportError(f"missing shard(s) {missing[:5]}; re-run the `flowsynth export` command to repair them")
    if not paths:
        raise ExportError(f"no shards in {source}")
    return paths
