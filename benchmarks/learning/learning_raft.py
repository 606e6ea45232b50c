"""The learning judge of issue 46: torchvision's RAFT-small, trained from scratch on each arm's pairs, tested on real
flow. ``benchmarks/learning/learning.py`` runs it (its default ``--net raft``); the protocol and the rules are
pre-registered in docs/decisions/0023-raft-judge.md.

    python benchmarks/learning/learning.py [--seeds 0,1] [--arms flowsynth,chairs2d_photos] [--steps 2400]
                                  [--middlebury DIR] [--set FIELD=JSON] [--tag NAME] [--device cuda] [--jobs 2]
    python benchmarks/learning/learning.py --summarize [--files 'learning_raft*.json'] [--arm flowsynth]
                                  [--against chairs2d_photos]
    python benchmarks/learning/learning.py --figures NAME [--middlebury DIR]   # predicted flow of the saved nets

Protocol (the numbers are module constants):

- Net: ``torchvision.models.optical_flow.raft_small(weights=None)`` (0.99 M parameters), RAFT's recipe as
  ``flowsynth.training`` implements it (the same step ``examples/train_raft.py`` runs): sequence loss (gamma 0.8),
  AdamW at ``LR`` with weight decay 1e-4 and a linear one-cycle schedule, gradient clip 1, ``UPDATES`` flow updates
  in training and ``TEST_UPDATES`` at test; ``STEPS`` steps of ``BATCH`` random ``CROP`` crops with flips and colour
  jitter, the same augmentation for every arm.
- Training pools: ``POOL`` pairs per arm rendered at ``RES`` (256x192), images kept as uint8.
  - ``flowsynth``: ``BouncingThingsConfig()`` (with ``--set`` changes: a lever) at 256x192, 2 frames, its
    ``flow_px`` halved so motion keeps the proportions of a 512x384 rendering; procedural textures only.
  - ``chairs2d_photos``: the FlyingChairs-style 2D baseline (``learning_sets.chairs2d_pairs``) textured with crops of
    every photograph that ships with scikit-image (``NATURAL_PHOTOS``), as FlyingChairs is textured with photographs.
  - ``chairs2d``: the same baseline textured with flowsynth frames not trained on: it isolates what the 3D motion
    teaches. Both baselines' motion is scaled so that their mean |flow| equals the flowsynth pool's.
  - ``flowsynth_photos``: the flowsynth config with NATURAL_PHOTOS as every texture (``texture_families=("image",)``).
  - ``flowsynth_natural``: the same with 96 textures made without files, with statistics of photographs instead
    (``learning_sets.natural_folder``: 1/f spectra, dead leaves, sparse edges over smooth regions).
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
.cache/learning_raft/TAG_ARM_sSEED.pt (for ``--figures``).
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

sys.path[:0] = [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parents[1])]  # siblings, _common

from _common import RESULTS_DIR, machine_info, print_table, pyplot, save_figure, write_json
from learning_sets import NATURAL_PHOTOS, chairs2d_pairs, middlebury_pairs, motorcycle_full, natural_folder, \
    photo_folder, photo_sources, small_motion_pairs

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
    ("rgb", or "rgb_final": the final pass)."""
    import torch
    from torch.utils.data import DataLoader

    import flowsynth as fs

    base = fs.BouncingThingsConfig.from_dict(overrides or {})
    cfg = dataclasses.replace(base, width=RES[0], height=RES[1], num_frames=2,
                              flow_px=tuple(x / SCALE for x in base.flow_px))
    ds = fs.datasets.BouncingThings(cfg, outputs=[image, "flow_fw", "valid_fw"], seed=seed, length=n)
    w, h = RES
    img1, img2 = torch.empty(n, 3, h, w, dtype=torch.uint8), torch.empty(n, 3, h, w, dtype=torch.uint8)
    flow, valid = torch.empty(n, 2, h, w), torch.empty(n, 1, h, w, dtype=torch.bool)
    o = 0
    for b in DataLoader(ds, batch_size=16, num_workers=workers):
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


