"""``DeviceBatches``: the BouncingThings stream in batches of B samples, rendered together on one device.

``DeviceBatches(cfg, outputs, batch_size, num_workers, seed=..., length=...)`` yields what
``loader(BouncingThings(cfg, outputs, seed=..., length=...), batch_size)`` yields on the same rank, epoch for epoch:
the same samples in the same batches (on the CPU the same bits; scene sampling and physics run on the CPU whatever
the device, so a sample's scene does not depend on it), with the tensors on ``device``. Its shard, epochs and
positions are ``IndexStream``'s (``flowsynth.datasets.stream``), with this process as the one consumer of its rank:
under torchrun each rank reads its own indices, and a state of either stream resumes in the other when both read the
same shard. The scenes come from ``num_workers`` CPU processes (``flowsynth.datasets.loader`` over ``SceneSet``:
forkserver workers, which survive a parent that has initialised CUDA), while this process renders each batch with
``fs.render_batch``: every per-pixel stage once per batch.

    batches = fs.datasets.DeviceBatches(cfg, ["depth", "flow_fw", "occ_fw"], 16, 8, device="cuda")
    for batch in batches:              # batch["flow_fw"]: (16, T-1, 2, H, W) float32 on the GPU
        ...

Iterate it directly, in the training process: it is not a DataLoader's dataset (its workers would render on the
device; the scenes' workers are its own).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence

import torch
from torch.utils.data import Dataset, Sampler, get_worker_info

from flowsynth.datasets.bouncing import stream_plan
from flowsynth.datasets.meta import PROVENANCE
from flowsynth.datasets.stream import StreamPosition, shard_indices, shard_size
from flowsynth.datasets.workers import loader
from flowsynth.errors import ConfigError
from flowsynth.options import check_int
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


class _ShardSampler(Sampler):
    """The indices of shard g of G from position ``pos`` of ``epoch`` on, epoch after epoch, without end
    (``flowsynth.datasets.stream.shard_indices``; a shard with no index in a finite epoch yields none)."""

    def __init__(self, start: int, length: int | None, g: int, G: int, epoch: int, pos: int) -> None:
        self.start, self.length, self.g, self.G, self.epoch, self.pos = start, length, g, G, epoch, pos

    def __iter__(self) -> Iterator[int]:
        if self.length is not None and shard_size(self.length, self.g, self.G) == 0:
            return
        for e in itertools.count(self.epoch):
            for i, _ in shard_indices(self.start, self.length, self.g, self.G, e, self.pos if e == self.epoch else 0):
                yield i


def scene_list(scenes: list) -> list:
    """A DataLoader's collate function that keeps a batch's scenes as a list (module level: workers pickle it)."""
    return list(scenes)


class DeviceBatches(StreamPosition):
    """Batches of ``batch_size`` BouncingThings samples as tensors on ``device``.

    Args:
        cfg: scene and rendering configuration (defaults when None); one camera for every sample (no
            ``camera_dist_max``) and, with rgb, no motion blur (``shutter`` 0).
        outputs: keys ``fs.render_batch`` renders (``flowsynth.renderer.BATCH_KEYS``, ``K`` and ``cam_T_world``
            among them), ``provenance``, ``"meta"`` for the three, or ``"all"`` for every key a batch renders and the
            three, as in ``BouncingThings``.
        batch_size: B >= 1 samples per batch.
        num_workers: CPU processes sampling and simulating the scenes (0: in this process, before each batch).
        seed: dataset seed (>= 0).
        length: samples per epoch, or None for an endless stream (as ``BouncingThings``' ``length``).
        start: first sample index (>= 0).
        occlusion, device, threads: as ``BouncingThings``' (``device``: the Warp device the batches are rendered and
            left on; ``threads``: of this process's launches).

    Raises:
        ConfigError: bad arguments, an output ``render_batch`` does not render, a config with a lens per sample or
        motion-blurred rgb, a device Warp does not find.

    Rank r of W (``flowsynth.datasets.stream.rank_world``: torchrun's ``RANK`` and ``WORLD_SIZE``, else the process
    group) reads shard r of W: epoch e of a finite stream holds the samples start + e L + k, k = r, r + W, ... < L
    (L = ``length``), in ``len()`` = ceil(n / B) batches of B in order (n of them, on one rank all L), the last one
    short when B does not divide n: what a DataLoader with ``batch_size`` B and at most one worker yields over
    ``BouncingThings(..., length=L)``'s epoch e on that rank. An endless stream holds start + r, start + r + W, ... in
    batches of B. Either way each sample is yielded once on one rank: an epoch broken off (the loop stopped reading)
    resumes at the next ``iter()`` with the first sample not yet yielded (the next epoch's first, when its last batch
    was read), a finite epoch read to its end is followed by the next epoch, and an endless stream continues where it
    stopped.
    ``set_epoch`` and ``load_state_dict`` (``IndexStream``'s: a state names its shard, and a position inside an
    epoch resumes only in that shard) move the position; the scene workers start at the first ``iter()`` and stay
    while the position follows on (their prefetched scenes are kept for the next batches), else restart at the new
    position.

    Each batch is a dict: every output (B, ...) (per-frame keys (B, T, C, H, W), per-pair (B, T-1, C, H, W), ``K``
    (B, 3, 3), ``cam_T_world`` (B, T, 4, 4) when asked for), ``index`` and ``seed`` (B,) int64, all on ``device``,
    and, when asked for, ``provenance``: the B samples' scene descriptions (JSON strings), as
    ``BouncingThings.sample`` gives them.
    """

    def __init__(self, cfg=None, outputs: Sequence[str] = ("rgb", "flow_fw"), batch_size: int = 8,
                 num_workers: int = 0, *, seed: int = 0, length: int | None = None, start: int = 0,
                 occlusion: str = "exact", device: str = "cpu", threads: int | None = None) -> None:
        from flowsynth.raycast import resolve_device
        from flowsynth.scene import BouncingThingsConfig

        cfg = BouncingThingsConfig() if cfg is None else cfg
        if not isinstance(cfg, BouncingThingsConfig):
            raise ConfigError(f"cfg must be a BouncingThingsConfig, got {type(cfg).__name__}")
        self.batch_size = check_int("batch_size", batch_size, 1)
        self.num_workers = check_int("num_workers", num_workers, 0)
        self._init_stream(seed, length, start)
        if cfg.camera_dist_max is not None:
            raise ConfigError("camera_dist_max draws a lens per sample, and a batch needs one camera: leave "
                              "camera_dist_max None, or stream with BouncingThings")
        self.plan, self.provenance = stream_plan(cfg, outputs, occlusion, threads, batch=True)
        check_batch_plan(self.plan)
        self.device = resolve_device(device)  # here: the scenes' workers start by forkserver, never by fork
        self.cfg = cfg
        self.outputs = self.plan.outputs + ((PROVENANCE,) if self.provenance else ())
        self.scenes = SceneSet(cfg, self.seed, self.plan)
        self._source = None  # the scene workers' iterator (a DataLoader's), and the scenes taken from it not yet used
        self._held: list = []
        self._next = None  # the (g, G, epoch, pos) of the scene the source gives next (None: no source)

    def __len__(self) -> int:
        """Batches per epoch on this rank: ceil(n / batch_size), n the samples of its shard (module docstring).
        TypeError for an endless stream."""
        if self.length is None:
            raise TypeError("an endless DeviceBatches stream has no len(); pass length=... (samples per epoch)")
        layout = self.shard_layout()
        g = layout["rank"] * layout["num_workers"] + layout["worker"]
        return -(-shard_size(self.length, g, layout["world_size"] * layout["num_workers"]) // self.batch_size)

    # -- iteration ---------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[dict]:
        g, G = self._begin()
        epoch = self._epoch
        todo = shard_indices(self.start, self.length, g, G, epoch, self._pos)
        while chunk := list(itertools.islice(todo, self.batch_size)):
            indices = [i for i, _ in chunk]
            out = self._render(self._take((g, G, epoch, self._pos), indices), indices)
            self._pos = chunk[-1][1]
            yield out
        self._epoch, self._pos = epoch + 1, 0

    def _follow(self, g: int, G: int, epoch: int, pos: int) -> tuple[int, int, int, int]:
        """The position (g, G, epoch, pos) as the scene source counts it: the end of a finite epoch is the start of
        the next."""
        if self.length is not None and pos >= shard_size(self.length, g, G):
            return g, G, epoch + 1, 0
        return g, G, epoch, pos

    def _take(self, at: tuple[int, int, int, int], indices: list[int]) -> list:
        """The scenes (with their tables) of ``indices``, the samples of shard g of G from position ``at`` =
        (g, G, epoch, pos) on, from the scene workers."""
        at = self._follow(*at)
        if self._next != at:  # a new position (the first iter(), set_epoch, load_state_dict): start the workers
            self.close()
            self._source = iter(loader(self.scenes, batch_size=self.batch_size, num_workers=self.num_workers,
                                       sampler=_ShardSampler(self.start, self.length, *at),
                                       collate_fn=scene_list, persistent_workers=False))
        self._next, items = None, []  # None until the scenes are taken (an error leaves no position)
        while len(items) < len(indices):
            if not self._held:
                self._held = next(self._source)
            k = min(len(indices) - len(items), len(self._held))
            items += self._held[:k]
            self._held = self._held[k:]
        g, G, epoch, pos = at
        self._next = self._follow(g, G, epoch, pos + len(indices))
        return items

    def close(self) -> None:
        """Stop the scene workers (and drop their prefetched scenes); the next ``iter()`` starts them again."""
        self._source, self._held, self._next = None, [], None

    def _render(self, items: list[tuple[Scene, dict]], indices: list[int]) -> dict:
        """The batch of ``items`` (``SceneSet``'s (scene, tables)), samples ``indices``, rendered on the device."""
        scenes = [scene for scene, _ in items]
        out = render_batch_plan(scenes, self.plan, device=self.device, prepared=[t for _, t in items])
        like = out[self.plan.outputs[0]]
        out["index"] = torch.tensor(indices, dtype=torch.int64, device=like.device)
        out["seed"] = torch.full((len(scenes),), self.seed, dtype=torch.int64, device=like.device)
        if self.provenance:
            out[PROVENANCE] = [provenance_json(s) for s in scenes]
        return out
