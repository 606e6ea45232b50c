"""The RAFT judge's pools and trainers (benchmarks/learning/pools.py, trainers.py) and its readings
(summary.py). Its small-motion diagnostic (``learning.sets.small_motion_pair``): exact affine flow between a
photograph and its moved copy, checked against brightness constancy on a smooth analytic image and against the
affine field's own algebra."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from learning import pools, protocol, sets, summary, trainers
from learning.sets import small_motion_pair, small_motion_pairs


def _smooth(xs, ys):
    """A smooth analytic colour image at the points (xs, ys): (..., 3)."""
    return np.stack([0.5 + 0.25 * np.sin(0.055 * xs + 0.035 * ys + p) + 0.2 * np.cos(0.045 * ys - 0.025 * xs + 2 * p)
                     for p in (0.0, 1.0, 2.0)], -1)


def _smooth_image(w=96, h=72):
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    return _smooth(xs, ys).astype(np.float32)


def _sample(img, x, y):
    return np.stack([map_coordinates(img[..., c].astype(np.float64), [y, x], order=1) for c in range(3)], -1)


def test_still_pair_is_the_photograph_twice_with_zero_flow():
    img = _smooth_image()
    img1, img2, flow, valid = small_motion_pair(img, 3, 0.0)
    assert np.array_equal(img1.numpy(), img2.numpy())
    assert not flow.any() and bool(valid.all())


@pytest.mark.parametrize("magnitude,seed", [(1.0, 0), (3.0, 1), (3.0, 7), (6.0, 3)])
def test_moved_pair_obeys_brightness_constancy_along_its_flow(magnitude, seed):
    img = _smooth_image()
    h, w = img.shape[:2]
    _, img2, flow, valid = small_motion_pair(img, seed, magnitude)
    f = flow[0].numpy().astype(np.float64)  # (2, h, w)
    v = valid[0, 0].numpy() > 0.5
    mag = np.hypot(f[0], f[1])
    assert mag.max() == pytest.approx(magnitude, rel=1e-5)
    # an affine field: every second difference vanishes
    for comp in f:
        assert np.abs(np.diff(comp, 2, axis=0)).max() < 1e-4 and np.abs(np.diff(comp, 2, axis=1)).max() < 1e-4
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    tx, ty = xs + f[0], ys + f[1]
    assert np.array_equal(v, (tx >= 0) & (tx <= w - 1) & (ty >= 0) & (ty <= h - 1))
    frame2 = img2[0].permute(1, 2, 0).numpy()
    # frame 2's pixels whose source lies outside frame 1 are filled by reflection: keep both frames' 1 px borders out
    v &= (tx >= 1) & (tx <= w - 2) & (ty >= 1) & (ty <= h - 2) & (xs >= 1) & (xs <= w - 2) & (ys >= 1) & (ys <= h - 2)
    along = np.abs(_sample(frame2, tx[v], ty[v]) - img[v]).max()
    against = np.abs(_sample(frame2, (xs - f[0])[v], (ys - f[1])[v]) - img[v]).mean()
    # two bilinear resamplings (each at most |f''| / 8 per axis, about 4e-4 here) and cv2.remap's 1/32 px grid
    assert along < 1e-3
    assert against > 10 * along  # the check can fail: the reversed flow does not match
    # frame 2 at y is the image at the exact inverse x = (I + A)^-1 (y - t) of the flow's own affine fit
    # flow(x) = t + A x (a first-order inverse, x = y - flow(y), misses by up to |A flow| ~ 0.2 px here)
    design = np.stack([np.ones(h * w), xs.ravel(), ys.ravel()], 1)
    coef = np.linalg.lstsq(design, f.reshape(2, -1).T, rcond=None)[0]  # (3, 2): t, then A's columns
    t, A = coef[0], coef[1:].T
    src = np.linalg.solve(np.eye(2) + A, np.stack([xs.ravel(), ys.ravel()]) - t[:, None]).reshape(2, h, w)
    inside = (src[0] >= 1) & (src[0] <= w - 2) & (src[1] >= 1) & (src[1] <= h - 2)
    assert np.abs(frame2[inside] - _smooth(src[0], src[1])[inside]).max() < 1e-3  # one bilinear resampling


def test_small_motion_pairs_cover_every_photograph_and_magnitude(monkeypatch):
    img = _smooth_image(160, 128)
    import torch

    t = torch.from_numpy(img).permute(2, 0, 1)[None]
    # Motorcycle stands in: the test needs neither scikit-image's data nor the bench extra
    stereo = torch.from_numpy(_smooth_image(185, 125)).permute(2, 0, 1)[None]

    def motorcycle(factor):
        assert factor == 2  # the diagnostic moves Motorcycle at half resolution, as the judge reads it
        return stereo, stereo

    monkeypatch.setattr(sets, "motorcycle_full", motorcycle)
    pairs = small_motion_pairs({"mb_Fake": (t, t, torch.zeros(1, 2, 128, 160), torch.ones(1, 1, 128, 160))},
                               magnitudes=(0.0, 2.0))
    assert set(pairs) == {"sm_stereo_0", "sm_stereo_2", "sm_Fake_0", "sm_Fake_2"}
    peak = torch.linalg.vector_norm(pairs["sm_Fake_2"][2], dim=1).max()
    assert float(peak) == pytest.approx(2.0, rel=1e-5)
    assert pairs["sm_stereo_0"][0].shape == (1, 3, 125, 185)
    assert torch.equal(pairs["sm_stereo_0"][0], stereo)


def test_mixture_and_final_pass_arms(monkeypatch):
    """``mixture`` is half the flowsynth pool and half the chairs2d pool; ``flowsynth_final`` has the flowsynth pool's
    truth (the same samples) under other images."""
    import torch


    arms, info, _ = pools.build_arms(["flowsynth", "mixture", "flowsynth_final", "chairs2d"], 0, 0, {}, n=4)
    fs, mix, fin, chairs = (arms[k] for k in ("flowsynth", "mixture", "flowsynth_final", "chairs2d"))
    for a, f, c in zip(mix, fs, chairs):
        assert torch.equal(a[:2], f[:2]) and torch.equal(a[2:], c[:2])
    assert torch.equal(fin[2], fs[2]) and torch.equal(fin[3], fs[3])
    assert not torch.equal(fin[0], fs[0])
    assert set(info["mean_flow"]) == {"flowsynth", "mixture", "flowsynth_final", "chairs2d"}


def test_curriculum_feeds_each_block_its_share_of_steps(monkeypatch):
    """``stages``: block k of the pool feeds the k-th share of the steps; with one stage the batches are the
    generator's plain draws over the whole pool, as before stages existed. The pool's images carry their index."""
    import torch

    import flowsynth.train.ensemble
    import flowsynth.train.steps

    seen = []

    def augment(i1, i2, f, v, crop, g):
        seen.append(i1[:, 0, 0, 0].tolist())
        return i1, i2, f, v

    monkeypatch.setattr(trainers, "evaluate", lambda net, tests, device: {})
    monkeypatch.setattr(flowsynth.train.steps, "augment", augment)
    monkeypatch.setattr(flowsynth.train.ensemble, "step_loss", lambda net, batch, opt, sched, *a, **k: torch.zeros(()))
    pool = (torch.arange(8, dtype=torch.uint8)[:, None, None, None].expand(8, 3, 4, 4), torch.zeros(8, 3, 4, 4),
            torch.zeros(8, 2, 4, 4), torch.ones(8, 1, 4, 4, dtype=torch.bool))
    trainers.train(pool, {}, 10, 3, 3, 5, stages=2)
    assert all(0 <= i < 4 for b in seen[:5] for i in b) and all(4 <= i < 8 for b in seen[5:] for i in b)
    assert len(seen) == 10 and len({i for b in seen for i in b}) > 4
    seen.clear()
    trainers.train(pool, {}, 10, 3, 3, 5)
    g = torch.Generator().manual_seed(3)
    assert seen == [torch.randint(8, (protocol.BATCH,), generator=g).tolist() for _ in range(10)]
    arms, _, _ = pools.build_arms(["curriculum", "chairs2d", "flowsynth"], 0, 0, {}, n=4)
    assert protocol.STAGES["curriculum"] == 2
    assert all(torch.equal(c, torch.cat([a, f])) for c, a, f in zip(arms["curriculum"], arms["chairs2d"],
                                                                      arms["flowsynth"]))


def test_train_keeps_every_checkpoints_weights(tmp_path, monkeypatch):
    """``save``: each tested checkpoint's weights go beside the final ones, as they were at that step (a stand-in
    step adds 1 to one weight, so checkpoint s holds the initial weight + s)."""
    import torch

    import flowsynth.train.ensemble
    import flowsynth.train.steps
    from flowsynth.train.nets import raft_small

    def step(net, batch, opt, sched, *args, **kwargs):
        next(net.parameters()).data.add_(1.0)
        return torch.zeros(())

    monkeypatch.setattr(trainers, "evaluate", lambda net, tests, device: {})
    monkeypatch.setattr(flowsynth.train.steps, "augment", lambda i1, i2, f, v, crop, g: (i1, i2, f, v))
    monkeypatch.setattr(flowsynth.train.ensemble, "step_loss", step)
    pool = tuple(torch.zeros(4, c, 4, 4) for c in (3, 3, 2, 1))
    torch.manual_seed(7)
    first = next(raft_small().parameters()).detach().clone()
    save = str(tmp_path / "net.pt")
    trainers.train(pool, {}, 10, 3, 7, 4, save=save)
    name = next(iter(torch.load(save)))
    for s in (4, 8, 10):
        weights = torch.load(protocol.checkpoint_path(save, s))
        assert torch.allclose(weights[name], first + s, rtol=0, atol=1e-5)
    assert torch.equal(torch.load(save)[name], weights[name])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["net.pt", "net_step10.pt", "net_step4.pt", "net_step8.pt"]


def _result(path, overrides, arms, seed=0):
    import json

    curve = {a: [{"step": 0, "stereo": 19.0, "middlebury": 10.0}] + [{"step": s, "stereo": m, "middlebury": b}
                                                                      for s, (m, b) in zip((2000, 2400), v)]
             for a, v in arms.items()}
    path.write_text(json.dumps({"overrides": overrides, "complete": True, "net": "raft_small", "steps": 2400, "runs": [
        {"seed": seed, "zero_flow_epe": {"stereo": 17.0, "middlebury": 4.0},
         "results": {a: {"curve": c} for a, c in curve.items()}}]}))


def test_summarize_pairs_one_seeds_arms_across_files(tmp_path, monkeypatch):
    """A seed's default and lever may come from two runs; the ratios, their geometric mean and its t interval are
    checked by hand; a --set run's flowsynth arm is not the default, and an arm twice on one seed is an error."""
    import json


    monkeypatch.setattr(summary, "RESULTS_DIR", tmp_path)
    # scores (mean of the last two checkpoints): default 3.0 / 2.0 on seeds 0 and 1; the lever 1.5 / 1.0 on seed 0
    # (ratios 0.5) and 3.0 / 4.0 on seed 1 (ratios 1.0 / 2.0)
    _result(tmp_path / "learning_raft_s0.json", {}, {"flowsynth": [(3.0, 2.0), (3.0, 2.0)]})
    _result(tmp_path / "learning_raft_s0_lever.json", {}, {"flowsynth_photos": [(1.5, 1.0), (1.5, 1.0)]})
    _result(tmp_path / "learning_raft_s0_set.json", {"rest_fraction": 0.3}, {"flowsynth": [(9.0, 9.0), (9.0, 9.0)]})
    out = summary.summarize("learning_raft_s*.json", "flowsynth_photos", "flowsynth")
    mb = out["judges"]["middlebury"]
    assert out["judges"]["stereo"]["ratios"] == [pytest.approx(0.5)]
    assert mb["seeds"] == [0] and mb["ratios"] == [pytest.approx(0.5)] and mb["ci95"] is None
    assert mb["useful"] == 1  # 1.0 is below zero flow's 4.0 and the untrained 10.0
    _result(tmp_path / "learning_raft_s1.json", {}, {"flowsynth": [(3.0, 2.0), (3.0, 2.0)],
                                                     "flowsynth_photos": [(3.0, 4.0), (3.0, 4.0)]}, seed=1)
    mb = summary.summarize("learning_raft_s*.json", "flowsynth_photos", "flowsynth")["judges"]["middlebury"]
    assert dict(zip(mb["seeds"], mb["ratios"])) == {0: pytest.approx(0.5), 1: pytest.approx(2.0)}
    assert mb["geometric_mean"] == pytest.approx(1.0) and mb["in_favour"] == 1
    half = 12.706205 * np.log(4.0) / np.sqrt(2) / np.sqrt(2)  # t(0.975, 1) * sd of (log 0.5, log 2) / sqrt(2)
    assert mb["ci95"] == [pytest.approx(np.exp(-half)), pytest.approx(np.exp(half))]
    _result(tmp_path / "learning_raft_s1_again.json", {}, {"flowsynth_photos": [(1.0, 1.0), (1.0, 1.0)]}, seed=1)
    with pytest.raises(SystemExit, match="is in"):
        summary.summarize("learning_raft_s*.json", "flowsynth_photos", "flowsynth")
    (tmp_path / "learning_raft_s1_again.json").unlink()
    # a lever judged on other pairs (another --middlebury: zero flow differs) does not pair with the default
    lever = tmp_path / "learning_raft_s0_lever.json"
    d = json.loads(lever.read_text())
    d["runs"][0]["zero_flow_epe"]["middlebury"] = 3.0
    lever.write_text(json.dumps(d))
    with pytest.raises(SystemExit, match="judges"):
        summary.summarize("learning_raft_s*.json", "flowsynth_photos", "flowsynth")
    d["runs"][0]["zero_flow_epe"]["middlebury"] = 4.0 * (1 + 1e-7)  # float32 sums in another order: the same judge
    d["runs"][0]["results"]["flowsynth_photos"]["curve"][-1]["middlebury"] = float("nan")  # a diverged net
    lever.write_text(json.dumps(d))
    with pytest.raises(SystemExit, match=r"not finite on seeds \[0\]"):
        summary.summarize("learning_raft_s*.json", "flowsynth_photos", "flowsynth")
    lever.write_text(json.dumps({**d, "flowsynth_config": {"num_objects": [1, 2]}}))  # another library's default
    with pytest.raises(SystemExit, match="flowsynth_config"):
        summary.summarize("learning_raft_s*.json", "flowsynth_photos", "flowsynth")
    with pytest.raises(SystemExit, match="holds both"):
        summary.summarize("learning_raft_s0*.json", "control", "flowsynth")


