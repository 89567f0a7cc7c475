"""The live fusion node: subscriptions enqueue, timers integrate and publish.

Constructed in one order: parameters, engine, subscriptions, timers, publishers, services.
Callbacks only hand messages to `Ingest` (bounded queues); a pose (or /tf) callback also takes the
messages queued behind it on its subscription, and a depth callback its sensor's queued poses before
its image (`TakingQueued`: one taker per pose subscription at a time, under its lock, so a frame
never waits for a pose that arrived before it). The integration timer drains them
into the engine, oldest first; the slower mesh timer runs `engine.update()`, publishes the
changed blocks, then gives the weighting net its time budget (`engine.refresh_alpha`; all three
in `senfunet_ros.mesh_publisher`). Each timer has its own callback group under a
MultiThreadedExecutor; the mesh timer hands its work to a thread of its own at a lower priority
(`lower_thread_priority`), so that frames come first where the cores are short; the ~/weights cloud is
built and published on another thread at that priority (`mesh_publisher.CloudWorker`), never on the
mesh thread. The engine is
thread-safe, so integration and mesh updates run at the same time on two cores. No callback
raises: failures are counted and logged, throttled per cause.

What happens to messages, frames, time jumps, failures and files is decided by
`senfunet_ros.pipeline.Pipeline`, shared with offline replay; this module adds the clock (timers,
/clock), the transport (subscriptions, publishers, services) and run-time parameters.

Topics (see ../shared/DESIGN.md, the interface contract):
  in:  /<s>/depth, /<s>/color (raw, or CompressedImage on .../compressedDepth, .../compressed),
       /<s>/camera_info, /<s>/pose (names from parameters), or /tf + /tf_static (pose_type tf)
  out: ~/mesh (MarkerArray of the display mesh, transient local), ~/weights (PointCloud2),
       /diagnostics and ~/status (DiagnosticArray)
  srv: ~/save_mesh, ~/save_map, ~/load_map, ~/reset (std_srvs/Trigger)
"""
from __future__ import annotations

import gc
import logging
import sys
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Any
from collections.abc import Callable, Iterator, Sequence

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as RosClock
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_srvs.srv import Trigger

from senfunet_core.errors import InputError
from senfunet_ros import conversions as conv
from senfunet_ros import params as P
from senfunet_ros.bagio import message_class
from senfunet_ros.conversions import PoseType
from senfunet_ros.dds import shut_down_rclpy
from senfunet_ros.health import HealthMonitor
from senfunet_ros.ingest import Frame, Ingest, TimeJump
from senfunet_ros.map_services import MapServices, NothingToSave
from senfunet_ros.mesh_publisher import MeshPublisher, MeshWorker, mesh_period_s
from senfunet_ros.pipeline import Pipeline, Stream, TimeJumpAction
from senfunet_ros.status import CounterWarnings, StatusReport, ThrottledWarnings
from senfunet_ros.timeline import ClockTimeline

__all__ = ["FusionNode", "main"]

_WARN_PERIOD_S = 5.0  # one warning per cause per this many seconds
_MAX_WAIT_SET_RACES = 20  # entities gone while the executor built its wait set, within 1 s: not a race (`spin`)
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
_CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.BEST_EFFORT,
                        durability=DurabilityPolicy.VOLATILE)
# /tf as tf2_ros's listener subscribes to it; /tf_static latched (transient local) so mounts published
# before the node started still arrive.
_TF_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
_TF_STATIC_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
_STATUS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)

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
    that began after it was integrated) and the interval between mesh updates, in seconds. Frames
    that were set aside while integration was behind (Ingest, behind_buffer_mb) are kept apart: they
    come late by design, and the live view's latency is that of the others."""

    def __init__(self, history: int = 1000, frame_history: int = 10_000) -> None:
        self._lock = threading.Lock()
        self._arrivals: list[tuple[float, bool]] = []  # frames integrated since the last take(): (arrival, set aside)
        self.updates: deque[tuple[float, float, float, int]] = deque(maxlen=history)  # (time, max, mean, frames)
        self.frames_s: deque[float] = deque(maxlen=frame_history)  # each published frame's latency
        self.set_aside_s: deque[float] = deque(maxlen=frame_history)  # ... of frames that had been set aside

    def integrated(self, arrival_s: float, *, set_aside: bool = False) -> None:
        with self._lock:
            if len(self._arrivals) < 100_000:
                self._arrivals.append((arrival_s, set_aside))

    def pending(self) -> bool:
        """Frames integrated since the last take()."""
        with self._lock:
            return bool(self._arrivals)

    def take(self) -> list[tuple[float, bool]]:
        with self._lock:
            taken, self._arrivals = self._arrivals, []
        return taken

    def published(self, taken: list[tuple[float, bool]]) -> None:
        now = time.monotonic()
        arrivals = [arrival for arrival, set_aside in taken if not set_aside]
        self.set_aside_s.extend(now - arrival for arrival, set_aside in taken if set_aside)
        if arrivals:
            self.updates.append((now, now - min(arrivals), now - sum(arrivals) / len(arrivals), len(arrivals)))
            self.frames_s.extend(now - arrival for arrival in arrivals)
        else:
            self.updates.append((now, 0.0, 0.0, 0))

    def summary(self) -> dict[str, float]:
        """Last (the update's oldest frame), median (over frames) and worst latency over the kept
        history, and the longest interval between updates."""
        updates = list(self.updates)
        with_frames = [u for u in updates if u[3]]
        intervals = [b[0] - a[0] for a, b in zip(updates, updates[1:])]
        return {"latency_last_s": with_frames[-1][1] if with_frames else 0.0,
                "latency_median_s": float(np.median(self.frames_s)) if self.frames_s else 0.0,
                "latency_max_s": max((u[1] for u in with_frames), default=0.0),
                "update_interval_max_s": max(intervals, default=0.0)}


