"""``fs.render`` and ``fs.render_plan``: one primary ray cast per frame -> G-buffer -> requested ground truth, as
torch tensors. The orchestrator: it runs the stages a plan asks for (``flowsynth.plan``), each in its own module.

Output keys, shapes and meaning are those of docs/conventions.md. (This module was ``flowsynth.renderer`` until the
folders of issue 48, and ``flowsynth.render`` before the function ``fs.render`` and a module of that name shadowed each
other; the G-buffer primitive it held is ``flowsynth.raycast.gbuffer``.)
"""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import torch

from flowsynth.options import RenderOptions
from flowsynth.plan import Plan, make_plan
from flowsynth.raycast import GBuffer, SceneAccel, cast_gbuffer, resolve_device, scene_arrays, to_torch
from flowsynth.scene import Scene, check_lens_outputs

__all__ = ["HOST_KEYS", "gbuffer_outputs", "render", "render_plan"]

# The G-buffer outputs computed on the host from ``GBuffer.host()`` (elementwise, where the sample leaves Warp).
HOST_KEYS = frozenset({"distance", "depth", "normals", "instance", "category", "asset"})


def render(scene: Scene, outputs: list[str] | tuple[str, ...] = ("depth",), *, options: RenderOptions | None = None,
           device: str = "cpu", occlusion: str = "exact", **kwargs) -> dict[str, torch.Tensor]:
    """Render the requested ground truth of every frame of ``scene``.

    Args:
        scene: camera path and objects.
        outputs: keys from ``flowsynth.plan.OUTPUTS`` (see docs/conventions.md for shapes and units).
        device: Warp device of every stage ("cpu", the default; "cuda", "cuda:1", ... where Warp finds one, else
            a ConfigError naming the device and what Warp found). Written for any Warp device; tested on the CPU
            only (docs/architecture.md, Devices). Results are CPU tensors.
        occlusion: "exact" (visibility rays) or "depth" (cheaper depth-buffer comparison;
            benchmarks/accuracy/accuracy.py measures what each costs and how often each is wrong:
            docs/decisions/0003-exact-occlusion.md).
        options: the render options (``fs.RenderOptions``: spp, edge_spp, render_mode, ..., final_*; None = the
            defaults, docs/rendering.md, Options), e.g. a config's ``cfg.render_options``.
        kwargs: render options by name (``spp=4``), applied on top of ``options``; and ``seed`` (None = the scene's
            render seed) and ``threads`` (ray-launch threads; None = every core the process may use, 1 inside
            DataLoader and export workers; see flowsynth.parallel), as ``flowsynth.plan.make_plan`` takes them.

    Returns:
        dict mapping each requested key to a CPU tensor.
    """
    plan = make_plan(outputs, options, occlusion=occlusion, **kwargs)
    return render_plan(scene, plan, device=device)


