"""Ctrl-C and SIGTERM stop `play`, `node`, `replay` and `demo` quietly: no traceback, queued work
finished or counted, exit code 0 (130 for an interrupted replay that saved what it fused)."""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from senfunet_ros.bagio import copy_bag, open_bag

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "bags" / "sim_room"
CLI = [sys.executable, "-m", "senfunet_ros.cli"]


@pytest.fixture(scope="module")
def prefix(tmp_path_factory: pytest.TempPathFactory) -> Path:
    with open_bag(SAMPLE) as reader:
        stop = reader.start_ns + 600_000_000
    return copy_bag(SAMPLE, tmp_path_factory.mktemp("bags") / "prefix", stop_ns=stop)


def _wait_for_text(path: Path, text: str, proc: subprocess.Popen, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if text in path.read_text(errors="replace"):
            return
        assert proc.poll() is None, f"exited early ({proc.returncode}): {path.read_text(errors='replace')}"
        time.sleep(0.1)
    raise AssertionError(f"no '{text}' in {path} after {timeout_s} s: {path.read_text(errors='replace')[-2000:]}")


def _start(cmd: list[str], log: Path) -> subprocess.Popen:
    """cmd run in log's folder, its output into log; this checkout's packages first on its path (the
    folder is not the checkout, whose sources `python -m` would otherwise take, not an installed copy's)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p)}
    with log.open("w") as out:
        return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=log.parent, env=env)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_play_loop_stops_quietly(prefix: Path, tmp_path: Path, ros_domain_id: int, sig: signal.Signals) -> None:
    """Ctrl-C, SIGTERM, and SIGHUP (the terminal or ssh session closed: it killed play, and a bag read
    through a temporary copy left the copy behind) end play with exit code 0."""
    log = tmp_path / "play.log"
    proc = _start([*CLI, "play", str(prefix), "--loop", "--rate", "2"], log)
    _wait_for_text(log, "playing", proc, 60)
    time.sleep(1.5)  # mid-publication, past the first loop
    proc.send_signal(sig)
    assert proc.wait(30) == 0, log.read_text()
    text = log.read_text()
    assert "Traceback" not in text and "RCLError" not in text and "stopped" in text


def _node_stopped_by_sigterm(tmp_path: Path, output_dir: Path) -> str:
    """A node saving on shutdown into output_dir, stopped by SIGTERM once it fuses: exit code 0, no
    traceback; its log."""
    log = tmp_path / "node.log"
    proc = _start([*CLI, "node", "--", "-p", "voxel_size_m:=0.04", "-p", "working_width:=64",
                   "-p", "save_on_shutdown:=true", "-p", f"output_dir:={output_dir}"], log)
    _wait_for_text(log, "fusing", proc, 180)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(60) == 0, log.read_text()
    text = log.read_text()
    assert "Traceback" not in text
    return text


# what a stop in the wrong order prints: a log call after rclpy's context or the node is gone, a handle
# used after its destruction, a timer or callback that outlived its node
_SHUTDOWN_TROUBLE = ("Error", "Traceback", "failed to publish", "InvalidHandle", "[ERROR]", "Exception")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_node_fusing_a_stream_stops_cleanly(prefix: Path, tmp_path: Path, ros_domain_id: int,
                                              sig: signal.Signals) -> None:
    """A node stopped by SIGINT or SIGTERM while a bag plays to it (its timers integrating and meshing):
    timers and worker threads stop, the queued frames are finished and counted, the meshes saved, and
    only then is the node destroyed and rclpy shut down. Exit code 0 and nothing in its output that a
    wrong order prints (a log line after the context is shut down, an invalid handle, a traceback)."""
    log = tmp_path / "node.log"
    node = _start([*CLI, "node", "--use-sim-time", "--", "-p", "voxel_size_m:=0.04", "-p", "working_width:=64",
                   "-p", "save_on_shutdown:=true", "-p", f"output_dir:={tmp_path / 'out'}"], log)
    play = None
    try:
        _wait_for_text(log, "fusing", node, 180)
        play_log = tmp_path / "play.log"
        play = _start([*CLI, "play", str(prefix), "--loop", "--rate", "1"], play_log)
        _wait_for_text(play_log, "playing", play, 60)
        time.sleep(5.0)  # several passes of the bag: frames integrated, mesh updates under way
        assert node.poll() is None, log.read_text()
        node.send_signal(sig)
        assert node.wait(60) == 0, log.read_text()
    finally:
        if node.poll() is None:
            node.kill()
        if play is not None:
            play.send_signal(signal.SIGINT)
            play.wait(30)
    text = log.read_text(errors="replace")
    assert "senfunet: stopped" in text and (tmp_path / "out" / "mesh.ply").is_file(), text[-3000:]
    trouble = [line for line in text.splitlines() if any(word in line for word in _SHUTDOWN_TROUBLE)]
    assert not trouble, text[-3000:]


def test_a_second_signal_while_the_net_judges_for_the_shutdown_save_writes_the_meshes_as_they_stand(
        tmp_path: Path, ros_domain_id: int) -> None:
    """ros2 launch stops a node with SIGINT, then SIGTERM after its sigterm_timeout (and SIGKILL after its
    sigkill_timeout): a node saving on shutdown with the weighting net's backlog to judge first (seconds,
    on a room) took the SIGTERM for "stop saving" and wrote nothing. The net now stops judging and the
    fused mesh alone is written, as it stands."""
    log = tmp_path / "node.log"
    node = _start([*CLI, "node", "--use-sim-time", "--", "-p", "save_on_shutdown:=true",
                   "-p", f"output_dir:={tmp_path / 'out'}"], log)
    play = None
    try:
        _wait_for_text(log, "fusing", node, 180)
        play_log = tmp_path / "play.log"
        play = _start([*CLI, "play", str(SAMPLE), "--wait-subscribers", "30"], play_log)
        assert play.wait(120) == 0, play_log.read_text()
        node.send_signal(signal.SIGINT)
        _wait_for_text(log, "the weighting net first judges", node, 60)
        node.send_signal(signal.SIGTERM)
        assert node.wait(60) == 0, log.read_text()
    finally:
        for proc in (node, play):
            if proc is not None and proc.poll() is None:
                proc.kill()
    text = log.read_text(errors="replace")
    assert "the weighting net stops judging; the fused mesh alone is written, as it stands" in text, text[-3000:]
    assert "blocks not judged" in text and (tmp_path / "out" / "mesh.ply").is_file(), text[-3000:]
    assert not (tmp_path / "out" / "tof.ply").exists()  # the per-sensor meshes would keep SIGKILL waiting
    # the frames set aside while the node was behind are in the saved map, not dropped at the stop
    assert "0 still waiting" in text, text[-3000:]


def test_node_sigterm_finishes_and_exits_zero(tmp_path: Path, ros_domain_id: int) -> None:
    text = _node_stopped_by_sigterm(tmp_path, tmp_path / "out")
    assert "rejected by the engine" not in text
    assert "senfunet: stopped" in text and (tmp_path / "out" / "mesh.ply").is_file()


def test_a_node_that_fused_nothing_keeps_the_meshes_an_earlier_run_saved(tmp_path: Path, ros_domain_id: int) -> None:
    """save_on_shutdown on a node that fused nothing (its sensors never came: a topic typo) replaced the
    earlier run's mesh.ply by an empty one; it is kept, and the log says why."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "mesh.ply").write_bytes(b"an earlier run's mesh")
    text = _node_stopped_by_sigterm(tmp_path, out)
    assert (out / "mesh.ply").read_bytes() == b"an earlier run's mesh"
    assert "senfunet: not saved on shutdown: the map is empty" in text and "senfunet: saved" not in text, text


