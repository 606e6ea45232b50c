"""A mixture preset file (what ``flowsynth tune`` writes) works everywhere a config does: ``flowsynth export``,
``preview`` and ``stats --mixture FILE``, ``export_dataset`` and ``FlowPairs`` of a ``MixtureConfig``; refused input
exits 2 naming the flag or the file."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
import tvision
from PIL import Image

import flowsynth as fs
from flowsynth.cli import PREVIEW_LAYERS, main
from flowsynth.datasets import Exported, FlowPairs, Layers, LayersConfig, Mixture, MixtureConfig, config_from
from flowsynth.datasets import config_kind
from flowsynth.export import estimate, export_dataset
from flowsynth.viz import contact_sheet, sample_preview

RGB_STEP = 0.5 / 255 + 1e-6  # 8-bit rounding of an exported frame
SIZE = {"width": 48, "height": 32, "num_frames": 2}


def _sources(photos):
    things = fs.BouncingThingsConfig(**SIZE, motion="kinematic", num_objects=(1, 2), max_objects=2,
                                     render_mode="flat")
    return {"things": things, "chairs": LayersConfig(**SIZE, texture_dir=photos)}


@pytest.fixture
def preset(photos, tmp_path):
    """A two-source preset file: a small BouncingThings config and a Layers config, weights 1:1."""
    return str(Mixture(_sources(photos), {"things": 1, "chairs": 1}).to_preset(tmp_path / "tuned.json"))


def _close(got: dict, want: dict, keys) -> None:
    for k in keys:
        if k == "rgb":
            assert (got[k] - want[k]).abs().max() <= RGB_STEP
        else:
            assert got[k].dtype == want[k].dtype and torch.equal(got[k], want[k]), k


def test_mixture_config_is_a_dataset_config(preset, photos):
    """MixtureConfig is the preset: from_file(path).to_dict() is the file, from_dict round-trips, config_from and
    config_kind know it, and its stream is Mixture.from_preset's sample for sample."""
    cfg = MixtureConfig.from_file(preset)
    assert cfg.to_dict() == json.loads(open(preset).read())
    assert MixtureConfig.from_dict(cfg.to_dict()) == cfg == config_from("mixture", cfg.to_dict())
    assert config_kind(cfg) == "mixture" and (cfg.width, cfg.height, cfg.num_frames) == (48, 32, 2)
    assert cfg.configs == _sources(photos)
    a = fs.datasets.make_stream(cfg, ["rgb", "flow_fw"], seed=4)
    b = Mixture.from_preset(preset, outputs=["rgb", "flow_fw"], seed=4)
    for i in range(3):
        assert a.source(i) == b.source(i)
        _close(a.sample(i), b.sample(i), ["rgb", "flow_fw", "source"])


