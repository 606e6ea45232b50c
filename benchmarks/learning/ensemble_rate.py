"""``--ensemble-rate K``: how fast K RAFT-small nets train at the protocol's shape in one process (batched, and a loop)
against K processes of one net each. Trains no net of the judge; writes results/learning_raft_ensemble_rate[_TAG].json.
"""

from __future__ import annotations

import time

from _common import machine_info, print_table, write_json

from .protocol import BATCH, CROP, LR, RES, UPDATES, results_name
from .trainers import draw


def _rate_loop(k: int, steps: int, warmup: int, batched: bool, device: str, threads: int, barrier=None) -> float:
    """Seconds for ``steps`` steps of ``train_many``'s loop (draw, augment, step, until the device has finished; the
    draws here in turn with the steps, where ``train_many`` draws ahead in threads) for ``k`` nets at the protocol's
    shape, on a random uint8 pool at RES, after ``warmup`` steps (and ``barrier``, when given)."""
    import torch

    from flowsynth.train.ensemble import Ensemble
    from flowsynth.train.nets import raft_small

    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(0)
    w, h = RES
    pool = (torch.randint(256, (16, 3, h, w), dtype=torch.uint8, generator=g),
            torch.randint(256, (16, 3, h, w), dtype=torch.uint8, generator=g),
            5 * torch.randn(16, 2, h, w, generator=g), torch.ones(16, 1, h, w, dtype=torch.bool))
    nets = [raft_small().to(device) for _ in range(k)]
    ens = Ensemble(nets, LR, warmup + steps, updates=UPDATES, batched=batched)
    gens = [torch.Generator().manual_seed(s) for s in range(k)]
    for step in range(1, warmup + steps + 1):
        if step == warmup + 1:
            if barrier is not None:
                barrier.wait()
            t = time.perf_counter()
        losses = ens.step(tuple(x.to(device) for x in draw([pool] * k, gens, [1] * k, step, warmup + steps)))
    losses.tolist()  # waits until the device has finished
    return time.perf_counter() - t


def ensemble_rate(k: int = 2, steps: int = 20, warmup: int = 2, device: str = "cpu", threads: int = 2,
                  tag: str = "") -> list[dict]:
    """Steps per second of K nets trained at once at the protocol's shape (BATCH crops of CROP, UPDATES updates):
    in one process batched (``Ensemble``, vmap over stacked weights), in one process as a loop of ``train_step``s,
    and in K processes of one net each (``--jobs K``: ``threads`` // K threads each, started together after their
    warm-up). Returns the rows {"mode", "processes", "threads each", "s", "ensemble steps/s", "vs processes"}, prints
    them as a table and writes them to results/learning_raft_ensemble_rate[_TAG].json."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    rows = []
    for mode, batched in (("one process, batched", True), ("one process, loop", False)):
        s = _rate_loop(k, steps, warmup, batched, device, threads)
        rows.append({"mode": mode, "processes": 1, "threads each": threads, "s": s})
    ctx = multiprocessing.get_context("spawn")
    with ctx.Manager() as manager, ProcessPoolExecutor(k, mp_context=ctx) as ex:
        barrier = manager.Barrier(k)
        futs = [ex.submit(_rate_loop, 1, steps, warmup, False, device, max(1, threads // k), barrier)
                for _ in range(k)]
        s = max(f.result() for f in futs)
    rows.append({"mode": f"{k} processes", "processes": k, "threads each": max(1, threads // k), "s": s})
    for r in rows:
        r["ensemble steps/s"] = steps / r["s"]
        r["vs processes"] = rows[-1]["s"] / r["s"]
    print(f"{k} RAFT-small nets, {steps} steps after {warmup} of warm-up, batch {BATCH} of {CROP}, {UPDATES} updates, "
          f"device {device}")
    print_table(rows, list(rows[0]))
    write_json(results_name("ensemble_rate", tag), {
        "nets": k, "steps": steps, "warmup": warmup, "batch": BATCH, "crop": CROP, "updates": UPDATES,
        "device": device, "threads": threads, "rows": rows, "machine": machine_info()})
    return rows
