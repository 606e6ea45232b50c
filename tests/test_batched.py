"""``fs.render_batch``, B scenes rendered as one batch on one device, against B single renders (the stream over it,
``fs.datasets.DeviceBatches``, is tested in test_device_batches).

On the CPU a batch of B scenes gives, scene by scene, exactly what B single renders give (``torch.equal``): every
kernel computes each pixel from the same inputs in the same steps, whether it runs over one clip or over the batch's
B T frames, in row bands (the CPU's shape) or a thread per pixel (the GPU's shape, run here on the CPU); the grouped
top-level BVH builds each frame's subtree from that frame's boxes alone. No output needs a tolerance: no summation
changes order. The recorder of tests/test_device.py shows the batch path on the ``cpu:twin`` device keeps every
array there and never reads a pixel into numpy.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import trimesh
from test_device import TWIN, Recorder, twin  # noqa: F401 (the fixture)

import flowsynth as fs
from flowsynth import parallel
from flowsynth.errors import ConfigError, ShapeError
from flowsynth.raycast import accel as accel_mod
from flowsynth.raycast import gbuffer as gbuffer_mod
from flowsynth.renderer import batch as batch_mod

CFG = fs.BouncingThingsConfig(width=48, height=36, num_frames=3, num_objects=(2, 6), flow_gaps=(1, 2))
KEYS = ["depth", "distance", "normals", "position", "instance", "category", "asset", "flow_fw", "flow_bw", "valid_fw",
        "valid_bw", "occ_fw", "occ_bw", "oof_fw", "oof_bw", "motion", "scene_flow_fw", "flow_fw_k2", "occ_bw_k2",
        "rgb", "K", "cam_T_world"]


@pytest.fixture(scope="module")
def scenes():
    ds = fs.datasets.BouncingThings(CFG, outputs=["depth"], seed=4)
    return [ds.scene(i) for i in range(3)]


def hand_scenes():
    """Three hand-built scenes of one camera: a sphere (no lights: the default lights, placed from the G-buffer's
    median hit distance, taken on the device in a batch), an empty scene, and two boxes, one passing the other."""
    T = 3
    cam = fs.Camera.from_fov(width=40, height=30, fov_deg=60.0)
    out = []
    for k in range(3):
        scene = fs.Scene(camera=cam, num_frames=T)
        scene.set_camera_poses(np.tile(np.eye(4), (T, 1, 1)))
        poses = np.tile(np.eye(4), (T, 1, 1))
        if k == 0:
            poses[:, :3, 3] = [[0.1 * t, 0.0, 4.0] for t in range(T)]
            scene.add_object(trimesh.creation.icosphere(subdivisions=2, radius=0.8), poses=poses, category=3)
        if k == 2:
            poses[:, :3, 3] = [[0.3 * t - 0.3, 0.0, 3.0] for t in range(T)]
            scene.add_object(trimesh.creation.box((0.6, 0.6, 0.6)), poses=poses, category=1)
            back = np.tile(np.eye(4), (T, 1, 1))
            back[:, :3, 3] = [0.0, 0.1, 5.0]
            scene.add_object(trimesh.creation.box((3.0, 2.0, 0.2)), poses=back, category=2)
        out.append(scene)
    return out


def assert_batch_equals_singles(scenes, keys, **opts):
    got = fs.render_batch(scenes, keys, **opts)
    assert list(got) == list(keys)
    for b, scene in enumerate(scenes):
        ref = fs.render(scene, keys, **opts)
        for k in keys:
            assert got[k].shape[0] == len(scenes), k
            assert torch.equal(got[k][b], ref[k]), (b, k)
    return got


def test_batch_equals_single_renders(scenes):
    """Every output the batch renders, flat rgb with silhouette samples, exact occlusion, frame gaps 1 and 2."""
    got = assert_batch_equals_singles(scenes, KEYS, edge_spp=4)
    assert got["flow_fw"].shape == (3, 2, 2, 36, 48) and got["flow_fw_k2"].shape == (3, 1, 2, 36, 48)
    assert got["rgb"].shape == (3, 3, 3, 36, 48) and got["cam_T_world"].shape == (3, 3, 4, 4)
    assert got["occ_fw"].any() and got["valid_fw"].any() and got["instance"].max() > 2


def test_batch_direct_rgb_and_depth_occlusion(scenes):
    """Shadow rays (direct mode), two samples a pixel, the depth-buffer occlusion test."""
    assert_batch_equals_singles(scenes, ["rgb", "occ_fw", "occ_bw"], render_mode="direct", spp=2, occlusion="depth")


def test_batch_of_hand_built_scenes():
    """Default lights (the median hit distance on the device), a scene with nothing in it, a batch of one."""
    scenes = hand_scenes()
    keys = ["rgb", "depth", "instance", "category", "flow_fw", "occ_fw", "motion", "position"]
    assert_batch_equals_singles(scenes, keys, render_mode="direct")
    assert_batch_equals_singles(scenes[1:2], keys)
    got = fs.render_batch(scenes[1], ["depth", "rgb"])  # one scene, not in a list
    assert got["depth"].shape == (1, 3, 1, 30, 40) and not got["depth"].any()


def test_gpu_launch_shape_gives_the_same_bits(scenes, monkeypatch):
    """A thread per pixel (the shape every image kernel takes on a GPU), run on the CPU: the batch and a single
    render both equal the row-band renders."""
    keys = ["depth", "normals", "flow_fw", "occ_fw", "motion", "position", "rgb"]
    ref = [fs.render(s, keys, render_mode="direct", edge_spp=4) for s in scenes]
    monkeypatch.setattr(parallel, "PIXEL_THREADS", True)
    got = fs.render_batch(scenes, keys, render_mode="direct", edge_spp=4)
    one = fs.render(scenes[0], keys, render_mode="direct", edge_spp=4)
    for k in keys:
        assert torch.equal(one[k], ref[0][k]), k
        for b in range(len(scenes)):
            assert torch.equal(got[k][b], ref[b][k]), (b, k)


@pytest.mark.parametrize("walk", ["every scene", "the largest scene"])
def test_batch_walking_the_bvh(scenes, monkeypatch, walk):
    """Camera and visibility rays that walk the grouped top-level BVH instead of the tile lists: those of every scene,
    or of the largest one only, beside scenes that walk their lists in the same batch."""
    counts = sorted(len(s.objects) for s in scenes)
    assert counts[0] < counts[-1], counts
    monkeypatch.setattr(accel_mod, "ORDERED_MAX", 0 if walk == "every scene" else counts[-1] - 1)
    assert_batch_equals_singles(scenes, ["depth", "instance", "flow_fw", "occ_fw", "occ_bw", "rgb"],
                                render_mode="direct")


def test_batch_path_stays_on_the_device(twin, scenes, monkeypatch):  # noqa: F811 (the fixture)
    """On ``cpu:twin``: every array allocated and every launch on the device asked for, no G-buffer handed to the
    host, no Warp array read into numpy (pixels never leave the device; only the face planes of a mesh not seen
    before come back once, as a table)."""
    keys = ["depth", "instance", "normals", "flow_fw", "occ_fw", "motion", "rgb"]
    ref = fs.render_batch(scenes, keys)
    rec = Recorder(monkeypatch)
    monkeypatch.setattr(batch_mod, "cast_gbuffer", gbuffer_mod.cast_gbuffer)  # the recorder's: it keeps the G-buffers
    got = fs.render_batch(scenes, keys, device=TWIN)
    assert rec.allocs and rec.launches and rec.gbuffers
    assert rec.violations(TWIN) == []
    assert all(gb._host is None for gb in rec.gbuffers)
    assert [who for _, who in rec.numpy_calls if who != "flowsynth.raycast.culling:_face_planes_of"] == []
    for prefix in ("pair_kernel", "world_points_kernel", "shade_kernel"):
        assert rec.launched_with_gbuffer(prefix), prefix
    for k in keys:
        assert torch.equal(got[k], ref[k]), k


def test_render_is_the_batch_of_one(scenes, monkeypatch):
    """``fs.render``'s batched keys are the very tensors ``batch_outputs`` made for its batch of one (the same
    memory), stereo's disparity change riding on the fw pass among them; the per-scene keys (object tables, stereo
    disparity, motion-blurred rgb) come from elsewhere."""
    from flowsynth.renderer import pipeline

    seen = []
    orig = pipeline.batch_outputs

    def record(batch_scenes, *args):
        out = orig(batch_scenes, *args)
        seen.append((len(batch_scenes), out))
        return out

    monkeypatch.setattr(pipeline, "batch_outputs", record)
    batched = ["depth", "instance", "flow_fw", "occ_bw", "motion", "rgb", "K", "disparity_change"]
    got = fs.render(scenes[0], [*batched, "box2d_visible", "disparity"], stereo_baseline=0.1)
    [(B, out)] = seen
    assert B == 1 and sorted(out) == sorted(batched)
    for k in batched:
        assert got[k].data_ptr() == out[k][0].data_ptr() and torch.equal(got[k], out[k][0]), k
    seen.clear()
    blurred = fs.render(scenes[0], ["depth", "rgb"], shutter=0.5)
    [(B, out)] = seen
    assert sorted(out) == ["depth"] and blurred["rgb"].shape == (3, 3, 36, 48)


def test_motion_blur_is_one_scene_at_a_time(scenes):
    from flowsynth.plan import make_plan
    from flowsynth.renderer import shading

    with pytest.raises(ConfigError, match="one scene at a time, got 2"):
        shading.render_rgb(scenes[:2], None, None, make_plan(["rgb"], shutter=0.5))


def test_bad_batches_say_what_to_do(scenes):
    small = fs.BouncingThingsConfig(width=32, height=24, num_frames=3)
    other = fs.datasets.BouncingThings(small, outputs=["depth"], seed=1).scene(0)
    with pytest.raises(ShapeError, match=r"one image size: scenes\[0\] is 48x36, scenes\[1\] 32x24"):
        fs.render_batch([scenes[0], other], ["depth"])
    short = fs.datasets.BouncingThings(dataclasses.replace(CFG, num_frames=2), outputs=["depth"], seed=1).scene(0)
    with pytest.raises(ShapeError, match="one frame count"):
        fs.render_batch([scenes[0], short], ["depth"])
    wide = fs.datasets.BouncingThings(dataclasses.replace(CFG, fov_deg=70.0), outputs=["depth"], seed=1).scene(0)
    with pytest.raises(ConfigError, match="one camera"):
        fs.render_batch([scenes[0], wide], ["depth"])
    with pytest.raises(ConfigError, match="at least one scene"):
        fs.render_batch([], ["depth"])
    with pytest.raises(ConfigError, match=r"does not render \['box2d_visible'\].*fs.render"):
        fs.render_batch(scenes, ["depth", "box2d_visible"])
    with pytest.raises(ConfigError, match="without motion blur"):
        fs.render_batch(scenes, ["rgb"], shutter=0.5)
    with pytest.raises(ConfigError, match=r"device 'cuda:7' is not available"):
        fs.render_batch(scenes, ["depth"], device="cuda:7")
