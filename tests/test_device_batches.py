"""``fs.datasets.DeviceBatches`` keeps ``BouncingThings``' promises, with the stream itself as the oracle.

Batch for batch, epoch for epoch, DeviceBatches yields what a DataLoader of the same batch size yields over
``BouncingThings(cfg, outputs, seed=..., length=..., start=...)`` (on the CPU, the same bits: every sample is
rendered once per side here, by ``fs.render_batch`` and by ``fs.render``). Each sample is yielded once: a broken-off
epoch resumes where it stopped, a finite stream's next epoch holds new samples, an endless stream iterated again
continues, and a position saved by ``state_dict`` resumes in a fresh object, or in a ``StatefulDataLoader`` over the
stream.
"""

from __future__ import annotations

import dataclasses
import itertools

import pytest
import torch
from torch.utils.data import DataLoader
from torchdata.stateful_dataloader import Stateful, StatefulDataLoader

import flowsynth as fs
from flowsynth.datasets import BouncingThings, DeviceBatches

CFG = fs.BouncingThingsConfig(width=32, height=24, num_frames=2, num_objects=(2, 3), max_objects=3,
                              motion="kinematic")
KEYS = ["depth", "flow_fw", "occ_fw", "rgb", "meta"]
TIMEOUT = 600  # [s] a worker's first scene on a loaded machine


def _stream(**kw) -> BouncingThings:
    return BouncingThings(CFG, outputs=KEYS, seed=2, **kw)


def _assert_same(got: dict, want: dict) -> None:
    assert set(got) == set(want), sorted(set(got) ^ set(want))
    assert got["provenance"] == want["provenance"]
    for k in got:
        if k != "provenance":
            assert got[k].dtype == want[k].dtype and torch.equal(got[k], want[k]), k


def _indices(batches) -> list[list[int]]:
    return [b["index"].tolist() for b in batches]


def test_epochs_are_the_dataloaders_epochs_of_the_stream():
    """length 5, batch 2, start 1: epoch 0 is [1, 2] [3, 4] [5], epoch 1 [6, 7] [8, 9] [10] (the short batch
    last), each batch equal to a DataLoader's over the stream, and no sample twice over the two epochs."""
    ds = _stream(length=5, start=1)
    oracle = DataLoader(ds, batch_size=2)
    want = [list(oracle), list(oracle)]  # the stream's epochs 0 and 1
    batches = DeviceBatches(CFG, KEYS, 2, seed=2, length=5, start=1)
    assert len(batches) == 3
    got = [list(batches), list(batches)]
    assert [_indices(e) for e in got] == [[[1, 2], [3, 4], [5]], [[6, 7], [8, 9], [10]]]
    for g, w in zip(itertools.chain(*got), itertools.chain(*want), strict=True):
        _assert_same(g, w)


def test_a_broken_off_epoch_resumes_where_it_stopped_with_scene_workers():
    """With a scene worker (forkserver; it prefetches scenes ahead): an epoch broken off after one batch resumes at
    the next sample, the next epoch follows, and the samples equal the in-process ones; an endless stream iterated
    again continues instead of starting over."""
    batches = DeviceBatches(CFG, KEYS, 2, 1, seed=2, length=5)
    first = next(iter(batches))
    rest = list(batches)  # the same epoch, from where it stopped
    after = next(iter(batches))  # the epoch was read to its end: the next one
    assert _indices([first, *rest, after]) == [[0, 1], [2, 3], [4], [5, 6]]
    batches.close()
    here = DeviceBatches(CFG, KEYS, 2, 0, seed=2, length=5)
    for g, w in zip([first, *rest, after], [*list(here), next(iter(here))], strict=True):
        _assert_same(g, w)

    endless = DeviceBatches(CFG, ["depth"], 2, seed=2, start=3)
    seen = []
    for _ in range(2):
        for b in endless:
            seen.append(b["index"].tolist())
            break
    assert seen == [[3, 4], [5, 6]]
    with pytest.raises(TypeError, match="endless"):
        len(endless)


