#!/usr/bin/env bash
# The README's test command: set-up, lint (ruff), types (mypy), then the tests.
# Arguments go to pytest, e.g. `bash scripts/check.sh -m "not slow"` or `bash scripts/check.sh test/core`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
echo "senfunet: ruff check"
.venv/bin/ruff check .
echo "senfunet: mypy"
.venv/bin/mypy
echo "senfunet: pytest"
if [ "$#" -eq 0 ]; then
  set -- test
fi
.venv/bin/python -m pytest -q "$@"
