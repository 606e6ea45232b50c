"""An export never traps the user: validation before any write, resume that checks every file against
the manifest, disk-full handling, permissions, and a memory estimate that refuses impossible sizes.

Oracles: sha256 computed here with hashlib, a second export of the same samples into another folder,
``os.stat`` modes against the umask, and the kernel's own ENOSPC error raised where a write happens."""

import errno
import hashlib
import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

import flowsynth as fs
from flowsynth import memory
from flowsynth.cli import main
from flowsynth.datasets import Exported

SMALL = ["--width", "32", "--height", "24", "--num-frames", "2", "--motion", "kinematic",
         "--num-objects", "2,3", "--max-objects", "4"]
OUTS = ["--outputs", "depth,flow_fw,instance"]


def export(out: Path, num: int, *extra: str) -> int:
    return main(["export", "--out", str(out), "--num", str(num), "--no-progress", *OUTS, *SMALL, *extra])


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def manifest(root: Path) -> dict:
    return json.loads((root / "manifest.json").read_text())


def tree(root: Path) -> dict[str, str]:
    """relative path -> sha256 of every file under root except the manifest."""
    return {p.relative_to(root).as_posix(): sha(p) for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != "manifest.json"}


def no_temporaries(root: Path) -> bool:
    return not [p for p in root.rglob("*") if ".tmp-" in p.name]


@pytest.mark.parametrize("bad,fixed", [
    (["--num-frames", "1"], []),                      # flow outputs need 2 frames: found by the dataset
    (["--outputs", "depht"], []),                     # unknown output
    (["--width", "100000", "--height", "100000"], []),  # cannot fit in memory
])
def test_failed_validation_writes_nothing_and_the_fixed_command_runs(tmp_path, capsys, bad, fixed):
    out = tmp_path / "ds"
    assert export(out, 1, *bad) == 2
    assert not out.exists() or not any(out.iterdir()), sorted(out.iterdir())
    err = capsys.readouterr().err
    assert "error" in err and ("--" in err or "valid outputs" in err), err  # names the flag (or the choices)
    assert export(out, 1, *fixed) == 0  # no --overwrite needed: nothing of the failed run is in the way
    assert sorted(manifest(out)["samples"]) == ["00000"]


def test_manifest_appears_only_with_the_first_sample(tmp_path, monkeypatch, capsys):
    """A failure while generating sample 0 (say Warp runs out of memory) leaves no manifest behind."""
    from flowsynth.datasets import BouncingThings

    def boom(self, i):
        raise RuntimeError("simulated failure inside sample generation")

    out = tmp_path / "ds"
    with monkeypatch.context() as m:
        m.setattr(BouncingThings, "sample", boom)
        assert export(out, 2) == 1  # not flowsynth's error: the CLI reports a bug, with the traceback
    assert "simulated failure" in capsys.readouterr().err
    assert not (out / "manifest.json").exists()
    assert export(out, 2, "--seed", "5") == 0  # another seed: accepted, nothing to overwrite
    assert manifest(out)["seed"] == 5


def test_resume_checks_every_file_and_repairs(tmp_path, capsys):
    ref, out = tmp_path / "ref", tmp_path / "ds"
    assert export(ref, 4) == 0 and export(out, 4) == 0
    expected = tree(ref)
    assert tree(out) == expected
    m = manifest(out)
    for files in m["samples"].values():  # the manifest's per-file list is the oracle's hashes
        for rel, rec in files.items():
            assert rec["sha256"] == sha(out / rel) and rec["size"] == (out / rel).stat().st_size
    flow1 = next(p for p in (out / "00001").iterdir() if p.name.startswith("flow_fw"))
    flow1.unlink()                                            # a deleted flow file
    depth2 = next(p for p in (out / "00002").iterdir() if p.name.startswith("depth"))
    depth2.write_bytes(depth2.read_bytes() + b"junk")         # a file of the wrong size
    inst3 = next(p for p in (out / "00003").iterdir() if p.name.startswith("instance"))
    data = bytearray(inst3.read_bytes())
    data[-20] ^= 0xFF
    inst3.write_bytes(bytes(data))                            # same size, other bytes: only sha256 sees it
    (out / "notes.txt").write_text("mine")                    # foreign files
    (out / "00000" / "extra.txt").write_text("also mine")
    capsys.readouterr()

    assert export(out, 4) == 0                                # quick check: presence and sizes
    report = capsys.readouterr()
    assert tree(out) == dict(expected, **{"notes.txt": sha(out / "notes.txt"),
                                          "00000/extra.txt": sha(out / "00000" / "extra.txt"),
                                          inst3.relative_to(out).as_posix(): sha(inst3)})
    assert sha(inst3) != expected[inst3.relative_to(out).as_posix()]  # the quick check cannot see it
    text = report.out + report.err
    assert "notes.txt" in text and "00000/extra.txt" in text and "foreign" in text
    assert (out / "notes.txt").read_text() == "mine"

    assert export(out, 4, "--verify") == 0                    # full check: sha256 of every file
    assert sha(inst3) == expected[inst3.relative_to(out).as_posix()]
    assert (out / "00000" / "extra.txt").read_text() == "also mine"
    assert no_temporaries(out)


