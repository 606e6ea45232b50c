"""Meshes for BouncingThings: built-in primitives and irregular shapes, and user mesh files.

Every asset is normalised in its object frame so that the sphere of radius 1/2 centred at the origin
bounds it (the farthest vertex lies at distance exactly 1/2). ``get_asset(name, size)`` scales it by
``size`` [m], so ``size`` is the diameter of the object's bounding sphere about its origin. The origin
is the centre of the unscaled mesh's axis-aligned bounding box.

Each asset carries its collision shape (:class:`Collider`): the analytic primitive for box, sphere,
capsule, cylinder and cone (axis +z, as Newton expects), and the convex hull of the visual mesh for
everything else (torus, irregular shapes, user files). The visual mesh always lies inside its
collider, so colliders that never overlap imply visual meshes that never overlap.

Meshes are cached per process: the same (name, size) returns the same ``trimesh.Trimesh`` object, so
objects that share an asset share an asset id in a :class:`flowsynth.Scene` and the renderer's per-asset
acceleration structures are reused across samples. Returned meshes are frozen (``flowsynth.scene.meshes.freeze``):
writing into their vertices or faces raises; ``mesh.copy()`` gives one to change. ``fs.clear_caches()`` empties
these caches (``flowsynth.caches``).
"""

from __future__ import annotations

import functools
import glob
import math
import os
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import HalfspaceIntersection

from flowsynth.caches import register
from flowsynth.errors import AssetError
from flowsynth.scene.meshes import clean_mesh, freeze, library_mesh

__all__ = [
    "BUILTIN_ASSETS",
    "HULL_MAX_VERTICES",
    "PRIMITIVE_ASSETS",
    "ROOM_WALLS",
    "Asset",
    "Collider",
    "check_asset_entries",
    "get_asset",
    "load_user_mesh",
    "resolve_assets",
    "room_walls",
    "unit_hull",
    "unit_mesh",
]

PRIMITIVE_ASSETS = ("box", "sphere", "cylinder", "capsule", "cone")
"""Built-in assets whose collider is the analytic primitive."""

BUILTIN_ASSETS = (*PRIMITIVE_ASSETS, "torus", "rock", "crystal", "star", "blob", "chair", "frame")
"""Every built-in asset name, in category order (see ``docs/scenes.md``). ``chair`` and ``frame`` (thin legs, bars
and holes: thin structures and chair-like parts) are not in the default config's ``assets``."""

_GLOB_CHARS = "*?["
HULL_MAX_VERTICES = 192
"""Largest convex collider kept exact [vertices]; bigger hulls are replaced by a coarser containing
polytope (collision cost in Newton grows with hull vertices)."""
# Bounding-sphere radius of every unit-size asset [m]: the farthest vertex from the origin.
_UNIT_RADIUS = 0.5


@dataclass(frozen=True)
class Collider:
    """Collision shape of an asset in its object frame [m].

    Attributes:
        kind: "box" | "sphere" | "capsule" | "cylinder" | "cone" | "convex".
        params: box (hx, hy, hz) half extents; sphere (r,); capsule (r, half_height) of the
            cylindrical part; cylinder (r, half_height); cone (r, half_height), base at z = -half_height,
            apex at +half_height. Axes of capsule, cylinder and cone are +z. Empty for "convex".
        hull: watertight convex polytope containing the visual mesh: the collider for "convex"
            (the convex hull, or a slightly larger one, see HULL_MAX_VERTICES); for primitives the convex
            hull of the visual mesh, used for mass properties only.
    """

    kind: str
    params: tuple[float, ...]
    hull: trimesh.Trimesh


@dataclass(frozen=True, eq=False)
class Asset:
    """A scaled mesh and its collider.

    Attributes:
        name: the built-in name, or the absolute path of a user mesh file.
        size: bounding-sphere diameter about the origin [m].
        mesh: visual mesh in the object frame [m]; every vertex has norm <= size / 2.
        collider: collision shape in the object frame [m].
    """

    name: str
    size: float
    mesh: trimesh.Trimesh
    collider: Collider


