"""The node as a robot runs it: malformed bursts keep the map, run-time parameters, /diagnostics,
map save/load, file modes. Real rclpy nodes on a private ROS_DOMAIN_ID (see conftest)."""
from __future__ import annotations

import contextlib
import os
import re
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from test_node import (BASE_S, MeshCollector, Running, SpinThread, _marker_keys, _pose_msg, _stamp, topic_params,
                       wait_for)

from senfunet_ros import params as P
from senfunet_ros.node import stop_executor

SIM = dict(duration_s=2.0, width=96, height=96, tof_rate_hz=6.0, stereo_rate_hz=6.0)
SMALL = dict(voxel_size_m=0.04, band_m=0.4, working_width=48, queue_size=500, max_lag_s=0.0, integrate_rate_hz=50.0,
             mesh_rate_hz=2.0, tsdf_fusion=False)


def scene_messages(seed: int = 5) -> list[tuple[str, str, Any]]:
    """A short simulated two-sensor scene as (sensor, stream, rclpy message) in stamp order."""
    from senfunet_core.learning.simulator import make_scene, simulate_sequence

    seq = simulate_sequence(make_scene(seed), seed=seed, **SIM)
    events: list[tuple[float, int, str, str, Any]] = []
    for s in ("tof", "stereo"):
        for t, T in zip(seq.pose_stamps_s[s], seq.pose_T_world_camera[s]):
            events.append((t, 0, s, "pose", _pose_msg(t, T)))
    for f in seq.frames:
        h, w = f.depth_m.shape
        info = CameraInfo(width=w, height=h, k=[float(v) for v in f.K.reshape(-1)])
        _stamp(info, f.stamp_s)
        depth = Image(height=h, width=w, encoding="32FC1", step=w * 4)
        depth.data = np.ascontiguousarray(f.depth_m, "<f4").tobytes()
        _stamp(depth, f.stamp_s)
        events += [(f.stamp_s, 1, f.sensor, "camera_info", info), (f.stamp_s, 2, f.sensor, "depth", depth)]
        if f.rgb is not None:
            color = Image(height=h, width=w, encoding="rgb8", step=w * 3)
            color.data = np.ascontiguousarray(f.rgb).tobytes()
            _stamp(color, f.stamp_s)
            events.append((f.stamp_s, 1, f.sensor, "color", color))
    events.sort(key=lambda e: (e[0], e[1]))
    return [(s, stream, msg) for _, _, s, stream, msg in events]


def fuse_in_process(run: Running, messages: list[tuple[str, str, Any]]) -> None:
    """The node's own subscription path (pipeline.dispatch), without DDS, then wait for integration."""
    for sensor, stream, msg in messages:
        run.node.pipeline.dispatch(sensor, stream, msg)
    expected = sum(1 for _, stream, _ in messages if stream == "depth")

    def settled() -> bool:  # nearly every frame integrated, and none still in flight
        counters = run.node.ingest.ledger.counters().values()
        return (sum(c["integrated"] for c in counters) >= expected - 2
                and all(c["integrated"] + sum(c["dropped"].values()) >= c["received"] for c in counters))

    wait_for(settled, 120, "the scene to be integrated")


def malformed(t_s: float, kind: str, i: int) -> Any:
    """A malformed message of every input type, with a bad stamp every other time."""
    stamp_s = [0.0 - BASE_S, 2**31 - 1 - BASE_S, t_s][i % 3]
    if kind == "depth":
        msg = Image(height=4, width=4, encoding=["bgr8", "32FC1", "16UC1"][i % 3], step=[12, 2, 8][i % 3])
        msg.data = bytes(range(16))
    elif kind == "color":
        msg = Image(height=4, width=4, encoding="yuv422", step=8)
    elif kind == "camera_info":
        msg = CameraInfo(width=0, height=4, k=[float("nan")] * 9)
    else:
        msg = PoseStamped()
        msg.pose.orientation.w = [float("nan"), 2.0, 1.0][i % 3]
    _stamp(msg, stamp_s)
    return msg


def test_malformed_burst_keeps_the_map(ros, tmp_path: Path) -> None:
    prefix = "burst"
    run = Running("burst", {**topic_params(prefix), **SMALL}, tmp_path)
    pub_node = Node("burst_publisher")
    try:
        fuse_in_process(run, scene_messages())
        before = run.node.engine.extract_mesh("fused").n_faces
        assert before > 100
        kinds = {"depth": Image, "color": Image, "camera_info": CameraInfo, "pose": PoseStamped}
        pubs = {(s, k): pub_node.create_publisher(t, f"/{prefix}/{s}/{k}", 50)
                for s in ("tof", "stereo") for k, t in kinds.items()}
        wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 20, "discovery")
        time.sleep(1.0)  # the node's side of discovery
        received_before = {s: c["received"] + c["pose_received"] + c["color_received"]
                           for s, c in run.node.ingest.ledger.counters().items()}
        for i in range(400):  # 400 malformed messages over every input type of both sensors
            sensor, kind = list(pubs)[i % len(pubs)]
            pubs[(sensor, kind)].publish(malformed(2.5, kind, i))
            if i % 8 == 7:
                time.sleep(0.01)  # best-effort readers keep 30: let them take the burst
        wait_for(lambda: sum(c["received"] + c["pose_received"] + c["color_received"]
                             for c in run.node.ingest.ledger.counters().values())
                         - sum(received_before.values()) >= 100,
                 20, "the burst to arrive")
        time.sleep(2.0)  # integration and mesh timers run over it
        counters = run.node.ingest.ledger.counters()
        assert run.thread.is_alive()
        assert run.node.pipeline.time_jumps == 0 and all(c["time_jumps"] == 0 for c in counters.values())
        assert sum(c["dropped"]["bad_stamp"] for c in counters.values()) > 0
        assert sum(c["dropped"]["bad_encoding"] + c["dropped"]["bad_pose"] for c in counters.values()) > 0
        after = run.node.engine.extract_mesh("fused").n_faces
        assert after == before  # nothing of the burst reached the map, and nothing of the map went
    finally:
        pub_node.destroy_node()
        run.close()


@pytest.mark.parametrize("buffer_mb", [256.0, 0.0])
def test_frames_behind_are_set_aside_and_integrated_once_nothing_newer_waits(ros, tmp_path: Path,
                                                                            buffer_mb: float) -> None:
    """A burst the node cannot integrate within max_lag_s: with behind_buffer_mb the frames it fell
    behind on are set aside and integrated once no newer frame waits, so every frame reaches the map;
    with 0 they are skipped, counted as behind."""
    prefix = f"aside{int(buffer_mb)}"
    run = Running(prefix, {**topic_params(prefix), **SMALL, "max_lag_s": 0.01, "behind_buffer_mb": buffer_mb},
                  tmp_path)
    try:
        messages = scene_messages()
        for sensor, stream, msg in messages:  # all at once, through the node's own subscription path
            run.node.pipeline.dispatch(sensor, stream, msg)
        expected = sum(1 for _, stream, _ in messages if stream == "depth")

        def settled() -> bool:
            return all(c["integrated"] + sum(c["dropped"].values()) >= c["received"]
                       for c in run.node.ingest.ledger.counters().values())

        wait_for(settled, 120, "every frame to be integrated or dropped")
        counters = run.node.ingest.ledger.counters().values()
        integrated = sum(c["integrated"] for c in counters)
        set_aside = sum(c["set_aside"] for c in counters)
        behind = sum(c["dropped"]["behind"] for c in counters)
        if buffer_mb:
            assert set_aside > 0 and behind == 0 and integrated == expected
        else:
            assert set_aside == 0 and behind > 0 and integrated + behind == expected
        assert all(c["set_aside_now"] == 0 for c in counters)
    finally:
        run.close()


def _set(run: Running, **values: Any) -> list[Any]:
    """SetParameters through the node's parameter service, as `ros2 param set` does."""
    client = run.helper.create_client(SetParameters, f"{run.prefix}/set_parameters")
    assert client.wait_for_service(timeout_sec=10.0)
    request = SetParameters.Request()
    for name, value in values.items():
        if isinstance(value, str):
            pv = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value)
        elif isinstance(value, float):
            pv = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
        else:
            pv = ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value)
        request.parameters.append(ParameterMsg(name=name, value=pv))
    future = client.call_async(request)
    wait_for(future.done, 10, "set_parameters")
    return future.result().results


def test_parameters_typed_ranged_read_only_and_applied(ros, tmp_path: Path) -> None:
    run = Running("params_rt", {**topic_params("params_rt"), **SMALL}, tmp_path)
    try:
        (r,) = _set(run, voxel_size_m="abc")
        assert not r.successful and "voxel_size_m" in r.reason
        (r,) = _set(run, mesh_rate_hz=-5.0)
        assert not r.successful and "mesh_rate_hz" in r.reason
        (r,) = _set(run, mesh_rate_hz="fast")
        assert not r.successful
        (r,) = _set(run, status_rate_hz=1e-12)  # a period beyond a timer's nanosecond counter
        assert not r.successful and "status_rate_hz" in r.reason
        (r,) = _set(run, pose_max_wait_s=3.0)  # poses lagging 3 s would be off the images' timeline (1 s)
        assert not r.successful and "time_jump_s" in r.reason
        (r,) = _set(run, voxel_size_m=0.02)  # the map's grid cannot change under it
        assert not r.successful and "read-only" in r.reason
        (r,) = _set(run, **{"tof.depth_max_m": 0.05})  # below depth_min_m: an empty range
        assert not r.successful and "depth" in r.reason
        # moving the range above its maximum one parameter at a time: the reply says which to set first
        (r,) = _set(run, **{"tof.depth_min_m": 4.0})
        assert not r.successful and "tof.depth_max_m" in r.reason and "first" in r.reason, r.reason
        assert run.node.settings.mesh_rate_hz == 2.0 and run.node.get_parameter("mesh_rate_hz").value == 2.0
        (r,) = _set(run, mesh_rate_hz=4)  # an integer for a float parameter is fine
        assert r.successful, r.reason
        # the timer's period is 10% shorter than asked, so that the refresh holds 4 Hz despite the updates' jitter
        assert run.node.settings.mesh_rate_hz == 4.0 and run.node._mesh_timer.timer_period_ns == 225_000_000
        (r,) = _set(run, **{"tof.depth_max_m": 2.0})
        assert r.successful and run.node.engine.config.depth_max_m[0] == 2.0
        (r,) = _set(run, max_lag_s=0.5)
        assert r.successful and run.node.ingest.config.max_lag_s == 0.5
        descriptor = run.node.describe_parameter("voxel_size_m")
        assert descriptor.read_only and descriptor.floating_point_range[0].from_value == pytest.approx(0.001)
        assert not run.node.describe_parameter("mesh_rate_hz").read_only
    finally:
        run.close()


