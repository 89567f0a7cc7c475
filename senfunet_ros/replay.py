"""Offline replay: a recording through the node's own message handling into the engine.

The bag's raw CDR bytes are deserialised into the real rclpy message classes (the same objects a
live subscription delivers) and handed to `senfunet_ros.ingest.Ingest` exactly like the node's
subscription callbacks do; the ready frames are drained into the engine after every message.
Ingest decides by stamps and arrival order only, so one bag always gives the same frames and,
with torch pinned to a fixed thread count, the same mesh bytes.

    result = replay_bag("bags/sim_room", "out/replay", gt="bags/sim_room_gt.ply")
    result.stats["sensors"]["tof"]["integrated"]
"""
from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from collections.abc import Callable, Iterator

import numpy as np

from senfunet_core.files import atomic_file
from senfunet_ros import params as P
from senfunet_ros.params import engine_config, engine_weights, ingest_config
from senfunet_ros.bagio import (BagBrokenError, BagError, BagMessage, TopicInfo, absolute_topic, is_cdr,
                                message_class, normalize_msgtype, open_bag)
from senfunet_ros.conversions import PoseType
from senfunet_ros.ingest import Frame, Ingest
from senfunet_ros.params_file import load_settings
from senfunet_ros.pipeline import MESH_FILES, Pipeline, Stream

__all__ = [
    "bag_frames",
    "ingest_config",
    "engine_config",
    "Route",
    "TopicRouter",
    "ReplayResult",
    "replay_bag",
    "MESH_FILES",
    "drop_summary",
    "DISTORTED_NOTE",
]

_IMAGES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
_CAMERA_INFO = "sensor_msgs/msg/CameraInfo"


# --------------------------------------------------------------------------------------------
# Topics -> Ingest


@dataclass(frozen=True)
class Route:
    topic: str
    # (sensor, stream) of each input the topic feeds: one topic may feed several sensors (one /odom for both,
    # as the node subscribes it once per sensor); sensor "" for /tf and /tf_static (every sensor's); stream a
    # senfunet_ros.pipeline.Stream value
    targets: tuple[tuple[str, str], ...]
    msgtype: str
    msg_class: type | None  # None: deserialised with rosbags' type store (tf2_msgs has no wheel here)


_TF_MSGTYPE = "tf2_msgs/msg/TFMessage"


def _merged_info(topic: str, infos: list[TopicInfo]) -> TopicInfo:
    """One topic recorded under several spellings ('tof/depth' and '/tof/depth': `bagio.absolute_topic`) as
    one TopicInfo named `topic`: counts and types summed; the first spelling's definition."""
    if len(infos) == 1:
        return infos[0]
    types: dict[str, int] = {}
    for info in infos:
        for msgtype, n in (info.types or {normalize_msgtype(info.msgtype): info.count}).items():
            types[msgtype] = types.get(msgtype, 0) + n
    main = max(types, key=lambda t: types[t])
    return TopicInfo(topic, main, sum(info.count for info in infos), infos[0].msgdef, infos[0].digest, types,
                     any(info.latched for info in infos))


