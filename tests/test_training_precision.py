"""Training precision (``flowsynth.train.steps.PRECISIONS``) against float32 and against itself: a bf16 step of
RAFT-small is the float32 step up to bf16's rounding, and autocast really ran; the ensemble in bf16 is K separate bf16
``train_step`` runs; fp16's loss scaling skips a step whose gradients overflow and otherwise takes float32's step
(run on the CPU by letting ``FP16_DEVICES`` include it: the scaler's arithmetic, not CUDA's kernels); bad precisions
raise ConfigError before any work; ``Ensemble.step`` hands back a device tensor.

Why these tolerances. bfloat16 keeps 8 significant bits: one rounding is off by up to 2 ** -9 = 0.2% of the value.
Under autocast every convolution and matmul of the forward pass rounds its output to bf16, and the backward pass
rounds its gradients the same way.
"""

from __future__ import annotations

import copy
import importlib.util

import pytest
import torch
from torch import nn

import flowsynth.train.steps as tr
from flowsynth.train.ensemble import Ensemble
from flowsynth.errors import ConfigError
from flowsynth.train.steps import check_precision, grad_scaler, one_cycle, step_loss, train_step

# bf16 against float32, one step of RAFT-small from the same weights and batch. Measured: loss 0.15% apart, the
# gradient 1.1% apart (norm of the difference over the norm). A step that skipped autocast would be 0 apart: the test
# also demands a difference.
BF16_LOSS_RTOL = 1e-2  # five times bf16's rounding of one value: the loss is a mean, so the roundings average out
BF16_GRAD_RTOL = 5e-2  # the gradient sums products of rounded values through ~20 layers: a few roundings deep
AUTOCAST_SEEN = 1e-4  # float32 against itself differs by 0; bf16 by ~1e-2: the least difference that shows autocast
# The ensemble in bf16 against K separate bf16 runs. The batched forward pass runs each convolution as one grouped
# convolution, which sums in another order; bf16 rounds the two sums' outputs differently. Measured at the first step
# (the same weights): losses 2e-4 apart, against 1.2e-3 between bf16 and float32. After that Adam amplifies rounding
# noise in weights whose gradient is near zero to about the learning rate (tests/test_ensemble.py's docstring): the
# second step's losses measured 8e-4 apart.
ENS_FIRST_RTOL = 1e-3
ENS_LATER_RTOL = 5e-3
# fp16 keeps 11 significant bits (2 ** -12 = 0.02% a rounding); its gradient measured 0.04% from float32's on the tiny
# net below (bf16's: 0.24%).
FP16_GRAD_RTOL = 5e-3
# The fp16 ensemble against the loop on the tiny net (grouped against separate convolutions, as for bf16): losses
# measured 1.4e-6 apart (relative), weights 3.4e-7 after two steps that moved them by 3e-3.
ENS_FP16_RTOL = 1e-4
ENS_FP16_WEIGHTS = 1e-5  # [weight units]
MOVED = 1e-3  # [weight units] two steps at these rates move some weight by more
H = W = 128  # RAFT's correlation pyramid needs 128 px a side
UPDATES = 2


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # one torch thread: tests/conftest.py


@pytest.fixture
def fp16_on_cpu(monkeypatch):
    """Let fp16 train on the CPU, so that its loss scaling runs here."""
    monkeypatch.setattr(tr, "FP16_DEVICES", ("cuda", "cpu"))


def _raft(seed: int):
    if importlib.util.find_spec("torchvision") is None:
        pytest.skip("torchvision is not installed (scripts/setup.sh installs it for the tests)")
    from flowsynth.train.nets import raft_small

    torch.manual_seed(seed)
    return raft_small()


def _batch(b: int = 2, seed: int = 0, k: int | None = None, h: int = H, w: int = W) -> tuple:
    """Random images in [0, 1], flow of about 3 px, every pixel valid; (K, B, ...) when ``k`` is given."""
    g = torch.Generator().manual_seed(seed)
    lead = (b,) if k is None else (k, b)
    return (torch.rand(*lead, 3, h, w, generator=g), torch.rand(*lead, 3, h, w, generator=g),
            3 * (1 + 0.3 * torch.randn(*lead, 2, h, w, generator=g)), torch.ones(*lead, 1, h, w))


def _sgd(net):
    """Plain SGD at rate 1 and a constant schedule: the step moves every weight by minus its gradient."""
    opt = torch.optim.SGD(net.parameters(), lr=1.0)
    return opt, torch.optim.lr_scheduler.LambdaLR(opt, lambda step: 1.0)


def _flat(net) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in net.parameters()])


def _dtypes_seen(net) -> list:
    """Record the output dtype of every Conv2d of ``net`` in each forward pass."""
    seen: list = []
    for m in net.modules():
        if isinstance(m, nn.Conv2d):
            m.register_forward_hook(lambda mod, args, out: seen.append(out.dtype))
    return seen


