"""The learning judge of issue 46: torchvision's RAFT-small, trained from scratch on each arm's pairs, tested on real
flow: the net, its recipe, the arms' pools and the runs. ``python benchmarks/learning`` runs it (``cli``); the protocol
and the rules are pre-registered in docs/decisions/0023-raft-judge.md.

Protocol (the numbers are module constants):

- Net: ``torchvision.models.optical_flow.raft_small(weights=None)`` (0.99 M parameters), RAFT's recipe as
  ``flowsynth.training`` implements it (the same step ``examples/train_raft.py`` runs): sequence loss (gamma 0.8),
  AdamW at ``LR`` with weight decay 1e-4 and a linear one-cycle schedule, gradient clip 1, ``UPDATES`` flow updates
  in training and ``TEST_UPDATES`` at test; ``STEPS`` steps of ``BATCH`` random ``CROP`` crops with flips and colour
  jitter, the same augmentation for every arm.
- Training pools: ``POOL`` pairs per arm rendered at ``RES`` (256x192), images kept as uint8.
  - ``flowsynth``: ``BouncingThingsConfig()`` (with ``--set`` changes: a lever) at 256x192, 2 frames, its
    ``flow_px`` halved so motion keeps the proportions of a 512x384 rendering; procedural textures only.
  - ``chairs2d_photos``: the FlyingChairs-style 2D baseline (``sets.chairs2d_pairs``) textured with crops of
    every photograph that ships with scikit-image (``NATURAL_PHOTOS``), as FlyingChairs is textured with photographs.
  - ``chairs2d``: the same baseline textured with flowsynth frames not trained on: it isolates what the 3D motion
    teaches. Both baselines' motion is scaled so that their mean |flow| equals the flowsynth pool's.
  - ``flowsynth_photos``: the flowsynth config with NATURAL_PHOTOS as every texture (``texture_families=("image",)``).
  - ``flowsynth_natural``: the same with 96 textures made without files, with statistics of photographs instead
    (``sets.natural_folder``: 1/f spectra, dead leaves, sparse edges over smooth regions).
  - ``flowsynth_final``: the flowsynth config's final pass (``rgb_final``: motion blur, depth of field, sensor
    noise) as the images, in place of ``rgb``; the flow is the same truth.
  - ``mixture``: a preset mixture, as FlowNet and RAFT start on chairs: half the ``flowsynth`` pool, half the
    ``chairs2d`` pool (no files).
  - ``curriculum``: chairs first, as FlowNet and RAFT train: the ``chairs2d`` pool for the first half of the steps,
    then the ``flowsynth`` pool (no files; both pools whole, so the arm holds 2 x POOL pairs).
  - ``control``: the flowsynth pool again, with another net seed (seed + 100): the judge's own noise.
- Judges: Motorcycle ("stereo": the whole stereo pair at half resolution, plain and mirrored, ``motorcycle_full``)
  and, with ``--middlebury DIR``, the mean EPE over the Middlebury pairs found there ("middlebury", each pair also
  "mb_NAME"), at full resolution. Tested at step 0 and every ``EVERY`` steps; a net's score on a judge is the mean of
  its last ``JUDGED`` checkpoints (steps 2000 and 2400), which halves the checkpoint-to-checkpoint swings one seed
  shows.

Writes results/learning_raft[_TAG].json after every seed, and each trained net's weights to
.cache/learning_raft/TAG_ARM_sSEED.pt (for ``--figures``), each tested checkpoint's beside them (``checkpoint_path``).
Each net trains in a process of its own (``train``), or with ``--ensemble`` all at once in one process
(``train_many``, ``flowsynth.ensemble``) on the same pools, draws and checkpoints, into the same files; the results
say which (``"trainer"``).
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

from _common import RESULTS_DIR, machine_info, print_table, write_json

from .sets import NATURAL_PHOTOS, chairs2d_pairs, middlebury_pairs, motorcycle_full, natural_folder, photo_folder, \
    photo_sources

NET = "raft_small"
RES = (256, 192)  # (w, h) the training pairs are rendered at [px]
CROP = (128, 160)  # (h, w) of the training crops [px]: RAFT's correlation pyramid needs 128 or more a side
BATCH = 6
STEPS = 2400
EVERY = 400  # test every this many steps
JUDGED = 2  # a net's score: the mean of its last JUDGED checkpoints
LR = 4e-4  # RAFT's peak learning rate (AdamW, one-cycle)
UPDATES, TEST_UPDATES = 8, 12
POOL = 1200  # training pairs per arm
SCALE = 512 // RES[0]  # flow_px is given at 512x384
ARMS = ("flowsynth", "chairs2d_photos", "chairs2d", "flowsynth_photos", "flowsynth_natural", "flowsynth_final",
        "mixture", "curriculum", "control")
STAGES = {"curriculum": 2}  # arms trained in stages: the pool's k-th of n equal blocks feeds the k-th n-th of steps
CONTROL_SEED = 100  # the control's net seed is the run's seed + this
DRAW_THREADS = 8  # train_many: threads drawing the nets' batches (the same batches whatever their number)
JUDGES = ("stereo", "middlebury")
CACHE = Path(__file__).resolve().parents[2] / ".cache" / "learning_raft"


def raft_small():
    """torchvision's RAFT-small with random weights (tests/tvision.py's shim for this CPU torch)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
    import tvision

    tvision.datasets()  # registers the shim module before torchvision's models import
    from torchvision.models.optical_flow import raft_small as build

    return build(weights=None)


