"""``--layout webdataset``: tar shards read back by readers nobody here wrote, equal to the stream.

Oracles: the ``webdataset`` package (``webdataset.WebDataset``), Python's ``tarfile``, Ray Data's
``read_webdataset`` (ray marker), with members decoded by numpy (``.npy``), Pillow (PNG) and the OpenEXR
library (EXR) here, compared with ``BouncingThings.sample``. Also: deterministic tars (headers, order, and
the same bytes from one worker, two workers and Ray), resume that rewrites only missing, damaged or
stale shards, and the streaming reader ``flowsynth.datasets.Shards`` (every sample once across
workers x ranks; seeded shuffles)."""

import io
import json
import tarfile
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

import flowsynth as fs
from flowsynth.cli import main
from flowsynth.datasets import BouncingThings, Exported, Shards

SMALL = ["--width", "64", "--height", "48", "--num-frames", "2", "--motion", "kinematic",
         "--num-objects", "2,3", "--max-objects", "4"]
CFG = fs.BouncingThingsConfig(width=64, height=48, num_frames=2, motion="kinematic", num_objects=(2, 3),
                              max_objects=4)
NUM, SHARD, SEED = 5, 2, 3  # shards of 2, 2 and 1 samples


def export(out: Path, *extra: str, num: int = NUM) -> int:
    return main(["export", "--out", str(out), "--num", str(num), "--seed", str(SEED), "--layout", "webdataset",
                 "--shard-size", str(SHARD), "--no-progress", *SMALL, *extra])


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wds") / "ds"
    assert export(out) == 0
    return out


@pytest.fixture(scope="module")
def stream(exported) -> list[dict]:
    outputs = json.loads((exported / "manifest.json").read_text())["outputs"]
    ds = BouncingThings(CFG, outputs=[*outputs, "meta"], seed=SEED)  # an export keeps the cameras and provenance
    return [ds.sample(i) for i in range(NUM)]


def shard_paths(root: Path) -> list[Path]:
    return sorted(root.glob("shard-*.tar"))


def _exr_channels(data: bytes, tmp: Path) -> dict[str, np.ndarray]:
    import OpenEXR

    path = tmp / "member.exr"
    path.write_bytes(data)
    return {k: np.array(c.pixels) for k, c in OpenEXR.File(str(path), separate_channels=True).channels().items()}


def _decode_member(suffix: str, value, tmp: Path):
    """(output key, frame or None, numpy array or str) of one member, decoded with numpy / Pillow / OpenEXR.
    ``value`` is the member's bytes, or what Ray's default decoder made of it (PNG, npy: arrays, a 0-d npy a
    Python scalar; json: dict)."""
    from PIL import Image

    name, ext = suffix.rsplit(".", 1)
    if ext == "npy":
        return name, None, np.load(io.BytesIO(value)) if isinstance(value, bytes) else np.asarray(value)
    if ext == "json":
        return "provenance", None, value if isinstance(value, dict) else json.loads(value)
    key, t = name.rsplit("_", 1)
    if ext == "png":
        a = value if isinstance(value, np.ndarray) else np.asarray(Image.open(io.BytesIO(value)))
        return key, int(t), (a.transpose(2, 0, 1) / 255.0 if a.ndim == 3 else a[None])
    channels = _exr_channels(value, tmp)
    names = {"depth": ["Z"], "flow_fw": ["flow.x", "flow.y"], "flow_bw": ["flow.x", "flow.y"]}[key]
    return key, int(t), np.stack([channels[c] for c in names])


def _without_added_nones(got, want):
    """``got`` less the None-valued keys that ``want`` lacks, at any depth. Ray Data keeps a JSON member as an
    Arrow struct column, which gives every row the union of the rows' keys (None where a row has none)."""
    if isinstance(got, dict) and isinstance(want, dict):
        return {k: _without_added_nones(v, want.get(k)) for k, v in got.items() if k in want or v is not None}
    if isinstance(got, list) and isinstance(want, list) and len(got) == len(want):
        return [_without_added_nones(a, b) for a, b in zip(got, want)]
    return got


def check_against_stream(members: dict, want: dict, tmp: Path) -> None:
    """Members of one key (suffix -> bytes or decoded value) equal the stream's sample ``want``."""
    frames: dict[str, dict[int, np.ndarray]] = {}
    got: dict = {}
    for suffix, value in members.items():
        key, t, a = _decode_member(suffix, value, tmp)
        if t is None:
            got[key] = a
        else:
            frames.setdefault(key, {})[t] = a
    got.update({k: np.stack([f[t] for t in sorted(f)]) for k, f in frames.items()})
    assert set(got) == set(want)
    assert _without_added_nones(got.pop("provenance"), json.loads(want["provenance"])) == json.loads(want["provenance"])
    for k, a in got.items():
        w = want[k].numpy()
        assert a.shape == w.shape, k
        if k == "rgb":
            assert np.abs(a - w).max() <= 0.5 / 255 + 1e-6
        else:
            assert np.array_equal(a.astype(w.dtype), w) and np.array_equal(a, w.astype(a.dtype)), k


