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
from flowsynth.errors import ConfigError
from flowsynth.kernels import wp_runtime
from flowsynth.raycast.blas import atlas, corner_normals
from flowsynth.raycast.culling import FLAT_REL, MESH_CACHE_SIZE, build_culling, hull_points
from flowsynth.raycast.tiles import posed_hull, tile_lists

# Up to this many instances per frame, camera rays walk candidate lists near to far instead of the BVH
# (``flowsynth.raycast.tiles``).
ORDERED_MAX = 64

__all__ = ["BOX_PAD_REL", "MESH_CACHE_SIZE", "SceneAccel", "pinhole", "resolve_device"]

# Instance boxes are inflated by this fraction of their size (plus the same fraction of their distance
# to the camera) so float32 rounding of the ray never culls a true hit.
BOX_PAD_REL = 1e-4


def resolve_device(device) -> str:
    """The Warp device ``device`` names ("cpu", "cuda", "cuda:1", or a ``warp.Device``) as Warp's alias
    ("cpu", "cuda:0", ...). Raises ConfigError naming the device and the devices Warp finds when it has none such
    (e.g. "cuda" on a machine without a CUDA driver)."""
    wp = wp_runtime()
    try:
        return wp.get_device(device).alias
    except (RuntimeError, ValueError, TypeError) as e:
        found = [d.alias for d in wp.get_devices()]
        raise ConfigError(f"device {device!r} is not available: Warp finds {found} "
                          f"({wp.get_cuda_device_count()} CUDA device(s); {e}). Use device='cpu' or one of "
                          f"those") from None


