"""One source for the render options (issue 41, item 2): ``fs.RenderOptions`` holds each option's one rule and one
default; ``BouncingThingsConfig`` and ``fs.render`` / ``make_plan`` apply them, docs/rendering.md's table states the
same defaults; and a config reads no file when it is made (its meshes and textures are resolved when a scene is
sampled, with an error naming the path)."""

from __future__ import annotations

import ast
import dataclasses
import glob
import math
import os
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh

import flowsynth as fs
from flowsynth.cli import main as cli_main
from flowsynth.scene.config import DATASET_MAX_OBJECTS, BouncingThingsConfig
from flowsynth.errors import AssetError, ConfigError
from flowsynth.options import FINAL_OPTIONS, OPTION_NAMES, FinalPass, RenderOptions
from flowsynth.plan import Plan, make_plan
from flowsynth.scene.sampling import sample_layout

DOCS = Path(__file__).resolve().parents[1] / "docs" / "rendering.md"

# (option, a value every route must refuse): the cases where config.py and plan.py once disagreed come first
BAD = [("spp", True), ("spp", 0), ("spp", 2.5), ("edge_spp", True), ("edge_spp", 0), ("max_objects", 0),
       ("max_objects", True), ("shutter", "0.5"), ("shutter", True), ("shutter", 1.5), ("shutter", math.nan),
       ("bounces", 65), ("bounces", -1), ("bounces", np.float64(2.0)), ("tonemap", "filmic"), ("exposure", -1.0),
       ("exposure", math.inf), ("render_mode", "raytrace"), ("flow_gaps", ()), ("flow_gaps", (0,)),
       ("flow_gaps", 3), ("flow_gaps", (1, True)), ("num_tracks", 0), ("num_tracks", np.float32(3)),
       ("track_sampling", "random"), ("stereo_baseline", -0.1), ("stereo_baseline", math.nan),
       ("final_shutter", 1.5), ("final_time_samples", 0), ("final_focus", 0.0), ("final_aperture", (0.04, 0.01)),
       ("final_fog_color", (1.0, 1.0)), ("final_max_coc", 65.0), ("final_shot_noise", (0.0, 2.0))]


@pytest.mark.parametrize("name, value", BAD, ids=[f"{n}={v!r}" for n, v in BAD])
def test_every_route_refuses_the_same_values(name, value):
    routes = {"RenderOptions": lambda: RenderOptions(**{name: value}),
              "BouncingThingsConfig": lambda: BouncingThingsConfig(**{name: value}),
              "make_plan": lambda: make_plan(["rgb", "flow_fw"], **{name: value}),
              "RenderOptions via options=": lambda: make_plan(["rgb"], RenderOptions(), **{name: value})}
    for route, call in routes.items():
        with pytest.raises(ConfigError, match=name):
            call()
            pytest.fail(f"{route} accepted {name}={value!r}")


GOOD = {"spp": np.int64(3), "edge_spp": 2, "shutter": 1, "bounces": np.int32(5), "exposure": 2, "max_objects": 20,
        "flow_gaps": [2, 1, 2], "num_tracks": 7, "stereo_baseline": 1, "render_mode": "direct",
        "final_aperture": [0.02, 0.03], "final_time_samples": np.int64(4), "final_focus": 3,
        "final_fog_color": [0.1, 0.2, 0.3]}
NORMALISED = {"spp": 3, "edge_spp": 2, "shutter": 1.0, "bounces": 5, "exposure": 2.0, "max_objects": 20,
              "flow_gaps": (2, 1), "num_tracks": 7, "stereo_baseline": 1.0, "render_mode": "direct",
              "final_aperture": (0.02, 0.03), "final_time_samples": 4, "final_focus": 3.0,
              "final_fog_color": (0.1, 0.2, 0.3)}


def test_every_route_normalises_the_same_way():
    direct = RenderOptions(**GOOD)
    cfg = BouncingThingsConfig(**GOOD)
    plan = make_plan(["rgb"], **GOOD)
    for name, want in NORMALISED.items():
        for route, got in (("RenderOptions", getattr(direct, name)), ("config", getattr(cfg, name)),
                           ("plan", getattr(plan, name))):
            assert got == want and type(got) is type(want), (route, name, got)
            if isinstance(want, tuple):
                assert all(type(a) is type(b) for a, b in zip(got, want)), (route, name, got)
    assert cfg.render_options == direct == plan.options
    assert cfg.plan_options() == direct.to_dict()
    assert make_plan(["rgb"], cfg.render_options) == make_plan(["rgb"], **cfg.plan_options()) == plan


