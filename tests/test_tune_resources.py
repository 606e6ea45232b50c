"""What a tune needs of its machine: the estimate (flowsynth.tune.resources) against what a process measures (peak
resident memory of real subprocesses, the bytes of the tensors read and the files written), the refusal before any
work and the flag that goes on; pools rendered into tensors allocated once (peak ~1x a pool, measured), by worker
processes reused across pools, and kept on disk against the tune's identity."""

import dataclasses
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from test_tune_run import write_middlebury

from flowsynth import memory
from flowsynth.cli import main
from flowsynth.datasets import LayersConfig, Mixture
from flowsynth.errors import ConfigError
from flowsynth.io import write_rgb_png
from flowsynth.scene import BouncingThingsConfig
from flowsynth.tune import DEFAULT_CANDIDATES, QUICK, RECIPE, PoolCache, PoolRenderer, draw_candidates, \
    pool_bytes, read_pairs, render_pool, sources, work_dir
from flowsynth.tune.pools import POOL_BYTES
from flowsynth.tune.resources import GIB, check, estimate, memory_to_test, memory_to_train

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # one torch thread: tests/conftest.py

MiB = 1 << 20
# a process's peak resident memory, from /proc (VmHWM, reset by writing 5 to clear_refs): Linux only
PEAK = """
def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
def reset():
    open("/proc/self/clear_refs", "w").write("5")
    return status("VmRSS")
"""
linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="peak memory from /proc")


