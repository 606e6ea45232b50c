"""Train a small optical-flow network on flowsynth samples streamed through ``fs.datasets.loader`` (no disk).

    python examples/train_flow.py --steps 200 --workers 2

Prints the training loss and the end-point error (EPE) on held-out streamed samples as it goes.
"""

from __future__ import annotations

import argparse
import time

import torch
from torch import nn
from torch.utils.data import DataLoader

import flowsynth as fs


class TinyFlowNet(nn.Module):
    """A few strided convolutions on the stacked frame pair, upsampled flow (2, H, W) [px]."""

    def __init__(self, width: int = 32) -> None:
        super().__init__()
        c = width
        self.encoder = nn.Sequential(
            nn.Conv2d(6, c, 3, padding=1), nn.ReLU(),
            nn.Conv2d(c, c, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(c, 2 * c, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(2 * c, 2 * c, 3, padding=2, dilation=2), nn.ReLU(),
            nn.Conv2d(2 * c, 2, 3, padding=1),
        )

    def forward(self, img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
        x = torch.cat([img1, img2], 1) * 2.0 - 1.0
        flow = self.encoder(x) * 4.0  # quarter resolution, in quarter-resolution pixels
        return nn.functional.interpolate(flow, size=img1.shape[-2:], mode="bilinear", align_corners=False) * 4.0


def epe(pred: torch.Tensor, flow: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean end-point error [px] over valid pixels."""
    err = (pred - flow).norm(dim=1, keepdim=True)
    return (err * valid).sum() / valid.sum().clamp(min=1)


def loader(cfg, seed: int, batch_size: int, workers: int, start: int = 0) -> DataLoader:
    """``fs.datasets.loader`` over the stream: its workers start with forkserver (or spawn), so a net already on the
    GPU does no harm (CUDA does not survive fork(); a forked worker would raise ``fs.ForkError``)."""
    ds = fs.datasets.BouncingThings(cfg, outputs=["rgb", "flow_fw", "valid_fw"], seed=seed, start=start)
    return fs.datasets.loader(ds, batch_size=batch_size, num_workers=workers)


def batches(cfg, seed: int, batch_size: int, workers: int, start: int = 0):
    """Endless batches (img1, img2 (B, 3, H, W) in [0, 1], flow (B, 2, H, W) [px], valid (B, 1, H, W) float)."""
    for b in loader(cfg, seed, batch_size, workers, start):
        yield b["rgb"][:, 0], b["rgb"][:, 1], b["flow_fw"][:, 0], b["valid_fw"][:, 0].float()


def train(steps: int = 200, *, width: int = 64, height: int = 48, batch_size: int = 4, workers: int = 2,
          lr: float = 2e-3, eval_batches: int = 2, log_every: int = 10, seed: int = 0) -> dict:
    """Train TinyFlowNet for ``steps`` steps; returns held-out EPE before and after and the loss history."""
    torch.manual_seed(seed)
    # Motion: 1/128 to 1/16 of the width per frame (4-32 px at 512 px wide, scaled to the width by the config;
    # smaller than the default's 2-48: a tiny net on tiny images learns small motions first).
    cfg = fs.BouncingThingsConfig(width=width, height=height, num_frames=2, motion="kinematic",
                                  render_mode="flat", num_objects=(3, 6), flow_px=(4.0, 32.0))
    held_out = list(zip(range(eval_batches), batches(cfg, seed + 1, batch_size, 0)))
    net = TinyFlowNet()
    opt = torch.optim.Adam(net.parameters(), lr=lr)

    def evaluate() -> float:
        with torch.no_grad():
            return float(sum(epe(net(a, b), f, v) for _, (a, b, f, v) in held_out) / len(held_out))

    before = evaluate()
    print(f"held-out EPE before training: {before:.3f} px")
    history = []
    t0 = time.time()
    for step, (a, b, f, v) in enumerate(batches(cfg, seed, batch_size, workers), 1):
        loss = epe(net(a, b), f, v)
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.append(loss.item())
        if step % log_every == 0 or step == steps:
            print(f"step {step:5d}  loss (train EPE) {sum(history[-log_every:]) / len(history[-log_every:]):.3f} px"
                  f"  held-out EPE {evaluate():.3f} px  {step / (time.time() - t0):.1f} steps/s")
        if step == steps:
            break
    after = evaluate()
    print(f"held-out EPE after {steps} steps: {after:.3f} px (before: {before:.3f} px)")
    return {"before": before, "after": after, "history": history}


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--width", type=int, default=64)
    p.add_argument("--height", type=int, default=48)
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--workers", type=int, default=2)
    a = p.parse_args()
    train(a.steps, width=a.width, height=a.height, batch_size=a.batch_size, workers=a.workers)
