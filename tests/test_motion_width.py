"""Motion that means the same at every resolution: ``flow_px`` is stated at ``flow_px_width`` (512) px wide and each
config scales it to the width it renders.

Oracles: the scene at 512 px wide (its speeds in m/s and the camera's path do not depend on the image size), the
flow ``flowsynth stats`` measures on rendered samples at two sizes, and, for the learning judge's and the tune's pools,
the pairs rendered from the form their code had before the config scaled the motion (flow_px divided by hand, in the
rendered image's pixels: ``flow_px_width`` = width). benchmarks/learning/pool_hashes.py compares the pools' hashes
across commits (docs/decisions/0029-flow-px-width.md records them).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import flowsynth as fs
from flowsynth.cli import main
from flowsynth.errors import ConfigError
from flowsynth.scene.config import FLOW_PX_WIDTH, BouncingThingsConfig
from flowsynth.scene.sampling import sample_layout

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


def _by_hand(cfg: BouncingThingsConfig) -> BouncingThingsConfig:
    """``cfg``'s motion in the form of before: flow_px scaled to the width by hand, stated at the rendered width."""
    s = cfg.width / FLOW_PX_WIDTH
    return BouncingThingsConfig.from_dict({**cfg.to_dict(), "flow_px": [x * s for x in cfg.flow_px],
                                           "flow_px_width": cfg.width})


def test_flow_px_is_stated_at_512_px_and_scaled_to_the_width():
    assert FLOW_PX_WIDTH == 512 and BouncingThingsConfig().flow_px_width == 512
    assert BouncingThingsConfig(width=512).flow_px_scaled == BouncingThingsConfig().flow_px == (2.0, 48.0)
    assert BouncingThingsConfig(width=64).flow_px_scaled == (0.25, 6.0)
    assert BouncingThingsConfig(width=300, flow_px_width=300).flow_px_scaled == (2.0, 48.0)
    assert BouncingThingsConfig(width=64, flow_px=None).flow_px_scaled is None
    things = BouncingThingsConfig.preset("things")
    assert things.flow_px_scaled == things.flow_px == (2.0, 100.0)  # stated at its own 960 px width
    assert BouncingThingsConfig.preset("things", width=480).flow_px_scaled == (1.0, 50.0)
    for bad in (0, 1.5, "512", True):
        with pytest.raises(ConfigError, match="flow_px_width"):
            BouncingThingsConfig(flow_px_width=bad)


def test_the_scene_moves_the_same_metres_at_every_width():
    """Same seed at 64x48 and 512x384: the targets scale exactly with the width; the speeds [m/s] and the camera's
    path, which the targets and the focal length (also proportional to the width) set, are the same scene's
    (the spawn points, aimed at pixels, differ by about a pixel of 64, so speeds agree to a few percent)."""
    small, large = (BouncingThingsConfig(width=w, height=h, num_frames=2) for w, h in ((64, 48), (512, 384)))
    for index in range(6):
        a, b = sample_layout(small, 0, index), sample_layout(large, 0, index)
        np.testing.assert_allclose(a.motion["camera_flow_px"], b.motion["camera_flow_px"] * 64 / 512, rtol=1e-12)
        np.testing.assert_allclose(a.motion["object_flow_px"], np.array(b.motion["object_flow_px"]) * 64 / 512,
                                   rtol=1e-12)
        speed_a, speed_b = (np.linalg.norm(x.initial.velocity, axis=1) for x in (a, b))
        np.testing.assert_allclose(speed_a, speed_b, rtol=0.05)
        step_a, step_b = (np.linalg.norm(x.world_T_cam[1, :3, 3] - x.world_T_cam[0, :3, 3]) for x in (a, b))
        np.testing.assert_allclose(step_a, step_b, rtol=0.05, atol=1e-9)


def _stats(tmp_path, w: int, h: int, capsys) -> dict:
    out = tmp_path / f"stats_{w}.json"
    assert main(["stats", "--num", "4", "--width", str(w), "--height", str(h), "--num-frames", "2",
                 "--render-mode", "flat", "--json", str(out)]) == 0
    capsys.readouterr()
    return json.loads(out.read_text())


def test_stats_at_two_sizes_measure_the_same_motion(tmp_path, capsys):
    """``flowsynth stats`` of the same samples at 64x48 and 128x96: mean |flow| / width, the occluded and the out of
    frame shares agree within sampling noise (with absolute pixels the small image's are twice as large)."""
    a, b = _stats(tmp_path, 64, 48, capsys), _stats(tmp_path, 128, 96, capsys)
    assert a["flow"]["mean"] / 64 == pytest.approx(b["flow"]["mean"] / 128, rel=0.1)
    for key in ("occluded_fraction", "out_of_frame_fraction"):
        assert a[key] == pytest.approx(b[key], abs=0.03), key


def _pool_equal(x: tuple, y: tuple) -> None:
    assert len(x) == len(y) == 4
    for u, v in zip(x, y):
        assert u.dtype == v.dtype and u.shape == v.shape and torch.equal(u, v)


def test_learning_pool_keeps_the_bytes_of_its_hand_scaled_form():
    """The judge's flowsynth pool at 256x192 (no hand scaling now) is the pool of the hand-scaled config."""
    from learning.pools import flowsynth_pool
    from learning.protocol import RES

    pool, cfg = flowsynth_pool(1, 0, 0)
    assert cfg.width == RES[0] != FLOW_PX_WIDTH and cfg.flow_px == BouncingThingsConfig().flow_px
    old = _by_hand(cfg)
    assert old.flow_px == (1.0, 24.0)  # what the registered runs' pools divided by hand
    ds = fs.datasets.BouncingThings(old, outputs=["rgb", "flow_fw", "valid_fw"], seed=0, length=1)
    s = ds.sample(0)
    u8 = (s["rgb"] * 255).round().clamp(0, 255).to(torch.uint8)
    _pool_equal(pool, (u8[None, 0], u8[None, 1], s["flow_fw"][None, 0], s["valid_fw"][None, 0]))


def test_tune_pool_keeps_the_bytes_of_its_hand_scaled_form():
    """The tune's pool at its quick size (160 px wide: a width no power of two divides 512 by) is the pool of the
    config it made by hand before."""
    from flowsynth.tune.space import default_point, key_of, sources
    from flowsynth.tune.pools import render_pool
    from flowsynth.tune.trainer import QUICK

    configs, weights = sources(key_of(default_point()), QUICK.res)
    things = configs["things"]
    assert things.width == 160 and things.flow_px == (2.0, 48.0)
    assert things.flow_px_scaled == tuple(x * 160 / 512 for x in (2.0, 48.0))
    old = ({"things": _by_hand(things)}, weights)
    _pool_equal(render_pool((configs, weights), 3, 1), render_pool(old, 3, 1))


def test_an_export_made_before_the_field_is_not_resumed(tmp_path, small_flags, capsys):
    """An export whose manifest's config lacks ``flow_px_width`` (made when flow_px was in the rendered pixels) is
    refused on resume, not continued with motion of another scale: exit 2, nothing rewritten."""
    out = tmp_path / "out"
    assert main(["export", "--out", str(out), "--num", "1", *small_flags]) == 0
    man = out / "manifest.json"
    old = json.loads(man.read_text())
    del old["config"]["flow_px_width"]
    man.write_text(json.dumps(old))
    files = sorted(p.relative_to(out) for p in out.rglob("*"))
    capsys.readouterr()
    assert main(["export", "--out", str(out), "--num", "2", *small_flags]) == 2
    assert "config" in capsys.readouterr().err
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == files and json.loads(man.read_text()) == old
