#!/usr/bin/env bash
# The README's test command: set-up, lint (ruff), types (mypy), then the tests.
# Without arguments: test/core on up to 4 pytest-xdist workers, then test/ros in one process.
# Arguments go to one pytest run instead, e.g. `bash scripts/check.sh -m "not slow"` or
# `bash scripts/check.sh test/core`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
echo "senfunet: ruff check"
.venv/bin/ruff check .
echo "senfunet: mypy"
.venv/bin/mypy
echo "senfunet: pytest"
if [ "$#" -gt 0 ]; then
  exec .venv/bin/python -m pytest -q "$@"
fi
# The core tests side by side, one file per worker (each is CPU work on one thread; up to 4 workers);
# then the ROS tests one at a time: they run live nodes, DDS and processes against the clock.
workers=$(nproc 2>/dev/null || echo 2)
workers=$(( workers < 2 ? 2 : (workers > 4 ? 4 : workers) ))
status=0
.venv/bin/python -m pytest -q -n "$workers" --dist loadfile test/core || status=$?
.venv/bin/python -m pytest -q test/ros || status=$?
exit "$status"
