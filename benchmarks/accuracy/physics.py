"""BouncingThings motion on one CPU core: Newton physics cost and accuracy against substeps per frame.

Scenes: n = 5, 20, 80 objects in a 6 x 5 x 4 m room (camera zone 1 m), sizes 0.3-0.6 m, speeds 1-4 m/s,
angular speeds 0-3 rad/s, 24 fps, from two asset sets: analytic primitives (box, sphere, cylinder,
capsule, cone) and convex hulls (torus, rock, crystal, star, blob). For each substep count the script
reports

- setup [ms]: Newton model, collision pipeline and graph capture, once per scene;
- step [ms/frame]: replaying the captured substeps, per frame;
- penetration: the deepest overlap of two visual meshes over all frames, found by python-fcl through
  trimesh's CollisionManager (independent of Newton), as a fraction of the smaller object's size;
- wall: the farthest any vertex gets outside the room, as a fraction of that object's size (0 = inside);
- d/s: the substep displacement fraction, (2 max_speed + max_angular_speed * max_size) / (fps * substeps
  * min_size), the quantity the automatic rule (flowsynth.scene.physics.choose_substeps) bounds by
  SUBSTEP_FRACTION. Rows marked "auto" use that rule.

It also times scene sampling (``sample_layout``) and kinematic against physics motion per frame, and
runs a "fast" set (speeds 6-12 m/s: one frame's motion exceeds the smallest object) at the automatic
substep count. Run ``taskset -c 0 python benchmarks/accuracy/physics.py [--quick]``. Prints tables, writes
``benchmarks/results/physics.json`` and, with matplotlib, ``benchmarks/results/physics.png``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parents[1])]
from _common import RESULTS_DIR, Timer, machine_info, pin_single_core, print_table, timeit, write_json

PINNING = pin_single_core()

import numpy as np
import warp as wp
from trimesh.collision import CollisionManager

from flowsynth.scene import (SUBSTEP_FRACTION, BouncingThingsConfig, NewtonScene, choose_substeps, sample_layout,
                             simulate)

SETS = {"primitives": ("box", "sphere", "cylinder", "capsule", "cone"),
        "hulls": ("torus", "rock", "crystal", "star", "blob")}


def make_cfg(n: int, assets: tuple[str, ...], num_frames: int, max_speed: float = 4.0,
             min_speed: float = 1.0, motion: str = "physics") -> BouncingThingsConfig:
    return BouncingThingsConfig(
        room_size=(6.0, 5.0, 4.0), camera_clearance=1.0, num_objects=(n, n), max_objects=max(32, n),
        object_size=(0.3, 0.6), min_speed=min_speed, max_speed=max_speed, angular_speed=(0.0, 3.0),
        num_frames=num_frames, assets=assets, motion=motion)


def check(cfg: BouncingThingsConfig, assets, poses: np.ndarray) -> tuple[float, float]:
    """(max mesh penetration / smaller size, max vertex excursion outside the room / size)."""
    sizes = np.array([a.size for a in assets])
    lo, hi = (np.asarray(b) for b in cfg.room_bounds)
    cm = CollisionManager()
    for i, a in enumerate(assets):
        cm.add_object(str(i), a.mesh)
    pen = wall = 0.0
    for t in range(poses.shape[0]):
        for i, a in enumerate(assets):
            cm.set_transform(str(i), poses[t, i])
            V = a.mesh.vertices @ poses[t, i, :3, :3].T + poses[t, i, :3, 3]
            wall = max(wall, float(max((lo - V).max(), (V - hi).max())) / a.size)
        _, contacts = cm.in_collision_internal(return_data=True)
        for c in contacts:
            i, j = (int(name) for name in c.names)
            pen = max(pen, c.depth / min(sizes[i], sizes[j]))
    return pen, wall


def run_physics(cfg: BouncingThingsConfig, seed: int, substeps: int) -> dict:
    layout = sample_layout(cfg, seed, 0)
    with Timer() as tm:
        sim = NewtonScene(cfg, layout.assets, layout.initial, substeps)
        sim.advance_frame()  # builds the captured graph
    setup = tm.wall_s
    poses = [sim.read()[0]]
    with Timer() as tm:
        for _ in range(cfg.num_frames - 1):
            sim.advance_frame()
            poses.append(sim.read()[0])
    step = tm.wall_s / max(cfg.num_frames - 1, 1)
    pen, wall = check(cfg, layout.assets, np.stack(poses))
    sizes = [a.size for a in layout.assets]
    approach = 2 * cfg.max_speed + cfg.angular_speed[1] * max(sizes)
    return {"setup_ms": 1e3 * setup, "step_ms": 1e3 * step, "penetration": pen, "wall": wall,
            "d_over_s": approach / (cfg.fps * substeps * min(sizes))}


_MEMO_PROBE = """
import json, sys, time
from flowsynth.scene import physics as fs_physics, sample_layout, simulate
sys.path.insert(0, {here!r})
from physics import SETS, make_cfg
if {off}:
    import contextlib
    fs_physics.memoise_newton_kernel_factories = contextlib.nullcontext  # Newton's own behaviour: fresh kernels