def test_screen_applies_rule_4_against_the_control(tmp_path, monkeypatch):
    import json


    monkeypatch.setattr(summary, "RESULTS_DIR", tmp_path)
    # scores are the mean of the last two checkpoints: default 3.0 / 2.0, control 3.3 / 2.1 (bands 0.909-1.1,
    # 0.952-1.05)
    _result(tmp_path / "learning_raft_s0.json", {}, {"flowsynth": [(2.9, 2.1), (3.1, 1.9)],
                                                     "chairs2d_photos": [(1.0, 1.0), (1.0, 1.0)]})
    _result(tmp_path / "learning_raft_s0_control.json", {}, {"control": [(3.3, 2.1), (3.3, 2.1)]})
    _result(tmp_path / "learning_raft_s0_a.json", {"rest_fraction": 0.3}, {"flowsynth": [(3.0, 1.6), (3.0, 1.6)]})
    _result(tmp_path / "learning_raft_s0_b.json", {}, {"flowsynth_natural": [(3.0, 1.8), (3.0, 1.8)]})
    _result(tmp_path / "learning_raft_s0_c.json", {}, {"mixture": [(3.5, 1.6), (3.5, 1.6)]})
    rows = {r["lever"]: r for r in summary.screen("learning_raft_s0*.json")}
    assert set(rows) == {"rest_fraction=0.3", "flowsynth_natural", "mixture"}  # not the baseline, default, control
    a, b, c = rows["rest_fraction=0.3"], rows["flowsynth_natural"], rows["mixture"]
    assert a["Middlebury"] == pytest.approx(0.8) and a["Middlebury vs noise"] == "better"
    assert a["Motorcycle vs noise"] == "noise"
    assert a["promising (rule 4)"]
    assert b["Middlebury"] == pytest.approx(0.9) and b["Middlebury vs noise"] == "better"
    assert not b["promising (rule 4)"]
    assert c["Motorcycle"] == pytest.approx(3.5 / 3.0) and c["Motorcycle vs noise"] == "worse"
    assert not c["promising (rule 4)"]
    # a noisier control (scores 4.0 / 2.5: bands 0.75-1.33, 0.8-1.25) leaves the 0.8 on Middlebury inside the noise
    _result(tmp_path / "learning_raft_s0_control.json", {}, {"control": [(4.0, 2.5), (4.0, 2.5)]})
    rows = {r["lever"]: r for r in summary.screen("learning_raft_s0*.json")}
    a = rows["rest_fraction=0.3"]
    assert a["Middlebury vs noise"] == "noise" and not a["promising (rule 4)"]
    # a second default, an unfinished run and another protocol
    _result(tmp_path / "learning_raft_s0_again.json", {}, {"flowsynth": [(3.0, 2.0), (3.0, 2.0)]})
    with pytest.raises(SystemExit, match="is in"):
        summary.screen("learning_raft_s0*.json")
    (tmp_path / "learning_raft_s0_again.json").unlink()
    _result(tmp_path / "learning_raft_s0_d.json", {}, {"flowsynth_final": [(1.0, 1.0), (1.0, 1.0)]})
    d = json.loads((tmp_path / "learning_raft_s0_d.json").read_text())
    (tmp_path / "learning_raft_s0_d.json").write_text(json.dumps({**d, "complete": False}))
    assert "flowsynth_final" not in {r["lever"] for r in summary.screen("learning_raft_s0*.json")}
    (tmp_path / "learning_raft_s0_d.json").write_text(json.dumps({**d, "steps": 20}))
    with pytest.raises(SystemExit, match="another protocol"):
        summary.screen("learning_raft_s0*.json")
    (tmp_path / "learning_raft_s0_d.json").unlink()
    (tmp_path / "learning_raft_s0_control.json").unlink()
    with pytest.raises(SystemExit, match="control"):
        summary.screen("learning_raft_s0*.json")


