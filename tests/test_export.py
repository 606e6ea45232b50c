"""Export: round trip against the stream, crash safety under SIGKILL, every layout's bookkeeping, dry run,
CLI errors. Each layout's format is proven against a reader nobody here wrote in tests/test_layout_<name>.py."""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import flowsynth as fs
from flowsynth.cli import main
from flowsynth.datasets import BouncingThings, Exported
from flowsynth.io import layouts
from flowsynth.io.sampleio import file_digest

SMALL = ["--width", "32", "--height", "24", "--num-frames", "2", "--motion", "kinematic",
         "--num-objects", "2,3", "--max-objects", "4"]
CFG = fs.BouncingThingsConfig(width=32, height=24, num_frames=2, motion="kinematic", num_objects=(2, 3),
                              max_objects=4)
FLOAT_OUTS = ["depth", "distance", "normals", "position", "flow_fw", "flow_bw", "valid_fw", "occ_fw", "oof_bw",
              "motion", "instance", "category", "asset", "object_valid", "object_category", "world_T_obj",
              "box3d_corners", "box2d_amodal", "box2d_visible", "visible_pixels"]


def check_manifest(root: Path, num: int):
    """Every file under root is the manifest or recorded in it with its true size and sha256, and no
    two samples share a file."""
    manifest = json.loads((root / "manifest.json").read_text())
    assert sorted(manifest["samples"]) == [f"{i:05d}" for i in range(num)]
    owners: dict[str, set[int]] = {}
    for name, files in manifest["samples"].items():
        for f in files:
            owners.setdefault(f, set()).add(int(name))
    # a file belongs to exactly the samples of one unit of the layout (one sample; a webdataset shard's)
    for unit in layouts.get(manifest["layout"], **manifest["layout_options"]).units(num):
        for i in unit:
            assert all(owners[f] == set(unit) for f in manifest["samples"][f"{i:05d}"]), (i, unit)
    recorded = [*manifest["index"], *owners]
    assert len(recorded) == len(set(recorded))
    on_disk = sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())
    assert on_disk == sorted([*recorded, "manifest.json"])
    for files in [manifest["index"], *manifest["samples"].values()]:
        for f, rec in files.items():
            assert file_digest(root / f) == rec["sha256"] and (root / f).stat().st_size == rec["size"]
    return manifest


def test_exported_equals_stream(tmp_path):
    from flowsynth.export import export_dataset

    root = export_dataset(CFG, tmp_path / "ds", 3, seed=4, outputs=FLOAT_OUTS, progress=False)
    manifest = check_manifest(root, 3)
    assert manifest["seed"] == 4 and manifest["layout"] == "native" and manifest["versions"]["warp-lang"]
    ds = BouncingThings(CFG, outputs=[*FLOAT_OUTS, "meta"], seed=4)  # an export keeps the cameras and provenance
    ex = Exported(root, verify=True)
    assert len(ex) == 3
    for i in range(3):
        a, b = ex[i], ds.sample(i)
        assert set(a) == set(b)
        assert a.pop("provenance") == b.pop("provenance")  # the scene record, character for character
        for k in b:
            assert a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]), k


def test_exported_rgb_within_quantisation(tmp_path):
    from flowsynth.export import export_dataset

    root = export_dataset(CFG, tmp_path / "ds", 1, outputs=["rgb", "flow_fw"], progress=False)
    a, b = Exported(root)[0], BouncingThings(CFG, outputs=["rgb", "flow_fw"]).sample(0)
    assert (a["rgb"] - b["rgb"]).abs().max() <= 0.5 / 255 + 1e-6
    assert torch.equal(a["flow_fw"], b["flow_fw"])


