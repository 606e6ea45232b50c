"""Optical flow, validity, occlusion, motion masks and scene flow by exact reprojection of ray-cast hit points.

For a pixel (u, v) of source frame s that sees instance n at object-frame point p (kept by the
primary cast), with target frame r (r = s + k forward, r = s - k backward, k a frame gap of
``flow_gaps``; keys of gap k >= 2 are named KEY_kK):

    X_r   = cam_T_world[r] @ world_T_obj[r, n] @ p           (float64)
    valid = hit and X_r.z > 0
    (u', v') = project(K, X_r)                     (full K, float64; kornia's dehomogenisation)
    flow  = (u' - u, v' - v)         where valid, else 0
    oof   = hit and (X_r.z <= 0 or (u', v') outside [-0.5, W - 0.5) x [-0.5, H - 0.5))
    occ   = oof or (hit and the ray from camera r towards X_r hits a surface closer than
                    (1 - VISIBILITY_REL_TOL) |X_r|)                         (occlusion="exact")
    motion = hit and |world_T_obj[s+1, n] p - world_T_obj[s, n] p| > MOTION_TOL
    scene_flow = cam_T_world[s] (world_T_obj[r, n] - world_T_obj[s, n]) p   [m], where hit, else 0

flow, valid, oof, occ and scene flow (and stereo's disparity change and view occlusion) come from one Warp kernel
launch (``pair_arrays``, flowsynth/kernels/reproject.py; a thread per (pair, row) on the CPU, per pixel on a GPU; one
clip, or a batch of clips for ``fs.render_batch``), visibility ray included (with
exact culls, ``SceneAccel.culling``): no per-point gather of matrices, no compaction. ``motion`` (and
``fs.render``'s ``position``) come from ``world_points_kernel`` the same way. ``reproject`` (numpy + kornia) serves
the sparse track points.
"""

from __future__ import annotations

import numpy as np
import torch
from kornia.geometry.conversions import convert_points_from_homogeneous

from flowsynth.kernels import wp_runtime
from flowsynth.parallel import BAND0, launch_bands, launch_image
from flowsynth.plan import gap_key

__all__ = ["DEPTH_TEST_REL_TOL", "MOTION_TOL", "VISIBILITY_REL_TOL", "flow_outputs", "reproject", "reproject_pixels",
           "visibility"]

# A visibility ray is blocked only by a hit closer than (1 - tol) * distance to the point: this absorbs
# float32 error of the hit point (~1e-7 relative) and grazing self-intersections, while an occluder
# must lie at least tol * distance (1 mm at 10 m) in front of the point to count.
VISIBILITY_REL_TOL = 1e-4
# occlusion="depth": occluded when the point's depth exceeds the target depth map at the nearest pixel
# by more than this fraction.
DEPTH_TEST_REL_TOL = 1e-2
# A surface point "moves" when its world displacement between frames exceeds this [m] (+1e-12 relative).
MOTION_TOL = 1e-7


