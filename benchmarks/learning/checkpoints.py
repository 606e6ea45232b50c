"""The RAFT judge's nets checkpoint by checkpoint (``--diagnose-checkpoints``): a net that does not
invent motion. For the runs in the results files of a glob and each tested checkpoint's saved weights
(``protocol.checkpoint_path``: TAG_ARM_sSEED_stepN.pt beside the final TAG_ARM_sSEED.pt), per (arm, seed, checkpoint):

- the motion the net invents on each still photograph of the small-motion diagnostic (``sets.small_motion_pairs`` at
  0 px: Motorcycle's left view and frame 1 of each Middlebury pair): its mean over the photographs and the worst;
- from the results' curves, each real pair's EPE (stereo, mb_NAME) and its change since the previous checkpoint (the
  swing), and zero flow's EPE on each pair.

Then the goal (``GOAL``), reported beside rule 5 of docs/decisions/0023 and deciding nothing. Weights that were not
kept (older runs kept only the final net; decision 0023) are reported missing, and a goal that needs them is unknown.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

from _common import RESULTS_DIR, print_table, pyplot, save_figure

from .protocol import CACHE, JUDGED, NET, TEST_UPDATES, checkpoint_path, net_stem, results_tag
from .sets import middlebury_pairs, small_motion_pairs

GOAL_INVENTED = 1.0  # [px] the most a net may invent on a still photograph (mean EPE over its valid pixels)
GOAL_FROM = 0.5  # ... at every checkpoint from this share of the run's steps on (step 1200 of 2400)
GOAL_SMALL = 4.0  # [px] a Middlebury pair whose mean true motion (zero flow's EPE) is below this: the net must beat
# zero flow there at both scored checkpoints (the last JUDGED: 2000 and 2400)
GOAL_SEEDS, GOAL_OF = 4, 5  # seeds that must pass, of the decision's seeds
GOAL = (f"on still real photographs the net invents under {GOAL_INVENTED:g} px on average at every checkpoint from "
        f"{GOAL_FROM:g} of the steps on (step 1200 of 2400), on every photograph; and its EPE is below zero flow's on "
        f"every Middlebury pair whose mean true motion is under {GOAL_SMALL:g} px, at both scored checkpoints; in at "
        f"least {GOAL_SEEDS} of {GOAL_OF} seeds")


def still_pairs(middlebury_dir: str | None) -> dict:
    """The still pairs of the small-motion diagnostic: {photograph: (img1, img2, flow, valid)}, Motorcycle's left view
    ("stereo") and frame 1 of each Middlebury pair under ``middlebury_dir`` ("Venus", ...), each twice, flow 0."""
    pairs = small_motion_pairs(middlebury_pairs(middlebury_dir), magnitudes=(0.0,))
    return {k.removeprefix("sm_").removesuffix("_0"): v for k, v in pairs.items()}


def invented_motion(path: str, stills: dict, device: str = "cpu") -> dict:
    """{photograph: the mean |flow| [px] the net saved at ``path`` predicts on its still pair} (its EPE there)."""
    import torch

    from flowsynth.train.nets import raft_small
    from flowsynth.train.steps import predict

    net = raft_small()
    net.load_state_dict(torch.load(path, map_location="cpu"))
    net.to(device)
    out = {}
    with torch.no_grad():
        for name, (img1, img2, _, valid) in stills.items():
            pred = predict(net, img1.to(device), img2.to(device), TEST_UPDATES).cpu()
            out[name] = float(torch.linalg.vector_norm(pred, dim=1, keepdim=True)[valid > 0.5].mean())
    return out


def changes(curve: list, pair: str) -> list[tuple]:
    """(step, EPE, change since the previous tested checkpoint) of each checkpoint after the untrained start."""
    pts = [(c["step"], c[pair]) for c in curve if pair in c]
    return [(s, e, e - pts[k][1]) for k, (s, e) in enumerate(pts[1:])]


def swing(curve: list, pair: str, from_step: float) -> float | None:
    """The largest |change| of ``pair``'s EPE between consecutive checkpoints at or after ``from_step``."""
    pts = [e for s, e in ((c["step"], c.get(pair)) for c in curve) if s >= from_step and e is not None]
    return max((abs(b - a) for a, b in itertools.pairwise(pts)), default=None)


