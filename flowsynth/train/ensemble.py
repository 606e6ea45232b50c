"""K RAFT-like nets trained at once in one process, each exactly as ``flowsynth.train.steps.train_step`` would train it
alone (docs/architecture.md: the judge must fit one GPU lease). Only torch is imported; the nets come from the
caller (torchvision's ``raft_small(weights=None)``, or any module called as ``net(img1, img2, num_flow_updates=N)``
that returns the list of its N flow estimates), all of one architecture.

What each net keeps of its own: its weights, its batch (the k-th of a (K, B, ...) stack), its sequence loss, its
gradient, its gradient-norm clip (by its own total norm, as ``torch.nn.utils.clip_grad_norm_`` on that net alone)
and its AdamW moments. What the K nets share: the architecture, the learning rate schedule (``one_cycle``'s, one
``lr`` and one ``steps``), the number of flow updates and the step count.

Two ways to run the K nets (``Ensemble(..., batched=...)``):

- batched (the default): the K nets' parameters are stacked into one (K, ...) tensor each
  (``torch.func.stack_module_state``), and ``torch.func.vmap`` over K maps ``torch.func.grad_and_value`` of
  ``torch.func.functional_call`` (the forward pass, ``training.sequence_loss``, the backward pass). Every op of the
  forward and backward pass runs once for all K nets: a convolution with per-net weights as one grouped
  convolution, the correlation volume as one batched matmul, ``grid_sample`` and InstanceNorm with K folded into
  the batch. Randomness inside the net is refused (``randomness="error"``): RAFT has no dropout. Buffers are stacked
  alongside and passed through unchanged; a norm layer that updates running statistics in place (BatchNorm, or
  InstanceNorm with ``track_running_stats``) is refused, since vmap cannot write per-net buffers in place (RAFT-small
  has none: its feature encoder's InstanceNorm keeps no statistics and its context encoder has no norm layer).
  The clip is ``clip_grad_norms_`` on the stacked gradients. One ``torch.optim.AdamW`` with ``one_cycle``'s
  schedule steps the stacked parameters: AdamW works element by element, with one step count and one learning
  rate per tensor, so on a (K, ...) stack it is K AdamWs of the same schedule.
- a loop (``batched=False``, the reference): K modules, K ``one_cycle`` optimisers, ``train_step`` on each in turn.

Precision (``Ensemble(..., precision=...)``, as ``flowsynth.train.steps.train_step`` takes it): fp32, bf16 (the
forward pass under autocast, inside the vmapped function in the batched mode) or fp16 (CUDA; dynamic loss scaling).
In fp16 the loop keeps a gradient scaler per net, as K separate runs do; the batched mode keeps one for the K nets
(one optimiser), so a step in which any net's gradients overflow is skipped for all K, where separate runs would skip
it for that net alone.

``step`` returns the K losses as a tensor on the nets' device and does not wait for the device (but in fp16, where
torch's gradient scaler reads whether the gradients overflowed: one wait a step); the weights stay in the stacked
tensors until ``copy_to_nets`` copies them into the modules.
"""

from __future__ import annotations

import torch
from torch import nn

from flowsynth.errors import ConfigError, ShapeError
from flowsynth.train.steps import CLIP, autocast, check_precision, full_precision, grad_scaler, one_cycle, \
    sequence_loss, step_loss

__all__ = ["Ensemble", "clip_grad_norms_"]

CLIP_EPS = 1e-6  # added to the norm before dividing, as torch.nn.utils.clip_grad_norm_ does


def clip_grad_norms_(grads: list[torch.Tensor], clip: float) -> torch.Tensor:
    """Clip K nets' gradients in place, each net by its own total norm: ``grads`` are one (K, ...) tensor per
    parameter, row k being net k's gradient. Net k's norm is the L2 norm over all its rows; its rows are multiplied
    by min(1, clip / (norm + 1e-6)), the rule and the arithmetic of ``torch.nn.utils.clip_grad_norm_`` on that net
    alone. Returns the K norms before clipping, (K,)."""
    k = grads[0].shape[0]
    per_tensor = torch.stack([torch.linalg.vector_norm(g.reshape(k, -1), dim=1) for g in grads], 1)  # (K, P)
    norms = torch.linalg.vector_norm(per_tensor, dim=1)
    coef = (clip / (norms + CLIP_EPS)).clamp(max=1.0)
    for g in grads:
        g.mul_(coef.view(k, *(1,) * (g.ndim - 1)).to(g.dtype))
    return norms


def _check_stack(batch: tuple, k: int) -> None:
    img1, img2, flow, valid = batch
    if img1.ndim != 5 or img1.shape[0] != k or img1.shape[2] != 3 or img2.shape != img1.shape:
        raise ShapeError(f"images must be two (K={k}, B, 3, H, W) tensors of one shape, got {tuple(img1.shape)} and "
                         f"{tuple(img2.shape)}")
    want = (img1.shape[:2] + (2,) + img1.shape[3:], img1.shape[:2] + (1,) + img1.shape[3:])
    if tuple(flow.shape) != want[0] or tuple(valid.shape) != want[1]:
        raise ShapeError(f"flow must be {want[0]} and valid {want[1]} for images {tuple(img1.shape)}, got "
                         f"{tuple(flow.shape)} and {tuple(valid.shape)}")


