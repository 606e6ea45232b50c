"""Crash-safe, resumable, parallel export of generated samples (BouncingThings, Layers or a Mixture of both) to disk,
in any registered layout.

The entry point is :func:`export_dataset` (what ``flowsynth export`` runs; exported by the folder,
``flowsynth.export.export_dataset``, which also keeps its deprecated old name ``flowsynth.export.export``).

What a layout writes is its own business (``flowsynth/io/layouts/``: native, flyingchairs, kitti,
sintel, ...). This module does the bookkeeping that is the same for every layout::

    DIR/
      manifest.json       config (a mixture's: its preset), dataset (its kind, but for BouncingThings),
                          seed, outputs, layout and its options, occlusion (the method): the export's
                          identity, which a resume must match; versions, num,
                          samples: {"NNNNN": {path: {"size": bytes, "sha256": hex}}},
                          cameras: {"NNNNN": {K, width, height, model, dist}}, index: {...},
                          stats (flowsynth.stats over the samples the last run generated),
                          run: {"present", "written", "repaired"}: samples the last run found whole,
                          wrote, and wrote again because their files were incomplete or damaged
      .journal.jsonl      records of samples finished since manifest.json was last rewritten
      ...                 the layout's files (paths in the manifest are relative to DIR)

``cameras`` holds each sample's camera (:func:`flowsynth.export.writer.camera_record`: its provenance's intrinsics
and lens, ``model`` "pinhole" and ``dist`` [] for a pinhole) in every layout, so that an export in a format
that stores no camera (kitti, sintel, flyingchairs, flyingthings3d) still tells K and the lens of each sample.

Units of work: a layout splits the export into units (``Layout.units``): one sample each, or for
``webdataset`` one shard of ``--shard-size`` samples. A worker (:class:`flowsynth.export.writer.ExportWriter`, the
same object in worker processes and Ray actors) makes a whole unit.

Crash safety: a unit is written by its layout into a hidden staging folder ``DIR/.tmp-NNNNN-*``,
hashed, recorded in the journal (every sample of the unit in one write), and then moved into place file
by file (a folder that does not exist yet moves whole) with :func:`os.replace`; so a file under its
final name is always whole. Folders and
files get the modes the umask gives (0755 / 0644 under the usual 022), never the staging folder's 0700.
``manifest.json`` is rewritten atomically every 16 samples and at the end, which empties the journal.

Nothing is written before everything is validated (arguments, layout, the dataset, the output folder,
the memory a sample needs, :mod:`flowsynth.memory`), and ``manifest.json`` appears only when the first
sample is about to be moved into place: a run that fails before that leaves nothing in the way of the
corrected command.

Resume (:mod:`flowsynth.io.integrity`): a unit counts as done when each of its samples has a record (files and camera),
every recorded file passes the check, quick (present, recorded size) or with ``verify=True`` full
(sha256), and the samples recorded with each file are exactly the unit's; every other unit is written
again whole. Files that no record names are reported as foreign and left untouched.

I/O failures (disk full, permission denied) raise :class:`flowsynth.errors.StorageError` (CLI exit
status 3) after the staging folders are removed; every finished sample stays recorded.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from tqdm import tqdm

from flowsynth.errors import ConfigError, ExportError, StorageError
from flowsynth.options import check_int
from flowsynth.export.writer import ExportWriter, run_job
from flowsynth.io import file_records, layouts
from flowsynth.processes import worker_context

__all__ = ["ENGINES", "JOURNAL", "MANIFEST", "Sizes", "estimate", "export_dataset"]

ENGINES = ("local", "ray")  # where samples are made: worker processes here, or actors of a Ray cluster

MANIFEST = "manifest.json"
JOURNAL = ".journal.jsonl"
_MANIFEST_EVERY = 16  # samples between manifest rewrites
# identity keys a manifest written before they were recorded lacks, read as their default (what such an export used
# unless it was given another value, which it did not record)
_UNRECORDED = {"occlusion": "exact"}


def _versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("flowsynth", "warp-lang", "torch", "kornia", "numpy", "newton"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = None
    return out


def _resolve(cfg, num, outputs, layout: str, workers: int | None, exr_compression: str, engine: str = "local",
             shard_size: int | None = None):
    """Validate everything before anything is written; returns (Layout, outputs tuple)."""
    from flowsynth.datasets import config_kind, stream_outputs
    from flowsynth.memory import check_sample_memory

    config_kind(cfg)  # a ConfigError for anything but a dataset config
    lay = layouts.get(layout, exr_compression=exr_compression)
    if shard_size is not None:
        if "shard_size" not in lay.options():
            raise ConfigError(f"--shard-size applies to layouts that write shards (webdataset), not {layout}")
        lay = layouts.get(layout, exr_compression=exr_compression, shard_size=shard_size)
    num = check_int("num", num, 1)
    workers = None if workers is None else check_int("workers (None: one per core)", workers, 1)
    if engine not in ENGINES:
        raise ConfigError(f"engine must be one of {ENGINES}, got {engine!r}")
    if engine == "ray":
        from flowsynth.distributed import require_ray

        require_ray()
    # a layout's default set: the outputs of it the dataset's kind gives (a Layers sample has no depth)
    outputs = stream_outputs(cfg, lay.default_outputs if outputs is None else outputs, drop_unknown=outputs is None)
    for source in [c for _, c in cfg.sources] if config_kind(cfg) == "mixture" else [cfg]:
        lay.check(source, outputs, num)  # a mixture's every source (a layout may read fields a mixture lacks)
    cfg.check_files()  # the meshes and textures it names (a config reads no file when it is made)
    check_sample_memory(cfg, processes=min(workers or 1, num))
    return lay, outputs


def _place(src: Path, dst: Path) -> None:
    """Move the tree ``src`` into ``dst``: a missing folder moves whole, files replace what is there."""
    for p in src.iterdir():
        q = dst / p.name
        if p.is_dir() and q.is_dir():
            _place(p, q)
        else:
            os.replace(p, q)


def _write_manifest(root: Path, identity: dict, num: int, samples: dict, run: dict, index: dict | None = None,
                    stats: dict | None = None) -> None:
    """``samples``: index -> record ``{"files": ..., "camera": ...}``, as the journal holds them; ``run``: the
    samples this run found whole (``present``, all of them in ``samples`` then) and ``repaired``."""
    from flowsynth.io import write_json

    body = dict(identity, num=num, versions=_versions(),
                run={"present": run["present"], "written": len(samples) - run["present"],
                     "repaired": run["repaired"]},
                samples={f"{i:05d}": samples[i]["files"] for i in sorted(samples)},
                cameras={f"{i:05d}": samples[i]["camera"] for i in sorted(samples)}, index=index or {})
    if stats is None and (root / MANIFEST).is_file():  # a run that generated nothing keeps the last stats
        stats = json.loads((root / MANIFEST).read_text()).get("stats")
    if stats is not None:  # flowsynth.stats.summarize over the samples the last run generated
        body["stats"] = stats
    write_json(root / MANIFEST, body)


def _recorded(root: Path, old: dict) -> dict[int, dict]:
    """Sample records ``{"files": ..., "camera": ...}`` of the manifest and of the journal (a torn last journal line
    is ignored; ``camera`` is missing from the records of an export written before cameras were recorded)."""
    cameras = old.get("cameras", {})
    records = {int(k): {"files": v, **({"camera": cameras[k]} if k in cameras else {})}
               for k, v in old.get("samples", {}).items()}
    journal = root / JOURNAL
    if journal.is_file():
        for line in journal.read_text().splitlines():
            try:
                entry = json.loads(line)
            except ValueError:
                continue
            records[int(entry.pop("sample"))] = entry
    return records


def export_dataset(cfg, out: str | os.PathLike, num: int, *, seed: int = 0, outputs=None,
                   workers: int | None = None, layout: str = "native", overwrite: bool = False,
                   occlusion: str = "exact", exr_compression: str = "zip", verify: bool = False, progress: bool = True,
                   engine: str = "local", address: str | None = None, shard_size: int | None = None) -> Path:
    """Export samples 0..num-1 of ``cfg``'s stream to ``out``; resumes if interrupted.

    Args:
        cfg: a ``BouncingThingsConfig`` (``BouncingThings(cfg, outputs, seed)``), a ``LayersConfig``
            (``Layers(cfg, outputs, seed)``) or a ``MixtureConfig`` (``Mixture(cfg, outputs=outputs, seed=seed)``,
            the stream of ``Mixture.from_preset``): ``flowsynth.datasets.make_stream``. The manifest records its
            ``to_dict()`` (a mixture's preset) as ``config``.
        layout: a name of ``flowsynth.io.layouts.names()``; ``outputs=None`` takes its defaults.
        exr_compression: lossless compression of EXR files, ``flowsynth.io.layouts.EXR_COMPRESSIONS``.
        shard_size: samples per shard of a layout that writes shards (``webdataset``; None: its default).
        verify: on resume, check the sha256 of every recorded file, not only its presence and size.
        workers: ``engine="local"``: processes on this machine (None: 1); ``engine="ray"``: Ray actors,
            one CPU each (None: one per CPU of the cluster).
        engine: "local", or "ray" (``flowsynth.distributed``; needs the ray extra): on the Ray cluster at
            ``address`` (None: the one this process joined, else a local one); ``out`` must then be a
            folder every node reaches. Both engines write the same files, and the same manifest up to its
            measured ``stats.seconds_per_sample``.

    The manifest's ``run`` says what this call did: how many samples it found whole, wrote and repaired.

    Raises ConfigError for invalid arguments (``engine="ray"`` without Ray installed included, ``address`` with
    the local engine, an occlusion method no source of the dataset can honour) and
    ExportError when ``out`` holds an export of other settings (config, a mixture's preset, seed, outputs, layout and
    its options, occlusion: the message names each that differs, with both values; pass ``overwrite=True`` to
    replace it) or something else; both before anything is written. StorageError
    (an ExportError) when a file cannot be written: finished samples are kept, temporaries removed, and
    the same call resumes. Returns the output folder.
    """
    from flowsynth.datasets import config_kind

    if engine == "local" and address is not None:
        raise ConfigError(f"address={address!r} (--address) names a Ray cluster; it needs engine='ray' (--engine ray)"
                          ", or leave it out")
    lay, outputs = _resolve(cfg, num, outputs, layout, workers, exr_compression, engine, shard_size)
    _check_dataset(cfg, outputs, seed, occlusion)
    root = Path(out)
    identity = {"config": cfg.to_dict(), "seed": seed, "outputs": list(outputs), "layout": lay.name,
                "layout_options": lay.options(), "occlusion": occlusion}
    if config_kind(cfg) != "bouncing":  # BouncingThings' manifests name no kind (older exports resume as they are)
        identity["dataset"] = config_kind(cfg)
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
        units = lay.units(num)
        found, repaired = _verified(root, records, units, "full" if verify else "quick")
        samples.update(found)
        run = {"present": len(samples), "repaired": repaired}
        _report_foreign(root, records, old)
        if (root / MANIFEST).exists():  # a resumed export: the manifest says what passed the check
            _write_manifest(root, identity, num, samples, run)
            (root / JOURNAL).unlink(missing_ok=True)  # its records are in the manifest now
        todo = [u for u in units if any(i not in samples for i in u)]
        writer = ExportWriter(cfg, outputs, seed, occlusion, lay)
        _run(todo, root, writer, workers, progress, identity, num, samples, run, engine, address)
        index = file_records(root, lay.finish(root, num, cfg))
        _write_manifest(root, identity, num, samples, run, index)
    except OSError as e:
        if isinstance(e, ExportError) and not isinstance(e, StorageError):
            raise
        for tmp in root.glob(".tmp-*"):
            shutil.rmtree(tmp, ignore_errors=True)
        raise StorageError(f"cannot write the export to {root}: {e.strerror or e}; {len(samples)} of {num} samples are "
                           "finished and kept, temporaries removed; fix the cause (free space?) and re-run the "
                           "same command to resume", e.errno) from e
    return root


def _saved(old: dict, identity: dict) -> dict:
    """The identity a manifest ``old`` records, over ``identity``'s keys (``_UNRECORDED`` fills what it lacks)."""
    return {k: old.get(k, _UNRECORDED.get(k)) for k in identity}


def _same(old: dict, identity: dict) -> bool:
    return _saved(old, identity) == json.loads(json.dumps(identity))


def _differences(old: dict, identity: dict) -> str:
    """Each identity field in which the manifest ``old`` differs from this export's, with both values."""
    from flowsynth.io import json_differences

    def short(v) -> str:
        text = json.dumps(v)
        return text if len(text) <= 100 else text[:97] + "..."

    diff = [f"{path} is {short(a)} there, {short(b)} here"
            for path, a, b in json_differences(_saved(old, identity), json.loads(json.dumps(identity)))]
    return "; ".join(diff[:8]) + (f"; ... ({len(diff) - 8} more)" if len(diff) > 8 else "")


def _check_dataset(cfg, outputs, seed, occlusion) -> None:
    """Build the dataset once, so what it refuses (num_frames for flow, assets, occlusion) fails first."""
    from flowsynth.datasets import make_stream

    make_stream(cfg, outputs, seed, occlusion=occlusion)


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
            raise ExportError(f"{root} holds an export of other settings: {_differences(old, identity)}; resume it "
                              "with its own settings, choose another --out, or pass --overwrite to replace it")
        return old
    if any(not p.name.startswith(".tmp-") for p in root.iterdir()) and not overwrite:
        raise ExportError(f"{root} is not empty and holds no flowsynth manifest; choose an empty folder "
                          "or pass --overwrite")
    return None


def _verified(root: Path, records: dict, units: list[range], mode: str) -> tuple[dict[int, dict], int]:
    """The records of the samples of ``units`` whose unit is complete, and how many samples of recorded units will
    be written again (the repairs); says which.

    A unit is complete when each of its samples has a record with a camera and files that pass the ``mode``
    check, and the samples recorded with each of those files are exactly the unit's (a shard written for
    another ``num`` holds other samples).
    """
    from flowsynth.io import sample_problem

    owners: dict[str, set[int]] = {}
    for i, rec in records.items():
        for rel in rec["files"]:
            owners.setdefault(rel, set()).add(i)
    samples, redo, repaired = {}, [], 0
    for unit in units:
        if not any(i in records for i in unit):
            continue
        problem = next((f"sample {i:05d} is not recorded" for i in unit if i not in records), None)
        problem = problem or next((f"sample {i:05d} has no camera record" for i in unit
                                   if "camera" not in records[i]), None)
        problem = problem or next((f"{rel} holds other samples" for i in unit for rel in records[i]["files"]
                                   if owners[rel] != set(unit)), None)
        problem = problem or next((p for i in unit if (p := sample_problem(root, records[i]["files"], mode))), None)
        if problem is None:
            samples.update({i: records[i] for i in unit})
        else:
            redo.append(f"{_unit_name(unit)} ({problem})")
            repaired += len(unit)
    if redo:
        what = "sample" if all(len(u) == 1 for u in units) else "shard"
        _note(f"{len(redo)} incomplete or damaged {what}{'s' if len(redo) != 1 else ''} will be written "
              f"again: {_first(redo)}")
    return samples, repaired


def _unit_name(unit: range) -> str:
    return f"{unit[0]:05d}" if len(unit) == 1 else f"{unit[0]:05d}-{unit[-1]:05d}"


def _report_foreign(root: Path, records: dict, old: dict | None) -> None:
    """Name the files under root that no record of this export names; they are left as they are."""
    from flowsynth.io import foreign_files

    known = {MANIFEST, JOURNAL, *(old or {}).get("index", {})}
    for rec in records.values():
        known.update(rec["files"])
    foreign = foreign_files(root, known)
    if foreign:
        _note(f"{len(foreign)} foreign file{'s' if len(foreign) != 1 else ''} in {root} (not written by this "
              f"export; left untouched): {_first(foreign)}")


def _first(items: list[str], n: int = 10) -> str:
    return ", ".join(items[:n]) + (f", ... ({len(items) - n} more)" if len(items) > n else "")


def _note(text: str) -> None:
    """A message for the user beside the progress bar (stderr)."""
    tqdm.write(f"flowsynth export: {text}", file=sys.stderr)


def _kill_for_tests(placed: int) -> None:
    """Kill-and-resume tests: with FLOWSYNTH_TEST_KILL_AFTER=N in the environment this process SIGKILLs itself once
    N samples of this run are journaled and placed: a crash at a known point, not one timed by a sleep
    (tests/test_resume.py). Unset, it does nothing."""
    after = os.environ.get("FLOWSYNTH_TEST_KILL_AFTER")
    if after and placed >= int(after):
        import signal

        os.kill(os.getpid(), signal.SIGKILL)


def _run(todo: list[range], root, writer: ExportWriter, workers, progress, identity, num, samples, run, engine,
         address) -> None:
    bar = tqdm(total=num, initial=num - sum(len(u) for u in todo), unit="sample", disable=not progress,
               dynamic_ncols=True)
    jobs = [(tuple(u), str(root)) for u in todo]
    records: list[tuple[int, dict]] = []  # (index, stats record): summed in index order, whatever the engine
    pool = None
    results = None
    journal = None
    placed = 0
    try:
        if engine == "ray" and jobs:
            from flowsynth.distributed import export_results

            results = export_results(jobs, writer, actors=workers, address=address)
        elif workers in (None, 1) or len(jobs) <= 1:
            results = map(writer, jobs)
        else:
            pool = ProcessPoolExecutor(min(workers, len(jobs)), mp_context=_mp_context(),
                                       initializer=writer.start_worker)
            results = pool.map(run_job, jobs, chunksize=1)
        for indices, staging, files, stats, cameras in results:
            if journal is None:  # the first unit is about to be placed: now the folder is an export
                if not (root / MANIFEST).exists():
                    _write_manifest(root, identity, num, samples, run)
                journal = open(root / JOURNAL, "a")  # closed in finally
            # record first, then move: a record whose files are not all in place fails the resume check;
            # one write for the whole unit (a torn line leaves the unit incomplete, so it is written again)
            journal.write("".join(json.dumps({"sample": f"{i:05d}", "files": files, "camera": cam}) + "\n"
                                  for i, cam in zip(indices, cameras)))
            journal.flush()
            os.fsync(journal.fileno())
            _place(Path(staging), root)
            shutil.rmtree(staging, ignore_errors=True)
            for i, st, cam in zip(indices, stats, cameras):
                samples[i] = {"files": files, "camera": cam}
                records.append((i, st))
            bar.update(len(indices))
            _kill_for_tests(len(records))
            placed, before = placed + len(indices), placed
            if placed // _MANIFEST_EVERY != before // _MANIFEST_EVERY:
                _write_manifest(root, identity, num, samples, run)
                journal.seek(0)
                journal.truncate()
    finally:
        if hasattr(results, "close"):  # a Ray run stopped early: its actors stop before the staging is removed
            results.close()
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        for tmp in root.glob(".tmp-*"):  # staging of units that never got placed
            shutil.rmtree(tmp, ignore_errors=True)
        bar.close()
        if journal is not None:
            journal.close()
        if (root / MANIFEST).exists():
            from flowsynth.stats import summarize

            records.sort(key=lambda x: x[0])
            _write_manifest(root, identity, num, samples, run,
                            stats=summarize([r for _, r in records], writer.cfg) if records else None)
            (root / JOURNAL).unlink(missing_ok=True)


def _mp_context():
    """fork where the platform has it and this process has not initialised CUDA (workers inherit the loaded Warp
    modules instead of importing them again), else forkserver or spawn: CUDA does not survive fork()
    (``flowsynth.processes.worker_context``)."""
    return worker_context()


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
             exr_compression: str = "zip", shard_size: int | None = None) -> Sizes:
    """Sizes of ``export_dataset(cfg, ..., num, ...)`` without writing under its folder
    (``flowsynth export --dry-run``).

    Sample 0 is generated and written in a temporary folder that is removed afterwards; other
    samples differ from it by what their content compresses to (a few per cent, benchmarks/speed/export.py).
    Raises ConfigError for invalid arguments, as :func:`export_dataset` does.
    """
    from flowsynth.datasets import make_stream

    lay, outputs = _resolve(cfg, num, outputs, layout, 1, exr_compression, shard_size=shard_size)
    # the keys the writer writes: the outputs and what every exported sample keeps (ExportWriter.kept; "meta": the
    # camera and provenance, as the writer asks)
    sample = ExportWriter(cfg, outputs, seed, occlusion, lay).kept(make_stream(cfg, (*outputs, "meta"), seed,
                                                                               occlusion=occlusion).sample(0))
    per_sample: dict[str, int] = {}
    with tempfile.TemporaryDirectory(prefix="flowsynth-dry-run-") as tmp:
        for rel, key in lay.write(sample, 0, Path(tmp)).items():
            per_sample[key] = per_sample.get(key, 0) + (Path(tmp) / rel).stat().st_size
        index = sum((Path(tmp) / rel).stat().st_size for rel in lay.finish(Path(tmp), num, cfg))
    return Sizes(per_sample=per_sample, index=index, num=num)
