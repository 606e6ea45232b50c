"""A tune's report: every net's curve and rung scores, the winner against the reference, and the noise.

``summarize`` reads a finished search's state into one JSON-able dict; ``markdown`` renders it as a table and three
lines; ``plot`` draws every net's curve (mean EPE over the validation pairs against training steps) where
matplotlib is installed.
"""

from __future__ import annotations

from pathlib import Path

from flowsynth.io import atomic_path
from flowsynth.tune.halving import TWIN, Rung, rank
from flowsynth.tune.space import SPACE, point_of

__all__ = ["WEAK", "markdown", "plot", "summarize"]

WEAK = 2.0  # a margin under this many noises (|twin - default|) is called weak evidence in the verdict


def summarize(state: dict, candidates: list[str], rungs: list[Rung]) -> dict:
    """The report of a finished search (``halving.search``'s final state) of ``candidates`` (the first is the
    reference) over ``rungs``.

    Returns {"winner", "reference", "twin": keys; "scores": {"winner", "reference", "twin": their last rung's
    scores [px], None for a net that diverged}; "margin": reference - winner [px]; "ratio": winner / reference;
    "noise": |twin - reference| [px] (these three None when one of the three diverged); "noise_by_rung": the same
    in every rung; "margin_over_noise" (None also when the noise is 0); "verdict": one sentence; "plan": [{"rung",
    "candidates", "start", "end", "checkpoints"}]; "nets": [{"key", "labels", "twin", "rungs": scores per rung it
    ran, "curve": [{"step", "mean", "epe": {pair: px}}]}] (the reference, its twin, then the candidates by how far
    they got and their last score)}."""
    ref, twin, winner = candidates[0], candidates[0] + TWIN, state["winner"]
    last = state["scores"][-1]
    s_w, s_r, s_t = last[winner], last[ref], last[twin]
    margin = ratio = noise = over = None
    if None in (s_w, s_r, s_t):
        gone = [name for name, v in (("the winner", s_w), ("the default", s_r), ("its twin", s_t)) if v is None]
        verdict = f"no comparison: {' and '.join(gone)} diverged in the last rung (an EPE that is not finite)"
    else:
        margin, ratio, noise = s_r - s_w, s_w / s_r, abs(s_t - s_r)
        over = margin / noise if noise > 0 else None
    if margin is None:
        pass
    elif winner == ref:
        verdict = (f"the default won: no candidate beat it in the last rung (the twin differs from it by {noise:.3f} "
                   "px)")
    else:
        verdict = (f"{winner} beat the default by {margin:.3f} px ({100 * (1 - ratio):.1f}% of its {s_r:.3f} px); a "
                   f"repeat of the default with other seeds moved by {noise:.3f} px, so the margin is "
                   + (f"{over:.1f}x the noise" if over is not None else "above a noise of 0")
                   + ("" if over is None or over >= WEAK else ": within the noise, no win" if over <= 1 else
                      f": under {WEAK:g}x the noise, weak evidence at best"))
    nets = []
    for key in [ref, twin, *candidates[1:]]:
        nets.append({"key": key, "labels": point_of(key.removesuffix(TWIN)), "twin": key == twin,
                     "rungs": [s[key] for s in state["scores"] if key in s], "curve": state["curves"][key]})
    nets[2:] = sorted(nets[2:], key=lambda n: (-len(n["rungs"]), rank(n["rungs"][-1]), n["key"]))
    by_rung = [None if None in (s[ref], s[twin]) else abs(s[twin] - s[ref]) for s in state["scores"]]
    return {"winner": winner, "reference": ref, "twin": twin,
            "scores": {"winner": s_w, "reference": s_r, "twin": s_t}, "margin": margin, "ratio": ratio,
            "noise": noise, "noise_by_rung": by_rung, "margin_over_noise": over, "verdict": verdict,
            "plan": [{"rung": r.index, "candidates": r.size, "start": r.start, "end": r.end,
                      "checkpoints": list(r.checkpoints)} for r in rungs],
            "nets": nets}


def _px(score: float | None) -> str:
    return "diverged" if score is None else f"{score:.3f}"


def markdown(summary: dict) -> str:
    """The report as markdown: the plan, a table of every net (its knobs' labels and its score in each rung it ran,
    the mean EPE [px] of the rung's two checkpoints on the validation pairs) and the verdict."""
    rungs = summary["plan"]
    lines = ["Plan: " + "; ".join(f"rung {r['rung']}: {r['candidates']} candidate{'s' * (r['candidates'] > 1)}, "
                                  f"steps {r['start']}-{r['end']}" for r in rungs)
             + " (the default and its twin run in every rung).", ""]
    head = ["net", *(k.name for k in SPACE), *(f"rung {r['rung']} [px]" for r in rungs)]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for n in summary["nets"]:
        roles = [r for r, on in (("winner", n["key"] == summary["winner"]), ("default", n["key"] == summary[
            "reference"]), ("the default's twin", n["twin"])) if on]
        cells = [", ".join(roles) or "candidate", *(n["labels"][k.name] for k in SPACE), *map(_px, n["rungs"])]
        lines.append("| " + " | ".join(cells + [""] * (len(head) - len(cells))) + " |")
    s = summary["scores"]
    ratio = "" if summary["ratio"] is None else f" (ratio winner / default {summary['ratio']:.3f})"
    lines += ["", f"Last rung [px]: winner {_px(s['winner'])}, default {_px(s['reference'])}, the default's twin "
                  f"{_px(s['twin'])}{ratio}. The twin's distance from the default, rung by rung [px]: "
                  + ", ".join(map(_px, summary["noise_by_rung"])) + ".", "",
              f"Verdict: {summary['verdict']}."]
    return "\n".join(lines) + "\n"


def plot(summary: dict, path: str | Path) -> bool:
    """Draw every net's curve (mean EPE over the validation pairs [px] against steps) into the PNG ``path``: the
    winner bold, the default and its twin dashed, the others thin. Returns False (and writes nothing) where
    matplotlib is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        from matplotlib import pyplot as plt
    except ImportError:
        return False
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for n in summary["nets"]:
        steps = [c["step"] for c in n["curve"]]
        epe = [float("nan") if c["mean"] is None else c["mean"] for c in n["curve"]]  # a gap where it diverged
        if n["key"] == summary["winner"] and not n["twin"]:
            ax.plot(steps, epe, lw=2.5, color="C3", label="winner" + (" (the default)" if n["key"] == summary[
                "reference"] else ""), zorder=3)
        elif n["key"] == summary["reference"] or n["twin"]:
            ax.plot(steps, epe, lw=1.5, ls="--", color="C0" if n["twin"] else "k",
                    label="the default's twin" if n["twin"] else "the default")
        else:
            ax.plot(steps, epe, lw=0.8, color="0.6", alpha=0.8)
    for r in summary["plan"][1:]:
        ax.axvline(r["start"], color="0.85", lw=0.8, zorder=0)
    ax.set_xlabel("training steps")
    ax.set_ylabel("EPE on the validation pairs [px]")
    ax.set_title("flowsynth tune: every candidate (grey), rungs (vertical lines)")
    ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return True