# -- data -----------------------------------------------------------------------------------------------------
def _u8(x):
    import torch

    return (x * 255).round().clamp(0, 255).to(torch.uint8)


def flowsynth_pool(n: int, seed: int, workers: int, overrides: dict | None = None, image: str = "rgb"):
    """n flowsynth pairs at RES: (img1, img2 uint8 (n, 3, h, w), flow (n, 2, h, w), valid (n, 1, h, w) bool), and the
    config. ``overrides``: config fields of a lever (not the size); ``image``: the output the images come from
    ("rgb", or "rgb_final": the final pass). The ``workers`` render through ``fs.datasets.loader`` (forkserver), so a
    process that has initialised CUDA renders its pools at the CPU rate; the pairs are those of any start method."""
    import torch

    import flowsynth as fs

    base = fs.BouncingThingsConfig.from_dict(overrides or {})
    cfg = dataclasses.replace(base, width=RES[0], height=RES[1], num_frames=2,
                              flow_px=tuple(x / SCALE for x in base.flow_px))
    ds = fs.datasets.BouncingThings(cfg, outputs=[image, "flow_fw", "valid_fw"], seed=seed, length=n)
    w, h = RES
    img1, img2 = torch.empty(n, 3, h, w, dtype=torch.uint8), torch.empty(n, 3, h, w, dtype=torch.uint8)
    flow, valid = torch.empty(n, 2, h, w), torch.empty(n, 1, h, w, dtype=torch.bool)
    o = 0
    for b in fs.datasets.loader(ds, batch_size=16, num_workers=workers, persistent_workers=False):
        k = len(b[image])
        img1[o:o + k], img2[o:o + k] = _u8(b[image][:, 0]), _u8(b[image][:, 1])
        flow[o:o + k], valid[o:o + k] = b["flow_fw"][:, 0], b["valid_fw"][:, 0]
        o += k
    return (img1, img2, flow, valid), cfg


def mean_flow(data) -> float:
    """Mean |flow| [px] over the valid pixels of an (img1, img2, flow, valid) set."""
    import torch

    return float(torch.linalg.vector_norm(data[2], dim=1)[data[3][:, 0] > 0.5].mean())


def baseline_pool(n: int, seed: int, sources, target_flow: float):
    """n chairs2d pairs from ``sources`` (float (m, 3, h, w)) whose mean |flow| matches ``target_flow`` [px]."""
    pilot = chairs2d_pairs(64, seed + 1, sources)
    scale = target_flow / mean_flow(pilot)
    img1, img2, flow, valid = chairs2d_pairs(n, seed, sources, scale)
    return (_u8(img1), _u8(img2), flow, valid > 0.5), scale


def judge_sets(middlebury_dir: str | None) -> dict:
    """The real judges: {"stereo": motorcycle_full(2), "mb_NAME": ...} (float32 tensors)."""
    return {"stereo": motorcycle_full(2), **middlebury_pairs(middlebury_dir)}


