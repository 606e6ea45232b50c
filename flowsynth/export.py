"""Crash-safe, resumable, parallel export of BouncingThings samples to disk.

Layouts:

native (one folder per sample, see flowsynth/sampleio.py for the files)::

    DIR/
      manifest.json            config, seed, outputs, layout, versions, per-sample checksums, stats
                               (flowsynth.stats over the samples the last run generated)
      00000/  rgb_0000.png  flow_fw_0000.exr  instance_0000.png ...  meta.json
      00001/  ...

flyingchairs (what ``torchvision.datasets.FlyingChairs`` reads)::

    DIR/
      manifest.json
      FlyingChairs_train_val.txt     one line per sample: 1 = train, 2 = val (every 10th sample)
      data/00001_img1.ppm  00001_img2.ppm  00001_flow.flo   (1-based numbering like the original)

Crash safety: a native sample is written into a hidden temporary folder and renamed into place when
complete, so a folder ``NNNNN/`` is always whole. A flyingchairs sample writes its images first and
its ``.flo`` last (each file atomically); a sample counts as present only when its ``.flo`` exists, and
a resumed export removes images left without one. ``manifest.json`` is rewritten atomically.
"""

from __future__ import annotations

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

__all__ = ["LAYOUTS", "MANIFEST", "export"]

LAYOUTS = ("native", "flyingchairs")
MANIFEST = "manifest.json"
_FC_OUTPUTS = ("rgb", "flow_fw")
# native layout default: images, flow both ways with occlusion, ids, and what boxes_coco.json needs
DEFAULT_OUTPUTS = ("rgb", "depth", "flow_fw", "flow_bw", "occ_fw", "occ_bw", "instance", "box2d_visible",
                   "visible_pixels", "object_valid", "object_category")


def _versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("flowsynth", "warp-lang", "torch", "kornia", "numpy", "newton"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = None
    return out


def _identity(cfg, seed: int, outputs: tuple, layout: str) -> dict:
    return {"config": cfg.to_dict(), "seed": seed, "outputs": list(outputs), "layout": layout}


def _sample_name(i: int, layout: str) -> str:
    return f"{i:05d}" if layout == "native" else f"data/{i + 1:05d}_flow.flo"


def _existing(root: Path, num: int, layout: str) -> set[int]:
    done = {i for i in range(num) if (root / _sample_name(i, layout)).exists()}
    if layout == "flyingchairs":
        for img in (root / "data").glob("*_img[12].ppm"):
            if not img.with_name(img.name.split("_")[0] + "_flow.flo").exists():
                img.unlink()
    for tmp in root.glob(".tmp-*"):
        shutil.rmtree(tmp, ignore_errors=True)
    return done


_WORKER: dict = {}


def _init_worker(cfg, outputs, seed, occlusion) -> None:
    import torch

    from flowsynth.datasets import BouncingThings

    torch.set_num_threads(1)
    from flowsynth.stats import cheap_stats_outputs

    _WORKER["ds"] = BouncingThings(cfg, outputs=cheap_stats_outputs(outputs), seed=seed, occlusion=occlusion)
    _WORKER["keep"] = set(outputs) | {"index", "seed", "K", "cam_T_world"}


def _init_pool_worker(cfg, outputs, seed, occlusion) -> None:
    """``_init_worker`` in one of several worker processes: ray launches use one thread (flowsynth.parallel)."""
    from flowsynth.parallel import set_worker_process

    set_worker_process()
    _init_worker(cfg, outputs, seed, occlusion)


def _write_one(args) -> tuple[int, dict, dict]:
    """Generate sample i and write it; returns (i, {file: sha256}, flowsynth.stats.sample_record)."""
    from flowsynth.sampleio import file_digest, write_sample
    from flowsynth.stats import sample_record

    i, root, layout = args
    root = Path(root)
    t = time.perf_counter()
    sample = _WORKER["ds"].sample(i)
    record = sample_record(sample, time.perf_counter() - t)
    sample = {k: v for k, v in sample.items() if k in _WORKER["keep"]}
    try:
        if layout == "native":
            tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{i:05d}-", dir=root))
            names = write_sample(sample, tmp)
            digests = {n: file_digest(tmp / n) for n in names}
            os.replace(tmp, root / f"{i:05d}")
            return i, digests, record
        from flowsynth.io import write_flo, write_ppm

        stem = root / "data" / f"{i + 1:05d}"
        files = {f"{stem.name}_img1.ppm": lambda p: write_ppm(p, sample["rgb"][0].numpy()),
                 f"{stem.name}_img2.ppm": lambda p: write_ppm(p, sample["rgb"][1].numpy()),
                 f"{stem.name}_flow.flo": lambda p: write_flo(p, sample["flow_fw"][0].numpy())}
        digests = {}
        for name, write in files.items():
            write(stem.parent / name)
            digests[name] = file_digest(stem.parent / name)
        return i, digests, record
    except OSError as e:
        raise ExportError(f"could not write sample {i} under {root}: {e}") from e


def _write_manifest(root: Path, identity: dict, num: int, samples: dict, stats: dict | None = None) -> None:
    from flowsynth.io import write_json

    body = dict(identity, num=num, versions=_versions(),
                samples={f"{i:05d}": samples[i] for i in sorted(samples)})
    if stats is None and (root / MANIFEST).is_file():  # a run that generated nothing keeps the last stats
        stats = json.loads((root / MANIFEST).read_text()).get("stats")
    if stats is not None:  # flowsynth.stats.summarize over the samples the last run generated
        body["stats"] = stats
    write_json(root / MANIFEST, body)


def export(cfg, out: str | os.PathLike, num: int, *, seed: int = 0, outputs=None, workers: int = 1,
           layout: str = "native", overwrite: bool = False, occlusion: str = "exact",
           progress: bool = True) -> Path:
    """Export samples 0..num-1 of ``BouncingThings(cfg, outputs, seed)`` to ``out``; resumes if interrupted.

    Raises ExportError when ``out`` holds an export of another config/seed/outputs/layout (pass
    ``overwrite=True`` to replace it) or cannot be written. Returns the output folder.
    """
    from flowsynth.plan import make_plan

    if layout not in LAYOUTS:
        raise ConfigError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    if not isinstance(num, int) or num < 1:
        raise ConfigError(f"num must be an integer >= 1, got {num!r}")
    if not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"workers must be an integer >= 1, got {workers!r}")
    if outputs is None:
        outputs = _FC_OUTPUTS if layout == "flyingchairs" else DEFAULT_OUTPUTS
    outputs = make_plan(outputs).outputs
    if layout == "flyingchairs":
        missing = [k for k in _FC_OUTPUTS if k not in outputs]
        if missing or cfg.num_frames < 2:
            raise ConfigError(f"layout flyingchairs needs outputs rgb and flow_fw and num_frames >= 2 "
                              f"(missing: {missing}, num_frames={cfg.num_frames})")
    root = Path(out)
    identity = _identity(cfg, seed, outputs, layout)
    samples: dict[int, dict] = {}
    try:
        root.mkdir(parents=True, exist_ok=True)
        manifest = root / MANIFEST
        if manifest.exists():
            old = json.loads(manifest.read_text())
            if {k: old.get(k) for k in identity} != json.loads(json.dumps(identity)):
                if not overwrite:
                    raise ExportError(f"{root} holds an export with a different config/seed/outputs/layout; "
                                      "choose another --out or pass --overwrite to replace it")
                _clear(root)
            else:
                samples = {int(k): v for k, v in old.get("samples", {}).items()}
        elif any(root.iterdir()) and not overwrite:
            raise ExportError(f"{root} is not empty and holds no flowsynth manifest; choose an empty folder "
                              "or pass --overwrite")
        if layout == "flyingchairs":
            (root / "data").mkdir(exist_ok=True)
        done = _existing(root, num, layout)
        samples = {i: v for i, v in samples.items() if i in done}
        for i in sorted(done - set(samples)):  # finished after the last manifest update
            samples[i] = _digests_on_disk(root, i, layout)
        _write_manifest(root, identity, num, samples)
        todo = [i for i in range(num) if i not in done]
        _run(todo, root, layout, cfg, outputs, seed, occlusion, workers, progress, identity, num, samples)
        if layout == "flyingchairs":
            from flowsynth.io import atomic_write_bytes

            split = "".join("2\n" if (i + 1) % 10 == 0 else "1\n" for i in range(num))
            atomic_write_bytes(root / "FlyingChairs_train_val.txt", split.encode())
    except OSError as e:
        if isinstance(e, ExportError):
            raise
        raise ExportError(f"cannot write the export to {root}: {e.strerror or e}; samples already written "
                          "are kept, re-run the same command to resume") from e
    return root


