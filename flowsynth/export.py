"""Crash-safe, resumable, parallel export of BouncingThings samples to disk, in any registered layout.

What a layout writes is its own business (``flowsynth/io/layouts/``: native, flyingchairs, kitti,
sintel, ...). This module does the bookkeeping that is the same for every layout::

    DIR/
      manifest.json       config, seed, outputs, layout and its options, versions, num,
                          samples: {"NNNNN": {path: {"size": bytes, "sha256": hex}}}, index: {...},
                          stats (flowsynth.stats over the samples the last run generated)
      .journal.jsonl      records of samples finished since manifest.json was last rewritten
      ...                 the layout's files (paths in the manifest are relative to DIR)

Crash safety: a sample is written by its layout into a hidden staging folder ``DIR/.tmp-NNNNN-*``,
hashed, recorded in the journal, and then moved into place file by file (a folder that does not exist
yet moves whole) with :func:`os.replace`; so a file under its final name is always whole. On resume a
sample counts as done when it has a record and every recorded file exists with the recorded size;
any other sample is written again. ``manifest.json`` is rewritten atomically every 16 samples and at
the end, which empties the journal.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import multiprocessing as mp
import os
import shutil
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from tqdm import tqdm

from flowsynth.errors import ConfigError, ExportError
from flowsynth.io import layouts

__all__ = ["JOURNAL", "MANIFEST", "Sizes", "estimate", "export"]

MANIFEST = "manifest.json"
JOURNAL = ".journal.jsonl"
_MANIFEST_EVERY = 16  # samples between manifest rewrites


def _versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("flowsynth", "warp-lang", "torch", "kornia", "numpy", "newton"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = None
    return out


def _resolve(cfg, num, outputs, layout: str, workers: int, exr_compression: str):
    """Validate everything before anything is written; returns (Layout, outputs tuple)."""
    from flowsynth.plan import make_plan

    lay = layouts.get(layout, exr_compression=exr_compression)
    if not isinstance(num, int) or num < 1:
        raise ConfigError(f"num must be an integer >= 1, got {num!r}")
    if not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"workers must be an integer >= 1, got {workers!r}")
    outputs = make_plan(lay.default_outputs if outputs is None else outputs).outputs
    lay.check(cfg, outputs, num)
    return lay, outputs


def _record(folder: Path, paths) -> dict:
    """{path: {"size": bytes, "sha256": hex}} of the files ``paths`` under ``folder``."""
    out = {}
    for rel in sorted(paths):
        data = (folder / rel).read_bytes()
        out[rel] = {"size": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    return out


_WORKER: dict = {}


def _init_worker(cfg, outputs, seed, occlusion, layout) -> None:
    import torch

    from flowsynth.datasets import BouncingThings
    from flowsynth.stats import cheap_stats_outputs

    torch.set_num_threads(1)
    _WORKER["ds"] = BouncingThings(cfg, outputs=cheap_stats_outputs(outputs), seed=seed, occlusion=occlusion)
    _WORKER["keep"] = set(outputs) | {"index", "seed", "K", "cam_T_world"}
    _WORKER["layout"] = layout


def _init_pool_worker(*args) -> None:
    """``_init_worker`` in one of several worker processes: ray launches use one thread (flowsynth.parallel)."""
    from flowsynth.parallel import set_worker_process

    set_worker_process()
    _init_worker(*args)


def _write_one(args) -> tuple[int, str, dict, dict]:
    """Generate sample i and write it into a staging folder.

    Returns (i, staging folder, {path: {size, sha256}}, flowsynth.stats.sample_record).
    """
    from flowsynth.stats import sample_record

    i, root = args
    t = time.perf_counter()
    sample = _WORKER["ds"].sample(i)
    stats = sample_record(sample, time.perf_counter() - t)
    sample = {k: v for k, v in sample.items() if k in _WORKER["keep"]}
    staging = Path(tempfile.mkdtemp(prefix=f".tmp-{i:05d}-", dir=root))
    try:
        files = _WORKER["layout"].write(sample, i, staging)
        return i, str(staging), _record(staging, files), stats
    except BaseException as e:
        shutil.rmtree(staging, ignore_errors=True)
        if isinstance(e, OSError) and not isinstance(e, ExportError):
            raise ExportError(f"could not write sample {i} under {root}: {e}") from e
        raise


def _place(src: Path, dst: Path) -> None:
    """Move the tree ``src`` into ``dst``: a missing folder moves whole, files replace what is there."""
    for p in src.iterdir():
        q = dst / p.name
        if p.is_dir() and q.is_dir():
            _place(p, q)
        else:
            os.replace(p, q)


def _write_manifest(root: Path, identity: dict, num: int, samples: dict, index: dict | None = None,
                    stats: dict | None = None) -> None:
    from flowsynth.io import write_json

    body = dict(identity, num=num, versions=_versions(),
                samples={f"{i:05d}": samples[i] for i in sorted(samples)}, index=index or {})
    if stats is None and (root / MANIFEST).is_file():  # a run that generated nothing keeps the last stats
        stats = json.loads((root / MANIFEST).read_text()).get("stats")
    if stats is not None:  # flowsynth.stats.summarize over the samples the last run generated
        body["stats"] = stats
    write_json(root / MANIFEST, body)


def _complete(root: Path, files: dict) -> bool:
    """Every recorded file exists with its recorded size (the quick resume check)."""
    for rel, rec in files.items():
        p = root / rel
        if not p.is_file() or p.stat().st_size != rec["size"]:
            return False
    return True


def _recorded(root: Path, old: dict) -> dict[int, dict]:
    """Sample records of the manifest and of the journal (a torn last journal line is ignored)."""
    records = {int(k): v for k, v in old.get("samples", {}).items()}
    journal = root / JOURNAL
    if journal.is_file():
        for line in journal.read_text().splitlines():
            try:
                entry = json.loads(line)
            except ValueError:
                continue
            records[int(entry["sample"])] = entry["files"]
    return records


def export(cfg, out: str | os.PathLike, num: int, *, seed: int = 0, outputs=None, workers: int = 1,
           layout: str = "native", overwrite: bool = False, occlusion: str = "exact",
           exr_compression: str = "zip", progress: bool = True) -> Path:
    """Export samples 0..num-1 of ``BouncingThings(cfg, outputs, seed)`` to ``out``; resumes if interrupted.

    Args:
        layout: a name of ``flowsynth.io.layouts.names()``; ``outputs=None`` takes its defaults.
        exr_compression: lossless compression of EXR files, ``flowsynth.io.layouts.EXR_COMPRESSIONS``.

    Raises ConfigError for invalid arguments (before anything is written); ExportError when ``out``
    holds an export of another config/seed/outputs/layout (pass ``overwrite=True`` to replace it) or
    cannot be written. Returns the output folder.
    """
    lay, outputs = _resolve(cfg, num, outputs, layout, workers, exr_compression)
    root = Path(out)
    identity = {"config": cfg.to_dict(), "seed": seed, "outputs": list(outputs), "layout": lay.name,
                "layout_options": lay.options()}
    try:
        root.mkdir(parents=True, exist_ok=True)
        manifest = root / MANIFEST
        records: dict[int, dict] = {}
        if manifest.exists():
            old = json.loads(manifest.read_text())
            if {k: old.get(k) for k in identity} != json.loads(json.dumps(identity)):
                if not overwrite:
                    raise ExportError(f"{root} holds an export with a different config/seed/outputs/layout; "
                                      "choose another --out or pass --overwrite to replace it")
                _clear(root, old.get("layout"))
            else:
                records = _recorded(root, old)
        elif any(root.iterdir()) and not overwrite:
            raise ExportError(f"{root} is not empty and holds no flowsynth manifest; choose an empty folder "
                              "or pass --overwrite")
        for tmp in root.glob(".tmp-*"):
            shutil.rmtree(tmp, ignore_errors=True)
        samples = {i: f for i, f in records.items() if i < num and _complete(root, f)}
        _write_manifest(root, identity, num, samples)
        (root / JOURNAL).unlink(missing_ok=True)  # its records are in the manifest now
        todo = [i for i in range(num) if i not in samples]
        _run(todo, root, lay, cfg, outputs, seed, occlusion, workers, progress, identity, num, samples)
        index = _record(root, lay.finish(root, num, cfg))
        _write_manifest(root, identity, num, samples, index)
    except OSError as e:
        if isinstance(e, ExportError):
            raise
        raise ExportError(f"cannot write the export to {root}: {e.strerror or e}; samples already written "
                          "are kept, re-run the same command to resume") from e
    return root


def _run(todo, root, lay, cfg, outputs, seed, occlusion, workers, progress, identity, num, samples) -> None:
    bar = tqdm(total=num, initial=num - len(todo), unit="sample", disable=not progress, dynamic_ncols=True)
    jobs = [(i, str(root)) for i in todo]
    records: list[dict] = []
    pool = None
    try:
        if workers == 1 or len(jobs) <= 1:
            _init_worker(cfg, outputs, seed, occlusion, lay)
            results = map(_write_one, jobs)
        else:
            pool = ProcessPoolExecutor(min(workers, len(jobs)), mp_context=_mp_context(),
                                       initializer=_init_pool_worker, initargs=(cfg, outputs, seed, occlusion, lay))
            results = pool.map(_write_one, jobs, chunksize=1)
        with open(root / JOURNAL, "a") as journal:
            for n, (i, staging, files, stats) in enumerate(results, 1):
                # record first, then move: a record whose files are not all in place fails the resume check
                journal.write(json.dumps({"sample": f"{i:05d}", "files": files}) + "\n")
                journal.flush()
                os.fsync(journal.fileno())
                _place(Path(staging), root)
                shutil.rmtree(staging, ignore_errors=True)
                samples[i] = files
                records.append(stats)
                bar.update(1)
                if n % _MANIFEST_EVERY == 0:
                    _write_manifest(root, identity, num, samples)
                    journal.seek(0)
                    journal.truncate()
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        bar.close()
        from flowsynth.stats import summarize

        _write_manifest(root, identity, num, samples, stats=summarize(records, cfg) if records else None)
        (root / JOURNAL).unlink(missing_ok=True)


def _mp_context():
    """fork where the platform has it (like DataLoader's default: workers inherit the loaded Warp modules
    instead of importing them again), spawn elsewhere."""
    return mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")


def _clear(root: Path, old_layout: str | None) -> None:
    if old_layout in layouts.names():
        layouts.get(old_layout).clear(root)
    for p in root.glob(".tmp-*"):
        shutil.rmtree(p)
    for name in (MANIFEST, JOURNAL):
        (root / name).unlink(missing_ok=True)


@dataclasses.dataclass(frozen=True)
class Sizes:
    """What an export costs on disk, measured by writing sample ``seed``'s sample 0 to a temporary folder."""

    per_sample: dict[str, int]
    """Output key (``"rgb"``, ``"flow_fw"``, ``"meta"``, ...) -> bytes of its files in one sample."""
    index: int
    """Bytes of the files that cover the whole export (manifest excluded), e.g. a split file."""
    num: int
    """Number of samples."""

    @property
    def total(self) -> int:
        """Estimated bytes of the whole export: num * sum(per_sample) + index."""
        return self.num * sum(self.per_sample.values()) + self.index


def estimate(cfg, num: int, *, seed: int = 0, outputs=None, layout: str = "native", occlusion: str = "exact",
             exr_compression: str = "zip") -> Sizes:
    """Sizes of ``export(cfg, ..., num, ...)`` without writing under its folder (``flowsynth export --dry-run``).

    Sample 0 is generated and written in a temporary folder that is removed afterwards; other
    samples differ from it by what their content compresses to (a few per cent, benchmarks/export.py).
    Raises ConfigError for invalid arguments, as :func:`export` does.
    """
    from flowsynth.datasets import BouncingThings

    lay, outputs = _resolve(cfg, num, outputs, layout, 1, exr_compression)
    sample = BouncingThings(cfg, outputs=outputs, seed=seed, occlusion=occlusion).sample(0)
    per_sample: dict[str, int] = {}
    with tempfile.TemporaryDirectory(prefix="flowsynth-dry-run-") as tmp:
        for rel, key in lay.write(sample, 0, Path(tmp)).items():
            per_sample[key] = per_sample.get(key, 0) + (Path(tmp) / rel).stat().st_size
        index = sum((Path(tmp) / rel).stat().st_size for rel in lay.finish(Path(tmp), num, cfg))
    return Sizes(per_sample=per_sample, index=index, num=num)