def test_plot_summary_draws_seeds_and_interval(tmp_path, monkeypatch):
    """``--summarize``'s picture: a PNG with matplotlib (the bench extra), None without it; one seed (no interval)
    draws too."""
    import _common

    monkeypatch.setattr(_common, "RESULTS_DIR", tmp_path)  # where write_json and the figures go
    judge = {"seeds": [0, 1], "ratios": [0.5, 2.0], "geometric_mean": 1.0, "ci95": [0.0002, 6000.0]}
    out = {"arm": "a", "against": "b", "judges": {"stereo": judge, "middlebury": {**judge, "seeds": [0],
                                                                                 "ratios": [0.7], "ci95": None}}}
    try:
        import matplotlib  # noqa: F401
    except ModuleNotFoundError:
        assert summary.plot_summary(out, "summary") is None
        return
    path = summary.plot_summary(out, "summary")
    assert path == tmp_path / "summary.png" and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_bf16_run_is_not_pooled_with_protocol_0023(tmp_path, monkeypatch):
    """A results file trained in bf16 (protocol 0025) is skipped by the 0023 readings: the same seed's arm in it does
    not collide with the float32 one ("is in"), and it does not move the ratios."""
    import json

    monkeypatch.setattr(summary, "RESULTS_DIR", tmp_path)
    _result(tmp_path / "learning_raft_s0.json", {}, {"flowsynth": [(3.0, 2.0), (3.0, 2.0)],
                                                     "chairs2d_photos": [(6.0, 4.0), (6.0, 4.0)]})
    before = summary.summarize("learning_raft_*.json", "flowsynth", "chairs2d_photos")["judges"]
    h0 = tmp_path / "learning_raft_h0.json"
    _result(h0, {}, {"flowsynth": [(1.0, 1.0), (1.0, 1.0)]})
    with pytest.raises(SystemExit, match="is in"):  # as float32, the second default of seed 0 is an error
        summary.summarize("learning_raft_*.json", "flowsynth", "chairs2d_photos")
    h0.write_text(json.dumps({**json.loads(h0.read_text()), "precision": "bf16"}))
    after = summary.summarize("learning_raft_*.json", "flowsynth", "chairs2d_photos")["judges"]
    assert after == before and before["middlebury"]["ratios"] == [pytest.approx(0.5)]


