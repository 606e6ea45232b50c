#!/usr/bin/env bash
# Decision 0028's confirmatory runs (issue 61), one after another in the registered order, each from the frozen
# worktree of 4d0de35 (the commit that registers them), at nice 19, in float32 (protocol 0025 read not equivalent):
#
#     bash scripts/registered_runs.sh [--dry-run]      # from the repository root; returns at once, runs go on
#
# A seed N whose result file (learning_raft_c5.json, ...) is already in benchmarks/results (taken in) is skipped;
# the next one starts. While a run it started is alive, a second call refuses (exit 1). Each run is its own
# session (setsid), so its process group can be paused while something is timed:
#     kill -STOP -- -"$(cat .cache/registered_run.pgid)"   ...   kill -CONT -- -"$(cat .cache/registered_run.pgid)"
# Results land in the worktree's benchmarks/results (check them, then copy them here: docs/decisions/0028). A run
# cut short leaves no result file; the chain stops there, and a new call starts that seed over. Log:
# .cache/registered_runs.log, each run's output .cache/registered_cN.log. Needs ../shared/data/middlebury.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
COMMIT=4d0de35
WT=${REGISTERED_WORKTREE:-$ROOT/../wt-$COMMIT}
MB=${MIDDLEBURY:-$ROOT/../shared/data/middlebury}
PY=$ROOT/.venv/bin/python
DRY=0; [ "${1:-}" = "--dry-run" ] && DRY=1
mkdir -p "$ROOT/.cache"
[ -d "$MB" ] || { echo "registered_runs.sh: no Middlebury pairs at $MB (set MIDDLEBURY)" >&2; exit 2; }
if [ ! -d "$WT" ]; then
  [ "$DRY" = 1 ] && echo "would add the worktree $WT at $COMMIT" || git worktree add --detach "$WT" "$COMMIT"
fi
PGID_FILE=$ROOT/.cache/registered_run.pgid
if [ -f "$PGID_FILE" ] && kill -0 "$(cat "$PGID_FILE")" 2>/dev/null; then
  echo "registered_runs.sh: a registered run is going (pgid $(cat "$PGID_FILE")); not starting another" >&2
  exit 1
fi
todo=()
for N in 5 6 7 8 9; do
  [ -f "$ROOT/benchmarks/results/learning_raft_c$N.json" ] || todo+=("$N")
done
if [ "${#todo[@]}" = 0 ]; then echo "registered_runs.sh: c5-c9 are all taken in; read decision 0028"; exit 0; fi
echo "registered_runs.sh: to run, in order: ${todo[*]/#/c}"
[ "$DRY" = 1 ] && exit 0
(
  for N in "${todo[@]}"; do
    [ -f "$WT/benchmarks/results/learning_raft_c$N.json" ] && continue  # finished, not yet taken in
    echo "c$N start $(date -u +%FT%TZ)" >> "$ROOT/.cache/registered_runs.log"
    cd "$WT"
    PYTHONPATH="$WT" setsid nice -n 19 "$PY" benchmarks/learning --arms flowsynth,mixture --seeds "$N" --tag "c$N" \
      --middlebury "$MB" > "$ROOT/.cache/registered_c$N.log" 2>&1 &
    echo $! > "$PGID_FILE"  # setsid in a background job: the python is its session's leader
    wait $! || true
    echo "c$N end $(date -u +%FT%TZ)" >> "$ROOT/.cache/registered_runs.log"
    if [ ! -f "$WT/benchmarks/results/learning_raft_c$N.json" ]; then
      echo "c$N left no result: stop" >> "$ROOT/.cache/registered_runs.log"
      exit 1
    fi
  done
) > /dev/null 2>&1 < /dev/null &
disown
echo "registered_runs.sh: started; log .cache/registered_runs.log"
