"""Streaming throughput: samples/s per output set and worker count, what each plan skip saves, memory.

    python benchmarks/speed/throughput.py [--quick]
    python benchmarks/speed/throughput.py --ratio [--samples 12]
    python benchmarks/speed/throughput.py --edge [--samples 8]
    python benchmarks/speed/throughput.py --lens [--quick] [--samples 8]

Writes benchmarks/results/throughput.json. Times are wall-clock on this machine (see "machine").

``--edge`` runs only the cost of silhouette anti-aliasing (``edge_spp``, default 4) on the full stream at
256x192 and 512x384, flat and direct rgb: the same indices with edge_spp 1 and the default, alternated in one
process; writes benchmarks/results/throughput_edge.json.

``--lens`` runs only the cost of a lens model: the stream of every output a lens camera allows (depth, flow
fw/bw, valid, occ, oof, instance, tracks, boxes, rgb; no stereo) with camera_model pinhole, brown_conrady and
kannala_brandt (fixed coefficients, and drawn per sample: "drawn") on the same indices, alternated in one
process, timed by process CPU time (and wall); 128x96 with --quick, else 256x192; writes
benchmarks/results/throughput_lens.json.

``--ratio`` runs only issue 13's "skipping pays" check (goal: depth-only >= 4x faster than the full stream at
256x192, T=2): depth-only and full samples of the same indices, alternated in one process after a warm-up
(caches of a long stream filled), timed by process CPU time (and wall), default threads; writes
benchmarks/results/throughput_ratio.json. With ``--pin`` (issue 39's goal 2: at least 3.5x on one pinned core) the
process first pins itself to one core, so each launch runs one thread; writes throughput_ratio_pinned.json. Not
pinned, process CPU time also counts the full sample's thread overhead, which flatters the ratio (3.37x unpinned
at a259332 on 2026-11-25; 2.66-2.71x pinned at 9912c1d on 2026-11-26, a core shared with a nice-19 job). Both
streams run with free flight (``physics.FREE_FLIGHT``, the default) and without it, alternated in the same run
(2.91x against 2.50x pinned at e2bb326: docs/decisions/0022-free-flight.md).
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common

from _common import machine_info, pin_single_core, print_table, write_json

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


def alternate(streams: dict, n: int, warm_stream: str | tuple, warm: int = 30) -> dict:
    """Process CPU and wall seconds per sample of each stream of ``streams`` (name -> BouncingThings), the same
    indices alternated (the order flips every index), after ``warm`` samples of other indices from
    ``streams[warm_stream]`` (asset BVHs, hulls and Newton's per-hull data and kernel variants cached, as in a long
    stream; each of several warm streams samples them) and one sample of each stream (kernel load)."""
    import os

    load0 = os.getloadavg()[0]
    for name in (warm_stream,) if isinstance(warm_stream, str) else warm_stream:
        for i in range(warm):
            streams[name].sample(5000 + i)
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
    return {"rows": rows, "cpu": cpu, "wall": wall, "samples": n, "warm": warm,
            "load_average": [load0, os.getloadavg()[0]]}


class _FreeFlight:
    """A stream sampled with ``physics.FREE_FLIGHT`` set to ``on`` for its own samples only; counts its clips and
    those that free flight kept (``physics.FREE_FLIGHT_COUNTS``)."""

    def __init__(self, ds, on: bool) -> None:
        self.ds, self.on, self.clips, self.free = ds, on, 0, 0

    def sample(self, i: int):
        from flowsynth.scene import physics

        old, kept = physics.FREE_FLIGHT, physics.FREE_FLIGHT_COUNTS["kept"]
        physics.FREE_FLIGHT = self.on
        try:
            self.clips += 1
            return self.ds.sample(i)
        finally:
            physics.FREE_FLIGHT = old
            self.free += physics.FREE_FLIGHT_COUNTS["kept"] - kept


def depth_vs_full(n: int) -> dict:
    """Issue 13's "skipping pays": the depth-only and the full stream at 256x192, T=2 (``alternate``), each with free
    flight (``physics.FREE_FLIGHT``, the default) and without it."""
    import flowsynth as fs
    from flowsynth.plan import CORE_OUTPUTS

    streams = {}
    for on in (True, False):
        tail = "" if on else ", no free flight"
        streams["depth" + tail] = _FreeFlight(fs.datasets.BouncingThings(
            fs.BouncingThingsConfig(width=256, height=192, num_frames=2), outputs=["depth"], seed=0, start=4000), on)
        streams["everything+direct rgb" + tail] = _FreeFlight(fs.datasets.BouncingThings(
            fs.BouncingThingsConfig(width=256, height=192, num_frames=2, render_mode="direct"),
            outputs=list(CORE_OUTPUTS), seed=0, start=4000), on)
    # warm-up without free flight meets Newton's kernel variants (built per new shape-type mix, ~0.25 s each) as the
    # full model always did; with it, the bodies-only scenes of a long stream are kept
    r = alternate(streams, n, ("depth, no free flight", "depth"), warm=40)
    for row in r["rows"]:
        st = streams[row["outputs"]]
        row["free flight"] = f"{st.free}/{st.clips}" if st.on else "off"  # warm-up clips included
    cpu, wall = r["cpu"], r["wall"]
    return {**r, "full/depth cpu": cpu["everything+direct rgb"] / cpu["depth"],
            "full/depth wall": wall["everything+direct rgb"] / wall["depth"],
            "full/depth cpu, no free flight": (cpu["everything+direct rgb, no free flight"]
                                               / cpu["depth, no free flight"]),
            "depth: free flight / none": cpu["depth"] / cpu["depth, no free flight"],
            "full: free flight / none": cpu["everything+direct rgb"] / cpu["everything+direct rgb, no free flight"]}


def edge_cost(n: int, size: tuple[int, int], mode: str) -> dict:
    """What silhouette anti-aliasing costs a whole sample: the full stream (every core output, ``mode`` rgb,
    T=2) with ``edge_spp`` 1 (off) and with the config's default, same indices alternated (``alternate``)."""
    import flowsynth as fs
    from flowsynth.plan import CORE_OUTPUTS

    default = fs.BouncingThingsConfig().edge_spp
    streams = {f"edge_spp {e}": fs.datasets.BouncingThings(
        fs.BouncingThingsConfig(width=size[0], height=size[1], num_frames=2, render_mode=mode, edge_spp=e),
        outputs=list(CORE_OUTPUTS), seed=0, start=4000) for e in (1, default)}
    r = alternate(streams, n, f"edge_spp {default}", warm=10)
    return {**r, "size": list(size), "mode": mode,
            "default/off cpu": r["cpu"][f"edge_spp {default}"] / r["cpu"]["edge_spp 1"]}


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


