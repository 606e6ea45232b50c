"""RAFT's training recipe, scaled down, for any net with torchvision RAFT's calling convention.

One training step (``train_step``) serves both ``examples/train_raft.py`` and the learning judge
(``benchmarks/learning/trainers.py``), so what the judge measures is what a user runs. Only torch is imported: the net
(torchvision's ``raft_small(weights=None)``, or any module called as ``net(img1, img2, num_flow_updates=N)`` that
returns the list of its N flow estimates) comes from the caller; flowsynth never depends on torchvision.

The recipe, as in torchvision's ``references/optical_flow`` (RAFT, Teed and Deng 2020):

- images (B, 3, H, W) float32 in [0, 1], handed to the net as 2x - 1 (RAFT's normalisation);
- sequence loss: L1 over valid pixels of every update, weighted gamma ** (N - 1 - i), gamma 0.8; pixels whose true
  flow exceeds ``max_flow`` px are left out (``sequence_loss``);
- AdamW with a linear one-cycle schedule (5% warm-up), gradient norm clipped at 1 (``one_cycle``);
- augmentation (``augment``): a random crop, flips (left-right 0.5, up-down 0.1; the flow's sign follows), and
  colour jitter of brightness, contrast and saturation (0.4) and hue (0.5 / pi of a turn), the same for both
  frames except with probability 0.2, when each frame draws its own (RAFT's asymmetric jitter).

Precision (``PRECISIONS``, the ``precision`` argument of ``train_step`` and ``flowsynth.train.ensemble.Ensemble``): the
weights, the optimiser and the loss stay float32 in every mode; what changes is the net's forward pass.

- ``"fp32"`` (the default): no autocast; the net runs in its own dtype.
- ``"bf16"``: the forward pass under ``torch.autocast`` to bfloat16, on the CPU or CUDA. bfloat16 keeps float32's
  exponent range, so no loss scaling is needed.
- ``"fp16"``: the forward pass under ``torch.autocast`` to float16, with dynamic loss scaling
  (``torch.amp.GradScaler``: the loss is multiplied before the backward pass, the gradients divided back before the
  clip, and a step whose gradients overflowed is skipped while the scale backs off). CUDA only.

The net's flow estimates are cast up to float32 (when they come out in a lower precision) before the sequence loss.
"""

from __future__ import annotations

import math

import torch
from torch.nn import functional as F

from flowsynth.errors import ConfigError, ShapeError

GAMMA = 0.8  # weight decay of earlier updates in the sequence loss (RAFT)
MAX_FLOW = 400.0  # [px] larger true flow is left out of the loss (RAFT)
CLIP = 1.0  # gradient norm clip (RAFT)
JITTER = 0.4  # brightness, contrast and saturation factors drawn from [1 - JITTER, 1 + JITTER] (RAFT)
HUE = 0.5 / math.pi  # hue shift drawn from [-HUE, HUE] of a full turn (RAFT: ColorJitter(hue=0.5 / 3.14))
ASYMMETRIC = 0.2  # chance that the two frames draw their jitter separately (RAFT)
PAD = 8  # RAFT's features are at 1/8 resolution: sides are padded to a multiple of this
PRECISIONS = ("fp32", "bf16", "fp16")  # training precisions (module docstring)
AUTOCAST = {"bf16": torch.bfloat16, "fp16": torch.float16}  # the forward pass's dtype under autocast
FP16_DEVICES = ("cuda",)  # device types that train in fp16; CPUs train in bf16, whose range needs no loss scaling


def check_precision(precision: str, device: torch.device | str) -> None:
    """Raise ConfigError unless ``precision`` is one of ``PRECISIONS`` and trains on ``device`` (fp16: CUDA only)."""
    if precision not in PRECISIONS:
        raise ConfigError(f"precision {precision!r} is not one of {', '.join(PRECISIONS)}")
    kind = torch.device(device).type
    if precision == "fp16" and kind not in FP16_DEVICES:
        raise ConfigError(f"precision 'fp16' trains on CUDA only (its gradient scaler), not on {kind!r}: use 'bf16' "
                          "or 'fp32' there")


def autocast(precision: str, device: torch.device | str):
    """The context for a forward pass in ``precision`` on ``device``: ``torch.autocast`` to ``AUTOCAST[precision]``,
    disabled for fp32. Raises ConfigError as ``check_precision``."""
    check_precision(precision, device)
    kind = torch.device(device).type
    return torch.autocast(kind, dtype=AUTOCAST.get(precision, torch.bfloat16), enabled=precision != "fp32")


def grad_scaler(precision: str, device: torch.device | str) -> torch.amp.GradScaler | None:
    """The gradient scaler ``train_step`` needs for ``precision`` on ``device``: a ``torch.amp.GradScaler`` (torch's
    defaults: initial scale 2 ** 16, halved on an overflow, doubled after 2000 steps without one) for fp16, None
    otherwise. One scaler serves one optimiser for a whole run; save its ``state_dict`` with the optimiser's. Raises
    ConfigError as ``check_precision``."""
    check_precision(precision, device)
    return torch.amp.GradScaler(torch.device(device).type) if precision == "fp16" else None


