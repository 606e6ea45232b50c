"""The layer contract of docs/architecture.md, checked on the source: imports point one way, at the level of folders
and of modules; no cycles, no private names across modules.

Every module of flowsynth/ is parsed with ``ast``; every import counts, top-level or inside a function (lazy), and
``importlib.import_module("flowsynth.<module>")`` with a literal name too. The contract is the ```layers block of
docs/architecture.md, top to bottom. Its unindented lines are the folder level: a folder (``scene/``) or a module of
the package's root (``cli``); a folder's indented lines below it order its own modules. A folder or root module
imports only lower lines of the folder level, and a module only its own entry (a package such as ``io.layouts`` with
its submodules) or lower lines of the module level; never a higher line, nor a sibling (``a | b`` on one line).
No private name (one leading underscore) is imported or read across modules, in flowsynth/ and in benchmarks/.

The checker's functions are tested on made-up graphs first, so each rule is shown to fail when it should.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "flowsynth"
ARCHITECTURE = REPO / "docs" / "architecture.md"

# Edges that break the contract today and are being removed by other work; each is printed when the test runs.
# The lead removes an entry once its work has landed: the test then fails if the edge comes back.
TEMPORARY_EXCEPTIONS: dict[tuple[str, str], str] = {}


# --- the checker -------------------------------------------------------------------------------------------------

def module_files(root: Path = REPO, package: str = PACKAGE) -> dict[str, Path]:
    """{dotted module name: file} of every module of the package (a package by its __init__.py)."""
    out = {}
    for p in sorted((root / package).rglob("*.py")):
        parts = list(p.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _resolve(name: str, modules) -> str | None:
    """The module a dotted import name loads: itself, or the nearest enclosing module (a name in a package)."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def imports_of(source: str, module: str, modules, is_package: bool = False) -> set[str]:
    """Modules of ``modules`` that ``source`` (the code of ``module``) imports anywhere: top level, in functions,
    relative imports, and ``importlib.import_module`` / ``__import__`` calls with a literal name."""
    out = set()
    for node in ast.walk(ast.parse(source)):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[:len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            # ``from pkg import sub`` loads pkg.sub when that is a module, else pkg itself
            names = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in modules else mod for a in node.names]
        elif (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
              and isinstance(node.args[0].value, str)
              and ((isinstance(node.func, ast.Attribute) and node.func.attr == "import_module")
                   or (isinstance(node.func, ast.Name) and node.func.id in ("import_module", "__import__")))):
            names = [node.args[0].value]
        for n in names:
            target = _resolve(n, modules)
            if target is not None and target != module:
                out.add(target)
    return out


def import_graph(root: Path = REPO, package: str = PACKAGE) -> dict[str, set[str]]:
    files = module_files(root, package)
    return {m: imports_of(p.read_text(), m, files, p.name == "__init__.py") for m, p in files.items()}


def _contract_lines(text: str) -> list[tuple[bool, list[str]]]:
    """(indented, entries) of each line of the ```layers block of a markdown text, top to bottom (``#`` comments)."""
    m = re.search(r"^```layers\n(.*?)^```", text, re.M | re.S)
    if m is None:
        raise AssertionError("no ```layers block in docs/architecture.md")
    lines = []
    for line in m.group(1).splitlines():
        body = line.split("#")[0]
        if body.strip():
            lines.append((body[0].isspace(), [e.strip() for e in body.split("|")]))
    return lines


def parse_folders(text: str) -> list[list[str]]:
    """The folder level of the contract: its unindented lines, each a list of folders (``name/``) and root modules.
    Raises AssertionError on an indented line that does not follow a folder alone on its line, or that names a module
    outside that folder."""
    lines: list[list[str]] = []
    for indented, entries in _contract_lines(text):
        if not indented:
            lines.append(entries)
            continue
        head = lines[-1] if lines else []
        if len(head) != 1 or not head[0].endswith("/"):
            raise AssertionError(f"indented line {' | '.join(entries)!r} follows no folder alone on its line")
        folder = head[0][:-1]
        stray = [e for e in entries if e != folder and not e.startswith(folder + ".")]
        if stray:
            raise AssertionError(f"{stray} listed under {folder}/ are not in that folder")
    return lines


def parse_layers(text: str) -> list[list[str]]:
    """The module level of the contract: every line with its entries, top to bottom; a folder's indented lines in its
    place, or the folder as one entry (``name``, all its modules) where it has none."""
    parse_folders(text)  # the shape of the block
    items = _contract_lines(text)
    layers = []
    for k, (indented, entries) in enumerate(items):
        if not indented and k + 1 < len(items) and items[k + 1][0]:
            continue  # a folder whose modules follow, indented
        layers.append([e.removesuffix("/") for e in entries])
    return layers


