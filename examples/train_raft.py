"""Train torchvision's RAFT-small from scratch on flowsynth's stream, with RAFT's own recipe.

    pip install "flowsynth[train]"        # torchvision; flowsynth itself never needs it (README: the build to pick)
    python examples/train_raft.py --steps 2400 --checkpoint raft.pt --eval middlebury/   # Middlebury layout
    python examples/train_raft.py --steps 2400 --checkpoint raft.pt --sintel /data/Sintel   # or --kitti ROOT

``fs.datasets.BouncingThings`` renders pairs in DataLoader workers (no disk); each batch is cropped, flipped and
colour-jittered and trained on by ``flowsynth.train.steps.train_step``: the step the learning judge
(``benchmarks/learning/trainers.py``) measures. A progress bar shows the loss; the checkpoint (model, optimiser,
schedule and step) is written atomically every ``--save-every`` steps and at the end, and the same command resumes
from it. With ``--eval DIR`` (NAME/frame10.png, frame11.png, flow10.flo for each pair, as Middlebury ships them),
``--sintel ROOT`` or ``--kitti ROOT`` (read by torchvision's dataset classes), the end-point error (EPE) on those
real pairs is printed before and after training. ``--precision bf16`` trains under bfloat16 autocast (CPU or CUDA),
``--precision fp16`` under float16 autocast with a gradient scaler (CUDA); ``--channels-last`` keeps the net and the
images in channels_last memory (``flowsynth.train.steps``'s module docstring; ``benchmarks/speed/precision.py`` times
both).

The workers come from ``fs.datasets.loader``, a DataLoader whose workers start with forkserver: the net is on the GPU
before they start, and CUDA does not survive fork() (a forked worker would raise ``fs.ForkError``).

Exit codes: 0 done; 2 bad arguments (argparse: a step count, batch, worker count, size or rate out of range, an
unknown precision or fp16 off CUDA) or, for ``--sintel`` and ``--kitti``, a torchvision that is missing or built for
another torch (the message says what to install); 3 an evaluation folder holds no pairs.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import torch

import flowsynth as fs
from flowsynth.errors import ConfigError, DependencyError
from flowsynth.train.steps import PRECISIONS, augment, check_precision, epe, grad_scaler, one_cycle, predict, train_step

EXIT_NO_PAIRS = 3


def build_raft():
    """torchvision's RAFT-small with random weights (``flowsynth.train.nets.raft_small``)."""
    from flowsynth.train.nets import raft_small

    return raft_small(weights=None)


def stream_config(width: int, height: int) -> fs.BouncingThingsConfig:
    """The default config at ``width`` x ``height``, 2 frames; its flow range, stated at 512 px wide, scales with the
    width (as benchmarks/learning/pools.py renders it)."""
    return fs.BouncingThingsConfig(width=width, height=height, num_frames=2)


def stream(cfg, seed: int, batch: int, workers: int, start: int = 0):
    """Endless batches (img1, img2 (B, 3, H, W) in [0, 1], flow (B, 2, H, W) [px], valid (B, 1, H, W) bool)."""
    ds = fs.datasets.BouncingThings(cfg, outputs=["rgb", "flow_fw", "valid_fw"], seed=seed, start=start)
    for b in fs.datasets.loader(ds, batch_size=batch, num_workers=workers):
        yield b["rgb"][:, 0], b["rgb"][:, 1], b["flow_fw"][:, 0], b["valid_fw"][:, 0]


def middlebury_pairs(root: str) -> list[tuple]:
    """The pairs under ``root`` in Middlebury's layout (``flowsynth.io.read_middlebury``): (name, img1, img2, flow,
    valid) tensors; flow of magnitude above 1e9 (the format's "unknown") is invalid."""
    from flowsynth.io import read_middlebury

    return [(name, *(torch.from_numpy(x) for x in (img1, img2, flow)), torch.from_numpy(known)[None])
            for name, img1, img2, flow, known in read_middlebury(root)]


