"""Host side of the two-level ray caster: per-clip instance BVH over the assets' own trees (``flowsynth.raycast.blas``).

``SceneAccel`` takes F "frames" (camera pose + one pose per instance); frames need not be the clip's
frames (motion blur passes sub-frame times). All poses are composed in float64 here and handed to the
kernels as float32 ``obj_T_ref`` matrices relative to the frame's camera, so the float32 kernels only
ever see camera-relative coordinates: precision does not depend on the distance from the world origin.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
import trimesh

from flowsynth.caches import register
from flowsynth.errors import ConfigError, ShapeError
from flowsynth.kernels import wp_runtime
from flowsynth.raycast.blas import atlas, corner_normals
from flowsynth.raycast.culling import (FLAT_REL, MESH_CACHE_SIZE, culling_struct, culling_tables, hull_points,
                                       join_culling)
from flowsynth.raycast.tiles import join_tiles, posed_hull, tile_struct, tile_tables

# Up to this many instances per frame, camera rays walk candidate lists near to far instead of the BVH
# (``flowsynth.raycast.tiles``).
ORDERED_MAX = 64

__all__ = ["BOX_PAD_REL", "MESH_CACHE_SIZE", "SceneAccel", "clip_tiles", "pinhole", "prepare_clip", "resolve_device",
           "tiles_key"]

# Instance boxes are inflated by this fraction of their size (plus the same fraction of their distance
# to the camera) so float32 rounding of the ray never culls a true hit.
BOX_PAD_REL = 1e-4


def resolve_device(device) -> str:
    """The Warp device ``device`` names ("cpu", "cuda", "cuda:1", or a ``warp.Device``) as Warp's alias
    ("cpu", "cuda:0", ...). Raises ConfigError naming the device and the devices Warp finds when it has none such
    (e.g. "cuda" on a machine without a CUDA driver), and ForkError in a process forked after CUDA (``wp_runtime``):
    every render starts here."""
    wp = wp_runtime()
    try:
        return wp.get_device(device).alias
    except (RuntimeError, ValueError, TypeError) as e:
        found = [d.alias for d in wp.get_devices()]
        raise ConfigError(f"device {device!r} is not available: Warp finds {found} "
                          f"({wp.get_cuda_device_count()} CUDA device(s); {e}). Use device='cpu' or one of "
                          f"those") from None


class SceneAccel:
    """Ray-casting structure for F frames of N instances, or for a batch of clips (``SceneAccel.batch``).

    Args:
        meshes: N object-frame meshes (instances may share a mesh).
        cam_T_world: (F, 4, 4) float64.
        world_T_obj: (F, N, 4, 4) float64.
        device: Warp device ("cpu", the default; "cuda", "cuda:1", ... where Warp finds one: ``resolve_device``).
            Every array of the accel lives there.

    Items: instance n of frame f is item ``frame_start[f] + n`` (f N + n for one clip); ``F`` counts every frame,
    ``B`` the clips, ``T`` the frames of each; ``frame_start`` (F + 1,) and ``inst_start`` (B + 1,) (the first row of
    each clip in per-instance tables) are numpy int64. ``N`` is the clip's instance count (one clip) or None.
    """

    def __init__(self, meshes: list[trimesh.Trimesh], cam_T_world: np.ndarray, world_T_obj: np.ndarray,
                 device: str = "cpu", *, clips: list | None = None, prepared: list | None = None) -> None:
        """Build the per-frame instance boxes (camera frame), their near-to-far order and the grouped BVH (of one
        clip, or of ``clips``: ``SceneAccel.batch``)."""
        clips = list(clips) if clips is not None else [(meshes, cam_T_world, world_T_obj)]
        self._build(clips, device, list(prepared) if prepared is not None else [None] * len(clips))

    @classmethod
    def batch(cls, clips, device: str = "cpu", prepared: list | None = None) -> SceneAccel:
        """One accel over B clips, each (meshes, cam_T_world (T, 4, 4), world_T_obj (T, N_b, 4, 4)) with the same T:
        frame b T + t is frame t of clip b, and every table holds clip b's rows after clip b - 1's. Each clip's
        rows are the ones its own accel holds (the grouped BVH builds each frame's subtree from that frame's boxes
        alone), so a kernel launched once over the batch computes what B launches over single clips compute.
        ``prepared``: each clip's ``prepare_clip`` (made where the scene was made), or None to compute it here."""
        return cls([], np.zeros((0, 4, 4)), np.zeros((0, 0, 4, 4)), device, clips=clips, prepared=prepared)

    def _build(self, clips: list, device: str, prepared: list) -> None:
        wp = wp_runtime()
        device = resolve_device(device)
        frames = {int(c[1].shape[0]) for c in clips}
        if len(frames) != 1:
            raise ShapeError(f"every clip of a batch needs the same number of frames, got {sorted(frames)}")
        T = frames.pop()
        counts = np.array([len(c[0]) for c in clips], np.int64)
        B = len(clips)
        self.B, self.T, self.F, self.device = B, T, B * T, device
        self.N = int(counts[0]) if B == 1 else None
        self.counts = counts
        self.frame_start = np.concatenate([[0], np.cumsum(np.repeat(counts, T))]).astype(np.int64)
        self.inst_start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.empty = int(counts.sum()) == 0
        if self.empty:
            return
        parts = [p["clip"] if p is not None else _clip_tables(*c) for c, p in zip(clips, prepared)]
        distinct = {id(m): m for c in clips for m in c[0]}  # instances sharing a mesh share its tree
        slot = {k: i for i, k in enumerate(distinct)}
        self._distinct = list(distinct.values())
        self.blas = atlas(self._distinct, device)
        which = [np.array([slot[id(m)] for m in c[0]], np.int64) for c in clips]
        item0 = self.frame_start[::T]  # (B + 1,) each clip's first item
        # near-to-far visiting order per frame, as items of the batch
        self._order_np = [part["order"] + item0[b] for b, part in enumerate(parts)]

        def cat(key, dtype):
            return np.concatenate([part[key] for part in parts]).astype(dtype)

        def arr(a, dtype):
            return wp.array(a, dtype=dtype, device=device)

        self.near = arr(cat("near", np.float32), wp.float32)
        self._frame_start_dev = arr(self.frame_start.astype(np.int32), wp.int32)
        self.frame_items = arr(np.concatenate([o.reshape(-1) for o in self._order_np]).astype(np.int32), wp.int32)
        self.use_bvh = np.repeat(counts > ORDERED_MAX, T).astype(np.int32)  # (F,) per frame, as its clip
        self._use_bvh = arr(self.use_bvh, wp.int32)
        self._tiles: dict = {}
        self._bounds: list = [{} for _ in clips]  # per clip: camera (size, K, lens) -> screen bounds (tiles.py)
        groups = np.repeat(np.arange(self.F, dtype=np.int32), np.repeat(counts, T))
        self.lowers = arr(cat("lowers", np.float32), wp.vec3)  # (items,) padded instance boxes, camera frame
        self.uppers = arr(cat("uppers", np.float32), wp.vec3)
        self._groups = arr(groups, wp.int32)
        self.bvh = wp.Bvh(self.lowers, self.uppers, constructor="sah" if wp.get_device(device).is_cpu else None,
                          groups=self._groups)
        self.roots = _group_roots(self.bvh, self.F, device)
        self._corners = None
        self.item_root = arr(np.concatenate([np.tile(self.blas["roots"][w], T) for w in which]), wp.int32)
        self.item_face0 = arr(np.concatenate([np.tile(self.blas["face0"][w], T) for w in which]), wp.int32)
        self.item_inst = arr(np.concatenate([np.tile(self.inst_start[b] + np.arange(counts[b]), T)
                                             for b in range(B)]).astype(np.int32), wp.int32)
        self.obj_T_ref = arr(cat("obj_T_ref", np.float32), wp.mat44)
        self.ref_T_obj = arr(cat("ref_T_obj", np.float32), wp.mat44)
        self.thin = arr(cat("thin", np.int32), wp.int32)
        self.obj_lo = arr(cat("obj_lo", np.float32), wp.vec3)
        self.obj_hi = arr(cat("obj_hi", np.float32), wp.vec3)
        self._clips, self._parts, self._item0, self._cull, self._prepared = clips, parts, item0, None, prepared

    def instances(self):
        """The kernels' ``Instances`` struct (flowsynth.kernels.raycast) over this accel's arrays (no copy):
        every tracing kernel reads the scene from it."""
        from flowsynth.kernels.raycast import Instances

        inst = Instances()
        inst.bvh, inst.roots, inst.use_bvh = self.bvh.id, self.roots, self._use_bvh
        inst.frame_start, inst.frame_items, inst.near = self._frame_start_dev, self.frame_items, self.near
        inst.lowers, inst.uppers = self.lowers, self.uppers
        inst.obj_T_ref, inst.ref_T_obj, inst.item_inst = self.obj_T_ref, self.ref_T_obj, self.item_inst
        inst.thin, inst.obj_lo, inst.obj_hi = self.thin, self.obj_lo, self.obj_hi
        inst.item_root, inst.item_face0 = self.item_root, self.item_face0
        inst.blas_bounds, inst.blas_kids = self.blas["bounds"], self.blas["kids"]
        inst.blas_tris, inst.blas_face, inst.blas_slot = self.blas["tris"], self.blas["face"], self.blas["slot"]
        return inst

    def corner_normals(self):
        """Smooth shading's corner normals of every face of the atlas (``flowsynth.raycast.blas.corner_normals``): a
        vec3 Warp array, the normal of corner k of face ``face`` of an item at ``3 * (item_face0 + face) + k``; built
        once per accel."""
        if self._corners is None:
            wp = wp_runtime()
            n = [corner_normals(m).reshape(-1, 3) for m in self._distinct]
            self._corners = wp.array(np.concatenate(n) if n else np.zeros((1, 3), np.float32), dtype=wp.vec3,
                                     device=self.device)
        return self._corners

    def culling(self, threads: int | None = None):
        """The visibility rays' exact culling data: a ``Culling`` struct (flowsynth.kernels.raycast), built once per
        accel by ``flowsynth.raycast.culling.culling_tables`` per clip (face planes, flat slabs, silhouette planes;
        ``threads``: those of the face planes' kernel on a mesh not yet cached), the clips' rows one after another."""
        if self._cull is None:
            tables = [pre["culling"] if pre is not None and pre["culling"] is not None
                      else culling_tables(c[0], p["cam_T_obj"], threads, self.device)
                      for c, p, pre in zip(self._clips, self._parts, self._prepared)]
            self._flat = [t["flat"] for t in tables]
            self._cull = culling_struct(join_culling(tables, self._item0, self.T), self.device)
        return self._cull

    def tile_lists(self, camera, flat: bool = True, threads: int | None = None):
        """The primary cast's per-(frame, screen tile) candidate lists: a ``TileLists`` struct
        (flowsynth.kernels.raycast) built by ``flowsynth.raycast.tiles.tile_tables`` per clip (empty where the rays
        walk the BVH), once per camera; ``flat=False``: without the flat instances of ``culling()`` (visibility rays
        test those apart; ``threads``: those of ``culling``)."""
        key = tiles_key(camera, flat)
        if key not in self._tiles:
            lists = []
            for b, (c, part, pre) in enumerate(zip(self._clips, self._parts, self._prepared)):
                if pre is not None and key in pre["tiles"]:
                    lists.append(pre["tiles"][key])
                    continue
                flags = None if flat else self._flat_flags(b, threads)
                lists.append(clip_tiles(c[0], part, camera, flags, self._bounds[b]))
            self._tiles[key] = tile_struct(join_tiles(lists, self._item0, self.T), self.device)
        return self._tiles[key]

    def _flat_flags(self, b: int, threads: int | None) -> np.ndarray:
        """Clip b's (N,) flags of the flat instances (``culling``'s)."""
        pre = self._prepared[b]
        if pre is not None and pre["culling"] is not None:
            return pre["culling"]["flat"]
        self.culling(threads)
        return self._flat[b]