def check_asset_entries(entries: tuple[str, ...] | list[str], field: str = "assets") -> None:
    """Check asset entries by their form alone, reading no file: each a non-empty string that is a built-in name, a
    glob or a path (it has a folder separator or an extension). Raises AssetError naming ``field`` otherwise.
    ``resolve_assets`` reads the files."""
    for entry in entries:
        _entry_kind(entry, field)


def _entry_kind(entry, field: str) -> str:
    """"builtin", "glob" or "path" for a valid entry (no file is read); AssetError naming ``field`` otherwise."""
    if not isinstance(entry, str) or not entry:
        raise AssetError(f"{field}: entries must be non-empty strings, got {entry!r}")
    if entry in BUILTIN_ASSETS:
        return "builtin"
    expanded = os.path.expanduser(entry)
    if any(c in expanded for c in _GLOB_CHARS):
        return "glob"
    if os.path.sep in expanded or os.path.splitext(expanded)[1]:
        return "path"
    raise AssetError(f"{field}: unknown asset {entry!r}; use one of {list(BUILTIN_ASSETS)} "
                     "or a path to a mesh file that trimesh can load")


def resolve_assets(entries: tuple[str, ...] | list[str], field: str = "assets") -> tuple[str, ...]:
    """Expand built-in names, file paths and globs into asset keys, in order.

    Built-in names stay as they are; paths become absolute; a glob expands to its matches sorted by
    name. Every file is loaded once (cached) to check it. Raises AssetError naming ``field`` when an
    entry is unknown, a glob matches nothing, or a file does not exist or does not load.
    """
    out: list[str] = []
    for entry in entries:
        kind = _entry_kind(entry, field)
        if kind == "builtin":
            out.append(entry)
            continue
        expanded = os.path.expanduser(entry)
        if kind == "glob":
            matches = sorted(p for p in glob.glob(expanded, recursive=True) if os.path.isfile(p))
            if not matches:
                raise AssetError(f"{field}: glob {entry!r} matches no files; fix the pattern or remove it")
        else:
            matches = [expanded]
        for path in matches:
            path = os.path.abspath(path)
            try:
                load_user_mesh(path)
            except AssetError as e:
                raise AssetError(f"{field}: {e}") from e
            out.append(path)
    return tuple(out)


def load_user_mesh(path: str) -> trimesh.Trimesh:
    """Load a mesh file with ``trimesh.load(path, force="mesh")``, cleaned and normalised to unit
    bounding-sphere diameter (see the module docstring). Cached per (path, mtime, size on disk).

    Raises AssetError when the file is missing, does not load, or has no usable triangles.
    """
    path = os.path.abspath(os.path.expanduser(path))
    if not os.path.isfile(path):
        raise AssetError(f"mesh file {path!r} does not exist; check the path in `assets`")
    st = os.stat(path)
    return _load_user_mesh_cached(path, st.st_mtime_ns, st.st_size)


@register("assets.user_meshes")
@functools.lru_cache(maxsize=256)
def _load_user_mesh_cached(path: str, mtime_ns: int, nbytes: int) -> trimesh.Trimesh:
    try:
        loaded = trimesh.load(path, force="mesh")
    except Exception as e:  # trimesh raises many exception types for bad files
        raise AssetError(f"mesh file {path!r} could not be loaded by trimesh ({type(e).__name__}: {e}); "
                         "use a format trimesh reads (obj, ply, stl, glb, off)") from e
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise AssetError(f"mesh file {path!r} contains no triangles; export it as a triangle mesh")
    return freeze(_normalise(clean_mesh(loaded, name=f"mesh file {path!r}")))


def unit_mesh(name: str) -> trimesh.Trimesh:
    """The visual mesh of a built-in asset or user file at bounding-sphere diameter 1 [m] (cached)."""
    if name in BUILTIN_ASSETS:
        return _builtin_unit(name)
    return load_user_mesh(name)