def test_webdataset_package_reads_the_stream(exported, stream, tmp_path):
    import webdataset as wds

    urls = [str(p) for p in shard_paths(exported)]
    assert [Path(u).name for u in urls] == ["shard-000000.tar", "shard-000001.tar", "shard-000002.tar"]
    seen = []
    for item in wds.WebDataset(urls, shardshuffle=False):
        want = stream[int(item["__key__"])]
        case = {k.lower(): k for k in want}  # the package lowercases member suffixes: K.npy comes as k.npy
        members = {case.get(k.split(".")[0], k.split(".")[0]) + "." + k.split(".", 1)[1]: v
                   for k, v in item.items() if not k.startswith("__")}
        seen.append(item["__key__"])
        check_against_stream(members, want, tmp_path)
    assert seen == [f"{i:08d}" for i in range(NUM)]


def test_tar_headers_are_deterministic_and_members_sorted(exported):
    for j, path in enumerate(shard_paths(exported)):
        with tarfile.open(path) as tar:
            members = tar.getmembers()
        names = [m.name for m in members]
        assert names == sorted(names)
        keys = sorted({n.split(".", 1)[0] for n in names})
        assert keys == [f"{i:08d}" for i in range(j * SHARD, min((j + 1) * SHARD, NUM))]
        for m in members:
            assert m.isfile() and (m.mtime, m.uid, m.gid, m.uname, m.gname, m.mode) == (0, 0, 0, "", "", 0o644)
        assert path.read_bytes()[257:263] == b"ustar\x00"  # POSIX USTAR header
    manifest = json.loads((exported / "manifest.json").read_text())
    assert manifest["layout"] == "webdataset" and manifest["layout_options"]["shard_size"] == SHARD
    for name, files in manifest["samples"].items():  # each sample records its shard, as it is on disk
        [(rel, rec)] = files.items()
        assert rel == f"shard-{int(name) // SHARD:06d}.tar" and rec["size"] == (exported / rel).stat().st_size


def test_exported_reads_the_stream(exported, stream):
    ex = Exported(exported, verify=True)
    assert len(ex) == NUM
    for i in (4, 0, 3):  # out of order: the shard index is reused
        a, b = ex[i], dict(stream[i])
        assert set(a) == set(b) and a.pop("provenance") == b.pop("provenance")
        for k in b:
            assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
            if k == "rgb":
                assert (a[k] - b[k]).abs().max() <= 0.5 / 255 + 1e-6
            else:
                assert torch.equal(a[k], b[k]), k


def test_a_lens_camera_sits_beside_K(exported, tmp_path):
    """A lens camera's model and coefficients are the member KEY.camera.json beside KEY.K.npy (what native writes
    into meta.json as camera_model and camera_dist). Read with the webdataset package, they are the lens each
    sample was rendered with (drawn per sample, inside the configured ranges) and K.npy its K; Exported gives the
    stream's K and provenance, and camera(i) the same lens. A pinhole shard has no camera.json."""
    import webdataset as wds

    out = tmp_path / "lens"
    assert export(out, "--camera-model", "brown_conrady", "--camera-dist=-0.2,0,0,0",
                  "--camera-dist-max=-0.1,0.05,0.001,0.001", "--outputs", "depth,flow_fw", num=3) == 0
    cfg = fs.BouncingThingsConfig(**{**CFG.to_dict(), "camera_model": "brown_conrady",
                                     "camera_dist": (-0.2, 0, 0, 0), "camera_dist_max": (-0.1, 0.05, 0.001, 0.001)})
    ds, ex = BouncingThings(cfg, outputs=["depth", "flow_fw", "meta"], seed=SEED), Exported(out, verify=True)
    items = list(wds.WebDataset([str(p) for p in shard_paths(out)], shardshuffle=False))
    assert [item["__key__"] for item in items] == [f"{i:08d}" for i in range(3)]
    for i, item in enumerate(items):
        cam, want = ds.scene(i).camera, ds.sample(i)
        lens = json.loads(item["camera.json"])
        assert lens == {"model": "brown_conrady", "dist": list(cam.dist)}
        assert all(lo <= d <= hi for d, lo, hi in zip(lens["dist"], cfg.camera_dist, cfg.camera_dist_max))
        assert np.array_equal(np.load(io.BytesIO(item["k.npy"])), want["K"].numpy())
        got = ex[i]
        assert torch.equal(got["K"], want["K"]) and got["provenance"] == want["provenance"]
        assert ex.camera(i) == {**json.loads(want["provenance"])["camera"], **lens}
    with tarfile.open(shard_paths(out)[0]) as tar:
        names = tar.getnames()
    assert {"00000000.K.npy", "00000000.camera.json", "00000001.K.npy", "00000001.camera.json"} <= set(names)
    for path in shard_paths(exported):
        with tarfile.open(path) as tar:
            assert not [n for n in tar.getnames() if n.endswith(".camera.json")]


