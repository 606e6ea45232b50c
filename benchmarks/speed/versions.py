"""Per-sample cost of two git revisions side by side: did a change make samples slower?

    python benchmarks/speed/versions.py --base 135a7ea [--head HEAD] [--num 8] [--rounds 3]

Each revision is checked out into a temporary git worktree and imported from there (``PYTHONPATH``), in its
own process, one thread (``torch.set_num_threads(1)``, ``threads=1`` where the revision has that setting).
Rounds alternate base/head so that load from other processes hits both alike. Clock: process CPU time per
sample after one warm-up sample (kernel load), and wall time.

Three settings per revision:

- ``fixed``: issue 13's full sample (``_common.FULL_SAMPLE``), given explicitly so both revisions render the same
  kind of scene: 512x384, T=2, direct RGB, 20 objects, static camera; outputs ``_common.FULL_SAMPLE_OUTPUTS`` (rgb,
  depth, normals, instance, flow, valid and occlusion both ways);
- ``default``: that revision's own default config at 512x384, T=2, same outputs;
- ``stream``: what ``BouncingThings()`` streams with no arguments in that revision: its default config as it
  is (320x240, 24 frames at the time of writing) and its default outputs (rgb and forward flow).

Writes benchmarks/results/versions.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common

from _common import FULL_SAMPLE, FULL_SAMPLE_OUTPUTS, machine_info, print_table, write_json

REPO = Path(__file__).resolve().parents[2]
MODES = ("fixed", "default", "stream")

CHILD = r"""
import inspect, json, sys, time
import torch
torch.set_num_threads(1)
import flowsynth as fs
n, mode, work = int(sys.argv[1]), sys.argv[2], json.loads(sys.argv[3])
full = {k: tuple(v) if isinstance(v, list) else v for k, v in work["full"].items()}
size = {k: full[k] for k in ("width", "height", "num_frames")}
kw = {"fixed": full, "default": size, "stream": {}}[mode]
outs = work["outputs"]
extra = {"threads": 1} if "threads" in inspect.signature(fs.datasets.BouncingThings).parameters else {}
if mode != "stream":
    extra["outputs"] = outs
ds = fs.datasets.BouncingThings(fs.BouncingThingsConfig(**kw), seed=0, **extra)
ds.sample(0)
c, t = time.process_time(), time.perf_counter()
for i in range(1, n + 1):
    ds.sample(i)
cpu, wall = (time.process_time() - c) / n, (time.perf_counter() - t) / n
print(json.dumps({"file": fs.__file__, "cpu_s": cpu, "wall_s": wall}))
"""


def run_child(tree: Path, n: int, mode: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    work = json.dumps({"full": FULL_SAMPLE, "outputs": FULL_SAMPLE_OUTPUTS})
    out = subprocess.run([sys.executable, "-c", CHILD, str(n), mode, work], cwd=tree, env=env, capture_output=True,
                         text=True, check=True).stdout.strip().splitlines()[-1]
    res = json.loads(out)
    if not res["file"].startswith(str(tree)):  # the revision under test, not an installed flowsynth
        raise RuntimeError(f"imported {res['file']}, expected a module under {tree}")
    return res


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--base", required=True, help="git revision before the change")
    p.add_argument("--head", default="HEAD", help="git revision after the change")
    p.add_argument("--num", type=int, default=8, help="timed samples per run")
    p.add_argument("--rounds", type=int, default=3)
    args = p.parse_args()
    revs = {name: subprocess.run(["git", "rev-parse", "--short", rev], cwd=REPO, capture_output=True, text=True,
                                 check=True).stdout.strip() for name, rev in (("base", args.base), ("head", args.head))}
    load0 = os.getloadavg()
    times: dict = {(name, mode): [] for name in revs for mode in MODES}
    with tempfile.TemporaryDirectory() as tmp:
        trees = {name: Path(tmp) / name for name in revs}
        for name, rev in revs.items():
            subprocess.run(["git", "worktree", "add", "-q", "--detach", str(trees[name]), rev], cwd=REPO, check=True)
        try:
            for _ in range(args.rounds):
                for name in revs:
                    for mode in MODES:
                        times[(name, mode)].append(run_child(trees[name], args.num, mode))
        finally:
            for tree in trees.values():
                subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=REPO, check=False)
    rows = []
    for mode in MODES:
        med = {name: statistics.median(r["cpu_s"] for r in times[(name, mode)]) for name in revs}
        wall = {name: statistics.median(r["wall_s"] for r in times[(name, mode)]) for name in revs}
        rows.append({"settings": mode, f"base {revs['base']} cpu s": med["base"],
                     f"head {revs['head']} cpu s": med["head"], "head/base cpu": med["head"] / med["base"],
                     "base samples/s (cpu)": 1 / med["base"], "head samples/s (cpu)": 1 / med["head"],
                     "head/base wall": wall["head"] / wall["base"]})
    load1 = os.getloadavg()
    print(f"\nPer-sample cost, one thread, medians of {args.rounds} alternating rounds of {args.num} samples; "
          f"load average {load0[0]:.1f} -> {load1[0]:.1f}")
    print_table(rows, list(rows[0]))
    write_json("versions", {"machine": machine_info(), "revisions": revs, "load_average": [load0, load1],
                            "num": args.num, "rounds": args.rounds, "rows": rows,
                            "runs": {f"{k[0]}/{k[1]}": v for k, v in times.items()}})


if __name__ == "__main__":
    main()
