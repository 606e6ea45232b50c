"""benchmarks/results/ holds current readings a newcomer can trace: a quick run never writes there, and every file
there is cited by SUMMARY.md, the docs, a decision record or the code.

A ``--quick`` run (a smoke run) writes to ``_common.QUICK_RESULTS_DIR``, an ignored folder outside the tracked
results; a full run writes ``_common.TRACKED_RESULTS_DIR``. Retired experiments live in
``benchmarks/results/archive/``, which the records that cite them point to.
"""

from __future__ import annotations

import fnmatch
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
RESULTS = BENCH / "results"
ARCHIVE = RESULTS / "archive"
# Where citations are looked for: the repository's text outside benchmarks/results/, and SUMMARY.md (generated from
# the runner's outputs, it names each file it shows).
SCANNED = ("flowsynth", "benchmarks", "docs", "tests", "scripts", "examples")
TEXT = (".py", ".md", ".sh", ".toml", ".yaml", ".txt")
# A results file name, or several in the shell's braces (`learning_raft_summary_{mixture,curriculum}_flowsynth.json`).
# A wildcard (`learning_raft_*.json`, a command's argument) cites nothing: it would cite files nobody reads.
NAME = re.compile(r"[\w{},.-]+\.(?:json|png|txt|log)\b")


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(BENCH))
    try:
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(BENCH))
    return mod


def _braces(pattern: str) -> list[str]:
    """``a_{x,y}.json`` -> [``a_x.json``, ``a_y.json``] (every brace group, as a shell expands it)."""
    m = re.search(r"\{([^{}]*)\}", pattern)
    if m is None:
        return [pattern]
    return [e for alt in m.group(1).split(",") for e in _braces(pattern[:m.start()] + alt + pattern[m.end():])]


def uncited(names: set[str], texts: list[str]) -> set[str]:
    """The file names of ``names`` that no text of ``texts`` cites.

    A file is cited by its exact name (not as the tail of a longer name: ``a.json`` is not cited by ``xa.json``), by
    braces that expand to it (``a_{x,y}.json``), or, for a ``.png`` or ``.txt``, through a cited ``.json`` of the
    same stem (a result's numbers, its plot and its printed table are one result). A wildcard cites nothing."""
    cited: set[str] = set()
    for text in texts:
        for token in NAME.findall(text):
            cited |= names & set(_braces(token))
        cited |= {n for n in names - cited if re.search(r"(?<![\w.-])" + re.escape(n) + r"(?![\w-])", text)}
    cited |= {n for n in names if Path(n).suffix in (".png", ".txt") and f"{Path(n).stem}.json" in cited}
    return names - cited


def _tracked_results() -> set[Path]:
    """The files of benchmarks/results/ outside archive/ (git's tracked ones in a git checkout, else every file)."""
    r = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z", "--", "benchmarks/results"], capture_output=True,
                       text=True) if shutil.which("git") else None
    files = ({ROOT / f for f in r.stdout.split("\0") if f} if r is not None and r.returncode == 0 and r.stdout
             else {p for p in RESULTS.rglob("*") if p.is_file()})
    return {p for p in files if not p.is_relative_to(ARCHIVE) and p.is_file()}


def _citing_texts() -> list[str]:
    paths = [ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "pyproject.toml", RESULTS / "SUMMARY.md"]
    paths += [p for d in SCANNED for p in (ROOT / d).rglob("*") if p.suffix in TEXT and p.is_file()
              and not p.is_relative_to(RESULTS) and p != Path(__file__).resolve()]
    return [p.read_text(errors="replace") for p in paths if p.is_file()]


def test_the_citation_check_finds_what_is_not_cited():
    names = {"a.json", "a.png", "b.png", "c_1.png", "c_2.txt", "d_x.json", "d_y.json", "e.txt", "f.json", "g.log"}
    texts = ["see `a.json` and xf.json", "figures `c_{1,3}.png`", "`d_{x,y}.json`", "the log g.log.", "`*.txt`"]
    assert uncited(names, texts) == {"b.png", "c_2.txt", "e.txt", "f.json"}
    assert _braces("s_{a,b}_{1,2}.json") == ["s_a_1.json", "s_a_2.json", "s_b_1.json", "s_b_2.json"]


def test_every_file_in_the_results_is_cited():
    files = _tracked_results()
    assert len(files) > 20 and RESULTS / "SUMMARY.md" in files
    names = {p.name for p in files if p.parent == RESULTS} - {"SUMMARY.md"}
    nested = sorted(str(p.relative_to(RESULTS)) for p in files if p.parent != RESULTS)
    assert not nested, f"benchmarks/results/ holds files only, and its archive/: {nested}"
    missing = sorted(uncited(names, _citing_texts()))
    assert not missing, ("files of benchmarks/results/ that nothing cites (cite them in a decision record or the "
                         f"docs, or move them to benchmarks/results/archive/ and say so in its README): {missing}")


def test_the_archive_says_what_it_holds():
    readme = (ARCHIVE / "README.md").read_text()
    archived = {p.name for p in ARCHIVE.iterdir() if p.is_file()} - {"README.md"}
    assert len(archived) > 10
    # the README may name a family by a wildcard (`learning_ncc*.json`): it describes the folder, it cites nothing
    patterns = [p for token in re.findall(r"`([^`]+)`", readme) for p in _braces(token)]
    missing = sorted(n for n in archived if not any(fnmatch.fnmatchcase(n, p) for p in patterns))
    assert not missing, f"archive/README.md does not say what these are: {missing}"


