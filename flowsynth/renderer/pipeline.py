"""``fs.render`` and ``fs.render_plan``: one primary ray cast per frame -> G-buffer -> requested ground truth, as
torch tensors. The orchestrator: it runs the stages a plan asks for (``flowsynth.plan``), each in its own module.

``fs.render`` is the batch of one: every key a batch renders comes from ``flowsynth.renderer.batch.batch_outputs``
with B = 1, the code ``fs.render_batch`` runs. Here, per scene, only what a batch does not render:

- stereo (a second cast from the right camera; disparity and the right view's depth on the host),
- point tracks (sparse query points drawn and reprojected on the host, numpy and kornia),
- object tables and boxes (per object, on the host),
- motion-blurred rgb (a second acceleration structure over the T x time slices of one scene),
- the final pass (per-clip draws, fog, gains and sensor noise on the host, numpy's RNG).

Output keys, shapes and meaning are those of docs/conventions.md.
"""

from __future__ import annotations

import copy
from dataclasses import replace

import torch

from flowsynth.options import RenderOptions
from flowsynth.plan import Plan, make_plan
from flowsynth.raycast import SceneAccel, cast_gbuffer, resolve_device, scene_arrays, to_torch
from flowsynth.renderer.batch import batch_outputs
from flowsynth.scene import Scene, check_lens_outputs

__all__ = ["render", "render_plan"]


def render(scene: Scene, outputs: list[str] | tuple[str, ...] = ("depth",), *, options: RenderOptions | None = None,
           device: str = "cpu", occlusion: str = "exact", **kwargs) -> dict[str, torch.Tensor]:
    """Render the requested ground truth of every frame of ``scene``.

    Args:
        scene: camera path and objects.
        outputs: keys from ``flowsynth.plan.OUTPUTS`` (see docs/conventions.md for shapes and units).
        device: Warp device of every stage ("cpu", the default; "cuda", "cuda:1", ... where Warp finds one, else
            a ConfigError naming the device and what Warp found).
        occlusion: "exact" (visibility rays) or "depth" (cheaper depth-buffer comparison;
            benchmarks/accuracy/accuracy.py measures what each costs and how often each is wrong:
            docs/decisions/0003-exact-occlusion.md).
        options: the render options (``fs.RenderOptions``: spp, edge_spp, render_mode, ..., final_*; None = the
            defaults, docs/rendering.md, Options), e.g. a config's ``cfg.render_options``.
        kwargs: render options by name (``spp=4``), applied on top of ``options``; and ``seed`` (None = the scene's
            render seed) and ``threads`` (ray-launch threads; None = every core the process may use, 1 inside
            DataLoader and export workers; see flowsynth.parallel), as ``flowsynth.plan.make_plan`` takes them.

    Returns:
        dict mapping each requested key to a tensor on the CPU, whatever ``device`` rendered it (``fs.render_batch``
        leaves its tensors on the device).
    """
    plan = make_plan(outputs, options, occlusion=occlusion, **kwargs)
    return render_plan(scene, plan, device=device)


def render_plan(scene: Scene, plan: Plan, device: str = "cpu") -> dict[str, torch.Tensor]:
    """Run the stages of ``plan`` (``flowsynth.plan.make_plan``, or ``fs.make_plan``) on ``scene``: what
    ``fs.render`` does after making the plan, and what the datasets call with the plan they made once.

    ``device``: as ``render``'s. The G-buffer stays in Warp arrays on it between the stages; ``GBuffer.host()``
    hands it to the per-scene stages that compute on the host (docs/architecture.md, Devices).

    Returns:
        dict mapping each key of ``plan.outputs`` to a CPU tensor (docs/conventions.md), whatever the device.
    """
    device = resolve_device(device)  # one device for every stage (ConfigError where Warp has none such)
    if plan.seed is None:  # the renderer's noise seed: the scene's unless the plan sets one
        plan = replace(plan, seed=int(scene.render_seed))
    check_lens_outputs(scene.camera, plan.outputs)
    clip = scene_arrays(scene)
    _, cam_T_world, world_T_obj = clip
    accel = SceneAccel(*clip, device=device)
    gb = cast_gbuffer(accel, scene.camera, want_normals=plan.normals, want_points=plan.points, threads=plan.threads)
    # the batch of one (a view on the CPU, one copy from a GPU)
    out = {k: v[0].cpu() for k, v in batch_outputs([scene], [clip], accel, gb, plan).items()}
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
    if plan.rgb and "rgb" not in out:  # motion blur: one scene at a time
        from flowsynth.renderer.shading import render_rgb

        out["rgb"] = to_torch(render_rgb([scene], accel, gb, plan, device=device))
    if plan.final:  # the final pass (flowsynth/renderer/finalpass.py): camera effects, the ground truth untouched
        from flowsynth.renderer.finalpass import render_final

        out["rgb_final"] = render_final(scene, accel, gb, plan, device=device)
    return {k: out[k] for k in plan.outputs}


def _rgb_right(scene: Scene, right, gb, plan: Plan, device: str) -> torch.Tensor:
    """The right view (``flowsynth.truth.stereo.right_view``) shaded with exactly the left view's lights (the defaults
    are placed from the left view's G-buffer ``gb``)."""
    from flowsynth.appearance import resolve_lights
    from flowsynth.renderer.shading import median_hit_distance, render_rgb

    view = copy.copy(scene)
    view.lights = resolve_lights(scene.lights, scene.world_T_cam[0], median_hit_distance(gb))
    view.world_T_cam = right.world_T_cam
    return to_torch(render_rgb([view], right.accel, right.gb, plan, device=device))
