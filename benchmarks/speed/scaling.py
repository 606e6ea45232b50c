"""Samples/s on one core and on all cores: thread scaling, and throughput against resolution, objects,
triangles per object and frames per clip.

    python benchmarks/speed/scaling.py [--quick]

Part 1, threads (``fs.render(..., threads=k)``, flowsynth/parallel.py), for k = 1, 2, ... up to the CPUs
this process may use:

- the primary G-buffer cast alone (``cast_gbuffer``, depth + instance + normals) of benchmarks/peers/raycast.py's
  scene (30 icospheres x 5120 faces, 640x480): Mrays/s;
- the issue-13 full sample (``_common.full_sample_config``: ``BouncingThings`` 512x384, T=2, 20 objects, physics,
  direct RGB, a static camera, with ``_common.FULL_SAMPLE_OUTPUTS``: depth, normals, instance, flow, validity and
  occlusion both ways; scene sampling and physics included): samples/s. Until issue 41 this part used a moving
  camera and no validity masks, part 1b a static camera.

Part 1b, processes against threads: the same full sample streamed from fresh indices (as a training loop reads
it) by one process at 1 thread, by one process at all cores (threads), and by K = 1, 2, ... up to the cores
DataLoader worker processes (1 thread each): samples/s, the CPU seconds each sample cost, and K workers' samples/s
over K times one worker's (issue 39's goal: at least 0.9). ``--streams`` runs only this part, ``--rounds``
times, and prints the medians (``--default-config``: ``_common.default_stream()`` instead).

``--stages`` runs only a breakdown of that full sample at 1 thread and all cores (``--rounds`` alternated rounds of
12 fresh samples): wall and CPU ms a sample of the scene (layout, materials, physics) and of each render stage, each
stage's speed-up, and how much of the sample's wall at all cores exceeds a perfect split of its one-thread wall.
Writes benchmarks/results/scaling_stages.json.

``--bands`` runs only the cost of how a threaded launch is cut (``flowsynth.parallel.BANDS_PER_THREAD``: each
launch of an image is cut into that many row bands per thread, which the pool's threads take in turn, so a thread
that ends a cheap band takes the next): the full sample at one thread and at all cores with each of
``BAND_SETTINGS``, the settings alternated round by round (order reversed every other round) on the same fresh
indices in one process, ``--rounds`` rounds of 5 samples; wall ms a sample, and each setting's speed-up over one
thread paired round by round (median and range). Writes benchmarks/results/scaling_bands.json.

Part 2, curves: hand-built scenes (icospheres of chosen resolution in front of a wall, random rigid
motion) rendered with depth + flow_fw + occ_fw + instance, at threads 1 and all; each curve fitted
with cost ~ x^k.

Clock: wall time (threads only show in wall time), medians over round-robin rounds so load from other
processes hits every thread count alike. The machine is shared: the load average (``os.getloadavg``)
before and after is printed and saved; a speed-up is only meaningful when the load leaves the cores
free. numpy/torch/OpenMP pools are held at one thread (only the ray launches are threaded). Writes
benchmarks/results/scaling.json and scaling_<axis>.png.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parents[1])]
for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

from _common import (
    FULL_SAMPLE_OUTPUTS,
    Timer,
    default_stream,
    fit_exponent,
    full_sample_config,
    machine_info,
    plot_curves,
    print_table,
    raycast_scene,
    time_round_robin,
    write_json,
)

OUTPUTS = ["depth", "flow_fw", "occ_fw", "instance"]
FULL_OUTPUTS = list(FULL_SAMPLE_OUTPUTS)


def load() -> str:
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def make_scene(W: int, H: int, n_obj: int, faces: int, T: int, seed: int = 0):
    import numpy as np
    import trimesh

    import flowsynth as fs

    rng = np.random.default_rng(seed)
    sub = max(0, int(round(np.log(faces / 20) / np.log(4))))  # icosphere: 20 * 4^s faces
    mesh = trimesh.creation.icosphere(sub, radius=0.3)
    scene = fs.Scene(fs.Camera.from_fov(W, H, 60), T)
    for _ in range(n_obj):
        p0 = rng.uniform([-3, -2, 4], [3, 2, 10])
        v = rng.uniform(-0.1, 0.1, 3)
        P = np.tile(np.eye(4), (T, 1, 1))
        for t in range(T):
            a = 0.05 * t
            P[t, :3, :3] = trimesh.transformations.rotation_matrix(a, [0, 1, 0])[:3, :3]
            P[t, :3, 3] = p0 + t * v
        scene.add_object(mesh, P)
    wall = np.eye(4)
    wall[2, 3] = 12
    scene.add_object(trimesh.creation.box((40, 40, 0.1)), wall)
    return scene, len(mesh.faces)


def thread_scaling(counts: list[int], repeat: int) -> list[dict]:
    """Mrays/s of the primary cast and samples/s of the full sample for each thread count."""
    import torch

    import flowsynth as fs
    from flowsynth.raycast import SceneAccel, cast_gbuffer, scene_arrays

    torch.set_num_threads(1)
    scene = raycast_scene()
    accel = SceneAccel(*scene_arrays(scene))
    cam = scene.camera
    fns = {("cast", k): (lambda k=k: cast_gbuffer(accel, cam, want_normals=True, want_points=False, threads=k))
           for k in counts}
    cfg = full_sample_config()
    sets = {k: fs.datasets.BouncingThings(cfg, outputs=FULL_OUTPUTS, seed=0, threads=k) for k in counts}
    index = {k: iter(range(10**6)) for k in counts}

    def full(k: int) -> None:
        # a counter per thread count: every count renders scenes 0, 1, 2, 3, 0, ... alike
        sets[k].sample(next(index[k]) % 4)

    fns.update({("sample", k): (lambda k=k: full(k)) for k in counts})
    # warm-up over all four scenes with every count: the process-wide caches (meshes, BVHs, textures) then hold
    # each scene before any count is timed on it
    times = time_round_robin(fns, repeat=repeat, warmup=4)
    rays = cam.width * cam.height
    rows = []
    for k in counts:
        cast, sample = times[("cast", k)]["wall_s"], times[("sample", k)]["wall_s"]
        rows.append({"threads": k, "cast_ms": 1e3 * cast, "cast_Mrays_s": rays / cast / 1e6,
                     "cast_cores_got": times[("cast", k)]["cpu_s"] / cast,
                     "sample_s": sample, "samples_s": 1.0 / sample,
                     "sample_cores_got": times[("sample", k)]["cpu_s"] / sample})
    for r in rows:
        r["cast_speedup"] = rows[0]["cast_ms"] / r["cast_ms"]
        r["sample_speedup"] = rows[0]["sample_s"] / r["sample_s"]
    return rows


def curves(quick: bool, counts: list[int], repeat: int) -> tuple[dict, list]:
    import flowsynth as fs

    axes = {
        "pixels": [(64, 48), (128, 96), (256, 192), (512, 384), (1024, 768)],
        "objects": [5, 10, 20, 40, 80, 160],
        "triangles": [80, 320, 1280, 5120, 20480, 81920],
        "frames": [2, 4, 8, 16, 32],
    }
    if quick:
        axes = {"pixels": axes["pixels"][:4], "objects": [5, 20, 80], "triangles": [80, 1280, 20480],
                "frames": [2, 4, 8]}
    base = dict(W=256, H=192, n_obj=20, faces=1280, T=2)
    results, fits = {}, []
    for axis, values in axes.items():
        rows = []
        for v in values:
            kw = dict(base)
            if axis == "pixels":
                kw["W"], kw["H"] = v
                x = v[0] * v[1]
            elif axis == "objects":
                kw["n_obj"] = x = v
            elif axis == "triangles":
                kw["faces"] = v
            else:
                kw["T"] = x = v
            scene, faces = make_scene(**kw)
            x = faces if axis == "triangles" else x
            fns = {k: (lambda k=k, scene=scene: fs.render(scene, OUTPUTS, threads=k)) for k in counts}
            times = time_round_robin(fns, repeat=repeat, warmup=1)
            row = {"axis": axis, "x": x}
            for k in counts:
                row[f"samples/s t{k}"] = 1.0 / times[k]["wall_s"]
            row["speed-up"] = row[f"samples/s t{counts[-1]}"] / row[f"samples/s t{counts[0]}"]
            rows.append(row)
        xs = [r["x"] for r in rows]
        series = {f"{k} thread{'s' if k > 1 else ''}": (xs, [r[f"samples/s t{k}"] for r in rows]) for k in counts}
        for k in counts:
            fits.append({"axis": axis, "threads": k, "exponent": fit_exponent(xs, [1 / r[f"samples/s t{k}"]
                                                                                  for r in rows]),
                         "range": f"{xs[0]}..{xs[-1]}"})
        results[axis] = rows
        print_table(rows, ["axis", "x", *[f"samples/s t{k}" for k in counts], "speed-up"])
        plot_curves(f"scaling_{axis}", series, axis, "samples/s (wall)",
                    title=f"depth+flow_fw+occ_fw+instance vs {axis}")
    return results, fits


def stream_rate(cfg, n: int, start: int, threads: int | None, workers: int, outputs=None) -> tuple[float, float]:
    """(samples/s wall, process CPU s a sample of this process and its workers) of n samples of the full output set
    streamed from index ``start`` (fresh scenes), in one process with ``threads`` or in ``workers`` DataLoader
    worker processes (1 thread each, the library's default there); the first sample (start-up) is not timed.
    ``outputs``: another output list than the full one."""
    import resource
    import time

    from torch.utils.data import DataLoader

    import flowsynth as fs

    def cpu_s() -> float:  # this process and its exited children (the DataLoader workers)
        return sum(r.ru_utime + r.ru_stime for r in map(resource.getrusage, (resource.RUSAGE_SELF,
                                                                             resource.RUSAGE_CHILDREN)))

    ds = fs.datasets.BouncingThings(cfg, outputs=outputs or FULL_OUTPUTS, seed=0, start=start, threads=threads)
    it = iter(DataLoader(ds, batch_size=None, num_workers=workers))
    next(it)
    cpu0 = cpu_s()
    t = time.perf_counter()
    for _ in range(n):
        next(it)
    dt = time.perf_counter() - t
    del it  # workers exit: their CPU time reaches RUSAGE_CHILDREN
    return n / dt, (cpu_s() - cpu0) / n


def processes_vs_threads(cpus: int, n: int, default: bool = False) -> list[dict]:
    """The full sample streamed (fresh scenes, as in training) with 1 thread, with all cores as threads of one
    process, and with all cores as DataLoader worker processes; each setting streams the same indices.
    ``default``: the default config (320x240, T=24) with rgb, flow_fw, valid_fw and occ_fw instead."""
    cfg, outputs = default_stream() if default else (full_sample_config(), None)
    rows = []
    settings = [("1 process, 1 thread", 1, 0, 0), (f"1 process, {cpus} threads", cpus, 0, 0)]
    settings += [(f"{k} worker process" + ("es" if k > 1 else "") + ", 1 thread each", None, k, k)
                 for k in range(1, cpus + 1)]
    for name, threads, workers, k in settings:
        rate, cpu = stream_rate(cfg, n, 5000, threads, workers, outputs)
        rows.append({"setting": name, "workers": k, "samples_s": rate, "cpu_s_per_sample": cpu})
    one = next(r["samples_s"] for r in rows if r["workers"] == 1)
    for r in rows:
        r["speedup"] = r["samples_s"] / rows[0]["samples_s"]
        # issue 39: K workers should stream at least 0.9 x K x one worker's samples/s
        r["of_k_x_one_worker"] = r["samples_s"] / (r["workers"] * one) if r["workers"] else None
    return rows


def streams_only(cpus: int, rounds: int, n: int, default: bool = False) -> None:
    """Part 1b alone, ``rounds`` times in a row (the settings' order within a round is fixed, so load from
    elsewhere is shared out over rounds); prints each round and the medians; writes
    results/scaling_streams[_default].json."""
    import statistics

    before = load()
    print(f"{cpus} CPUs allowed; {before}")
    runs = []
    for r in range(rounds):
        rows = processes_vs_threads(cpus, n, default)
        runs.append(rows)
        print(f"\nround {r + 1}:")
        print_table(rows, ["setting", "samples_s", "speedup", "of_k_x_one_worker", "cpu_s_per_sample"])
    keys = ("samples_s", "speedup", "of_k_x_one_worker", "cpu_s_per_sample")
    medians = [{"setting": row["setting"]} | {k: statistics.median(run[i][k] for run in runs)
                                              if row[k] is not None else None for k in keys}
               for i, row in enumerate(runs[0])]
    print(f"\nmedians of {rounds} rounds, {n} samples a setting (of_k_x_one_worker: K workers' samples/s over K "
          "times one worker's; issue 39 asks >= 0.9):")
    print_table(medians, ["setting", *keys])
    after = load()
    print(after)
    write_json("scaling_streams" + ("_default" if default else ""), {
        "machine": machine_info(), "load_before": before, "load_after": after, "samples": n,
        "config": "default (rgb, flow_fw, valid_fw, occ_fw)" if default else "issue 13 full sample (512x384, T=2)",
        "rounds": runs, "medians": medians})


# The stages of a full sample, timed by ``--stages``: (module, function) wrapped for the run (render_plan looks them
# up in their modules at call time), and the scene itself (``BouncingThings.scene``: layout, materials, physics).
STAGES = (("flowsynth.renderer.pipeline", "SceneAccel", "accel"),
          ("flowsynth.renderer.pipeline", "cast_gbuffer", "cast"),
          ("flowsynth.renderer.batch", "gbuffer_outputs", "gbuffer outputs"),
          ("flowsynth.truth", "flow_outputs", "flow"), ("flowsynth.renderer.shading", "render_rgb", "rgb"))


def stage_times(counts: list[int], n: int, rounds: int) -> list[dict]:
    """Wall and CPU ms a sample of each stage of the issue-13 full sample (512x384, T=2, 20 objects, direct RGB)
    streamed from fresh indices, at each thread count; the counts alternate round by round on the same indices."""
    import importlib
    from collections import defaultdict

    import flowsynth as fs
    from flowsynth.renderer import render_plan

    wall: dict = defaultdict(float)
    cpu: dict = defaultdict(float)
    current = {"k": None}

    def timed(fn, label):
        def run(*a, **kw):
            t = Timer()
            try:
                with t:
                    return fn(*a, **kw)
            finally:
                wall[current["k"], label] += t.wall_s
                cpu[current["k"], label] += t.cpu_s
        return run

    saved = []
    for mod_name, attr, label in STAGES:
        mod = importlib.import_module(mod_name)
        saved.append((mod, attr, getattr(mod, attr)))
        setattr(mod, attr, timed(getattr(mod, attr), label))
    try:
        cfg = full_sample_config()
        sets = {k: fs.datasets.BouncingThings(cfg, outputs=FULL_OUTPUTS, seed=0, threads=k) for k in counts}
        for k in counts:  # caches of a long stream filled, kernels loaded
            current["k"] = k
            for i in range(15):
                sets[k].sample(9000 + 15 * counts.index(k) + i)
        wall.clear()
        cpu.clear()
        for r in range(rounds):
            for k in (counts if r % 2 == 0 else counts[::-1]):
                current["k"] = k
                for i in range(5000 + r * n, 5000 + (r + 1) * n):
                    with Timer() as whole:
                        with Timer() as part:
                            scene = sets[k].scene(i)
                        render_plan(scene, sets[k].plan)
                    wall[k, "scene"] += part.wall_s
                    cpu[k, "scene"] += part.cpu_s
                    wall[k, "sample"] += whole.wall_s
                    cpu[k, "sample"] += whole.cpu_s
    finally:
        for mod, attr, fn in saved:
            setattr(mod, attr, fn)
    total = n * rounds
    labels = ["scene"] + [label for _, _, label in STAGES]
    for k in counts:
        wall[k, "rest"] = wall[k, "sample"] - sum(wall[k, x] for x in labels)
        cpu[k, "rest"] = cpu[k, "sample"] - sum(cpu[k, x] for x in labels)
    rows = []
    top = counts[-1]
    for label in labels + ["rest", "sample"]:
        row = {"stage": label}
        for k in counts:
            row[f"wall_ms_t{k}"] = 1e3 * wall[k, label] / total
            row[f"cpu_ms_t{k}"] = 1e3 * cpu[k, label] / total
        row["speedup"] = wall[1, label] / wall[top, label] if wall[top, label] > 0 else None
        # wall at all threads above a perfect split of the one-thread wall: what keeps the sample from top x
        row["excess_ms"] = row[f"wall_ms_t{top}"] - row["wall_ms_t1"] / top
        rows.append(row)
    return rows


# Row bands per thread compared by ``--bands`` (flowsynth.parallel.BANDS_PER_THREAD).
BAND_SETTINGS = (4, 8, 16)


def band_times(cpus: int, n: int, rounds: int) -> list[dict]:
    """Wall ms a full sample (fresh indices from 5000, ``n`` a round) at one thread and at ``cpus`` threads with each
    of ``BAND_SETTINGS`` bands per thread, alternated round by round in one process (order reversed every other
    round); each setting's speed-up over the one-thread wall of the same round."""
    import time

    import numpy as np

    import flowsynth as fs
    from flowsynth import parallel

    cfg = full_sample_config()
    streams = {k: fs.datasets.BouncingThings(cfg, outputs=FULL_OUTPUTS, seed=0, threads=k) for k in (1, cpus)}
    for ds in streams.values():  # kernels loaded, caches filled
        for i in range(4):
            ds.sample(9000 + i)
    settings = [(1, parallel.BANDS_PER_THREAD)] + [(cpus, b) for b in BAND_SETTINGS]
    walls: dict = {s: [] for s in settings}
    saved = parallel.BANDS_PER_THREAD
    try:
        for r in range(rounds):
            for k, b in (settings if r % 2 == 0 else settings[::-1]):
                parallel.BANDS_PER_THREAD = b
                t = time.perf_counter()
                for i in range(5000 + n * r, 5000 + n * (r + 1)):
                    streams[k].sample(i)
                walls[k, b].append((time.perf_counter() - t) / n)
    finally:
        parallel.BANDS_PER_THREAD = saved
    one = np.array(walls[settings[0]])
    rows = []
    for (k, b), w in walls.items():
        w = np.array(w)
        ratio = one / w
        rows.append({"threads": k, "bands_per_thread": b if k > 1 else None, "wall_ms": float(np.median(w)) * 1e3,
                     "speedup": float(np.median(ratio)), "speedup_min": float(ratio.min()),
                     "speedup_max": float(ratio.max())})
    return rows


def _one_against_all(p, option: str, rounds: int, cpus: int) -> str:
    """Checks of a part that compares one thread with every core (``--rounds`` >= 1, two CPUs at least; else the
    parser's error, exit 2), torch held at one thread; returns the load average before it."""
    if rounds < 1:
        p.error(f"--rounds must be >= 1, got {rounds}")
    if cpus < 2:
        p.error(f"{option} compares one thread with all cores: this process may use only one CPU")
    import torch

    torch.set_num_threads(1)
    return load()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--streams", action="store_true", help="only part 1b (processes against threads), --rounds times")
    p.add_argument("--rounds", type=int, default=3, help="--streams: rounds of the three settings, one after another")
    p.add_argument("--default-config", action="store_true",
                   help="--streams: stream the default config (rgb + flow) instead of the full sample (512x384, "
                   "2 frames, 20 objects, every output)")
    p.add_argument("--stages", action="store_true",
                   help="only the full sample's stages timed at 1 thread and all cores (--rounds rounds)")
    p.add_argument("--bands", action="store_true",
                   help="only the full sample at 1 thread and at all cores with 4, 8 and 16 row bands a thread "
                   "(--rounds rounds of 5 samples, alternated)")
    args = p.parse_args()
    cpus = len(os.sched_getaffinity(0))
    if args.bands:
        before = _one_against_all(p, "--bands", args.rounds, cpus)
        rows = band_times(cpus, 2 if args.quick else 5, args.rounds)
        print(f"Full sample (512x384, T=2, 20 objects, direct RGB, every output) at 1 thread and {cpus} threads by "
              f"row bands a thread; {args.rounds} rounds alternated, wall ms a sample (median); speedup over 1 thread "
              f"paired by round (median, min, max); {before}")
        print_table(rows, ["threads", "bands_per_thread", "wall_ms", "speedup", "speedup_min", "speedup_max"])
        after = load()
        print(after)
        write_json("scaling_bands", {"machine": machine_info(), "load_before": before, "load_after": after,
                                     "rounds": args.rounds, "settings": list(BAND_SETTINGS), "rows": rows})
        return
    if args.stages:
        before = _one_against_all(p, "--stages", args.rounds, cpus)
        n = 4 if args.quick else 12
        rows = stage_times([1, cpus], n, args.rounds)
        print(f"Stages of the full sample (512x384, T=2, 20 objects, direct RGB, depth/normals/instance/flow+occ "
              f"both ways), {n} fresh samples x {args.rounds} rounds at threads 1 and {cpus}, alternated; ms a "
              f"sample; speedup: wall at 1 / wall at {cpus}; excess_ms: wall at {cpus} minus wall at 1 / {cpus}; "
              f"{before}")
        print_table(rows, ["stage", "wall_ms_t1", "cpu_ms_t1", f"wall_ms_t{cpus}", f"cpu_ms_t{cpus}", "speedup",
                           "excess_ms"])
        after = load()
        print(after)
        write_json("scaling_stages", {"machine": machine_info(), "load_before": before, "load_after": after,
                                      "samples": n, "rounds": args.rounds, "threads": [1, cpus], "stages": rows})
        return
    if args.streams:
        if args.rounds < 1:
            p.error(f"--rounds must be >= 1, got {args.rounds}")
        if cpus < 2:
            p.error("--streams compares one thread with all cores: this process may use only one CPU")
        streams_only(cpus, args.rounds, 8 if args.quick else 24, args.default_config)
        return
    counts = sorted({1, 2, cpus} & set(range(1, cpus + 1)))
    before = load()
    print(f"{cpus} CPUs allowed; {before}")
    threads = thread_scaling(counts, 3 if args.quick else 7)
    print("\nThreads: primary cast (30 icospheres x 5120 faces, 640x480) and full sample (512x384, T=2, 20 objects, "
          "direct RGB, depth/normals/instance/flow+occ both ways); wall-clock medians")
    print("cores_got: process CPU time / wall time, the cores this process actually had (less than the threads "
          "when other processes load the machine)")
    print_table(threads, ["threads", "cast_ms", "cast_Mrays_s", "cast_speedup", "cast_cores_got", "sample_s",
                          "samples_s", "sample_speedup", "sample_cores_got"])
    print(load())
    procs = processes_vs_threads(cpus, 8 if args.quick else 24) if cpus > 1 else []
    if procs:
        print("\nThe same full sample streamed (fresh scenes from index 5000, as in training): threads of one process "
              "against DataLoader worker processes; wall-clock samples/s, CPU s a sample (process and workers)")
        print_table(procs, ["setting", "samples_s", "speedup", "of_k_x_one_worker", "cpu_s_per_sample"])
        print(load())
    print("\nSamples/s (wall) at threads " + ", ".join(map(str, counts)) + "; others at 256x192, 20 objects, "
          "1280 faces, T=2")
    results, fits = curves(args.quick, counts, 2 if args.quick else 3)
    print("\nFitted exponents (cost ~ x^k):")
    print_table(fits, ["axis", "threads", "exponent", "range"])
    after = load()
    print(after)
    write_json("scaling", {"machine": machine_info(), "load_before": before, "load_after": after,
                           "threads": threads, "processes_vs_threads": procs, "curves": results, "exponents": fits,
                           "base": dict(W=256, H=192, n_obj=20, faces=1280, T=2)})


if __name__ == "__main__":
    main()