def full_precision(x: torch.Tensor) -> torch.Tensor:
    """``x`` as float32 if it is bfloat16 or float16; otherwise ``x`` itself (float32 and float64 pass unchanged)."""
    return x.float() if x.dtype in (torch.bfloat16, torch.float16) else x


def _check_pair(img1: torch.Tensor, img2: torch.Tensor) -> None:
    if img1.ndim != 4 or img1.shape[1] != 3 or img1.shape != img2.shape:
        raise ShapeError(f"images must be two (B, 3, H, W) tensors of one shape, got {tuple(img1.shape)} and "
                         f"{tuple(img2.shape)}")


def sequence_loss(preds: list[torch.Tensor], flow: torch.Tensor, valid: torch.Tensor, gamma: float = GAMMA,
                  max_flow: float = MAX_FLOW) -> torch.Tensor:
    """RAFT's loss: sum over the N estimates ``preds`` (each (B, 2, H, W) [px]) of gamma ** (N - 1 - i) times the
    mean L1 error against ``flow`` (B, 2, H, W) [px] over pixels where ``valid`` (B, 1, H, W) (bool or 0/1) holds
    and |flow| < ``max_flow``; invalid pixels count as zero error in the mean (torchvision's reference does the
    same)."""
    mask = (valid.reshape(flow.shape[0], 1, *flow.shape[-2:]) > 0.5) & (
        torch.linalg.vector_norm(flow, dim=1, keepdim=True) < max_flow)
    n = len(preds)
    return sum(gamma ** (n - 1 - i) * ((p - flow).abs() * mask).mean() for i, p in enumerate(preds))


