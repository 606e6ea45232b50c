"""What each optional output adds to a sample's time: stereo, scene flow, extra frame gaps, point tracks.

    python benchmarks/speed/outputs_cost.py [--quick]

A "sample" is one BouncingThings sample at 512x384 (``--quick``: 256x192), T = 2 and T = 24, in one
process with every core (the default ``threads``): the scene is sampled (physics) and rendered. The base
request is a typical mono training sample: rgb (flat shading), depth, flow both ways with exact occlusion.
Each variant adds one family to it; all variants of one T render the same scenes, called in turn each round
(``_common.time_round_robin``) so the machine's load hits them alike. Before each call the per-process
mesh caches are emptied (``cold_caches``): a dataset's samples draw new object sizes, so every sample
builds its meshes, BVHs, hulls and culling planes, and a variant that ran after another on the same scene
would otherwise find them built (the previous version of this script did: its variants after the base
were ~0.05-0.1 s per T=24 sample at 256x192 too cheap). Goals (issue 17): stereo <= 2x the
mono cost, scene flow and one extra gap <= +15 % each, 256 tracks over 24 frames <= +20 %. The goal is judged
on process CPU time: every variant renders the same scenes (T=2: 7, T=24: 3), each scene 3 times at T=24 (2 at
T=2) in round-robin order, rotated each round; each (variant, scene) keeps its fastest repeat, since load on a shared
machine only ever adds time, and the ratio is the total over the scenes to the base's total. Process CPU time (the work,
all threads) rather than wall time, which on the shared 2-core machine mostly measures the other processes.

Writes benchmarks/results/outputs_cost.json (or outputs_cost_quick.json) with the load average.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common

from _common import machine_info, print_table, time_round_robin, write_json

BASE = ["rgb", "depth", "flow_fw", "flow_bw", "occ_fw", "occ_bw"]
STEREO = ["rgb_right", "depth_right", "disparity", "disparity_right", "disparity_change", "disparity_occ",
          "disparity_occ_right"]
# name: (extra outputs, render options, goal as a ratio to the base time)
VARIANTS = {
    "mono (base)": ([], {}, None),
    "+ stereo (all 7 keys)": (STEREO, {"stereo_baseline": 0.1}, 2.0),
    "+ scene flow fw+bw": (["scene_flow_fw", "scene_flow_bw"], {}, 1.15),
    "+ gap 2 (flow, occ fw+bw)": ([], {"flow_gaps": (1, 2)}, 1.15),
    "+ 256 tracks": (["tracks"], {"num_tracks": 256}, 1.20),
}


def cold_caches() -> None:
    """Empty the per-process caches keyed by a mesh: scaled assets, asset BVH trees, hulls, culling planes."""
    from flowsynth import raycast, scene  # noqa: F401  (their caches, named below, are registered on import)
    from flowsynth.caches import clear_caches

    clear_caches("assets.get_asset", "culling.hulls", "culling.face_planes", "blas.topology")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    args = p.parse_args()
    import flowsynth as fs
    from flowsynth.datasets import sample_seed
    from flowsynth.plan import make_plan
    from flowsynth.renderer import render_plan
    from flowsynth.scene import sample_scene

    W, H = (256, 192) if args.quick else (512, 384)
    rows = []
    # (T, scenes, repeats of each scene, warm-up rounds): T=2's warm-up loads the kernels
    for T, scenes, reps, warmup in ((2, 5 if args.quick else 7, 2, 1), (24, 2 if args.quick else 3, 3, 0)):
        cfg = fs.BouncingThingsConfig(width=W, height=H, num_frames=T, render_mode="flat")
        counter = {"i": 0}

        def run(extra, opts, cfg=cfg, counter=counter, scenes=scenes):
            i = (counter["i"] // len(VARIANTS)) % scenes  # every variant gets the same scene in a round (the
            # order rotates each round: the first call of a round, on a scene new to the process, ran slower)
            counter["i"] += 1
            cold_caches()
            scene = sample_scene(cfg, 0, i)
            plan = make_plan(BASE + extra, seed=sample_seed(0, i), max_objects=cfg.max_objects, **opts)
            render_plan(scene, plan)

        fns = {name: (lambda e=e, o=o: run(e, o)) for name, (e, o, _) in VARIANTS.items()}
        res = time_round_robin(fns, repeat=scenes * reps, warmup=warmup, rotate=True)
        scene_of_round = [(k + warmup) % scenes for k in range(scenes * reps)]

        def per_scene_min(times, scene_of_round=scene_of_round, scenes=scenes):
            """Each scene's fastest repeat: on a shared machine noise only ever adds time."""
            return [min(t for t, sc in zip(times, scene_of_round) if sc == j) for j in range(scenes)]

        base_cpu, base_wall = (per_scene_min(res["mono (base)"][k]) for k in ("cpu_all_s", "wall_all_s"))
        for name, (_, _, goal) in VARIANTS.items():
            cpu, wall = per_scene_min(res[name]["cpu_all_s"]), per_scene_min(res[name]["wall_all_s"])
            per_scene = [c / b for c, b in zip(cpu, base_cpu)]
            ratio = sum(cpu) / sum(base_cpu)
            rows.append({"T": T, "variant": name, "cpu s": sum(cpu) / scenes, "wall s": sum(wall) / scenes,
                         "cpu vs base": ratio, "per-scene range": f"{min(per_scene):.3f}-{max(per_scene):.3f}",
                         "wall vs base": sum(wall) / sum(base_wall), "goal": goal,
                         "met (cpu)": None if goal is None else ("yes" if ratio <= goal else "NO"),
                         "cpu_all_s": res[name]["cpu_all_s"], "wall_all_s": res[name]["wall_all_s"],
                         "scene_of_round": scene_of_round})
    load = os.getloadavg()
    print(f"\nWhat each output adds to a sample at {W}x{H} (scene sampling + render; process CPU time (all threads: "
          f"the work) and wall time: each scene's fastest of its repeats, averaged over the scenes; vs base = total "
          f"over the same scenes / the base's total, and the range of the per-scene ratios; {os.cpu_count()} cores "
          f"shared, load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}, so wall time is the noisier)")
    print_table(rows, ["T", "variant", "cpu s", "wall s", "cpu vs base", "per-scene range", "wall vs base", "goal",
                       "met (cpu)"])
    write_json("outputs_cost_quick" if args.quick else "outputs_cost",
               {"machine": machine_info(), "load_average": load, "resolution": [W, H], "base_outputs": BASE,
                "rows": rows})


if __name__ == "__main__":
    main()