def test_sigkill_then_resume(tmp_path):
    """SIGKILL after the 17th of 18 samples, one past a manifest rewrite (every 16 samples): the manifest holds 16
    records and the journal the 17th. The export kills itself there (FLOWSYNTH_TEST_KILL_AFTER, a hook in
    flowsynth/export/exporter.py), so the crash is at that point on a machine of any speed. The resume keeps all 17
    (their files are not written again), and the result is a complete export equal byte for byte to an uninterrupted
    one."""
    from flowsynth.export import export_dataset

    out, num, outputs = tmp_path / "ds", 18, ["depth", "flow_fw", "instance"]
    cmd = [sys.executable, "-m", "flowsynth.cli", "export", "--out", str(out), "--num", str(num), "--no-progress",
           "--outputs", ",".join(outputs), *SMALL]
    env = {k: v for k, v in os.environ.items() if k != "FLOWSYNTH_TEST_KILL_AFTER"}
    killed = subprocess.run(cmd, env=dict(env, FLOWSYNTH_TEST_KILL_AFTER="17"), capture_output=True, text=True,
                            timeout=600)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    done = sorted(p.name for p in out.iterdir() if p.name.isdigit())
    assert done == [f"{i:05d}" for i in range(17)]
    assert sorted(json.loads((out / "manifest.json").read_text())["samples"]) == done[:16]
    assert [json.loads(line)["sample"] for line in (out / ".journal.jsonl").read_text().splitlines()] == ["00016"]
    mtimes = {p: p.stat().st_mtime_ns for n in done for p in (out / n).iterdir()}
    resumed = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    check_manifest(out, num)
    assert all(p.stat().st_mtime_ns == m for p, m in mtimes.items())  # nothing lost, nothing made again
    ref = export_dataset(CFG, tmp_path / "ref", num, outputs=outputs, progress=False)
    files = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    assert files == {p.relative_to(ref).as_posix() for p in ref.rglob("*") if p.is_file()}
    assert [f for f in sorted(files) if (out / f).read_bytes() != (ref / f).read_bytes() and f != "manifest.json"] == []
    a, b = (json.loads((r / "manifest.json").read_text()) for r in (out, ref))
    assert a["samples"] == b["samples"] and a["config"] == b["config"] and a["outputs"] == b["outputs"]


LENS = ["--camera-model", "brown_conrady", "--camera-dist=-0.2,0,0,0", "--camera-dist-max=-0.1,0.05,0.001,0.001"]


def test_the_manifest_records_each_sample_camera_in_every_layout(tmp_path):
    """sintel's format holds no camera, so the manifest records each sample's: an export with a lens drawn per
    sample gives back, per sample, the K, model and coefficients that sample's scene was rendered with (the
    stream's scene and provenance), each coefficient inside its configured range; a pinhole export records model
    "pinhole" and no coefficients."""
    out = tmp_path / "sintel"
    assert main(["export", "--out", str(out), "--num", "2", "--layout", "sintel", "--no-progress", *SMALL, *LENS]) == 0
    cfg = fs.BouncingThingsConfig(**{**CFG.to_dict(), "camera_model": "brown_conrady",
                                     "camera_dist": (-0.2, 0, 0, 0), "camera_dist_max": (-0.1, 0.05, 0.001, 0.001)})
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"] == json.loads(json.dumps(cfg.to_dict()))
    assert {p.name for p in (out / "Sintel" / "training").iterdir()} == {"clean", "flow", "occlusions"}
    stream, ex = BouncingThings(cfg, outputs=["rgb", "flow_fw", "occ_fw", "provenance"]), Exported(out)
    for i in range(2):
        cam, scene = manifest["cameras"][f"{i:05d}"], stream.scene(i)
        assert ex.camera(i) == cam and set(cam) == {"K", "width", "height", "model", "dist"}
        assert cam["model"] == scene.camera.model == "brown_conrady" and cam["dist"] == list(scene.camera.dist)
        assert (cam["width"], cam["height"]) == (CFG.width, CFG.height)
        assert torch.equal(torch.tensor(cam["K"], dtype=torch.float64), torch.from_numpy(scene.camera.K))
        assert cam == {"model": "pinhole", "dist": [], **json.loads(stream.sample(i)["provenance"])["camera"]}
        assert all(lo <= d <= hi for d, lo, hi in zip(cam["dist"], cfg.camera_dist, cfg.camera_dist_max))
    assert manifest["cameras"]["00000"]["dist"] != manifest["cameras"]["00001"]["dist"]
    assert main(["export", "--out", str(tmp_path / "pin"), "--num", "1", "--outputs", "depth", "--no-progress",
                 *SMALL]) == 0
    pin = Exported(tmp_path / "pin").camera(0)
    assert (pin["model"], pin["dist"]) == ("pinhole", []) and pin["K"] == BouncingThings(CFG).scene(0).camera.K.tolist()


