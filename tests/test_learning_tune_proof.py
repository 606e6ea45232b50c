"""Decision 0026's judge of ``flowsynth tune`` (benchmarks/learning): the ``tuned`` arm trains on the tune's preset
file rendered exactly as the tune rendered that point's own pool (the tune's in-memory sources, not the file, as the
oracle), and ``--tune-proof`` reads the goal, checked by hand from synthetic results files (numpy and scipy's t)."""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from learning import cli, pools, protocol, summary

from flowsynth.tune import RECIPE, preset, render_pool, sources

# a point of the search space that mixes in the 2D layers (both of a preset's sources)
KEY = "motion=small,objects=few,camera=moving,still=0,textures=procedural,layers=0.5"


def test_tuned_arm_is_the_tunes_own_pool_of_its_point(tmp_path):
    """The preset file (written at 512x384) read back at the judge's size gives the configs and weights the tune
    trained that point on (it trains at the judge's size), and the arm's pairs are the tune's pool of that point and
    seed, bit for bit; the results record the file's SHA-256 and contents."""
    assert tuple(RECIPE.res) == tuple(protocol.RES)
    path = preset(KEY).to_file(tmp_path / "tuned.json")
    configs, weights = pools.preset_sources(path)
    want_configs, want_weights = sources(KEY, protocol.RES)
    assert {k: c.to_dict() for k, c in configs.items()} == {k: c.to_dict() for k, c in want_configs.items()}
    assert weights == want_weights and set(configs) == {"things", "layers"}
    s = pools.SeedPools(3, 2, 0, {}, (), {}, preset=str(path))
    got = pools.tuned(s)
    want = render_pool((want_configs, want_weights), 2, 3)
    assert len(got) == 4 and all(torch.equal(a, b) for a, b in zip(got, want))
    assert got[0].shape == (3, 3, protocol.RES[1], protocol.RES[0]) and got[0].dtype == torch.uint8
    assert s.info["preset"] == {"file": "tuned.json", "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
                                "preset": json.loads(path.read_text())}


def test_tuned_arm_without_a_preset_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["--arms", "flowsynth,tuned", "--quick"])
    assert e.value.code == 2 and "--preset FILE" in capsys.readouterr().err


PAIRS = ("Dimetrodon", "Grove2", "Urban2", "Venus")


def _write(path, arm, seed, epe: dict):
    """A complete run of one seed and one arm whose checkpoints at 2000 and 2400 both score ``epe`` ({judge: EPE},
    the per-pair judges and "stereo"), untrained 9.0 everywhere, zero flow 5.0 on every pair and 17.0 on Motorcycle."""
    keys = ["stereo", *(f"mb_{p}" for p in PAIRS)]
    curve = [{"step": 0, **{k: 9.0 for k in keys}}] + [{"step": s, **{k: epe[k] for k in keys}} for s in (2000, 2400)]
    zero = {"stereo": 17.0, **{f"mb_{p}": 5.0 for p in PAIRS}}
    path.write_text(json.dumps({"complete": True, "net": protocol.NET, "steps": 2400, "overrides": {}, "runs": [
        {"seed": seed, "zero_flow_epe": zero, "results": {arm: {"curve": curve}}}]}))


def _runs(tmp_path, held_ratios, seeds=(0, 1, 2, 3, 4)):
    """The default scores Urban2 2.0 and Venus 4.0 (held-out score 3.0), Dimetrodon 1.0 and Grove2 3.0 (2.0),
    Motorcycle 3.0; the tuned net of seed k scores held_ratios[k] x the default's held-out pairs, 0.5 x its tuned-on
    pairs and 1.1 x its Motorcycle."""
    ref = {"stereo": 3.0, "mb_Dimetrodon": 1.0, "mb_Grove2": 3.0, "mb_Urban2": 2.0, "mb_Venus": 4.0}
    for k in seeds:
        r = held_ratios[k]
        tuned = {"stereo": 3.3, "mb_Dimetrodon": 0.5, "mb_Grove2": 1.5, "mb_Urban2": 2.0 * r, "mb_Venus": 4.0 * r}
        _write(tmp_path / f"learning_raft_s{k}.json", "flowsynth", k, ref)
        _write(tmp_path / f"learning_raft_tuned{k}.json", "tuned", k, tuned)