def net_goal(invented: dict, curve: list, zero: dict, steps: int) -> dict:
    """The goal for one net: ``invented`` {step: {photograph: px} or None where the weights are missing}, its results
    ``curve`` and ``zero`` (zero flow's EPE per pair) of a run of ``steps`` steps. Returns {"pass": True, False or None
    (unknown: something it needs is missing), "fails": [what fails], "missing": [what is missing]}."""
    fails, missing = [], []
    from_step = GOAL_FROM * steps
    for step, photos in sorted(invented.items()):
        if step < from_step:
            continue
        if photos is None:
            missing.append(f"step {step}: weights")
            continue
        fails += [f"step {step}: invents {e:.2f} px on {p}" for p, e in photos.items() if not e < GOAL_INVENTED]
    if not any(s >= from_step for s in invented):
        missing.append(f"checkpoints from step {from_step:g}")
    small = sorted(k for k in zero if k.startswith("mb_") and zero[k] < GOAL_SMALL)
    if not any(k.startswith("mb_") for k in zero):
        missing.append("Middlebury pairs (a run without --middlebury)")
    for c in curve[1:][-JUDGED:]:
        fails += [f"step {c['step']}: {k} {c[k]:.2f} px, zero flow {zero[k]:.2f}" for k in small if not c[k] < zero[k]]
    return {"pass": False if fails else None if missing else True, "fails": fails, "missing": missing,
            "small_motion_pairs": small}


def arm_goal(goals: dict) -> dict:
    """The goal for an arm from its nets' ``goals`` {seed: ``net_goal``}: met (True) when at least GOAL_SEEDS seeds
    pass, not met (False) when too few can (passing, unknown or not yet run, of GOAL_OF), else unknown (None)."""
    passed = sorted(s for s, g in goals.items() if g["pass"] is True)
    failed = sorted(s for s, g in goals.items() if g["pass"] is False)
    unknown = sorted(s for s, g in goals.items() if g["pass"] is None)
    reachable = GOAL_OF - len(failed)
    met = True if len(passed) >= GOAL_SEEDS else False if reachable < GOAL_SEEDS else None
    return {"seeds": sorted(goals), "pass": passed, "fail": failed, "unknown": unknown, "met": met,
            "fails": {s: goals[s]["fails"] for s in failed}}


def _runs(pattern: str):
    """(file, its tag (``protocol.results_tag``), its JSON, one seed's run) for every run of this judge in the
    results/ files matching ``pattern`` (unfinished files' finished seeds included)."""
    for f in sorted(RESULTS_DIR.glob(pattern)):
        d = json.loads(f.read_text())
        if d.get("net") != NET or "runs" not in d:
            continue
        tag = results_tag(f.stem)
        for r in d["runs"]:
            yield f, tag, d, r


def diagnose_checkpoints(pattern: str, middlebury_dir: str | None, device: str = "cpu",
                         weights: str | Path | None = None) -> dict:
    """The module docstring's report for the runs of the results/ files matching ``pattern``, their checkpoints'
    weights under ``weights`` (default .cache/learning_raft). Returns {"rows": one per (arm, seed, checkpoint),
    "nets": one per (arm, seed) with its goal, "arms": ``arm_goal`` per arm}; an arm's seed twice is an error. A --set
    run's flowsynth arm is labelled by its changes, as ``--screen`` labels it."""
    stills = still_pairs(middlebury_dir)
    folder = Path(weights) if weights else CACHE
    rows, nets, seen = [], [], {}
    for f, tag, d, r in _runs(pattern):
        seed, zero, steps = r["seed"], r["zero_flow_epe"], d["steps"]
        pairs = [k for k in zero if k == "stereo" or k.startswith("mb_")]
        for arm, res in r["results"].items():
            label = arm if arm != "flowsynth" or not d.get("overrides") else \
                "flowsynth " + ",".join(f"{k}={v}" for k, v in d["overrides"].items())
            if (label, seed) in seen:
                raise SystemExit(f"--diagnose-checkpoints: seed {seed}'s {label} is in {seen[label, seed]} and in "
                                 f"{f.name}; narrow --files")
            seen[label, seed] = f.name
            curve, invented = res["curve"], {}
            delta = {k: {s: x for s, _, x in changes(curve, k)} for k in pairs}
            for c in curve[1:]:
                path = checkpoint_path(str(folder / f"{net_stem(tag, arm, seed)}.pt"), c["step"])
                photos = invented_motion(path, stills, device) if Path(path).exists() else None
                invented[c["step"]] = photos
                worst = max(photos, key=photos.get) if photos else None
                rows.append({"file": f.name, "arm": label, "seed": seed, "step": c["step"],
                             "weights": "ok" if photos else "missing",
                             "invented mean": sum(photos.values()) / len(photos) if photos else None,
                             "invented worst": photos[worst] if photos else None, "worst photograph": worst,
                             **{f"still {p}": e for p, e in (photos or {}).items()},
                             **{k: c.get(k) for k in pairs}, **{f"change {k}": delta[k].get(c["step"]) for k in pairs}})
            nets.append({"file": f.name, "arm": label, "seed": seed, "steps": steps, "invented": invented,
                         "zero_flow": {k: zero[k] for k in pairs},
                         "swing": {k: swing(curve, k, GOAL_FROM * steps) for k in pairs},
                         **net_goal(invented, curve, zero, steps)})
    arms = {a: arm_goal({n["seed"]: n for n in nets if n["arm"] == a}) for a in dict.fromkeys(n["arm"] for n in nets)}
    return {"goal": GOAL, "files": pattern, "photographs": list(stills), "rows": rows, "nets": nets, "arms": arms}