def test_node_saving_on_shutdown_into_an_unusable_output_dir_saves_elsewhere_and_says_so(tmp_path: Path,
                                                                                          ros_domain_id: int) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("")  # output_dir below a file: no folder can be made there
    text = _node_stopped_by_sigterm(tmp_path, blocker / "out")
    assert "saving on shutdown into output_dir failed" in text and "check parameter output_dir" in text
    saved = [line for line in text.splitlines() if line.startswith("senfunet: saved instead ")]
    assert saved, text
    paths = [Path(path) for path in saved[0].removeprefix("senfunet: saved instead ").split(", ")]
    mesh = paths[0]  # written first
    assert mesh.name == "mesh.ply" and all(path.is_file() for path in paths)
    shutil.rmtree(mesh.parent)


def test_replay_sigterm_saves_what_it_fused(tmp_path: Path) -> None:
    log = tmp_path / "replay.log"
    proc = _start([*CLI, "replay", str(SAMPLE), "--out", str(tmp_path / "out")], log)
    _wait_for_text(log, "frames=", proc, 300)  # the progress bar shows fused frames
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(300) == 130, log.read_text()
    text = log.read_text()
    assert "Traceback" not in text and "stopping" in text and "interrupted" in text
    assert (tmp_path / "out" / "mesh.ply").is_file() and (tmp_path / "out" / "stats.json").is_file()


