"""flowsynth.train.ensemble against the single-net path: K RAFT-small nets trained at once (vmap over stacked weights)
equal K separate runs of ``training.train_step`` with ``one_cycle`` (same init, same batches); each net is clipped by
its own gradient norm, and a joint clip (the mutant) would be caught; ``learning.trainers.train_many`` equals ``train``
per net.

The comparisons run in float64. Adam divides each gradient element by its own running magnitude plus eps (1e-8). In
float32 the biases of the convolutions before RAFT's InstanceNorm, whose true gradient is zero, get gradients of
rounding noise (~1e-9), not far below eps, so Adam moves them by a fair share of the learning rate in the noise's
direction; other elements with near-zero gradients flip sign the same way. Two correct implementations that only sum
in another order then differ by about lr in such weights after a few steps (measured here: 1e-3 at lr 1e-3, and 0.01
px in the flow). In float64 the noise is ~1e-13, 1e5 below eps, and every weight agrees to < 1e-12. torchvision's RAFT
builds its coordinate grid in float32 whatever the default dtype; ``float64`` makes it follow the default (the same
net code for both paths).
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import pytest
import torch

from flowsynth.train.ensemble import Ensemble, clip_grad_norms_
from flowsynth.errors import ConfigError, ShapeError
from flowsynth.train.nets import raft_small
from flowsynth.train.steps import one_cycle, train_step

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from learning import trainers

# Measured in float64: weights within 5e-13 (the largest in the biases before InstanceNorm, noise over eps), losses
# within 3e-16 relative. A joint clip or no clip moves weights by ~1e-2 in these runs; DISCERNED is what a test
# demands of a difference it must see.
WEIGHTS_ATOL = 1e-11  # [weight units]
LOSS_RTOL = 1e-10
DISCERNED = 1e-6  # [weight units]
H = W = 128  # RAFT's correlation pyramid needs 128 px a side
UPDATES = 2


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # one torch thread: tests/conftest.py


@pytest.fixture
def float64(monkeypatch):
    """Default dtype float64, and torchvision RAFT's coordinate grid in it."""
    raft_small()  # installs the shim before torchvision's model module is imported
    import torchvision.models.optical_flow.raft as tv_raft

    grid = tv_raft.make_coords_grid
    monkeypatch.setattr(tv_raft, "make_coords_grid", lambda *a, **k: grid(*a, **k).to(torch.get_default_dtype()))
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


def _nets(seeds) -> list:
    out = []
    for s in seeds:
        torch.manual_seed(s)
        out.append(raft_small())
    return out


def _batches(k: int, steps: int, flow_px: tuple, valid_share: tuple, b: int = 2, seed: int = 0) -> list:
    """``steps`` stacked batches (K, B, ...): random images, flow of scale ``flow_px[k]`` [px] (a common drift of that
    size plus noise), valid on a random ``valid_share[k]`` of the pixels."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(steps):
        img1, img2 = torch.rand(k, b, 3, H, W, generator=g), torch.rand(k, b, 3, H, W, generator=g)
        scale = torch.tensor(flow_px[:k]).view(k, 1, 1, 1, 1)
        flow = scale * (1 + 0.3 * torch.randn(k, b, 2, H, W, generator=g))
        share = torch.tensor(valid_share[:k]).view(k, 1, 1, 1, 1)
        valid = (torch.rand(k, b, 1, H, W, generator=g) < share).to(img1.dtype)
        out.append((img1, img2, flow, valid))
    return out


def _separate(nets, batches, lr, clip, norms=None) -> list[list[float]]:
    """The single-net path: per net, ``one_cycle`` and ``train_step`` on its rows of ``batches``. ``norms``: a list
    that receives each net's list of gradient norms, one a step (what clip_grad_norm_ returned)."""
    real = torch.nn.utils.clip_grad_norm_
    losses = []
    for k, net in enumerate(nets):
        opt, sched = one_cycle(net.parameters(), lr, len(batches))
        seen: list[float] = []

        def record(params, c, seen=seen):
            seen.append(float(real(params, c)))
            return seen[-1]

        torch.nn.utils.clip_grad_norm_ = record  # train_step looks it up at each call
        try:
            losses.append([train_step(net, tuple(x[k] for x in b), opt, sched, UPDATES, clip) for b in batches])
        finally:
            torch.nn.utils.clip_grad_norm_ = real
        if norms is not None:
            norms.append(seen)
    return losses


