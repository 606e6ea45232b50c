"""``IndexStream``: iteration, sharding, epochs and resume of a stream whose sample i is a pure function of
(config, seed, i). ``BouncingThings``, ``Layers`` and ``Mixture`` are ones; each defines ``sample(i)``.
``StreamPosition`` is the part of it that ``DeviceBatches`` shares: the shard, the epoch and the position in both.

Shards. The global index stream is split into shards: shard g of G = world_size * num_workers, with
g = rank * num_workers + worker_id, takes the indices i = start + g + G m (m = 0, 1, ...). So the union over shards
is every index exactly once, whatever the number of workers, ranks or the process start method. The rank and world
size are ``rank_world()``'s: ``RANK`` and ``WORLD_SIZE`` from the environment (as torchrun sets them, and as every
DataLoader worker inherits them), else torch.distributed's process group, else, in a DataLoader worker, what the
main process had when it built or pickled the stream (a spawned or forkserver worker has no process group), else
rank 0 of 1. With ranks, each rank reads about ``length / world_size`` samples an epoch: choose ``length`` a multiple
of world_size x num_workers x batch_size, so that every rank gets as many batches.

Epochs. With ``length=None`` the stream is endless: an epoch ends when the training loop stops reading, and the
next ``iter()`` on the same dataset object (num_workers=0, or persistent workers) continues after the last sample
this shard produced, so no sample repeats. With a finite ``length`` L, epoch e covers indices
[start + e L, start + (e + 1) L): every epoch sees new samples. The epoch counter advances on each ``iter()`` of the
same object; with non-persistent workers (fresh copies every epoch) call ``set_epoch(e)`` before each epoch, as
with ``DistributedSampler``. An endless stream has no epochs: ``set_epoch`` on it raises ConfigError, as
``DeviceBatches.set_epoch`` does, since starting it over would repeat its samples.

Resuming. ``state_dict()`` / ``load_state_dict()`` follow torchdata's ``StatefulDataLoader`` protocol: each
worker's copy reports its own position, and a restored loader continues with exactly the samples an uninterrupted
run would have produced. A state records its shard layout (``LAYOUT_KEYS``: rank, world_size, worker,
num_workers). The start of an epoch (pos 0) is the same position in every layout and loads into any; any other
position counts the samples of one shard, and resumes only in that shard: a copy that would read it in another
layout (at ``load_state_dict``, or at the next ``iter()`` when the layout is only known then, in a worker) raises
ConfigError naming what differs.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import torch
from torch.utils.data import IterableDataset, get_worker_info

from flowsynth.errors import ConfigError
from flowsynth.options import check_int

__all__ = ["LAYOUT_KEYS", "IndexStream", "StreamPosition", "check_index", "rank_world", "read_state",
           "shard_indices", "shard_size"]

LAYOUT_KEYS = ("rank", "world_size", "worker", "num_workers")
"""The keys of a shard layout (``StreamPosition.shard_layout``), which every saved state holds."""
_POSITION_KEYS = ("epoch", "pos", "seed", "start")


def rank_world(fallback: tuple[int, int] = (0, 1)) -> tuple[int, int]:
    """(rank, world size) of this process: ``RANK`` and ``WORLD_SIZE`` from the environment when both are set (as
    torchrun sets them; webdataset reads them first too), else torch.distributed's when a process group is
    initialised, else ``fallback``. ConfigError for environment values that are not integers with
    0 <= RANK < WORLD_SIZE."""
    env = os.environ.get("RANK"), os.environ.get("WORLD_SIZE")
    if env[0] is not None and env[1] is not None:
        try:
            rank, world = int(env[0]), int(env[1])
        except ValueError:
            rank, world = -1, 0
        if not 0 <= rank < world:
            raise ConfigError(f"the environment's RANK={env[0]!r} and WORLD_SIZE={env[1]!r} must be integers with "
                              "0 <= RANK < WORLD_SIZE (torchrun sets both); unset both in a single process")
        return rank, world
    dist = torch.distributed
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return fallback


def shard_indices(start: int, length: int | None, g: int, G: int, epoch: int, pos: int
                  ) -> Iterator[tuple[int, int]]:
    """(index, position after it) of shard ``g`` of ``G`` in ``epoch``, from position ``pos`` (the shard's samples
    already read) to the epoch's end (endless: forever); module docstring."""
    base = start + (epoch * length if length is not None else 0)
    m = pos
    while length is None or g + G * m < length:
        yield base + g + G * m, m + 1
        m += 1


