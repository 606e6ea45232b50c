"""Shared helpers for the scripts in ``benchmarks/``: the named workloads, machine description, timing, table,
JSON, plot.

Every benchmark prints a table, writes ``benchmarks/results/<name>.json`` holding its numbers and
``machine_info()``, and says how it was pinned. Only the standard library is imported at module level,
so a benchmark can set its thread environment before numpy, torch or Warp are loaded (the workload functions
import flowsynth when called).

Where results go (``results_dir``): a full run writes the tracked results, ``benchmarks/results/``
(``TRACKED_RESULTS_DIR``); a run with ``--quick`` on its command line, a smoke run, writes ``.cache/bench-quick/``
(``QUICK_RESULTS_DIR``, ignored by git), so it never changes the recorded numbers; ``FLOWSYNTH_BENCH_RESULTS=DIR``
sends every results file to DIR in both cases. ``RESULTS_DIR`` is that choice for this process's command line.

Named workloads, defined once here so that every script measures the same thing:

- ``full_sample_config()`` / ``FULL_SAMPLE_OUTPUTS``: issue 13's full sample, 512x384, T=2, direct RGB, 20 objects,
  a static camera, and every per-pixel output of the pair pass. Before issue 41 five scripts configured it, and
  scaling.py's part 1, cycles.py and shading_cost.py used a moving camera (the config's default) where
  versions.py and scaling.py's part 1b used a static one; results recorded before then are not comparable to
  within that difference.
- ``default_stream()``: ``BouncingThingsConfig()`` as it is, with rgb and forward flow, validity and occlusion.
- ``EXPORT_SAMPLE`` / ``EXPORT_OUTPUTS``: what export.py and ray_export.py write (T=2, direct RGB, 8 outputs).
- ``raycast_scene()``: 30 icospheres of 5120 faces at 640x480 (``RAYCAST_WIDTH`` x ``RAYCAST_HEIGHT``), the scene of
  raycast.py, bvh.py, tiles.py and scaling.py's cast.
"""

from __future__ import annotations

import datetime
import importlib.metadata
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

__all__ = ["DEFAULT_STREAM_OUTPUTS", "EXPORT_OUTPUTS", "EXPORT_SAMPLE", "FULL_SAMPLE", "FULL_SAMPLE_OUTPUTS",
           "QUICK_RESULTS_DIR", "RAYCAST_FOV_DEG", "RAYCAST_HEIGHT", "RAYCAST_RADIUS", "RAYCAST_SPHERES",
           "RAYCAST_SUBDIVISIONS", "RAYCAST_WIDTH", "RAYCAST_Z_RANGE", "RESULTS_DIR", "TRACKED_RESULTS_DIR", "Timer",
           "default_stream", "full_sample_config", "is_quick", "machine_info", "pin_single_core", "print_table",
           "raycast_scene", "results_dir", "save_plot", "time_calls", "time_round_robin", "timeit", "write_json"]

TRACKED_RESULTS_DIR = Path(__file__).resolve().parent / "results"
"""The recorded results, tracked by git: what SUMMARY.md, the docs and the decision records cite."""
QUICK_RESULTS_DIR = Path(__file__).resolve().parent.parent / ".cache" / "bench-quick"
"""Where a ``--quick`` run writes: under the repository's ``.cache/``, which git ignores."""


def is_quick(argv: Sequence[str]) -> bool:
    """Whether the command-line arguments ``argv`` (without the program) ask for a quick run: ``--quick`` or a
    prefix of it that argparse would accept for it (``--qui``)."""
    return any(len(a) > 2 and "--quick".startswith(a) for a in argv)


def results_dir(quick: bool, environ: dict | None = None) -> Path:
    """The folder a run's results files go to: ``FLOWSYNTH_BENCH_RESULTS`` of ``environ`` (default ``os.environ``)
    when set, else ``QUICK_RESULTS_DIR`` for a quick run and ``TRACKED_RESULTS_DIR`` for a full one."""
    override = (os.environ if environ is None else environ).get("FLOWSYNTH_BENCH_RESULTS")
    return Path(override) if override else QUICK_RESULTS_DIR if quick else TRACKED_RESULTS_DIR


RESULTS_DIR = results_dir(is_quick(sys.argv[1:]))