def run_at_once(args, names: list, seeds: list, steps: int, every: int, tests: dict, zero: dict, header) -> None:
    """``--at-once`` (a lent GPU): the pools of every seed first, then every net of every seed at once, each in a
    process of its own; a seed's results are written when all its nets are done."""
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

    def save(runs: list, cfg, complete: bool) -> None:
        write_json(name, {"complete": complete, "seeds_planned": seeds, "net": NET, "steps": steps,
                          "every": every, "batch": BATCH, "crop": CROP, "resolution": RES, "pool": args.pool or POOL,
                          "lr": LR,
                          "updates": [UPDATES, TEST_UPDATES], "judged_checkpoints": JUDGED, "device": args.device,
                          "overrides": args.overrides, "flowsynth_config": cfg.to_dict(), "machine": machine_info(),
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
        res = train_all(arms, tests, steps, seed, every, args.jobs, args.threads, args.device, args.tag)
        runs.append({"seed": seed, "zero_flow_epe": zero, "results": res, "data": info, "generation_s": gen_s})
        save(runs, cfg, seed == seeds[-1])


# -- pooling --------------------------------------------------------------------------------------------------
def _complete_runs(pattern: str, who: str):
    """(file, its JSON, one seed's run) for every seed of the complete runs of this judge in the results/ files
    matching ``pattern``, in name order; unfinished runs and other judges are skipped. All must share the protocol."""
    protocol = {}
    for f in sorted(RESULTS_DIR.glob(pattern)):
        d = json.loads(f.read_text())
        if not d.get("complete") or d.get("net") != NET:
            continue
        same = {k: d.get(k) for k in ("steps", "pool", "batch", "resolution", "every", "lr", "updates")}
        if protocol and same != protocol:
            raise SystemExit(f"{who}: {f.name} ran another protocol ({same}) than the files before it ({protocol})")
        protocol = same
        for r in d.get("runs", []):
            yield f, d, r


def summarize(pattern: str, arm: str, against: str) -> dict:
    """Pool the seeds on which the complete runs with no ``--set`` in the results/ files matching ``pattern`` hold
    both arms (a seed's two arms may come from two files; an arm twice on one seed is an error): per judge, each
    seed's score ratio ``arm`` / ``against``, their geometric mean with a 95% interval (t on the log ratios), the
    seeds in favour, and the rule-1 count (``arm``'s net ends below zero flow and below its untrained start)."""
    import numpy as np
    from scipy import stats

    runs = {}  # seed -> {"results": {arm: result}, "zero_flow_epe": ...}: one seed's arms may lie in several files
    for f, d, r in _complete_runs(pattern, "--summarize"):
        if d.get("overrides"):
            continue  # a --set lever's flowsynth arm is not the default
        names = {arm, against} & set(r["results"])
        if not names:
            continue
        seed = runs.setdefault(r["seed"], {"seed": r["seed"], "results": {}, "zero_flow_epe": r["zero_flow_epe"],
                                           "config": d.get("flowsynth_config"), "file": f.name})
        zero, other = seed["zero_flow_epe"], r["zero_flow_epe"]  # float32 sums differ in the 7th digit
        if set(zero) != set(other) or any(abs(zero[k] - other[k]) > 1e-5 * abs(zero[k]) for k in zero):
            differ = "their judges (zero flow EPE)"  # another --middlebury: not one comparison
        elif d.get("flowsynth_config") != seed["config"]:
            differ = "flowsynth_config"  # another default
        else:
            differ = None
        if differ:
            raise SystemExit(f"--summarize: seed {r['seed']}'s runs in {seed['file']} and {f.name} differ in {differ}")
        for name in names:
            if name in seed["results"]:
                raise SystemExit(f"--summarize: seed {r['seed']}'s {name} is in {seed['results'][name][0]} and in "
                                 f"{f.name}")
            seed["results"][name] = (f.name, r["results"][name])
    runs = {k: {**v, "results": {a: res for a, (_, res) in v["results"].items()}} for k, v in sorted(runs.items())
            if {arm, against} <= set(v["results"])}
    if not runs:
        raise SystemExit(f"--summarize: no complete run of results/{pattern} with no --set holds both {arm} and "
                         f"{against} on a seed")
    out, rows = {}, []
    for j in JUDGES:
        rs = [r for r in runs.values() if j in r["zero_flow_epe"]]
        if not rs:
            continue
        a = np.array([score(r["results"][arm]["curve"], j) for r in rs])
        b = np.array([score(r["results"][against]["curve"], j) for r in rs])
        logs = np.log(a / b)
        if not np.isfinite(logs).all():  # a diverged net (NaN EPE) or a zero score: no ratio to pool
            bad = [r["seed"] for r, x in zip(rs, logs) if not np.isfinite(x)]
            raise SystemExit(f"--summarize: {arm} / {against} on {j} is not finite on seeds {bad}")
        n = len(logs)
        half = stats.t.ppf(0.975, n - 1) * logs.std(ddof=1) / np.sqrt(n) if n > 1 else None  # one seed: none
        useful = sum(score(r["results"][arm]["curve"], j) < min(r["zero_flow_epe"][j],
                                                                 r["results"][arm]["curve"][0][j]) for r in rs)
        out[j] = {"seeds": [r["seed"] for r in rs], "ratios": (a / b).tolist(),
                  "geometric_mean": float(np.exp(logs.mean())),
                  "ci95": None if half is None else [float(np.exp(logs.mean() - half)),
                                                     float(np.exp(logs.mean() + half))],
                  "in_favour": int((logs < 0).sum()), "useful": useful, arm: a.tolist(), against: b.tolist(),
                  "zero_flow": float(np.mean([r["zero_flow_epe"][j] for r in rs])),
                  "untrained": float(np.mean([r["results"][arm]["curve"][0][j] for r in rs]))}
        o = out[j]
        rows.append({"judge": j, "seeds": n, "ratio": o["geometric_mean"],
                     "95% CI": f"{o['ci95'][0]:.3f}-{o['ci95'][1]:.3f}" if o["ci95"] else "n/a (one seed)",
                     "in favour": f"{o['in_favour']} of {n}",
                     f"{arm} useful": f"{useful} of {n}", arm: float(a.mean()), against: float(b.mean()),
                     "zero flow": o["zero_flow"], "untrained": o["untrained"]})
    print(f"{arm} / {against}, scores (mean of the last {JUDGED} checkpoints), seeds {sorted(runs)}")
    print_table(rows, list(rows[0]))
    return {"arm": arm, "against": against, "pattern": pattern, "judges": out}


def plot_summary(out: dict, name: str):
    """``summarize``'s result as a picture (results/NAME.png): per judge, each seed's ratio arm / against as a dot
    labelled by its seed, the geometric mean as a bar with its 95% interval, and 1 (no difference) as a line; a log
    axis, so 0.5 and 2 lie as far from 1. Returns the path (None without matplotlib)."""
    plt = pyplot()
    if plt is None:
        return None
    judges = list(out["judges"])
    fig, ax = plt.subplots(figsize=(5, 4), dpi=110)
    for x, j in enumerate(judges):
        o = out["judges"][j]
        ax.plot([x] * len(o["ratios"]), o["ratios"], "o", color="C0", alpha=0.7)
        for seed, r in zip(o["seeds"], o["ratios"]):
            ax.annotate(f"s{seed}", (x, r), textcoords="offset points", xytext=(6, -3), fontsize=7)
        lo, hi = o["ci95"] or (o["geometric_mean"],) * 2
        ax.errorbar([x + 0.25], [o["geometric_mean"]], yerr=[[o["geometric_mean"] - lo], [hi - o["geometric_mean"]]],
                    fmt="s", color="C3", capsize=4)
    ax.axhline(1.0, color="grey", lw=1)
    ax.set_yscale("log")
    from matplotlib.ticker import FormatStrFormatter

    ax.yaxis.set_major_formatter(FormatStrFormatter("%.2g"))
    ax.yaxis.set_minor_formatter(FormatStrFormatter("%.2g"))
    ax.set_xticks(range(len(judges)), [{"stereo": "Motorcycle", "middlebury": "Middlebury mean"}.get(j, j)
                                       for j in judges])
    ax.set_xlim(-0.5, len(judges) - 0.3)
    ax.set_ylabel(f"score ratio {out['arm']} / {out['against']}")
    ax.set_title("seeds (dots), geometric mean and 95% interval (squares)", fontsize=9)
    ax.grid(True, which="both", axis="y", alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, name)


SCREEN_MB, SCREEN_MOTO = 0.85, 1.10  # rule 4's thresholds on candidate / default (Middlebury mean, Motorcycle)


def screen(pattern: str, seed: int = 0) -> list[dict]:
    """Rule 4 of docs/decisions/0023 for every lever in the results/ files matching ``pattern``: on ``seed``, the
    score ratio candidate / default per judge beside the control's ratio control / default. The default is the
    ``flowsynth`` arm of a run with no ``--set``; the control, the ``control`` arm of such a run; a candidate, any
    other flowsynth-made arm (``flowsynth`` with ``--set``, ``flowsynth_natural``, ``flowsynth_photos``,
    ``flowsynth_final``, ``mixture``, ``curriculum``). Promising: Middlebury ratio below ``SCREEN_MB`` and below the
    control's band (the lower of c and 1/c: a gain beyond the noise), and Motorcycle ratio at most ``SCREEN_MOTO``;
    each judge's ratio is also read against the band (better, within the noise, worse). Only complete runs of this
    judge count, and all must share the protocol."""
    ref, cands = {}, []
    for f, d, r in _complete_runs(pattern, "--screen"):
        if r["seed"] != seed:
            continue
        for arm, res in r["results"].items():
            if arm in ("flowsynth", "control") and not d.get("overrides"):
                if arm in ref:
                    raise SystemExit(f"--screen: seed {seed}'s {arm} is in {ref[arm][0]} and in {f.name}")
                ref[arm] = (f.name, res["curve"])
            elif not arm.startswith("chairs2d"):
                label = arm if arm != "flowsynth" else ",".join(f"{k}={v}" for k, v in d["overrides"].items())
                cands.append((f.stem.removeprefix("learning_raft_"), label, res["curve"]))
    if len(ref) < 2:
        raise SystemExit(f"--screen: results/{pattern} must hold seed {seed}'s default and its control (complete runs "
                         "with no --set)")
    default, control = ref["flowsynth"][1], ref["control"][1]
    band = {j: sorted((score(control, j) / score(default, j), score(default, j) / score(control, j))) for j in JUDGES}
    rows = []
    for tag, label, curve in cands:
        ratio = {j: score(curve, j) / score(default, j) for j in JUDGES}
        reading = {j: "better" if ratio[j] < band[j][0] else "worse" if ratio[j] > band[j][1] else "noise"
                   for j in JUDGES}
        promising = (ratio["middlebury"] < SCREEN_MB and reading["middlebury"] == "better"
                     and ratio["stereo"] <= SCREEN_MOTO)
        rows.append({"run": tag, "lever": label, "Motorcycle": ratio["stereo"],
                     "Motorcycle vs noise": reading["stereo"], "Middlebury": ratio["middlebury"],
                     "Middlebury vs noise": reading["middlebury"],
                     "promising (rule 4)": promising})
    print(f"seed {seed}: candidate / default; control / default: Motorcycle {band['stereo'][0]:.3f}-"
          f"{band['stereo'][1]:.3f}, Middlebury {band['middlebury'][0]:.3f}-{band['middlebury'][1]:.3f}")
    return rows


def texture_map(img):
    """(B, 1, H, W) mean |grey-level gradient| over each pixel's 9x9 window (images (B, 3, H, W) in [0, 1])."""
    from torch.nn import functional as F

    grey = img.float().mean(1, keepdim=True)
    grad = (grey[..., :, 1:] - grey[..., :, :-1]).abs()[..., :-1, :] + \
        (grey[..., 1:, :] - grey[..., :-1, :]).abs()[..., :, :-1]
    return F.avg_pool2d(F.pad(grad, (4, 5, 4, 5), mode="replicate"), 9, 1)


def pool_stats(names: list, n: int, workers: int, overrides: dict, middlebury_dir: str | None = None) -> list[dict]:
    """Per arm, over ``n`` training pairs of seed 0 at RES: |flow| percentiles and the share of valid pixels moving
    less than 0.5, 1 and 2 px, and the textureless share (``SMOOTH``); the real judges beside them."""
    import torch

    arms, _, _ = build_arms(names, 0, workers, overrides, n)
    sets = {**{k: (v[0].float() / 255, v[1], v[2], v[3]) for k, v in arms.items()}, **judge_sets(middlebury_dir)}
    rows = []
    for name, (img1, _, flow, valid) in sets.items():
        mag = torch.linalg.vector_norm(flow, dim=1)[valid[:, 0] > 0.5]
        q = torch.quantile(mag[torch.randperm(len(mag))[:1_000_000]], torch.tensor([0.1, 0.5, 0.9]))
        rows.append({"set": name, "mean |flow|": float(mag.mean()), "p10": float(q[0]), "p50": float(q[1]),
                     "p90": float(q[2]), "< 0.5 px": float((mag < 0.5).float().mean()),
                     "< 1 px": float((mag < 1).float().mean()), "< 2 px": float((mag < 2).float().mean()),
                     "textureless": float((texture_map(img1) < SMOOTH).float().mean())})
    return rows


# -- where a net fails ----------------------------------------------------------------------------------------
SMOOTH = 0.02  # a pixel is "smooth" when the mean |grey-level gradient| over its 9x9 window is below this (of 1)
SMALL = 4.0  # [px] "small" true motion


def diagnose(nets: list[str], middlebury_dir: str | None) -> list[dict]:
    """Per saved net and real pair, the EPE over four kinds of valid pixel: smooth (low texture, ``SMOOTH``) or
    textured, crossed with small (|flow| < ``SMALL``) or large true motion; the share of each kind; and zero flow's
    EPE. Where a net "sees motion everywhere", its error on smooth pixels with small motion stands out. The pairs:
    the real judges and the small-motion diagnostic (``small_motion_pairs``: the judges' photographs moved by at
    most 0, 1 and 3 px; on a still pair the EPE is the motion the net invents)."""
    import torch

    from flowsynth.training import predict

    tests = judge_sets(middlebury_dir)
    tests.update(small_motion_pairs({k: v for k, v in tests.items() if k.startswith("mb_")}))
    rows = []
    for path in nets:
        net = raft_small()
        net.load_state_dict(torch.load(path, map_location="cpu"))
        for pair, (img1, img2, flow, valid) in tests.items():
            texture = texture_map(img1[:1])
            err = torch.linalg.vector_norm(predict(net, img1[:1], img2[:1], TEST_UPDATES) - flow[:1], dim=1,
                                           keepdim=True)
            small = torch.linalg.vector_norm(flow[:1], dim=1, keepdim=True) < SMALL
            v = valid[:1] > 0.5
            row = {"net": Path(path).stem, "pair": pair, "all": float(err[v].mean()),
                   "zero flow": float(torch.linalg.vector_norm(flow[:1], dim=1, keepdim=True)[v].mean())}
            for tname, tmask in (("smooth", texture < SMOOTH), ("textured", texture >= SMOOTH)):
                for mname, mmask in (("small", small), ("large", ~small)):
                    m = v & tmask & mmask
                    row[f"{tname}/{mname}"] = float(err[m].mean()) if m.any() else None
                    row[f"share {tname}/{mname}"] = float(m.sum() / v.sum())
            rows.append(row)
    return rows


# -- figures --------------------------------------------------------------------------------------------------
def figures(name: str, middlebury_dir: str | None, nets: list[str]) -> list:
    """One PNG per real pair and per still pair of the small-motion diagnostic (results/NAME_PAIR.png): frame 1, the
    ground truth and, per saved net (``nets``: paths of .pt files from ``train``), its predicted flow and its
    end-point error, on one colour scale per pair (at least 1 px)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    from flowsynth.training import predict
    from flowsynth.viz import flow_to_color

    tests = judge_sets(middlebury_dir)
    still = small_motion_pairs({k: v for k, v in tests.items() if k.startswith("mb_")}, magnitudes=(0.0,))
    tests.update(still)  # the still pairs of the small-motion diagnostic: the motion a net invents
    loaded = {}
    for p in nets:
        net = raft_small()
        net.load_state_dict(torch.load(p, map_location="cpu"))
        loaded[Path(p).stem] = net
    paths = []
    for pair, (img1, img2, flow, valid) in tests.items():
        gt = flow[:1]
        scale = max(float(torch.linalg.vector_norm(gt, dim=1)[valid[:1, 0] > 0.5].max()), 1.0)
        cols = 2 + len(loaded)
        fig, ax = plt.subplots(2, cols, figsize=(3.2 * cols, 5.6))
        ax[0, 0].imshow(img1[0].permute(1, 2, 0).numpy())
        ax[0, 0].set_title(f"{pair}: frame 1")
        ax[0, 1].imshow(flow_to_color(gt[0], max_flow=scale))
        ax[0, 1].set_title(f"ground truth (max {scale:.1f} px)")
        ax[1, 0].imshow(valid[0, 0].numpy(), cmap="gray", vmin=0, vmax=1)
        ax[1, 0].set_title("valid")
        ax[1, 1].axis("off")
        for k, (label, net) in enumerate(loaded.items(), 2):
            pred = predict(net, img1[:1], img2[:1], TEST_UPDATES)
            err = torch.linalg.vector_norm(pred - gt, dim=1)[0] * (valid[0, 0] > 0.5)
            epe = float(err.sum() / (valid[0, 0] > 0.5).sum())
            ax[0, k].imshow(flow_to_color(pred[0], max_flow=scale))
            ax[0, k].set_title(f"{label}")
            im = ax[1, k].imshow(err.numpy(), cmap="magma", vmin=0, vmax=max(scale, 1.0))
            ax[1, k].set_title(f"error, EPE {epe:.2f} px")
        if loaded:
            fig.colorbar(im, ax=ax[1, -1], fraction=0.046)
        for a in ax.flat:
            a.set_xticks([])
            a.set_yticks([])
        fig.tight_layout()
        out = RESULTS_DIR / f"{name}_{pair}.png"
        RESULTS_DIR.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=80)
        plt.close(fig)
        paths.append(out)
    return paths


# -- command line ---------------------------------------------------------------------------------------------
def main(argv: list[str]) -> None:
    """``benchmarks/learning/learning.py --net raft`` (the default since issue 46): the command line of this judge."""
    import argparse

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--net", choices=("raft", "ncc-v2"), default="raft")
    p.add_argument("--quick", action="store_true", help="a smoke run: 12 pairs an arm, 20 steps, tests every 10")
    p.add_argument("--seeds", default="0")
    p.add_argument("--arms", default="flowsynth,chairs2d_photos",
                   help=f"comma-separated, of {', '.join(ARMS)}")
    p.add_argument("--steps", type=int, default=None, help=f"training steps per net (default {STEPS})")
    p.add_argument("--every", type=int, default=None, help=f"test every this many steps (default {EVERY})")
    p.add_argument("--pool", type=int, default=None, help=f"training pairs per arm (default {POOL})")
    p.add_argument("--workers", type=int, default=2, help="DataLoader workers rendering the flowsynth pairs")
    p.add_argument("--threads", type=int, default=2, help="torch threads in all (split between --jobs)")
    p.add_argument("--jobs", type=int, default=2, help="nets trained at once, each in a process of its own; 0: one "
                                                       "after another in this process")
    p.add_argument("--device", default="cpu", help="torch device the nets train and test on (e.g. cuda)")
    p.add_argument("--at-once", action="store_true", help="render every seed's pools, then train every net of every "
                   "seed at once, each in a process of its own (a lent GPU)")
    p.add_argument("--train-after", default=None, metavar="FILE", help="--at-once: render the pools, then wait until "
                   "FILE exists before training (so that other benchmarks have the GPU to themselves)")
    p.add_argument("--middlebury", default=None, metavar="DIR",
                   help="a folder of Middlebury flow pairs (NAME/frame10.png, frame11.png, flow10.flo)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=JSON",
                   help="a lever: the flowsynth arms' config with this field changed (repeatable); use with --tag")
    p.add_argument("--tag", default="", help="results/learning_raft_TAG.json")
    p.add_argument("--summarize", action="store_true", help="train nothing: pool the seeds of --files")
    p.add_argument("--files", default="learning_raft*.json", help="--summarize: results/ files to pool (a glob)")
    p.add_argument("--arm", default="flowsynth", help="--summarize: the numerator arm")
    p.add_argument("--against", default="chairs2d_photos", help="--summarize: the denominator arm")
    p.add_argument("--screen", action="store_true", help="train nothing: rule 4 for every lever of seed 0 in the "
                   "--files results, against the default and its control (results/learning_raft_screens.json)")
    p.add_argument("--figures", default=None, metavar="NAME",
                   help="train nothing: results/NAME_PAIR.png per real pair, the nets in --nets against the truth")
    p.add_argument("--nets", default="", help="--figures, --diagnose: comma-separated .pt files of training runs")
    p.add_argument("--plot", default=None, metavar="NAME", help="train nothing: results/NAME_JUDGE.png, the learning "
                   "curves of every arm and seed in the --files results")
    p.add_argument("--stats", action="store_true", help="train nothing: flow-magnitude and texture statistics of "
                   "--arms' pools, a lever's with --set (--pool pairs, default 64), beside the real judges")
    p.add_argument("--diagnose", action="store_true", help="train nothing: per net of --nets and real pair, the EPE "
                   "on smooth or textured pixels with small or large true motion (results/learning_raft_diagnose"
                   "[_TAG].json)")
    args = p.parse_args(argv)
    args.overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        if key in ("width", "height", "num_frames") or not value:
            p.error(f"--set {item!r}: give FIELD=JSON for a field other than width, height, num_frames")
        try:
            args.overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            p.error(f"--set {item!r}: the value must be JSON, e.g. num_objects=[2,8]")
    if args.summarize:
        out = summarize(args.files, args.arm, args.against)
        name = f"learning_raft_summary_{args.arm}_{args.against}" + (f"_{args.tag}" if args.tag else "")
        write_json(name, out)
        print(f"plot: {plot_summary(out, name) or 'none (matplotlib is in the bench extra)'}")
        return
    if args.screen:
        rows = screen(args.files)
        print_table(rows, list(rows[0])) if rows else print("--screen: no lever in the files")
        write_json("learning_raft_screens" + (f"_{args.tag}" if args.tag else ""), {"files": args.files, "rows": rows})
        return
    if args.plot:
        from learning import plot_judge_curves

        for path in plot_judge_curves(args.plot, args.files):
            print(f"wrote {path}")
        return
    if args.stats:
        rows = pool_stats(args.arms.split(","), args.pool or 64, args.workers, args.overrides, args.middlebury)
        print_table(rows, list(rows[0]))
        write_json("learning_raft_stats" + (f"_{args.tag}" if args.tag else ""), {"pairs": args.pool or 64,
                                                                                   "rows": rows})
        return
    if args.diagnose:
        rows = diagnose([n for n in args.nets.split(",") if n], args.middlebury)
        print_table(rows, list(rows[0]))
        write_json("learning_raft_diagnose" + (f"_{args.tag}" if args.tag else ""), {"rows": rows})
        return
    if args.figures:
        for path in figures(args.figures, args.middlebury, [n for n in args.nets.split(",") if n]):
            print(f"wrote {path}")
        return
    if args.steps is not None and args.steps < 20:
        p.error(f"--steps {args.steps}: give at least 20 steps")
    if args.quick:
        args.pool, args.steps, args.every = args.pool or 12, args.steps or 20, args.every or 10
    run(args)
