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
yet moves whole) with :func:`os.replace`; so a file under its final name is always whole. Folders and
files get the modes the umask gives (0755 / 0644 under the usual 022), never the staging folder's 0700.
``manifest.json`` is rewritten atomically every 16 samples and at the end, which empties the journal.

Nothing is written before everything is validated (arguments, layout, the dataset, the output folder,
the memory a sample needs, :mod:`flowsynth.memory`), and ``manifest.json`` appears only when the first
sample is about to be moved into place: a run that fails before that leaves nothing in the way of the
corrected command.

Resume (:mod:`flowsynth.integrity`): a sample counts as done when it has a record and every recorded
file passes the check, quick (present, recorded size) or with ``verify=True`` full (sha256); every
other sample is written again. Files that no record names are reported as foreign and left untouched.

I/O failures (disk full, permission denied) raise :class:`flowsynth.errors.StorageError` (CLI exit
status 3) after the staging folders are removed; every finished sample stays recorded.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import multiprocessing as mp
import os
import shutil
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from tqdm import tqdm

from flowsynth.errors import ConfigError, ExportError, StorageError
from flowsynth.io import layouts

__all__ = ["ENGINES", "JOURNAL", "MANIFEST", "Sizes", "estimate", "export"]

ENGINES = ("local", "ray")  # where samples are made: worker processes here, or actors of a Ray cluster

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


def _resolve(cfg, num, outputs, layout: str, workers: int | None, exr_compression: str, engine: str = "local"):
    """Validate everything before anything is written; returns (Layout, outputs tuple)."""
    from flowsynth.memory import check_sample_memory
    from flowsynth.plan import make_plan

    lay = layouts.get(layout, exr_compression=exr_compression)
    if not isinstance(num, int) or num < 1:
        raise ConfigError(f"num must be an integer >= 1, got {num!r}")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ConfigError(f"workers must be None or an integer >= 1, got {workers!r}")
    if engine not in ENGINES:
        raise ConfigError(f"engine must be one of {ENGINES}, got {engine!r}")
    if engine == "ray":
        from flowsynth.distributed import require_ray

        require_ray()
    outputs = make_plan(lay.default_outputs if outputs is None else outputs, flow_gaps=cfg.flow_gaps,
                        stereo_baseline=cfg.stereo_baseline).outputs
    lay.check(cfg, outputs, num)
    check_sample_memory(cfg, processes=min(workers or 1, num))
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
    _WORKER["keep"] = set(outputs) | {"index", "seed", "K", "cam_T_world", "provenance"}
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
            raise StorageError(f"could not write sample {i} under {root}: {e.strerror or e}", e.errno) from e
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


