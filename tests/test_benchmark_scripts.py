"""Benchmarks stay runnable when code moves (issue 48: two of them failed silently for a round): every module of
benchmarks/ imports, every script answers ``--help``, and every flowsynth name a benchmark imports exists, lazy imports
(inside functions) included. benchmarks/ stays grouped by concern (issue 53): its folders of ``GROUPS``, the shared
``_common.py``, the runner ``run.py`` and ``results/``, nothing else.

Hermetic and quick: one child process runs the scripts one after the other with ``--help`` (argparse prints the usage
and exits before any work), from a temporary folder, with the results folder sent there too
(``FLOWSYNTH_BENCH_RESULTS``); nothing under benchmarks/results changes.
"""

from __future__ import annotations

import ast
import importlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "benchmarks"
# What benchmarks/ holds: a folder per concern (benchmarks/run.py's GROUPS), the shared helpers, the runner, the
# results.
GROUPS = ("speed", "accuracy", "learning", "peers", "device")
TOP = {"_common.py", "run.py", "results"}
# Files of benchmarks/ that this interpreter cannot import, and why.
NOT_HERE = {"_cycles_scene.py": "Blender's own Python runs it (bpy); it imports nothing of flowsynth"}
# Modules of the optional extras (pyproject.toml: bench, ray) a benchmark may need at import; without them it is
# reported as skipped, not failed.
OPTIONAL = {"embreex", "matplotlib", "mitsuba", "pybullet", "skimage", "ray"}
# An issue number in a --help text ("issue 39's goal", "issues 47 and 52", "issue-13"): the text should say what the
# option does; the history lives in docs/decisions/.
ISSUE_NUMBER = re.compile(r"(?i)\bissues?[ -]+#?\d+|#\d+\b")

CHILD = r"""
import contextlib, importlib, io, json, runpy, sys, traceback
from pathlib import Path

results = {}
for path, script, module in json.loads(sys.argv[1]):
    sys.argv = [path, "--help"]
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            if module and not script:  # a module of a package (relative imports): imported, as its users do
                importlib.import_module(module)
            else:
                runpy.run_path(path, run_name="__main__" if script else Path(path).stem)
        results[path] = ["no exit" if script else "ok", out.getvalue()]
    except SystemExit as e:
        results[path] = ["ok" if e.code in (0, None) else f"exit {e.code}", out.getvalue()]
    except ModuleNotFoundError as e:
        results[path] = ["missing", str(e.name)]
    except BaseException:
        results[path] = ["error", traceback.format_exc()[-3000:]]
print(json.dumps(results))
"""


def benchmark_files() -> list[Path]:
    return [p for p in sorted(BENCH.rglob("*.py")) if p.name not in NOT_HERE and "results" not in p.parts]


def module_name(path: Path) -> str | None:
    """The dotted name of a module of a package under benchmarks/ (``learning.runs``, ``learning`` for its
    ``__init__.py``), with benchmarks/ on the path; None for a script outside a package."""
    if not (path.parent / "__init__.py").is_file():
        return None
    parts = path.relative_to(BENCH).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def is_script(source: str) -> bool:
    """Whether the module runs something under ``if __name__ == "__main__":`` (at its top level)."""
    for node in ast.parse(source).body:
        if isinstance(node, ast.If) and isinstance(node.test, ast.Compare) and isinstance(node.test.left, ast.Name) \
                and node.test.left.id == "__name__" and any(isinstance(c, ast.Constant) and c.value == "__main__"
                                                            for c in node.test.comparators):
            return True
    return False


def test_benchmark_files_are_found():
    names = {str(p.relative_to(BENCH)) for p in benchmark_files()}
    assert {"run.py", "speed/hashes.py", "accuracy/physics.py", "_common.py", "learning/protocol.py"} <= names
    assert is_script((BENCH / "run.py").read_text()) and not is_script((BENCH / "_common.py").read_text())
    assert all(len(list(BENCH.rglob(n))) == 1 for n in NOT_HERE)


def _listing(folder: Path) -> set[str]:
    """Names in ``folder`` that git would track (no caches: __pycache__, .pyc)."""
    return {p.name for p in folder.iterdir() if p.name != "__pycache__" and p.suffix != ".pyc"}


