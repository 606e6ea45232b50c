"""The scene stage (``sample_scene``: draws, Newton physics, materials, lights) with and without Newton scene reuse.

``flowsynth.scene.physics.SCENE_REUSE`` keeps each finished Newton scene (model, collision pipeline, solver, captured
substep) and runs a later clip with the same key on it, reset (docs/decisions/0020-newton-scene-reuse.md). The key is
everything but the initial state (config, substeps, contact capacity, the assets in order), so how much reuse saves
depends on how often a dataset repeats a key: never in the default config (its assets, sizes and drawn speed band
differ per sample), always where every sample has the same shapes.

For each config the script alternates rounds of ``--block`` consecutive indices, fresh (reuse off) and reused (the
cache kept warm across rounds, as in a stream), on the same indices, and reports process CPU [ms] per sample (median
over rounds), the ratio fresh / reused, and the share of clips that found a scene to reuse. Run
``taskset -c 0 python benchmarks/speed/scene_setup.py [--quick]``. Prints a table and writes
``benchmarks/results/scene_setup.json``.

``--free-flight`` compares instead the scene stage of the default config (2, 4 and 8 frames) and of the full
sample's config (20 objects) with free flight
(``physics.FREE_FLIGHT``: clips clear of contact on a bodies-only model; docs/decisions/0022-free-flight.md) and
without, and writes ``benchmarks/results/scene_setup_free_flight.json``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parents[1])]
from _common import full_sample_config, machine_info, pin_single_core, print_table, write_json

PINNING = pin_single_core()

from flowsynth.scene import BouncingThingsConfig, physics, sample_scene

CONFIGS = {
    "default 256x192, 2 frames": BouncingThingsConfig(width=256, height=192, num_frames=2),
    "8 spheres, one size, flow_px off": BouncingThingsConfig(width=256, height=192, num_frames=2,
                                                             assets=("sphere",), size_levels=1,
                                                             num_objects=(8, 8), flow_px=None),
    "4-6 rocks, one size, flow_px off": BouncingThingsConfig(width=256, height=192, num_frames=2,
                                                             assets=("rock",), size_levels=1,
                                                             num_objects=(4, 6), flow_px=None),
}


class _Builds:
    """Counts NewtonScene constructions (clips that found no scene to reuse)."""

    def __init__(self) -> None:
        self.count = 0
        init = physics.NewtonScene.__init__

        def counting(scene, *args, **kwargs):
            self.count += 1
            init(scene, *args, **kwargs)

        physics.NewtonScene.__init__ = counting


def scene_cpu(cfg: BouncingThingsConfig, indices: range, reuse: bool) -> float:
    """Process CPU seconds per sample of ``sample_scene`` over ``indices``, reuse on or off."""
    physics.SCENE_REUSE = reuse
    t0 = time.process_time()
    for i in indices:
        sample_scene(cfg, 0, i)
    return (time.process_time() - t0) / len(indices)


def free_flight(rounds: int, block: int, warm: int) -> None:
    """``--free-flight``: the scene stage of the default config at 2, 4 and 8 frames, and of the full sample's config
    (``_common.full_sample_config``: 20 objects), with free flight
    (``physics.FREE_FLIGHT``) and without, alternating rounds of ``block`` indices after ``warm`` samples with it
    (its bodies-only scenes kept, as in a long stream); and the share of clips free flight kept."""
    counts = physics.FREE_FLIGHT_COUNTS
    load_before = os.getloadavg()
    rows = []
    configs = {f"default, {f} frames": BouncingThingsConfig(width=256, height=192, num_frames=f) for f in (2, 4, 8)}
    configs["full sample (20 objects, 2 frames)"] = full_sample_config()
    for name, cfg in configs.items():
        physics.FREE_FLIGHT = True
        scene_cpu(cfg, range(10_000, 10_000 + warm), True)
        on, off = [], []
        tried0, kept0 = counts["tried"], counts["kept"]
        for r in range(rounds):
            indices = range(r * block, (r + 1) * block)
            for flag in ((False, True) if r % 2 == 0 else (True, False)):
                physics.FREE_FLIGHT = flag
                (on if flag else off).append(scene_cpu(cfg, indices, True))
        f, n = statistics.median(on), statistics.median(off)
        rows.append({"config": name, "without_ms": 1e3 * n, "free_flight_ms": 1e3 * f, "free/without": f / n,
                     "tried": (counts["tried"] - tried0) / (rounds * block),
                     "kept": (counts["kept"] - kept0) / (rounds * block)})
        print(f"  {name}: without {1e3 * n:.1f} ms, free flight {1e3 * f:.1f} ms", file=sys.stderr, flush=True)
    physics.FREE_FLIGHT = True
    load_after = os.getloadavg()
    print(f"Scene stage (sample_scene) per sample, process CPU, one thread; "
          f"{rounds} alternating rounds of {block} samples after {warm} with free flight; load average "
          f"{load_before[0]:.2f} -> {load_after[0]:.2f}. tried / kept: shares of the clips free flight ran / kept")
    print_table(rows, ["config", "without_ms", "free_flight_ms", "free/without", "tried", "kept"])
    path = write_json("scene_setup_free_flight", {"machine": machine_info(), "pinning": PINNING, "rounds": rounds,
                                                  "block": block, "warm": warm, "load_before": load_before,
                                                  "load_after": load_after, "rows": rows})
    print(f"wrote {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 rounds of 3 samples per config")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--block", type=int, default=10, help="samples per round and mode")
    ap.add_argument("--free-flight", action="store_true",
                    help="the default config at 2, 4 and 8 frames with free flight and without (docs/decisions/0022)")
    args = ap.parse_args()
    rounds, block = (2, 3) if args.quick else (args.rounds, args.block)
    if args.free_flight:
        free_flight(rounds, block, 3 if args.quick else 60)
        return
    load_before = os.getloadavg()
    builds = _Builds()
    rows = []
    for name, cfg in CONFIGS.items():
        scene_cpu(cfg, range(10_000, 10_003), True)  # compile Newton's kernels and fill the per-process caches
        fresh, reused, clips, built = [], [], 0, 0
        for r in range(rounds):
            indices = range(r * block, (r + 1) * block)
            for reuse in ((False, True) if r % 2 == 0 else (True, False)):
                before = builds.count
                t = scene_cpu(cfg, indices, reuse)
                (reused if reuse else fresh).append(t)
                if reuse:
                    clips += len(indices)
                    built += builds.count - before
        f, u = statistics.median(fresh), statistics.median(reused)
        rows.append({"config": name, "fresh_ms": 1e3 * f, "reused_ms": 1e3 * u, "fresh/reused": f / u,
                     "reuse_hits": 1.0 - built / clips})
        print(f"  {name}: fresh {1e3 * f:.1f} ms, reused {1e3 * u:.1f} ms", file=sys.stderr, flush=True)
    physics.SCENE_REUSE = True
    load_after = os.getloadavg()
    print(f"Scene stage (sample_scene) per sample, process CPU, one thread; {rounds} alternating rounds of {block} "
          f"samples; load average {load_before[0]:.2f} -> {load_after[0]:.2f}")
    print_table(rows, ["config", "fresh_ms", "reused_ms", "fresh/reused", "reuse_hits"])
    path = write_json("scene_setup", {"machine": machine_info(), "pinning": PINNING, "quick": args.quick,
                                      "rounds": rounds, "block": block, "load_before": load_before,
                                      "load_after": load_after, "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