def _run(code: str) -> list[float]:
    """``code`` run in a fresh interpreter on one torch thread; the numbers its last line prints."""
    out = subprocess.run([sys.executable, "-c", PEAK + code], capture_output=True, text=True, timeout=600,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert out.returncode == 0, out.stderr[-3000:]
    return [float(x) for x in out.stdout.split()[-3:]]


def _settings(n: int, res=QUICK.res) -> list[tuple[dict, dict]]:
    keys = draw_candidates(n, 0)
    return [sources(k, res) for k in keys] + [sources(keys[0], res)]


@linux
def test_training_memory_estimate_bounds_a_measured_peak():
    """Two RAFT-small nets stepped twice at once (the tune's Ensemble) at a small shape: the estimate is at least the
    measured growth of peak resident memory and at most 1.5 times it."""
    recipe = dataclasses.replace(QUICK, batch=2, crop=(128, 128), updates=2)
    code = f"""
import torch
from flowsynth.train.ensemble import Ensemble
from flowsynth.train.nets import raft_small
torch.manual_seed(0)
nets = [raft_small() for _ in range(2)]
ens = Ensemble(nets, 4e-4, 10, updates={recipe.updates})
b = {recipe.batch}
batch = (torch.rand(2, b, 3, 128, 128), torch.rand(2, b, 3, 128, 128), torch.randn(2, b, 2, 128, 128),
         torch.ones(2, b, 1, 128, 128))
before = reset()
ens.step(batch)
ens.step(batch)
print(status("VmHWM") - before)
"""
    measured = _run(code)[-1]
    est = memory_to_train(recipe, 2)
    assert measured <= est <= 1.5 * measured, (est / MiB, measured / MiB)


@linux
def test_testing_memory_estimate_bounds_a_measured_peak():
    """One RAFT-small net tested on one 400x600 pair (padded to 400x600, RAFT's correlation pyramid of 1/8 scale):
    the estimate is at least the measured growth of peak resident memory and at most 1.5 times it."""
    code = """
import torch
from flowsynth.train.nets import raft_small
from flowsynth.train.steps import predict
net = raft_small()
a, b = torch.rand(1, 3, 400, 600), torch.rand(1, 3, 400, 600)
before = reset()
with torch.no_grad():
    predict(net, a, b, 12)
print(status("VmHWM") - before)
"""
    measured = _run(code)[-1]
    est = memory_to_test((400, 600))
    assert measured <= est <= 1.5 * measured, (est / MiB, measured / MiB)


def test_validation_pairs_are_counted_as_read(tmp_path):
    """The estimate's validation pairs, sized from the files' headers, are the bytes ``read_pairs`` holds: uint8
    images (the files' 8 bits: 3 + 3 bytes a pixel), float32 flow and bool valid."""
    val = write_middlebury(tmp_path / "mb", names=("Alpha", "Beta"), h=40, w=56)
    _, pairs = read_pairs(val)
    held = sum(x.nbytes for p in pairs.values() for x in p)
    need = estimate(QUICK, 3, {k: tuple(p.flow.shape[-2:]) for k, p in pairs.items()}, sources=_settings(2))
    assert need["host"]["validation pairs"] == held == 2 * 40 * 56 * POOL_BYTES


def test_the_defaults_fit_an_8_gib_machine():
    """The default tune on the CPU (its candidates, the judge's recipe, Middlebury's four public pairs at 388x584)
    needs at most 7 GiB at its peak (an 8 GiB machine, 1 GiB left to its system); 8 candidates would not."""
    sizes = {f"p{i}": (388, 584) for i in range(4)}
    need = estimate(RECIPE, DEFAULT_CANDIDATES + 1, sizes, sources=_settings(DEFAULT_CANDIDATES, RECIPE.res))
    assert need["peak"] <= 7 * GIB, need
    more = estimate(RECIPE, 9, sizes, sources=_settings(8, RECIPE.res))
    assert more["peak"] > 7 * GIB


def test_sintel_training_set_whole_is_refused_on_8_gib(monkeypatch, tmp_path):
    """Sintel's training pairs (1041 a pass, both passes) at 436x1024: 12.99 GiB as held; refused where 8 GiB are
    available, naming the validation pairs and the flag."""
    monkeypatch.setattr(memory, "available_memory_bytes", lambda: 8 << 30)
    sizes = {f"p{i}": (436, 1024) for i in range(2082)}
    need = estimate(QUICK, 3, sizes, sources=_settings(2))
    assert need["host"]["validation pairs"] == 2082 * 436 * 1024 * 15
    with pytest.raises(ConfigError, match=r"validation pairs 12\.99.*--pairs.*FLAG"):
        check(need, "cpu", tmp_path, "FLAG")


def test_a_tune_too_big_is_refused_before_any_work(tmp_path):
    """`flowsynth tune --pool 100000000` (85 TiB of pools): exit 2 within seconds, naming what it needs and the flag,
    and no work folder made (a pool of 1000000 logged 858 GiB and began to render)."""
    val = write_middlebury(tmp_path / "mb", names=("Alpha",))
    out = tmp_path / "p.json"
    run = subprocess.run([sys.executable, "-m", "flowsynth.cli", "tune", "--val", str(val), "--out", str(out),
                          "--quick", "--pool", "100000000"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2, run.stderr[-2000:]
    assert "this tune needs" in run.stderr and "GiB" in run.stderr and "--no-resource-check" in run.stderr
    assert not work_dir(out).exists()


def test_the_flag_goes_on(tmp_path, monkeypatch, capsys):
    """With 64 MiB available (less than one process), `--quick` is refused (exit 2) and runs with the flag."""
    monkeypatch.setattr(memory, "available_memory_bytes", lambda: 64 << 20)
    val = write_middlebury(tmp_path / "mb", names=("Alpha",))
    argv = ["tune", "--val", str(val), "--out", str(tmp_path / "p.json"), "--quick"]
    assert main(argv) == 2
    assert "GiB are available" in capsys.readouterr().err
    assert main([*argv, "--no-resource-check"]) == 0
    assert (tmp_path / "p.json").is_file() and not (work_dir(tmp_path / "p.json") / "pools").exists()


def _layers(tmp_path, w=64, h=48):
    tex = tmp_path / "tex"
    tex.mkdir(exist_ok=True)
    write_rgb_png(tex / "t.png", np.random.default_rng(0).random((3, 32, 32)).astype(np.float32))
    return {"l": LayersConfig(width=w, height=h, num_frames=2, texture_dir=str(tex))}, {"l": 1.0}


@linux
def test_render_pool_peaks_at_one_pool(tmp_path):
    """160 pairs at 64x48 (8.8 MiB): the growth of peak resident memory while rendering is under 1.5 pools (the
    tensors allocated once, filled a chunk at a time; concatenating the batches held two)."""
    _layers(tmp_path)
    code = f"""
from flowsynth.datasets import LayersConfig
from flowsynth.tune import render_pool
src = ({{"l": LayersConfig(width=64, height=48, num_frames=2, texture_dir={str(tmp_path / "tex")!r})}}, {{"l": 1.0}})
render_pool(src, 0, 20)
before = reset()
pool = render_pool(src, 0, 160)
print(sum(x.nbytes for x in pool), status("VmHWM") - before)
"""
    held, grew = _run(code)[-2:]
    assert held == 160 * 64 * 48 * POOL_BYTES
    assert grew < 1.5 * held, (grew / held)


def test_pools_are_the_streams_pairs_at_any_workers_and_workers_are_reused(tmp_path):
    """Two pools (a 3D and a 2D setting) through one PoolRenderer of 2 processes: each pool is pairs 0..n-1 of its
    Mixture in order (sample by sample, the oracle), equal to the pool rendered here, and both were rendered by the
    same 2 processes at most (started once: their caches, a texture bank's frames, serve every pool; a renderer per
    pool would have started 4)."""
    things = ({"t": BouncingThingsConfig(width=64, height=48, num_frames=2)}, {"t": 1.0})
    layers = _layers(tmp_path)
    with PoolRenderer(2) as render:
        pools = [render(things, 3, 5), render(layers, 4, 5)]
        assert 1 <= len(render.pids) <= 2 and os.getpid() not in render.pids
    for (src, seed), pool in zip([(things, 3), (layers, 4)], pools):
        ds = Mixture(*src, outputs=["rgb", "flow_fw", "valid_fw"], seed=seed)
        for i in (0, 4):
            s = ds.sample(i)
            rgb = (s["rgb"][:2] * 255).round().clamp(0, 255).to(torch.uint8)
            want = (rgb[0], rgb[1], s["flow_fw"][0], s["valid_fw"][0] > 0.5)
            assert all(torch.equal(p[i], x) for p, x in zip(pool, want)), i
        here = render_pool(src, seed, 5)
        assert all(torch.equal(a, b) for a, b in zip(pool, here))


def test_pool_cache_reads_what_it_wrote_and_refuses_another_tune(tmp_path):
    """A cached pool reads back bit for bit without rendering; its files hold the pool's bytes (the disk estimate,
    plus the header and alignment); a folder of another tune's pools is refused, naming what differs."""
    src = ({"t": BouncingThingsConfig(width=64, height=48, num_frames=2)}, {"t": 1.0})
    calls = []

    def render(sources, seed, n, out=None):
        calls.append(seed)
        return render_pool(sources, seed, n, out=out)

    cache = PoolCache(tmp_path / "pools", {"seed": 0, "pairs": ["a"]})
    made = tuple(x.clone() for x in cache.get(src, 0, 3, render))
    again = cache.get(src, 0, 3, render)
    assert calls == [0] and all(torch.equal(a, b) for a, b in zip(made, again))
    assert all(torch.equal(a, b) for a, b in zip(made, render_pool(src, 0, 3)))
    data, meta = cache.paths(src, 0, 3)
    est = estimate(dataclasses.replace(QUICK, pool=3), 1, {"a": (48, 64)}, sources=[src])["disk"]["pools"]
    assert est == 3 * 160 * 128 * POOL_BYTES  # QUICK's size: the estimate is pool_bytes at the recipe's
    assert pool_bytes(3, (64, 48)) == 3 * 64 * 48 * POOL_BYTES <= data.stat().st_size <= pool_bytes(3, (64, 48)) + 384
    assert json.loads(meta.read_text())["tune"] == {"seed": 0, "pairs": ["a"]}
    with pytest.raises(ConfigError, match=r"differ in \['seed'\]: seed: 0 there, 1 here\)"):
        PoolCache(tmp_path / "pools", {"seed": 1, "pairs": ["a"]}).check()
    cache.clear()
    assert not (tmp_path / "pools").exists()


@linux
def test_a_cgroup_limit_bounds_the_memory_a_process_may_use(tmp_path, monkeypatch):
    """cgroup v2: memory.max less what the group holds beyond its file pages (memory.current less memory.stat's
    file); no limit ("max") is None; ``available_memory_bytes`` takes the smaller of that and the system's."""
    with open("/proc/self/cgroup") as f:
        own = next((line.split(":", 2)[2].strip() for line in f if line.startswith("0::")), None)
    if own is None:
        pytest.skip("no cgroup v2 line in /proc/self/cgroup")
    folder = tmp_path / own.lstrip("/")
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "memory.current").write_text(str(3 << 30))
    (folder / "memory.stat").write_text(f"anon {2 << 30}\nfile {1 << 30}\nkernel 0\n")
    (folder / "memory.max").write_text("max\n")
    assert memory.cgroup_room_bytes(str(tmp_path)) is None
    (folder / "memory.max").write_text(f"{4 << 30}\n")
    assert memory.cgroup_room_bytes(str(tmp_path)) == 2 << 30
    monkeypatch.setattr(memory, "cgroup_room_bytes", lambda: 1 << 20)
    assert memory.available_memory_bytes() == 1 << 20
