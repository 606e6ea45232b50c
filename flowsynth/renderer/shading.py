"""RGB rendering: materials and lights packed for the shading kernel, motion-blur time slices, tone mapping.

``render_rgb`` shades and tone-maps B scenes in one launch each (``flowsynth.renderer.batch``; ``fs.render`` is its
batch of one). The model (render modes, material schema, lights, time model, tone mapping, RNG) is documented in
docs/rendering.md.

Motion-blur time model: the shutter opens at the frame instant. Frame t integrates times
t + shutter * (s + 1/2) / S [frame units], s = 0 .. S-1, with S = min(spp, MAX_TIME_SLICES) time slices
(sample k of a pixel uses slice (k + o) mod S, o random per pixel); the scene at those times
is a second ``SceneAccel`` over T * S pose sets. Poses between frames k and k+1 (fraction a): translation
linear, rotation R(a) = exp(a log(R_{k+1} R_k^T)) R_k (slerp); after the last frame the last interval's
motion continues (a > 1); a one-frame clip does not move.

A lens camera (flowsynth/scene/camera.py) shades through its model: the pixel-centre sample on the G-buffer's ray,
sub-pixel samples (anti-aliasing, spp > 1, motion blur) on blended rays of the surrounding centres, uncovered
pixels black (``flowsynth.kernels.shade.shade_kernel``).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from flowsynth.appearance import mip_pyramid, resolve_lights, resolve_material, srgb_to_linear
from flowsynth.caches import register
from flowsynth.errors import ConfigError
from flowsynth.kernels import wp_runtime
from flowsynth.parallel import BAND0, launch_image
from flowsynth.plan import TONEMAPS
from flowsynth.raycast import SceneAccel, pinhole

__all__ = ["MAX_TIME_SLICES", "median_hit_distance", "pack_material_batch", "pack_materials", "poses_at", "render_rgb",
           "shade_radiance", "shade_scenes", "shutter_times", "srgb_tables", "tonemap_array", "tonemap_frames",
           "tonemap_srgb"]

# White point of the extended Reinhard operator: linear radiance that maps to 1.
REINHARD_WHITE = 4.0
# Motion blur uses min(spp, MAX_TIME_SLICES) time slices per frame (samples share slices beyond that).
MAX_TIME_SLICES = 64
# Rays end at this distance [m] (beyond any scene).
MAX_RAY_DIST = 1.0e9
# Camera rays of the shading kernel walk the G-buffer cast's tile lists when there is no motion blur (False: the
# top-level BVH, as with motion blur; the same hits, tests/test_rgb.py):
# docs/decisions/0015-shading-camera-rays-tiles.md.
CAMERA_RAY_TILES = True
# A lens camera's shading kernel reads the rays of the pixel centres and of this many rings around the image
# (``Camera.ray_grid``): a sub-pixel sample blends its four surrounding centres' rays.
LENS_RAY_PAD = 2

# The sRGB tables of the tone-mapping kernel per Warp device (``srgb_tables``).
_SRGB_TABLES: dict = register("shading.srgb_pow_tables", {})


def render_rgb(scenes, accel: SceneAccel, gb, plan, device: str = "cpu"):
    """Render ``rgb`` of B scenes together (one scene, or a batch: ``flowsynth.renderer.batch``): one shading launch
    and one tone-mapping launch.

    Args:
        scenes: B scenes of one camera and frame count T (objects' ``material`` dicts, ``lights``; empty lights: the
            defaults, placed from the median hit distance of the scene's frame 0, ``median_hit_distance``).
        accel: the G-buffer's acceleration structure (one group per frame of the B T).
        gb: the G-buffer of the pixel-centre rays (``flowsynth.raycast.gbuffer.GBuffer``, on ``device``); reused as
            the primary hit when spp == 1 and shutter == 0.
        plan: a validated ``flowsynth.plan.Plan``: ``render_mode``, ``spp``, ``shutter``, ``seed`` (None: each
            scene's render seed), ``bounces``, ``tonemap``, ``exposure``.
        device: Warp device of the shading and the tone mapping (the G-buffer's).

    Returns:
        (B T, 3, H, W) float32 Warp array on ``device``, sRGB-encoded colour in [0, 1]; frame b T + t is frame t of
        scene b.

    Raises:
        ConfigError: a bad ``tonemap`` or ``exposure``; motion blur (shutter > 0) asked of more than one scene.
    """
    _check_tonemap(plan.tonemap, plan.exposure)
    radiance = shade_radiance(scenes, accel, gb, plan, device=device)
    return tonemap_array(radiance, plan.tonemap, plan.exposure, plan.threads)


def tonemap_frames(radiance: np.ndarray, method: str = "clamp", exposure: float = 1.0,
                   threads: int | None = None, device: str = "cpu") -> np.ndarray:
    """``tonemap_array`` of host (T, H, W, 3) float32 radiance: (T, 3, H, W) float32 in numpy."""
    wp = wp_runtime()
    src = wp.array(np.ascontiguousarray(radiance, np.float32), dtype=wp.vec3, device=device,
                   copy=not wp.get_device(device).is_cpu)  # a view on the CPU
    return tonemap_array(src, method, exposure, threads).numpy()


def tonemap_array(radiance, method: str = "clamp", exposure: float = 1.0, threads: int | None = None):
    """``tonemap_srgb`` of a (T, H, W) vec3 Warp array of linear radiance into a (T, 3, H, W) float32 Warp array on
    the same device, the same float64 steps in one Warp kernel pass (a thread per row on the CPU, per pixel on a GPU)
    (``flowsynth.kernels.tonemap.tonemap_kernel``); the numpy form took 0.81 s of CPU per T=24 view at 512x384
    (docs/decisions/0013-tonemap-kernel.md)."""
    from flowsynth.kernels.tonemap import tonemap_kernel

    _check_tonemap(method, exposure)
    wp = wp_runtime()
    dev = str(radiance.device)
    T, H, W = radiance.shape
    rgb = wp.empty((T, 3, H, W), dtype=wp.float32, device=dev)
    launch_image(tonemap_kernel, (T, H, W), [radiance, float(exposure), int(method == "reinhard"), REINHARD_WHITE**2,
                                             srgb_tables(dev), BAND0], [rgb], dev, threads)
    return rgb


def srgb_tables(device: str = "cpu"):
    """``flowsynth.kernels.tonemap.srgb_pow_tables`` on ``device``, built once per process and device (the
    registered cache ``shading.srgb_pow_tables``)."""
    from flowsynth.kernels.tonemap import srgb_pow_tables

    tab = _SRGB_TABLES.get(device)
    if tab is None:
        tab = _SRGB_TABLES[device] = srgb_pow_tables(device)
    return tab


def median_hit_distance(gb, frame: int = 0) -> float:
    """Median ray length [m] of the hit pixels of frame ``frame`` of G-buffer ``gb`` (1 when none): the default lights'
    scale (``flowsynth.appearance.lights.resolve_lights``). Computed on the G-buffer's device as numpy's median
    computes it (the mean of the two middle values in float32 for an even count); one number comes to the host."""
    wp = wp_runtime()
    dist = wp.to_torch(gb.dist)[frame]
    hits = torch.sort(dist[wp.to_torch(gb.item)[frame] >= 0]).values
    n = hits.numel()
    if n == 0:
        return 1.0
    mid = hits[n // 2] if n % 2 else (hits[n // 2 - 1] + hits[n // 2]) / 2
    return float(mid)


def shade_radiance(scenes, accel: SceneAccel, gb, plan, device: str = "cpu"):
    """Linear radiance of every pixel of B scenes (``render_rgb``'s arguments), before tone mapping: a (B T, H, W)
    vec3 Warp array on ``device``, finite and >= 0. With motion blur (``plan.shutter`` > 0; one scene only) the scene
    is cast again at ``min(spp, MAX_TIME_SLICES)`` times per frame (module docstring)."""
    wp = wp_runtime()
    B, T = len(scenes), scenes[0].num_frames
    H, W = scenes[0].camera.height, scenes[0].camera.width
    spp, shutter = int(plan.spp), float(plan.shutter)
    if shutter > 0 and B != 1:
        raise ConfigError(f"motion blur (shutter {shutter}) renders one scene at a time, got {B}; render "
                          "motion-blurred rgb per scene with fs.render")
    lights = [resolve_lights(s.lights, s.world_T_cam[0], median_hit_distance(gb, b * T) if not s.lights else 1.0)
              for b, s in enumerate(scenes)]
    if accel.empty:
        sky = np.stack([np.broadcast_to(_sky(x).astype(np.float32), (T, H, W, 3)) for x in lights])
        return wp.array(sky.reshape(-1, H, W, 3), dtype=wp.vec3, device=device)
    seeds = [int(s.render_seed) if plan.seed is None else plan.seed for s in scenes]
    slices = min(spp, MAX_TIME_SLICES) if shutter > 0 else 1
    cam_T_worlds = [s.cam_T_world for s in scenes]
    if shutter > 0:
        scene = scenes[0]
        times = shutter_times(T, shutter, slices).reshape(-1) + plan.shutter_offset  # offset: the final pass
        cam_T_worlds = [np.linalg.inv(poses_at(scene.world_T_cam, times))]
        world_T_obj = np.stack([poses_at(o.poses, times) for o in scene.objects], 1)
        accel = SceneAccel([o.mesh for o in scene.objects], cam_T_worlds[0], world_T_obj, device=device)
    return shade_scenes(scenes, lights, cam_T_worlds, seeds, accel, gb, plan, slices, device)


def _sky(lights) -> np.ndarray:
    """The ambient lights' radiance, (3,) float64."""
    return sum((np.asarray(x.color) * x.intensity for x in lights if x.kind == "ambient"), np.zeros(3))


def shade_scenes(scenes, lights: list, cam_T_worlds: list, seeds: list, accel: SceneAccel, gb, plan, slices: int,
                 device: str):
    """The shading kernel over B scenes of T frames each (one, or a batch: ``accel`` and ``gb`` hold their B T frames,
    or, with motion blur, one scene's T ``slices`` time groups), one launch: (B T, H, W) vec3 radiance on ``device``.
    ``lights``: each scene's resolved lights; ``cam_T_worlds``: each scene's (groups, 4, 4) camera poses of the
    light vectors; ``seeds``: each scene's render seed."""
    wp = wp_runtime()
    from flowsynth.kernels.raycast import TileLists
    from flowsynth.kernels.shade import ShadeGBuffer, ShadeSampling, ShadeScene, shade_kernel
    from flowsynth.kernels.texture import Material, layer_trig_kernel

    camera = scenes[0].camera
    T, H, W = scenes[0].num_frames, camera.height, camera.width
    B = len(scenes)
    spp, shutter = int(plan.spp), float(plan.shutter)
    reuse = spp == 1 and shutter == 0 and gb.point is not None
    sc = ShadeScene()
    sc.inst, sc.max_t = accel.instances(), MAX_RAY_DIST
    # Without motion blur, camera rays (extra samples of edge pixels, spp > 1) walk the G-buffer cast's tile lists
    # (sample offsets stay within a pixel of the tile, as the lists allow) instead of the top-level BVH.
    sc.use_tiles = int(shutter == 0 and CAMERA_RAY_TILES)
    sc.tiles = accel.tile_lists(camera) if sc.use_tiles else TileLists()
    sc.smooth = int(bool(plan.smooth_shading))
    sc.corner_n = accel.corner_normals() if sc.smooth else wp.zeros(1, dtype=wp.vec3, device=device)
    mats, img_data, img_info = pack_material_batch(scenes)
    sc.mats = wp.array(mats, dtype=Material, device=device)
    wp.launch(layer_trig_kernel, len(mats), [sc.mats], device=device)
    sc.img_data = wp.array(img_data, dtype=wp.vec3, device=device)
    sc.img_info = wp.array(img_info, dtype=wp.int32, device=device)
    delta = [[light for light in x if light.kind != "ambient"] for x in lights]
    L = max(max(len(d) for d in delta), 1)
    kind, vec, irr = np.zeros((B, L), np.int32), [], np.zeros((B, L, 3), np.float32)
    for b, (d, cam_T_world) in enumerate(zip(delta, cam_T_worlds)):
        k, v, e = _light_tables(d, cam_T_world)
        kind[b, :len(k)], irr[b, :len(e)] = k, e
        vec.append(np.pad(v, ((0, 0), (0, L - v.shape[1]), (0, 0))))
    sc.n_lights = wp.array(np.array([len(d) for d in delta], np.int32), dtype=wp.int32, device=device)
    sc.light_kind = wp.array(kind, dtype=wp.int32, device=device)
    sc.light_vec = wp.array(np.concatenate(vec), dtype=wp.vec3, device=device)
    sc.light_irr = wp.array(irr, dtype=wp.vec3, device=device)
    sc.sky = wp.array(np.stack([_sky(x) for x in lights]).astype(np.float32), dtype=wp.vec3, device=device)
    # Ray-cone spread per metre of one sample: a pixel's angle shared by spp samples (texture filtering).
    sc.pix_angle = float(1.0 / np.sqrt(camera.K[0, 0] * camera.K[1, 1] * spp))

    edge_spp = int(plan.edge_spp) if plan.edge_spp > spp else 0  # 0: no pixel gets extra samples

    def gbuf(a, dtype, fill, needed=False):  # the G-buffer's own array where the kernel reads it, else a dummy
        return a if reuse or needed else wp.full((1, 1, 1), fill, dtype=dtype, device=device)

    radiance = wp.empty((B * T, H, W), dtype=wp.vec3, device=device)  # the kernel writes every pixel
    lens = not camera.is_pinhole  # sub-pixel rays blend the ray grid's centres (kernels/shade.lens_ray)
    cam = pinhole(camera, device, pad=LENS_RAY_PAD if lens else 0)
    g = ShadeGBuffer()
    g.item, g.face = gbuf(gb.item, wp.int32, -1, edge_spp > 0), gbuf(gb.face, wp.int32, -1)
    g.dist, g.point = gbuf(gb.dist, wp.float32, 0.0), gbuf(gb.point, wp.vec3, wp.vec3(0.0))
    g.reuse = int(reuse)
    smp = ShadeSampling()
    smp.spp, smp.edge_spp, smp.slices = spp, edge_spp, slices
    smp.seeds = wp.array(np.array([_seed32(x) for x in seeds], np.int32), dtype=wp.int32, device=device)
    smp.frames, smp.bounces = T, int(plan.bounces)
    launch_image(lambda per_pixel: shade_kernel(plan.render_mode, lens, per_pixel), (B * T, H, W),
                 [sc, g, cam, smp, BAND0], [radiance], device, plan.threads)
    return radiance  # finite and >= 0: the kernel clamps each value (kernels/shade.finite_nonneg)


def _light_tables(delta: list, cam_T_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kernel tables of the directional and point lights: kind (L,), per-group camera-frame vector (G, L, 3)
    (unit vector towards a directional light, position of a point light) and irradiance scale pi I c (L, 3).
    One dummy entry when there are none."""
    from flowsynth.kernels.shade import LIGHT_DIRECTIONAL, LIGHT_POINT

    L = max(len(delta), 1)
    kind = np.zeros(L, np.int32)
    vec = np.zeros((len(cam_T_world), L, 3))
    irr = np.zeros((L, 3), np.float32)
    R, t = cam_T_world[:, :3, :3], cam_T_world[:, :3, 3]
    for n, light in enumerate(delta):
        if light.kind == "directional":
            kind[n] = LIGHT_DIRECTIONAL
            vec[:, n] = R @ -np.asarray(light.direction)
        else:
            kind[n] = LIGHT_POINT
            vec[:, n] = R @ np.asarray(light.position) + t
        irr[n] = np.pi * light.intensity * np.asarray(light.color)
    return kind, vec.astype(np.float32), irr


def shutter_times(num_frames: int, shutter: float, slices: int) -> np.ndarray:
    """(T, S) sample times [frame units]: t + shutter * (s + 1/2) / S (the shutter opens at the frame instant)."""
    s = (np.arange(slices) + 0.5) / slices
    return np.arange(num_frames)[:, None] + shutter * s[None, :]


def poses_at(poses: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Rigid poses (T, 4, 4) at fractional frame times (K,): slerp + linear translation, extrapolated past
    the last frame with the last interval's motion, and before frame 0 with the first's. Returns (K, 4, 4) float64."""
    poses = np.asarray(poses, np.float64)
    times = np.asarray(times, np.float64)
    if len(poses) == 1:
        return np.repeat(poses, len(times), 0)
    k = np.clip(np.floor(times).astype(np.int64), 0, len(poses) - 2)
    a = (times - k)[:, None]
    A, B = poses[k], poses[k + 1]
    rel = Rotation.from_matrix(B[:, :3, :3] @ np.swapaxes(A[:, :3, :3], 1, 2)).as_rotvec()
    out = np.zeros((len(times), 4, 4))
    out[:, :3, :3] = Rotation.from_rotvec(a * rel).as_matrix() @ A[:, :3, :3]
    out[:, :3, 3] = (1.0 - a) * A[:, :3, 3] + a * B[:, :3, 3]
    out[:, 3, 3] = 1.0
    return out


def _check_tonemap(method: str, exposure: float) -> None:
    if method not in TONEMAPS:
        raise ConfigError(f"tonemap must be one of {TONEMAPS}, got {method!r}")
    if not (np.isfinite(exposure) and exposure >= 0):
        raise ConfigError(f"exposure must be finite and >= 0, got {exposure!r}")


def tonemap_srgb(radiance: np.ndarray, method: str = "clamp", exposure: float = 1.0) -> np.ndarray:
    """Linear radiance (..., 3) -> sRGB-encoded float32 in [0, 1].

    "clamp": c = min(exposure * L, 1). "reinhard" (extended, per channel): c = x (1 + x / w^2) / (1 + x),
    x = exposure * L, w = REINHARD_WHITE, then clamped. Then the sRGB transfer function (IEC 61966-2-1).
    """
    _check_tonemap(method, exposure)
    x = np.nan_to_num(np.asarray(radiance, np.float64) * exposure, nan=0.0, posinf=1e30, neginf=0.0)
    x = np.maximum(x, 0.0)
    if method == "reinhard":
        x = x * (1.0 + x / REINHARD_WHITE**2) / (1.0 + x)
    x = np.minimum(x, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.clip(srgb, 0.0, 1.0).astype(np.float32)


def pack_materials(scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kernel tables of the objects' materials, packed by field name.

    Returns mats (N,) numpy structured array of ``flowsynth.kernels.texture.Material.numpy_dtype()`` (one per
    object; ``wp.array(mats, dtype=Material)`` on the device), img_data (P, 3) float32 linear RGB atlas of mip
    pyramids, img_info (rows, 4) int32 (offset, width, height, levels), one row per level; a dummy one-entry
    atlas when no object uses an image. Each layer's ``cos_angle`` and ``sin_angle`` are 0 here:
    ``layer_trig_kernel`` fills them on the device from ``angle`` (numpy's cos would not give Warp's bits).
    """
    from flowsynth.kernels.texture import FAMILIES, FAMILY_NONE, Material

    N = len(scene.objects)
    mats = np.zeros(max(N, 1), Material.numpy_dtype())
    images: dict[str, int] = {}
    pyramids: list[list[np.ndarray]] = []
    for n, obj in enumerate(scene.objects):
        V = np.asarray(obj.mesh.vertices)
        size = float(np.ptp(V, axis=0).max()) or 1.0
        mat = resolve_material(obj.material, instance=obj.instance, size=size)
        layers = mat["layers"] if mat["texture"] == "blend" else [mat]
        mats["b"]["family"][n] = FAMILY_NONE
        for name, layer in zip(("a", "b"), layers):
            lay = mats[name]  # a view: writes land in mats
            colors = srgb_to_linear(np.asarray(layer["colors"]))
            lay["color_a"][n], lay["color_b"][n] = colors[0], colors[1]
            for field in ("scale", "angle", "gain", "grain", "grain_scale", "octaves"):
                lay[field][n] = layer[field]
            lay["family"][n], lay["seed"][n] = FAMILIES[layer["texture"]], _seed32(layer["seed"])
            if layer["image"] is not None:
                if layer["image"] not in images:
                    images[layer["image"]] = sum(len(p) for p in pyramids)
                    pyramids.append(mip_pyramid(layer["image"]))
                lay["image"][n] = images[layer["image"]]
        mats["mask_scale"][n] = mat.get("mask_scale", 0.0)
        mats["roughness"][n], mats["specular"][n] = mat["roughness"], mat["specular"]
        mats["mask_seed"][n] = _seed32(mat["seed"])
    levels = [lv for p in pyramids for lv in p]
    if not levels:
        return mats, np.zeros((1, 3), np.float32), np.array([[0, 1, 1, 1]], np.int32)
    sizes = np.array([lv.shape[0] * lv.shape[1] for lv in levels])
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    counts = [len(p) for p in pyramids for _ in p]
    info = np.array([[o, lv.shape[1], lv.shape[0], c] for o, lv, c in zip(offsets, levels, counts)], np.int32)
    return mats, np.concatenate([lv.reshape(-1, 3) for lv in levels]).astype(np.float32), info


def pack_material_batch(scenes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``pack_materials`` of B scenes as one set of tables: scene b's N_b materials from row ``inst_start[b]`` on
    (``SceneAccel``'s instance rows), their image atlases one after another (an image layer's row shifted). One
    scene's tables are ``pack_materials``' own."""
    from flowsynth.kernels.texture import FAMILIES

    packed = [pack_materials(s) for s in scenes]
    if len(packed) == 1:
        return packed[0]
    mats, data, info, rows, texels = [], [], [], 0, 0
    for s, (m, d, i) in zip(scenes, packed):
        m = m[:len(s.objects)].copy()
        for name in ("a", "b"):
            lay = m[name]
            lay["image"] = np.where(lay["family"] == FAMILIES["image"], lay["image"] + rows, lay["image"])
        i = i.copy()
        i[:, 0] += texels
        mats.append(m)
        data.append(d)
        info.append(i)
        rows, texels = rows + len(i), texels + len(d)
    m = np.concatenate(mats)
    if not len(m):
        m = packed[0][0][:1]
    return m, np.concatenate(data), np.concatenate(info)


def _seed32(seed: int) -> int:
    """Any integer seed folded into int32 range (deterministically)."""
    x = int(seed) % (1 << 32)
    return x - (1 << 32) if x >= (1 << 31) else x
