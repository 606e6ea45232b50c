"""What the RAFT judge's runs say: ``--summarize`` pools the seeds of complete runs (rule 5 of
docs/decisions/0023-raft-judge.md), ``--screen`` applies rule 4 to every lever against the default and its control,
and the plots of both (``plot_summary``, ``plot_judge_curves``). Reads results/learning_raft*.json, old runs' too.
"""

from __future__ import annotations

import json

from _common import RESULTS_DIR, plot_curves, print_table, pyplot, save_figure

from .protocol import JUDGED, JUDGES, NET, score


def absolute_motion(config: dict | None) -> dict | None:
    """A results file's ``flowsynth_config`` with ``flow_px`` in pixels of its own width: a config that states it at
    ``flow_px_width`` (decision 0029) scaled to ``width`` and the field dropped, so that a run made before the field
    existed (``flow_px`` already in its pixels) and one made after compare equal when they rendered the same motion."""
    if not config or "flow_px_width" not in config:
        return config
    out = dict(config)
    k = out["width"] / out.pop("flow_px_width")
    out["flow_px"] = [x * k for x in out["flow_px"]]
    return out


def _complete_runs(pattern: str, who: str, precision: str = "fp32"):
    """(file, its JSON, one seed's run) for every seed of the complete runs of this judge in the results/ files
    matching ``pattern``, in name order; unfinished runs, other judges and runs trained in another ``precision`` (a
    file without the key trained in fp32: protocol 0023) are skipped. All must share the protocol."""
    protocol = {}
    for f in sorted(RESULTS_DIR.glob(pattern)):
        d = json.loads(f.read_text())
        if not d.get("complete") or d.get("net") != NET or d.get("precision", "fp32") != precision:
            continue
        same = {k: d.get(k) for k in ("steps", "pool", "batch", "resolution", "every", "lr", "updates")}
        if protocol and same != protocol:
            raise SystemExit(f"{who}: {f.name} ran another protocol ({same}) than the files before it ({protocol})")
        protocol = same
        for r in d.get("runs", []):
            yield f, d, r


def _mean(values) -> float:
    """The mean of an iterable of numbers (one number: itself, to the bit)."""
    values = list(values)
    return sum(values) / len(values)


def summarize(pattern: str, arm: str, against: str, judges: dict[str, tuple[str, ...]] | None = None) -> dict:
    """Pool the seeds on which the complete runs with no ``--set`` in the results/ files matching ``pattern`` hold
    both arms (a seed's two arms may come from two files; an arm twice on one seed is an error): per judge, each
    seed's score ratio ``arm`` / ``against``, their geometric mean with a 95% interval (t on the log ratios), the
    seeds in favour, and the rule-1 count (``arm``'s net ends below zero flow and below its untrained start).
    ``judges``: {name: the curves' judges it averages} (default: each of JUDGES alone); a net's score on one is the
    mean of its scores on those, and so are zero flow's and the untrained net's EPE."""
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
                                           "config": absolute_motion(d.get("flowsynth_config")), "file": f.name})
        zero, other = seed["zero_flow_epe"], r["zero_flow_epe"]  # float32 sums differ in the 7th digit
        if set(zero) != set(other) or any(abs(zero[k] - other[k]) > 1e-5 * abs(zero[k]) for k in zero):
            differ = "their judges (zero flow EPE)"  # another --middlebury: not one comparison
        elif absolute_motion(d.get("flowsynth_config")) != seed["config"]:
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
    for j, keys in (judges or {j: (j,) for j in JUDGES}).items():
        rs = [r for r in runs.values() if all(k in r["zero_flow_epe"] for k in keys)]
        if not rs:
            continue

        a = np.array([_mean(score(r["results"][arm]["curve"], k) for k in keys) for r in rs])
        b = np.array([_mean(score(r["results"][against]["curve"], k) for k in keys) for r in rs])
        logs = np.log(a / b)
        if not np.isfinite(logs).all():  # a diverged net (NaN EPE) or a zero score: no ratio to pool
            bad = [r["seed"] for r, x in zip(rs, logs) if not np.isfinite(x)]
            raise SystemExit(f"--summarize: {arm} / {against} on {j} is not finite on seeds {bad}")
        n = len(logs)
        half = stats.t.ppf(0.975, n - 1) * logs.std(ddof=1) / np.sqrt(n) if n > 1 else None  # one seed: none
        zero = [_mean(r["zero_flow_epe"][k] for k in keys) for r in rs]
        untrained = [_mean(r["results"][arm]["curve"][0][k] for k in keys) for r in rs]
        useful = int(sum(x < min(z, u) for x, z, u in zip(a, zero, untrained)))
        out[j] = {"seeds": [r["seed"] for r in rs], "ratios": (a / b).tolist(),
                  "geometric_mean": float(np.exp(logs.mean())),
                  "ci95": None if half is None else [float(np.exp(logs.mean() - half)),
                                                     float(np.exp(logs.mean() + half))],
                  "in_favour": int((logs < 0).sum()), "useful": useful, arm: a.tolist(), against: b.tolist(),
                  "zero_flow": float(np.mean(zero)), "untrained": float(np.mean(untrained))}
        o = out[j]
        rows.append({"judge": j, "seeds": n, "ratio": o["geometric_mean"],
                     "95% CI": f"{o['ci95'][0]:.3f}-{o['ci95'][1]:.3f}" if o["ci95"] else "n/a (one seed)",
                     "in favour": f"{o['in_favour']} of {n}",
                     f"{arm} useful": f"{useful} of {n}", arm: float(a.mean()), against: float(b.mean()),
                     "zero flow": o["zero_flow"], "untrained": o["untrained"]})
    print(f"{arm} / {against}, scores (mean of the last {JUDGED} checkpoints), seeds {sorted(runs)}")
    print_table(rows, list(rows[0]))
    return {"arm": arm, "against": against, "pattern": pattern, "judges": out}


