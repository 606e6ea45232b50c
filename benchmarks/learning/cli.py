"""The learning benchmark's command line: does a flow network trained on flowsynth work on real flow?
The RAFT judge (``protocol``; protocol and rules pre-registered in docs/decisions/0023-raft-judge.md) trains, pools and
diagnoses.

    python benchmarks/learning [--seeds 0,1] [--arms flowsynth,chairs2d_photos] [--steps 2400] [--middlebury DIR]
                               [--set FIELD=JSON] [--tag NAME] [--device cuda] [--jobs 2] [--at-once] [--ensemble]
    python benchmarks/learning --summarize [--files 'learning_raft*.json'] [--arm flowsynth] [--against chairs2d_photos]
    python benchmarks/learning --equivalence [--files 'learning_raft_*.json']  # protocol 0025's rule
    python benchmarks/learning --arms tuned --preset tuned.json --seeds 0 --tag t0 --middlebury DIR  # a tuned net
    python benchmarks/learning --tune-proof [--files 'learning_raft_*.json']  # decision 0026: tuned / default
    python benchmarks/learning --screen [--files 'learning_raft_s0*.json']       # rule 4 for every lever of seed 0
    python benchmarks/learning --diagnose --nets A.pt,B.pt [--middlebury DIR]   # where the saved nets fail
    python benchmarks/learning --diagnose-checkpoints [--files 'learning_raft_l*.json'] [--middlebury DIR]  # every
                               # checkpoint's invented motion and swings, and the goal (``checkpoints.GOAL``)
    python benchmarks/learning --figures NAME --nets A.pt [--middlebury DIR]    # their predicted flow
    python benchmarks/learning --plot NAME | --stats [--set FIELD=JSON]
    python benchmarks/learning --ensemble-rate 2 [--steps 20] [--device cuda]  # K nets in one process vs K processes

Without a reading (``--summarize`` ... ``--ensemble-rate``: at most one, ``READINGS``) a run trains the nets
(``runs.run``) and writes results/learning_raft[_TAG].json after every seed; the readings write beside it:
learning_raft_summary_*, learning_raft_tune_proof*, learning_raft_screens*, learning_raft_diagnose*,
learning_raft_stats* (``summary``, ``diagnose``), learning_raft_diagnose_checkpoints* (``checkpoints``),
learning_raft_ensemble_rate* (``ensemble_rate``).
Two readings, or a reading with a flag that only a training run reads (``TRAINING_ONLY``), are usage errors (exit 2).
"""

from __future__ import annotations

import argparse
import json

from _common import print_table, write_json

from .checkpoints import diagnose_checkpoints, plot_invented, report
from .diagnose import diagnose, figures, pool_stats
from .ensemble_rate import ensemble_rate
from .protocol import ARMS, EVERY, POOL, STEPS, results_name
from .runs import run
from .summary import HELD_OUT, TUNED_ON, equivalence, plot_judge_curves, plot_summary, screen, summarize, tune_proof

TRAINING_ONLY = ("quick", "at_once", "ensemble", "train_after")  # flags a reading refuses


def _summarize(args) -> None:
    arm, against = args.arm or "flowsynth", args.against or "chairs2d_photos"
    out = summarize(args.files, arm, against)
    name = results_name(f"summary_{arm}_{against}", args.tag)
    write_json(name, out)
    print(f"plot: {plot_summary(out, name) or 'none (matplotlib is in the bench extra)'}")


def _tune_proof(args) -> None:
    out = tune_proof(args.files, args.arm or "tuned", args.against or "flowsynth", args.held_out.split(","),
                     args.tuned_on.split(","))
    name = results_name("tune_proof", args.tag)
    write_json(name, out)
    print(f"plot: {plot_summary(out, name) or 'none (matplotlib is in the bench extra)'}")


def _screen(args) -> None:
    rows = screen(args.files)
    print_table(rows, list(rows[0])) if rows else print("--screen: no lever in the files")
    write_json(results_name("screens", args.tag), {"files": args.files, "rows": rows})