def test_killed_at_a_known_sample_resumes_to_the_same_bytes(tmp_path):
    """The export kills itself (SIGKILL) right after its second sample is journaled and placed
    (FLOWSYNTH_TEST_KILL_AFTER, a hook in flowsynth/export/exporter.py): a crash at a known point, whatever the
    machine's speed, where a kill timed by polling could come after the export had finished. Resume keeps the two
    samples (their files are not written again), makes the rest, and the result equals an uninterrupted export's
    bytes."""
    ref, out = tmp_path / "ref", tmp_path / "ds"
    assert export(ref, 6) == 0
    cmd = [sys.executable, "-m", "flowsynth.cli", "export", "--out", str(out), "--num", "6", "--no-progress", *OUTS,
           *SMALL]
    env = {k: v for k, v in os.environ.items() if k != "FLOWSYNTH_TEST_KILL_AFTER"}
    killed = subprocess.run(cmd, env=dict(env, FLOWSYNTH_TEST_KILL_AFTER="2"), capture_output=True, text=True,
                            timeout=600)
    assert killed.returncode == -9, killed.stderr[-2000:]
    done = sorted(p.name for p in out.iterdir() if p.name.isdigit())
    assert done == ["00000", "00001"]
    assert (out / ".journal.jsonl").exists() and (out / "manifest.json").exists()
    mtimes = {p: p.stat().st_mtime_ns for n in done for p in (out / n).iterdir()}
    resumed = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert all(p.stat().st_mtime_ns == m for p, m in mtimes.items())  # kept, not made again
    assert tree(out) == tree(ref)
    assert sorted(manifest(out)["samples"]) == [f"{i:05d}" for i in range(6)]
    assert not (out / ".journal.jsonl").exists() and no_temporaries(out)