class SceneAccel:
    """Ray-casting structure for F frames of N instances.

    Args:
        meshes: N object-frame meshes (instances may share a mesh).
        cam_T_world: (F, 4, 4) float64.
        world_T_obj: (F, N, 4, 4) float64.
        device: Warp device ("cpu", the default; "cuda", "cuda:1", ... where Warp finds one: ``resolve_device``).
            Every array of the accel lives there.
    """

    def __init__(self, meshes: list[trimesh.Trimesh], cam_T_world: np.ndarray, world_T_obj: np.ndarray,
                 device: str = "cpu") -> None:
        """Build the per-frame instance boxes (camera frame), their near-to-far order and the grouped BVH."""
        wp = wp_runtime()
        F = cam_T_world.shape[0]
        N = len(meshes)
        device = resolve_device(device)
        self.F, self.N, self.device = F, N, device
        self.empty = N == 0
        if self.empty:
            return
        # cam_T_obj per (frame, instance), float64
        cam_T_obj = np.einsum("fij,fnjk->fnik", cam_T_world, world_T_obj)
        obj_T_cam = _rigid_inverse(cam_T_obj)
        lo = np.empty((F, N, 3))
        hi = np.empty((F, N, 3))
        scale = np.empty((F, N, 1))
        v_lo, v_hi = np.empty((N, 3)), np.empty((N, 3))  # object-frame boxes: those of the hull points
        self._posed = []  # each instance's hull points in the camera frames (F, K, 3): the screen bounds' too
        boxes = {}  # id(mesh) -> its hull points and their object-frame box, once per distinct mesh
        for n, m in enumerate(meshes):  # tight boxes: the posed hull vertices, not the posed local box
            if id(m) not in boxes:
                hull = hull_points(m)
                boxes[id(m)] = hull, hull.min(0), hull.max(0)
            hull, v_lo[n], v_hi[n] = boxes[id(m)]
            pts = posed_hull(hull, cam_T_obj[:, n])
            self._posed.append(pts)
            lo[:, n], hi[:, n] = pts.min(1), pts.max(1)
            # max |coordinate| of the points: max(max, -min) over the axes, the same value as abs().max()
            scale[:, n, 0] = (hi[:, n] - lo[:, n]).max(-1) + np.maximum(hi[:, n], -lo[:, n]).max(-1)
        pad = BOX_PAD_REL * scale + 1e-30
        lowers = (lo - pad).reshape(-1, 3).astype(np.float32)
        uppers = (hi + pad).reshape(-1, 3).astype(np.float32)
        # distance from each frame's camera centre to each box, and the near-to-far visiting order
        near = np.linalg.norm(np.maximum(lo - pad, 0.0) + np.maximum(-(hi + pad), 0.0), axis=-1)
        order = np.argsort(near, axis=1, kind="stable") + (np.arange(F) * N)[:, None]
        self.near = wp.array((near * (1.0 - 1e-6)).reshape(-1).astype(np.float32), dtype=wp.float32, device=device)
        self._order_np, self._lo, self._hi = order, lo - pad, hi + pad
        self.frame_start = wp.array(np.arange(F + 1, dtype=np.int32) * N, dtype=wp.int32, device=device)
        self.frame_items = wp.array(order.reshape(-1).astype(np.int32), dtype=wp.int32, device=device)
        self.use_bvh = int(N > ORDERED_MAX)
        self._tiles: dict = {}
        self._bounds: dict = {}  # camera (size, K, lens) -> its screen bounds (flowsynth.raycast.tiles)
        groups = np.repeat(np.arange(F, dtype=np.int32), N)
        self.lowers = wp.array(lowers, dtype=wp.vec3, device=device)  # (F * N,) padded instance boxes, camera frame
        self.uppers = wp.array(uppers, dtype=wp.vec3, device=device)
        self._groups = wp.array(groups, dtype=wp.int32, device=device)
        self.bvh = wp.Bvh(self.lowers, self.uppers, constructor="sah" if wp.get_device(device).is_cpu else None,
                          groups=self._groups)
        roots = _group_roots(self.bvh, F, device)
        self.roots = roots
        distinct = {id(m): m for m in meshes}  # instances sharing a mesh share its tree
        slot = {k: i for i, k in enumerate(distinct)}
        self._distinct = list(distinct.values())
        self.blas = atlas(self._distinct, device)
        self._corners = None
        which = [slot[id(m)] for m in meshes]
        self.item_root = wp.array(np.tile(self.blas["roots"][which], F), dtype=wp.int32, device=device)
        self.item_face0 = wp.array(np.tile(self.blas["face0"][which], F), dtype=wp.int32, device=device)
        self.obj_T_ref = wp.array(obj_T_cam.reshape(-1, 4, 4).astype(np.float32), dtype=wp.mat44, device=device)
        self.ref_T_obj = wp.array(cam_T_obj.reshape(-1, 4, 4).astype(np.float32), dtype=wp.mat44, device=device)
        self._meshes, self._cam_T_obj, self._cull = meshes, cam_T_obj, None
        # object-frame boxes, padded like the camera-frame ones (size plus the camera's farthest distance);
        # per item (tiled over the frames), so the kernels index them by item like every other array
        ext = v_hi - v_lo
        far = np.abs(obj_T_cam[..., :3, 3]).max((0, 2)) + np.abs(np.concatenate([v_lo, v_hi], 1)).max(1)
        o_pad = (BOX_PAD_REL * (ext.max(1) + far) + 1e-30)[:, None]
        thin = (ext.min(1) <= FLAT_REL * ext.max(1)).astype(np.int32)
        self.thin = wp.array(np.tile(thin, F), dtype=wp.int32, device=device)
        self.obj_lo = wp.array(np.tile((v_lo - o_pad).astype(np.float32), (F, 1)), dtype=wp.vec3, device=device)
        self.obj_hi = wp.array(np.tile((v_hi + o_pad).astype(np.float32), (F, 1)), dtype=wp.vec3, device=device)

    def instances(self):
        """The kernels' ``Instances`` struct (flowsynth.kernels.raycast) over this accel's arrays (no copy):
        every tracing kernel reads the scene from it."""
        from flowsynth.kernels.raycast import Instances

        inst = Instances()
        inst.bvh, inst.roots, inst.use_bvh = self.bvh.id, self.roots, self.use_bvh
        inst.frame_start, inst.frame_items, inst.near = self.frame_start, self.frame_items, self.near
        inst.lowers, inst.uppers = self.lowers, self.uppers
        inst.obj_T_ref, inst.ref_T_obj, inst.n_inst = self.obj_T_ref, self.ref_T_obj, self.N
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
        accel by ``flowsynth.raycast.culling.build_culling`` (face planes, flat slabs, silhouette planes; ``threads``:
        those of the face planes' kernel on a mesh not yet cached)."""
        if self._cull is None:
            self._cull, self._flat = build_culling(self._meshes, self._cam_T_obj, threads, self.device)
        return self._cull

    def tile_lists(self, camera, flat: bool = True, threads: int | None = None):
        """The primary cast's per-(frame, screen tile) candidate lists: a ``TileLists`` struct
        (flowsynth.kernels.raycast) built by ``flowsynth.raycast.tiles.tile_lists`` (empty when the rays walk the BVH),
        once per camera; ``flat=False``: without the flat instances of ``culling()`` (visibility rays test those
        apart; ``threads``: those of ``culling``)."""
        key = (camera.width, camera.height, camera.K.tobytes(), flat, camera.model, camera.dist)
        if key not in self._tiles:
            order = None
            if not self.use_bvh:
                order = self._order_np
                if not flat:
                    self.culling(threads)
                    local = order - (np.arange(self.F) * self.N)[:, None]
                    keep = ~self._flat[local]  # (F, N): the same instances are flat in every frame
                    order = order[keep].reshape(self.F, -1)
            self._tiles[key] = tile_lists(self._meshes, self._cam_T_obj, order, camera, self._bounds, self.device,
                                          self._posed)
        return self._tiles[key]


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
