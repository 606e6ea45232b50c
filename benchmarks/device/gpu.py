"""CPU against GPU in one run: samples/s of the default scene at 512x384, 2 frames.

    python benchmarks/device/gpu.py [--quick] [--cpu-samples N] [--gpu-samples M] [--workers K] [--batch B]

Two workloads, each a ``fs.datasets.BouncingThings(cfg, outputs, seed=0, device=...)`` timed through ``.sample(i)``
on the CPU ("cpu", every core the process may use) and on Warp's "cuda" where Warp finds one (else that column says
"no CUDA" and the script still exits 0):

- ``depth+flow+occ``: depth, flow_fw, occ_fw of ``BouncingThingsConfig(width=512, height=384, num_frames=2)`` (the
  default scene otherwise: flat shading, 4-12 objects, physics);
- ``+direct rgb``: the same outputs and rgb, with ``render_mode="direct"``.

How it is timed. Every scene the run will render is simulated once first (``ds.scene(i)``, on the host whatever the
device), so Newton's kernels and its per-shape-mix variants are built before any clock runs; the median of those
scene times is reported as ``scene_s``, the host's physics share of a sample. Then, per workload and device: warm-up
samples (the first on CUDA compiles or loads every render kernel: ``first_sample_s``), then timed samples
(``samples_per_s`` = samples / their summed wall time; ``median_s``; every time in ``times_s``): one scene per
``sample(i)`` call.

Batched rows (issue 52, item 3; ``--batch B``, default 32, 0 skips): ``render_batch of B, scenes ready`` times
``fs.render_batch`` alone on batches of scenes simulated before the clock (the device's ceiling; on CUDA one more batch
runs under Warp's activity timing: the GPU's busy share and its top kernels), and ``batches of B, K scene workers``
times ``fs.datasets.DeviceBatches`` end to end (scenes sampled and simulated by K CPU processes while the device
renders; K + 1 batches untimed, then at least 2 K timed, so the workers must keep up). Each batch is read back once
(a sum), so the clock waits for the device.

Where the time goes: one CUDA sample (a CPU sample where there is no CUDA) of each workload under cProfile (the
host functions with the most cumulative and the most own time, and own time summed per file), and one more under
Warp's CUDA activity timing (``wp.timing_begin``: the GPU's busy time per kernel and copy, against the sample's
wall time).

``--workers K`` (default 8; 0 skips; --quick skips) also streams each workload through a DataLoader of K spawned
workers, on the CPU (one thread each) and on CUDA (K processes sharing the GPU), after the rest: 2 K samples to warm
up (``first_sample_s``: start-up, kernel loads, and Newton's variants, which each worker builds anew), 4 K timed.

Writes benchmarks/results/gpu.json after every measurement (``_quick`` with --quick, ``_nocuda`` where Warp finds
no CUDA device), with the device, the driver (``nvidia-smi``), torch, warp, newton and Python versions, and the load
average before each measurement (other jobs on the machine show there).
"""

from __future__ import annotations

import argparse
import functools
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common

from _common import machine_info, print_table, write_json

SIZE = (512, 384)
FRAMES = 2
WORKLOADS = {
    "depth+flow+occ": (["depth", "flow_fw", "occ_fw"], {}),
    "+direct rgb": (["depth", "flow_fw", "occ_fw", "rgb"], {"render_mode": "direct"}),
}
GOALS = {"depth+flow+occ": 100.0, "+direct rgb": 30.0}
"""Issue 47's goals [samples/s] on an H100."""


def config(**overrides):
    import flowsynth as fs

    return fs.BouncingThingsConfig(width=SIZE[0], height=SIZE[1], num_frames=FRAMES, **overrides)


def dataset(name: str, device: str, length: int | None = None):
    import flowsynth as fs

    outputs, overrides = WORKLOADS[name]
    return fs.datasets.BouncingThings(config(**overrides), outputs=outputs, seed=0, device=device, length=length)


