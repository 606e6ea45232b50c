"""Newton stepping on one CPU core: plain Python launches against the replayed Warp CPU graph.

``flowsynth.scene.motion.NewtonScene.advance_frame`` captures one substep once per scene into a Warp CPU
graph and replays it; this script steps the same scene both ways (``substep`` called ``substeps`` times
per frame against ``advance_frame``), from the same initial state, and reports per frame and per substep
[ms] (medians over frames, the first frame excluded: it compiles or captures) and the largest difference
of the body poses after all frames (0 = identical). docs/scenes.md ("Cost") quotes this table.

Run ``taskset -c 0 python benchmarks/speed/physics_graph.py [--quick]``. Prints a table and writes
``benchmarks/results/physics_graph.json``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parents[1])]
from _common import Timer, machine_info, pin_single_core, print_table, write_json

PINNING = pin_single_core()

import numpy as np

from flowsynth.scene import BouncingThingsConfig, NewtonScene, sample_layout

SUBSTEPS = 10


def frame_times(sim: NewtonScene, frames: int, replay: bool) -> tuple[list[float], np.ndarray]:
    """Per-frame wall times [s] of ``frames`` frames and the final (N, 7) body state."""
    times = []
    for _ in range(frames):
        with Timer() as tm:
            if replay:
                sim.advance_frame()
            else:
                for _ in range(sim.substeps):
                    sim.substep()
        times.append(tm.wall_s)
    return times, sim.state0.body_q.numpy().copy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames and scene sizes")
    args = ap.parse_args()
    frames = 6 if args.quick else 24
    counts = [16] if args.quick else [5, 16, 40]
    load_before = os.getloadavg()
    rows = []
    for n in counts:
        cfg = BouncingThingsConfig(num_objects=(n, n), max_objects=max(32, n), object_size=(0.3, 0.6),
                                   assets=("box", "sphere", "capsule", "rock", "crystal"), num_frames=frames)
        layout = sample_layout(cfg, 0, 0)
        result = {}
        for name, replay in (("plain", False), ("replayed", True)):
            sim = NewtonScene(cfg, layout.assets, layout.initial, SUBSTEPS)
            result[name] = frame_times(sim, frames, replay)
        plain = 1e3 * statistics.median(result["plain"][0][1:])
        replayed = 1e3 * statistics.median(result["replayed"][0][1:])
        rows.append({"objects": n, "substeps": SUBSTEPS, "plain_ms_frame": plain, "replayed_ms_frame": replayed,
                     "plain_ms_substep": plain / SUBSTEPS, "replayed_ms_substep": replayed / SUBSTEPS,
                     "speedup": plain / replayed,
                     "max_pose_diff": float(np.abs(result["plain"][1] - result["replayed"][1]).max())})
    load_after = os.getloadavg()
    print(f"Newton stepping, plain launches vs replayed Warp CPU graph; {frames} frames, medians over frames "
          f"1..{frames - 1}; load average {load_before[0]:.2f} -> {load_after[0]:.2f}")
    print_table(rows, ["objects", "substeps", "plain_ms_frame", "replayed_ms_frame", "plain_ms_substep",
                       "replayed_ms_substep", "speedup", "max_pose_diff"])
    path = write_json("physics_graph", {"machine": machine_info(), "pinning": PINNING, "frames": frames,
                                        "load_before": load_before, "load_after": load_after, "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
