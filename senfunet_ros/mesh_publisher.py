"""~/mesh and ~/weights: the node's mesh timer work, from `engine.update()` to the readers.

One `publish` at a time (`lock`, shared with the map services that replace or empty the map):
update the engine's meshes (on every core when no frame waits), encode and publish the changed
blocks (or the whole map for a subscriber that just joined) and, when due, start the weight cloud;
then give the weighting net its turn (when no frame waits, on a thread of its own while the update is
encoded). The node calls `publish` from its mesh thread (`MeshWorker`: the mesh timer's ticks run
there, one update at a time), at a lower priority than integration's (see
`node.lower_thread_priority`; the turn thread and the weights thread are set to it too); the engine
is thread-safe: integration goes on meanwhile.

The weight cloud reads the whole map (seconds on a room, with its encoding and publication): it is
built, encoded and published on a thread of its own (`CloudWorker`, "senfunet-weights"), not under
`lock` and not on the mesh thread, so a ~/weights subscriber never holds the mesh refresh back; a
cloud due while the previous one is still being built is skipped. It reads the engine as any
reader does (`readout.weight_cloud`: the data lock a slice at a time, never the update lock).
"""
from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from concurrent import futures
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
from rclpy.event_handler import PublisherEventCallbacks, QoSPublisherMatchedInfo, UnsupportedEventTypeError
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from senfunet_ros import conversions as conv
from senfunet_ros import params as P
from senfunet_ros.params import MESH_PERIOD_MARGIN
from senfunet_ros.dds import publish_serialized, wait_for_all_acked
from senfunet_ros.pipeline import Pipeline

# The map: reliable and kept for late subscribers. Depth > 1 so a burst (delta then snapshot) is
# not overwritten before a slow reader acknowledged it.
MESH_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)
CLOUD_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)
_PARTS_ACK_TIMEOUT_S = 1.0  # a stuck reader delays the later parts of one update at most this, in all
# the net's turn while frames come, however long the update took (if alpha_budget_s allows): short, since
# an update that took the whole period already delays the next
MIN_TURN_S = 0.05
# the share of the mesh period an update may spend re-meshing (the blocks beyond it go first in the next
# updates): encoding, publishing and the net's turn take the rest, so that a burst of changed blocks
# (frames arriving faster than they are integrated, a backlog of set-aside frames) never stretches the
# refresh past its period
MESH_BUDGET_SHARE = 0.5


def next_due_s(due_s: float, now_s: float, period_s: float) -> float:
    """When a periodic output that was due at `due_s` and went out at `now_s` (at a later tick) is due
    next: a period after the time it was due, not after the tick (else a rate near the ticks' skips
    every other tick); after a pause longer than a period, a period from now."""
    due_s += period_s
    return due_s if due_s > now_s else now_s + period_s


def mesh_period_s(mesh_rate_hz: float) -> float:
    """The mesh timer's period for parameter mesh_rate_hz (a little shorter: see MESH_PERIOD_MARGIN)."""
    return (1.0 - MESH_PERIOD_MARGIN) / mesh_rate_hz


class MeshWorker:
    """The mesh timer's work on a thread of its own. A tick while an update runs makes the next one
    start as soon as that one ends (an update longer than the period is followed at once, not at
    the tick after); ticks meanwhile coalesce into that one. The timer thread calls `tick`; `update`
    runs on the worker thread only. An update that fails is warned about (`warn(key, message)`), unless
    the node is shutting down, whose publishers may go away under it."""

    def __init__(self, update: Callable[[], None], *, keep_going: Callable[[], bool],
                 thread_setup: Callable[[], Any], warn: Callable[[tuple[str, ...], str], None]) -> None:
        self._update = update
        self._keep_going = keep_going  # False: stop after the update under way (shutting down)
        self._warn = warn
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="senfunet-mesh", initializer=thread_setup)
        self._lock = threading.Lock()  # guards the three flags below (timer thread vs. worker thread)
        self._running = False  # an update is under way on the worker thread
        self._due = False  # a tick came meanwhile: the next update starts as soon as that one ends
        self._stopped = False  # `shutdown` was called: a due update does not start

    def tick(self) -> None:
        with self._lock:
            if self._running:
                self._due = True
                return
            self._running = True
        try:
            self._pool.submit(self._updates)
        except RuntimeError:  # shut down under this last tick
            with self._lock:
                self._running = False

    def _updates(self) -> None:
        """Updates, as long as ticks came during the last one."""
        while True:
            try:
                self._update()
            except Exception as err:
                if self._keep_going():
                    self._warn(("mesh_update",), f"mesh update failed: {err!r}")
            with self._lock:
                if not self._due or self._stopped or not self._keep_going():
                    self._running = False
                    return
                self._due = False

    def shutdown(self) -> None:
        """No update starts any more; the one under way finishes first."""
        with self._lock:
            self._stopped = True
        self._pool.shutdown(wait=True)


