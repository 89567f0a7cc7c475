"""A SIGTERM (docker stop, systemd, launch) while the node starts stops it quietly, exit 0."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

# FusionNode replaced by a start-up that takes long (as the kernel warm-up does on a first start)
# and then creates a subscription, as the real one does after its warm-up
SCRIPT = r"""
import sys, time
import senfunet_ros.node as n

class SlowStart:
    def __init__(self):
        import rclpy
        from std_msgs.msg import String
        print("starting", flush=True)
        end = time.monotonic() + 30.0
        while time.monotonic() < end:
            sum(range(10000))  # Python work, like the warm-up's
        self.inner = rclpy.create_node("slow_start")
        self.inner.create_subscription(String, "/x", lambda m: None, 10)

n.FusionNode = SlowStart
sys.exit(n.main(["senfunet"]))
"""


def test_sigterm_during_start_up_exits_quietly():
    env = {**os.environ, "PYTHONPATH": str(REPO), "ROS_DOMAIN_ID": os.environ.get("ROS_DOMAIN_ID", "174"),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=env)
    assert proc.stdout.readline().strip() == "starting"
    time.sleep(0.5)
    t0 = time.monotonic()
    proc.terminate()
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert "Traceback" not in out, out
    assert time.monotonic() - t0 < 10.0  # stopped at once, not after the start-up