def same_shards(a: Path, b: Path) -> None:
    """The exports a and b hold the same shards byte for byte, and their manifests the same sample records and
    cameras."""
    assert [p.read_bytes() for p in shard_paths(a)] == [p.read_bytes() for p in shard_paths(b)]
    ma, mb = (json.loads((r / "manifest.json").read_text()) for r in (a, b))
    assert ma["samples"] == mb["samples"] and ma["cameras"] == mb["cameras"]


def test_two_workers_write_the_same_bytes(exported, tmp_path):
    assert export(tmp_path / "two", "--workers", "2") == 0
    same_shards(tmp_path / "two", exported)


def test_resume_rewrites_only_missing_damaged_or_stale_shards(exported, tmp_path, monkeypatch):
    import shutil

    from flowsynth.io.layouts.webdataset import WebDataset

    out = tmp_path / "ds"
    real = WebDataset.write

    def fail_on_3(self, sample, index, folder):
        if index == 3:
            raise OSError(28, "No space left on device")
        return real(self, sample, index, folder)

    with monkeypatch.context() as m:  # a failure inside shard 1: shard 0 is kept, nothing half-written
        m.setattr(WebDataset, "write", fail_on_3)
        assert export(out, "--workers", "1") == 3
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json", "shard-000000.tar"]
    kept = (out / "shard-000000.tar").stat().st_mtime_ns
    assert export(out) == 0
    assert (out / "shard-000000.tar").stat().st_mtime_ns == kept
    assert [p.read_bytes() for p in shard_paths(out)] == [p.read_bytes() for p in shard_paths(exported)]

    (out / "shard-000001.tar").unlink()                                            # missing
    with open(out / "shard-000002.tar", "ab") as f:                                # damaged (size)
        f.write(b"junk")
    stale = out / ".tmp-00004-x"                                                   # a crashed worker's staging
    stale.mkdir()
    shutil.copy(exported / "shard-000002.tar", stale / "shard-000002.tar")
    assert export(out) == 0
    assert (out / "shard-000000.tar").stat().st_mtime_ns == kept
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json", *(p.name for p in shard_paths(exported))]
    assert [p.read_bytes() for p in shard_paths(out)] == [p.read_bytes() for p in shard_paths(exported)]

    mtimes = {p.name: p.stat().st_mtime_ns for p in shard_paths(out)}
    assert export(out, num=6) == 0  # shard 2 held sample 4 only; now it holds 4 and 5: written again
    assert export(tmp_path / "ref6", num=6) == 0
    assert {p.name: p.stat().st_mtime_ns for p in shard_paths(out)[:2]} == {k: mtimes[k] for k in sorted(mtimes)[:2]}
    assert [p.read_bytes() for p in shard_paths(out)] == [p.read_bytes() for p in shard_paths(tmp_path / "ref6")]


def test_cli_refuses_bad_shard_sizes(tmp_path, capsys):
    assert export(tmp_path / "a", "--shard-size", "0") == 2
    assert "--shard-size" in capsys.readouterr().err
    assert main(["export", "--out", str(tmp_path / "b"), "--num", "1", "--shard-size", "4", *SMALL]) == 2
    assert "webdataset" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


# -- the streaming reader ---------------------------------------------------------------------------------


class _Indices(torch.utils.data.IterableDataset):
    """The sample indices a Shards copy yields (keeps DataLoader traffic small)."""

    def __init__(self, shards: Shards) -> None:
        self.shards = shards

    def __iter__(self):
        for s in self.shards:
            yield int(s["index"])


def _read(root: Path, workers: int, **kw) -> list[int]:
    loader = torch.utils.data.DataLoader(_Indices(Shards(root, **kw)), num_workers=workers, batch_size=None,
                                         timeout=600 if workers else 0)
    return list(loader)


@pytest.mark.parametrize("world,workers", [(1, 0), (1, 2), (2, 0), (3, 2)])
def test_shards_every_sample_once_across_workers_and_ranks(exported, world, workers):
    seen = [i for rank in range(world) for i in _read(exported, workers, rank=rank, world_size=world, seed=1)]
    assert sorted(seen) == list(range(NUM))


