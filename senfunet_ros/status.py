"""~/status and /diagnostics: the node's health, counters, timings and engine statistics, as one
diagnostic_msgs/DiagnosticArray per status tick.

One DiagnosticStatus per sensor (rates over the recent window, recent drops, STALE streams, the
counters) and one for the pipeline (stage timings, frame-to-mesh latency, the engine's counters,
timings and statistics: every key it reports). A subscribed topic that never received anything is
named in the log once.
"""
from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from senfunet_ros import conversions as conv
from senfunet_ros import params as P
from senfunet_ros.health import HealthMonitor
from senfunet_ros.ingest import DROP_REASONS, Ingest, split_stream_errors
from senfunet_ros.pipeline import Pipeline


ENGINE_STATS_PERIOD_S = 5.0  # engine.stats() takes the engine's locks and sums the grid: at most this often
# a silent topic whose publishers are of the subscribed type is warned about after this many diagnostics windows,
# not one: a player waits for every topic's subscriber, then a moment, before it publishes (no false alarm)
SILENT_WITH_PUBLISHERS_WINDOWS = 4


# What a drop usually means and what to check, for the reasons whose message gives no detail of
# its own ({s}: the sensor's SensorSettings).
DROP_HINTS: dict[str, str] = {
    "no_camera_info": "no usable CameraInfo arrived on {s.camera_info_topic} within pose_max_wait_s of the image "
                      "(see bad_camera_info, if any were refused); check the topic (parameter "
                      "{s.name}.camera_info_topic) and that its publisher sends more than once",
    "bad_camera_info": "the CameraInfo on {s.camera_info_topic} has no usable K, width or height",
    "bad_encoding": "publish depth on {s.depth_topic} as 32FC1 (metres) or 16UC1 (millimetres)",
    "size_mismatch": "the depth images on {s.depth_topic} differ in aspect ratio from the CameraInfo on "
                     "{s.camera_info_topic} (another size of the same aspect ratio is taken, K scaled)",
    "all_invalid": "every pixel of the depth image was 0, negative, NaN or inf",
    "out_of_range": "no depth pixel lay within {s.depth_min_m}..{s.depth_max_m} m inside the image border",
    "bad_pose": "a pose on {s.pose_topic} had NaN/inf or a quaternion of length other than 1",
    "pose_conflict": "a pose on {s.pose_topic} (or a /tf transform) came again for a stamp already given, with "
                     "another value; the first is kept: two publishers on one topic, or a driver rewriting its past?",
    "pose_timeout": "no pose on {s.pose_topic} (or /tf transform) at or after the image's stamp within "
                    "pose_max_wait_s; check that poses arrive and are stamped on the depth images' clock, or raise "
                    "pose_max_wait_s if they come later than that",
    "pose_gap": "the poses around the image's stamp are more than pose_tolerance_s from it; publish poses more "
                "often or raise pose_tolerance_s",
    "queue_full": "more than queue_size images waited for their poses; the oldest went",
    "behind": "integration cannot keep up with the sensors, and the images it set aside (max_lag_s behind the "
              "newest) fill behind_buffer_mb: the next ones are skipped (a smaller working_width, a lower sensor "
              "rate or a larger behind_buffer_mb helps)",
    "out_of_order": "a depth stamp on {s.depth_topic} went back in time, behind the sensor's two newest",
    "duplicate": "a depth stamp on {s.depth_topic} came twice",
    "bad_stamp": "a stamp far (time_jump_s) from its stream's timeline, or 0; check the driver's clock",
    "time_jump": "time restarted (a bag looping?): the queued images were flushed, messages that showed it "
                 "beyond a queue's worth went, and messages of the old time handed over after it too",
    "engine_error": "the engine rejected the frame",
    "shutdown": "the node stopped while the frame was being integrated, or had set it aside",
    "map_reset": "the map was reset or replaced while the image waited or was set aside",
}