class _Tf2Lookup:
    """tf2_ros.Buffer behind the lookup(target, source, stamp_ns) that Ingest calls (see senfunet_ros.tf)."""

    def __init__(self, buffer: Any, tf2_ros: Any) -> None:
        self._buffer, self._tf2 = buffer, tf2_ros

    def lookup(self, target: str, source: str, stamp_ns: int) -> np.ndarray:
        from rclpy.time import Time

        from senfunet_ros.tf import TfError, TfNotConnected, TfWait

        # tf2 strips a leading '/' from the frames it is sent (a ROS 1 habit some drivers keep) but refuses
        # one in a lookup (InvalidArgumentException): strip it here too, as the node's own buffer does
        target, source = target.lstrip("/"), source.lstrip("/")
        if not source:
            raise TfError("the depth image has no header.frame_id; the driver must name its optical frame")
        try:
            tf = self._buffer.lookup_transform(target, source, Time(nanoseconds=stamp_ns))
        except self._tf2.ExtrapolationException as err:
            if "future" in str(err):  # the transform at the stamp has not arrived yet
                raise TfWait(str(err)) from None
            raise TfError(str(err)) from None
        except (self._tf2.LookupException, self._tf2.ConnectivityException) as err:
            raise TfNotConnected(str(err)) from None
        except self._tf2.TransformException as err:  # an invalid frame id, ...: this frame cannot be posed
            raise TfError(f"{type(err).__name__}: {err}") from None
        return conv.transform_from_msg(tf.transform.translation, tf.transform.rotation,
                                       f"transform {target} -> {source}")

    def newest_common_ns(self, target: str, source: str) -> int | None:
        """The stamp of the newest transform tf2 can give between the frames (its latest common time);
        None when it has none, or only static ones (a lookup then holds at any stamp)."""
        from rclpy.time import Time

        try:
            tf = self._buffer.lookup_transform(target.lstrip("/"), source.lstrip("/"), Time())
            stamp_ns = conv.stamp_to_ns(tf.header.stamp)
        except (self._tf2.TransformException, ValueError):  # no transform, or a stamp that is no time
            return None
        return stamp_ns or None

    def clear(self) -> None:
        self._buffer.clear()


class _EngineLogToRos(logging.Handler):
    """The engine's own log lines (Python logging, e.g. each map-bound eviction) in the node's log;
    once the ROS context has shut down (the node finishing its frames after Ctrl-C), on stderr: the
    ROS logger would add a "Failed to publish log message to rosout" line to each."""

    def __init__(self, ros_logger: Any, context: Any) -> None:
        super().__init__(logging.INFO)
        self._ros_logger, self._context = ros_logger, context

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        if not self._context.ok():
            print(f"senfunet: {record.levelname.lower()}: {text}", file=sys.stderr, flush=True)
        elif record.levelno >= logging.ERROR:
            self._ros_logger.error(text)
        elif record.levelno >= logging.WARNING:
            self._ros_logger.warning(text)
        else:
            self._ros_logger.info(text)


class _ClockWatch:
    """Under use_sim_time: /clock going back by more than time_jump_s is a restart (a bag looping),
    confirmed by the next /clock (`timeline.ClockTimeline`: a single stray one restarts nothing).
    /clock is subscribed while use_sim_time is true, set at start or at run time (rclpy's own
    parameter: its clock follows it at once; the watch must too, else a bag looping after
    `ros2 param set ... use_sim_time true` were recognised only from the new timeline, and after
    `false` a /clock still flushed the queues). `on_clock` runs in the subscription's callback,
    (un)subscribing in the parameter callbacks: the /clock timeline is under a lock of its own."""

    def __init__(self, node: Node, ingest: Ingest, time_jump_s: Callable[[], float],
                 warn: Callable[[tuple[str, ...], str], None]) -> None:
        self._node, self._ingest, self._time_jump_s, self._warn = node, ingest, time_jump_s, warn
        self._timeline = ClockTimeline()
        self._timeline_lock = threading.Lock()
        self._subscription: Any = None
        self.follow(bool(node.get_parameter("use_sim_time").value))

    def follow(self, on: bool) -> None:
        """Subscribe /clock (on; the /clock seen before it was dropped is no reference) or drop it."""
        if on and self._subscription is None:
            with self._timeline_lock:
                self._timeline.reset()
            self._subscription = self._node.create_subscription(
                RosClock, "/clock", self.on_clock, _CLOCK_QOS, callback_group=MutuallyExclusiveCallbackGroup())
        elif not on and self._subscription is not None:
            self._node.destroy_subscription(self._subscription)
            self._subscription = None

    def on_parameters(self, parameters: list[Parameter]) -> None:
        """A post-set parameters callback: follows use_sim_time."""
        for p in parameters:
            if p.name == "use_sim_time" and p.type_ is Parameter.Type.BOOL:
                self.follow(bool(p.value))

    def on_clock(self, msg: Any) -> None:
        try:
            now_ns = conv.stamp_to_ns(msg.clock)
            with self._timeline_lock:
                seen = self._timeline.observe(now_ns, int(self._time_jump_s() * 1e9))
            if seen is not None and seen[0] == "restart":
                self._ingest.restart(now_ns)  # the pipeline says so, once, as it handles the restart
            elif seen is not None:
                self._warn(("clock_stray",), f"/clock went back from {seen[1] * 1e-9:.3f} s to {seen[2] * 1e-9:.3f} s "
                           f"for one message, then on to {now_ns * 1e-9:.3f} s: a stray /clock (a second publisher "
                           "of /clock?), not a restart; nothing was flushed and the map is kept")
        except Exception as err:
            self._warn(("clock",), f"/clock message ignored: {err!r}")


