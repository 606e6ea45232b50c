"""Export on the same CPUs: local worker processes against Ray actors, end to end, and what one node pays.

    python benchmarks/speed/ray_export.py [--quick] [--lengths 16,48] [--rounds 2] [--cold]

What a user runs, each in a fresh Python process, timed from its start to its exit: ``export_dataset(workers=2)``
(fork, one thread each) and ``ray.init(num_cpus=2)`` + ``export_dataset(engine="ray", workers=2)`` (2 actors),
for every run length of ``--lengths``, alternating engines (load from other processes hits both alike).
Per run: wall time, seconds to the first finished sample, the steady rate between the first and the last
finished sample (the sample folders' mtimes), and the start-up ``wall - samples / steady rate``.
Ray's overhead at N samples = 1 - local samples/s / Ray samples/s, i.e. 1 - local wall / Ray wall:
measured (fastest round of each), and modelled per engine as ``wall(N) = start-up + N / steady rate``
(medians over the engine's runs, robust to a load burst in one run), which gives the run length from
which the overhead stays <= 15%; also with one rate for both engines (same processes, same work).

Also, for docs/distributed.md's 100-node plan, on one thread: scene setup (sampling + physics) against
rendering per sample, a fresh process's first sample with a warm Warp kernel cache (with ``--cold``
also with an empty one: a full kernel compile, ~5 min here), bytes written per sample, and whether the
runs compiled any kernel (new entries in the Warp cache: the actors must load the driver's cache).

Needs the ray extra (``bash scripts/setup.sh --ray``). Writes benchmarks/results/ray_export.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # benchmarks/: _common

from _common import EXPORT_OUTPUTS, EXPORT_SAMPLE, Timer, machine_info, print_table, write_json

OUTPUTS = list(EXPORT_OUTPUTS)
_ONE_SAMPLE = """
import json, sys, time
t = time.perf_counter()
import flowsynth as fs
cfg = fs.BouncingThingsConfig(**json.loads(sys.argv[1]))
fs.datasets.BouncingThings(cfg, outputs=json.loads(sys.argv[2]), threads=1).sample(0)
print(time.perf_counter() - t)
"""
_EXPORT = """
import json, sys, time
t = time.perf_counter()
import flowsynth as fs
from flowsynth.export import export_dataset
a = json.loads(sys.argv[1])
out = {"import_s": time.perf_counter() - t}
if a["engine"] == "ray":
    import ray
    t = time.perf_counter()
    ray.init(num_cpus=a["cpus"], include_dashboard=False, log_to_driver=False)
    out["ray_init_s"] = time.perf_counter() - t
t = time.perf_counter()
export_dataset(fs.BouncingThingsConfig(**a["cfg"]), a["out"], a["num"], outputs=a["outputs"], workers=a["cpus"],
               engine=a["engine"], progress=False)