def tiles_key(camera, flat: bool) -> tuple:
    """The key of a camera's tile lists (with or without the flat instances) in ``SceneAccel`` and ``prepare_clip``."""
    return (camera.width, camera.height, camera.K.tobytes(), flat, camera.model, camera.dist)


def clip_tiles(meshes: list, part: dict, camera, flat_flags: np.ndarray | None, bounds: dict):
    """``tile_tables`` of one clip (``_clip_tables``' ``part``) for ``camera``: None where its rays walk the BVH
    (more than ``ORDERED_MAX`` instances); ``flat_flags`` (N,) bool leaves the flat instances out (None: all)."""
    if len(meshes) > ORDERED_MAX:
        return None
    order = part["order"]  # the clip's own items: join_tiles shifts them
    if flat_flags is not None:
        keep = ~flat_flags[part["rank"]]  # (T, N): the same instances are flat in every frame
        order = order[keep].reshape(len(order), -1)
    return tile_tables(meshes, part["cam_T_obj"], order, camera, bounds, part["posed"])


def prepare_clip(meshes: list, cam_T_world: np.ndarray, world_T_obj: np.ndarray, camera, *, occlusion: bool = True,
                 threads: int | None = None, device: str = "cpu") -> dict:
    """Everything ``SceneAccel.batch`` computes on the host for one clip and ``camera``, in numpy: the clip's tables,
    its tile lists, and with ``occlusion`` (exact visibility rays) its culling tables (the face planes' kernel on
    ``device``) and tile lists without the flat instances. Made where the scene is made (``DeviceBatches``' CPU
    workers), so that the rendering process only joins and uploads them; the same arrays as computed there."""
    part = _clip_tables(meshes, cam_T_world, world_T_obj)
    bounds: dict = {}
    out = {"clip": part, "culling": None, "tiles": {tiles_key(camera, True): clip_tiles(meshes, part, camera, None,
                                                                                         bounds)}}
    if occlusion:
        out["culling"] = culling_tables(meshes, part["cam_T_obj"], threads, device)
        out["tiles"][tiles_key(camera, False)] = clip_tiles(meshes, part, camera, out["culling"]["flat"], bounds)
    return out


