"""BouncingThingsConfig: defaults, immutability, dict round trip, and one error per invalid value."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import itertools
import json
import math
import textwrap

import numpy as np
import pytest
import trimesh

from flowsynth.scene.config import BouncingThingsConfig
from flowsynth.errors import AssetError, ConfigError


def test_defaults_are_valid_frozen_and_hashable():
    cfg = BouncingThingsConfig()
    assert cfg.motion == "physics" and cfg.gravity == (0.0, 0.0, 0.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.width = 10
    assert hash(cfg) == hash(BouncingThingsConfig())


def test_every_field_has_a_default_and_a_docstring():
    body = ast.parse(textwrap.dedent(inspect.getsource(BouncingThingsConfig))).body[0].body
    documented = {stmt.target.id for stmt, nxt in itertools.pairwise(body)
                  if isinstance(stmt, ast.AnnAssign) and isinstance(nxt, ast.Expr)
                  and isinstance(nxt.value, ast.Constant) and str(nxt.value.value).strip()}
    for f in dataclasses.fields(BouncingThingsConfig):
        assert f.default is not dataclasses.MISSING, f.name
        assert f.name in documented, f"{f.name} has no docstring"


def test_dict_round_trip_through_json(tmp_path):
    from PIL import Image
    Image.fromarray(np.full((8, 8, 3), 128, np.uint8)).save(tmp_path / "tex.png")
    cfg = BouncingThingsConfig(width=64, height=48, num_objects=(2, 3), gravity=(0.0, 0.0, -9.81),
                               camera_motion="moving", substeps=6, texture_dir=str(tmp_path))
    d = json.loads(json.dumps(cfg.to_dict()))
    assert BouncingThingsConfig.from_dict(d) == cfg
    assert isinstance(d["num_objects"], list)


def test_sequences_become_tuples():
    cfg = BouncingThingsConfig(num_objects=[1, 2], object_size=[0.3, 0.5], assets=["box", "sphere"],
                               room_size=[6, 5, 4])
    assert cfg.num_objects == (1, 2) and cfg.assets == ("box", "sphere") and cfg.room_size == (6.0, 5.0, 4.0)
    assert hash(cfg)


def test_from_dict_rejects_unknown_keys_and_lists_valid_ones():
    with pytest.raises(ConfigError, match="unknown.*'colour'.*valid fields.*'width'"):
        BouncingThingsConfig.from_dict({"width": 10, "colour": "red"})


INVALID = [
    ({"width": 0}, "width"),
    ({"height": -3}, "height"),
    ({"width": 32.0}, "width"),
    ({"num_frames": 0}, "num_frames"),
    ({"fps": 0.0}, "fps"),
    ({"fps": math.nan}, "fps"),
    ({"fov_deg": 0.0}, "fov_deg"),
    ({"fov_deg": 180.0}, "fov_deg"),
    ({"num_objects": (5, 3)}, "num_objects"),
    ({"num_objects": (-1, 3)}, "num_objects"),
    ({"num_objects": (1, 40)}, "max_objects"),
    ({"num_objects": (1, 2.5)}, "num_objects"),
    ({"object_size": (0.8, 0.4)}, "object_size"),
    ({"object_size": (-0.1, 0.4)}, "object_size"),
    ({"object_size": (0.0, 0.4)}, "object_size"),
    ({"object_size": (0.1, math.inf)}, "object_size"),
    ({"object_size": (0.5, 9.0)}, "object_size"),
    ({"size_levels": 0}, "size_levels"),
    ({"min_speed": -1.0}, "min_speed"),
    ({"min_speed": 3.0, "max_speed": 2.0}, "min_speed"),
    ({"max_speed": math.inf}, "max_speed"),
    ({"angular_speed": (2.0, 1.0)}, "angular_speed"),
    ({"angular_speed": (-1.0, 1.0)}, "angular_speed"),
    ({"motion": "flying"}, "motion"),
    ({"gravity": (0.0, -9.81)}, "gravity"),
    ({"gravity": (0.0, 0.0, math.nan)}, "gravity"),
    ({"restitution": 1.5}, "restitution"),
    ({"friction": -0.1}, "friction"),
    ({"substeps": 0}, "substeps"),
    ({"camera_motion": "orbit"}, "camera_motion"),
    ({"camera_speed": (1.0, 0.5)}, "camera_speed"),
    ({"room_size": (0.0, 5.0, 5.0)}, "room_size"),
    ({"room_size": (5.0, 5.0)}, "room_size"),
    ({"camera_clearance": 0.0}, "camera_clearance"),
    ({"camera_clearance": 6.0}, "camera_clearance"),
    ({"num_objects": (30, 32), "object_size": (1.0, 3.0)}, "num_objects"),
    ({"max_objects": 0, "num_objects": (0, 0)}, "max_objects"),
    ({"render_mode": "raytrace"}, "render_mode"),
    ({"spp": 0}, "spp"),
    ({"edge_spp": 0}, "edge_spp"),
    ({"shutter": 1.5}, "shutter"),
    ({"texture_families": ()}, "texture_families"),
    ({"texture_dir": 3}, "texture_dir"),
    ({"assets": ()}, "assets"),
    ({"assets": ("box", "dodecahedron")}, "dodecahedron"),
]  # missing or unreadable mesh files fail when a scene is sampled (tests/test_options.py), not here


@pytest.mark.parametrize("kwargs, field", INVALID, ids=[f"{k}-{i}" for i, (k, _) in enumerate(INVALID)])
def test_invalid_values_raise_config_error_naming_the_field(kwargs, field):
    with pytest.raises(ConfigError, match=field):
        BouncingThingsConfig(**kwargs)


def test_user_mesh_files_and_globs(tmp_path):
    trimesh.creation.box(extents=(1, 2, 3)).export(tmp_path / "a.obj")
    trimesh.creation.icosphere().export(tmp_path / "b.obj")
    cfg = BouncingThingsConfig(assets=("sphere", str(tmp_path / "*.obj")))
    assert cfg.assets == ("sphere", str(tmp_path / "*.obj"))
    BouncingThingsConfig(assets=(str(tmp_path / "a.obj"),))


def test_mesh_file_that_does_not_load_raises_when_sampled(tmp_path):
    bad = tmp_path / "broken.obj"
    bad.write_text("this is not a mesh\n")
    cfg = BouncingThingsConfig(assets=(str(bad),))  # a config reads no file
    with pytest.raises(AssetError, match="assets.*broken.obj"):
        cfg.check_files()
