"""One reader and one writer of mixture presets: ``MixtureConfig.from_file`` and ``MixtureConfig.to_file``.
``Mixture.from_preset`` / ``to_preset`` are thin aliases of them; the tune writes its winner with ``to_file`` and the
CLI's ``--mixture`` reads with ``from_file``."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest

from flowsynth.datasets import LayersConfig, Mixture, MixtureConfig
from flowsynth.errors import ConfigError
from flowsynth.scene import BouncingThingsConfig

REPO = Path(__file__).resolve().parents[1]
THINGS = BouncingThingsConfig(width=32, height=32, num_frames=2)
CHAIRS = LayersConfig(width=32, height=32, num_frames=2)


def _mix():
    return MixtureConfig({"things": THINGS, "chairs": CHAIRS}, [(5, {"chairs": 1}), (None, {"things": 1})])


def test_to_file_and_from_file_round_trip(tmp_path):
    cfg = _mix()
    path = cfg.to_file(tmp_path / "new" / "folder" / "p.json")
    assert path == tmp_path / "new" / "folder" / "p.json"
    assert sorted(p.name for p in path.parent.iterdir()) == ["p.json"], "no temporary file is left beside it"
    assert json.loads(path.read_text()) == cfg.to_dict()
    assert MixtureConfig.from_file(path) == cfg


def test_the_stream_aliases_write_and_read_the_same_file(tmp_path):
    cfg = _mix()
    a = cfg.to_file(tmp_path / "a.json")
    b = Mixture(cfg, None, ["rgb"], seed=3).to_preset(tmp_path / "b.json")
    assert a.read_bytes() == b.read_bytes()
    back = Mixture.from_preset(a, ["rgb"], seed=3)
    assert back.config == MixtureConfig.from_file(a) == cfg and back.seed == 3
    with pytest.raises(ConfigError, match="does not exist"):
        Mixture.from_preset(tmp_path / "none.json")


def test_no_other_entry_point_reads_or_writes_a_preset():
    assert not hasattr(Mixture, "preset_dict") and not hasattr(Mixture, "from_preset_dict")
    calls = {}
    for p in sorted((REPO / "flowsynth").rglob("*.py")):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.Attribute) and node.attr in ("to_file", "from_file", "from_preset", "to_preset"):
                calls.setdefault(node.attr, set()).add(str(p.relative_to(REPO)))
    assert "flowsynth/tune/run.py" in calls["to_file"], "the tune writes its preset with MixtureConfig.to_file"
    assert "flowsynth/cli.py" in calls["from_file"], "the CLI reads --mixture with MixtureConfig.from_file"
    run = (REPO / "flowsynth" / "tune" / "run.py").read_text()
    assert "write_json(out" not in run, "the tune writes its preset through MixtureConfig.to_file alone"
