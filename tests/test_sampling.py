"""Scene sampling: determinism (in process and across processes), layout, room, camera, materials."""

from __future__ import annotations

import hashlib
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from flowsynth.scene.assets import ROOM_WALLS, resolve_assets
from flowsynth.scene.config import BouncingThingsConfig
from flowsynth.errors import ConfigError
from flowsynth.scene.sampling import (
    OBJECT_CATEGORY_OFFSET,
    ROOM_CATEGORY,
    look_at,
    sample_layout,
    sample_scene,
    size_levels,
)

ROOT = Path(__file__).resolve().parents[1]
KIN = BouncingThingsConfig(width=64, height=48, num_frames=8, motion="kinematic", num_objects=(3, 9))
PHYS = BouncingThingsConfig(width=64, height=48, num_frames=6, num_objects=(3, 5), room_size=(5.0, 4.0, 3.0),
                            camera_clearance=1.0, object_size=(0.3, 0.6))


def scene_digest(scene) -> str:
    """sha256 over everything a scene holds: camera, poses, meshes, categories, assets, materials."""
    h = hashlib.sha256()
    h.update(scene.camera.K.tobytes())
    h.update(scene.world_T_cam.tobytes())
    for o in scene.objects:
        h.update(np.asarray(o.poses).tobytes())
        h.update(np.asarray(o.mesh.vertices).tobytes())
        h.update(np.asarray(o.mesh.faces).tobytes())
        h.update(repr((o.instance, o.category, o.asset, sorted(o.material.items()), o.background)).encode())
    h.update(repr((scene.lights, scene.render_seed)).encode())
    return h.hexdigest()


def test_same_seed_same_scene_bit_for_bit():
    for cfg in (KIN, PHYS):
        assert scene_digest(sample_scene(cfg, 0, 3)) == scene_digest(sample_scene(cfg, 0, 3))


def test_seed_and_index_both_matter_and_seed_zero_is_used():
    digests = {scene_digest(sample_scene(KIN, s, i)) for s in (0, 1) for i in (0, 1)}
    assert len(digests) == 4


def test_same_scene_in_another_process():
    code = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r}); sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_sampling import KIN, PHYS, scene_digest
        from flowsynth.scene.sampling import sample_scene
        print(scene_digest(sample_scene(KIN, 7, 2)), scene_digest(sample_scene(PHYS, 7, 2)))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, cwd=ROOT,
                         check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    theirs = out.stdout.split()[-2:]
    assert theirs == [scene_digest(sample_scene(KIN, 7, 2)), scene_digest(sample_scene(PHYS, 7, 2))]


@pytest.mark.parametrize("index", range(6))
def test_layout_objects_room_and_ids(index):
    cfg = KIN
    scene = sample_scene(cfg, 0, index)
    layout = sample_layout(cfg, 0, index)
    n = len(layout.assets)
    assert cfg.num_objects[0] <= n <= cfg.num_objects[1]
    assert len(scene.objects) == n + len(ROOM_WALLS)
    keys = resolve_assets(cfg.assets)
    for i, o in enumerate(scene.objects[:n]):
        assert o.instance == i + 1 and not o.background
        assert o.category == OBJECT_CATEGORY_OFFSET + int(layout.asset_index[i])
        assert keys[layout.asset_index[i]] == layout.assets[i].name
        assert "texture_seed" not in o.material and {"texture", "roughness", "specular", "seed"} <= set(o.material)
        assert o.source == {"asset": layout.assets[i].name, "size": layout.assets[i].size}
    walls = scene.objects[n:]
    for w, room in enumerate(walls):
        assert room.instance == n + 1 + w and room.category == ROOM_CATEGORY and room.background
        np.testing.assert_array_equal(room.poses, np.tile(np.eye(4), (cfg.num_frames, 1, 1)))
    bounds = np.concatenate([np.asarray(o.mesh.vertices) for o in walls])
    np.testing.assert_allclose([bounds.min(0), bounds.max(0)], cfg.room_bounds)
    assert scene.meta["seed"] == 0 and scene.meta["index"] == index
    assert BouncingThingsConfig.from_dict(scene.meta["config"]) == cfg


