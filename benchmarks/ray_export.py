"""Export throughput on the same CPUs: local worker processes against Ray actors, and what one node pays.

    python benchmarks/ray_export.py [--quick]

Side by side, in alternating rounds (load from other processes hits both alike): ``export(workers=2)``
(fork, one thread each) and ``export(engine="ray", workers=2)`` on ``ray.init(num_cpus=2)``. For each run:
wall time of the whole call (pool or actor start-up included), and the steady rate between the first and
the last finished sample (from the sample folders' mtimes). Ray's overhead = 1 - Ray rate / local rate.

Also, for docs/distributed.md's 100-node plan, on one thread: scene setup (sampling + physics) against
rendering per sample, Warp kernel compile with an empty cache against loading a warm one (each in a
fresh process), and bytes written per sample.

Needs the ray extra (``bash scripts/setup.sh --ray``). Writes benchmarks/results/ray_export.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _common import machine_info, print_table, write_json

OUTPUTS = ["rgb", "depth", "normals", "flow_fw", "flow_bw", "occ_fw", "instance", "box2d_visible"]
_ONE_SAMPLE = """
import json, sys, time
t = time.perf_counter()
import flowsynth as fs
cfg = fs.BouncingThingsConfig(**json.loads(sys.argv[1]))
fs.datasets.BouncingThings(cfg, outputs=json.loads(sys.argv[2]), threads=1).sample(0)
print(time.perf_counter() - t)
"""


def _steady_rate(root: Path) -> float:
    """Samples/s between the first and the last finished sample (a folder's mtime: its last file)."""
    done = sorted(max(f.stat().st_mtime for f in d.iterdir()) for d in root.iterdir() if d.name.isdigit())
    return (len(done) - 1) / (done[-1] - done[0])


def _first_sample_s(cfg_dict: dict, cache: Path) -> float:
    """Seconds from a fresh process's start to its first sample (imports and kernels included)."""
    env = dict(os.environ, WARP_CACHE_PATH=str(cache), PYTHONPATH=str(HERE.parent))
    r = subprocess.run([sys.executable, "-c", _ONE_SAMPLE, json.dumps(cfg_dict), json.dumps(OUTPUTS)],
                       capture_output=True, text=True, env=env, check=True)
    return float(r.stdout.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    args = p.parse_args()
    try:
        import ray
    except ImportError:
        print("skipped: benchmarks/ray_export.py needs Ray (bash scripts/setup.sh --ray)")
        return
    import flowsynth as fs
    from flowsynth.export import export

    W, H = (256, 192) if args.quick else (512, 384)
    num, rounds = (16, 2) if args.quick else (48, 2)
    cfg_dict = dict(width=W, height=H, num_frames=2, render_mode="direct")
    cfg = fs.BouncingThingsConfig(**cfg_dict)
    load = [os.getloadavg()]
    tmp = Path(tempfile.mkdtemp(prefix="fs-ray-bench-"))
    try:
        export(cfg, tmp / "warm", 1, outputs=OUTPUTS, progress=False)  # Warp kernel cache warm for both engines
        t = time.perf_counter()
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        ray_start = time.perf_counter() - t
        rows = []
        for r in range(rounds):
            for engine in ("local", "ray") if r % 2 == 0 else ("ray", "local"):
                out = tmp / f"{engine}{r}"
                t = time.perf_counter()
                export(cfg, out, num, seed=r, outputs=OUTPUTS, workers=2, engine=engine, progress=False)
                wall = time.perf_counter() - t
                rows.append({"engine": engine, "round": r, "samples": num, "wall_s": wall, "samples/s": num / wall,
                             "steady samples/s": _steady_rate(out)})
                load.append(os.getloadavg())
        ray.shutdown()
        bytes_per_sample = sum(f.stat().st_size for f in (tmp / "local0").glob("[0-9]*/*")) / num

        from flowsynth.datasets import BouncingThings

        ds = BouncingThings(cfg, outputs=OUTPUTS, threads=1)
        ds.sample(0)
        setup, total = [], []
        for i in range(1, 5):
            t = time.perf_counter()
            ds.scene(i)
            setup.append(time.perf_counter() - t)
            t = time.perf_counter()
            ds.sample(i)
            total.append(time.perf_counter() - t)
        warm = _first_sample_s(cfg_dict, Path(os.environ.get("WARP_CACHE_PATH", HERE.parent / ".cache" / "warp")))
        cold = _first_sample_s(cfg_dict, tmp / "empty-warp-cache")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    def mean(engine: str, key: str) -> float:
        vals = [r[key] for r in rows if r["engine"] == engine]
        return sum(vals) / len(vals)

    summary = []
    for key in ("samples/s", "steady samples/s"):
        loc, ray_ = mean("local", key), mean("ray", key)
        summary.append({"measure": key, "local (2 processes)": loc, "ray (2 actors)": ray_,
                        "ray overhead": 1.0 - ray_ / loc})
    per_sample = sum(total) / len(total)
    node = {"scene setup s/sample (1 thread)": sum(setup) / len(setup),
            "sample s (1 thread, setup included)": per_sample,
            "first sample, warm kernel cache s": warm, "first sample, empty kernel cache s": cold,
            "kernel compile s": cold - warm, "ray.init(num_cpus=2) s": ray_start, "bytes/sample": bytes_per_sample}
    print(f"Export at {W}x{H}, T=2, render_mode=direct, outputs={','.join(OUTPUTS)}; {num} samples per run, "
          f"{rounds} alternating rounds; 2 CPUs; load average (1 min) {load[0][0]:.1f} before, "
          f"{max(x[0] for x in load):.1f} max")
    print_table(rows, ["engine", "round", "samples", "wall_s", "samples/s", "steady samples/s"])
    print("\nMeans (overhead = 1 - ray / local; goal <= 0.15)")
    print_table(summary, ["measure", "local (2 processes)", "ray (2 actors)", "ray overhead"])
    print("\nOne node's costs (for docs/distributed.md)")
    print_table([{"cost": k, "value": v} for k, v in node.items()], ["cost", "value"])
    write_json("ray_export", {"machine": machine_info(["ray"]), "resolution": [W, H], "outputs": OUTPUTS,
                              "loadavg": load, "runs": rows, "summary": summary, "node": node})


if __name__ == "__main__":
    main()