def test_train_in_bf16_steps_under_autocast():
    """``precision="bf16"``: the first step's loss is the float32 step's to bf16's rounding, and not the same number
    (the step really ran in bf16); the float32 default is unchanged by the argument's existence."""
    import torch

    g = torch.Generator().manual_seed(0)
    h, w = protocol.CROP
    pool = (torch.randint(256, (8, 3, h, w), dtype=torch.uint8, generator=g),
            torch.randint(256, (8, 3, h, w), dtype=torch.uint8, generator=g),
            torch.randn(8, 2, h, w, generator=g) * 3, torch.ones(8, 1, h, w, dtype=torch.bool))
    losses = {p: trainers.train(pool, {}, 1, 0, 0, 1, threads=1, precision=p)["curve"][1]["train_loss"]
              for p in ("fp32", "bf16")}
    default = trainers.train(pool, {}, 1, 0, 0, 1, threads=1)["curve"][1]["train_loss"]
    assert default == losses["fp32"]
    assert losses["bf16"] != losses["fp32"]
    assert losses["bf16"] == pytest.approx(losses["fp32"], rel=2e-2)


def test_equivalence_reads_protocol_0025s_rule(tmp_path, monkeypatch):
    """The three conditions of 0025 on hand-made scores: ratios, their geometric mean, the band from seed 0's
    control, and the direction of default / baseline; a missing net is an error."""
    import json

    monkeypatch.setattr(summary, "RESULTS_DIR", tmp_path)
    _result(tmp_path / "learning_raft_s0.json", {}, {"flowsynth": [(3.0, 2.0), (3.0, 2.0)],
                                                     "chairs2d_photos": [(6.0, 4.0), (6.0, 4.0)],
                                                     "control": [(3.3, 2.2), (3.3, 2.2)]})
    _result(tmp_path / "learning_raft_s1.json", {}, {"flowsynth": [(3.0, 2.0), (3.0, 2.0)],
                                                     "chairs2d_photos": [(6.0, 4.0), (6.0, 4.0)]}, seed=1)
    with pytest.raises(SystemExit, match="lacks bf16 seed 0 flowsynth"):
        summary.equivalence("learning_raft_*.json")

    def bf16(name, arms, seed):
        _result(tmp_path / name, {}, arms, seed)
        d = json.loads((tmp_path / name).read_text())
        (tmp_path / name).write_text(json.dumps({**d, "precision": "bf16"}))

    bf16("learning_raft_h0.json", {"flowsynth": [(3.06, 2.1), (3.06, 2.1)],
                                   "chairs2d_photos": [(6.0, 4.0), (6.0, 4.0)]}, 0)
    bf16("learning_raft_h1.json", {"flowsynth": [(2.94, 1.9), (2.94, 1.9)],
                                   "chairs2d_photos": [(6.0, 4.0), (6.0, 4.0)]}, 1)
    out = summary.equivalence("learning_raft_*.json")
    mb = out["middlebury"]
    assert mb["ratios"] == {"flowsynth s0": pytest.approx(1.05), "chairs2d_photos s0": pytest.approx(1.0),
                            "flowsynth s1": pytest.approx(0.95), "chairs2d_photos s1": pytest.approx(1.0)}
    assert mb["geometric_mean"] == pytest.approx((1.05 * 0.95) ** 0.25)
    assert mb["single_band"] == [pytest.approx(1.1 ** -2.5), pytest.approx(1.1 ** 2.5)]  # c = 2.2 / 2.0
    assert out["equivalent"] and all(mb["held"].values())
    # the baseline of seed 1 scores 1.5 in bf16: default / baseline flips above 1, and its ratio leaves the band
    bf16("learning_raft_h1.json", {"flowsynth": [(2.94, 1.9), (2.94, 1.9)],
                                   "chairs2d_photos": [(6.0, 1.5), (6.0, 1.5)]}, 1)
    out = summary.equivalence("learning_raft_*.json")
    assert not out["equivalent"] and all(out["stereo"]["held"].values())
    assert out["middlebury"]["held"] == {"1 geometric mean": False, "2 every ratio": False, "3 same direction": False}