def reproject(points: np.ndarray, M: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map object-frame points by per-point (4,4) transforms into a camera and project them.

    Args:
        points: (P, 3) float64 object-frame points.
        M: (P, 4, 4) float64 cam_T_obj per point.
        K: (3, 3) intrinsics.
    Returns:
        X (P, 3) camera-frame points [m] and uv (P, 2) image coordinates [px] (0 where X.z <= 0).
    """
    X = (M[:, :3, :3] @ points[:, :, None])[:, :, 0] + M[:, :3, 3]
    front = X[:, 2] > 0
    Xs = np.where(front[:, None], X, np.array([0.0, 0.0, 1.0]))
    # full K (skew included; kornia's project_points drops K[0, 1]), dehomogenised by kornia in float64
    uv = convert_points_from_homogeneous(torch.from_numpy(Xs @ K.T)).numpy()
    uv = np.where(front[:, None], uv, 0.0)
    return X, uv


def reproject_pixels(gb, cam_T_obj: np.ndarray, K: np.ndarray, src0: int, step: int, P: int, *, accel=None,
                     camera=None, flow: bool = False, occlusion: str | None = None, fB: float | None = None,
                     scene_flow_T: np.ndarray | None = None, lens=None,
                     threads: int | None = None) -> dict[str, np.ndarray]:
    """Every hit pixel of one clip's G-buffer ``gb`` reprojected into a target frame, per pair (``pair_arrays``
    handed to the host as numpy).

    Pair t maps frame s = src0 + t into frame s + step of the target view, whose (T, N, 4, 4) float64
    ``cam_T_obj`` is given (the same view for flow, the other view for stereo). Definitions: module docstring.

    Args:
        gb: G-buffer with ``point``.
        K: (3, 3) intrinsics of the target view (skew included).
        accel, camera: the target view's ``SceneAccel`` and camera (visibility rays, occlusion="exact").
        flow: also return ``flow``; occlusion: None, "exact" or "depth" (``occ``); fB: also return the
            disparity change ``dc`` = fB / z_target - fB / z_source; scene_flow_T: (P, N, 4, 4) float64, also
            return ``scene_flow`` = scene_flow_T[t, n] @ p (where hit, valid or not).
        lens: the target view's ``fs.Camera`` when it has a lens model (flowsynth/scene/camera.py): projection through
            the model, valid only in its domain; None or a pinhole camera: K alone.
    Returns:
        ``valid``, ``oof`` (P, 1, H, W) bool; ``flow`` (P, 2, H, W) float32, ``occ`` (P, 1, H, W) bool,
        ``dc`` (P, 1, H, W) float64, ``scene_flow`` (P, 3, H, W) float32 when asked; 0 where not hit (flow and dc
        also where not valid).
    """
    F = gb.shape[0]
    P = max(P, 0)
    want_dc = fB is not None
    want_sf = scene_flow_T is not None
    N = cam_T_obj.shape[1]
    sfM = None
    if want_sf:  # per source item: frame src0 + t's rows hold pair t's transforms
        sfM = np.zeros((F * N, 4, 4))
        sfM[src0 * N:(src0 + P) * N] = np.asarray(scene_flow_T, np.float64).reshape(-1, 4, 4)
    got = pair_arrays(gb, cam_T_obj.reshape(-1, 4, 4), K, np.arange(P) + src0, step, accel=accel, camera=camera,
                      flow=flow, occlusion=occlusion, fB=fB, scene_flow_items=sfM, lens=lens, threads=threads)
    res = {"valid": got["valid"].numpy().view(bool)[:, None], "oof": got["oof"].numpy().view(bool)[:, None]}
    if flow:
        res["flow"] = got["flow"].numpy()
    if occlusion is not None:
        res["occ"] = got["occ"].numpy().view(bool)[:, None]
    if want_dc:
        res["dc"] = got["dc"].numpy()[:, None]
    if want_sf:
        res["scene_flow"] = got["scene_flow"].numpy()
    return res


def pair_arrays(gb, cam_T_obj_items: np.ndarray, K: np.ndarray, pair_src: np.ndarray, step: int, *, accel=None,
                camera=None, flow: bool = False, occlusion: str | None = None, fB: float | None = None,
                scene_flow_items: np.ndarray | None = None, lens=None, threads: int | None = None) -> dict:
    """The pair kernel (flowsynth/kernels/reproject.py) over G-buffer ``gb`` of one clip or a batch of clips: one
    launch, a thread per pixel on a GPU, row bands on the CPU; the results stay Warp arrays on the G-buffer's
    device.

    Pair t maps frame s = ``pair_src[t]`` (P,) into frame s + step of the target view. ``cam_T_obj_items``: (items,
    4, 4) float64 target view from each item's object in its frame (``SceneAccel``'s item order);
    ``scene_flow_items``: (items, 4, 4) float64 scene-flow transform of each source item, or None. Other arguments
    as ``reproject_pixels``'. Returns Warp arrays: ``valid``, ``oof`` (P, H, W) uint8, and as asked ``flow`` (P, 2,
    H, W) float32, ``occ`` (P, H, W) uint8, ``dc`` (P, H, W) float64, ``scene_flow`` (P, 3, H, W) float32; zeros
    (False) where there is no pair or nothing to hit (no launch then).
    """
    from flowsynth.kernels.raycast import Culling, Instances, TileLists
    from flowsynth.kernels.reproject import (LENS_CODES, OCC_DEPTH, OCC_EXACT, OCC_NONE, PairOcclusion, PairSource,
                                             PairTarget, pair_kernel)

    F, H, W = gb.shape
    P = len(pair_src)
    want_dc = fB is not None
    want_sf = scene_flow_items is not None
    occ_mode = {None: OCC_NONE, "exact": OCC_EXACT, "depth": OCC_DEPTH}[occlusion]
    wp = wp_runtime()
    dev = gb.device
    shape = (P, H, W)
    kinds = {"valid": (shape, wp.uint8), "oof": (shape, wp.uint8), "occ": (shape, wp.uint8),
             "flow": ((P, 2, H, W), wp.float32), "dc": (shape, wp.float64), "scene_flow": ((P, 3, H, W), wp.float32)}
    asked = [k for k, on in (("valid", True), ("oof", True), ("flow", flow), ("occ", occ_mode != OCC_NONE),
                             ("dc", want_dc), ("scene_flow", want_sf)) if on]
    if P == 0 or gb.num_instances == 0:  # nothing to reproject (a clip without objects has no culling tables)
        return {k: wp.zeros(*kinds[k], device=dev) for k in asked}
    item, point, face = gb.item, gb.point, gb.face  # the G-buffer's own arrays, on its device
    M = wp.array(np.ascontiguousarray(cam_T_obj_items, np.float64), dtype=wp.mat44d, device=dev)
    inst, tiles, cull = Instances(), TileLists(), Culling()
    if occ_mode == OCC_EXACT:
        cull = accel.culling(threads)
        inst, tiles = accel.instances(), accel.tile_lists(camera, flat=False, threads=threads)
    one = (1, 1, 1)
    dist = gb.dist if occ_mode == OCC_DEPTH else wp.empty(one, wp.float32, dev)
    dz = wp.array(np.ascontiguousarray(camera.pixel_rays_numpy()[..., 2]) if occ_mode == OCC_DEPTH
                  else np.zeros((1, 1)), dtype=wp.float64, device=dev)
    out = {k: wp.empty(s if k in asked else (1,) * len(s), d, dev) for k, (s, d) in kinds.items()}  # else a dummy
    sfM = wp.array(np.ascontiguousarray(scene_flow_items, np.float64) if want_sf else np.zeros((1, 4, 4)),
                   dtype=wp.mat44d, device=dev)
    model = 0 if lens is None else LENS_CODES[lens.model]
    coef = np.zeros(8)
    if model:
        coef[:len(lens.dist)] = lens.dist
    lens_k = wp.array(coef, dtype=wp.float64, device=dev)
    lens_lim = min(float(lens.lens_limit), 1e300) if model else 0.0
    src = PairSource()
    src.item, src.point, src.face, src.dist = item, point, face, dist
    src.frame_start = wp.array(np.asarray(gb.frame_start, np.int32), dtype=wp.int32, device=dev)
    # each item's instance row: read by occlusion="exact" only (the own item's face planes), which has an accel
    src.item_inst = accel.item_inst if occ_mode == OCC_EXACT else wp.zeros(1, dtype=wp.int32, device=dev)
    src.pair_src = wp.array(np.asarray(pair_src, np.int32), dtype=wp.int32, device=dev)
    src.step = int(step)
    tgt = PairTarget()
    tgt.cam_T_obj, tgt.K = M, wp.mat33d(*np.asarray(K, np.float64).ravel())
    tgt.lens_k, tgt.lens_lim, tgt.fB, tgt.sfM = lens_k, lens_lim, float(fB or 0.0), sfM
    occl = PairOcclusion()
    occl.inst, occl.tiles, occl.cull, occl.rel_tol = inst, tiles, cull, VISIBILITY_REL_TOL
    occl.dz, occl.depth_tol = dz, DEPTH_TEST_REL_TOL
    launch_image(lambda per_pixel: pair_kernel(flow, occ_mode, want_dc, want_sf, model, per_pixel), shape,
                 [src, tgt, occl, BAND0], [out[k] for k in ("valid", "oof", "occ", "flow", "dc", "scene_flow")],
                 dev, threads)
    return {k: out[k] for k in asked}


def flow_outputs(camera, clips, accel, gb, plan) -> dict[str, torch.Tensor]:
    """Every flow-family key ``plan`` asks for, of B clips cast together (one scene, or a batch:
    ``flowsynth.renderer.batch``), as tensors on the G-buffer's device: one pair-kernel launch per (direction, gap k)
    of ``plan.pair_jobs`` over the B (T - k) pairs.

    Args:
        camera: the clips' camera (``fs.Camera``: K, size, lens model).
        clips: B ``flowsynth.raycast.scene_arrays`` (meshes, cam_T_world (T, 4, 4), world_T_obj (T, N_b, 4, 4)
            float64), in the order of ``accel``.
        accel, gb: their ``SceneAccel`` (``SceneAccel.batch`` of the clips) and G-buffer (with ``point``).
        plan: the plan (``pair_jobs``, ``occlusion``, ``threads``, ``stereo_baseline``).

    Returns:
        Per (direction, gap k), each requested key of ``flow``, ``valid``, ``occ``, ``oof``, ``scene_flow`` (named by
        ``gap_key``): (B, P, C, H, W), P = max(T - k, 0), index t the pair (t, t + k); flow float32 [px] (C = 2),
        scene flow float32 [m] (C = 3), masks bool (C = 1). With ``disparity_change`` asked beside a key of the fw
        gap-1 pass, also that (B, T - 1, 1, H, W) float32 [px] from the same launch (flowsynth/truth/stereo.py
        computes it otherwise).
    """
    wp = wp_runtime()
    B = len(clips)
    T, H, W = gb.shape[0] // B, camera.height, camera.width
    want = set(plan.outputs)
    cam_T_obj = [np.matmul(c[:, None], w) for _, c, w in clips]  # (T, N_b, 4, 4) per clip, once per frame and object
    items = np.concatenate([m.reshape(-1, 4, 4) for m in cam_T_obj])
    out: dict[str, torch.Tensor] = {}
    for name, k in plan.pair_jobs:
        P = max(T - k, 0)  # pairs (t, t+k); none when the clip is not longer than the gap
        key = {kind: gap_key(f"{kind}_{name}", k) for kind in ("flow", "valid", "occ", "oof", "scene_flow")}
        if not want & set(key.values()):
            continue
        src0, step = (0, k) if name == "fw" else (k, -k)
        pair_src = (np.arange(B)[:, None] * T + src0 + np.arange(P)[None, :]).reshape(-1)
        sf = None
        if key["scene_flow"] in want:  # per source item: cam_T_world[s] (world_T_obj[s + step] - world_T_obj[s])
            sf = []
            for _, c, w in clips:
                rows = np.zeros((T,) + w.shape[1:])
                src = np.arange(P) + src0
                rows[src] = np.matmul(c[src][:, None], w[src + step] - w[src])
                sf.append(rows.reshape(-1, 4, 4))
            sf = np.concatenate(sf)
        # stereo's disparity change maps the pairs (t, t + 1) of the left view too: it rides on the fw gap-1 pass
        # when that pass runs anyway
        fB = camera.fx * plan.stereo_baseline if (name, k) == ("fw", 1) and "disparity_change" in want else None
        got = pair_arrays(gb, items, camera.K, pair_src, step, accel=accel, camera=camera, flow=key["flow"] in want,
                          occlusion=plan.occlusion if key["occ"] in want else None, fB=fB, scene_flow_items=sf,
                          lens=camera, threads=plan.threads)
        for kind, arr in got.items():
            x = wp.to_torch(arr)
            if kind in ("valid", "oof", "occ"):
                x = x.view(torch.bool)[:, None]
            if kind == "dc":
                out["disparity_change"] = x.to(torch.float32)[:, None].reshape(B, P, 1, H, W)
            else:
                out[key[kind]] = x.reshape(B, P, *x.shape[1:])
    return {k: v for k, v in out.items() if k in want}


def visibility(accel, rays: list[tuple[np.ndarray, np.ndarray]], threads: int | None) -> np.ndarray:
    """Blocked flag per point: (X in camera frame r, r) lists -> one visibility-kernel launch (in bands)."""
    X = np.concatenate([x for x, _ in rays]).astype(np.float32)
    r = np.concatenate([f for _, f in rays]).astype(np.int32)
    if len(X) == 0 or accel.empty:
        return np.zeros(len(X), bool)
    wp = wp_runtime()
    from flowsynth.kernels.raycast import visibility_kernel

    dev = accel.device
    blocked = wp.zeros(len(X), dtype=wp.int8, device=dev)
    launch_bands(visibility_kernel, (len(X),), 0,
                 [accel.instances(), wp.array(X, dtype=wp.vec3, device=dev),
                  wp.array(r, dtype=wp.int32, device=dev), VISIBILITY_REL_TOL, BAND0],
                 [blocked], dev, threads)
    return blocked.numpy().astype(bool)


def world_points(gb, world_T_obj: np.ndarray, *, moved: bool, threads: int | None = None):
    """The G-buffer's hit points in the world frame, (T, H, W, 3) float64 (0 where not hit), and with ``moved``
    the ``motion`` flags (T-1, H, W) bool of frames 0 .. T-2 (else None): ``world_point_arrays`` of one clip
    (``world_T_obj`` (T, N, 4, 4)) handed to the host."""
    T, H, W = gb.shape
    world, flags = world_point_arrays(gb, np.asarray(world_T_obj).reshape(-1, 4, 4), T, moved=moved, threads=threads)
    if not moved:
        return world.numpy(), None
    return world.numpy(), (flags.numpy().astype(bool) if T > 1 else np.zeros((0, H, W), bool))


def world_point_arrays(gb, world_T_obj_items: np.ndarray, frames: int, *, moved: bool, threads: int | None = None):
    """``world_points_kernel`` (flowsynth/kernels/reproject.py) over G-buffer ``gb`` of B clips of ``frames`` T
    frames each, one launch (a thread per pixel on a GPU, row bands on the CPU): Warp arrays on its device, the
    world points (B T, H, W) vec3d and with ``moved`` the flags (B (T-1), H, W) uint8 (else a dummy).
    ``world_T_obj_items``: (items, 4, 4) float64, each item's object pose in its frame (``SceneAccel``'s order)."""
    from flowsynth.kernels.reproject import world_points_kernel

    wp = wp_runtime()
    F, H, W = gb.shape
    dev = gb.device
    world = wp.empty((F, H, W), dtype=wp.vec3d, device=dev)  # the kernel writes every pixel
    flags = wp.empty((F - F // frames, H, W) if moved and frames > 1 else (1, 1, 1), dtype=wp.uint8, device=dev)
    M = np.ascontiguousarray(world_T_obj_items, np.float64) if len(world_T_obj_items) else np.zeros((1, 4, 4))
    launch_image(lambda per_pixel: world_points_kernel(per_pixel), (F, H, W),
                 [gb.item, gb.point, wp.array(M, dtype=wp.mat44d, device=dev),
                  wp.array(np.asarray(gb.frame_start, np.int32), dtype=wp.int32, device=dev), int(frames), int(moved),
                  MOTION_TOL, BAND0], [world, flags], dev, threads)
    return world, flags
