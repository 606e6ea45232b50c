#!/usr/bin/env bash
# Run the test suite as a clean machine would: a fresh, empty TMPDIR and HOME for this run, and every
# cache (Warp kernels, XDG, matplotlib, hypothesis) in the repository's ignored .cache/ folder, never
# under HOME. Arguments go to pytest. Run scripts/setup.sh first (the README's test command does).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
mkdir -p "$ROOT/.cache"
RUN=$(mktemp -d "$ROOT/.cache/run.XXXXXX")
trap 'rm -rf "$RUN"' EXIT
mkdir -p "$RUN/tmp" "$RUN/home"
export TMPDIR="$RUN/tmp" HOME="$RUN/home"
export XDG_CACHE_HOME="$ROOT/.cache/xdg" WARP_CACHE_PATH="$ROOT/.cache/warp" MPLCONFIGDIR="$ROOT/.cache/mpl"
export FLOWSYNTH_HERMETIC=1
.venv/bin/python -m pytest "$@"