def test_two_workers_match_one(tmp_path):
    from flowsynth.export import export_dataset

    a = export_dataset(CFG, tmp_path / "a", 4, outputs=["depth", "instance"], workers=2, progress=False)
    b = export_dataset(CFG, tmp_path / "b", 4, outputs=["depth", "instance"], workers=1, progress=False)
    ma, mb = (json.loads((r / "manifest.json").read_text())["samples"] for r in (a, b))
    assert ma == mb


@pytest.mark.parametrize("name", layouts.names())
def test_every_layout_round_trips_and_keeps_books(tmp_path, name):
    """Generic contract of a layout: files recorded in the manifest, read back with the stream's keys, shapes
    and dtypes; 3 frames so layouts that store frame pairs write several per sample."""
    from flowsynth.export import export_dataset

    cfg = fs.BouncingThingsConfig(**{**CFG.to_dict(), "num_frames": 3, "stereo_baseline": 0.1})  # for flyingthings3d
    lay = layouts.get(name)
    root = export_dataset(cfg, tmp_path / name, 2, seed=1, layout=name, progress=False)
    manifest = check_manifest(root, 2)
    assert manifest["layout"] == name and manifest["outputs"] == list(lay.default_outputs)
    ex = Exported(root, verify=True)
    stream = BouncingThings(cfg, outputs=[*lay.default_outputs, "meta"], seed=1)
    assert len(ex) == 2
    for i in range(2):
        a, b = ex[i], stream.sample(i)
        assert set(a) <= set(b) and {"rgb", "flow_fw"} <= set(a)
        assert a.pop("provenance", b["provenance"]) == b.pop("provenance")  # the scene record, where kept
        for k in a:
            assert a[k].shape == b[k].shape and a[k].dtype == b[k].dtype, k
        assert (a["rgb"] - b["rgb"]).abs().max() <= 0.5 / 255 + 1e-6
    lay.clear(root)
    assert sorted(p.name for p in root.iterdir()) == ["manifest.json"]


def test_layout_checks_refuse_before_writing(tmp_path):
    from flowsynth.errors import ConfigError
    from flowsynth.export import export_dataset

    cfg = fs.BouncingThingsConfig(**{**CFG.to_dict(), "stereo_baseline": 0.1})  # flyingthings3d needs stereo
    one = fs.BouncingThingsConfig(**{**cfg.to_dict(), "num_frames": 1})
    for name in layouts.names():
        lay = layouts.get(name)
        if lay.min_frames > 1:
            with pytest.raises(ConfigError, match="num_frames"):
                export_dataset(one, tmp_path / name, 1, layout=name, progress=False)
        if lay.required_outputs:
            with pytest.raises(ConfigError, match="needs the outputs"):
                export_dataset(cfg, tmp_path / name, 1, layout=name, outputs=["depth"], progress=False)
        if lay.stored_outputs is not None:
            with pytest.raises(ConfigError, match="stores only"):
                export_dataset(cfg, tmp_path / name, 1, layout=name, outputs=[*lay.required_outputs, "depth"],
                               progress=False)
        assert not (tmp_path / name).exists()
    with pytest.raises(ConfigError, match="unknown layout"):
        layouts.get("nope")