class FusionNode(Node):
    """SenFuNet as a ROS 2 node. See the module docstring for its interface."""

    def __init__(self, node_name: str = P.NODE_NAME, *, argv: Sequence[str] = (), **kwargs: Any) -> None:
        """argv: the process's command line (`main`), whose parameter files are checked like `cli_args`'."""
        super().__init__(node_name, **kwargs)
        self._engine_log = _EngineLogToRos(self.get_logger(), self.context)
        engine_logger = logging.getLogger("senfunet")
        engine_logger.addHandler(self._engine_log)
        engine_logger.setLevel(min(engine_logger.getEffectiveLevel(), logging.INFO))
        self._warn = ThrottledWarnings(self.get_logger().warning, period_s=_WARN_PERIOD_S).warn
        # 1. parameters
        self.settings = P.declare(self)
        lines = [f"  {name}: {value!r}" for name, value in self.settings.values.items()]
        lines.append(f"  use_sim_time: {self.get_parameter('use_sim_time').value!r}")
        self.get_logger().info("parameters:\n" + "\n".join(lines))
        # rclpy ignores parameters given for the node that it never declared: a misspelt name would
        # silently leave its parameter at the default (in a section for every node, '/**', a name that is
        # no near miss of ours is another node's; a near miss comes with its suggestion, so it is warned)
        command_line = [*argv, *(kwargs.get("cli_args") or ())]
        shared = shared_file_parameters(command_line, self.get_fully_qualified_name())
        overrides = set(getattr(self, "_parameter_overrides", {}))
        for name in P.unknown_parameters(overrides, self.settings.sensor_names):
            if name in shared:
                self.get_logger().info(f"parameter {name}, from a section for every node, is another node's: ignored")
            else:
                self.get_logger().warning(f"parameter {name} is not one of this node's and is ignored; see "
                                          "config/default.yaml for the names")
        # ... and a parameter file none of whose sections reaches the node (renamed, or in a namespace)
        for problem in unread_params_files(command_line, self.get_fully_qualified_name()):
            self.get_logger().error(problem)
        for note in P.colourless_sensors(self.settings):
            self.get_logger().warning(note)
        # 2. engine and ingest (the engine is thread-safe: integration and mesh updates overlap)
        s = self.settings
        self.timings = {name: _Timing() for name in ("integrate", "update", "alpha", "weights", "encode", "publish")}
        self.latency = LatencyStats()  # frame arrival -> the mesh that contains it
        from senfunet_core.colors import ColorGrid

        self.camera_colors = ColorGrid(2 * s.voxel_size_m)  # fed only with mesh_colors: camera
        # before the heavy engine: a pose_type tf that cannot work is refused at once
        tf, self._tf_parts = make_tf(self, s, self._guard) if PoseType(s.pose_type) is PoseType.TF else (None, [])
        ingest = Ingest(P.ingest_config(self.settings, **P.live_lag(s), tf=tf))
        logger = self.get_logger()
        self.pipeline = Pipeline(make_engine(s, logger), ingest, on_time_jump=s.on_time_jump,
                                 log=lambda level, text: getattr(logger, level)(text),
                                 on_integrated=self._integrated, on_new_map=self.camera_colors.clear)
        self.ingest = self.pipeline.ingest
        self._counter_warnings = CounterWarnings(self.ingest, hold_s=_WARN_PERIOD_S)
        # 3. subscriptions: they only enqueue; the status reports their health
        self._subscriptions_keep, self.health = subscribe(self, s, callback=self._guard)
        # under use_sim_time, /clock going back is a restart: followed as use_sim_time is set, at start or later
        self._clock_watch = _ClockWatch(self, self.ingest, lambda: self.settings.time_jump_s, self._warn)
        # the names the subscriptions have, expanded in the namespace and remapped (`-r /tof/depth:=/cam/depth`): the
        # warnings name the topics to check, not the parameters' values
        topics = {sensor.name: {stream.value: topic and self.resolve_topic_name(topic)
                                for stream, _, topic, _ in sensor_streams(sensor, s.pose_type)}
                  for sensor in s.sensors}
        self._topics = topics
        self.status_report = StatusReport(self.pipeline, self.health, self.timings, self.latency, topics=topics,
                                          hardware_id=self.get_fully_qualified_name(), warn=self._warn,
                                          logger=self.get_logger(), name=self.get_name(),
                                          graph_hint=self._silent_topic_hint)
        # 4. timers, each in its own group so a long mesh update never stalls integration. They run
        # on the steady clock: with use_sim_time, /clock stops when a bag ends, and queued frames
        # must still be integrated and meshed.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._integrate_timer = self.create_timer(1.0 / s.integrate_rate_hz, self._integrate_tick, clock=steady,
                                                  callback_group=MutuallyExclusiveCallbackGroup())
        # the mesh timer's work runs on a thread of its own at a lower priority than integration's
        # (`lower_thread_priority`): where the cores cannot do both at once, frames come first, and
        # the mesh and the weighting net take the time left
        self._mesh_worker = MeshWorker(lambda: self.publish_mesh(), keep_going=self.context.ok,
                                       thread_setup=at_mesh_priority, warn=self._warn)
        self._mesh_timer = self.create_timer(mesh_period_s(s.mesh_rate_hz), self._mesh_worker.tick, clock=steady,
                                             callback_group=MutuallyExclusiveCallbackGroup())
        self._status_timer = self.create_timer(1.0 / s.status_rate_hz, self._status_tick, clock=steady,
                                               callback_group=MutuallyExclusiveCallbackGroup())
        # 5. publishers
        self.mesh_publisher = MeshPublisher(self, self.pipeline, lambda: self.settings, timings=self.timings,
                                            latency=self.latency, camera_colors=self.camera_colors,
                                            frame_waiting=lambda: any(self.ingest.ledger.queue_depths().values()),
                                            warn=self._warn, thread_setup=at_mesh_priority)
        self.status_pub = self.create_publisher(DiagnosticArray, "~/status", _STATUS_QOS)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", _STATUS_QOS)
        # 6. services
        self.map_services = MapServices(self.pipeline, lambda: self.settings, self.mesh_publisher, self.get_logger())
        services_group = MutuallyExclusiveCallbackGroup()
        for name, handler in (("save_mesh", self.map_services.save_mesh), ("save_map", self.map_services.save_map),
                              ("load_map", self.map_services.load_map), ("reset", self.map_services.reset)):
            self.create_service(Trigger, f"~/{name}", handler, callback_group=services_group)
        # 7. run-time parameter changes: checked first (a bad value is refused with the reason), then applied
        self._validated: dict[str, Any] | None = None
        self.add_pre_set_parameters_callback(
            lambda parameters: P.as_declared_types(parameters, P.param_table(self.settings.sensor_names)))
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.add_post_set_parameters_callback(self._clock_watch.on_parameters)
        # Ctrl-C / SIGTERM shut the context down while timers may be mid-frame: say so to the pipeline,
        # so what the stop interrupts is counted as such, not as an engine error
        self.context.on_shutdown(lambda: setattr(self.pipeline, "stopping", True))
        self.get_logger().info(
            f"fusing {list(s.sensor_names)} into '{s.fixed_frame}' with weights: {self.engine.weights_source}")

    # -- set-up and stop -------------------------------------------------------------------------
    def finish(self, abandon: threading.Event | None = None, *, set_aside: bool = False) -> dict[str, Any]:
        """After the executor stopped: the streams ended (`Ingest.stream_ends.end`: frames newer than
        their sensor's newest pose are posed by extrapolation within pose_tolerance_s, or dropped as
        pose_timeout); integrate the frames that are ready, and with `set_aside` (the map is saved
        next) the frames set aside, count the ones still waiting (for a camera_info, or set aside) as
        dropped at shutdown. `abandon` set (a second Ctrl-C): the frames not started yet are dropped
        too, once the frame under way is integrated.
        Returns the counts, and under "ends" the (level, line)s of `Pipeline.stream_ends` (for the
        caller to print: the node's log may be shut down)."""
        self.pipeline.stopping = True
        self.ingest.stream_ends.end()
        ready = self.ingest.pop_ready(set_aside=False) + (self.ingest.pop_set_aside() if set_aside else [])
        left: list[Frame | TimeJump] = []

        def until_abandoned() -> Iterator[Frame | TimeJump]:
            for i, item in enumerate(ready):
                if abandon is not None and abandon.is_set():
                    left.extend(ready[i:])
                    return
                yield item

        integrated = self.pipeline.drain(until_abandoned())
        for item in left:
            if isinstance(item, Frame):
                self.ingest.ledger.mark_dropped(item.sensor, "shutdown")
        waiting = self.ingest.ledger.discard_waiting("shutdown")
        return {"integrated": integrated, "discarded": waiting + sum(isinstance(item, Frame) for item in left),
                "interrupted": self.pipeline.frames_unfinished, "ends": self.pipeline.stream_ends()}

    # -- warnings -------------------------------------------------------------------------------

    def _guard(self, sensor: str, stream: Stream) -> Callable[[Any], None]:
        """A subscription callback that enqueues and never raises."""

        paired = stream in (Stream.DEPTH, Stream.CAMERA_INFO)  # health pairs their stamps

        def callback(msg: Any) -> None:
            try:
                self.health.received(sensor, stream.value, _header_stamp_ns(msg) if paired else None)
                self.pipeline.dispatch(sensor, stream, msg)
            except Exception as err:  # a malformed message must not kill the executor thread
                self._warn((sensor, stream.value, "exception"), f"{sensor} {stream.value}: message ignored: {err!r}")

        return callback

    # -- parameters at run time ------------------------------------------------------------------

    def _check_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        ours = [p for p in parameters if p.name in self.settings.values]
        reason = P.type_error(ours, P.param_table(self.settings.sensor_names))
        if reason is None:
            try:
                changes = {p.name: p.value for p in ours}
                self._validated = P.validate(self.settings.values, changes) if changes else None
                return SetParametersResult(successful=True)
            except ValueError as err:
                reason = str(err)
        self._validated = None
        for p in parameters:  # rclpy set the descriptors' types from the refused values already (dynamic typing)
            if self.has_parameter(p.name):
                self.describe_parameter(p.name).type = self.get_parameter(p.name).type_.value
        return SetParametersResult(successful=False, reason=reason)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        """Validated values (`_check_parameters`) into every part they concern."""
        values, self._validated = self._validated, None
        if values is None:
            return
        try:
            old, new = self.settings, P.Settings.from_values(values)
            self.settings = new
            for name, timer, period_s in (("integrate_rate_hz", self._integrate_timer, 1.0 / new.integrate_rate_hz),
                                          ("mesh_rate_hz", self._mesh_timer, mesh_period_s(new.mesh_rate_hz)),
                                          ("status_rate_hz", self._status_timer, 1.0 / new.status_rate_hz)):
                if getattr(new, name) != getattr(old, name):
                    set_timer_period(timer, period_s)
            tf = self.ingest.config.tf
            if hasattr(tf, "max_gap_ns"):  # our own TF buffer interpolates within pose_tolerance_s
                tf.max_gap_ns = int(new.pose_tolerance_s * 1e9)
            self.ingest.config = P.ingest_config(new, **P.live_lag(new), tf=tf)
            self.pipeline.on_time_jump = TimeJumpAction.parse(new.on_time_jump)
            self.health.window_s, self.health.stale_after_s = new.diagnostics_window_s, new.stale_after_s
            P.configure_engine(self.engine, new)
            if new.mesh_colors != old.mesh_colors or new.mesh_display_cell_m != old.mesh_display_cell_m:
                self.mesh_publisher.resend_all()  # readers get the whole map as it is now shown
            changed = sorted(name for name in values if values[name] != old.values[name])
            if changed:  # a value set again (0.0 as -0.0) changes nothing to say
                self.get_logger().info("parameters changed: " + ", ".join(f"{n} = {values[n]!r}" for n in changed))
        except Exception as err:  # a post-set callback that raises takes the executor down
            self.get_logger().error(f"parameters accepted but not all applied ({err!r}); set them again")

    # -- timers ---------------------------------------------------------------------------------

    def _integrate_tick(self) -> None:
        """Integrate ready frames one at a time, oldest first, for at most _INTEGRATE_SLICE_S (then
        the timer fires again): frames that arrive meanwhile wait in Ingest's bounded queues. The
        next frame is taken (and its feature net started) before the current one is integrated."""
        try:
            deadline = time.monotonic() + _INTEGRATE_SLICE_S
            # a sensor silent for pose_max_wait_s has ended its streams: no pose will come for what waits.
            # Its message count is read first, so that a message arriving meanwhile keeps it going
            counts = self.ingest.stream_ends.message_counts()
            quiet = self.health.quiet_sensors(self.settings.pose_max_wait_s)
            if quiet:
                self.ingest.stream_ends.end(quiet, counts=counts)

            def ready() -> Iterator[Frame | TimeJump]:
                while time.monotonic() < deadline:
                    items = self.ingest.pop_ready(max_frames=1)
                    if not items:
                        return
                    yield from items

            self.pipeline.drain(ready())
            for level, line in self.pipeline.stream_ends():
                getattr(self.get_logger(), level)(line)
            for key, message in self._counter_warnings.since_last(self.settings, self._topics):
                self._warn(key, message)
        except Exception as err:  # never let the timer die
            self._warn(("integrate_tick",), f"integration step failed: {err!r}")

    def _integrated(self, frame: Frame, seconds: float) -> None:
        self.timings["integrate"].add(seconds)
        self.latency.integrated(frame.arrival_s, set_aside=frame.set_aside)
        if frame.rgb is not None and self.settings.mesh_colors == "camera":
            from senfunet_core.colors import unproject

            points, pixels = unproject(frame.depth_m, frame.K, frame.T_world_camera)
            self.camera_colors.add(points, frame.rgb[pixels[:, 0], pixels[:, 1]])

    @property
    def engine(self) -> Any:
        """The engine (`~/load_map` replaces it)."""
        return self.pipeline.engine

    def publish_mesh(self, weights: bool | None = None) -> None:
        """What the mesh timer does, now (`MeshPublisher.publish`), then the engine's statistics for
        ~/status when due (the status timer finds the map held by the updates too often)."""
        self.mesh_publisher.publish(weights)
        self.status_report.refresh_engine_stats()

    def _status_tick(self) -> None:
        try:
            msg = self.status()
            self.status_pub.publish(msg)
            self.diagnostics_pub.publish(msg)
            if (same := namesakes(self)) > 1:
                self._warn(("namesakes",), f"{same} nodes named {self.get_fully_qualified_name()} are in the ROS "
                           "graph (a second launch?): their ~/mesh, services and parameters clash, and a client "
                           "reaches either; stop the other, or start this one under another name (--ros-args -r "
                           "__node:=NAME) or namespace")
        except Exception as err:
            if self.context.ok():  # else the node is stopping: its publishers may be gone under this tick
                self._warn(("status_tick",), f"status failed: {err!r}")

    def status(self) -> DiagnosticArray:
        """~/status and /diagnostics now (`senfunet_ros.status.StatusReport`)."""
        return self.status_report.message(self.settings.fixed_frame)

    def _silent_topic_hint(self, topic: str) -> tuple[str, bool]:
        """What the ROS graph says of a subscribed topic nothing came on: nobody publishes it, or its
        publishers' type is not the one subscribed (an amcl pose, a CompressedImage under a raw name);
        and whether its publishers are all of the subscribed type (they may not have begun yet)."""
        wanted = next((sub.msg_type for sub in self._subscriptions_keep if sub.topic_name == topic), None)
        if wanted is None:
            return "", False
        try:
            types = {info.topic_type for info in self.get_publishers_info_by_topic(topic)}
        except Exception:  # noqa: BLE001 (a graph query failing under a stop): the warning stands without it
            return "", False
        wanted_type = f"{wanted.__module__.split('.')[0]}/msg/{wanted.__name__}"
        if not types:
            return f"; nobody publishes {topic} now", False
        other = sorted(types - {wanted_type})
        if not other:  # the graph shows them, so they share the node's domain: silent, or QoS that does not match
            return (f"; it has publishers of {wanted_type}, which sent nothing the node took: they have published "
                    f"nothing yet, or their QoS does not match the subscription's (`ros2 topic info -v {topic}`)"
                    ), True
        hint = f"; it is published as {', '.join(other)}, the node subscribes {wanted_type}"
        if any(streams.get("pose") == topic for streams in self._topics.values()):
            matching = [t.value for t in PoseType if t.msgtype in other]
            hint += (f": set pose_type to {matching[0]}" if matching else
                     ": pose_type takes " + ", ".join(f"{t.value} ({t.msgtype or '/tf'})" for t in PoseType)
                     + "; republish the poses as one of those")
        return hint, False

    def destroy_node(self) -> None:
        self._mesh_timer.cancel()
        self._mesh_worker.shutdown()  # the update under way finishes while its publishers exist
        self.mesh_publisher.close()
        logging.getLogger("senfunet").removeHandler(self._engine_log)
        super().destroy_node()