def test_export_read_back_by_torchvision_and_exported_then_resumed(preset, tmp_path, capsys):
    """``flowsynth export --mixture``: torchvision's FlyingChairs reads the pairs of a flyingchairs export (flow
    bit-exact, img2 within 8-bit rounding) and Exported the native one (every key, provenance included) as
    ``Mixture.from_preset(FILE, outputs, seed).sample(i)``, both sources among the 4 samples; the manifest records
    the preset; a re-run writes nothing, a deleted sample is written again, another preset is refused (exit 2)."""
    stream = Mixture.from_preset(preset, outputs=["rgb", "flow_fw", "valid_fw", "occ_fw"], seed=2)
    assert {stream.source(i) for i in range(4)} == {0, 1}, "both sources must occur among the exported samples"
    chairs = tmp_path / "chairs"
    assert main(["export", "--mixture", preset, "--out", str(chairs), "--num", "4", "--seed", "2",
                 "--layout", "flyingchairs", "--no-progress"]) == 0
    ds = tvision.datasets().FlyingChairs(root=chairs, split="train")
    assert len(ds) == 4
    for i in range(4):
        img1, img2, flow = ds[i]
        want = stream.sample(i)
        np.testing.assert_array_equal(flow, want["flow_fw"][0].numpy())
        assert np.abs(np.asarray(img2) / 255 - want["rgb"][1].permute(1, 2, 0).numpy()).max() <= RGB_STEP

    native = tmp_path / "native"
    argv = ["export", "--mixture", preset, "--out", str(native), "--num", "4", "--seed", "2", "--no-progress"]
    assert main(argv) == 0
    manifest = json.loads((native / "manifest.json").read_text())
    assert manifest["config"] == json.loads(open(preset).read()) and manifest["dataset"] == "mixture"
    back = Exported(native, verify=True)
    outs = manifest["outputs"]
    assert {"rgb", "flow_fw", "occ_fw", "instance"} <= set(outs)
    full = Mixture.from_preset(preset, outputs=[*outs, "meta"], seed=2)
    for i in range(4):
        got, want = back[i], full.sample(i)
        assert set(got) == {*outs, "index", "seed", "source", "provenance"}
        assert int(got["source"]) == full.source(i)
        assert got["provenance"] == want["provenance"]
        _close(got, want, outs)

    files = {p: p.stat().st_mtime_ns for p in native.rglob("*") if p.is_file() and p.name != "manifest.json"}
    assert main(argv) == 0
    assert {p: p.stat().st_mtime_ns for p in files} == files
    for p in (native / "00002").iterdir():
        p.unlink()
    assert main(argv) == 0
    _close(Exported(native, verify=True)[2], full.sample(2), outs)
    assert all(p.stat().st_mtime_ns == t for p, t in files.items() if "00002" not in p.parts)

    other = Mixture(MixtureConfig.from_file(preset).configs, {"things": 3, "chairs": 1}).to_preset(tmp_path / "o.json")
    capsys.readouterr()
    assert main([*argv[:2], str(other), *argv[3:]]) == 2
    assert "config.weights.things is 1.0 there, 3.0 here" in capsys.readouterr().err
    assert json.loads((native / "manifest.json").read_text())["config"] == manifest["config"]


CONFLICTS = [
    (["--dataset", "layers"], ["--dataset"]),
    (["--dataset", "bouncing"], ["--dataset"]),
    (["--fov-deg", "30"], ["--fov-deg"]),
    (["--motion-scale", "2"], ["--motion-scale"]),
    (["--preset", "chairs"], ["--preset"]),
    (["--config", "c.json"], ["--config"]),
    (["--width", "64"], ["--width 64", "--width 48"]),
    (["--num-frames", "3", "--height", "32"], ["--num-frames 3", "--num-frames 2"]),
    (["--outputs", "rgb,depth"], ["'chairs'", "Layers gives"]),
]


@pytest.mark.parametrize("command, argv, needles", [(c, a, n) for c in ("export", "preview", "stats")
                                                    for a, n in CONFLICTS if c != "stats" or "--outputs" not in a])
def test_flags_that_conflict_with_the_file_exit_2_naming_the_flag(preset, tmp_path, capsys, command, argv, needles):
    """Each refused before anything is written; the error names the flag (and the file's value for a size)."""
    out = tmp_path / ("out" if command == "export" else "p.png")
    extra = {"export": ["--out", str(out), "--num", "1", "--no-progress"], "preview": ["--out", str(out)],
             "stats": ["--num", "1"]}[command]
    capsys.readouterr()
    assert main([command, "--mixture", preset, *extra, *argv]) == 2
    err = capsys.readouterr().err
    assert all(n in err for n in needles), err
    assert not out.exists()


