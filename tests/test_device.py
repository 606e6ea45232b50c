"""One device from scene to tensors (issue 40, part 1): every stage allocates and launches on the device asked for,
and the G-buffer stays in Warp arrays between stages.

This machine has only Warp's CPU, so a stage that writes "cpu" where it should pass the device on would look the
same as one that passes it on. The tests therefore register a second CPU device, ``cpu:twin`` (the same host
memory and kernels, another alias), render on it, and record the device alias of every Warp array allocated and
every launch: anything on plain "cpu" is a stage that chose its own device. Where CUDA is present the same walk
runs on "cuda" as well.

The recorder patches ``warp.array.__init__`` (every allocation: ``wp.array``, ``wp.empty``, ``wp.zeros``,
``wp.full``; not the host array Warp stages numpy data through inside another array's construction, as it does
for any device but "cpu"), ``warp.array.numpy`` and ``warp.launch``, and wraps ``cast_gbuffer`` to know the
G-buffers. It reports (``Recorder.violations``):

- an array allocated on another device than the one asked for (with the flowsynth function that did it);
- a launch on another device, or with an array argument on another device;
- a G-buffer array read into numpy anywhere but ``GBuffer.host()`` (the one hand-over to the host stages);
- a Warp array made from numpy memory of a G-buffer (a round trip through numpy between stages).

``test_recorder_catches_*`` make it fail on purpose with tiny fake stages.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import flowsynth as fs
from flowsynth.raycast import gbuffer as gbuffer_mod
from flowsynth.renderer import pipeline as renderer_mod
from flowsynth.errors import ConfigError
from flowsynth.kernels import wp_runtime

wp = wp_runtime()
REPO = Path(__file__).resolve().parents[1]
PKG = str(REPO / "flowsynth")
TWIN = "cpu:twin"

# Every stage the renderer runs, in two renders (the plan's occlusion method is one per render).
KEYS_A = ["depth", "distance", "normals", "position", "instance", "category", "asset", "flow_fw", "valid_fw",
          "occ_fw", "oof_fw", "flow_bw", "occ_bw", "scene_flow_fw", "motion", "rgb", "rgb_final", "disparity",
          "disparity_change", "depth_right", "disparity_right", "disparity_occ", "disparity_occ_right", "rgb_right",
          "target_points", "occluded", "box2d_visible", "visible_pixels", "box2d_amodal", "K"]
OPTS_A = dict(stereo_baseline=0.2, edge_spp=4, num_tracks=16, final_dof_prob=1.0, final_fog_density=0.05,
              final_shot_noise=(0.001, 0.002), final_time_samples=2)
KEYS_B = ["depth", "flow_fw", "occ_fw", "rgb"]
OPTS_B = dict(occlusion="depth", spp=2, shutter=0.5)


@pytest.fixture(scope="module")
def twin():
    """A second Warp device on the CPU, alias ``cpu:twin`` (Warp's Device for the host, registered under another
    name; removed afterwards)."""
    from warp._src import context

    rt = context.runtime
    rt.device_map[TWIN] = context.Device(rt, TWIN)
    yield TWIN
    del rt.device_map[TWIN]


def _alias(device) -> str:
    return str(device) if device is not None else str(wp.get_device())


def _flatten(args) -> list:
    """Launch arguments with every Warp struct (a parameter block, ``Instances``) replaced by its fields, nested
    structs included, so the arrays a struct carries are checked like arrays passed alone."""
    out = []
    for a in args:
        if isinstance(a, wp.array) or not hasattr(a, "_ctype"):  # a Warp struct instance has a ctypes mirror
            out.append(a)
        else:
            out += _flatten([v for k, v in vars(a).items() if not k.startswith("_")])
    return out


def _caller() -> str:
    """The innermost flowsynth function on the stack (module:function), or the test's."""
    f = sys._getframe(2)
    while f is not None:
        name = f.f_code.co_filename
        if name.startswith(PKG) and not name.endswith("test_device.py"):
            rel = Path(name).relative_to(REPO).with_suffix("")
            return f"{'.'.join(rel.parts)}:{f.f_code.co_name}"
        f = f.f_back
    return "(test)"