def torchvision_pairs(kind: str, root: str, limit: int) -> list[tuple]:
    """Up to ``limit`` training pairs of torchvision's Sintel (clean pass) or KittiFlow under ``root``; DependencyError
    where torchvision is missing or built for another torch (``flowsynth.train.nets.torchvision_datasets``)."""
    from flowsynth.train.nets import torchvision_datasets

    datasets = torchvision_datasets()
    ds = datasets.Sintel(root, split="train", pass_name="clean") if kind == "sintel" else \
        datasets.KittiFlow(root, split="train")
    out = []
    for i in range(min(limit, len(ds))):
        item = ds[i]
        img1, img2, flow = item[:3]
        valid = np.ones(flow.shape[1:], bool) if len(item) < 4 or item[3] is None else item[3]
        out.append((f"{kind}_{i}", *(torch.from_numpy(np.asarray(x, dtype=np.float32)).permute(2, 0, 1) / 255
                                     for x in (img1, img2)),
                    torch.from_numpy(np.asarray(flow, dtype=np.float32)), torch.from_numpy(np.asarray(valid))[None]))
    return out


def evaluate(net, pairs: list[tuple], device: str) -> dict:
    """EPE [px] per pair and their mean ("mean")."""
    out = {name: epe(predict(net, a[None].to(device), b[None].to(device)).cpu(), f[None], v[None])
           for name, a, b, f, v in pairs}
    return {**out, "mean": float(np.mean(list(out.values())))} if out else {}


def save_checkpoint(path: Path, net, opt, sched, step: int, scaler=None) -> None:
    """Write the checkpoint to a temporary file beside ``path``, then rename it: a crash leaves the last one whole.
    ``scaler``: fp16's gradient scaler, saved with the rest (None otherwise)."""
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"model": net.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                "scaler": None if scaler is None else scaler.state_dict(), "step": step}, tmp)
    os.replace(tmp, path)