def _worst(nets_a, nets_b) -> float:
    """The largest difference of any weight between two lists of nets."""
    with torch.no_grad():
        return max(float((pa - pb).abs().max()) for a, b in zip(nets_a, nets_b)
                   for pa, pb in zip(a.parameters(), b.parameters()))


# Net 1's gradient alone exceeds the clip (every pixel valid, 20 px of flow); nets 0 and 2 see 0.4% valid pixels and
# stay below it: one step clips one net and not the others
STEPS, LR, CLIP = 3, 1e-2, 1.0
FLOW_PX, VALID_SHARE = (3.0, 20.0, 3.0), (0.004, 1.0, 0.004)


@functools.cache
def _reference() -> tuple:
    """The three nets' batches, and their separate runs (``_separate``): losses (3, STEPS), trained nets, gradient
    norms per net and step. Computed once for the tests below (each asks for ``float64``)."""
    batches = _batches(3, STEPS, flow_px=FLOW_PX, valid_share=VALID_SHARE)
    alone, norms = _nets(range(3)), []
    losses = torch.tensor(_separate(alone, batches, LR, CLIP, norms))
    return batches, losses, alone, norms


def test_three_nets_at_once_equal_three_separate_runs(float64):
    batches, losses, alone, norms = _reference()
    assert all(n > CLIP for n in norms[1]) and all(n < CLIP for n in norms[0] + norms[2])  # one net clipped, two not
    ens = Ensemble(_nets(range(3)), LR, STEPS, updates=UPDATES)
    together = torch.stack([ens.step(b) for b in batches], 1)  # (K, STEPS)
    assert torch.allclose(together, losses, rtol=LOSS_RTOL, atol=0)
    assert _worst(ens.copy_to_nets(), alone) < WEIGHTS_ATOL
    assert _worst(_nets(range(3)), alone) > DISCERNED  # the steps moved the weights well beyond the tolerance
    assert len(set(losses[:, 0].tolist())) == 3  # every net trained on its own batches


def test_each_net_is_clipped_by_its_own_gradient_norm(float64, monkeypatch):
    """Clipping changes net 1's training (a run without it differs), and a joint clip over the three nets' stacked
    gradients (the mutant) changes nets 0 and 2, which per-net clipping leaves alone."""
    batches, losses, alone, norms = _reference()
    unclipped = _nets([1])
    _separate(unclipped, [tuple(x[1:2] for x in b) for b in batches], LR, float("inf"))
    assert _worst(unclipped, alone[1:2]) > DISCERNED

    def joint(grads, c):  # the mutant: one norm over the K nets' stacked gradients, one coefficient for all
        total = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads]))
        for g in grads:
            g.mul_((c / (total + 1e-6)).clamp(max=1.0))
        return total

    import flowsynth.train.ensemble

    monkeypatch.setattr(flowsynth.train.ensemble, "clip_grad_norms_", joint)
    mutant = Ensemble(_nets(range(3)), LR, STEPS, updates=UPDATES)
    for b in batches:
        mutant.step(b)
    nets = mutant.copy_to_nets()
    assert _worst(nets[0:1], alone[0:1]) > DISCERNED and _worst(nets[2:3], alone[2:3]) > DISCERNED


