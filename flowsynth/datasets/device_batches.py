"""``DeviceBatches``: the BouncingThings stream in batches of B samples, rendered together on one device.

Batch i holds samples start + i B .. start + i B + B - 1 of ``BouncingThings(cfg, outputs, seed=seed)``: the same
scenes (scene sampling and physics run on the CPU whatever the device, so a sample's scene does not depend on it) and,
on the CPU, the same bits. The scenes come from ``workers`` CPU processes (a ``flowsynth.datasets.loader`` DataLoader
over ``SceneSet``: forkserver workers, which survive a parent that has initialised CUDA), while this process renders
each batch with ``fs.render_batch``: every per-pixel stage once per batch, the tensors left on the device.

    batches = fs.datasets.DeviceBatches(cfg, ["depth", "flow_fw", "occ_fw"], batch_size=16, device="cuda", workers=8)
    for batch in batches:              # batch["flow_fw"]: (16, T-1, 2, H, W) float32 on the GPU
        ...

Iterate it directly, in the training process: it is not a DataLoader's dataset (its workers would render on the
device; the scenes' workers are its own).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler, get_worker_info

from flowsynth.datasets.bouncing import stream_plan
from flowsynth.datasets.workers import loader
from flowsynth.errors import ConfigError
from flowsynth.renderer import batch_tables, check_batch_plan, render_batch_plan
from flowsynth.scene import Scene, provenance_json

__all__ = ["DeviceBatches", "SceneSet"]


class SceneSet(Dataset):
    """Map-style dataset of the simulated scenes of the dataset (cfg, seed): item i is the ``fs.Scene`` behind sample
    i of ``BouncingThings(cfg, seed=seed)`` (``flowsynth.scene.sample_scene``); with a ``plan``, the pair (scene, its
    host tables for the plan, ``flowsynth.renderer.batch_tables``). What ``DeviceBatches``' workers make: the scene's
    sampling, physics and tables on a CPU, so the rendering process only joins and uploads."""

    def __init__(self, cfg, seed: int, plan=None) -> None:
        self.cfg, self.seed, self.plan = cfg, int(seed), plan

    def __getitem__(self, i: int):
        from flowsynth.scene import sample_scene

        in_worker = get_worker_info() is not None
        if in_worker:
            torch.set_num_threads(1)  # workers share the cores (flowsynth.parallel: one thread each)
        scene = sample_scene(self.cfg, self.seed, int(i))
        if self.plan is None:
            return scene
        return scene, batch_tables(scene, self.plan, threads=1 if in_worker else self.plan.threads)


class _Indices(Sampler):
    """start, start + 1, ... (``count`` of them, or endless)."""

    def __init__(self, start: int, count: int | None) -> None:
        self.start, self.count = start, count

    def __iter__(self) -> Iterator[int]:
        it = itertools.count(self.start)
        return it if self.count is None else itertools.islice(it, self.count)


def scene_list(scenes: list) -> list:
    """A DataLoader's collate function that keeps a batch's scenes as a list (module level: workers pickle it)."""
    return list(scenes)


class DeviceBatches:
    """Batches of ``batch_size`` BouncingThings samples as tensors on ``device`` (batch i: samples start + i B ..).

    Args:
        cfg: scene and rendering configuration (defaults when None); one camera for every sample (no
            ``camera_dist_max``) and, with rgb, no motion blur (``shutter`` 0).
        outputs: keys ``fs.render_batch`` renders (``flowsynth.renderer.BATCH_KEYS``); ``K`` and ``cam_T_world`` are
            always added, as in ``BouncingThings``.
        batch_size: B >= 1 samples per batch.
        device: Warp device of the renderer ("cpu", "cuda", "cuda:1", ...); the tensors live there.
        seed: dataset seed (>= 0); start: first sample index (>= 0).
        workers: CPU processes sampling and simulating scenes (0: in this process, between batches).
        length: batches per pass, or None for an endless stream.
        occlusion, threads: as ``BouncingThings``' (threads of this process's launches).

    Each batch is a dict: every output (B, ...) (per-frame keys (B, T, C, H, W), per-pair (B, T-1, C, H, W), ``K``
    (B, 3, 3), ``cam_T_world`` (B, T, 4, 4)), ``index`` and ``seed`` (B,) int64, all on ``device``, and
    ``provenance``, the B samples' scene descriptions (JSON strings), as ``BouncingThings.sample`` gives them.
    """

    def __init__(self, cfg=None, outputs: Sequence[str] = ("rgb", "flow_fw"), batch_size: int = 8, *,
                 device: str = "cpu", seed: int = 0, start: int = 0, workers: int = 0, length: int | None = None,
                 occlusion: str = "exact", threads: int | None = None) -> None:
        from flowsynth.raycast import resolve_device
        from flowsynth.scene import BouncingThingsConfig

        cfg = BouncingThingsConfig() if cfg is None else cfg
        if not isinstance(cfg, BouncingThingsConfig):
            raise ConfigError(f"cfg must be a BouncingThingsConfig, got {type(cfg).__name__}")
        for name, v, lo in (("batch_size", batch_size, 1), ("seed", seed, 0), ("start", start, 0),
                            ("workers", workers, 0)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ConfigError(f"{name} must be an integer >= {lo}, got {v!r}")
        if length is not None and (isinstance(length, bool) or not isinstance(length, (int, np.integer))
                                   or length < 1):
            raise ConfigError(f"length must be None (endless) or an integer >= 1 (batches), got {length!r}")
        if cfg.camera_dist_max is not None:
            raise ConfigError("camera_dist_max draws a lens per sample, and a batch needs one camera: leave "
                              "camera_dist_max None, or stream with BouncingThings")
        self.plan = stream_plan(cfg, outputs, occlusion, threads)
        check_batch_plan(self.plan)
        self.device = resolve_device(device)  # here: the scenes' workers start by forkserver, never by fork
        self.cfg, self.batch_size, self.seed, self.start = cfg, int(batch_size), int(seed), int(start)
        self.workers, self.length = int(workers), length
        self.outputs = self.plan.outputs
        self.scenes = SceneSet(cfg, self.seed, self.plan)
        self._epoch = 0  # passes made over a finite stream

    def __len__(self) -> int:
        if self.length is None:
            raise TypeError("an endless DeviceBatches stream has no len(); pass length=...")
        return self.length

    def indices(self, i: int) -> range:
        """The sample indices of batch ``i``."""
        first = self.start + int(i) * self.batch_size
        return range(first, first + self.batch_size)

    def batch(self, i: int) -> dict:
        """Batch ``i``, its scenes made in this process: exactly the batch the stream yields at position i."""
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or i < 0:
            raise ConfigError(f"batch index must be an integer >= 0, got {i!r}")
        return self.render([self.scenes[k] for k in self.indices(i)], self.indices(i).start)

    def render(self, items: list[tuple[Scene, dict]], first: int) -> dict:
        """Render the batch of ``items`` (``SceneSet``'s (scene, tables)), samples ``first`` .. ``first`` + B - 1, on
        the device."""
        scenes = [scene for scene, _ in items]
        out = render_batch_plan(scenes, self.plan, device=self.device, prepared=[t for _, t in items])
        like = out[self.plan.outputs[0]]
        out["index"] = torch.arange(first, first + len(scenes), dtype=torch.int64, device=like.device)
        out["seed"] = torch.full((len(scenes),), self.seed, dtype=torch.int64, device=like.device)
        out["provenance"] = [provenance_json(s) for s in scenes]
        return out

    def __iter__(self) -> Iterator[dict]:
        """Endless, or (``length``) one pass of ``length`` batches; as ``BouncingThings``' epochs, pass e of a finite
        stream holds batches e ``length`` .. (e + 1) ``length`` - 1: every pass sees new scenes."""
        count = None if self.length is None else self.length * self.batch_size
        first = self.start + (0 if count is None else self._epoch * count)
        scenes = loader(self.scenes, batch_size=self.batch_size, num_workers=self.workers,
                        sampler=_Indices(first, count), collate_fn=scene_list, persistent_workers=False)
        for batch in scenes:
            yield self.render(batch, first)
            first += len(batch)
        self._epoch += 1
