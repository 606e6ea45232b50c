"""A first run without guessing: ``flowsynth --version``, an example config that ``--config`` reads, ``--print-config``
that ``--config`` reads back, "did you mean" on a misspelt field or flag, and ``--help`` short enough to read, with
every field behind ``--help-fields``."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import yaml

import flowsynth as fs
from flowsynth.cli import main
from flowsynth.datasets import LayersConfig, Mixture
from flowsynth.scene.config import PRESETS

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "config.yaml"
HELP_LINES = 60  # at 80 columns


def _printed(capsys, argv: list[str]) -> dict:
    assert main(argv) == 0, capsys.readouterr().err
    return json.loads(capsys.readouterr().out)


def test_version_is_the_packages(tmp_path):
    """``flowsynth --version`` in a fresh process prints pyproject.toml's version and exits 0."""
    want = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    r = subprocess.run([sys.executable, "-m", "flowsynth.cli", "--version"], capture_output=True, text=True,
                       cwd=tmp_path, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"flowsynth {want}"


def test_example_config_is_what_config_reads(capsys):
    """examples/config.yaml, read by PyYAML here: ``--config`` gives its values, the defaults elsewhere."""
    given = yaml.safe_load(EXAMPLE.read_text())
    assert given and all(isinstance(k, str) for k in given)
    printed = _printed(capsys, ["export", "--config", str(EXAMPLE), "--print-config"])
    defaults = fs.BouncingThingsConfig().to_dict()
    assert set(printed) == set(defaults)
    for k, v in printed.items():
        assert v == given.get(k, defaults[k]), k
    assert printed == json.loads(json.dumps(fs.BouncingThingsConfig.from_dict(
        {k: tuple(v) if isinstance(v, list) else v for k, v in given.items()}).to_dict()))


@pytest.mark.parametrize("command", ["export", "preview", "stats"])
@pytest.mark.parametrize("argv, kind", [
    (["--preset", "chairs", "--width", "64", "--object-size", "0.3,0.9", "--flow-gaps", "1,3"], "bouncing"),
    (["--config", str(EXAMPLE), "--num-frames", "3", "--camera-dist-max", "none"], "bouncing"),
    (["--dataset", "layers", "--width", "40", "--motion-scale", "0.5"], "layers"),
])
def test_print_config_reads_back(tmp_path, capsys, command, argv, kind):
    """``--print-config`` prints the resolved config; that file through ``--config`` prints the same again, and it is
    the config the flags describe (built here from the preset and the fields, not by the CLI)."""
    first = _printed(capsys, [command, *argv, "--print-config"])
    path = tmp_path / "resolved.json"
    path.write_text(json.dumps(first))
    again = _printed(capsys, [command, "--config", str(path), "--print-config"]
                     + (["--dataset", "layers"] if kind == "layers" else []))
    assert again == first
    if kind == "layers":
        want = LayersConfig(width=40, motion_scale=0.5)
    elif "--preset" in argv:
        want = dataclasses.replace(fs.BouncingThingsConfig(**PRESETS["chairs"]), width=64, object_size=(0.3, 0.9),
                                   flow_gaps=(1, 3))
    else:
        cfg = {k: tuple(v) if isinstance(v, list) else v for k, v in yaml.safe_load(EXAMPLE.read_text()).items()}
        want = fs.BouncingThingsConfig(**dict(cfg, num_frames=3, camera_dist_max=None))
    assert first == json.loads(json.dumps(want.to_dict()))


def test_print_config_of_a_mixture_is_a_preset_mixture_reads(tmp_path, capsys):
    sources = {"things": fs.BouncingThingsConfig(width=48, height=32, num_frames=2),
               "chairs": LayersConfig(width=48, height=32, num_frames=2)}
    preset = Mixture(sources, {"things": 1, "chairs": 3}).to_preset(tmp_path / "tuned.json")
    first = _printed(capsys, ["stats", "--mixture", str(preset), "--print-config"])
    assert first == json.loads(Path(preset).read_text())
    path = tmp_path / "printed.json"
    path.write_text(json.dumps(first))
    assert _printed(capsys, ["stats", "--mixture", str(path), "--print-config"]) == first


@pytest.mark.parametrize("suffix, text, needle", [
    (".json", '{"fov_dg": 50, "width": 64}', "'fov_dg': did you mean 'fov_deg'?"),
    (".yaml", "num_object: [2, 3]\n", "'num_object': did you mean 'num_objects'?"),
    (".toml", "texture_familes = ['noise']\n", "'texture_familes': did you mean 'texture_families'?"),
])
def test_misspelt_field_in_a_config_file_says_did_you_mean(tmp_path, capsys, suffix, text, needle):
    path = tmp_path / f"c{suffix}"
    path.write_text(text)
    assert main(["export", "--out", str(tmp_path / "o"), "--num", "1", "--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert needle in err and "valid fields" in err, err
    assert not (tmp_path / "o").exists()


def test_misspelt_layers_field_says_did_you_mean(tmp_path, capsys):
    path = tmp_path / "l.json"
    path.write_text('{"motion_scal": 0.5}')
    assert main(["stats", "--dataset", "layers", "--config", str(path), "--print-config"]) == 2
    assert "'motion_scal': did you mean 'motion_scale'?" in capsys.readouterr().err


def test_misspelt_field_through_the_api_says_did_you_mean():
    with pytest.raises(fs.ConfigError, match=r"'heigth': did you mean 'height'\?"):
        fs.BouncingThingsConfig.from_dict({"heigth": 48})
    with pytest.raises(fs.ConfigError) as e:  # nothing close: no guess
        fs.BouncingThingsConfig.from_dict({"zzzz": 1})
    assert "did you mean" not in str(e.value)


@pytest.mark.parametrize("command, flag, hint", [
    ("export", "--fov-dg", "--fov-deg"), ("stats", "--widht", "--width"),
    ("preview", "--motoin-scale", "--motion-scale"),
])
def test_misspelt_flag_says_did_you_mean(capsys, command, flag, hint):
    assert main([command, flag, "3", "--print-config"]) == 2
    err = capsys.readouterr().err
    assert f"unrecognized arguments: {flag} 3" in err and f"did you mean {hint}" in err, err
    assert err.startswith(f"usage: flowsynth {command}"), err


def test_yaml_without_pyyaml_says_what_to_install(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "yaml", None)  # import yaml raises ImportError, as where it is not installed
    assert main(["export", "--config", str(EXAMPLE), "--print-config"]) == 2
    err = capsys.readouterr().err
    assert "pip install pyyaml" in err and str(EXAMPLE) in err, err


def test_pyyaml_is_declared():
    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    assert any(re.match(r"pyyaml\b", d, re.I) for d in deps), deps


def _help(monkeypatch, capsys, argv: list[str]) -> str:
    monkeypatch.setenv("COLUMNS", "80")
    assert main(argv) == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("command", [[], ["export"], ["preview"], ["stats"], ["tune"]])
def test_help_reads_in_a_minute(monkeypatch, capsys, command):
    """Each ``--help`` fits in HELP_LINES lines at 80 columns, without RST markup."""
    text = _help(monkeypatch, capsys, [*command, "--help"])
    assert len(text.splitlines()) <= HELP_LINES, (command, len(text.splitlines()))
    assert "``" not in text
    if command and command[0] != "tune":
        assert f"flowsynth {command[0]} --help-fields" in text  # says where the fields are


def _field_flags(cls, skip=()) -> list[tuple[str, dataclasses.Field]]:
    return [("--" + f.name.replace("_", "-"), f) for f in dataclasses.fields(cls) if f.name not in skip]


@pytest.mark.parametrize("command", ["export", "preview", "stats"])
def test_help_fields_lists_every_field_with_a_readable_metavar(monkeypatch, capsys, command):
    """``--help-fields`` lists every BouncingThingsConfig and LayersConfig field flag; number lists read as numbers
    (X,X,... or N,N,...), never NAME,...; no RST markup."""
    text = _help(monkeypatch, capsys, [command, "--help-fields"])
    assert "``" not in text
    scene = {f.name for f in dataclasses.fields(fs.BouncingThingsConfig)}
    for flag, f in _field_flags(fs.BouncingThingsConfig) + _field_flags(LayersConfig, skip=scene):
        m = re.search(rf"^  {re.escape(flag)} (\S+)", text, re.M)
        assert m, flag
        t = str(f.type).replace(" ", "")
        if t.startswith("tuple[float") or t.startswith("tuple[int"):
            assert "NAME" not in m.group(1), (flag, m.group(1))
    for name in ("native", "kitti", "webdataset") if command == "export" else ():
        assert re.search(rf"^  {name}: ", text, re.M), name