# decision 0026's proof of the tune: the pairs it tuned on and the two it never saw (Middlebury), the seeds, the goal
TUNED_ON, HELD_OUT = ("Dimetrodon", "Grove2"), ("Urban2", "Venus")
PROOF_SEEDS, PROOF_GOAL = (0, 1, 2, 3, 4), 0.9


def tune_proof(pattern: str, arm: str = "tuned", against: str = "flowsynth", held_out=HELD_OUT,
               tuned_on=TUNED_ON) -> dict:
    """Decision 0026's reading over the results/``pattern`` files: ``summarize`` of ``arm`` / ``against`` on the
    held-out score (a net's mean score on the ``held_out`` Middlebury pairs), beside the pairs the tune saw
    (``tuned_on``: the gap is how much the tune overfits) and Motorcycle, deciding nothing. The goal: over seeds
    PROOF_SEEDS, the held-out geometric mean at most PROOF_GOAL and the upper end of its 95% interval below 1; read
    only when the pooled seeds are exactly PROOF_SEEDS ("goal_met" None otherwise)."""
    judges = {"held_out": tuple(f"mb_{p}" for p in held_out), "tuned_on": tuple(f"mb_{p}" for p in tuned_on),
              "stereo": ("stereo",)}
    out = summarize(pattern, arm, against, judges)
    h = out["judges"].get("held_out")
    if h is None:
        raise SystemExit(f"--tune-proof: no seed of results/{pattern} was judged on {', '.join(held_out)}")
    read = tuple(h["seeds"]) == PROOF_SEEDS
    met = read and h["geometric_mean"] <= PROOF_GOAL and h["ci95"][1] < 1
    out.update({"held_out": list(held_out), "tuned_on": list(tuned_on), "goal": {
        "seeds": list(PROOF_SEEDS), "geometric_mean_at_most": PROOF_GOAL, "ci95_upper_below": 1.0},
        "goal_met": met if read else None})
    verdict = ("met" if met else "missed") if read else f"not read: seeds {h['seeds']}, not {list(PROOF_SEEDS)}"
    print(f"decision 0026: held-out ({', '.join(held_out)}) {arm} / {against} {h['geometric_mean']:.3f}"
          + (f" ({h['ci95'][0]:.3f}-{h['ci95'][1]:.3f})" if h["ci95"] else "") + f"; the goal: {verdict}")
    return out


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
    if "goal" in out:  # tune_proof's: the held-out geometric mean at most this
        ax.axhline(out["goal"]["geometric_mean_at_most"], color="C2", lw=1, ls="--",
                   label=f"decision 0026's goal ({out['goal']['geometric_mean_at_most']})")
        ax.legend(fontsize=7, loc="upper right")
    ax.set_yscale("log")
    from matplotlib.ticker import FormatStrFormatter

    ax.yaxis.set_major_formatter(FormatStrFormatter("%.2g"))
    ax.yaxis.set_minor_formatter(FormatStrFormatter("%.2g"))
    names = {"stereo": "Motorcycle", "middlebury": "Middlebury mean",  # tune_proof's judges name their pairs
             "held_out": "held out\n" + ", ".join(out.get("held_out", ())),
             "tuned_on": "tuned on\n" + ", ".join(out.get("tuned_on", ()))}
    ax.set_xticks(range(len(judges)), [names.get(j, j) for j in judges], fontsize=8)
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