FULL_SAMPLE = {"width": 512, "height": 384, "num_frames": 2, "render_mode": "direct", "num_objects": (20, 20),
               "camera_motion": "static"}
"""Issue 13's full sample as config keywords (plain data: versions.py hands it to another revision's flowsynth)."""
FULL_SAMPLE_OUTPUTS = ("rgb", "depth", "normals", "instance", "flow_fw", "flow_bw", "valid_fw", "valid_bw", "occ_fw",
                       "occ_bw")
"""The full sample's outputs: the image, the G-buffer and the flow family both ways."""
DEFAULT_STREAM_OUTPUTS = ("rgb", "flow_fw", "valid_fw", "occ_fw")
EXPORT_SAMPLE = {"num_frames": 2, "render_mode": "direct"}
"""The export benchmarks' sample (export.py, ray_export.py) as config keywords; the width and height are theirs."""
EXPORT_OUTPUTS = ("rgb", "depth", "normals", "flow_fw", "flow_bw", "occ_fw", "instance", "box2d_visible")
RAYCAST_WIDTH, RAYCAST_HEIGHT, RAYCAST_FOV_DEG = 640, 480, 60.0
RAYCAST_SPHERES, RAYCAST_SUBDIVISIONS, RAYCAST_RADIUS = 30, 4, 1.0
RAYCAST_Z_RANGE = (4.0, 12.0)  # sphere centre depth [m]


def full_sample_config(**overrides):
    """``BouncingThingsConfig`` of issue 13's full sample (``FULL_SAMPLE``), with ``overrides`` applied (a variant
    says what it changes: ``full_sample_config(width=256, height=192)``)."""
    import flowsynth as fs

    return fs.BouncingThingsConfig(**{**FULL_SAMPLE, **overrides})


def default_stream():
    """(config, outputs) of the default stream: ``BouncingThingsConfig()`` and ``DEFAULT_STREAM_OUTPUTS``."""
    import flowsynth as fs

    return fs.BouncingThingsConfig(), list(DEFAULT_STREAM_OUTPUTS)


def raycast_scene(seed: int = 0):
    """30 unit icospheres (5120 faces) at random rotations and non-overlapping positions 4-12 m away inside the view
    frustum of a 640x480, 60 degree camera; one frame. The same scene for every seed-0 caller."""
    import numpy as np
    import trimesh

    import flowsynth as fs

    rng = np.random.default_rng(seed)
    camera = fs.Camera.from_fov(RAYCAST_WIDTH, RAYCAST_HEIGHT, RAYCAST_FOV_DEG)
    scene = fs.Scene(camera, num_frames=1)
    mesh = trimesh.creation.icosphere(subdivisions=RAYCAST_SUBDIVISIONS, radius=RAYCAST_RADIUS)
    half_x = np.tan(np.radians(RAYCAST_FOV_DEG) / 2)
    half_y = half_x * RAYCAST_HEIGHT / RAYCAST_WIDTH
    centres: list = []
    while len(centres) < RAYCAST_SPHERES:
        z = rng.uniform(*RAYCAST_Z_RANGE)
        c = np.array([rng.uniform(-1, 1) * half_x * z * 0.85, rng.uniform(-1, 1) * half_y * z * 0.85, z])
        if all(np.linalg.norm(c - p) > 2.02 * RAYCAST_RADIUS for p in centres):
            centres.append(c)
    for c in centres:
        pose = np.eye(4)
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        pose[:3, :3] = q * np.sign(np.diag(r)) * np.sign(np.linalg.det(q * np.sign(np.diag(r))))
        pose[:3, 3] = c
        scene.add_object(mesh, pose)
    return scene


class Timer:
    """Wall and process-CPU time of a block: ``with Timer() as t: ...`` then ``t.wall_s``, ``t.cpu_s`` [s].

    Process CPU time counts every thread of this process (not child processes)."""

    def __enter__(self) -> Timer:
        self.wall_s = self.cpu_s = 0.0
        self._w, self._c = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc) -> None:
        self.wall_s = time.perf_counter() - self._w
        self.cpu_s = time.process_time() - self._c