class TopicRouter:
    """Which bag topic feeds which sensor stream; checks the bag has what the node needs.

    Raises BagError (one line) when a sensor's depth, camera_info or pose topic (or, with
    pose_type tf, /tf) is missing or has the wrong or an unknown type. Colour topics and
    /tf_static are optional. Other topics are ignored.
    """

    def __init__(self, settings: P.Settings, topics: dict[str, TopicInfo], bag_path: str | Path) -> None:
        self.bag_path = Path(bag_path)
        self.routes: dict[str, Route] = {}  # by absolute topic name
        self._recorded: dict[str, str] = {}  # a routed topic as the bag names it -> its absolute name
        self.undecodable: dict[str, int] = {}
        self.not_cdr: set[str] = set()  # topics with undecodable messages that are not CDR at all
        self.not_cdr_count: dict[str, int] = {}  # ... how many
        self.recorded: dict[str, int] = {}  # routed topic -> messages recorded on it (every spelling and type)
        self.other_types: dict[str, dict[str, int]] = {}  # routed topic -> its other recorded types (left out)
        pose_type = PoseType(settings.pose_type)
        missing: list[str] = []
        empty: list[str] = []  # of them, those the bag lists, with no message recorded (a latched one missed?)
        missing_params: list[str] = []  # the parameters that name the missing topics
        # sensor, stream, topic, accepted types, required
        wanted: list[tuple[str, Stream, str, tuple[str | None, ...], bool]] = []
        for sensor in settings.sensors:
            wanted += [(sensor.name, Stream.CAMERA_INFO, sensor.camera_info_topic, (_CAMERA_INFO,), True),
                       (sensor.name, Stream.DEPTH, sensor.depth_topic, _IMAGES, True),
                       (sensor.name, Stream.COLOR, sensor.color_topic, _IMAGES, False)]
            if pose_type is not PoseType.TF:
                wanted.append((sensor.name, Stream.POSE, sensor.pose_topic, (pose_type.msgtype,), True))
        # the bag's topics by their absolute names: a recorder may have written 'tof/depth' for /tof/depth, and
        # two recordings merged may hold both spellings, one topic whose messages are under either name
        spellings: dict[str, list[str]] = {}
        for recorded in topics:
            spellings.setdefault(absolute_topic(recorded), []).append(recorded)
        by_name = {name: _merged_info(name, [topics[t] for t in recorded]) for name, recorded in spellings.items()}
        if pose_type is PoseType.TF:  # a fixed rig's whole tree may be static (/tf_static alone)
            static = by_name.get("/tf_static")
            wanted += [("", Stream.TF, "/tf", (_TF_MSGTYPE,), static is None or static.count == 0),
                       ("", Stream.TF_STATIC, "/tf_static", (_TF_MSGTYPE,), False)]
        for sensor_name, stream, topic, expected, required in wanted:
            if not topic:
                continue
            topic = absolute_topic(topic)
            info = by_name.get(topic)
            if info is None or info.count == 0:  # an optional topic recorded empty is absent too (colour: said)
                if required:
                    missing.append(topic)
                    empty += [topic] if info is not None else []
                    if sensor_name:
                        missing_params.append(f"{sensor_name}.{Stream(stream).value}_topic")
                continue
            # a topic recorded with several types (two recordings merged): the most recorded type the
            # node takes there; the others are left out, and said so
            types = info.types or {normalize_msgtype(info.msgtype): info.count}
            taken = sorted((t for t in types if t in expected), key=lambda t: -types[t])
            msgtype = taken[0] if taken else normalize_msgtype(info.msgtype)
            if len(types) > 1 and taken:
                self.other_types[topic] = {t: n for t, n in types.items() if t != msgtype}
            if msgtype not in expected:
                accepted = " or ".join(t for t in expected if t)
                raise BagError(self._type_error(topic, msgtype, accepted, stream, settings))
            target = (sensor_name, Stream(stream).value)
            route = self.routes.get(topic)
            if route is not None and route.msgtype != msgtype:
                raise BagError(f"{self.bag_path}: topic {topic} is named for inputs that take different types "
                               f"({', '.join(f'{s}.{kind}_topic' for s, kind in (*route.targets, target))}); give "
                               "each its own topic with --params")
            msg_class = None if msgtype == _TF_MSGTYPE else message_class(msgtype)
            self.routes[topic] = Route(topic, (*route.targets, target) if route else (target,), msgtype, msg_class)
            self._recorded.update(dict.fromkeys(spellings[topic], topic))
            self.recorded[topic] = info.count
        if missing:
            have = sorted(topics)
            shown = ", ".join(have[:12]) + (f" (+{len(have) - 12} more)" if len(have) > 12 else "")
            listed = (f" ({', '.join(empty)} listed, but recorded without a message: a latched topic published "
                      "before the recording started?)" if empty else "")
            raise BagError(f"{self.bag_path}: no messages on {', '.join(missing)}{listed}; the bag has: "
                           f"{shown or 'no topics'}; " + self._missing_hint(missing_params, "/tf" in missing, topics,
                                                                              routed=set(self._recorded)))
        self.ignored = {t: i.msgtype for t, i in topics.items() if t not in self._recorded}
        self._typestore: Any = None

    @staticmethod
    def _missing_hint(params: list[str], no_tf: bool, topics: dict[str, TopicInfo], *, routed: set[str]) -> str:
        """What to do about missing topics: the parameters that name them, for a bag of one sensor's
        depth that it needs two, and for a bag without /tf under pose_type tf, the pose topics it has
        instead. `routed`: the bag's topics already taken."""
        hints = []
        other_images = [t for t, i in topics.items() if t not in routed and normalize_msgtype(i.msgtype) in _IMAGES]
        depthless = [param.removesuffix(".depth_topic") for param in params if param.endswith(".depth_topic")]
        infoless = [param.removesuffix(".camera_info_topic") for param in params
                    if param.endswith(".camera_info_topic")]
        any_info = any(normalize_msgtype(i.msgtype) == _CAMERA_INFO for i in topics.values())
        unexplained = list(params)
        if depthless and not other_images:
            hints.append(f"the bag holds no other image topic to take as {' and '.join(depthless)}'s depth: "
                         "SenFuNet fuses the depth of two sensors; record both sensors' depth images")
            unexplained = []  # a bag of one sensor: its other topics are missing too
        elif infoless and not any_info:
            hints.append(f"the bag holds no {_CAMERA_INFO} topic to take as {' and '.join(infoless)}'s: the node "
                         "takes each sensor's intrinsics (K) from its camera_info; record the camera_info topics with "
                         "the depth images")
            unexplained = [param for param in unexplained if not param.endswith(".camera_info_topic")]
        if unexplained:
            hints.append(f"set {', '.join(unexplained)} to the bag's topics with --params")
        if "/tf" in topics and any(param.endswith(".pose_topic") for param in params):
            hints.append("the bag has /tf: for poses from TF, set pose_type: tf with --params")
        if no_tf:
            kinds = {t: PoseType.from_msgtype(normalize_msgtype(i.msgtype)) for t, i in topics.items()}
            pose_topics = sorted(t for t, kind in kinds.items() if kind is not None)
            named = {kind.value for kind in kinds.values() if kind is not None}
            to = f"pose_type: {named.pop()}" if len(named) == 1 else "pose_type to their type"
            hints.append("pose_type tf reads poses from /tf and /tf_static, which the bag does not have" + (
                f"; it has pose topics ({', '.join(pose_topics)}): set {to} and <sensor>.pose_topic with --params"
                if pose_topics else ""))
        return "; ".join(hints)

    def _type_error(self, topic: str, msgtype: str, expected: str, stream: str, settings: P.Settings) -> str:
        if stream == "pose":
            alt = PoseType.from_msgtype(msgtype)
            if alt is not None:
                return (f"{self.bag_path}: topic {topic} is {msgtype} but parameter pose_type is "
                        f"'{settings.pose_type}'; set pose_type: {alt.value} with --params")
        try:
            message_class(msgtype)
            known = True
        except BagError:
            known = False
        what = f"has type {msgtype}" + ("" if known else ", unknown here,")
        return (f"{self.bag_path}: topic {topic} {what} but the node takes {expected} there; record {expected} or "
                "remap the topic with --params")

    @property
    def topics(self) -> set[str]:
        """The routed topics as the bag names them."""
        return set(self._recorded)

    def decode(self, msg: BagMessage) -> tuple[Route, Any] | None:
        """(route, message), or None for an unrouted topic or bytes that do not deserialise. Messages
        are rclpy's classes (what a live subscription delivers), TF messages rosbags' own."""
        from rclpy.serialization import deserialize_message

        route = self.routes.get(self._recorded.get(msg.topic, ""))
        if route is None or normalize_msgtype(msg.msgtype) != route.msgtype:  # unrouted, or another type
            return None
        try:
            if route.msg_class is None:
                if self._typestore is None:
                    from rosbags.typesys import Stores, get_typestore

                    self._typestore = get_typestore(Stores.ROS2_JAZZY)
                return route, self._typestore.deserialize_cdr(msg.data, route.msgtype)
            return route, deserialize_message(msg.data, route.msg_class)
        except Exception:
            self.undecodable[route.topic] = self.undecodable.get(route.topic, 0) + 1
            if not is_cdr(msg.data):
                self.not_cdr.add(route.topic)
                self.not_cdr_count[route.topic] = self.not_cdr_count.get(route.topic, 0) + 1
            return None

    def failed(self, msg: BagMessage) -> tuple[tuple[str, str], ...]:
        """The (sensor, stream) inputs of a message that `decode` could not deserialise (of a routed topic and
        type); () for others."""
        route = self.routes.get(self._recorded.get(msg.topic, ""))
        if route is None or normalize_msgtype(msg.msgtype) != route.msgtype:
            return ()
        return tuple(target for target in route.targets if target[0])

    @staticmethod
    def dispatch(ingest: Ingest, route: Route, message: Any) -> str | None:
        """Hand one message to Ingest for each input its topic feeds, as the node's subscription callbacks
        do; returns a drop reason (the last input's that dropped it), or None."""
        reasons = [Pipeline.dispatch_to(ingest, sensor, stream, message) for sensor, stream in route.targets]
        return next((reason for reason in reversed(reasons) if reason is not None), None)


