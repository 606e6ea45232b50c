#!/usr/bin/env bash
# Issue 47's checks on a lent GPU machine, as one bounded run (after the wheels are installed into /tmp/site; see
# the lead's notes on the device calls). Usage, from the repository root there:
#
#     OUT=/some/dir bash scripts/device_run.sh [BUDGET_S]        # BUDGET_S: the whole run's seconds, default 420
#
# Steps, in order, each under its own `timeout` (its cap, or what is left of the budget) and each run whatever the
# step before it returned:
#   env          nvidia-smi; Python, torch, warp (and its devices), numpy versions
#   gpu          python benchmarks/device/gpu.py (CPU against GPU samples/s at 512x384, T=2; profile); then it touches
#                $GPU_DONE_MARKER (default /tmp/gpu_steps_done): the hook may use the GPU from then on
#   agreement    python benchmarks/device/device_agreement.py (CPU against cuda, every main output, issue 47's tolerances)
#   tests        python -m pytest -q -x tests/test_device.py (placement of every stage, parametrised on "cuda")
#   tests_more   the other tests that touch CUDA: tests/test_device_agreement.py (a small scene on every CUDA
#                device against the CPU) and tests/test_datasets.py::test_cpu_run_never_initialises_cuda
# Hook: if an executable device_extra.sh sits beside this script, it starts in the background before the first
# step (its output in $OUT/extra.log, stdin closed), bounded by the same deadline, and is waited for at the end.
# It shares the machine with the steps: its CPU and GPU load slow them and colour every timing of the gpu step.
# EXTRA_AT=after_gpu starts it after the last step instead (then it has only what is left of the budget).
#
# Everything comes back through $OUT, written as it goes: device_run.log (every step's output, step headers, and a
# summary line per step: name, exit status, seconds), device_agreement.json and gpu.json (each rewritten after every
# measurement), extra.log. That is 4 of the 8 files a device call returns; the hook's own files must fit the rest.
# Just before the budget ends (MARGIN_S, default 20 s, is kept for the read-back) whatever still runs is killed.
#
# Environment: PYTHONPATH=/tmp/site:<repo root> (the carried wheels, then this checkout); WARP_CACHE_PATH (default
# /tmp/warp-cache, shared by every step and the hook); FLOWSYNTH_BENCH_RESULTS=$OUT (the benchmarks' JSON); PYTHON
# (default python3); AGREEMENT_ARGS and GPU_ARGS, extra arguments of the two benchmarks (GPU_ARGS="--workers 0"
# drops the DataLoader rows, the slowest part of gpu.py). Where /tmp/site exists, a .pth file in the interpreter's
# site-packages also names it, for the test that starts a fresh interpreter with its own PYTHONPATH. Exit status: 0
# when every step passed, else 1.
set -u -o pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
BUDGET=${1:-420}
MARGIN=${MARGIN_S:-20}
START=$(date +%s)
DEADLINE=$((START + BUDGET - MARGIN))
OUT=${OUT:-/tmp/device_out}
export OUT
mkdir -p "$OUT"
LOG=$OUT/device_run.log
PY=${PYTHON:-python3}
export PYTHONPATH="/tmp/site:$ROOT${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONUNBUFFERED=1
export WARP_CACHE_PATH=${WARP_CACHE_PATH:-/tmp/warp-cache}
export FLOWSYNTH_BENCH_RESULTS=$OUT
export MPLCONFIGDIR=${MPLCONFIGDIR:-/tmp/mpl-cache}
mkdir -p "$WARP_CACHE_PATH"

log() { echo "$*" | tee -a "$LOG"; }
left() { echo $((DEADLINE - $(date +%s))); }

FAILED=0
SUMMARY=()
step() {  # step NAME CAP_S COMMAND...
    local name=$1 cap=$2 t0 rc s
    shift 2
    s=$(left)
    if ((s < 10)); then
        log "== $name: skipped, $s s of the budget left"
        SUMMARY+=("$name skipped 0")
        FAILED=1
        return
    fi
    ((cap > s)) && cap=$s
    log "== $name (at +$(($(date +%s) - START)) s, timeout $cap s): $*"
    t0=$(date +%s)
    timeout -k 5 "$cap" "$@" < /dev/null 2>&1 | tee -a "$LOG"
    rc=${PIPESTATUS[0]}
    s=$(($(date +%s) - t0))
    echo >> "$LOG"  # a step's last line may lack its newline (pytest's dots when killed)
    ((rc == 124 || rc == 137)) && log "== $name: TIMED OUT after $s s" || log "== $name: exit $rc after $s s"
    SUMMARY+=("$name $rc $s")
    ((rc == 0)) || FAILED=1
}

