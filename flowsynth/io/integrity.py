"""An export's files against its manifest, for every layout: what is missing, damaged or foreign.

``manifest.json`` records, per sample, every file the layout wrote as ``{path: {"size": bytes,
"sha256": hex}}`` (paths relative to the export root, ``/``-separated). Two depths of checking:

- ``quick``: every recorded file exists with its recorded size (one ``stat`` per file);
- ``full``: also the sha256 of its bytes (reads every byte).

``flowsynth export`` checks quickly when it resumes (``--verify``: fully) and writes again every
sample that fails; :class:`flowsynth.datasets.Exported` checks quickly when it opens a folder.
Files that no record names are *foreign*: reported, never touched.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from pathlib import Path

from flowsynth.errors import ConfigError, ExportError

__all__ = ["VERIFY_MODES", "file_problem", "file_records", "foreign_files", "read_manifest", "sample_problem"]

VERIFY_MODES = ("quick", "full", "none")
_CHUNK = 1 << 20


def read_manifest(root: str | Path) -> dict:
    """The ``manifest.json`` of the export folder ``root``, for a reader of the export.

    Raises ExportError when there is none, or it is not JSON, saying what the folder should be."""
    manifest = Path(root) / "manifest.json"
    if not manifest.is_file():
        raise ExportError(f"could not find {manifest}; is {root} a folder written by `flowsynth export`?")
    try:
        return json.loads(manifest.read_text())
    except ValueError as e:
        raise ExportError(f"{manifest} is not valid JSON ({e}); re-run the `flowsynth export` command that wrote "
                          "it") from e


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def file_records(folder: Path, paths: Iterable[str]) -> dict[str, dict]:
    """The manifest's records ``{path: {"size": bytes, "sha256": hex}}`` of the files ``paths`` under ``folder``."""
    out = {}
    for rel in sorted(paths):
        data = (Path(folder) / rel).read_bytes()
        out[rel] = {"size": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    return out


def file_problem(root: Path, rel: str, record: dict, mode: str = "quick") -> str | None:
    """What is wrong with file ``rel`` against its ``{"size", "sha256"}`` record, or None when it passes."""
    if mode not in VERIFY_MODES:
        raise ConfigError(f"verify must be one of {VERIFY_MODES}, got {mode!r}")
    if mode == "none":
        return None
    p = Path(root) / rel
    if not p.is_file():
        return f"{rel} is missing"
    size = p.stat().st_size
    if size != record["size"]:
        return f"{rel} has {size} bytes, the manifest says {record['size']}"
    if mode == "full" and _sha256(p) != record["sha256"]:
        return f"{rel} has another sha256 than the manifest records"
    return None


def sample_problem(root: Path, files: dict, mode: str = "quick") -> str | None:
    """First problem of a sample's files (``{path: record}``), or None when every file passes."""
    for rel, record in files.items():
        problem = file_problem(root, rel, record, mode)
        if problem:
            return problem
    return None


def foreign_files(root: Path, known: Iterable[str]) -> list[str]:
    """Files under ``root`` (relative, ``/``-separated, sorted) that are not in ``known``.

    Hidden temporaries of the exporter (``.tmp-*`` folders) are not listed: they are its own.
    """
    root = Path(root)
    known = set(known)
    out = []
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root)
        if p.is_dir() or rel.parts[0].startswith(".tmp-"):
            continue
        if rel.as_posix() not in known:
            out.append(rel.as_posix())
    return out
