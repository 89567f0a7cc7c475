"""The live fusion node: subscriptions enqueue, timers integrate and publish.

Constructed in one order: parameters, engine, subscriptions, timers, publishers, services.
Callbacks only hand messages to `Ingest` (bounded queues); the integration timer drains them
into the engine, oldest first; the slower mesh timer runs `engine.update()`, publishes the
changed blocks, then gives the weighting net its time budget (`engine.refresh_alpha`). Each
timer has its own callback group under a MultiThreadedExecutor, and the engine is thread-safe,
so integration and mesh updates run at the same time on two cores. No callback raises: failures
are counted and logged, throttled per cause.

Topics (see ../shared/DESIGN.md, the interface contract):
  in:  /<s>/depth, /<s>/color, /<s>/camera_info, /<s>/pose    (names from parameters)
  out: ~/mesh (MarkerArray, transient local), ~/weights (PointCloud2), ~/status (DiagnosticArray)
  srv: ~/save_mesh, ~/reset (std_srvs/Trigger)
"""
from __future__ import annotations

import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from senfunet_ros import conversions as conv
from senfunet_ros import params as P
from senfunet_ros.bagio import message_class
from senfunet_ros.conversions import PoseType
from senfunet_ros.dds import publish_serialized
from senfunet_ros.ingest import DROP_REASONS, Frame, Ingest, TimeJump, integrate_ready

__all__ = ["FusionNode", "main"]

_WARN_PERIOD_S = 5.0  # one warning per cause per this many seconds
_INTEGRATE_SLICE_S = 0.5  # an integration tick returns after this long, so the executor stays responsive

# Best effort + volatile subscriptions match both reliable and best-effort publishers (and
# volatile or transient-local ones); keep-last bounds what piles up if a callback lags.
# Depth 30 (~1-2 s of images, ~8 MB of 256x256 float depth): executor threads can be held up by
# the GIL during a mesh update, and a shallow reader queue then silently overwrites frames.
_SENSOR_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=30, reliability=ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.VOLATILE)
# Poses come at ~100 Hz: 1000 is 10 s, so a busy executor that takes them late loses none.
_POSE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT,
                       durability=DurabilityPolicy.VOLATILE)
# The map: reliable and kept for late subscribers. Depth > 1 so a burst (delta then snapshot) is
# not overwritten before a slow reader acknowledged it.
_MESH_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)
_NO_WAIT = Duration(seconds=0)
_PARTS_ACK_TIMEOUT_S = 1.0  # a stuck reader delays the later parts of one update at most this, in all
_CLOUD_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
_STATUS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)

# What a drop usually means and what to check, for the reasons whose message gives no detail of
# its own ({s}: the sensor's SensorSettings).
DROP_HINTS: dict[str, str] = {
    "no_camera_info": "no CameraInfo arrived on {s.camera_info_topic} within pose_max_wait_s of the image; check "
                      "the topic (parameter {s.name}.camera_info_topic) and that its publisher sends more than once",
    "bad_camera_info": "the CameraInfo on {s.camera_info_topic} has no usable K, width or height",
    "bad_encoding": "publish depth on {s.depth_topic} as 32FC1 (metres) or 16UC1 (millimetres)",
    "size_mismatch": "the depth images on {s.depth_topic} differ in size from the CameraInfo on {s.camera_info_topic}",
    "all_invalid": "every pixel of the depth image was 0, negative, NaN or inf",
    "bad_pose": "a pose on {s.pose_topic} had NaN/inf or a quaternion of length other than 1",
    "pose_timeout": "no pose on {s.pose_topic} at or after the image's stamp within pose_max_wait_s; check that "
                    "poses arrive and are stamped on the depth images' clock",
    "pose_gap": "the poses around the image's stamp are more than pose_tolerance_s from it; publish poses more "
                "often or raise pose_tolerance_s",
    "queue_full": "more than queue_size images waited for their poses; the oldest went",
    "behind": "integration cannot keep up with the sensors; images more than max_lag_s behind the newest are "
              "skipped (a smaller working_width or a lower sensor rate helps)",
    "out_of_order": "a depth stamp on {s.depth_topic} went back in time",
    "duplicate": "a depth stamp on {s.depth_topic} came twice",
    "time_jump": "time jumped back (a bag restarting?); the queued images were flushed",
    "engine_error": "the engine rejected the frame (the warning before says why)",
}


