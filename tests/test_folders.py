"""Folders hand on what the layers above them use (docs/architecture.md, Layers): each folder's __init__.py says in two
or three lines what the folder is, lists its exports in ``__all__``, and code outside a folder imports those exports,
never a module inside the folder, unless the folder exports that module by name (``kernels``' families,
``io.layouts``). Checked on flowsynth/, benchmarks/, examples/ and scripts/; tests may reach inside a folder."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest
from test_layers import PACKAGE, REPO, folders_of, module_files

FOLDERS = sorted(folders_of(module_files()))
CHECKED = ("benchmarks", "examples", "scripts")


def exports_of(folder: str, root: Path = REPO) -> list[str]:
    """The ``__all__`` of a folder's __init__.py, as written (a literal list or tuple); [] without one."""
    tree = ast.parse((root / PACKAGE / folder / "__init__.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
            return list(ast.literal_eval(node.value))
    return []


def _imported_by_name(node: ast.AST) -> str | None:
    """The literal module name of an ``importlib.import_module("...")`` / ``__import__("...")`` call, else None."""
    if not (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)):
        return None
    f = node.func
    if (isinstance(f, ast.Attribute) and f.attr == "import_module") or (
            isinstance(f, ast.Name) and f.id in ("import_module", "__import__")):
        return node.args[0].value
    return None


def reach_ins(source: str, own: str | None, exports: dict[str, list[str]]) -> list[str]:
    """Imports of ``source`` (code in folder ``own``, or in none: None) that go around another folder's exports: a
    module inside the folder that the folder does not export by name, or a name it does not export. Lazy imports and
    ``import_module`` with a literal name count."""
    found = []
    for node in ast.walk(ast.parse(source)):
        targets: list[tuple[str, list[str]]] = []
        if isinstance(node, ast.Import):
            targets = [(a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            targets = [(node.module, [a.name for a in node.names])]
        elif _imported_by_name(node):
            targets = [(_imported_by_name(node), [])]
        for mod, names in targets:
            parts = mod.split(".")
            if parts[0] != PACKAGE or len(parts) == 1 or parts[1] not in exports or parts[1] == own:
                continue  # not flowsynth, the package itself (fs.*, a folder, a root module), or the own folder
            folder = parts[1]
            if len(parts) == 2:
                found += [f"line {node.lineno}: {n} is not exported by {folder}/" for n in names
                          if n not in exports[folder]]
            elif parts[2] not in exports[folder]:
                found.append(f"line {node.lineno}: {mod} is inside {folder}/, which does not export {parts[2]!r}")
    return found


def _src(code: str) -> str:
    """Made-up code naming the package as PKG (so that the repository's name checks do not read it as a real path)."""
    return code.replace("PKG", PACKAGE)


def test_checker_reports_imports_around_a_folders_exports():
    exports = {"io": ["read_flo", "layouts"], "kernels": ["raycast"]}
    fine = _src("import PKG\nfrom PKG import io, plan\nfrom PKG.io import read_flo\nfrom PKG.plan import OUTPUTS\n"
                "from PKG.kernels.raycast import k\nfrom PKG.io.layouts.webdataset import decode\n"
                "def f():\n    from PKG.io import layouts\n")
    assert reach_ins(fine, None, exports) == []
    bad = _src("from PKG.io.flo import read_flo\ndef f():\n    from PKG.io import write_flo\n"
               "import importlib\nm = importlib.import_module('PKG.kernels.blas')\n")
    assert reach_ins(bad, None, exports) == [
        f"line 1: {PACKAGE}.io.flo is inside io/, which does not export 'flo'",
        "line 3: write_flo is not exported by io/",
        f"line 5: {PACKAGE}.kernels.blas is inside kernels/, which does not export 'blas'"]
    assert reach_ins(bad, "io", exports) == [reach_ins(bad, None, exports)[-1]]  # a folder's own modules: fine


def _checked_files() -> list[tuple[Path, str | None]]:
    """(file, its folder or None) of every Python file the rule covers."""
    files = [(p, p.relative_to(REPO / PACKAGE).parts[0] if len(p.relative_to(REPO / PACKAGE).parts) > 1 else None)
             for p in sorted((REPO / PACKAGE).rglob("*.py"))]
    return files + [(p, None) for d in CHECKED for p in sorted((REPO / d).rglob("*.py"))]


def test_code_outside_a_folder_imports_its_exports():
    exports = {f: exports_of(f) for f in FOLDERS}
    found = [f"{p.relative_to(REPO)} {problem}" for p, own in _checked_files()
             for problem in reach_ins(p.read_text(), own, exports)]
    assert not found, ("imports that reach inside a folder (import what its __init__.py exports, or export it "
                       "there):\n" + "\n".join(found))


@pytest.mark.parametrize("folder", FOLDERS)
def test_a_folder_says_what_it_is_in_two_or_three_lines(folder):
    doc = ast.get_docstring(ast.parse((REPO / PACKAGE / folder / "__init__.py").read_text()))
    assert doc, f"{folder}/__init__.py has no docstring"
    assert 2 <= len(doc.strip().splitlines()) <= 3, f"{folder}/__init__.py's docstring: two or three lines\n{doc}"


@pytest.mark.parametrize("folder", FOLDERS)
def test_every_export_of_a_folder_exists(folder):
    names = exports_of(folder)
    assert names, f"{folder}/__init__.py lists no __all__"
    pkg = importlib.import_module(f"{PACKAGE}.{folder}")
    missing = []
    for name in names:
        if not hasattr(pkg, name):
            try:  # a module the folder exports by name (imported on first use)
                importlib.import_module(f"{PACKAGE}.{folder}.{name}")
            except ModuleNotFoundError:
                missing.append(name)
    assert missing == [], f"{folder}/__init__.py's __all__ names what it does not have: {missing}"
