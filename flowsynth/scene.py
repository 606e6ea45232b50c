"""Scene: plain data describing what the renderer sees — a camera path and rigid objects with per-frame poses.

No rendering happens here. Transforms are named ``a_T_b`` (maps b-frame points into frame a) and are
stored as float64 (T, 4, 4) arrays.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import trimesh

from flowsynth._checks import as_float64_array, check_rigid
from flowsynth.camera import Camera
from flowsynth.errors import AssetError, ConfigError

__all__ = ["Scene", "SceneObject", "clean_mesh"]

# Triangles with area below this fraction of (bounding-box diagonal)^2 are dropped as degenerate.
DEGENERATE_AREA_REL = 1e-14


@dataclass
class SceneObject:
    """One rigid instance in a scene.

    Attributes:
        instance: instance id k >= 1 (0 is reserved for "nothing").
        mesh: triangle mesh in the object frame [m] (cleaned: finite, no zero-area triangles).
        poses: (T, 4, 4) float64 world_T_obj per frame.
        category: category id >= 0 written to the ``category`` channel.
        asset: id of the mesh asset, >= 1; objects added with the same mesh object share it.
        material: free-form shading parameters (used by RGB rendering); empty means defaults.
        background: part of the set (e.g. the room): rendered, but left out of the object tables.
    """

    instance: int
    mesh: trimesh.Trimesh
    poses: np.ndarray
    category: int
    asset: int
    material: dict = field(default_factory=dict)
    background: bool = False


def clean_mesh(mesh: trimesh.Trimesh, name: str = "mesh") -> trimesh.Trimesh:
    """Validate a mesh and drop zero-area triangles (with a warning). Returns a new float64 mesh.

    Raises AssetError for meshes that are not triangle meshes, have no faces, or non-finite vertices.
    """
    if not isinstance(mesh, trimesh.Trimesh):
        raise AssetError(f"{name} must be a trimesh.Trimesh, got {type(mesh).__name__}; "
                         "load files with trimesh.load(path, force='mesh')")
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    if F.ndim != 2 or F.shape[0] == 0:
        raise AssetError(f"{name} has no faces")
    if not np.isfinite(V).all():
        raise AssetError(f"{name} has non-finite vertex coordinates")
    if F.min() < 0 or F.max() >= len(V):
        raise AssetError(f"{name} has face indices outside its vertex array")
    diag2 = float(np.sum((V.max(0) - V.min(0)) ** 2))
    tri = V[F]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    keep = area2 > 2.0 * DEGENERATE_AREA_REL * max(diag2, 1e-300)
    if not keep.all():
        warnings.warn(f"{name}: dropped {int((~keep).sum())} degenerate (zero-area) triangles", stacklevel=3)
        F = F[keep]
        if F.shape[0] == 0:
            raise AssetError(f"{name} has only degenerate (zero-area) triangles")
    return trimesh.Trimesh(vertices=V, faces=F, process=False, validate=False)


class Scene:
    """A camera moving through T frames and rigid objects with one pose per frame.

    Args:
        camera: intrinsics and image size.
        num_frames: T >= 1.
        fps: frames per second [1/s]; used for velocities and motion blur times.
    """

    def __init__(self, camera: Camera, num_frames: int, fps: float = 24.0) -> None:
        if not isinstance(camera, Camera):
            raise ConfigError(f"camera must be a flowsynth.Camera, got {type(camera).__name__}")
        if not isinstance(num_frames, (int, np.integer)) or num_frames < 1:
            raise ConfigError(f"num_frames must be an integer >= 1, got {num_frames!r}")
        if not (fps > 0 and np.isfinite(fps)):
            raise ConfigError(f"fps must be positive and finite, got {fps!r}")
        self.camera = camera
        self.num_frames = int(num_frames)
        self.fps = float(fps)
        self.world_T_cam = np.tile(np.eye(4), (self.num_frames, 1, 1))
        self.objects: list[SceneObject] = []
        self.lights: list = []  # light sources for RGB shading (see flowsynth.shading); empty = defaults
        self.meta: dict = {}  # provenance: config, seed, index when the scene was sampled
        self._assets: dict[int, tuple[int, trimesh.Trimesh]] = {}  # id(mesh) -> (asset id, cleaned mesh)
        self._asset_refs: list[trimesh.Trimesh] = []  # keeps user meshes alive so id() stays unique

    @property
    def cam_T_world(self) -> np.ndarray:
        """(T, 4, 4) float64 extrinsics (inverse of world_T_cam)."""
        return np.linalg.inv(self.world_T_cam)

    def set_camera_poses(self, world_T_cam) -> None:
        """Set the camera path: (T, 4, 4) world_T_cam, OpenCV axes (or one (4, 4) pose for all frames)."""
        self.world_T_cam = self._poses(world_T_cam, "world_T_cam")

    def add_object(self, mesh: trimesh.Trimesh, poses=None, category: int = 1, material: dict | None = None,
                   *, background: bool = False) -> int:
        """Add a rigid object and return its instance id k (1, 2, ... in call order).

        Args:
            mesh: triangle mesh in the object frame [m]. Passing the same mesh object again shares its asset id.
            poses: (T, 4, 4) world_T_obj, or (4, 4) for a static object; identity when None.
            category: category id >= 0.
            material: optional shading parameters for RGB rendering.
            background: scenery such as the room: rendered, not listed in the object tables.
        """
        if not isinstance(category, (int, np.integer)) or category < 0:
            raise ConfigError(f"category must be a non-negative integer, got {category!r}")
        poses = np.tile(np.eye(4), (self.num_frames, 1, 1)) if poses is None else self._poses(poses, "poses")
        key = id(mesh)
        if key not in self._assets:
            cleaned = clean_mesh(mesh, name=f"mesh of object {len(self.objects) + 1}")
            self._assets[key] = (len(self._assets) + 1, cleaned)
            self._asset_refs.append(mesh)
        asset, cleaned = self._assets[key]
        k = len(self.objects) + 1
        self.objects.append(SceneObject(k, cleaned, poses, int(category), asset, dict(material or {}),
                                        bool(background)))
        return k

    def _poses(self, poses, name: str) -> np.ndarray:
        P = as_float64_array(poses, name, (None, 4, 4) if np.ndim(poses) == 3 else (4, 4))
        if P.ndim == 2:
            P = np.tile(P, (self.num_frames, 1, 1))
        if P.shape[0] != self.num_frames:
            raise ConfigError(f"{name} must have one pose per frame: expected ({self.num_frames}, 4, 4), "
                              f"got {tuple(P.shape)}")
        check_rigid(P, name)
        return P.copy()

    def __repr__(self) -> str:
        return f"Scene({self.camera!r}, num_frames={self.num_frames}, objects={len(self.objects)})"