@contextlib.contextmanager
def _posing_run(name: str, tmp_path: Path, **params: Any) -> Iterator[tuple[Running, Any, list[DiagnosticArray]]]:
    """A node on topics /<name>/..., its /diagnostics as they come, and a publisher of its tof poses
    the node has discovered; both go at the end."""
    run = Running(name, {**topic_params(name), **SMALL, "status_rate_hz": 5.0, **params}, tmp_path)
    pub_node = Node(f"{name}_publisher")
    got: list[DiagnosticArray] = []
    run.helper.create_subscription(DiagnosticArray, "/diagnostics", got.append, 10)
    try:
        pose_pub = pub_node.create_publisher(PoseStamped, f"/{name}/tof/pose", 50)
        wait_for(lambda: pose_pub.get_subscription_count() > 0, 20, "discovery")
        time.sleep(1.0)  # the node's side of discovery
        yield run, pose_pub, got
    finally:
        # the helper's subscription goes with it in close(), once the executor stopped: destroyed while
        # it spins, a callback it had already queued fails on the handle, an error nobody retrieves
        pub_node.destroy_node()
        run.close()


def test_diagnostics_rates_warn_clears_and_stale(ros, tmp_path: Path) -> None:
    with _posing_run("diag", tmp_path, diagnostics_window_s=1.5, stale_after_s=1.0) as (run, pose_pub, got):
        def tof_status() -> Any:
            for msg in reversed(got):
                for status in msg.status:
                    if status.name == "senfunet: tof":
                        return status
            return None

        def values(status: Any) -> dict[str, str]:
            return {kv.key: kv.value for kv in status.values}

        wait_for(lambda: tof_status() is not None, 10, "/diagnostics")
        t0 = time.monotonic()
        t = 10.0
        while time.monotonic() - t0 < 2.0:  # poses at ~20 Hz, then a bad one, then good ones
            msg = PoseStamped()
            msg.pose.orientation.w = 1.0 if abs(time.monotonic() - t0 - 0.5) > 0.05 else float("nan")
            _stamp(msg, t)
            pose_pub.publish(msg)
            t += 0.05
            time.sleep(0.05)
        wait_for(lambda: float(values(tof_status()).get("rate_hz.pose", 0)) > 5, 5, "a pose rate")
        assert int(values(tof_status())["dropped.bad_pose"]) >= 1
        assert tof_status().level == DiagnosticStatus.STALE or tof_status().level == DiagnosticStatus.WARN
        # the stream stops: STALE; the old drop leaves the window, so no WARN for it later
        wait_for(lambda: tof_status().level == DiagnosticStatus.STALE, 10, "STALE after the pose stream stopped")
        assert "pose" in tof_status().message
        wait_for(lambda: "recent_dropped.bad_pose" not in values(tof_status()), 10, "the drop to leave the window")
        # the stereo topics never received anything: a WARN naming them
        stereo = next(s for s in got[-1].status if s.name == "senfunet: stereo")
        assert stereo.level == DiagnosticStatus.WARN and "nothing received" in stereo.message
        assert any(s.name == "senfunet: pipeline" for s in got[-1].status)


def test_a_pose_republished_with_another_value_is_counted_in_diagnostics_and_logged_once(ros, tmp_path: Path,
                                                                                         capfd) -> None:
    """A pose driver that republishes stamps with other poses: each such pose is dropped as
    pose_conflict (the first kept), on /diagnostics with what differed, and warned about once per
    warning period, not once per message; the same pose again is no conflict."""
    with _posing_run("conflict", tmp_path) as (run, pose_pub, got):
        for i in range(10):
            for x in (0.0, 0.0, 0.5):  # each stamp: a pose, the same again, then another pose
                msg = PoseStamped()
                msg.pose.orientation.w, msg.pose.position.x = 1.0, 0.1 * i + x
                _stamp(msg, 10.0 + 0.05 * i)
                pose_pub.publish(msg)
            time.sleep(0.05)

        def tof_values() -> dict[str, str]:
            for msg in reversed(got):
                for status in msg.status:
                    if status.name == "senfunet: tof":
                        return {kv.key: kv.value for kv in status.values}
            return {}

        wait_for(lambda: int(tof_values().get("pose_received", 0)) == 30, 20, "the poses")
        wait_for(lambda: int(tof_values().get("dropped.pose_conflict", 0)) == 10, 10, "the conflicts on /diagnostics")
        values = tof_values()
        assert "0.500 m" in values["error.pose_conflict"] and "the first" in values["error.pose_conflict"]
        assert int(values["recent_dropped.pose_conflict"]) == 10
        time.sleep(0.5)  # the integration tick's warnings
    log = capfd.readouterr().err
    assert len([line for line in log.splitlines() if "pose_conflict" in line]) == 1, log


def test_a_silent_colour_topic_is_a_warning_only_for_a_sensor_whose_net_takes_colour() -> None:
    """The sample has no /tof/color and the ToF net takes no colour: nothing is missing, so no warning."""
    from types import SimpleNamespace

    from senfunet_ros.health import HealthMonitor
    from senfunet_ros.node import LatencyStats
    from senfunet_ros.status import StatusReport

    logged: list[tuple[str, str]] = []
    logger = SimpleNamespace(warning=lambda text: logged.append(("warning", text)),
                             info=lambda text: logged.append(("info", text)))
    engine = SimpleNamespace(counters={}, timings_s={}, stats=lambda wait=True: {},
                             config=SimpleNamespace(sensors=("tof", "stereo"), sensor_uses_rgb=(False, True)))
    pipeline = SimpleNamespace(latest_stamp_ns=0, ingest=SimpleNamespace(ledger=SimpleNamespace(counters=lambda: {})),
                               time_jumps=0, maps=1, frames_failed=0, frames_unfinished=0, engine=engine)
    health = HealthMonitor({"tof": ("depth", "color"), "stereo": ("depth", "color")}, window_s=0.05,
                           stale_after_s=1.0)
    for sensor in ("tof", "stereo"):
        health.received(sensor, "depth")
    topics = {s: {"depth": f"/{s}/depth", "color": f"/{s}/color"} for s in ("tof", "stereo")}
    report = StatusReport(pipeline, health, {}, LatencyStats(), topics=topics, hardware_id="/senfunet",
                          warn=lambda key, text: None, logger=logger)
    time.sleep(0.1)
    report.message("map")
    assert [level for level, text in logged if "/tof/color" in text] == ["info"]
    assert [level for level, text in logged if "/stereo/color" in text] == ["warning"]


def _running_once_it_sees(publisher: Any, name: str, tmp_path: Path, *, window_s: float) -> Running:
    """A node whose silent-topic warnings come once its graph holds `publisher` (another participant's):
    started with a long diagnostics window, narrowed to `window_s` once discovery is done, so that a
    loaded machine's slow discovery cannot make the warning say that nobody publishes."""
    from rclpy.parameter import Parameter

    run = Running(name, {**topic_params(name), **SMALL, "diagnostics_window_s": 600.0, "status_rate_hz": 10.0},
                  tmp_path)
    try:
        wait_for(lambda: run.node.get_publishers_info_by_topic(publisher.topic_name), 30, "discovery")
        assert all(r.successful for r in run.node.set_parameters([Parameter("diagnostics_window_s",
                                                                            value=window_s)]))
    except BaseException:
        run.close()
        raise
    return run


def test_a_silent_topic_published_under_another_type_is_named_with_that_type(ros, tmp_path: Path, capfd) -> None:
    """amcl's PoseWithCovarianceStamped on the pose topic, where the node subscribes PoseStamped: nothing
    arrives, and the warning said only "check the topic name, its message type and QoS". It now names
    the type the topic is published as, what pose_type takes, and, for a topic nobody publishes, that."""
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped

    # another participant, as another process would be (DDS refuses a second type for a topic in one)
    context = rclpy.Context()
    rclpy.init(context=context)
    amcl = Node("amcl_like", context=context)
    publisher = amcl.create_publisher(PoseWithCovarianceStamped, "/othertype/tof/pose", 10)
    run = _running_once_it_sees(publisher, "othertype", tmp_path, window_s=0.5)
    log = ""
    try:
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline and "tof: nothing received on /othertype/tof/pose" not in log:
            publisher.publish(PoseWithCovarianceStamped())
            time.sleep(0.1)
            log += capfd.readouterr().err
    finally:
        run.close()
        amcl.destroy_node()
        rclpy.shutdown(context=context)
    line = next((x for x in log.splitlines() if "tof: nothing received on /othertype/tof/pose" in x), None)
    assert line is not None, log[-3000:]
    assert ("published as geometry_msgs/msg/PoseWithCovarianceStamped, the node subscribes "
            "geometry_msgs/msg/PoseStamped: pose_type takes pose_stamped" in line), line
    depth = next((x for x in log.splitlines() if "tof: nothing received on /othertype/tof/depth" in x), "")
    assert "nobody publishes /othertype/tof/depth now" in depth, log[-3000:]


def test_a_silent_topic_with_publishers_of_its_type_is_warned_about_later_and_not_blamed_on_the_domain(
        ros, tmp_path: Path, capfd) -> None:
    """`senfunet demo`: play waits until every topic has a subscriber before it publishes, and the node
    warned a window after it subscribed that the topic "has publishers, yet nothing came: check that they
    share the node's ROS_DOMAIN_ID" (the graph showing them proves they do). A topic whose publishers are
    of the subscribed type is now warned about after SILENT_WITH_PUBLISHERS_WINDOWS windows, naming what
    can be wrong: they have not published yet, or their QoS does not match."""
    import rclpy

    from senfunet_ros.status import SILENT_WITH_PUBLISHERS_WINDOWS

    window_s = 1.0
    context = rclpy.Context()
    rclpy.init(context=context)
    player = Node("waiting_player", context=context)
    publisher = player.create_publisher(PoseStamped, "/quiet/tof/pose", 10)  # never publishes
    run = _running_once_it_sees(publisher, "quiet", tmp_path, window_s=window_s)
    log, depth_seen_s = "", None
    start = time.monotonic()
    try:
        while time.monotonic() - start < 30.0 and "tof: nothing received on /quiet/tof/pose" not in log:
            time.sleep(0.1)
            log += capfd.readouterr().err
            if depth_seen_s is None and "tof: nothing received on /quiet/tof/depth" in log:
                depth_seen_s = time.monotonic() - start
                assert "nothing received on /quiet/tof/pose" not in log, log[-3000:]  # a window: not yet
    finally:
        run.close()
        player.destroy_node()
        rclpy.shutdown(context=context)
    assert depth_seen_s is not None, log[-3000:]
    line = next((x for x in log.splitlines() if "tof: nothing received on /quiet/tof/pose" in x), "")
    assert "which sent nothing the node took" in line and "ROS_DOMAIN_ID" not in line, log[-3000:]
    silent_s = float(re.search(r"/quiet/tof/pose for (\d+) s", line).group(1))
    assert silent_s >= SILENT_WITH_PUBLISHERS_WINDOWS * window_s - 0.5, line


def test_a_second_node_of_the_same_name_is_warned_about(ros, tmp_path: Path, monkeypatch) -> None:
    """A second launch of the node (same name and namespace, another process) clashes on every service
    and parameter, and ROS says nothing across processes: the node says so."""
    run = Running("namesake", {**topic_params("namesake"), **SMALL, "status_rate_hz": 10.0}, tmp_path)
    warned: list[str] = []
    monkeypatch.setattr(run.node, "_warn", lambda key, text: warned.append(text) if key == ("namesakes",) else None)
    try:
        time.sleep(1.0)
        assert warned == []  # alone
        other = Node("senfunet", namespace="namesake")
        try:
            wait_for(lambda: warned, 20, "the namesake warning")
        finally:
            other.destroy_node()
    finally:
        run.close()
    assert "2 nodes named /namesake/senfunet are in the ROS graph" in warned[0], warned


