"""The one piece the live node and offline replay share: what happens to messages, frames, time
jumps, failures, saving and loading. They differ only in clock and transport (DDS callbacks and
timers vs. a bag read in a loop).

    pipeline = Pipeline(engine, ingest, on_time_jump="keep", log=print)
    pipeline.dispatch("tof", Stream.DEPTH, msg)   # a subscription callback / a bag message
    pipeline.drain(ingest.pop_ready())             # the integration timer / after each message
    pipeline.save_meshes(Path("out"), sensors=("tof", "stereo"), tsdf_fusion=True)

No rclpy here: messages are duck-typed, logging goes through the `log(level, text)` callback.
Threading: `dispatch` may run on several threads (Ingest locks); `drain`, `reset`, `load_map`
run on one thread at a time (the node's integration timer and its services share a lock);
`save_meshes` and `save_map` run beside them (the engine is thread-safe), so that frames keep
being integrated while a large map is saved; a reset (a time jump) waits for the save (each holds the
engine's update lock throughout), so that what is saved is one map.
"""
from __future__ import annotations

import contextlib
import enum
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from senfunet_ros.ingest import Frame, Ingest, IngestConfig, NoDepthInRange, TimeJump, integrate_ready

__all__ = ["MESH_FILES", "Pipeline", "SavedMesh", "Stream", "TimeJumpAction", "mesh_paths",
           "optical_frame_advice"]

MESH_FILES = {"fused": "mesh"}  # engine mesh name -> file stem (sensors and tsdf_fusion keep their names)


class Stream(str, enum.Enum):
    """The input streams of a sensor."""

    CAMERA_INFO = "camera_info"
    DEPTH = "depth"
    COLOR = "color"
    POSE = "pose"
    TF = "tf"  # /tf and /tf_static belong to every sensor (sensor "")
    TF_STATIC = "tf_static"


class TimeJumpAction(str, enum.Enum):
    """What a confirmed restart of time (a bag looping, a robot rebooting its clock) does to the map."""

    KEEP = "keep"
    RESET = "reset"

    @classmethod
    def parse(cls, value: str) -> TimeJumpAction:
        """'ignore' is the older spelling of 'keep'."""
        return cls.KEEP if value == "ignore" else cls(value)


def mesh_paths(out_dir: Path, *, sensors: Iterable[str], tsdf_fusion: bool) -> dict[str, Path]:
    """Engine mesh name -> the PLY file `Pipeline.save_meshes` writes it to, in the order it makes them
    (the fused mesh last)."""
    names = [*sensors] + (["tsdf_fusion"] if tsdf_fusion else []) + ["fused"]
    return {name: out_dir / f"{MESH_FILES.get(name, name)}.ply" for name in names}


@dataclass(frozen=True)
class SavedMesh:
    path: Path
    mesh: Any  # senfunet_core.mesher.Mesh
    extract_s: float


Log = Callable[[str, str], None]  # (level: "info" | "warning" | "error", text)