def _by_hand(ratios):
    logs = np.log(ratios)
    half = stats.t.ppf(0.975, len(logs) - 1) * logs.std(ddof=1) / np.sqrt(len(logs))
    return np.exp(logs.mean()), np.exp(logs.mean() - half), np.exp(logs.mean() + half)


@pytest.mark.parametrize("ratios,met", [((0.8, 0.85, 0.82, 0.78, 0.84), True),  # at most 0.9, upper end below 1
                                        ((0.6, 0.7, 0.95, 0.8, 1.3), False),  # mean 0.83, but the upper end above 1
                                        ((0.92, 0.91, 0.93, 0.9, 0.94), False)])  # tight, but the mean above 0.9
def test_tune_proof_reads_0026s_goal(tmp_path, monkeypatch, ratios, met):
    monkeypatch.setattr(summary, "RESULTS_DIR", tmp_path)
    _runs(tmp_path, ratios)
    out = summary.tune_proof("learning_raft_*.json")
    h = out["judges"]["held_out"]
    gm, lo, hi = _by_hand(ratios)
    assert h["seeds"] == [0, 1, 2, 3, 4] and h["ratios"] == pytest.approx(list(ratios))
    assert h["geometric_mean"] == pytest.approx(gm) and h["ci95"] == [pytest.approx(lo), pytest.approx(hi)]
    assert bool(gm <= 0.9 and hi < 1) is met and out["goal_met"] is met
    assert h["tuned"] == pytest.approx([3.0 * r for r in ratios]) and h["flowsynth"] == pytest.approx([3.0] * 5)
    assert h["zero_flow"] == pytest.approx(5.0) and h["untrained"] == pytest.approx(9.0)
    assert out["judges"]["tuned_on"]["ratios"] == pytest.approx([0.5] * 5)
    assert out["judges"]["stereo"]["ratios"] == pytest.approx([1.1] * 5)
    assert out["held_out"] == ["Urban2", "Venus"] and out["tuned_on"] == ["Dimetrodon", "Grove2"]


def test_tune_proof_is_not_read_on_other_seeds(tmp_path, monkeypatch):
    """Four seeds, or seeds 1-5, are not decision 0026's five: the numbers come out, the verdict does not; pairs no
    run was judged on are an error."""
    monkeypatch.setattr(summary, "RESULTS_DIR", tmp_path)
    _runs(tmp_path, {k: 0.5 for k in range(6)}, seeds=(0, 1, 2, 3))
    out = summary.tune_proof("learning_raft_*.json")
    assert out["judges"]["held_out"]["seeds"] == [0, 1, 2, 3] and out["goal_met"] is None
    _runs(tmp_path, {k: 0.5 for k in range(6)}, seeds=(4, 5))
    (tmp_path / "learning_raft_s0.json").unlink()
    assert summary.tune_proof("learning_raft_*.json")["goal_met"] is None
    with pytest.raises(SystemExit, match="judged on Art"):
        summary.tune_proof("learning_raft_*.json", held_out=("Art",))



def test_tune_proof_picture_is_written(tmp_path, monkeypatch):
    """With matplotlib (the bench extra) the reading's picture is a PNG under results/; without it, none."""
    import _common

    monkeypatch.setattr(summary, "RESULTS_DIR", tmp_path)
    monkeypatch.setattr(_common, "RESULTS_DIR", tmp_path)
    _runs(tmp_path, (0.8, 0.85, 0.82, 0.78, 0.84))
    path = summary.plot_summary(summary.tune_proof("learning_raft_*.json"), "learning_raft_tune_proof")
    if _common.pyplot() is None:
        assert path is None
    else:
        assert Path(path).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