def test_one_default_per_option():
    defaults = RenderOptions()
    cfg_fields = {f.name: f.default for f in dataclasses.fields(BouncingThingsConfig)}
    assert set(OPTION_NAMES) <= set(cfg_fields)
    for name in OPTION_NAMES:
        want = DATASET_MAX_OBJECTS if name == "max_objects" else getattr(defaults, name)
        assert cfg_fields[name] == want, name
    assert defaults.max_objects is None and DATASET_MAX_OBJECTS == 32  # the one documented exception
    assert defaults.edge_spp == 4  # docs/decisions/0009-edge-spp-default-4.md, for fs.render as for the config
    assert make_plan(["depth"]).options == defaults  # fs.render's defaults are RenderOptions'
    assert BouncingThingsConfig().render_options == dataclasses.replace(defaults, max_objects=DATASET_MAX_OBJECTS)
    fp = FinalPass()
    assert all(getattr(defaults, n) == getattr(fp, n.removeprefix("final_")) for n in FINAL_OPTIONS)
    assert defaults.final_pass == fp


def _docs_table() -> dict[str, str]:
    text = DOCS.read_text()
    section = text.split("\n## Options\n", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `(\w+)` \| `([^`]*)` \|(.*)\|(.*)\|$", section, re.M)
    assert rows, "docs/rendering.md: no options table under '## Options'"
    for name, _, why, decision in rows:
        assert why.strip() and decision.strip(), f"docs/rendering.md, Options: {name} lacks a reason or decision"
    return {name: default for name, default, _, _ in rows}


def test_docs_table_states_every_default_of_the_code():
    table = _docs_table()
    assert sorted(table) == sorted(OPTION_NAMES), "docs/rendering.md's Options table and RenderOptions differ"
    defaults = RenderOptions()
    for name, cell in table.items():
        assert ast.literal_eval(cell) == getattr(defaults, name), f"docs/rendering.md: {name} default {cell}"
    for path in re.findall(r"\(decisions/([\w.-]+\.md)\)", DOCS.read_text().split("\n## Options\n", 1)[1]):
        assert (DOCS.parent / "decisions" / path).is_file(), path


def test_keyword_only_and_plan_reads_through():
    with pytest.raises(TypeError):
        RenderOptions("flat")  # positional: refused
    with pytest.raises(TypeError):
        Plan(("depth",), RenderOptions())
    with pytest.raises(ConfigError, match="options must be"):
        make_plan(["depth"], "exact")
    with pytest.raises(ConfigError, match="unknown render option.*'sppp'.*valid options: render_mode"):
        make_plan(["depth"], sppp=2)
    plan = make_plan(["rgb"], RenderOptions(spp=2), spp=5, seed=3)  # keywords apply on top of options=
    assert plan.spp == plan.options.spp == 5 and plan.seed == 3 and plan.final_pass == FinalPass()
    assert plan.with_options(edge_spp=1).edge_spp == 1 and plan.edge_spp == 4
    with pytest.raises(ConfigError, match="edge_spp"):
        plan.with_options(edge_spp=0)
    with pytest.raises(AttributeError):
        plan.no_such_option  # noqa: B018


def _sphere_scene() -> fs.Scene:
    T = 2
    scene = fs.Scene(camera=fs.Camera.from_fov(width=40, height=30, fov_deg=60.0), num_frames=T)
    scene.set_camera_poses(np.tile(np.eye(4), (T, 1, 1)))
    poses = np.tile(np.eye(4), (T, 1, 1))
    poses[:, :3, 3] = [[0.1 * t, 0.0, 4.0] for t in range(T)]
    scene.add_object(trimesh.creation.icosphere(subdivisions=2, radius=0.8), poses=poses, category=3)
    return scene


def test_render_takes_options_or_keywords_alike():
    scene = _sphere_scene()
    opts = RenderOptions(spp=2, edge_spp=1, render_mode="direct")
    a = fs.render(scene, ["rgb"], options=opts, threads=1)["rgb"]
    b = fs.render(scene, ["rgb"], spp=2, edge_spp=1, render_mode="direct", threads=1)["rgb"]
    c = fs.render(scene, ["rgb"], options=RenderOptions(spp=7, edge_spp=1), spp=2, render_mode="direct")["rgb"]
    assert torch_equal(a, b) and torch_equal(a, c)
    # the default edge_spp is 4: equal to passing 4, and unlike edge_spp=1 only at the sphere's outline
    default = fs.render(scene, ["rgb", "instance"], threads=1)
    four = fs.render(scene, ["rgb"], edge_spp=4, threads=1)["rgb"]
    one = fs.render(scene, ["rgb"], edge_spp=1, threads=1)["rgb"]
    assert torch_equal(default["rgb"], four)
    inst = default["instance"][:, 0].numpy()
    edge = np.zeros_like(inst, bool)
    edge[:, 1:] |= inst[:, 1:] != inst[:, :-1]
    edge[:, :-1] |= inst[:, 1:] != inst[:, :-1]
    edge[:, :, 1:] |= inst[:, :, 1:] != inst[:, :, :-1]
    edge[:, :, :-1] |= inst[:, :, 1:] != inst[:, :, :-1]
    differs = (default["rgb"] != one).any(1).numpy()
    assert differs.any() and not (differs & ~edge).any()


def torch_equal(a, b) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and bool((a == b).all())


# ------------------------------------------------------------------------------- no file I/O in the config

def _no_io(*args, **kwargs):
    raise AssertionError(f"file I/O while making a config: {args!r}")


def test_config_from_manifest_reads_no_file(tmp_path, monkeypatch):
    mesh, tex = tmp_path / "meshes" / "chair.obj", tmp_path / "textures"
    d = {"width": 32, "height": 24, "assets": ["box", str(mesh), str(tmp_path / "more" / "*.ply")],
         "texture_dir": str(tex), "texture_families": ["noise", "image"]}
    BouncingThingsConfig()  # imports done before I/O is forbidden
    for mod, name in ((os, "stat"), (os, "lstat"), (os, "listdir"), (os, "scandir"), (glob, "glob"),
                      (trimesh, "load"), (Path, "iterdir"), (Path, "stat"), (Path, "is_dir"), (Path, "is_file")):
        monkeypatch.setattr(mod, name, _no_io)
    cfg = BouncingThingsConfig.from_dict(d)
    again = BouncingThingsConfig.from_dict(cfg.to_dict())
    monkeypatch.undo()
    assert again == cfg and cfg.assets[1] == str(mesh) and cfg.texture_dir == str(tex)


def test_sampling_names_the_missing_mesh(tmp_path):
    gone = tmp_path / "user" / "gone.obj"
    cfg = BouncingThingsConfig.from_dict({"width": 32, "height": 24, "num_frames": 2, "motion": "static",
                                          "assets": ["box", str(gone)]})
    with pytest.raises(AssetError, match=re.escape(str(gone)) + ".*does not exist"):
        sample_layout(cfg, 0, 0)
    with pytest.raises(AssetError, match=re.escape(str(gone))):
        fs.datasets.BouncingThings(cfg, outputs=["depth"], seed=0).sample(0)
    with pytest.raises(AssetError, match=re.escape(str(gone))):
        cfg.check_files()
    pattern = str(tmp_path / "none" / "*.obj")
    with pytest.raises(AssetError, match=re.escape(pattern) + ".*matches no files"):
        sample_layout(dataclasses.replace(cfg, assets=("box", pattern)), 0, 0)
    gone.parent.mkdir()
    trimesh.creation.icosphere(subdivisions=1).export(gone)  # the same config samples once the file is there
    assert sample_layout(cfg, 0, 0).asset_keys == cfg.check_files() == ("box", str(gone))


def test_sampling_names_the_missing_texture_dir(tmp_path):
    tex = tmp_path / "no_textures_here"
    cfg = BouncingThingsConfig.from_dict({"width": 32, "height": 24, "num_frames": 2, "motion": "static",
                                          "num_objects": [1, 2], "texture_dir": str(tex),
                                          "texture_families": ["noise", "image"]})
    ds = fs.datasets.BouncingThings(cfg, outputs=["depth"], seed=0)
    with pytest.raises(ConfigError, match=re.escape(str(tex)) + ".*does not exist"):
        ds.scene(0)
    tex.mkdir()
    with pytest.raises(ConfigError, match=re.escape(str(tex)) + ".*holds no images"):
        ds.scene(0)


def test_export_refuses_missing_files_before_writing(tmp_path, capsys):
    out = tmp_path / "out"
    status = cli_main(["export", "--out", str(out), "--num", "1", "--width", "32", "--height", "24",
                       "--num-frames", "2", "--motion", "static", "--assets", f"box,{tmp_path / 'gone.obj'}"])
    assert status == 2 and "gone.obj" in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("bad", [np.array([1, 2]), np.array([1.0, 2.0]), True, "3"])
def test_checks_refuse_arrays_bools_and_strings_with_config_errors(bad):
    """Integer and number checks name the argument for anything but one integer or number: an array of two values
    used to pass the integer check and fail later in int() with a TypeError."""
    from flowsynth.options import check_int, check_number

    with pytest.raises(fs.ConfigError, match="must be an integer"):
        check_int("n", bad, 0)
    with pytest.raises(fs.ConfigError, match="must be a number"):
        check_number("x", bad)


def test_checks_refuse_torch_scalars_and_take_numpy_scalars():
    """A torch scalar has a dtype without numpy's ``kind``: a ConfigError, not an AttributeError."""
    import torch

    from flowsynth.options import check_int, check_number

    with pytest.raises(fs.ConfigError, match="must be an integer"):
        check_int("n", torch.tensor(3), 0)
    with pytest.raises(fs.ConfigError, match="must be a number"):
        check_number("x", torch.tensor(3.0))
    assert check_int("n", np.int64(3), 0) == 3 and check_int("n", np.uint8(7), 0, 9) == 7
    assert check_number("x", np.float32(2.5)) == 2.5 and check_number("x", np.array(4.0)) == 4.0