def test_quick_results_go_to_an_ignored_folder_outside_the_tracked_results(tmp_path):
    common = _load("bench_common_probe", BENCH / "_common.py")
    quick, full = common.results_dir(True, {}), common.results_dir(False, {})
    assert full.resolve() == RESULTS.resolve() == common.TRACKED_RESULTS_DIR.resolve()
    assert quick.resolve() == common.QUICK_RESULTS_DIR.resolve()
    assert not quick.resolve().is_relative_to(RESULTS.resolve()) and not RESULTS.resolve().is_relative_to(quick)
    assert common.results_dir(True, {"FLOWSYNTH_BENCH_RESULTS": str(tmp_path)}) == tmp_path
    assert common.results_dir(False, {"FLOWSYNTH_BENCH_RESULTS": str(tmp_path)}) == tmp_path
    if shutil.which("git") and (ROOT / ".git").exists():
        def ignored(p: Path) -> bool:
            return subprocess.run(["git", "-C", str(ROOT), "check-ignore", "-q", "--no-index", str(p)]).returncode == 0
        assert ignored(quick / "raycast.json") and not ignored(RESULTS / "raycast.json")
    # argparse accepts an unambiguous prefix of --quick; the choice must too
    assert all(common.is_quick(a) for a in (["--quick"], ["--qui"], ["--samples", "3", "--quick"]))
    assert not any(common.is_quick(a) for a in ([], ["-q"], ["--samples", "3"], ["--", "x"]))


def test_a_process_run_with_quick_chooses_the_quick_folder(tmp_path):
    """A fresh process, as a script runs: ``--quick`` on its command line sends _common's and run.py's results to the
    quick folder; without it, to the tracked results. It only prints the choice, writing nothing."""
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import _common, run; "
            "print(_common.RESULTS_DIR); print(run.RESULTS_DIR)")
    env = {k: v for k, v in os.environ.items() if k != "FLOWSYNTH_BENCH_RESULTS"}
    out = {}
    for flags in ([], ["--quick"]):
        r = subprocess.run([sys.executable, "-c", code, str(BENCH), *flags], cwd=tmp_path, env=env,
                           capture_output=True, text=True, timeout=120, check=True)
        out[bool(flags)] = [Path(line) for line in r.stdout.split()]
    common = _load("bench_common_probe2", BENCH / "_common.py")
    assert out[False] == [common.TRACKED_RESULTS_DIR] * 2
    assert out[True] == [common.QUICK_RESULTS_DIR] * 2


def test_the_runner_sends_a_quick_benchmark_to_its_results_folder(tmp_path, monkeypatch):
    """run.py's ``run_one`` on a stand-in benchmark (a real child process): the child writes its JSON where the runner
    writes (``FLOWSYNTH_BENCH_RESULTS``), and the JSON's machine field records the command, so SUMMARY.md can say
    when, on what and how each table was made."""
    run = _load("bench_run_probe", BENCH / "run.py")
    fake = tmp_path / "benchmarks"
    (fake / "speed").mkdir(parents=True)
    (fake / "speed" / "tiles.py").write_text(
        f"import sys\nsys.path.insert(0, {str(BENCH)!r})\nfrom _common import machine_info, write_json\n"
        "print('wrote', write_json('tiles', {'machine': machine_info(), 'quick': '--quick' in sys.argv}))\n")
    monkeypatch.setattr(run, "HERE", fake)
    before = sorted((p.name, p.stat().st_mtime_ns) for p in RESULTS.iterdir())
    quick = tmp_path / "quick"
    status = run.run_one("tiles", True, quick)
    assert status["returncode"] == 0, status["stderr_tail"]
    data = json.loads((quick / "tiles.json").read_text())
    assert data["machine"]["command"].startswith("python ") and data["machine"]["command"].endswith(
        "benchmarks/speed/tiles.py --quick") and data["quick"]
    assert sorted(p.name for p in quick.iterdir()) == ["tiles.json", "tiles.run.json", "tiles.txt"]
    rec = run.run_record(quick, "tiles")
    assert rec["command"] == "python benchmarks/speed/tiles.py --quick" and rec["status"] == "ok" and rec["machine"]
    (quick / "tiles.run.json").unlink()  # no run record: the JSON's machine field says it
    rec = run.run_record(quick, "tiles")
    assert rec["command"] == data["machine"]["command"] and rec["made"] == data["machine"]["date"]
    assert sorted((p.name, p.stat().st_mtime_ns) for p in RESULTS.iterdir()) == before


@pytest.mark.parametrize("name", ["raycast", "bvh", "cycles"])
def test_summary_says_when_and_how_each_recorded_table_was_made(name):
    run = _load("bench_run_probe3", BENCH / "run.py")
    rec = run.run_record(RESULTS, name)
    assert rec["status"] != "no record" and rec["made"][:4] == "2026" and rec["machine"]
    assert rec["command"].startswith(f"python {run.script(name).relative_to(BENCH.parent)}")
    summary = (RESULTS / "SUMMARY.md").read_text()
    assert f"| {name} | {rec['status']} | {rec['made']} | {rec['machine']} |" in summary
