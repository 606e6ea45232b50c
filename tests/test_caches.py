"""Per-process caches have one owner: every module-level cache of flowsynth is registered in flowsynth.caches,
``fs.clear_caches()`` empties them all without changing any result, and the meshes a cache keys on are frozen so a
change to one raises instead of reusing what was cached for it."""

from __future__ import annotations

import ast
import importlib
import pkgutil
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from oracle import pose

import flowsynth as fs
from flowsynth import caches
from flowsynth.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]

# Module-level objects that look like caches and are not: clearing them frees nothing and can make nothing stale.
NOT_CACHES = {
    "flowsynth.caches._REGISTRY": "the registry itself",
    "flowsynth.io.layouts._REGISTRY": "the export layout plug-ins by name",
    "flowsynth.datasets.kinds._MIXTURE": "the mixture kind's classes, registered once at import (a registry)",
    "flowsynth.kernels._initialised_warp": "Warp's initialisation, once per process",
    "flowsynth.scene.physics._clamp_kernel": "a compiled Warp kernel (no argument)",
    "flowsynth._flags.field_docs": "the config's field docstrings, read once from the source (no argument)",
    "flowsynth.parallel._pools": "thread pools by size (a resource, not data)",
    "flowsynth.parallel._loaded": "which Warp kernels were loaded before a threaded launch (not data)",
}

_EMPTY_CONTAINERS = {"dict", "OrderedDict", "WeakKeyDictionary", "WeakValueDictionary", "set", "list", "defaultdict"}


def _call_name(node) -> str | None:
    f = node.func if isinstance(node, ast.Call) else node
    return f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None


def module_level_caches(source: str) -> list[str]:
    """Names of the module-level caches of ``source``: functions decorated with ``functools.cache`` /
    ``lru_cache``, and module-level containers that start empty (``{}``, ``dict()``, ``OrderedDict()``,
    ``WeakKeyDictionary()``, ``[]``, ``set()``; also inside a ``register(name, ...)`` call) to be filled at run
    time. Tables written out in the source are not caches."""
    found = []
    for node in ast.parse(source).body:
        if isinstance(node, ast.FunctionDef):
            if any(_call_name(d) in ("cache", "lru_cache") for d in node.decorator_list):
                found.append(node.name)
            continue
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            target, value = node.targets[0].id, node.value
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.value is not None:
            target, value = node.target.id, node.value
        else:
            continue
        if isinstance(value, ast.Call) and _call_name(value) == "register" and len(value.args) == 2:
            value = value.args[1]
        empty = ((isinstance(value, ast.Dict) and not value.keys) or (isinstance(value, ast.List) and not value.elts)
                 or (isinstance(value, ast.Call) and _call_name(value) in _EMPTY_CONTAINERS and not value.args
                     and not value.keywords))
        if empty:
            found.append(target)
    return found


def _all_modules() -> list[str]:
    return ["flowsynth"] + [m.name for m in pkgutil.walk_packages(fs.__path__, "flowsynth.")]


def test_finder_sees_caches_and_not_tables():
    src = ("import functools, weakref\nfrom collections import OrderedDict\nTABLE = {'a': 1}\nNAMES = ('x',)\n"
           "_A: dict = {}\n_B = OrderedDict()\n_C = weakref.WeakKeyDictionary()\n_D = register('d', OrderedDict())\n"
           "@functools.lru_cache(maxsize=4)\ndef f(x):\n    return x\n@functools.cache\ndef g():\n    return 1\n"
           "def h():\n    local = {}\n    return local\n")
    assert module_level_caches(src) == ["_A", "_B", "_C", "_D", "f", "g"]


def test_every_module_level_cache_is_registered():
    modules = {name: importlib.import_module(name) for name in _all_modules()}  # each registers its caches
    registered = {id(c) for c in caches.registered().values()}
    unregistered = []
    for name, mod in modules.items():
        for attr in module_level_caches(Path(mod.__file__).read_text()):
            full = f"{name}.{attr}"
            if full in NOT_CACHES:
                continue
            if id(getattr(mod, attr)) not in registered:
                unregistered.append(full)
    stale = [k for k in NOT_CACHES if not hasattr(importlib.import_module(k.rsplit(".", 1)[0]), k.rsplit(".", 1)[1])]
    assert not unregistered, ("module-level caches not registered in flowsynth.caches (register them where they are "
                              f"defined, or say in NOT_CACHES why one is no cache): {unregistered}")
    assert not stale, f"NOT_CACHES names objects that no longer exist: {stale}"
    assert len(caches.registered()) >= 16


def _size(cache) -> int:
    return cache.cache_info().currsize if hasattr(cache, "cache_info") else len(cache)


def _scene(tmp_path: Path) -> fs.Scene:
    """Two frames: a library asset, a user mesh from a file, the room's floor, a textured material."""
    from PIL import Image

    from flowsynth.scene.assets import get_asset, load_user_mesh, room_walls

    Image.fromarray((np.arange(48).reshape(4, 4, 3) * 5).astype(np.uint8)).save(tmp_path / "tex.png")
    trimesh.creation.icosphere(subdivisions=2).export(tmp_path / "ball.obj")
    cam = fs.Camera.from_fov(width=40, height=30, fov_deg=60.0)
    scene = fs.Scene(cam, num_frames=2)
    scene.add_object(get_asset("torus", 0.8).mesh, np.stack([pose(t=(0.3 * k, 0.0, 4.0)) for k in range(2)]),
                     source={"asset": "torus", "size": 0.8},
                     material={"texture": "image", "image": str(tmp_path / "tex.png")})
    scene.add_object(load_user_mesh(str(tmp_path / "ball.obj")), pose(t=(-0.8, 0.2, 5.0)), category=2)
    scene.add_object(room_walls((-5.0, -5.0, -1.0), (5.0, 5.0, 9.0))[0], background=True)
    return scene


