"""RAFT-small's training step by precision, memory format and threads: s/step and the ratio to float32.

    python benchmarks/speed/precision.py [--quick] [--threads 1 2] [--steps N] [--warmup N] [--rounds R] [--device D]

``flowsynth.train.steps.train_step`` on ``flowsynth.train.nets.raft_small`` at protocol 0023's shape (batch 6, 128x160
crops, 8 flow updates, random images and flow), for every combination of precision (fp32, bf16; fp16 too on CUDA),
memory format (contiguous, or channels_last: the net converted before its optimiser is made, the images converted each
step) and torch thread count. Every configuration keeps its own net (one seed for all) and optimiser; each round runs
every configuration in turn, ``--warmup`` untimed steps then ``--steps`` timed ones, so load changes on a shared
machine hit all of them alike. Per configuration: the median over rounds of the mean s/step, and its ratio to fp32 with
contiguous memory at the same thread count (below 1: faster). Prints a table; writes
results/precision[_quick].json and a bar chart results/precision[_quick].png when matplotlib is there. ``--quick``
(the suite's smoke run): batch 2, one thread, one warm-up and one timed step, one round; its ratios mean nothing.
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common

from _common import machine_info, print_table, pyplot, save_figure, write_json

BATCH, CROP, UPDATES = 6, (128, 160), 8  # protocol 0023's training step
LR, SEED = 4e-4, 0
FORMATS = ("contiguous", "channels_last")


class Config:
    """One configuration's net, optimiser and scaler, and the step that trains it on the fixed batch."""

    def __init__(self, precision: str, fmt: str, threads: int, batch: tuple, device: str):
        import torch

        from flowsynth.train.nets import raft_small
        from flowsynth.train.steps import grad_scaler, one_cycle

        self.precision, self.fmt, self.threads = precision, fmt, threads
        self.memory = torch.channels_last if fmt == "channels_last" else torch.contiguous_format
        torch.manual_seed(SEED)
        self.net = raft_small().to(device, memory_format=self.memory)
        self.opt, self.sched = one_cycle(self.net.parameters(), LR, 10_000)
        self.scaler = grad_scaler(precision, device)
        self.batch = batch

    def step(self) -> float:
        """One training step; returns its loss (read from the device: the step has finished)."""
        import torch

        from flowsynth.train.steps import train_step

        torch.set_num_threads(self.threads)
        img1, img2, flow, valid = self.batch
        images = (img1.contiguous(memory_format=self.memory), img2.contiguous(memory_format=self.memory))
        return train_step(self.net, (*images, flow, valid), self.opt, self.sched, UPDATES, precision=self.precision,
                          scaler=self.scaler)


def random_batch(batch: int, device: str) -> tuple:
    """Images (B, 3, H, W) in [0, 1] twice, flow (B, 2, H, W) of about 5 px, valid (B, 1, H, W) everywhere."""
    import torch

    g = torch.Generator().manual_seed(SEED)
    h, w = CROP
    out = (torch.rand(batch, 3, h, w, generator=g), torch.rand(batch, 3, h, w, generator=g),
           5 * torch.randn(batch, 2, h, w, generator=g), torch.ones(batch, 1, h, w))
    return tuple(x.to(device) for x in out)


def measure(configs: list[Config], warmup: int, steps: int, rounds: int) -> list[list[float]]:
    """Per configuration, the mean s/step of each round (configurations in turn within a round)."""
    out = [[] for _ in configs]
    for _ in range(rounds):
        for times, cfg in zip(out, configs):
            for _ in range(warmup):
                cfg.step()
            t = time.perf_counter()
            for _ in range(steps):
                cfg.step()
            times.append((time.perf_counter() - t) / steps)
    return out