log "device_run.sh: budget $BUDGET s (deadline at +$((DEADLINE - START)) s), OUT=$OUT, $(date -u +%FT%TZ)"

if [ -d /tmp/site ]; then  # a fresh interpreter started with PYTHONPATH=<repo> still finds the carried wheels
    SP=$("$PY" -c 'import os, site; print(next((p for p in site.getsitepackages() if os.access(p, os.W_OK)), ""))')
    if [ -n "$SP" ]; then
        echo /tmp/site > "$SP/flowsynth-device-site.pth"
        log "wrote $SP/flowsynth-device-site.pth"
    fi
fi

EXTRA=$ROOT/scripts/device_extra.sh
EXTRA_PID=
start_extra() {  # the hook, in the background until it ends or the deadline; its end is the last line of extra.log
    [ -x "$EXTRA" ] || return 0
    if (($(left) < 10)); then  # (timeout 0 would mean no limit at all)
        log "== extra: not started, $(left) s of the budget left"
        SUMMARY+=("extra skipped 0")
        FAILED=1
        return 0
    fi
    log "== extra: starting $EXTRA in the background (at +$(($(date +%s) - START)) s, output in $OUT/extra.log," \
        "timeout $(left) s)"
    (
        timeout -k 5 "$(left)" "$EXTRA" < /dev/null >> "$OUT/extra.log" 2>&1
        rc=$?
        echo "== extra ended: exit $rc at +$(($(date +%s) - START)) s" >> "$OUT/extra.log"
        exit $rc
    ) &
    EXTRA_PID=$!
}
[ "${EXTRA_AT:-start}" = start ] && start_extra

step env 60 bash -c 'nvidia-smi || echo "nvidia-smi: not found or failed"; nproc; free -g | head -2
"$0" -c "
import platform, sys
import numpy, torch
print(\"python\", sys.version.split()[0], platform.platform())
print(\"torch\", torch.__version__, \"cuda\", torch.version.cuda, \"available\", torch.cuda.is_available())
print(\"numpy\", numpy.__version__)
import warp as wp
wp.init()
print(\"warp\", wp.__version__, \"cuda devices\", wp.get_cuda_device_count(), [str(d) for d in wp.get_devices()])
"' "$PY"
# the timings first, with the GPU to themselves (the hook only renders on the CPU, at nice 19, until the marker)
# shellcheck disable=SC2086  # the extra arguments split on spaces on purpose
step gpu 300 "$PY" benchmarks/device/gpu.py ${GPU_ARGS:-}
touch "${GPU_DONE_MARKER:-/tmp/gpu_steps_done}"  # the hook's GPU work may start now
# shellcheck disable=SC2086
step agreement 180 "$PY" benchmarks/device/device_agreement.py ${AGREEMENT_ARGS:-}
step tests 240 "$PY" -m pytest -q -x -rfEs --durations=8 -p no:cacheprovider tests/test_device.py
step tests_more 150 "$PY" -m pytest -q -rfEs --durations=5 -p no:cacheprovider tests/test_device_agreement.py
# alone: tests/test_datasets.py imports torchdata, which the device's image lacks (2026-11-26, H200); a collection
# error there stopped the agreement tests beside it
step tests_cuda_init 60 "$PY" -m pytest -q -rfEs -p no:cacheprovider \
    "tests/test_datasets.py::test_cpu_run_never_initialises_cuda"
[ "${EXTRA_AT:-start}" = start ] || start_extra

if [ -n "$EXTRA_PID" ]; then
    log "== extra: waiting (at +$(($(date +%s) - START)) s)"
    wait "$EXTRA_PID"
    rc=$?
    log "$(tail -n 1 "$OUT/extra.log")"
    ((rc == 124 || rc == 137)) && log "== extra: TIMED OUT" || log "== extra: exit $rc"
    SUMMARY+=("extra $rc $(($(date +%s) - START))")
    ((rc == 0)) || FAILED=1
fi

log "== summary (step, exit status, seconds; extra: seconds since the start; 124/137 = timed out)," \
    "$(($(date +%s) - START)) s in all:"
for line in "${SUMMARY[@]}"; do log "   $line"; done
log "== files in $OUT: $(find "$OUT" -type f | wc -l) (a device call returns at most 8)"
find "$OUT" -type f -printf '   %P %s\n' | tee -a "$LOG"
exit $FAILED
