"""``python benchmarks/learning --diagnose-checkpoints`` (``learning.checkpoints``): the goal's logic
on hand-made numbers (a pass; a fail by one photograph at one checkpoint; a fail on one Middlebury pair; the 4-of-5
rule), the swing arithmetic, and a whole report from fake results files and tiny fake nets under tmp_path, with
checkpoints whose weights are missing. Nothing here loads a real photograph or trains a net."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import _common
from learning import checkpoints, cli
from learning.checkpoints import arm_goal, changes, net_goal, swing

PHOTOS = ("stereo", "Dimetrodon", "Grove2", "Urban2", "Venus")
STEPS = (400, 800, 1200, 1600, 2000, 2400)
# zero flow's EPE: Dimetrodon, Grove2 and Venus move under 4 px on average, Urban2 does not
ZERO = {"stereo": 17.0, "mb_Dimetrodon": 2.1, "mb_Grove2": 2.4, "mb_Urban2": 6.4, "mb_Venus": 3.0, "middlebury": 3.5}


def _curve(**worse) -> list:
    """A net's curve that beats zero flow on every pair at every checkpoint; ``worse``: {"mb_X": {step: EPE}}."""
    out = [{"step": 0, "train_loss": None, **{k: 2 * v for k, v in ZERO.items()}}]
    for s in STEPS:
        out.append({"step": s, "train_loss": 1.0, **{k: 0.5 * v for k, v in ZERO.items()}})
        for pair, at in worse.items():
            out[-1][pair] = at.get(s, out[-1][pair])
    return out


def _invented(worst: float = 0.6, at: tuple = (), early: float = 3.0) -> dict:
    """{step: {photograph: px}}: 0.6 px everywhere from step 1200 on, ``early`` before it; ``at`` = (step,
    photograph) where the net invents ``worst``."""
    out = {s: {p: 0.6 if s >= 1200 else early for p in PHOTOS} for s in STEPS}
    if at:
        out[at[0]][at[1]] = worst
    return out


def test_a_net_that_invents_little_and_beats_zero_flow_passes():
    goal = net_goal(_invented(), _curve(), ZERO, 2400)
    assert goal["pass"] is True and goal["fails"] == [] and goal["missing"] == []
    assert goal["small_motion_pairs"] == ["mb_Dimetrodon", "mb_Grove2", "mb_Venus"]  # Urban2 moves 6.4 px
    # before step 1200 a net may invent what it likes; on Urban2 (6.4 px of motion) it may lose to zero flow
    assert net_goal(_invented(early=9.0), _curve(mb_Urban2={2000: 9.0, 2400: 9.0}), ZERO, 2400)["pass"] is True


def test_one_photograph_at_one_checkpoint_fails_the_net():
    goal = net_goal(_invented(1.0, (1600, "Venus")), _curve(), ZERO, 2400)  # 1 px is not under 1 px
    assert goal["pass"] is False and goal["fails"] == ["step 1600: invents 1.00 px on Venus"]
    assert net_goal(_invented(0.99, (1200, "Venus")), _curve(), ZERO, 2400)["pass"] is True
    assert net_goal(_invented(float("nan"), (2400, "stereo")), _curve(), ZERO, 2400)["pass"] is False


def test_one_middlebury_pair_at_one_scored_checkpoint_fails_the_net():
    goal = net_goal(_invented(), _curve(mb_Venus={2400: 3.0}), ZERO, 2400)  # level with zero flow is not below it
    assert goal["pass"] is False and goal["fails"] == ["step 2400: mb_Venus 3.00 px, zero flow 3.00"]
    assert net_goal(_invented(), _curve(mb_Grove2={2000: 2.5}), ZERO, 2400)["pass"] is False
    assert net_goal(_invented(), _curve(mb_Grove2={1600: 9.0}), ZERO, 2400)["pass"] is True  # not a scored checkpoint


