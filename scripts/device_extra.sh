#!/usr/bin/env bash
# The hook scripts/device_run.sh starts in the background: the whole decision of protocol 0023
# (docs/decisions/0023-raft-judge.md) on the lent GPU in one call: seeds 0-4 of the default, the photo baseline and the
# two presets (mixture, curriculum), 20 nets x 2400 steps, their tests and their pools. The pools render on the
# machine's CPU cores (forkserver workers) while device_run.sh's steps run; training waits for $GPU_DONE_MARKER
# (default /tmp/gpu_steps_done; device_run.sh removes it at its start and writes it after its last timing step), so
# the timings have the GPU to themselves. Then every net trains at once in one process (--ensemble:
# flowsynth.train.ensemble, vmap over the 20 nets), which prints the ensemble's steps/s at each checkpoint (learn.log,
# rate.txt). When it ends well, --diagnose-checkpoints reads every net's kept checkpoints there (the weights stay on
# the machine): the motion each invents on the still photographs, and the goal decision 0023 sets for it
# (learning_raft_diagnose_checkpoints_gpu.json, .png; DIAGNOSE=0 skips it). Results come back in one archive,
# $OUT/learning.tgz, rewritten every 15 s (a run cut short keeps every net's curve so far).
#
# Environment: OUT (required: where learning.tgz goes; device_run.sh sets it); MIDDLEBURY (required: the folder of
# Middlebury pairs, NAME/frame10.png, frame11.png, flow10.flo; on the lent machine wherever the data were carried);
# LEARN_DIR (default /tmp/learn: the run's own files); DEVICE (default cuda); LEARN_ARGS replaces the seeds, workers
# and threads; PYTHON (default python3). A smoke test on the CPU: LEARN_ARGS="--quick --seeds 0 --workers 2"
# DEVICE=cpu GPU_DONE_MARKER=/dev/null MIDDLEBURY=... OUT=... Exit status: the benchmark's; 2 for a missing variable.
set -u
cd "$(dirname "$0")/.."
if [ -z "${OUT:-}" ]; then
    echo "device_extra.sh: set OUT to the folder the results archive goes to" >&2
    exit 2
fi
MB=${MIDDLEBURY:-}
if [ -z "$MB" ] || [ ! -d "$MB" ]; then
    echo "device_extra.sh: set MIDDLEBURY to the folder of Middlebury pairs (NAME/frame10.png, frame11.png," \
        "flow10.flo); got '$MB'" >&2
    exit 2
fi
L=${LEARN_DIR:-/tmp/learn}
mkdir -p "$L"
DEVICE=${DEVICE:-cuda}
pack() {  # the results, progress curves, the log and seed 0's nets (for the figures), one file (a call returns 8)
    mkdir -p "$L/nets"
    cp -f .cache/learning_raft/gpu_*_s0.pt "$L/nets/" 2>/dev/null
    grep -h "steps/s" "$L/learn.log" > "$L/rate.txt" 2>/dev/null
    tar czf "$OUT/learning.tgz.tmp" -C "$L" . && mv -f "$OUT/learning.tgz.tmp" "$OUT/learning.tgz"
}
# shellcheck disable=SC2086  # LEARN_ARGS splits on spaces on purpose (a smoke test on the CPU sets it)
FLOWSYNTH_BENCH_RESULTS=$L nice -n 19 "${PYTHON:-python3}" benchmarks/learning --at-once --ensemble \
    --arms flowsynth,chairs2d_photos,mixture,curriculum --middlebury "$MB" --tag gpu \
    --train-after "${GPU_DONE_MARKER:-/tmp/gpu_steps_done}" \
    --device "$DEVICE" ${LEARN_ARGS:---seeds 0,1,2,3,4 --workers 12 --threads 4} > >(tee "$L/learn.log") 2>&1 &
PID=$!
trap 'pack; kill $PID 2>/dev/null' TERM INT
while kill -0 "$PID" 2>/dev/null; do sleep 15 & wait $!; pack; done
wait "$PID"
rc=$?
if [ "$rc" = 0 ] && [ "${DIAGNOSE:-1}" = 1 ]; then
    FLOWSYNTH_BENCH_RESULTS=$L nice -n 19 "${PYTHON:-python3}" benchmarks/learning --diagnose-checkpoints \
        --files learning_raft_gpu.json --middlebury "$MB" --device "$DEVICE" --tag gpu 2>&1 | tee -a "$L/learn.log"
    rc=${PIPESTATUS[0]}
fi
pack
exit $rc
