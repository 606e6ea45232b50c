"""Streaming throughput: samples/s per output set and worker count, what each plan skip saves, memory.

    python benchmarks/throughput.py [--quick]
    python benchmarks/throughput.py --ratio [--samples 12]

Writes benchmarks/results/throughput.json. Times are wall-clock on this machine (see "machine").

``--ratio`` runs only issue 13's "skipping pays" check (goal: depth-only >= 4x faster than the full stream at
256x192, T=2): depth-only and full samples of the same indices, alternated in one process after a warm-up
(caches of a long stream filled), timed by process CPU time (and wall), default threads; writes
benchmarks/results/throughput_ratio.json.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine_info, print_table, write_json

OUTPUT_SETS = {
    "depth": ["depth"],
    "flow+occ": ["flow_fw", "valid_fw", "occ_fw"],
    "everything+direct rgb": None,  # filled from plan.CORE_OUTPUTS below (issue-17 outputs: outputs_cost.py)
}


def rate(cfg, outputs, workers: int, n: int) -> float:
    import torch
    from torch.utils.data import DataLoader

    import flowsynth as fs

    ds = fs.datasets.BouncingThings(cfg, outputs=outputs, seed=0, start=1000)
    loader = DataLoader(ds, batch_size=None, num_workers=workers, persistent_workers=False)
    it = iter(loader)
    next(it)  # worker start-up and first sample (kernel cache load) are not counted
    t = time.perf_counter()
    for _ in range(n):
        next(it)
    dt = time.perf_counter() - t
    del it
    assert not torch.cuda.is_initialized()
    return n / dt


def skip_savings(cfg, n: int) -> list[dict]:
    import flowsynth as fs
    from flowsynth.plan import CORE_OUTPUTS

    full = list(CORE_OUTPUTS)
    rows = []
    cases = {
        "full request": full,
        "no rgb (no shading)": [k for k in full if k != "rgb"],
        "no occlusion rays": [k for k in full if not k.startswith("occ_")],
        "no flow family": [k for k in full if k.split("_")[0] not in ("flow", "valid", "occ", "oof", "motion")],
        "no object tables": [k for k in full if not (k.startswith("object_") or k.startswith("box")
                                                     or k in ("world_T_obj", "visible_pixels"))],
        "depth only": ["depth"],
    }
    base = None
    for name, outs in cases.items():
        ds = fs.datasets.BouncingThings(cfg, outputs=outs, seed=0, start=2000)
        ds.sample(0)
        t = time.perf_counter()
        for i in range(n):
            ds.sample(i + 1)
        per = (time.perf_counter() - t) / n
        base = per if base is None else base
        rows.append({"request": name, "s/sample": per, "vs full": per / base})
    for motion in ("physics", "kinematic", "static"):
        from dataclasses import replace

        c = replace(cfg, motion=motion)
        ds = fs.datasets.BouncingThings(c, outputs=["depth"], seed=0, start=3000)
        ds.scene(0)
        t = time.perf_counter()
        for i in range(n):
            ds.scene(i + 1)
        per = (time.perf_counter() - t) / n
        rows.append({"request": f"scene only, motion={motion}", "s/sample": per, "vs full": per / base})
    return rows


def depth_vs_full(n: int, warm: int = 30) -> dict:
    """Process CPU and wall seconds per sample of the depth-only and the full stream at 256x192, T=2, the same
    indices alternated, after ``warm`` depth-only samples of other indices (asset BVHs, hulls and Newton's
    per-hull data cached, as in a long stream) and one sample of each stream (kernel load)."""
    import os

    import flowsynth as fs
    from flowsynth.plan import CORE_OUTPUTS

    streams = {
        "depth": fs.datasets.BouncingThings(fs.BouncingThingsConfig(width=256, height=192, num_frames=2),
                                            outputs=["depth"], seed=0, start=4000),
        "everything+direct rgb": fs.datasets.BouncingThings(
            fs.BouncingThingsConfig(width=256, height=192, num_frames=2, render_mode="direct"),
            outputs=list(CORE_OUTPUTS), seed=0, start=4000),
    }
    load0 = os.getloadavg()[0]
    for i in range(warm):
        streams["depth"].sample(5000 + i)
    for ds in streams.values():
        ds.sample(0)
    cpu = dict.fromkeys(streams, 0.0)
    wall = dict.fromkeys(streams, 0.0)
    for i in range(1, n + 1):
        for name, ds in (streams.items() if i % 2 else reversed(streams.items())):
            c, t = time.process_time(), time.perf_counter()
            ds.sample(i)
            cpu[name] += time.process_time() - c
            wall[name] += time.perf_counter() - t
    rows = [{"outputs": k, "cpu s/sample": cpu[k] / n, "wall s/sample": wall[k] / n} for k in streams]
    return {"rows": rows, "full/depth cpu": cpu["everything+direct rgb"] / cpu["depth"],
            "full/depth wall": wall["everything+direct rgb"] / wall["depth"], "samples": n, "warm": warm,
            "load_average": [load0, os.getloadavg()[0]]}


def memory_curve(cfg, n: int) -> list[dict]:
    import flowsynth as fs

    ds = fs.datasets.BouncingThings(cfg, outputs=["depth", "flow_fw", "occ_fw"], seed=0)
    out = []
    for k, _ in enumerate(ds):
        if k % max(1, n // 10) == 0:
            out.append({"samples": k, "max_rss_MiB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024})
        if k == n:
            break
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--samples", type=int, default=None, help="samples per measurement (default 24 quick, 64 full)")
    p.add_argument("--ratio", action="store_true", help="only depth-only vs full at 256x192 (process CPU time)")
    args = p.parse_args()
    if args.ratio:
        r = depth_vs_full(args.samples or 12)
        print(f"\nDepth-only vs full stream, 256x192, T=2, {r['samples']} samples each alternated, after "
              f"{r['warm']} warm-up samples; load average {r['load_average'][0]:.2f} -> {r['load_average'][1]:.2f}")
        print_table(r["rows"], ["outputs", "cpu s/sample", "wall s/sample"])
        print(f"full/depth: {r['full/depth cpu']:.3g} (process CPU), {r['full/depth wall']:.3g} (wall)")
        write_json("throughput_ratio", {"machine": machine_info(), **r})
        return
    import flowsynth as fs
    from flowsynth.plan import CORE_OUTPUTS

    OUTPUT_SETS["everything+direct rgb"] = list(CORE_OUTPUTS)
    W, H = (256, 192) if args.quick else (512, 384)
    n = args.samples or (24 if args.quick else 64)  # long enough that the prefetch buffer does not flatter workers
    rows = []
    for name, outs in OUTPUT_SETS.items():
        mode = "direct" if "rgb" in outs else "flat"
        cfg = fs.BouncingThingsConfig(width=W, height=H, num_frames=2, render_mode=mode)
        base = None
        for workers in (0, 1, 2):
            r = rate(cfg, outs, workers, n)
            base = r if base is None else base
            rows.append({"outputs": name, "workers": workers, "samples/s": r, "speed-up vs 0": r / base})
    print(f"\nThroughput at {W}x{H}, T=2 (physics motion)")
    print_table(rows, ["outputs", "workers", "samples/s", "speed-up vs 0"])
    skip_cfg = fs.BouncingThingsConfig(width=W, height=H, num_frames=2, render_mode="direct")
    skips = skip_savings(skip_cfg, 4 if args.quick else min(n, 12))
    print("\nWhat each skip saves (one process)")
    print_table(skips, ["request", "s/sample", "vs full"])
    mem_n = 200 if args.quick else 1000
    mem = memory_curve(fs.BouncingThingsConfig(width=64, height=48, num_frames=2, motion="kinematic"), mem_n)
    print(f"\nResident memory over a {mem_n}-sample stream (64x48)")
    print_table(mem, ["samples", "max_rss_MiB"])
    name = "throughput" if args.quick else "throughput_512x384"
    write_json(name, {"machine": machine_info(), "resolution": [W, H], "throughput": rows,
                              "skips": skips, "memory": mem})


if __name__ == "__main__":
    main()
