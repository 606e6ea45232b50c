"""What each issue-17 output adds to a sample's time: stereo, scene flow, extra frame gaps, point tracks.

    python benchmarks/outputs_cost.py [--quick]

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
on process CPU time (the work, all threads), since wall time on the shared 2-core machine mostly measures
the other processes.

Writes benchmarks/results/outputs_cost.json (or outputs_cost_quick.json) with the load average.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

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
    """Empty the per-process caches keyed by a mesh: scaled assets, asset BVHs, hulls, culling planes."""
    import flowsynth.accel as accel
    from flowsynth.assets import get_asset

    get_asset.cache_clear()
    for cache in (accel._MESHES, accel._HULLS, accel._PLANES):
        cache.clear()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    args = p.parse_args()
    import flowsynth as fs
    from flowsynth.datasets.bouncing import sample_seed
    from flowsynth.plan import make_plan
    from flowsynth.render import render_plan
    from flowsynth.sampling import sample_scene

    W, H = (256, 192) if args.quick else (512, 384)
    rows = []
    for T, repeat, warmup in ((2, 5 if args.quick else 7, 1), (24, 3, 0)):  # T=2's warm-up loads the kernels
        cfg = fs.BouncingThingsConfig(width=W, height=H, num_frames=T, render_mode="flat")
        counter = {"i": 0}

        def run(extra, opts, cfg=cfg, counter=counter):
            i = counter["i"] // len(VARIANTS)  # every variant gets the same scene in a round
            counter["i"] += 1
            cold_caches()
            scene = sample_scene(cfg, 0, i)
            plan = make_plan(BASE + extra, seed=sample_seed(0, i), max_objects=cfg.max_objects, **opts)
            render_plan(scene, plan)

        fns = {name: (lambda e=e, o=o: run(e, o)) for name, (e, o, _) in VARIANTS.items()}
        res = time_round_robin(fns, repeat=repeat, warmup=warmup)
        base, base_cpu = res["mono (base)"]["wall_s"], res["mono (base)"]["cpu_s"]
        for name, (_, _, goal) in VARIANTS.items():
            ratio = res[name]["cpu_s"] / base_cpu
            rows.append({"T": T, "variant": name, "cpu s": res[name]["cpu_s"], "wall s": res[name]["wall_s"],
                         "cpu vs base": ratio, "wall vs base": res[name]["wall_s"] / base, "goal": goal,
                         "met (cpu)": None if goal is None else ("yes" if ratio <= goal else "NO")})
    load = os.getloadavg()
    print(f"\nWhat each output adds to a sample at {W}x{H} (scene sampling + render; medians of process CPU time "
          f"(all threads: the work) and wall time; {os.cpu_count()} cores shared, load average {load[0]:.1f} / "
          f"{load[1]:.1f} / {load[2]:.1f}, so wall time is the noisier)")
    print_table(rows, ["T", "variant", "cpu s", "wall s", "cpu vs base", "wall vs base", "goal", "met (cpu)"])
    write_json("outputs_cost_quick" if args.quick else "outputs_cost",
               {"machine": machine_info(), "load_average": load, "resolution": [W, H], "base_outputs": BASE,
                "rows": rows})


if __name__ == "__main__":
    main()