def shard_size(length: int, g: int, G: int) -> int:
    """Samples shard ``g`` of ``G`` reads in an epoch of ``length``."""
    return len(range(g, length, G))


def _describe(layout: dict) -> str:
    g = layout["rank"] * layout["num_workers"] + layout["worker"]
    return (f"shard {g} of {layout['world_size'] * layout['num_workers']} (rank {layout['rank']} of "
            f"{layout['world_size']}, worker {layout['worker']} of {layout['num_workers']})")


def check_index(i) -> int:
    """``i`` as an int; ConfigError unless it is an integer >= 0 (a sample index)."""
    return check_int("sample index", i, 0)


def read_state(state, owner: str, seed: int, start: int, length: int | None) -> tuple[int, int, dict]:
    """The (epoch, pos, layout) of a stream's saved ``state`` (what ``owner``'s ``state_dict`` returns: "epoch",
    "pos", "seed", "start" and ``LAYOUT_KEYS``), checked against the stream's ``seed``, ``start`` and ``length``
    (None: endless). ConfigError for a state that is not a dict, misses a key, was saved with another seed or start,
    holds an epoch or position that is not an integer >= 0 (a position past its shard's samples of a finite epoch
    included) or a layout that is no shard (0 <= rank < world_size, 0 <= worker < num_workers)."""
    if not isinstance(state, dict):
        raise ConfigError(f"state must be the dict state_dict() returned, got {type(state).__name__}")
    missing = [k for k in (*_POSITION_KEYS, *LAYOUT_KEYS) if k not in state]
    if missing:
        raise ConfigError(f"state misses {missing}: pass what {owner}.state_dict() returned")
    if state["seed"] != seed or state["start"] != start:
        raise ConfigError(f"state was saved with seed={state['seed']}, start={state['start']}; "
                          f"this {owner} has seed={seed}, start={start}")
    epoch, pos = check_int("state's epoch", state["epoch"], 0), check_int("state's pos", state["pos"], 0)
    layout = {k: check_int(f"state's {k}", state[k], 1 if k in ("world_size", "num_workers") else 0)
              for k in LAYOUT_KEYS}
    if layout["rank"] >= layout["world_size"] or layout["worker"] >= layout["num_workers"]:
        raise ConfigError(f"state's layout {layout} is no shard: it needs rank < world_size and "
                          "worker < num_workers")
    if length is not None:
        g = layout["rank"] * layout["num_workers"] + layout["worker"]
        n = shard_size(length, g, layout["world_size"] * layout["num_workers"])
        if pos > n:
            raise ConfigError(f"state's pos {pos} is past the {n} samples {_describe(layout)} reads of the epoch's "
                              f"{length} (length)")
    return epoch, pos, layout


