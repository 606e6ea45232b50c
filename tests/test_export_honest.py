"""An export that honours every option it takes and says what it did: an option no source can honour is refused
(exit 2, nothing written), every option that changes bytes is in the identity a resume must match (a refusal names
each field that differs, with both values), ``--dry-run`` of a mixture measures what the writer writes, and an
exported mixture sample keeps its ``source``."""

from __future__ import annotations

import json

import pytest

import flowsynth as fs
from flowsynth.cli import main
from flowsynth.datasets import Exported, LayersConfig, Mixture, make_stream
from flowsynth.io import json_differences

SIZE = {"width": 48, "height": 32, "num_frames": 2}


def _layers(photos, **kw):
    return LayersConfig(**SIZE, texture_dir=photos, **kw)


@pytest.fixture
def layers_only(photos, tmp_path):
    """A mixture preset of two Layers sources and no BouncingThings one."""
    return str(Mixture({"a": _layers(photos), "b": _layers(photos, motion_scale=2.0)}).to_preset(tmp_path / "l.json"))


@pytest.mark.parametrize("option, value", [("occlusion", "depth"), ("device", "cuda"), ("threads", 2)])
def test_scene_options_are_refused_where_no_source_renders_a_scene(photos, option, value):
    """occlusion, device and threads are BouncingThings' options: a Layers stream and a Mixture of Layers sources
    only refuse them, naming the option; a mixture with a BouncingThings source passes them to it."""
    with pytest.raises(fs.ConfigError, match=f"{option}={value!r}"):
        make_stream(_layers(photos), ["rgb"], **{option: value})
    with pytest.raises(fs.ConfigError, match=f"Layers sources only cannot honour {option}={value!r}"):
        Mixture({"a": _layers(photos), "b": _layers(photos, motion_scale=2.0)}, outputs=["rgb"], **{option: value})
    things = fs.BouncingThingsConfig(**SIZE, motion="kinematic", num_objects=(1, 2), max_objects=2)
    mixed = Mixture({"things": things, "chairs": _layers(photos)}, outputs=["rgb", "occ_fw"], occlusion="depth")
    assert mixed.parts[0].plan.occlusion == "depth"


def test_cli_refuses_occlusion_a_layers_mixture_cannot_honour(layers_only, tmp_path, capsys):
    """``export --mixture layers_only.json --occlusion depth`` exits 2 and writes nothing."""
    out = tmp_path / "e"
    assert main(["export", "--mixture", layers_only, "--occlusion", "depth", "--out", str(out), "--num", "1",
                 "--no-progress"]) == 2
    assert "cannot honour occlusion='depth'" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("argv, needle", [
    (["--layout", "kitti", "--exr-compression", "none"], "writes no EXR files"),
    (["--layout", "flyingchairs", "--exr-compression", "piz"], "writes no EXR files"),
    (["--address", "auto"], "--engine ray"),
])
def test_cli_refuses_options_that_would_change_nothing(photos, tmp_path, capsys, argv, needle):
    """An EXR compression for a layout that writes no EXR, a Ray address for the local engine: exit 2, nothing
    written."""
    out = tmp_path / "e"
    assert main(["export", "--dataset", "layers", "--width", "48", "--height", "32", "--texture-dir", photos,
                 "--out", str(out), "--num", "1", "--no-progress", *argv]) == 2
    assert needle in capsys.readouterr().err
    assert not out.exists()


def test_occlusion_is_part_of_the_identity(tmp_path, capsys, small_flags):
    """A resume under another --occlusion is refused, naming the field and both values; a manifest written before
    the method was recorded reads as "exact": it resumes with the default (writing nothing) and refuses "depth"."""
    out = tmp_path / "e"
    argv = ["export", "--out", str(out), "--num", "1", "--no-progress", "--outputs", "occ_fw", *small_flags]
    assert main(argv) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["occlusion"] == "exact"
    capsys.readouterr()
    assert main([*argv, "--occlusion", "depth"]) == 2
    assert 'occlusion is "exact" there, "depth" here' in capsys.readouterr().err
    del manifest["occlusion"]
    (out / "manifest.json").write_text(json.dumps(manifest))
    assert main(argv) == 0
    assert "1 present (whole), 0 written" in capsys.readouterr().out
    assert main([*argv, "--occlusion", "depth"]) == 2
    assert 'occlusion is "exact" there, "depth" here' in capsys.readouterr().err


def test_refusal_names_each_config_field_with_both_values(photos, tmp_path, capsys):
    """Another --width and --motion-scale than the export's: the refusal names config.width and
    config.motion_scale, each with the folder's value and the command's, and leaves the export as it was."""
    base = ["export", "--dataset", "layers", "--texture-dir", photos, "--height", "32", "--out", str(tmp_path / "e"),
            "--num", "1", "--no-progress"]
    assert main([*base, "--width", "48"]) == 0
    before = (tmp_path / "e" / "manifest.json").read_bytes()
    capsys.readouterr()
    assert main([*base, "--width", "64", "--motion-scale", "2"]) == 2
    err = capsys.readouterr().err
    assert "config.width is 48 there, 64 here" in err and "config.motion_scale is 1.0 there, 2.0 here" in err
    assert "seed" not in err.split("other settings:")[1].split("; resume")[0]
    assert (tmp_path / "e" / "manifest.json").read_bytes() == before


def test_json_differences_paths_and_values():
    """Nested dicts by key, equal-length lists by item, anything else whole; a key one side lacks is None there."""
    old = {"a": 1, "b": {"c": [1, 2], "d": "x"}, "e": [1], "f": 0}
    new = {"a": 1, "b": {"c": [1, 3], "d": "y"}, "e": [1, 2], "g": 5}
    assert json_differences(old, new) == [("b.c[1]", 2, 3), ("b.d", "x", "y"), ("e", [1], [1, 2]), ("f", 0, None),
                                          ("g", None, 5)]
    assert json_differences(old, old) == []


@pytest.mark.parametrize("layout", ["native", "webdataset"])
def test_dry_run_of_a_mixture_measures_what_the_export_writes(layers_only, tmp_path, capsys, layout):
    """``export --mixture FILE --dry-run`` exits 0, writes nothing, and its bytes per sample are the bytes the export
    of sample 0 then writes (native: every file but the manifest; webdataset: the shard's members, without the tar
    headers); the exported samples keep their source, as the stream's."""
    out = tmp_path / "e"
    argv = ["export", "--mixture", layers_only, "--out", str(out), "--num", "1", "--layout", layout, "--no-progress"]
    assert main([*argv, "--dry-run"]) == 0
    table = capsys.readouterr().out
    assert not out.exists()
    total = int(next(line for line in table.splitlines() if line.startswith("total")).split()[1].replace(",", ""))
    assert main(argv) == 0
    if layout == "native":
        written = sum(p.stat().st_size for p in out.rglob("*") if p.is_file() and p.name != "manifest.json")
    else:
        import tarfile

        with tarfile.open(out / "shard-000000.tar") as tar:
            written = sum(m.size for m in tar.getmembers())
    assert total == written
    manifest = json.loads((out / "manifest.json").read_text())
    stream = Mixture.from_preset(layers_only, outputs=manifest["outputs"], seed=0)
    assert main([*argv[:-3], "--num", "6", "--layout", layout, "--no-progress"]) == 0
    back = Exported(out, verify=True)
    sources = [int(back[i]["source"]) for i in range(6)]
    assert sources == [stream.source(i) for i in range(6)] and set(sources) == {0, 1}
