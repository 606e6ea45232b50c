"""Ray engine (flowsynth.distributed) on a local 2-CPU cluster: dataset rows equal the stream, Ray export equals
local export byte for byte, a killed actor loses nothing, a killed driver resumes. Without Ray: nothing imports
it, and asking for it names the install command."""

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch

import flowsynth as fs
from flowsynth.cli import main

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["--width", "32", "--height", "24", "--num-frames", "2", "--motion", "kinematic",
         "--num-objects", "2,3", "--max-objects", "4"]
CFG = fs.BouncingThingsConfig(width=32, height=24, num_frames=2, motion="kinematic", num_objects=(2, 3),
                              max_objects=4)
OUTS = "depth,flow_fw,occ_fw,instance,box2d_visible,object_valid"


def test_nothing_imports_ray():
    code = ("import sys, flowsynth as fs, flowsynth.cli, flowsynth.export, flowsynth.stats\n"
            "from flowsynth.datasets import BouncingThings, Exported\n"
            "fs.BouncingThingsConfig(); fs.datasets\n"
            "bad = sorted(m for m in sys.modules if m == 'ray' or m.startswith('ray.'))\n"
            "assert not bad, bad\n")
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))


def test_ray_engine_without_ray_names_the_install_command(tmp_path, monkeypatch, capsys):
    for name in [m for m in sys.modules if m == "ray" or m.startswith("ray.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError, as when it is not installed
    out = tmp_path / "ds"
    assert main(["export", "--out", str(out), "--num", "2", "--engine", "ray", "--no-progress", *SMALL]) == 2
    err = capsys.readouterr().err
    assert "pip install 'flowsynth[ray]'" in err and "scripts/setup.sh --ray" in err
    assert not out.exists()  # refused before anything was written
    with pytest.raises(fs.ConfigError, match=r"flowsynth\[ray\]"):
        from flowsynth.distributed import ray_dataset

        ray_dataset(CFG, 2)


# -- on a local Ray cluster of exactly 2 CPUs ---------------------------------------------------------------


@pytest.fixture(scope="module")
def cluster(ray_cluster) -> str:
    """The address of this module's local 2-CPU Ray cluster (conftest's ``ray_cluster``)."""
    return ray_cluster.get_runtime_context().gcs_address


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _same_export(a: Path, b: Path) -> None:
    """Every file byte-identical; manifests equal except the wall-clock seconds per sample."""
    ta, tb = _tree(a), _tree(b)
    assert sorted(ta) == sorted(tb)
    assert [k for k in ta if k != "manifest.json" and ta[k] != tb[k]] == []
    ma, mb = (json.loads(t["manifest.json"]) for t in (ta, tb))
    for m in (ma, mb):
        assert m["stats"].pop("seconds_per_sample")["mean"] > 0
    assert ma == mb


@pytest.mark.ray
def test_ray_dataset_equals_stream(cluster):
    from flowsynth.distributed import ray_dataset

    outputs = [*OUTS.split(","), "meta"]
    rows = ray_dataset(CFG, 4, seed=3, outputs=outputs, start=5).take_all()
    ds = fs.datasets.BouncingThings(CFG, outputs=outputs, seed=3)
    assert sorted(int(r["index"]) for r in rows) == [5, 6, 7, 8]
    for r in rows:
        s = ds.sample(int(r["index"]))
        assert set(r) == set(s)
        assert str(r.pop("provenance")) == s.pop("provenance")
        for k, v in s.items():
            got = torch.as_tensor(r[k])
            assert got.dtype == v.dtype and torch.equal(got, v), k


@pytest.mark.ray
def test_ray_export_equals_local_export(cluster, tmp_path):
    for layout in ("native", "flyingchairs"):
        args = ["--num", "3", "--seed", "7", "--layout", layout, "--no-progress", *SMALL]
        if layout == "native":
            args += ["--outputs", OUTS]
        assert main(["export", "--out", str(tmp_path / f"ray-{layout}"), "--engine", "ray", *args]) == 0
        assert main(["export", "--out", str(tmp_path / f"local-{layout}"), *args]) == 0
        _same_export(tmp_path / f"ray-{layout}", tmp_path / f"local-{layout}")


def _parent(pid: int) -> int:
    return int((Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[1])


def _ours(pid: int) -> bool:
    """``pid`` descends from this test process (so it belongs to this test's cluster, not another run's)."""
    while pid > 1:
        pid = _parent(pid)
        if pid == os.getpid():
            return True
    return False


def _actor_pids(name: str) -> list[int]:
    """PIDs of this cluster's Ray actor processes whose title names ``name`` (``ray::MapWorker(...)``)."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if name.encode() in (d / "cmdline").read_bytes() and _ours(int(d.name)):
                    pids.append(int(d.name))
            except OSError:
                continue
    return pids


def _done(out: Path) -> int:
    return len([p for p in out.iterdir() if p.name.isdigit()]) if out.exists() else 0


@pytest.mark.ray
def test_ray_export_from_a_driver_with_cuda_writes_the_local_bytes(cluster, tmp_path, monkeypatch):
    """Issue 52: Ray's actors are processes the raylet starts, not forks of the driver, so a driver that initialised
    CUDA (made to say so here: flowsynth.processes.cuda_initialised) still exports through them, byte for byte as
    one local process writes (a forked worker would raise ForkError)."""
    from flowsynth import processes
    from flowsynth.export import export_dataset

    export_dataset(CFG, tmp_path / "local", 3, seed=2, outputs=OUTS.split(","), progress=False)
    monkeypatch.setattr(processes, "cuda_initialised", lambda: True)
    export_dataset(CFG, tmp_path / "ray", 3, seed=2, outputs=OUTS.split(","), engine="ray", workers=2, progress=False)
    _same_export(tmp_path / "ray", tmp_path / "local")


@pytest.mark.ray
def test_killed_actor_loses_nothing(cluster, tmp_path):
    from flowsynth.export import export_dataset

    out, num = tmp_path / "ray", 8
    errors: list[BaseException] = []

    def run():
        try:
            export_dataset(CFG, out, num, seed=1, outputs=OUTS.split(","), engine="ray", workers=2, progress=False)
        except BaseException as e:  # reported by the assertion below
            errors.append(e)

    thread = threading.Thread(target=run)
    thread.start()
    deadline = time.time() + 300
    while time.time() < deadline and _done(out) < 1:
        time.sleep(0.05)
    victims = _actor_pids("WriterActor")
    assert victims and _done(out) < num, "no actor was running while samples remained; make the export longer"
    os.kill(victims[0], signal.SIGKILL)
    thread.join(600)
    assert not thread.is_alive() and not errors, errors
    export_dataset(CFG, tmp_path / "local", num, seed=1, outputs=OUTS.split(","), progress=False)
    _same_export(out, tmp_path / "local")


@pytest.mark.ray
def test_killed_driver_resumes(cluster, tmp_path):
    """The driver SIGKILLs itself once 2 samples are journaled and placed (FLOWSYNTH_TEST_KILL_AFTER, a hook in
    flowsynth/export/exporter.py: a crash at that point on a machine of any speed, not after a sleep), with the next
    jobs running in its actors. Once those actors are gone, the same command resumes: the 2 samples are kept (their
    files not written again), and the files equal a local export's byte for byte."""
    out, num = tmp_path / "ray", 8
    cmd = [sys.executable, "-m", "flowsynth.cli", "export", "--out", str(out), "--num", str(num), "--engine", "ray",
           "--address", cluster, "--outputs", OUTS, "--no-progress", *SMALL]
    env = dict({k: v for k, v in os.environ.items() if k != "FLOWSYNTH_TEST_KILL_AFTER"}, PYTHONPATH=str(ROOT))
    with open(tmp_path / "killed.err", "w") as err:  # a file, not a pipe: no process Ray started can hold it open
        killed = subprocess.run(cmd, cwd=ROOT, env=dict(env, FLOWSYNTH_TEST_KILL_AFTER="2"),
                                stdout=subprocess.DEVNULL, stderr=err, timeout=600)
    assert killed.returncode == -signal.SIGKILL, (tmp_path / "killed.err").read_text()[-2000:]
    before = sorted(p.name for p in out.iterdir() if p.name.isdigit())
    assert len(before) == 2 and sorted(json.loads((out / "manifest.json").read_text())["samples"]) == []
    journaled = [json.loads(line)["sample"] for line in (out / ".journal.jsonl").read_text().splitlines()]
    assert sorted(journaled) == before
    deadline = time.time() + 60  # Ray kills the actors of a dead driver; wait until none can write any more
    while _actor_pids("WriterActor") and time.time() < deadline:
        time.sleep(0.1)
    assert _actor_pids("WriterActor") == []
    mtimes = {p: p.stat().st_mtime_ns for n in before for p in (out / n).iterdir()}
    done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert all(p.stat().st_mtime_ns == m for p, m in mtimes.items())  # kept, not generated again
    assert main(["export", "--out", str(tmp_path / "local"), "--num", str(num), "--outputs", OUTS,
                 "--no-progress", *SMALL]) == 0
    ray_tree, local = _tree(out), _tree(tmp_path / "local")
    assert sorted(ray_tree) == sorted(local)
    assert [k for k in local if k != "manifest.json" and ray_tree[k] != local[k]] == []
    assert json.loads(ray_tree["manifest.json"])["samples"] == json.loads(local["manifest.json"])["samples"]


@pytest.mark.ray
def test_ray_job_error_is_the_local_one(cluster, tmp_path):
    """A job that fails in an actor raises what the same job raises in this process (type and errno), not
    Ray's wrapper: the exporter turns an OSError into StorageError (exit status 3) with its errno."""
    from flowsynth.distributed import export_results
    from flowsynth.io import layouts
    from flowsynth.export.writer import ExportWriter

    writer = ExportWriter(CFG, OUTS.split(","), 0, "exact", layouts.get("native"))
    job = ((0,), str(tmp_path / "missing"))  # the staging folder cannot be made there
    with pytest.raises(OSError) as local:
        writer(job)
    with pytest.raises(OSError) as remote:
        list(export_results([job], writer, actors=1))
    assert type(remote.value) is type(local.value) and remote.value.errno == local.value.errno is not None
    assert not (tmp_path / "missing").exists()


@pytest.mark.ray
def test_driver_failure_stops_the_actors_before_cleaning_up(cluster, tmp_path, monkeypatch):
    """The driver fails placing its first sample: the export raises StorageError, its actors are gone, and no
    staging folder is left, nor written later by an actor still working on a queued sample."""
    import flowsynth.export.exporter as ex

    def full_disk(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ex, "_place", full_disk)
    out = tmp_path / "ray"
    from flowsynth.errors import StorageError

    with pytest.raises(StorageError) as err:
        ex.export_dataset(CFG, out, 8, seed=1, outputs=OUTS.split(","), engine="ray", workers=2, progress=False)
    assert err.value.errno == 28
    deadline = time.time() + 30  # killed and waited for; their processes may take a moment to exit
    while _actor_pids("WriterActor") and time.time() < deadline:
        time.sleep(0.1)
    assert _actor_pids("WriterActor") == []
    time.sleep(3)  # a sample of this size renders in well under a second
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".tmp-")) == []