def _plot(args) -> None:
    for path in plot_judge_curves(args.plot, args.files):
        print(f"wrote {path}")


def _stats(args) -> None:
    rows = pool_stats(args.arms.split(","), args.pool or 64, args.workers, args.overrides, args.middlebury)
    print_table(rows, list(rows[0]))
    write_json(results_name("stats", args.tag), {"pairs": args.pool or 64, "rows": rows})


def _diagnose(args) -> None:
    rows = diagnose([n for n in args.nets.split(",") if n], args.middlebury)
    print_table(rows, list(rows[0]))
    write_json(results_name("diagnose", args.tag), {"rows": rows})


def _diagnose_checkpoints(args) -> None:
    out = diagnose_checkpoints(args.files, args.middlebury, args.device, args.weights)
    report(out)
    name = results_name("diagnose_checkpoints", args.tag)
    write_json(name, out)
    print(f"plot: {plot_invented(out, name) or 'none (no weights, or matplotlib is not installed)'}")


def _figures(args) -> None:
    for path in figures(args.figures, args.middlebury, [n for n in args.nets.split(",") if n]):
        print(f"wrote {path}")


def _ensemble_rate(args) -> None:
    ensemble_rate(args.ensemble_rate, args.steps or 20, device=args.device, threads=args.threads, tag=args.tag)


def _equivalence(args) -> None:
    write_json(results_name("equivalence", args.tag), equivalence(args.files))


READINGS = {"summarize": _summarize, "tune_proof": _tune_proof, "equivalence": _equivalence, "screen": _screen,
            "plot": _plot, "stats": _stats,
            "diagnose": _diagnose, "diagnose_checkpoints": _diagnose_checkpoints, "figures": _figures,
            "ensemble_rate": _ensemble_rate}


def _given(value) -> bool:
    """Whether an option's parsed ``value`` says it was given: not its default None or False (0 is a value)."""
    return value is not None and value is not False