class CloudWorker:
    """~/weights clouds on a thread of their own, off the mesh update's path (see the module
    docstring). `request` (from the mesh thread) starts `build(job)` on the worker thread unless one
    is under way, and returns at once: a due cloud is then skipped (counted in `skipped`; the next is
    due a period later), a forced one (`force`: ~/weights asked for now) follows the one under way.
    A build that fails is warned about (`warn(key, message)`), unless the node is shutting down."""

    def __init__(self, build: Callable[[Any], None], *, keep_going: Callable[[], bool],
                 thread_setup: Callable[[], Any] | None, warn: Callable[[tuple[str, ...], str], None]) -> None:
        self._build = build
        self._keep_going = keep_going
        self._warn = warn
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="senfunet-weights", initializer=thread_setup)
        self._lock = threading.Lock()  # guards the three fields below (mesh thread vs. worker thread)
        self._running = False  # a build is under way on the worker thread
        self._forced: Any = None  # the job of a forced request made meanwhile: built next
        self.skipped = 0  # due clouds skipped because the previous one was still being built

    def request(self, job: Any, *, force: bool = False) -> bool:
        """Start building `job`'s cloud now (True), or not (False: one is under way; a forced job
        is built once it ends)."""
        with self._lock:
            if self._running:
                if force:
                    self._forced = job
                else:
                    self.skipped += 1
                return False
            self._running = True
        try:
            self._pool.submit(self._builds, job)
        except RuntimeError:  # shut down under this last request
            with self._lock:
                self._running = False
            return False
        return True

    def _builds(self, job: Any) -> None:
        """Builds, as long as forced requests came during the last one."""
        while True:
            try:
                self._build(job)
            except Exception as err:
                if self._keep_going():
                    self._warn(("weights_cloud",), f"~/weights cloud failed: {err!r}")
            with self._lock:
                job, self._forced = self._forced, None
                if job is None:
                    self._running = False
                    return

    def shutdown(self) -> None:
        """No build starts any more; the one under way (and a forced one after it) finishes first."""
        self._pool.shutdown(wait=True)


class UpdateSignal:
    """Mesh updates as they end, for a thread that waits for the next one (`~/save_mesh` lets them
    come between its turns of the weighting net): `ended` from the publishing thread, `wait_next`
    from any other."""

    def __init__(self) -> None:
        self._ended = threading.Condition()
        self._count = 0  # updates ended so far (guarded by the condition's lock)

    def ended(self) -> None:
        with self._ended:
            self._count += 1
            self._ended.notify_all()

    def wait_next(self, timeout_s: float) -> bool:
        """Until an update ends after this call (True), or timeout_s passes (False)."""
        with self._ended:
            count = self._count
            return self._ended.wait_for(lambda: self._count != count, timeout=timeout_s)


