"""Ranks x workers, with real processes: no sample twice across ranks, and a saved position knows its shard.

``test_two_ranks_read_every_index_once`` starts 2 ranks with torchrun (gloo; ``RANK``, ``WORLD_SIZE``,
``MASTER_ADDR`` ... in each rank's environment, as a DDP script sees them), once per stream kind; each rank reads
through 2 worker processes (``tests/ranks_program.py`` says what it reads). The oracle is the index set itself:
epoch e of a stream of length L is start + e L .. start + (e + 1) L - 1, each exactly once over the ranks.
The states the ranks' workers saved are then loaded here, in another layout (one process, no worker).
The other tests set ``RANK`` and ``WORLD_SIZE`` in this process's environment, which is where the streams read them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import ranks_program
import torch
from torch.utils.data import DataLoader

import flowsynth as fs
from flowsynth.datasets import BouncingThings, DeviceBatches
from flowsynth.datasets.stream import IndexStream

ROOT = Path(__file__).resolve().parents[1]
PROGRAM = ROOT / "tests" / "ranks_program.py"

TIMEOUT = 900  # [s] two ranks, each starting 6 worker processes that import torch and flowsynth, on a loaded machine
LENGTH = ranks_program.LENGTH


def _launch(kind: str, out: Path) -> list[dict]:
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK")}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])
    run = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                          str(PROGRAM), kind, str(out)], env=env, capture_output=True, text=True, timeout=TIMEOUT)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-6000:]
    return [json.loads((out / f"rank{r}.json").read_text()) for r in (0, 1)]


def _worker_states(state: dict) -> list[dict]:
    """The stream states inside a StatefulDataLoader's state, one per worker."""
    workers = state["_snapshot"]["_worker_snapshots"]
    return [workers[f"worker_{w}"]["dataset_state"] for w in range(len(workers))]


@pytest.mark.parametrize("kind", ["bouncing", "layers", "mixture", "device"])
def test_two_ranks_read_every_index_once(kind, tmp_path, monkeypatch):
    """Over 2 ranks x 2 workers (forkserver through fs.datasets.loader, spawn through StatefulDataLoader, resumed
    from its state; for DeviceBatches its 2 scene workers, resumed in a fresh object): every index of epoch e exactly
    once, none twice over the two epochs. Then the ranks' saved states, loaded in this process (rank 0 of 1, no
    worker), are refused with both layouts named."""
    ranks = _launch(kind, tmp_path)
    assert [r["rank"] for r in ranks] == [0, 1] and {r["world_size"] for r in ranks} == {2}
    for way in ("loader", "stateful"):
        for e in (0, 1):
            got = sorted(i for r in ranks for i in r[way][e])
            assert got == list(range(e * LENGTH, (e + 1) * LENGTH)), (way, e, [r[way][e] for r in ranks])
    for r in ranks:  # the resumed reads continue where the saved ones stopped: the first reads are a prefix
        assert r["stateful"][0][:len(r["saved"])] == r["saved"]

    monkeypatch.delenv("RANK", raising=False)
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    states = [torch.load(tmp_path / f"state{r}.pt", weights_only=False) for r in (0, 1)]
    if kind == "device":  # DeviceBatches' own state: one shard a rank
        assert [{k: s[k] for k in ("rank", "world_size", "worker", "num_workers", "pos")} for s in states] == [
            {"rank": r, "world_size": 2, "worker": 0, "num_workers": 1, "pos": 2} for r in (0, 1)]
        into = BouncingThings(fs.BouncingThingsConfig(width=32, height=24, num_frames=2, num_objects=(1, 2),
                                                      max_objects=2, motion="kinematic"), ["depth"], seed=3,
                              length=LENGTH)
        with pytest.raises(fs.ConfigError, match=r"rank 1 \(saved\) vs 0 \(here\), world_size 2 \(saved\) vs 1 "
                                                 r"\(here\)\. Resume with the ranks and workers"):
            into.load_state_dict(states[1])
        return
    workers = [_worker_states(s) for s in states]
    assert [[{k: w[k] for k in ("rank", "world_size", "worker", "num_workers")} for w in ws] for ws in workers] == [
        [{"rank": r, "world_size": 2, "worker": w, "num_workers": 2} for w in (0, 1)] for r in (0, 1)]
    fresh = ranks_program.stream(kind)
    with pytest.raises(fs.ConfigError, match=r"shard 3 of 4 \(rank 1 of 2, worker 1 of 2\) and cannot resume in "
                                             r"shard 0 of 1 \(rank 0 of 1, worker 0 of 1\): rank 1 \(saved\) vs 0 "
                                             r"\(here\), world_size 2 \(saved\) vs 1 \(here\), worker 1 \(saved\) vs "
                                             r"0 \(here\), num_workers 2 \(saved\) vs 1 \(here\)"):
        fresh.load_state_dict(workers[1][1])
    assert fresh.state_dict()["pos"] == 0  # a refused state moves nothing
    if kind == "bouncing":  # a BouncingThings worker's state, into DeviceBatches: another shard
        batches = DeviceBatches(fs.BouncingThingsConfig(width=32, height=32, num_frames=2, num_objects=(1, 2),
                                                        max_objects=2, motion="kinematic"), ["depth"], 2, seed=3,
                                length=LENGTH)
        with pytest.raises(fs.ConfigError, match=r"worker 1 \(saved\) vs 0 \(here\), num_workers 2 \(saved\) vs 1"):
            batches.load_state_dict(workers[0][1])