def with_means(epe: dict) -> dict:
    """``epe`` plus "middlebury", the mean over its mb_* pairs, when there are any."""
    mb = [v for k, v in epe.items() if k.startswith("mb_")]
    return {**epe, "middlebury": sum(mb) / len(mb)} if mb else dict(epe)


def zero_flow(tests: dict) -> dict:
    import torch

    from flowsynth.training import epe

    return with_means({k: epe(torch.zeros_like(v[2]), v[2], v[3]) for k, v in tests.items()})


# -- train and test -------------------------------------------------------------------------------------------
def evaluate(net, tests: dict, device: str) -> dict:
    """EPE [px] of ``net`` on every judge set (pairs one at a time, at full size), with the Middlebury mean."""
    import torch

    from flowsynth.training import predict

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


def train(data, tests: dict, steps: int, seed: int, net_seed: int, every: int, threads: int = 0,
          device: str = "cpu", save: str | None = None, progress: str | None = None, stages: int = 1) -> dict:
    """Train RAFT-small (initialised from ``net_seed``) on ``data`` (a pool) for ``steps`` steps of RAFT's recipe;
    batches drawn from ``seed``. Tests at step 0, every ``every`` steps and at the end. ``save``: a path for the final
    weights (each tested checkpoint's beside it, ``checkpoint_path``); ``progress``: a JSON path rewritten with the
    curve after every test (a run cut short keeps its curve).
    ``stages``: the pool is that many equal blocks, block k feeding steps k * steps / stages + 1 to (k + 1) * steps /
    stages (a curriculum); with 1 the batches are what they were before stages existed."""
    import torch

    from flowsynth.training import augment, one_cycle, train_step

    if threads:
        torch.set_num_threads(threads)
    torch.manual_seed(net_seed)
    net = raft_small().to(device)
    opt, sched = one_cycle(net.parameters(), LR, steps)
    g = torch.Generator().manual_seed(seed)
    img1, img2, flow, valid = data
    block = len(img1) // stages
    t = time.perf_counter()
    curve = [{"step": 0, "train_loss": None, **evaluate(net, tests, device)}]
    losses = []
    for step in range(1, steps + 1):
        stage = min((step - 1) * stages // steps, stages - 1)
        idx = torch.randint(block, (BATCH,), generator=g) + stage * block  # one stage: the whole pool, as before
        batch = augment(img1[idx], img2[idx], flow[idx], valid[idx], CROP, g)
        losses.append(train_step(net, tuple(x.to(device) for x in batch), opt, sched, UPDATES))
        if step % every == 0 or step == steps:
            curve.append({"step": step, "train_loss": sum(losses[-every:]) / len(losses[-every:]),
                          **evaluate(net, tests, device)})
            if save:  # every checkpoint's weights, for the small-motion diagnostic at each (issue 53, item 5)
                Path(save).parent.mkdir(parents=True, exist_ok=True)
                torch.save(net.state_dict(), checkpoint_path(save, step))
            if progress:
                Path(progress).parent.mkdir(parents=True, exist_ok=True)
                Path(progress + ".tmp").write_text(json.dumps({"curve": curve, "s": time.perf_counter() - t}))
                Path(progress + ".tmp").replace(progress)
    if save:
        Path(save).parent.mkdir(parents=True, exist_ok=True)
        torch.save(net.state_dict(), save)
    return {"curve": curve, "train_s": time.perf_counter() - t, "net_seed": net_seed,
            "parameters": sum(p.numel() for p in net.parameters())}


def checkpoint_path(save: str, step: int) -> str:
    """Where ``train`` keeps the weights of its checkpoint at ``step`` beside the final ones at ``save``."""
    return str(Path(save).with_name(f"{Path(save).stem}_step{step}.pt"))


def _draw_one(pool: tuple, g, n: int, step: int, steps: int) -> tuple:
    """``train``'s draw of one step's batch from ``pool`` and generator ``g`` in a run of ``n`` stages."""
    import torch

    from flowsynth.training import augment

    img1, img2, flow, valid = pool
    block = len(img1) // n
    idx = torch.randint(block, (BATCH,), generator=g) + min((step - 1) * n // steps, n - 1) * block
    return augment(img1[idx], img2[idx], flow[idx], valid[idx], CROP, g)


def _draw(pools: list, gens: list, stages: list, step: int, steps: int, drawers=None) -> tuple:
    """One step's batches of ``train_many``: per net, ``train``'s draw from its pool and generator, stacked (K, ...).
    ``drawers``: an executor that draws the nets' batches side by side (each net draws from its own generator only,
    so the batches are the same)."""
    import torch

    jobs = [(pool, g, n, step, steps) for pool, g, n in zip(pools, gens, stages)]
    out = list(drawers.map(lambda a: _draw_one(*a), jobs)) if drawers else [_draw_one(*a) for a in jobs]
    return tuple(torch.stack(x) for x in zip(*out))


def train_many(pools: list, tests: dict, steps: int, seeds: list, net_seeds: list, every: int, device: str = "cpu",
               threads: int = 0, saves: list | None = None, progresses: list | None = None,
               stages: list | None = None, batched: bool = True) -> list[dict]:
    """``train`` for K nets at once in this process (``flowsynth.ensemble.Ensemble``: one batched step of the K nets,
    ``batched=False``: a loop of ``train_step``s). Net k: pool ``pools[k]``, initialised from ``net_seeds[k]``,
    batches drawn from its own generator seeded ``seeds[k]`` (``train``'s draws), ``stages[k]`` stages (default 1),
    weights saved to ``saves[k]`` and its curve to ``progresses[k]`` as ``train`` does. Returns ``train``'s result per
    net, with ``at_once`` = K; ``train_s`` is the whole ensemble's, ``step_s`` its training steps' alone (draws,
    augmentation and the step; no tests). Prints the ensemble's steps/s at each checkpoint. The next step's batches
    are drawn (``DRAW_THREADS`` threads, a net's draws from its own generator) while the ensemble steps."""
    from concurrent.futures import ThreadPoolExecutor

    import torch

    from flowsynth.ensemble import Ensemble

    k = len(pools)
    stages, saves, progresses = stages or [1] * k, saves or [None] * k, progresses or [None] * k
    if not len(seeds) == len(net_seeds) == len(stages) == len(saves) == len(progresses) == k:
        raise ValueError(f"train_many: {k} pools need as many seeds, net_seeds, stages, saves and progresses")
    if threads:
        torch.set_num_threads(threads)
    nets = []
    for s in net_seeds:
        torch.manual_seed(s)
        nets.append(raft_small().to(device))
    ens = Ensemble(nets, LR, steps, updates=UPDATES, batched=batched)
    gens = [torch.Generator().manual_seed(s) for s in seeds]
    t = time.perf_counter()
    curves = [[{"step": 0, "train_loss": None, **evaluate(net, tests, device)}] for net in nets]
    losses = []  # per step, the K losses (device tensors until the next checkpoint reads them)
    step_s, read = 0.0, 0
    with ThreadPoolExecutor(1) as ahead, ThreadPoolExecutor(min(k, DRAW_THREADS)) as drawers:
        batches = ahead.submit(_draw, pools, gens, stages, 1, steps, drawers)
        for step in range(1, steps + 1):
            t0 = time.perf_counter()
            batch = batches.result()
            if step < steps:
                batches = ahead.submit(_draw, pools, gens, stages, step + 1, steps, drawers)
            losses.append(ens.step(tuple(x.to(device) for x in batch)))
            if step % every == 0 or step == steps:  # the losses are read (the device has finished) at a checkpoint
                losses[read:], read = torch.stack(losses[read:]).tolist(), len(losses)
            step_s += time.perf_counter() - t0
            if step % every == 0 or step == steps:
                _checkpoint(ens, step, steps, every, losses, curves, tests, device, saves, progresses, t, step_s)
    for net, save in zip(ens.copy_to_nets(), saves):
        if save:
            torch.save(net.state_dict(), save)
    train_s = time.perf_counter() - t
    return [{"curve": c, "train_s": train_s, "net_seed": s, "parameters": sum(p.numel() for p in net.parameters()),
             "at_once": k, "step_s": step_s} for c, s, net in zip(curves, net_seeds, ens.copy_to_nets())]


def _checkpoint(ens, step: int, steps: int, every: int, losses: list, curves: list, tests: dict, device: str,
                saves: list, progresses: list, t: float, step_s: float) -> None:
    """``train_many``'s checkpoint at ``step``: each net's test, saved weights and progress file, as ``train``'s."""
    import torch

    k = len(curves)
    print(f"ensemble of {k} nets: step {step} of {steps}, {step / step_s:.2f} steps/s "
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


def _rate_loop(k: int, steps: int, warmup: int, batched: bool, device: str, threads: int, barrier=None) -> float:
    """Seconds for ``steps`` steps of ``train_many``'s loop (draw, augment, step; the draws here in turn with the steps,
    where ``train_many`` draws ahead in threads) for ``k`` nets at the protocol's shape, on a random uint8 pool at RES,
    after ``warmup`` steps (and ``barrier``, when given)."""
    import torch

    from flowsynth.ensemble import Ensemble

    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(0)
    w, h = RES
    pool = (torch.randint(256, (16, 3, h, w), dtype=torch.uint8, generator=g),
            torch.randint(256, (16, 3, h, w), dtype=torch.uint8, generator=g), 5 * torch.randn(16, 2, h, w,
                                                                                              generator=g),
            torch.ones(16, 1, h, w, dtype=torch.bool))
    nets = [raft_small().to(device) for _ in range(k)]
    ens = Ensemble(nets, LR, warmup + steps, updates=UPDATES, batched=batched)
    gens = [torch.Generator().manual_seed(s) for s in range(k)]
    for step in range(1, warmup + steps + 1):
        if step == warmup + 1:
            if barrier is not None:
                barrier.wait()
            t = time.perf_counter()
        losses = ens.step(tuple(x.to(device) for x in _draw([pool] * k, gens, [1] * k, step, warmup + steps)))
    losses.tolist()  # waits for the device to finish the last step
    return time.perf_counter() - t


def ensemble_rate(k: int = 2, steps: int = 20, warmup: int = 2, device: str = "cpu", threads: int = 2,
                  tag: str = "") -> list[dict]:
    """Steps per second of K nets trained at once at the protocol's shape (BATCH crops of CROP, UPDATES updates):
    in one process batched (``Ensemble``, vmap over stacked weights), in one process as a loop of ``train_step``s,
    and in K processes of one net each (``--jobs K``: ``threads`` // K threads each, started together after their
    warm-up). Prints a table; writes results/learning_raft_ensemble_rate[_TAG].json."""
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
    write_json("learning_raft_ensemble_rate" + (f"_{tag}" if tag else ""), {
        "nets": k, "steps": steps, "warmup": warmup, "batch": BATCH, "crop": CROP, "updates": UPDATES,
        "device": device, "threads": threads, "rows": rows, "machine": machine_info()})
    return rows


def score(curve: list, judge: str) -> float:
    """A net's score on ``judge``: the mean EPE of its last JUDGED checkpoints (the pre-registered rule)."""
    pts = [c[judge] for c in curve[1:] if judge in c][-JUDGED:]
    return sum(pts) / len(pts)


def _train_args(arms: dict, name: str, tests: dict, steps: int, seed: int, every: int, threads: int, device: str,
                tag: str) -> tuple:
    """``train``'s arguments for arm ``name`` of ``seed`` (the control's net seed is seed + CONTROL_SEED)."""
    net_seed = seed + CONTROL_SEED if name == "control" else seed
    stem = f"{tag or 'default'}_{name}_s{seed}"
    return (arms[name], tests, steps, seed, net_seed, every, threads, device, str(CACHE / f"{stem}.pt"),
            str(RESULTS_DIR / "learning_raft_progress" / f"{stem}.json"), STAGES.get(name, 1))


def train_all(arms: dict, tests: dict, steps: int, seed: int, every: int, jobs: int, threads: int, device: str,
              tag: str) -> dict:
    """Train every arm's net (name -> pool), ``jobs`` at once in spawned processes (0: here, one after another)."""
    import torch.multiprocessing as tmp
    from concurrent.futures import ProcessPoolExecutor

    per = max(1, threads // max(jobs, 1))
    if jobs == 0:
        return {name: train(*_train_args(arms, name, tests, steps, seed, every, per, device, tag)) for name in arms}
    with ProcessPoolExecutor(min(jobs, len(arms)), mp_context=tmp.get_context("spawn")) as ex:
        futs = {name: ex.submit(train, *_train_args(arms, name, tests, steps, seed, every, per, device, tag))
                for name in arms}
        return {name: f.result() for name, f in futs.items()}


def train_together(pools: dict, tests: dict, steps: int, every: int, threads: int, device: str, tag: str) -> dict:
    """``--ensemble``: the nets of ``pools`` ((seed, arm) -> pool) trained at once in this process (``train_many``),
    each with what ``train`` gets from ``_train_args`` in its own process: its pool, batch seed, net seed, stages,
    saved weights and progress file. Returns {(seed, arm): ``train_many``'s result}."""
    keys = list(pools)
    # each: (pool, tests, steps, seed, net_seed, every, threads, device, save, progress, stages)
    argv = [_train_args({arm: pools[seed, arm]}, arm, tests, steps, seed, every, threads, device, tag)
            for seed, arm in keys]
    out = train_many([a[0] for a in argv], tests, steps, [a[3] for a in argv], [a[4] for a in argv], every,
                     device=device, threads=threads, saves=[a[8] for a in argv], progresses=[a[9] for a in argv],
                     stages=[a[10] for a in argv])
    step_s = out[0]["step_s"]
    print(f"ensemble of {len(keys)} nets: {steps} steps, {steps / step_s:.2f} steps/s in its training steps "
          f"({len(keys) * steps / step_s:.1f} net-steps/s), {out[0]['train_s']:.0f} s with the tests", flush=True)
    return dict(zip(keys, out))


def run_at_once(args, names: list, seeds: list, steps: int, every: int, tests: dict, zero: dict, header) -> None:
    """``--at-once`` (a lent GPU): the pools of every seed first, then every net of every seed at once, each in a
    process of its own (``--ensemble``: all in this process, ``train_together``); a seed's results are written when
    all its nets are done."""
    import torch.multiprocessing as tmp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    pools, infos, cfg = {}, {}, None
    t = time.perf_counter()
    for seed in seeds:
        pools[seed], infos[seed], cfg = build_arms(names, seed, args.workers, args.overrides, args.pool or POOL)
        print(f"pools of seed {seed} ready after {time.perf_counter() - t:.0f} s", flush=True)
    gen_s = time.perf_counter() - t
    while args.train_after and not Path(args.train_after).exists():  # the device's other benchmarks come first
        time.sleep(1)
    print(f"training starts after {time.perf_counter() - t:.0f} s", flush=True)
    if args.ensemble:
        res = train_together({(seed, name): pools[seed][name] for seed in seeds for name in names}, tests, steps,
                             every, args.threads, args.device, args.tag)
        runs = []
        for seed in seeds:
            runs.append({"seed": seed, "zero_flow_epe": zero, "results": {name: res[seed, name] for name in names},
                         "data": infos[seed], "generation_s": gen_s})
            header(runs, cfg, len(runs) == len(seeds))
        return
    done: dict = {seed: {} for seed in seeds}
    runs = []
    with ProcessPoolExecutor(len(seeds) * len(names), mp_context=tmp.get_context("spawn")) as ex:
        futs = {ex.submit(train, *_train_args(pools[seed], name, tests, steps, seed, every, 1, args.device,
                                              args.tag)): (seed, name) for seed in seeds for name in names}
        for f in as_completed(futs):
            seed, name = futs[f]
            done[seed][name] = f.result()
            print(f"seed {seed} {name} done after {time.perf_counter() - t:.0f} s", flush=True)
            if len(done[seed]) == len(names):
                runs.append({"seed": seed, "zero_flow_epe": zero, "results": done[seed], "data": infos[seed],
                             "generation_s": gen_s})
                header(runs, cfg, len(runs) == len(seeds))


def build_arms(names: list, seed: int, workers: int, overrides: dict, n: int = POOL) -> tuple[dict, dict, object]:
    """The pools (``n`` pairs each) of the arms ``names`` for ``seed``, their mean |flow| and the flowsynth
    config."""
    import torch

    # frames for chairs2d's textures, not trained on
    extra = n // 2 if {"chairs2d", "mixture", "curriculum"} & set(names) else 0
    pool, cfg = flowsynth_pool(n + extra, seed, workers, overrides)
    fs_pool = tuple(x[:n] for x in pool)
    target = mean_flow(fs_pool)
    arms, info = {}, {"flowsynth_mean_flow": target}
    for name in names:
        if name in ("flowsynth", "control"):
            arms[name] = fs_pool
        elif name in ("chairs2d", "mixture", "curriculum"):
            if "chairs2d_motion_scale" not in info:  # one chairs2d pool (a pure function of n, seed) for all three
                chairs, info["chairs2d_motion_scale"] = baseline_pool(n, seed, pool[0][n:].float() / 255, target)
            if name == "chairs2d":
                arms[name] = chairs
            elif name == "mixture":
                arms[name] = tuple(torch.cat([f[:n // 2], c[:n - n // 2]]) for f, c in zip(fs_pool, chairs))
            else:  # the curriculum's two blocks, in order: STAGES
                arms[name] = tuple(torch.cat([c, f]) for c, f in zip(chairs, fs_pool))
        elif name == "flowsynth_final":
            arms[name], _ = flowsynth_pool(n, seed, workers, overrides, image="rgb_final")
        elif name == "chairs2d_photos":
            sources = photo_sources(max(n // 2, 8), seed, RES, NATURAL_PHOTOS)
            arms[name], info["chairs2d_photos_motion_scale"] = baseline_pool(n, seed, sources, target)
        elif name in ("flowsynth_photos", "flowsynth_natural"):
            folder = photo_folder(NATURAL_PHOTOS) if name == "flowsynth_photos" else natural_folder()
            arms[name], _ = flowsynth_pool(n, seed, workers, {
                **overrides, "texture_dir": str(folder), "texture_families": ["image"]})
    info["mean_flow"] = {k: mean_flow(v) for k, v in arms.items()}
    info["still_share"] = {k: float((torch.linalg.vector_norm(v[2], dim=1) < 0.5)[v[3][:, 0]].float().mean())
                           for k, v in arms.items()}
    return arms, info, cfg


def run(args) -> None:
    """Train the arms of every seed (the module docstring's protocol) and write the results after each seed."""
    import torch

    torch.set_num_threads(args.threads)
    steps = args.steps or STEPS
    every = min(args.every or EVERY, steps)
    names = args.arms.split(",")
    bad = [n for n in names if n not in ARMS]
    if bad:
        raise SystemExit(f"--arms: unknown {bad}; known {ARMS}")
    tests = judge_sets(args.middlebury)
    zero = zero_flow(tests)
    seeds = [int(s) for s in args.seeds.split(",")]
    name = "learning_raft" + (f"_{args.tag}" if args.tag else "")
    # how the nets trained: all at once in this process, each in a process of its own, or one after another here
    trainer = "ensemble" if args.ensemble else "processes" if args.at_once or args.jobs else "in turn"

    def save(runs: list, cfg, complete: bool) -> None:
        write_json(name, {"complete": complete, "seeds_planned": seeds, "net": NET, "steps": steps,
                          "every": every, "batch": BATCH, "crop": CROP, "resolution": RES, "pool": args.pool or POOL,
                          "lr": LR,
                          "updates": [UPDATES, TEST_UPDATES], "judged_checkpoints": JUDGED, "device": args.device,
                          "trainer": trainer, "overrides": args.overrides, "flowsynth_config": cfg.to_dict(),
                          "machine": machine_info(),
                          "runs": sorted(runs, key=lambda r: r["seed"])})
        seed, res = runs[-1]["seed"], runs[-1]["results"]
        rows = [{"seed": seed, "arm": arm, "judge": j, "zero flow": zero[j], "untrained": r["curve"][0][j],
                 **{f"@{c['step']}": c[j] for c in r["curve"][1:]}, "score": score(r["curve"], j)}
                for arm, r in res.items() for j in JUDGES if j in r["curve"][0]]
        print_table(rows, list(rows[0]))

    if args.at_once:
        return run_at_once(args, names, seeds, steps, every, tests, zero, save)
    runs = []
    for seed in seeds:
        t = time.perf_counter()
        arms, info, cfg = build_arms(names, seed, args.workers, args.overrides, args.pool or POOL)
        gen_s = time.perf_counter() - t
        if args.ensemble:
            res = {arm: r for (_, arm), r in train_together({(seed, arm): pool for arm, pool in arms.items()}, tests,
                                                            steps, every, args.threads, args.device,
                                                            args.tag).items()}
        else:
            res = train_all(arms, tests, steps, seed, every, args.jobs, args.threads, args.device, args.tag)
        runs.append({"seed": seed, "zero_flow_epe": zero, "results": res, "data": info, "generation_s": gen_s})
        save(runs, cfg, seed == seeds[-1])