def counter_warnings(before: dict[str, dict[str, Any]], now: dict[str, dict[str, Any]], settings: P.Settings,
                     resolved: dict[str, dict[str, str]] | None = None) -> list[tuple[tuple[str, ...], str]]:
    """(key, message) of each warning that Ingest's counters `now` call for since `before`: new drops,
    by reason (the error, else the reason's hint), a distorted camera_info, frames without colour,
    depth images missing from the stream's regular stamps,
    the sensors' notes (each once: colour of another aspect ratio, a camera_info's K taken as given,
    pixels further apart than 1.5 voxels) and frames set aside. The caller rate-limits them by key.
    resolved: sensor -> stream -> the topic as subscribed (namespace, remapping), named instead of the
    parameter's value."""
    out: list[tuple[tuple[str, ...], str]] = []
    topics = {}
    for given in settings.sensors:
        subscribed = (resolved or {}).get(given.name, {})
        names: dict[str, Any] = {f"{stream}_topic": topic for stream, topic in subscribed.items()}
        topics[given.name] = dataclasses.replace(given, **names)
    for sensor, counters in now.items():
        last = before.get(sensor, {})
        for reason, count in counters["dropped"].items():
            new = count - last.get("dropped", {}).get(reason, 0)
            if new > 0:
                why = counters["errors"].get(reason) or DROP_HINTS[reason].format(s=topics[sensor])
                out.append(((sensor, reason), f"{sensor}: dropped {new} message(s): {reason}: {why} "
                                              f"({count} so far; see ~/status)"))
        if counters["distorted"] and not last.get("distorted", False):
            out.append(((sensor, "distorted"), f"{sensor}: the camera_info on {topics[sensor].camera_info_topic} has "
                        "non-zero distortion coefficients, which the node does not apply: it takes the depth images "
                        "as rectified (pinhole K); subscribe to the driver's rectified depth topic"))
        new_without_color = counters["without_color"] - last.get("without_color", 0)
        if new_without_color > 0:
            colour_error = split_stream_errors(counters["errors"].get("bad_encoding", ""))[1]
            colour_came = counters.get("color_received", 0) > last.get("color_received", 0)
            why = (f"the colour images on {topics[sensor].color_topic} cannot be decoded ({colour_error})"
                   if colour_error else
                   f"no colour image came on {topics[sensor].color_topic} meanwhile (has its stream stopped?)"
                   if not colour_came else
                   f"no colour image within color_tolerance_s ({settings.color_tolerance_s:g} s) of their depth "
                   f"stamps came in time, though colour arrives on {topics[sensor].color_topic}; check the stamps "
                   "or raise color_tolerance_s (or queue_size, if colour comes late: frames wait for it until it "
                   "passes them, at most pose_max_wait_s, and only while they fill less than half the queue)")
            out.append(((sensor, "without_color"), f"{sensor}: {new_without_color} frame(s) integrated without "
                        f"colour: {why} ({counters['without_color']} so far; see ~/status)"))
        new_missing = counters.get("missing_depth", 0) - last.get("missing_depth", 0)
        if new_missing > 0:
            out.append(((sensor, "missing_depth"), f"{sensor}: {new_missing} depth image(s) missing on "
                        f"{topics[sensor].depth_topic} ({counters['missing_depth']} so far; the latest gap "
                        f"{counters['missing_depth_gap']}): lost before they reached the node (a burst faster than "
                        "it takes images overflows its subscription's queue; a recorder that dropped them) or "
                        "skipped by the driver; see ~/status"))
        # each said once (colour of another aspect ratio goes on being refused, counted in color_refused)
        for key, note in counters["notes"].items():
            if key not in last.get("notes", {}):
                out.append(((sensor, key), f"{sensor}: {note}"))
        if counters["set_aside"] > last.get("set_aside", 0):
            out.append(((sensor, "set_aside"), f"{sensor}: integration is behind the sensors: images more than "
                        f"max_lag_s behind the newest are set aside ({counters['set_aside_now']} now, "
                        f"{counters['set_aside']} so far) and integrated once the sensors pause"))
    return out


