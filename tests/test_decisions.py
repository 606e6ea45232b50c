"""docs/decisions/: every decision cited exists and is complete, and the benchmark runner cannot write there.

A decision record (a numbered file in docs/decisions/, ``NNNN-name.md``) holds the reading of a benchmark and what
was decided on it.
benchmarks/run.py regenerates benchmarks/results/SUMMARY.md; before issue 41 hand-written readings lived there and
a run erased them. These tests hold the split: records complete and cited correctly, the runner's writer confined
to the files it owns.
"""

from __future__ import annotations

import hashlib
import importlib.util
import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DECISIONS = ROOT / "docs" / "decisions"
SECTIONS = ("Context", "Options measured", "Choice", "Numbers", "Commit", "Revisit")
CITE = re.compile(r"docs/decisions/(\d{4}-[A-Za-z0-9_\-]+\.md)")
SCANNED = ("flowsynth", "benchmarks", "docs", "tests", "scripts", "examples")


def _records() -> list[Path]:
    return sorted(DECISIONS.glob("[0-9][0-9][0-9][0-9]-*.md"))


def _sections(text: str) -> dict[str, str]:
    """{section name: body}; a heading may qualify its name after a colon ('## Choice: the protocol')."""
    parts = re.split(r"(?m)^## +(.+?)\s*$", text)
    return {parts[i].split(":")[0].strip(): parts[i + 1] for i in range(1, len(parts) - 1, 2)}


def _cited() -> dict[str, list[str]]:
    """{decision file name: [files citing it]} over the repository's source and docs."""
    files = [ROOT / "README.md"] + [p for d in SCANNED if (ROOT / d).is_dir() for p in (ROOT / d).rglob("*")
                                    if p.suffix in (".py", ".md", ".sh", ".toml", ".yaml") and p.is_file()]
    cited: dict[str, list[str]] = {}
    for path in files:
        for name in CITE.findall(path.read_text(errors="replace")):
            cited.setdefault(name, []).append(str(path.relative_to(ROOT)))
    return cited


def test_there_are_decisions_and_code_cites_them():
    assert len(_records()) >= 10
    cited = _cited()
    # the library's own comments point at records (not only the docs)
    assert any(f.startswith("flowsynth/") for users in cited.values() for f in users)


def test_every_cited_decision_exists():
    missing = {name: users for name, users in _cited().items() if not (DECISIONS / name).is_file()}
    assert not missing, f"cited decision files that do not exist: {missing}"


def test_nothing_cites_the_generated_summary_for_a_reading():
    """SUMMARY.md is regenerated whole; a comment citing a section of it for a number cites text that a run
    erases. The summary itself may be named (README: where the tables are), but not as '(SUMMARY.md, section)'."""
    bad = []
    for d in ("flowsynth", "benchmarks", "docs"):
        for p in (ROOT / d).rglob("*"):
            if p.suffix in (".py", ".md") and p.is_file() and "decisions" not in p.parts:
                for k, line in enumerate(p.read_text().splitlines(), 1):
                    if re.search(r"SUMMARY\.md`?\)?,? *\(?[a-z_]+\)", line):
                        bad.append(f"{p.relative_to(ROOT)}:{k}")
    assert not bad, f"cite docs/decisions/NNNN-*.md instead of a SUMMARY.md section: {bad}"


@pytest.mark.parametrize("path", _records(), ids=lambda p: p.name)
def test_decision_has_every_section_and_its_number(path: Path):
    text = path.read_text()
    number = path.name[:4]
    assert re.match(rf"# {number}\. \S", text), f"{path.name}: the title must read '# {number}. <decision>'"
    sections = _sections(text)
    for name in SECTIONS:
        assert name in sections, f"{path.name}: no '## {name}' section"
        assert sections[name].strip(), f"{path.name}: '## {name}' is empty"
    assert re.search(r"\b[0-9a-f]{7,40}\b", sections["Commit"]), f"{path.name}: '## Commit' names no commit"


def test_decision_numbers_are_unique_and_indexed():
    records = _records()
    numbers = [p.name[:4] for p in records]
    assert len(numbers) == len(set(numbers)), f"two records share a number: {numbers}"
    index = (DECISIONS / "README.md").read_text()
    assert [p.name for p in records if f"]({p.name})" not in index] == [], "docs/decisions/README.md misses a record"


def _git_ok() -> bool:
    if shutil.which("git") is None:
        return False
    r = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--is-inside-work-tree"], capture_output=True, text=True)
    return r.returncode == 0 and r.stdout.strip() == "true"


@pytest.mark.skipif(not _git_ok(), reason="not a git checkout: commit hashes cannot be checked")
@pytest.mark.parametrize("path", _records(), ids=lambda p: p.name)
def test_decision_commits_exist_in_history(path: Path):
    commits = re.findall(r"\b[0-9a-f]{7,40}\b", _sections(path.read_text())["Commit"])
    for c in commits:
        r = subprocess.run(["git", "-C", str(ROOT), "cat-file", "-e", f"{c}^{{commit}}"], capture_output=True)
        assert r.returncode == 0, f"{path.name}: commit {c} is not in this repository's history"


def _run_module():
    spec = importlib.util.spec_from_file_location("benchmarks_run", ROOT / "benchmarks" / "run.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_runner_writer_refuses_every_path_it_does_not_own(tmp_path: Path):
    run = _run_module()
    results = tmp_path / "results"
    results.mkdir()
    for target in (DECISIONS / "0001-per-asset-bvh4.md", DECISIONS / "README.md", tmp_path / "SUMMARY.md",
                   results / "notes.md", results / "raycast.json", results / ".." / "results2" / "SUMMARY.md"):
        with pytest.raises(PermissionError):
            run._write(results, target, "x")
    run._write(results, results / "SUMMARY.md", "generated")
    run._write(results, results / "raycast.txt", "table")
    assert sorted(p.name for p in results.iterdir()) == ["SUMMARY.md", "raycast.txt"]


def test_summary_rebuild_writes_only_summary_and_leaves_decisions_alone(tmp_path: Path):
    """run.py --summary-only on a copy of the recorded outputs: SUMMARY.md is the one file that changes, it carries
    every recorded table, and docs/decisions/ is byte-for-byte unchanged."""
    run = _run_module()
    results = tmp_path / "results"
    results.mkdir()
    src = ROOT / "benchmarks" / "results"
    for p in list(src.glob("*.txt")) + list(src.glob("*.run.json")):
        shutil.copy(p, results / p.name)
    (results / "SUMMARY.md").write_text("# hand-written text that a rebuild must replace\n")
    before_results, before_decisions = _digest(results), _digest(DECISIONS)
    assert run.main(["--summary-only", "--results", str(results)]) == 0
    after = _digest(results)
    changed = sorted(k for k in after if after[k] != before_results.get(k))
    assert changed == ["SUMMARY.md"]
    assert _digest(DECISIONS) == before_decisions
    summary = (results / "SUMMARY.md").read_text()
    assert "hand-written text" not in summary
    for txt in results.glob("*.txt"):
        name = txt.stem
        if name in run.BENCHMARKS:
            assert f"## {name}\n" in summary and txt.read_text().strip()[:200] in summary


def test_checked_in_summary_is_the_generated_form():
    text = (ROOT / "benchmarks" / "results" / "SUMMARY.md").read_text()
    assert text.startswith("# Benchmark summary (generated)"), "SUMMARY.md was edited by hand or by an old runner"
    assert "Reading (added by hand)" not in text