def params_files(argv: Sequence[str]) -> list[str]:
    """The files of the `--params-file FILE` arguments among the ROS arguments of a command line (those
    after `--ros-args`, up to a `--`)."""
    files, in_ros_args = [], False
    for arg, following in zip(argv, [*argv[1:], None]):
        if arg in ("--ros-args", "--"):
            in_ros_args = arg == "--ros-args"
        elif in_ros_args and arg == "--params-file" and following is not None:
            files.append(following)
    return files


def unread_params_files(argv: Sequence[str], node_fqn: str) -> list[str]:
    """Why each parameter file of `argv` gives the node `node_fqn` nothing (none of its sections reaches
    it, as rcl matches them): rcl skips such a file silently, and the node would run with its defaults,
    e.g. config/default.yaml's 'senfunet' section under `-r __ns:=/robot1` or `-r __node:=front`."""
    from pathlib import Path

    from senfunet_ros.params_file import read_params_file

    out = []
    for path in params_files(argv):
        try:
            read_params_file(Path(path), node_sections_only=True, node_fqn=node_fqn)
        except ValueError as err:
            out.append(f"{err}; the node runs without this file's parameters")
    return out


def shared_file_parameters(argv: Sequence[str], node_fqn: str) -> set[str]:
    """The parameter names that only the sections for every node ('/**') of the parameter files of
    `argv` give the node `node_fqn` (`params_file.shared_parameter_names`)."""
    from pathlib import Path

    from senfunet_ros.params_file import shared_parameter_names

    shared: set[str] = set()
    for path in params_files(argv):
        try:
            shared |= shared_parameter_names(Path(path), node_fqn)
        except ValueError:  # unreadable: unread_params_files says so
            pass
    return shared