class _Timing:
    """Last, exponentially averaged (milliseconds) and summed (seconds) duration of one stage."""

    def __init__(self) -> None:
        self.last_ms = 0.0
        self.mean_ms = 0.0
        self.count = 0
        self.total_s = 0.0

    def add(self, seconds: float) -> None:
        ms = seconds * 1e3
        self.last_ms = ms
        self.mean_ms = ms if self.count == 0 else 0.9 * self.mean_ms + 0.1 * ms
        self.count += 1
        self.total_s += seconds


class LatencyStats:
    """Frame-to-mesh latency (arrival of a depth image -> publication of the first mesh update
    that began after it was integrated) and the interval between mesh updates, in seconds."""

    def __init__(self, history: int = 1000) -> None:
        self._lock = threading.Lock()
        self._arrivals: list[float] = []  # frames integrated since the last take()
        self.updates: deque[tuple[float, float, float, int]] = deque(maxlen=history)  # (time, max, mean, frames)

    def integrated(self, arrival_s: float) -> None:
        with self._lock:
            if len(self._arrivals) < 100_000:
                self._arrivals.append(arrival_s)

    def take(self) -> list[float]:
        with self._lock:
            taken, self._arrivals = self._arrivals, []
        return taken

    def published(self, arrivals: list[float]) -> None:
        now = time.monotonic()
        if arrivals:
            self.updates.append((now, now - min(arrivals), now - sum(arrivals) / len(arrivals), len(arrivals)))
        else:
            self.updates.append((now, 0.0, 0.0, 0))

    def summary(self) -> dict[str, float]:
        """Last and worst latency over the kept history, and the longest interval between updates."""
        updates = list(self.updates)
        with_frames = [u for u in updates if u[3]]
        intervals = [b[0] - a[0] for a, b in zip(updates, updates[1:])]
        return {"latency_last_s": with_frames[-1][1] if with_frames else 0.0,
                "latency_max_s": max((u[1] for u in with_frames), default=0.0),
                "update_interval_max_s": max(intervals, default=0.0)}


