#!/usr/bin/env bash
# Issue 47 item 3, the hook scripts/device_run.sh starts in the background: protocol 0023 (docs/decisions/0023) on
# the lent GPU, every net at once: seeds 0-4 of the default and of the photo baseline. The pools render on the
# machine's CPU cores while device_run.sh's steps run; training waits for /tmp/gpu_steps_done (written by
# device_run.sh after its last timing step), so the timings have the GPU to themselves. Results come back in one
# archive, $OUT/learning.tgz, rewritten every 15 s (a run cut short keeps every net's curve so far).
set -u
cd "$(dirname "$0")/.."
L=/tmp/learn
mkdir -p "$L"
MB=${MIDDLEBURY:-/root/stage/middlebury}
pack() {  # the results, progress curves and seed 0's nets (for the figures), one file (a call returns at most 8)
    mkdir -p "$L/nets"
    cp -f .cache/learning_raft/gpu_*_s0.pt "$L/nets/" 2>/dev/null
    tar czf "$OUT/learning.tgz.tmp" -C "$L" . && mv -f "$OUT/learning.tgz.tmp" "$OUT/learning.tgz"
}
# shellcheck disable=SC2086  # LEARN_ARGS splits on spaces on purpose (a smoke test on the CPU sets it)
FLOWSYNTH_BENCH_RESULTS=$L nice -n 19 "${PYTHON:-python3}" benchmarks/learning --at-once \
    --arms flowsynth,chairs2d_photos --middlebury "$MB" --tag gpu --train-after "${GPU_DONE_MARKER:-/tmp/gpu_steps_done}" \
    ${LEARN_ARGS:---device cuda --seeds 0,1,2,3,4 --workers 12} &
PID=$!
trap 'pack; kill $PID 2>/dev/null' TERM INT
while kill -0 "$PID" 2>/dev/null; do sleep 15 & wait $!; pack; done
wait "$PID"
rc=$?
pack
exit $rc