def cuda_devices() -> int:
    """CUDA devices Warp finds (0 without a driver)."""
    from flowsynth.kernels import wp_runtime

    return wp_runtime().get_cuda_device_count()


def nvidia_smi() -> dict:
    """``nvidia-smi``'s query of name, driver and memory, and its full text; None where it is not installed."""
    exe = shutil.which("nvidia-smi")
    if exe is None:
        return {"query": None, "text": None}
    out = {}
    for key, args in (("query", ["--query-gpu=name,driver_version,memory.total,clocks.max.sm,pstate",
                                 "--format=csv,noheader"]), ("text", [])):
        try:
            r = subprocess.run([exe, *args], capture_output=True, text=True, timeout=30, check=False)
            out[key] = (r.stdout + r.stderr).strip()
        except (OSError, subprocess.SubprocessError) as e:
            out[key] = f"failed: {e}"
    return out


def versions(has_cuda: bool) -> dict:
    import torch

    from flowsynth.kernels import wp_runtime

    wp = wp_runtime()
    info = machine_info(extra_packages=("kornia", "kornia_rs", "OpenEXR"))
    info.update({"torch_version": torch.__version__, "torch_cuda": torch.version.cuda, "warp_version": wp.__version__,
                 "warp_cuda_toolkit": _ver(wp.get_cuda_toolkit_version()),
                 "warp_cuda_driver": _ver(wp.get_cuda_driver_version()) if has_cuda else None,
                 "nvidia_smi": nvidia_smi(), "cuda_device": None})
    if has_cuda:
        d = wp.get_device("cuda")
        info["cuda_device"] = {"alias": d.alias, "name": d.name, "arch": d.arch,
                               "sm_count": getattr(d, "sm_count", None),
                               "memory_gib": round(getattr(d, "total_memory", 0) / 2**30, 1)}
    return info


def _ver(v) -> str | None:
    if v is None:
        return None
    return ".".join(str(x) for x in v) if isinstance(v, (tuple, list)) else str(v)


def presimulate(indices) -> dict:
    """Simulate every scene the run renders, once (physics on the host; builds Newton's kernels and variants)."""
    import flowsynth as fs

    ds = fs.datasets.BouncingThings(config(), outputs=["depth"], seed=0)  # the scene does not depend on the outputs
    times = []
    for i in indices:
        t = time.perf_counter()
        ds.scene(i)
        times.append(time.perf_counter() - t)
    return {"scenes": len(times), "scene_s": statistics.median(times), "first_s": times[0], "max_s": max(times),
            "total_s": sum(times)}


def time_samples(name: str, device: str, warm: int, n: int) -> dict:
    """Warm-up samples 0..warm-1 (the first's time kept), then samples warm..warm+n-1 timed one by one."""
    ds = dataset(name, device)
    load = os.getloadavg()[0]
    first = None
    for i in range(warm):
        t = time.perf_counter()
        ds.sample(i)
        first = time.perf_counter() - t if first is None else first
    times = []
    for i in range(warm, warm + n):
        t = time.perf_counter()
        ds.sample(i)
        times.append(time.perf_counter() - t)
    return {"workload": name, "device": device, "mode": "1 process", "samples": n, "warm": warm,
            "first_sample_s": first, "median_s": statistics.median(times), "samples_per_s": n / sum(times),
            "times_s": times, "load_average": [load, os.getloadavg()[0]]}


