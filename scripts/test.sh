#!/usr/bin/env bash
# Run the test suite as a clean machine would: a fresh, empty TMPDIR and HOME for this run, and every
# cache (Warp kernels, XDG, matplotlib) in the repository's ignored .cache/ folder, never under HOME.
# Hypothesis runs derandomized and keeps no example database; HYPOTHESIS_PROFILE=dev keeps one in
# .cache/hypothesis (tests/conftest.py). Arguments go to pytest. Run scripts/setup.sh first (the README's
# test command does).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
mkdir -p "$ROOT/.cache"
# A fresh, empty run folder (TMPDIR and HOME) of a short name in /tmp, not under the checkout: sockets live under
# TMPDIR (multiprocessing's resource sharer, which DataLoader workers use to send tensors; Ray under RAY_TMPDIR), and
# an AF_UNIX path may not exceed 107 bytes, while a checkout's path may be long (a CI runner's). Under a long
# checkout path the sockets failed: Ray at startup, DataLoader workers by hanging. Falls back to .cache/run.*.
RUN=$(mktemp -d /tmp/fs.XXXXXX 2>/dev/null || mktemp -d "$ROOT/.cache/run.XXXXXX")
RAY_RUN=$(mktemp -d /tmp/fr.XXXXXX 2>/dev/null || echo "$RUN/ray")
trap 'rm -rf "$RUN" "$RAY_RUN"' EXIT
mkdir -p "$RUN/tmp" "$RUN/home" "$RAY_RUN"
export TMPDIR="$RUN/tmp" HOME="$RUN/home" RAY_TMPDIR="$RAY_RUN"
export XDG_CACHE_HOME="$ROOT/.cache/xdg" WARP_CACHE_PATH="$ROOT/.cache/warp" MPLCONFIGDIR="$ROOT/.cache/mpl"
export FLOWSYNTH_HERMETIC=1
# --as-ci first: the bench extra's modules cannot be imported (a folder of stand-ins that raise ModuleNotFoundError,
# first on PYTHONPATH), so a .venv set up with --bench runs the suite as CI's (set up with --ray only) does. Limits:
# importlib.util.find_spec and importlib.metadata still see the real packages, and a child process given a PYTHONPATH
# of its own (not prepended to this one) imports them.
if [ "${1:-}" = "--as-ci" ]; then
  shift
  for m in embreex matplotlib mitsuba pybullet skimage; do
    mkdir -p "$RUN/without/$m"
    echo "raise ModuleNotFoundError('$m: scripts/test.sh --as-ci hides the bench extra', name='$m')" \
      > "$RUN/without/$m/__init__.py"
  done
  export PYTHONPATH="$RUN/without${PYTHONPATH:+:$PYTHONPATH}"
fi
.venv/bin/python -m pytest "$@"
