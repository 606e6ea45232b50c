"""``tune``: the generator's knobs fitted to a user's validation pairs, resumable; what ``flowsynth tune`` runs.

Files, beside the preset ``out`` (``PRESET.json``): a folder ``PRESET.tune/`` holding ``state.pt`` (the search and
its nets, replaced atomically after every checkpoint: the same call continues from it), ``progress.json`` (the curves
so far), ``pools/`` (the training pools of the nets still in the search, ``flowsynth.tune.PoolCache``: a resumed
tune reads them instead of rendering them; deleted when the tune is done), and once done ``report.json``,
``report.md`` and ``curves.png`` (where matplotlib is installed).
"""

from __future__ import annotations

import dataclasses
import hashlib
import re
from collections.abc import Callable
from pathlib import Path

import torch

from flowsynth.errors import ConfigError
from flowsynth.options import check_int
from flowsynth.io import atomic_path, atomic_write_bytes, write_json
from flowsynth.tune.halving import TWIN, TWIN_SEED, plan_cost, plan_rungs, rank, search
from flowsynth.tune.pairs import find_pairs, image_size, load_pairs
from flowsynth.tune.pools import PoolCache, refuse_other_tune
from flowsynth.tune.report import markdown, plot, summarize
from flowsynth.tune.resources import GIB, check, estimate
from flowsynth.tune.space import draw_candidates, preset, sources
from flowsynth.tune.trainer import QUICK, RECIPE, EnsembleTrainer, Pair, Recipe

__all__ = ["DEFAULT_BUDGET", "DEFAULT_CANDIDATES", "tune", "work_dir"]

DEFAULT_CANDIDATES = 6
"""The most whose rung 0 (7 nets with the twin) trains at the judge's recipe on the CPU of an 8 GiB machine
(``flowsynth.tune.resources``: about 6.5 GiB at the peak; 8 candidates need 8.1)."""
DEFAULT_BUDGET = plan_cost(DEFAULT_CANDIDATES, 300)
"""[net-steps] 9600: 6 candidates halved over rungs ending at steps 300, 600, 1200 and 2400 (the judge's length)."""
QUICK_CANDIDATES = 2
RAFT_MIN = 128  # [px] RAFT-small's correlation pyramid needs crops of at least this a side
GO_ON = "pass --no-resource-check to go on anyway"  # the message's last words: how to skip check_resources


def work_dir(out: str | Path) -> Path:
    """The folder of a tune's state and report beside its preset ``out``: PRESET.json -> PRESET.tune."""
    out = Path(out)
    return out.with_name(out.stem + ".tune")


def _fingerprint(pairs: dict[str, Pair]) -> str:
    h = hashlib.sha256()
    for name, pair in pairs.items():  # the images as float32 in [0, 1], as the pairs were once held
        h.update(name.encode())
        for x in (*pair.images(), pair.flow, pair.valid):
            h.update(x.numpy().tobytes())
    return h.hexdigest()[:16]


def _device(name: str) -> torch.device:
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError) as e:
        raise ConfigError(f"device {name!r} is not a torch device name (cpu, cuda, cuda:1, ...): {e}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device {name!r}: torch finds no CUDA device here; use --device cpu")
    return dev


def _px(score: float | None) -> str:
    return "diverged" if score is None else f"{score:.3f} px"


def _remove_temporaries(work: Path, out: Path) -> None:
    """Delete the temporaries a killed run left: ``flowsynth.io.atomic_path`` writes ``.NAME.tmp-XXXXXXXX.EXT``
    beside each file and renames it over the file when whole, so one a SIGKILL interrupted stays (a partial state is
    tens of MB). Every such file in ``work`` is this tune's; beside the preset ``out``, only ``out``'s own."""
    own = re.compile(rf"\.{re.escape(out.stem)}\.tmp-[0-9a-f]{{8}}{re.escape(out.suffix)}")
    for p in [*work.glob(".*.tmp-*"), *work.glob("pools/.*.tmp-*"),
              *(p for p in out.parent.glob(".*.tmp-*") if own.fullmatch(p.name))]:
        p.unlink(missing_ok=True)