def test_a_config_stating_flow_px_at_512_pairs_with_one_in_pixels(tmp_path, monkeypatch):
    """A run recorded after decision 0029 (flow_px (2, 48) at flow_px_width 512, width 256) pools with one recorded
    before it (flow_px (1, 24) in its own pixels); one of another motion does not."""
    import json

    monkeypatch.setattr(summary, "RESULTS_DIR", tmp_path)
    old = {"width": 256, "flow_px": [1.0, 24.0]}
    _result(tmp_path / "learning_raft_s0.json", {}, {"flowsynth": [(3.0, 2.0), (3.0, 2.0)]})
    _result(tmp_path / "learning_raft_s0_lever.json", {}, {"flowsynth_photos": [(1.5, 1.0), (1.5, 1.0)]})
    for name, cfg in (("learning_raft_s0.json", old),
                      ("learning_raft_s0_lever.json", {"width": 256, "flow_px": [2.0, 48.0], "flow_px_width": 512})):
        d = json.loads((tmp_path / name).read_text())
        (tmp_path / name).write_text(json.dumps({**d, "flowsynth_config": cfg}))
    out = summary.summarize("learning_raft_s0*.json", "flowsynth_photos", "flowsynth")
    assert out["judges"]["middlebury"]["ratios"] == [pytest.approx(0.5)]
    d = json.loads((tmp_path / "learning_raft_s0_lever.json").read_text())
    d["flowsynth_config"]["flow_px"] = [4.0, 48.0]
    (tmp_path / "learning_raft_s0_lever.json").write_text(json.dumps(d))
    with pytest.raises(SystemExit, match="flowsynth_config"):
        summary.summarize("learning_raft_s0*.json", "flowsynth_photos", "flowsynth")
