"""The stream's rate through DataLoader workers by start method: fork against forkserver and spawn.

    python benchmarks/speed/start_methods.py [--quick] [--workers K] [--samples N] [--rounds R]

``fs.datasets.loader`` starts its workers with forkserver, because CUDA does not survive fork(). This measures what
that costs on the CPU: ``BouncingThings`` at 256x192, 2 frames (rgb, flow_fw, valid_fw: what a RAFT loop reads)
through K workers, batch 4, persistent workers, for each start method in turn, ``--rounds`` times alternated. Per
run: the start-up (loader creation to its first 2 batches a worker: imports, kernel loads, the first scenes) and the
steady rate (``--samples`` samples after that). Prints a table; writes results/start_methods[_quick].json.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common

from _common import machine_info, print_table, write_json

METHODS = ("fork", "forkserver", "spawn")


def run_once(method: str, workers: int, samples: int) -> dict:
    """One loader of ``workers`` ``method`` workers: its start-up [s] and its steady samples/s."""
    import flowsynth as fs
    from torch.utils.data import DataLoader

    cfg = fs.BouncingThingsConfig(width=256, height=192, num_frames=2)
    ds = fs.datasets.BouncingThings(cfg, outputs=["rgb", "flow_fw", "valid_fw"], seed=0)
    t0 = time.perf_counter()
    it = iter(DataLoader(ds, batch_size=4, num_workers=workers, multiprocessing_context=method,
                         persistent_workers=True, timeout=900))
    for _ in range(2 * workers):  # start-up, and the batches prefetched meanwhile
        next(it)
    start_s = time.perf_counter() - t0
    t, got = time.perf_counter(), 0
    while got < samples:
        got += len(next(it)["index"])
    return {"start_s": start_s, "samples_per_s": got / (time.perf_counter() - t)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="8 samples a run, one round")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--samples", type=int, default=None, help="timed samples a run (default 32; --quick 8)")
    p.add_argument("--rounds", type=int, default=None, help="alternated rounds (default 2; --quick 1)")
    a = p.parse_args(argv)
    samples = a.samples if a.samples is not None else (8 if a.quick else 32)
    rounds = a.rounds if a.rounds is not None else (1 if a.quick else 2)
    for name, v in (("workers", a.workers), ("samples", samples), ("rounds", rounds)):
        if v < 1:
            p.error(f"--{name} {v}: must be at least 1")
    runs = {m: [] for m in METHODS}
    for _ in range(rounds):
        for m in METHODS:
            runs[m].append(run_once(m, a.workers, samples))
    fork = statistics.mean(r["samples_per_s"] for r in runs["fork"])
    rows = [{"start method": m, "start-up s": statistics.mean(r["start_s"] for r in rs),
             "samples/s": statistics.mean(r["samples_per_s"] for r in rs),
             "x fork": statistics.mean(r["samples_per_s"] for r in rs) / fork} for m, rs in runs.items()]
    print(f"BouncingThings 256x192, 2 frames (rgb, flow_fw, valid_fw), {a.workers} workers, batch 4, {samples} samples "
          f"a run, {rounds} round(s) alternated")
    print_table(rows, list(rows[0]))
    write_json("start_methods" + ("_quick" if a.quick else ""), {
        "workers": a.workers, "samples": samples, "rounds": rounds, "rows": rows, "runs": runs,
        "machine": machine_info()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
