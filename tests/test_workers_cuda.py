"""A stream that survives CUDA (issue 52, item 1).

CUDA does not survive fork(). flowsynth notes, at every fork, whether the parent had initialised CUDA (torch, or
Warp's runtime with CUDA devices: ``flowsynth.processes.cuda_initialised``); a stream in such a forked child raises
``ForkError`` at its first sample. ``fs.datasets.loader`` starts its workers with forkserver instead, and ``export``
leaves fork once CUDA is initialised. This CPU machine cannot initialise CUDA, so the CPU tests make
``cuda_initialised`` answer True in the parent (the fork hook reads it there) and check what the children do;
``test_stream_on_a_cuda_machine`` does it for real where a GPU is lent (marked ``cuda``; skipped elsewhere).
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torch.utils.data import DataLoader

import flowsynth as fs
from flowsynth import processes
from flowsynth.datasets.bouncing import BouncingThings

ROOT = Path(__file__).resolve().parents[1]
# physics motion: the Newton path (Warp) runs in the workers, not only the ray casts
CFG = fs.BouncingThingsConfig(width=32, height=24, num_frames=2, num_objects=(2, 3), max_objects=3)
OUTS = ["rgb", "flow_fw", "occ_fw", "depth", "instance"]
TIMEOUT = 600  # [s] a cold Warp cache compiles kernels in a worker's first sample


def _items(loader, n: int) -> dict[int, dict]:
    out = {}
    for item in loader:
        out[int(item["index"])] = item
        if len(out) >= n:
            break
    return out


def _equal(a: dict, b: dict) -> None:
    assert set(a) == set(b)
    for k in a:
        if k == "provenance":
            assert a[k] == b[k]
        else:
            assert a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]), k


@pytest.fixture(scope="module")
def fork_samples():
    """Four samples of the stream through two forked workers: the reference the other start methods must give."""
    ds = BouncingThings(CFG, outputs=OUTS, seed=3, length=4)
    return _items(DataLoader(ds, batch_size=None, num_workers=2, multiprocessing_context="fork", timeout=TIMEOUT), 4)


@pytest.mark.parametrize("how", ["spawn", "forkserver", "loader"])
def test_spawned_and_forkserver_workers_yield_the_fork_samples(fork_samples, how):
    ds = BouncingThings(CFG, outputs=OUTS, seed=3, length=4)
    if how == "loader":
        loader = fs.datasets.loader(ds, batch_size=None, num_workers=2, timeout=TIMEOUT)
        assert loader.multiprocessing_context.get_start_method() in ("forkserver", "spawn")
    else:
        loader = DataLoader(ds, batch_size=None, num_workers=2, multiprocessing_context=how, timeout=TIMEOUT)
    got = _items(loader, 4)
    assert sorted(got) == sorted(fork_samples) == [0, 1, 2, 3]
    for i in got:
        _equal(got[i], fork_samples[i])


def test_a_worker_forked_after_cuda_refuses_and_the_loader_does_not(monkeypatch):
    """With CUDA initialised in the parent, a plain (fork) DataLoader's worker raises ForkError at its first sample,
    with what to do; ``fs.datasets.loader``'s workers (forkserver: a fresh interpreter forks them) render."""
    monkeypatch.setattr(processes, "cuda_initialised", lambda: True)
    ds = BouncingThings(CFG, outputs=["depth"], seed=1, length=2)
    with pytest.raises(fs.ForkError, match="forkserver") as e:
        next(iter(DataLoader(ds, batch_size=None, num_workers=1, multiprocessing_context="fork", timeout=TIMEOUT)))
    assert "fs.datasets.loader" in str(e.value)
    got = _items(fs.datasets.loader(ds, batch_size=None, num_workers=1, timeout=TIMEOUT), 2)
    assert sorted(got) == [0, 1] and torch.equal(got[1]["depth"], ds.sample(1)["depth"])


def _render_in_child(q, scene):
    try:
        fs.render(scene, ["depth"])
        q.put("rendered")
    except fs.ForkError:
        q.put("ForkError")


def test_render_in_a_child_forked_after_cuda_refuses(monkeypatch):
    """Not only the stream: ``fs.render`` (every render starts at ``resolve_device``) in a user's own forked process
    after CUDA raises ForkError; the same child without CUDA in its parent renders."""
    import multiprocessing as mp

    scene = BouncingThings(dataclasses.replace(CFG, motion="kinematic"), outputs=["depth"], seed=1).scene(0)
    ctx = mp.get_context("fork")
    got = []
    for cuda in (False, True):
        monkeypatch.setattr(processes, "cuda_initialised", lambda cuda=cuda: cuda)
        q = ctx.Queue()
        p = ctx.Process(target=_render_in_child, args=(q, scene))
        p.start()
        got.append(q.get(timeout=TIMEOUT))
        p.join()
    assert got == ["rendered", "ForkError"]


def test_fork_without_cuda_still_renders():
    """The guard is not a blanket ban: in a CPU-only parent a forked child renders, and its child too."""
    def child(q):
        q.put(float(BouncingThings(CFG, outputs=["depth"], seed=1).sample(0)["depth"].sum()))

    import multiprocessing as mp

    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=child, args=(q,))
    p.start()
    got = q.get(timeout=TIMEOUT)
    p.join()
    assert p.exitcode == 0 and got == float(BouncingThings(CFG, outputs=["depth"], seed=1).sample(0)["depth"].sum())


