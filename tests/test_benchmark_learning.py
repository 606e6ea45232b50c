"""benchmarks/learning.py's network starts as a working block matcher (issue 12's protocol): untrained, it
recovers a known translation of a random texture. The oracle is the translation itself."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import learning


def _shifted_pair(dx: int, dy: int):
    """A smooth random texture (bicubic upsampling of noise) and the same texture moved by (dx, dy) px: the
    content at pixel x of the first image is at x + (dx, dy) in the second."""
    g = torch.Generator().manual_seed(1)
    big = torch.nn.functional.interpolate(torch.rand(1, 3, 48, 64, generator=g), size=(192, 256), mode="bicubic",
                                          align_corners=False).clamp(0, 1)
    a = big[:, :, 40:136, 40:168]
    b = big[:, :, 40 - dy:136 - dy, 40 - dx:168 - dx]
    return a, b


@pytest.mark.parametrize(("dx", "dy", "tol"), [(0, 0, 0.01), (3, -2, 0.6), (7, 5, 0.4)])
def test_untrained_net_recovers_a_translation(dx, dy, tol):
    torch.manual_seed(0)
    net = learning.build_net()
    a, b = _shifted_pair(dx, dy)
    with torch.no_grad():
        flow = net(a, b)[-1][0]
    assert flow.shape == (2, 96, 128)
    inner = flow[:, 16:-16, 16:-16]  # away from the borders, where part of a window leaves the image
    err = (inner - torch.tensor([dx, dy], dtype=inner.dtype).view(2, 1, 1)).norm(dim=0)
    assert float(err.mean()) < tol
    assert torch.isfinite(flow).all()


def test_batches_stream_each_pair_once_and_pool_draws_with_replacement():
    """A pool of steps x batch pairs or more is a stream: the batches are one permutation's consecutive slices.
    A smaller pool is drawn from with replacement, the same draws as ``torch.randint`` on the same generator."""
    stream = list(learning.batches(12, 3, 4, torch.Generator().manual_seed(5)))
    assert [len(b) for b in stream] == [4, 4, 4]
    assert sorted(torch.cat(stream).tolist()) == list(range(12))
    assert torch.equal(torch.cat(stream), torch.randperm(12, generator=torch.Generator().manual_seed(5)))
    pool = list(learning.batches(11, 3, 4, torch.Generator().manual_seed(5)))
    g = torch.Generator().manual_seed(5)
    for b in pool:
        assert torch.equal(b, torch.randint(11, (4,), generator=g))


def test_too_few_steps_is_a_usage_error():
    import subprocess

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "learning.py"
    r = subprocess.run([sys.executable, str(script), "--steps", "10"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "at least 20 steps" in r.stderr
