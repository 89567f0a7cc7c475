"""The live node with real rclpy: a separate process streams a simulated scene on the contract's
topics; the node is spun in this process so its counters can be read directly."""
from __future__ import annotations

import multiprocessing
import threading
import time
from pathlib import Path
from typing import Any
from collections.abc import Callable

import numpy as np
import pytest
import rclpy
import yaml
from geometry_msgs.msg import PoseStamped
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from senfunet_ros import params as P
from senfunet_ros.node import FusionNode, stop_executor
from senfunet_ros.mesh_publisher import MIN_TURN_S

ROOT = Path(__file__).resolve().parents[2]
BASE_S = 1000  # added to simulator stamps (which start below 0 for poses)
# Kept small so the whole file runs in a few minutes on 2 cores with the CPU engine:
# 128 px simulated images, integrated at 64 px, 4 cm voxels (band = 10 voxels, as 0.1 m at 1 cm).
# Sensor rates lowered from the contract's 15/20 Hz: fewer frames of the same trajectory.
SIM = dict(seed=3, duration_s=3.0, width=128, height=128, tof_rate_hz=6.0, stereo_rate_hz=6.0)
# tsdf_fusion: keep the TSDF Fusion baseline, so ~/save_mesh writes tsdf_fusion.ply too.
E2E_PARAMS = dict(voxel_size_m=0.04, band_m=0.4, working_width=64, queue_size=500, max_lag_s=0.0, mesh_rate_hz=1.0,
                  integrate_rate_hz=50.0, weights_band_m=0.0, tsdf_fusion=True)


# ------------------------------------------------------------------------------------------------
# helpers


def topic_params(prefix: str, sensors: tuple[str, ...] = ("tof", "stereo")) -> dict[str, Any]:
    """Per-test topic names so tests never hear each other's publishers."""
    out: dict[str, Any] = {}
    for s in sensors:
        for kind in ("depth", "color", "camera_info", "pose"):
            out[f"{s}.{kind}_topic"] = f"/{prefix}/{s}/{kind}"
    return out


class SpinThread:
    """An executor spun in a thread until `stop`, which returns once no callback runs any more (then
    the executor's nodes may go). It spins once at a time: rclpy's shutdown, called from another
    thread while the executor spins, takes the guard condition from under the executor's wait."""

    def __init__(self, executor: Any) -> None:
        self.executor = executor
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.1)

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=10)  # no more callbacks handed out
        stop_executor(self.executor)  # and those under way ended


class Running:
    """A FusionNode and a helper node spun by one MultiThreadedExecutor in a thread."""

    def __init__(self, namespace: str, overrides: dict[str, Any], tmp_path: Path) -> None:
        overrides = {"output_dir": str(tmp_path / "out"), **overrides}
        self.node = FusionNode(namespace=namespace,
                               parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
        self.helper = Node("test_helper", namespace=namespace)
        self.executor = MultiThreadedExecutor(num_threads=6)
        self.executor.add_node(self.node)
        self.executor.add_node(self.helper)
        self.spinning = SpinThread(self.executor)
        self.thread = self.spinning.thread
        self.prefix = f"/{namespace}/senfunet"

    def close(self) -> None:
        self.spinning.stop()
        self.node.destroy_node()
        self.helper.destroy_node()

    def call(self, service: str, timeout_s: float = 120.0) -> Trigger.Response:
        client = self.helper.create_client(Trigger, f"{self.prefix}/{service}")
        assert client.wait_for_service(timeout_sec=10.0), f"{service} not available"
        future = client.call_async(Trigger.Request())
        deadline = time.monotonic() + timeout_s
        while not future.done() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert future.done(), f"{service} did not answer"
        return future.result()


class MeshCollector:
    """Applies MarkerArray updates (ADD/DELETE/DELETEALL) like RViz does."""

    def __init__(self, node: Node, topic: str) -> None:
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.markers: dict[tuple[str, int], np.ndarray] = {}
        self.messages = 0
        self.delete_alls = 0
        self.lock = threading.Lock()
        self.sub = node.create_subscription(MarkerArray, topic, self._on_msg, qos)

    def _on_msg(self, msg: MarkerArray) -> None:
        with self.lock:
            self.messages += 1
            for m in msg.markers:
                if m.action == Marker.DELETEALL:
                    self.markers.clear()
                    self.delete_alls += 1
                elif m.action == Marker.DELETE:
                    self.markers.pop((m.ns, m.id), None)
                else:
                    assert m.type == Marker.TRIANGLE_LIST and len(m.points) % 3 == 0
                    assert len(m.colors) == len(m.points)
                    self.markers[(m.ns, m.id)] = np.array([[p.x, p.y, p.z] for p in m.points], np.float32)

    def points(self) -> np.ndarray:
        with self.lock:
            parts = list(self.markers.values())
        return np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)

    def keys(self) -> set[tuple[str, int]]:
        with self.lock:
            return set(self.markers)


def wait_for(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


# ------------------------------------------------------------------------------------------------
# the publisher process


def _stamp(msg: Any, t_s: float) -> None:
    ns = int(round((t_s + BASE_S) * 1e9))
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)


def _pose_msg(t_s: float, T: np.ndarray) -> PoseStamped:
    from senfunet_ros.geometry import quat_from_matrix

    msg = PoseStamped()
    _stamp(msg, t_s)
    msg.header.frame_id = "map"
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in T[:3, 3])
    q = quat_from_matrix(T[:3, :3])
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in q)
    return msg


def _sim_kwargs() -> dict[str, Any]:
    return {"seed": SIM["seed"], **{k: v for k, v in SIM.items() if k != "seed"}}


# Flow control of stream_scene: the node's counters of taken messages, per (sensor, stream), and how
# far the streamer may run ahead of them. The node's best-effort readers keep the last 200 poses
# and 30 images (_POSE_QOS, _SENSOR_QOS); when the executor threads cannot take messages for a
# while (the GIL held by an integration or a mesh update, a loaded machine), 100 Hz poses
# overflow that in 2 s and are lost (measured: scripts/dds_probe.py --busy, and a full test run
# that lost a third of the poses while every image arrived). The node works on stamps, never wall
# time, so pausing the stream changes nothing it computes.
FLOW = (("tof", "pose_received"), ("stereo", "pose_received"), ("tof", "received"), ("stereo", "received"))
FLOW_AHEAD = (100, 100, 10, 10)