class CounterWarnings:
    """The warnings Ingest's counters call for since the last call (`counter_warnings`), with a restart
    of time in mind: a restart tells of the messages it cost itself (a looping bag: every pass), so
    its `time_jump` drops (flushed queues, messages of the old time in flight) are not warned per
    stream for `hold_s` after it. While a restart may be under way, `bad_stamp` drops wait, at most
    `hold_s`: a confirmed restart takes the new timeline's first messages back (no longer dropped),
    or counts them as its loss; those left are bad stamps and are warned (an unset stamp right after
    a restart too), as are those of a driver whose stamps are always off (it keeps a restart
    pending). Called from one thread (the node's integration tick)."""

    def __init__(self, ingest: Ingest, *, hold_s: float) -> None:
        self._ingest = ingest
        self._hold_s = hold_s
        self._last = ingest.ledger.counters()
        self._time_jumps_seen, self._time_jump_at_s = 0, -float("inf")  # the latest restart seen
        self._held_since: dict[tuple[str, ...], float] = {}  # drops held while a restart may be under way

    def since_last(self, settings: P.Settings, resolved: dict[str, dict[str, str]] | None = None
                   ) -> list[tuple[tuple[str, ...], str]]:
        """(key, message) of each warning due now (`counter_warnings`' arguments)."""
        # asked before and after the counters are read: drops they hold may come from candidates of a new
        # timeline that appeared, or were confirmed as a restart (time_jumps), between the two reads
        pending = self._ingest.restart_pending()
        counters = self._ingest.ledger.counters()
        pending = pending or self._ingest.restart_pending()
        now_s = time.monotonic()
        jumps = sum(c["time_jumps"] for c in counters.values())  # read with the drops it caused
        if jumps != self._time_jumps_seen:
            self._time_jumps_seen, self._time_jump_at_s = jumps, now_s
        restarting = now_s - self._time_jump_at_s < self._hold_s
        if not pending:  # the holds of a restart that was confirmed or ended: the next restart's start afresh
            self._held_since.clear()
        due = []
        for key, message in counter_warnings(self._last, counters, settings, resolved):
            if key[-1] == "bad_stamp" and pending:
                if now_s - self._held_since.setdefault(key, now_s) < self._hold_s:
                    sensor, reason = key  # compared again next time
                    counters[sensor]["dropped"][reason] = self._last[sensor]["dropped"][reason]
                    continue
            self._held_since.pop(key, None)
            if not (key[-1] == "time_jump" and restarting):
                due.append((key, message))
        self._last = counters
        return due


