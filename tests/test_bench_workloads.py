"""benchmarks/_common.py defines each named workload once: the scripts take it from there, and importing a
benchmark does not change the importing process (issue 41, item 10)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
sys.path.insert(0, str(BENCH))

import _common  # noqa: E402


def test_full_sample_is_issue_13s_fixed_settings():
    cfg = _common.full_sample_config()
    assert (cfg.width, cfg.height, cfg.num_frames, cfg.render_mode, cfg.num_objects, cfg.camera_motion) == \
        (512, 384, 2, "direct", (20, 20), "static")
    assert _common.full_sample_config(width=256, height=192).num_objects == (20, 20)  # a variant keeps the rest
    import flowsynth as fs

    assert set(_common.FULL_SAMPLE_OUTPUTS) <= set(fs.plan.OUTPUTS)
    assert set(_common.EXPORT_OUTPUTS) <= set(fs.plan.OUTPUTS)


def test_no_script_configures_the_full_sample_by_hand():
    """The full sample's signature (20 objects at 512x384, direct) appears only in _common.py."""
    offenders = []
    for path in sorted(BENCH.rglob("*.py")):
        if path.name == "_common.py":
            continue
        text = path.read_text()
        if re.search(r"num_objects=\(20, 20\)", text) or re.search(r"\bmake_scene\b.*from raycast|from raycast", text):
            offenders.append(path.name)
    assert offenders == [], f"define the workload in benchmarks/_common.py and import it: {offenders}"


def test_raycast_scene_is_deterministic_and_the_documented_size():
    a, b = _common.raycast_scene(), _common.raycast_scene()
    assert len(a.objects) == _common.RAYCAST_SPHERES == 30
    assert (a.camera.width, a.camera.height) == (_common.RAYCAST_WIDTH, _common.RAYCAST_HEIGHT)
    assert all(len(o.mesh.faces) == 5120 for o in a.objects)
    for oa, ob in zip(a.objects, b.objects, strict=True):
        assert (oa.poses == ob.poses).all()


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs a process allowed on two CPUs or more")
def test_importing_raycast_does_not_pin_the_importer():
    code = ("import os, sys; sys.path[:0] = [sys.argv[1]]; before = sorted(os.sched_getaffinity(0)); "
            "import raycast; print(before == sorted(os.sched_getaffinity(0)), raycast.PINNING, "
            "os.environ.get('OMP_NUM_THREADS'))")
    out = subprocess.run([sys.executable, "-c", code, str(BENCH / "peers")], capture_output=True, text=True,
                         timeout=300, env={k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}, check=True)
    assert out.stdout.split()[-3:] == ["True", "None", "None"], out.stdout + out.stderr[-2000:]


def test_timer_measures_wall_and_cpu():
    import time

    with _common.Timer() as t:
        end = time.process_time() + 0.05
        while time.process_time() < end:
            pass
        time.sleep(0.05)
    assert t.cpu_s >= 0.05 and t.wall_s >= t.cpu_s - 0.01 and t.wall_s >= 0.1


def test_results_dir_can_be_redirected(tmp_path):
    code = "import sys; sys.path[:0] = [sys.argv[1]]; import _common; print(_common.RESULTS_DIR)"
    out = subprocess.run([sys.executable, "-c", code, str(BENCH)], capture_output=True, text=True, check=True,
                         env=dict(os.environ, FLOWSYNTH_BENCH_RESULTS=str(tmp_path)))
    assert Path(out.stdout.strip()) == tmp_path