# Thread-count variables read by OpenMP, MKL, OpenBLAS and numexpr when they load. TBB (Embree's thread
# pool) has none: it sizes itself from the CPU affinity mask, hence ``pin_single_core``'s affinity.
_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def pin_single_core(cpu: int | None = None) -> dict:
    """Restrict this process to one CPU and one thread per library. Call before importing numpy/torch.

    Sets the thread-count variables of ``_THREAD_VARS`` to 1 and, when the process may run on more than
    one CPU, sets its affinity to a single one (``cpu``, default the lowest allowed): thread pools that
    size themselves from the affinity mask (TBB, which Embree uses; OpenMP) then start one worker.
    Running the script under ``taskset -c 0`` has the same effect on the affinity.

    Returns:
        dict describing the pinning, for the results file.
    """
    for var in _THREAD_VARS:
        os.environ[var] = "1"
    allowed = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    if len(allowed) > 1:
        os.sched_setaffinity(0, {allowed[0] if cpu is None else cpu})
    return {
        "affinity_before": allowed,
        "affinity": sorted(os.sched_getaffinity(0)) if allowed else [],
        "env": {var: os.environ[var] for var in _THREAD_VARS},
    }


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def machine_info(extra_packages: Sequence[str] = ()) -> dict:
    """Platform, CPU model, CPU counts, package versions, the date and the command that ran, for a results file."""
    info = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": _command(),
        "platform": platform.platform(),
        "cpu_model": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "cpus_allowed": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "python": platform.python_version(),
    }
    for dist in ("torch", "warp-lang", "newton", "numpy", "trimesh", *extra_packages):
        info[dist] = _version(dist)
    info.update(_library_commit())
    return info


def _command() -> str:
    """This process's command line as ``python PATH ARGS``, PATH relative to the repository when inside it."""
    if not sys.argv or not sys.argv[0]:
        return "python"
    prog = Path(sys.argv[0]).resolve()
    root = Path(__file__).resolve().parent.parent
    shown = prog.relative_to(root) if prog.is_relative_to(root) else prog
    return " ".join(["python", str(shown), *sys.argv[1:]])


def _library_commit() -> dict:
    """``flowsynth_commit``: the git commit of the checkout the imported flowsynth package comes from, and
    ``flowsynth_modified``: whether its ``flowsynth/`` differs from that commit (uncommitted library changes); both
    None outside a git checkout. Two results files of one commit and no modification ran the same library code."""
    import subprocess
    from importlib.util import find_spec

    spec = find_spec("flowsynth")
    if spec is None or spec.origin is None:
        return {"flowsynth_commit": None, "flowsynth_modified": None}
    root = Path(spec.origin).resolve().parent.parent
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=10, check=True).stdout.strip()
        changed = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--", "flowsynth"],
                                 capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return {"flowsynth_commit": None, "flowsynth_modified": None}
    return {"flowsynth_commit": commit, "flowsynth_modified": bool(changed)}


def time_calls(fn: Callable[[], object], repeat: int = 5, warmup: int = 1) -> dict:
    """Wall and process-CPU time of ``fn()`` over ``repeat`` calls after ``warmup`` untimed calls.

    Returns:
        dict with ``wall_s`` and ``cpu_s`` (medians), ``wall_min_s``, ``cpu_min_s`` [s] and ``repeat``.
        On a single pinned core the CPU time is the work done; wall time also counts time the core
        spent on other processes, so it is the noisier of the two on a shared machine.
    """
    return time_round_robin({"fn": fn}, repeat, warmup)["fn"]