class Recorder:
    """Records allocations, launches, ``.numpy()`` calls and the G-buffers cast while installed."""

    def __init__(self, monkeypatch):
        self.allocs: list[tuple[str, str, object]] = []  # (device alias, caller, numpy data or None)
        self.launches: list[tuple[str, str, str, list]] = []  # (kernel, device alias, caller, args)
        self.numpy_calls: list[tuple[int, str]] = []  # (id of the array, caller)
        self.gbuffers: list = []
        self._depth = 0
        rec = self
        orig_init, orig_numpy, orig_launch = wp.array.__init__, wp.array.numpy, wp.launch
        orig_cast = gbuffer_mod.cast_gbuffer

        def init(self_, *args, **kwargs):
            rec._depth += 1  # Warp stages numpy data for another device through a host array made inside
            try:
                orig_init(self_, *args, **kwargs)
            finally:
                rec._depth -= 1
            if rec._depth == 0:
                data = args[0] if args else kwargs.get("data")
                rec.allocs.append((_alias(self_.device), _caller(), data if isinstance(data, np.ndarray) else None))

        def numpy(self_):
            rec.numpy_calls.append((id(self_), _caller()))
            rec._depth += 1  # reading a device array back stages it through a host array made inside numpy()
            try:
                return orig_numpy(self_)
            finally:
                rec._depth -= 1

        def launch(kernel, dim, inputs=(), outputs=(), *args, device=None, **kwargs):
            name = getattr(kernel, "key", str(kernel))
            rec.launches.append((name, _alias(wp.get_device(device)), _caller(), _flatten([*inputs, *outputs])))
            return orig_launch(kernel, dim, inputs, outputs, *args, device=device, **kwargs)

        def cast(*args, **kwargs):
            gb = orig_cast(*args, **kwargs)
            rec.gbuffers.append(gb)
            return gb

        monkeypatch.setattr(wp.array, "__init__", init)
        monkeypatch.setattr(wp.array, "numpy", numpy)
        monkeypatch.setattr(wp, "launch", launch)
        monkeypatch.setattr(gbuffer_mod, "cast_gbuffer", cast)
        monkeypatch.setattr(renderer_mod, "cast_gbuffer", cast)

    def _gb_arrays(self) -> list:
        return [a for gb in self.gbuffers for a in (gb.dist, gb.item, gb.face, gb.point, gb.normal) if a is not None]

    def violations(self, device: str) -> list[str]:
        device = device if device == TWIN else str(wp.get_device(device))  # "cuda" is recorded as "cuda:0"
        bad = [f"{who} allocated an array on {dev}" for dev, who, _ in self.allocs if dev != device]
        for name, dev, who, args in self.launches:
            if dev != device:
                bad.append(f"{who} launched {name} on {dev}")
            bad += [f"{who} passed an array on {a.device} to {name}" for a in args
                    if isinstance(a, wp.array) and _alias(a.device) != device]
        gb_ids = {id(a) for a in self._gb_arrays()}
        bad += [f"{who} read a G-buffer array into numpy" for i, who in self.numpy_calls
                if i in gb_ids and who != "flowsynth.raycast.gbuffer:host"]
        hosts = [h for gb in self.gbuffers if gb._host is not None
                 for h in (gb._host.dist, gb._host.item, gb._host.face, gb._host.point, gb._host.normal)
                 if h is not None]
        bad += [f"{who} made a Warp array from the G-buffer's numpy copy" for _, who, data in self.allocs
                if data is not None and any(np.shares_memory(data, h) for h in hosts)]
        return bad

    def launched_with_gbuffer(self, kernel_prefix: str) -> bool:
        """Whether a launch of a kernel whose key starts with ``kernel_prefix`` read a G-buffer's own item array."""
        items = {id(gb.item) for gb in self.gbuffers}
        return any(name.startswith(kernel_prefix) and any(id(a) in items for a in args)
                   for name, _, _, args in self.launches)


def _devices() -> list[str]:
    return ["cpu:twin"] + (["cuda"] if wp.get_cuda_device_count() > 0 else [])


@pytest.fixture(scope="module")
def scene():
    cfg = fs.BouncingThingsConfig(width=40, height=30, num_frames=3, num_objects=(3, 4))
    return fs.datasets.BouncingThings(cfg, outputs=["depth"], seed=5).scene(1)


@pytest.mark.parametrize("device", _devices())
@pytest.mark.parametrize("keys,opts,readers", [
    (KEYS_A, OPTS_A, ("pair_kernel", "world_points_kernel", "shade_kernel")), (KEYS_B, OPTS_B, ("pair_kernel",))],
    ids=["all-stages", "depth-occ-blur"])
def test_every_stage_stays_on_the_device_asked_for(twin, scene, monkeypatch, device, keys, opts, readers):
    ref = fs.render(scene, keys, **opts)  # on the CPU, before the recorder
    rec = Recorder(monkeypatch)
    got = fs.render(scene, keys, device=device, **opts)
    assert rec.allocs and rec.launches and rec.gbuffers, "the recorder saw nothing"
    assert rec.violations(device) == []
    assert all(gb.device == str(wp.get_device(device)) for gb in rec.gbuffers)
    # the kernel stages read the G-buffer's own Warp arrays (shading with spp 1 or edge samples)
    for prefix in readers:
        assert rec.launched_with_gbuffer(prefix), prefix
    if device == TWIN:  # the same CPU: the same bits
        for k in keys:
            assert torch.equal(got[k], ref[k]), k
    for k, v in got.items():
        assert v.device.type == "cpu", k