def test_a_camera_info_that_came_once_is_not_stale_while_its_depth_comes() -> None:
    """A driver that publishes camera_info once (latched): its K is cached and the sensor fuses, so
    the sensor is not STALE for that silence; once its depth stops too, both are named."""
    from senfunet_ros.health import HealthMonitor, Level

    now = [0.0]
    health = HealthMonitor({"tof": ("camera_info", "depth")}, window_s=1.0, stale_after_s=2.0, clock=lambda: now[0])
    health.received("tof", "camera_info")
    for _ in range(50):  # depth at 10 Hz for 5 s
        now[0] += 0.1
        health.received("tof", "depth")
    assert health.report()["tof"].level == Level.OK
    now[0] += 3.0
    report = health.report()["tof"]
    assert report.level == Level.STALE and "camera_info, depth" in report.message


def test_depth_images_lost_on_the_way_warn() -> None:
    """1280x720 depth over best-effort DDS with a small shared memory: a quarter of the images came,
    camera_info all of them, and ~/status stayed OK. Depth at under half camera_info's rate, or depth
    images found missing (gaps in the stamps), now warn; the warning clears when they end."""
    from senfunet_ros.health import HealthMonitor, Level

    now = [0.0]
    health = HealthMonitor({"tof": ("camera_info", "depth")}, window_s=1.0, stale_after_s=2.0, clock=lambda: now[0])

    def image(k: int, *, depth: bool) -> None:  # the driver's image k: its camera_info, then (if it came) depth
        now[0] += 0.1
        health.received("tof", "camera_info", 10**9 + k * 10**8)
        if depth:
            health.received("tof", "depth", 10**9 + k * 10**8)

    for k in range(40):  # camera_info at 10 Hz, depth starting 0.5 s later (no loss: no warning)
        image(k, depth=k >= 5)
        assert health.report()["tof"].level == Level.OK, (k, health.report()["tof"])
    for k in range(40, 80):  # every fourth depth image
        image(k, depth=k % 4 == 0)
    report = health.report()["tof"]
    assert report.level == Level.WARN and "depth 2.0 Hz against camera_info" in report.message, report
    assert "most depth images are lost on the way" in report.message
    for k in range(80, 100):  # all of them again
        image(k, depth=True)
    assert health.report()["tof"].level == Level.OK
    health.counters({"tof": {"dropped": {}, "missing_depth": 3}})
    report = health.report()["tof"]
    assert report.level == Level.WARN and "recently missing: 3 depth image(s)" in report.message
    now[0] += 1.5
    image(100, depth=True)
    assert health.report()["tof"].level == Level.OK


def test_a_stream_that_started_lately_has_its_rate_and_images_taken_back_leave_the_warning() -> None:
    """A 10 Hz camera that started 1 s ago read 2 Hz on /diagnostics (its 10 messages over the 5 s window,
    not over the second it has run); a burst of a driver's first frames is no 180 Hz either. Images
    counted missing and then taken back (they came late) kept the sensor at WARN until the window passed."""
    from senfunet_ros.health import HealthMonitor, Level

    now = [0.0]
    health = HealthMonitor({"tof": ("depth",)}, window_s=5.0, stale_after_s=2.0, clock=lambda: now[0])
    now[0] = 3.0  # subscribed 3 s before the camera starts
    for _ in range(11):
        health.received("tof", "depth")
        now[0] += 0.1
    assert health.report()["tof"].streams["depth"].rate_hz == pytest.approx(10.0, rel=0.15)
    burst = HealthMonitor({"tof": ("depth",)}, window_s=5.0, stale_after_s=2.0, clock=lambda: now[0])
    for _ in range(10):  # ten frames within 50 ms, then the status report
        now[0] += 0.005
        burst.received("tof", "depth")
    assert burst.report()["tof"].streams["depth"].rate_hz <= 10.0
    health.counters({"tof": {"dropped": {}, "missing_depth": 4}})
    assert health.report()["tof"].level == Level.WARN
    health.counters({"tof": {"dropped": {}, "missing_depth": 1}})
    assert health.report()["tof"].recent_missing == 1
    health.counters({"tof": {"dropped": {}, "missing_depth": 0}})
    assert health.report()["tof"].level == Level.OK, health.report()["tof"]


def test_a_camera_info_sent_at_its_own_rate_does_not_warn_of_lost_depth() -> None:
    """A driver that publishes camera_info on its own timer (30 Hz, its own stamps) beside depth at
    5 Hz loses no image: the rate of a camera_info not stamped as the images says nothing of loss."""
    from senfunet_ros.health import HealthMonitor, Level

    now = [0.0]
    health = HealthMonitor({"tof": ("camera_info", "depth")}, window_s=1.0, stale_after_s=2.0, clock=lambda: now[0])
    for k in range(180):  # 6 s
        now[0] += 1 / 30
        health.received("tof", "camera_info", 5 * 10**8 + k * 33_333_333)
        if k % 6 == 0:
            health.received("tof", "depth", 10**9 + k * 33_333_400)
    report = health.report()["tof"]
    assert report.level == Level.OK and report.streams["depth"].rate_hz < 0.5 * report.streams["camera_info"].rate_hz, \
        report


def test_a_stalled_mesh_update_says_where_its_time_went(ros, tmp_path: Path, monkeypatch) -> None:
    """A mesh update that takes over twice the mesh period (here the map is held by another thread for a
    second, as an eviction or a save can hold it) is warned about with the time of each of its stages,
    so that a stalled refresh tells whether the map, the publication or the weighting net held it."""

    # a short net's turn: a turn that waited for the map then works at most the rest of its period, not 0.5 s
    run = Running("slow_update", {**topic_params("slow_update"), **SMALL, "mesh_rate_hz": 5.0, "alpha_budget_s": 0.05},
                  tmp_path)
    warned: list[tuple[tuple[str, ...], str]] = []
    try:
        fuse_in_process(run, scene_messages())
        monkeypatch.setattr(run.node.mesh_publisher, "_warn", lambda key, text: warned.append((key, text)))
        with run.node.engine.update_lock.held():
            time.sleep(1.0)
        wait_for(lambda: any(key == ("mesh_update_slow",) for key, _ in warned), 30, "the slow update's warning")
    finally:
        run.close()
    pattern = (r"took ([\d.]+) s, over twice the mesh period .*engine\.update ([\d.]+) s.*encoding and publishing "
               r".* ([\d.]+) s, then the weighting net's turn ([\d.]+) s")
    stalls = [(float(m.group(1)), float(m.group(2)), float(m.group(4)), text) for key, text in warned
              if key == ("mesh_update_slow",) and (m := re.search(pattern, text))]
    assert stalls, warned
    # the update that met the map held above waited in engine.update, or in the net's turn after it
    total_s, update_s, turn_s, text = max(stalls, key=lambda stall: max(stall[1], stall[2]))
    assert 1.5 >= max(update_s, turn_s) >= 0.5 and total_s >= max(update_s, turn_s), text


def test_save_map_load_map_round_trip_and_file_modes(ros, tmp_path: Path) -> None:
    run = Running("maps", {**topic_params("maps"), **SMALL, "map_file": "room.pt"}, tmp_path)
    old_umask = os.umask(0o077)  # a restrictive umask: the files must still be readable by others
    try:
        fuse_in_process(run, scene_messages())
        before = run.node.engine.extract_mesh("fused")
        r = run.call("save_map")
        path = tmp_path / "out" / "room.pt"
        assert r.success and str(path) in r.message, r.message
        assert path.stat().st_mode & 0o777 == 0o644
        r = run.call("save_mesh")
        assert r.success and "mesh.ply" in r.message
        assert (tmp_path / "out" / "mesh.ply").stat().st_mode & 0o777 == 0o644
        assert run.call("reset").success
        assert run.node.engine.extract_mesh("fused").n_faces == 0
        (res,) = _set(run, **{"tof.depth_max_m": 2.5})  # the map file holds the old limit
        assert res.successful
        r = run.call("load_map")
        assert r.success and str(path) in r.message, r.message
        assert run.node.engine.config.depth_max_m[0] == 2.5  # the parameters hold for the loaded map
        after = run.node.engine.extract_mesh("fused")
        assert after.n_faces == before.n_faces and np.array_equal(after.vertices, before.vertices)
        from senfunet_core.engine import EngineConfig, SenFuNet
        from senfunet_core.map_file import save_map

        save_map(SenFuNet(EngineConfig(voxel_size_m=0.01, band_m=0.04), weights=None), tmp_path / "other.pt")
        (res,) = _set(run, map_file=str(tmp_path / "other.pt"))  # a map of another grid
        assert res.successful
        r = run.call("load_map")
        assert not r.success and "voxel_size_m 0.01 (the node's 0.04)" in r.message, r.message
        assert run.node.engine.extract_mesh("fused").n_faces == before.n_faces  # the map stays
        (res,) = _set(run, map_file=str(tmp_path / "missing.pt"))
        assert res.successful
        r = run.call("load_map")
        assert not r.success and "missing.pt" in r.message
    finally:
        os.umask(old_umask)
        run.close()


def test_load_map_of_a_file_that_is_no_map_says_so_and_keeps_the_map(ros, tmp_path: Path) -> None:
    """~/load_map with map_file naming a PLY (a mesh next to the maps), or a map cut short: the reply
    passed on torch's error, which for the PLY advised loading it with weights_only=False (unsafe) and
    for the cut one said "[Errno 22] Invalid argument"."""
    run = Running("notmap", {**topic_params("notmap"), **SMALL}, tmp_path)
    try:
        fuse_in_process(run, scene_messages())
        faces = run.node.engine.extract_mesh("fused").n_faces
        assert run.call("save_map").success and run.call("save_mesh").success
        out = tmp_path / "out"
        cut = out / "cut.pt"
        cut.write_bytes((out / "map.pt").read_bytes()[:50_000])
        ply = out / "room.ply"  # map_file cannot be mesh.ply itself (a name ~/save_mesh writes): refused
        ply.write_bytes((out / "mesh.ply").read_bytes())
        for path in (ply, cut):
            (res,) = _set(run, map_file=str(path))
            assert res.successful
            r = run.call("load_map")
            assert not r.success and f"{path} is not a map" in r.message, r.message
            assert "weights_only" not in r.message and "Errno" not in r.message, r.message
            assert run.node.engine.extract_mesh("fused").n_faces == faces  # the map stays
    finally:
        run.close()


def test_compressed_inputs_are_decoded(ros, tmp_path: Path) -> None:
    import cv2

    from senfunet_ros import conversions as conv

    depth_mm = np.full((8, 10), 1500, np.uint16)
    depth_mm[0, 0] = 0
    _, png = cv2.imencode(".png", depth_mm)
    msg = CompressedImage(format="16UC1; compressedDepth png")
    msg.data = np.concatenate([np.zeros(12, np.uint8), png.reshape(-1)]).tobytes()
    depth_m = conv.depth_from_image(msg)
    assert depth_m.shape == (8, 10) and depth_m[1, 1] == pytest.approx(1.5) and depth_m[0, 0] == 0
    rgb = np.zeros((8, 10, 3), np.uint8)
    rgb[..., 0] = 200  # red
    _ok, jpg = cv2.imencode(".png", rgb[..., ::-1])
    color = CompressedImage(format="rgb8; png compressed bgr8")
    color.data = jpg.reshape(-1).tobytes()
    out = conv.rgb_from_image(color)
    assert out.shape == (8, 10, 3) and out[0, 0, 0] == 200 and out[0, 0, 2] == 0
    bad = CompressedImage(format="16UC1; compressedDepth png")
    bad.data = b"\x00" * 12 + b"not a png"
    with pytest.raises(ValueError, match="png"):
        conv.depth_from_image(bad)


