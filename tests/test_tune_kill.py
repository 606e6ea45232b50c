"""`flowsynth tune` stopped from outside, as a user's machine stops it: a real process SIGKILLed while it replaces its
state, the rerun interrupted by SIGINT (Ctrl-C: exit 130 and a message to rerun), and a last rerun that ends with the
preset and report of an uninterrupted run of the same command, equal bit for bit: the state holds every net's
weights, AdamW moments and batch generator and the shared schedule, and a rerun renders the pools again from their
seeds, so no tolerance is needed. Each rerun must start at the checkpoint after the saved one (its progress lines).

Every run is `python -m flowsynth.cli tune --quick` (RAFT-small, 3 nets, steps 0 to 4) on one validation pair
written under tmp_path (tests/test_tune_run.py's Middlebury pair), with torch on one thread (OMP_NUM_THREADS=1): the
reference and the interrupted runs then do the same arithmetic, and the reference runs beside them on CI's second
core."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch
from test_tune_run import write_middlebury

from flowsynth.tune import work_dir

POLL = 0.002  # [s] between looks at the work folder: a state write (tens of MB) takes longer
PATIENCE = 600  # [s] the longest a stage may take on a busy 2-core machine


@pytest.fixture
def start():
    """``start(cmd, log)``: ``cmd`` started with torch on one thread, its stdout and stderr in LOG.out and LOG.err,
    line by line; those still running when the test ends (a failed assertion) are killed."""
    procs = []

    def start(cmd, log):
        env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
        with open(log.with_suffix(".out"), "w") as out, open(log.with_suffix(".err"), "w") as err:
            procs.append(subprocess.Popen(cmd, env=env, stdout=out, stderr=err))
        return procs[-1]
    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _wait_for(proc, ready, what, log):
    """Poll until ``ready()`` is true while ``proc`` runs; fail, with its output, if it ends first."""
    deadline = time.monotonic() + PATIENCE
    while not ready():
        assert proc.poll() is None, (f"the tune ended (status {proc.returncode}) before {what}:\n"
                                     + log.with_suffix(".err").read_text()[-2000:])
        assert time.monotonic() < deadline, f"no {what} within {PATIENCE} s"
        time.sleep(POLL)


def _progress(work) -> dict | None:
    try:
        return json.loads((work / "progress.json").read_text())  # written atomically: whole or absent
    except FileNotFoundError:
        return None


def _writing(work) -> bool:
    """Whether a state is being written: its temporary holds some bytes but has not replaced state.pt yet."""
    for p in work.glob(".state.tmp-*"):
        try:
            if p.stat().st_size > 0:
                return True
        except FileNotFoundError:  # renamed over state.pt since the glob
            pass
    return False


def _state(work) -> dict:
    """state.pt as the next run loads it: it must load whole."""
    return torch.load(work / "state.pt", map_location="cpu", weights_only=True)["search"]


def _stepped(log) -> list[int]:
    """The checkpoints a run tested, from its progress lines."""
    return [int(line.split()[2]) for line in log.with_suffix(".out").read_text().splitlines()
            if line.startswith("tune: step ")]


def _pools(log) -> tuple[int, int]:
    """(pools rendered, pools read from the cache), from a run's log lines."""
    lines = log.with_suffix(".out").read_text().splitlines()
    return (sum(x.startswith("tune: rendering a pool") for x in lines),
            sum(x.startswith("tune: pool of") and " read from " in x for x in lines))


def _files(work) -> dict:
    return {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in sorted((work / "pools").iterdir())}


def test_a_killed_then_interrupted_tune_resumes_to_the_uninterrupted_result(tmp_path, start):
    val = write_middlebury(tmp_path / "mb", names=("Alpha",))

    def command(out):
        return [sys.executable, "-m", "flowsynth.cli", "tune", "--val", str(val), "--out", str(out), "--quick"]

    ref_out, out = tmp_path / "ref" / "preset.json", tmp_path / "run" / "preset.json"
    ref_out.parent.mkdir()
    out.parent.mkdir()
    work = work_dir(out)
    ref = start(command(ref_out), tmp_path / "ref")

    # 1. SIGKILL while the state after the first trained checkpoint is half written (a write takes ~0.1 s)
    first = start(command(out), tmp_path / "first")
    _wait_for(first, lambda: (_progress(work) or {"step": -1})["step"] >= 1, "a state past step 1", tmp_path / "first")
    _wait_for(first, lambda: _writing(work), "a state write after step 1", tmp_path / "first")
    first.send_signal(signal.SIGKILL)
    assert first.wait(PATIENCE) == -signal.SIGKILL
    partial = [p.name for p in work.iterdir() if ".tmp-" in p.name]  # the write the kill cut (unless it won the race)
    killed = _state(work)
    assert killed["step"] >= 1 and "winner" not in killed and len(partial) <= 1, (killed["step"], partial)
    assert _pools(tmp_path / "first") == (3, 0)  # the reference, its twin and the other candidate
    cached = _files(work)
    assert len(cached) == 6  # each pool's .npy and .json

    # 2. the same command continues from that state, testing no checkpoint again; Ctrl-C after its first new one
    second = start(command(out), tmp_path / "second")
    _wait_for(second, lambda: _stepped(tmp_path / "second")[-1:] > [killed["step"]], "a new checkpoint",
              tmp_path / "second")
    second.send_signal(signal.SIGINT)
    assert second.wait(PATIENCE) == 130
    err = (tmp_path / "second.err").read_text()
    assert "flowsynth tune: interrupted; re-run the same command to resume" in err, err[-2000:]
    assert "continuing" in (tmp_path / "second.out").read_text()
    tested = _stepped(tmp_path / "second")
    assert tested[0] == killed["step"] + 1 and tested == sorted(set(tested)), (killed["step"], tested)
    interrupted = _state(work)
    assert interrupted["step"] > killed["step"] and "winner" not in interrupted
    assert [p.name for p in work.iterdir() if ".tmp-" in p.name] == []  # the kill's removed, its own never left
    assert _pools(tmp_path / "second") == (0, 3) and _files(work) == cached  # no pool rendered or written again

    # 3. and again, to the end: it too starts where the last state left off
    third = start(command(out), tmp_path / "third")
    assert third.wait(PATIENCE) == 0, (tmp_path / "third.err").read_text()[-2000:]
    assert _stepped(tmp_path / "third")[:1] in ([], [interrupted["step"] + 1])
    assert _pools(tmp_path / "third")[0] == 0 and not (work / "pools").exists()  # done: the pools deleted

    assert ref.wait(PATIENCE) == 0, (tmp_path / "ref.err").read_text()[-2000:]
    assert _stepped(tmp_path / "ref") == [0, 1, 2, 3, 4]
    assert out.read_bytes() == ref_out.read_bytes()
    reports = [json.loads((work_dir(p) / "report.json").read_text()) for p in (out, ref_out)]
    assert reports[0] == reports[1]
    assert (work_dir(out) / "report.md").read_bytes() == (work_dir(ref_out) / "report.md").read_bytes()
