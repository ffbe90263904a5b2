#!/usr/bin/env bash
# Create .venv (if missing) and install torchtrack with its test extras.
# The CPU build of torch is installed first, explicitly: a bare `torch` requirement
# would otherwise resolve to a multi-GB CUDA build.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install --quiet "torch==2.13.0"
.venv/bin/python -m pip install --quiet -e ".[test]"
echo "torchtrack installed in .venv ($(.venv/bin/python -c 'import torch; print("torch", torch.__version__)'))" >&2