def _clip_tables(meshes: list, cam_T_world: np.ndarray, world_T_obj: np.ndarray) -> dict:
    """One clip's per-item tables in numpy, item t N + n for instance n of frame t (``SceneAccel``): padded
    camera-frame boxes ``lowers``, ``uppers`` (T N, 3), their distance ``near`` from the camera, the near-to-far
    ``order`` (T, N) of the clip's items (``rank``: of its instances), ``obj_T_ref`` and ``ref_T_obj`` (T N, 4, 4),
    the thin flags and padded object-frame boxes ``thin``, ``obj_lo``, ``obj_hi``; ``cam_T_obj`` (T, N, 4, 4)
    float64 and each instance's hull points in the camera frames ``posed``."""
    F = cam_T_world.shape[0]
    N = len(meshes)
    # cam_T_obj per (frame, instance), float64
    cam_T_obj = np.einsum("fij,fnjk->fnik", cam_T_world, world_T_obj) if N else np.zeros((F, 0, 4, 4))
    none = np.zeros((F, 0), np.int64)
    out = {"cam_T_obj": cam_T_obj, "posed": [], "order": none, "rank": none}
    if N == 0:
        for k, w in (("lowers", 3), ("uppers", 3), ("obj_lo", 3), ("obj_hi", 3)):
            out[k] = np.zeros((0, w))
        for k in ("near", "thin"):
            out[k] = np.zeros(0)
        out["obj_T_ref"] = out["ref_T_obj"] = np.zeros((0, 4, 4))
        return out
    obj_T_cam = _rigid_inverse(cam_T_obj)
    lo = np.empty((F, N, 3))
    hi = np.empty((F, N, 3))
    scale = np.empty((F, N, 1))
    v_lo, v_hi = np.empty((N, 3)), np.empty((N, 3))  # object-frame boxes: those of the hull points
    posed = out["posed"]  # each instance's hull points in the camera frames (F, K, 3): the screen bounds' too
    boxes = {}  # id(mesh) -> its hull points and their object-frame box, once per distinct mesh
    for n, m in enumerate(meshes):  # tight boxes: the posed hull vertices, not the posed local box
        if id(m) not in boxes:
            hull = hull_points(m)
            boxes[id(m)] = hull, hull.min(0), hull.max(0)
        hull, v_lo[n], v_hi[n] = boxes[id(m)]
        pts = posed_hull(hull, cam_T_obj[:, n])
        posed.append(pts)
        lo[:, n], hi[:, n] = pts.min(1), pts.max(1)
        # max |coordinate| of the points: max(max, -min) over the axes, the same value as abs().max()
        scale[:, n, 0] = (hi[:, n] - lo[:, n]).max(-1) + np.maximum(hi[:, n], -lo[:, n]).max(-1)
    pad = BOX_PAD_REL * scale + 1e-30
    out["lowers"] = (lo - pad).reshape(-1, 3).astype(np.float32)
    out["uppers"] = (hi + pad).reshape(-1, 3).astype(np.float32)
    # distance from each frame's camera centre to each box, and the near-to-far visiting order
    near = np.linalg.norm(np.maximum(lo - pad, 0.0) + np.maximum(-(hi + pad), 0.0), axis=-1)
    out["rank"] = np.argsort(near, axis=1, kind="stable")  # (F, N) instances near to far
    out["order"] = out["rank"] + (np.arange(F) * N)[:, None]
    out["near"] = (near * (1.0 - 1e-6)).reshape(-1).astype(np.float32)
    out["obj_T_ref"] = obj_T_cam.reshape(-1, 4, 4).astype(np.float32)
    out["ref_T_obj"] = cam_T_obj.reshape(-1, 4, 4).astype(np.float32)
    # object-frame boxes, padded like the camera-frame ones (size plus the camera's farthest distance);
    # per item (tiled over the frames), so the kernels index them by item like every other array
    ext = v_hi - v_lo
    far = np.abs(obj_T_cam[..., :3, 3]).max((0, 2)) + np.abs(np.concatenate([v_lo, v_hi], 1)).max(1)
    o_pad = (BOX_PAD_REL * (ext.max(1) + far) + 1e-30)[:, None]
    out["thin"] = np.tile((ext.min(1) <= FLAT_REL * ext.max(1)).astype(np.int32), F)
    out["obj_lo"] = np.tile((v_lo - o_pad).astype(np.float32), (F, 1))
    out["obj_hi"] = np.tile((v_hi + o_pad).astype(np.float32), (F, 1))
    return out