def namesakes(node: Node) -> int:
    """How many nodes of this node's name and namespace the ROS graph holds (itself included; ROS
    does not warn of two across processes)."""
    try:
        graph = node.get_node_names_and_namespaces()
    except Exception:  # noqa: BLE001 (a graph query failing under a stop)
        return 1
    return sum(1 for name, namespace in graph if (name, namespace) == (node.get_name(), node.get_namespace()))


def set_timer_period(timer: Any, period_s: float) -> None:
    """A timer's new period, in force at once: rcl keeps the next call the old period scheduled (a
    rate raised from 0.01 Hz would take effect up to 100 s later), so a timer due later than one new
    period from now is restarted on the new one."""
    period_ns = int(1e9 * period_s)
    timer.timer_period_ns = period_ns
    if (timer.time_until_next_call() or 0) > period_ns:
        timer.reset()


def subscribe(node: Node, settings: P.Settings, *, callback: Callable[[str, Stream], Callable[[Any], None]]
              ) -> tuple[list[Any], HealthMonitor]:
    """Each sensor's topics: the subscriptions and the health monitor of what they subscribed. Each
    subscription has its own mutually exclusive group: streams run in parallel, but one stream's
    messages never overlap, so they reach Ingest in arrival order. (/clock: `_ClockWatch`.)"""
    subscriptions = []
    subscribed: dict[str, tuple[str, ...]] = {}
    for sensor in settings.sensors:
        streams = [entry for entry in sensor_streams(sensor, settings.pose_type) if entry[2]]  # a topic set
        subscribed[sensor.name] = tuple(stream.value for stream, *_ in streams)
        # poses come several times as often as images: a pose callback takes all that wait, and so does
        # the sensor's depth callback before its image (TakingQueued)
        handlers = {stream: callback(sensor.name, stream) for stream, *_ in streams}
        poses = (TakingQueued(handlers[Stream.POSE], limit=next(qos.depth for stream, _, _, qos in streams
                                                               if stream is Stream.POSE))
                 if Stream.POSE in handlers else None)
        if poses is not None:
            handlers[Stream.POSE] = poses
            if Stream.DEPTH in handlers:
                handlers[Stream.DEPTH] = _after(poses.take_queued, handlers[Stream.DEPTH])
        for stream, msg_type, topic, qos in streams:
            subscription = node.create_subscription(msg_type, topic, handlers[stream], qos,
                                                    callback_group=MutuallyExclusiveCallbackGroup())
            if stream is Stream.POSE and poses is not None:
                poses.subscription = subscription
            subscriptions.append(subscription)
    health = HealthMonitor(subscribed, window_s=settings.diagnostics_window_s, stale_after_s=settings.stale_after_s)
    return subscriptions, health