# --------------------------------------------------------------------------------------------
# Replay


@dataclass
class ReplayResult:
    stats: dict[str, Any]
    meshes: dict[str, Any] = field(default_factory=dict)  # file stem -> Mesh
    files: dict[str, Path] = field(default_factory=dict)  # file stem -> path
    error: str | None = None  # the bag broke midway or nothing could be fused
    interrupted: bool = False

    @property
    def ok(self) -> bool:
        return self.error is None and not self.interrupted


@dataclass
class _Run:
    """What one pass through the bag gave."""

    bag_info: dict[str, Any]
    router: TopicRouter
    total: int  # messages recorded on the fused topics
    read: int = 0
    error: str | None = None
    interrupted: bool = False
    read_s: float = 0.0
    # colour sensors whose colour topic the bag lacks: their note (every frame is fused without colour)
    colourless: dict[str, str] = field(default_factory=dict)


def replay_bag(bag: str | Path, out_dir: str | Path, *, params: str | Path | None = None,
               gt: str | Path | None = None, progress: bool = True, threads: int = 1,
               weights: str | None = None, compare: bool = False,
               log: Callable[[str], None] | None = None, stop: threading.Event | None = None) -> ReplayResult:
    """Fuse a recording as fast as possible and write DIR/mesh.ply (the fused, filtered mesh) and
    DIR/stats.json (plus mesh metrics against `gt` if given). With `compare`, also DIR/<sensor>.ply
    per sensor and DIR/tsdf_fusion.ply (the plain TSDF Fusion baseline, integrated alongside: more
    time and memory, which is why it is opt-in).

    Raises BagError before anything is fused if the bag cannot be used, ValueError for bad
    parameters. A bag that breaks midway still gets its meshes: `result.error` says where it broke.
    `threads` pins torch's CPU threads: the mesh bytes depend on it, so keep it fixed (default 1).
    `stop`, once set, ends the reading like a KeyboardInterrupt (`result.interrupted`): what was
    fused is still meshed and written.
    """
    t_start = time.perf_counter()
    log = log or (lambda text: None)
    settings = load_settings(params, {"weights": weights} if weights is not None else None)
    gt_mesh = _read_gt(gt)
    out = Path(out_dir)
    with open_bag(bag) as reader:
        TopicRouter(settings, reader.topics, bag)  # a BagError comes before the heavy imports
    _prepare_out(out)  # and a bad --out before the fusing, not after it
    with _out_lock(out):
        return _replay(bag, out, settings, gt=gt, gt_mesh=gt_mesh, progress=progress, threads=threads,
                       compare=compare, params=params, log=log, stop=stop, t_start=t_start)


