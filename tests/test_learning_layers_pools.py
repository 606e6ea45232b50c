"""The RAFT judge's 2D pools come from the library's layers (benchmarks/learning/pools.py): the chairs2d pool is
``fs.datasets.layers_pairs``' output bit for bit, at the motion scale of its pilot pairs, with the pool's dtypes,
shapes and all-valid mask; no OpenCV is needed to make it; a run records the generator; ``--quick`` on the 2D arms
runs through the command line.

Oracles: ``fs.datasets.layers_pairs`` called here with the same sources, seeds and scale (its own agreement with the
OpenCV helper, ``sets.chairs2d_pairs``, is tests/test_layers2d.py's); the pilot's mean |flow| recomputed over all
pixels with torch alone.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import _common
import flowsynth as fs
from learning import cli, pools, runs, trainers

H, W = 48, 64  # a small pool: the layers' shapes and shifts scale with the width


def _seed_pools(n: int, seed: int, target: float) -> pools.SeedPools:
    """A seed's pools as ``build_arms`` makes them, with random uint8 frames standing in for the flowsynth renders
    (n pairs trained on, then n / 2 frames: the 2D pool's textures)."""
    g = torch.Generator().manual_seed(seed)
    m = n + n // 2
    rendered = (torch.randint(256, (m, 3, H, W), dtype=torch.uint8, generator=g),
                torch.randint(256, (m, 3, H, W), dtype=torch.uint8, generator=g),
                torch.randn(m, 2, H, W, generator=g), torch.ones(m, 1, H, W, dtype=torch.bool))
    return pools.SeedPools(n, seed, 0, {}, rendered, {"flowsynth_mean_flow": target})


@pytest.fixture
def two_threads():
    """Two torch threads in the caller (the judge's default), restored after the test."""
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("n,seed,target", [(6, 0, 4.0), (8, 3, 9.5)])
def test_chairs2d_pool_is_layers_pairs_bit_for_bit(monkeypatch, two_threads, n, seed, target):
    s = _seed_pools(n, seed, target)
    monkeypatch.setitem(sys.modules, "cv2", None)  # any OpenCV import on the way raises ImportError
    img1, img2, flow, valid = s.chairs2d()
    assert torch.get_num_threads() == 2  # the caller's count, restored
    sources = s.rendered[0][n:].float() / 255
    pilot = fs.datasets.layers_pairs(64, seed + 1, sources)["flow_fw"]
    scale = target / float(torch.linalg.vector_norm(pilot.double(), dim=2).mean())
    assert s.info["chairs2d_motion_scale"] == pytest.approx(scale, rel=1e-6)
    assert s.info["layers"] == pools.LAYERS == "flowsynth"
    want = fs.datasets.layers_pairs(n, seed, sources, s.info["chairs2d_motion_scale"])
    u8 = (want["rgb"] * 255).round().clamp(0, 255).to(torch.uint8)
    assert torch.equal(img1, u8[:, 0]) and torch.equal(img2, u8[:, 1])
    assert torch.equal(flow, want["flow_fw"][:, 0])
    # the pool's contract: uint8 images, float32 flow, bool valid everywhere (as in FlyingChairs)
    assert (img1.dtype, img2.dtype, flow.dtype, valid.dtype) == (torch.uint8, torch.uint8, torch.float32, torch.bool)
    assert (img1.shape, flow.shape, valid.shape) == ((n, 3, H, W), (n, 2, H, W), (n, 1, H, W))
    assert bool(valid.all())
    assert s.chairs2d() is s.chairs2d()  # made once for the arms that share it
    # the scale moves the motion: the pool at scale 1 is another pool (the check can fail)
    assert not torch.equal(flow, fs.datasets.layers_pairs(n, seed, sources)["flow_fw"][:, 0])


def test_the_2d_pools_motion_matches_its_target():
    """Scaled to the pilot's mean |flow|, a 64-pair pool of another seed has about the target's mean |flow|."""
    s = _seed_pools(64, 5, 6.0)
    assert pools.mean_flow(s.chairs2d()) == pytest.approx(6.0, rel=0.1)  # 6.05 measured; inverted: ~0.4


def test_quick_run_on_the_2d_arms_records_the_layers(tmp_path, monkeypatch):
    """``--quick`` on chairs2d, mixture and curriculum: the real pools (flowsynth renders and the library's layers),
    the real trainer at a test's size (one 128x128 crop a step, two updates), the judges stubbed; the results file
    records the 2D pools' generator and a finite curve per arm."""
    monkeypatch.setattr(trainers, "BATCH", 1)
    monkeypatch.setattr(trainers, "CROP", (128, 128))
    monkeypatch.setattr(trainers, "UPDATES", 2)
    monkeypatch.setattr(trainers, "evaluate", lambda net, tests, device: {"stereo": float(
        sum(p.detach().abs().sum() for p in net.parameters()))})
    monkeypatch.setattr(runs, "judge_sets", lambda middlebury: {})
    monkeypatch.setattr(runs, "zero_flow", lambda tests: {"stereo": 17.0})
    monkeypatch.setattr(runs, "CACHE", tmp_path / "cache")
    monkeypatch.setattr(runs, "RESULTS_DIR", tmp_path)
    monkeypatch.setattr(_common, "RESULTS_DIR", tmp_path)
    threads = torch.get_num_threads()
    try:
        cli.main(["--quick", "--arms", "chairs2d,mixture,curriculum", "--pool", "4", "--workers", "0", "--jobs", "0",
                  "--threads", "1", "--tag", "q"])
    finally:
        torch.set_num_threads(threads)
    out = json.loads((tmp_path / "learning_raft_q.json").read_text())
    assert out["complete"] and out["steps"] == 20 and out["pool"] == 4
    (run,) = out["runs"]
    assert run["data"]["layers"] == "flowsynth" and run["data"]["chairs2d_motion_scale"] > 0
    assert set(run["results"]) == set(run["data"]["mean_flow"]) == {"chairs2d", "mixture", "curriculum"}
    for r in run["results"].values():
        assert [c["step"] for c in r["curve"]] == [0, 10, 20]
        assert all(math.isfinite(c["stereo"]) for c in r["curve"])


def test_still_natural_replaces_the_default_pools_last_share(monkeypatch):
    """``still_natural``: the default pool's first 85% unchanged; its last 15% the layers pairs of the still (motion
    scale 0: zero flow everywhere) and near-still (sub-pixel) draws, with the pool's dtypes and valid everywhere."""
    n, seed = 20, 2
    s = _seed_pools(n, seed, 5.0)
    g = torch.Generator().manual_seed(7)
    sources = torch.rand(4, 3, H, W, generator=g)
    img1, img2, flow, valid = pools.still_natural(s, sources)
    k = round(0.15 * n)
    assert s.info["still_natural"]["replaced"] == k == 3
    for got, base in zip((img1, img2, flow, valid), s.pool):
        assert got.dtype == base.dtype and got.shape == base.shape
        assert torch.equal(got[:n - k], base[:n - k])
    still = fs.datasets.layers_pairs(1, pools.STILL_SEED + seed, sources, 0.0)
    near = fs.datasets.layers_pairs(2, pools.NEAR_STILL_SEED + seed, sources, pools.NEAR_STILL_SCALE)
    u8 = lambda x: (x * 255).round().clamp(0, 255).to(torch.uint8)
    assert torch.equal(img1[n - k:], u8(torch.cat([still["rgb"][:, 0], near["rgb"][:, 0]])))
    assert torch.equal(img2[n - k:], u8(torch.cat([still["rgb"][:, 1], near["rgb"][:, 1]])))
    assert torch.equal(flow[n - k:], torch.cat([still["flow_fw"][:, 0], near["flow_fw"][:, 0]]))
    assert bool((flow[n - k] == 0).all())  # still: no motion anywhere
    mag = torch.linalg.vector_norm(flow[n - k + 1:], dim=1)
    assert 0 < float(mag.max()) < 1.0  # near-still: sub-pixel, and not still
    assert bool(valid.all())


def test_natural_sources_are_centred_crops_averaged_2x2(monkeypatch, tmp_path):
    """The still_natural textures: each PNG's centred 4:3 crop at RES, equal to OpenCV's area resize (the oracle)."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    ims = [rng.integers(0, 256, (512, 512, 3), dtype=np.uint8) for _ in range(2)]
    for i, im in enumerate(ims):
        cv2.imwrite(str(tmp_path / f"t{i}.png"), im)
    monkeypatch.setattr(pools, "natural_folder", lambda: tmp_path)
    got = pools.natural_sources()
    w, h = pools.RES
    assert got.shape == (2, 3, h, w)
    for i, im in enumerate(ims):
        rgb = cv2.cvtColor(im, cv2.COLOR_BGR2RGB)[64:448].astype(np.float32) / 255
        want = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
        assert np.abs(got[i].permute(1, 2, 0).numpy() - want).max() < 1e-6