def export(cfg, out: str | os.PathLike, num: int, *, seed: int = 0, outputs=None, workers: int | None = None,
           layout: str = "native", overwrite: bool = False, occlusion: str = "exact",
           exr_compression: str = "zip", verify: bool = False, progress: bool = True, engine: str = "local",
           address: str | None = None) -> Path:
    """Export samples 0..num-1 of ``BouncingThings(cfg, outputs, seed)`` to ``out``; resumes if interrupted.

    Args:
        layout: a name of ``flowsynth.io.layouts.names()``; ``outputs=None`` takes its defaults.
        exr_compression: lossless compression of EXR files, ``flowsynth.io.layouts.EXR_COMPRESSIONS``.
        verify: on resume, check the sha256 of every recorded file, not only its presence and size.
        workers: ``engine="local"``: processes on this machine (None: 1); ``engine="ray"``: Ray actors,
            one CPU each (None: one per CPU of the cluster).
        engine: "local", or "ray" (``flowsynth.distributed``; needs the ray extra): on the Ray cluster at
            ``address`` (None: the one this process joined, else a local one); ``out`` must then be a
            folder every node reaches. Both engines write the same files, and the same manifest up to its
            measured ``stats.seconds_per_sample``.

    Raises ConfigError for invalid arguments (``engine="ray"`` without Ray installed included) and
    ExportError when ``out`` holds an export of another config/seed/outputs/layout (pass
    ``overwrite=True`` to replace it) or something else; both before anything is written. StorageError
    (an ExportError) when a file cannot be written: finished samples are kept, temporaries removed, and
    the same call resumes. Returns the output folder.
    """
    lay, outputs = _resolve(cfg, num, outputs, layout, workers, exr_compression, engine)
    _check_dataset(cfg, outputs, seed, occlusion)
    root = Path(out)
    identity = {"config": cfg.to_dict(), "seed": seed, "outputs": list(outputs), "layout": lay.name,
                "layout_options": lay.options()}
    old = _check_folder(root, identity, overwrite)
    samples: dict[int, dict] = {}
    try:
        root.mkdir(parents=True, exist_ok=True)
        for tmp in root.glob(".tmp-*"):
            shutil.rmtree(tmp, ignore_errors=True)
        records: dict[int, dict] = {}
        if old is not None and _same(old, identity):
            records = _recorded(root, old)
        elif old is not None:  # another export, overwrite=True
            _clear(root, old.get("layout"))
        samples.update(_verified(root, records, num, "full" if verify else "quick"))
        _report_foreign(root, records, old)
        if (root / MANIFEST).exists():  # a resumed export: the manifest says what passed the check
            _write_manifest(root, identity, num, samples)
            (root / JOURNAL).unlink(missing_ok=True)  # its records are in the manifest now
        todo = [i for i in range(num) if i not in samples]
        _run(todo, root, lay, cfg, outputs, seed, occlusion, workers, progress, identity, num, samples, engine,
             address)
        index = _record(root, lay.finish(root, num, cfg))
        _write_manifest(root, identity, num, samples, index)
    except OSError as e:
        if isinstance(e, ExportError) and not isinstance(e, StorageError):
            raise
        for tmp in root.glob(".tmp-*"):
            shutil.rmtree(tmp, ignore_errors=True)
        raise StorageError(f"cannot write the export to {root}: {e.strerror or e}; {len(samples)} of {num} samples are "
                           "finished and kept, temporaries removed; fix the cause (free space?) and re-run the "
                           "same command to resume", e.errno) from e
    return root


def _same(old: dict, identity: dict) -> bool:
    return {k: old.get(k) for k in identity} == json.loads(json.dumps(identity))


def _check_dataset(cfg, outputs, seed, occlusion) -> None:
    """Build the dataset once, so what it refuses (num_frames for flow, assets, occlusion) fails first."""
    from flowsynth.datasets import BouncingThings

    BouncingThings(cfg, outputs=outputs, seed=seed, occlusion=occlusion)


def _check_folder(root: Path, identity: dict, overwrite: bool) -> dict | None:
    """Refuse an output folder that cannot be used, reading only; returns its manifest (None if none)."""
    if root.exists() and not root.is_dir():
        raise ExportError(f"--out {root} is a file; choose a folder")
    if not root.exists():
        parent = next(p for p in root.parents if p.exists())
        if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
            raise ExportError(f"cannot write the export to {root}: {parent} is not a writable folder")
        return None
    if not os.access(root, os.W_OK | os.X_OK):
        raise ExportError(f"cannot write the export to {root}: the folder is not writable")
    manifest = root / MANIFEST
    if manifest.is_file():
        try:
            old = json.loads(manifest.read_text())
        except ValueError as e:
            raise ExportError(f"{manifest} is not valid JSON ({e}); move it away or pass --overwrite") from e
        if not _same(old, identity) and not overwrite:
            raise ExportError(f"{root} holds an export with a different config/seed/outputs/layout; "
                              "choose another --out or pass --overwrite to replace it")
        return old
    if any(not p.name.startswith(".tmp-") for p in root.iterdir()) and not overwrite:
        raise ExportError(f"{root} is not empty and holds no flowsynth manifest; choose an empty folder "
                          "or pass --overwrite")
    return None


