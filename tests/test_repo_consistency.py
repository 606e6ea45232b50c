"""The repository stays consistent: documents do not point at files that are not there, and tests do not skip what they
need.

Every relative link in README.md, docs/*.md, the decision records and the results archive's README resolves (relative to
the document), and every file path the code, benchmarks, tests and documents mention (``docs/...``, ``flowsynth/...``,
``benchmarks/...``, ..., relative to the repository root) exists, except the results a benchmark says it writes. A bare
``DESIGN.md`` is a reference to a file this repository does not have: cite docs/ instead. Tests import their required
dependencies (runtime and the `test` extra) plainly, so a missing one fails instead of skipping.
"""

from __future__ import annotations

import importlib
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "docs" / "decisions").glob("*.md")),
        ROOT / "benchmarks" / "results" / "archive" / "README.md"]
SOURCES = [p for pattern in ("flowsynth/**/*.py", "benchmarks/**/*.py", "tests/*.py", "examples/*.py", "scripts/*",
                             "docs/*.md", "README.md", "pyproject.toml", ".ci/*")
           for p in sorted(ROOT.glob(pattern)) if p.is_file() and p != Path(__file__).resolve()]
# [text](target) and ![alt](target); the target ends at whitespace or ")"
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
# a repository path: a top-level folder, then path characters, ending in a file extension
PATH = re.compile(r"(?<![\w./-])((?:docs|flowsynth|benchmarks|tests|scripts|examples)/[\w./-]*\.(?:md|py|json|png|"
                  r"txt|sh|toml|svg))(?![\w/-])")
DESIGN = re.compile(r"(?<![\w/])DESIGN\.md")


def test_scanned_files_exist():
    assert len(DOCS) >= 4 and len(SOURCES) > 40


def test_markdown_links_resolve():
    broken = []
    for doc in DOCS:
        for target in LINK.findall(doc.read_text()):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue  # http(s), mailto, in-page anchors
            path = (doc.parent / target.split("#")[0]).resolve()
            if not path.exists():
                broken.append(f"{doc.relative_to(ROOT)}: {target}")
    assert not broken, "links to missing files:\n" + "\n".join(broken)


def test_file_references_exist():
    missing = []
    for src in SOURCES:
        text = src.read_text(errors="replace")
        for ref in PATH.findall(text):
            if src.relative_to(ROOT).parts[0] == "benchmarks" and ref.startswith("benchmarks/results/"):
                continue  # a benchmark naming the results it writes (which a run creates)
            if not (ROOT / ref.rstrip(".")).exists():
                missing.append(f"{src.relative_to(ROOT)}: {ref}")
        if DESIGN.search(text):
            missing.append(f"{src.relative_to(ROOT)}: DESIGN.md (not in this repository; cite docs/)")
    assert not missing, "references to missing files:\n" + "\n".join(missing)


def test_the_checks_catch_a_broken_reference():
    assert PATH.findall("see docs/nowhere.md, and flowsynth/io/png.py.") == ["docs/nowhere.md", "flowsynth/io/png.py"]
    assert LINK.findall("[a](docs/x.md#y) ![b](p.png)") == ["docs/x.md#y", "p.png"]
    assert DESIGN.search("(DESIGN.md section 3)") and not DESIGN.search("docs/DESIGN.md")


def _optional_extras() -> set[str]:
    """Distribution names in pyproject.toml's optional extras other than `test` (which the tests require)."""
    text = (ROOT / "pyproject.toml").read_text()
    section = text.split("[project.optional-dependencies]", 1)[1].split("\n[", 1)[0]  # tomllib needs 3.11
    extras = dict(re.findall(r"^(\w+)\s*=\s*\[(.*?)\]\s*$", section, flags=re.M | re.S))  # a list may span lines
    names = {name: {re.split(r"[\[<>=!~ ;]", req, maxsplit=1)[0].lower() for req in re.findall(r"\"([^\"]+)\"", reqs)}
             for name, reqs in extras.items()}
    return set().union(*(v for k, v in names.items() if k != "test")) - names["test"]  # in test too: required


def test_required_dependencies_are_imported_not_skipped():
    # A missing required dependency (runtime or the `test` extra) must fail the suite, not skip tests; only a
    # package of another optional extra (ray, bench) may be skipped for.
    optional = _optional_extras()
    offenders = [f"{p.relative_to(ROOT)}:{n}: {line.strip()}" for p in sorted((ROOT / "tests").glob("*.py"))
                 if p != Path(__file__).resolve()
                 for n, line in enumerate(p.read_text().splitlines(), 1)
                 for mod in re.findall(r"importorskip\(\s*[\"']([\w.]+)", line)
                 if mod.split(".")[0].lower() not in optional]
    assert not offenders, "pytest.importorskip hides a missing required dependency: " + ", ".join(offenders)
    assert {"ray", "matplotlib", "embreex"} <= optional
    assert not {"torchdata", "webdataset", "opencv-python-headless"} & optional


DOTTED = re.compile(r"(?<![\w/])flowsynth(?:\.\w+)+")


def _resolves(name: str) -> bool:
    """``flowsynth.a.b.C`` names a module, or an attribute of the longest importable module prefix."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def test_dotted_names_resolve():
    # "flowsynth.renderer.shading.pack_materials" in a docstring or document names something that exists.
    stale = sorted({f"{src.relative_to(ROOT)}: {name}" for src in SOURCES if src.suffix in (".py", ".md")
                    for name in DOTTED.findall(src.read_text()) if not _resolves(name.rstrip("."))})
    assert not stale, "names of things that do not exist:\n" + "\n".join(stale)
    assert not _resolves("flowsynth.renderer.shading.no_such_function") and _resolves("flowsynth.plan.OUTPUTS")