def test_cli_bad_inputs(tmp_path, capsys):
    assert main(["export", "--out", str(tmp_path / "a"), "--num", "1", "--outputs", "depht", *SMALL]) == 2
    assert "valid outputs" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert main(["export", "--out", str(tmp_path / "b"), "--num", "1", "--config", str(bad)]) == 2
    assert "not valid JSON" in capsys.readouterr().err
    wrong = tmp_path / "wrong.toml"
    wrong.write_text("widht = 3\n")
    assert main(["export", "--out", str(tmp_path / "b"), "--num", "1", "--config", str(wrong)]) == 2
    assert "unknown BouncingThingsConfig field" in capsys.readouterr().err
    assert main(["export", "--out", str(tmp_path / "c"), "--num", "1", "--no-progress", "--outputs", "depth",
                 *SMALL]) == 0
    assert main(["export", "--out", str(tmp_path / "c"), "--num", "1", "--no-progress", "--outputs", "depth",
                 "--seed", "9", *SMALL]) == 2
    assert "other settings: seed is 0 there, 9 here; resume it" in capsys.readouterr().err
    assert main(["export", "--out", str(tmp_path / "c"), "--num", "1", "--no-progress", "--outputs", "depth",
                 "--seed", "9", "--overwrite", *SMALL]) == 0
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["export", "--out", str(blocker / "sub"), "--num", "1", "--no-progress", *SMALL]) == 2
    assert "cannot write" in capsys.readouterr().err
    assert main(["export", "--out", str(tmp_path / "d"), "--num", "1", "--width", "-3"]) == 2
    assert "width" in capsys.readouterr().err


def test_cli_entry_point_exit_codes(tmp_path):
    r = subprocess.run([sys.executable, "-m", "flowsynth.cli", "export", "--out", str(tmp_path), "--num", "0"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "num must be" in r.stderr


def test_preview_writes_png(tmp_path):
    out = tmp_path / "p.png"
    assert main(["preview", "--out", str(out), *SMALL]) == 0
    from PIL import Image

    assert Image.open(out).size[0] > CFG.width
    assert os.path.getsize(out) > 1000


def test_dry_run_writes_nothing_and_predicts_the_real_sizes(tmp_path, capsys):
    from flowsynth.export import estimate, export_dataset

    out = tmp_path / "dry"
    assert main(["export", "--out", str(out), "--num", "3", "--dry-run", *SMALL]) == 0
    printed = capsys.readouterr().out
    assert not out.exists() and "nothing written" in printed
    sizes = estimate(CFG, 3)
    total_line = next(line for line in printed.splitlines() if line.startswith("total"))
    assert total_line.split()[1:] == [f"{sum(sizes.per_sample.values()):,}", f"{sizes.total:,}"]
    # sample 0 exported for real is the very sample the dry run measured: equal byte for byte, per output
    one = export_dataset(CFG, tmp_path / "one", 1, progress=False)
    files = json.loads((one / "manifest.json").read_text())["samples"]["00000"]
    by_output: dict[str, int] = {}
    for rel, rec in files.items():
        stem = Path(rel).stem
        key = stem.rsplit("_", 1)[0] if stem[-4:].isdigit() else stem
        by_output[key] = by_output.get(key, 0) + rec["size"]
    assert by_output == sizes.per_sample
    # other samples compress differently: 3 samples here came to 1.3 % above 3 x sample 0
    three = export_dataset(CFG, tmp_path / "three", 3, progress=False)
    real = sum(r["size"] for f in json.loads((three / "manifest.json").read_text())["samples"].values()
               for r in f.values())
    assert abs(real - sizes.total) <= 0.1 * sizes.total


def test_layouts_that_number_pairs_refuse_too_many():
    from flowsynth.io import layouts

    cfg = fs.BouncingThingsConfig(num_frames=3)  # 2 pairs per sample
    outputs = ("rgb", "flow_fw", "valid_fw")
    for name, digits in (("flyingchairs", 5), ("kitti", 6)):
        layout = layouts.get(name)
        layout.check(cfg, layout.required_outputs, num=10**digits // 2 - 1)  # 10**digits - 2 pairs fit
        with pytest.raises(fs.ConfigError, match=f"{digits} digits"):
            layout.check(cfg, layout.required_outputs, num=10**digits // 2)
    layouts.get("native").check(cfg, outputs, num=10**7)
