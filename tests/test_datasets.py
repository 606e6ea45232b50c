"""Streaming dataset: determinism across workers/start methods, resume, shapes, sharding."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader
from torchdata.stateful_dataloader import StatefulDataLoader

import flowsynth as fs
from flowsynth.datasets.bouncing import BouncingThings
from flowsynth.datasets.stream import shard_indices

CFG = fs.BouncingThingsConfig(width=32, height=24, num_frames=2, motion="kinematic", num_objects=(2, 4),
                              max_objects=4)
ROOT = Path(__file__).resolve().parents[1]
# Longest wait for one batch from worker processes [s]: a worker's first sample may compile kernels (a cold Warp
# cache: Newton's take about a minute), so generous; it turns a stuck worker into an error instead of a stalled
# run (a fork-context run hung once in a fresh clone, 2026-11-25, and could not be reproduced).
LOADER_TIMEOUT = 600
OUTS = ["depth", "flow_fw", "valid_fw", "occ_fw", "instance", "box2d_visible", "object_valid"]


def assert_sample_equal(a: dict, b: dict):
    assert set(a) == set(b)
    for k in a:
        if k == "provenance":  # the scene record: a JSON string (tests/test_provenance.py)
            assert isinstance(a[k], str) and a[k] == b[k]
            continue
        assert a[k].dtype == b[k].dtype, k
        assert torch.equal(a[k], b[k]), k


def unbatch(batch: dict, j: int) -> dict:
    return {k: v[j] for k, v in batch.items()}


def first_items(loader, n):
    out = []
    for batch in loader:
        out += [unbatch(batch, j) for j in range(len(batch["index"]))]
        if len(out) >= n:
            return out[:n]
    return out


@pytest.mark.parametrize("ctx", ["fork", "spawn"])
def test_workers_match_sample_and_single_process(ctx):
    ds = BouncingThings(CFG, outputs=OUTS, seed=5, length=6)
    multi = first_items(DataLoader(ds, batch_size=2, num_workers=2, multiprocessing_context=ctx,
                                   timeout=LOADER_TIMEOUT), 6)
    single = first_items(DataLoader(ds, batch_size=2, num_workers=0), 6)
    assert sorted(int(s["index"]) for s in multi) == list(range(6))
    by_index = {int(s["index"]): s for s in single}
    for s in multi:
        i = int(s["index"])
        assert_sample_equal(s, by_index[i])
        assert_sample_equal(s, ds.sample(i))
        assert int(s["seed"]) == 5


def test_keys_shapes_dtypes_follow_design():
    T, H, W, N = CFG.num_frames, CFG.height, CFG.width, CFG.max_objects
    expect = {
        "depth": ((T, 1, H, W), torch.float32), "distance": ((T, 1, H, W), torch.float32),
        "normals": ((T, 3, H, W), torch.float32), "position": ((T, 3, H, W), torch.float32),
        "instance": ((T, 1, H, W), torch.int32), "category": ((T, 1, H, W), torch.int32),
        "asset": ((T, 1, H, W), torch.int32),
        "flow_fw": ((T - 1, 2, H, W), torch.float32), "flow_bw": ((T - 1, 2, H, W), torch.float32),
        "valid_fw": ((T - 1, 1, H, W), torch.bool), "occ_bw": ((T - 1, 1, H, W), torch.bool),
        "oof_fw": ((T - 1, 1, H, W), torch.bool), "motion": ((T - 1, 1, H, W), torch.bool),
        "K": ((3, 3), torch.float32), "cam_T_world": ((T, 4, 4), torch.float32),
        "object_valid": ((N,), torch.bool), "object_category": ((N,), torch.int32),
        "world_T_obj": ((T, N, 4, 4), torch.float32), "box3d_corners": ((T, N, 8, 3), torch.float32),
        "box2d_amodal": ((T, N, 4), torch.float32), "box2d_visible": ((T, N, 4), torch.float32),
        "visible_pixels": ((T, N), torch.int32), "index": ((), torch.int64), "seed": ((), torch.int64),
    }
    subsets = [["depth"], ["flow_fw", "occ_bw", "motion"], [k for k in expect if k not in ("index", "seed")],
               ["depth", "provenance"]]
    for outs in subsets:
        s = BouncingThings(CFG, outputs=outs, seed=1).sample(3)
        assert set(s) == set(outs) | {"index", "seed"}  # what was asked, and index and seed: nothing else
        if "provenance" in outs:
            assert isinstance(s.pop("provenance"), str)
        for k, v in s.items():
            assert (tuple(v.shape), v.dtype) == expect[k], k
            if v.is_floating_point():
                assert torch.isfinite(v).all(), k


def test_meta_and_all_name_the_metadata_and_everything():
    """A sample holds no metadata unless asked: "meta" adds K and cam_T_world (the scene's camera, as float32) and
    provenance (the scene's record); "all" is every output (stereo only with a baseline) and the metadata, the same
    tensors as the outputs named one by one; a Layers stream's "meta" is its provenance, and K is refused there; a
    DeviceBatches batch holds what it was asked, and "all" is every key a batch renders."""
    from flowsynth.plan import CORE_OUTPUTS, FINAL_KEYS, SCENE_FLOW_KEYS, STEREO_KEYS, TRACK_KEYS
    from flowsynth.renderer import BATCH_KEYS
    from flowsynth.scene import provenance_json

    ds = BouncingThings(CFG, outputs=["rgb", "meta"], seed=1)
    s, scene = ds.sample(2), ds.scene(2)
    assert set(s) == {"rgb", "K", "cam_T_world", "provenance", "index", "seed"}
    assert torch.equal(s["K"], torch.from_numpy(scene.camera.K.astype(np.float32)))
    assert torch.equal(s["cam_T_world"], torch.from_numpy(scene.cam_T_world.astype(np.float32)))
    assert s["provenance"] == provenance_json(scene)
    assert set(BouncingThings(CFG, outputs=["rgb", "K"], seed=1).sample(2)) == {"rgb", "K", "index", "seed"}
    named = [*CORE_OUTPUTS, *SCENE_FLOW_KEYS, *TRACK_KEYS, *FINAL_KEYS, "provenance"]
    every, one_by_one = BouncingThings(CFG, "all", seed=1).sample(2), BouncingThings(CFG, named, seed=1).sample(2)
    assert set(every) == set(one_by_one) == {*named, "index", "seed"}
    for k in ("rgb", "flow_fw", "box2d_visible", "target_points", "rgb_final"):
        assert torch.equal(every[k], one_by_one[k]), k
    stereo = fs.BouncingThingsConfig(**{**CFG.to_dict(), "stereo_baseline": 0.1})
    assert set(STEREO_KEYS) <= set(BouncingThings(stereo, ["all"]).outputs)
    layers = fs.datasets.LayersConfig(width=32, height=32, texture_bank=2)
    assert set(fs.datasets.Layers(layers, ["rgb", "meta"]).sample(0)) == {"rgb", "provenance", "index", "seed"}
    assert set(fs.datasets.Layers(layers, ["all"]).sample(0)) == {*fs.datasets.LAYERS_OUTPUTS, "provenance",
                                                                  "index", "seed"}
    with pytest.raises(fs.ConfigError, match="Layers sample has no"):
        fs.datasets.Layers(layers, ["rgb", "K"])
    batch = next(iter(fs.datasets.DeviceBatches(CFG, ["depth"], 2, seed=1, length=2)))
    assert set(batch) == {"depth", "index", "seed"}
    batch = next(iter(fs.datasets.DeviceBatches(CFG, ["all"], 2, seed=1, length=2)))
    assert set(batch) == {*BATCH_KEYS, "provenance", "index", "seed"} and len(batch["provenance"]) == 2


def test_unknown_output_and_bad_arguments():
    with pytest.raises(fs.ConfigError, match="valid outputs"):
        BouncingThings(CFG, outputs=["flow"])
    with pytest.raises(fs.ConfigError):
        BouncingThings(CFG, seed=-1)
    with pytest.raises(fs.ConfigError):
        BouncingThings(CFG, length=0)
    with pytest.raises(fs.ConfigError, match="num_frames"):
        BouncingThings(fs.BouncingThingsConfig(num_frames=1), outputs=["flow_fw"])


def test_resume_with_stateful_dataloader():
    ds = BouncingThings(CFG, outputs=["depth", "instance"], seed=2)
    kw = dict(batch_size=2, num_workers=2, timeout=LOADER_TIMEOUT)
    full = StatefulDataLoader(ds, **kw)
    it = iter(full)
    reference = [next(it) for _ in range(5)]
    del it
    first = StatefulDataLoader(BouncingThings(CFG, outputs=["depth", "instance"], seed=2), **kw)
    it = iter(first)
    for _ in range(2):
        next(it)
    state = first.state_dict()
    del it
    resumed = StatefulDataLoader(BouncingThings(CFG, outputs=["depth", "instance"], seed=2), **kw)
    resumed.load_state_dict(state)
    it = iter(resumed)
    for ref in reference[2:]:
        got = next(it)
        assert torch.equal(got["index"], ref["index"])
        assert torch.equal(got["depth"], ref["depth"])


def test_endless_stream_does_not_repeat_across_epochs():
    ds = BouncingThings(CFG, outputs=["depth"], seed=0)
    seen = []
    for _ in range(2):  # two "epochs" of an endless stream on the same object
        for n, s in enumerate(ds):
            seen.append(int(s["index"]))
            if n == 2:
                break
    assert seen == list(range(6))
    finite = BouncingThings(CFG, outputs=["depth"], seed=0, length=3)
    epochs = [[int(s["index"]) for s in finite] for _ in range(2)]
    assert epochs == [[0, 1, 2], [3, 4, 5]]
    loader = DataLoader(finite, batch_size=None, num_workers=2, persistent_workers=True, timeout=LOADER_TIMEOUT)
    finite.set_epoch(0)
    e0 = sorted(int(s["index"]) for s in loader)
    e1 = sorted(int(s["index"]) for s in loader)
    assert e0 == [0, 1, 2] and e1 == [3, 4, 5]


def test_shards_cover_every_index_once():
    for G in (1, 2, 3, 8, 64):
        got = sorted(i for g in range(G) for i, _ in shard_indices(0, 50, g, G, epoch=1, pos=0))
        assert got == list(range(50, 100))


CUDA_SPY = """
import sys
import torch
import warp._src.context as wc

calls = []

def spy(mod, name):
    orig = getattr(mod, name)
    def wrapped(*a, **k):
        calls.append(f"torch.cuda.{name}")
        return orig(*a, **k)
    setattr(mod, name, wrapped)

# Every way into torch's CUDA runtime goes through one of these (tensor creation on "cuda" calls _lazy_init).
for name in ("_lazy_init", "init", "is_available", "device_count", "current_device", "set_device"):
    spy(torch.cuda, name)
get_device = wc.Runtime.get_device

def warp_device(self, ident=None):
    if str(ident).startswith("cuda"):
        calls.append(f"warp {ident}")
    d = get_device(self, ident)
    if d.is_cuda:
        calls.append(f"warp {d}")
    return d

wc.Runtime.get_device = warp_device
import flowsynth as fs

cfg = fs.BouncingThingsConfig(width=32, height=24, num_frames=2, num_objects=(2, 3), render_mode="direct")
fs.datasets.BouncingThings(cfg, outputs=["rgb", "depth", "flow_fw", "occ_fw", "box2d_visible"]).sample(0)
print("run", sorted(set(calls)))
calls.clear()
for make in (lambda: torch.zeros(1, device="cuda"), lambda: wc.runtime.get_device("cuda:0")):
    try:
        make()
    except Exception:
        pass
print("control", sorted(set(calls)))
"""


def test_cpu_run_never_initialises_cuda():
    # A fresh interpreter spies on every entry into torch's CUDA runtime and on every Warp device that is
    # resolved, then runs a physics sample with RGB, flow, occlusion and boxes. The control shows that the
    # spies do see a CUDA request (on a CPU-only machine the request fails, but is still recorded).
    out = subprocess.run([sys.executable, "-c", CUDA_SPY], capture_output=True, text=True, timeout=600,
                         cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = dict(line.split(" ", 1) for line in out.stdout.splitlines() if line.startswith(("run ", "control ")))
    assert lines["run"] == "[]", f"a CPU run touched CUDA: {lines['run']}"
    assert "torch.cuda._lazy_init" in lines["control"] and "warp cuda:0" in lines["control"], lines["control"]


def test_flow_pairs_adapter_matches_torchvision_convention():
    from PIL import Image

    pairs = fs.datasets.FlowPairs(CFG, seed=0, length=4)
    img1, img2, flow, valid = pairs[1]
    assert isinstance(img1, Image.Image) and img1.size == (CFG.width, CFG.height) and img1.mode == "RGB"
    assert flow.shape == (2, CFG.height, CFG.width) and flow.dtype == np.float32
    assert valid.shape == (CFG.height, CFG.width) and valid.dtype == bool
    s = BouncingThings(CFG, outputs=["flow_fw"], seed=0).sample(1)
    np.testing.assert_array_equal(flow, s["flow_fw"][0].numpy())
    with pytest.raises(IndexError):
        pairs[4]


def test_flow_pairs_masks_valid_includes_occluded_and_visible_excludes_it():
    cfg = fs.BouncingThingsConfig(width=48, height=32, num_frames=2, motion="kinematic", num_objects=(8, 10),
                                  camera_motion="moving")
    s = BouncingThings(cfg, outputs=["valid_fw", "occ_fw"], seed=0).sample(2)
    valid, occ = s["valid_fw"][0, 0].numpy(), s["occ_fw"][0, 0].numpy()
    assert (valid & occ).any(), "the check needs a sample with occluded pixels"
    *_, default = fs.datasets.FlowPairs(cfg, seed=0, length=4)[2]
    *_, visible = fs.datasets.FlowPairs(cfg, seed=0, length=4, mask="visible")[2]
    np.testing.assert_array_equal(default, valid)
    np.testing.assert_array_equal(visible, valid & ~occ)
    with pytest.raises(fs.ConfigError):
        fs.datasets.FlowPairs(cfg, mask="noc")