def _rigid_inverse(T: np.ndarray) -> np.ndarray:
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def _group_roots(bvh, F: int, device: str):
    from flowsynth.kernels.raycast import group_roots_kernel

    wp = wp_runtime()
    roots = wp.zeros(F, dtype=wp.int32, device=device)
    wp.launch(group_roots_kernel, dim=F, inputs=[bvh.id], outputs=[roots], device=device)
    return roots


def pinhole(camera, device: str = "cpu", pad: int = 0):
    """The kernels' ``Pinhole`` struct of a camera's K (and a lens model's per-pixel rays, on ``device``; with
    ``pad`` > 0 those of ``Camera.ray_grid(pad)``, rows and columns -pad .. H - 1 + pad, for the shading kernel)."""
    from flowsynth.kernels.raycast import Pinhole

    wp = wp_runtime()
    K = camera.K
    p = Pinhole()
    p.intr = wp.vec4(K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    p.skew = float(K[0, 1])
    if not camera.is_pinhole:  # a lens model's rays, uploaded once per camera, pad and device (cached)
        key = (str(device), K.tobytes(), camera.width, camera.height, camera.model, camera.dist, int(pad))
        rays = _RAYS.get(key)
        if rays is None:
            rays = _RAYS[key] = _ray_array(camera, device, pad)
            while len(_RAYS) > RAY_CACHE_SIZE:
                _RAYS.popitem(last=False)
        _RAYS.move_to_end(key)
        p.rays = rays
    return p


# Lens cameras' ray arrays kept per process (per camera, pad and device; least recently used dropped), as
# flowsynth.scene.camera keeps their numpy rays.
RAY_CACHE_SIZE = 16
_RAYS: OrderedDict = register("accel.lens_ray_arrays", OrderedDict())


def _ray_array(camera, device: str, pad: int):
    """A lens camera's ``ray_grid(pad)`` as a float32 vec3 Warp array on ``device``; uncovered pixels get
    (0, 0, -1): no hit."""
    wp = wp_runtime()
    rays = camera.ray_grid(pad).astype(np.float32)
    rays[rays[..., 2] <= 0] = (0.0, 0.0, -1.0)
    return wp.array(rays, dtype=wp.vec3, device=device)
