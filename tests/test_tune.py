"""flowsynth.tune's search space, plan, successive halving and report, with stand-in trainers whose scores are known
(training real nets would be too slow to test the search's logic): the rank a brute-force sort gives, the judge's
score rule, resume after an interruption at any point."""

import io
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import flowsynth as fs
from flowsynth import tune
from flowsynth.tune import TWIN, Rung, plan_cost, plan_rungs, search


# -- the search space ---------------------------------------------------------------------------------------------
def test_default_point_is_the_generators_defaults():
    configs, weights = tune.sources(tune.key_of(tune.default_point()))
    assert configs == {"things": fs.BouncingThingsConfig(width=512, height=384, num_frames=2)}
    assert weights == {"things": 1.0}
    for knob in tune.SPACE:  # every knob's default label holds its field's default (no 2D layers)
        want = 0.0 if knob.field == tune.LAYERS else getattr(fs.BouncingThingsConfig(), knob.field)
        assert knob.values[knob.default] == want


def test_grid_is_the_product_of_the_knobs_and_every_point_makes_its_mixture():
    points = tune.grid()
    assert len(points) == math.prod(len(k.values) for k in tune.SPACE)
    keys = [tune.key_of(p) for p in points]
    assert len(set(keys)) == len(keys)
    for key in keys:
        point = tune.point_of(key)
        configs, weights = tune.sources(key)  # validated by the configs
        for knob in tune.SPACE:
            value = knob.values[point[knob.name]]
            if knob.field == tune.LAYERS:
                assert weights.get(tune.LAYERS, 0.0) == value and sum(weights.values()) == pytest.approx(1)
                assert (tune.LAYERS in configs) == (value > 0)
            else:
                assert getattr(configs["things"], knob.field) == value
    for key in keys[::29]:  # the preset file's dict, read back by the Mixture
        mix = fs.datasets.MixtureConfig.from_dict(tune.preset(key).to_dict())
        configs, weights = tune.sources(key)
        assert mix.configs == configs and mix.weights == weights


def _fmt(v):
    if isinstance(v, tuple):
        return "(" + ", ".join(_fmt(x) for x in v) + ")"
    return v if isinstance(v, str) else f"{v:g}"


def test_docs_table_is_the_search_space():
    """docs/tune.md's table, row by row, rendered from SPACE: the table in the code and in the docs are one."""
    doc = (Path(__file__).resolve().parents[1] / "docs" / "tune.md").read_text()
    rows = ["| knob | sets | values (label: value) | default | what it changes |", "|---|---|---|---|---|"]
    for k in tune.SPACE:
        sets = "the 2D layers' weight in the mixture" if k.field == tune.LAYERS else f"`BouncingThingsConfig.{k.field}`"
        vals = "; ".join(f"`{label}`: {_fmt(v)}" for label, v in k.values.items())
        rows.append(f"| `{k.name}` | {sets} | {vals} | `{k.default}` | {k.what} |")
    assert "\n".join(rows) + "\n\n" in doc
    assert f"{len(tune.grid())} points" in doc


def test_candidates_are_distinct_seeded_and_start_with_the_default():
    a, b, c = tune.draw_candidates(8, 0), tune.draw_candidates(8, 0), tune.draw_candidates(8, 1)
    assert a == b and a != c and len(set(a)) == 8
    assert a[0] == c[0] == tune.key_of(tune.default_point())
    with pytest.raises(fs.ConfigError, match="between 2 and"):
        tune.draw_candidates(1, 0)
    with pytest.raises(fs.ConfigError, match="between 2 and"):
        tune.draw_candidates(len(tune.grid()) + 1, 0)


def test_training_sources_scale_motion_with_the_width():
    key = tune.key_of({**tune.default_point(), tune.LAYERS: "0.5", "motion": "large"})
    big, big_layers = tune.sources(key)[0].values()
    small, small_layers = tune.sources(key, (256, 192))[0].values()
    assert (small.width, small.height) == (small_layers.width, small_layers.height) == (256, 192)
    assert big_layers.motion_scale == small_layers.motion_scale == tune.LAYERS_MOTION_SCALE * 96 / 48  # width-free
    assert small.flow_px == big.flow_px == (4.0, 96.0)  # stated at 512 px wide; each config scales it to its width
    assert small.flow_px_scaled == tuple(x / 2 for x in big.flow_px_scaled) == (2.0, 48.0)
    assert small.num_objects == big.num_objects and small.texture_families == big.texture_families


def test_malformed_keys_are_named_errors():
    with pytest.raises(fs.ConfigError, match="malformed"):
        tune.point_of("motion")
    with pytest.raises(fs.ConfigError, match="unknown label"):
        tune.point_of(tune.key_of(tune.default_point()).replace("motion=default", "motion=huge"))