def test_state_round_trip_and_stateful_dataloader():
    """A position saved after one batch resumes, batch for batch, in a fresh DeviceBatches (of another batch size
    too: the state counts samples) and in a StatefulDataLoader over the stream; and a StatefulDataLoader's stream,
    broken off after a batch, hands its position to DeviceBatches."""
    batches = DeviceBatches(CFG, KEYS, 2, seed=2, length=5)
    assert isinstance(batches, Stateful)
    next(iter(batches))
    state = batches.state_dict()
    assert state == {"epoch": 0, "pos": 2, "seed": 2, "start": 0, "rank": 0, "world_size": 1, "worker": 0,
                     "num_workers": 1}

    ds = _stream(length=5)
    loader = StatefulDataLoader(ds, batch_size=2)
    it = iter(loader)
    next(it)
    resumed = StatefulDataLoader(_stream(length=5), batch_size=2)
    resumed.load_state_dict(loader.state_dict())  # the oracle: the stream's own resume
    want = list(resumed)
    assert _indices(want) == [[2, 3], [4]]

    fresh = DeviceBatches(CFG, KEYS, 2, seed=2, length=5)
    fresh.load_state_dict(state)
    for g, w in zip(list(fresh), want, strict=True):
        _assert_same(g, w)
    other_size = DeviceBatches(CFG, ["depth"], 3, seed=2, length=5)
    other_size.load_state_dict(state)
    assert _indices(other_size) == [[2, 3, 4]]

    into_stream = _stream(length=5)
    into_stream.load_state_dict(state)
    assert _indices(StatefulDataLoader(into_stream, batch_size=2)) == [[2, 3], [4]]
    from_stream = DeviceBatches(CFG, ["depth"], 2, seed=2, length=5)
    from_stream.load_state_dict(ds.state_dict())  # no workers: the loader's dataset is this object, one batch in
    assert _indices(from_stream) == [[2, 3], [4]]

    fresh.set_epoch(3)
    assert next(iter(fresh))["index"].tolist() == [15, 16]


@pytest.mark.parametrize(("kwargs", "match"), [
    (dict(batch_size=0), "batch_size must be an integer >= 1"),
    (dict(num_workers=-1), "num_workers must be an integer >= 0"),
    (dict(num_workers=1.5), "num_workers must be"),
    (dict(length=0), r"length \(None: endless\) must be an integer >= 1"),
    (dict(seed=-1), "seed must be"),
    (dict(start=True), "start must be"),
    (dict(device="gpu"), "device 'gpu' is not available"),
    (dict(outputs=["tracks"]), "does not render"),
    (dict(cfg=fs.BouncingThingsConfig(num_frames=1), outputs=["flow_fw"]), "num_frames"),
    (dict(cfg=dataclasses.replace(CFG, camera_model="brown_conrady", camera_dist=(-0.1, 0.0, 0.0, 0.0),
                                  camera_dist_max=(0.1, 0.0, 0.0, 0.0))), "camera_dist_max"),
])
def test_bad_arguments_say_what_to_do(kwargs, match):
    kwargs = {"cfg": CFG, "outputs": ["depth"], **kwargs}
    with pytest.raises(fs.ConfigError, match=match):
        DeviceBatches(**kwargs)


def test_bad_positions_say_what_to_do():
    batches = DeviceBatches(CFG, ["depth"], 2, seed=2, length=4)
    good = batches.state_dict()
    for state, match in (({**good, "seed": 3}, "seed=3"), ({**good, "start": 1}, "start=1"),
                         ({k: v for k, v in good.items() if k != "pos"}, r"misses \[.pos.\]"),
                         ({**good, "pos": 5}, "past the 4 samples shard 0 of 1"), ({**good, "epoch": -1}, "epoch")):
        with pytest.raises(fs.ConfigError, match=match):
            batches.load_state_dict(state)
    assert batches.state_dict() == good  # a refused state moves nothing
    with pytest.raises(fs.ConfigError, match="epoch must be"):
        batches.set_epoch(-1)
    with pytest.raises(fs.ConfigError, match="endless"):
        DeviceBatches(CFG, ["depth"], 2).set_epoch(1)
    with pytest.raises(TypeError):
        DeviceBatches(CFG, ["depth"], 2, workers=1)  # the name is DataLoader's: num_workers


def test_the_loaders_endless_stream_broken_off_repeats_nothing():
    """The same promise for ``fs.datasets.loader`` over an endless BouncingThings (persistent forkserver workers):
    a loop broken off and iterated again repeats no sample; it skips at most the batches the workers had prefetched
    (``prefetch_factor`` 2 a worker)."""
    loader = fs.datasets.loader(BouncingThings(CFG, outputs=["depth"], seed=2), batch_size=2, num_workers=2,
                                timeout=TIMEOUT)
    passes = []
    for _ in range(2):
        seen = []
        for b in loader:
            seen += b["index"].tolist()
            if len(seen) == 4:
                break
        passes.append(seen)
    first, second = passes
    assert not set(first) & set(second), passes
    skipped = set(range(max(second) + 1)) - set(first) - set(second)
    assert len(skipped) <= 2 * 2 * 2, passes


def test_len_batches_then_the_next_iter_is_the_next_epoch():
    """Taking exactly ``len(db)`` batches (``zip(range(len(db)), db)``) and iterating again gives the next epoch,
    not an empty one."""
    db = DeviceBatches(CFG, ["depth"], 2, 0, seed=2, length=4)
    epochs = [[b["index"].tolist() for _, b in zip(range(len(db)), db)] for _ in range(2)]
    db.close()
    assert epochs == [[[0, 1], [2, 3]], [[4, 5], [6, 7]]]