def test_missing_weights_leave_the_goal_unknown_unless_it_fails():
    invented = {**_invented(), 1600: None}
    goal = net_goal(invented, _curve(), ZERO, 2400)
    assert goal["pass"] is None and goal["missing"] == ["step 1600: weights"]
    assert net_goal({**invented, 400: None}, _curve(), ZERO, 2400)["missing"] == ["step 1600: weights"]
    assert net_goal(invented, _curve(mb_Venus={2000: 4.0}), ZERO, 2400)["pass"] is False  # fails whatever is missing
    # a quick run's checkpoints: the goal's steps are the run's share (from half its steps)
    quick = net_goal({10: {"stereo": 5.0}, 20: {"stereo": 0.5}}, _curve()[:1] + [{**_curve()[1], "step": s}
                                                                                  for s in (10, 20)], ZERO, 20)
    assert quick["pass"] is False and quick["fails"] == ["step 10: invents 5.00 px on stereo"]


def test_four_of_five_seeds():
    ok, bad, unknown = {"pass": True, "fails": []}, {"pass": False, "fails": ["x"]}, {"pass": None, "fails": []}
    assert arm_goal({0: ok, 1: ok, 2: ok, 3: ok, 4: bad}) == {"seeds": [0, 1, 2, 3, 4], "pass": [0, 1, 2, 3],
                                                              "fail": [4], "unknown": [], "met": True,
                                                              "fails": {4: ["x"]}}
    assert arm_goal({0: ok, 1: ok, 2: ok, 3: bad, 4: bad})["met"] is False
    assert arm_goal({0: ok, 1: ok, 2: ok, 3: unknown, 4: bad})["met"] is None  # seed 3 may yet pass
    assert arm_goal({0: ok, 1: ok, 2: ok, 3: bad})["met"] is None  # seed 4 has not run
    assert arm_goal({0: ok, 1: bad, 2: bad})["met"] is False
    assert arm_goal({0: ok, 1: ok, 2: ok, 3: ok})["met"] is True


def test_swing_is_the_largest_change_between_checkpoints():
    curve = [{"step": s, "mb_Venus": e} for s, e in zip((0, 400, 800, 1200, 1600, 2000, 2400),
                                                        (10.0, 4.0, 3.0, 2.5, 4.12, 1.64, 2.0))]
    assert changes(curve, "mb_Venus") == [(400, 4.0, -6.0), (800, 3.0, -1.0), (1200, 2.5, -0.5),
                                          (1600, 4.12, pytest.approx(1.62)), (2000, 1.64, pytest.approx(-2.48)),
                                          (2400, 2.0, pytest.approx(0.36))]
    assert swing(curve, "mb_Venus", 1200) == pytest.approx(2.48)  # 4.12 -> 1.64
    assert swing(curve, "mb_Venus", 2000) == pytest.approx(0.36)
    assert swing(curve, "mb_Venus", 2400) is None and swing(curve, "stereo", 0) is None


class Shift(torch.nn.Module):
    """A stand-in net: flow (``shift``, 0) everywhere, whatever the images (so the motion it invents is |shift|)."""

    def __init__(self):
        super().__init__()
        self.shift = torch.nn.Parameter(torch.zeros(()))

    def forward(self, img1, img2, num_flow_updates=12):
        flow = torch.zeros_like(img1[:, :2])
        flow[:, 0] = self.shift
        return [flow]