def time_round_robin(fns: dict[str, Callable[[], object]], repeat: int = 5, warmup: int = 1,
                     rotate: bool = False) -> dict[str, dict]:
    """``time_calls`` for several functions, called in turn each round, so load changes on a shared
    machine hit all of them alike and their ratios stay meaningful. ``rotate``: round r starts with function
    r mod n (so none is always the first call of a round). Returns {name: time_calls dict}, plus every round's
    times (``cpu_all_s``, ``wall_all_s``, in round order)."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    wall: dict[str, list[float]] = {k: [] for k in fns}
    cpu: dict[str, list[float]] = {k: [] for k in fns}
    names = list(fns)
    for r in range(max(repeat, 1)):
        for name in names[r % len(names):] + names[:r % len(names)] if rotate else names:
            fn = fns[name]
            w0, c0 = time.perf_counter(), time.process_time()
            fn()
            cpu[name].append(time.process_time() - c0)
            wall[name].append(time.perf_counter() - w0)
    return {k: {"wall_s": statistics.median(wall[k]), "cpu_s": statistics.median(cpu[k]), "wall_min_s": min(wall[k]),
                "cpu_min_s": min(cpu[k]), "repeat": len(wall[k]), "wall_all_s": wall[k], "cpu_all_s": cpu[k]}
            for k in fns}


def timeit(fn: Callable[[], object], repeat: int = 5, warmup: int = 1, clock: str = "wall") -> float:
    """Median time of ``fn()`` over ``repeat`` calls after ``warmup`` untimed calls [s].

    ``clock`` is "wall" (``time.perf_counter``) or "cpu" (``time.process_time``, all threads of this process).
    """
    if clock not in ("wall", "cpu"):
        raise ValueError(f"clock must be 'wall' or 'cpu', got {clock!r}")
    return time_calls(fn, repeat, warmup)[f"{clock}_s"]


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}" if abs(value) < 1e5 else f"{value:.3e}"
    return "" if value is None else str(value)


def print_table(rows: Sequence[dict], columns: Sequence[str]) -> None:
    """Print ``rows`` (dicts) as an aligned text table with the given column keys."""
    cells = [[_fmt(r.get(c)) for c in columns] for r in rows]
    widths = [max([len(c)] + [len(row[k]) for row in cells]) for k, c in enumerate(columns)]
    print("  ".join(c.ljust(w) for c, w in zip(columns, widths)))
    print("  ".join("-" * w for w in widths))
    for row in cells:
        print("  ".join(v.rjust(w) if k else v.ljust(w) for k, (v, w) in enumerate(zip(row, widths))))


def write_json(name: str, data: dict) -> Path:
    """Write ``data`` to ``benchmarks/results/<name>.json`` (indented) and return the path."""
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / f"{name}.json"
    tmp = path.with_suffix(".json.tmp")  # written whole, then renamed: a crash never leaves half a file
    tmp.write_text(json.dumps(data, indent=2, default=_json_default) + "\n")
    os.replace(tmp, path)
    return path


def _json_default(obj):
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} to JSON")


def pyplot():
    """matplotlib.pyplot on the Agg backend (files only), or None without matplotlib (the bench extra)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def save_figure(fig, name: str, dpi: float | None = None) -> Path:
    """Write ``fig`` to ``benchmarks/results/<name>.png`` (the folder made if missing), close it, return the path."""
    import matplotlib.pyplot as plt

    path = RESULTS_DIR / f"{name}.png"
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, **({"dpi": dpi} if dpi else {}))
    plt.close(fig)
    return path


def save_plot(name: str, labels: Sequence[str], values: Sequence[float], ylabel: str,
              title: str = "") -> Path | None:
    """Bar chart to ``benchmarks/results/<name>.png``; returns None (and does nothing) without matplotlib."""
    plt = pyplot()
    if plt is None:
        return None
    fig, ax = plt.subplots(figsize=(1.2 + 1.1 * len(labels), 3.2))
    ax.bar(range(len(labels)), values)
    ax.set_xticks(range(len(labels)), labels, rotation=20, ha="right")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    fig.tight_layout()
    return save_figure(fig, name, dpi=120)


def plot_curves(name: str, series: dict, xlabel: str, ylabel: str, *, logx: bool = True, logy: bool = True,
                title: str = "") -> Path | None:
    """Line plot of ``series`` {label: (xs, ys)} to ``benchmarks/results/<name>.png`` (None without matplotlib)."""
    plt = pyplot()
    if plt is None:
        return None
    fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
    for label, (xs, ys) in series.items():
        ax.plot(xs, ys, "o-", label=label)
    ax.set_xscale("log" if logx else "linear")
    ax.set_yscale("log" if logy else "linear")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return save_figure(fig, name)


def fit_exponent(xs, ys) -> float:
    """Slope of log(y) against log(x) (least squares): cost ~ x^slope."""
    import numpy as np

    return float(np.polyfit(np.log(np.asarray(xs, float)), np.log(np.asarray(ys, float)), 1)[0])