class FusionNode(Node):
    """SenFuNet as a ROS 2 node. See the module docstring for its interface."""

    def __init__(self, node_name: str = P.NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._warned_at: dict[tuple[str, ...], float] = {}
        self._warn_lock = threading.Lock()
        # 1. parameters
        self.settings = P.declare(self)
        self._log_parameters()
        # 2. engine and ingest (the engine is thread-safe: integration and mesh updates overlap)
        self.engine = self._make_engine()
        s = self.settings
        self.ingest = Ingest(P.ingest_config(self.settings, max_lag_s=s.max_lag_s))
        self.latest_stamp_ns = 0  # latest integrated sensor time: the stamp of every output
        self.timings = {name: _Timing() for name in ("integrate", "update", "alpha", "weights", "encode", "publish")}
        self.frames_failed = 0
        self.time_jumps = 0
        self._last_counters = self.ingest.counters()
        self._mesh_subscribers = 0
        self._next_weights_s = 0.0  # monotonic time of the next ~/weights cloud
        self._mesh_lock = threading.Lock()  # one mesh publication at a time (timer vs. reset service)
        self.latency = LatencyStats()  # frame arrival -> the mesh that contains it
        # 3. subscriptions: they only enqueue
        # Each subscription has its own mutually exclusive group: streams run in parallel, but one
        # stream's messages never overlap, so they reach Ingest in arrival order.
        self._subscriptions_keep = []
        pose_msg = message_class(PoseType(s.pose_type).msgtype)
        for sensor in s.sensors:
            name = sensor.name
            self._subscriptions_keep += [
                self.create_subscription(CameraInfo, sensor.camera_info_topic,
                                         self._guard(name, "camera_info", self.ingest.add_camera_info), _SENSOR_QOS,
                                         callback_group=MutuallyExclusiveCallbackGroup()),
                self.create_subscription(Image, sensor.depth_topic, self._guard(name, "depth", self.ingest.add_depth),
                                         _SENSOR_QOS, callback_group=MutuallyExclusiveCallbackGroup()),
                self.create_subscription(pose_msg, sensor.pose_topic, self._guard(name, "pose", self.ingest.add_pose),
                                         _POSE_QOS, callback_group=MutuallyExclusiveCallbackGroup()),
            ]
            if sensor.color_topic:
                self._subscriptions_keep.append(self.create_subscription(
                    Image, sensor.color_topic, self._guard(name, "color", self.ingest.add_color), _SENSOR_QOS,
                    callback_group=MutuallyExclusiveCallbackGroup()))
        # 4. timers, each in its own group so a long mesh update never stalls integration. They run
        # on the steady clock: with use_sim_time, /clock stops when a bag ends, and queued frames
        # must still be integrated and meshed.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._integrate_timer = self.create_timer(1.0 / s.integrate_rate_hz, self._integrate_tick, clock=steady,
                                                  callback_group=MutuallyExclusiveCallbackGroup())
        self._mesh_timer = self.create_timer(1.0 / s.mesh_rate_hz, self._mesh_tick, clock=steady,
                                             callback_group=MutuallyExclusiveCallbackGroup())
        self._status_timer = self.create_timer(1.0 / s.status_rate_hz, self._status_tick, clock=steady,
                                               callback_group=MutuallyExclusiveCallbackGroup())
        # 5. publishers
        self.mesh_pub = self.create_publisher(MarkerArray, "~/mesh", _MESH_QOS)
        self.weights_pub = self.create_publisher(PointCloud2, "~/weights", _CLOUD_QOS)
        self.status_pub = self.create_publisher(DiagnosticArray, "~/status", _STATUS_QOS)
        # 6. services
        services_group = MutuallyExclusiveCallbackGroup()
        self.create_service(Trigger, "~/save_mesh", self._save_mesh_srv, callback_group=services_group)
        self.create_service(Trigger, "~/reset", self._reset_srv, callback_group=services_group)
        self.get_logger().info(
            f"fusing {list(s.sensor_names)} into '{s.fixed_frame}' with weights: {self.engine.weights_source}")

    # -- set-up ---------------------------------------------------------------------------------

    def _log_parameters(self) -> None:
        lines = [f"  {name}: {value!r}" for name, value in self.settings.values.items()]
        use_sim_time = self.get_parameter("use_sim_time").value
        self.get_logger().info("parameters:\n" + "\n".join(lines + [f"  use_sim_time: {use_sim_time!r}"]))

    def _make_engine(self) -> Any:
        import torch  # heavy: imported when a node is made, not when this module is

        from senfunet_core.engine import SenFuNet

        if self.settings.device.startswith("cuda") and not torch.cuda.is_available():
            self.get_logger().warning(f"device '{self.settings.device}' requested but CUDA is not available: using cpu")
        weights = P.engine_weights(self.settings)
        if weights is None:
            self.get_logger().warning("parameter weights = 'none': the networks are untrained")
        engine = SenFuNet(P.engine_config(self.settings), weights=weights)
        start = time.monotonic()
        engine.warm_up()  # compile the kernels now, not in the first frame's integration
        conv.marker_array_cdr({}, (), stamp_ns=0, frame_id="")
        self.get_logger().info(f"engine kernels ready in {time.monotonic() - start:.1f} s")
        return engine

    # -- warnings -------------------------------------------------------------------------------

    def _warn(self, key: tuple[str, ...], message: str) -> None:
        """At most one warning per key per _WARN_PERIOD_S (wall time: sim time may stand still)."""
        now = time.monotonic()
        with self._warn_lock:
            if now - self._warned_at.get(key, -1e9) < _WARN_PERIOD_S:
                return
            self._warned_at[key] = now
        self.get_logger().warning(message)

    def _guard(self, sensor: str, stream: str, add: Callable[[str, Any], Any]) -> Callable[[Any], None]:
        """A subscription callback that enqueues and never raises."""

        def callback(msg: Any) -> None:
            try:
                add(sensor, msg)
            except Exception as err:  # a malformed message must not kill the executor thread
                self._warn((sensor, stream, "exception"), f"{sensor} {stream}: message ignored: {err!r}")

        return callback

    def _warn_new_drops(self) -> None:
        counters = self.ingest.counters()
        topics = {sensor.name: sensor for sensor in self.settings.sensors}
        for sensor, now in counters.items():
            before = self._last_counters.get(sensor, {}).get("dropped", {})
            for reason, count in now["dropped"].items():
                new = count - before.get(reason, 0)
                if new > 0:
                    why = now["errors"].get(reason) or DROP_HINTS[reason].format(s=topics[sensor])
                    self._warn((sensor, reason), f"{sensor}: dropped {new} message(s): {reason}: {why} "
                               f"({count} so far; see ~/status)")
        self._last_counters = counters

    # -- timers ---------------------------------------------------------------------------------

    def _integrate_tick(self) -> None:
        """Integrate ready frames one at a time, oldest first, for at most _INTEGRATE_SLICE_S (then
        the timer fires again): frames that arrive meanwhile wait in Ingest's bounded queues. The
        next frame is taken (and its feature net started) before the current one is integrated."""
        try:
            deadline = time.monotonic() + _INTEGRATE_SLICE_S

            def ready() -> Iterator[Frame | TimeJump]:
                while time.monotonic() < deadline:
                    items = self.ingest.pop_ready(max_frames=1)
                    if not items:
                        return
                    yield from items

            integrate_ready(self.engine, ready(), self._on_time_jump, self._integrated)
            self._warn_new_drops()
        except Exception as err:  # never let the timer die
            self._warn(("integrate_tick",), f"integration step failed: {err!r}")

    def _integrated(self, frame: Frame, error: Exception | None, seconds: float) -> None:
        if error is not None:  # InputError or worse: this frame is lost, the map is not
            self.frames_failed += 1
            self.ingest.mark_dropped(frame.sensor, "engine_error")
            self._warn((frame.sensor, "engine"), f"{frame.sensor}: frame at {frame.stamp_ns * 1e-9:.3f} s "
                       f"rejected by the engine: {error}")
            return
        self.timings["integrate"].add(seconds)
        self.ingest.mark_integrated(frame.sensor)
        self.latency.integrated(frame.arrival_s)
        self.latest_stamp_ns = max(self.latest_stamp_ns, frame.stamp_ns)

    def _on_time_jump(self, jump: TimeJump) -> None:
        self.time_jumps += 1
        action = self.settings.on_time_jump
        self.get_logger().warning(
            f"time jumped back on {jump.sensor} {jump.stream}: {jump.from_ns * 1e-9:.3f} s -> {jump.to_ns * 1e-9:.3f} s "
            f"(a bag restarting?); queued frames flushed, map {'reset' if action == 'reset' else 'kept'} "
            "(parameter on_time_jump)")
        if action == "reset":
            self.engine.reset()
        self.latest_stamp_ns = jump.to_ns

    def _mesh_tick(self) -> None:
        try:
            self.publish_mesh()
        except Exception as err:
            if not self.context.ok():  # shutting down: the publishers went away under this update
                return
            self._warn(("mesh_tick",), f"mesh update failed: {err!r}")

    def publish_mesh(self, weights: bool | None = None) -> None:
        """engine.update() -> ~/mesh (changed blocks, or a full snapshot for new subscribers), and
        ~/weights when it is due (every 1 / weights_rate_hz s; `weights` forces or skips it) and
        somebody listens; then the weighting net's turn (engine.refresh_alpha, within
        alpha_budget_s), after publishing: a frame's geometry is shown one alpha phase sooner
        (median latency on the large benchmark room 2.30 -> 1.85 s), and the alpha it changed
        comes with the next update."""
        s = self.settings
        with self._mesh_lock:
            start = time.perf_counter()
            now = time.monotonic()
            if weights is None:
                weights = now >= self._next_weights_s
            weights = weights and self.weights_pub.get_subscription_count() > 0
            contained = self.latency.take()  # frames integrated before this update began
            update = self.engine.update(alpha_budget_s=0.0)
            stamp_ns = self.latest_stamp_ns
            t_update = time.perf_counter()
            self.timings["update"].add(t_update - start)
            cloud = None
            if weights:
                self._next_weights_s = now + 1.0 / s.weights_rate_hz
                band = s.weights_band_m
                # alpha as the budgeted updates left it (NaN: not evaluated yet), not a full refresh
                cloud = self.engine.weight_cloud(band if band > 0 else None, refresh_alpha=False)
                self.timings["weights"].add(time.perf_counter() - t_update)
            t_cloud = time.perf_counter()
            frame_id = s.fixed_frame
            subscribers = self.mesh_pub.get_subscription_count()
            messages = None
            if subscribers > self._mesh_subscribers:
                # Someone new joined: transient local only holds the last few messages, so send it all.
                messages = conv.marker_array_messages(self.engine.block_meshes(), (), stamp_ns=stamp_ns,
                                                      frame_id=frame_id, delete_all_first=True)
            elif update.cleared or len(update.meshes) or update.removed:
                messages = conv.marker_array_messages(update.meshes, update.removed, stamp_ns=stamp_ns,
                                                      frame_id=frame_id, delete_all_first=update.cleared)
            self._mesh_subscribers = subscribers
            publish_s = 0.0  # the rest, from t_cloud on, is encoding (the parts are encoded as they are taken)
            if cloud is not None:
                cloud_data = conv.point_cloud2_cdr(cloud.positions_m, cloud.alpha, cloud.weights,
                                                   s.sensor_names, stamp_ns=stamp_ns, frame_id=frame_id)
                t_encoded = time.perf_counter()
                publish_serialized(self.weights_pub, np.frombuffer(cloud_data, np.uint8))
                publish_s += time.perf_counter() - t_encoded
            ack_deadline = time.monotonic() + _PARTS_ACK_TIMEOUT_S
            for i, data in enumerate(messages or ()):
                t_encoded = time.perf_counter()
                if i:  # the history holds 2: let readers take the previous part before it can be overwritten
                    self._wait_mesh_acked(ack_deadline)
                publish_serialized(self.mesh_pub, data)  # large: without holding the GIL
                publish_s += time.perf_counter() - t_encoded
            if messages is not None or cloud is not None:
                self.timings["encode"].add(time.perf_counter() - t_cloud - publish_s)
                self.timings["publish"].add(publish_s)
            self.latency.published(contained)
            t_alpha = time.perf_counter()
            self.engine.refresh_alpha(s.alpha_budget_s or None)
            self.timings["alpha"].add(time.perf_counter() - t_alpha)

    def _wait_mesh_acked(self, deadline: float) -> None:
        """Until every reader acknowledged ~/mesh's samples, or time.monotonic() reaches deadline.
        Polled with short sleeps, so the node's other threads run meanwhile (a blocking wait in the
        binding could hold the GIL)."""
        while not self.mesh_pub.wait_for_all_acked(_NO_WAIT) and time.monotonic() < deadline:
            time.sleep(0.002)

    def _status_tick(self) -> None:
        try:
            self.status_pub.publish(self.status())
        except Exception as err:
            self._warn(("status_tick",), f"status failed: {err!r}")

    def status(self) -> DiagnosticArray:
        """Per-sensor counters and queue depths, then the pipeline's timings."""
        msg = DiagnosticArray()
        sec, nanosec = conv.ns_to_stamp(self.latest_stamp_ns)
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        msg.header.frame_id = self.settings.fixed_frame
        hardware_id = self.get_fully_qualified_name()
        for sensor, c in self.ingest.counters().items():
            dropped = sum(c["dropped"].values())
            level = DiagnosticStatus.OK if c["integrated"] > 0 and dropped == 0 else DiagnosticStatus.WARN
            summary = f"{c['integrated']} of {c['received']} frames integrated, {dropped} messages dropped"
            values = [KeyValue(key=k, value=str(c[k])) for k in
                      ("received", "integrated", "queue_depth", "color_received", "pose_received", "time_jumps")]
            values += [KeyValue(key=f"dropped.{reason}", value=str(c["dropped"][reason])) for reason in DROP_REASONS]
            values += [KeyValue(key=f"error.{reason}", value=why) for reason, why in c["errors"].items()]
            msg.status.append(DiagnosticStatus(level=level, name=f"senfunet: {sensor}", message=summary,
                                               hardware_id=hardware_id, values=values))
        values = [KeyValue(key=f"{stage}_ms", value=f"{t.last_ms:.1f} (mean {t.mean_ms:.1f})")
                  for stage, t in self.timings.items()]
        values += [KeyValue(key=k, value=f"{v:.2f}") for k, v in self.latency.summary().items()]
        values += [KeyValue(key="alpha_backlog_blocks", value=str(self.engine.counters.get("alpha_backlog_blocks", 0))),
                   KeyValue(key="mesh_blocks", value=str(self.engine.counters.get("meshed_blocks", 0))),
                   KeyValue(key="time_jumps", value=str(self.time_jumps)),
                   KeyValue(key="frames_failed", value=str(self.frames_failed))]
        values += [KeyValue(key=f"engine.{k}_ms", value=f"{v * 1e3:.1f}")
                   for k, v in dict(getattr(self.engine, "timings_s", {})).items()]
        msg.status.append(DiagnosticStatus(level=DiagnosticStatus.OK, name="senfunet: pipeline",
                                           message=f"{self.engine.counters.get('meshed_blocks', 0)} mesh blocks", hardware_id=hardware_id,
                                           values=values))
        return msg

    # -- services -------------------------------------------------------------------------------

    def save_meshes(self, output_dir: str | Path | None = None) -> list[Path]:
        """Fused (filtered), per-sensor and TSDF Fusion meshes as PLY files; returns their paths."""
        from senfunet_core.ply import write_ply

        out = Path(output_dir or self.settings.output_dir).expanduser()
        out.mkdir(parents=True, exist_ok=True)
        names = {"fused": "mesh", **{s: s for s in self.settings.sensor_names}}
        if self.settings.tsdf_fusion:
            names["tsdf_fusion"] = "tsdf_fusion"
        meshes = {name: self.engine.extract_mesh(which) for which, name in names.items()}
        paths = []
        for name, mesh in meshes.items():
            path = out / f"{name}.ply"
            write_ply(path, mesh)
            paths.append(path)
        return paths

    def _save_mesh_srv(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            paths = self.save_meshes()
            response.success = True
            response.message = "wrote " + ", ".join(str(p) for p in paths)
            self.get_logger().info(response.message)
        except Exception as err:
            response.success = False
            response.message = f"saving failed: {err}; check parameter output_dir"
            self.get_logger().error(response.message)
        return response

    def reset_map(self) -> None:
        """Forget the map and queued frames; subscribers get a DELETEALL right away."""
        self.engine.reset()
        self.ingest.clear_frames()
        self.publish_mesh()

    def _reset_srv(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            self.reset_map()
            response.success, response.message = True, "map reset"
            self.get_logger().info("map reset by ~/reset")
        except Exception as err:
            response.success, response.message = False, f"reset failed: {err}"
            self.get_logger().error(response.message)
        return response


def spin(node: FusionNode, num_threads: int = 6) -> None:
    """Spin until shutdown; enough threads that subscriptions run while both timers are busy."""
    executor = MultiThreadedExecutor(num_threads=num_threads)
    executor.add_node(node)
    try:
        executor.spin()
    finally:
        executor.shutdown()


# Python hands the GIL to a waiting thread only every switch interval (default 5 ms). Each
# message needs several hand-overs (the executor's wait returns, a worker takes and converts it),
# so while integration and a mesh update run Python between their numpy/torch calls, a 5 ms
# interval held dispatch below the ~70 messages/s of the sample bag at the demo's rate 0.25:
# `senfunet demo` lost a third to a half of its frames (pose callbacks lagged up to 15 s, frames
# timed out waiting for them). At 0.5 ms it fuses all of them (test/ros/test_play.py).
GIL_SWITCH_INTERVAL_S = 0.0005


def prepare_process() -> None:
    """Process settings for a node with busy timers: a short GIL switch interval (see above) and
    glibc malloc limits (`limit_malloc`). Call before the executor's threads exist."""
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    limit_malloc()


def limit_malloc(arenas: int = 2, mmap_threshold_bytes: int = 4 << 20) -> bool:
    """Cap glibc's malloc arenas (default: 8 per core) for the threads started from now on, and fix
    the size from which allocations get their own mapping (returned to the OS when freed). Each
    executor, feature-net and kernel thread would otherwise keep its own heap of freed per-frame
    arrays (arenas), and glibc raises the threshold up to 32 MB after the first such array is freed,
    after which the per-update arrays of 4-32 MB stay in the heaps. Peak RSS on the large benchmark
    room: ~2.5 GB -> ~2.1 GB (arenas), -> ~1.85 GB (threshold 4 MB; at 1 MB the page faults of
    re-mapping cost a fifth of the frame rate, at 8 MB it saved less: 1.91 GB). False where there
    is no glibc (nothing changes)."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        threshold_set = libc.mallopt(-3, mmap_threshold_bytes)  # M_MMAP_THRESHOLD
        return bool(libc.mallopt(-8, arenas)) and bool(threshold_set)  # M_ARENA_MAX
    except (OSError, AttributeError):
        return False


def main(args: list[str] | None = None) -> int:
    """`ros2 run senfunet_ros fusion_node [--ros-args ...]`."""
    from senfunet_ros.dds import use_large_shm_profile

    use_large_shm_profile()  # large mesh messages; set before the participant exists
    prepare_process()  # before the executor's threads exist
    rclpy.init(args=args)
    node: FusionNode | None = None
    try:
        node = FusionNode()
        spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as err:  # bad parameters (InputError is a ValueError too): say which, no traceback
        print(f"senfunet: cannot start: {err}", flush=True)
        return 2
    finally:
        if node is not None:
            if node.settings.save_on_shutdown:
                try:
                    paths = node.save_meshes()
                    print("senfunet: saved " + ", ".join(str(p) for p in paths), flush=True)
                except Exception as err:
                    print(f"senfunet: saving on shutdown failed: {err}", flush=True)
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