def test_report_from_fake_runs_and_nets(tmp_path, monkeypatch):
    """Two results files (one with a --set lever); weights kept at some checkpoints, missing at others (an old run
    kept only its final net); the rows, goals, JSON and picture."""
    import flowsynth.train.nets

    results, weights = tmp_path / "results", tmp_path / "weights"
    results.mkdir()
    weights.mkdir()
    monkeypatch.setattr(checkpoints, "RESULTS_DIR", results)
    monkeypatch.setattr(_common, "RESULTS_DIR", results)
    monkeypatch.setattr(flowsynth.train.nets, "raft_small", Shift)  # checkpoints imports it when it loads a net
    still = tuple(torch.zeros(1, c, 8, 12) for c in (3, 3, 2)) + (torch.ones(1, 1, 8, 12),)
    monkeypatch.setattr(checkpoints, "still_pairs", lambda middlebury: {p: still for p in PHOTOS})
    run = {"seed": 0, "zero_flow_epe": ZERO, "results": {"flowsynth": {"curve": _curve(mb_Venus={2000: 3.5})},
                                                         "mixture": {"curve": _curve()}}}
    (results / "learning_raft_l0.json").write_text(json.dumps({"net": "raft_small", "steps": 2400, "overrides": {},
                                                               "complete": True, "runs": [run]}))
    (results / "learning_raft_set.json").write_text(json.dumps({"net": "raft_small", "steps": 2400, "overrides": {
        "rest_fraction": 0.3}, "complete": False, "runs": [{**run, "results": {"flowsynth": {"curve": _curve()}}}]}))
    (results / "learning_raft_screens.json").write_text(json.dumps({"rows": []}))  # not a run: skipped
    for arm, tag, shift in (("flowsynth", "l0", 0.5), ("mixture", "l0", 0.7), ("flowsynth", "set", 0.2)):
        net = Shift()
        for s in STEPS:
            if tag == "set" and s != 2400:
                continue  # this run kept its final net only (as runs before issue 53 did)
            net.shift.data.fill_(-shift if s >= 1200 else 4.0)
            torch.save(net.state_dict(), weights / f"{tag}_{arm}_s0_step{s}.pt")
    cli.main(["--diagnose-checkpoints", "--files", "learning_raft_*.json", "--weights", str(weights), "--tag", "t"])
    out = json.loads((results / "learning_raft_diagnose_checkpoints_t.json").read_text())
    assert out["photographs"] == list(PHOTOS) and "4 of 5 seeds" in out["goal"]
    rows = {(r["arm"], r["step"]): r for r in out["rows"]}
    assert len(rows) == 3 * len(STEPS)
    r = rows["flowsynth", 1200]
    assert r["weights"] == "ok" and r["invented mean"] == pytest.approx(0.5) and r["still Venus"] == pytest.approx(0.5)
    assert rows["flowsynth", 800]["invented worst"] == pytest.approx(4.0)
    assert r["mb_Venus"] == 1.5 and r["change mb_Venus"] == pytest.approx(0.0)
    assert rows["flowsynth", 2000]["change mb_Venus"] == pytest.approx(2.0)  # 1.5 -> 3.5
    lever = rows["flowsynth rest_fraction=0.3", 1600]
    assert lever["weights"] == "missing" and lever["invented mean"] is None and "still Venus" not in lever
    assert rows["flowsynth rest_fraction=0.3", 2400]["invented mean"] == pytest.approx(0.2)
    nets = {n["arm"]: n for n in out["nets"]}
    assert nets["flowsynth"]["pass"] is False and nets["flowsynth"]["fails"] == [
        "step 2000: mb_Venus 3.50 px, zero flow 3.00"]
    assert nets["flowsynth"]["swing"]["mb_Venus"] == pytest.approx(2.0)
    assert nets["flowsynth"]["zero_flow"] == {k: v for k, v in ZERO.items() if k != "middlebury"}
    assert nets["mixture"]["pass"] is True
    assert nets["flowsynth rest_fraction=0.3"]["pass"] is None
    assert nets["flowsynth rest_fraction=0.3"]["missing"] == ["step 1200: weights", "step 1600: weights",
                                                              "step 2000: weights"]
    assert out["arms"]["mixture"] == {"seeds": [0], "pass": [0], "fail": [], "unknown": [], "met": None, "fails": {}}
    assert out["arms"]["flowsynth"]["met"] is None and out["arms"]["flowsynth"]["fail"] == [0]
    pytest.importorskip("matplotlib", reason="the picture needs the bench extra")
    assert (results / "learning_raft_diagnose_checkpoints_t.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # an arm's seed in two files is an error, as --summarize has it
    (results / "learning_raft_l0_again.json").write_text((results / "learning_raft_l0.json").read_text())
    with pytest.raises(SystemExit, match="seed 0's flowsynth is in"):
        checkpoints.diagnose_checkpoints("learning_raft_*.json", None, weights=weights)