def test_shards_take_rank_from_torch_distributed(exported, monkeypatch):
    dist = torch.distributed
    explicit = [list(Shards(exported, rank=r, world_size=2).shards()) for r in range(2)]
    monkeypatch.setattr(dist, "is_initialized", lambda: True)
    monkeypatch.setattr(dist, "get_world_size", lambda group=None: 2)
    for r in range(2):
        monkeypatch.setattr(dist, "get_rank", lambda group=None, r=r: r)
        assert list(Shards(exported).shards()) == explicit[r]
    monkeypatch.setenv("RANK", "1")  # torchrun's environment comes first: a spawned worker has no process group
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setattr(dist, "is_initialized", lambda: False)
    assert list(Shards(exported).shards()) == explicit[1]
    with pytest.raises(fs.ConfigError, match="rank"):
        Shards(exported, rank=2, world_size=2)


def test_shards_shuffle_is_seeded_per_epoch(exported, stream):
    def epoch(ds, e):
        ds.set_epoch(e)
        return [int(s["index"]) for s in ds]

    a, b = Shards(exported, seed=7, buffer=2), Shards(exported, seed=7, buffer=2)
    orders = [epoch(a, e) for e in range(4)]
    assert orders == [epoch(b, e) for e in range(4)]                  # same seed, same epochs: same order
    assert all(sorted(o) == list(range(NUM)) for o in orders)         # a permutation every epoch
    assert len({tuple(o) for o in orders}) > 1                        # epochs differ
    assert [list(a.shards(e)) for e in range(4)] != [list(a.shards(0))] * 4  # the shard order too
    assert epoch(Shards(exported, shuffle=False), 3) == list(range(NUM))
    plain = list(Shards(exported, shuffle=False))
    for s, want in zip(plain, stream):                                 # what it yields is the stream's sample
        assert s.pop("provenance") == want["provenance"]
        assert torch.equal(s["depth"], want["depth"]) and torch.equal(s["flow_fw"], want["flow_fw"])
        assert s["instance"].dtype == torch.int32 and torch.equal(s["instance"], want["instance"])


def test_shards_refuses_other_layouts(tmp_path):
    assert main(["export", "--out", str(tmp_path / "n"), "--num", "1", "--outputs", "depth", "--no-progress",
                 *SMALL]) == 0
    with pytest.raises(fs.errors.ExportError, match="webdataset"):
        Shards(tmp_path / "n")


def test_readers_name_a_missing_or_broken_manifest(tmp_path):
    """Exported and Shards read an export's manifest alike (flowsynth.io.integrity.read_manifest): a folder without
    one, or with one that is not JSON, is an ExportError that says what the folder should be."""
    (tmp_path / "empty").mkdir()
    (tmp_path / "torn").mkdir()
    (tmp_path / "torn" / "manifest.json").write_text('{"layout": "webdata')
    for reader in (Exported, Shards):
        with pytest.raises(fs.ExportError, match="could not find .*manifest.json; is .* written by `flowsynth export`"):
            reader(tmp_path / "empty")
        with pytest.raises(fs.ExportError, match="manifest.json is not valid JSON"):
            reader(tmp_path / "torn")


# -- Ray -------------------------------------------------------------------------------------------------


@pytest.mark.ray
def test_ray_read_webdataset_reads_the_stream(ray_cluster, exported, stream, tmp_path):
    rows = ray_cluster.data.read_webdataset([str(p) for p in shard_paths(exported)]).take_all()
    assert sorted(r["__key__"] for r in rows) == [f"{i:08d}" for i in range(NUM)]
    for r in rows:
        members = {k: v for k, v in r.items() if not k.startswith("__")}
        check_against_stream(members, stream[int(r["__key__"])], tmp_path)


@pytest.mark.ray
def test_ray_engine_writes_the_same_shards(ray_cluster, exported, tmp_path):
    assert export(tmp_path / "ray", "--engine", "ray") == 0
    same_shards(tmp_path / "ray", exported)
    assert Counter(p.name.split("-")[0] for p in (tmp_path / "ray").iterdir()) == {"manifest.json": 1, "shard": 3}


def test_shards_split_over_ranks_known_from_the_process_group_only(exported, tmp_path):
    """Two real ranks that know their rank from ``init_process_group`` alone (as ``mp.spawn`` starts them: no
    ``RANK`` in the environment), each reading through ``fs.datasets.loader``'s forkserver workers, which have no
    process group: every sample once over both ranks."""
    import os
    import socket
    import subprocess
    import sys

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK")}
    program = Path(__file__).with_name("shards_rank_program.py")
    procs = [subprocess.Popen([sys.executable, str(program), str(exported), str(r), str(port),
                               str(tmp_path / f"rank{r}.json")], env=env) for r in range(2)]
    assert [p.wait(timeout=600) for p in procs] == [0, 0]
    got = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(2)]
    assert sorted(got[0] + got[1]) == list(range(NUM)), got