def train(steps: int = 2400, *, width: int = 256, height: int = 192, crop: tuple[int, int] = (128, 160),
          batch: int = 6, lr: float = 4e-4, workers: int = 2, seed: int = 0, device: str = "cpu",
          checkpoint: str | None = None, save_every: int = 200, pairs: list | None = None,
          progress: bool = True, precision: str = "fp32", channels_last: bool = False) -> dict:
    """Train RAFT-small for ``steps`` steps on the stream (resuming from ``checkpoint`` when it exists) in
    ``precision`` (``flowsynth.train.steps.PRECISIONS``), net and batches in channels_last memory if ``channels_last``;
    returns the EPE on ``pairs`` before ("before", from the start or the resumed net) and after ("after"), the losses
    of the steps run here, and the step reached. Raises ConfigError for an unknown precision or fp16 off CUDA."""
    from tqdm import tqdm

    check_precision(precision, device)
    memory = torch.channels_last if channels_last else torch.contiguous_format
    torch.manual_seed(seed)
    net = build_raft().to(device, memory_format=memory)
    opt, sched = one_cycle(net.parameters(), lr, steps)
    scaler = grad_scaler(precision, device)
    start = 0
    ckpt = Path(checkpoint) if checkpoint else None
    if ckpt is not None and ckpt.is_file():
        state = torch.load(ckpt, map_location=device)
        net.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        if scaler is not None and state.get("scaler") is not None:
            scaler.load_state_dict(state["scaler"])
        start = int(state["step"])
        print(f"resumed from {ckpt} at step {start}")
    pairs = pairs or []
    before = evaluate(net, pairs, device)
    if before:
        print("EPE before: " + ", ".join(f"{k} {v:.3f}" for k, v in before.items()))
    g = torch.Generator().manual_seed(seed + start)
    losses = []
    bar = tqdm(total=steps, initial=start, unit="step", disable=not progress)
    batches = stream(stream_config(width, height), seed, batch, workers, start=start * batch)
    for step in range(start + 1, steps + 1):
        img1, img2, flow, valid = next(batches)
        aug = augment(img1, img2, flow, valid, crop, g)
        losses.append(train_step(net, tuple(x.to(device, memory_format=memory) for x in aug), opt, sched,
                                 precision=precision, scaler=scaler))
        bar.update(1)
        bar.set_postfix(loss=f"{losses[-1]:.3f}")
        if ckpt is not None and (step % save_every == 0 or step == steps):
            save_checkpoint(ckpt, net, opt, sched, step, scaler)
    bar.close()
    after = evaluate(net, pairs, device)
    if after:
        print("EPE after: " + ", ".join(f"{k} {v:.3f}" for k, v in after.items()))
    return {"before": before, "after": after, "losses": losses, "step": max(start, steps), "net": net}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--steps", type=int, default=2400)
    p.add_argument("--batch", type=int, default=6)
    p.add_argument("--width", type=int, default=256, help="rendered width [px]")
    p.add_argument("--height", type=int, default=192, help="rendered height [px]")
    p.add_argument("--crop", type=int, nargs=2, default=(128, 160), metavar=("H", "W"),
                   help="training crop; RAFT needs at least 128 px a side")
    p.add_argument("--lr", type=float, default=4e-4)
    p.add_argument("--workers", type=int, default=2, help="DataLoader workers rendering the stream")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--checkpoint", default=None, help="written every --save-every steps; resumed from if present")
    p.add_argument("--save-every", type=int, default=200)
    p.add_argument("--eval", default=None, metavar="DIR", help="a folder of pairs in Middlebury's layout")
    p.add_argument("--sintel", default=None, metavar="ROOT", help="a Sintel root (torchvision.datasets.Sintel)")
    p.add_argument("--kitti", default=None, metavar="ROOT", help="a KITTI 2015 root (torchvision.datasets.KittiFlow)")
    p.add_argument("--eval-limit", type=int, default=20, help="Sintel / KITTI pairs to evaluate on")
    p.add_argument("--precision", choices=PRECISIONS, default="fp32",
                   help="fp32; bf16 (autocast, CPU or CUDA); fp16 (autocast and a gradient scaler, CUDA only)")
    p.add_argument("--channels-last", action="store_true", help="the net and its batches in channels_last memory")
    a = p.parse_args(argv)
    for name, lo in (("steps", 1), ("batch", 1), ("workers", 0), ("save_every", 1), ("eval_limit", 1),
                     ("width", 128), ("height", 128), ("seed", 0)):
        if getattr(a, name) < lo:
            p.error(f"--{name.replace('_', '-')} {getattr(a, name)}: must be at least {lo}")
    if not a.lr > 0:
        p.error(f"--lr {a.lr}: must be above 0")
    if min(a.crop) < 128 or a.crop[0] > a.height or a.crop[1] > a.width:
        p.error(f"--crop {a.crop}: at least 128 px a side and within --height x --width")
    try:
        check_precision(a.precision, a.device)
    except (ConfigError, RuntimeError) as e:  # RuntimeError: torch cannot parse --device
        p.error(f"--precision {a.precision} on --device {a.device}: {e}")
    pairs = []
    if a.eval:
        pairs += middlebury_pairs(a.eval)
    for kind in ("sintel", "kitti"):
        if getattr(a, kind):
            try:
                pairs += torchvision_pairs(kind, getattr(a, kind), a.eval_limit)
            except DependencyError as e:
                p.error(f"--{kind}: {e}")
    if (a.eval or a.sintel or a.kitti) and not pairs:
        print("no evaluation pairs found (Middlebury layout: NAME/frame10.png, frame11.png, flow10.flo)",
              file=sys.stderr)
        return EXIT_NO_PAIRS
    train(a.steps, width=a.width, height=a.height, crop=tuple(a.crop), batch=a.batch, lr=a.lr, workers=a.workers,
          seed=a.seed, device=a.device, checkpoint=a.checkpoint, save_every=a.save_every, pairs=pairs,
          precision=a.precision, channels_last=a.channels_last)
    return 0


if __name__ == "__main__":
    sys.exit(main())