def folders_of(modules, package: str = PACKAGE) -> set[str]:
    """The folders of the package: its subpackages (``io``, ``kernels``...)."""
    return {m.split(".")[1] for m in modules if m.count(".") == 1 and any(n.startswith(m + ".") for n in modules)}


def unit_of(module: str, folders: set[str], package: str = PACKAGE) -> str:
    """The unit of the folder level a module belongs to: its folder (``io/``), a root module (``cli``) or the
    package."""
    parts = module.split(".")
    if len(parts) == 1:
        return package
    return parts[1] + "/" if parts[1] in folders else parts[1]


def folder_graph(graph: dict[str, set[str]], package: str = PACKAGE) -> dict[str, set[str]]:
    """The import graph between units of the folder level (folders, root modules, the package)."""
    folders = folders_of(graph, package)
    out: dict[str, set[str]] = {}
    for a, targets in graph.items():
        ua = unit_of(a, folders, package)
        out.setdefault(ua, set()).update(unit_of(b, folders, package) for b in targets)
        out[ua].discard(ua)
    return out


def folder_violations(units: dict[str, set[str]], lines: list[list[str]]) -> list[str]:
    """Every import between folders or root modules that climbs the folder level or joins two siblings, every unit
    outside it and every entry that names nothing."""
    where = {u: i for i, line in enumerate(lines) for u in line}
    problems = [f"{u} is in no line of the contract" for u in sorted(units) if u not in where]
    problems += [f"line entry {u!r} names no folder or module" for u in where if u not in units]
    for a, targets in sorted(units.items()):
        for b in sorted(targets):
            if a not in where or b not in where:
                continue
            if where[b] < where[a]:
                problems.append(f"{a} imports {b}: upward ({a!r} is below {b!r})")
            elif where[b] == where[a]:
                problems.append(f"{a} imports {b}: siblings {a!r} | {b!r} must not import each other")
    return problems


def entry_of(module: str, layers: list[list[str]], package: str = PACKAGE) -> tuple[int, str] | None:
    """(line index, entry) of a module: the longest entry that is the module or a package holding it."""
    best = None
    for i, line in enumerate(layers):
        for e in line:
            full = package if e == package else f"{package}.{e}"
            if (module == full or module.startswith(full + ".")) and (best is None or len(full) > len(best[2])):
                best = (i, e, full)
    return None if best is None else best[:2]


def layer_violations(graph: dict[str, set[str]], layers: list[list[str]], package: str = PACKAGE) -> list[str]:
    """Every import that climbs the layers or joins two siblings, every module outside the contract and every
    entry that names no module."""
    problems = []
    where = {m: entry_of(m, layers, package) for m in graph}
    problems += [f"{m} is in no layer of the contract" for m, w in where.items() if w is None]
    used = {w[1] for w in where.values() if w is not None}
    problems += [f"layer entry {e!r} names no module" for line in layers for e in line if e not in used]
    for a, targets in sorted(graph.items()):
        for b in sorted(targets):
            wa, wb = where.get(a), where.get(b)
            if wa is None or wb is None or wa[1] == wb[1]:
                continue
            if wb[0] < wa[0]:
                problems.append(f"{a} imports {b}: upward ({wa[1]!r} is below {wb[1]!r})")
            elif wb[0] == wa[0]:
                problems.append(f"{a} imports {b}: siblings {wa[1]!r} | {wb[1]!r} must not import each other")
    return problems


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted: the import cycles."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


def private_uses(source: str, module: str, modules, is_package: bool = False) -> list[str]:
    """Private names (one leading underscore, not dunder) that ``source`` takes from other flowsynth modules:
    ``from flowsynth.<module> import _name``, ``module._name`` on a flowsynth module bound by an import, and
    ``obj._name`` on any object but ``self`` / ``cls`` or a third-party module (another object's private attribute)."""
    tree = ast.parse(source)
    own: dict[str, str] = {}  # local name -> flowsynth module it is bound to
    foreign: set[str] = set()  # local names bound to third-party modules or their names
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == PACKAGE:
                    if a.asname:
                        own[a.asname] = a.name
                else:
                    foreign.add((a.asname or a.name).split(".")[0])
        elif isinstance(node, ast.ImportFrom):
            if node.level or (node.module or "").split(".")[0] == PACKAGE:
                if node.level:
                    base = module.split(".") if is_package else module.split(".")[:-1]
                    mod = ".".join(base[:len(base) - node.level + 1] + ([node.module] if node.module else []))
                else:
                    mod = node.module
                for a in node.names:
                    if f"{mod}.{a.name}" in modules:
                        own[a.asname or a.name] = f"{mod}.{a.name}"
                    elif a.name.startswith("_") and not a.name.startswith("__") and _resolve(mod, modules) != module:
                        found.append(f"line {node.lineno}: from {mod} import {a.name}")
            else:
                foreign.update(a.asname or a.name for a in node.names)
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")):
            continue
        v = node.value
        if isinstance(v, ast.Name) and (v.id in ("self", "cls") or v.id in foreign):
            continue
        if isinstance(v, ast.Name) and v.id in own and own[v.id] == module:
            continue
        found.append(f"line {node.lineno}: {ast.unparse(node)}")
    return found


