"""Shared fixtures: a private ROS domain per test run, so parallel runs never hear each other."""
from __future__ import annotations

import os
import sys
from collections.abc import Iterator

import pytest

# Fast DDS reads this when the first participant of a process is created, so it is set at import
# time (before any test calls rclpy.init) and inherited by every child process (publishers,
# `senfunet play`, `senfunet demo` and its node). The profile gives each sender a large
# shared-memory segment instead of 512 KB: with the default, a receiving process that is not
# scheduled for ~0.5 s (a loaded 2-core CI machine) loses best-effort images. See the file.
from senfunet_ros.dds import use_large_shm_profile  # noqa: E402
from senfunet_ros.node import GIL_SWITCH_INTERVAL_S  # noqa: E402

use_large_shm_profile()
# The in-process node tests run FusionNode with the process settings its main() applies (a short
# GIL switch interval, without which busy timers starve the subscriptions).
sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)


@pytest.fixture(scope="session")
def ros_domain_id() -> int:
    """A ROS_DOMAIN_ID in 1..101 from the pid, or SENFUNET_TEST_DOMAIN_ID when set (a shared machine
    that hands each run its own); exported so child processes inherit it. Under pytest-xdist each
    worker takes its own: SENFUNET_TEST_DOMAIN_ID (or one from the parent's pid) plus the worker's
    number, so that the live nodes of two workers never hear each other."""
    chosen = os.environ.get("SENFUNET_TEST_DOMAIN_ID", "").strip()
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if worker:
        index = int(worker.removeprefix("gw"))
        domain = int(chosen) + index if chosen else 1 + (os.getppid() + index) % 101
    else:
        domain = int(chosen) if chosen else 1 + os.getpid() % 101
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # keep test traffic off the network
    return domain


@pytest.fixture(scope="module")
def ros(ros_domain_id: int) -> Iterator[int]:
    """rclpy initialised for the tests of one module (in this process), shut down after them."""
    import rclpy

    rclpy.init()
    yield ros_domain_id
    rclpy.try_shutdown()


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test under test/ros needs rclpy (or rosbags): `-m "not ros"` runs the core alone."""
    here = os.path.dirname(__file__)
    for item in items:
        if str(item.path).startswith(here):
            item.add_marker(pytest.mark.ros)