def time_workers(name: str, device: str, workers: int, n: int) -> dict:
    """A DataLoader of ``workers`` spawned workers over samples 0..2 workers+n-1; after two samples per worker
    (each worker's start-up, kernel load and first Newton variants), the other ``n`` timed together. The epoch is
    finite so that every worker ends its stream itself (a worker stopped in the middle of a sample aborts noisily)."""
    from torch.utils.data import DataLoader

    ds = dataset(name, device, length=2 * workers + n)
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    loader = DataLoader(ds, batch_size=None, num_workers=workers, multiprocessing_context="spawn")
    it = iter(loader)
    for _ in range(2 * workers):
        next(it)
    start_s = time.perf_counter() - t0
    t = time.perf_counter()
    got = sum(1 for _ in it)
    dt = time.perf_counter() - t
    assert got == n, (got, n)
    del it, loader
    return {"workload": name, "device": device, "mode": f"{workers} workers", "samples": n, "warm": 2 * workers,
            "first_sample_s": start_s, "median_s": None, "samples_per_s": n / dt, "times_s": [dt],
            "load_average": [load, os.getloadavg()[0]]}


def time_batches(name: str, device: str, batch: int, workers: int, n: int) -> dict:
    """``fs.datasets.DeviceBatches`` end to end: scenes from ``workers`` CPU processes (each makes a whole batch's
    scenes), every per-pixel stage once per batch of ``batch`` on ``device``. The first ``workers`` + 1 batches are
    not timed (start-up, kernel loads, and the first wave, which the workers make all at once), then ``max(n, 2
    workers)`` batches timed together, so the workers must keep up; each batch's tensors are read back to the host
    once (``.sum().item()``), so the clock waits for the device."""
    import flowsynth as fs

    warm, n = workers + 1, max(n, 2 * workers)
    outputs, overrides = WORKLOADS[name]
    ds = fs.datasets.DeviceBatches(config(**overrides), outputs, batch, workers, device=device, seed=0,
                                   length=(warm + n) * batch)
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    it = iter(ds)
    for _ in range(warm):
        next(it)["depth"].sum().item()
    start_s = time.perf_counter() - t0
    t = time.perf_counter()
    got = sum(int(b["depth"].sum().item() >= 0) for b in it)
    dt = time.perf_counter() - t
    assert got == n, (got, n)
    return {"workload": name, "device": device, "mode": f"batches of {batch}, {workers} scene workers",
            "samples": n * batch, "warm": warm * batch, "first_sample_s": start_s, "median_s": None,
            "samples_per_s": n * batch / dt, "times_s": [dt], "load_average": [load, os.getloadavg()[0]]}


@functools.cache
def _scene_batches(batch: int, count: int) -> list:
    """``count`` batches of ``batch`` scenes of seed 0, simulated once for every workload and device (the scene does
    not depend on the outputs, the render mode or the device)."""
    import flowsynth as fs

    ds = fs.datasets.BouncingThings(config(), outputs=["depth"], seed=0)
    return [[ds.scene(b * batch + k) for k in range(batch)] for b in range(count)]


def batch_render(name: str, device: str, batch: int, n: int, activity: bool = False) -> dict:
    """``fs.render_batch`` alone on ``n`` batches of scenes simulated before the clock (the device's ceiling, no
    physics); with ``activity`` the last batch also runs under Warp's CUDA activity timing (the GPU's busy share)."""
    import flowsynth as fs

    from flowsynth.kernels import wp_runtime

    outputs, overrides = WORKLOADS[name]
    batches = _scene_batches(batch, n + 1)
    fs.render_batch(batches[0], outputs, device=device, **overrides)["depth"].sum().item()  # warm: kernels
    times = []
    for scenes in batches[1:]:
        t = time.perf_counter()
        fs.render_batch(scenes, outputs, device=device, **overrides)["depth"].sum().item()
        times.append(time.perf_counter() - t)
    row = {"workload": name, "device": device, "mode": f"render_batch of {batch}, scenes ready",
           "samples": n * batch, "warm": batch, "first_sample_s": None, "median_s": statistics.median(times) / batch,
           "samples_per_s": n * batch / sum(times), "times_s": times}
    if activity:
        wp = wp_runtime()
        wp.timing_begin(wp.TIMING_ALL)
        try:
            t = time.perf_counter()
            fs.render_batch(batches[-1], outputs, device=device, **overrides)["depth"].sum().item()
            wall = time.perf_counter() - t
        finally:
            results = wp.timing_end()
        busy = sum(r.elapsed for r in results) / 1e3
        by_name: dict[str, float] = {}
        for r in results:
            by_name[r.name] = by_name.get(r.name, 0.0) + r.elapsed
        row["gpu_activity"] = {"wall_s": wall, "gpu_busy_s": busy, "gpu_busy_fraction": busy / wall,
                               "top": sorted(({"activity": k, "ms": v} for k, v in by_name.items()),
                                             key=lambda r: -r["ms"])[:15]}
    return row