# --- the checker, tested on made-up code ---------------------------------------------------------------------------

FAKE_LAYERS = [["app"], ["mid_a", "mid_b"], ["low"]]


def _fake(edges: dict[str, set[str]]) -> dict[str, set[str]]:
    return {f"{PACKAGE}.{a}": {f"{PACKAGE}.{b}" for b in bs} for a, bs in edges.items()}


def test_checker_reports_an_upward_import_and_a_sibling_import():
    good = _fake({"app": {"mid_a", "low"}, "mid_a": {"low"}, "mid_b": {"low"}, "low": set()})
    assert layer_violations(good, FAKE_LAYERS) == []
    up = _fake({"app": set(), "mid_a": {"low"}, "mid_b": set(), "low": {"mid_a"}})
    assert layer_violations(up, FAKE_LAYERS) == [f"{PACKAGE}.low imports {PACKAGE}.mid_a: upward ('low' is below "
                                                 "'mid_a')"]
    side = _fake({"app": set(), "mid_a": {"mid_b"}, "mid_b": set(), "low": set()})
    assert "siblings 'mid_a' | 'mid_b'" in " ".join(layer_violations(side, FAKE_LAYERS))


def test_checker_reports_modules_outside_the_contract_and_stale_entries():
    problems = layer_violations(_fake({"app": set(), "mid_a": set(), "stray": set()}), FAKE_LAYERS)
    assert f"{PACKAGE}.stray is in no layer of the contract" in problems
    assert "layer entry 'low' names no module" in problems and "layer entry 'mid_b' names no module" in problems


def _src(code: str) -> str:
    """Made-up source code naming the package as PKG (so the repository's name checks do not read it as a real
    module path)."""
    return code.replace("PKG", PACKAGE)


FAKE_CONTRACT = """```layers
app                     # a root module
low/                    # a folder
    low                 # its exports
    low.b | low.c
    low.a
base
```
"""


def test_checker_reads_folders_and_their_modules():
    assert parse_folders(FAKE_CONTRACT) == [["app"], ["low/"], ["base"]]
    assert parse_layers(FAKE_CONTRACT) == [["app"], ["low"], ["low.b", "low.c"], ["low.a"], ["base"]]
    with pytest.raises(AssertionError, match="follows no folder alone"):
        parse_folders(FAKE_CONTRACT.replace("low/ ", "low/ | base "))
    with pytest.raises(AssertionError, match=r"\['app.x'\] listed under low/"):
        parse_folders(FAKE_CONTRACT.replace("low.a", "app.x"))
    # a folder without indented lines is one entry of the module level
    assert parse_layers("```layers\napp\nerrors | kernels/\n```\n") == [["app"], ["errors", "kernels"]]


def test_checker_reports_imports_that_climb_folders():
    graph = _fake({"app": {"low.b"}, "low": {"low.b", "low.a"}, "low.b": {"low.a"}, "low.c": set(),
                   "low.a": {"base"}, "base": set()})
    assert folder_graph(graph) == {"app": {"low/"}, "low/": {"base"}, "base": set()}
    lines = parse_folders(FAKE_CONTRACT)
    assert folder_violations(folder_graph(graph), lines) == []
    assert layer_violations(graph, parse_layers(FAKE_CONTRACT)) == []
    graph[f"{PACKAGE}.base"] = {f"{PACKAGE}.low.c"}
    assert folder_violations(folder_graph(graph), lines) == ["base imports low/: upward ('base' is below 'low/')"]
    assert find_cycles(folder_graph(graph)) == [["base", "low/"]]
    assert "stray is in no line of the contract" in folder_violations({"stray": set(), **folder_graph(graph)}, lines)