def test_benchmarks_stay_grouped_by_concern():
    import importlib.util

    spec = importlib.util.spec_from_file_location("benchmarks_run", BENCH / "run.py")
    run = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(run)
    assert run.GROUPS == GROUPS
    assert _listing(BENCH) == set(GROUPS) | TOP, "benchmarks/ holds its groups, _common.py, run.py and results/ only"
    for group in GROUPS:
        assert {Path(n).suffix for n in _listing(BENCH / group)} == {".py"}, f"benchmarks/{group}/: scripts only"
    assert all(run.script(name).relative_to(BENCH).parts[0] in GROUPS for name in run.BENCHMARKS)
    assert run.script("learning") == BENCH / "learning"  # the learning benchmark is its package, run whole


def test_every_benchmark_imports_and_answers_help(tmp_path):
    files = [[str(p), is_script(p.read_text()), module_name(p)] for p in benchmark_files()]
    before = sorted((p.name, p.stat().st_mtime_ns) for p in (BENCH / "results").iterdir())
    env = dict(os.environ, FLOWSYNTH_BENCH_RESULTS=str(tmp_path / "results"),
               PYTHONPATH=os.pathsep.join([str(REPO), str(BENCH), os.environ.get("PYTHONPATH", "")]))
    r = subprocess.run([sys.executable, "-c", CHILD, json.dumps(files)], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=600, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    results = json.loads(r.stdout.strip().splitlines()[-1])
    assert sorted(results) == sorted(f for f, _, _ in files)
    skipped = {Path(f).name: why for f, (status, why) in results.items()
               if status == "missing" and why.split(".")[0] in OPTIONAL}
    for name, module in skipped.items():
        print(f"skipped {name}: optional module {module} is not installed")
    failed = {Path(f).name: f"{status}: {why[:500]}" for f, (status, why) in results.items()
              if status != "ok" and Path(f).name not in skipped}
    assert not failed, "benchmarks that do not import or answer --help:\n" + "\n\n".join(
        f"{k}: {v}" for k, v in failed.items())
    assert all("usage:" in results[f][1] for f, s, _ in files if s and Path(f).name not in skipped)
    cites = {str(Path(f).relative_to(BENCH)): ISSUE_NUMBER.findall(" ".join(out.split()))
             for f, (status, out) in results.items() if status == "ok"}
    cites = {f: c for f, c in cites.items() if c}
    assert not cites, f"--help texts that cite issue numbers: {cites}"
    assert sorted((p.name, p.stat().st_mtime_ns) for p in (BENCH / "results").iterdir()) == before


def flowsynth_imports(source: str) -> list[tuple[int, str, list[str]]]:
    """(line, module, names) of every import of flowsynth in ``source``, in functions too
    (``import flowsynth.<module>``: names [])."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name, []) for a in node.names if a.name.split(".")[0] == "flowsynth"]
        elif isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").split(".")[0] == "flowsynth":
            found.append((node.lineno, node.module, [a.name for a in node.names]))
    return found


def _missing(module: str, names: list[str]) -> list[str]:
    try:
        mod = importlib.import_module(module)
    except ImportError as e:
        return [f"{module} ({e})"]
    out = []
    for n in names:
        if not hasattr(mod, n):
            try:
                importlib.import_module(f"{module}.{n}")
            except ImportError:
                out.append(f"{module}.{n}")
    return out


def test_checker_sees_lazy_imports_and_missing_names():
    plan = "flowsynth" + ".plan"  # (spelled apart: the repository's name check reads literal dotted names)
    src = f"import flowsynth as fs\n\ndef f():\n    from {plan} import OUTPUTS, NOT_THERE\n"
    assert flowsynth_imports(src) == [(1, "flowsynth", []), (4, plan, ["OUTPUTS", "NOT_THERE"])]
    assert _missing(plan, ["OUTPUTS", "NOT_THERE"]) == [f"{plan}.NOT_THERE"]


def test_every_flowsynth_name_a_benchmark_imports_exists():
    missing = [f"{p.relative_to(REPO)} line {line}: {m}" for p in benchmark_files()
               for line, module, names in flowsynth_imports(p.read_text()) for m in _missing(module, names)]
    assert not missing, "benchmarks import flowsynth names that do not exist:\n" + "\n".join(missing)


def test_as_ci_hides_every_bench_only_module(tmp_path):
    """``scripts/test.sh --as-ci`` hides the modules of pyproject's bench extra that the test extra lacks (CI's
    machine is set up with --ray only), and a hidden module cannot be imported."""
    import re
    import tomllib

    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    dist = {re.split(r"[<>=\[ ]", d)[0] for d in extras["bench"]} - {re.split(r"[<>=\[ ]", d)[0]
                                                                      for d in extras["test"]}
    module = {"scikit-image": "skimage"}  # the distributions whose import name differs
    text = (REPO / "scripts" / "test.sh").read_text()
    hidden = re.search(r"for m in ([\w ]+); do", text)
    assert hidden is not None, "scripts/test.sh --as-ci lost its list of hidden modules"
    assert set(hidden.group(1).split()) == {module.get(d, d) for d in dist} == OPTIONAL - {"ray"}
    # the stand-in it writes makes the import fail as a missing module does (pytest.importorskip skips on it)
    body = re.search(r"echo \"(raise ModuleNotFoundError\(.*?\))\"", text)
    assert body is not None
    (tmp_path / "skimage").mkdir()
    (tmp_path / "skimage" / "__init__.py").write_text(body.group(1).replace("$m", "skimage") + "\n")
    child = subprocess.run([sys.executable, "-c", "import skimage"], capture_output=True, text=True,
                           env={**os.environ, "PYTHONPATH": str(tmp_path)})
    assert child.returncode != 0 and "ModuleNotFoundError" in child.stderr and "--as-ci" in child.stderr


# The learning package's import order (issue 53: before it, learning.py and learning_raft.py imported each other): a
# module imports only modules before it, so there is no circle; the scripts come last.
LEARNING_ORDER = ("sets", "protocol", "pools", "trainers", "runs", "ensemble_rate", "summary", "diagnose",
                  "checkpoints", "cli", "__main__", "magnitudes", "pool_hashes")


def package_imports(source: str, package: str) -> set[str]:
    """Modules of ``package`` that ``source`` imports, lazy imports included: ``from .x import``, ``from . import x``,
    ``from package.x import``, ``from package import x`` and ``import package.x``."""
    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found |= {a.name.split(".")[1] for a in node.names if a.name.startswith(f"{package}.")}
        elif isinstance(node, ast.ImportFrom):
            if node.level == 1 or node.module == package or (node.module or "").startswith(f"{package}."):
                mod = node.module or ""
                if node.level == 0:
                    mod = mod.removeprefix(package).removeprefix(".")
                found |= {mod.split(".")[0]} if mod else {a.name for a in node.names}
    return found


def test_checker_sees_every_form_of_a_package_import():
    src = ("from .sets import a\nfrom . import raft\nimport learning.cli\n"
           "def f():\n    from learning.summary import b\n    from learning import diagnose\nimport os\n")
    assert package_imports(src, "learning") == {"sets", "raft", "cli", "summary", "diagnose"}


def test_learning_package_imports_run_one_way():
    folder = BENCH / "learning"
    files = {p.stem: p for p in folder.glob("*.py") if p.name != "__init__.py"}
    assert set(files) == set(LEARNING_ORDER), "place every module of benchmarks/learning/ in LEARNING_ORDER"
    assert package_imports((folder / "__init__.py").read_text(), "learning") == set()
    climbing = [f"{name} imports {dep}" for k, name in enumerate(LEARNING_ORDER)
                for dep in package_imports(files[name].read_text(), "learning") if dep not in LEARNING_ORDER[:k]]
    assert not climbing, "imports against benchmarks/learning's order (LEARNING_ORDER):\n" + "\n".join(climbing)


def test_each_learning_module_imports_first_in_a_fresh_process():
    """A circle shows when its modules are imported in another order than usual: each module is imported first, alone,
    in a process of its own."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(BENCH), str(REPO), os.environ.get("PYTHONPATH", "")]))
    for name in LEARNING_ORDER[:LEARNING_ORDER.index("cli") + 1]:
        r = subprocess.run([sys.executable, "-c", f"import learning.{name}"], env=env, capture_output=True, text=True,
                           timeout=120, check=False)
        assert r.returncode == 0, f"learning.{name}: {r.stderr[-2000:]}"