def _step_and_gradient(net, batch, precision: str, scaler=None) -> tuple[torch.Tensor, torch.Tensor]:
    """One ``step_loss`` of SGD at rate 1, unclipped: (the loss, the gradient it applied)."""
    opt, sched = _sgd(net)
    before = _flat(net)
    loss = step_loss(net, batch, opt, sched, UPDATES, float("inf"), precision=precision, scaler=scaler)
    return loss, before - _flat(net)


def test_bf16_step_is_the_float32_step_within_bf16_rounding():
    base, batch = _raft(0), _batch()
    loss32, grad32 = _step_and_gradient(copy.deepcopy(base), batch, "fp32")
    net = copy.deepcopy(base)
    seen = _dtypes_seen(net)
    loss16, grad16 = _step_and_gradient(net, batch, "bf16")
    assert torch.bfloat16 in seen and loss16.dtype == torch.float32  # autocast ran; the loss is float32
    assert torch.isfinite(loss16) and torch.isfinite(grad16).all()
    rel = float((loss16 - loss32).abs() / loss32)
    assert AUTOCAST_SEEN < rel < BF16_LOSS_RTOL, rel
    rel = float((grad16 - grad32).norm() / grad32.norm())
    assert AUTOCAST_SEEN < rel < BF16_GRAD_RTOL, rel


def test_ensemble_in_bf16_is_separate_bf16_runs():
    k, steps, lr = 2, 2, 1e-3
    batches = [_batch(k=k, seed=s) for s in range(steps)]
    alone = []
    for i in range(k):
        net = _raft(i)
        opt, sched = one_cycle(net.parameters(), lr, steps)
        alone.append([train_step(net, tuple(x[i] for x in b), opt, sched, UPDATES, precision="bf16")
                      for b in batches])
    alone = torch.tensor(alone)  # (K, steps)
    nets = [_raft(i) for i in range(k)]
    seen = _dtypes_seen(nets[0])  # the batched mode runs net 0's modules with every net's weights
    ens = Ensemble(nets, lr, steps, updates=UPDATES, precision="bf16")
    out = [ens.step(b) for b in batches]
    assert all(x.shape == (k,) and x.device == batches[0][0].device and x.dtype == torch.float32
               and not x.requires_grad for x in out)
    together = torch.stack(out, 1)
    assert torch.bfloat16 in seen and torch.isfinite(together).all()
    assert torch.allclose(together[:, 0], alone[:, 0], rtol=ENS_FIRST_RTOL, atol=0), (together, alone)
    assert torch.allclose(together[:, 1:], alone[:, 1:], rtol=ENS_LATER_RTOL, atol=0), (together, alone)
    assert float((together[0] - together[1]).abs().min()) > 0.1  # each net trained on its own batches


class TinyFlow(nn.Module):
    """A RAFT-like net small enough for float16 on a CPU: ``net(img1, img2, num_flow_updates=N)`` returns N flows
    (B, 2, H, W), each the last plus a convolution of features and the last flow."""

    def __init__(self):
        super().__init__()
        self.features, self.update = nn.Conv2d(6, 8, 3, padding=1), nn.Conv2d(10, 2, 3, padding=1)

    def forward(self, img1, img2, num_flow_updates=2):
        feat = torch.relu(self.features(torch.cat([img1, img2], 1)))
        flow, out = torch.zeros_like(img1[:, :2]), []
        for _ in range(num_flow_updates):
            flow = flow + self.update(torch.cat([feat, flow.to(feat.dtype)], 1))
            out.append(flow)
        return out


def _tiny(seed: int) -> TinyFlow:
    torch.manual_seed(seed)
    return TinyFlow()


SKIPPED_STEP = "ignore:Detected call of .lr_scheduler"  # torch's warning after a skipped step
SMALL_SCALE = 2.0 ** 8  # the tiny net's gradients times 2 ** 8 stay far below float16's 65504; times 2 ** 16 not


@pytest.mark.filterwarnings(SKIPPED_STEP)
def test_fp16_skips_an_overflowing_step_and_otherwise_takes_the_float32_step(fp16_on_cpu):
    batch = _batch(h=16, w=16)
    base = _tiny(0)
    _, grad32 = _step_and_gradient(copy.deepcopy(base), batch, "fp32")
    net = copy.deepcopy(base)
    huge = torch.amp.GradScaler("cpu", init_scale=2.0 ** 40)  # the scaled gradients overflow float16 (65504)
    loss, moved = _step_and_gradient(net, batch, "fp16", huge)
    assert torch.isfinite(loss) and float(moved.abs().max()) == 0.0  # skipped: no weight moved
    assert huge.get_scale() == 2.0 ** 39  # and the scale backed off
    seen = _dtypes_seen(net)
    loss, grad16 = _step_and_gradient(net, batch, "fp16", torch.amp.GradScaler("cpu", init_scale=SMALL_SCALE))
    assert torch.float16 in seen and loss.dtype == torch.float32
    rel = float((grad16 - grad32).norm() / grad32.norm())
    assert AUTOCAST_SEEN / 10 < rel < FP16_GRAD_RTOL, rel  # unscaled before the step: float32's gradient
    with pytest.raises(ConfigError, match="scaler"):
        train_step(net, batch, *_sgd(net), precision="fp16")