def test_checker_finds_cycles_through_lazy_and_string_imports():
    modules = {f"{PACKAGE}.{m}": None for m in ("a", "b", "c", "pkg", "pkg.sub")}
    a = _src("import os\n\ndef f():\n    from PKG.b import thing\n")  # lazy
    b = _src("import importlib\n\nX = importlib.import_module('PKG.c')\n")  # by name
    c = _src("from PKG import a\n")  # a module imported from its package
    graph = {f"{PACKAGE}.a": imports_of(a, f"{PACKAGE}.a", modules),
             f"{PACKAGE}.b": imports_of(b, f"{PACKAGE}.b", modules),
             f"{PACKAGE}.c": imports_of(c, f"{PACKAGE}.c", modules)}
    assert graph == {f"{PACKAGE}.a": {f"{PACKAGE}.b"}, f"{PACKAGE}.b": {f"{PACKAGE}.c"},
                     f"{PACKAGE}.c": {f"{PACKAGE}.a"}}
    assert find_cycles(graph) == [[f"{PACKAGE}.a", f"{PACKAGE}.b", f"{PACKAGE}.c"]]
    graph[f"{PACKAGE}.c"] = set()
    assert find_cycles(graph) == []
    # relative imports and names of a package resolve to the module that defines them
    assert imports_of("from . import sub\nfrom .sub import x\n", f"{PACKAGE}.pkg", modules, is_package=True) == {
        f"{PACKAGE}.pkg.sub"}
    assert imports_of(_src("from PKG.pkg import name\n"), f"{PACKAGE}.a", modules) == {f"{PACKAGE}.pkg"}


def test_checker_reports_private_names_across_modules():
    modules = {f"{PACKAGE}.{m}": None for m in ("a", "b")}
    src = _src("import numpy as np\nimport PKG.b as bm\nfrom PKG import b\nfrom PKG.b import _hidden, "
               "shown\n\nclass K:\n    def f(self, accel):\n        return self._x, np._NoValue, accel._lowers, bm._T, "
               "b._U\n")
    found = private_uses(src, f"{PACKAGE}.a", modules)
    assert [f.split(": ", 1)[1] for f in found] == [f"from {PACKAGE}.b import _hidden", "accel._lowers", "bm._T",
                                                    "b._U"]
    assert private_uses(_src("from PKG.a import _own\n"), f"{PACKAGE}.a", modules) == []


# --- the contract, checked on flowsynth ----------------------------------------------------------------------------

def _graph_without_exceptions() -> dict[str, set[str]]:
    graph = import_graph()
    for (a, b), why in TEMPORARY_EXCEPTIONS.items():
        if b in graph.get(a, set()):
            print(f"TEMPORARY EXCEPTION to the layer contract (tests/test_layers.py): {a} -> {b}: {why}")
            graph[a] = graph[a] - {b}
    return graph


def test_layer_contract_of_architecture_md_holds():
    layers = parse_layers(ARCHITECTURE.read_text())
    assert layers and layers[0] == [PACKAGE], "the contract's first line is the package itself (its re-exports)"
    problems = layer_violations(_graph_without_exceptions(), layers)
    assert not problems, "imports against docs/architecture.md's layers:\n" + "\n".join(problems)


def test_folders_are_layers():
    text = ARCHITECTURE.read_text()
    graph = _graph_without_exceptions()
    units = folder_graph(graph)
    assert [u for u in units if u.endswith("/")], "the package has folders"
    problems = folder_violations(units, parse_folders(text))
    assert not problems, "imports against the folder level of docs/architecture.md's layers:\n" + "\n".join(problems)
    cycles = find_cycles(units)
    assert not cycles, "import cycles between folders:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_no_import_cycles():
    cycles = find_cycles(_graph_without_exceptions())
    assert not cycles, "import cycles (lazy imports included):\n" + "\n".join(" <-> ".join(c) for c in cycles)


@pytest.mark.parametrize("folder", ["flowsynth", "benchmarks"])
def test_no_private_names_cross_modules(folder):
    modules = module_files()
    found = []
    for p in sorted((REPO / folder).rglob("*.py")):
        name = ".".join(p.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")
        for f in private_uses(p.read_text(), name, modules, p.name == "__init__.py"):
            if any(a == name and f"from {b} import" in f for a, b in TEMPORARY_EXCEPTIONS):
                print(f"TEMPORARY EXCEPTION to the layer contract (tests/test_layers.py): {name} {f}")
                continue
            found.append(f"{p.relative_to(REPO)} {f}")
    assert not found, "private names used across modules (give them a public name):\n" + "\n".join(found)
