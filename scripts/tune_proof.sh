#!/usr/bin/env bash
# Decision 0026's proof of `flowsynth tune` (issue 61, step 5), as 0026's Numbers section registers it: the tune on
# Dimetrodon and Grove2, then the tuned preset's nets on seeds 0-4, each from the frozen worktree of 0201cb6 (the
# commit that registers the budget and the runs), at nice 19, in float32:
#
#     bash scripts/tune_proof.sh [--dry-run]      # from the repository root; returns at once, the work goes on
#
# It starts only when step 4 is in (0028's seeds c5-c9 all taken into benchmarks/results) and no registered run of
# scripts/registered_runs.sh is alive; while a step it started is alive, a second call refuses (exit 1).
# 1. The tune, into .cache/tune-0026 in this checkout (TUNE_OUT overrides): the same command resumes it from its saved
#    state, so a session that ends under it loses at most one checkpoint's work; a finished tune only rewrites its
#    preset and report. In the checkout, because the tune (9600 net-steps) outlasts a session and the checkout is what
#    a next session has been seen to keep (../shared came back fresh, losing a tune at step 1800 of 2400).
#    Where it writes changes nothing the tune finds. A finished tune's preset and report, once taken in
#    (benchmarks/results/tune_0026_tuned.json and its report), are what the judge uses, and the tune is not
#    run again: its state is GBs and cannot be committed, its preset can.
# 2. The judge runs (benchmarks/learning --arms tuned --preset PRESET): tags tuned_a (seeds 0,1 at
#    once), tuned_b (2,3), tuned_c (4). A tag whose results file is already here (taken in) or in the worktree
#    (finished, not yet taken in) is skipped. A run cut short leaves no complete file and starts over.
# Each step is its own session (setsid): pause it with kill -STOP -- -"$(cat .cache/tune_proof.pgid)" (and -CONT).
# Log: .cache/tune_proof.log, each step's output .cache/tune_proof_STEP.log. Then read it (0026):
#     python benchmarks/learning --tune-proof --files 'learning_raft_*.json'
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
COMMIT=0201cb6
WT=${TUNE_WORKTREE:-$ROOT/../wt-$COMMIT}
MB=${MIDDLEBURY:-$ROOT/../shared/data/middlebury}
OUT=${TUNE_OUT:-$ROOT/.cache/tune-0026}
PY=$ROOT/.venv/bin/python
FS=$ROOT/.venv/bin/flowsynth
DRY=0; [ "${1:-}" = "--dry-run" ] && DRY=1
mkdir -p "$ROOT/.cache"
[ -d "$MB" ] || { echo "tune_proof.sh: no Middlebury pairs at $MB (set MIDDLEBURY)" >&2; exit 2; }
missing=()
for N in 5 6 7 8 9; do
  [ -f "$ROOT/benchmarks/results/learning_raft_c$N.json" ] || missing+=("c$N")
done
if [ "${#missing[@]}" != 0 ]; then
  echo "tune_proof.sh: step 4 (0028) is not in: ${missing[*]} still to take in; run scripts/registered_runs.sh" >&2
  exit 1
fi
for f in "$ROOT/.cache/registered_run.pgid" "$ROOT/.cache/tune_proof.pgid"; do
  if [ -f "$f" ] && kill -0 "$(cat "$f")" 2>/dev/null; then
    echo "tune_proof.sh: a run is going (pgid $(cat "$f"), $(basename "$f")); not starting another" >&2
    exit 1
  fi
done
if [ ! -d "$WT" ]; then
  [ "$DRY" = 1 ] && echo "would add the worktree $WT at $COMMIT" || git worktree add --detach "$WT" "$COMMIT"
fi
PRESET=$ROOT/benchmarks/results/tune_0026_tuned.json
TUNE=0
[ -f "$PRESET" ] || { PRESET=$OUT/tuned.json; TUNE=1; }
judge=()
for tag in tuned_a tuned_b tuned_c; do
  [ -f "$ROOT/benchmarks/results/learning_raft_$tag.json" ] || judge+=("$tag")
done
if [ "$TUNE" = 1 ]; then
  echo "tune_proof.sh: to run, in order: tune ${judge[*]} (the tune resumes, or only rewrites its report when finished)"
else
  echo "tune_proof.sh: the tune is taken in ($PRESET); to run, in order: ${judge[*]:-nothing}"
fi
[ "$DRY" = 1 ] && exit 0
PGID_FILE=$ROOT/.cache/tune_proof.pgid
LOG=$ROOT/.cache/tune_proof.log
mkdir -p "$OUT"
(
  cd "$WT"
  step() {  # step NAME COMMAND...: run it in its own session at nice 19; its exit status
    echo "$1 start $(date -u +%FT%TZ)" >> "$LOG"
    PYTHONPATH="$WT" setsid nice -n 19 "${@:2}" > "$ROOT/.cache/tune_proof_$1.log" 2>&1 &
    echo $! > "$PGID_FILE"
    local rc=0
    wait $! || rc=$?
    echo "$1 end $(date -u +%FT%TZ) rc $rc" >> "$LOG"
    return $rc
  }
  if [ "$TUNE" = 1 ]; then
    step tune "$FS" tune --val "$MB" --pairs Dimetrodon,Grove2 --out "$OUT/tuned.json" --budget 9600 --candidates 6 \
      --seed 0 --precision fp32 --device cpu --workers 2 || { echo "the tune stopped: stop" >> "$LOG"; exit 1; }
  fi
  for tag in "${judge[@]}"; do
    [ -f "$WT/benchmarks/results/learning_raft_$tag.json" ] && grep -q '"complete": true' \
      "$WT/benchmarks/results/learning_raft_$tag.json" && continue  # finished, not yet taken in
    case $tag in
      tuned_a) seeds=(--seeds 0,1 --at-once) ;;
      tuned_b) seeds=(--seeds 2,3 --at-once) ;;
      tuned_c) seeds=(--seeds 4) ;;
    esac
    step "$tag" "$PY" benchmarks/learning --arms tuned --preset "$PRESET" "${seeds[@]}" --tag "$tag" \
      --middlebury "$MB" || true
    if ! grep -q '"complete": true' "$WT/benchmarks/results/learning_raft_$tag.json" 2>/dev/null; then
      echo "$tag left no complete result: stop" >> "$LOG"
      exit 1
    fi
  done
) > /dev/null 2>&1 < /dev/null &
disown
echo "tune_proof.sh: started; log .cache/tune_proof.log"