class MeshPublisher:
    """The node's ~/mesh and ~/weights publishers and what the mesh timer does with them.

    timings: the node's stage timings ("update", "alpha", "weights", "encode", "publish" are
    added here); latency: frame arrival -> the update that shows it; camera_colors: the colour
    grid of mesh_colors "camera"; frame_waiting: whether a frame waits in Ingest.
    """

    def __init__(self, node: Node, pipeline: Pipeline, settings: Callable[[], P.Settings], *, timings: dict[str, Any],
                 latency: Any, camera_colors: Any, frame_waiting: Callable[[], bool],
                 warn: Callable[[tuple[str, ...], str], None], thread_setup: Callable[[], object] | None = None
                 ) -> None:
        self.pipeline = pipeline
        self._settings = settings
        self._timings = timings
        self._latency = latency
        self._camera_colors = camera_colors
        self._frame_waiting = frame_waiting
        self._warn = warn
        self.lock = threading.Lock()  # one publication at a time (timer vs. reset and load_map services)
        self.updates = UpdateSignal()  # each publication's end (one that fails: a waiter's timeout)
        # called on the mesh thread with (engine, update, whole) as each update is published, `whole` when it
        # sends the whole map instead of the update's changes (a reader joined, a map loaded): what a
        # subscriber holds
        self.taps: list[Callable[[Any, Any, bool], None]] = []
        self._matched = 0  # mesh readers matched so far (written by the matched event's callback only)
        try:
            self.mesh_pub = node.create_publisher(MarkerArray, "~/mesh", MESH_QOS,
                                                  event_callbacks=PublisherEventCallbacks(matched=self._on_matched))
        except UnsupportedEventTypeError:  # an RMW without the event: the reader count alone tells
            self.mesh_pub = node.create_publisher(MarkerArray, "~/mesh", MESH_QOS)
        self.weights_pub = node.create_publisher(PointCloud2, "~/weights", CLOUD_QOS)
        # the mesh readers (how many, and how many matched so far) the last publication reached: one
        # more, or one that replaced another between two publications (RViz re-subscribing), gets
        # the whole map
        self._served = (0, 0)
        self._resend = threading.Event()  # the next publication sends the whole map (`resend_all`)
        # an update's parts went out while a reader had not taken the ones before (they may have
        # been lost, for it and for readers that could not keep up with the rest): once every reader
        # has taken what was published, the next publication sends the whole map
        self._parts_unacknowledged = False
        self._most_parts = 1  # the most parts an update went out in so far (said in the log as it grows)
        self._logger = node.get_logger()
        self._next_weights_s = 0.0  # monotonic time of the next ~/weights cloud
        # an idle turn of the net runs on this thread while `publish`'s thread encodes and publishes
        self._turns = ThreadPoolExecutor(1, thread_name_prefix="senfunet-net-turn", initializer=thread_setup)
        # how far the last turn while frames came ran past its budget (its first batch always runs): the next
        # turn ends that much sooner, so that update, publication and turn end within the mesh period
        self._turn_overrun_s = 0.0
        # ~/weights clouds, built, encoded and published off the mesh thread (one at a time)
        self.clouds = CloudWorker(self._publish_cloud, keep_going=node.context.ok, thread_setup=thread_setup,
                                  warn=warn)

    def resend_all(self) -> None:
        """The next publication sends the whole map (a loaded map replaced what readers hold, or they
        are to be shown otherwise). From any thread, without waiting for a publication."""
        self._resend.set()

    def _on_matched(self, info: QoSPublisherMatchedInfo) -> None:
        self._matched = info.total_count

    def publish(self, weights: bool | None = None) -> None:
        """engine.update() -> ~/mesh (changed blocks, or a full snapshot for new subscribers), and
        ~/weights when it is due (every 1 / weights_rate_hz s; `weights` forces or skips it) and
        somebody listens (started on the weights thread, `CloudWorker`: this call does not wait for
        it; a due cloud is skipped while the previous one is still being built); then the weighting
        net's turn (engine.refresh_alpha, within alpha_budget_s), after publishing: a frame's
        geometry is shown one alpha phase sooner (the net's budget no longer sits between
        integration and the mesh subscribers), and the alpha it changed comes with the next update.
        When idle (`weighting_net_turn`), the turn starts once the update is meshed, on the turn
        thread, while this thread encodes and publishes (on one core: the turn gets the other), and
        ends before this call returns."""
        s = self._settings()
        with self.lock:
            engine = self.pipeline.engine  # under the lock: ~/load_map replaces it under the same lock
            start = time.perf_counter()
            now = time.monotonic()
            forced = weights is True
            if weights is None:
                weights = now >= self._next_weights_s
            weights = weights and self.weights_pub.get_subscription_count() > 0
            contained = self._latency.take()  # frames integrated before this update began
            stamp_ns = self.pipeline.latest_stamp_ns  # of them: a frame integrated during the update may be missing
            # the update takes the engine's changes: until they are published, a failure (the update's
            # own, encoding, a refused publication) makes the next publication send the whole map
            served, self._served = self._served, (0, 0)
            # no frame waiting (the sensors paused, or integration keeps up): mesh on every core; a
            # frame coming meanwhile still goes first (the mesh thread's lower priority, which its
            # helper threads share)
            update = engine.update(alpha_budget_s=0.0,
                                   mesh_threads=1 if self._frame_waiting() else engine.config.alpha_threads,
                                   mesh_budget_s=MESH_BUDGET_SHARE * mesh_period_s(s.mesh_rate_hz))
            replaced = self._resend.is_set()  # cleared before the map is read: a later request gets the next one
            if replaced:
                self._resend.clear()
                served = (0, 0)
            t_update = time.perf_counter()
            self._timings["update"].add(t_update - start)
            if weights:  # built on the weights thread, from the map as it is then (this update's meshes or later)
                self._next_weights_s = next_due_s(self._next_weights_s, now, 1.0 / s.weights_rate_hz)
                self.clouds.request((engine, s, stamp_ns), force=forced)
            t_cloud = time.perf_counter()
            readers = (self.mesh_pub.get_subscription_count(), self._matched)
            caught_up = self._parts_unacknowledged and wait_for_all_acked(self.mesh_pub, 0.0)
            whole = readers[0] > served[0] or readers[1] > served[1] or caught_up
            for tap in self.taps:  # a map replaced (a load) is whole for them, readers or not
                tap(engine, update, whole or replaced)
            messages = self._mesh_messages(engine, update, s, stamp_ns, whole=whole)
            # the net's turn ends with this mesh period (less a margin for the updates' jitter): the next
            # update is not to wait for it
            period_s = (1.0 - MESH_PERIOD_MARGIN) * mesh_period_s(s.mesh_rate_hz)
            # idle when no frame came while this update ran: the frames it holds may have been the
            # stream's last, and the net's catch-up (which stops at the next frame) should not wait a
            # period; it starts now, on the cores the encoding leaves (one), and this thread joins it
            # once the update is published (so a frame's geometry is not held back by the net's turn)
            idle = self._no_frame_waiting()
            t_alpha = time.perf_counter()
            turn = (self._turns.submit(self.weighting_net_turn, idle=True, period_left_s=period_s - (t_alpha - start))
                    if idle else None)
            t_sent = t_cloud
            try:
                unacknowledged = self._send(messages, s, t_cloud=t_cloud)
                t_sent = time.perf_counter()
                self._latency.published(contained)
                self._parts_unacknowledged = unacknowledged or (self._parts_unacknowledged and not caught_up)
                self._served = readers
            finally:  # the turn ends before the next publication, even if this one failed
                if turn is not None:
                    futures.wait([turn])
            if turn is not None:
                turn.result()
            else:  # frames come: the net's turn after publishing, on this thread (integration needs the other core)
                t_alpha = time.perf_counter()
                self.weighting_net_turn(idle=False, period_left_s=period_s - (t_alpha - start))
            end = time.perf_counter()
            self._timings["alpha"].add(end - t_alpha)
            if end - start > 2.0 * mesh_period_s(s.mesh_rate_hz):  # the refresh stalls: say where the time went
                self._warn(("mesh_update_slow",), f"a mesh update took {end - start:.2f} s, over twice the mesh period "
                           f"(mesh_rate_hz {s.mesh_rate_hz:g}): engine.update {t_update - start:.2f} s "
                           f"({len(update.meshes)} block meshes), encoding and publishing "
                           f"{'the whole map' if whole else 'the changed blocks'} {t_sent - t_cloud:.2f} s, "
                           f"then the weighting net's turn {end - t_sent:.2f} s "
                           f"({'idle, beside the publication' if turn is not None else 'frames coming'}); if this "
                           "recurs, a lower mesh_rate_hz gives each update more time")
        self.updates.ended()

    def _publish_cloud(self, job: tuple[Any, P.Settings, int]) -> None:
        """Build, encode and publish one ~/weights cloud (on the weights thread; timed as "weights"):
        alpha as the budgeted updates left it (not a full refresh: voxels the net has not judged yet
        are left out), within weights_band_m of the surface (0: everywhere observed), stamped as the
        mesh update that asked for it."""
        from senfunet_core.readout import weight_cloud

        engine, s, stamp_ns = job
        start = time.perf_counter()
        cloud = weight_cloud(engine, s.weights_band_m if s.weights_band_m > 0 else None, refresh_alpha=False)
        data = conv.point_cloud2_cdr(cloud.positions_m, cloud.alpha, cloud.weights, s.sensor_names,
                                     stamp_ns=stamp_ns, frame_id=s.fixed_frame)
        del cloud
        publish_serialized(self.weights_pub, np.frombuffer(data, np.uint8))
        self._timings["weights"].add(time.perf_counter() - start)

    def _mesh_messages(self, engine: Any, update: Any, s: P.Settings, stamp_ns: int, *, whole: bool) -> Any:
        """The update's ~/mesh parts (encoded as they are taken), or None when nothing changed; the
        whole map when `whole` (a reader joined or caught up: transient local keeps only the last few
        messages)."""
        frame_id, max_bytes = s.fixed_frame, int(s.mesh_message_max_mb * (1 << 20))
        if whole:
            return conv.marker_array_messages(self.display(engine.block_meshes()), (), stamp_ns=stamp_ns,
                                              frame_id=frame_id, delete_all_first=True, max_bytes=max_bytes)
        if update.cleared or len(update.meshes) or update.removed:
            return conv.marker_array_messages(self.display(update.meshes), update.removed, stamp_ns=stamp_ns,
                                              frame_id=frame_id, delete_all_first=update.cleared,
                                              max_bytes=max_bytes)
        return None

    def _send(self, messages: Any, s: P.Settings, *, t_cloud: float) -> bool:
        """Publish the mesh parts, each part once the readers took the one before,
        within _PARTS_ACK_TIMEOUT_S for all. Returns whether a part went out before a reader took the
        one before (warned about: the whole map goes out again once every reader has caught up)."""
        publish_s = 0.0  # the rest, from t_cloud on, is encoding (the parts are encoded as they are taken)
        ack_deadline = time.monotonic() + _PARTS_ACK_TIMEOUT_S
        unacknowledged = 0  # parts published while a reader had not taken the one before
        parts = 0
        for parts, data in enumerate(messages or (), start=1):
            t_encoded = time.perf_counter()
            # the history holds 2: let readers take the previous part before it can be overwritten
            if parts > 1 and not wait_for_all_acked(self.mesh_pub, ack_deadline - time.monotonic()):
                unacknowledged += 1
            publish_serialized(self.mesh_pub, data)  # large: without holding the GIL
            publish_s += time.perf_counter() - t_encoded
        if messages is not None:
            self._timings["encode"].add(time.perf_counter() - t_cloud - publish_s)
            self._timings["publish"].add(publish_s)
        if parts > self._most_parts:
            self._most_parts = parts
            self._logger.info(f"a ~/mesh update went out in {parts} parts of at most {s.mesh_message_max_mb:g} MB: a "
                              "reader keeping fewer messages than that (a latched reader of depth 1) loses parts; "
                              "subscribe with KEEP_ALL or raise parameter mesh_message_max_mb")
        if unacknowledged:
            self._warn(("mesh_readers_behind",), f"a ~/mesh reader did not take the parts of a mesh update within "
                       f"{_PARTS_ACK_TIMEOUT_S:g} s ({unacknowledged} part(s) published without waiting for it; "
                       "readers may have missed some): the whole map is sent again once every reader has caught up")
        return bool(unacknowledged)

    def close(self) -> None:
        """End the net's turn thread and the weights thread (after the last `publish`; a cloud under way
        is published first)."""
        self._turns.shutdown(wait=True)
        self.clouds.shutdown()

    def _no_frame_waiting(self) -> bool:
        """No frame queued in Ingest and none integrated since the last mesh update began."""
        return not self._frame_waiting() and not self._latency.pending()

    def weighting_net_turn(self, *, idle: bool, period_left_s: float) -> None:
        """The weighting net's turn after a mesh update.

        While frames come: alpha_budget_s (0: no limit), but no longer than what is left of the mesh
        period, so that the mesh refresh keeps its rate; and at least MIN_TURN_S (or the budget, if
        less), so that on a map whose updates take the whole period the net still judges while the
        sensors stream. Idle (no frame integrated while the update ran and none queued: the sensors paused
        or stopped): the net catches up on what it has not judged yet, on every core, for the rest
        of the mesh period (at least alpha_budget_s), and stops as soon as a frame is integrated; the
        next update publishes what it judged and gives it the next slice, so the mesh keeps its
        refresh rate and soon equals what an offline replay makes (a frame queued but not yet
        integrated is not idleness)."""
        s = self._settings()
        engine = self.pipeline.engine
        if not s.alpha_budget_s:
            engine.refresh_alpha(None)
        elif idle:
            engine.refresh_alpha(max(period_left_s, s.alpha_budget_s), until_frame=True)
        else:
            budget_s = min(s.alpha_budget_s, max(period_left_s - self._turn_overrun_s, MIN_TURN_S))
            start = time.perf_counter()
            engine.refresh_alpha(budget_s)
            self._turn_overrun_s = max(0.0, time.perf_counter() - start - budget_s)

    def display(self, meshes: Any) -> Any:
        """The display mesh of a batch of block meshes (parameter mesh_display_cell_m)."""
        from senfunet_core.decimate import decimate_block_meshes
        from senfunet_core.mesher import BlockMeshes

        s = self._settings()
        if not isinstance(meshes, BlockMeshes):
            meshes = BlockMeshes.from_meshes(dict(meshes))
        if s.mesh_display_cell_m > s.voxel_size_m:
            meshes = decimate_block_meshes(meshes, s.mesh_display_cell_m)
        if s.mesh_colors == "camera" and len(meshes.vertices):
            seen = self._camera_colors.lookup(meshes.vertices)
            known = ~np.isnan(seen[:, 0])
            colors = np.array(meshes.colors, np.float32, copy=True)
            colors[known] = seen[known]
            meshes = dataclasses.replace(meshes, colors=colors)
        return meshes

