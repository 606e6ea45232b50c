"""Camera paths (pan, tilt, roll, moving look-at target, bounds), flow set in pixels, presets.

Oracles: relative rotations between frames read back with scipy, geometry of look_at, and the flow the
renderer produces (measured, not derived from the speed formula).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import flowsynth as fs
from flowsynth.cli import main
from flowsynth.scene.config import PRESETS, BouncingThingsConfig
from flowsynth.errors import ConfigError
from flowsynth.scene.sampling import ROOM_CATEGORY, sample_layout

# Physical units (flow_px=None), one mechanism at a time, nothing else moving.
STILL = dict(motion="static", num_frames=12, flow_px=None, camera_motion="moving", camera_speed=(0.0, 0.0),
             camera_target_speed=(0.0, 0.0), camera_pan=0.0, camera_tilt=0.0, camera_roll=0.0,
             camera_angle_limit=(1.5, 1.5, 1.5))


def _relative_rotvecs(world_T_cam: np.ndarray) -> np.ndarray:
    """(T-1, 3) rotation vectors of cam_k_R_cam_k+1, in camera k's axes [rad]."""
    R = world_T_cam[:, :3, :3]
    return Rotation.from_matrix(np.swapaxes(R[:-1], 1, 2) @ R[1:]).as_rotvec()


@pytest.mark.parametrize("axis, field", [(1, "camera_pan"), (0, "camera_tilt"), (2, "camera_roll")])
def test_each_rotation_turns_about_its_camera_axis_within_its_bound(axis, field):
    rates = []
    for index in range(6):
        limit = tuple(1.5 * (i == axis) for i in (1, 0, 2))  # other offsets 0: each turns about its own axis
        cfg = BouncingThingsConfig(**{**STILL, field: 0.8, "camera_angle_limit": limit})
        T = sample_layout(cfg, 0, index).world_T_cam
        np.testing.assert_allclose(T[:, :3, 3], T[:1, :3, 3].repeat(len(T), 0), atol=0)  # the eye stays
        w = _relative_rotvecs(T) * cfg.fps  # [rad/s]
        others = np.delete(w, axis, axis=1)
        np.testing.assert_allclose(others, 0.0, atol=1e-9)
        assert np.abs(w[:, axis]).max() <= 0.8 + 1e-9
        rates.append(abs(w[0, axis]))
    assert max(rates) > 0.3, "rates are drawn from [-bound, bound]"


def test_rotation_offsets_stay_inside_the_angle_limit():
    cfg = BouncingThingsConfig(**{**STILL, "camera_pan": 3.0, "camera_tilt": 3.0, "camera_roll": 3.0,
                                  "camera_angle_limit": (0.2, 0.1, 0.3), "num_frames": 48})
    base = BouncingThingsConfig(**{**STILL, "camera_angle_limit": (0.0, 0.0, 0.0)})
    for index in range(3):
        T = sample_layout(cfg, 0, index).world_T_cam
        look = sample_layout(base, 0, index).world_T_cam[0, :3, :3]  # same eye and target: the look-at frame
        pan, tilt, roll = Rotation.from_matrix(look.T @ T[:, :3, :3]).as_euler("YXZ").T  # R = Ry Rx Rz
        assert np.abs(pan).max() <= 0.2 + 1e-9 and np.abs(tilt).max() <= 0.1 + 1e-9
        assert np.abs(roll).max() <= 0.3 + 1e-9
        assert np.ptp(pan) > 0.2, "the pan offset sweeps its range"


def test_moving_target_turns_the_camera_without_roll():
    cfg = BouncingThingsConfig(**{**STILL, "camera_target_speed": (1.0, 2.0), "camera_angle_limit": (0, 0, 0)})
    T = sample_layout(cfg, 0, 1).world_T_cam
    x, z = T[:, :3, 0], T[:, :3, 2]
    np.testing.assert_allclose(x[:, 2], 0.0, atol=1e-12)  # image x stays horizontal: look-at, no roll
    angle = np.arccos(np.clip((z[1:] * z[:-1]).sum(1), -1, 1))
    assert (angle > 0).all()
    eye_to_objects = np.linalg.norm(np.asarray(cfg.object_bounds).mean(0) - T[0, :3, 3])
    assert angle.max() * cfg.fps <= 2.0 / (eye_to_objects - 5.0) + 1e-9  # a 2 m/s target seen from > 5 m


def test_planar_motion_moves_parallel_to_the_first_image_plane():
    cfg = BouncingThingsConfig(motion="kinematic", num_frames=2, planar_motion=True, flow_px=None,
                               camera_target_speed=(0.0, 0.0), camera_pan=0.0, camera_tilt=0.0, camera_roll=0.0)
    for index in range(4):
        layout = sample_layout(cfg, 0, index)
        forward = layout.world_T_cam[0, :3, 2]
        np.testing.assert_allclose(layout.initial.velocity @ forward, 0.0, atol=1e-12)
        eye_step = layout.world_T_cam[1, :3, 3] - layout.world_T_cam[0, :3, 3]
        assert abs(eye_step @ forward) <= 1e-12 + 1e-9 * np.linalg.norm(eye_step)