class Ensemble:
    """K nets trained at once by RAFT's recipe (the module docstring says what is batched and what each net keeps).

    ``nets``: K modules of one architecture (the same parameter and buffer names, shapes, dtypes and devices), each
    initialised as its own run would be; they are trained in place of K ``train_step`` runs with
    ``one_cycle(net.parameters(), lr, steps, weight_decay, pct_start)`` each. ``updates`` flow updates a step,
    gradient norm clipped at ``clip`` per net, the forward pass in ``precision`` (``flowsynth.train.steps.PRECISIONS``).
    In the batched mode the weights live in stacked tensors while training and ``copy_to_nets()`` copies them back
    into the modules. Raises ConfigError for no nets, nets of different architectures, running statistics in the
    batched mode, an unknown precision, or fp16 off CUDA."""

    def __init__(self, nets: list[nn.Module], lr: float, steps: int, *, updates: int = 8, clip: float = CLIP,
                 weight_decay: float = 1e-4, pct_start: float = 0.05, batched: bool = True, precision: str = "fp32"):
        if not nets:
            raise ConfigError("Ensemble needs at least one net")
        self.modules, self.updates, self.clip, self.batched = list(nets), updates, clip, batched
        self.device = next(nets[0].parameters()).device
        check_precision(precision, self.device)
        self.precision = precision
        if not batched:
            self.opts = [one_cycle(net.parameters(), lr, steps, weight_decay, pct_start) for net in self.modules]
            self.scalers = [grad_scaler(precision, self.device) for _ in self.modules]
            return
        first = {n: (p.shape, p.dtype, p.device) for n, p in (*nets[0].named_parameters(), *nets[0].named_buffers())}
        for i, net in enumerate(nets[1:], 1):
            other = {n: (p.shape, p.dtype, p.device) for n, p in (*net.named_parameters(), *net.named_buffers())}
            if other != first:
                raise ConfigError(f"net {i} differs from net 0 in its parameters or buffers (names, shapes, dtypes "
                                  "or devices): an Ensemble's nets share one architecture")
        stats = [n for n, m in nets[0].named_modules()
                 if getattr(m, "track_running_stats", False) and getattr(m, "running_mean", None) is not None]
        if stats:
            raise ConfigError(f"{stats[:3]} keep running statistics, which the batched mode cannot update per net; "
                              "use Ensemble(..., batched=False)")
        params, buffers = torch.func.stack_module_state(self.modules)
        self.params = {n: p.detach() for n, p in params.items()}  # (K, ...) leaves, one per parameter
        self.buffers = {n: b.detach() for n, b in buffers.items()}
        self.opt, self.sched = one_cycle(list(self.params.values()), lr, steps, weight_decay, pct_start)
        self.scaler = grad_scaler(precision, self.device)
        template = self.modules[0]  # functional_call runs it with each net's weights in place of its own

        def loss(params: dict, buffers: dict, scale, img1, img2, flow, valid):
            with autocast(precision, self.device):
                preds = torch.func.functional_call(template, (params, buffers), (img1 * 2 - 1, img2 * 2 - 1),
                                                   {"num_flow_updates": self.updates})
            value = sequence_loss([full_precision(p) for p in preds], flow, valid)
            return (value if scale is None else value * scale), value

        self._grads = torch.func.vmap(torch.func.grad_and_value(loss, has_aux=True), in_dims=(0, 0, None, 0, 0, 0, 0),
                                      randomness="error")

    def step(self, batch: tuple) -> torch.Tensor:
        """One step of RAFT's recipe for every net: ``batch`` = (img1, img2, flow, valid), (K, B, 3, H, W),
        (K, B, 3, H, W) in [0, 1], (K, B, 2, H, W) [px], (K, B, 1, H, W), on the nets' device; net k trains on row k
        (augmented as ``train_step``'s batch is). Returns the K losses, (K,), detached, in the dtype of the loss
        (float32 for float32 nets, whatever the precision) on the nets' device: the caller synchronises when it reads
        them (the module docstring says when a step waits)."""
        _check_stack(batch, len(self.modules))
        if not self.batched:
            return torch.stack([step_loss(net, tuple(x[k] for x in batch), opt, sched, self.updates, self.clip,
                                          precision=self.precision, scaler=scaler)
                                for k, (net, (opt, sched), scaler) in enumerate(zip(self.modules, self.opts,
                                                                                    self.scalers))])
        self.modules[0].train()
        scale = None if self.scaler is None else self.scaler.scale(torch.ones((), device=self.device))
        grads, (_, losses) = self._grads(self.params, self.buffers, scale, *batch)
        for name, p in self.params.items():
            p.grad = grads[name]
        if self.scaler is not None:
            self.scaler.unscale_(self.opt)
        clip_grad_norms_([p.grad for p in self.params.values()], self.clip)
        if self.scaler is None:
            self.opt.step()
        else:
            self.scaler.step(self.opt)
            self.scaler.update()
        self.sched.step()
        self.opt.zero_grad(set_to_none=True)
        return losses.detach()

    @torch.no_grad()
    def copy_to_nets(self) -> list[nn.Module]:
        """Copy the current weights into the K modules (in the batched mode, from the stacked tensors: a copy of every
        parameter and buffer, which waits for the device) and return them."""
        if self.batched:
            for k, net in enumerate(self.modules):
                for name, t in (*net.named_parameters(), *net.named_buffers()):
                    t.copy_((self.params if name in self.params else self.buffers)[name][k])
        return self.modules
