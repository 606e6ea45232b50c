"""The native sample folder: every key has a declared file format; an unknown key is an error, not JSON."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

import flowsynth as fs
from flowsynth.plan import OUTPUTS
from flowsynth.io.sampleio import read_sample, write_sample


def test_unknown_key_is_an_error_and_writes_nothing(tmp_path):
    sample = {"depth": torch.ones(2, 1, 3, 4), "index": torch.tensor(0), "depth_left": torch.ones(2, 1, 3, 4)}
    with pytest.raises(fs.ExportError, match="depth_left"):
        write_sample(sample, tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_every_output_has_a_format(tmp_path):
    # Every key the renderer can produce, plus the sample's index and seed, is written and read back.
    scene = fs.Scene(camera=fs.Camera.from_fov(width=8, height=6, fov_deg=60.0), num_frames=2)
    poses = np.repeat(np.eye(4)[None], 2, 0)
    poses[:, 2, 3] = 3.0
    poses[1, 0, 3] = 0.1
    scene.add_object(trimesh.creation.box((1.0, 1.0, 1.0)), poses=poses, category=2)
    sample = fs.render(scene, list(OUTPUTS), max_objects=2, stereo_baseline=0.1, num_tracks=5)
    sample["index"], sample["seed"] = torch.tensor(3), torch.tensor(5)
    write_sample(sample, tmp_path)
    back = read_sample(tmp_path)
    assert list(back) == list(sample)
    for k, v in sample.items():
        assert back[k].dtype == v.dtype and back[k].shape == v.shape, k
        if k in ("rgb", "rgb_right", "rgb_final"):  # 8-bit PNG: within half a step
            assert (back[k] - v).abs().max() <= 0.5 / 255 + 1e-6
        else:
            assert torch.equal(back[k], v), k