class _StopAfter(threading.Event):
    """Set once it was asked n times: a stop at a known point of the reading loop."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.n = n

    def is_set(self) -> bool:
        self.n -= 1
        return self.n < 0


def test_replay_stops_on_its_stop_event_even_without_an_exception(tmp_path: Path) -> None:
    """The signal handlers set the stop event: the reading ends at the next message, with no
    exception, and what was fused is written."""
    from senfunet_ros.replay import replay_bag

    result = replay_bag(SAMPLE, tmp_path, progress=False, stop=_StopAfter(400))
    assert result.interrupted and result.error is None
    sensors = result.stats["sensors"]
    assert sum(c["integrated"] for c in sensors.values()) > 0
    assert result.stats["messages_read"] < 500 < result.stats["bag"]["messages"]  # it stopped at its 400th message
    assert (tmp_path / "mesh.ply").is_file() and (tmp_path / "stats.json").is_file()


@pytest.mark.slow
def test_demo_ctrl_c_stops_node_and_play(tmp_path: Path, ros_domain_id: int) -> None:
    log = tmp_path / "demo.log"
    proc = _start([*CLI, "demo", "--out", str(tmp_path / "demo"), "--no-render", "--domain-id", str(ros_domain_id)],
                  log)
    _wait_for_text(log, "node up", proc, 300)
    time.sleep(3.0)  # play is running
    proc.send_signal(signal.SIGINT)
    assert proc.wait(120) == 0, log.read_text()
    text = log.read_text()
    assert "Traceback" not in text and "interrupted" in text
    node_log = (tmp_path / "demo" / "node.log")
    if node_log.exists():
        assert "Traceback" not in node_log.read_text(errors="replace")


# FusionNode replaced by a start-up that takes long (as the kernel warm-up does on a first start)
# and then creates a subscription, as the real one does after its warm-up
SCRIPT = r"""
import sys, time
import senfunet_ros.node as n

class SlowStart:
    def __init__(self, **kwargs):
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


def test_sigterm_during_start_up_exits_quietly(ros_domain_id: int):
    """A SIGTERM (docker stop, systemd, launch) while the node starts stops it quietly, exit 0."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
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


def test_a_shutdown_the_signal_handler_raced_is_a_stop(monkeypatch: pytest.MonkeyPatch) -> None:
    """rclpy's signal handler shuts the context down from its own thread: main's try_shutdown, racing
    it, got 'rcl_shutdown already called' (a traceback and exit 1 after a SIGTERM at start-up)."""
    import rclpy
    from rclpy._rclpy_pybind11 import RCLError

    from senfunet_ros.dds import shut_down_rclpy

    def raced() -> None:
        raise RCLError("failed to shutdown: rcl_shutdown already called on the given context")

    monkeypatch.setattr(rclpy, "try_shutdown", raced)
    monkeypatch.setattr(rclpy, "ok", lambda: False)
    shut_down_rclpy()  # a stop, not an error
    monkeypatch.setattr(rclpy, "ok", lambda: True)  # the context still up: a real failure, raised
    with pytest.raises(RCLError):
        shut_down_rclpy()


def test_use_sim_time_toggled_through_the_parameter_service_leaves_the_node_running(tmp_path: Path, ros) -> None:
    """`ros2 param set /senfunet use_sim_time true|false`, again and again: setting it false drops the
    /clock subscriptions (rclpy's and the node's) in the parameter service's callback while the spin
    thread may be putting them in its wait set. rclpy raised InvalidHandle there, out of the spin:
    the node died (exit code 1) after a few toggles."""
    import rclpy
    from rcl_interfaces.srv import SetParameters
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    log = tmp_path / "node.log"
    node = _start([*CLI, "node", "--", "-r", "__ns:=/simtoggle", "-p", "voxel_size_m:=0.04", "-p", "working_width:=64",
                   "-p", f"output_dir:={tmp_path / 'out'}"], log)
    client_node = Node("simtoggle_client")
    try:
        _wait_for_text(log, "fusing", node, 180)
        client = client_node.create_client(SetParameters, "/simtoggle/senfunet/set_parameters")
        assert client.wait_for_service(timeout_sec=30), log.read_text()
        for i in range(100):
            request = SetParameters.Request(parameters=[Parameter("use_sim_time", value=i % 2 == 0).to_parameter_msg()])
            future = client.call_async(request)
            rclpy.spin_until_future_complete(client_node, future, timeout_sec=20)
            assert node.poll() is None, f"died after {i + 1} toggles: {log.read_text()[-3000:]}"
            assert future.done() and future.result().results[0].successful, log.read_text()[-3000:]
        time.sleep(0.5)
        assert node.poll() is None, log.read_text()[-3000:]
        node.send_signal(signal.SIGINT)
        assert node.wait(60) == 0, log.read_text()[-3000:]
    finally:
        client_node.destroy_node()
        if node.poll() is None:
            node.kill()
    assert "Traceback" not in log.read_text(), log.read_text()[-3000:]
