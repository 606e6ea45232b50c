"""Run every benchmark and write benchmarks/results/SUMMARY.md.

    python benchmarks/run.py [--quick] [--only raycast,scaling]

Each benchmark is a script in this folder that prints its tables and writes results/<name>.json (and PNG
plots for curves). This runner calls them one after the other (each in its own process, so kernel
caches and memory don't leak between them), keeps their printed tables, and writes SUMMARY.md with the
machine, versions, load average and date (with ``--only``, the other benchmarks' sections are kept from the
previous SUMMARY.md). ``--quick`` is passed on to every script (all of them within ~10 min on 2 cores).
"""

from __future__ import annotations

import argparse
import datetime
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _common import RESULTS_DIR, machine_info

BENCHMARKS = ["raycast", "bvh", "accuracy", "physics", "peers_physics", "rgb", "throughput", "export", "ray_export",
              "scaling", "physics_graph", "png_level", "tiles", "outputs_cost", "datastats", "learning",
              "texture", "shading_cost", "cycles"]
# Benchmarks that need an optional outside program print a line starting with this and exit 0 without it
# (cycles: Blender); their row then reads "skipped".
SKIP_MARK = "SKIPPED"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--only", default=None, help="comma-separated subset of " + ",".join(BENCHMARKS))
    args = p.parse_args()
    names = args.only.split(",") if args.only else BENCHMARKS
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    sections, status = [], []
    for name in names:
        script = HERE / f"{name}.py"
        cmd = [sys.executable, str(script)] + (["--quick"] if args.quick else [])
        print(f"== {name}: {' '.join(cmd[1:])}", flush=True)
        t = time.time()
        r = subprocess.run(cmd, capture_output=True, text=True, cwd=HERE.parent)
        dt = time.time() - t
        text = "\n".join(line for line in r.stdout.splitlines() if "CUDA" not in line)
        print(text, flush=True)
        ok = r.returncode == 0
        skipped = ok and any(line.startswith(SKIP_MARK) for line in r.stdout.splitlines())
        status.append((name, ok, dt, skipped))
        (RESULTS_DIR / f"{name}.txt").write_text(text + ("" if ok else "\n" + r.stderr[-4000:]))
        plots = sorted(x.name for x in RESULTS_DIR.glob(f"{name}*.png"))
        verdict = ("skipped" if skipped else "ok") if ok else f"FAILED (exit {r.returncode})"
        body = f"## {name}\n\n`python benchmarks/{name}.py{' --quick' if args.quick else ''}` — " \
               f"{verdict} in {dt:.0f} s; JSON: " \
               f"[results/{name}.json]({name}.json)\n\n```\n{text.strip()}\n```\n"
        body += "".join(f"\n![{pl}]({pl})\n" for pl in plots)
        if not ok:
            body += f"\n```\n{r.stderr.strip()[-2000:]}\n```\n"
        sections.append(body)
    m = machine_info()
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    kept_rows, kept_sections = _kept(names) if args.only else ({}, {})
    head = ["# Benchmark summary", "",
            f"Date: {datetime.datetime.now().isoformat(timespec='seconds')}" +
            (f" (sections {', '.join(names)}; the others are kept from the previous run)" if args.only else "") +
            "  ",
            f"Machine: {m.get('cpu_model')} — {m.get('cpu_count')} CPUs, {m.get('platform')}; load average at the "
            f"end {load} (the machine is shared)  ",
            f"Python {m.get('python')}; " + ", ".join(f"{k} {m.get(k)}" for k in ("torch", "warp-lang", "newton",
                                                                               "numpy", "trimesh")) + "  ",
            f"Mode: {'--quick' if args.quick else 'full'}", "",
            "| benchmark | status | seconds |", "|---|---|---|"]
    rows = {n: f"| {n} | {('skipped' if sk else 'ok') if ok else 'FAILED'} | {dt:.0f} |" for n, ok, dt, sk in status}
    done = dict(zip(names, sections))
    order = [n for n in BENCHMARKS if n in rows or n in kept_rows]
    order += [n for n in [*kept_rows, *names] if n not in order]
    head += [rows.get(n) or kept_rows[n] for n in order]
    body = [done.get(n) or kept_sections.get(n, "") for n in order]
    (RESULTS_DIR / "SUMMARY.md").write_text("\n".join(head) + "\n\n" + "\n".join(b for b in body if b))
    print(f"wrote {RESULTS_DIR / 'SUMMARY.md'}")
    return 0 if all(ok for _, ok, _, _ in status) else 1


def _kept(names: list[str]) -> tuple[dict, dict]:
    """Status rows and sections of the previous SUMMARY.md for the benchmarks not run now (``--only``)."""
    path = RESULTS_DIR / "SUMMARY.md"
    if not path.exists():
        return {}, {}
    text = path.read_text()
    rows = {line.split("|")[1].strip(): line for line in text.splitlines() if line.startswith("| ")
            and not line.startswith("| benchmark")}
    sections = {}
    for part in text.split("\n## ")[1:]:
        name = part.split("\n", 1)[0].strip()
        sections[name] = "## " + part.rstrip("\n") + "\n"
    return ({k: v for k, v in rows.items() if k not in names}, {k: v for k, v in sections.items() if k not in names})


if __name__ == "__main__":
    sys.exit(main())