def _flow_counts(node: FusionNode) -> list[int]:
    counters = node.ingest.ledger.counters()
    return [counters[s][key] for s, key in FLOW]


def stream_scene(prefix: str, speed: float, go: Any = None, taken: Any = None) -> None:
    """Child process: simulate SIM and publish it on the contract topics with reliable QoS.

    With `go` (a multiprocessing.Event) the stream starts only after a handshake: until the test
    process sets it, each sensor's first camera_info and first pose are republished every 0.1 s
    (the node keeps the latest camera_info and overwrites a pose with the same stamp, so this
    changes no frame). `get_subscription_count()` only says that OUR writers matched the node's
    readers; a best-effort reader drops everything that arrives before IT has matched the writer,
    which can be a second later under load. The test sets `go` once the node's readers count our
    writers and the node holds a camera_info and a pose of each sensor (see _node_hears_streamer).

    With `taken` (a shared array the test keeps equal to _flow_counts(node)) the stream pauses
    while the node has taken FLOW_AHEAD or fewer messages less than were sent of a stream, so
    its reader queues never overflow; stamps and order stay those of the scene.
    """
    from senfunet_core.learning.simulator import make_scene, simulate_sequence

    seq = simulate_sequence(make_scene(SIM["seed"]), **_sim_kwargs())
    rclpy.init()
    node = Node("scene_streamer")
    pubs = {(s, k): node.create_publisher(t, f"/{prefix}/{s}/{k}", 50)
            for s in ("tof", "stereo")
            for k, t in (("depth", Image), ("color", Image), ("camera_info", CameraInfo), ("pose", PoseStamped))}
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and any(p.get_subscription_count() == 0 for (s, k), p in pubs.items()
                                              if k != "color" or s == "stereo"):
        time.sleep(0.05)
    if go is not None:
        warmup = []
        for s in ("tof", "stereo"):
            f = next(f for f in seq.frames if f.sensor == s)
            h, w = f.depth_m.shape
            info = CameraInfo(width=w, height=h, k=[float(v) for v in f.K.reshape(-1)])
            _stamp(info, f.stamp_s)
            pose = _pose_msg(seq.pose_stamps_s[s][0], seq.pose_T_world_camera[s][0])
            warmup += [(pubs[(s, "camera_info")], info), (pubs[(s, "pose")], pose)]
        deadline = time.monotonic() + 60
        while not go.wait(0.1):
            if time.monotonic() > deadline:
                raise RuntimeError("handshake: the node never heard the warm-up messages")
            for publisher, msg in warmup:
                publisher.publish(msg)
    events: list[tuple[float, int, int, Callable[[], None]]] = []  # (stamp, order, FLOW index or -1, publish)
    for s in ("tof", "stereo"):
        for t, T in zip(seq.pose_stamps_s[s], seq.pose_T_world_camera[s]):
            events.append((t, 0, FLOW.index((s, "pose_received")),
                           lambda m=_pose_msg(t, T), s=s: pubs[(s, "pose")].publish(m)))  # noqa: B008 (bound now)
    for f in seq.frames:
        h, w = f.depth_m.shape
        info = CameraInfo(width=w, height=h, k=[float(v) for v in f.K.reshape(-1)])
        _stamp(info, f.stamp_s)
        if f.sensor == "tof":  # metres as 32FC1
            depth = Image(height=h, width=w, encoding="32FC1", step=w * 4)
            depth.data = np.ascontiguousarray(f.depth_m, "<f4").tobytes()
        else:  # millimetres as 16UC1, the other contract encoding
            depth = Image(height=h, width=w, encoding="16UC1", step=w * 2)
            depth.data = np.clip(np.rint(f.depth_m * 1000), 0, 65535).astype("<u2").tobytes()
        _stamp(depth, f.stamp_s)
        msgs = [("camera_info", info), ("depth", depth)]
        if f.rgb is not None:
            color = Image(height=h, width=w, encoding="rgb8", step=w * 3)
            color.data = np.ascontiguousarray(f.rgb).tobytes()
            _stamp(color, f.stamp_s)
            msgs.insert(1, ("color", color))
        for key, msg in msgs:
            flow = FLOW.index((f.sensor, "received")) if key == "depth" else -1
            events.append((f.stamp_s, 1, flow, lambda m=msg, s=f.sensor, k=key: pubs[(s, k)].publish(m)))
    events.sort(key=lambda e: (e[0], e[1]))
    base = list(taken) if taken is not None else None  # the node's counts before the stream
    sent = [0] * len(FLOW)
    paused_s = 0.0
    start_wall, start_sim = time.monotonic(), events[0][0]
    for t, _, flow, publish in events:
        if base is not None and flow >= 0:
            waited = time.monotonic()
            while (sent[flow] - (taken[flow] - base[flow]) >= FLOW_AHEAD[flow]
                   and time.monotonic() - waited < 60.0):  # lost messages must not stall it forever
                time.sleep(0.005)
            paused_s += time.monotonic() - waited
            sent[flow] += 1
        delay = (t - start_sim) / speed + paused_s - (time.monotonic() - start_wall)
        if delay > 0:
            time.sleep(delay)
        publish()
    if paused_s > 0.05:
        print(f"stream_scene: paused {paused_s:.1f} s for the node to take its messages", flush=True)
    time.sleep(1.0)  # let best-effort readers drain before the participant goes
    node.destroy_node()
    rclpy.shutdown()


# ------------------------------------------------------------------------------------------------
# tests


def test_parameter_table_declared_and_default_yaml_matches(ros, tmp_path: Path, capfd) -> None:
    expected = P.expanded_defaults()
    run = Running("params", {"voxel_sise_m": 0.05}, tmp_path)  # a typo: rclpy ignores it, the node says so
    try:
        assert "parameter voxel_sise_m (did you mean voxel_size_m?) is not one of this node's" in capfd.readouterr().err
        for name, (_default, help_text) in expected.items():
            assert run.node.has_parameter(name), name
            descriptor = run.node.describe_parameter(name)
            assert descriptor.description == help_text
        assert run.node.get_parameter("fixed_frame").value == "map"
    finally:
        run.close()
    data = yaml.safe_load((ROOT / "config" / "default.yaml").read_text())
    flat: dict[str, Any] = {}

    def walk(prefix: str, tree: dict[str, Any]) -> None:
        for key, value in tree.items():
            if isinstance(value, dict):
                walk(f"{prefix}{key}.", value)
            else:
                flat[f"{prefix}{key}"] = value

    walk("", data[P.NODE_NAME]["ros__parameters"])
    assert flat == {name: default for name, (default, _) in expected.items()}