def _verified(root: Path, records: dict, num: int, mode: str) -> dict[int, dict]:
    """The records of samples < num whose files pass the ``mode`` check; says which will be written again."""
    from flowsynth.integrity import sample_problem

    samples, redo = {}, []
    for i, files in sorted(records.items()):
        if i >= num:
            continue
        problem = sample_problem(root, files, mode)
        if problem is None:
            samples[i] = files
        else:
            redo.append(f"{i:05d} ({problem})")
    if redo:
        _note(f"{len(redo)} incomplete or damaged sample{'s' if len(redo) != 1 else ''} will be written "
              f"again: {_first(redo)}")
    return samples


def _report_foreign(root: Path, records: dict, old: dict | None) -> None:
    """Name the files under root that no record of this export names; they are left as they are."""
    from flowsynth.integrity import foreign_files

    known = {MANIFEST, JOURNAL, *(old or {}).get("index", {})}
    for files in records.values():
        known.update(files)
    foreign = foreign_files(root, known)
    if foreign:
        _note(f"{len(foreign)} foreign file{'s' if len(foreign) != 1 else ''} in {root} (not written by this "
              f"export; left untouched): {_first(foreign)}")


def _first(items: list[str], n: int = 10) -> str:
    return ", ".join(items[:n]) + (f", ... ({len(items) - n} more)" if len(items) > n else "")


def _note(text: str) -> None:
    """A message for the user beside the progress bar (stderr)."""
    tqdm.write(f"flowsynth export: {text}", file=sys.stderr)


def _run(todo, root, lay, cfg, outputs, seed, occlusion, workers, progress, identity, num, samples, engine,
         address) -> None:
    bar = tqdm(total=num, initial=num - len(todo), unit="sample", disable=not progress, dynamic_ncols=True)
    jobs = [(i, str(root)) for i in todo]
    records: list[tuple[int, dict]] = []  # (index, stats record): summed in index order, whatever the engine
    pool = None
    results = None
    journal = None
    try:
        if engine == "ray" and jobs:
            from flowsynth.distributed import export_results

            results = export_results(jobs, (cfg, outputs, seed, occlusion, lay), actors=workers, address=address)
        elif workers in (None, 1) or len(jobs) <= 1:
            _init_worker(cfg, outputs, seed, occlusion, lay)
            results = map(_write_one, jobs)
        else:
            pool = ProcessPoolExecutor(min(workers, len(jobs)), mp_context=_mp_context(),
                                       initializer=_init_pool_worker, initargs=(cfg, outputs, seed, occlusion, lay))
            results = pool.map(_write_one, jobs, chunksize=1)
        for n, (i, staging, files, stats) in enumerate(results, 1):
            if journal is None:  # the first sample is about to be placed: now the folder is an export
                if not (root / MANIFEST).exists():
                    _write_manifest(root, identity, num, samples)
                journal = open(root / JOURNAL, "a")  # closed in finally
            # record first, then move: a record whose files are not all in place fails the resume check
            journal.write(json.dumps({"sample": f"{i:05d}", "files": files}) + "\n")
            journal.flush()
            os.fsync(journal.fileno())
            _place(Path(staging), root)
            shutil.rmtree(staging, ignore_errors=True)
            samples[i] = files
            records.append((i, stats))
            bar.update(1)
            if n % _MANIFEST_EVERY == 0:
                _write_manifest(root, identity, num, samples)
                journal.seek(0)
                journal.truncate()
    finally:
        if hasattr(results, "close"):  # a Ray run stopped early: its actors stop before the staging is removed
            results.close()
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        for tmp in root.glob(".tmp-*"):  # staging of samples that never got placed
            shutil.rmtree(tmp, ignore_errors=True)
        bar.close()
        if journal is not None:
            journal.close()
        if (root / MANIFEST).exists():
            from flowsynth.stats import summarize

            records.sort(key=lambda x: x[0])
            _write_manifest(root, identity, num, samples,
                            stats=summarize([r for _, r in records], cfg) if records else None)
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