@register("assets.get_asset")
@functools.lru_cache(maxsize=1024)
def get_asset(name: str, size: float) -> Asset:
    """The asset ``name`` (built-in name or mesh file path) scaled to bounding-sphere diameter ``size`` [m].

    Cached: the same (name, size) returns the same :class:`Asset` and the same mesh object.
    """
    if not (isinstance(size, (int, float)) and math.isfinite(size) and size > 0):
        raise AssetError(f"asset size must be a positive finite number of metres, got {size!r}")
    unit = unit_mesh(name)
    mesh = library_mesh(trimesh.Trimesh(vertices=unit.vertices * size, faces=unit.faces, process=False, validate=False),
                        name=f"asset {name}")
    uh = unit_hull(name)
    hull = freeze(trimesh.Trimesh(vertices=uh.vertices * size, faces=uh.faces, process=False, validate=False))
    kind, params = _PRIMITIVE_PARAMS.get(name, ("convex", ()))
    return Asset(name=name, size=float(size), mesh=mesh,
                 collider=Collider(kind=kind, params=tuple(p * size for p in params), hull=hull))


@register("assets.unit_hull")
@functools.lru_cache(maxsize=1024)
def unit_hull(name: str) -> trimesh.Trimesh:
    """Convex polytope containing the unit mesh (cached): its convex hull, or, when that has more than
    HULL_MAX_VERTICES vertices, a coarser polytope whose every face plane is pushed out to the hull's
    support (so it still contains the mesh; a few percent larger by volume)."""
    hull = unit_mesh(name).convex_hull
    V = np.asarray(hull.vertices, dtype=np.float64)
    if len(V) <= HULL_MAX_VERTICES:
        return freeze(hull)
    coarse = trimesh.convex.convex_hull(V[_farthest_points(V, max(8, HULL_MAX_VERTICES // 4))])
    normals = np.asarray(coarse.face_normals)
    offsets = (V @ normals.T).max(0)
    cut = HalfspaceIntersection(np.hstack([normals, -offsets[:, None]]), V.mean(0))
    return freeze(trimesh.convex.convex_hull(cut.intersections))


def _farthest_points(V: np.ndarray, k: int) -> np.ndarray:
    """Indices of k points of V (M, 3) chosen greedily, each farthest from those before (deterministic)."""
    idx = [int(np.argmax(np.linalg.norm(V - V.mean(0), axis=1)))]
    d = np.linalg.norm(V - V[idx[0]], axis=1)
    for _ in range(k - 1):
        idx.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(V - V[idx[-1]], axis=1))
    return np.asarray(idx)


ROOM_WALLS = ("floor", "ceiling", "wall_x-", "wall_x+", "wall_y-", "wall_y+")
"""Names of the room's six faces, in the order of ``room_walls`` (wall_x- is the wall at x = lo[0], ...)."""


@register("assets.room_walls")
@functools.lru_cache(maxsize=64)
def room_walls(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> tuple[trimesh.Trimesh, ...]:
    """The six faces of the axis-aligned box from ``lo`` to ``hi`` [m], one two-triangle mesh each, in
    ``ROOM_WALLS`` order, with normals facing into the box (seen from inside); cached."""
    lo_a, hi_a = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    walls = []
    for axis, side in ((2, 0), (2, 1), (0, 0), (0, 1), (1, 0), (1, 1)):
        u, v = [a for a in range(3) if a != axis]
        corners = np.zeros((4, 3))
        corners[:, axis] = (lo_a, hi_a)[side][axis]
        corners[:, u] = [lo_a[u], hi_a[u], hi_a[u], lo_a[u]]
        corners[:, v] = [lo_a[v], lo_a[v], hi_a[v], hi_a[v]]
        faces = np.array([[0, 1, 2], [0, 2, 3]])
        normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        inward = 1.0 if side == 0 else -1.0
        if normal[axis] * inward < 0:
            faces = faces[:, ::-1]
        walls.append(library_mesh(trimesh.Trimesh(vertices=corners, faces=faces, process=False, validate=False),
                                  name=ROOM_WALLS[len(walls)]))
    return tuple(walls)


# Built-in shapes, proportions before normalisation. Primitive parameters are stored at unit size.
_BOX_EXTENTS = (1.0, 0.7, 0.45)
_CYL_R, _CYL_H = 0.35, 1.0
_CAP_R, _CAP_H = 0.25, 0.7  # radius, length of the cylindrical part
_CONE_R, _CONE_H = 0.45, 0.9
_SECTIONS = 32


def _primitive_params() -> dict[str, tuple[str, tuple[float, ...]]]:
    def unit(kind: str, params: tuple[float, ...], radius: float) -> tuple[str, tuple[float, ...]]:
        s = _UNIT_RADIUS / radius
        return kind, tuple(p * s for p in params)

    bx = tuple(e / 2 for e in _BOX_EXTENTS)
    return {
        "box": unit("box", bx, math.sqrt(sum(e * e for e in bx))),
        "sphere": ("sphere", (_UNIT_RADIUS,)),
        "cylinder": unit("cylinder", (_CYL_R, _CYL_H / 2), math.hypot(_CYL_R, _CYL_H / 2)),
        "capsule": unit("capsule", (_CAP_R, _CAP_H / 2), _CAP_R + _CAP_H / 2),
        "cone": unit("cone", (_CONE_R, _CONE_H / 2), math.hypot(_CONE_R, _CONE_H / 2)),
    }


_PRIMITIVE_PARAMS = _primitive_params()


@register("assets.builtin_unit")
@functools.cache
def _builtin_unit(name: str) -> trimesh.Trimesh:
    if name == "box":
        m = trimesh.creation.box(extents=_BOX_EXTENTS)
    elif name == "sphere":
        m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    elif name == "cylinder":
        m = trimesh.creation.cylinder(radius=_CYL_R, height=_CYL_H, sections=_SECTIONS)
    elif name == "capsule":
        m = trimesh.creation.capsule(height=_CAP_H, radius=_CAP_R, count=[_SECTIONS, _SECTIONS])
    elif name == "cone":
        m = trimesh.creation.cone(radius=_CONE_R, height=_CONE_H, sections=_SECTIONS)
    elif name == "torus":
        m = trimesh.creation.torus(major_radius=0.35, minor_radius=0.15, major_sections=32, minor_sections=16)
    elif name == "rock":
        m = _displaced_sphere(seed=1, lobes=9, amplitude=0.18, sharpness=3.0, subdivisions=2)
    elif name == "blob":
        m = _displaced_sphere(seed=2, lobes=4, amplitude=0.45, sharpness=12.0, subdivisions=3)
    elif name == "star":
        m = _star()
    elif name == "crystal":
        m = _crystal()
    elif name == "chair":
        m = _voxel_solid(_CHAIR)
    elif name == "frame":
        m = _voxel_solid(_FRAME)
    else:
        raise AssetError(f"unknown built-in asset {name!r}; use one of {list(BUILTIN_ASSETS)}")
    # Cones are centred on their geometric centre (base at -h, apex at +h), like Newton's cone.
    return freeze(_normalise(m))


def _normalise(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Centre on the bounding-box centre and scale so the farthest vertex is at distance 1/2."""
    V = np.asarray(mesh.vertices, dtype=np.float64)
    V = V - (V.min(0) + V.max(0)) / 2.0
    radius = float(np.linalg.norm(V, axis=1).max())
    if not radius > 0:
        raise AssetError("mesh has zero extent (all vertices coincide)")
    return trimesh.Trimesh(vertices=V * (_UNIT_RADIUS / radius), faces=np.asarray(mesh.faces), process=False,
                           validate=False)


def _displaced_sphere(seed: int, lobes: int, amplitude: float, sharpness: float, subdivisions: int
                      ) -> trimesh.Trimesh:
    """Icosphere with radius 1 + amplitude * sum of smooth bumps exp(sharpness (n . d_k - 1))."""
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    n = np.asarray(sphere.vertices)
    dirs = rng.normal(size=(lobes, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    weights = rng.uniform(0.3, 1.0, size=lobes)
    r = 1.0 + amplitude * (weights * np.exp(sharpness * (n @ dirs.T - 1.0))).sum(1)
    return trimesh.Trimesh(vertices=n * r[:, None], faces=sphere.faces, process=False)


def _star() -> trimesh.Trimesh:
    """Spiky ball: an icosphere with 12 cone-like spikes along the icosahedron's vertex directions."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    n = np.asarray(sphere.vertices)
    spikes = np.asarray(trimesh.creation.icosahedron().vertices)
    spikes /= np.linalg.norm(spikes, axis=1, keepdims=True)
    c = np.clip((n @ spikes.T).max(1), -1.0, 1.0)
    r = 0.55 + 0.45 * np.clip((c - 0.85) / 0.15, 0.0, 1.0) ** 1.5
    return trimesh.Trimesh(vertices=n * r[:, None], faces=sphere.faces, process=False)


def _chair_cells() -> np.ndarray:
    """Occupancy (x, y, z) of a chair on a 9 x 9 x 16 grid: four one-cell legs, a seat, a back of two posts and two
    rails (holes between them)."""
    g = np.zeros((9, 9, 16), bool)
    for x in (0, 8):
        for y in (0, 8):
            g[x, y, :7] = True  # legs
    g[:, :, 7] = True  # seat
    g[0, 8, 8:] = g[8, 8, 8:] = True  # back posts
    g[:, 8, 11] = g[:, 8, 15] = True  # back rails
    return g


def _frame_cells() -> np.ndarray:
    """Occupancy of the twelve one-cell edges of a 10 x 10 x 10 cube (a wire frame: thin bars, open faces)."""
    g = np.zeros((10, 10, 10), bool)
    e = (0, 9)
    for a in e:
        for b in e:
            g[:, a, b] = g[a, :, b] = g[a, b, :] = True
    return g


_CHAIR = _chair_cells()
_FRAME = _frame_cells()


def _voxel_solid(cells: np.ndarray) -> trimesh.Trimesh:
    """The closed surface of a union of unit cubes (``cells``, a boolean grid): one outward quad (two triangles)
    per face between a filled and an empty cell, corners shared. Watertight and consistently wound wherever no two
    cells touch along an edge or corner alone."""
    filled = np.pad(cells, 1)
    verts: dict = {}
    faces = []
    # per axis and side: the face's four corners (offsets from the cell's low corner), counter-clockwise seen from
    # outside
    quads = {
        (0, -1): [(0, 0, 0), (0, 0, 1), (0, 1, 1), (0, 1, 0)], (0, 1): [(1, 0, 0), (1, 1, 0), (1, 1, 1), (1, 0, 1)],
        (1, -1): [(0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1)], (1, 1): [(0, 1, 0), (0, 1, 1), (1, 1, 1), (1, 1, 0)],
        (2, -1): [(0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 0)], (2, 1): [(0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)],
    }
    for x, y, z in zip(*np.nonzero(filled)):
        for (axis, side), corners in quads.items():
            n = [x, y, z]
            n[axis] += side
            if filled[tuple(n)]:
                continue
            ids = [verts.setdefault((x + dx, y + dy, z + dz), len(verts)) for dx, dy, dz in corners]
            faces += [(ids[0], ids[1], ids[2]), (ids[0], ids[2], ids[3])]
    V = np.array(sorted(verts, key=verts.get), dtype=np.float64)
    return trimesh.Trimesh(vertices=V, faces=np.array(faces), process=False)


def _crystal() -> trimesh.Trimesh:
    """Elongated hexagonal crystal with pointed tips: convex hull of jittered prism and apex points."""
    rng = np.random.default_rng(3)
    ang = np.arange(6) * (np.pi / 3) + rng.uniform(-0.15, 0.15, 6)
    rad = 0.3 * rng.uniform(0.85, 1.15, 6)
    ring = np.stack([rad * np.cos(ang), rad * np.sin(ang), np.zeros(6)], axis=1)
    pts = [ring + [0, 0, -0.45], ring + [0, 0, 0.35], [[0.03, -0.02, -0.75]], [[-0.02, 0.04, 0.8]]]
    return trimesh.convex.convex_hull(np.concatenate(pts))