def _digests_on_disk(root: Path, i: int, layout: str) -> dict:
    from flowsynth.sampleio import file_digest

    if layout == "native":
        return {p.name: file_digest(p) for p in sorted((root / f"{i:05d}").iterdir())}
    stem = f"{i + 1:05d}"
    return {n: file_digest(root / "data" / n) for n in (f"{stem}_img1.ppm", f"{stem}_img2.ppm", f"{stem}_flow.flo")}


def _run(todo, root, layout, cfg, outputs, seed, occlusion, workers, progress, identity, num, samples) -> None:
    bar = tqdm(total=num, initial=num - len(todo), unit="sample", disable=not progress, dynamic_ncols=True)
    jobs = [(i, str(root), layout) for i in todo]
    records: list[dict] = []
    pool = None
    try:
        if workers == 1 or len(jobs) <= 1:
            _init_worker(cfg, outputs, seed, occlusion)
            results = map(_write_one, jobs)
        else:
            pool = ProcessPoolExecutor(min(workers, len(jobs)), mp_context=_mp_context(),
                                       initializer=_init_pool_worker, initargs=(cfg, outputs, seed, occlusion))
            results = pool.map(_write_one, jobs, chunksize=1)
        for n, (i, digests, record) in enumerate(results, 1):
            samples[i] = digests
            records.append(record)
            bar.update(1)
            if n % 16 == 0:
                _write_manifest(root, identity, num, samples)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        bar.close()
        from flowsynth.stats import summarize

        _write_manifest(root, identity, num, samples, summarize(records, cfg) if records else None)


def _mp_context():
    """fork where the platform has it (like DataLoader's default: workers inherit the loaded Warp modules
    instead of importing them again), spawn elsewhere."""
    return mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")


def _clear(root: Path) -> None:
    for p in root.iterdir():
        if p.is_dir() and (p.name.isdigit() or p.name == "data" or p.name.startswith(".tmp-")):
            shutil.rmtree(p)
        elif p.name in (MANIFEST, "FlyingChairs_train_val.txt"):
            p.unlink()