# -- the plan -----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [2, 3, 5, 8, 13])
def test_plan_halves_to_one_and_fits_the_budget(n):
    budget = 5000
    rungs = plan_rungs(n, budget)
    sizes = [r.size for r in rungs]
    assert sizes[0] == n and sizes[-1] == 1
    assert all(b == math.ceil(a / 2) for a, b in itertools.pairwise(sizes))
    assert [r.start for r in rungs] == [0] + [r.end for r in rungs[:-1]]
    assert all(r.end == rungs[0].end * 2**r.index for r in rungs)
    # brute force: the most any run can cost (every rung with the reference beside the survivors, and the twin)
    worst = sum((r.size + (r.index > 0) + 1) * (r.end - r.start) for r in rungs)
    assert worst == plan_cost(n, rungs[0].end) <= budget
    assert plan_cost(n, rungs[0].end + 2) > budget  # the largest first rung that fits (steps come in pairs)


def test_the_default_plan_ends_at_the_judges_length():
    rungs = plan_rungs(tune.DEFAULT_CANDIDATES, tune.DEFAULT_BUDGET)
    assert (tune.DEFAULT_CANDIDATES, tune.DEFAULT_BUDGET) == (6, 9600)  # docs/tune.md's numbers
    assert [r.end for r in rungs] == [300, 600, 1200, 2400]


def test_a_budget_too_small_is_a_named_error_with_the_smallest_that_works():
    need = tune.min_budget(4)
    assert plan_rungs(4, need)[0].end == 2
    with pytest.raises(fs.ConfigError, match=f"too small for 4 candidates.*at least {need}"):
        plan_rungs(4, need - 1)


# -- the search, with stand-in trainers ---------------------------------------------------------------------------
class Standin:
    """EPE on two pairs of net ``key`` at ``step``: its quality plus a decay, plus a wobble drawn from a generator
    that every call advances (so a search that resumed without the trainer's state would see other numbers)."""

    def __init__(self, quality: dict, wobble: float = 0.0, fail_at: int | None = None):
        self.quality, self.wobble, self.fail_at = quality, wobble, fail_at
        self.rng, self.step, self.keys, self.calls = np.random.default_rng(0), 0, [], 0

    def advance(self, keys, step):
        assert step >= self.step and (step == 0 or set(keys) <= set(self.keys)), (keys, self.keys)
        self.calls += 1
        if self.fail_at is not None and self.calls == self.fail_at:
            raise KeyboardInterrupt
        self.keys, self.step = list(keys), step
        return {k: {p: self.quality[k] + 4 / (1 + step) + self.wobble * float(self.rng.random()) for p in ("a", "b")}
                for k in keys}

    def state_dict(self):
        return {"rng": self.rng.bit_generator.state, "step": self.step, "keys": list(self.keys)}

    def load_state_dict(self, state):
        self.rng.bit_generator.state, self.step, self.keys = state["rng"], state["step"], list(state["keys"])


def _qualities(keys, seed=0):
    q = dict(zip(keys, np.random.default_rng(seed).permutation(len(keys)).astype(float)))
    q[keys[0] + TWIN] = q[keys[0]] + 0.25
    return q


def test_halving_keeps_the_best_and_runs_the_reference_and_twin_in_every_rung():
    keys = tune.draw_candidates(8, 0)
    quality = _qualities(keys)
    rungs = plan_rungs(8, 4000)
    state = search(Standin(quality), keys, rungs)
    order = sorted(keys, key=quality.get)  # brute force: with no wobble the rank is the quality's
    for r, scores in enumerate(state["scores"]):
        assert set(scores) >= {keys[0], keys[0] + TWIN}
        assert set(scores) - {keys[0], keys[0] + TWIN} == set(order[:rungs[r].size]) - {keys[0]}
    assert state["winner"] == order[0]
    assert [c["step"] for c in state["curves"][order[0]]] == [0, *(s for r in rungs for s in r.checkpoints)]


def test_the_score_is_the_mean_of_the_rungs_two_checkpoints():
    """Net "good" is best on average over the rung's checkpoints, "late" only at its last one."""

    class Swing(Standin):
        def advance(self, keys, step):
            self.keys, self.step = list(keys), step
            table = {"good": {0: 9, 2: 1.0, 4: 3.0}, "late": {0: 9, 2: 2.6, 4: 2.6}, "ref": {0: 9, 2: 5, 4: 5},
                     "ref" + TWIN: {0: 9, 2: 5, 4: 5}}
            return {k: {"a": table[k][step]} for k in keys}

    rungs = [Rung(0, 3, 0, 4)]
    state = search(Swing({}), ["ref", "good", "late"], rungs)
    assert state["scores"][0]["good"] == pytest.approx(2.0) and state["scores"][0]["late"] == pytest.approx(2.6)
    assert state["winner"] == "good"


