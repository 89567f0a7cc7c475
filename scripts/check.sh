#!/usr/bin/env bash
# The README's test command: set-up, lint (ruff), types (mypy), then the tests.
# Without arguments: test/core and the offline ROS tests on up to 4 pytest-xdist workers, then the
# other ROS tests on 2 workers.
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
# The core tests, and the ROS tests that exchange no DDS messages (bag files, packaging, conversions, ingest, replay,
# sensor set-ups, TF, mesh size on the wire, map services), side by side, one file per worker (each is CPU work on one
# thread; up to 4 workers); then
# the other ROS tests, which run live nodes, DDS and processes against the clock, on 2 workers, one file each (most
# of their time is waiting: for discovery, a child process's start, a stream at its recorded rate; each worker has
# its own ROS_DOMAIN_ID, conftest.py). Each run lists its slowest tests (--durations): the suite should stay under
# 10 minutes.
offline=(test/ros/test_bags.py test/ros/test_sample_bag.py test/ros/test_packaging.py test/ros/test_conversions.py
         test/ros/test_ingest.py test/ros/test_compressed.py test/ros/test_replay.py test/ros/test_tf.py
         test/ros/test_mesh_wire.py test/ros/test_map_bound_services.py test/ros/test_sensor_setups.py)
workers=$(nproc 2>/dev/null || echo 2)
workers=$(( workers < 2 ? 2 : (workers > 4 ? 4 : workers) ))
status=0
.venv/bin/python -m pytest -q --durations=12 -n "$workers" --dist loadfile test/core "${offline[@]}" || status=$?
.venv/bin/python -m pytest -q --durations=12 -n 2 --dist loadfile test/ros "${offline[@]/#/--ignore=}" || status=$?
exit "$status"
