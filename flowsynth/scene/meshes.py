"""Mesh hygiene shared by the scene and the asset library: validation and cleaning, frozen (read-only) meshes,
and the cleaned copies of library meshes.

A leaf module (it imports only ``flowsynth.errors`` and ``flowsynth.caches``), so that ``flowsynth.scene.scene`` (which
cleans every mesh added to a scene) and ``flowsynth.scene.assets`` (which makes the library meshes) both sit above it.
"""

from __future__ import annotations

import warnings
import weakref

import numpy as np
import trimesh

from flowsynth.caches import register
from flowsynth.errors import AssetError

__all__ = ["DEGENERATE_AREA_REL", "clean_mesh", "freeze", "library_copy", "library_mesh"]

# Triangles with area below this fraction of (bounding-box diagonal)^2 are dropped as degenerate.
DEGENERATE_AREA_REL = 1e-14

# Cleaned copies of the meshes flowsynth.scene.assets makes once per process and never modifies (get_asset, room_walls),
# keyed by identity: each is cleaned once and its copy shared by every scene, instead of cleaned per scene (which,
# with the content hash every new mesh object then costs the ray caster, was ~6 ms of a 256x192 sample:
# docs/decisions/0008-library-meshes-cleaned-once.md). A user's mesh, even one equal to a library mesh, is never
# looked up.
_LIBRARY_MESHES: weakref.WeakKeyDictionary = register("meshes.library", weakref.WeakKeyDictionary())


def freeze(mesh):
    """Make ``mesh``'s vertex and face arrays read-only, in place, and return it.

    For a ``trimesh.Trimesh`` this is ``mesh.mutable = False``: writing into ``mesh.vertices`` or ``mesh.faces``
    raises ValueError ("assignment destination is read-only"), and so does assigning new arrays. Per-process
    caches keyed by a mesh object (``flowsynth.raycast.accel``, ``flowsynth.raycast.blas``) freeze it before they keep
    anything of it, so a mesh changed after it was cached fails loudly instead of being drawn with a stale tree. Other
    objects with numpy ``vertices`` and ``faces`` get those arrays' ``writeable`` flag cleared.
    """
    if isinstance(mesh, trimesh.Trimesh):
        if mesh.mutable:
            mesh.mutable = False
        return mesh
    for name in ("vertices", "faces"):
        arr = getattr(mesh, name, None)
        if isinstance(arr, np.ndarray) and arr.flags.writeable:
            arr.flags.writeable = False
    return mesh


def library_mesh(mesh: trimesh.Trimesh, name: str = "mesh") -> trimesh.Trimesh:
    """Mark ``mesh``, made by flowsynth.scene.assets, as shared: it is frozen (``freeze``), and ``Scene.add_object``
    then uses one cleaned (and frozen) copy of it in every scene. Returns ``mesh``."""
    _LIBRARY_MESHES[freeze(mesh)] = clean_mesh(mesh, name=name)
    return mesh


def library_copy(mesh) -> trimesh.Trimesh | None:
    """The cleaned copy of a library mesh (``library_mesh``), or None for any other mesh."""
    return _LIBRARY_MESHES.get(mesh) if isinstance(mesh, trimesh.Trimesh) else None


def clean_mesh(mesh: trimesh.Trimesh, name: str = "mesh") -> trimesh.Trimesh:
    """Validate a mesh and drop zero-area triangles (with a warning). Returns a new, frozen float64 mesh
    (``freeze``) that shares no memory with ``mesh``.

    Raises AssetError for meshes that are not triangle meshes, have no faces, or non-finite vertices.
    """
    if not isinstance(mesh, trimesh.Trimesh):
        raise AssetError(f"{name} must be a trimesh.Trimesh, got {type(mesh).__name__}; "
                         "load files with trimesh.load(path, force='mesh')")
    # copies: the frozen result shares no memory with ``mesh``, which its owner may still change
    V = np.array(mesh.vertices, dtype=np.float64)
    F = np.array(mesh.faces, dtype=np.int64)
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
    return freeze(trimesh.Trimesh(vertices=V, faces=F, process=False, validate=False))
