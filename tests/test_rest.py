"""``rest_fraction``: objects at rest and a camera that holds still. Oracles: analytic (nothing moves -> the
camera poses are equal and the flow is zero), the config's draws (velocities zeroed exactly where the layout says
an object rests), and a config without the field (every other draw unchanged)."""

import dataclasses

import numpy as np
import pytest
import torch

import flowsynth as fs
from flowsynth.errors import ConfigError
from flowsynth.scene.sampling import sample_layout

SMALL = dict(width=64, height=48, num_frames=3)


def test_everything_at_rest_gives_zero_flow():
    cfg = fs.BouncingThingsConfig(**SMALL, rest_fraction=1.0)
    layout = sample_layout(cfg, 0, 4)
    assert np.all(layout.world_T_cam == layout.world_T_cam[:1])
    assert np.all(layout.initial.velocity == 0) and np.all(layout.initial.angular_velocity == 0)
    assert layout.motion["camera_at_rest"] and layout.motion["objects_at_rest"] == len(layout.assets)
    s = fs.datasets.BouncingThings(cfg, outputs=["flow_fw", "valid_fw", "motion"], seed=0).sample(4)
    valid = s["valid_fw"].expand_as(s["flow_fw"])
    assert valid.any()
    assert float(s["flow_fw"][valid].abs().max()) < 1e-3  # float32 poses of unmoved objects
    assert not s["motion"].any()


def test_some_at_rest_zero_exactly_those_and_keep_other_draws():
    base = fs.BouncingThingsConfig(**SMALL)
    cfg = dataclasses.replace(base, rest_fraction=0.5)
    seen_rest = seen_moving = 0
    for index in range(6):
        a, b = sample_layout(base, 0, index), sample_layout(cfg, 0, index)
        rest = np.all(b.initial.velocity == 0, axis=1)
        assert b.motion["objects_at_rest"] == int(rest.sum())
        # everything drawn before the rest draws is the same as without the field
        np.testing.assert_array_equal(a.initial.position, b.initial.position)
        np.testing.assert_array_equal(a.initial.velocity[~rest], b.initial.velocity[~rest])
        np.testing.assert_array_equal(a.initial.angular_velocity[~rest], b.initial.angular_velocity[~rest])
        assert np.all(b.initial.angular_velocity[rest] == 0)
        assert np.array_equal(a.texture_seeds, b.texture_seeds)
        if b.motion.get("camera_at_rest"):
            assert np.all(b.world_T_cam == a.world_T_cam[:1])
        else:
            np.testing.assert_array_equal(a.world_T_cam, b.world_T_cam)
        seen_rest += int(rest.sum())
        seen_moving += int((~rest).sum())
    assert seen_rest and seen_moving  # 0.5 gives both over 6 clips


@pytest.mark.parametrize("bad", [-0.1, 1.5, "half", True])
def test_rest_fraction_validated(bad):
    with pytest.raises(ConfigError, match="rest_fraction"):
        fs.BouncingThingsConfig(rest_fraction=bad)


def test_rest_fraction_zero_flow_share_rises():
    """A still camera shows a room of zero flow: the zero-flow share of a clip with the camera at rest and no
    object moving exceeds that of the same clip with rest_fraction 0."""
    cfg = fs.BouncingThingsConfig(**SMALL, rest_fraction=1.0)
    s = fs.datasets.BouncingThings(cfg, outputs=["flow_fw", "valid_fw"], seed=1).sample(0)
    m = torch.linalg.vector_norm(s["flow_fw"][0], dim=0)[s["valid_fw"][0, 0]]
    s0 = fs.datasets.BouncingThings(dataclasses.replace(cfg, rest_fraction=0.0), outputs=["flow_fw", "valid_fw"],
                                    seed=1).sample(0)
    m0 = torch.linalg.vector_norm(s0["flow_fw"][0], dim=0)[s0["valid_fw"][0, 0]]
    assert float((m < 0.1).float().mean()) == 1.0
    assert float((m0 < 0.1).float().mean()) < 0.5