LENS_SETTINGS = {"pinhole": (), "brown_conrady": (-0.25, 0.05, -0.001, -0.001, 0.0),
                 "kannala_brandt": (0.05, -0.01, 0.002, -0.0005)}
# Rows whose coefficients are drawn per sample (camera_dist .. camera_dist_max): each sample unprojects its own
# pixel rays and finds its lens_limit, which a fixed lens does once (cached).
LENS_DRAWN = {"brown_conrady": ((-0.3, 0.0, -0.002, -0.002, 0.0), (-0.1, 0.1, 0.002, 0.002, 0.0)),
              "kannala_brandt": ((0.0, -0.02, 0.0, -0.001), (0.1, 0.0, 0.004, 0.0))}
LENS_OUTPUTS = ["depth", "instance", "flow_fw", "flow_bw", "valid_fw", "occ_fw", "oof_fw", "target_points",
                "occluded", "query_points", "box2d_amodal", "box2d_visible", "visible_pixels", "rgb"]


def lens_cost(n: int, size: tuple[int, int]) -> dict:
    """Process CPU and wall seconds per sample of LENS_OUTPUTS for each of LENS_SETTINGS, alternated per index."""
    import os

    import flowsynth as fs

    W, H = size
    streams = {}
    for model, dist in LENS_SETTINGS.items():
        cfg = fs.BouncingThingsConfig(width=W, height=H, num_frames=2, camera_model=model, camera_dist=dist)
        streams[model] = fs.datasets.BouncingThings(cfg, outputs=LENS_OUTPUTS, seed=0)
    for model, (lo, hi) in LENS_DRAWN.items():
        cfg = fs.BouncingThingsConfig(width=W, height=H, num_frames=2, camera_model=model, camera_dist=lo,
                                      camera_dist_max=hi)
        streams[model + " drawn"] = fs.datasets.BouncingThings(cfg, outputs=LENS_OUTPUTS, seed=0)
    for ds in streams.values():
        ds.sample(0)  # warm-up: kernels compiled, caches filled
    cpu = dict.fromkeys(streams, 0.0)
    wall = dict.fromkeys(streams, 0.0)
    load0 = os.getloadavg()
    for i in range(1, n + 1):
        for model, ds in streams.items():
            c, t = time.process_time(), time.perf_counter()
            ds.sample(i)
            cpu[model] += time.process_time() - c
            wall[model] += time.perf_counter() - t
    rows = [{"camera_model": m, "cpu s/sample": cpu[m] / n, "wall s/sample": wall[m] / n,
             "vs pinhole": cpu[m] / cpu["pinhole"]} for m in streams]
    return {"size": [W, H], "samples": n, "outputs": LENS_OUTPUTS, "settings": LENS_SETTINGS, "drawn": LENS_DRAWN,
            "rows": rows,
            "load_average": [load0[0], os.getloadavg()[0]]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--samples", type=int, default=None, help="samples per measurement (default 24 quick, 64 full)")
    p.add_argument("--ratio", action="store_true", help="only depth-only vs full at 256x192 (process CPU time)")
    p.add_argument("--pin", action="store_true", help="--ratio on one pinned core, one thread a launch (the ratio "
                   "per core); writes results/throughput_ratio_pinned.json")
    p.add_argument("--edge", action="store_true",
                   help="only the full stream with edge_spp 1 vs the default, 256x192 and 512x384 (process CPU time)")
    p.add_argument("--lens", action="store_true",
                   help="only pinhole vs brown_conrady vs kannala_brandt (fixed and drawn), process CPU time")
    args = p.parse_args()
    if args.lens:
        r = lens_cost(args.samples or (4 if args.quick else 16), (128, 96) if args.quick else (256, 192))
        print(f"\nLens models, {r['size'][0]}x{r['size'][1]}, T=2, {r['samples']} samples each alternated; load "
              f"average {r['load_average'][0]:.2f} -> {r['load_average'][1]:.2f}")
        print_table(r["rows"], ["camera_model", "cpu s/sample", "wall s/sample", "vs pinhole"])
        write_json("throughput_lens" + ("_quick" if args.quick else ""), {"machine": machine_info(), **r})
        return
    if args.edge:
        runs = [edge_cost(args.samples or 8, size, mode) for size in ((256, 192), (512, 384))
                for mode in ("flat", "direct")]
        rows = [{"size": f"{r['size'][0]}x{r['size'][1]}", "rgb": r["mode"], **row,
                 "vs edge_spp 1": row["cpu s/sample"] / r["rows"][0]["cpu s/sample"]}
                for r in runs for row in r["rows"]]
        print(f"\nFull stream (every core output, T=2), edge_spp 1 vs the default, {runs[0]['samples']} samples each "
              f"alternated; load average {runs[0]['load_average'][0]:.2f} -> {runs[-1]['load_average'][1]:.2f}")
        print_table(rows, ["size", "rgb", "outputs", "cpu s/sample", "wall s/sample", "vs edge_spp 1"])
        write_json("throughput_edge", {"machine": machine_info(), "runs": runs, "rows": rows})
        return
    if args.ratio:
        pinning = pin_single_core() if args.pin else None
        r = depth_vs_full(args.samples or 12)
        print(f"\nDepth-only vs full stream, 256x192, T=2, {r['samples']} samples each alternated, after "
              f"{r['warm']} warm-up samples; load average {r['load_average'][0]:.2f} -> {r['load_average'][1]:.2f}")
        print_table(r["rows"], ["outputs", "cpu s/sample", "wall s/sample", "free flight"])
        print(f"full/depth: {r['full/depth cpu']:.3g} (process CPU), {r['full/depth wall']:.3g} (wall); without free "
              f"flight {r['full/depth cpu, no free flight']:.3g} (process CPU). Free flight / none, process CPU: "
              f"depth {r['depth: free flight / none']:.3f}, full {r['full: free flight / none']:.3f}")
        write_json("throughput_ratio" + ("_pinned" if args.pin else ""), {"machine": machine_info(),
                                                                         "pinning": pinning, **r})
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