class ThrottledWarnings:
    """At most one warning per key per period (wall time: sim time may stand still); thread-safe. The
    period starts at `period_s` and doubles each time the cause comes back within twice it, up to
    `max_period_s` (a robot that runs behind for hours logs a dozen lines an hour about it, not
    hundreds); a cause quiet for twice its period starts again at `period_s`."""

    def __init__(self, log: Callable[[str], Any], *, period_s: float, max_period_s: float = 300.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._log, self._clock = log, clock
        self._period_s = period_s
        self._max_period_s = max(period_s, max_period_s)
        self._warned: dict[tuple[str, ...], tuple[float, float]] = {}  # key -> (when warned, its period then)
        self._lock = threading.Lock()

    def warn(self, key: tuple[str, ...], message: str) -> None:
        now = self._clock()
        with self._lock:
            last_s, period_s = self._warned.get(key, (-1e9, self._period_s))
            if now - last_s < period_s:
                return
            recurring = now - last_s < 2 * period_s
            period_s = min(2 * period_s, self._max_period_s) if recurring else self._period_s
            self._warned[key] = (now, period_s)
        self._log(message + (f" (recurring: said again in {period_s:.0f} s at the earliest; ~/status counts every "
                             "one)" if recurring else ""))


def _short(value: Any) -> str:
    """A statistic as diagnostics text: floats rounded."""
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def _flat(prefix: str, stats: dict[str, Any]) -> list[tuple[str, str]]:
    """(key, text) of statistics; a dict (per sensor) gives one key per entry, so every value parses."""
    out: list[tuple[str, str]] = []
    for key, value in stats.items():
        out += _flat(f"{prefix}{key}.", value) if isinstance(value, dict) else [(f"{prefix}{key}", _short(value))]
    return out


class StatusReport:
    """Builds the node's DiagnosticArray from the pipeline and the node's monitors (shared, read
    here): `health`, `timings` (stage -> an object with last_ms, mean_ms) and `latency` (with
    summary()). topics: sensor -> stream -> topic, for the warnings; warn(key, text): the node's
    throttled warning; graph_hint(topic): what the ROS graph says of a topic nothing came on (its
    publishers), to add to that warning, and whether it has publishers of the subscribed type."""

    def __init__(self, pipeline: Pipeline, health: HealthMonitor, timings: dict[str, Any], latency: Any, *,
                 topics: dict[str, dict[str, str]], hardware_id: str, warn: Callable[[tuple[str, ...], str], None],
                 logger: Any, name: str = P.NODE_NAME,
                 graph_hint: Callable[[str], tuple[str, bool]] = lambda topic: ("", False)) -> None:
        self.pipeline = pipeline
        # each status is named "<node name>: <part>", as diagnostic_updater does: two fusion nodes (`-r __node:=front`)
        # must not share names, which the aggregator and rqt_robot_monitor key their entries by
        self.name = name
        self.health = health
        self.timings = timings
        self.latency = latency
        self.topics = topics
        self.hardware_id = hardware_id
        self._warn = warn
        self._logger = logger
        self._graph_hint = graph_hint
        # (monotonic time, engine.stats(), of which of the pipeline's maps)
        self._engine_stats_at: tuple[float, dict[str, Any], int] = (-1e9, {}, 0)
        self._engine_stats_lock = threading.Lock()
        self._silent_warned: set[tuple[str, str]] = set()

    def message(self, fixed_frame: str) -> DiagnosticArray:
        """Per-sensor health (rates over the recent window, recent drops, STALE streams) with the
        counters, then the pipeline's timings and the engine's statistics (every key it reports)."""
        pipeline = self.pipeline
        msg = DiagnosticArray()
        sec, nanosec = conv.ns_to_stamp(pipeline.latest_stamp_ns)
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        msg.header.frame_id = fixed_frame
        counters = pipeline.ingest.ledger.counters()
        self.health.counters(counters)
        reports = self.health.report()
        self._warn_silent_topics(reports)
        for sensor, c in counters.items():
            report = reports[sensor]
            values = [KeyValue(key=k, value=str(c[k])) for k in
                      ("received", "integrated", "extrapolated", "queue_depth", "set_aside", "set_aside_now",
                       "color_received", "pose_received", "time_jumps", "without_color", "color_refused", "distorted",
                       "missing_depth")]
            if c["missing_depth_gap"]:
                values.append(KeyValue(key="missing_depth_gap", value=c["missing_depth_gap"]))
            values += [KeyValue(key=f"note.{key}", value=note) for key, note in c["notes"].items()]
            for stream, r in report.streams.items():
                values += [KeyValue(key=f"rate_hz.{stream}", value=f"{r.rate_hz:.2f}"),
                           KeyValue(key=f"silent_s.{stream}", value=f"{r.silent_s:.1f}")]
            values += [KeyValue(key=f"dropped.{reason}", value=str(c["dropped"][reason])) for reason in DROP_REASONS]
            values += [KeyValue(key=f"recent_dropped.{reason}", value=str(n))
                       for reason, n in report.recent_drops.items()]
            values.append(KeyValue(key="recent_missing_depth", value=str(report.recent_missing)))
            values += [KeyValue(key=f"error.{reason}", value=why) for reason, why in c["errors"].items()]
            summary = (f"{report.message}; {c['integrated']} of {c['received']} frames integrated, "
                       f"{sum(c['dropped'].values())} messages dropped in all")
            msg.status.append(DiagnosticStatus(level=bytes([int(report.level)]), name=f"{self.name}: {sensor}",
                                               message=summary, hardware_id=self.hardware_id, values=values))
        values = [KeyValue(key=f"{stage}_ms", value=f"{t.last_ms:.1f} (mean {t.mean_ms:.1f})")
                  for stage, t in self.timings.items()]
        values += [KeyValue(key=k, value=f"{v:.2f}") for k, v in self.latency.summary().items()]
        values += [KeyValue(key="time_jumps", value=str(pipeline.time_jumps)),
                   KeyValue(key="frames_failed", value=str(pipeline.frames_failed)),
                   KeyValue(key="frames_unfinished", value=str(pipeline.frames_unfinished))]
        engine = pipeline.engine
        counters_engine = dict(getattr(engine, "counters", {}))
        values += [KeyValue(key="alpha_backlog_blocks", value=str(counters_engine.get("alpha_backlog_blocks", 0))),
                   KeyValue(key="mesh_backlog_blocks", value=str(counters_engine.get("mesh_backlog_blocks", 0))),
                   KeyValue(key="mesh_blocks", value=str(counters_engine.get("meshed_blocks", 0)))]
        values += [KeyValue(key=f"engine.counters.{k}", value=str(v)) for k, v in counters_engine.items()]
        values += [KeyValue(key=f"engine.{k}_ms", value=f"{v * 1e3:.1f}")
                   for k, v in dict(getattr(engine, "timings_s", {})).items()]
        stats = self._engine_stats()
        values += [KeyValue(key=k, value=v) for k, v in _flat("engine.stats.", stats)]
        level, message = DiagnosticStatus.OK, f"{counters_engine.get('meshed_blocks', 0)} mesh blocks"
        blocks, max_blocks = stats.get("blocks", 0), stats.get("max_blocks") or 0
        if counters_engine.get("spill_failing") and 0 < max_blocks < blocks:  # the bound given up for now
            level = DiagnosticStatus.WARN
            message += (f"; the map holds {blocks} blocks, over its bound max_map_blocks {max_blocks}: its evictions "
                        f"were abandoned ({counters_engine['spill_failures']} so far), the spill file cannot be "
                        "written (see the log)")
        msg.status.append(DiagnosticStatus(level=level, name=f"{self.name}: pipeline", message=message,
                                           hardware_id=self.hardware_id, values=values))
        return msg

    def _warn_silent_topics(self, reports: dict[str, Any]) -> None:
        """One warning per subscribed topic that has received nothing for a window (once: an unused
        optional colour topic must not fill the log)."""
        for sensor, report in reports.items():
            for stream, r in report.streams.items():
                if r.never and (sensor, stream) not in self._silent_warned:
                    topic = self.topics[sensor][stream]
                    hint, publishers = self._graph_hint(topic)
                    if publishers and r.silent_s < SILENT_WITH_PUBLISHERS_WINDOWS * self.health.window_s:
                        continue  # judged again on the next report
                    self._silent_warned.add((sensor, stream))
                    config = self.pipeline.engine.config
                    if stream == "color" and not dict(zip(config.sensors, config.sensor_uses_rgb)).get(sensor, True):
                        # nothing is missing
                        self._logger.info(f"{sensor}: nothing on {topic}; {sensor}'s feature net takes no colour, "
                                          "only mesh_colors: camera would show it")
                        continue
                    self._logger.warning(
                        f"{sensor}: nothing received on {topic} for {r.silent_s:.0f} s; check "
                        f"the topic name (parameter {sensor}.{stream}_topic), its message type and QoS"
                        + (" (colour is optional: set it to '' if there is none)" if stream == "color" else "")
                        + hint)

    def refresh_engine_stats(self) -> None:
        """engine.stats() when the last are due, waiting for the map: for the mesh thread, after each
        publication. The status timer does not wait, and under a map bound updates, evictions (seconds
        each) and the weighting net's turns hold the map one after the other: the statistics it found
        the map free for were the first ones, shown for the whole run."""
        self._engine_stats(wait=True)

    def _engine_stats(self, *, wait: bool = False) -> dict[str, Any]:
        """engine.stats(), at most every ENGINE_STATS_PERIOD_S (a failure keeps the last ones). Called by
        the status timer and the mesh thread: the lock guards the last statistics, not the engine call
        (which may wait for the map), so neither thread holds the other up."""
        now = time.monotonic()
        maps = self.pipeline.maps  # a reset or load_map since: the new map's, now
        with self._engine_stats_lock:
            at, last, of_map = self._engine_stats_at
        if now - at < ENGINE_STATS_PERIOD_S and of_map == maps:
            return last
        try:
            stats = self.pipeline.engine.stats(wait=wait)
        except Exception as err:  # statistics never stop the status: the last ones, tried again when due
            self._warn(("engine_stats",), f"engine statistics failed: {err!r}")
            stats = last
        if stats is None:  # a save or extraction holds the map: the last ones, tried again next time
            return last
        with self._engine_stats_lock:
            self._engine_stats_at = (now, stats, maps)
        return stats