def test_cuda_initialised_reads_torch_and_warp(monkeypatch):
    from flowsynth.kernels import wp_runtime

    wp_runtime()  # Warp's runtime exists; on this machine it found no CUDA device
    assert processes.cuda_initialised() is False
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: True)
    assert processes.cuda_initialised() is True
    monkeypatch.undo()
    runtime = sys.modules["warp._src.context"].runtime
    monkeypatch.setattr(runtime, "cuda_devices", [object()])
    assert processes.cuda_initialised() is True


def test_worker_context_leaves_fork_once_cuda_is_initialised(monkeypatch):
    assert processes.worker_context().get_start_method() == "fork"
    assert processes.worker_context(fork_ok=False).get_start_method() == "forkserver"
    monkeypatch.setattr(processes, "cuda_initialised", lambda: True)
    assert processes.worker_context().get_start_method() == "forkserver"


def test_export_workers_after_cuda_write_what_one_process_writes(tmp_path, monkeypatch):
    """``export --workers K`` in a process that initialised CUDA: its workers start with forkserver (a forked one
    would raise ForkError) and the manifest's files and hashes equal a one-process export's."""
    from flowsynth.export import export_dataset

    cfg = fs.BouncingThingsConfig(width=32, height=24, num_frames=2, motion="kinematic", num_objects=(2, 3),
                               max_objects=3)
    b = export_dataset(cfg, tmp_path / "b", 3, outputs=["depth", "flow_fw"], workers=1, progress=False)
    monkeypatch.setattr(processes, "cuda_initialised", lambda: True)
    a = export_dataset(cfg, tmp_path / "a", 3, outputs=["depth", "flow_fw"], workers=2, progress=False)
    ma, mb = (json.loads((r / "manifest.json").read_text())["samples"] for r in (a, b))
    assert ma == mb and len(ma) == 3


# -- where a GPU is lent -------------------------------------------------------------------------------------
CUDA_STREAM = r"""
import json, sys, time
import torch
from torch.utils.data import DataLoader
import flowsynth as fs
from flowsynth.processes import cuda_initialised

def rate(ds, n, workers):
    '''samples/s of n samples after 2 batches per worker (start-up and the batches prefetched meanwhile left out)'''
    it = iter(fs.datasets.loader(ds, batch_size=4, num_workers=workers, timeout=600))
    for _ in range(2 * workers):
        next(it)
    t, got = time.perf_counter(), 0
    while got < n:
        got += len(next(it)["index"])
    return got / (time.perf_counter() - t)

if __name__ == "__main__":
    order, workers, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    cfg = fs.BouncingThingsConfig(width=256, height=192, num_frames=2)
    ds = fs.datasets.BouncingThings(cfg, outputs=["rgb", "flow_fw", "valid_fw"], seed=0)
    before = rate(ds, n, workers)            # no CUDA in this process yet
    torch.zeros(1, device="cuda").sum().item()
    if "warp" in order:                      # a warm-up render: Warp initialises CUDA here too
        ds.sample(0)
        fs.render(ds.scene(1), ["depth"], device="cuda")
    after = rate(ds, n, workers)
    try:
        next(iter(DataLoader(ds, batch_size=2, num_workers=1, timeout=600)))   # a plain, forked DataLoader
        refused = False
    except fs.ForkError:
        refused = True
    print(json.dumps({"order": order, "before": before, "after": after, "fork_refused": refused,
                      "cuda_initialised": cuda_initialised()}))
"""


def _has_cuda() -> bool:
    if not os.path.exists("/dev/nvidiactl"):
        return False
    out = subprocess.run([sys.executable, "-c", "import torch; print(torch.cuda.is_available())"],
                         capture_output=True, text=True, timeout=120, check=False)
    return out.stdout.strip() == "True"


@pytest.mark.cuda
@pytest.mark.parametrize("order", ["torch", "torch+warp"])
def test_stream_on_a_cuda_machine(order):
    """In a fresh process: stream through ``fs.datasets.loader`` with 4 workers, initialise CUDA (torch alone, or
    torch and a Warp render on the CPU and on the GPU), stream again. No CUDA error line, a rate that does not
    collapse (the H200's forked workers were about 10x slow: at least half the rate before CUDA), and a plain
    forked DataLoader refused with ForkError."""
    if not _has_cuda():
        pytest.skip("no CUDA device")
    out = subprocess.run([sys.executable, "-c", CUDA_STREAM, order, "4", "64"], capture_output=True, text=True,
                         timeout=900, cwd=ROOT, env={**os.environ, "PYTHONPATH": os.pathsep.join(
                             filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}, check=False)
    assert out.returncode == 0, out.stderr[-3000:]
    assert not [line for line in (out.stdout + out.stderr).splitlines() if "CUDA error" in line], out.stderr[-3000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["cuda_initialised"] and r["fork_refused"], r
    assert r["after"] >= 0.5 * r["before"], r