class StreamPosition:
    """The shard, epoch and position of a stream (module docstring), shared by ``IndexStream`` and
    ``DeviceBatches``: ``_init_stream`` in ``__init__``, ``_begin`` when an iteration starts, then the shard's
    indices from ``shard_indices``; ``_epoch`` and ``_pos`` (this shard's samples of the epoch already yielded) are
    the position, which the iteration moves."""

    def _init_stream(self, seed: int, length: int | None, start: int) -> None:
        """Check and keep ``seed`` (>= 0), ``length`` (None or >= 1) and ``start`` (>= 0); ConfigError otherwise.
        Reads this process's rank and world size (``rank_world``)."""
        self.seed, self.start = check_int("seed", seed, 0), check_int("start", start, 0)
        self.length = None if length is None else check_int("length (None: endless)", length, 1)
        self._ranks = rank_world()
        self._epoch = 0
        self._pos = 0  # samples this shard has produced in the current epoch (endless: ever)
        self._pos_layout: dict | None = None  # the layout _pos counts in (None: this copy's own)

    def __getstate__(self) -> dict:
        if get_worker_info() is None:  # the main process pickles the stream for a spawned worker: its rank now
            self._ranks = rank_world()
        return self.__dict__.copy()

    def shard_layout(self) -> dict:
        """This copy's shard layout now, {"rank", "world_size", "worker", "num_workers"} (``LAYOUT_KEYS``): the
        rank and world size of ``rank_world`` (in a DataLoader worker, falling back on the main process's), the
        DataLoader worker's id and count (0 and 1 outside a worker)."""
        info = get_worker_info()
        if info is None:
            self._ranks = rank_world()
            (rank, world), wid, nw = self._ranks, 0, 1
        else:
            (rank, world), wid, nw = rank_world(self._ranks), info.id, info.num_workers
        return {"rank": rank, "world_size": world, "worker": wid, "num_workers": nw}

    def _check_layout(self, layout: dict) -> None:
        """ConfigError when the position counts samples of a shard other than ``layout``'s."""
        saved = self._pos_layout
        if self._pos == 0 or saved is None or saved == layout:
            return
        differ = ", ".join(f"{k} {saved[k]} (saved) vs {layout[k]} (here)" for k in LAYOUT_KEYS
                           if saved[k] != layout[k])
        raise ConfigError(f"this {type(self).__name__}'s position (epoch {self._epoch}, {self._pos} samples read) "
                          f"was counted in {_describe(saved)} and cannot resume in {_describe(layout)}: {differ}. "
                          "Resume with the ranks and workers it was saved with, or from the start of an epoch "
                          "(pos 0), which any layout reads")

    def _begin(self) -> tuple[int, int]:
        """(g, G): the shard an iteration starting now reads; ConfigError when the position is another shard's. A
        finite epoch whose every sample was read (an iteration stopped right after its last one, as
        ``zip(range(len(ds)), ds)`` stops) moves to the next epoch here, so no iteration comes out empty."""
        layout = self.shard_layout()
        self._check_layout(layout)
        self._pos_layout = layout
        g, G = (layout["rank"] * layout["num_workers"] + layout["worker"],
                layout["world_size"] * layout["num_workers"])
        if self.length is not None and self._pos and self._pos >= shard_size(self.length, g, G):
            self._epoch, self._pos = self._epoch + 1, 0
        return g, G

    def set_epoch(self, epoch: int) -> None:
        """Start the next ``iter()`` at the beginning of ``epoch`` (an integer >= 0; needed with non-persistent
        workers). ConfigError for an endless stream, which has no epochs: it continues where it stopped."""
        if self.length is None:
            raise ConfigError(f"set_epoch needs a finite stream (length=...): an endless {type(self).__name__} "
                              "has no epochs and continues where it stopped")
        self._epoch, self._pos = check_int("epoch", epoch, 0), 0

    def state_dict(self) -> dict:
        """This copy's position (per worker under StatefulDataLoader): {"epoch", "pos" (this shard's samples of the
        epoch already yielded), "seed", "start"} and the shard layout it counts in (``LAYOUT_KEYS``)."""
        layout = self._pos_layout if self._pos and self._pos_layout is not None else self.shard_layout()
        return {"epoch": self._epoch, "pos": self._pos, "seed": self.seed, "start": self.start, **layout}

    def load_state_dict(self, state: dict) -> None:
        """Restore a position saved by ``state_dict``. ConfigError for a state that is not a dict, misses a key, was
        saved with another seed or start, holds an epoch or position that is not an integer >= 0 (a position past
        its shard's samples of a finite epoch included), or a position inside an epoch saved in another shard
        layout than this copy's (module docstring); a refused state moves nothing."""
        epoch, pos, layout = read_state(state, type(self).__name__, self.seed, self.start, self.length)
        before = self._epoch, self._pos, self._pos_layout
        self._epoch, self._pos, self._pos_layout = epoch, pos, layout
        try:
            self._check_layout(self.shard_layout())
        except ConfigError:
            self._epoch, self._pos, self._pos_layout = before
            raise


class IndexStream(StreamPosition, IterableDataset):
    """Base of flowsynth's streams: subclasses call ``_init_stream(seed, length, start)`` in ``__init__`` and define
    ``sample(i) -> dict``; this class iterates, shards, counts epochs and saves positions (module docstring)."""

    def __len__(self) -> int:
        if self.length is None:
            raise TypeError(f"an endless {type(self).__name__} stream has no len(); pass length=...")
        return self.length

    def __iter__(self) -> Iterator[dict]:
        if get_worker_info() is not None:
            torch.set_num_threads(1)
        g, G = self._begin()
        epoch = self._epoch
        for i, next_pos in shard_indices(self.start, self.length, g, G, epoch, self._pos):
            item = self.sample(i)
            self._pos = next_pos
            yield item
        # finite epoch exhausted: the next iter() starts the next epoch
        self._epoch, self._pos = epoch + 1, 0