def _short(path: str) -> str:
    for marker in ("/site-packages/", "/flowsynth/", "/benchmarks/"):
        if marker in path:
            return marker.strip("/") + "/" + path.split(marker, 1)[1] if marker != "/site-packages/" else \
                path.split(marker, 1)[1]
    return path.rsplit("/", 1)[-1] if path.startswith("/") else path


def profile_sample(name: str, device: str, index: int, top: int = 25) -> dict:
    """One warmed-up sample under cProfile: the host functions by cumulative and by own time, own time per file."""
    import cProfile
    import pstats

    ds = dataset(name, device)
    ds.sample(index)  # warm: this stream's plan and kernels
    prof = cProfile.Profile()
    t = time.perf_counter()
    prof.enable()
    ds.sample(index + 1)
    prof.disable()
    wall = time.perf_counter() - t
    st = pstats.Stats(prof)
    rows = []
    per_file: dict[str, float] = {}
    for (file, line, func), (_cc, nc, tt, ct, _callers) in st.stats.items():
        where = f"{_short(file)}:{line}({func})"
        rows.append({"function": where, "calls": nc, "own_s": tt, "cumulative_s": ct})
        key = _short(file)
        per_file[key] = per_file.get(key, 0.0) + tt
    by_cum = sorted(rows, key=lambda r: -r["cumulative_s"])[:top]
    by_own = sorted(rows, key=lambda r: -r["own_s"])[:top]
    files = sorted(({"file": k, "own_s": v} for k, v in per_file.items()), key=lambda r: -r["own_s"])[:top]
    return {"workload": name, "device": device, "index": index + 1, "wall_s_under_profiler": wall,
            "total_own_s": st.total_tt, "top_cumulative": by_cum, "top_own": by_own, "own_by_file": files}