def test_train_many_is_train_per_net(float64, monkeypatch, tmp_path):
    """Two nets at once, a curriculum of two stages beside a plain pool, equal two ``train`` runs: the same draws,
    checkpoints, losses and saved weights. The protocol shrinks to one 128x128 crop and two updates a step, and
    ``evaluate`` is a function of the weights, so each checkpoint's entry shows the weights it saw."""
    import flowsynth.train.steps

    monkeypatch.setattr(trainers, "BATCH", 1)
    monkeypatch.setattr(trainers, "CROP", (H, W))
    monkeypatch.setattr(trainers, "UPDATES", UPDATES)
    crop = flowsynth.train.steps.augment
    monkeypatch.setattr(flowsynth.train.steps, "augment", lambda *a: tuple(x.double() for x in crop(*a)))
    monkeypatch.setattr(trainers, "evaluate", lambda net, tests, device: {
        "weights": float(sum(p.detach().sum() for p in net.parameters()))})
    g = torch.Generator().manual_seed(2)
    pools = [(torch.randint(256, (4, 3, H + 8, W + 16), dtype=torch.uint8, generator=g),
              torch.randint(256, (4, 3, H + 8, W + 16), dtype=torch.uint8, generator=g),
              3 * torch.randn(4, 2, H + 8, W + 16, generator=g), torch.ones(4, 1, H + 8, W + 16, dtype=torch.bool))
             for _ in range(2)]
    seeds, net_seeds, stages = [3, 4], [5, 6], [1, 2]
    saves = [str(tmp_path / f"many{i}.pt") for i in range(2)]
    many = trainers.train_many(pools, {}, 3, seeds, net_seeds, 2, saves=saves, stages=stages)
    for i in range(2):
        one = trainers.train(pools[i], {}, 3, seeds[i], net_seeds[i], 2, save=str(tmp_path / f"one{i}.pt"),
                             stages=stages[i])
        assert [c["step"] for c in many[i]["curve"]] == [c["step"] for c in one["curve"]] == [0, 2, 3]
        for a, b in zip(many[i]["curve"][1:], one["curve"][1:]):
            assert a["train_loss"] == pytest.approx(b["train_loss"], rel=LOSS_RTOL)
            assert a["weights"] == pytest.approx(b["weights"], rel=1e-12)
        for name in (f"{{}}{i}.pt", f"{{}}{i}_step2.pt"):
            mine, theirs = (torch.load(tmp_path / name.format(who)) for who in ("many", "one"))
            assert max(float((mine[k] - theirs[k]).abs().max()) for k in theirs) < WEIGHTS_ATOL
        assert many[i]["net_seed"] == net_seeds[i] and many[i]["at_once"] == 2
    assert many[0]["curve"][1]["train_loss"] != many[1]["curve"][1]["train_loss"]


def test_clip_grad_norms_is_clip_grad_norm_per_net():
    g = torch.Generator().manual_seed(0)
    scale = torch.tensor([0.01, 1.0, 10.0])
    grads = [torch.randn(3, 4, 5, generator=g) * scale.view(3, 1, 1), torch.randn(3, 7, generator=g) * scale.view(3, 1)]
    want = []
    for k in range(3):
        ps = [torch.nn.Parameter(torch.zeros_like(x[k])) for x in grads]
        for p, x in zip(ps, grads):
            p.grad = x[k].clone()
        want.append((float(torch.nn.utils.clip_grad_norm_(ps, 2.0)), [p.grad for p in ps]))
    norms = clip_grad_norms_(grads, 2.0)
    for k, (norm, clipped) in enumerate(want):
        assert float(norms[k]) == pytest.approx(norm, rel=1e-6)
        assert all(torch.allclose(x[k], c, rtol=1e-6, atol=0) for x, c in zip(grads, clipped))
    assert float(norms[0]) < 2.0 < float(norms[2])  # one net kept its gradient, one was scaled down


def test_the_loop_is_train_step_per_net():
    batches = _batches(2, 1, (3.0, 3.0), (1.0, 1.0))
    ens = Ensemble(_nets([4, 5]), 1e-2, 1, updates=UPDATES, batched=False)
    losses = ens.step(batches[0])
    alone = _nets([4, 5])
    assert losses.tolist() == [x[0] for x in _separate(alone, batches, 1e-2, 1.0)]
    assert _worst(ens.copy_to_nets(), alone) == 0.0


def test_ensemble_refuses_what_it_cannot_batch():
    class Norm(torch.nn.Module):
        def __init__(self, width):
            super().__init__()
            self.conv, self.norm = torch.nn.Conv2d(3, width, 1), torch.nn.BatchNorm2d(width)

    with pytest.raises(ConfigError, match="net 1 differs"):
        Ensemble([Norm(4), Norm(5)], 1e-3, 10)
    with pytest.raises(ConfigError, match="running statistics"):
        Ensemble([Norm(4), Norm(4)], 1e-3, 10)
    Ensemble([Norm(4), Norm(4)], 1e-3, 10, batched=False)  # the loop updates each net's statistics itself
    ens = Ensemble([torch.nn.Conv2d(3, 2, 1)] * 2, 1e-3, 10)
    x = torch.zeros(2, 1, 3, 8, 8)
    with pytest.raises(ShapeError, match="K=2"):
        ens.step((x[:1], x[:1], x[:1, :, :2], x[:1, :, :1]))
    with pytest.raises(ShapeError, match="flow must be"):
        ens.step((x, x, x, x[:, :, :1]))
