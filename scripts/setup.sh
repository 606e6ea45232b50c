#!/usr/bin/env bash
# Create .venv and install flowsynth with its test extras. The pinned CPU torch goes in FIRST so that no
# later requirement pulls a CUDA build of torch (several GB).
#   bash scripts/setup.sh            flowsynth + test extras
#   bash scripts/setup.sh --ray      also the Ray engine (flowsynth[ray]: Ray Data and Ray Train)
#   bash scripts/setup.sh --bench    also the benchmark peers and plots (flowsynth[bench])
# benchmarks/peers/cycles.py also needs Blender on PATH, which this script does not install (Debian: apt-get install
# blender); without it that benchmark prints a "not installed" row and exits 0.
set -euo pipefail
cd "$(dirname "$0")/.."
EXTRAS=test
for arg in "$@"; do
  case "$arg" in
    --ray) EXTRAS="$EXTRAS,ray" ;;
    --bench) EXTRAS="$EXTRAS,bench" ;;
    *) echo "scripts/setup.sh: unknown option $arg (known: --ray, --bench)" >&2; exit 2 ;;
  esac
done
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q "torch==2.13.0"
.venv/bin/python -m pip install -q -e ".[$EXTRAS]"
# torchvision (the train extra's package) for the tests, whose dataset classes read the export layouts: --no-deps,
# or it pulls a CUDA torch; so not as .[train]
.venv/bin/python -m pip install -q --no-deps "torchvision==0.28.0"
