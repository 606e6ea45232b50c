"""``ExportWriter``: makes one unit of an export (its samples, written by the layout into a staging folder).

One picklable object holds what a worker needs (config, outputs, seed, occlusion method, layout); the
local exporter (:mod:`flowsynth.export`) calls it in this process or in worker processes, and the Ray
engine (:mod:`flowsynth.distributed`) in Ray actors. Every engine therefore runs the same code and writes
the same bytes. The dataset is built on first use in the process that runs the writer, never pickled.

A job is ``(indices, root)``: the sample indices of one unit (``Layout.units``: one sample for most
layouts, a shard for ``webdataset``) and the export root. ``writer(job)`` generates the samples, lets
the layout write them into a new hidden staging folder ``root/.tmp-NNNNN-*`` and returns
``(indices, staging folder, {path: {"size", "sha256"}}, [flowsynth.stats.sample_record per sample],
[camera record per sample])``; moving the files into place is the caller's job. A camera record is the
sample's provenance ``camera`` (``K``, ``width``, ``height``) with the lens ``model`` and its coefficients
``dist`` always present (``"pinhole"`` and ``[]`` for a pinhole): the exporter keeps it in the manifest, so
that every layout, the ones that mimic formats without a lens model included, tells each sample's camera.
On failure the staging folder is removed, and an ``OSError`` becomes :class:`flowsynth.errors.StorageError`
naming the sample.

In a pool of worker processes, ``ProcessPoolExecutor(initializer=writer.start_worker)`` installs the
writer as its process's writer once, and ``pool.map(run_job, jobs)`` runs jobs on it.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

from flowsynth.errors import ExportError, StorageError

__all__ = ["ExportWriter", "camera_record", "run_job"]

# keys every exported sample keeps besides the requested outputs (index, seed, a mixture's source; the cameras and
# provenance, which the stream gives when asked for: "meta")
_ALWAYS_KEPT = ("index", "seed", "source", "K", "cam_T_world", "provenance")


def camera_record(provenance: str) -> dict | None:
    """The camera of a sample's ``provenance`` (JSON string): K (3x3 list), width, height, model, dist; None for a
    sample without a camera (a ``Layers`` sample)."""
    import json

    camera = json.loads(provenance).get("camera")
    return None if camera is None else {"model": "pinhole", "dist": [], **camera}


class ExportWriter:
    """Generate and write units of ``cfg``'s stream (``flowsynth.datasets.make_stream``: BouncingThings, Layers or
    Mixture) in ``layout``.

    Args:
        cfg: the export's ``BouncingThingsConfig``, ``LayersConfig`` or ``MixtureConfig``.
        outputs: resolved output keys (``flowsynth.plan.make_plan(...).outputs``).
        seed: dataset seed.
        occlusion: occlusion method (``flowsynth.plan.OCCLUSION_METHODS``).
        layout: a ``flowsynth.io.layouts.Layout`` instance.
    """

    def __init__(self, cfg, outputs: Sequence[str], seed: int, occlusion: str, layout) -> None:
        self.cfg, self.outputs, self.seed, self.occlusion, self.layout = cfg, tuple(outputs), seed, occlusion, layout
        self.keep = set(self.outputs) | set(_ALWAYS_KEPT)
        self._ds = None

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_ds"}  # the dataset is per process

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, _ds=None)

    def open(self, *, worker_process: bool = False) -> ExportWriter:
        """Build the dataset now (it is built on first use otherwise); returns self.

        ``worker_process``: this process is one of several workers (a pool process, a Ray actor):
        launches use one thread (``flowsynth.processes.set_worker_process``), and so does torch.
        """
        import torch

        from flowsynth.datasets import make_stream
        from flowsynth.stats import cheap_stats_outputs

        if worker_process:
            from flowsynth.processes import set_worker_process

            set_worker_process()
        torch.set_num_threads(1)
        self._ds = make_stream(self.cfg, (*cheap_stats_outputs(self.outputs), "meta"), self.seed,
                               occlusion=self.occlusion)
        return self

    def kept(self, sample: dict) -> dict:
        """What of ``sample`` the layout writes: the outputs and the keys every exported sample keeps (index, seed,
        a mixture's ``source``, the camera, provenance); the extra keys the statistics read are dropped."""
        return {k: v for k, v in sample.items() if k in self.keep}

    def start_worker(self) -> None:
        """Initializer of a worker process: open this writer and make it the one :func:`run_job` uses."""
        global _PROCESS_WRITER
        _PROCESS_WRITER = self.open(worker_process=True)

    def _samples(self, indices: Sequence[int], stats: list, cameras: list) -> Iterator[tuple[int, dict]]:
        """(index, sample) of each index, made when the layout asks for it; appends each one's stats and camera."""
        from flowsynth.stats import sample_record

        for i in indices:
            t = time.perf_counter()
            sample = self._ds.sample(i)
            stats.append(sample_record(sample, time.perf_counter() - t))
            cameras.append(camera_record(sample["provenance"]))
            yield i, self.kept(sample)

    def __call__(self, job: tuple[Sequence[int], str]) -> tuple[tuple[int, ...], str, dict, list[dict], list[dict]]:
        """Write the unit ``job = (indices, root)`` into a staging folder under root (module docstring)."""
        from flowsynth.io import file_records

        indices, root = tuple(int(i) for i in job[0]), job[1]
        if self._ds is None:
            self.open()
        staging = Path(tempfile.mkdtemp(prefix=f".tmp-{indices[0]:05d}-", dir=root))
        stats: list[dict] = []
        cameras: list[dict] = []
        try:
            files = self.layout.write_unit(self._samples(indices, stats, cameras), staging)
            return indices, str(staging), file_records(staging, files), stats, cameras
        except BaseException as e:
            shutil.rmtree(staging, ignore_errors=True)
            if isinstance(e, OSError) and not isinstance(e, ExportError):
                what = f"sample {indices[0]}" if len(indices) == 1 else f"samples {indices[0]}-{indices[-1]}"
                raise StorageError(f"could not write {what} under {root}: {e.strerror or e}", e.errno) from e
            raise


_PROCESS_WRITER: ExportWriter | None = None  # set in a worker process by ExportWriter.start_worker


def run_job(job: tuple[Sequence[int], str]) -> tuple[tuple[int, ...], str, dict, list[dict], list[dict]]:
    """Run ``job`` on this worker process's writer (installed by :meth:`ExportWriter.start_worker`)."""
    if _PROCESS_WRITER is None:
        raise RuntimeError("run_job runs in a worker process started with initializer=ExportWriter.start_worker")
    return _PROCESS_WRITER(job)