def test_samples_without_a_camera_record_are_written_again(tmp_path, capsys):
    """An export whose manifest records no camera for a sample (written before cameras were recorded, or edited)
    is not complete: Exported.camera says so and how to repair it, and re-running the command writes those samples
    again (the same bytes) and records their cameras; the samples that have one are kept."""
    out = tmp_path / "ds"
    assert export(out, 3) == 0
    m = manifest(out)
    want, files = dict(m["cameras"]), tree(out)
    del m["cameras"]["00001"]
    (out / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(fs.ExportError, match="records no camera for sample 00001; re-run"):
        Exported(out).camera(1)
    assert Exported(out).camera(2) == want["00002"]
    kept = {p: p.stat().st_mtime_ns for n in ("00000", "00002") for p in (out / n).iterdir()}
    capsys.readouterr()
    assert export(out, 3) == 0
    assert "00001 (sample 00001 has no camera record)" in capsys.readouterr().err
    assert manifest(out)["cameras"] == want and tree(out) == files
    assert Exported(out).camera(1) == want["00001"]
    assert all(p.stat().st_mtime_ns == t for p, t in kept.items())


def test_stray_folder_where_a_sample_belongs_is_not_a_sample(tmp_path, capsys):
    out = tmp_path / "ds"
    assert export(out, 2) == 0
    (out / "00002").mkdir()
    (out / "00002" / "holiday.jpg").write_bytes(b"\xff\xd8 not a sample")
    assert export(out, 3) == 0
    assert sorted(manifest(out)["samples"]) == ["00000", "00001", "00002"]
    assert (out / "00002" / "holiday.jpg").read_bytes() == b"\xff\xd8 not a sample"
    report = capsys.readouterr()
    assert "00002/holiday.jpg" in report.out + report.err
    ds = Exported(out)
    assert len(ds) == 3 and ds[2]["depth"].shape == (2, 1, 24, 32)


def test_exported_verifies_quick_by_default_full_on_request(tmp_path):
    out = tmp_path / "ds"
    assert export(out, 2) == 0
    flow = next(p for p in (out / "00001").iterdir() if p.name.startswith("flow_fw"))
    flow.unlink()
    with pytest.raises(fs.errors.ExportError, match="00001"):
        Exported(out)                                          # default: quick check at construction
    assert len(Exported(out, verify="none")) == 2
    assert export(out, 2) == 0                                 # repaired
    depth = next(p for p in (out / "00000").iterdir() if p.name.startswith("depth"))
    data = bytearray(depth.read_bytes())
    data[-8] ^= 0x01
    depth.write_bytes(bytes(data))
    Exported(out)[0]                                           # quick: sizes agree, not caught
    with pytest.raises(fs.errors.ExportError, match="sha256"):
        Exported(out, verify="full")[0]
    with pytest.raises(fs.errors.ConfigError, match="verify"):
        Exported(out, verify="sometimes")


def test_disk_full_exits_3_keeps_finished_samples_and_cleans_up(tmp_path, monkeypatch, capsys):
    """ENOSPC raised by the file system while sample 2 is being written."""
    from flowsynth.io import atomic

    real = atomic._fsync_file

    def fsync(path):
        if ".tmp-00002-" in str(path):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        real(path)

    out = tmp_path / "ds"
    with monkeypatch.context() as m:
        m.setattr(atomic, "_fsync_file", fsync)
        assert export(out, 4) == 3
    err = capsys.readouterr().err
    assert os.strerror(errno.ENOSPC) in err and "re-run" in err
    assert sorted(manifest(out)["samples"]) == ["00000", "00001"]
    assert no_temporaries(out)
    kept = {n: (out / n / "meta.json").stat().st_mtime_ns for n in ("00000", "00001")}
    assert export(out, 4) == 0                                 # space is back: resume
    assert sorted(manifest(out)["samples"]) == ["00000", "00001", "00002", "00003"]
    assert {n: (out / n / "meta.json").stat().st_mtime_ns for n in kept} == kept


@pytest.mark.parametrize("umask", [0o022, 0o027])
def test_modes_follow_the_umask(tmp_path, umask):
    old = os.umask(umask)
    try:
        out = tmp_path / "ds"
        assert export(out, 2) == 0
    finally:
        os.umask(old)
    paths = [out, *out.rglob("*")]
    assert len(paths) > 4
    for p in paths:
        mode = stat.S_IMODE(p.stat().st_mode)
        assert mode == (0o777 if p.is_dir() else 0o666) & ~umask, (p, oct(mode))


def test_memory_estimate_refuses_huge_sizes_with_the_flags_and_gib(tmp_path, capsys, monkeypatch):
    out = tmp_path / "ds"
    assert main(["export", "--out", str(out), "--num", "1", "--width", "100000", "--height", "100000"]) == 2
    err = capsys.readouterr().err
    assert "--width 100000" in err and "--height 100000" in err and "GiB" in err
    need = memory.sample_memory_bytes(fs.BouncingThingsConfig(width=100000, height=100000)) / 2**30
    assert f"{need:.1f} GiB" in err and need > 1e5
    assert not out.exists()
    for cmd in (["preview", "--out", str(tmp_path / "p.png")], ["stats", "--num", "1"],  # the other commands
                ["export", "--out", str(out), "--num", "1", "--dry-run"]):
        assert main([*cmd, "--width", "100000", "--height", "100000"]) == 2
        assert "GiB" in capsys.readouterr().err
    assert not (tmp_path / "p.png").exists()
    # against a known amount of free memory: 4 workers of a mid-size sample do not fit in 2 GiB
    monkeypatch.setattr(memory, "available_memory_bytes", lambda: 2 << 30)
    cfg = fs.BouncingThingsConfig(width=640, height=480, num_frames=4)
    memory.check_sample_memory(cfg, processes=1)
    with pytest.raises(fs.errors.ConfigError, match="--workers"):
        memory.check_sample_memory(cfg, processes=4)


def test_available_memory_is_plausible():
    avail = memory.available_memory_bytes()
    total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    assert avail is not None and 0 < avail <= total


def _mount_tmpfs(path: Path, size: str, remount: bool = False) -> bool:
    opts = f"remount,size={size}" if remount else f"size={size}"
    cmd = ["mount", "-o", opts, str(path)] if remount else ["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(path)]
    return subprocess.run(cmd, capture_output=True).returncode == 0


def test_real_disk_full_on_a_small_tmpfs(tmp_path, capsys):
    """The file system itself runs out of space (a 120 KiB tmpfs), where root may mount one."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0 or not _mount_tmpfs(disk, "120k"):
        pytest.skip("mounting a tmpfs needs root; tests/test_resume.py's injected ENOSPC covers the rest")
    try:
        out = disk / "ds"
        assert export(out, 8) == 3
        err = capsys.readouterr().err
        assert os.strerror(errno.ENOSPC) in err and "re-run the same command" in err
        assert no_temporaries(out)
        finished = sorted(p.name for p in out.iterdir() if p.name.isdigit())
        assert 1 <= len(finished) < 8
        mtimes = {n: (out / n / "meta.json").stat().st_mtime_ns for n in finished}
        assert _mount_tmpfs(disk, "8m", remount=True)
        assert export(out, 8) == 0
        assert export(tmp_path / "ref", 8) == 0
        assert tree(out) == tree(tmp_path / "ref")
        assert {n: (out / n / "meta.json").stat().st_mtime_ns for n in finished} == mtimes
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)