def report(out: dict) -> None:
    """Print ``diagnose_checkpoints``' tables: invented motion per checkpoint, each net's swings and zero flow, each
    net's goal and each arm's."""
    if not out["rows"]:
        print(f"--diagnose-checkpoints: no run of this judge in results/{out['files']}")
        return
    print("motion invented on the still photographs [px], and each real pair's EPE (change since the last checkpoint)")
    pairs = [k for k in out["nets"][0]["zero_flow"]]
    print_table([{**{k: r[k] for k in ("arm", "seed", "step", "weights", "invented mean", "invented worst",
                                       "worst photograph")},
                  **{k: None if r.get(k) is None else f"{r[k]:.2f} ({r[f'change {k}']:+.2f})" for k in pairs}}
                 for r in out["rows"]], ["arm", "seed", "step", "weights", "invented mean", "invented worst",
                                         "worst photograph", *pairs])
    print(f"\nlargest swing of each pair's EPE between checkpoints from {GOAL_FROM:g} of the steps on, zero flow's EPE")
    print_table([{"arm": n["arm"], "seed": n["seed"], **{f"swing {k}": n["swing"].get(k) for k in pairs},
                  **{f"zero {k}": n["zero_flow"].get(k) for k in pairs}} for n in out["nets"]],
                ["arm", "seed", *(f"swing {k}" for k in pairs), *(f"zero {k}" for k in pairs)])
    print(f"\nthe goal (decides nothing): {out['goal']}")
    word = {True: "yes", False: "no", None: "unknown"}
    print_table([{"arm": n["arm"], "seed": n["seed"], "pass": word[n["pass"]],
                  "what fails": "; ".join(n["fails"][:3]) + (f" (+{len(n['fails']) - 3})" if len(n["fails"]) > 3
                                                             else ""),
                  "missing": "; ".join(n["missing"][:2])} for n in out["nets"]],
                ["arm", "seed", "pass", "what fails", "missing"])
    print_table([{"arm": a, "seeds": g["seeds"], "pass": g["pass"], "fail": g["fail"], "unknown": g["unknown"],
                  f"goal ({GOAL_SEEDS} of {GOAL_OF})": {True: "met", False: "not met", None: "unknown"}[g["met"]]}
                 for a, g in out["arms"].items()],
                ["arm", "seeds", "pass", "fail", "unknown", f"goal ({GOAL_SEEDS} of {GOAL_OF})"])


def plot_invented(out: dict, name: str):
    """results/NAME.png: the motion each net invents on the still photographs (mean over them) against the step, one
    line per net, arms coloured, the goal's 1 px marked. Returns the path (None without matplotlib or data)."""
    plt = pyplot()
    if plt is None or not any(r["invented mean"] is not None for r in out["rows"]):
        return None
    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=110)
    colour = {a: f"C{k % 10}" for k, a in enumerate(out["arms"])}
    for n in out["nets"]:
        pts = [(s, sum(p.values()) / len(p)) for s, p in sorted(n["invented"].items()) if p]
        if pts:
            ax.plot(*zip(*pts), "o-", color=colour[n["arm"]], alpha=0.8, ms=3, lw=1,
                    label=n["arm"] if n is next(m for m in out["nets"] if m["arm"] == n["arm"]) else None)
    ax.axhline(GOAL_INVENTED, color="grey", ls="--", lw=1, label=f"goal: under {GOAL_INVENTED:g} px")
    ax.set_xlabel("training step")
    ax.set_ylabel(f"motion invented on still photographs [px]\n(mean of {len(out['photographs'])})")
    ax.set_yscale("log")
    ax.set_title(f"a net that does not invent motion ({out['files']})", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, name)