def _replay(bag: str | Path, out: Path, settings: P.Settings, *, gt: str | Path | None, gt_mesh: Any,
            progress: bool, threads: int, compare: bool, params: str | Path | None, log: Callable[[str], None],
            stop: threading.Event | None, t_start: float) -> ReplayResult:
    """`replay_bag` once its bag, settings and output folder are known to be usable."""
    warnings: list[str] = []  # every note and warning the run says as it goes (stats.json), besides printing it

    def say(text: str) -> None:
        warnings.append(text)
        log(text)

    if settings.tsdf_fusion and not compare:  # the node's switch; replay's is --compare
        say("note: parameter tsdf_fusion is for the node (~/save_mesh); replay writes tsdf_fusion.ply and each "
            "sensor's mesh with --compare")
    import torch  # heavy: only once the bag is known to be usable

    from senfunet_core.engine import SenFuNet

    fallback = P.device_fallback(settings)
    if fallback:  # the parameter's promise: the fall back is said, as the live node says it
        say(f"note: {fallback}")

    previous_threads = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        # offline: float32 alpha and features whatever the CPU; the node's map bound (max_map_blocks: evicted blocks
        # keep their fused meshes and come back from disk, so the mesh stays the same), except when
        # comparing: evicted blocks keep no per-sensor or TSDF Fusion mesh
        bound = {"max_blocks": 0} if compare else {}
        engine = SenFuNet(engine_config(settings, tsdf_fusion=compare, alpha_dtype="float32",
                                        feature_dtype="float32", **bound),
                          weights=engine_weights(settings))
        def pipeline_log(level: str, text: str) -> None:  # a camera frame_id that is no optical frame, a restart...
            if level == "error":
                log(text)
            else:
                say(f"{level}: {text}")

        pipeline = Pipeline(engine, Ingest(ingest_config(settings)), on_time_jump=settings.on_time_jump,
                            log=pipeline_log)
        engine_log = _EngineLog(say)  # the engine's own warnings (a map bound below what a frame sees)
        logging.getLogger("senfunet").addHandler(engine_log)
        try:
            run = _fuse(bag, settings, pipeline, progress=progress, log=say, stop=stop)
        finally:
            logging.getLogger("senfunet").removeHandler(engine_log)
    finally:
        torch.set_num_threads(previous_threads)

    counters = pipeline.ingest.ledger.counters()
    n_integrated = sum(c["integrated"] for c in counters.values())
    result = ReplayResult(stats={}, error=run.error, interrupted=run.interrupted)
    timings: dict[str, Any] = {"read_decode_s": round(run.read_s - pipeline.integrate_s, 3),
                               "integrate_s": round(pipeline.integrate_s, 3),
                               "integrate_per_frame_ms": round(1e3 * pipeline.integrate_s / max(n_integrated, 1), 2)}
    if result.error is None and not run.interrupted and run.read < run.total:
        result.error = (f"{bag}: only {run.read} of the {run.total} recorded messages on the fused topics could be "
                        "read; the file is damaged")
    if n_integrated == 0 and result.error is None:
        dropped = "; ".join(f"{s}: " + (drop_summary(c) or "no frames") for s, c in counters.items())
        result.error = f"{bag}: no frame could be fused ({dropped}); see {out / 'stats.json'}"
    # what needs the map is read before its last mesh: the map's memory goes as that mesh is made. The
    # live node's mesh-update statistics (meshed blocks, how long they waited for the net) mean nothing
    # here: replay runs no mesh update, its one mesh judges every block
    engine_stats = {key: value for key, value in (pipeline.engine.stats() or {}).items()
                    if not key.startswith("meshed_blocks") and key != "oldest_unjudged_change_s"}
    gt_vertices = _observed_gt(pipeline.engine, gt_mesh) if n_integrated else None
    if n_integrated:
        torch.set_num_threads(max(1, int(threads)))
        try:
            t0 = time.perf_counter()
            saved = pipeline.save_meshes(out, sensors=settings.sensor_names if compare else (), tsdf_fusion=compare,
                                         then_reset=True)
            t_saved = time.perf_counter() - t0
        finally:
            torch.set_num_threads(previous_threads)
        result.meshes = {stem: s.mesh for stem, s in saved.items()}
        result.files = {stem: s.path for stem, s in saved.items()}
        timings["extract_s"] = {stem: round(s.extract_s, 3) for stem, s in saved.items()}
        timings["write_s"] = round(t_saved - sum(s.extract_s for s in saved.values()), 3)
    metrics, gt_info = _metrics(gt_vertices, gt, gt_mesh, result.meshes, timings)
    timings["total_s"] = round(time.perf_counter() - t_start, 3)
    result.stats = _stats(result, run, pipeline, settings, counters, params=params, threads=threads,
                          gt_info=gt_info, metrics=metrics, timings=timings, engine_stats=engine_stats,
                          warnings=warnings)
    with atomic_file(out / "stats.json") as file:  # whole or not at all (a full disk), as the meshes
        file.write((json.dumps(result.stats, indent=2, default=_json_default) + "\n").encode())
    result.files["stats"] = out / "stats.json"
    return result