@pytest.mark.parametrize("write, needle", [
    (None, "does not exist"),
    ("{not json", "not valid JSON"),
    ('{"format": "flowsynth-mixture", "version": 2, "sources": []}', "version 2"),
    ('{"format": "other"}', "flowsynth-mixture"),
    ('{"format": "flowsynth-mixture", "version": 1, "sources": [{"name": "a", "kind": "blobs", "config": {}}]}',
     "unknown source kind 'blobs'"),
    ('{"format": "flowsynth-mixture", "version": 1, "sources": [{"name": "a", "kind": "layers", "config": '
     '{"fov_deg": 60}}]}', "unknown LayersConfig field"),
    ('{"format": "flowsynth-mixture", "version": 1, "sources": [{"name": "a", "kind": "layers", "config": {}}], '
     '"weights": {"b": 1}}', "weights must name"),
])
def test_a_missing_or_malformed_file_exits_2_with_the_path_and_what_is_wrong(tmp_path, capsys, write, needle):
    path = tmp_path / "bad.json"
    if write is not None:
        path.write_text(write)
    for command in (["export", "--out", str(tmp_path / "e"), "--num", "1"],
                    ["preview", "--out", str(tmp_path / "p.png")], ["stats", "--num", "1"]):
        capsys.readouterr()
        assert main([*command, "--mixture", str(path)]) == 2
        err = capsys.readouterr().err
        assert "--mixture" in err and str(path) in err and needle in err, err
    assert not (tmp_path / "e").exists() and not (tmp_path / "p.png").exists()


def test_size_flags_equal_to_the_files_are_accepted(preset, tmp_path):
    assert main(["preview", "--mixture", preset, "--out", str(tmp_path / "p.png"), "--width", "48", "--height", "32",
                 "--num-frames", "2"]) == 0


def test_preview_shows_a_sample_of_the_mixture_and_names_its_source(preset, tmp_path):
    """The PNG below its title line is the contact sheet of ``Mixture.from_preset(FILE).sample(index)``; its text
    chunks name the dataset, the source and the preset; the title line holds drawn text. One index of each source."""
    stream = Mixture.from_preset(preset, outputs=PREVIEW_LAYERS, seed=3)
    for k, name in enumerate(["things", "chairs"]):
        i = next(i for i in range(50) if stream.source(i) == k)
        png = tmp_path / f"{name}.png"
        assert main(["preview", "--mixture", preset, "--out", str(png), "--seed", "3", "--index", str(i)]) == 0
        with Image.open(png) as im:
            text, got = dict(im.text), np.asarray(im.convert("RGB"))
        assert text["flowsynth:dataset"] == "mixture" and text["flowsynth:source"] == name
        assert json.loads(text["flowsynth:config"]) == json.loads(open(preset).read())
        assert (text["flowsynth:seed"], text["flowsynth:index"]) == ("3", str(i))
        sheet = sample_preview(stream.sample(i))
        top = got.shape[0] - sheet.shape[0]
        assert top > 0
        np.testing.assert_array_equal(got[top:, :sheet.shape[1]], sheet)
        assert (got[:top] > 128).any(), "no title text drawn (light on the dark grey band)"


def test_contact_sheet_title_is_a_line_above_the_same_grid():
    """A title adds a band of text above the sheet without it, the grid unchanged; a title wider than the grid
    widens the sheet."""
    tiles = [("a", np.full((10, 60, 3), 200, np.uint8)), ("b", np.zeros((10, 60, 3), np.uint8))]
    plain = contact_sheet(tiles, columns=2)
    titled = contact_sheet(tiles, columns=2, title="source 'x'")
    top = titled.shape[0] - plain.shape[0]
    assert top > 0 and titled.shape[1] == plain.shape[1]
    np.testing.assert_array_equal(titled[top:], plain)
    assert (titled[:top] > 128).any() and (titled[:top] == 32).any()
    wide = contact_sheet(tiles, columns=2, title="a title much wider than two tiles sixty pixels wide each")
    assert wide.shape[1] > plain.shape[1]
    np.testing.assert_array_equal(wide[top:, :plain.shape[1]], plain)