cfg = make_cfg(20, SETS["primitives"] + SETS["hulls"], 2)
times = []
for seed in range(5):
    layout = sample_layout(cfg, seed, 0)
    t = time.perf_counter()
    simulate(cfg, layout.assets, layout.initial)
    times.append(time.perf_counter() - t)
print(json.dumps(times))
"""


def memo_saving() -> list[dict]:
    """Seconds per 2-frame physics clip (20 objects, five scenes in a fresh process) with and without
    flowsynth.scene.motion's memoisation of Newton's narrow-phase kernel factories."""
    import json
    import subprocess

    rows = []
    for name, off in (("memoised (flowsynth)", False), ("Newton as shipped", True)):
        out = subprocess.run([sys.executable, "-c", _MEMO_PROBE.format(here=str(HERE), off=off)], capture_output=True,
                             text=True, check=True, env={**os.environ, "PYTHONPATH": str(HERE.parents[1])})
        times = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append({"newton kernels": name, "first_scene_s": times[0], "next_scenes_s": float(np.median(times[1:]))})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer substep counts, frames and seeds")
    args = ap.parse_args()
    wp.config.quiet = True
    load_before = os.getloadavg()
    T = 24 if args.quick else 48
    seeds = [0] if args.quick else [0, 1]
    counts = [5, 20, 80]
    substep_list = [2, 8, 32] if args.quick else [2, 4, 8, 16, 32, 64]

    run_physics(make_cfg(5, SETS["hulls"], 2), 0, 2)  # compile / load Newton's kernels untimed
    rows = []
    for set_name, assets in SETS.items():
        for n in counts:
            cfg = make_cfg(n, assets, T)
            auto = choose_substeps(cfg, [a.size for a in sample_layout(cfg, 0, 0).assets])
            for sub in sorted(set(substep_list) | {auto}):
                results = [run_physics(cfg, s, sub) for s in seeds]
                row = {"set": set_name, "n": n, "substeps": sub, "rule": "auto" if sub == auto else "",
                       "d/s": results[0]["d_over_s"],
                       "setup_ms": float(np.median([r["setup_ms"] for r in results])),
                       "step_ms": float(np.median([r["step_ms"] for r in results])),
                       "penetration": max(r["penetration"] for r in results),
                       "wall": max(r["wall"] for r in results)}
                rows.append(row)
                print(f"  {set_name} n={n} substeps={sub}: step {row['step_ms']:.2f} ms/frame, "
                      f"penetration {row['penetration']:.3g}", file=sys.stderr, flush=True)
    print("\nPhysics: cost and accuracy against substeps per frame")
    columns = ["set", "n", "substeps", "rule", "d/s", "setup_ms", "step_ms", "penetration", "wall"]
    print_table(rows, columns)

    fast = []
    for set_name, assets in SETS.items():
        cfg = make_cfg(20, assets, T, min_speed=6.0, max_speed=12.0)
        for s in seeds:
            layout = sample_layout(cfg, s, 0)
            sub = choose_substeps(cfg, [a.size for a in layout.assets])
            r = run_physics(cfg, s, sub)
            fast.append({"set": set_name, "n": 20, "seed": s, "substeps": sub, **r})
    print("\nFast objects (6-12 m/s, one frame's motion > smallest size), automatic substeps")
    print_table(fast, ["set", "n", "seed", "substeps", "d_over_s", "setup_ms", "step_ms", "penetration",
                       "wall"])

    sampling, motion_rows = [], []
    for n in counts:
        cfg = make_cfg(n, SETS["primitives"] + SETS["hulls"], T)
        sampling.append({"n": n, "sample_layout_ms": 1e3 * timeit(lambda cfg=cfg: sample_layout(cfg, 0, 0),
                                                                   repeat=5)})
        layout = sample_layout(cfg, 0, 0)
        kin = make_cfg(n, SETS["primitives"] + SETS["hulls"], T, motion="kinematic")
        t_kin = timeit(lambda kin=kin, layout=layout: simulate(kin, layout.assets, layout.initial), repeat=5)
        with Timer() as tm:
            traj = simulate(cfg, layout.assets, layout.initial)
        t_phys = tm.wall_s
        motion_rows.append({"n": n, "kinematic_ms_per_frame": 1e3 * t_kin / T,
                            "physics_ms_per_frame": 1e3 * t_phys / T, "physics_substeps": traj.substeps})
    print("\nScene sampling (sample_layout: draws, placement, asset lookup; no motion)")
    print_table(sampling, ["n", "sample_layout_ms"])
    print(f"\nMotion per frame, whole clip of {T} frames including physics setup")
    print_table(motion_rows, ["n", "kinematic_ms_per_frame", "physics_ms_per_frame", "physics_substeps"])

    memo = memo_saving()
    print("\nNewton narrow-phase kernel factories memoised per process (flowsynth.scene.motion) or not: seconds per "
          "2-frame clip of 20 objects, fresh process, first scene and median of the next four")
    print_table(memo, ["newton kernels", "first_scene_s", "next_scenes_s"])

    path = write_json("physics", {
        "machine": machine_info(), "pinning": PINNING, "loadavg_1_5_15": [load_before, os.getloadavg()],
        "quick": args.quick, "frames": T, "seeds": seeds,
        "substep_fraction": SUBSTEP_FRACTION, "substeps": rows, "fast": fast, "sampling": sampling,
        "motion": motion_rows, "memoisation": memo})
    print(f"\nwrote {path}")
    plot(rows)


def plot(rows: list[dict]) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8))
    for set_name in SETS:
        for n in sorted({r["n"] for r in rows}):
            rs = [r for r in rows if r["set"] == set_name and r["n"] == n]
            x = [r["substeps"] for r in rs]
            label = f"{set_name}, n={n}"
            a1.plot(x, [max(r["penetration"], r["wall"], 1e-4) for r in rs], marker="o", label=label)
            a2.plot(x, [r["step_ms"] for r in rs], marker="o", label=label)
    a1.axhline(0.01, color="k", lw=0.8, ls="--")
    a1.set(xscale="log", yscale="log", xlabel="substeps per frame",
           ylabel="max penetration / size (floor 1e-4)", title="accuracy (dashed: 1% tolerance)")
    a2.set(xscale="log", yscale="log", xlabel="substeps per frame", ylabel="ms per frame", title="cost")
    a2.legend(fontsize=7)
    fig.tight_layout()
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    fig.savefig(RESULTS_DIR / "physics.png", dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