def test_mesh_coloured_by_camera_colour(ros, tmp_path: Path) -> None:
    run = Running("colours", {**topic_params("colours"), **SMALL, "mesh_colors": "camera"}, tmp_path)
    try:
        reader = MeshCollector(run.helper, f"{run.prefix}/mesh")
        wait_for(lambda: run.node.mesh_publisher.mesh_pub.get_subscription_count() == 1, 10, "the reader")
        fuse_in_process(run, scene_messages())
        run.node.publish_mesh()  # every integrated block meshed
        wait_for(lambda: reader.keys() and reader.keys() == _marker_keys(run.node), 30, "the mesh")
        meshes = run.node.engine.block_meshes()
        assert len(meshes.faces) > 100
        camera = run.node.mesh_publisher.display(meshes)
        (r,) = _set(run, mesh_colors="weighting")
        assert r.successful
        received = reader.messages
        run.node.publish_mesh()  # nothing new in the engine: the reader gets the whole map in its new colours
        wait_for(lambda: reader.messages > received, 10, "the map in its new colours")
        weighting = run.node.mesh_publisher.display(meshes)
        assert len(run.node.camera_colors) > 100  # the stereo colour images were averaged in
        seen = ~np.isnan(run.node.camera_colors.lookup(meshes.vertices)[:, 0])  # where the stereo camera saw
        assert seen.mean() > 0.2, seen.mean()
        assert np.array_equal(camera.colors[~seen], weighting.colors[~seen])  # elsewhere the weighting colours
        changed = np.abs(camera.colors - weighting.colors).max(axis=1) > 0.02
        assert changed[seen].mean() > 0.8, changed[seen].mean()
        assert camera.colors[seen].std(axis=0).max() > 0.02  # texture, not one flat colour
        assert run.call("reset").success and len(run.node.camera_colors) == 0
    finally:
        run.close()


def _publish_clock_going_back(run: Running, clock: Any) -> None:
    """A timeline at 1100 s, then /clock at 1100 s, 1100.5 s, one stray 1000 s, 1101 s, 1101.5 s, then 1010 s
    and 1010.5 s: the bag loops."""
    from rosgraph_msgs.msg import Clock

    pose = PoseStamped()
    pose.pose.orientation.w = 1.0
    _stamp(pose, 100.0)
    run.node.pipeline.dispatch("tof", "pose", pose)
    for t_s in (100.0, 100.5, 0.0, 101.0, 101.5, 10.0, 10.5):  # /clock goes back by 90 s
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = int(t_s + BASE_S), int(round(t_s % 1 * 1e9))
        clock.publish(msg)
        time.sleep(0.2)
        if t_s == 101.5:  # the stray 0 s, which the next /clock left again, restarted nothing
            assert run.node.pipeline.time_jumps == 0


@pytest.mark.parametrize("sim_time_set", ["at_start", "at_run_time"])
def test_clock_going_back_restarts_time_once_the_next_clock_goes_on(ros, tmp_path: Path, sim_time_set: str) -> None:
    """Under use_sim_time, given at start or set at run time (`ros2 param set /senfunet use_sim_time true`,
    which the node accepted but left /clock unwatched: a loop was recognised only from the new timeline),
    and no longer once it is set false; a single stray /clock going back restarts nothing."""
    from rclpy.parameter import Parameter
    from rosgraph_msgs.msg import Clock

    run = Running("clock", {**topic_params("clock"), **SMALL, "use_sim_time": sim_time_set == "at_start",
                            "tof.T_body_camera": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]}, tmp_path)
    pub_node = Node("clock_publisher")
    try:
        if sim_time_set == "at_run_time":
            assert all(r.successful for r in run.node.set_parameters([Parameter("use_sim_time", value=True)]))
        clock = pub_node.create_publisher(Clock, "/clock", 10)
        wait_for(lambda: clock.get_subscription_count() > 0, 20, "discovery")
        _publish_clock_going_back(run, clock)
        wait_for(lambda: run.node.pipeline.time_jumps >= 1, 10, "the restart")
        assert run.node.pipeline.time_jumps == 1
        assert run.node.ingest.ledger.counters()["tof"]["dropped"]["bad_stamp"] == 0
        assert all(r.successful for r in run.node.set_parameters([Parameter("use_sim_time", value=False)]))
        wait_for(lambda: clock.get_subscription_count() == 0, 20, "the /clock watch dropped")
    finally:
        pub_node.destroy_node()
        run.close()


def test_bad_extrinsic_refuses_to_start(ros, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="T_body_camera"):
        Running("extrinsic", {**topic_params("extrinsic"), **SMALL,
                              "tof.T_body_camera": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]}, tmp_path)


def test_weighting_net_catches_up_in_slices_only_while_no_frame_comes(ros, tmp_path: Path) -> None:
    """While frames come (one integrated while the update ran, or one waiting), the net gets
    alpha_budget_s after each mesh update; when none came while the update ran and none waits (the
    update's frames may have been the stream's last), it catches up on every core for the rest of
    the mesh period (one slice per update, so the mesh keeps being published), until nothing is
    left, and stops once a frame comes."""
    import copy

    mesh_rate_hz = 500.0  # slices of 2 ms: about one batch of blocks each
    run = Running("catchup", {**topic_params("catchup"), **SMALL, "voxel_size_m": 0.03, "band_m": 0.3,
                              "mesh_rate_hz": mesh_rate_hz, "alpha_budget_s": 0.001}, tmp_path)
    try:
        # the test calls publish_mesh itself: the timer's next period is far away (the slices still
        # follow the parameter); one call at the old period may still come, long before the calls below
        run.node._mesh_timer.timer_period_ns = 10**12
        messages = scene_messages()
        last_tof = max(i for i, (sensor, stream, _) in enumerate(messages) if (sensor, stream) == ("tof", "depth"))
        held_back = [m for i, m in enumerate(messages) if i == last_tof or i == last_tof - 1]
        assert [stream for _, stream, _ in held_back] == ["camera_info", "depth"]
        fuse_in_process(run, [m for m in messages if m not in held_back])

        def settled() -> bool:  # every frame received integrated (or dropped): none in flight
            return all(c["integrated"] + sum(c["dropped"].values()) >= c["received"]
                       for c in run.node.ingest.ledger.counters().values())

        wait_for(settled, 60, "every frame to be integrated")
        engine = run.node.engine
        turns: list[tuple[float | None, bool]] = []  # (budget, until a frame is integrated)
        refresh = engine.refresh_alpha
        arrive: list[Any] = []  # messages to hand over during the next refresh

        turn_threads: list[int] = []

        def recording_refresh(budget_s: float | None = None, *, until_frame: bool = False) -> None:
            turns.append((budget_s, until_frame))
            turn_threads.append(threading.get_ident())
            refresh(budget_s, until_frame=until_frame)
            for sensor, stream, msg in arrive:
                run.node.pipeline.dispatch(sensor, stream, msg)
            arrive.clear()

        engine.refresh_alpha = recording_refresh
        slices = run.node.settings
        # a frame that waits: the other sensor's last, stamped a second past the last pose, waits for one
        stamp = [msg for sensor, stream, msg in messages if (sensor, stream) == ("stereo", "depth")][-1].header.stamp
        for sensor, stream, msg in messages:
            if sensor != "stereo" or stream == "pose" or msg.header.stamp != stamp:
                continue
            later = copy.deepcopy(msg)
            later.header.stamp.sec += 1
            run.node.pipeline.dispatch(sensor, stream, later)
        assert sum(run.node.ingest.ledger.queue_depths().values()) == 1
        run.node.settings = P.Settings.from_values({**slices.values, "mesh_rate_hz": 1.0})  # room for the budget
        run.node.publish_mesh()  # a frame waits: the running budget
        run.node.settings = slices
        assert turns == [(0.001, False)] and turn_threads == [threading.get_ident()]  # after publishing
        backlog = engine.counters["alpha_backlog_blocks"]
        assert backlog > 0
        assert run.node.ingest.ledger.discard_waiting("pose_timeout") == 1  # its pose will not come
        turns.clear()
        arrive.extend(held_back)
        run.node.publish_mesh()  # idle, but a frame comes during the slice
        assert [until_frame for _, until_frame in turns] == [True]
        assert 0 < engine.counters["alpha_backlog_blocks"] < backlog  # stopped with work left
        wait_for(settled, 60, "the last frame to be integrated")
        turns.clear()
        for updates in range(1, 1000):  # that frame in the first update, none since: a slice per update
            run.node.publish_mesh()
            assert len(turns) == updates and turns[-1][1]
            if not engine.counters["alpha_backlog_blocks"]:
                break
        assert engine.counters["alpha_backlog_blocks"] == 0 and len(turns) > 1
        # idle: on the turn thread, while this one encoded and published the update
        assert threading.get_ident() not in turn_threads[1:]
        run.node.publish_mesh()  # the update that shows the judged blocks
        stats = engine.stats()
        assert stats["meshed_blocks_alpha_current"] == stats["meshed_blocks"] > 0
    finally:
        run.close()


def test_a_failed_publication_is_made_good_by_the_next(ros, tmp_path: Path, monkeypatch) -> None:
    """A mesh update takes the engine's changes; when publishing it fails (here ~/mesh refuses one
    message), the next publication sends the whole map, so a subscriber misses nothing for good."""
    from senfunet_ros import mesh_publisher

    run = Running("pubfail", {**topic_params("pubfail"), **SMALL, "mesh_rate_hz": 0.05}, tmp_path)
    try:
        collector = MeshCollector(run.helper, f"{run.prefix}/mesh")
        wait_for(lambda: run.node.mesh_publisher.mesh_pub.get_subscription_count() > 0, 10, "the subscriber")
        messages = scene_messages()
        half = len(messages) // 2
        fuse_in_process(run, messages[:half])
        run.node.engine.refresh_alpha(None)  # all judged: the first update holds the whole map (else the rest
        #   the net judges after it waits for the mesh timer)
        run.node.publish_mesh()
        wait_for(lambda: collector.keys() and collector.keys() == _marker_keys(run.node), 30, "the first mesh")
        fuse_in_process(run, messages)  # the second half (the first again: stamps behind, dropped)
        run.node.engine.refresh_alpha(None)  # all judged: no later update re-meshes anything by itself
        publish = mesh_publisher.publish_serialized
        refused = []

        def refuse_once(publisher: Any, data: Any) -> None:
            if publisher is run.node.mesh_publisher.mesh_pub and not refused:
                refused.append(True)
                raise RuntimeError("publication refused (test)")
            publish(publisher, data)

        monkeypatch.setattr(mesh_publisher, "publish_serialized", refuse_once)
        with pytest.raises(RuntimeError, match="refused"):
            run.node.publish_mesh()  # the second half's blocks: taken from the engine, not delivered
        assert refused and collector.keys() != _marker_keys(run.node)
        run.node.publish_mesh()  # nothing new in the engine: the whole map again
        wait_for(lambda: collector.keys() == _marker_keys(run.node), 30, "the map the failed update held")
    finally:
        run.close()


