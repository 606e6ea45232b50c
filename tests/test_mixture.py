"""fs.datasets.Mixture: samples of several configs, drawn reproducibly by weights or a curriculum."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

import flowsynth as fs

SMALL = dict(width=32, height=24, num_frames=2, num_objects=(1, 2), render_mode="flat")


def _configs():
    return {"chairs": fs.BouncingThingsConfig.preset("chairs", **SMALL),
            "default": fs.BouncingThingsConfig(**SMALL)}


def test_each_sample_is_its_source_configs_own_sample():
    """Sample i of a mixture is, bit for bit, sample i of BouncingThings(its source's config, seed): the oracle is
    a plain BouncingThings of each config; both sources occur in 8 indices at equal weights."""
    cfgs = _configs()
    mix = fs.datasets.Mixture(cfgs, outputs=["rgb", "flow_fw"], seed=3)
    plain = {k: fs.datasets.BouncingThings(c, outputs=["rgb", "flow_fw"], seed=3) for k, c in cfgs.items()}
    seen = set()
    for i in range(8):
        k = mix.source(i)
        seen.add(k)
        got, want = mix.sample(i), plain[mix.names[k]].sample(i)
        assert int(got["source"]) == k
        for key in ("rgb", "flow_fw"):
            assert torch.equal(got[key], want[key]), (i, key)
    assert seen == {0, 1}


def test_weights_and_curriculum_choose_the_sources():
    """Sources follow the weights in force: 2000 draws at 1:3 give 25% +- 3% of the first; a curriculum gives
    only the first source before its first stage ends, and the later weights after it; the draws depend on
    (seed, i) alone."""
    cfgs = _configs()
    mix = fs.datasets.Mixture(cfgs, {"chairs": 1, "default": 3}, seed=0)
    share = np.mean([mix.source(i) == 0 for i in range(2000)])
    assert abs(share - 0.25) < 0.03
    cur = fs.datasets.Mixture(cfgs, [(100, {"chairs": 1}), (None, {"chairs": 1, "default": 1})], seed=0)
    assert all(cur.source(i) == 0 for i in range(100))
    later = [cur.source(i) for i in range(100, 1100)]
    assert 0.4 < np.mean(later) < 0.6
    again = fs.datasets.Mixture(cfgs, [(100, {"chairs": 1}), (None, {"chairs": 1, "default": 1})], seed=0)
    assert [again.source(i) for i in range(100, 200)] == later[:100]
    other = fs.datasets.Mixture(cfgs, {"chairs": 1, "default": 3}, seed=1)
    assert [other.source(i) for i in range(200)] != [mix.source(i) for i in range(200)]


def test_loader_workers_read_every_index_once():
    """Iteration is BouncingThings' own: two DataLoader workers yield indices 0..5 once each, with the items
    sample(i) gives, and the batch carries each item's source."""
    mix = fs.datasets.Mixture(_configs(), outputs=["flow_fw"], seed=5, length=6)
    items = [b for b in DataLoader(mix, batch_size=1, num_workers=2)]
    idx = sorted(int(b["index"]) for b in items)
    assert idx == list(range(6))
    for b in items:
        i = int(b["index"])
        assert int(b["source"]) == mix.source(i)
        assert torch.equal(b["flow_fw"][0], mix.sample(i)["flow_fw"])


@pytest.mark.parametrize("configs, weights, match", [
    ({"a": fs.BouncingThingsConfig(width=32, height=24), "b": fs.BouncingThingsConfig(width=64, height=24)},
     None, "width"),
    ({"a": fs.BouncingThingsConfig(**SMALL)}, {"b": 1}, "weights must name"),
    ({"a": fs.BouncingThingsConfig(**SMALL)}, {"a": -1}, ">= 0"),
    ({"a": fs.BouncingThingsConfig(**SMALL)}, {"a": 0}, "not all 0"),
    ({"a": fs.BouncingThingsConfig(**SMALL)}, [(10, {"a": 1}), (5, {"a": 1})], "increasing"),
    ({"a": fs.BouncingThingsConfig(**SMALL)}, [(None, {"a": 1}), (5, {"a": 1})], "open-ended"),
    ({}, None, "at least one"),
    ({"a": 3}, None, "BouncingThingsConfig"),
    ({"a": "nope"}, None, "unknown preset"),
])
def test_bad_mixtures_are_config_errors(configs, weights, match):
    with pytest.raises(fs.ConfigError, match=match):
        fs.datasets.Mixture(configs, weights)