@pytest.mark.parametrize("flow_px", [(2.0, 3.0), (6.0, 9.0)])
def test_rendered_median_flow_lands_in_the_requested_range(flow_px):
    """flow_px in the rendered image's pixels (flow_px_width = width); tests/test_motion_width.py scales it."""
    cfg = BouncingThingsConfig(width=96, height=72, num_frames=2, motion="kinematic", flow_px=flow_px,
                               flow_px_width=96)
    ds = fs.datasets.BouncingThings(cfg, outputs=["flow_fw", "valid_fw", "category"], seed=5)
    pooled = []
    for i in range(4):
        s = ds.sample(i)
        valid, room = s["valid_fw"][0, 0].numpy(), s["category"][0, 0].numpy() == ROOM_CATEGORY
        mag = s["flow_fw"][0].double().norm(dim=0).numpy()
        pooled.append(mag[valid])
        # the camera's target is met on the room; objects add their own motion and parallax
        assert flow_px[0] <= np.median(mag[valid & room]) <= flow_px[1], (i, np.median(mag[valid & room]))
        meta = ds.scene(i).meta["motion"]
        assert flow_px[0] <= meta["camera_flow_px"] <= flow_px[1]
        assert meta["camera_flow_px_achieved"] == pytest.approx(meta["camera_flow_px"], rel=0.02)
    assert flow_px[0] <= np.median(np.concatenate(pooled)) <= flow_px[1]


def test_pixel_targets_scale_with_the_request():
    # no speed clip at either end: at 320 px wide the 1 px target (at 512) is 0.625 px, slower than min_speed's 0.1
    lo = BouncingThingsConfig(motion="kinematic", num_frames=2, flow_px=(1.0, 1.0), min_speed=0.0, max_speed=100.0)
    hi = BouncingThingsConfig(motion="kinematic", num_frames=2, flow_px=(8.0, 8.0), min_speed=0.0, max_speed=100.0)
    for index in range(3):
        a, b = sample_layout(lo, 0, index), sample_layout(hi, 0, index)
        np.testing.assert_allclose(b.initial.velocity, 8.0 * a.initial.velocity, rtol=1e-12)


def test_presets():
    things = BouncingThingsConfig.preset("things")
    assert things.num_objects == (5, 20) and things.camera_motion == "moving" and things.spawn_margin < 0
    assert min(things.camera_pan, things.camera_tilt, things.camera_roll) > 0
    chairs = BouncingThingsConfig.preset("chairs", width=64)
    assert chairs.planar_motion and chairs.width == 64 and chairs.num_frames == 2
    assert BouncingThingsConfig.preset("default") == BouncingThingsConfig()
    assert set(PRESETS) >= {"default", "chairs", "things"}
    with pytest.raises(ConfigError, match="preset"):
        BouncingThingsConfig.preset("sintel")
    with pytest.raises(ConfigError):
        BouncingThingsConfig(camera_pan=-1.0)
    with pytest.raises(ConfigError):
        BouncingThingsConfig(flow_px=(0.0, 4.0))
    with pytest.raises(ConfigError):
        BouncingThingsConfig(spawn_margin=0.5)


def test_things_objects_start_near_and_partly_out_of_frame():
    cfg = BouncingThingsConfig.preset("things", width=192, height=108)
    K = fs.Camera.from_fov(cfg.width, cfg.height, cfg.fov_deg).K
    outside = near = total = 0
    for index in range(6):
        layout = sample_layout(cfg, 0, index)
        cam_T_world = np.linalg.inv(layout.world_T_cam[0])
        pc = layout.initial.position @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]
        uv = (pc @ K.T)[:, :2] / pc[:, 2:]
        outside += int(((uv < 0) | (uv > [cfg.width - 1, cfg.height - 1])).any(1).sum())
        near += int((pc[:, 2] < 2.0).sum())
        total += len(pc)
    assert total >= 6 * 5 and outside > 0 and near > 0


def test_cli_preset_flag_and_overrides(tmp_path, capsys):
    out = tmp_path / "s.json"
    assert main(["stats", "--preset", "chairs", "--num", "1", "--width", "48", "--height", "32",
                 "--json", str(out)]) == 0
    cfg = json.loads(out.read_text())["config"]
    assert cfg["planar_motion"] is True and cfg["width"] == 48 and cfg["flow_px"] == list(PRESETS["chairs"]["flow_px"])
    assert main(["stats", "--preset", "nope", "--num", "1"]) == 2