def parser() -> argparse.ArgumentParser:
    """The command line's parser (the module docstring)."""
    p = argparse.ArgumentParser(prog="python benchmarks/learning", description=__doc__.split("\n")[0])
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
    p.add_argument("--precision", default="fp32", choices=("fp32", "bf16"),
                   help="the training step's precision (flowsynth.train.steps): fp32 is protocol 0023, bf16 protocol "
                        "0025; tests run in float32 either way")
    p.add_argument("--at-once", action="store_true", help="render every seed's pools, then train every net of every "
                   "seed at once, each in a process of its own (a lent GPU)")
    p.add_argument("--ensemble", action="store_true", help="train the nets (of each seed; with --at-once, of every "
                   "seed) at once in this process, batched (flowsynth.train.ensemble), in place of a process each: "
                   "the same pools, draws, checkpoints and files")
    p.add_argument("--train-after", default=None, metavar="FILE", help="--at-once: render the pools, then wait until "
                   "FILE exists before training (so that other benchmarks have the GPU to themselves)")
    p.add_argument("--middlebury", default=None, metavar="DIR",
                   help="a folder of Middlebury flow pairs (NAME/frame10.png, frame11.png, flow10.flo)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=JSON",
                   help="a lever: the flowsynth arms' config with this field changed (repeatable); use with --tag")
    p.add_argument("--preset", default=None, metavar="FILE", help="the tuned arm's preset (what flowsynth tune wrote)")
    p.add_argument("--held-out", default=",".join(HELD_OUT), help="--tune-proof: the Middlebury pairs the tune never "
                   "saw (comma-separated)")
    p.add_argument("--tuned-on", default=",".join(TUNED_ON), help="--tune-proof: the pairs it was tuned on")
    p.add_argument("--tag", default="", help="results/learning_raft_TAG.json")
    p.add_argument("--files", default="learning_raft*.json", help="--summarize: results/ files to pool (a glob)")
    p.add_argument("--arm", default=None, help="--summarize, --tune-proof: the numerator arm (default flowsynth; "
                   "tuned)")
    p.add_argument("--against", default=None, help="--summarize, --tune-proof: the denominator arm (default "
                   "chairs2d_photos; flowsynth)")
    p.add_argument("--nets", default="", help="--figures, --diagnose: comma-separated .pt files of training runs")
    p.add_argument("--weights", default=None, metavar="DIR", help="--diagnose-checkpoints: the folder of the runs' "
                   "saved weights (default .cache/learning_raft)")
    readings = p.add_argument_group("readings", "each trains nothing; at most one, and none of --quick, --at-once, "
                                    "--ensemble, --train-after with it").add_mutually_exclusive_group()
    readings.add_argument("--summarize", action="store_true", help="pool the seeds of --files")
    readings.add_argument("--tune-proof", action="store_true", help="decision 0026's reading: --arm (default tuned) "
                          "/ --against (default flowsynth) on the --held-out pairs' mean score, beside --tuned-on and "
                          "Motorcycle, and the goal (results/learning_raft_tune_proof[_TAG].json, .png)")
    readings.add_argument("--equivalence", action="store_true", help="protocol 0025's rule: bf16 / fp32 scores of "
                          "the default and the photo baseline, seeds 0-1, in the --files results "
                          "(results/learning_raft_equivalence[_TAG].json)")
    readings.add_argument("--screen", action="store_true", help="rule 4 for every lever of seed 0 in the --files "
                          "results, against the default and its control (results/learning_raft_screens.json)")
    readings.add_argument("--plot", default=None, metavar="NAME", help="results/NAME_JUDGE.png, the learning curves "
                          "of every arm and seed in the --files results")
    readings.add_argument("--stats", action="store_true", help="flow-magnitude and texture statistics of --arms' "
                          "pools, a lever's with --set (--pool pairs, default 64), beside the real judges")
    readings.add_argument("--diagnose", action="store_true", help="per net of --nets and real pair, the EPE on "
                          "smooth or textured pixels with small or large true motion "
                          "(results/learning_raft_diagnose[_TAG].json)")
    readings.add_argument("--diagnose-checkpoints", action="store_true", help="per arm, seed and tested checkpoint "
                          "of the --files runs, the motion its saved net invents on the five still photographs, each "
                          "real pair's EPE swing and zero flow's, and whether the nets reach the goal of a net that "
                          "does not invent motion, deciding nothing (--middlebury, --device, --weights; "
                          "results/learning_raft_diagnose_checkpoints[_TAG].json, .png)")
    readings.add_argument("--figures", default=None, metavar="NAME",
                          help="results/NAME_PAIR.png per real pair, the nets in --nets against the truth")
    readings.add_argument("--ensemble-rate", type=int, default=None, metavar="K", help="steps/s of K nets at the "
                          "protocol's shape in one process (batched, and a loop) against K processes (--steps timed "
                          "steps, default 20; --threads, --device; results/learning_raft_ensemble_rate[_TAG].json)")
    return p


def main(argv: list[str] | None = None) -> None:
    """Parse ``argv`` (default: the process's arguments) and run what it asks for (the module docstring). Usage errors
    exit 2 with argparse's message."""
    p = parser()
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
    reading = next((m for m in READINGS if _given(getattr(args, m))), None)
    if reading:
        training = [f"--{f.replace('_', '-')}" for f in TRAINING_ONLY if _given(getattr(args, f))]
        if training:
            p.error(f"--{reading.replace('_', '-')} trains nothing: drop {', '.join(training)}")
        if args.ensemble_rate is not None and args.ensemble_rate < 1:
            p.error(f"--ensemble-rate {args.ensemble_rate}: give at least 1 net")
        return READINGS[reading](args)
    if "tuned" in args.arms.split(",") and not args.preset:
        p.error("--arms tuned: give --preset FILE (the preset flowsynth tune wrote)")
    if args.steps is not None and args.steps < 20:
        p.error(f"--steps {args.steps}: give at least 20 steps")
    if args.quick:
        args.pool, args.steps, args.every = args.pool or 12, args.steps or 20, args.every or 10
    run(args)