def test_a_failed_mesh_update_is_made_good_by_the_next(ros, tmp_path: Path, monkeypatch) -> None:
    """An update that fails after it took the engine's changes (here its meshing) leaves nothing
    out for good: the next publication sends the whole map."""
    run = Running("updfail", {**topic_params("updfail"), **SMALL, "mesh_rate_hz": 0.05}, tmp_path)
    try:
        collector = MeshCollector(run.helper, f"{run.prefix}/mesh")
        wait_for(lambda: run.node.mesh_publisher.mesh_pub.get_subscription_count() > 0, 10, "the subscriber")
        messages = scene_messages()
        fuse_in_process(run, messages[: len(messages) // 2])
        run.node.engine.refresh_alpha(None)
        run.node.publish_mesh()
        wait_for(lambda: collector.keys() and collector.keys() == _marker_keys(run.node), 30, "the first mesh")
        fuse_in_process(run, messages)  # the second half
        run.node.engine.refresh_alpha(None)  # all judged: no later update re-meshes anything by itself
        engine = run.node.engine
        block_meshes = engine._block_meshes

        def fail(*args: Any, **kwargs: Any) -> Any:
            raise MemoryError("meshing failed (test)")

        monkeypatch.setattr(engine, "_block_meshes", fail)
        with pytest.raises(MemoryError, match="test"):
            run.node.publish_mesh()  # the second half's changes: taken from the engine, not meshed
        monkeypatch.setattr(engine, "_block_meshes", block_meshes)
        assert collector.keys() != _marker_keys(run.node)
        run.node.publish_mesh()  # nothing new in the engine: the whole map
        wait_for(lambda: collector.keys() == _marker_keys(run.node), 30, "the map the failed update held")
    finally:
        run.close()


def test_ctrl_c_during_the_stop_drops_the_queued_frames_and_the_saving_not_the_node(ros, tmp_path: Path,
                                                                                   monkeypatch, capsys) -> None:
    """A second Ctrl-C while `stop_node` integrates the ready frames drops the ones not started yet;
    one while it saves stops the saving; the node is destroyed all the same, nothing escapes."""
    import signal

    from rclpy._rclpy_pybind11 import InvalidHandle

    from senfunet_ros.node import stop_node

    run = Running("stopnode", {**topic_params("stopnode"), **SMALL, "save_on_shutdown": True}, tmp_path)
    try:
        messages = scene_messages()
        fuse_in_process(run, messages[: len(messages) // 2])
        run.spinning.stop()  # as the first Ctrl-C stops the executor
        for sensor, stream, msg in messages[len(messages) // 2:]:  # frames ready, not integrated
            run.node.pipeline.dispatch(sensor, stream, msg)
        integrated = sum(c["integrated"] for c in run.node.ingest.ledger.counters().values())
        drain, save = run.node.pipeline.drain, run.node.map_services.save_meshes

        def interrupted(action: Any) -> Any:
            def call(*args: Any, **kwargs: Any) -> Any:
                signal.raise_signal(signal.SIGINT)
                return action(*args, **kwargs)
            return call

        monkeypatch.setattr(run.node.pipeline, "drain", interrupted(drain))
        monkeypatch.setattr(run.node.map_services, "save_meshes", interrupted(save))
        stop_node(run.node)
        out = capsys.readouterr().out
        assert "frames not integrated yet are dropped" in out and "saving on shutdown stopped" in out
        # ros2 launch's SIGTERM comes once: one during the frames also spares the net's judging
        assert "the weighting net stops judging; the fused mesh alone is written" in out
        counters = run.node.ingest.ledger.counters().values()
        assert sum(c["integrated"] for c in counters) == integrated
        assert sum(c["dropped"]["shutdown"] for c in counters) >= 2
        assert not list((tmp_path / "out").glob("*.ply*"))
        with pytest.raises(InvalidHandle):  # destroyed
            run.node.create_publisher(Image, "after_destroy", 1)
    finally:
        run.helper.destroy_node()


def test_save_on_shutdown_into_an_output_dir_it_cannot_use_saves_into_a_temporary_folder(ros, tmp_path: Path,
                                                                                          monkeypatch, capsys) -> None:
    """save_on_shutdown with a folder where output_dir's mesh.ply goes: the refusal (InputError, not an
    OSError) skipped the temporary folder meant for an output_dir that cannot be written, and the map
    ended with the process."""
    import tempfile

    from senfunet_core.ply import read_ply
    from senfunet_ros.node import stop_node

    run = Running("stopsave", {**topic_params("stopsave"), **SMALL, "save_on_shutdown": True}, tmp_path)
    try:
        fuse_in_process(run, scene_messages())
        faces = run.node.engine.extract_mesh("fused").n_faces
        (tmp_path / "out" / "mesh.ply").mkdir(parents=True)
        fallback = tmp_path / "fallback"
        monkeypatch.setattr(tempfile, "mkdtemp", lambda prefix="": (fallback.mkdir(), str(fallback))[1])
        run.spinning.stop()
        stop_node(run.node)
        captured = capsys.readouterr()
        assert "saving into a new temporary folder instead" in captured.err, captured.err
        assert f"saved instead {fallback}" in captured.out, captured.out
        assert faces > 0 and read_ply(fallback / "mesh.ply").n_faces == faces
    finally:
        run.helper.destroy_node()


_READER = """
import sys
import rclpy
import rclpy.executors
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from visualization_msgs.msg import MarkerArray
rclpy.init()
node = rclpy.create_node("stopped_reader")
qos = QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
node.create_subscription(MarkerArray, sys.argv[1], lambda msg: None, qos)
print("ready", flush=True)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
    pass
"""


def test_a_reader_too_slow_for_an_update_gets_the_whole_map_next(ros, tmp_path: Path, monkeypatch) -> None:
    """A mesh reader that does not acknowledge the parts of an update within the wait (here a
    reader process stopped with SIGSTOP) makes the rest come faster than the history keeps them:
    once every reader has caught up, the next publication, with nothing new in the engine, sends
    the whole map (not while one is still behind: a stuck reader would make every update whole)."""
    import signal
    import subprocess
    import sys

    from senfunet_ros.dds import wait_for_all_acked

    run = Running("slowreader", {**topic_params("slowreader"), **SMALL, "mesh_rate_hz": 0.05}, tmp_path)
    reader = subprocess.Popen([sys.executable, "-c", _READER, f"{run.prefix}/mesh"], stdout=subprocess.PIPE, text=True,
                              stderr=subprocess.DEVNULL)
    try:
        assert reader.stdout is not None and reader.stdout.readline().strip() == "ready"
        collector = MeshCollector(run.helper, f"{run.prefix}/mesh")
        wait_for(lambda: run.node.mesh_publisher.mesh_pub.get_subscription_count() == 2, 20, "both readers")
        messages = scene_messages()
        fuse_in_process(run, messages[: len(messages) // 2])
        run.node.engine.refresh_alpha(None)  # all judged: the first update holds the whole map
        run.node.publish_mesh()
        wait_for(lambda: collector.keys() and collector.keys() == _marker_keys(run.node), 30, "the first mesh")
        # from now on parts of ~4 KB (below the parameter's range: set directly): every update of this scene is
        #   several (the first mesh came whole: its many parts would wait for acknowledgements longer than the node
        #   waits)
        run.node.settings.values["mesh_message_max_mb"] = 4096 / (1 << 20)
        reader.send_signal(signal.SIGSTOP)
        fuse_in_process(run, messages)
        run.node.engine.refresh_alpha(None)  # all judged: no later update re-meshes anything by itself
        run.node.publish_mesh()  # parts the stopped reader does not acknowledge: after the wait, they
        #   come faster than the history of 2 keeps them, for every reader
        whole_maps = collector.delete_alls
        run.node.publish_mesh()  # nothing new in the engine, and a reader still behind: no message
        reader.send_signal(signal.SIGCONT)
        assert wait_for_all_acked(run.node.mesh_publisher.mesh_pub, 10.0), "the reader did not catch up"
        assert collector.delete_alls == whole_maps
        run.node.publish_mesh()  # nothing new in the engine, every reader caught up
        wait_for(lambda: collector.delete_alls > whole_maps, 10, "the whole map again")
        wait_for(lambda: collector.keys() == _marker_keys(run.node), 30, "all of the whole map")
    finally:
        reader.send_signal(signal.SIGCONT)
        reader.send_signal(signal.SIGINT)
        try:
            reader.wait(10)
        except subprocess.TimeoutExpired:  # the test's own reader, slow to stop under load: not what is tested;
            reader.kill()                   # raising here left the node running (run.close() never came)
            reader.wait()
        run.close()


def test_waiting_for_a_reader_lets_the_other_threads_run(ros) -> None:
    """dds.wait_for_all_acked, with which the node waits between the parts of a mesh update, blocks
    without the GIL: while a reader that does not acknowledge (a process stopped with SIGSTOP) keeps
    it waiting, the process's other Python threads run on. It gives up at its timeout, and says so;
    once the reader is resumed and takes the message, it says every reader has."""
    import signal
    import subprocess
    import sys

    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from visualization_msgs.msg import Marker, MarkerArray

    from senfunet_ros.dds import wait_for_all_acked

    node = Node("ack_wait_test")
    qos = QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    publisher = node.create_publisher(MarkerArray, "/ack_wait_test/mesh", qos)
    reader = subprocess.Popen([sys.executable, "-c", _READER, "/ack_wait_test/mesh"], stdout=subprocess.PIPE,
                              text=True, stderr=subprocess.DEVNULL)
    ticks, stop = [0], threading.Event()

    def count() -> None:  # pure Python: it runs only while it holds the GIL
        while not stop.is_set():
            ticks[0] += 1

    counter = threading.Thread(target=count)
    try:
        assert reader.stdout is not None and reader.stdout.readline().strip() == "ready"
        wait_for(lambda: publisher.get_subscription_count() == 1, 20, "the reader")
        assert wait_for_all_acked(publisher, 0.0)  # nothing published yet
        reader.send_signal(signal.SIGSTOP)
        publisher.publish(MarkerArray(markers=[Marker(id=i, ns="test") for i in range(100)]))
        counter.start()
        before = ticks[0]
        time.sleep(1.0)  # what the counter does in a second this thread leaves it
        in_a_second, started = ticks[0] - before, time.monotonic()
        acknowledged = wait_for_all_acked(publisher, 1.0)
        waited_s, during = time.monotonic() - started, ticks[0] - before - in_a_second
        assert not acknowledged and waited_s >= 0.9
        # a wait holding the GIL would leave the counter a switch interval or so
        assert during > 0.3 * in_a_second * waited_s, (during, in_a_second)
        reader.send_signal(signal.SIGCONT)
        assert wait_for_all_acked(publisher, 10.0)
    finally:
        stop.set()
        if counter.is_alive():
            counter.join()
        reader.send_signal(signal.SIGCONT)
        reader.send_signal(signal.SIGINT)
        reader.wait(10)
        node.destroy_node()


def test_the_mesh_part_size_is_a_parameter(ros, tmp_path: Path, monkeypatch) -> None:
    """A reader that keeps one message (latched, depth 1) needs each update whole: parameter
    mesh_message_max_mb sets the size above which an update goes out in parts."""
    from senfunet_ros import mesh_publisher

    run = Running("partsize", {**topic_params("partsize"), **SMALL}, tmp_path)
    split = mesh_publisher.conv.marker_array_messages
    asked: list[int] = []

    def recording(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        asked.append(kwargs["max_bytes"])
        return split(*args, **kwargs)

    monkeypatch.setattr(mesh_publisher.conv, "marker_array_messages", recording)
    try:
        messages = scene_messages()
        fuse_in_process(run, messages[: len(messages) // 2])
        run.node.publish_mesh()
        (r,) = _set(run, mesh_message_max_mb=64.0)
        assert r.successful, r.reason
        fuse_in_process(run, messages)
        run.node.publish_mesh()
        assert asked[0] == 16 << 20 and asked[-1] == 64 << 20
        (r,) = _set(run, mesh_message_max_mb=0.5)
        assert not r.successful and "mesh_message_max_mb" in r.reason
    finally:
        run.close()


def test_a_reader_that_replaces_another_between_two_publications_gets_the_whole_map(ros, tmp_path: Path) -> None:
    """RViz re-subscribing: one mesh reader leaves and another joins between two publications, so the
    reader count is the same; the newcomer, whose transient-local history holds only the last two
    updates, still gets the whole map with the next publication (the publisher's matched event)."""
    from rclpy.executors import SingleThreadedExecutor

    from senfunet_ros.ingest import Frame

    rng = np.random.default_rng(0)
    K = np.array([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1.0]])

    def frames(first: int, end: int) -> list[Frame]:  # 2 m apart: each pair of frames meshes blocks of its own
        out = []
        for i in range(first, end):
            T = np.eye(4)
            T[0, 3] = 2.0 * i
            for n, sensor in enumerate(("tof", "stereo")):
                depth = (1.2 + 0.05 * rng.random((48, 64))).astype(np.float32)
                out.append(Frame(sensor, BASE_S * 10**9 + (2 * i + n) * 50_000_000, depth, None, K, T))
        return out

    run = Running("churn", {**topic_params("churn"), **SMALL, "mesh_rate_hz": 0.05}, tmp_path)
    topic = f"{run.prefix}/mesh"
    first_node = Node("first_reader")
    first_executor = SingleThreadedExecutor()
    first_executor.add_node(first_node)
    spinning = SpinThread(first_executor)
    try:
        first = MeshCollector(first_node, topic)
        wait_for(lambda: run.node.mesh_publisher.mesh_pub.get_subscription_count() == 1, 10, "the first reader")
        for part in range(3):  # a snapshot, then two updates: the history holds those two
            run.node.pipeline.drain(frames(2 * part, 2 * part + 2))
            run.node.engine.refresh_alpha(None)
            run.node.publish_mesh()
            wait_for(lambda: first.keys() and first.keys() == _marker_keys(run.node), 30, f"update {part}")
        spinning.stop()
        first_node.destroy_node()
        wait_for(lambda: run.node.mesh_publisher.mesh_pub.get_subscription_count() == 0, 10, "the first to leave")
        second = MeshCollector(run.helper, topic)
        wait_for(lambda: second.messages >= 2, 10, "the history")
        assert second.keys() and second.keys() < _marker_keys(run.node)  # the first update's blocks are not in it
        run.node.publish_mesh()  # nothing new in the engine
        wait_for(lambda: second.keys() == _marker_keys(run.node), 30, "the whole map")
    finally:
        if spinning.thread.is_alive():
            spinning.stop()
        run.close()


def _set_values(run: Running, **values: ParameterValue) -> list[Any]:
    """SetParameters with ParameterValues as given (any type, PARAMETER_NOT_SET too)."""
    client = run.helper.create_client(SetParameters, f"{run.prefix}/set_parameters")
    assert client.wait_for_service(timeout_sec=10.0)
    request = SetParameters.Request(parameters=[ParameterMsg(name=n, value=v) for n, v in values.items()])
    future = client.call_async(request)
    wait_for(future.done, 10, "set_parameters")
    return future.result().results


def test_a_client_cannot_delete_a_parameter(ros, tmp_path: Path) -> None:
    """`ros2 param delete` sends PARAMETER_NOT_SET: accepted, rclpy would undeclare the parameter for good
    (never settable again) while the node used the string 'None' (files written into ./None)."""
    run = Running("params_del", {**topic_params("params_del"), **SMALL}, tmp_path)
    try:
        for name in ("output_dir", "save_on_shutdown", "mesh_rate_hz"):
            (r,) = _set_values(run, **{name: ParameterValue(type=ParameterType.PARAMETER_NOT_SET)})
            assert not r.successful and name in r.reason and "delete" in r.reason
            assert run.node.has_parameter(name)
            assert run.node.describe_parameter(name).type == run.node.get_parameter(name).type_.value
        assert run.node.settings.output_dir == str(tmp_path / "out")
        (r,) = _set(run, output_dir=str(tmp_path / "other"))
        assert r.successful and run.node.settings.output_dir == str(tmp_path / "other")
    finally:
        run.close()


def test_parameters_keep_their_declared_types(ros, tmp_path: Path) -> None:
    """A value of another type is refused (a bool for a rate, a number for a path); an integer for a
    float parameter is taken as a float and the parameter stays a double for typed clients."""
    run = Running("params_type", {**topic_params("params_type"), **SMALL}, tmp_path)
    double = ParameterType.PARAMETER_DOUBLE
    try:
        (r,) = _set_values(run, mesh_rate_hz=ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=True))
        assert not r.successful and "mesh_rate_hz" in r.reason
        (r,) = _set_values(run, output_dir=ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=5))
        assert not r.successful and "output_dir" in r.reason
        (r,) = _set_values(run, save_on_shutdown=ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=7))
        assert not r.successful and "save_on_shutdown" in r.reason
        (r,) = _set(run, mesh_rate_hz="fast")
        assert not r.successful
        assert run.node.describe_parameter("mesh_rate_hz").type == double
        (r,) = _set(run, mesh_rate_hz=4)
        assert r.successful, r.reason
        assert run.node.settings.mesh_rate_hz == 4.0
        assert run.node.get_parameter("mesh_rate_hz").type_.value == double
        assert run.node.describe_parameter("mesh_rate_hz").type == double
    finally:
        run.close()
    from rclpy.parameter import Parameter

    table = P.param_table(("tof", "stereo"))  # an integer list for a float list is taken as floats too
    (extrinsic,) = P.as_declared_types([Parameter("tof.T_body_camera", value=[0, 0, 0, 0, 0, 0, 1])], table)
    assert extrinsic.type_ is Parameter.Type.DOUBLE_ARRAY and P.type_error([extrinsic], table) is None
    # in plain words: "is a integer, not a double" before
    error = P.type_error([Parameter("queue_size", value=2.5)], table)
    assert error is not None and "is an integer, not a double" in error, error


@pytest.mark.parametrize("map_file", ["", "  ", "maps/", "/tmp/", "..", "maps/.", "maps/.."])
def test_a_map_file_that_names_no_file_is_refused(map_file: str) -> None:
    """'' resolved to output_dir itself: ~/save_map wrote the map as a file where the mesh folder goes,
    and every ~/save_mesh after it failed with 'File exists'; 'maps/' wrote a file named maps."""
    values = {name: default for name, (default, _) in P.expanded_defaults().items()}
    with pytest.raises(ValueError, match="map_file"):
        P.validate(values, {"map_file": map_file})
    assert P.validate(values, {"map_file": "maps/room.pt"})["map_file"] == "maps/room.pt"


@pytest.mark.parametrize(("name", "value", "says"), [
    ("map_file", "mesh.ply", "has the name of a mesh ~/save_mesh writes"),
    ("map_file", "maps/stereo.ply", "has the name of a mesh ~/save_mesh writes"),
    ("output_dir", "", "'output_dir' is empty")])
def test_a_map_file_named_like_a_mesh_or_an_empty_output_dir_is_refused(name: str, value: str, says: str) -> None:
    """map_file mesh.ply: ~/save_map wrote the map over the fused mesh (and ~/save_mesh the mesh over the
    map); output_dir '': the files went into whatever folder the node was started in."""
    values = {key: default for key, (default, _) in P.expanded_defaults().items()}
    with pytest.raises(ValueError, match=says):
        P.validate(values, {name: value})
    assert P.validate(values, {"map_file": "maps/mesh.pt"})["map_file"] == "maps/mesh.pt"


def test_service_replies_name_absolute_paths(ros, tmp_path: Path, monkeypatch) -> None:
    """A client in another process (another working directory) must find the files a reply names:
    with the default, relative output_dir they were named relative to the node's working directory."""

    monkeypatch.chdir(tmp_path)
    run = Running("abs_paths", {**topic_params("abs_paths"), **SMALL, "output_dir": "rel out"}, tmp_path)
    try:
        for service in ("save_mesh", "save_map", "load_map"):
            r = run.call(service)
            assert r.success, r.message
            paths = re.findall(r"(?:wrote |loaded |, )(.+?\.(?:ply|pt))", r.message)
            assert paths and all(Path(p).is_absolute() and Path(p).is_file() for p in paths), r.message
            assert all(Path(p).parent == tmp_path / "rel out" for p in paths), r.message
    finally:
        run.close()


def test_diagnostics_values_of_engine_statistics_are_plain_numbers() -> None:
    """A per-sensor engine statistic went out as a Python dict repr ("{'tof': 56, 'stereo': 74}"), which
    no diagnostics reader parses; each sensor's number is a value of its own."""
    from types import SimpleNamespace

    from senfunet_ros.health import HealthMonitor
    from senfunet_ros.node import LatencyStats
    from senfunet_ros.status import StatusReport

    engine = SimpleNamespace(counters={}, timings_s={},
                             stats=lambda wait=True: {"frames_integrated": {"tof": 56, "stereo": 74}, "blocks": 5})
    pipeline = SimpleNamespace(latest_stamp_ns=0, ingest=SimpleNamespace(ledger=SimpleNamespace(counters=lambda: {})),
                               time_jumps=0, maps=1, frames_failed=0, frames_unfinished=0, engine=engine)
    report = StatusReport(pipeline, HealthMonitor({}, window_s=1.0, stale_after_s=1.0), {}, LatencyStats(), topics={},
                          hardware_id="/senfunet", warn=lambda key, text: None, logger=None)
    (status,) = report.message("map").status
    values = {kv.key: kv.value for kv in status.values}
    assert values["engine.stats.frames_integrated.tof"] == "56" and values["engine.stats.blocks"] == "5"
    assert "engine.stats.frames_integrated" not in values


def test_a_rate_raised_at_run_time_takes_effect_at_once(ros, tmp_path: Path) -> None:
    """`ros2 param set /senfunet status_rate_hz 5` on a node started at 0.002 Hz: rcl keeps the next call the
    old period scheduled, so ~/status stayed silent for up to 500 s after the change (and the mesh timer
    likewise for mesh_rate_hz)."""
    run = Running("rates_rt", {**topic_params("rates_rt"), **SMALL, "status_rate_hz": 0.002, "mesh_rate_hz": 0.002},
                  tmp_path)
    got: list[DiagnosticArray] = []
    try:
        run.helper.create_subscription(DiagnosticArray, f"{run.prefix}/status", got.append, 10)
        time.sleep(1.0)  # discovery; no status is due for 500 s
        assert not got and run.node.timings["update"].count == 0
        (r_status, r_mesh) = _set(run, status_rate_hz=5.0, mesh_rate_hz=5.0)
        assert r_status.successful and r_mesh.successful
        wait_for(lambda: len(got) >= 2, 20, "~/status at the new rate")
        wait_for(lambda: run.node.timings["update"].count >= 2, 20, "mesh updates at the new rate")
    finally:
        run.close()


def test_a_parameter_file_with_no_section_for_the_node_is_named_at_start(ros, tmp_path: Path, capfd) -> None:
    """`ros2 run senfunet_ros fusion_node --ros-args -r __ns:=/robot1 --params-file config/default.yaml` (or a
    launch file in a namespace, or `-r __node:=front`): rcl gives the node none of the file's 'senfunet'
    section, and the node ran with its defaults (other topics, rates, ...) without a word."""
    from rclpy.parameter import Parameter

    from senfunet_ros.node import FusionNode

    plain = tmp_path / "plain.yaml"
    plain.write_text("senfunet:\n  ros__parameters:\n    mesh_rate_hz: 3.0\n")
    wildcard = tmp_path / "wildcard.yaml"
    wildcard.write_text("/**:\n  ros__parameters:\n    status_rate_hz: 3.0\n")
    overrides = [Parameter(k, value=v) for k, v in {**topic_params("paramfile"), **SMALL,
                                                    "output_dir": str(tmp_path / "out")}.items()]
    for namespace, remap, fqn in (("paramfile", [], "/paramfile/senfunet"), ("", ["-r", "__node:=front"], "/front")):
        capfd.readouterr()
        node = FusionNode(namespace=namespace, parameter_overrides=overrides,
                          cli_args=["--ros-args", *remap, "--params-file", str(plain), "--params-file", str(wildcard)])
        try:
            err = capfd.readouterr().err
            assert node.get_fully_qualified_name() == fqn
            assert node.settings.status_rate_hz == 3.0  # the wildcard section reaches it: not named
            assert f"{plain}:" in err and fqn in err and "runs without this file's parameters" in err, err
            assert f"{wildcard}:" not in err, err
        finally:
            node.destroy_node()
    from senfunet_ros.node import params_files

    assert params_files(["fusion_node", "--params-file", "x", "--ros-args", "-r", "a:=b", "--params-file", "y.yaml",
                         "--", "--params-file", "z"]) == ["y.yaml"]


def test_warnings_name_the_topics_as_subscribed_under_a_remapping(ros, tmp_path: Path, capfd) -> None:
    """`--ros-args -r /tof/depth:=/cam/depth`: the node subscribes to /cam/depth, but its warnings named
    the parameter's /tof/depth ("nothing received on /tof/depth"), a topic the user had remapped away."""
    from rclpy.parameter import Parameter

    from senfunet_ros.ingest import Ingest, IngestConfig
    from senfunet_ros.node import FusionNode
    from senfunet_ros.status import counter_warnings

    overrides = {**topic_params("remap"), **SMALL, "diagnostics_window_s": 0.2, "output_dir": str(tmp_path / "out")}
    node = FusionNode(namespace="remap", parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()],
                      cli_args=["--ros-args", "-r", "/remap/tof/depth:=/cam/depth"])
    try:
        time.sleep(0.5)  # longer than a window: every topic is silent
        capfd.readouterr()
        node.status()
        err = capfd.readouterr().err
        assert "tof: nothing received on /cam/depth" in err, err
        assert "/remap/tof/depth" not in err, err
        before = Ingest(IngestConfig(sensors=node.settings.sensor_names)).ledger.counters()
        now = {name: {**c, "dropped": dict(c["dropped"]), "errors": {}} for name, c in before.items()}
        now["tof"]["dropped"]["duplicate"] = 1  # its hint names the depth topic
        (warning,) = counter_warnings(before, now, node.settings, node._topics)
        assert "/cam/depth" in warning[1], warning
    finally:
        node.destroy_node()


def test_two_renamed_nodes_report_under_their_own_names(ros, tmp_path: Path) -> None:
    """Two fusion nodes on one robot (`-r __node:=front`, `-r __node:=rear`) both named their statuses
    "senfunet: tof", "senfunet: pipeline": the diagnostic aggregator and rqt_robot_monitor key entries by
    name, so one node's STALE camera showed as the other's, or hid it."""
    from rclpy.parameter import Parameter

    from senfunet_ros.node import FusionNode

    names = []
    for name in ("front", "rear"):
        overrides = {**topic_params(name), **SMALL, "output_dir": str(tmp_path / name)}
        node = FusionNode(parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()],
                          cli_args=["--ros-args", "-r", f"__node:={name}"])
        try:
            names.append({status.name for status in node.status().status})
        finally:
            node.destroy_node()
    assert names[0] == {"front: tof", "front: stereo", "front: pipeline"}, names
    assert names[1] == {"rear: tof", "rear: stereo", "rear: pipeline"}, names


def test_a_diagnostics_window_widened_at_run_time_keeps_the_rates_right() -> None:
    """`ros2 param set /senfunet diagnostics_window_s 10` from 1 s: the arrivals kept covered the last
    second only, but the rate divided them by 10 s, so a 10 Hz camera showed 1 Hz for the next 9 s."""
    from senfunet_ros.health import HealthMonitor

    now = [0.0]
    health = HealthMonitor({"tof": ("depth",)}, window_s=1.0, stale_after_s=2.0, clock=lambda: now[0])

    def stream(seconds: float) -> float:  # depth at 10 Hz; the rate then reported
        for _ in range(round(seconds * 10)):
            now[0] += 0.1
            health.received("tof", "depth")
        return health.report()["tof"].streams["depth"].rate_hz

    assert stream(20.0) == pytest.approx(10.0, rel=0.15)
    health.window_s = 10.0  # what the node's parameter callback sets
    assert stream(0.5) == pytest.approx(10.0, rel=0.15)
    assert stream(12.0) == pytest.approx(10.0, rel=0.15)  # then over the whole new window
    health.window_s = 2.0  # narrowed: the arrivals beyond it expire
    assert stream(0.5) == pytest.approx(10.0, rel=0.15)


def test_poses_queued_behind_the_images_cost_no_frame(ros, tmp_path: Path) -> None:
    """A busy node takes one message per subscription per executor round, and poses come at several
    times the image rate: the images it takes ran seconds ahead of the poses queued for them, and the
    frames timed out waiting for poses that were already there (pose_timeout, under overload). With
    every message queued before the node takes them, each frame still gets its pose."""
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.parameter import Parameter

    from senfunet_ros.node import FusionNode

    prefix = "poselag"
    overrides = {"output_dir": str(tmp_path / "out"), **topic_params(prefix), **SMALL, "queue_size": 30}
    node = FusionNode(namespace=prefix, parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
    pub_node, witness = Node("poselag_publisher"), Node("poselag_witness")
    kinds = {"depth": Image, "color": Image, "camera_info": CameraInfo, "pose": PoseStamped}
    heard = [0]
    pubs = {(s, k): pub_node.create_publisher(t, f"/{prefix}/{s}/{k}", 1000) for s in ("tof", "stereo")
            for k, t in kinds.items()}
    for s, k in pubs:
        witness.create_subscription(kinds[k], f"/{prefix}/{s}/{k}", lambda _msg: heard.__setitem__(0, heard[0] + 1),
                                    1000)
    witnessing = SpinThread(MultiThreadedExecutor(num_threads=2))
    witnessing.executor.add_node(witness)
    executor = MultiThreadedExecutor(num_threads=6)
    executor.add_node(node)
    spinning = None
    try:
        wait_for(lambda: all(p.get_subscription_count() == 2 for p in pubs.values()), 20, "discovery")
        time.sleep(1.0)  # the readers' side of discovery
        messages = scene_messages()
        firsts = {}  # each stream's first message, taken by the node before the others are queued
        for sensor, stream, msg in messages:
            firsts.setdefault((sensor, stream), msg)
        for (sensor, stream), msg in firsts.items():
            pubs[(sensor, stream)].publish(msg)

        def took_firsts() -> bool:
            executor.spin_once(timeout_sec=0.05)
            c = node.ingest.ledger.counters()
            return all(c[s]["received"] and c[s]["pose_received"] for s in ("tof", "stereo"))

        wait_for(took_firsts, 20, "the node to take each stream's first message")
        rest = [(sensor, stream, msg) for sensor, stream, msg in messages if firsts[(sensor, stream)] is not msg]
        for sensor, stream, msg in rest:
            pubs[(sensor, stream)].publish(msg)
        # the node's readers hold them all now, as a reader of the same publishers does, none taken yet
        wait_for(lambda: heard[0] >= len(messages), 20, "the messages to be delivered")
        spinning = SpinThread(executor)
        expected = {s: sum(1 for sensor, stream, _ in messages if (sensor, stream) == (s, "depth"))
                    for s in ("tof", "stereo")}

        def settled() -> bool:
            return all(c["integrated"] + sum(c["dropped"].values()) >= expected[s]
                       for s, c in node.ingest.ledger.counters().items())

        wait_for(settled, 60, "every frame to be integrated or dropped")
        counters = node.ingest.ledger.counters()
        drops = str({s: {r: n for r, n in c["dropped"].items() if n} for s, c in counters.items()})
        assert all(c["dropped"]["pose_timeout"] == 0 for c in counters.values()), drops
        # the first and last frames of a stream may lack a pose on one side (pose_gap)
        assert all(c["integrated"] >= expected[s] - 2 for s, c in counters.items()), drops
    finally:
        if spinning is not None:
            spinning.stop()
        else:
            stop_executor(executor)
        witnessing.stop()
        node.destroy_node()
        pub_node.destroy_node()
        witness.destroy_node()


def test_frames_set_aside_before_a_time_jump_that_resets_the_map_stay_out_of_the_new_map(ros, tmp_path: Path
                                                                                          ) -> None:
    """on_time_jump: reset, and time goes back (a bag looping) while frames the node fell behind on
    are set aside: they belong to the map that was reset, and were integrated into the new one once
    the sensors paused. They are dropped as time_jump, like the frames queued then."""
    prefix = "asidejump"
    run = Running(prefix, {**topic_params(prefix), **SMALL, "max_lag_s": 0.01, "behind_buffer_mb": 64.0,
                           "on_time_jump": "reset"}, tmp_path)
    try:
        messages = scene_messages()
        with run.node.pipeline.lock:  # integration waits meanwhile: the node falls behind on every frame
            for sensor, stream, msg in messages:
                run.node.pipeline.dispatch(sensor, stream, msg)
            for _ in range(2):  # integration ticks that got no frame done: the first poses them, the second sets
                run.node.ingest.pop_ready(max_frames=0)  # those behind aside
            set_aside = sum(c["set_aside_now"] for c in run.node.ingest.ledger.counters().values())
            assert set_aside > 5
            run.node.ingest.restart(int((BASE_S - 100) * 1e9))  # /clock went back: the map is reset

        def settled() -> bool:
            return (run.node.pipeline.time_jumps == 1
                    and all(c["set_aside_now"] == 0 and c["integrated"] + sum(c["dropped"].values()) >= c["received"]
                            for c in run.node.ingest.ledger.counters().values()))

        wait_for(settled, 30, "the time jump and the frames set aside to be handled")
        time.sleep(1.0)  # set-aside frames are handed out once no image came for max_lag_s: none may come now
        counters = run.node.ingest.ledger.counters().values()
        assert sum(c["integrated"] for c in counters) == 0
        assert sum(c["dropped"]["time_jump"] for c in counters) == sum(c["received"] for c in counters)
        assert run.node.engine.extract_mesh("fused").n_faces == 0
    finally:
        run.close()


def test_frames_after_the_last_pose_are_integrated_once_the_sensor_falls_silent(ros, tmp_path: Path, capfd) -> None:
    """The pose streams stop 50 ms before the depth streams (a robot's localisation stopping first): the
    last frame of each sensor lies past its newest pose and waited for a pose that never came, until
    the stop dropped it. Once the sensor has been silent for pose_max_wait_s, it is posed by
    extrapolating the poses' motion and integrated; ~/status counts it as extrapolated and the log
    says so once."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    def stamp_s(msg: Any) -> float:
        return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9

    messages = scene_messages()
    last_depth_s = {s: max(stamp_s(m) for sensor, stream, m in messages if (sensor, stream) == (s, "depth"))
                    for s in ("tof", "stereo")}
    # poses stamped up to 50 ms before each sensor's last depth image, no later
    messages = [(s, stream, m) for s, stream, m in messages
                if stream != "pose" or stamp_s(m) <= last_depth_s[s] - 0.05]
    name = "streamend"
    with _posing_run(name, tmp_path, pose_max_wait_s=1.0, pose_tolerance_s=0.1) as (run, _, got):
        kinds = {"depth": Image, "color": Image, "camera_info": CameraInfo, "pose": PoseStamped}
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        pub_node = Node(f"{name}_streams")
        try:
            pubs = {(s, k): pub_node.create_publisher(t, f"/{name}/{s}/{k}", qos) for s in ("tof", "stereo")
                    for k, t in kinds.items()}
            wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 20, "discovery")
            time.sleep(1.0)  # the node's side of discovery
            for sensor, stream, msg in messages:  # a stream in stamp order, a little faster than real time
                pubs[(sensor, stream)].publish(msg)
                time.sleep(0.003)
            received = {s: sum(1 for sensor, stream, _ in messages if (sensor, stream) == (s, "depth"))
                        for s in ("tof", "stereo")}

            def sensor_values() -> dict[str, dict[str, str]]:
                out: dict[str, dict[str, str]] = {}
                for msg in reversed(got[-5:]):
                    for status in msg.status:
                        sensor = status.name.removeprefix("senfunet: ")
                        if sensor in received and sensor not in out:
                            out[sensor] = {kv.key: kv.value for kv in status.values}
                return out

            def settled() -> bool:  # every frame received, decided (integrated or dropped), none waiting
                values = sensor_values()
                return all(s in values and int(values[s]["received"]) == n and values[s]["queue_depth"] == "0"
                           and int(values[s]["integrated"]) + sum(int(v) for k, v in values[s].items()
                                                                  if k.startswith("dropped.")) == n
                           for s, n in received.items())

            wait_for(settled, 60, "the last frames to be integrated once the sensors fell silent")
            values = sensor_values()
            drops = {s: {k: v for k, v in sensor.items() if k.startswith("dropped.") and v != "0"}
                     for s, sensor in values.items()}
            for s in received:
                assert values[s]["extrapolated"] == "1", (s, values[s].get("extrapolated"), drops)
                assert values[s]["dropped.pose_timeout"] == "0", drops
            time.sleep(0.3)  # the log line of the integration tick
        finally:
            pub_node.destroy_node()
    log = capfd.readouterr().err
    ended = [line for line in log.splitlines() if "streams ended" in line]
    assert len(ended) == 2 and all("1 frame(s)" in line and "extrapolated" in line for line in ended), log[-3000:]


def test_a_looping_bag_gets_one_line_per_pass_with_the_pass_and_the_map(ros, tmp_path: Path, capfd) -> None:
    """A bag played with --loop restarts time every pass: each restart is one warning that names the pass
    and what became of the map (on_time_jump), not a line per stream for the messages it cost (those are
    counted on ~/status)."""
    run = Running("looping", {**topic_params("looping"), **SMALL}, tmp_path)
    try:
        messages = scene_messages()
        for _ in range(3):  # three passes of the same 2 s recording
            fuse_in_process(run, messages)
            time.sleep(0.3)  # the integration tick's warnings
        wait_for(lambda: run.node.pipeline.time_jumps == 2, 20, "two restarts")
        time.sleep(0.5)
    finally:
        run.close()
    log = capfd.readouterr().err
    restarts = [line for line in log.splitlines() if "time restarted" in line]
    assert len(restarts) == 2, log[-3000:]
    for line, n in zip(restarts, (2, 3)):
        assert f"pass {n}" in line and "map kept (parameter on_time_jump)" in line, line
    per_stream = [line for line in log.splitlines() if ": time_jump:" in line or ": bad_stamp:" in line]
    assert not per_stream, per_stream


def test_a_stray_stamp_is_still_warned_once_it_turns_out_no_restart(ros, tmp_path: Path, capfd) -> None:
    """While stamps off the timeline may yet start a new one, their bad_stamp drops wait; a stray, the
    stream going on on its timeline, is warned about after all."""
    run = Running("stray", {**topic_params("stray"), **SMALL}, tmp_path)
    try:
        for i in range(40):  # poses at 20 Hz for 2 s, one of them stamped 50 s ahead
            msg = PoseStamped()
            msg.pose.orientation.w = 1.0
            _stamp(msg, 10.0 + 0.05 * i + (50.0 if i == 5 else 0.0))
            run.node.pipeline.dispatch("tof", "pose", msg)
            time.sleep(0.02)
        wait_for(lambda: not run.node.ingest.restart_pending(), 10, "the stray's episode to end")
        time.sleep(0.5)  # the integration tick's warnings
        assert run.node.pipeline.time_jumps == 0
    finally:
        run.close()
    log = capfd.readouterr().err
    assert len([line for line in log.splitlines() if "tof: dropped 1 message(s): bad_stamp" in line]) == 1, log[-3000:]


def test_a_sensor_whose_stamps_are_always_off_is_warned_while_a_restart_stays_pending(ros, tmp_path: Path,
                                                                                      capfd) -> None:
    """A driver whose clock runs 100 s behind the others keeps a restart pending (its stamps build a new
    timeline the other sensor never joins): its bad_stamp drops wait at most a warning period, then are
    warned, not held for as long as it goes on."""
    run = Running("offclock", {**topic_params("offclock"), **SMALL}, tmp_path)
    try:
        for i in range(200):  # 20 Hz for 10 s; stereo's clock 100 s behind tof's
            for sensor, offset_s in (("tof", 0.0), ("stereo", -100.0)):
                msg = PoseStamped()
                msg.pose.orientation.w = 1.0
                _stamp(msg, 200.0 + 0.05 * i + offset_s)
                run.node.pipeline.dispatch(sensor, "pose", msg)
            time.sleep(0.05)
        assert run.node.pipeline.time_jumps == 0
    finally:
        run.close()
    log = capfd.readouterr().err
    assert any("stereo: dropped" in line and "bad_stamp" in line for line in log.splitlines()), log[-3000:]



def test_the_engines_log_lines_after_the_context_shut_down_go_to_stderr_not_to_a_dead_rosout(capfd):
    """After Ctrl-C the node finishes its queued frames with the ROS context shut down: each engine log
    line (a map-bound eviction) came with rcl's "Failed to publish log message to rosout: publisher's
    context is invalid"."""
    import logging

    import rclpy
    from rclpy.parameter import Parameter

    from senfunet_ros.node import FusionNode

    context = rclpy.Context()
    rclpy.init(context=context)
    node = FusionNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in SMALL.items()])
    try:
        capfd.readouterr()
        logging.getLogger("senfunet.engine").warning("map bound: evicted 12 blocks (a test line)")
        assert "map bound: evicted 12 blocks" in capfd.readouterr().err
        rclpy.shutdown(context=context)
        logging.getLogger("senfunet.engine").warning("map bound: evicted 34 blocks (after the stop)")
        err = capfd.readouterr().err
        assert "senfunet: warning: map bound: evicted 34 blocks" in err and "rosout" not in err, err
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_an_empty_list_given_to_the_node_is_an_empty_list_not_the_default(ros):
    """rcl reads `rgb_sensors: []` (a file, or -p rgb_sensors:=[]) as a parameter without a value, and the
    node took the default (['stereo']) without a word: colour went to stereo's feature net while replay,
    reading the same file, fused without it."""
    from rclpy.parameter import Parameter

    from senfunet_ros.node import FusionNode

    overrides = {**SMALL, "weights": "none"}  # the default weights were trained with colour for stereo
    node = FusionNode(parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()],
                      cli_args=["--ros-args", "-p", "rgb_sensors:=[]"])
    try:
        assert tuple(node.settings.rgb_sensors) == (), node.settings.rgb_sensors
    finally:
        node.destroy_node()


def test_another_nodes_parameter_in_a_section_for_every_node_is_no_warning(ros, tmp_path: Path, capfd) -> None:
    """A launch set-up's `/**` section holds parameters for every node (robot_name): the node warned that
    each "is not one of this node's", as for a typo. It says so at info level; a near miss of one of its
    own names is still a warning."""
    from rclpy.parameter import Parameter

    from senfunet_ros.node import FusionNode

    shared = tmp_path / "shared.yaml"
    shared.write_text("/**:\n  ros__parameters:\n    robot_name: rover\n    status_rate_hz: 3.0\n"
                      "    mesh_rate_hs: 2.0\n")
    overrides = [Parameter(k, value=v) for k, v in {**SMALL, "output_dir": str(tmp_path / "out")}.items()]
    capfd.readouterr()
    node = FusionNode(parameter_overrides=overrides, cli_args=["--ros-args", "--params-file", str(shared)])
    try:
        err = capfd.readouterr().err
        assert node.settings.status_rate_hz == 3.0
        assert "[INFO]" in err.split("parameter robot_name, from a section for every node")[0].rsplit("\n", 1)[-1], err
        assert "[WARN]" in err.split("parameter mesh_rate_hs (did you mean mesh_rate_hz?)")[0].rsplit("\n", 1)[-1], err
    finally:
        node.destroy_node()


def test_weights_clouds_keep_their_rate_on_mesh_ticks_that_come_a_little_late():
    """~/weights at 2 Hz with mesh updates every 0.45 s: the next cloud was due a period after the tick
    that sent one, so a tick just short of it skipped, and clouds came at about 1.1 Hz."""
    from senfunet_ros.mesh_publisher import next_due_s

    due, sent = 0.0, []
    for k in range(1, 46):  # 20 s of ticks, each a few ms late
        now = 100.0 + 0.45 * k + 0.003
        if now >= due:
            sent.append(now)
            due = next_due_s(due, now, 0.5)
    assert len(sent) >= 36, len(sent)  # 2 Hz, less the ticks a cloud falls between
    assert next_due_s(0.0, 100.0, 0.5) == 100.5  # after a pause (or the first): a period from now