class TakingQueued:
    """A subscription callback that, after its message, takes the messages already queued on its
    subscription (at most `limit`; `subscription` set once it exists); `take_queued` takes them from
    another callback. rclpy's executors take one message per subscription per round: on a node too
    busy for a round per pose (100 Hz a sensor), the pose streams fell seconds behind the image
    streams, whose frames then timed out waiting for poses that were queued already (pose_timeout)
    instead of being set aside as behind. A sensor's depth callback takes its queued poses first, so
    no frame runs ahead of the poses that arrived before it."""

    def __init__(self, callback: Callable[[Any], None], *, limit: int) -> None:
        self._callback = callback
        self._limit = limit
        self._lock = threading.Lock()  # one taker at a time: poses reach Ingest in arrival order
        self.subscription: Any = None

    def __call__(self, msg: Any) -> None:
        with self._lock:
            self._callback(msg)
            self._take_all()

    def take_queued(self) -> None:
        """Hand over the messages queued on the subscription now (from another subscription's callback)."""
        with self._lock:
            self._take_all()

    def _take_all(self) -> None:
        for _ in range(self._limit):  # what arrives meanwhile is taken next time
            queued = self._take()
            if queued is None:
                return
            self._callback(queued)

    def _take(self) -> Any:
        """The next queued message, or None (none, or the subscription is gone), taken as the executor
        takes its messages."""
        sub = self.subscription
        if sub is None:
            return None
        try:
            with sub.handle:
                taken = sub.handle.take_message(sub.msg_type, sub.raw)
        except Exception:  # noqa: BLE001 (destroyed under a stop, ...): the executor's next round takes it
            return None
        return None if taken is None else taken[0]


def _header_stamp_ns(msg: Any) -> int | None:
    """The message's header stamp in ns, None where it has none or a malformed one (Ingest says so)."""
    try:
        return conv.stamp_to_ns(msg.header.stamp)
    except (AttributeError, TypeError, ValueError):
        return None


def _after(first: Callable[[], None], callback: Callable[[Any], None]) -> Callable[[Any], None]:
    """A callback that calls `first()`, then `callback(msg)`."""

    def both(msg: Any) -> None:
        first()
        callback(msg)

    return both


def sensor_streams(sensor: P.SensorSettings, pose_type: str) -> list[tuple[Stream, type, str, QoSProfile]]:
    """(stream, message type, topic, QoS) of a sensor's inputs; image_transport's compressed topic
    names take sensor_msgs/CompressedImage."""
    depth_type = CompressedImage if sensor.depth_topic.endswith("/compressedDepth") else Image
    color_type = CompressedImage if sensor.color_topic.endswith("/compressed") else Image
    out = [(Stream.CAMERA_INFO, CameraInfo, sensor.camera_info_topic, _SENSOR_QOS),
           (Stream.DEPTH, depth_type, sensor.depth_topic, _SENSOR_QOS),
           (Stream.COLOR, color_type, sensor.color_topic, _SENSOR_QOS)]
    msgtype = PoseType(pose_type).msgtype
    if msgtype is not None:  # not TF
        out.append((Stream.POSE, message_class(msgtype), sensor.pose_topic, _POSE_QOS))
    return out


def make_tf(node: Node, settings: P.Settings, callback: Callable[[str, Stream], Callable[[Any], None]]
            ) -> tuple[Any, list[Any]]:
    """Poses from TF: tf2_ros's buffer and listener when a sourced ROS 2 install provides them, else
    our own buffer fed by /tf and /tf_static (`callback(sensor "", stream)` subscribed to them) when
    tf2_msgs can be imported; else a clear refusal. Returns the lookup and what must stay alive."""
    try:
        import tf2_ros  # only in a sourced ROS 2 install
    except ImportError:
        tf2_ros = None
    if tf2_ros is not None:
        buffer = tf2_ros.Buffer()
        listener = tf2_ros.TransformListener(buffer, node)
        node.get_logger().info("pose_type tf: poses from tf2_ros")
        return _Tf2Lookup(buffer, tf2_ros), [listener]
    try:
        from tf2_msgs.msg import TFMessage  # no wheel on the index
    except ImportError:
        raise ValueError("pose_type tf needs tf2_ros, which cannot be imported here: source a ROS 2 install "
                         "(e.g. . /opt/ros/jazzy/setup.bash) before starting the node, or give poses on pose "
                         "topics (pose_type pose_stamped | odometry | transform_stamped)") from None
    from senfunet_ros.tf import TfBuffer

    subscriptions = []
    for topic, stream, qos in (("/tf", Stream.TF, _TF_QOS), ("/tf_static", Stream.TF_STATIC, _TF_STATIC_QOS)):
        handler = TakingQueued(callback("", stream), limit=qos.depth)  # /tf comes as often as poses do
        handler.subscription = node.create_subscription(TFMessage, topic, handler, qos,
                                                        callback_group=MutuallyExclusiveCallbackGroup())
        subscriptions.append(handler.subscription)
    node.get_logger().warning("pose_type tf: tf2_ros cannot be imported; reading /tf and /tf_static with the "
                              "node's own buffer (source a ROS 2 install to use tf2_ros)")
    return TfBuffer(max_gap_s=settings.pose_tolerance_s), subscriptions


def make_engine(settings: P.Settings, logger: Any) -> Any:
    """The node's engine, its kernels compiled (or loaded from numba's cache) before the first frame."""
    # heavy (torch): imported when a node is made, not when this module is
    from senfunet_core import decimate
    from senfunet_core.engine import SenFuNet, warm_up

    fallback = P.device_fallback(settings)
    if fallback:
        logger.warning(fallback)
    weights = P.engine_weights(settings)
    if weights is None:
        logger.warning("parameter weights = 'none': the networks are untrained")
    # the alpha threads run the idle mesh updates and the net's turns: at the mesh thread's priority,
    # whichever thread starts them (a ~/save_mesh call before the first update does)
    engine = SenFuNet(P.engine_config(settings), weights=weights, worker_setup=at_mesh_priority)
    start = time.monotonic()
    warm_up(engine)  # compile the kernels now, not in the first frame's integration
    conv.marker_array_cdr({}, (), stamp_ns=0, frame_id="")
    decimate.warm_up()
    logger.info(f"engine kernels ready in {time.monotonic() - start:.1f} s")
    return engine