def drop_summary(sensor: dict[str, Any]) -> str:
    """A sensor's drops by reason, each with what its last such message had wrong when known:
    "8 bad_camera_info (camera_info K has no positive finite focal lengths ...)"."""
    errors = sensor.get("errors", {})
    return ", ".join(f"{n} {reason}" + (f" ({errors[reason]})" if errors.get(reason) else "")
                     for reason, n in sensor["dropped"].items() if n)


DISTORTED_NOTE = ("its camera_info has non-zero distortion coefficients, which are not applied: the depth images are "
                  "taken as rectified (pinhole K); record the driver's rectified depth topic")


def _prepare_out(out: Path) -> None:
    """Create the output folder (ValueError, saying what to pass, when that is impossible)."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; pass a folder for mesh.ply and stats.json")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"--out {out}: cannot create the folder ({err.strerror}); pass a writable folder") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise ValueError(f"--out {out}: the folder is not writable; pass a writable folder")


@contextlib.contextmanager
def _out_lock(out: Path) -> Iterator[None]:
    """Hold the output folder for one replay: a second replay into it at once would leave one run's
    mesh.ply beside the other's stats.json. An advisory lock on the folder itself (nothing is written
    into it; the kernel lets go of it when the process ends, however it ends); ValueError when another
    replay holds it."""
    try:
        fd = os.open(out, os.O_RDONLY)
    except OSError:  # a folder that cannot be opened for reading (write-only): nothing to lock with
        yield
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ValueError(f"--out {out}: another senfunet replay is writing to this folder now; wait for it to "
                             "end, or pass another --out") from None
        except OSError:  # a file system without locks (some network ones): replay as before, unguarded
            pass
        yield
    finally:
        os.close(fd)  # closing lets go of the lock


def _read_gt(gt: str | Path | None) -> Any:
    if gt is None:
        return None
    from senfunet_core.ply import read_ply

    try:
        return read_ply(gt)
    except FileNotFoundError:
        raise ValueError(f"{gt}: no such ground-truth mesh") from None
    except Exception as err:
        raise ValueError(f"{gt}: cannot read the ground-truth mesh: {err}") from None


def _fuse(bag: str | Path, settings: P.Settings, pipeline: Pipeline, *, progress: bool,
          log: Callable[[str], None], stop: threading.Event | None = None) -> _Run:
    """Every routed message of the bag through the pipeline, draining ready frames after each."""
    from tqdm import tqdm

    ingest = pipeline.ingest
    with open_bag(bag) as reader:
        if reader.note:
            log(f"note: {reader.note}")
        router = TopicRouter(settings, reader.topics, bag)
        bag_info = {"path": str(bag), "storage": reader.storage, "messages": reader.message_count,
                    "duration_s": round(reader.duration_s, 6), "start_ns": reader.start_ns, "note": reader.note}
        run = _Run(bag_info, router, total=sum(reader.topics[t].count for t in router.topics))
        for sensor in settings.sensors:  # a colour net without colour: fused, but not as the weights were trained
            colour = absolute_topic(sensor.color_topic) if sensor.color_topic else ""
            if sensor.name in settings.rgb_sensors and colour not in router.routes:
                why = f"the bag has no messages on {colour}" if colour else f"{sensor.name}.color_topic is empty"
                run.colourless[sensor.name] = P.colourless_note(sensor, why)  # a sensor note: said with the others'
        for topic, others in router.other_types.items():
            left_out = ", ".join(f"{n} {t}" for t, n in others.items())
            log(f"topic {topic} was recorded with several types: its {router.routes[topic].msgtype} messages are "
                f"fused, the others left out ({left_out})")
        t_loop = time.perf_counter()
        # the live node's rule for a sensor's streams ending (silent for pose_max_wait_s: Ingest.stream_ends.end),
        # on the recording's clock, so that a bag gives the same frames live and replayed
        quiet_ns = int(settings.pose_max_wait_s * 1e9)
        spoke_ns: dict[str, int] = {}  # sensor -> log time of its last depth, colour or pose message

        def end_streams(sensors: list[str] | None) -> None:
            ingest.stream_ends.end(sensors)
            pipeline.drain(ingest.pop_ready())
            for _, line in pipeline.stream_ends():
                log(line)

        with tqdm(total=run.total, unit="msg", desc="replay", disable=not progress, dynamic_ncols=True,
                  mininterval=0.5) as bar:
            try:
                for msg in reader.messages(router.topics):
                    if stop is not None and stop.is_set():
                        raise KeyboardInterrupt
                    run.read += 1
                    bar.update(1)
                    decoded = router.decode(msg)
                    if decoded is None:
                        for name, stream in router.failed(msg):  # a damaged message: counted for its sensor
                            ingest.add_undecodable(name, stream)
                        continue
                    route, message = decoded
                    quiet = [name for name, t_ns in spoke_ns.items() if msg.log_time_ns - t_ns >= quiet_ns]
                    if quiet:
                        for name in quiet:
                            del spoke_ns[name]
                        end_streams(quiet)
                    for name, stream in route.targets:
                        if stream in (Stream.DEPTH, Stream.COLOR, Stream.POSE):
                            spoke_ns[name] = msg.log_time_ns
                    try:
                        for name, stream in route.targets:
                            pipeline.dispatch(name, stream, message)
                    except ValueError:  # a malformed message: Ingest refuses it like the node's callback
                        router.undecodable[route.topic] = router.undecodable.get(route.topic, 0) + 1
                        for name, stream in route.targets:
                            if name:
                                ingest.add_undecodable(name, stream)
                        continue
                    if route.targets[0][1] != "camera_info" and pipeline.drain(ingest.pop_ready()):
                        bar.set_postfix(frames=pipeline.frames_integrated, refresh=False)
            except BagBrokenError as err:
                run.error = str(err)
            except KeyboardInterrupt:
                run.interrupted = True
            end_streams(None)  # the bag ended (or the replay was stopped): no pose will come for what waits
        for note in reader.read_notes():  # damage read past (an MCAP index that broke midway)
            log(f"note: {note}")
        bag_info["read_notes"] = reader.read_notes()
        run.read_s = time.perf_counter() - t_loop
        damaged = False
        for topic, n in router.undecodable.items():
            line, not_cdr = _undecodable_line(topic, n, recorded=router.recorded.get(topic, n),
                                              not_cdr=router.not_cdr_count.get(topic, 0),
                                              msgtype=router.routes[topic].msgtype)
            log(line)
            damaged = damaged or not not_cdr
        if damaged:  # rclpy's C deserialiser prints a line of its own for some, naming no topic
            log("(lines such as 'sequence size exceeds remaining buffer' above came from deserialising those damaged "
                "messages)")
        counters = ingest.ledger.counters()
        for sensor in settings.sensors:  # colour in the bag, but not one image of it could be used
            c = counters[sensor.name]
            topic = absolute_topic(sensor.color_topic) if sensor.color_topic else ""
            if sensor.name in settings.rgb_sensors and topic in router.routes and c["integrated"] and not (
                    c["color_usable"]):
                run.colourless[sensor.name] = P.colourless_note(
                    sensor, f"none of the colour images on {topic} could be decoded")
    return run


class _EngineLog(logging.Handler):
    """The engine's log records of WARNING and above, said as the run's own lines."""

    def __init__(self, say: Callable[[str], None]) -> None:
        super().__init__(logging.WARNING)
        self._say = say

    def emit(self, record: logging.LogRecord) -> None:
        self._say(f"{record.levelname.lower()}: {record.getMessage()}")


def _undecodable_line(topic: str, n: int, *, recorded: int, not_cdr: int, msgtype: str) -> tuple[str, bool]:
    """What replay says of a topic's n messages that could not be deserialised, of `recorded`, and whether they
    are of a bag of another kind: most of them not CDR at all (ROS 1, JSON); else, among good ones, damaged."""
    if 2 * not_cdr > recorded:
        return (f"{n} of the {recorded} message(s) on {topic} could not be decoded as {msgtype} and were left out "
                "(they are not ROS 2 serialised messages, CDR: ROS 1 or JSON data? convert the bag with "
                "rosbags-convert or record it with ros2 bag)"), True
    return (f"{n} of the {recorded} message(s) on {topic} are damaged (could not be deserialised as {msgtype}): "
            "skipped"), False


def _observed_gt(engine: Any, gt_mesh: Any) -> Any:
    """As `senfunet evaluate` (the paper's protocol): the GT vertices cropped to the surface the
    recording observed, the same crop for every mesh (None without a GT mesh)."""
    if gt_mesh is None:
        return None
    from senfunet_core.learning.evaluation import observed_gt_vertices

    return observed_gt_vertices(engine, gt_mesh.vertices)


def _metrics(gt_vertices: Any, gt: str | Path | None, gt_mesh: Any, meshes: dict[str, Any],
             timings: dict[str, Any]) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """F-score, precision and recall of each mesh against the GT cropped to the observed surface."""
    if gt_mesh is None or gt_vertices is None or not meshes:
        return None, None
    from senfunet_core.metrics import mesh_metrics

    t0 = time.perf_counter()
    gt_info = {"path": str(gt), "vertices": gt_mesh.n_vertices, "vertices_observed": int(len(gt_vertices)),
               "tau_m": 0.02}
    metrics = None
    if len(gt_vertices):
        metrics = {stem: {k: round(float(v), 4) for k, v in mesh_metrics(mesh.vertices, gt_vertices).items()}
                   for stem, mesh in meshes.items()}
    timings["metrics_s"] = round(time.perf_counter() - t0, 3)
    return metrics, gt_info


def _stats(result: ReplayResult, run: _Run, pipeline: Pipeline, settings: P.Settings,
           counters: dict[str, dict[str, Any]], *, params: str | Path | None, threads: int,
           gt_info: dict[str, Any] | None, metrics: dict[str, Any] | None,
           timings: dict[str, Any], engine_stats: dict[str, Any], warnings: list[str]) -> dict[str, Any]:
    sensors = {}
    for name, c in counters.items():
        sensors[name] = {
            "received": c["received"], "integrated": c["integrated"],
            "dropped": dict(c["dropped"]),
            "dropped_total": sum(c["dropped"].values()),
            "pending_at_end": c["queue_depth"],  # frames still waiting (for a pose or camera_info) when the bag ended
            "color_received": c["color_received"], "pose_received": c["pose_received"],
            "time_jumps": c["time_jumps"],
            # frames newer than their sensor's newest pose when its streams ended (the bag's end, or silent for
            # pose_max_wait_s), posed by extrapolating the two newest poses' motion (within pose_tolerance_s)
            "extrapolated": c["extrapolated"],
            # what the counts alone do not say: what the last dropped message of each reason had wrong (a
            # camera_info without K, an image too small for the border...), frames fused without their colour,
            # and a camera_info whose distortion replay does not apply
            "errors": dict(c["errors"]),
            "without_color": c["integrated"] if name in run.colourless else c["without_color"],
            "color_usable": c["color_usable"],  # colour images decoded for matching
            # messages of its topics that could not be deserialised, per stream (depth: not in `received`)
            "undecodable": c["undecodable"],
            "distorted": c["distorted"],
            "color_refused": c["color_refused"],  # fused without colour: colour of another aspect ratio
            # depth images missing from the stream's regular stamps (the recorder or the driver lost them)
            "missing_depth": c["missing_depth"], "missing_depth_gap": c["missing_depth_gap"],
            # what about the sensor's set-up to know (see SensorCounters.notes)
            "notes": {**c["notes"], **({"colourless": run.colourless[name]} if name in run.colourless else {})},
        }
    router = run.router
    return {
        "bag": run.bag_info,
        "complete": result.ok,
        "error": result.error,
        "interrupted": run.interrupted,
        "messages_read": run.read,
        "params": str(params) if params else None,
        "weights": pipeline.engine.weights_source,
        "torch_threads": int(threads),
        "sensors": sensors,
        # sensor and stream: comma-separated when the topic feeds several inputs (one /odom for both sensors)
        "topics": {t: {"type": r.msgtype, "sensor": ", ".join(dict.fromkeys(sensor for sensor, _ in r.targets)),
                       "stream": ", ".join(dict.fromkeys(stream for _, stream in r.targets)),
                       "undecodable": router.undecodable.get(t, 0), "other_types": router.other_types.get(t, {})}
                   for t, r in sorted(router.routes.items())},
        "ignored_topics": dict(sorted(router.ignored.items())),
        "time_jumps": pipeline.time_jumps,
        "warnings": warnings,  # every note and warning the run said as it went (also printed)
        "engine_errors": pipeline.engine_errors,
        "engine": engine_stats,
        "meshes": {stem: {"file": str(result.files[stem]), "vertices": m.n_vertices, "faces": m.n_faces}
                   for stem, m in result.meshes.items()},
        "gt": gt_info,
        "metrics": metrics,
        "timings": timings,
    }


def _json_default(value: Any) -> Any:
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    if isinstance(value, tuple):
        return list(value)
    return str(value)


def bag_frames(bag: str | Path, limit: int | None = None) -> list[Frame]:
    """The bag's depth frames as the node's Ingest makes them (`senfunet_ros.ingest.Frame`: pose at
    the stamp, colour matched), in the order Ingest releases them; at most `limit`."""
    settings = load_settings(None)
    frames: list[Frame] = []
    with open_bag(bag) as reader:
        router = TopicRouter(settings, reader.topics, bag)
        ingest = Ingest(ingest_config(settings))
        for msg in reader.messages(router.topics):
            decoded = router.decode(msg)
            if decoded is not None:
                router.dispatch(ingest, *decoded)
                frames += [f for f in ingest.pop_ready() if isinstance(f, Frame)]
            if limit is not None and len(frames) >= limit:
                break
    return frames[:limit]