def test_stats_of_a_mixture(preset, tmp_path, capsys):
    """``flowsynth stats --mixture``: the mean |flow| over valid pixels equals the one summed here from the
    Mixture's samples; category names come from both sources (an id they name differently joined by "|")."""
    assert main(["stats", "--mixture", preset, "--num", "4", "--json", str(tmp_path / "s.json")]) == 0
    st = json.loads((tmp_path / "s.json").read_text())
    assert st["config"] == json.loads(open(preset).read()) and st["num_samples"] == 4
    stream = Mixture.from_preset(preset, outputs=["flow_fw", "valid_fw"], seed=0)
    assert {stream.source(i) for i in range(4)} == {0, 1}, "both sources must occur among the 4 samples"
    mags, n = 0.0, 0
    for i in range(4):
        s = stream.sample(i)
        valid = s["valid_fw"][:, 0]
        mags += float(s["flow_fw"].to(torch.float64).norm(dim=1)[valid].sum())
        n += int(valid.sum())
    assert st["valid_pixels"] == n
    assert st["flow"]["mean"] == pytest.approx(mags / n, rel=1e-9)
    assert "room|background" in st["category_share"]
    assert sum(st["category_share"].values()) == pytest.approx(1.0)


@pytest.mark.parametrize("mask", ["valid", "visible"])
def test_flowpairs_over_layers_and_mixture_are_the_streams_samples(preset, photos, mask):
    """FlowPairs of a LayersConfig and of a MixtureConfig: item i is frames 0 and 1 of the stream's sample i (images
    rounded to 8 bits), its flow, and valid_fw (and not occ_fw for mask="visible")."""
    cfg = LayersConfig(**SIZE, texture_dir=photos)
    outs = ["rgb", "flow_fw", "valid_fw", "occ_fw"]
    for pairs, stream in ((FlowPairs(cfg, seed=2, length=3, mask=mask), Layers(cfg, outs, seed=2)),
                          (FlowPairs(MixtureConfig.from_file(preset), seed=2, length=3, mask=mask),
                           Mixture.from_preset(preset, outputs=outs, seed=2))):
        assert len(pairs) == 3
        for i in range(3):
            img1, img2, flow, valid = pairs[i]
            s = stream.sample(i)
            for t, img in enumerate((img1, img2)):
                assert np.abs(np.asarray(img) / 255 - s["rgb"][t].permute(1, 2, 0).numpy()).max() <= RGB_STEP
            np.testing.assert_array_equal(flow, s["flow_fw"][0].numpy())
            want = s["valid_fw"][0, 0].numpy()
            if mask == "visible":
                want = want & ~s["occ_fw"][0, 0].numpy()
            np.testing.assert_array_equal(valid, want)
    with pytest.raises(fs.ConfigError, match="num_frames >= 2"):
        FlowPairs(LayersConfig(width=48, height=32, num_frames=1))
    with pytest.raises(fs.ConfigError, match="MixtureConfig"):
        FlowPairs({"width": 48})


def test_export_of_a_mixture_checks_the_layout_against_every_source(photos, tmp_path):
    """A layout's checks run on each source: flyingthings3d sizes a BouncingThings-only mixture with a right camera
    (its outputs, its 7-digit frame numbers), is refused without one and for a mixture with a Layers source; nothing
    is written."""
    things = dataclasses.replace(_sources(photos)["things"], stereo_baseline=0.1)
    chairs = fs.BouncingThingsConfig.preset("chairs", **SIZE, num_objects=(1, 2), max_objects=2, render_mode="flat",
                                            stereo_baseline=0.1)
    stereo = MixtureConfig({"a": things, "b": chairs})
    assert {"rgb", "rgb_right", "disparity"} <= set(estimate(stereo, 2, layout="flyingthings3d").per_sample)
    with pytest.raises(fs.ConfigError, match="7 digits"):
        export_dataset(stereo, tmp_path / "ft3d", 10**7, layout="flyingthings3d", progress=False)
    mono = MixtureConfig({"a": dataclasses.replace(things, stereo_baseline=0.0), "b": chairs})
    with pytest.raises(fs.ConfigError, match="mixture source 'a'.*stereo_baseline"):
        export_dataset(mono, tmp_path / "ft3d", 1, layout="flyingthings3d", progress=False)
    with pytest.raises(fs.ConfigError, match="needs the outputs"):
        export_dataset(MixtureConfig({"things": things, "chairs": _sources(photos)["chairs"]}), tmp_path / "ft3d", 1,
                       layout="flyingthings3d", progress=False)
    assert not (tmp_path / "ft3d").exists()
