"""``BouncingThings``: a ``torch.utils.data.IterableDataset`` of generated samples.

Sample i is a pure function of (config, seed, i). Sharding over DataLoader workers and ranks, epochs and
``state_dict`` / ``load_state_dict`` (torchdata's ``StatefulDataLoader`` protocol) are ``IndexStream``'s
(flowsynth/datasets/stream.py): every index exactly once over the shards, new samples every epoch, and a restored
loader continues with exactly the samples an uninterrupted run would have produced.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from flowsynth.datasets.meta import ALL, META_OUTPUTS, PROVENANCE, split_meta
from flowsynth.datasets.stream import IndexStream, check_index
from flowsynth.errors import ConfigError
from flowsynth.plan import make_plan
from flowsynth.scene import Scene, provenance_json, sample_seed

__all__ = ["BouncingThings", "sample_seed", "stream_plan"]


def every_output(cfg, batch: bool = False) -> tuple[str, ...]:
    """What ``"all"`` names of ``cfg``'s outputs: ``flowsynth.plan.OUTPUTS`` but the stereo keys when
    ``stereo_baseline`` is 0 and the per-pair keys with one frame; with ``batch``, only what a ``DeviceBatches``
    batch renders (``BATCH_KEYS``; no rgb under motion blur)."""
    from flowsynth.plan import OUTPUTS, STEREO_KEYS, split_gap_key

    keys = [k for k in OUTPUTS if cfg.stereo_baseline > 0 or k not in STEREO_KEYS]
    if cfg.num_frames < 2:
        keys = [k for k in keys if split_gap_key(k) is None and k not in ("motion", "disparity_change")]
    if batch:
        from flowsynth.renderer import BATCH_KEYS

        keys = [k for k in keys if k in BATCH_KEYS and (k != "rgb" or cfg.shutter == 0)]
    return tuple(keys)


def stream_plan(cfg, outputs: Sequence[str], occlusion: str, threads: int | None, *, batch: bool = False):
    """(plan, provenance asked for) of a stream of ``cfg``'s samples: the plan of ``outputs`` (``"meta"`` expanded
    to ``META_OUTPUTS``, ``"all"`` to ``every_output(cfg, batch)`` and those, ``provenance`` taken out: the stream
    adds it), checked against the frame count (flow needs two frames, a frame gap fewer than ``num_frames``). Shared
    by ``BouncingThings`` and ``DeviceBatches`` (``batch``)."""
    if isinstance(outputs, str):
        outputs = [s for s in outputs.split(",") if s]
    every = every_output(cfg, batch) if isinstance(outputs, Sequence) and ALL in outputs else ()
    keys, provenance = split_meta(outputs, META_OUTPUTS, every)
    if provenance and not keys:
        raise ConfigError("outputs names only provenance; add an output to render (e.g. rgb)")
    plan = make_plan(keys, occlusion=occlusion, threads=threads, **cfg.plan_options())
    if cfg.num_frames < 2 and plan.flow_stage:
        raise ConfigError(f"flow outputs need num_frames >= 2, got {cfg.num_frames}; raise num_frames "
                          "(--num-frames) or leave the flow outputs out")
    gaps = [k for _, k in plan.pair_jobs]
    if gaps and max(gaps) >= cfg.num_frames:
        raise ConfigError(f"frame gap {max(gaps)} (flow_gaps) needs num_frames > {max(gaps)}, got {cfg.num_frames}")
    return plan, provenance


class BouncingThings(IndexStream):
    """Endless (or ``length``-long per epoch) stream of BouncingThings samples.

    Args:
        cfg: scene and rendering configuration (defaults when None).
        outputs: output keys (see ``flowsynth.plan.OUTPUTS``), and the metadata keys ``K``, ``cam_T_world``,
            ``provenance`` (the scene as a JSON string, ``Scene.from_meta`` rebuilds it), or ``"meta"`` for the
            three (``flowsynth.datasets.META_OUTPUTS``), or ``"all"`` for every output the config can make and the
            three; ``index`` and ``seed`` are always added.
        seed: dataset seed; any integer >= 0, 0 included.
        length: samples per epoch, or None for an endless stream.
        start: first index of the stream.
        occlusion: "exact" or "depth" (see flowsynth.truth.flow).
        device: Warp device of the renderer's stages ("cpu", the default; "cuda" or "cuda:N" where Warp finds one,
            else a ConfigError from the first sample, in the process that renders it: Warp is not initialised
            before DataLoader workers fork). Physics runs on the CPU whatever the device (a sample's scene does not
            depend on it).
        threads: threads of each ray launch (None = every core the process may use, and 1 inside a
            DataLoader worker, so workers x threads never exceed the cores; see flowsynth.parallel).

    Each item is a dict of tensors with fixed shapes, so ``default_collate`` batches it: per-frame
    keys (T, C, H, W), per-pair keys (T-1, C, H, W), object tables padded to ``cfg.max_objects``,
    ``index`` and ``seed`` int64 scalars; ``K`` (3, 3), ``cam_T_world`` (T, 4, 4) float32 and ``provenance`` (str)
    only when asked for. ``outputs`` lists the item's keys but ``index`` and ``seed``.
    """

    def __init__(self, cfg=None, outputs: Sequence[str] = ("rgb", "flow_fw"), seed: int = 0,
                 length: int | None = None, *, start: int = 0, occlusion: str = "exact",
                 device: str = "cpu", threads: int | None = None) -> None:
        from flowsynth.scene import BouncingThingsConfig

        cfg = BouncingThingsConfig() if cfg is None else cfg
        if not isinstance(cfg, BouncingThingsConfig):
            raise ConfigError(f"cfg must be a BouncingThingsConfig, got {type(cfg).__name__}")
        self._init_stream(seed, length, start)
        self.plan, self.provenance = stream_plan(cfg, outputs, occlusion, threads)
        self.cfg, self.device = cfg, device
        self.outputs = self.plan.outputs + ((PROVENANCE,) if self.provenance else ())

    def scene(self, i: int) -> Scene:
        """The simulated scene behind sample ``i``."""
        from flowsynth.scene import sample_scene

        return sample_scene(self.cfg, self.seed, int(i))

    def sample(self, i: int) -> dict[str, torch.Tensor]:
        """Sample ``i``: exactly the item the stream yields for index ``i``."""
        from flowsynth.raycast import resolve_device
        from flowsynth.renderer import render_plan

        i = check_index(i)
        resolve_device(self.device)  # first: a ForkError after CUDA, or a device Warp does not find, before physics
        scene = self.scene(i)
        out = render_plan(scene, self.plan, device=self.device)
        out["index"] = torch.tensor(int(i), dtype=torch.int64)
        out["seed"] = torch.tensor(self.seed, dtype=torch.int64)
        if self.provenance:
            out[PROVENANCE] = provenance_json(scene)
        return out