def test_senfunet_node_in_a_namespace_takes_the_file_sections_that_reach_it(ros, tmp_path: Path) -> None:
    """`senfunet node --params FILE -- --ros-args -r __ns:=/robot1`: rcl gives the node /robot1/senfunet
    the file's '/robot1/senfunet' (or '/**/senfunet') section, which the command refused, and not a plain
    'senfunet' one, which the command let through: the node then ran with the defaults, silently."""
    import subprocess
    import sys

    from rclpy.parameter_client import AsyncParameterClient

    plain = tmp_path / "plain.yaml"
    plain.write_text(f"senfunet:\n  ros__parameters:\n    output_dir: {tmp_path / 'plain'}\n")
    command = [sys.executable, "-m", "senfunet_ros.cli", "node", "--params"]
    refused = subprocess.run([*command, str(plain), "--", "--ros-args", "-r", "__ns:=/robot1"], capture_output=True,
                             text=True, timeout=120)
    assert refused.returncode == 2 and "'/**/senfunet'" in refused.stderr, refused.stderr
    namespaced = tmp_path / "namespaced.yaml"
    namespaced.write_text(f"/robot1/senfunet:\n  ros__parameters:\n    output_dir: {tmp_path / 'robot1'}\n")
    node = subprocess.Popen([*command, str(namespaced), "--", "--ros-args", "-r", "__ns:=/robot1"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    client_node = Node("namespace_client")
    try:
        client = AsyncParameterClient(client_node, "/robot1/senfunet")
        deadline = time.monotonic() + 120
        while not client.services_are_ready() and node.poll() is None and time.monotonic() < deadline:
            rclpy.spin_once(client_node, timeout_sec=0.1)
        assert node.poll() is None, node.communicate()[1]
        future = client.get_parameters(["output_dir"])
        rclpy.spin_until_future_complete(client_node, future, timeout_sec=30)
        assert future.result() is not None and future.result().values[0].string_value == str(tmp_path / "robot1")
    finally:
        client_node.destroy_node()
        node.terminate()
        node.wait(timeout=60)


def _visible_gt(gt_vertices: np.ndarray, seq: Any, border_px: int = 10, tol_m: float = 0.1) -> np.ndarray:
    """GT vertices some ToF frame saw (in its image, depth agreeing): the part a short
    trajectory can reconstruct, so recall measures the fusion, not the trajectory's coverage."""
    seen = np.zeros(len(gt_vertices), bool)
    hom = np.c_[gt_vertices, np.ones(len(gt_vertices))].T
    for f in seq.frames:
        if f.sensor != "tof":
            continue
        cam = (np.linalg.inv(f.T_world_camera) @ hom)[:3]
        z = cam[2]
        ok = z > 0.1
        u = np.full(z.shape, -1, np.int64)
        v = np.full(z.shape, -1, np.int64)
        u[ok] = np.rint(f.K[0, 0] * cam[0, ok] / z[ok] + f.K[0, 2]).astype(np.int64)
        v[ok] = np.rint(f.K[1, 1] * cam[1, ok] / z[ok] + f.K[1, 2]).astype(np.int64)
        h, w = f.depth_m.shape
        ok &= (u >= border_px) & (u < w - border_px) & (v >= border_px) & (v < h - border_px)
        d = np.zeros(z.shape, np.float32)
        d[ok] = f.depth_m[v[ok], u[ok]]
        seen |= ok & (d > 0) & (np.abs(d - z) < tol_m)
    return gt_vertices[seen]


@pytest.mark.slow
def test_streamed_scene_mesh_weights_save_reset_late_subscriber(ros, tmp_path: Path) -> None:
    from senfunet_core.metrics import mesh_metrics
    from senfunet_core.ply import read_ply
    from senfunet_core.readout import weight_cloud
    from senfunet_core.learning.simulator import gt_mesh, make_scene, simulate_sequence

    prefix = "e2e"
    run = Running("e2e", {**E2E_PARAMS, **topic_params(prefix)}, tmp_path)
    child = late_node = None
    try:
        collector = MeshCollector(run.helper, f"{run.prefix}/mesh")
        clouds: list[PointCloud2] = []
        run.helper.create_subscription(PointCloud2, f"{run.prefix}/weights", clouds.append,
                                       QoSProfile(depth=2, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        # Real time (paused while the node's executor lags, see FLOW), with a queue large enough
        # that nothing is dropped: the test is about what the node makes of the stream; keeping
        # up is measured by bench/, not on a loaded test machine.
        ctx = multiprocessing.get_context("spawn")
        go = ctx.Event()
        taken = ctx.Array("q", len(FLOW), lock=False)  # _flow_counts(run.node), for flow control
        child = ctx.Process(target=stream_scene, args=(prefix, 1.0, go, taken))
        child.start()
        scene = make_scene(SIM["seed"])  # meanwhile: the same scene and frames, for ground truth
        seq = simulate_sequence(scene, **_sim_kwargs())
        gt = gt_mesh(scene, voxel_size_m=0.02)
        # Handshake: stream only once the node's readers have matched every writer (not only the
        # other way round) and its callbacks got data from the streamer.
        t0 = time.monotonic()
        wait_for(lambda: _node_hears_streamer(run.node, prefix) or child.exitcode is not None, 90,
                 "the node to hear the streamer's warm-up messages")
        assert child.exitcode is None, "publisher process failed before streaming"
        taken[:] = _flow_counts(run.node)
        go.set()
        print(f"\nhandshake done {time.monotonic() - t0:.1f} s after the ground truth")
        deadline = time.monotonic() + 300
        while child.is_alive() and time.monotonic() < deadline:
            taken[:] = _flow_counts(run.node)
            child.join(timeout=0.02)
        assert child.exitcode == 0, "publisher process failed"
        n_tof = sum(f.sensor == "tof" for f in seq.frames)
        n_stereo = len(seq.frames) - n_tof
        # The executor may still be taking messages out of the readers: count once it stopped.
        counters = _settled_counters(run.node)
        print(f"\nreceived after the stream: { {s: c['received'] for s, c in counters.items()} } "
              f"of tof {n_tof}, stereo {n_stereo}; poses "
              f"{ {s: c['pose_received'] for s, c in counters.items()} }")
        # best effort over loopback may lose the odd image; most must arrive
        assert counters["tof"]["received"] >= 0.8 * n_tof and counters["stereo"]["received"] >= 0.8 * n_stereo, \
            str(counters)
        assert counters["stereo"]["color_received"] > 0
        def all_accounted() -> bool:  # every received frame integrated or dropped (not just dequeued)
            return all(c["integrated"] + sum(c["dropped"].values()) >= c["received"]
                       for c in run.node.ingest.ledger.counters().values())

        t0 = time.monotonic()
        wait_for(all_accounted, 120, "every frame to be integrated")
        print(f"\nintegration finished {time.monotonic() - t0:.1f} s after the stream ended")
        integrated = {s: c["integrated"] for s, c in run.node.ingest.ledger.counters().items()}
        # Frames not bracketed by received poses (the first and last of a short best-effort stream,
        # more under CPU load) are dropped by design as pose_gap / pose_timeout.
        counters = run.node.ingest.ledger.counters()
        assert integrated["tof"] >= 0.6 * n_tof and integrated["stereo"] >= 0.6 * n_stereo, str(counters)
        # One more mesh update after the last integration, then wait for it to arrive.
        run.node.publish_mesh()
        wait_for(lambda: collector.keys() and collector.keys() == {
            k for k in _marker_keys(run.node)}, 60, "the mesh to arrive")
        points = collector.points()
        assert len(points) > 1000
        visible = _visible_gt(gt.vertices, seq)
        m = mesh_metrics(points, visible, tau_m=0.08)
        # Threshold: 4 cm voxels and untrained/noisy inputs put vertices up to ~1 voxel off the
        # surface, so tau = 2 voxels; a mesh of the scene scores well above 40 % on the visible
        # part, while a mesh in the wrong frame or place (pose/K/stamp mix-ups) scores near 0.
        assert m["F"] > 40.0, m
        print(f"\nstreamed mesh vs visible GT (tau 8 cm): {m}; counters: {run.node.ingest.ledger.counters()}")

        # ~/weights: the contract's fields, and each voxel's own values. The stream is over, and the
        # weighting net now judges what is still stale (else the mesh timer's budgeted refreshes, on
        # a loaded machine, re-judge it between the cloud and the check): the map stands still, and
        # a cloud published now holds, point for point, what the engine holds.
        run.node.engine.refresh_alpha()
        sent = len(clouds)
        run.node.publish_mesh(weights=True)
        wait_for(lambda: len(clouds) > sent and clouds[-1].width > 0, 30, "a weights cloud of the map")
        cloud = clouds[-1]
        assert [f.name for f in cloud.fields] == ["x", "y", "z", "alpha", "weight_tof", "weight_stereo"]
        assert all(f.datatype == PointField_FLOAT32 for f in cloud.fields)
        assert cloud.header.frame_id == "map" and cloud.width > 0
        table = np.frombuffer(bytes(cloud.data), "<f4").reshape(cloud.width, 6)
        voxel_m = E2E_PARAMS["voxel_size_m"]
        voxels = np.round(table[:, :3] / voxel_m).astype(np.int64)
        np.testing.assert_allclose(table[:, :3], voxels * voxel_m, atol=1e-4)  # voxel centres, metres
        engine_cloud = weight_cloud(run.node.engine, refresh_alpha=False)
        expected = {tuple(v): (a, *w) for v, a, w in zip(
            np.round(engine_cloud.positions_m / voxel_m).astype(np.int64).tolist(), engine_cloud.alpha.tolist(),
            engine_cloud.weights.tolist())}
        rows = [expected.get(tuple(v)) for v in voxels.tolist()]
        assert all(row is not None for row in rows), "cloud points the engine does not hold"
        rows_array = np.array(rows, np.float32)
        np.testing.assert_allclose(table[:, 3], rows_array[:, 0], atol=1e-3)  # alpha
        np.testing.assert_array_equal(table[:, 4:], rows_array[:, 1:])  # weight_tof, weight_stereo
        assert np.any(table[:, 4] != table[:, 5])  # the two sensors' columns differ somewhere

        # a late subscriber gets the whole mesh
        late_node = Node("late_subscriber", namespace="e2e")
        run.executor.add_node(late_node)
        late = MeshCollector(late_node, f"{run.prefix}/mesh")
        wait_for(lambda: late.keys() == collector.keys(), 30, "the late subscriber's full mesh")

        # ~/save_mesh writes fused, per-sensor and baseline PLY files
        response = run.call("save_mesh")
        assert response.success, response.message
        out = tmp_path / "out"
        for name in ("mesh", "tof", "stereo", "tsdf_fusion"):
            assert read_ply(out / f"{name}.ply").n_faces > 0, name

        # ~/reset empties the mesh in every subscriber
        response = run.call("reset")
        assert response.success, response.message
        wait_for(lambda: not collector.keys() and not late.keys(), 30, "the mesh to be cleared")
        assert collector.delete_alls >= 1
    finally:
        if child is not None and child.is_alive():  # a failed handshake: do not leave it waiting
            child.terminate()
            child.join(timeout=10)
        run.close()
        if late_node is not None:  # once the executor's thread is gone (it may be waiting on its handles)
            late_node.destroy_node()


PointField_FLOAT32 = 7


def _node_hears_streamer(node: FusionNode, prefix: str) -> bool:
    """Every reader of the node on the streamer's topics counts a matched writer, and each sensor's
    camera_info and a pose reached the node's message handling."""
    readers = [sub for sub in node.subscriptions if sub.topic_name.startswith(f"/{prefix}/")]
    if not readers or any(sub.get_publisher_count() == 0 for sub in readers):
        return False
    counters = node.ingest.ledger.counters()
    return all(counters[s]["pose_received"] > 0 and node.ingest._sensors[s].camera_info is not None
               for s in ("tof", "stereo"))


def _settled_counters(node: FusionNode, quiet_s: float = 1.0, timeout_s: float = 30.0) -> dict[str, Any]:
    """The ingest counters once no message has arrived for quiet_s."""
    def arrivals(c: dict[str, Any]) -> tuple[int, ...]:
        return tuple(v for s in sorted(c) for v in (c[s]["received"], c[s]["color_received"], c[s]["pose_received"]))

    deadline = time.monotonic() + timeout_s
    counters = node.ingest.ledger.counters()
    while time.monotonic() < deadline:
        time.sleep(quiet_s)
        latest = node.ingest.ledger.counters()
        if arrivals(latest) == arrivals(counters):
            return latest
        counters = latest
    return counters


def _marker_keys(node: FusionNode) -> set[tuple[str, int]]:
    """The markers the node's whole mesh consists of (what a subscriber should hold)."""
    from senfunet_ros.conversions import block_marker_id

    return {block_marker_id(k) for k in node.engine.block_meshes().keys.tolist()}


def _image(t_ns: int, depth: np.ndarray, encoding: str = "32FC1") -> Image:
    h, w = depth.shape
    msg = Image(height=h, width=w, encoding=encoding, step=w * 4)
    msg.data = np.ascontiguousarray(depth, "<f4").tobytes()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
    return msg


def _pose(t_ns: int, nan: bool = False) -> PoseStamped:
    msg = PoseStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
    msg.pose.orientation.w = float("nan") if nan else 1.0
    return msg


def test_bad_inputs_are_counted_and_the_node_survives(ros, tmp_path: Path) -> None:
    prefix = "bad"
    run = Running("bad", {**topic_params(prefix), "pose_max_wait_s": 0.3, "time_jump_s": 3.0,
                          "restart_confirm_msgs": 3, "restart_confirm_s": 0.1,
                          "working_width": 0, "voxel_size_m": 0.04, "band_m": 0.4, "on_time_jump": "keep"},
                  tmp_path)
    pub_node = Node("bad_publisher")
    try:
        pubs = {(s, k): pub_node.create_publisher(t, f"/{prefix}/{s}/{k}", 50)
                for s in ("tof", "stereo")
                for k, t in (("depth", Image), ("camera_info", CameraInfo), ("pose", PoseStamped))}
        wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 20, "discovery")
        ingest = run.node.ingest

        def dropped(sensor: str, reason: str) -> int:
            return ingest.ledger.counters()[sensor]["dropped"][reason]

        def send(sensor: str, kind: str, msg: Any) -> None:
            pubs[(sensor, kind)].publish(msg)
            time.sleep(0.02)  # the best-effort reader keeps 5 messages: do not flood it

        S = 1_000_000_000
        good = np.full((32, 32), 1.5, np.float32)
        info = CameraInfo(width=32, height=32, k=[30.0, 0, 15.5, 0, 30.0, 15.5, 0, 0, 1])

        # missing camera_info: stereo has none, and its stream time moves on past pose_max_wait_s
        send("stereo", "depth", _image(1 * S, good))
        send("stereo", "pose", _pose(2 * S))
        wait_for(lambda: dropped("stereo", "no_camera_info") >= 1, 10, "no_camera_info")

        send("tof", "camera_info", info)
        wait_for(lambda: ingest._sensors["tof"].camera_info is not None, 10, "camera_info")
        checks = [
            ("bad_encoding", _image(2 * S, good, encoding="bgr8")),
            ("size_mismatch", _image(3 * S, np.ones((16, 32), np.float32))),
            ("all_invalid", _image(4 * S, np.full((32, 32), np.nan, np.float32))),
        ]
        for reason, msg in checks:
            send("tof", "depth", msg)
            wait_for(lambda r=reason: dropped("tof", r) >= 1, 10, reason)

        send("tof", "pose", _pose(5 * S, nan=True))
        wait_for(lambda: dropped("tof", "bad_pose") >= 1, 10, "bad_pose")

        # out-of-order and duplicate stamps
        send("tof", "depth", _image(6 * S, good))
        send("tof", "depth", _image(6 * S, good))
        send("tof", "depth", _image(3 * S + S // 2, good))  # older than the two newest (4 s, 6 s)
        wait_for(lambda: dropped("tof", "duplicate") >= 1 and dropped("tof", "out_of_order") >= 1, 10,
                 "duplicate and out_of_order")

        # no pose stream: the frame at 6 s times out once stream time passes 6.3 s
        send("tof", "depth", _image(7 * S, good))
        wait_for(lambda: dropped("tof", "pose_timeout") >= 1, 10, "pose_timeout")

        # one stray stamp is dropped, it is no time jump
        send("tof", "depth", _image(1 * S, good))
        wait_for(lambda: dropped("tof", "bad_stamp") >= 1, 10, "bad_stamp")
        assert ingest.ledger.counters()["tof"]["time_jumps"] == 0

        # time going back on every stream that speaks (a bag restarting): confirmed after 3 messages each
        for k in range(1, 5):
            send("tof", "pose", _pose(1 * S + k * S // 20))
            send("tof", "depth", _image(1 * S + k * S // 20 + 1, good))
        wait_for(lambda: ingest.ledger.counters()["tof"]["time_jumps"] >= 1, 10, "time jump")
        wait_for(lambda: run.node.pipeline.time_jumps >= 1, 10, "the node to handle the time jump")

        # still alive: a good frame with poses around it is integrated
        send("tof", "pose", _pose(1 * S + S // 3))
        send("tof", "pose", _pose(1 * S + S // 2))
        send("tof", "depth", _image(1 * S + S * 4 // 10, good))
        send("tof", "pose", _pose(1 * S + S * 6 // 10))
        wait_for(lambda: ingest.ledger.counters()["tof"]["integrated"] >= 1, 30, "a good frame to be integrated")
        assert run.thread.is_alive()
        status = run.node.status()
        names = [s.name for s in status.status]
        assert "senfunet: tof" in names and "senfunet: pipeline" in names
        tof = {kv.key: kv.value for kv in status.status[names.index("senfunet: tof")].values}
        assert int(tof["dropped.bad_encoding"]) >= 1 and int(tof["integrated"]) >= 1
        assert "32FC1" in tof["error.bad_encoding"] and "32x16" in tof["error.size_mismatch"]  # what to fix
    finally:
        pub_node.destroy_node()
        run.close()


def test_publish_serialized_delivers_the_same_message(ros) -> None:
    """The node publishes its big messages with dds.publish_serialized (no GIL, no copy): a
    subscriber receives exactly the message the CDR bytes encode."""
    from rclpy.serialization import deserialize_message

    from senfunet_core.mesher import Mesh
    from senfunet_ros import conversions as conv
    from senfunet_ros.dds import publish_serialized

    node = Node("publish_serialized_test")
    try:
        qos = QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        publisher = node.create_publisher(MarkerArray, "/serialized_test/mesh", qos)
        received: list[MarkerArray] = []
        node.create_subscription(MarkerArray, "/serialized_test/mesh", received.append, qos)
        rng = np.random.default_rng(1)
        meshes = {(i, -i, 2000 * i): Mesh(rng.random((30, 3), np.float32), rng.integers(0, 30, (40, 3)),
                                          rng.random((30, 3), np.float32)) for i in range(50)}
        data = conv.marker_array_cdr(meshes, [(1, 2, 3)], stamp_ns=7, frame_id="map", as_array=True)
        publish_serialized(publisher, data)
        deadline = time.monotonic() + 10
        while not received and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
        assert received and received[0] == deserialize_message(data.tobytes(), MarkerArray)
        assert len(received[0].markers) == 51 and len(received[0].markers[1].points) == 120
    finally:
        node.destroy_node()


def test_the_mesh_timer_runs_the_mesh_update_on_a_thread_of_lower_priority(ros, tmp_path: Path, monkeypatch) -> None:
    """Frames come first: the mesh timer's update runs on its own thread, MESH_THREAD_NICE below the
    threads that integrate; an update longer than the mesh period is followed at once by the next
    (not at the tick after: that would stretch the refresh to two periods)."""
    import os
    import sys

    from senfunet_ros import node as node_module
    from senfunet_ros.mesh_publisher import mesh_period_s

    running = Running("mesh_priority", topic_params("mesh_priority"), tmp_path)
    try:
        period_s = mesh_period_s(running.node.settings.mesh_rate_hz)
        seen: list[tuple[int, int, float]] = []

        def publish(weights: bool | None = None) -> None:
            thread = threading.get_native_id()
            seen.append((thread, os.getpriority(os.PRIO_PROCESS, thread), time.monotonic()))
            time.sleep(1.3 * period_s)

        monkeypatch.setattr(running.node, "publish_mesh", publish)
        wait_for(lambda: len(seen) >= 4, 20 * period_s, "four mesh updates")
        mesh_threads = {thread for thread, _, _ in seen}
        assert len(mesh_threads) == 1 and threading.get_native_id() not in mesh_threads
        if sys.platform.startswith("linux"):
            here = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
            low = min(here + node_module.MESH_THREAD_NICE, 19)
            assert {nice for _, nice, _ in seen} == {low}
            # the alpha threads too, even when a thread of normal priority (here, this one; in the node, a
            # ~/save_mesh call before the first update) is the first to need them
            alpha = running.node.pipeline.engine.alpha
            alpha.stop_workers()

            def own_nice() -> int:
                return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

            assert {alpha.workers().submit(own_nice).result() for _ in range(alpha.threads)} == {low}
        starts = [t for _, _, t in seen]
        assert float(np.median(np.diff(starts))) < 1.6 * period_s
    finally:
        running.close()


def test_no_mesh_update_starts_once_the_mesh_worker_shuts_down() -> None:
    """`MeshWorker.shutdown` (the node being destroyed): the update under way finishes and none starts
    after it, though a tick came during it. A node destroyed while its context is still up (tests, a
    process spinning nodes in turn) ran one more whole update, and its net's turn, first."""
    from senfunet_ros.mesh_publisher import MeshWorker

    started, release, shutting_down = threading.Event(), threading.Event(), threading.Event()
    updates: list[int] = []

    def update() -> None:
        updates.append(threading.get_ident())
        started.set()
        release.wait(30)

    worker = MeshWorker(update, keep_going=lambda: True, thread_setup=lambda: None, warn=lambda key, text: None)
    pool_shutdown = worker._pool.shutdown

    def watched_pool_shutdown(*args: Any, **kwargs: Any) -> None:
        shutting_down.set()  # shutdown() was called: from here on no update may start
        pool_shutdown(*args, **kwargs)

    worker._pool.shutdown = watched_pool_shutdown
    worker.tick()
    assert started.wait(30)
    worker.tick()  # during the update: the next one is due
    stopper = threading.Thread(target=worker.shutdown)
    stopper.start()
    try:
        assert shutting_down.wait(30)
    finally:
        release.set()
        stopper.join(30)
    assert not stopper.is_alive() and len(updates) == 1


def test_limit_malloc_applies_on_glibc() -> None:
    import platform

    from senfunet_ros.node import limit_malloc

    assert limit_malloc() == (platform.libc_ver()[0] == "glibc")


def test_prepare_process_shortens_the_gil_switch_interval() -> None:
    import sys

    from senfunet_ros.node import GIL_SWITCH_INTERVAL_S, prepare_process

    before = sys.getswitchinterval()
    sys.setswitchinterval(0.005)
    try:
        prepare_process()
        assert sys.getswitchinterval() == pytest.approx(GIL_SWITCH_INTERVAL_S)
    finally:
        sys.setswitchinterval(before)


@pytest.mark.parametrize("user_policy", [None, "ACTIVE"])
def test_prepare_process_makes_openmp_threads_sleep_unless_the_user_chose(user_policy: str | None) -> None:
    """In a fresh interpreter (OpenMP reads the policy once, when torch loads): the node's process
    preparation sets OMP_WAIT_POLICY=PASSIVE before torch is imported, and keeps a policy the user set."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if user_policy:
        env["OMP_WAIT_POLICY"] = user_policy
    code = ("import os, sys; from senfunet_ros.node import prepare_process; prepare_process(); "
            "assert 'torch' not in sys.modules; import torch; print(os.environ['OMP_WAIT_POLICY'])")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == (user_policy or "PASSIVE")


def test_every_drop_reason_has_a_hint_naming_what_to_check() -> None:
    from senfunet_ros.ingest import DROP_REASONS
    from senfunet_ros.status import DROP_HINTS
    from senfunet_ros.params import SensorSettings

    sensor = SensorSettings("tof", "/robot/tof/depth", "", "/robot/tof/info", "/robot/tof/pose", 0.1, 3.0)
    assert set(DROP_HINTS) == set(DROP_REASONS)
    hints = {reason: hint.format(s=sensor) for reason, hint in DROP_HINTS.items()}
    assert "/robot/tof/info" in hints["no_camera_info"] and "tof.camera_info_topic" in hints["no_camera_info"]
    assert "/robot/tof/pose" in hints["pose_timeout"] and "/robot/tof/depth" in hints["out_of_order"]


def test_counter_warnings_name_what_is_new_and_why_colour_is_missing() -> None:
    """Frames integrated without colour: because the colour images cannot be decoded, because the
    colour stream stopped, or because none came near their stamps; the warning says which (raising a
    tolerance cannot fix the first two)."""
    from senfunet_ros.ingest import Ingest, IngestConfig
    from senfunet_ros.status import counter_warnings

    settings = P.Settings.from_values({name: default for name, (default, _) in P.expanded_defaults().items()})
    before = Ingest(IngestConfig(sensors=settings.sensor_names)).ledger.counters()
    now = {name: {**c, "dropped": dict(c["dropped"]), "errors": dict(c["errors"])} for name, c in before.items()}
    now["stereo"]["without_color"] = 3
    warnings = dict(counter_warnings(before, now, settings))  # no colour image came meanwhile: it stopped
    assert list(warnings) == [("stereo", "without_color")]
    assert "stream stopped" in warnings[("stereo", "without_color")]
    now["stereo"]["color_received"] = 5  # colour comes, but not near the depth stamps
    warnings = dict(counter_warnings(before, now, settings))
    assert "color_tolerance_s" in warnings[("stereo", "without_color")]
    assert "stream stopped" not in warnings[("stereo", "without_color")]
    now["stereo"]["dropped"]["bad_encoding"] = 3
    now["stereo"]["errors"]["bad_encoding"] = "colour: colour encoding 'yuv422' is not supported"
    warnings = dict(counter_warnings(before, now, settings))
    assert set(warnings) == {("stereo", "without_color"), ("stereo", "bad_encoding")}
    without_color = warnings[("stereo", "without_color")]
    assert "cannot be decoded" in without_color and "yuv422" in without_color
    assert "color_tolerance_s" not in without_color
    assert counter_warnings(now, now, settings) == []  # nothing new


def test_latency_is_counted_per_frame_from_its_arrival_to_the_update_that_publishes_it(monkeypatch) -> None:
    """The node's frame-to-mesh latency: each integrated frame counts once, from its arrival to the
    publication of the first update begun after it was integrated; the median is over frames (an
    update holding many frames weighs more than one holding few); frames that had been set aside
    while integration was behind are kept apart."""
    import senfunet_ros.node as node_module
    from senfunet_ros.node import LatencyStats

    from types import SimpleNamespace

    clock = SimpleNamespace(now_s=0.0)
    monkeypatch.setattr(node_module, "time", SimpleNamespace(monotonic=lambda: clock.now_s))
    latency = LatencyStats()
    for arrival in (0.1, 0.2, 0.3):
        latency.integrated(arrival)
    contained = latency.take()
    latency.integrated(0.9)  # integrated while the update runs: the next update's
    latency.integrated(0.05, set_aside=True)
    clock.now_s = 1.0
    latency.published(contained)
    latency.published(latency.take())
    assert np.allclose(list(latency.frames_s), [0.9, 0.8, 0.7, 0.1])
    assert np.allclose(list(latency.set_aside_s), [0.95])
    summary = latency.summary()
    assert summary["latency_median_s"] == pytest.approx(0.75) and summary["latency_max_s"] == pytest.approx(0.9)


def test_the_weighting_net_turn_leaves_the_mesh_period_to_the_next_update(ros, tmp_path: Path) -> None:
    """While frames come, the weighting net gets alpha_budget_s after a mesh update, but no more
    than what is left of the mesh period, so that the mesh refresh rate holds, and no less than
    MIN_TURN_S (or the budget, if less), so that it never stops while the sensors stream; with budget
    0 (no limit) it judges everything."""
    run = Running("turn", {**topic_params("turn"), "alpha_budget_s": 0.3, "mesh_rate_hz": 1.0}, tmp_path)
    try:
        budgets: list[float | None] = []
        run.node.engine.refresh_alpha = lambda budget_s=None, until_frame=False: budgets.append(budget_s)
        for left_s in (0.9, 0.1, 0.0, -0.2):
            run.node.mesh_publisher.weighting_net_turn(idle=False, period_left_s=left_s)
        assert budgets == pytest.approx([0.3, 0.1, MIN_TURN_S, MIN_TURN_S])
        run.node.set_parameters([Parameter("alpha_budget_s", value=0.01)])  # below MIN_TURN_S: the budget
        run.node.mesh_publisher.weighting_net_turn(idle=False, period_left_s=-0.2)
        run.node.set_parameters([Parameter("alpha_budget_s", value=0.0)])
        run.node.mesh_publisher.weighting_net_turn(idle=False, period_left_s=-0.2)
        assert budgets[4:] == [0.01, None]
    finally:
        run.close()


def test_stop_executor_waits_for_the_callbacks_under_way(ros) -> None:
    """Nodes are destroyed after their executor stopped: `stop_executor` returns only once the
    callbacks it was running have ended (rclpy's own shutdown returned while they ran on)."""
    node = Node("stop_executor_test")
    started, ended = threading.Event(), threading.Event()

    def slow() -> None:
        started.set()
        time.sleep(1.0)
        ended.set()

    node.create_timer(0.01, slow)
    executor = MultiThreadedExecutor(num_threads=2)
    executor.add_node(node)
    spinning = SpinThread(executor)
    try:
        assert started.wait(10)
        spinning.stop()
        assert ended.is_set() and not spinning.thread.is_alive()
    finally:
        node.destroy_node()


def _engine_stat(msg: Any, key: str) -> str | None:
    for status in msg.status:
        for kv in status.values:
            if kv.key == key:
                return kv.value
    return None


def test_status_shows_the_engine_statistics_of_now_though_the_map_is_always_held(tmp_path: Path, monkeypatch,
                                                                                 ros_domain_id: int) -> None:
    """Under a map bound, mesh updates, evictions and the weighting net's turns hold the map one after
    the other; the status timer, which does not wait for it, found it held at every tick and showed the
    first statistics all run (a 170 s bounded run over DDS: engine.stats.evicted_blocks 0 beside
    engine.counters.evicted_blocks 62405). The mesh thread now takes them after publishing when due."""
    from senfunet_ros import status

    monkeypatch.setattr(status, "ENGINE_STATS_PERIOD_S", 0.0)  # due at every look
    context = rclpy.Context()  # a context of its own: the node is destroyed with it
    rclpy.init(context=context, domain_id=ros_domain_id)
    node = FusionNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in {
        **topic_params("stats"), "weights": "none", "output_dir": str(tmp_path), "max_map_blocks": 1}.items()])
    try:
        engine = node.engine
        assert _engine_stat(node.status(), "engine.stats.frames_integrated.tof") == "0"  # the first statistics
        K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
        engine.integrate("tof", np.full((48, 64), 1.0, np.float32), K, np.eye(4))
        node.publish_mesh()
        held, release = threading.Event(), threading.Event()

        def hold_the_map() -> None:  # the next update, eviction or turn
            with engine.update_lock.held():
                held.set()
                release.wait(30)

        holder = threading.Thread(target=hold_the_map)
        holder.start()
        try:
            assert held.wait(30)
            msg = node.status()
        finally:
            release.set()
            holder.join(30)
        assert _engine_stat(msg, "engine.stats.frames_integrated.tof") == "1"
        assert int(_engine_stat(msg, "engine.stats.evicted_blocks") or 0) > 0
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)


def test_status_shows_a_reset_or_loaded_maps_statistics_at_once(tmp_path: Path, ros_domain_id: int) -> None:
    """The engine's statistics are taken at most every few seconds: after ~/reset or ~/load_map,
    ~/status went on showing the old map's blocks and frames until they were due again."""
    from types import SimpleNamespace

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=ros_domain_id)
    node = FusionNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in {
        **topic_params("new_map"), "weights": "none", "output_dir": str(tmp_path)}.items()])
    try:
        K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
        assert _engine_stat(node.status(), "engine.stats.frames_integrated.tof") == "0"  # taken now, due in seconds
        node.map_services.save_map(None, SimpleNamespace(success=None, message=None))  # an empty map
        node.engine.integrate("tof", np.full((48, 64), 1.0, np.float32), K, np.eye(4))
        node.map_services.reset(None, SimpleNamespace(success=None, message=None))
        node.engine.integrate("tof", np.full((48, 64), 1.0, np.float32), K, np.eye(4))
        msg = node.status()
        assert _engine_stat(msg, "engine.stats.frames_integrated.tof") == "1"
        assert int(_engine_stat(msg, "engine.stats.blocks") or 0) > 0
        reply = node.map_services.load_map(None, SimpleNamespace(success=None, message=None))
        assert reply.success, reply.message
        msg = node.status()
        assert _engine_stat(msg, "engine.stats.frames_integrated.tof") == "0"
        assert _engine_stat(msg, "engine.stats.blocks") == "0"
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)


def test_a_due_weights_cloud_is_skipped_while_the_previous_one_is_built() -> None:
    """`CloudWorker`: a request returns at once while the cloud is built on the weights thread; a due
    request meanwhile is skipped, a forced one is built once the one under way ends."""
    from senfunet_ros.mesh_publisher import CloudWorker

    started, release = threading.Event(), threading.Event()
    built: list[tuple[str, int]] = []

    def build(job: str) -> None:
        built.append((job, threading.get_ident()))
        started.set()
        release.wait(30)

    worker = CloudWorker(build, keep_going=lambda: True, thread_setup=None, warn=lambda key, text: None)
    try:
        assert worker.request("first")
        assert started.wait(30)  # building, and request returned without waiting for it
        assert not worker.request("due")
        assert not worker.request("forced", force=True)
        assert worker.skipped == 1
        release.set()
    finally:
        release.set()
        worker.shutdown()
    assert [job for job, _ in built] == ["first", "forced"]
    assert all(ident != threading.get_ident() for _, ident in built)


def test_mesh_updates_go_on_while_a_weights_cloud_is_built(ros, tmp_path: Path, monkeypatch) -> None:
    """With a ~/weights subscriber, a mesh update does not wait for the cloud: it is built (the readout
    held here until the test lets it go) on the weights thread while updates are published."""
    from senfunet_core import readout

    run = Running("wstall", {**E2E_PARAMS, **topic_params("wstall")}, tmp_path)
    try:
        clouds: list[PointCloud2] = []
        run.helper.create_subscription(PointCloud2, f"{run.prefix}/weights", clouds.append,
                                       QoSProfile(depth=2, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        wait_for(lambda: run.node.mesh_publisher.weights_pub.get_subscription_count() > 0, 30,
                 "the weights subscriber to match")
        started, release = threading.Event(), threading.Event()
        real = readout.weight_cloud

        def held_cloud(*args: Any, **kwargs: Any) -> Any:
            started.set()
            release.wait(60)
            return real(*args, **kwargs)

        monkeypatch.setattr(readout, "weight_cloud", held_cloud)
        updates_before = run.node.timings["update"].count
        updater = threading.Thread(target=lambda: [run.node.publish_mesh(weights=True) for _ in range(2)])
        updater.start()
        try:
            assert started.wait(60), "no weights cloud was started"
            updater.join(timeout=120)  # a guard against a deadlock, not a timing
            assert not updater.is_alive(), "the mesh updates waited for the weights cloud"
        finally:
            release.set()
            updater.join(timeout=120)
        assert run.node.timings["update"].count >= updates_before + 2
        wait_for(lambda: len(clouds) >= 2, 60, "the held cloud and the forced one after it")
        assert [f.name for f in clouds[-1].fields] == ["x", "y", "z", "alpha", "weight_tof", "weight_stereo"]
    finally:
        run.close()