def spin(node: FusionNode, num_threads: int = 6) -> None:
    """Spin until shutdown; enough threads that subscriptions run while both timers are busy."""
    from rclpy._rclpy_pybind11 import InvalidHandle, RCLError

    executor = MultiThreadedExecutor(num_threads=num_threads)
    executor.add_node(node)
    # What exists now (modules, networks, the node and its engine) leaves the cycle collector's full
    # passes, which otherwise walk it all while holding the GIL, stalling every thread of the node. An
    # engine is freed by reference counting alone (no reference cycles: test_engine checks it), so a
    # map replaced by ~/load_map still goes. Unfrozen when the spin ends, so that a process spinning
    # several nodes in turn (tests, benchmarks) can collect the ones it is done with.
    gc.collect()
    gc.freeze()
    recent_races_s: deque[float] = deque(maxlen=_MAX_WAIT_SET_RACES)
    main_thread = threading.current_thread() is threading.main_thread()
    try:
        while True:
            try:
                if main_thread:
                    _SPINNING.set()
                executor.spin()
                return
            except InvalidHandle as err:
                # a subscription destroyed by another thread while this one put it in the wait set: rclpy's
                # TimeSource and _ClockWatch drop their /clock subscriptions in the parameter service's
                # callback when use_sim_time turns false (`ros2 param set`). rclpy raises instead of leaving it
                # out; the next wait set is built without it. Only a race that keeps recurring is an error.
                if not node.context.ok():
                    return
                recent_races_s.append(time.monotonic())
                if len(recent_races_s) == recent_races_s.maxlen and recent_races_s[-1] - recent_races_s[0] < 1.0:
                    raise
                node.get_logger().debug(f"an entity went while the executor waited on it ({err}); spinning on")
            except RCLError:
                if node.context.ok():
                    raise
                return  # SIGINT/SIGTERM shut the context down while the executor was building its wait set: a stop
    finally:
        _SPINNING.clear()
        stop_executor(executor)
        gc.unfreeze()


def stop_executor(executor: MultiThreadedExecutor) -> None:
    """Once its spin ended, stop an executor, first waiting for the callbacks it handed out (then
    its nodes may go): rclpy 7.1's `shutdown` returns at once (its wait tests the flag it has just
    set), and a callback still running when its node is destroyed fails on the node's handles, or
    its work is cut off. They end before `shutdown`, which destroys the guard condition that each
    of them triggers as it ends (else an InvalidHandle in a task nobody reads)."""
    pool = getattr(executor, "_executor", None)  # MultiThreadedExecutor's worker threads (no public handle)
    if isinstance(pool, ThreadPoolExecutor):
        pool.shutdown(wait=True)
    executor.shutdown()


# Python hands the GIL to a waiting thread only every switch interval (default 5 ms). Each
# message needs several hand-overs (the executor's wait returns, a worker takes and converts it),
# so while integration and a mesh update run Python between their numpy/torch calls, the default
# interval holds message dispatch below the rate of the sample bag: pose callbacks lag and frames
# time out waiting for them. A tenth of it lets `senfunet demo` fuse every frame
# (test/ros/test_play.py checks that).
GIL_SWITCH_INTERVAL_S = 0.0005


def prepare_process() -> None:
    """Process settings for a node with busy timers: a short GIL switch interval (see above), glibc
    malloc limits (`limit_malloc`) and OpenMP threads that sleep when idle (`passive_openmp_threads`).
    Call before the executor's threads exist and before torch is imported."""
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    limit_malloc()
    passive_openmp_threads()


# How much lower the mesh thread's priority is than the other threads' (a nice value, Linux): where
# both want a core, integration gets about three quarters of it and the mesh updates and the
# weighting net the rest (the lowest priority, 19, starves the net while frames come:
# bench/realtime.py measures both sides, frames integrated on arrival and the net's waits)
MESH_THREAD_NICE = 5


def lower_thread_priority(nice: int) -> bool:
    """Lower the calling thread's scheduling priority to `nice` below the main thread's (Linux keeps
    a nice value per thread, and the threads it starts inherit it); a thread already that low is
    left as it is, so threads the mesh thread starts can call it too. Not undone: raising a
    priority back needs privileges. False where it cannot be done (nothing changes)."""
    import os

    if not sys.platform.startswith("linux"):  # elsewhere PRIO_PROCESS would take the whole process
        return False
    try:
        thread = threading.get_native_id()
        target = min(os.getpriority(os.PRIO_PROCESS, os.getpid()) + nice, 19)  # the main thread's id is the pid
        if os.getpriority(os.PRIO_PROCESS, thread) < target:
            os.setpriority(os.PRIO_PROCESS, thread, target)
        return True
    except (AttributeError, OSError):
        return False


def at_mesh_priority() -> bool:
    """`lower_thread_priority(MESH_THREAD_NICE)`: what every thread of the mesh side runs as it starts
    (the mesh thread, the net's turn thread, the engine's alpha threads)."""
    return lower_thread_priority(MESH_THREAD_NICE)


def passive_openmp_threads() -> bool:
    """OMP_WAIT_POLICY=PASSIVE unless the user set a policy: torch's OpenMP workers (the weighting
    net's intra-op threads) otherwise spin for a while after each parallel region, burning the
    cores that the integration and the mesh updates need (bench/realtime.py measures the process's
    CPU time per frame). OpenMP reads it once, when torch loads: False (nothing changes) if torch is
    already imported."""
    import os

    if "torch" in sys.modules:
        return False
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    return True


def limit_malloc(arenas: int = 2, mmap_threshold_bytes: int = 4 << 20, trim_threshold_bytes: int = 64 << 20) -> bool:
    """Cap glibc's malloc arenas (default: 8 per core) for the threads started from now on, and fix
    the size from which allocations get their own mapping (returned to the OS when freed). Each
    executor, feature-net and kernel thread would otherwise keep its own heap of freed per-frame
    arrays (arenas), and glibc raises the threshold up to 32 MB after the first such array is freed,
    after which the per-update arrays of a few MB and more stay in the heaps. The threshold trades
    the memory those heaps keep against the page faults of re-mapping: lower costs frame rate,
    higher keeps more (bench/realtime.py measures both). Fixing it also fixes the trim threshold
    (free memory at a heap's top given back) at 128 KB, so every frame's arrays below the mmap
    threshold would be given back and faulted in again: trim_threshold_bytes keeps that much.
    False where there is no glibc (nothing changes)."""
    import ctypes
    import ctypes.util

    from senfunet_core.memory import large_allocations_outside_the_heap

    threshold_set = large_allocations_outside_the_heap(mmap_threshold_bytes)
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt(-1, trim_threshold_bytes)  # M_TRIM_THRESHOLD
        return bool(libc.mallopt(-8, arenas)) and threshold_set  # M_ARENA_MAX
    except (OSError, AttributeError):
        return False


