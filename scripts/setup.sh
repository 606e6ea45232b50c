#!/usr/bin/env bash
# Create .venv and install flowsynth with its test extras. The pinned CPU torch goes in FIRST so that no
# later requirement pulls a CUDA build of torch (several GB).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q "torch==2.13.0"
.venv/bin/python -m pip install -q -e ".[test]"
# torchvision for the tests only (its dataset classes read the export layouts): --no-deps, or it pulls a CUDA torch
.venv/bin/python -m pip install -q --no-deps "torchvision==0.28.0"
