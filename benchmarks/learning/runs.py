"""The RAFT judge's runs: every arm of every seed of a run, its pools (``pools.build_arms``), its nets trained
(``trainers``) and its results written (``ResultsFile``). ``python benchmarks/learning`` calls ``run``.

A run writes results/learning_raft[_TAG].json after every seed, each trained net's weights to
.cache/learning_raft/TAG_ARM_sSEED.pt (``protocol.net_stem``; for ``--figures``, ``--diagnose``), each tested
checkpoint's beside them (``protocol.checkpoint_path``), and each net's curve so far to
results/learning_raft_progress/TAG_ARM_sSEED.json. Each net trains in a process of its own (``train_all``, or
``--at-once`` with every seed's nets at once), one after another in this process (``--jobs 0``), or with
``--ensemble`` all at once in this process (``train_together``) on the same pools, draws and checkpoints, into the
same files; the results say which (``"trainer"``).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from _common import RESULTS_DIR, machine_info, print_table, write_json

from .pools import build_arms
from .protocol import ARMS, BATCH, CACHE, CONTROL_SEED, CROP, EVERY, JUDGED, JUDGES, LR, NET, POOL, RES, STAGES, \
    STEPS, TEST_UPDATES, UPDATES, judge_sets, net_stem, results_name, score, zero_flow
from .trainers import train, train_many


@dataclasses.dataclass(frozen=True)
class NetJob:
    """One net of a run, what it trains on and where its files go: ``pool`` (``pools``' layout), ``seed`` (its batch
    draws), ``net_seed`` (its initial weights; the control's is seed + CONTROL_SEED), ``stages`` (STAGES), ``save``
    (its weights' path), ``progress`` (its progress file's path) and ``precision`` (its training step's)."""

    pool: tuple
    seed: int
    net_seed: int
    stages: int
    save: str
    progress: str
    precision: str = "fp32"

    @classmethod
    def of(cls, arm: str, pool: tuple, seed: int, tag: str, precision: str = "fp32") -> NetJob:
        """Arm ``arm``'s net of ``seed`` on ``pool`` in a run tagged ``tag``, trained in ``precision``."""
        stem = net_stem(tag, arm, seed)
        return cls(pool, seed, seed + CONTROL_SEED if arm == "control" else seed, STAGES.get(arm, 1),
                   str(CACHE / f"{stem}.pt"), str(RESULTS_DIR / results_name("progress") / f"{stem}.json"), precision)

    def train(self, tests: dict, steps: int, every: int, threads: int, device: str) -> dict:
        """``trainers.train`` of this net (in this process)."""
        return train(self.pool, tests, steps, self.seed, self.net_seed, every, threads, device, self.save,
                     self.progress, self.stages, self.precision)


def train_all(arms: dict, tests: dict, steps: int, seed: int, every: int, jobs: int, threads: int, device: str,
              tag: str, precision: str = "fp32") -> dict:
    """Train the net of every arm of ``arms`` (name -> pool) for ``seed``, ``jobs`` at once in spawned processes of
    ``threads`` // ``jobs`` torch threads each (0: here, one after another): {arm: ``trainers.train``'s result}."""
    import torch.multiprocessing as tmp
    from concurrent.futures import ProcessPoolExecutor

    per = max(1, threads // max(jobs, 1))
    nets = {name: NetJob.of(name, pool, seed, tag, precision) for name, pool in arms.items()}
    if jobs == 0:
        return {name: job.train(tests, steps, every, per, device) for name, job in nets.items()}
    with ProcessPoolExecutor(min(jobs, len(arms)), mp_context=tmp.get_context("spawn")) as ex:
        futs = {name: ex.submit(job.train, tests, steps, every, per, device) for name, job in nets.items()}
        return {name: f.result() for name, f in futs.items()}


def train_together(pools: dict, tests: dict, steps: int, every: int, threads: int, device: str, tag: str,
                   precision: str = "fp32") -> dict:
    """``--ensemble``: the nets of ``pools`` ((seed, arm) -> pool) trained at once in this process (``train_many``),
    each with what ``train_all`` gives it in a process of its own (``NetJob``): its pool, batch seed, net seed,
    stages, saved weights and progress file. Returns {(seed, arm): ``train_many``'s result}."""
    keys = list(pools)
    nets = [NetJob.of(arm, pools[seed, arm], seed, tag, precision) for seed, arm in keys]
    out = train_many([j.pool for j in nets], tests, steps, [j.seed for j in nets], [j.net_seed for j in nets], every,
                     device=device, threads=threads, saves=[j.save for j in nets],
                     progresses=[j.progress for j in nets], stages=[j.stages for j in nets], precision=precision)
    step_s = out[0]["step_s"]
    print(f"ensemble of {len(keys)} nets: {steps} steps, {steps / step_s:.2f} steps/s in its training steps "
          f"({len(keys) * steps / step_s:.1f} net-steps/s), {out[0]['train_s']:.0f} s with the tests", flush=True)
    return dict(zip(keys, out))


@dataclasses.dataclass
class ResultsFile:
    """results/learning_raft[_TAG].json of a run (``protocol.results_name``): the protocol's settings, the machine
    and every finished seed's runs; ``write`` rewrites it and prints the last seed's scores."""

    args: object
    seeds: list
    steps: int
    every: int
    zero: dict
    trainer: str

    def write(self, runs: list, cfg, complete: bool) -> None:
        """Write ``runs`` (one {"seed", "zero_flow_epe", "results": {arm: result}, "data", "generation_s"} per
        finished seed, in any order), the flowsynth config ``cfg`` and whether every planned seed is in
        (``complete``); print a table of the last seed's EPE per checkpoint and score."""
        a = self.args
        write_json(results_name("", a.tag), {
            "complete": complete, "seeds_planned": self.seeds, "net": NET, "steps": self.steps, "every": self.every,
            "batch": BATCH, "crop": CROP, "resolution": RES, "pool": a.pool or POOL, "lr": LR,
            "updates": [UPDATES, TEST_UPDATES], "judged_checkpoints": JUDGED, "device": a.device,
            "trainer": self.trainer, "precision": a.precision, "overrides": a.overrides,
            "flowsynth_config": cfg.to_dict(),
            "machine": machine_info(), "runs": sorted(runs, key=lambda r: r["seed"])})
        seed, res = runs[-1]["seed"], runs[-1]["results"]
        rows = [{"seed": seed, "arm": arm, "judge": j, "zero flow": self.zero[j], "untrained": r["curve"][0][j],
                 **{f"@{c['step']}": c[j] for c in r["curve"][1:]}, "score": score(r["curve"], j)}
                for arm, r in res.items() for j in JUDGES if j in r["curve"][0]]
        print_table(rows, list(rows[0]))


def run_at_once(args, names: list, seeds: list, steps: int, every: int, tests: dict, results: ResultsFile) -> None:
    """``--at-once`` (a lent GPU): the pools of every seed first, then every net of every seed at once, each in a
    process of its own (``--ensemble``: all in this process, ``train_together``); a seed's results are written when
    all its nets are done."""
    import torch.multiprocessing as tmp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    pools, infos, cfg = {}, {}, None
    t = time.perf_counter()
    for seed in seeds:
        pools[seed], infos[seed], cfg = build_arms(names, seed, args.workers, args.overrides, args.pool or POOL,
                                                   args.preset)
        print(f"pools of seed {seed} ready after {time.perf_counter() - t:.0f} s", flush=True)
    gen_s = time.perf_counter() - t
    while args.train_after and not Path(args.train_after).exists():  # the device's other benchmarks come first
        time.sleep(1)
    print(f"training starts after {time.perf_counter() - t:.0f} s", flush=True)
    runs = []
    if args.ensemble:
        res = train_together({(seed, name): pools[seed][name] for seed in seeds for name in names}, tests, steps,
                             every, args.threads, args.device, args.tag, args.precision)
        for seed in seeds:
            runs.append({"seed": seed, "zero_flow_epe": results.zero, "results": {name: res[seed, name]
                                                                                  for name in names},
                         "data": infos[seed], "generation_s": gen_s})
            results.write(runs, cfg, len(runs) == len(seeds))
        return
    done: dict = {seed: {} for seed in seeds}
    with ProcessPoolExecutor(len(seeds) * len(names), mp_context=tmp.get_context("spawn")) as ex:
        futs = {ex.submit(NetJob.of(name, pools[seed][name], seed, args.tag, args.precision).train, tests, steps,
                          every, 1, args.device): (seed, name) for seed in seeds for name in names}
        for f in as_completed(futs):
            seed, name = futs[f]
            done[seed][name] = f.result()
            print(f"seed {seed} {name} done after {time.perf_counter() - t:.0f} s", flush=True)
            if len(done[seed]) == len(names):
                runs.append({"seed": seed, "zero_flow_epe": results.zero, "results": done[seed], "data": infos[seed],
                             "generation_s": gen_s})
                results.write(runs, cfg, len(runs) == len(seeds))


def run(args) -> None:
    """Train the arms of every seed (``protocol``'s docstring) and write the results after each seed. ``args``: the
    command line's namespace (``cli``): seeds, arms, steps, every, pool, workers, threads, jobs, device, at_once,
    ensemble, train_after, middlebury, overrides (the ``--set`` fields), tag, precision, preset (the ``tuned`` arm's
    file). Raises SystemExit for an
    unknown arm."""
    import torch

    torch.set_num_threads(args.threads)
    steps = args.steps or STEPS
    every = min(args.every or EVERY, steps)
    names = args.arms.split(",")
    bad = [n for n in names if n not in ARMS]
    if bad:
        raise SystemExit(f"--arms: unknown {bad}; known {ARMS}")
    tests = judge_sets(args.middlebury)
    seeds = [int(s) for s in args.seeds.split(",")]
    # how the nets trained: all at once in this process, each in a process of its own, or one after another here
    trainer = "ensemble" if args.ensemble else "processes" if args.at_once or args.jobs else "in turn"
    results = ResultsFile(args, seeds, steps, every, zero_flow(tests), trainer)
    if args.at_once:
        return run_at_once(args, names, seeds, steps, every, tests, results)
    runs = []
    for seed in seeds:
        t = time.perf_counter()
        arms, info, cfg = build_arms(names, seed, args.workers, args.overrides, args.pool or POOL, args.preset)
        gen_s = time.perf_counter() - t
        if args.ensemble:
            res = {arm: r for (_, arm), r in train_together({(seed, arm): pool for arm, pool in arms.items()}, tests,
                                                            steps, every, args.threads, args.device,
                                                            args.tag, args.precision).items()}
        else:
            res = train_all(arms, tests, steps, seed, every, args.jobs, args.threads, args.device, args.tag,
                            args.precision)
        runs.append({"seed": seed, "zero_flow_epe": results.zero, "results": res, "data": info, "generation_s": gen_s})
        results.write(runs, cfg, seed == seeds[-1])