def _load(path: Path, identity: dict) -> dict | None:
    if not path.is_file():
        return None
    saved = torch.load(path, map_location="cpu", weights_only=True)
    refuse_other_tune(f"{path.parent} holds", saved["identity"], identity)
    return saved["search"]


def tune(val: str | Path, out: str | Path, *, pairs: list[str] | None = None, budget: int | None = None,
         candidates: int | None = None, seed: int = 0, device: str = "cpu", precision: str = "fp32",
         workers: int = 0, quick: bool = False, pool: int | None = None, recipe: Recipe | None = None,
         check_resources: bool = True, net: Callable | None = None, render: Callable | None = None,
         log: Callable[[str], None] = print) -> dict:
    """Fit the generator to the validation pairs in ``val`` by successive halving of nets trained on its settings
    (docs/tune.md), write the winner's preset to ``out`` and the report beside it (``work_dir(out)``).

    Args:
        val: a folder of validation pairs (``flowsynth.tune.pairs``: Middlebury, FlyingChairs, KITTI, Sintel).
        out: the preset file to write (``fs.datasets.Mixture.from_preset`` reads it; its first source's config is
            ``BouncingThingsConfig.from_dict``'s).
        pairs: only these pairs (names or globs); None: all.
        budget: training steps over all nets [net-steps: one step of one net on one batch of ``recipe.batch``
            crops]; None: ``DEFAULT_BUDGET`` (``quick``: the smallest that trains the candidates).
        candidates: points of the search space tried, the default's among them (None: 8; ``quick``: 2).
        seed: the tune's seed: the candidates drawn, the nets' weights, pools and batches.
        device: the torch device the nets train on ("cpu", "cuda", ...); pools render on the CPU.
        precision: "fp32", "bf16" or "fp16" (CUDA) (``flowsynth.train.steps.PRECISIONS``).
        workers: processes rendering the pools (0: this one).
        quick: a tiny recipe (``flowsynth.tune.trainer.QUICK``) to check that a tune runs; its winner means little.
        pool: training pairs rendered per net (None: the recipe's).
        recipe: how nets train and test (default ``RECIPE``, the learning judge's; ``quick``: ``QUICK``).
        check_resources: estimate the memory and disk the tune needs before any work (``flowsynth.tune.resources``)
            and refuse what does not fit; False: go on anyway.
        net: builds one net (default ``flowsynth.train.nets.raft_small``); render: renders a pool
            (``EnsembleTrainer``'s).
        log: called with a line of progress after every checkpoint and pool.

    Returns:
        the report (``flowsynth.tune.report.summarize``), with ``"settings"``.

    Raises:
        ConfigError: no pairs or an unreadable one, a budget too small for the candidates, bad arguments, more
            memory or disk than the machine has (``check_resources``), or a state or pools in the work folder of
            other settings. DependencyError: torchvision is missing (``net`` None).
    """
    from flowsynth.train.steps import check_precision

    recipe = recipe or (QUICK if quick else RECIPE)
    if pool is not None:
        recipe = dataclasses.replace(recipe, pool=pool)
    if candidates is None:
        candidates = QUICK_CANDIDATES if quick else DEFAULT_CANDIDATES
    candidates = check_int("candidates", candidates, 2)
    seed, workers = check_int("seed", seed, 0), check_int("workers", workers, 0)
    check_precision(precision, _device(device))
    keys = draw_candidates(candidates, seed)
    if budget is None:
        budget = plan_cost(candidates, 2) if quick else DEFAULT_BUDGET
    rungs = plan_rungs(candidates, check_int("budget", budget, 1))
    layout, files = find_pairs(val, pairs)
    if net is None:
        from flowsynth.train.nets import raft_small

        raft_small()  # DependencyError now, before any work, where torchvision is missing
        if min(recipe.crop) < RAFT_MIN:
            raise ConfigError(f"RAFT-small trains on crops of at least {RAFT_MIN} px a side; got {recipe.crop}")
    out, work = Path(out), work_dir(out)
    settings = {k: (sources(k, recipe.res), seed) for k in keys}
    settings[keys[0] + TWIN] = (sources(keys[0], recipe.res), seed + TWIN_SEED)
    sizes = {name: image_size(layout, name, f) for name, f in files.items()}
    cache = PoolCache(work / "pools", {})
    cached = sum(cache.paths(src, s, recipe.pool)[1].is_file() for src, s in settings.values())
    need = estimate(recipe, len(settings), sizes, sources=[src for src, _ in settings.values()], workers=workers,
                    device=device, cached=cached)
    if check_resources:
        check(need, device, work, GO_ON)
    val_pairs = load_pairs(layout, files)
    identity = {"layout": layout, "pairs": list(val_pairs),
                "fingerprint": _fingerprint(val_pairs), "budget": budget, "candidates": keys, "seed": seed,
                "recipe": recipe.to_dict(), "precision": precision}
    work.mkdir(parents=True, exist_ok=True)
    state = _load(work / "state.pt", identity)
    cache.tune = identity
    cache.check()
    _remove_temporaries(work, out)  # after the checks: a tune of other settings is refused and left as it is

    logged = [None if state is None else state["step"]]  # the step of the last checkpoint logged (resumed: its)

    def save(st: dict) -> None:
        with atomic_path(work / "state.pt") as tmp:
            torch.save({"identity": identity, "search": st}, tmp)
        write_json(work / "progress.json", {k: v for k, v in st.items() if k != "trainer"})
        if st["step"] == logged[0]:  # the end of a rung: its scores
            scores = st["scores"][-1]
            best = min(scores, key=lambda k: (rank(scores[k]), k))
            log(f"tune: rung {len(st['scores']) - 1} (of 0-{len(rungs) - 1}) done, best score {_px(scores[best])} "
                f"({best})"
                + (f"; kept {len(st['alive'])}" if "winner" not in st else f"; winner {st['winner']}"))
            return
        logged[0] = st["step"]
        now = {k: c[-1]["mean"] for k, c in st["curves"].items() if c[-1]["step"] == st["step"]}
        best = min(now, key=lambda k: (rank(now[k]), k))
        log(f"tune: step {st['step']} of {rungs[-1].end} (rung {st['rung']}): {len(now)} nets tested, best "
            f"{_px(now[best])} ({best})")

    log(f"tune: {len(val_pairs)} {layout} pairs, {candidates} candidates, {len(rungs)} rungs (0-{len(rungs) - 1}) "
        f"ending at steps {[r.end for r in rungs]}, budget {budget} net-steps; "
        f"needs about {need['peak'] / GIB:.1f} GiB of memory"
        + (f" and {need['device_peak'] / GIB:.1f} GiB on {device}" if need["device_peak"] else "")
        + f", {need['disk']['pools'] / GIB:.1f} GiB of disk for new pools" + (", continuing" if state else ""))
    if state is None or "winner" not in state:
        trainer = EnsembleTrainer(settings, val_pairs, recipe, rungs[-1].end, device=device, precision=precision,
                                  workers=workers, net=net, render=render, cache=cache, log=log)
        state = search(trainer, keys, rungs, state, save)
    cache.clear()  # done: no net trains again
    summary = {**summarize(state, keys, rungs), "settings": {**identity, "val": str(val)}}
    write_json(work / "report.json", summary)
    atomic_write_bytes(work / "report.md", markdown(summary).encode())
    plot(summary, work / "curves.png")
    preset(summary["winner"]).to_file(out)
    return summary