@pytest.mark.filterwarnings(SKIPPED_STEP)
def test_fp16_ensemble_skips_for_all_nets_and_otherwise_matches_the_loop(fp16_on_cpu):
    """The batched mode keeps one scaler: an overflow in any net skips the step for all (ensemble.py's contract);
    without one, its steps are the loop's (a scaler per net) up to float16's rounding."""
    batches = [_batch(h=16, w=16, k=2, seed=s) for s in range(2)]
    ens = Ensemble([_tiny(0), _tiny(1)], 1e-2, 2, updates=UPDATES, precision="fp16")
    start = copy.deepcopy(ens.params)
    ens.scaler = torch.amp.GradScaler("cpu", init_scale=2.0 ** 40)
    ens.step(batches[0])
    assert all(torch.equal(start[n], p) for n, p in ens.params.items())  # both nets skipped
    ens = Ensemble([_tiny(0), _tiny(1)], 1e-2, 2, updates=UPDATES, precision="fp16")
    loop = Ensemble([_tiny(0), _tiny(1)], 1e-2, 2, updates=UPDATES, precision="fp16", batched=False)
    assert isinstance(ens.scaler, torch.amp.GradScaler) and len({id(s) for s in loop.scalers}) == 2
    ens.scaler = torch.amp.GradScaler("cpu", init_scale=SMALL_SCALE)
    loop.scalers = [torch.amp.GradScaler("cpu", init_scale=SMALL_SCALE) for _ in range(2)]
    for b in batches:
        together, alone = ens.step(b), loop.step(b)
        assert not together.requires_grad and not alone.requires_grad and together.shape == alone.shape == (2,)
        assert torch.allclose(together, alone, rtol=ENS_FP16_RTOL, atol=0)
    assert ens.scaler.get_scale() == SMALL_SCALE and all(s.get_scale() == SMALL_SCALE for s in loop.scalers)
    for a, b, c in zip(ens.copy_to_nets(), loop.copy_to_nets(), [_tiny(0), _tiny(1)]):
        assert float((_flat(a) - _flat(b)).abs().max()) < ENS_FP16_WEIGHTS
        assert float((_flat(a) - _flat(c)).abs().max()) > MOVED


@pytest.mark.parametrize("precision", ["fp8", "FP32", "float32", ""])
def test_an_unknown_precision_raises_before_any_work(precision):
    net = _tiny(0)
    before = _flat(net)
    with pytest.raises(ConfigError, match="fp32, bf16, fp16"):
        train_step(net, _batch(h=16, w=16), *one_cycle(net.parameters(), 1e-3, 1), precision=precision)
    assert torch.equal(_flat(net), before)
    with pytest.raises(ConfigError, match="not one of"):
        Ensemble([_tiny(0), _tiny(1)], 1e-3, 1, precision=precision)
    with pytest.raises(ConfigError, match="not one of"):
        grad_scaler(precision, "cpu")


def test_fp16_off_cuda_raises():
    net = _tiny(0)
    for call in (lambda: check_precision("fp16", "cpu"), lambda: grad_scaler("fp16", torch.device("cpu")),
                 lambda: Ensemble([_tiny(0), _tiny(1)], 1e-3, 1, precision="fp16"),
                 lambda: Ensemble([_tiny(0)], 1e-3, 1, precision="fp16", batched=False),
                 lambda: train_step(net, _batch(h=16, w=16), *one_cycle(net.parameters(), 1e-3, 1), precision="fp16",
                                    scaler=torch.amp.GradScaler("cpu"))):
        with pytest.raises(ConfigError, match="CUDA only.*'bf16'"):
            call()
    check_precision("fp16", "cuda")  # allowed where CUDA is (checked by name: no device needed)
    check_precision("bf16", "cpu")


def test_ensemble_step_returns_the_losses_on_the_device_without_a_graph():
    for batched in (True, False):
        ens = Ensemble([_tiny(0), _tiny(1)], 1e-3, 1, updates=UPDATES, batched=batched)
        losses = ens.step(_batch(h=16, w=16, k=2))
        assert isinstance(losses, torch.Tensor) and losses.shape == (2,) and losses.dtype == torch.float32
        assert losses.device == next(ens.modules[0].parameters()).device and not losses.requires_grad
