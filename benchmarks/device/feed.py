"""A training loop fed by the live stream: does RAFT-small's training step wait for data?

    python benchmarks/device/feed.py [--quick] [--device cuda] [--workers K] [--steps N] [--source stream|device]

Two loops run the same step: RAFT's augmentation (``flowsynth.train.steps.augment``: crop, flips, jitter) on the host,
then ``flowsynth.train.steps.train_step`` on ``--device`` (torchvision's ``raft_small(weights=None)``, batch 6, 128x160
crops, 8 updates: protocol 0023's recipe, decision 0023), on pairs of the default config at 256x192, 2 frames, its
``flow_px`` halved as the judge renders it.

- **in memory**: batches drawn at random from a pool of ``--pool`` pairs rendered before the clock (the rate a
  loop reaches when data is free);
- **live**: each batch is the next one the stream hands over. ``--source stream``: ``fs.datasets.loader`` with
  ``--workers`` K processes rendering on the CPU (forkserver: this process has put the net on the device first, as a
  training script does). ``--source device``: ``fs.datasets.DeviceBatches`` (scenes from K CPU workers, every
  per-pixel stage once per batch on ``--device``; the clock waits for the batch's render before it counts the step,
  and the host augmentation copies the batch to the host and back).

Reported per loop, after ``--warmup`` steps (the live loop's also drains the 2 batches per worker prefetched while
the in-memory loop ran): steps/s; for the live loop the share of its wall time spent waiting in
``next(batch)`` ("wait") and its rate over the in-memory rate ("live / in memory"). The goal where a GPU is lent
(16 cores, H100 or H200): live / in memory >= 0.9. On this 2-core machine without a GPU it runs as a smoke test
(``--quick``: 160x128 pairs, 128x128 crops, batch 2, 2 updates, a few steps).

Writes benchmarks/results/feed[_device][_quick].json (``_device`` with --source device, ``_quick`` with --quick) with
the machine and every step's times, and the same name's .png: steps done against wall time for both loops, and the
live loop's wait per step.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common

from _common import machine_info, print_table, pyplot, save_figure, write_json

FULL = {"res": (256, 192), "crop": (128, 160), "batch": 6, "updates": 8, "steps": 200, "warmup": 20, "pool": 240,
        "workers": 15}
QUICK = {"res": (160, 128), "crop": (128, 128), "batch": 2, "updates": 2, "steps": 4, "warmup": 1, "pool": 4,
         "workers": 2}
OUTPUTS = ["rgb", "flow_fw", "valid_fw"]
LR = 4e-4


def stream_config(res: tuple[int, int]):
    """The default config at ``res`` (w, h), 2 frames (its ``flow_px`` scales from 512 px wide, as the judge's)."""
    import flowsynth as fs

    return fs.BouncingThingsConfig(width=res[0], height=res[1], num_frames=2)


def pairs(batch: dict) -> tuple:
    """(img1, img2, flow, valid) of a collated batch of the stream."""
    return batch["rgb"][:, 0], batch["rgb"][:, 1], batch["flow_fw"][:, 0], batch["valid_fw"][:, 0]


def live_batches(source: str, cfg, batch: int, workers: int, device: str, seed: int):
    """Endless (img1, img2, flow, valid) batches of the live stream (``--source``)."""
    import flowsynth as fs

    if source == "device":
        if not hasattr(fs.datasets, "DeviceBatches"):
            raise SystemExit("--source device: this flowsynth has no fs.datasets.DeviceBatches")
        for b in fs.datasets.DeviceBatches(cfg, OUTPUTS, batch, workers, device=device, seed=seed):
            yield pairs(b)
        return
    ds = fs.datasets.BouncingThings(cfg, outputs=OUTPUTS, seed=seed)
    for b in fs.datasets.loader(ds, batch_size=batch, num_workers=workers, timeout=900):
        yield pairs(b)


def run_loop(net, opt, sched, next_batch, steps: int, warmup: int, crop, updates: int, device: str, g) -> dict:
    """``warmup`` + ``steps`` training steps on batches from ``next_batch()``; per timed step, the seconds spent
    waiting for the batch and the seconds of the whole step (the loss's read-back synchronises the device)."""
    import torch

    from flowsynth.train.steps import augment, train_step

    waits, totals = [], []
    for k in range(warmup + steps):
        t0 = time.perf_counter()
        img1, img2, flow, valid = next_batch()
        if img1.is_cuda:  # a device batch's launches are queued, not done: its render is time spent waiting
            torch.cuda.synchronize(img1.device)
        t1 = time.perf_counter()
        aug = augment(img1.cpu(), img2.cpu(), flow.cpu(), valid.cpu(), crop, g)
        train_step(net, tuple(x.to(device) for x in aug), opt, sched, updates)
        t2 = time.perf_counter()
        if k >= warmup:
            waits.append(t1 - t0)
            totals.append(t2 - t0)
    wall = sum(totals)
    return {"steps": steps, "wall_s": wall, "steps_per_s": steps / wall, "wait_share": sum(waits) / wall,
            "wait_s": waits, "step_s": totals}


def main(argv: list[str] | None = None) -> int:
    import torch

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="a smoke run: tiny pairs, a few steps, 2 workers")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="torch device of the net")
    p.add_argument("--source", choices=("stream", "device"), default="stream",
                   help="stream: fs.datasets.loader's CPU workers; device: fs.datasets.DeviceBatches")
    p.add_argument("--workers", type=int, default=None, help="worker processes of the live stream")
    p.add_argument("--steps", type=int, default=None, help="timed steps per loop")
    p.add_argument("--warmup", type=int, default=None, help="untimed steps before them")
    p.add_argument("--pool", type=int, default=None, help="pairs of the in-memory loop")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    s = dict(QUICK if a.quick else FULL)
    for key in ("workers", "steps", "warmup", "pool"):
        if getattr(a, key) is not None:
            s[key] = getattr(a, key)
    for key, lo in (("workers", 0), ("steps", 1), ("warmup", 0), ("pool", s["batch"])):
        if s[key] < lo:
            p.error(f"--{key} {s[key]}: must be at least {lo}")

    from flowsynth.train.nets import raft_small
    from flowsynth.train.steps import one_cycle

    torch.manual_seed(a.seed)
    net = raft_small().to(a.device)  # on the device before any worker starts, as a training script does
    opt, sched = one_cycle(net.parameters(), LR, 2 * (s["warmup"] + s["steps"]) + 2 * s["workers"])  # both loops
    cfg = stream_config(s["res"])
    live = live_batches(a.source, cfg, s["batch"], s["workers"], a.device, a.seed)

    t = time.perf_counter()  # the in-memory pool: the stream's first pairs, gathered before the clock
    got = [next(live) for _ in range(-(-s["pool"] // s["batch"]))]
    pool = tuple(torch.cat([b[k] for b in got])[:s["pool"]] for k in range(4))
    pool_s = time.perf_counter() - t
    g = torch.Generator().manual_seed(a.seed)

    def from_memory():
        idx = torch.randint(len(pool[0]), (s["batch"],), generator=g)
        return tuple(x[idx] for x in pool)

    loops = {"in memory": run_loop(net, opt, sched, from_memory, s["steps"], s["warmup"], s["crop"], s["updates"],
                                   a.device, g),
             # the live loop's warm-up also drains what the workers prefetched during the in-memory loop (DataLoader's
             # prefetch_factor 2 per worker), which would otherwise come free
             "live": run_loop(net, opt, sched, lambda: next(live), s["steps"], s["warmup"] + 2 * s["workers"],
                              s["crop"], s["updates"], a.device, g)}
    ratio = loops["live"]["steps_per_s"] / loops["in memory"]["steps_per_s"]
    rows = [{"loop": name, "steps/s": r["steps_per_s"], "samples/s": r["steps_per_s"] * s["batch"],
             "wait": r["wait_share"], "live / in memory": ratio if name == "live" else 1.0}
            for name, r in loops.items()]
    print(f"device {a.device}, source {a.source}, {s['workers']} workers, {s['res'][0]}x{s['res'][1]} pairs, "
          f"batch {s['batch']}, crop {s['crop']}, {s['updates']} updates, {s['steps']} timed steps")
    print_table(rows, list(rows[0]))
    name = "feed" + ("_device" if a.source == "device" else "") + ("_quick" if a.quick else "")
    device_name = torch.cuda.get_device_name() if a.device.startswith("cuda") else None
    write_json(name, {"settings": {**s, "device": a.device, "device_name": device_name, "source": a.source},
                      "pool_s": pool_s, "live_over_in_memory": ratio, "rows": rows, "loops": loops,
                      "machine": machine_info()})
    plot(name, loops, s)
    return 0


def plot(name: str, loops: dict, s: dict):
    """Steps done against wall time for both loops, and the live loop's wait per step."""
    plt = pyplot()
    if plt is None:
        return None
    import numpy as np

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    for label, r in loops.items():
        left.plot(np.cumsum(r["step_s"]), np.arange(1, r["steps"] + 1), label=f"{label}: {r['steps_per_s']:.2f}/s")
    left.set_xlabel("wall time [s]")
    left.set_ylabel("steps done")
    left.legend()
    right.bar(np.arange(1, loops["live"]["steps"] + 1), loops["live"]["wait_s"], color="tab:red")
    right.set_xlabel("live step")
    right.set_ylabel("wait for the batch [s]")
    right.set_title(f"live: {100 * loops['live']['wait_share']:.0f}% of wall time waiting")
    fig.suptitle(f"RAFT-small fed by flowsynth, batch {s['batch']}, {s['workers']} workers")
    fig.tight_layout()
    return save_figure(fig, name)


if __name__ == "__main__":
    sys.exit(main())