def render_plan(scene: Scene, plan: Plan, device: str = "cpu") -> dict[str, torch.Tensor]:
    """Run the stages of ``plan`` (``flowsynth.plan.make_plan``, or ``fs.make_plan``) on ``scene``: what
    ``fs.render`` does after making the plan, and what the datasets call with the plan they made once.

    ``device``: as ``render``'s. The G-buffer stays in Warp arrays on it between the stages; ``GBuffer.host()``
    hands it to the stages that compute on the host (docs/architecture.md, Devices).

    Returns:
        dict mapping each key of ``plan.outputs`` to a CPU tensor (docs/conventions.md).
    """
    device = resolve_device(device)  # one device for every stage (ConfigError where Warp has none such)
    if plan.seed is None:  # the renderer's noise seed: the scene's unless the plan sets one
        plan = replace(plan, seed=int(scene.render_seed))
    check_lens_outputs(scene.camera, plan.outputs)
    meshes, cam_T_world, world_T_obj = scene_arrays(scene)
    accel = SceneAccel(meshes, cam_T_world, world_T_obj, device=device)
    gb = cast_gbuffer(accel, scene.camera, want_normals=plan.normals, want_points=plan.points, threads=plan.threads)
    out: dict[str, torch.Tensor] = {}
    out.update(gbuffer_outputs(scene, gb, plan, world_T_obj))
    if plan.flow_stage:
        from flowsynth.truth import flow_outputs, world_points

        clip = (meshes, cam_T_world, world_T_obj)
        out.update({k: v[0] for k, v in flow_outputs(scene.camera, [clip], accel, gb, plan).items()})
        if "motion" in plan.outputs:
            moved = world_points(gb, world_T_obj, moved=True, threads=plan.threads)[1]
            out["motion"] = torch.from_numpy(moved[:, None])
    if plan.stereo:
        from flowsynth.truth import right_view, stereo_outputs

        right = right_view(scene, world_T_obj, plan, device=device)
        out.update(stereo_outputs(scene, accel, gb, plan, world_T_obj, cam_T_world, right=right, done=out))
        if "rgb_right" in plan.outputs:
            out["rgb_right"] = _rgb_right(scene, right, gb, plan, device)
    if plan.tracks:
        from flowsynth.truth import track_outputs

        out.update(track_outputs(scene, accel, gb, plan, world_T_obj, cam_T_world))
    if plan.boxes:
        from flowsynth.truth import object_tables

        out.update(object_tables(scene, gb, plan, world_T_obj, cam_T_world))
    if plan.rgb:
        from flowsynth.renderer.shading import render_rgb

        out["rgb"] = to_torch(render_rgb([scene], accel, gb, plan, device=device))
    if plan.final:  # the final pass (flowsynth/renderer/finalpass.py): camera effects, the ground truth untouched
        from flowsynth.renderer.finalpass import render_final

        out["rgb_final"] = render_final(scene, accel, gb, plan, device=device)
    if "K" in plan.outputs:
        out["K"] = torch.from_numpy(scene.camera.K.astype(np.float32))
    if "cam_T_world" in plan.outputs:
        out["cam_T_world"] = torch.from_numpy(cam_T_world.astype(np.float32))
    return {k: out[k] for k in plan.outputs}


def gbuffer_outputs(scene: Scene, gb: GBuffer, plan: Plan, world_T_obj: np.ndarray) -> dict[str, torch.Tensor]:
    """depth, distance, normals, position, instance, category, asset from the raw G-buffer."""
    out = {}
    want = set(plan.outputs)
    if "position" in want:  # world points on the G-buffer's device (flowsynth.truth.flow.world_points)
        from flowsynth.truth import world_points

        pos = world_points(gb, world_T_obj, moved=False, threads=plan.threads)[0]
        out["position"] = torch.from_numpy(np.ascontiguousarray(pos.astype(np.float32).transpose(0, 3, 1, 2)))
    if not want & HOST_KEYS:
        return out
    host = gb.host()  # the hand-over: these outputs are computed on the host
    idx = host.instance_index
    if "distance" in want:
        out["distance"] = torch.from_numpy(host.dist[:, None].copy())
    if "depth" in want:
        dz = scene.camera.pixel_rays_numpy()[..., 2]
        out["depth"] = torch.from_numpy(np.multiply(host.dist, dz, dtype=np.float64).astype(np.float32)[:, None])
    if "normals" in want:
        out["normals"] = torch.from_numpy(np.ascontiguousarray(host.normal.transpose(0, 3, 1, 2)))
    lut = {
        "instance": np.array([o.instance for o in scene.objects], np.int32),
        "category": np.array([o.category for o in scene.objects], np.int32),
        "asset": np.array([o.asset for o in scene.objects], np.int32),
    }
    for key, table in lut.items():
        if key in want:
            table0 = np.concatenate([table, np.zeros(1, np.int32)])  # index -1 -> 0
            out[key] = torch.from_numpy(table0[idx][:, None])  # a fresh array: indexing copies
    return out


def _rgb_right(scene: Scene, right, gb: GBuffer, plan: Plan, device: str) -> torch.Tensor:
    """The right view (``flowsynth.truth.stereo.right_view``) shaded with exactly the left view's lights (the defaults
    are placed from the left view's G-buffer ``gb``)."""
    from flowsynth.appearance import resolve_lights
    from flowsynth.renderer.shading import median_hit_distance, render_rgb

    view = copy.copy(scene)
    view.lights = resolve_lights(scene.lights, scene.world_T_cam[0], median_hit_distance(gb))
    view.world_T_cam = right.world_T_cam
    return to_torch(render_rgb([view], right.accel, right.gb, plan, device=device))