class Pipeline:
    """Messages -> Ingest -> engine, with one policy for time jumps, failures and files."""

    def __init__(self, engine: Any, ingest: Ingest, *, on_time_jump: str = "keep", log: Log | None = None,
                 on_integrated: Callable[[Frame, float], None] | None = None,
                 on_new_map: Callable[[], None] | None = None) -> None:
        self.engine = engine
        self.ingest = ingest
        self.on_time_jump = TimeJumpAction.parse(on_time_jump)
        self._log = log or (lambda level, text: None)
        self._on_integrated = on_integrated
        # called under the lock whenever the map is emptied or replaced, so that what the caller
        # derives from integrated frames (camera colours) never outlives the map nor misses a frame
        self._on_new_map = on_new_map or (lambda: None)
        self.lock = threading.RLock()  # held while the engine is fed, reset or replaced (not while saving)
        self.latest_stamp_ns = 0  # latest integrated sensor time: the stamp of every output
        self.frames_integrated = 0
        self.frames_failed = 0  # the engine rejected them (the map is untouched)
        self.frames_unfinished = 0  # taken from the queues but not integrated because the process stopped
        self.time_jumps = 0
        self.maps = 1  # maps the engine has held: a reset or a load_map starts the next
        self.integrate_s = 0.0
        self.engine_errors: list[str] = []  # the first few, for stats.json and the status
        self.stopping = False
        self._frame_ids_checked: set[str] = set()  # sensors whose depth frame_id was looked at

    # -- messages ---------------------------------------------------------------------------------

    def dispatch(self, sensor: str, stream: Stream | str, message: Any) -> str | None:
        """Hand one message to Ingest (what a subscription callback does); returns the drop reason."""
        if stream == Stream.DEPTH and sensor not in self._frame_ids_checked:
            self._frame_ids_checked.add(sensor)
            advice = optical_frame_advice(self.ingest.config, sensor, getattr(message.header, "frame_id", ""))
            if advice:
                self._log("warning", advice)
        return self.dispatch_to(self.ingest, sensor, stream, message)

    @staticmethod
    def dispatch_to(ingest: Ingest, sensor: str, stream: Stream | str, message: Any) -> str | None:
        stream = Stream(stream)
        if stream is Stream.DEPTH:
            return ingest.add_depth(sensor, message)
        if stream is Stream.COLOR:
            return ingest.add_color(sensor, message)
        if stream is Stream.POSE:
            return ingest.add_pose(sensor, message)
        if stream in (Stream.TF, Stream.TF_STATIC):
            return ingest.add_tf(message, static=stream is Stream.TF_STATIC)
        return ingest.add_camera_info(sensor, message)

    # -- frames ----------------------------------------------------------------------------------

    def drain(self, items: Iterable[Frame | TimeJump]) -> int:
        """Integrate ready items in order (each next frame's feature net overlapping the current
        frame's kernels); returns the frames integrated."""
        with self.lock:
            before = self.frames_integrated
            integrate_ready(self.engine, items, self._time_jump, self._frame_done)
            return self.frames_integrated - before

    def stream_ends(self) -> list[tuple[str, str]]:
        """(level, line) per sensor whose streams' end (`Ingest.stream_ends.end`) posed frames by extrapolation
        or dropped them since the last call: how many, and how far past the newest pose. Not logged here:
        the node's stop prints them (its log may be gone by then), replay prints them."""
        lines = []
        poses = "a /tf stream" if self.ingest.config.tf is not None else "a pose stream"
        for sensor, end in self.ingest.stream_ends.take().items():
            parts = []
            if end.extrapolated:
                parts.append(f"{end.extrapolated} frame(s) newer than its newest pose posed by continuing the two "
                             f"newest poses' motion (constant velocity) up to {end.extrapolated_max_ns * 1e-6:.0f} ms "
                             "past it (counted as extrapolated)")
            if end.timed_out:
                far = (f" (up to {end.timed_out_max_ns * 1e-6:.0f} ms past the newest pose)"
                       if end.timed_out_max_ns else "")
                parts.append(f"{end.timed_out} frame(s) dropped as pose_timeout{far}: more than pose_tolerance_s "
                             f"({self.ingest.config.pose_tolerance_s:g} s) past the newest pose, or too few poses; "
                             f"{poses} that ends later than the depth stream keeps them")
            lines.append(("warning" if end.timed_out else "info",
                          f"{sensor}: its streams ended with frames waiting for a pose: " + "; ".join(parts)))
        return lines

    def _time_jump(self, jump: TimeJump) -> None:
        reset = self.on_time_jump is TimeJumpAction.RESET
        where = "/clock" if jump.stream == "clock" else f"{jump.sensor} {jump.stream}"
        if jump.stray_start:  # no pass of a bag: the first stamps were off, the streams go on from the others
            self._log("warning", f"the streams' first stamps (up to {jump.from_ns * 1e-9:.3f} s) lay far from those "
                      f"that followed (from {jump.to_ns * 1e-9:.3f} s, as {where} showed): taken as stray stamps, the "
                      f"streams go on from there; what waited was flushed, map {'reset' if reset else 'kept'} "
                      "(parameter on_time_jump); check the drivers' first stamps")
        else:
            self.time_jumps += 1
            # one line a restart, whatever stream showed it (a looping bag says so every pass); the messages
            # the restart cost are counted per stream on ~/status (time_jump)
            self._log("warning", f"time restarted, pass {self.time_jumps + 1} (a bag looping or restarting?): {where} "
                      f"went back from {jump.from_ns * 1e-9:.3f} s to {jump.to_ns * 1e-9:.3f} s; queued frames "
                      f"flushed, map {'reset' if reset else 'kept'} (parameter on_time_jump); messages it cost are "
                      "counted on ~/status (time_jump)")
        if reset:
            self.engine.reset()
            self._new_map()
        self.latest_stamp_ns = jump.to_ns

    def _new_map(self) -> None:
        """The map was emptied or replaced (the lock held)."""
        self.maps += 1
        self._on_new_map()

    def _frame_done(self, frame: Frame, error: Exception | None, seconds: float) -> None:
        self.integrate_s += seconds
        if error is None:
            self.frames_integrated += 1
            self.ingest.ledger.mark_integrated(frame.sensor)
            self.latest_stamp_ns = max(self.latest_stamp_ns, frame.stamp_ns)
            if self._on_integrated is not None:
                self._on_integrated(frame, seconds)
            return
        if self.stopping and isinstance(error, RuntimeError):  # the worker pools went away under it
            self.frames_unfinished += 1
            self.ingest.ledger.mark_dropped(frame.sensor, "shutdown")
            return
        # counted and described: the node warns of new drops once per cause and period, not per frame
        what = f"frame at {frame.stamp_ns * 1e-9:.3f} s: {error}"
        if isinstance(error, NoDepthInRange):  # nothing to integrate: a drop, not a failure
            self.ingest.ledger.mark_dropped(frame.sensor, "out_of_range", what)
            return
        self.frames_failed += 1  # InputError or worse: this frame is lost, the map is not
        self.ingest.ledger.mark_dropped(frame.sensor, "engine_error", what)
        if len(self.engine_errors) < 10:
            self.engine_errors.append(f"{frame.sensor} {what}")

    # -- map and files ---------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget the map and the queued frames (poses and camera_info stay)."""
        with self.lock:
            self.engine.reset()
            self.ingest.ledger.discard_waiting("map_reset")
            self._new_map()

    def save_meshes(self, out_dir: str | Path, *, sensors: Iterable[str], tsdf_fusion: bool,
                    then_reset: bool = False, judge: bool = True) -> dict[str, SavedMesh]:
        """Fused (filtered), per-sensor and, if kept, TSDF Fusion meshes as PLY files (mode 0644).
        `then_reset`: the map is forgotten as the last mesh is made; `judge`: the weighting net judges
        what it has not reached first (`SenFuNet.extract_mesh`)."""
        from senfunet_core.ply import write_ply

        out = Path(out_dir).expanduser()
        out.mkdir(parents=True, exist_ok=True)
        paths = mesh_paths(out, sensors=sensors, tsdf_fusion=tsdf_fusion)
        which = list(paths)
        meshes: dict[str, tuple[Any, float]] = {}
        # the engine is thread-safe: frames keep being integrated while the meshes are made (holding the
        # lock would stop draining the queues, which then overflow); only a reset excludes them
        with self.lock if then_reset else contextlib.nullcontext():
            engine = self.engine
            # the map's update lock from the first mesh to the last: a reset (a time jump) waits, so that
            # the files show one map
            with engine.update_lock.held():
                spill = getattr(engine.grid, "spill", None)
                on_disk = len(spill) if spill is not None else 0  # evicted blocks: only their fused meshes are kept
                for name in which:
                    t0 = time.perf_counter()
                    mesh = engine.extract_mesh(name, then_reset=then_reset and name == which[-1], judge=judge)
                    meshes[name] = (mesh, time.perf_counter() - t0)
            if then_reset:
                self._new_map()
        saved = {}
        # the fused mesh written first: a save cut short (a process killed) keeps the one that matters most
        for name, (mesh, seconds) in sorted(meshes.items(), key=lambda item: item[0] != "fused"):
            path = paths[name]
            write_ply(path, mesh)  # mode 0644
            saved[path.stem] = SavedMesh(path, mesh, seconds)
        partial = [paths[name].name for name in which if name != "fused"]
        if on_disk and partial:
            self._log("warning", f"{', '.join(partial)} cover only the blocks in memory: the {on_disk} blocks the map "
                      f"bound (max_map_blocks) evicted to disk are not in them; {paths['fused'].name} has them (their "
                      "final fused meshes)")
        return saved

    def save_map(self, path: str | Path) -> Path:
        """The whole engine state (grids, networks, config) in one file, mode 0644."""
        path = Path(path).expanduser()
        from senfunet_core.map_file import save_map

        save_map(self.engine, path)  # thread-safe, as frames keep being integrated (see save_meshes)
        return path

    def load_map(self, path: str | Path, *, run_config: Any = None, configure: Callable[[Any], None] | None = None
                 ) -> Any:
        """Replace the engine by the one saved in `path` (InputError if it is not a saved map); the
        queued frames go (they belong to the old map's timeline). run_config: the caller's EngineConfig,
        whose run-time fields the new engine takes (`map_file.load_map`). `configure` gets the new
        engine before it replaces the old (a check that may refuse it). Returns the new engine."""
        from senfunet_core.errors import InputError
        from senfunet_core.map_file import load_map

        path = Path(path).expanduser()
        if path.is_dir():
            raise IsADirectoryError(f"{path} is a folder, not a map file; set parameter map_file to the map's file")
        if path.exists() and not path.is_file():  # a FIFO, a device: reading one could block the node
            raise InputError(f"{path} is not a regular file (a pipe or a device?), not a map file; set parameter "
                             "map_file to the map's file")
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such map file; set parameter map_file or call ~/save_map first")
        # its alpha threads start as the old engine's did (the node's: at its mesh thread's priority)
        engine = load_map(path, run_config=run_config, worker_setup=self.engine.alpha.worker_setup)
        if configure is not None:
            configure(engine)
        with self.lock:
            self.engine = engine
            self.ingest.ledger.discard_waiting("map_reset")
            self._new_map()
        return engine


def optical_frame_advice(config: IngestConfig, sensor: str, frame_id: str) -> str:
    """What to check when frames are posed by TF as a depth image's frame_id that does not look like
    an optical frame (REP 103 names them *_optical_frame), with no T_body_camera to turn it: a
    driver naming its camera_link (x forward) would turn the map by 90 degrees. Empty if fine."""
    if config.tf is None or sensor in config.T_body_camera or not frame_id or "optical" in frame_id.lower():
        return ""
    return (f"{sensor}: depth images name frame '{frame_id}', which does not look like an optical frame (z forward, "
            f"x right, y down; REP 103 names them '*_optical_frame'). With pose_type tf the camera is posed as that "
            f"frame: if it is the camera's body frame (x forward), set {sensor}.T_body_camera to "
            f"'0 0 0 -0.5 0.5 -0.5 0.5', or the map is turned by 90 degrees; if it is an optical frame by another "
            f"name, nothing to do")
