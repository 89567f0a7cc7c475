"""Shared fixtures: a private ROS domain per test run, so parallel runs never hear each other."""
from __future__ import annotations

import os

import pytest


@pytest.fixture(scope="session")
def ros_domain_id() -> int:
    """A ROS_DOMAIN_ID in 1..101 from the pid, exported so child processes inherit it."""
    domain = 1 + os.getpid() % 101
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # keep test traffic off the network
    return domain
