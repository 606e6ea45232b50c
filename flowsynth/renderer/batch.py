"""``fs.render_batch``: B scenes rendered together on one device, every per-pixel stage launched once per batch, the
results (B, ...) torch tensors on that device; and ``batch_outputs``, the one host pipeline of every key a batch
renders, which ``fs.render`` runs as the batch of one.

A batch is one clip of B T frames to the kernels (``flowsynth.raycast.SceneAccel.batch``): frame b T + t is frame t
of scene b, and the scenes' items follow one another (``Instances.frame_start``). The primary cast, the pair kernel
(flow, validity, occlusion, out of frame, scene flow), world points (position, motion), shading and tone mapping each
run once, a thread per pixel on a GPU and row bands on the CPU (``flowsynth.parallel.launch_image``). The per-pixel
outputs stay on the device: Warp arrays become tensors by ``wp.to_torch`` (no copy), and depth and the ids are torch
operations there. Only the scenes' tables (poses, boxes, tile lists, materials) go up; no pixel comes down.

On the CPU, scene b of a batch gets bit for bit what ``fs.render(scenes[b], ...)`` gives (tests/test_batched.py): each
pixel is computed from the same inputs in the same steps, and the grouped top-level BVH builds each frame's subtree
from that frame's boxes alone.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from flowsynth.errors import ConfigError, ShapeError
from flowsynth.kernels import wp_runtime
from flowsynth.options import RenderOptions
from flowsynth.plan import Plan, make_plan, split_gap_key
from flowsynth.raycast import SceneAccel, cast_gbuffer, resolve_device, scene_arrays
from flowsynth.scene import Scene, check_lens_outputs

__all__ = ["BATCH_KEYS", "batch_outputs", "batch_tables", "batches", "check_batch_plan", "gbuffer_outputs",
           "render_batch", "render_batch_plan"]

# The outputs a batch renders (flow-family keys at every frame gap too: ``gap_key``); rgb without motion blur
# (``batches``). The others (stereo, tracks, object tables, motion-blurred rgb, the final pass) come from
# ``fs.render`` per scene.
BATCH_KEYS = frozenset({"depth", "distance", "normals", "position", "instance", "category", "asset", "flow_fw",
                        "flow_bw", "valid_fw", "valid_bw", "occ_fw", "occ_bw", "oof_fw", "oof_bw", "motion",
                        "scene_flow_fw", "scene_flow_bw", "rgb", "K", "cam_T_world"})


def render_batch(scenes: Sequence[Scene], outputs: Sequence[str] = ("depth",), *,
                 options: RenderOptions | None = None, device: str = "cpu", occlusion: str = "exact",
                 **kwargs) -> dict[str, torch.Tensor]:
    """Render the requested outputs of B scenes at once, as (B, ...) tensors on ``device``.

    Args:
        scenes: B >= 1 scenes with one camera (size, K and lens model) and one frame count T.
        outputs: keys of ``BATCH_KEYS`` (shapes and units as ``fs.render``'s, docs/conventions.md).
        options, occlusion, kwargs: as ``fs.render``'s (``spp``, ``render_mode``, ``threads``...); ``seed`` None
            gives each scene its own render seed.
        device: Warp device of every stage ("cpu", "cuda", "cuda:1", ...).

    Returns:
        dict mapping each key to a tensor with a leading batch dimension: per-frame keys (B, T, C, H, W),
        per-pair keys (B, T-k, C, H, W), ``K`` (B, 3, 3), ``cam_T_world`` (B, T, 4, 4). The tensors live on
        ``device`` (a CUDA device's on torch's device of the same ordinal, by ``wp.to_torch``; nothing is copied to
        the CPU). Scene b's slice equals ``fs.render(scenes[b], outputs, ...)`` (bit for bit on the CPU).

    Raises:
        ConfigError: no scene, an output the batch does not render, a motion-blurred rgb, scenes with different
            cameras, or a device Warp does not find. ShapeError: scenes of different sizes or frame counts.
    """
    plan = make_plan(outputs, options, occlusion=occlusion, **kwargs)
    return render_batch_plan(scenes, plan, device=device)


def render_batch_plan(scenes: Sequence[Scene], plan: Plan, device: str = "cpu",
                      prepared: Sequence[dict] | None = None) -> dict[str, torch.Tensor]:
    """``render_batch`` with a plan made once (``fs.make_plan``), as the device datasets call it; ``prepared``: each
    scene's host tables (``flowsynth.raycast.prepare_clip``, made where the scene was made, for ``batch_tables``), or
    None to make them here. The tensors live on ``device``, as ``render_batch``'s."""
    scenes = _check_scenes(scenes, plan)
    device = resolve_device(device)  # one device for every stage (ConfigError where Warp has none such)
    clips = [scene_arrays(s) for s in scenes]
    accel = SceneAccel.batch(clips, device, prepared=None if prepared is None else list(prepared))
    gb = cast_gbuffer(accel, scenes[0].camera, want_normals=plan.normals, want_points=plan.points,
                      threads=plan.threads)
    out = batch_outputs(scenes, clips, accel, gb, plan)
    return {k: out[k] for k in plan.outputs}


def batches(key: str, plan: Plan) -> bool:
    """Whether a batch renders output ``key`` under ``plan``: a key of ``BATCH_KEYS`` or of the flow family at any
    frame gap, and rgb only without motion blur (``plan.shutter`` 0)."""
    if key == "rgb":
        return plan.shutter == 0
    return key in BATCH_KEYS or split_gap_key(key) is not None


def batch_outputs(scenes: Sequence[Scene], clips: list, accel: SceneAccel, gb, plan: Plan) -> dict[str, torch.Tensor]:
    """Every output of ``plan`` that a batch renders (``batches``), of B scenes cast together: the one host pipeline
    of these keys (``fs.render`` runs it with its one scene, ``render_batch_plan`` with the batch).

    Args:
        scenes: the B scenes (one camera and frame count T); ``plan.seed`` None gives each its own render seed.
        clips: their ``flowsynth.raycast.scene_arrays``, in the order of ``accel``.
        accel, gb: the clips' ``SceneAccel`` (``SceneAccel.batch``) and their G-buffer, cast with ``plan.normals``
            and ``plan.points``.
        plan: the plan; its other outputs are left out.

    Returns:
        dict of (B, ...) tensors on the G-buffer's device (``render_batch``'s shapes), in no fixed order; with
        ``disparity_change`` asked beside a key of the fw gap-1 pass, that too (``flowsynth.truth.flow_outputs``).
    """
    wp = wp_runtime()
    want = {k for k in plan.outputs if batches(k, plan)}
    out = gbuffer_outputs(scenes, clips, accel, gb, plan)
    if plan.flow_stage:
        from flowsynth.truth import flow_outputs

        out.update(flow_outputs(scenes[0].camera, clips, accel, gb, plan))
    if "rgb" in want:
        from flowsynth.renderer.shading import render_rgb

        rgb = wp.to_torch(render_rgb(scenes, accel, gb, plan, accel.device))
        out["rgb"] = rgb.reshape(len(scenes), -1, *rgb.shape[1:])
    tdev = wp.to_torch(gb.dist).device  # wp.to_torch's mapping of the Warp device (wp.device_to_torch for CUDA)
    if "K" in want:
        out["K"] = torch.as_tensor(np.stack([s.camera.K for s in scenes]).astype(np.float32), device=tdev)
    if "cam_T_world" in want:
        out["cam_T_world"] = torch.as_tensor(np.stack([c for _, c, _ in clips]).astype(np.float32), device=tdev)
    return out


def gbuffer_outputs(scenes: Sequence[Scene], clips: list, accel: SceneAccel, gb, plan: Plan) -> dict[str, torch.Tensor]:
    """The outputs of ``plan`` read from the G-buffer of B scenes (``batch_outputs``' arguments): depth, distance,
    normals, instance, category, asset (torch operations on the G-buffer's device), position and motion (world
    points, one kernel launch), as (B, T or T - 1, C, H, W) tensors on that device."""
    wp = wp_runtime()
    camera = scenes[0].camera
    B, T, H, W = len(scenes), scenes[0].num_frames, camera.height, camera.width
    want = set(plan.outputs)
    out: dict[str, torch.Tensor] = {}

    def frames(x: torch.Tensor) -> torch.Tensor:  # (B T, ...) -> (B, T, ...)
        return x.reshape(B, T, *x.shape[1:])

    dist = wp.to_torch(gb.dist)
    tdev = dist.device  # wp.to_torch's mapping of the Warp device (wp.device_to_torch for CUDA)
    if "distance" in want:
        out["distance"] = frames(dist[:, None])
    if "depth" in want:  # float64 product, rounded to float32
        dz = torch.tensor(camera.pixel_rays_numpy()[..., 2], dtype=torch.float64, device=tdev)
        out["depth"] = frames((dist.to(torch.float64) * dz).to(torch.float32)[:, None])
    if "normals" in want:
        out["normals"] = frames(wp.to_torch(gb.normal).permute(0, 3, 1, 2).contiguous())
    ids = [k for k in ("instance", "category", "asset") if k in want]
    if ids:
        item = wp.to_torch(gb.item).long()
        rows = torch.full_like(item, int(accel.inst_start[-1]))  # no hit: the table's last row, 0
        if not accel.empty:  # (no boolean indexing: nothing waits for the device)
            rows = torch.where(item >= 0, wp.to_torch(accel.item_inst).long()[item.clamp(min=0)], rows)
        for key in ids:
            table = np.array([getattr(o, key) for s in scenes for o in s.objects] + [0], np.int32)
            out[key] = frames(torch.as_tensor(table, device=tdev)[rows][:, None])
    if "position" in want or "motion" in want:
        from flowsynth.truth import world_point_arrays

        world_T_obj = np.concatenate([w.reshape(-1, 4, 4) for _, _, w in clips])
        world, moved = world_point_arrays(gb, world_T_obj, T, moved="motion" in want, threads=plan.threads)
        if "position" in want:
            out["position"] = frames(wp.to_torch(world).to(torch.float32).permute(0, 3, 1, 2).contiguous())
        if "motion" in want:
            out["motion"] = (wp.to_torch(moved).view(torch.bool)[:, None].reshape(B, T - 1, 1, H, W) if T > 1
                             else torch.zeros((B, 0, 1, H, W), dtype=torch.bool, device=tdev))
    return out


def batch_tables(scene: Scene, plan: Plan, threads: int | None = 1) -> dict:
    """The host tables ``render_batch_plan`` needs of ``scene`` under ``plan`` (``flowsynth.raycast.prepare_clip``: the
    culling tables only where the plan asks for exact occlusion), numpy, to make in a scene worker."""
    from flowsynth.raycast import prepare_clip

    exact = plan.occlusion == "exact" and any((split_gap_key(k) or ("",))[0].startswith("occ_") for k in plan.outputs)
    return prepare_clip(*scene_arrays(scene), scene.camera, occlusion=exact, threads=threads)


def check_batch_plan(plan: Plan) -> None:
    """ConfigError unless a batch renders every output of ``plan``: keys of ``BATCH_KEYS`` (and the flow family at
    any frame gap), and rgb without motion blur."""
    unknown = [k for k in plan.outputs if k not in BATCH_KEYS and split_gap_key(k) is None]
    if unknown:
        raise ConfigError(f"render_batch does not render {unknown}; it renders {sorted(BATCH_KEYS)} (and the flow "
                          "family at every frame gap). Render the others per scene with fs.render")
    if plan.rgb and plan.shutter > 0:
        raise ConfigError(f"render_batch renders rgb without motion blur only (shutter 0, got {plan.shutter}); "
                          "render motion-blurred rgb per scene with fs.render")


def _check_scenes(scenes, plan: Plan) -> list[Scene]:
    """The batch's checks, before anything runs: scenes given, one size, frame count and camera, outputs the batch
    renders, no motion blur."""
    if isinstance(scenes, Scene):
        scenes = [scenes]
    scenes = list(scenes)
    if not scenes:
        raise ConfigError("render_batch needs at least one scene (B >= 1), got none")
    for i, s in enumerate(scenes):
        if not isinstance(s, Scene):
            raise ConfigError(f"scenes[{i}] is a {type(s).__name__}, not an fs.Scene")
    check_batch_plan(plan)
    c0, T0 = scenes[0].camera, scenes[0].num_frames
    for i, s in enumerate(scenes[1:], 1):
        c = s.camera
        if (c.width, c.height) != (c0.width, c0.height):
            raise ShapeError(f"every scene of a batch needs one image size: scenes[0] is {c0.width}x{c0.height}, "
                             f"scenes[{i}] {c.width}x{c.height}; batch scenes of one size together")
        if s.num_frames != T0:
            raise ShapeError(f"every scene of a batch needs one frame count: scenes[0] has {T0}, scenes[{i}] "
                             f"{s.num_frames}")
        if not (np.array_equal(c.K, c0.K) and c.model == c0.model and tuple(c.dist) == tuple(c0.dist)):
            raise ConfigError(f"every scene of a batch needs one camera (K and lens model): scenes[{i}] differs "
                              "from scenes[0]; batch scenes of one camera together, or render them with fs.render")
    for s in scenes:
        check_lens_outputs(s.camera, plan.outputs)
    return scenes
