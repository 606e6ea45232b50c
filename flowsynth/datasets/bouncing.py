"""``BouncingThings``: a ``torch.utils.data.IterableDataset`` of generated samples.

Sample i is a pure function of (config, seed, i). The global index stream is split into shards:
shard g of G = world_size * num_workers, with g = rank * num_workers + worker_id, takes the indices
i = start + g + G m (m = 0, 1, ...). So the union over shards is every index exactly once, whatever
the number of workers, ranks or the process start method.

Epochs. With ``length=None`` the stream is endless: an epoch ends when the training loop stops
reading, and the next ``iter()`` on the same dataset object (num_workers=0, or persistent workers)
continues after the last sample this shard produced, so no sample repeats. With a finite ``length``
L, epoch e covers indices [start + e L, start + (e + 1) L): every epoch sees new scenes. The epoch
counter advances on each ``iter()`` of the same object; with non-persistent workers (fresh copies
every epoch) call ``set_epoch(e)`` before each epoch, as with ``DistributedSampler``.

Resuming. ``state_dict()`` / ``load_state_dict()`` follow torchdata's ``StatefulDataLoader``
protocol: each worker's copy reports its own position, and a restored loader continues with exactly
the samples an uninterrupted run would have produced.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from flowsynth.errors import ConfigError
from flowsynth.parallel import check_not_forked_from_cuda
from flowsynth.plan import make_plan
from flowsynth.scene import Scene, provenance_json, sample_seed

__all__ = ["BouncingThings", "sample_seed", "stream_plan"]


def _shard() -> tuple[int, int]:
    """(shard id, number of shards) from torch.distributed rank/world size and the DataLoader worker."""
    rank, world = 0, 1
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        rank, world = torch.distributed.get_rank(), torch.distributed.get_world_size()
    info = get_worker_info()
    wid, nw = (info.id, info.num_workers) if info is not None else (0, 1)
    return rank * nw + wid, world * nw


def stream_plan(cfg, outputs: Sequence[str], occlusion: str, threads: int | None):
    """The plan of a stream of ``cfg``'s samples: ``outputs`` and K and cam_T_world, checked against the frame count
    (flow needs two frames, a frame gap fewer than ``num_frames``). Shared by ``BouncingThings`` and
    ``DeviceBatches``."""
    plan = make_plan(tuple(dict.fromkeys([*outputs, "K", "cam_T_world"])), occlusion=occlusion, threads=threads,
                     **cfg.plan_options())
    if cfg.num_frames < 2 and plan.flow_stage:
        raise ConfigError(f"flow outputs need num_frames >= 2, got {cfg.num_frames}; raise num_frames "
                          "(--num-frames) or leave the flow outputs out")
    gaps = [k for _, k in plan.pair_jobs]
    if gaps and max(gaps) >= cfg.num_frames:
        raise ConfigError(f"frame gap {max(gaps)} (flow_gaps) needs num_frames > {max(gaps)}, got {cfg.num_frames}")
    return plan


class BouncingThings(IterableDataset):
    """Endless (or ``length``-long per epoch) stream of BouncingThings samples.

    Args:
        cfg: scene and rendering configuration (defaults when None).
        outputs: output keys (see ``flowsynth.plan.OUTPUTS``); ``index``, ``seed``, ``K`` and
            ``cam_T_world`` are always added.
        seed: dataset seed; any integer >= 0, 0 included.
        length: samples per epoch, or None for an endless stream.
        start: first index of the stream.
        occlusion: "exact" or "depth" (see flowsynth.truth.flow).
        device: Warp device of the renderer's stages ("cpu", the default; "cuda" or "cuda:N" where Warp finds one,
            else a ConfigError from the first sample, in the process that renders it: Warp is not initialised
            before DataLoader workers fork). Written for any Warp device; device placement tested on an H100,
            speed not. Physics runs on the CPU whatever the device (a sample's scene does not depend on it).
        threads: threads of each ray launch (None = every core the process may use, and 1 inside a
            DataLoader worker, so workers x threads never exceed the cores; see flowsynth.parallel).

    Each item is a dict of tensors with fixed shapes, so ``default_collate`` batches it: per-frame
    keys (T, C, H, W), per-pair keys (T-1, C, H, W), object tables padded to ``cfg.max_objects``,
    ``index`` and ``seed`` int64 scalars.
    """

    def __init__(self, cfg=None, outputs: Sequence[str] = ("rgb", "flow_fw"), seed: int = 0,
                 length: int | None = None, *, start: int = 0, occlusion: str = "exact",
                 device: str = "cpu", threads: int | None = None) -> None:
        from flowsynth.scene import BouncingThingsConfig

        cfg = BouncingThingsConfig() if cfg is None else cfg
        if not isinstance(cfg, BouncingThingsConfig):
            raise ConfigError(f"cfg must be a BouncingThingsConfig, got {type(cfg).__name__}")
        for name, v, lo in (("seed", seed, 0), ("start", start, 0)):
            if not isinstance(v, (int, np.integer)) or v < lo:
                raise ConfigError(f"{name} must be an integer >= {lo}, got {v!r}")
        if length is not None and (not isinstance(length, (int, np.integer)) or length < 1):
            raise ConfigError(f"length must be None (endless) or an integer >= 1, got {length!r}")
        self.plan = stream_plan(cfg, outputs, occlusion, threads)
        self.cfg, self.seed, self.length, self.start, self.device = cfg, int(seed), length, int(start), device
        self.outputs = self.plan.outputs
        self._epoch = 0
        self._pos = 0  # samples this shard has produced in the current epoch (endless: ever)

    def __len__(self) -> int:
        if self.length is None:
            raise TypeError("an endless BouncingThings stream has no len(); pass length=...")
        return self.length

    def scene(self, i: int) -> Scene:
        """The simulated scene behind sample ``i``."""
        from flowsynth.scene import sample_scene

        check_not_forked_from_cuda()
        return sample_scene(self.cfg, self.seed, int(i))

    def sample(self, i: int) -> dict[str, torch.Tensor]:
        """Sample ``i``: exactly the item the stream yields for index ``i``."""
        from flowsynth.raycast import resolve_device
        from flowsynth.renderer import render_plan

        if not isinstance(i, (int, np.integer)) or i < 0:
            raise ConfigError(f"sample index must be an integer >= 0, got {i!r}")
        resolve_device(self.device)  # first: a ForkError after CUDA, or a device Warp does not find, before physics
        scene = self.scene(i)
        out = render_plan(scene, self.plan, device=self.device)
        out["index"] = torch.tensor(int(i), dtype=torch.int64)
        out["seed"] = torch.tensor(self.seed, dtype=torch.int64)
        out["provenance"] = provenance_json(scene)
        return out

    # -- iteration ---------------------------------------------------------------------------------
    def set_epoch(self, epoch: int) -> None:
        """Start the next ``iter()`` at ``epoch`` (finite length; needed with non-persistent workers)."""
        self._epoch, self._pos = int(epoch), 0

    def _indices(self, g: int, G: int, epoch: int, pos: int) -> Iterator[int]:
        m = pos
        while True:
            k = g + G * m
            if self.length is not None and k >= self.length:
                return
            base = self.start + (epoch * self.length if self.length is not None else 0)
            yield base + k, m + 1
            m += 1

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        if get_worker_info() is not None:
            torch.set_num_threads(1)
        g, G = _shard()
        epoch = self._epoch
        for i, next_pos in self._indices(g, G, epoch, self._pos):
            item = self.sample(i)
            self._pos = next_pos
            yield item
        # finite epoch exhausted: the next iter() starts the next epoch
        self._epoch, self._pos = epoch + 1, 0

    def state_dict(self) -> dict:
        """This copy's position (per worker under StatefulDataLoader)."""
        return {"epoch": self._epoch, "pos": self._pos, "seed": self.seed, "start": self.start}

    def load_state_dict(self, state: dict) -> None:
        """Restore a position saved by ``state_dict``; refuses a state of another seed or start."""
        if state.get("seed") != self.seed or state.get("start") != self.start:
            raise ConfigError(f"state was saved with seed={state.get('seed')}, start={state.get('start')}; "
                              f"this dataset has seed={self.seed}, start={self.start}")
        self._epoch, self._pos = int(state["epoch"]), int(state["pos"])
