"""The docs agree with the code, where a test can tell: every config field documented, every output key in
docs/conventions.md, every export layout in the README, and a few numeric claims recomputed from the code."""

from __future__ import annotations

import ast
import dataclasses
import itertools
import math
import re
from pathlib import Path

import flowsynth as fs
from flowsynth import plan
from flowsynth.appearance import materials
from flowsynth.io import layouts

ROOT = Path(__file__).resolve().parents[1]
USER_DOCS = ("README.md", "docs/scenes.md", "docs/rendering.md", "docs/conventions.md", "docs/statistics.md")


def _read(rel: str) -> str:
    return (ROOT / rel).read_text()


def _field_docstrings(cls) -> dict[str, str]:
    """{field: the string literal right below it} in the class body's source (Newton's style: a docstring per
    field)."""
    src = Path(__import__(cls.__module__, fromlist=["_"]).__file__).read_text()
    body = next(n for n in ast.walk(ast.parse(src)) if isinstance(n, ast.ClassDef) and n.name == cls.__name__).body
    docs = {}
    for a, b in itertools.pairwise(body):
        if isinstance(a, ast.AnnAssign) and isinstance(a.target, ast.Name) and isinstance(b, ast.Expr) \
                and isinstance(b.value, ast.Constant) and isinstance(b.value.value, str):
            docs[a.target.id] = b.value.value
    return docs


def test_every_config_field_has_a_docstring():
    fields = [f.name for f in dataclasses.fields(fs.BouncingThingsConfig)]
    docs = _field_docstrings(fs.BouncingThingsConfig)
    assert [f for f in fields if not docs.get(f, "").strip()] == []


def test_every_config_field_is_named_in_the_user_docs():
    text = "\n".join(_read(p) for p in USER_DOCS)
    missing = [f.name for f in dataclasses.fields(fs.BouncingThingsConfig)
               if not re.search(rf"`{f.name}(`|[ =(])", text)]
    assert missing == [], f"config fields named in none of {USER_DOCS}: {missing}"


def test_every_output_key_is_in_the_conventions():
    text = _read("docs/conventions.md")
    missing = [k for k in plan.OUTPUTS if f"`{k}`" not in text]
    assert missing == [], f"output keys (flowsynth.plan.OUTPUTS) missing from docs/conventions.md: {missing}"


def test_every_layout_is_in_the_readme_table_and_flag_line():
    readme = _read("README.md")
    rows = set(re.findall(r"(?m)^\| `([a-z0-9_]+)` \|", readme))
    missing_rows = [n for n in layouts.names() if n not in rows]
    assert missing_rows == [], f"layouts with no row in the README's layout table: {missing_rows}"
    flag = re.search(r"--layout ([a-z0-9_|]+)\]", readme)
    assert flag, "the README's export synopsis names no --layout choices"
    assert sorted(flag.group(1).split("|")) == sorted(layouts.names())


def test_io_package_docstring_lists_every_layout_and_format_module():
    import flowsynth.io as io

    doc = io.__doc__
    assert [n for n in layouts.names() if n not in doc] == []
    modules = sorted(p.stem for p in (ROOT / "flowsynth" / "io").glob("*.py") if p.stem not in ("__init__", "atomic"))
    assert [m for m in modules if f"``{m}``" not in doc] == []


def test_rendering_doc_octave_count_matches_the_sampler():
    """docs/rendering.md: floor(log2(largest / lo)) + 1 octaves, 5 at the default texture_px, where the largest
    feature is 60-100% of hi. Recomputed here from the config default and materials.MAX_OCTAVES."""
    lo, hi = fs.BouncingThingsConfig().texture_px
    counts = {min(math.floor(math.log2(hi * f / lo)) + 1, materials.MAX_OCTAVES) for f in (0.6, 0.8, 0.999)}
    text = _read("docs/rendering.md")
    assert f"{counts.pop()} at the default ({lo:g}, {hi:g}) px" in text and not counts
    assert f"`flowsynth.appearance.materials.MAX_OCTAVES` = {materials.MAX_OCTAVES}" in text


def test_rendering_doc_names_where_render_modes_are_defined():
    from flowsynth import kernels

    assert "RENDER_MODES" in vars(kernels) and "flowsynth.kernels.RENDER_MODES" in _read("docs/rendering.md")
    assert "RENDER_MODES =" not in (ROOT / "flowsynth" / "plan.py").read_text()


def test_versions_benchmark_docstring_counts_its_settings():
    src = _read("benchmarks/speed/versions.py")
    modes = ast.literal_eval(re.search(r"(?m)^MODES = (\(.*\))$", src).group(1))
    words = {2: "Two", 3: "Three", 4: "Four"}
    assert f"{words[len(modes)]} settings per revision" in src
    assert all(f"``{m}``" in src for m in modes)


def test_test_script_keeps_hypothesis_cache_under_dot_cache():
    """scripts/test.sh says every cache, hypothesis's included, lives in .cache/. conftest's default profile is
    derandomized and keeps no database; the random ``dev`` profile keeps its database under .cache/hypothesis."""
    from hypothesis import settings
    from hypothesis.database import DirectoryBasedExampleDatabase

    assert "hypothesis" in _read("scripts/test.sh")
    assert settings.get_profile("ci").derandomize and settings.get_profile("ci").database is None
    db = settings.get_profile("dev").database
    assert isinstance(db, DirectoryBasedExampleDatabase)
    assert Path(db.path).resolve().is_relative_to(ROOT / ".cache")
    assert settings().derandomize or "HYPOTHESIS_PROFILE" in __import__("os").environ
    from hypothesis.configuration import storage_directory

    assert Path(storage_directory(intent_to_write=False).path).resolve().is_relative_to(ROOT / ".cache")
