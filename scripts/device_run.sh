#!/usr/bin/env bash
# The checks of a lent GPU machine (the stream after CUDA, a training loop fed by the stream, the device's rates), as one
# bounded run after the wheels are installed into $SITE_DIR (../shared/GPU.md's three calls). Usage, from the
# repository root there:
#
#     OUT=/some/dir bash scripts/device_run.sh [BUDGET_S]        # BUDGET_S: the whole run's seconds, default 450
#     SMOKE=1 OUT=/tmp/o bash scripts/device_run.sh 900           # the same steps on a CPU-only machine, quick sizes
#
# Steps, in order, each under its own `timeout` (its cap, or what is left of the budget) and each run whatever the
# step before it returned:
#   env          nvidia-smi; Python, torch, warp (and its devices), numpy versions
#   stream       tests/test_workers_cuda.py (spawn, forkserver and fs.datasets.loader yield the fork samples;
#                a worker forked after CUDA refuses; and, marked cuda, the stream with 4 workers in a process that
#                initialised CUDA by torch alone and by torch and Warp renders: rate against before CUDA, no
#                "CUDA error" line, a plain forked DataLoader refused)
#   feed         benchmarks/device/feed.py, RAFT-small's step on cuda fed by fs.datasets.loader's workers
#                (the cores less one) against pairs in memory (feed.json, feed.png)
#   feed_device  the same with batched device rendering: feed.py --source device (fs.datasets.DeviceBatches;
#                feed_device.json, feed_device.png)
#   gpu          benchmarks/device/gpu.py, CPU and GPU side by side at 512x384, T=2: one by one, batched
#                (render_batch alone and DeviceBatches end to end, the GPU's busy share), profiles (gpu.json)
#   tests        tests/test_batched.py and tests/test_device.py (placement of every stage, on "cuda" too)
# SMOKE=1: no GPU needed: feed on the CPU with --quick, gpu.py --quick, the same tests (their cuda cases skip);
# every step's cap is multiplied by CAP_SCALE (SMOKE's default 4: a 2-core machine is slower than the lent one).
# Hook: an executable scripts/device_extra.sh runs in the background only when EXTRA_AT is set (start: before the
# first step; after_gpu: after the last), bounded by the same deadline (output in $OUT/extra.log; it needs its own
# variables, MIDDLEBURY at least); it shares the machine with the steps, so every timing would carry its load. The
# marker $GPU_DONE_MARKER (default /tmp/gpu_steps_done; exported to the hook) says the timings are done: removed at
# the start (a regular file only: GPU_DONE_MARKER=/dev/null stays), written after the gpu step; the hook's training
# waits for it, so a rerun on a warm machine cannot let training start during the timings.
#
# Everything comes back through $OUT, written as it goes: device_run.log (every step's output, step headers, and a
# summary line per step: name, exit status, seconds), feed.json, feed.png, feed_device.json, feed_device.png, gpu.json (each
# rewritten after every measurement). Just before the budget ends (MARGIN_S, default 20 s, kept for the read-back)
# whatever still runs is killed.
#
# Environment: SITE_DIR (default /tmp/site: the carried wheels); PYTHONPATH=$SITE_DIR:<repo root> (the wheels, then
# this checkout); WARP_CACHE_PATH (default /tmp/warp-cache, shared by every step); FLOWSYNTH_BENCH_RESULTS=$OUT (the
# benchmarks' JSON); PYTHON (default python3); FEED_ARGS and GPU_ARGS, extra arguments of the two benchmarks. Where
# $SITE_DIR exists, a .pth file in the interpreter's site-packages also names it, for the tests that start a fresh
# interpreter with their own PYTHONPATH. Exit status: 0 when every step passed, else 1.
set -u -o pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
BUDGET=${1:-450}
MARGIN=${MARGIN_S:-20}
START=$(date +%s)
DEADLINE=$((START + BUDGET - MARGIN))
OUT=${OUT:-/tmp/device_out}
export OUT
mkdir -p "$OUT"
LOG=$OUT/device_run.log
PY=${PYTHON:-python3}
SITE_DIR=${SITE_DIR:-/tmp/site}
export PYTHONPATH="$SITE_DIR:$ROOT${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONUNBUFFERED=1
export WARP_CACHE_PATH=${WARP_CACHE_PATH:-/tmp/warp-cache}
export FLOWSYNTH_BENCH_RESULTS=$OUT
export MPLCONFIGDIR=${MPLCONFIGDIR:-/tmp/mpl-cache}
mkdir -p "$WARP_CACHE_PATH"
export GPU_DONE_MARKER=${GPU_DONE_MARKER:-/tmp/gpu_steps_done}
[ -f "$GPU_DONE_MARKER" ] && rm -f "$GPU_DONE_MARKER"  # a warm machine's last run wrote it: not done yet this run

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
    cap=$((cap * ${CAP_SCALE:-1}))
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

if [ -d "$SITE_DIR" ]; then  # a fresh interpreter started with PYTHONPATH=<repo> still finds the carried wheels
    SP=$("$PY" -c 'import os, site; print(next((p for p in site.getsitepackages() if os.access(p, os.W_OK)), ""))')
    if [ -n "$SP" ]; then
        echo "$SITE_DIR" > "$SP/flowsynth-device-site.pth"
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
[ "${EXTRA_AT:-}" = start ] && start_extra

CORES=$(nproc)
if [ -n "${SMOKE:-}" ]; then
    CAP_SCALE=${CAP_SCALE:-4}
    FEED=(--quick --device cpu)
    GPU=(--quick)
else
    FEED=(--device cuda --workers $((CORES > 1 ? CORES - 1 : 1)))
    GPU=(--cpu-samples 4 --gpu-samples 16 --workers 0 --batch 32 --batches 6)
fi
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
step stream 150 "$PY" -m pytest -q -rfEs --durations=5 -p no:cacheprovider tests/test_workers_cuda.py
# shellcheck disable=SC2086  # the extra arguments split on spaces on purpose
step feed 110 "$PY" benchmarks/device/feed.py "${FEED[@]}" ${FEED_ARGS:-}
# shellcheck disable=SC2086
step feed_device 90 "$PY" benchmarks/device/feed.py --source device "${FEED[@]}" ${FEED_ARGS:-}
# shellcheck disable=SC2086
step gpu 150 "$PY" benchmarks/device/gpu.py "${GPU[@]}" ${GPU_ARGS:-}
touch "$GPU_DONE_MARKER"  # the timings are done: device_extra.sh's training may use the GPU
step tests 120 "$PY" -m pytest -q -x -rfEs --durations=8 -p no:cacheprovider tests/test_batched.py tests/test_device.py
[ "${EXTRA_AT:-}" = after_gpu ] && start_extra

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
