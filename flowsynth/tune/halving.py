"""Successive halving over candidates, with a pinned reference and its twin (the noise), resumable.

The plan (``plan_rungs``): rung r trains its nets from step ``start`` to ``end`` = first * 2 ** r, where ``first`` is
the largest even step count the budget affords; rung 0 holds every candidate, each later rung the better half
(rounded up) of the one before, the last rung one. Every net of a rung is tested at the rung's middle and end
(``Rung.checkpoints``), and its rung score is the mean EPE of those two: the learning judge's rule (the mean of the
last checkpoints), because single checkpoints swing.

Two nets run beside the candidates in every rung whatever their rank: the reference (the first candidate, the
generator's defaults) and its twin (the same setting, every seed moved by ``TWIN_SEED``). The twin's score minus the
reference's is the noise a repeat shows; the winner, the best of the last rung, is judged against the reference by
that. Survivors continue training (their weights, optimiser state and batch generator carry on), so a survivor of
the last rung has trained ``end`` steps, on one one-cycle schedule of that length.

``search`` runs a plan with any ``Trainer`` (``flowsynth.tune.trainer.EnsembleTrainer``, or a stand-in): after every
checkpoint it hands ``save`` the whole state, the trainer's included, so a killed search resumes from its last
checkpoint with the same results.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from flowsynth.errors import ConfigError

__all__ = ["TWIN", "TWIN_SEED", "Rung", "Trainer", "min_budget", "plan_cost", "plan_rungs", "rank", "search"]

TWIN = "#twin"  # suffix of the twin's key: the reference repeated with other seeds
TWIN_SEED = 100  # the twin's seeds (nets, pools, batches) are the tune's seed + this
SCORED = 2  # checkpoints a rung scores: its middle and its end


@dataclass(frozen=True)
class Rung:
    """One rung of the plan."""

    index: int
    """0, 1, ..."""
    size: int
    """Candidates that enter the rung on their rank (the reference and its twin come besides)."""
    start: int
    """Step its nets have trained when it starts."""
    end: int
    """Step they have trained when it ends."""

    @property
    def checkpoints(self) -> tuple[int, int]:
        """The steps it tests at and scores: its middle and its end."""
        return self.start + (self.end - self.start) // 2, self.end


def _sizes(candidates: int) -> list[int]:
    sizes = [candidates]
    while sizes[-1] > 1:
        sizes.append(math.ceil(sizes[-1] / 2))
    return sizes


def plan_cost(candidates: int, first: int) -> int:
    """Training steps over all nets [net-steps] of the plan for ``candidates`` with ``first`` steps in rung 0, at
    most: it counts the reference beside every later rung (it is one of them when it survives on its rank) and the
    twin beside every rung."""
    sizes = _sizes(candidates)
    ends = [first * 2**r for r in range(len(sizes))]
    return sum((n + 1 + (r > 0)) * (ends[r] - (ends[r - 1] if r else 0)) for r, n in enumerate(sizes))


def min_budget(candidates: int) -> int:
    """The smallest budget [net-steps] that trains ``candidates`` (2 steps in rung 0: one per scored checkpoint)."""
    return plan_cost(candidates, SCORED)


def plan_rungs(candidates: int, budget: int) -> list[Rung]:
    """The rungs of successive halving over ``candidates`` (>= 2) within ``budget`` training steps over all nets
    [net-steps, one step of one net on one batch]. Raises ConfigError when the budget cannot train them (the message
    gives the smallest budget that can)."""
    if candidates < 2:
        raise ConfigError(f"a tune needs at least 2 candidates (the default and another), got {candidates}")
    unit = plan_cost(candidates, 1)
    first = budget // unit // SCORED * SCORED
    if first < SCORED:
        raise ConfigError(f"budget {budget} net-steps is too small for {candidates} candidates: halving them needs "
                          f"at least {min_budget(candidates)} (2 candidates: {min_budget(2)}); raise the budget or "
                          f"lower the candidates")
    return [Rung(r, n, first * 2 ** (r - 1) if r else 0, first * 2**r) for r, n in enumerate(_sizes(candidates))]


class Trainer(Protocol):
    """What ``search`` needs of a trainer."""

    def advance(self, keys: list[str], step: int) -> dict[str, dict[str, float]]:
        """Train the nets ``keys`` (a subset of those of the last call, or new nets at step 0) to ``step`` and
        return each one's EPE [px] on every validation pair: {key: {pair: EPE}}."""

    def state_dict(self) -> dict:
        """Everything needed to continue from here (``torch.save``-able)."""

    def load_state_dict(self, state: dict) -> None:
        """Continue from a ``state_dict``."""


def _mean(values: list) -> float | None:
    """The mean, or None when a value is None or not finite (a net that diverged)."""
    ok = all(v is not None and math.isfinite(v) for v in values)
    return sum(values) / len(values) if ok and values else None


def rank(score: float | None) -> tuple[bool, float]:
    """A sort key: lower scores first, a diverged net's None last."""
    return score is None, 0.0 if score is None else score


def _score(curve: list[dict], steps: tuple[int, ...]) -> float | None:
    pts = [c["mean"] for c in curve if c["step"] in steps]
    if len(pts) != len(steps):
        raise ConfigError(f"a curve lacks the checkpoints {steps}: the state is not this plan's")
    return _mean(pts)


def search(trainer: Trainer, candidates: list[str], rungs: list[Rung], state: dict | None = None,
           save: Callable[[dict], None] | None = None) -> dict:
    """Successive halving (module docstring) of ``candidates`` (keys; the first is the reference) over ``rungs``.

    ``state``: a state ``save`` was given (the search continues from it, its trainer's state loaded), or None to
    start. ``save(state)`` is called after every checkpoint and rung with the whole state (a dict: ``"trainer"``
    holds ``trainer.state_dict()``, the rest is JSON: ``"curves"`` {key: [{"step", "epe": {pair: px}, "mean"}]},
    ``"scores"`` [{key: rung score}] per finished rung, ``"alive"``, ``"rung"``, ``"step"``, and once done
    ``"winner"``). Returns the final state."""
    ref = candidates[0]
    twin = ref + TWIN
    if state is None:
        state = {"rung": 0, "step": -1, "alive": list(candidates), "curves": {}, "scores": []}
    else:
        trainer.load_state_dict(state["trainer"])

    def checkpoint(nets: list[str], step: int) -> None:
        for key, epe in trainer.advance(nets, step).items():
            epe = {p: float(v) if math.isfinite(v) else None for p, v in epe.items()}
            state["curves"].setdefault(key, []).append({"step": step, "epe": epe, "mean": _mean(list(epe.values()))})
        state["step"] = step
        if save:
            save({**state, "trainer": trainer.state_dict()})

    while state["rung"] < len(rungs):
        rung = rungs[state["rung"]]
        nets = state["alive"] + [k for k in (ref, twin) if k not in state["alive"]]
        if state["step"] < 0:
            checkpoint(nets, 0)  # the untrained nets: each curve's first point
        for step in rung.checkpoints:
            if step > state["step"]:
                checkpoint(nets, step)
        scores = {k: _score(state["curves"][k], rung.checkpoints) for k in nets}
        state["scores"].append(scores)
        ranked = sorted(state["alive"], key=lambda k: (rank(scores[k]), k))
        if rung.index + 1 < len(rungs):
            state["alive"] = ranked[:rungs[rung.index + 1].size]
        else:
            state["winner"] = min((k for k in nets if k != twin), key=lambda k: (rank(scores[k]), k))
        state["rung"] += 1
        if save:
            save({**state, "trainer": trainer.state_dict()})
    return state
