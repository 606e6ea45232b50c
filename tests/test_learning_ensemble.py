"""The RAFT judge's ``--ensemble``: ``runs.run`` and its ``--at-once`` path with every net of every
seed and arm trained at once in one process (``train_many``) write the results file of the nets trained one by one
(``train``): the same layout, the same curves, checkpoints and saved weights, and ``"trainer"`` saying which ran. And
the pools render through ``fs.datasets.loader`` (forkserver workers) into the pairs the fork DataLoader gave.

As in tests/test_ensemble.py (whose module docstring says why) the nets train in float64, so that two correct
implementations that sum in another order agree to its tolerances; the protocol shrinks to one 128x128 crop, two
updates and three steps, and ``evaluate`` is a function of the weights, so each checkpoint shows the weights it saw.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import _common
from flowsynth.train.nets import raft_small
from learning import pools, protocol, runs, trainers

WEIGHTS_ATOL, LOSS_RTOL = 1e-11, 1e-10  # tests/test_ensemble.py's, measured there in float64
H = W = 128
ENSEMBLE_ONLY = {"at_once", "step_s"}  # what train_many's results add to train's


@pytest.fixture
def float64(monkeypatch):
    """Default dtype float64, torchvision RAFT's coordinate grid in it, and one torch thread (as tests/test_ensemble.py
    runs)."""
    raft_small()  # installs the shim before torchvision's model module is imported
    import torchvision.models.optical_flow.raft as tv_raft

    grid = tv_raft.make_coords_grid
    monkeypatch.setattr(tv_raft, "make_coords_grid", lambda *a, **k: grid(*a, **k).to(torch.get_default_dtype()))
    old, threads = torch.get_default_dtype(), torch.get_num_threads()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)
    torch.set_num_threads(threads)


@pytest.fixture
def tiny(float64, monkeypatch, tmp_path):
    """The protocol at a test's size, its pools random (the curriculum's two blocks included), results and weights
    under ``tmp_path``."""
    import flowsynth as fs
    import flowsynth.train.steps

    monkeypatch.setattr(trainers, "BATCH", 1)
    monkeypatch.setattr(trainers, "CROP", (H, W))
    monkeypatch.setattr(trainers, "UPDATES", 2)
    crop = flowsynth.train.steps.augment
    monkeypatch.setattr(flowsynth.train.steps, "augment", lambda *a: tuple(x.double() for x in crop(*a)))
    monkeypatch.setattr(trainers, "evaluate", lambda net, tests, device: protocol.with_means({
        "stereo": float(sum(p.detach().sum() for p in net.parameters())),
        "mb_A": float(sum(p.detach().abs().sum() for p in net.parameters()))}))
    monkeypatch.setattr(runs, "judge_sets", lambda middlebury: {})
    monkeypatch.setattr(runs, "zero_flow", lambda tests: {"stereo": 17.0, "mb_A": 4.0, "middlebury": 4.0})

    def pool(seed):
        g = torch.Generator().manual_seed(seed)
        return (torch.randint(256, (4, 3, H + 8, W + 16), dtype=torch.uint8, generator=g),
                torch.randint(256, (4, 3, H + 8, W + 16), dtype=torch.uint8, generator=g),
                3 * torch.randn(4, 2, H + 8, W + 16, generator=g), torch.ones(4, 1, H + 8, W + 16, dtype=torch.bool))

    def build_arms(names, seed, workers, overrides, n, preset=None):
        arms = {a: pool(10 * seed + k) for k, a in enumerate(names)}
        return arms, {"mean_flow": {a: 3.0 for a in names}}, fs.BouncingThingsConfig()

    monkeypatch.setattr(runs, "build_arms", build_arms)
    monkeypatch.setattr(runs, "CACHE", tmp_path / "cache")
    monkeypatch.setattr(runs, "RESULTS_DIR", tmp_path)  # progress files
    monkeypatch.setattr(_common, "RESULTS_DIR", tmp_path)  # write_json
    return tmp_path


def _args(tag: str, **kw) -> argparse.Namespace:
    base = {"threads": 1, "steps": 3, "every": 2, "arms": "flowsynth,curriculum", "middlebury": None, "seeds": "0,1",
            "tag": tag, "pool": 4, "workers": 0, "overrides": {}, "at_once": False, "ensemble": False, "jobs": 0,
            "device": "cpu", "train_after": None, "precision": "fp32", "preset": None}
    return argparse.Namespace(**{**base, **kw})


def _keys(x, path=""):
    """Every key path of a JSON value (lists by their first entry)."""
    if isinstance(x, dict):
        return {k for key, v in x.items() for k in {f"{path}/{key}"} | _keys(v, f"{path}/{key}")}
    return _keys(x[0], path + "[]") if isinstance(x, list) and x and isinstance(x[0], (dict, list)) else set()


@pytest.mark.parametrize("at_once", [False, True])
def test_ensemble_run_writes_the_runs_of_nets_trained_one_by_one(tiny, at_once):
    runs.run(_args("one"))
    runs.run(_args("many", ensemble=True, at_once=at_once))
    one, many = (json.loads((tiny / f"learning_raft_{t}.json").read_text()) for t in ("one", "many"))
    assert (one["trainer"], many["trainer"]) == ("in turn", "ensemble")
    assert one["complete"] and many["complete"] and [r["seed"] for r in many["runs"]] == [0, 1]
    extra = {k for k in _keys(many) - _keys(one)}
    assert {k.rsplit("/", 1)[1] for k in extra} == ENSEMBLE_ONLY and _keys(one) <= _keys(many)
    for a, b in zip(one["runs"], many["runs"]):
        assert set(a["results"]) == set(b["results"]) == {"flowsynth", "curriculum"}
        for arm in a["results"]:
            ca, cb = a["results"][arm]["curve"], b["results"][arm]["curve"]
            assert [c["step"] for c in ca] == [c["step"] for c in cb] == [0, 2, 3]
            assert cb[0] == ca[0]  # the same initial nets
            for x, y in zip(ca[1:], cb[1:]):
                assert y["train_loss"] == pytest.approx(x["train_loss"], rel=LOSS_RTOL)
                for j in ("stereo", "mb_A", "middlebury"):
                    assert y[j] == pytest.approx(x[j], rel=1e-12)
            assert b["results"][arm]["at_once"] == (4 if at_once else 2)
            assert b["results"][arm]["net_seed"] == a["results"][arm]["net_seed"]
            for name in ("{}_{}_s{}.pt", "{}_{}_s{}_step2.pt", "{}_{}_s{}_step3.pt"):
                x, y = (torch.load(tiny / "cache" / name.format(t, arm, a["seed"])) for t in ("one", "many"))
                assert max(float((x[k] - y[k]).abs().max()) for k in x) < WEIGHTS_ATOL
            progress = json.loads((tiny / "learning_raft_progress" / f"many_{arm}_s{a['seed']}.json").read_text())
            assert progress["curve"] == cb
    # the arms and seeds trained on their own pools and draws: no two nets' curves alike
    assert len({r["results"][arm]["curve"][1]["train_loss"] for r in many["runs"] for arm in r["results"]}) == 4


def test_pool_through_the_forkserver_loader_is_the_fork_pool(monkeypatch):
    """``flowsynth_pool`` renders through ``fs.datasets.loader`` (forkserver workers): the same pairs, in the same
    order, as the fork DataLoader it used before."""
    from torch.utils.data import DataLoader

    import flowsynth as fs

    monkeypatch.setattr(pools, "RES", (48, 32))
    made = []

    def fork_loader(ds, batch_size, num_workers, **kwargs):
        made.append(kwargs)
        return DataLoader(ds, batch_size=batch_size, num_workers=num_workers, multiprocessing_context="fork")

    new, cfg = pools.flowsynth_pool(5, 3, 2)
    monkeypatch.setattr(fs.datasets, "loader", fork_loader)
    old, _ = pools.flowsynth_pool(5, 3, 2)
    assert made and (cfg.width, cfg.height) == (48, 32)
    for a, b in zip(new, old):
        assert a.dtype == b.dtype and torch.equal(a, b)
    assert new[0].shape == (5, 3, 32, 48) and bool(new[3].any())