def gpu_activity(name: str, index: int) -> dict:
    """One warmed-up CUDA sample under Warp's activity timing: GPU busy time per activity against the wall time."""
    from flowsynth.kernels import wp_runtime

    wp = wp_runtime()
    ds = dataset(name, "cuda")
    ds.sample(index)
    try:
        wp.timing_begin(wp.TIMING_ALL)
    except Exception as e:  # a Warp without activity timing must not cost the rest of the run
        return {"workload": name, "error": f"timing_begin: {type(e).__name__}: {e}"}
    try:
        t = time.perf_counter()
        ds.sample(index + 1)
        wall = time.perf_counter() - t
    finally:
        results = wp.timing_end()
    by_name: dict[str, list] = {}
    for r in results:
        entry = by_name.setdefault(r.name, [0, 0.0])
        entry[0] += 1
        entry[1] += r.elapsed
    busy_ms = sum(v[1] for v in by_name.values())
    top = sorted(({"activity": k, "count": v[0], "ms": v[1]} for k, v in by_name.items()), key=lambda r: -r["ms"])
    return {"workload": name, "index": index + 1, "wall_s": wall, "gpu_busy_ms": busy_ms,
            "gpu_busy_fraction": busy_ms / 1e3 / wall, "activities": len(results), "top": top[:25]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="few samples, no workers (a smoke run)")
    p.add_argument("--cpu-samples", type=int, default=None, help="timed CPU samples per workload (default 4; 2 quick)")
    p.add_argument("--gpu-samples", type=int, default=None,
                   help="timed CUDA samples per workload (default 24; 4 quick)")
    p.add_argument("--workers", type=int, default=None, help="DataLoader workers for the streamed rows (default 8; "
                   "0 skips; --quick: 0)")
    p.add_argument("--no-cpu", action="store_true", help="skip the CPU rows (CUDA only)")
    p.add_argument("--batch", type=int, default=None, help="samples per batch of the batched rows (default 32; "
                   "--quick 2; 0 skips them)")
    p.add_argument("--batches", type=int, default=None, help="timed batches per batched row (default 8; --quick 2)")
    p.add_argument("--scene-workers", type=int, default=None, help="CPU processes making the batched rows' scenes "
                   "(default: the cores less one; --quick 1)")
    args = p.parse_args()
    for key in ("cpu_samples", "gpu_samples", "workers", "batch", "batches", "scene_workers"):
        if getattr(args, key) is not None and getattr(args, key) < 0:
            p.error(f"--{key.replace('_', '-')} {getattr(args, key)}: must be at least 0")
    batch = args.batch if args.batch is not None else (2 if args.quick else 32)
    n_batches = args.batches if args.batches is not None else (2 if args.quick else 8)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    scene_workers = args.scene_workers if args.scene_workers is not None else (1 if args.quick else max(cores - 1, 1))
    n_cpu = args.cpu_samples if args.cpu_samples is not None else (2 if args.quick else 4)
    n_gpu = args.gpu_samples if args.gpu_samples is not None else (4 if args.quick else 24)
    workers = args.workers if args.workers is not None else (0 if args.quick else 8)
    warm_cpu, warm_gpu = 1, 2

    has_cuda = cuda_devices() > 0
    name = "gpu" + ("_quick" if args.quick else "") + ("" if has_cuda else "_nocuda")
    result: dict = {"size": list(SIZE), "num_frames": FRAMES, "seed": 0,
                    "workloads": {k: {"outputs": v[0], **v[1]} for k, v in WORKLOADS.items()}, "goals": GOALS,
                    "batching": "rows '1 process' and 'N workers': one scene per sample() call; rows 'render_batch' "
                                "and 'batches of B': fs.render_batch / fs.datasets.DeviceBatches, B scenes a launch",
                    "cuda": has_cuda, "machine": versions(has_cuda), "rows": [], "profile": [], "gpu_activity": []}
    cuda_note = None if has_cuda else "no CUDA: Warp finds no CUDA device"
    result["note"] = cuda_note

    def save():
        return write_json(name, result)

    # every index rendered below: timed samples, the profiled and activity-timed samples (two each, one to warm),
    # and the streamed rows' 6 x workers
    last_cpu, last_gpu = warm_cpu + n_cpu + 2, (warm_gpu + n_gpu + 4) if has_cuda else 0
    indices = range(max(last_cpu, last_gpu, 6 * workers))
    t = time.perf_counter()
    result["presimulate"] = presimulate(indices)
    print(f"pre-simulated {len(indices)} scenes in {time.perf_counter() - t:.1f} s "
          f"(median {result['presimulate']['scene_s'] * 1e3:.1f} ms per scene)", flush=True)
    save()

    devices = ([] if args.no_cpu else [("cpu", warm_cpu, n_cpu)]) + ([("cuda", warm_gpu, n_gpu)] if has_cuda else [])
    for wl in WORKLOADS:
        for device, warm, n in devices:
            t = time.perf_counter()
            row = time_samples(wl, device, warm, n)
            result["rows"].append(row)
            save()
            print(f"{wl} on {device}: {row['samples_per_s']:.2f} samples/s (median {row['median_s'] * 1e3:.0f} ms; "
                  f"first {row['first_sample_s']:.1f} s; {time.perf_counter() - t:.1f} s in all)", flush=True)
        if not has_cuda:
            result["rows"].append({"workload": wl, "device": "cuda", "mode": "1 process", "note": cuda_note})

    prof_device = "cuda" if has_cuda else "cpu"
    for wl in WORKLOADS:
        t = time.perf_counter()
        prof = profile_sample(wl, prof_device, index=warm_gpu + n_gpu if has_cuda else warm_cpu + n_cpu)
        result["profile"].append(prof)
        save()
        print(f"\nprofile of one {prof_device} sample, {wl} ({prof['wall_s_under_profiler']:.3f} s under cProfile, "
              f"{time.perf_counter() - t:.1f} s with its warm-up); top host functions by cumulative time:")
        print_table([{"function": r["function"][-90:], "calls": r["calls"], "cumulative s": r["cumulative_s"],
                      "own s": r["own_s"]} for r in prof["top_cumulative"][:15]],
                    ["function", "calls", "cumulative s", "own s"])
        print("own time by file:")
        print_table([{"file": r["file"][-90:], "own s": r["own_s"]} for r in prof["own_by_file"][:10]],
                    ["file", "own s"])
        if has_cuda:
            act = gpu_activity(wl, index=warm_gpu + n_gpu + 2)
            result["gpu_activity"].append(act)
            save()
            if "error" in act:
                print(f"GPU activity timing failed: {act['error']}")
            else:
                print(f"GPU busy {act['gpu_busy_ms']:.1f} ms of a {act['wall_s'] * 1e3:.0f} ms sample "
                      f"({100 * act['gpu_busy_fraction']:.1f}%); top activities:")
                print_table([{"activity": r["activity"][-70:], "count": r["count"], "ms": r["ms"]}
                             for r in act["top"][:10]], ["activity", "count", "ms"])
        sys.stdout.flush()

    if batch > 0:  # issue 52, item 3: every per-pixel stage once per batch on the device
        for wl in WORKLOADS:
            for device in ["cpu"] * (not args.no_cpu) + ["cuda"] * has_cuda:
                for row in (batch_render(wl, device, batch, n_batches, activity=device == "cuda"),
                            time_batches(wl, device, batch, scene_workers, n_batches)):
                    result["rows"].append(row)
                    save()
                    busy = row.get("gpu_activity", {}).get("gpu_busy_fraction")
                    print(f"{wl} on {device}, {row['mode']}: {row['samples_per_s']:.2f} samples/s"
                          + (f" (GPU busy {100 * busy:.0f}%)" if busy is not None else ""), flush=True)

    if workers > 0:
        for wl in WORKLOADS:
            for device in ["cpu"] * (not args.no_cpu) + ["cuda"] * has_cuda:
                t = time.perf_counter()
                row = time_workers(wl, device, workers, 4 * workers)
                result["rows"].append(row)
                save()
                print(f"{wl} on {device}, {workers} workers: {row['samples_per_s']:.2f} samples/s "
                      f"(start-up {row['first_sample_s']:.1f} s; {time.perf_counter() - t:.1f} s in all)", flush=True)

    print(f"\n{SIZE[0]}x{SIZE[1]}, T={FRAMES}, seed 0; {result['machine']['cpus_allowed']} CPUs allowed; "
          f"CUDA: {result['machine']['cuda_device'] or 'none'}")
    table = [{"workload": r["workload"], "device": r["device"], "mode": r["mode"],
              "samples/s": r.get("samples_per_s", "no CUDA"),
              "median ms": r["median_s"] * 1e3 if r.get("median_s") else None,
              "first s": r.get("first_sample_s"), "n": r.get("samples"),
              "goal /s": GOALS[r["workload"]] if r["device"] == "cuda" else None} for r in result["rows"]]
    print_table(table, ["workload", "device", "mode", "samples/s", "median ms", "first s", "n", "goal /s"])
    path = save()
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
