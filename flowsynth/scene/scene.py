"""Scene: plain data describing what the renderer sees — a camera path, rigid objects with per-frame poses and
resolved materials, lights and the render seed.

No rendering happens here: the scene is the whole description of what is rendered, and ``Scene.to_meta`` /
``Scene.from_meta`` turn it into JSON and back exactly (the provenance a sample carries). Transforms are named
``a_T_b`` (maps b-frame points into frame a) and are stored as float64 (T, 4, 4) arrays.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field

import numpy as np
import trimesh

from flowsynth.errors import ConfigError
from flowsynth.options import check_int
from flowsynth.scene._checks import as_float64_array, check_rigid
from flowsynth.scene.camera import Camera
from flowsynth.scene.meshes import clean_mesh, library_copy

__all__ = ["PROVENANCE_VERSION", "Scene", "SceneObject", "clean_mesh", "provenance_json"]

PROVENANCE_VERSION = 1
"""Version of the ``Scene.to_meta`` schema."""


@dataclass
class SceneObject:
    """One rigid instance in a scene.

    Attributes:
        instance: instance id k >= 1 (0 is reserved for "nothing").
        mesh: triangle mesh in the object frame [m] (cleaned: finite, no zero-area triangles; frozen, i.e.
            read-only: ``flowsynth.scene.meshes.freeze``).
        poses: (T, 4, 4) float64 world_T_obj per frame.
        category: category id >= 0 written to the ``category`` channel.
        asset: id of the mesh asset, >= 1; objects added with the same mesh object share it.
        material: resolved material dict (``flowsynth.appearance.materials.resolve_material``: every key explicit).
        background: part of the set (e.g. the room): rendered, but left out of the object tables.
        source: where the mesh comes from, for provenance: ``{"asset": name, "size": metres}`` for a
            library asset (``flowsynth.scene.assets.get_asset``); None stores the vertices and faces themselves.
    """

    instance: int
    mesh: trimesh.Trimesh
    poses: np.ndarray
    category: int
    asset: int
    material: dict = field(default_factory=dict)
    background: bool = False
    source: dict | None = None


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
        num_frames = check_int("num_frames", num_frames, 1)
        if not (fps > 0 and np.isfinite(fps)):
            raise ConfigError(f"fps must be positive and finite, got {fps!r}")
        self.camera = camera
        self.num_frames = int(num_frames)
        self.fps = float(fps)
        self.world_T_cam = np.tile(np.eye(4), (self.num_frames, 1, 1))
        self.objects: list[SceneObject] = []
        self.lights: list = []  # flowsynth.appearance.lights.Light sources for RGB shading; empty = default_lights
        self.render_seed: int = 0  # seed of the renderer's noise (anti-aliasing, path tracing, motion blur)
        self.meta: dict = {}  # how the scene was made: config, seed, index when it was sampled
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
                   *, background: bool = False, source: dict | None = None) -> int:
        """Add a rigid object and return its instance id k (1, 2, ... in call order).

        Args:
            mesh: triangle mesh in the object frame [m]. Passing the same mesh object again shares its asset id.
            poses: (T, 4, 4) world_T_obj, or (4, 4) for a static object; identity when None.
            category: category id >= 0.
            material: shading parameters for RGB rendering (schema: docs/rendering.md); resolved here
                (``flowsynth.appearance.materials.resolve_material``), so an empty one becomes the instance's default.
            background: scenery such as the room: rendered, not listed in the object tables.
            source: ``{"asset": name, "size": metres}`` when ``mesh`` is ``flowsynth.scene.assets.get_asset(name,
                size).mesh``: provenance then names the asset instead of storing the mesh.
        """
        from flowsynth.appearance import resolve_material

        category = check_int("category", category, 0)
        poses = np.tile(np.eye(4), (self.num_frames, 1, 1)) if poses is None else self._poses(poses, "poses")
        key = id(mesh)
        if key not in self._assets:
            cleaned = library_copy(mesh)
            if cleaned is None:
                cleaned = clean_mesh(mesh, name=f"mesh of object {len(self.objects) + 1}")
            self._assets[key] = (len(self._assets) + 1, cleaned)
            self._asset_refs.append(mesh)
        asset, cleaned = self._assets[key]
        k = len(self.objects) + 1
        size = float(np.ptp(np.asarray(cleaned.vertices), axis=0).max()) or 1.0
        self.objects.append(SceneObject(k, cleaned, poses, int(category), asset,
                                        resolve_material(material, instance=k, size=size), bool(background),
                                        None if source is None else dict(source)))
        return k

    def to_meta(self) -> dict:
        """Everything rendered, as a JSON-compatible dict (floats exact): camera, poses, objects (asset or mesh,
        poses, resolved material), lights, render seed and ``meta``. ``Scene.from_meta`` rebuilds it."""
        from flowsynth.appearance import Light

        objects = []
        for o in self.objects:
            mesh = dict(o.source) if o.source is not None else {
                "vertices": np.asarray(o.mesh.vertices, np.float64).tolist(),
                "faces": np.asarray(o.mesh.faces, np.int64).tolist()}
            objects.append({"instance": o.instance, "category": o.category, "asset": o.asset,
                            "background": o.background, "mesh": mesh, "material": o.material,
                            "poses": o.poses.tolist()})
        lights = [{k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(Light(**x) if
                   isinstance(x, dict) else x).items()} for x in self.lights]
        return {"version": PROVENANCE_VERSION,
                "camera": {"K": self.camera.K.tolist(), "width": self.camera.width, "height": self.camera.height,
                           **self.camera.lens_meta()},
                "num_frames": self.num_frames, "fps": self.fps, "world_T_cam": self.world_T_cam.tolist(),
                "render_seed": int(self.render_seed), "lights": lights, "objects": objects,
                "meta": json.loads(json.dumps(self.meta))}

    @classmethod
    def from_meta(cls, meta) -> Scene:
        """Rebuild a scene from ``to_meta()`` output: the dict, its JSON string (a sample's ``provenance``),
        or a sample folder's meta.json dict (which holds it under ``provenance``). Rendering the result gives
        the sample bit for bit. Raises ConfigError when the description is not one."""
        from flowsynth.scene.assets import get_asset
        from flowsynth.appearance import Light

        if isinstance(meta, str):
            meta = json.loads(meta)
        if isinstance(meta, dict) and "provenance" in meta:
            meta = meta["provenance"]
            meta = json.loads(meta) if isinstance(meta, str) else meta
        if not isinstance(meta, dict) or meta.get("version") != PROVENANCE_VERSION:
            raise ConfigError(f"Scene.from_meta needs a Scene.to_meta() dict of version {PROVENANCE_VERSION}")
        cam = meta["camera"]
        scene = cls(Camera(np.asarray(cam["K"], np.float64), cam["width"], cam["height"],
                           model=cam.get("model", "pinhole"), dist=cam.get("dist")), meta["num_frames"],
                    meta["fps"])
        scene.set_camera_poses(np.asarray(meta["world_T_cam"], np.float64))
        meshes: dict[int, trimesh.Trimesh] = {}
        for o in meta["objects"]:
            src = o["mesh"]
            if o["asset"] not in meshes:
                meshes[o["asset"]] = (get_asset(src["asset"], float(src["size"])).mesh if "asset" in src else
                                      trimesh.Trimesh(np.asarray(src["vertices"], np.float64),
                                                      np.asarray(src["faces"], np.int64), process=False,
                                                      validate=False))
            scene.add_object(meshes[o["asset"]], np.asarray(o["poses"], np.float64), o["category"], o["material"],
                             background=o["background"], source=src if "asset" in src else None)
        scene.lights = [Light(**x) for x in meta["lights"]]
        scene.render_seed = int(meta["render_seed"])
        scene.meta = dict(meta["meta"])
        return scene

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


def provenance_json(scene: Scene) -> str:
    """``scene.to_meta()`` as one compact JSON string (what a sample's ``provenance`` key holds)."""
    return json.dumps(scene.to_meta(), separators=(",", ":"))