class Indices(IndexStream):
    """Sample i is {"index": i}: the index stream alone."""

    def __init__(self, length: int | None = None) -> None:
        self._init_stream(0, length, 0)

    def sample(self, i: int) -> dict:
        return {"index": i}


def _take(ds, n: int | None = None) -> list[int]:
    out = []
    for item in ds:
        out += torch.as_tensor(item["index"]).reshape(-1).tolist()
        if len(out) == n:
            break
    return out


def _rank(monkeypatch, rank: int | None, world: int = 2) -> None:
    if rank is None:
        monkeypatch.delenv("RANK", raising=False)
        monkeypatch.delenv("WORLD_SIZE", raising=False)
    else:
        monkeypatch.setenv("RANK", str(rank))
        monkeypatch.setenv("WORLD_SIZE", str(world))


def test_a_position_resumes_in_its_shard_only_and_an_epoch_start_anywhere(monkeypatch):
    """Rank 1 of 2 reads 1, 3, 5, 7 of an epoch of 8; its position after two reads is refused by rank 0 of 2 and by
    one process, and resumes on rank 1 (hand-written indices). An epoch read to its end (pos 0 of the next) re-shards
    exactly: ranks 0 and 1 of 2 read epoch 0, one process resumed from rank 0's state reads epoch 1, and the union
    is 0 .. 15, each once."""
    _rank(monkeypatch, 1)
    ds = Indices(length=8)
    assert _take(ds, 2) == [1, 3]
    state = ds.state_dict()
    assert state == {"epoch": 0, "pos": 2, "seed": 0, "start": 0, "rank": 1, "world_size": 2, "worker": 0,
                     "num_workers": 1}
    for rank, match in ((0, r"rank 1 \(saved\) vs 0 \(here\)\. "),
                        (None, r"rank 1 \(saved\) vs 0 \(here\), world_size 2 \(saved\) vs 1 \(here\)\. ")):
        _rank(monkeypatch, rank)
        other = Indices(length=8)
        with pytest.raises(fs.ConfigError, match=match):
            other.load_state_dict(state)
        assert _take(other) == list(range(0, 8, 2) if rank == 0 else range(8))  # refused: its own epoch 0
    _rank(monkeypatch, 1)
    resumed = Indices(length=8)
    resumed.load_state_dict(state)
    assert _take(resumed) == [5, 7]

    seen = []
    for rank in (0, 1):
        _rank(monkeypatch, rank)
        epoch0 = Indices(length=8)
        seen += _take(epoch0)
    end = epoch0.state_dict()
    assert (end["epoch"], end["pos"]) == (1, 0)
    _rank(monkeypatch, None)
    alone = Indices(length=8)
    alone.load_state_dict(end)
    seen += _take(alone)
    assert sorted(seen) == list(range(16))


def test_a_main_process_position_is_refused_by_the_workers_that_would_split_it(monkeypatch):
    """A position read in this process (shard 0 of 1), handed to a DataLoader of 2 worker processes: each worker
    would resume it in another shard (losing samples), so the first batch raises, naming the layouts."""
    _rank(monkeypatch, None)
    ds = Indices(length=8)
    assert _take(ds, 3) == [0, 1, 2]
    with pytest.raises(fs.ConfigError, match=r"worker 0 of 1\) and cannot resume in shard \d of 2 .*num_workers 1 "
                                             r"\(saved\) vs 2 \(here\)"):
        next(iter(DataLoader(ds, batch_size=None, num_workers=2, multiprocessing_context="fork")))


def test_a_stream_state_resumes_in_device_batches_on_the_same_rank(monkeypatch):
    """Rank 1 of 2 (``RANK``/``WORLD_SIZE``): BouncingThings and DeviceBatches read 1, 3, 5, ... of an epoch of 10,
    and BouncingThings' position after two samples resumes in DeviceBatches at 5, 7, 9 (hand-written), batch
    after batch; len() counts the rank's batches."""
    _rank(monkeypatch, 1)
    cfg = fs.BouncingThingsConfig(width=32, height=24, num_frames=2, num_objects=(1, 2), max_objects=2,
                                  motion="kinematic")
    ds = BouncingThings(cfg, ["depth"], seed=1, length=10)
    assert _take(ds, 2) == [1, 3]
    batches = DeviceBatches(cfg, ["depth"], 2, seed=1, length=10)
    assert len(batches) == 3
    batches.load_state_dict(ds.state_dict())
    assert [b["index"].tolist() for b in batches] == [[5, 7], [9]]
    assert [b["index"].tolist() for b in batches] == [[11, 13], [15, 17], [19]]  # epoch 1: rank 1's share


def test_a_bad_rank_in_the_environment_is_refused(monkeypatch):
    for rank, world in (("2", "2"), ("x", "2"), ("0", "0")):
        monkeypatch.setenv("RANK", rank)
        monkeypatch.setenv("WORLD_SIZE", world)
        with pytest.raises(fs.ConfigError, match=f"RANK='{rank}' and WORLD_SIZE='{world}' must be integers"):
            Indices(length=4)
