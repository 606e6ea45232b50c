"""Run every benchmark and write benchmarks/results/SUMMARY.md, a generated file.

    python benchmarks/run.py [--quick] [--only raycast,scaling]
    python benchmarks/run.py --summary-only          # rebuild SUMMARY.md from the recorded outputs, run nothing

Each benchmark is a script in a folder of this one, by concern (``GROUPS``: speed/, accuracy/, learning/, peers/,
device/), that prints its tables and writes results/<name>.json (and PNG plots for curves). This runner calls them
one after the other (each in its own process, so kernel caches and memory don't leak between them), keeps each one's
printed tables in results/<name>.txt and how it ran (command, exit status, seconds, date) in results/<name>.run.json,
and then builds SUMMARY.md from those files alone: the machine, versions, load average and date, a table of when
each benchmark's results were made, on what machine and by which command, and every benchmark's last recorded output.
``--quick`` is passed on to every script (all of them within ~10 min on 2 cores), and a quick run writes everything,
SUMMARY.md included, to ``.cache/bench-quick/`` (``_common.QUICK_RESULTS_DIR``, ignored by git): only a full run
writes the tracked ``benchmarks/results/``. Every script runs with ``FLOWSYNTH_BENCH_RESULTS`` set to the folder
this runner writes.

What this runner owns: exactly the files under ``RESULTS_DIR`` named by ``OWNED``. Everything it writes goes
through ``_write``, which refuses any other path. SUMMARY.md holds no hand-written text: the readings of a run
and the decisions taken on them live in docs/decisions/ (one file per decision), where no runner writes.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _common import RESULTS_DIR, machine_info

GROUPS = ("speed", "accuracy", "learning", "peers", "device")  # the folders of benchmarks/, by concern
BENCHMARKS = ["raycast", "bvh", "accuracy", "physics", "peers_physics", "rgb", "throughput", "export", "ray_export",
              "scaling", "physics_graph", "png_level", "tiles", "outputs_cost", "datastats", "learning",
              "texture", "shading_cost", "cycles", "start_methods", "precision", "layers_equivalence"]
# Benchmarks that need an optional outside program print a line starting with this and exit 0 without it
# (cycles: Blender); their row then reads "skipped".
SKIP_MARK = "SKIPPED"
# The only files this runner may write, as patterns relative to the results folder.
OWNED = ("SUMMARY.md", "{name}.txt", "{name}.run.json")


def _owned(results: Path, path: Path) -> bool:
    """Whether ``path`` is one of ``OWNED`` directly inside ``results`` for a name in ``BENCHMARKS``."""
    if path.resolve().parent != results.resolve():
        return False
    allowed = {"SUMMARY.md"} | {p.format(name=n) for p in OWNED[1:] for n in BENCHMARKS}
    return path.name in allowed


def _write(results: Path, path: Path, text: str) -> None:
    """Write ``text`` to ``path`` if this runner owns it (``_owned``); raise PermissionError otherwise."""
    if not _owned(results, path):
        raise PermissionError(f"benchmarks/run.py does not write {path}: it owns only {OWNED} in {results}")
    results.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def script(name: str) -> Path:
    """What runs benchmark ``name``: ``benchmarks/<group>/<name>.py`` for the one group of ``GROUPS`` holding it, or the
    group ``benchmarks/<name>`` itself where it is a package run as a whole (its ``__main__.py``: learning)."""
    found = [HERE / g / f"{name}.py" for g in GROUPS if (HERE / g / f"{name}.py").is_file()]
    found += [HERE / name] if name in GROUPS and (HERE / name / "__main__.py").is_file() else []
    if len(found) != 1:
        raise FileNotFoundError(f"benchmark {name!r}: {len(found)} scripts of that name in {GROUPS}")
    return found[0]


def run_one(name: str, quick: bool, results: Path = RESULTS_DIR) -> dict:
    """Run ``benchmarks/<group>/<name>.py`` in a fresh process; record its output and status. Returns the status
    dict."""
    path = script(name)
    cmd = [sys.executable, str(path)] + (["--quick"] if quick else [])
    print(f"== {name}: {' '.join(cmd[1:])} (results in {results})", flush=True)
    t = time.time()
    env = dict(os.environ, FLOWSYNTH_BENCH_RESULTS=str(results.resolve()))
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=HERE.parent, env=env)
    text = "\n".join(line for line in r.stdout.splitlines() if "CUDA" not in line)
    print(text, flush=True)
    status = {"command": f"python {path.relative_to(HERE.parent)}" + (" --quick" if quick else ""),
              "returncode": r.returncode, "seconds": round(time.time() - t, 1),
              "skipped": r.returncode == 0 and any(line.startswith(SKIP_MARK) for line in r.stdout.splitlines()),
              "date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": _machine_line(machine_info()),
              "stderr_tail": r.stderr[-2000:]}
    _write(results, results / f"{name}.txt", text + ("" if r.returncode == 0 else "\n" + r.stderr[-4000:]))
    _write(results, results / f"{name}.run.json", json.dumps(status, indent=2) + "\n")
    return status


def _status(results: Path, name: str) -> dict | None:
    path = results / f"{name}.run.json"
    return json.loads(path.read_text()) if path.exists() else None


def _machine_line(m: dict) -> str:
    """``machine_info()`` in a few words: the CPU model, its CPUs, and how many the run could use where fewer."""
    total, allowed = m.get("cpu_count"), m.get("cpus_allowed")
    cpus = "" if not total else f", {total} CPUs" if allowed in (None, total) else (
        f", pinned to {allowed} of {total} CPUs")
    return f"{m.get('cpu_model') or 'unknown CPU'}{cpus}"


def run_record(results: Path, name: str) -> dict:
    """When, on what and by which command benchmark ``name``'s results in ``results`` were made: {"status", "made",
    "machine", "command", "note", "seconds", "source"}.

    From this runner's record (``results/<name>.run.json``) where there is one; else from the ``machine`` field of
    the benchmark's JSON (``results/<name>.json``, written by ``_common.machine_info``: its date, CPU, and the
    command where the JSON records it, else the script with ``--quick`` where the JSON says it was a quick run);
    else every field says there is no record."""
    st = _status(results, name)
    if st is not None:
        ok = st["returncode"] == 0
        return {"status": ("skipped" if st.get("skipped") else "ok") if ok else f"FAILED (exit {st['returncode']})",
                "made": st["date"], "machine": st.get("machine", "not recorded"), "command": st["command"],
                "note": "", "seconds": f"{st['seconds']:.0f}", "source": f"{name}.run.json"}
    path = results / f"{name}.json"
    data = json.loads(path.read_text()) if path.exists() else {}
    m = data.get("machine") if isinstance(data.get("machine"), dict) else None
    if m is None:
        return {"status": "no record", "made": "", "machine": "", "command": "", "note": "", "seconds": "",
                "source": ""}
    command, note = m.get("command"), ""
    if not command:
        command = f"python {script(name).relative_to(HERE.parent)}" + (" --quick" if data.get("quick") else "")
        note = "" if "quick" in data else " (flags not recorded)"
    return {"status": "not run by run.py", "made": m.get("date", "not recorded"), "machine": _machine_line(m),
            "command": command, "note": note, "seconds": "", "source": f"{name}.json"}


def plots(results: Path, name: str) -> list[Path]:
    """The plots of benchmark ``name``: ``results/<name>.png`` and ``results/<name>_*.png``, less those of a benchmark
    whose name extends this one (``physics_graph`` is not ``physics``) and the learning judge's readings
    (``learning_raft_*``, which docs/decisions/ cite)."""
    longer = [n for n in BENCHMARKS if n != name and n.startswith(name + "_")]
    found = [results / f"{name}.png"] + sorted(results.glob(f"{name}_*.png"))
    return [p for p in found if p.is_file() and not any(p.name.startswith(n) for n in longer)
            and not p.name.startswith("learning_raft_")]


def summary_text(results: Path, names: list[str], mode: str) -> str:
    """SUMMARY.md built from ``results/<name>.txt`` and ``results/<name>.run.json`` of every benchmark."""
    m = machine_info()
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    head = ["# Benchmark summary (generated)", "",
            "Written by `python benchmarks/run.py`; every edit here is lost at its next run. The readings of these "
            "tables and the decisions taken on them are in [docs/decisions/](../../docs/decisions/README.md).", "",
            f"Written: {datetime.datetime.now().isoformat(timespec='seconds')} ({mode})  ",
            f"Machine writing this file (each table names its own): {m.get('cpu_model')} — {m.get('cpu_count')} "
            f"CPUs, {m.get('platform')}; load average {load} (the machine is shared)  ",
            f"Python {m.get('python')}; " + ", ".join(f"{k} {m.get(k)}" for k in ("torch", "warp-lang", "newton",
                                                                               "numpy", "trimesh")), "",
            "When each benchmark's results were made, on what machine and by which command: from run.py's record "
            "of the run (`<name>.run.json`) where there is one, else from the `machine` field of the benchmark's "
            "JSON. A command with `--quick` is a smoke run's numbers. A quick run of this runner writes to "
            "`.cache/bench-quick/`, never here.", "",
            "| benchmark | status | made | machine | command | seconds | record |", "|---|---|---|---|---|---|---|"]
    body = []
    for name in names:
        rec, txt = run_record(results, name), results / f"{name}.txt"
        command = f"`{rec['command']}`{rec['note']}" if rec["command"] else ""
        source = f"[{rec['source']}]({rec['source']})" if rec["source"] else ""
        head.append(f"| {name} | {rec['status']} | {rec['made']} | {rec['machine']} | {command} | {rec['seconds']} "
                    f"| {source} |")
        section = [f"## {name}", "", f"JSON: [results/{name}.json]({name}.json)" if (results / f"{name}.json").exists()
                   else "No JSON recorded."]
        section += [f"Output: [results/{name}.txt]({name}.txt)" if txt.exists() else "No output recorded."]
        section += ["", "```", txt.read_text().strip() if txt.exists() else "(no output recorded)", "```"]
        section += [f"\n![{pl.name}]({pl.name})" for pl in plots(results, name)]
        body.append("\n".join(section) + "\n")
    return "\n".join(head) + "\n\n" + "\n".join(body)


def write_summary(results: Path, names: list[str], mode: str) -> Path:
    """Write ``results/SUMMARY.md`` (``summary_text``) and return its path."""
    path = results / "SUMMARY.md"
    _write(results, path, summary_text(results, names, mode))
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--only", default=None, help="comma-separated subset of " + ",".join(BENCHMARKS))
    p.add_argument("--summary-only", action="store_true", help="run nothing; rebuild SUMMARY.md from results/")
    p.add_argument("--results", type=Path, default=RESULTS_DIR, help=argparse.SUPPRESS)  # tests: a copy
    args = p.parse_args(argv)
    names = args.only.split(",") if args.only else BENCHMARKS
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        p.error(f"unknown benchmark(s) {unknown}; choose from {BENCHMARKS}")
    status = [] if args.summary_only else [run_one(name, args.quick, args.results) for name in names]
    mode = "rebuilt from recorded outputs" if args.summary_only else (
        f"ran {', '.join(names)}{' --quick' if args.quick else ''}")
    path = write_summary(args.results, BENCHMARKS, mode)
    print(f"wrote {path}")
    return 0 if all(s["returncode"] == 0 for s in status) else 1


if __name__ == "__main__":
    sys.exit(main())