out["export_s"] = time.perf_counter() - t
print(json.dumps(out))
"""
CPUS = 2


def _env(cache: Path) -> dict:
    """This checkout first on the path, for the driver and (through the raylet it starts) every actor."""
    return dict(os.environ, WARP_CACHE_PATH=str(cache), PYTHONPATH=str(HERE.parents[1]))


def _done_times(root: Path) -> list[float]:
    """Finish time of every sample (a folder's mtime: its last file), sorted."""
    return sorted(max(f.stat().st_mtime for f in d.iterdir()) for d in root.iterdir() if d.name.isdigit())


def _run(engine: str, num: int, cfg_dict: dict, out: Path, cache: Path) -> dict:
    """One export in a fresh process, as a user runs it; wall time from spawn to exit."""
    args = {"engine": engine, "num": num, "cfg": cfg_dict, "outputs": OUTPUTS, "out": str(out), "cpus": CPUS}
    before = _cache_entries(cache)
    t0 = time.time()
    r = subprocess.run([sys.executable, "-c", _EXPORT, json.dumps(args)], capture_output=True, text=True,
                       env=_env(cache), check=False)
    wall = time.time() - t0
    if r.returncode != 0:
        raise RuntimeError(f"{engine} export failed:\n{r.stderr[-3000:]}")
    child = json.loads(r.stdout.strip().splitlines()[-1])
    done = _done_times(out)
    steady = (len(done) - 1) / (done[-1] - done[0]) if len(done) > 1 else float("nan")
    return {"engine": engine, "samples": num, "wall_s": wall, "samples/s": num / wall,
            "first sample s": done[0] - t0, "steady samples/s": steady, "start-up s": wall - num / steady,
            "import s": child["import_s"], "ray.init s": child.get("ray_init_s", 0.0),
            "kernels compiled": len({e.split("/")[1] for e in _cache_entries(cache) - before if "/" in e})}


def _first_sample_s(cfg_dict: dict, cache: Path) -> float:
    """Seconds from a fresh process's start to its first sample (imports and kernels included)."""
    r = subprocess.run([sys.executable, "-c", _ONE_SAMPLE, json.dumps(cfg_dict), json.dumps(OUTPUTS)],
                       capture_output=True, text=True, env=_env(cache), check=True)
    return float(r.stdout.strip().splitlines()[-1])


def _cache_entries(cache: Path) -> set[str]:
    return {str(p.relative_to(cache)) for p in cache.rglob("*")} if cache.exists() else set()


def _mean(rows: list[dict], key: str, **match) -> float:
    vals = [r[key] for r in rows if all(r[k] == v for k, v in match.items())]
    return sum(vals) / len(vals)


def _median(rows: list[dict], key: str, **match) -> float:
    return statistics.median(r[key] for r in rows if all(r[k] == v for k, v in match.items()))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="256x192 instead of 512x384")
    p.add_argument("--lengths", default=None, help="run lengths in samples [default 16,64; 16,48 at 512x384]")
    p.add_argument("--rounds", type=int, default=2, help="rounds over every length and engine [default 2]")
    p.add_argument("--cold", action="store_true", help="also time a first sample with an empty kernel cache")
    args = p.parse_args()
    try:
        import ray  # noqa: F401
    except ImportError:
        print("skipped: benchmarks/speed/ray_export.py needs Ray (bash scripts/setup.sh --ray)")
        return

    W, H = (256, 192) if args.quick else (512, 384)
    lengths = [int(x) for x in (args.lengths or ("16,64" if args.quick else "16,48")).split(",")]
    cfg_dict = dict(width=W, height=H, **EXPORT_SAMPLE)
    load = [os.getloadavg()]
    tmp = Path(tempfile.mkdtemp(prefix="fs-ray-bench-"))
    # a private copy of the kernel cache: what these runs compile is then theirs, not another process's
    cache = tmp / "warp-cache"
    shared = Path(os.environ.get("WARP_CACHE_PATH", HERE.parents[1] / ".cache" / "warp"))
    try:
        if shared.is_dir():
            shutil.copytree(shared, cache, ignore=shutil.ignore_patterns("*_p[0-9]*_t[0-9]*"))
        _run("local", 4, cfg_dict, tmp / "warm", cache)  # the Warp kernel cache is warm for every run
        cache_before = _cache_entries(cache)
        rows = []
        order = [(n, e) for n in lengths for e in ("local", "ray")]
        for r in range(args.rounds):
            for k, (num, engine) in enumerate(order):
                if (r + k // 2) % 2:  # alternate which engine goes first
                    engine = "ray" if engine == "local" else "local"
                rows.append(dict(_run(engine, num, cfg_dict, tmp / f"{engine}{num}-{r}", cache), round=r))
                load.append(os.getloadavg())
        new_kernels = sorted(_cache_entries(cache) - cache_before)
        bytes_per_sample = sum(f.stat().st_size for f in (tmp / f"local{lengths[0]}-0").glob("[0-9]*/*")) / lengths[0]

        import flowsynth as fs
        from flowsynth.datasets import BouncingThings

        ds = BouncingThings(fs.BouncingThingsConfig(**cfg_dict), outputs=OUTPUTS, threads=1)
        ds.sample(0)
        setup, total = [], []
        for i in range(1, 5):
            with Timer() as tm:
                ds.scene(i)
            setup.append(tm.wall_s)
            with Timer() as tm:
                ds.sample(i)
            total.append(tm.wall_s)
        warm = _first_sample_s(cfg_dict, cache)
        cold = _first_sample_s(cfg_dict, tmp / "empty-warp-cache") if args.cold else None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    # Per engine, medians over its runs (robust to a load burst from other processes in one run) of each
    # run's own start-up and steady rate; wall(N) = start-up + N / rate.
    model = {e: (_median(rows, "start-up s", engine=e), _median(rows, "steady samples/s", engine=e))
             for e in ("local", "ray")}

    def wall(e: str, n: float, rate: float | None = None) -> float:
        return model[e][0] + n / (rate or model[e][1])

    def break_even(s_l: float, s_r: float) -> float | None:
        """Samples from which overhead(N) <= 15%, i.e. wall_ray(N) <= wall_local(N) / 0.85 (None: never)."""
        (f_l, _), (f_r, _) = model["local"], model["ray"]
        denom = 1 / (0.85 * s_l) - 1 / s_r
        return max((f_r - f_l / 0.85) / denom, 0.0) if denom > 0 else None

    # both engines run the same processes doing the same work: their rates differ only by noise, so
    # also the break-even with one rate (the median over every run) for both
    same = _median(rows, "steady samples/s")
    even = {"measured rates": break_even(model["local"][1], model["ray"][1]), "equal rates": break_even(same, same)}
    fastest = {(e, n): min(r["wall_s"] for r in rows if r["engine"] == e and r["samples"] == n)
               for e in ("local", "ray") for n in lengths}
    table = []
    for n in sorted({*lengths, 256, 1024, 4096} | {round(v) for v in even.values() if v}):
        table.append({"samples": n, "local wall s": wall("local", n), "ray wall s": wall("ray", n),
                      "overhead (model)": 1 - wall("local", n) / wall("ray", n),
                      "overhead (equal rates)": 1 - wall("local", n, same) / wall("ray", n, same),
                      "overhead (measured)": 1 - fastest["local", n] / fastest["ray", n] if n in lengths else ""})
    per_sample = sum(total) / len(total)
    node = {"scene setup s/sample (1 thread)": sum(setup) / len(setup),
            "sample s (1 thread, setup included)": per_sample,
            "first sample, warm kernel cache s": warm,
            "ray.init(num_cpus=2) s": _mean(rows, "ray.init s", engine="ray"),
            "Warp modules compiled during the timed runs": len({e.split("/")[1] for e in new_kernels if "/" in e}),
            "bytes/sample": bytes_per_sample}
    if cold is not None:
        node.update({"first sample, empty kernel cache s": cold, "kernel compile s": cold - warm})
    print(f"Export at {W}x{H}, T=2, render_mode=direct, outputs={','.join(OUTPUTS)}; fresh process per run; "
          f"{CPUS} CPUs; {args.rounds} round(s); load average (1 min) {load[0][0]:.1f} before, "
          f"{max(x[0] for x in load):.1f} max")
    print_table(rows, ["engine", "round", "samples", "wall_s", "samples/s", "first sample s", "steady samples/s",
                       "start-up s", "import s", "ray.init s", "kernels compiled"])
    print("\nPer engine, medians over its runs: wall(N) = start-up + N / steady rate")
    print_table([{"engine": e, "start-up s": model[e][0], "samples/s": model[e][1]} for e in model],
                ["engine", "start-up s", "samples/s"])
    print("\nRay overhead by run length (1 - local wall / ray wall; goal <= 0.15; measured: fastest round); "
          "overhead <= 0.15 from " + ", ".join(f"{v:.0f} samples ({k})" if v is not None else f"never ({k})"
                                               for k, v in even.items()))
    print_table(table, ["samples", "local wall s", "ray wall s", "overhead (model)", "overhead (equal rates)",
                        "overhead (measured)"])
    print("\nOne node's costs (for docs/distributed.md)")
    print_table([{"cost": k, "value": v} for k, v in node.items()], ["cost", "value"])
    write_json("ray_export", {"machine": machine_info(["ray"]), "resolution": [W, H], "outputs": OUTPUTS,
                              "cpus": CPUS, "loadavg": load, "runs": rows,
                              "model": {e: {"start-up s": f, "samples/s": s} for e, (f, s) in model.items()},
                              "break_even_samples": even, "overhead_by_length": table, "node": node,
                              "new_kernel_cache_entries": new_kernels})


if __name__ == "__main__":
    main()
