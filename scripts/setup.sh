#!/usr/bin/env bash
# Creates ./.venv with the pinned dependencies and this package, and compiles the numba kernels
# (idempotent).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.senfunet-setup
if [ ! -f "$stamp" ] || [ requirements.txt -nt "$stamp" ] || [ setup.py -nt "$stamp" ]; then
  .venv/bin/python -m pip install -q --disable-pip-version-check -r requirements.txt
  .venv/bin/python -m pip install -q --disable-pip-version-check --no-deps -e .
  touch "$stamp"
fi
# numba's kernels compiled now, not in the first frames of a node or the first test
.venv/bin/python scripts/compile_kernels.py
echo "senfunet: environment ready in $(pwd)/.venv"