def plot_judge_curves(name: str, pattern: str) -> list:
    """One plot per real judge (results/NAME_JUDGE.png): test EPE against training step of every arm and seed of
    the results files matching ``pattern``, each line labelled by its file's tag, arm and seed; the untrained start
    is the step-0 point; zero flow's EPE is a line. Returns the paths written (none without matplotlib)."""
    files = sorted(RESULTS_DIR.glob(pattern))
    paths = []
    for judge in JUDGES:
        series, zero = {}, {}
        for f in files:
            d = json.loads(f.read_text())
            tag = f.stem.removeprefix("learning_")
            for r in d.get("runs", []):
                for arm, res in r["results"].items():
                    pts = [(c["step"], c[judge]) for c in res["curve"] if judge in c]
                    if pts:
                        series[f"{tag} {arm} s{r['seed']}"] = tuple(zip(*pts))
                        if judge in r.get("zero_flow_epe", {}):
                            zero[r["zero_flow_epe"][judge]] = max(zero.get(r["zero_flow_epe"][judge], 0), pts[-1][0])
        for z, last in zero.items():  # zero flow's EPE: a net above this line is worse than predicting nothing
            series[f"zero flow ({z:.2f})"] = ((0, last), (z, z))
        if series:
            path = plot_curves(f"{name}_{judge}", series, "training step", f"{judge} test EPE [px]", logx=False,
                               logy=True, title=f"{judge}: the learning curves ({pattern})")
            paths += [path] if path else []
    return paths


# protocol 0025's equivalence rule (docs/decisions/0025-protocol-bf16.md): the geometric mean's band per judge, the
# width of a single ratio's band in units of |log c| (c: seed 0's control / default ratio in float32), the arms, seeds
EQUIV_MEAN = {"stereo": (0.95, 1.05), "middlebury": (0.90, 1.11)}
EQUIV_SINGLE = 2.5
EQUIV_ARMS, EQUIV_SEEDS = ("flowsynth", "chairs2d_photos"), (0, 1)


def _scores(pattern: str, precision: str) -> dict:
    """{(seed, arm): curve} of the complete runs with no ``--set`` in results/``pattern`` trained in ``precision``;
    an arm twice on one seed is an error."""
    out, where = {}, {}
    for f, d, r in _complete_runs(pattern, "--equivalence", precision):
        if d.get("overrides"):
            continue
        for arm, res in r["results"].items():
            key = (r["seed"], arm)
            if key in out:
                raise SystemExit(f"--equivalence: seed {key[0]}'s {arm} in {precision} is in {where[key]} and {f.name}")
            out[key], where[key] = res["curve"], f.name
    return out


def equivalence(pattern: str) -> dict:
    """Protocol 0025's rule over the results/``pattern`` files: per judge and (arm, seed) of ``EQUIV_ARMS`` x
    ``EQUIV_SEEDS``, the score ratio bf16 / fp32; (1) their geometric mean inside ``EQUIV_MEAN``; (2) each inside
    exp(+-``EQUIV_SINGLE`` |log c|); (3) default / baseline on the same side of 1 in both precisions, per judge and
    seed. Raises SystemExit when a net of the rule is missing."""
    import numpy as np

    fp32, bf16 = _scores(pattern, "fp32"), _scores(pattern, "bf16")
    need = [(s, a) for s in EQUIV_SEEDS for a in EQUIV_ARMS]
    missing = [f"{p} seed {s} {a}" for p, got in (("fp32", fp32), ("bf16", bf16)) for s, a in need if (s, a) not in got]
    missing += [f"fp32 seed 0 {a}" for a in ("control",) if (0, a) not in fp32]
    if missing:
        raise SystemExit(f"--equivalence: results/{pattern} lacks {', '.join(missing)}")
    out, rows = {}, []
    for j in JUDGES:
        c = score(fp32[0, "control"], j) / score(fp32[0, "flowsynth"], j)
        band = (float(np.exp(-EQUIV_SINGLE * abs(np.log(c)))), float(np.exp(EQUIV_SINGLE * abs(np.log(c)))))
        ratios = {f"{a} s{s}": score(bf16[s, a], j) / score(fp32[s, a], j) for s, a in need}
        gm = float(np.exp(np.mean(np.log(list(ratios.values())))))
        side = {s: [score(p[s, "flowsynth"], j) < score(p[s, "chairs2d_photos"], j) for p in (fp32, bf16)]
                for s in EQUIV_SEEDS}
        held = {"1 geometric mean": EQUIV_MEAN[j][0] <= gm <= EQUIV_MEAN[j][1],
                "2 every ratio": all(band[0] <= r <= band[1] for r in ratios.values()),
                "3 same direction": all(a == b for a, b in side.values())}
        out[j] = {"ratios": ratios, "geometric_mean": gm, "mean_band": list(EQUIV_MEAN[j]), "control_ratio": c,
                  "single_band": list(band), "held": held}
        rows.append({"judge": j, **{k: round(v, 3) for k, v in ratios.items()}, "geo mean": round(gm, 3),
                     **{k: "yes" if v else "NO" for k, v in held.items()}})
    out["equivalent"] = all(all(o["held"].values()) for o in out.values())
    print(f"bf16 / fp32 score ratios (protocol 0025's rule): {'equivalent' if out['equivalent'] else 'NOT equivalent'}")
    print_table(rows, list(rows[0]))
    return out