def main(args: list[str] | None = None) -> int:
    """`ros2 run senfunet_ros fusion_node [--ros-args ...]`."""
    from senfunet_ros.dds import use_large_shm_profile

    use_large_shm_profile()  # large mesh messages; set before the participant exists
    prepare_process()  # before the executor's threads exist
    _signals_as_interrupt()  # rclpy's handler calls it too: a SIGTERM during start-up stops it like Ctrl-C
    try:
        rclpy.init(args=args)
    except Exception as err:  # noqa: BLE001 (rcl's own: a parameter file or -p it cannot parse)
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        print(f"senfunet: cannot start: ROS refused the command line's ROS arguments: {reason}; check the "
              "parameter files and -p/-r arguments", file=sys.stderr, flush=True)
        return 2
    node: FusionNode | None = None
    try:
        node = FusionNode(argv=sys.argv if args is None else args)
        spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as err:
        if not rclpy.ok():  # a signal shut the context down under the start-up (a handle failed on it): a stop
            return 0
        if isinstance(err, ValueError):  # bad parameters (InputError is a ValueError too): say which, no traceback
            print(f"senfunet: cannot start: {err}", file=sys.stderr, flush=True)
            return 2
        raise
    finally:
        if node is not None:
            stop_node(node)
        shut_down_rclpy()
    return 0


# Set while `spin` runs the executor: a SIGINT or SIGTERM then only shuts the context down (rclpy's own
# handler), which ends the spin. A KeyboardInterrupt raised there can land inside the executor's thread
# pool while it holds a lock (ThreadPoolExecutor.submit's idle semaphore), which its worker threads then
# wait for forever, and the node never stopped (1 in 10 stops under test_stops).
_SPINNING = threading.Event()


def _signals_as_interrupt() -> None:
    """SIGINT and SIGTERM raise KeyboardInterrupt in the main thread, except while it spins (`_SPINNING`).
    rclpy's own handler, installed by rclpy.init, shuts the context down and then calls this one:
    without it a SIGTERM during the start-up (kernel warm-up: seconds, a minute on a first start) went
    unnoticed until a handle failed. Call before rclpy.init, so that rclpy chains to it."""
    import signal

    def interrupt(signum: int, frame: Any) -> None:
        if not _SPINNING.is_set():
            raise KeyboardInterrupt

    try:
        for sig, default in ((signal.SIGINT, signal.default_int_handler), (signal.SIGTERM, signal.SIG_DFL)):
            if signal.getsignal(sig) is default:
                signal.signal(sig, interrupt)
    except ValueError:  # not the main thread
        pass


def _judge_before_saving(engine: Any, hurry: threading.Event) -> None:
    """The weighting net's backlog judged in short turns until none is left, a turn leaves no fewer (as
    `MapServices._judge_between_updates` stops; the save's own judging finishes it), or `hurry` is set
    (then said, with what is left: the fused mesh shows it as it stands)."""
    left_before = None
    while not hurry.is_set():
        engine.refresh_alpha(0.25)  # its first turn also counts the blocks that integration left to judge
        left = engine.counters["alpha_backlog_blocks"]
        if left == 0 or (left_before is not None and left >= left_before):
            return
        if left_before is None:
            print(f"senfunet: saving on shutdown: the weighting net first judges the {left} blocks it has not "
                  "reached (Ctrl-C: write the fused mesh as it stands)", flush=True)
        left_before = left
    if engine.counters.get("alpha_backlog_blocks"):
        print(f"senfunet: {engine.counters['alpha_backlog_blocks']} blocks not judged: the fused mesh leaves out "
              "the surface one sensor alone saw there", flush=True)


def stop_node(node: FusionNode) -> None:
    """What `main` does once the executor stopped: integrate the ready frames (`finish`), save the
    meshes (parameter save_on_shutdown: the weighting net first judges what it has not reached),
    destroy the node. Ctrl-C or SIGTERM meanwhile (someone in a hurry, or ros2 launch's SIGTERM after
    its sigterm_timeout) shortens it without losing the map: the frames not started yet are dropped, the
    net does not judge any further and the fused mesh alone is written, as it stands; while the files are
    written, the writing stops (each file is written whole or not at all, see `write_ply`); the node is
    destroyed either way."""
    import signal
    import tempfile

    abandon = threading.Event()  # drop the frames not integrated yet
    hurry = threading.Event()  # the net stops judging; the fused mesh alone is written, as it stands
    phase = "finish"  # then "judge", then "write"

    def interrupted(signum: int, frame: Any) -> None:
        if phase == "write":
            raise KeyboardInterrupt
        hurried = "the weighting net stops judging; the fused mesh alone is written, as it stands"
        hurry.set()
        if phase == "judge":
            print(f"senfunet: interrupted again: {hurried}", flush=True)
            return
        abandon.set()
        print("senfunet: interrupted again: the frames not integrated yet are dropped" +
              (f"; {hurried}" if node.settings.save_on_shutdown else ""), flush=True)

    try:
        previous = {sig: signal.signal(sig, interrupted) for sig in (signal.SIGINT, signal.SIGTERM)}
    except ValueError:  # not the main thread: signals go to the main thread's handlers
        previous = None
    try:
        try:
            done = node.finish(abandon, set_aside=node.settings.save_on_shutdown)
            for _, line in done["ends"]:
                print(f"senfunet: {line}", flush=True)
            print(f"senfunet: stopped; at the stop {done['integrated']} ready frame(s) integrated, "
                  f"{done['discarded']} still waiting and {done['interrupted']} being integrated were dropped "
                  "(counted as shutdown)", flush=True)
        except Exception as err:
            print(f"senfunet: finishing the queued frames failed: {err}", file=sys.stderr, flush=True)
        if node.settings.save_on_shutdown:
            phase = "judge"
            _judge_before_saving(node.pipeline.engine, hurry)
            phase = "write"
            try:
                try:
                    paths, saved = node.map_services.save_meshes(hurry=hurry.is_set()), "saved"
                except NothingToSave as err:  # the files of an earlier run stay
                    print(f"senfunet: not saved on shutdown: {err}", flush=True)
                    paths = []
                except (OSError, InputError) as err:  # output_dir cannot be written (a file there is a folder):
                    # the map would end with the process
                    print(f"senfunet: saving on shutdown into output_dir failed: {err}; check parameter output_dir; "
                          "saving into a new temporary folder instead", file=sys.stderr, flush=True)
                    paths = node.map_services.save_meshes(tempfile.mkdtemp(prefix="senfunet_output_"),
                                                          hurry=hurry.is_set())
                    saved = "saved instead"
                if paths:
                    print(f"senfunet: {saved} " + ", ".join(str(p) for p in paths), flush=True)
            except KeyboardInterrupt:
                print("senfunet: interrupted again: saving on shutdown stopped (files already written stay, "
                      "the one being written was not replaced)", flush=True)
            except Exception as err:
                print(f"senfunet: saving on shutdown failed: {err}", file=sys.stderr, flush=True)
    finally:
        for sig, handler in (previous or {}).items():
            signal.signal(sig, handler)
        node.destroy_node()


if __name__ == "__main__":
    raise SystemExit(main())