def test_lens_camera_stays_on_the_device_asked_for(twin, monkeypatch):
    cfg = fs.BouncingThingsConfig(width=40, height=30, num_frames=2, camera_model="brown_conrady",
                                  camera_dist=(-0.2, 0.05, 0.0, 0.0))
    lens_scene = fs.datasets.BouncingThings(cfg, outputs=["depth"], seed=2).scene(0)
    keys = ["depth", "flow_fw", "occ_fw", "rgb"]
    ref = fs.render(lens_scene, keys, edge_spp=4)
    rec = Recorder(monkeypatch)
    got = fs.render(lens_scene, keys, device=TWIN, edge_spp=4)
    assert rec.violations(TWIN) == []
    for k in keys:
        assert torch.equal(got[k], ref[k]), k


def test_recorder_catches_a_wrong_device_allocation(twin, scene, monkeypatch):
    rec = Recorder(monkeypatch)
    fs.render(scene, ["depth"], device=TWIN)
    assert rec.violations(TWIN) == []
    wp.zeros(4, dtype=wp.float32, device="cpu")  # a fake stage that picks its own device
    bad = rec.violations(TWIN)
    assert len(bad) == 1 and "allocated an array on cpu" in bad[0]
    out = wp.zeros(4, dtype=wp.float32, device=TWIN)

    @wp.kernel
    def fill(x: wp.array[wp.float32]):
        x[wp.tid()] = 1.0

    wp.launch(fill, 4, [out], device="cpu")  # launched on its own device
    assert any("launched" in b and "on cpu" in b for b in rec.violations(TWIN))


def test_recorder_catches_a_gbuffer_round_trip(twin, scene, monkeypatch):
    from flowsynth.raycast.accel import SceneAccel

    rec = Recorder(monkeypatch)
    meshes, cam_T_world, world_T_obj = gbuffer_mod.scene_arrays(scene)
    gb = gbuffer_mod.cast_gbuffer(SceneAccel(meshes, cam_T_world, world_T_obj, device=TWIN), scene.camera,
                                  want_normals=False, want_points=True)
    gb.host()  # the hand-over: allowed
    assert rec.violations(TWIN) == []
    wp.array(gb.host().item, dtype=wp.int32, device=TWIN)  # a stage that wraps the host copy again
    assert any("from the G-buffer's numpy copy" in b for b in rec.violations(TWIN))
    rec.allocs.pop()
    gb.point.numpy()  # a stage that reads a G-buffer array itself
    assert any("read a G-buffer array into numpy" in b for b in rec.violations(TWIN))


STAGES = ["raycast/gbuffer", "renderer/pipeline", "renderer/batch", "truth/flow", "renderer/shading",
          "renderer/finalpass", "raycast/accel", "raycast/tiles", "raycast/culling", "raycast/blas", "truth/stereo",
          "truth/tracks", "truth/annotations", "scene/camera", "datasets/bouncing", "kernels/shade", "kernels/tonemap",
          "kernels/dof", "scene/motion", "scene/physics"]


@pytest.mark.parametrize("module", STAGES)
def test_no_stage_names_the_cpu_but_as_a_default(module):
    """The string "cpu" appears in a stage's source only as the default value of a parameter."""
    tree = ast.parse((REPO / "flowsynth" / f"{module}.py").read_text())
    defaults = {id(d) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.Lambda))
                for d in (*f.args.defaults, *f.args.kw_defaults) if d is not None}
    named = [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Constant) and n.value == "cpu"
             and id(n) not in defaults]
    assert named == [], f"flowsynth/{module}.py names 'cpu' on lines {named}"


@pytest.mark.parametrize("device", ["cuda", "cuda:1", "gpu"])
def test_a_device_warp_does_not_find_is_a_config_error(scene, device):
    if device.startswith("cuda") and wp.get_cuda_device_count() > int(device.partition(":")[2] or 0):
        pytest.skip(f"Warp finds {device} here")
    with pytest.raises(ConfigError, match=rf"device '{device}' is not available: Warp finds \[.*'cpu'"):
        fs.render(scene, ["depth"], device=device)
    ds = fs.datasets.BouncingThings(fs.BouncingThingsConfig(width=16, height=12, num_frames=2), outputs=["depth"],
                                    device=device)
    with pytest.raises(ConfigError, match=f"device '{device}'"):
        ds.sample(0)


def test_resolved_devices_are_warps_aliases(twin):
    from flowsynth.raycast.accel import resolve_device

    assert resolve_device("cpu") == "cpu"
    assert resolve_device(wp.get_device("cpu")) == "cpu"
    assert resolve_device(TWIN) == TWIN


@pytest.mark.parametrize("device", ["cuda", "cuda:9"])
def test_physics_takes_a_cpu_device_only(device):
    """NewtonScene reads and resets its state through numpy views: another device is refused, not half run."""
    from flowsynth.scene.motion import NewtonScene

    with pytest.raises(ConfigError, match=f"physics runs on a CPU device only.*'{device}'"):
        NewtonScene(fs.BouncingThingsConfig(), [], None, 2, device=device)
