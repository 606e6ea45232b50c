"""IndexStream's positions: an endless stream never repeats a sample (set_epoch refuses it, as DeviceBatches' does),
epochs and saved states are checked at the boundary. A stream whose sample i is {"index": i} stands for every stream,
so the expected indices are written out by hand."""

from __future__ import annotations

import pytest

import flowsynth as fs
from flowsynth.datasets import BouncingThings, Layers, LayersConfig
from flowsynth.datasets.stream import IndexStream


class Indices(IndexStream):
    def __init__(self, length: int | None = None, start: int = 0, seed: int = 0) -> None:
        self._init_stream(seed, length, start)

    def sample(self, i: int) -> dict:
        return {"index": i}


def _take(ds: IndexStream, n: int | None = None) -> list[int]:
    out = []
    for item in ds:
        out.append(item["index"])
        if len(out) == n:
            break
    return out


def test_set_epoch_on_an_endless_stream_is_refused_and_the_stream_goes_on():
    ds = Indices(start=5)
    assert _take(ds, 3) == [5, 6, 7]
    with pytest.raises(fs.ConfigError, match="endless"):
        ds.set_epoch(0)
    assert _take(ds, 3) == [8, 9, 10]  # nothing repeats
    streams = (BouncingThings(fs.BouncingThingsConfig(width=32, height=32), ["depth"]),
               Layers(LayersConfig(width=32, height=32)))
    for stream in streams:  # no sample made
        with pytest.raises(fs.ConfigError, match="finite stream"):
            stream.set_epoch(1)


def test_set_epoch_of_a_finite_stream_and_its_bad_values():
    ds = Indices(length=3, start=10)
    assert _take(ds) == [10, 11, 12] and _take(ds) == [13, 14, 15]
    ds.set_epoch(4)
    assert _take(ds) == [22, 23, 24]
    for bad in (-1, 1.5, True, "2"):
        with pytest.raises(fs.ConfigError, match="epoch must be an integer >= 0"):
            ds.set_epoch(bad)
    assert _take(ds) == [25, 26, 27]  # a refused value leaves the position


def test_load_state_dict_resumes_and_refuses_a_bad_state():
    whole = _take(Indices(length=6, seed=2), None)
    part = Indices(length=6, seed=2)
    assert _take(part, 2) == whole[:2]
    state = part.state_dict()
    resumed = Indices(length=6, seed=2)
    resumed.load_state_dict(state)
    assert _take(resumed) == whole[2:]
    ds = Indices(length=6, seed=2)
    for bad, match in (({k: v for k, v in state.items() if k != "pos"}, r"misses \['pos'\]"),
                       ({}, r"misses \['epoch', 'pos', 'seed', 'start', 'rank', 'world_size', 'worker', "
                            r"'num_workers'\]"),
                       ({k: v for k, v in state.items() if k != "worker"}, r"misses \['worker'\]"),
                       ([0, 2, 2, 0], "must be the dict"),
                       ({**state, "seed": 3}, "seed=3"),
                       ({**state, "start": 1}, "start=1"),
                       ({**state, "epoch": -1}, "epoch must be"),
                       ({**state, "pos": 2.5}, "pos must be"),
                       ({**state, "pos": 7}, r"past the 6 samples shard 0 of 1 .rank 0 of 1, worker 0 of 1. "
                                             r"reads of the epoch's 6"),
                       ({**state, "rank": 1}, "no shard"), ({**state, "num_workers": 0}, "num_workers must be")):
        with pytest.raises(fs.ConfigError, match=match):
            ds.load_state_dict(bad)
    assert _take(ds) == whole  # refused states leave the position
    endless = Indices()
    endless.load_state_dict({"epoch": 0, "pos": 10**6, "seed": 0, "start": 0, "rank": 0, "world_size": 1,
                             "worker": 0, "num_workers": 1})
    assert _take(endless, 2) == [10**6, 10**6 + 1]


def test_an_epoch_read_to_its_last_sample_without_exhausting_goes_on_to_the_next():
    """A loop that stops right after the epoch's last sample (``zip(range(len(ds)), ds)``) leaves the generator
    unexhausted: the next ``iter()`` is the next epoch, never an empty one; a saved state of that moment resumes
    there too."""
    ds = Indices(length=4)
    assert _take(ds, 4) == [0, 1, 2, 3]  # stops after the last sample: the generator is not exhausted
    state = ds.state_dict()
    assert _take(ds, 4) == [4, 5, 6, 7]
    again = Indices(length=4)
    again.load_state_dict(state)
    assert _take(again) == [4, 5, 6, 7]
    assert _take(again) == [8, 9, 10, 11]  # an exhausted epoch moves on as before