def test_clear_caches_empties_every_registered_cache_and_changes_no_result(tmp_path):
    from flowsynth.scene import camerapath

    for name in _all_modules():  # every cache registered
        importlib.import_module(name)
    outputs = ["depth", "instance", "flow_fw", "occ_fw", "rgb"]
    scene = _scene(tmp_path)
    before = fs.render(scene, outputs, render_mode="flat")
    camerapath._probe_rays(40, 30, 60.0)
    filled = {n for n, c in caches.registered().items() if _size(c) > 0}
    expected = {"assets.get_asset", "assets.builtin_unit", "assets.user_meshes", "assets.room_walls",
                "meshes.library", "culling.mesh_keys", "culling.hulls", "culling.face_planes", "blas.topology",
                "blas.topology_of_mesh", "camera.pixel_rays", "camerapath.probe_rays", "textures.images",
                "textures.mip_pyramids"}
    assert expected <= filled, f"the workload did not fill {sorted(expected - filled)}"
    assert fs.clear_caches() == sorted(caches.registered())
    assert {n: _size(c) for n, c in caches.registered().items() if _size(c)} == {}
    after = fs.render(_scene(tmp_path), outputs, render_mode="flat")  # everything rebuilt from nothing
    for k in outputs:
        assert torch.equal(before[k], after[k]), k


def test_clear_caches_by_name_and_bad_names():
    from flowsynth.scene.assets import get_asset, unit_hull

    get_asset("box", 0.5)
    unit_hull("box")
    assert fs.clear_caches("assets.get_asset") == ["assets.get_asset"]
    assert get_asset.cache_info().currsize == 0 and unit_hull.cache_info().currsize > 0
    with pytest.raises(ConfigError, match="no cache named"):
        fs.clear_caches("assets.nothing")
    with pytest.raises(TypeError, match="clear"):
        caches.register("test.not_a_cache", object())
    assert "test.not_a_cache" not in caches.registered()


def test_cached_meshes_are_frozen(tmp_path):
    from flowsynth.raycast.accel import SceneAccel
    from flowsynth.scene.assets import get_asset, unit_hull

    lib = get_asset("cone", 0.6)
    for mesh in (lib.mesh, lib.collider.hull, unit_hull("rock")):
        with pytest.raises(ValueError, match="read-only"):
            mesh.vertices[0, 0] += 1.0
        with pytest.raises(ValueError, match="read-only"):
            mesh.faces[0] = mesh.faces[1]
    scene = _scene(tmp_path)
    for o in scene.objects:
        with pytest.raises(ValueError, match="read-only"):
            o.mesh.vertices *= 2.0
    # a mesh handed straight to the ray caster is frozen when it is cached: in place and by new arrays alike
    mine = trimesh.creation.box()
    SceneAccel([mine], np.eye(4)[None], np.stack([pose(t=(0.0, 0.0, 3.0))])[None])
    with pytest.raises(ValueError, match="read-only"):
        mine.vertices[0, 0] = 9.0
    with pytest.raises(ValueError, match="immutable"):
        mine.vertices = np.zeros((8, 3))
    # a copy is the way to change one
    changed = lib.mesh.copy()
    changed.vertices[0, 0] += 1.0
    assert changed.vertices[0, 0] != lib.mesh.vertices[0, 0]


def test_a_scene_keeps_its_own_copy_of_a_user_mesh():
    """The user's mesh stays theirs (writable); the scene's cleaned copy shares no memory with it, so changing
    the user's mesh afterwards changes neither the scene nor what the caches hold for it."""
    user = trimesh.creation.icosphere(subdivisions=1)
    scene = fs.Scene(fs.Camera.from_fov(width=16, height=12, fov_deg=60.0), num_frames=1)
    scene.add_object(user, pose(t=(0.0, 0.0, 3.0)))
    kept = scene.objects[0].mesh
    assert not np.shares_memory(kept.vertices, user.vertices) and not np.shares_memory(kept.faces, user.faces)
    v0 = np.array(kept.vertices)
    user.vertices[:] *= 2.0  # allowed: the user's own mesh
    np.testing.assert_array_equal(kept.vertices, v0)


def test_specialised_kernels_are_built_once_per_combination_of_flags():
    """The primary, pair and shading kernels come from one registered cache (kernels.specialised): the same flags
    (defaults filled in) give the same kernel object, other flags another; cleared, a builder returns Warp's same
    kernel again (Warp keeps module="unique" kernels by content)."""
    from flowsynth.kernels.raycast import primary_kernel
    from flowsynth.kernels.reproject import pair_kernel
    from flowsynth.kernels.shade import shade_kernel
    from flowsynth.kernels.specialise import KERNELS

    assert caches.registered()["kernels.specialised"] is KERNELS
    a = primary_kernel(True, False)
    assert primary_kernel(True, False, False) is a and primary_kernel(True, False, lens=True) is not a
    assert pair_kernel(True, 1, False) is pair_kernel(True, 1, False, False, 0) is not pair_kernel(True, 2, False)
    assert shade_kernel("flat") is shade_kernel("flat", False) is not shade_kernel("direct")
    n = len(KERNELS)
    assert n >= 6
    fs.clear_caches("kernels.specialised")
    assert len(KERNELS) == 0 and primary_kernel(True, False) is a