@pytest.mark.parametrize("index", range(6))
def test_initial_placement(index):
    cfg = KIN
    layout = sample_layout(cfg, 1, index)
    sizes = np.array([a.size for a in layout.assets])
    assert np.isin(sizes, size_levels(cfg)).all()
    p = layout.initial.position
    lo, hi = (np.asarray(b) for b in cfg.object_bounds)
    assert ((p - sizes[:, None] / 2 >= lo) & (p + sizes[:, None] / 2 <= hi)).all()
    d = np.linalg.norm(p[:, None] - p[None], axis=-1) + np.eye(len(p)) * 1e9
    assert (d >= (sizes[:, None] + sizes[None]) / 2).all(), "bounding spheres overlap"
    R = layout.initial.rotation
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    speed = np.linalg.norm(layout.initial.velocity, axis=1)
    assert ((speed >= cfg.min_speed) & (speed <= cfg.max_speed)).all()
    w = np.linalg.norm(layout.initial.angular_velocity, axis=1)
    assert ((w >= cfg.angular_speed[0]) & (w <= cfg.angular_speed[1])).all()


def test_objects_start_in_view_and_camera_in_its_zone():
    cfg = KIN
    in_view = total = 0
    for index in range(10):
        layout = sample_layout(cfg, 2, index)
        world_T_cam = layout.world_T_cam
        eye = world_T_cam[:, :3, 3]
        (x0, y0, z0), (_, y1, z1) = cfg.room_bounds
        assert (eye[:, 0] > x0).all() and (eye[:, 0] < x0 + cfg.camera_clearance).all()
        assert ((eye[:, 1:] > [y0, z0]) & (eye[:, 1:] < [y1, z1])).all()
        cam_T_world = np.linalg.inv(world_T_cam[0])
        pc = layout.initial.position @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]
        uv = (pc @ _K(cfg).T)[:, :2] / pc[:, 2:]
        ok = (pc[:, 2] > 0) & (uv >= 0).all(1) & (uv <= [cfg.width - 1, cfg.height - 1]).all(1)
        in_view += int(ok.sum())
        total += len(ok)
    assert in_view >= 0.9 * total


def _K(cfg):
    from flowsynth.scene.camera import Camera

    return Camera.from_fov(cfg.width, cfg.height, cfg.fov_deg).K


def test_look_at_uses_opencv_axes_with_world_up_up_in_the_image():
    T = look_at(np.array([0.0, 0.0, 1.0]), np.array([5.0, 0.0, 1.0]))
    np.testing.assert_allclose(T[:3, 2], [1, 0, 0])   # z forward
    np.testing.assert_allclose(T[:3, 0], [0, -1, 0])  # x right (world -y when looking along +x, z up)
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1])  # y down
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)


def test_moving_camera_speed_in_range_and_static_camera_still():
    cfg = BouncingThingsConfig(motion="static", camera_motion="moving", camera_speed=(0.5, 1.0),
                               num_frames=12, flow_px=None)
    eye = sample_layout(cfg, 0, 0).world_T_cam[:, :3, 3]
    step = np.linalg.norm(np.diff(eye, axis=0), axis=1) * cfg.fps
    assert step.max() <= 1.0 + 1e-9 and np.median(step) >= 0.5 - 1e-9
    static = sample_layout(BouncingThingsConfig(motion="static", camera_motion="static", num_frames=4), 0,
                           0).world_T_cam
    assert (static == static[0]).all()


def test_negative_seed_or_index_is_rejected():
    with pytest.raises(ConfigError, match="seed"):
        sample_scene(KIN, -1, 0)
    with pytest.raises(ConfigError, match="index"):
        sample_scene(KIN, 0, -2)
