"""flowsynth.train.steps, RAFT's recipe, against oracles: the loss by a direct sum, the augmentation by the translation
it must keep, the colour jitter by its identity and grey invariants, and ``predict``'s padding by a net that records
what it was given."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flowsynth.errors import ShapeError
from flowsynth.train.steps import _jitter_one, augment, epe, one_cycle, predict, sequence_loss, train_step


def test_sequence_loss_is_the_weighted_sum_of_masked_l1_means():
    g = torch.Generator().manual_seed(0)
    flow = torch.randn(2, 2, 5, 7, generator=g) * 3
    flow[0, 0, 0, 0] = 500.0  # above max_flow: left out
    valid = torch.rand(2, 1, 5, 7, generator=g) > 0.3
    preds = [torch.randn(2, 2, 5, 7, generator=g) for _ in range(3)]
    f, v = flow.numpy(), valid.numpy()[:, 0] & (np.linalg.norm(flow.numpy(), axis=1) < 400)
    want = 0.0
    for i, p in enumerate(preds):
        err = np.abs(p.numpy() - f) * v[:, None]
        want += 0.8 ** (2 - i) * err.sum() / err.size
    assert float(sequence_loss(preds, flow, valid)) == pytest.approx(want, rel=1e-5)


def _translated_pair(dx: int, dy: int, h: int = 40, w: int = 48):
    """A random image and the same image moved by (dx, dy) (content at x of frame 1 is at x + (dx, dy) in frame 2),
    with the constant flow and the valid mask where the target stays inside the big image."""
    g = torch.Generator().manual_seed(3)
    big = torch.rand(1, 3, h + 20, w + 20, generator=g)
    a = big[:, :, 10:10 + h, 10:10 + w]
    b = big[:, :, 10 - dy:10 - dy + h, 10 - dx:10 - dx + w]
    flow = torch.tensor([float(dx), float(dy)]).view(1, 2, 1, 1).expand(1, 2, h, w).clone()
    return a.repeat(8, 1, 1, 1), b.repeat(8, 1, 1, 1), flow.repeat(8, 1, 1, 1), torch.ones(8, 1, h, w, dtype=bool)


def test_augment_keeps_the_correspondence_under_crops_and_flips(monkeypatch):
    """With the colour jitter at identity, every augmented pair must still satisfy img2[p + flow(p)] = img1[p]."""
    import flowsynth.train.steps as tr

    monkeypatch.setattr(tr, "_draw_jitter", lambda n, g: torch.tensor([[1.0, 1.0, 1.0, 0.0]]).repeat(n, 1))
    a, b, f, v = _translated_pair(3, -2)
    g = torch.Generator().manual_seed(1)
    flips = set()
    for _ in range(6):
        a2, b2, f2, v2 = augment(a, b, f, v, (24, 32), g, hflip=0.5, vflip=0.5)
        assert a2.shape == (8, 3, 24, 32) and f2.shape == (8, 2, 24, 32) and v2.dtype == torch.float32
        for k in range(8):
            fx, fy = int(f2[k, 0, 0, 0]), int(f2[k, 1, 0, 0])
            flips.add((fx, fy))
            ys, xs = np.mgrid[4:20, 4:28]
            assert torch.allclose(b2[k][:, ys + fy, xs + fx], a2[k][:, ys, xs], atol=1e-5)
    assert flips == {(3, -2), (-3, -2), (3, 2), (-3, 2)}  # every flip was drawn and changed the flow's sign


def test_colour_jitter_identity_and_grey_invariance():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(3, 3, 8, 8, generator=g)
    ident = torch.tensor([[1.0, 1.0, 1.0, 0.0]]).repeat(3, 1)
    assert torch.allclose(_jitter_one(img, ident), img, atol=1e-5)
    grey = img[:, :1].repeat(1, 3, 1, 1) * 0.8
    out = _jitter_one(grey, torch.tensor([[1.0, 1.0, 0.5, 0.13]]).repeat(3, 1))  # saturation and hue: no colour
    assert torch.allclose(out, grey, atol=1e-5)
    out = _jitter_one(img, torch.tensor([[1.3, 0.7, 1.4, -0.15]]).repeat(3, 1))
    assert out.min() >= 0 and out.max() <= 1 and not torch.allclose(out, img)


def test_augment_rejects_a_crop_larger_than_the_images():
    a, b, f, v = _translated_pair(1, 1)
    with pytest.raises(ShapeError, match="crop"):
        augment(a, b, f, v, (64, 32), torch.Generator())
    with pytest.raises(ShapeError, match="images"):
        augment(a, b[:, :2], f, v, (8, 8), torch.Generator())


class _Recorder(torch.nn.Module):
    """A RAFT-like net: returns ``num_flow_updates`` flows, each a learnable constant (dx, dy); records input
    sizes."""

    def __init__(self):
        super().__init__()
        self.flow = torch.nn.Parameter(torch.zeros(1, 2, 1, 1))
        self.seen = []

    def forward(self, img1, img2, num_flow_updates=12):
        self.seen.append((tuple(img1.shape), float(img1.min()), float(img1.max())))
        return [self.flow.expand(img1.shape[0], 2, *img1.shape[-2:]) for _ in range(num_flow_updates)]


def test_predict_pads_to_raft_sizes_and_crops_back():
    net = _Recorder()
    with torch.no_grad():
        net.flow[:] = torch.tensor([1.5, -2.0]).view(1, 2, 1, 1)
    img = torch.rand(1, 3, 101, 250)
    out = predict(net, img, img)
    assert out.shape == (1, 2, 101, 250)
    (shape, lo, hi), = net.seen
    assert shape == (1, 3, 128, 256) and lo >= -1 and hi <= 1  # at least 128, multiples of 8, normalised to [-1, 1]
    assert epe(out, torch.zeros_like(out), torch.ones(1, 1, 101, 250)) == pytest.approx(2.5)


def test_train_step_learns_a_constant_flow():
    net = _Recorder()
    opt, sched = one_cycle(net.parameters(), 0.5, 60)
    flow = torch.tensor([2.0, -1.0]).view(1, 2, 1, 1).expand(2, 2, 16, 16)
    batch = (torch.rand(2, 3, 16, 16), torch.rand(2, 3, 16, 16), flow, torch.ones(2, 1, 16, 16))
    losses = [train_step(net, batch, opt, sched, updates=3) for _ in range(60)]
    assert losses[-1] < 0.1 * losses[0]
    assert torch.allclose(net.flow.flatten(), torch.tensor([2.0, -1.0]), atol=0.1)