def _saved(store):
    def save(st):
        buf = io.BytesIO()
        torch.save(st, buf)  # what run.py writes: a copy, as a file holds it
        buf.seek(0)
        store.append(torch.load(buf, weights_only=True))
    return save


@pytest.mark.parametrize("fail_at", [1, 2, 4, 7])
def test_an_interrupted_search_resumes_to_the_uninterrupted_result(fail_at):
    keys = tune.draw_candidates(5, 3)
    quality, rungs = _qualities(keys, 3), plan_rungs(5, 2000)
    whole = search(Standin(quality, wobble=3.0), keys, rungs)
    store = []
    with pytest.raises(KeyboardInterrupt):
        search(Standin(quality, wobble=3.0, fail_at=fail_at), keys, rungs, save=_saved(store))
    resumed = search(Standin(quality, wobble=3.0), keys, rungs, state=store[-1] if store else None)
    for k in ("curves", "scores", "winner", "alive"):
        assert resumed[k] == whole[k], k


def test_a_diverged_net_ranks_last_and_its_scores_are_none():
    class Diverge(Standin):
        def advance(self, keys, step):
            out = super().advance(keys, step)
            out["bad"] = {"a": float("nan"), "b": 1.0} if step else out["bad"]
            return out

    keys = ["ref", "bad", "ok"]
    state = search(Diverge({"ref": 1.0, "ref" + TWIN: 1.0, "bad": 0.0, "ok": 2.0}), keys, plan_rungs(3, 500))
    assert state["scores"][0]["bad"] is None and "bad" not in state["alive"]
    assert state["curves"]["bad"][1]["epe"]["a"] is None and state["curves"]["bad"][1]["mean"] is None


# -- the report ---------------------------------------------------------------------------------------------------
def test_report_numbers_come_from_the_last_rung(tmp_path):
    keys = tune.draw_candidates(4, 0)
    quality = _qualities(keys)
    quality[keys[2]] = -1.0  # a clear winner
    rungs = plan_rungs(4, 1000)
    state = search(Standin(quality), keys, rungs)
    rep = tune.summarize(state, keys, rungs)
    last = state["scores"][-1]
    assert rep["winner"] == keys[2]
    assert rep["margin"] == pytest.approx(last[keys[0]] - last[keys[2]])
    assert rep["noise"] == pytest.approx(0.25) and rep["margin_over_noise"] == pytest.approx(rep["margin"] / 0.25)
    assert [n["key"] for n in rep["nets"][:2]] == [keys[0], keys[0] + TWIN]
    assert {n["key"] for n in rep["nets"]} == {*keys, keys[0] + TWIN}
    text = tune.markdown(rep)
    assert text.count("\n| ") == 1 + len(keys) + 1 and "x the noise" in text  # the header, the nets, the twin
    assert f"{last[keys[2]]:.3f}" in text


@pytest.mark.parametrize("margin, words", [(0.2, "0.8x the noise: within the noise, no win"),
                                           (0.4, "1.6x the noise: under 2x the noise, weak evidence at best"),
                                           (1.0, "4.0x the noise"), (-1.0, "the default won")])
def test_the_verdict_reads_the_margin_in_noises(margin, words):
    keys = tune.draw_candidates(2, 0)
    quality = {keys[0]: 1.0, keys[0] + TWIN: 1.25, keys[1]: 1.0 - margin}  # the noise: 0.25 px
    rungs = plan_rungs(2, 100)
    rep = tune.summarize(search(Standin(quality), keys, rungs), keys, rungs)
    assert words in rep["verdict"]
    assert rep["winner"] == (keys[0] if margin < 0 else keys[1]) and rep["noise"] == pytest.approx(0.25)


def test_layers_motion_follows_the_motion_knob():
    """The 2D layers' motion scale is 1.5 at the default motion and scales with the knob's largest flow."""
    from flowsynth.tune import space

    def layers_scale(motion):
        point = {**space.default_point(), "layers": "0.5", "motion": motion}
        configs, weights = space.sources(space.key_of(point))
        assert weights == {"things": 0.5, "layers": 0.5}
        return configs["layers"].motion_scale

    assert layers_scale("default") == 1.5
    assert layers_scale("small") == 1.5 * 16 / 48 and layers_scale("large") == 1.5 * 96 / 48