def _jitter_one(img: torch.Tensor, factors: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) in [0, 1] with per-image brightness, contrast, saturation (multiplicative) and hue (a turn's
    fraction, rotated in YIQ) from ``factors`` (B, 4)."""
    b, c, s, h = (factors[:, k, None, None, None] for k in range(4))
    img = (img * b).clamp(0, 1)
    grey = (0.299 * img[:, 0:1] + 0.587 * img[:, 1:2] + 0.114 * img[:, 2:3])
    img = (grey.mean((2, 3), keepdim=True) + c * (img - grey.mean((2, 3), keepdim=True))).clamp(0, 1)
    grey = 0.299 * img[:, 0:1] + 0.587 * img[:, 1:2] + 0.114 * img[:, 2:3]
    img = (grey + s * (img - grey)).clamp(0, 1)
    yiq = torch.tensor([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]], dtype=img.dtype,
                       device=img.device)
    q = torch.einsum("kc,bchw->bkhw", yiq, img)
    cos, sin = torch.cos(2 * math.pi * h), torch.sin(2 * math.pi * h)
    i, qq = q[:, 1:2] * cos - q[:, 2:3] * sin, q[:, 1:2] * sin + q[:, 2:3] * cos
    rgb = torch.einsum("kc,bchw->bkhw", torch.linalg.inv(yiq), torch.cat([q[:, 0:1], i, qq], 1))
    return rgb.clamp(0, 1)


def _draw_jitter(n: int, g: torch.Generator) -> torch.Tensor:
    u = torch.rand(n, 4, generator=g)
    return torch.cat([1 + JITTER * (2 * u[:, :3] - 1), HUE * (2 * u[:, 3:] - 1)], 1)


def augment(img1: torch.Tensor, img2: torch.Tensor, flow: torch.Tensor, valid: torch.Tensor,
            crop: tuple[int, int], g: torch.Generator, hflip: float = 0.5, vflip: float = 0.1):
    """RAFT's augmentation of a batch, drawn from generator ``g`` (CPU): a random ``crop`` = (h, w) window per
    pair, flips and colour jitter (module docstring). Inputs: images (B, 3, H, W) float in [0, 1] (or uint8, scaled
    by 1/255), ``flow`` (B, 2, H, W) [px], ``valid`` (B, 1, H, W). Returns the four cropped tensors, the images float32
    in [0, 1] and ``valid`` float32 0/1."""
    _check_pair(img1, img2)
    bsz, _, H, W = img1.shape
    h, w = crop
    if h > H or w > W:
        raise ShapeError(f"crop {crop} is larger than the images ({H}, {W})")
    if img1.dtype == torch.uint8:
        img1, img2 = img1.float() / 255, img2.float() / 255
    y0 = torch.randint(H - h + 1, (bsz,), generator=g)
    x0 = torch.randint(W - w + 1, (bsz,), generator=g)
    flips = torch.rand(bsz, 2, generator=g)
    out = [[], [], [], []]
    for k in range(bsz):
        win = (slice(None), slice(int(y0[k]), int(y0[k]) + h), slice(int(x0[k]), int(x0[k]) + w))
        a, b, f, v = img1[k][win], img2[k][win], flow[k][win].clone(), valid[k][win].float()
        if flips[k, 0] < hflip:
            a, b, f, v = (x.flip(-1) for x in (a, b, f, v))
            f[0] = -f[0]
        if flips[k, 1] < vflip:
            a, b, f, v = (x.flip(-2) for x in (a, b, f, v))
            f[1] = -f[1]
        for lst, x in zip(out, (a, b, f, v)):
            lst.append(x)
    img1, img2, flow, valid = (torch.stack(x) for x in out)
    f1 = _draw_jitter(bsz, g)
    f2 = torch.where((torch.rand(bsz, 1, generator=g) < ASYMMETRIC), _draw_jitter(bsz, g), f1)
    return _jitter_one(img1.float(), f1), _jitter_one(img2.float(), f2), flow.float(), valid


def one_cycle(params, lr: float, steps: int, weight_decay: float = 1e-4, pct_start: float = 0.05):
    """RAFT's optimiser: AdamW (eps 1e-8) and a linear one-cycle schedule to ``lr`` over ``steps`` steps (without
    momentum cycling). Returns (optimizer, scheduler); call the scheduler once per step."""
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay, eps=1e-8)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps + 100, pct_start=pct_start,
                                                cycle_momentum=False, anneal_strategy="linear")
    return opt, sched


def train_step(net, batch: tuple, opt, sched, updates: int = 8, clip: float = CLIP, *, precision: str = "fp32",
               scaler: torch.amp.GradScaler | None = None) -> float:
    """One step of RAFT's recipe on ``batch`` = (img1, img2, flow, valid) (augmented, on the net's device; images in
    [0, 1]): ``updates`` flow updates, the sequence loss, backward, gradient clipping at ``clip``, an optimiser and a
    scheduler step. ``precision``: one of ``PRECISIONS`` (module docstring). ``scaler``: the run's gradient scaler,
    used when given; fp16 needs one (``grad_scaler("fp16", device)``). Returns the loss (float32 from the net's
    outputs, whatever the precision). Raises ConfigError for an unknown precision, fp16 off CUDA, or fp16 without a
    scaler."""
    return float(step_loss(net, batch, opt, sched, updates, clip, precision=precision, scaler=scaler))


def step_loss(net, batch: tuple, opt, sched, updates: int = 8, clip: float = CLIP, *, precision: str = "fp32",
              scaler: torch.amp.GradScaler | None = None) -> torch.Tensor:
    """``train_step`` without the wait for the device: the same step, the same arguments and errors; returns the loss
    as a 0-dim tensor on the batch's device (detached), which the caller reads when it chooses to synchronise (in
    fp16, torch's gradient scaler waits once a step to read whether the gradients overflowed)."""
    img1, img2, flow, valid = batch
    _check_pair(img1, img2)
    check_precision(precision, img1.device)
    if precision == "fp16" and scaler is None:
        raise ConfigError("precision 'fp16' needs the run's gradient scaler: scaler=grad_scaler('fp16', device)")
    net.train()
    with autocast(precision, img1.device):
        preds = net(img1 * 2 - 1, img2 * 2 - 1, num_flow_updates=updates)
    loss = sequence_loss([full_precision(p) for p in preds], flow, valid)
    opt.zero_grad(set_to_none=True)
    if scaler is None:
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), clip)
        opt.step()
    else:
        scaler.scale(loss).backward()
        scaler.unscale_(opt)
        torch.nn.utils.clip_grad_norm_(net.parameters(), clip)
        scaler.step(opt)
        scaler.update()
    sched.step()
    return loss.detach()


@torch.no_grad()
def predict(net, img1: torch.Tensor, img2: torch.Tensor, updates: int = 12) -> torch.Tensor:
    """The net's final flow (B, 2, H, W) [px] for images (B, 3, H, W) in [0, 1] of any size: padded on the bottom
    and right to a multiple of 8 by edge replication (at least 128 px a side, which RAFT's correlation pyramid
    needs), the flow cropped back."""
    _check_pair(img1, img2)
    net.eval()
    h, w = img1.shape[-2:]
    ph, pw = max(-h % PAD, 128 - h), max(-w % PAD, 128 - w)
    ph, pw = ph + (-(h + ph) % PAD), pw + (-(w + pw) % PAD)
    if ph or pw:
        img1, img2 = (F.pad(x, (0, pw, 0, ph), mode="replicate") for x in (img1, img2))
    return net(img1 * 2 - 1, img2 * 2 - 1, num_flow_updates=updates)[-1][..., :h, :w]


def epe(pred: torch.Tensor, flow: torch.Tensor, valid: torch.Tensor) -> float:
    """Mean end-point error [px] of ``pred`` against ``flow`` (B, 2, H, W) over the pixels where ``valid`` (B, 1, H, W)
    holds; 0 where none does."""
    v = valid > 0.5
    err = torch.linalg.vector_norm(pred.detach() - flow, dim=1, keepdim=True)
    return float(err[v].sum() / v.sum().clamp(min=1))