def plot(rows: list[dict], name: str) -> None:
    """Bars of s/step per configuration, grouped by thread count (nothing without matplotlib)."""
    plt = pyplot()
    if plt is None:
        return
    fig, ax = plt.subplots(figsize=(1.5 + 0.8 * len(rows), 3.6))
    labels = [f"{r['precision']} {r['memory']}\n{r['threads']} thr" for r in rows]
    ax.bar(range(len(rows)), [r["s/step"] for r in rows])
    ax.set_xticks(range(len(rows)), labels, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("s / training step")
    ax.set_title("RAFT-small training step by precision, memory format, threads")
    fig.tight_layout()
    save_figure(fig, name, dpi=120)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="batch 2, 1 thread, 1 warm-up and 1 timed step, 1 round")
    p.add_argument("--threads", type=int, nargs="+", default=None, help="torch thread counts (default 1 2; --quick 1)")
    p.add_argument("--steps", type=int, default=None, help="timed steps a configuration and round (default 4)")
    p.add_argument("--warmup", type=int, default=None, help="untimed steps before them (default 2)")
    p.add_argument("--rounds", type=int, default=None, help="alternated rounds (default 3)")
    p.add_argument("--device", default="cpu", help="torch device (cpu, cuda); fp16 joins the precisions on cuda")
    a = p.parse_args(argv)
    steps = a.steps if a.steps is not None else (1 if a.quick else 4)
    warmup = a.warmup if a.warmup is not None else (1 if a.quick else 2)
    rounds = a.rounds if a.rounds is not None else (1 if a.quick else 3)
    threads = a.threads if a.threads is not None else ([1] if a.quick else [1, 2])
    for name, v, lo in (("steps", steps, 1), ("warmup", warmup, 0), ("rounds", rounds, 1),
                        ("threads", min(threads), 1)):
        if v < lo:
            p.error(f"--{name} {v}: must be at least {lo}")
    import torch

    from flowsynth.errors import DependencyError
    from flowsynth.train.steps import FP16_DEVICES, PRECISIONS

    try:
        device = torch.device(a.device)
    except RuntimeError as e:
        p.error(f"--device {a.device}: {e}")
    if device.type == "cuda" and not torch.cuda.is_available():
        p.error(f"--device {a.device}: CUDA is not available here")
    batch_size = 2 if a.quick else BATCH
    precisions = tuple(x for x in PRECISIONS if x != "fp16" or device.type in FP16_DEVICES)
    batch = random_batch(batch_size, a.device)
    try:
        configs = [Config(prec, fmt, t, batch, a.device)
                   for t, prec, fmt in itertools.product(threads, precisions, FORMATS)]
    except DependencyError as e:
        print(f"SKIPPED: {e}")
        return 0
    times = measure(configs, warmup, steps, rounds)
    rows = []
    for cfg, ts in zip(configs, times):
        rows.append({"threads": cfg.threads, "precision": cfg.precision, "memory": cfg.fmt,
                     "s/step": statistics.median(ts)})
    base = {r["threads"]: r["s/step"] for r in rows if r["precision"] == "fp32" and r["memory"] == "contiguous"}
    for r in rows:
        r["x fp32"] = r["s/step"] / base[r["threads"]]
    print(f"RAFT-small train_step on {a.device}: batch {batch_size}, {CROP[0]}x{CROP[1]} crops, {UPDATES} updates; "
          f"{warmup} warm-up + {steps} timed steps a configuration, {rounds} round(s) alternated")
    print_table(rows, list(rows[0]))
    name = "precision" + ("_quick" if a.quick else "")
    write_json(name, {"device": a.device, "batch": batch_size, "crop": CROP, "updates": UPDATES, "steps": steps,
                      "warmup": warmup, "rounds": rounds, "rows": rows,
                      "runs": [{"threads": c.threads, "precision": c.precision, "memory": c.fmt,
                                "s/step each round": ts} for c, ts in zip(configs, times)],
                      "machine": machine_info(["torch"])})
    plot(rows, name)
    return 0


if __name__ == "__main__":
    sys.exit(main())
