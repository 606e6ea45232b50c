"""``IndexStream``: iteration, sharding, epochs and resume of a stream whose sample i is a pure function of
(config, seed, i). ``BouncingThings``, ``Layers`` and ``Mixture`` are ones; each defines ``sample(i)``.

The global index stream is split into shards: shard g of G = world_size * num_workers, with
g = rank * num_workers + worker_id, takes the indices i = start + g + G m (m = 0, 1, ...). So the union over shards
is every index exactly once, whatever the number of workers, ranks or the process start method.

Epochs. With ``length=None`` the stream is endless: an epoch ends when the training loop stops reading, and the
next ``iter()`` on the same dataset object (num_workers=0, or persistent workers) continues after the last sample
this shard produced, so no sample repeats. With a finite ``length`` L, epoch e covers indices
[start + e L, start + (e + 1) L): every epoch sees new samples. The epoch counter advances on each ``iter()`` of the
same object; with non-persistent workers (fresh copies every epoch) call ``set_epoch(e)`` before each epoch, as
with ``DistributedSampler``. An endless stream has no epochs: ``set_epoch`` on it raises ConfigError, as
``DeviceBatches.set_epoch`` does, since starting it over would repeat its samples.

Resuming. ``state_dict()`` / ``load_state_dict()`` follow torchdata's ``StatefulDataLoader`` protocol: each
worker's copy reports its own position, and a restored loader continues with exactly the samples an uninterrupted
run would have produced.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from flowsynth.errors import ConfigError

__all__ = ["IndexStream", "check_index", "count", "read_position"]


def _shard() -> tuple[int, int]:
    """(shard id, number of shards) from torch.distributed rank/world size and the DataLoader worker."""
    rank, world = 0, 1
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        rank, world = torch.distributed.get_rank(), torch.distributed.get_world_size()
    info = get_worker_info()
    wid, nw = (info.id, info.num_workers) if info is not None else (0, 1)
    return rank * nw + wid, world * nw


def count(name: str, v, lo: int = 0) -> int:
    """``v`` as an int; ConfigError naming ``name`` unless it is an integer >= ``lo``."""
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
        raise ConfigError(f"{name} must be an integer >= {lo}, got {v!r}")
    return int(v)


def read_position(state, owner: str, seed: int, start: int, length: int | None) -> tuple[int, int]:
    """The (epoch, pos) of a stream's saved ``state`` ({"epoch", "pos", "seed", "start"}: what ``owner``'s
    ``state_dict`` returns), checked against the stream's ``seed``, ``start`` and ``length`` (None: endless).
    ConfigError for a state that is not a dict, misses a key, was saved with another seed or start, or holds an epoch
    or position that is not an integer >= 0 (a position past a finite epoch's ``length`` included)."""
    if not isinstance(state, dict):
        raise ConfigError(f"state must be the dict state_dict() returned, got {type(state).__name__}")
    missing = [k for k in ("epoch", "pos", "seed", "start") if k not in state]
    if missing:
        raise ConfigError(f"state misses {missing}: pass what {owner}.state_dict() returned")
    if state["seed"] != seed or state["start"] != start:
        raise ConfigError(f"state was saved with seed={state['seed']}, start={state['start']}; "
                          f"this {owner} has seed={seed}, start={start}")
    epoch, pos = count("state's epoch", state["epoch"]), count("state's pos", state["pos"])
    if length is not None and pos > length:
        raise ConfigError(f"state's pos {pos} is past the epoch's {length} samples (length)")
    return epoch, pos


def check_index(i) -> int:
    """``i`` as an int; ConfigError unless it is an integer >= 0 (a sample index)."""
    return count("sample index", i)


class IndexStream(IterableDataset):
    """Base of flowsynth's streams: subclasses call ``_init_stream(seed, length, start)`` in ``__init__`` and define
    ``sample(i) -> dict``; this class iterates, shards, counts epochs and saves positions (module docstring)."""

    def _init_stream(self, seed: int, length: int | None, start: int) -> None:
        """Check and keep ``seed`` (>= 0), ``length`` (None or >= 1) and ``start`` (>= 0); ConfigError otherwise."""
        self.seed, self.start = count("seed", seed), count("start", start)
        if length is not None and (isinstance(length, bool) or not isinstance(length, (int, np.integer))
                                   or length < 1):
            raise ConfigError(f"length must be None (endless) or an integer >= 1, got {length!r}")
        self.length = None if length is None else int(length)
        self._epoch = 0
        self._pos = 0  # samples this shard has produced in the current epoch (endless: ever)

    def __len__(self) -> int:
        if self.length is None:
            raise TypeError(f"an endless {type(self).__name__} stream has no len(); pass length=...")
        return self.length

    def set_epoch(self, epoch: int) -> None:
        """Start the next ``iter()`` at the beginning of ``epoch`` (an integer >= 0; needed with non-persistent
        workers). ConfigError for an endless stream, which has no epochs: it continues where it stopped."""
        if self.length is None:
            raise ConfigError(f"set_epoch needs a finite stream (length=...): an endless {type(self).__name__} "
                              "has no epochs and continues where it stopped")
        self._epoch, self._pos = count("epoch", epoch), 0

    def _indices(self, g: int, G: int, epoch: int, pos: int) -> Iterator[tuple[int, int]]:
        m = pos
        while True:
            k = g + G * m
            if self.length is not None and k >= self.length:
                return
            base = self.start + (epoch * self.length if self.length is not None else 0)
            yield base + k, m + 1
            m += 1

    def __iter__(self) -> Iterator[dict]:
        if get_worker_info() is not None:
            torch.set_num_threads(1)
        g, G = _shard()
        epoch = self._epoch
        for i, next_pos in self._indices(g, G, epoch, self._pos):
            item = self.sample(i)
            self._pos = next_pos
            yield item
        # finite epoch exhausted: the next iter() starts the next epoch
        self._epoch, self._pos = epoch + 1, 0

    def state_dict(self) -> dict:
        """This copy's position (per worker under StatefulDataLoader)."""
        return {"epoch": self._epoch, "pos": self._pos, "seed": self.seed, "start": self.start}

    def load_state_dict(self, state: dict) -> None:
        """Restore a position saved by ``state_dict``. ConfigError for a state that is not a dict, misses a key, was
        saved with another seed or start, or holds an epoch or position that is not an integer >= 0 (a position
        past a finite epoch's ``length`` included)."""
        self._epoch, self._pos = read_position(state, type(self).__name__, self.seed, self.start, self.length)
