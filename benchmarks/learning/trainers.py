"""The RAFT judge's trainers: ``train_many`` trains K nets at once in this process by the protocol's recipe
(``flowsynth.train.ensemble.Ensemble``) and tests them at every checkpoint (``evaluate``); ``train`` is its one net,
``train_many([pool], ...)[0]``, stepped by ``flowsynth.train.steps.train_step`` itself.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from .protocol import BATCH, CROP, LR, TEST_UPDATES, UPDATES, checkpoint_path, with_means

DRAW_THREADS = 8  # train_many: threads drawing the nets' batches (the same batches whatever their number)
ENSEMBLE_ONLY = ("at_once", "step_s")  # what train_many's results hold beside train's


def evaluate(net, tests: dict, device: str) -> dict:
    """EPE [px] of ``net`` on every judge set of ``tests`` (``protocol.judge_sets``' dict; pairs one at a time, at full
    size, ``TEST_UPDATES`` updates), with the Middlebury mean (``protocol.with_means``)."""
    import torch

    from flowsynth.train.steps import predict

    out = {}
    for name, (img1, img2, flow, valid) in tests.items():
        err = n = 0.0
        for i in range(len(img1)):
            pred = predict(net, img1[i:i + 1].to(device), img2[i:i + 1].to(device), TEST_UPDATES).cpu()
            e = torch.linalg.vector_norm(pred - flow[i:i + 1], dim=1, keepdim=True)
            v = valid[i:i + 1] > 0.5
            err, n = err + float(e[v].sum()), n + float(v.sum())
        out[name] = err / max(n, 1.0)
    return with_means(out)


def draw_one(pool: tuple, g, n: int, step: int, steps: int) -> tuple:
    """One net's batch at ``step`` (1-based) of ``steps``: BATCH pairs drawn from generator ``g`` out of the block of
    ``pool`` that feeds this step in a run of ``n`` stages (the pool's k-th of n equal blocks feeds steps
    k * steps / n + 1 to (k + 1) * steps / n; one stage: the whole pool), augmented to CROP
    (``flowsynth.train.steps.augment``, from ``g``)."""
    import torch

    from flowsynth.train.steps import augment

    img1, img2, flow, valid = pool
    block = len(img1) // n
    idx = torch.randint(block, (BATCH,), generator=g) + min((step - 1) * n // steps, n - 1) * block
    return augment(img1[idx], img2[idx], flow[idx], valid[idx], CROP, g)


def draw(pools: list, gens: list, stages: list, step: int, steps: int, drawers=None) -> tuple:
    """One step's batches of K nets: per net, ``draw_one`` from its pool and generator, stacked (K, BATCH, ...).
    ``drawers``: an executor that draws the nets' batches side by side (each net draws from its own generator only,
    so the batches are the same)."""
    import torch

    jobs = [(pool, g, n, step, steps) for pool, g, n in zip(pools, gens, stages)]
    out = list(drawers.map(lambda a: draw_one(*a), jobs)) if drawers else [draw_one(*a) for a in jobs]
    return tuple(torch.stack(x) for x in zip(*out))


def train_many(pools: list, tests: dict, steps: int, seeds: list, net_seeds: list, every: int, device: str = "cpu",
               threads: int = 0, saves: list | None = None, progresses: list | None = None,
               stages: list | None = None, batched: bool = True, precision: str = "fp32") -> list[dict]:
    """Train K RAFT-small nets at once in this process for ``steps`` steps of the protocol's recipe, testing each
    (``evaluate`` on ``tests``) at step 0, every ``every`` steps and at the end.

    Net k: initialised from ``torch.manual_seed(net_seeds[k])``, trained on pool ``pools[k]`` ((img1, img2, flow,
    valid), ``pools``' layout) in ``stages[k]`` stages (default 1; ``draw_one``), its batches drawn from a generator
    of its own seeded ``seeds[k]``. ``saves[k]``: a path for its final weights, each tested checkpoint's beside them
    (``protocol.checkpoint_path``); ``progresses[k]``: a JSON path rewritten with its curve after every test (a run
    cut short keeps its curve). ``batched``: one vmapped step of the K nets (``Ensemble``), or a loop of
    ``flowsynth.train.steps.train_step``s (the reference). ``threads``: torch threads (0: leave as is). ``precision``:
    the training step's (``flowsynth.train.steps.PRECISIONS``; tests run in float32 whatever it is).

    Returns per net {"curve": [{"step", "train_loss" (the mean loss of the last ``every`` steps; None at step 0),
    judge set: EPE [px], ...}], "train_s", "net_seed", "parameters", "at_once": K, "step_s"}: ``train_s`` [s] the
    whole run's, ``step_s`` [s] its training steps' alone (draws, augmentation, the steps, until the device has
    finished them; no tests). The next step's batches are drawn (``DRAW_THREADS`` threads, a net's draws from its own
    generator) while the nets step. Prints the steps/s at each checkpoint."""
    from concurrent.futures import ThreadPoolExecutor

    import torch

    from flowsynth.train.ensemble import Ensemble
    from flowsynth.train.nets import raft_small

    k = len(pools)
    saves, progresses = saves or [None] * k, progresses or [None] * k
    stages = stages or [1] * k
    if threads:
        torch.set_num_threads(threads)
    nets = []
    for s in net_seeds:
        torch.manual_seed(s)
        nets.append(raft_small().to(device))
    ens = Ensemble(nets, LR, steps, updates=UPDATES, batched=batched, precision=precision)
    gens = [torch.Generator().manual_seed(s) for s in seeds]
    t = time.perf_counter()
    curves = [[{"step": 0, "train_loss": None, **evaluate(net, tests, device)}] for net in nets]
    losses, pending = [], []  # per step, the K losses: read, and on the device since the last checkpoint
    step_s = 0.0
    with ThreadPoolExecutor(1) as ahead, ThreadPoolExecutor(min(k, DRAW_THREADS)) as drawers:
        batches = ahead.submit(draw, pools, gens, stages, 1, steps, drawers)
        for step in range(1, steps + 1):
            t0 = time.perf_counter()
            batch = batches.result()
            if step < steps:
                batches = ahead.submit(draw, pools, gens, stages, step + 1, steps, drawers)
            pending.append(ens.step(tuple(x.to(device) for x in batch)))
            tested = step % every == 0 or step == steps
            if tested:  # one read of the losses a checkpoint: it waits until the device has finished the steps
                losses += torch.stack(pending).tolist()
                pending = []
            step_s += time.perf_counter() - t0
            if tested:
                _checkpoint(ens, step, steps, every, losses, curves, tests, device, saves, progresses, t, step_s)
    trained = ens.copy_to_nets()
    for net, save in zip(trained, saves):
        if save:
            torch.save(net.state_dict(), save)
    train_s = time.perf_counter() - t
    return [{"curve": c, "train_s": train_s, "net_seed": s, "parameters": sum(p.numel() for p in net.parameters()),
             "at_once": k, "step_s": step_s} for c, s, net in zip(curves, net_seeds, trained)]


def _checkpoint(ens, step: int, steps: int, every: int, losses: list, curves: list, tests: dict, device: str,
                saves: list, progresses: list, t: float, step_s: float) -> None:
    """``train_many``'s checkpoint at ``step``: each net's test, saved weights and progress file."""
    import torch

    k = len(curves)
    print(f"{k} net{'s' if k > 1 else ''} at once: step {step} of {steps}, {step / step_s:.2f} steps/s "
          f"({k * step / step_s:.1f} net-steps/s) after {time.perf_counter() - t:.0f} s", flush=True)
    for i, net in enumerate(ens.copy_to_nets()):
        mine = [row[i] for row in losses[-every:]]
        curves[i].append({"step": step, "train_loss": sum(mine) / len(mine), **evaluate(net, tests, device)})
        if saves[i]:
            Path(saves[i]).parent.mkdir(parents=True, exist_ok=True)
            torch.save(net.state_dict(), checkpoint_path(saves[i], step))
        if progresses[i]:
            Path(progresses[i]).parent.mkdir(parents=True, exist_ok=True)
            Path(progresses[i] + ".tmp").write_text(json.dumps({"curve": curves[i], "s": time.perf_counter() - t}))
            Path(progresses[i] + ".tmp").replace(progresses[i])


def train(pool: tuple, tests: dict, steps: int, seed: int, net_seed: int, every: int, threads: int = 0,
          device: str = "cpu", save: str | None = None, progress: str | None = None, stages: int = 1,
          precision: str = "fp32") -> dict:
    """One net of ``train_many``: ``train_many([pool], tests, steps, [seed], [net_seed], every, ...)[0]``, stepped by
    ``flowsynth.train.steps.train_step`` (``batched=False``), without the ensemble's fields (``ENSEMBLE_ONLY``). Returns
    {"curve", "train_s", "net_seed", "parameters"} as ``train_many`` says."""
    out = train_many([pool], tests, steps, [seed], [net_seed], every, device=device, threads=threads,
                     saves=[save], progresses=[progress], stages=[stages], batched=False, precision=precision)[0]
    return {k: v for k, v in out.items() if k not in ENSEMBLE_ONLY}
