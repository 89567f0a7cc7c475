"""The node's parameters as data: one table of (name, default, help, range, choices, run-time).

The help text becomes the ROS ParameterDescriptor description (with the range, the choices and
read-only for those that cannot change at run time), `config/default.yaml` mirrors the table (a
test checks both), and `declare(node)` returns the values as a frozen `Settings`. Names
containing `{sensor}` exist once per entry of `sensors`, e.g. `tof.depth_topic`. `validate`
checks a set of new values the way the node's on-set-parameters callback refuses bad ones.
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from collections.abc import Iterable, Sequence

from senfunet_ros.conversions.images import names_raw_image
from senfunet_ros.conversions.poses import PoseType

__all__ = ["Param", "GLOBAL_PARAMS", "SENSOR_PARAMS", "NODE_NAME", "expanded_defaults", "Settings", "declare",
           "validate", "param_table"]

NODE_NAME = "senfunet"
# meshes the engine and the files name besides the sensors' (senfunet_core.block_mesher FUSED and TSDF_FUSION,
# the fused mesh's file stem): a sensor of that name would lose its mesh to theirs
RESERVED_SENSOR_NAMES = ("fused", "mesh", "tsdf_fusion")
ON_TIME_JUMP = ("keep", "reset", "ignore")  # ignore: the older spelling of keep
INF = math.inf


@dataclass(frozen=True)
class Param:
    name: str
    default: Any
    help: str
    lo: float | None = None  # inclusive bounds of numbers
    hi: float | None = None
    choices: tuple[str, ...] = ()
    runtime: bool = False  # applied when set at run time; False = read-only after start
    lo_open: bool = False  # lo itself is refused (a rate of 0)

    def check(self, name: str, value: Any) -> None:
        """ValueError saying why `value` is refused."""
        if self.choices and value not in self.choices:
            raise ValueError(f"parameter '{name}' = {value!r}; use one of {list(self.choices)}")
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value) and not (value == INF and self.hi == INF):
                raise ValueError(f"parameter '{name}' = {value!r} is not a finite number")
            if self.lo is not None and (value < self.lo or (self.lo_open and value == self.lo)):
                raise ValueError(f"parameter '{name}' = {value} must be {'>' if self.lo_open else '>='} {self.lo}")
            if self.hi is not None and value > self.hi:
                raise ValueError(f"parameter '{name}' = {value} must be <= {self.hi}")


def _rate(name: str, default: float, help_text: str) -> Param:
    # at least once in 1000 s: a timer's period must fit its nanosecond counter
    return Param(name, default, help_text, lo=0.001, hi=1000.0, runtime=True)


# the mesh timer's period is this much shorter than 1 / mesh_rate_hz, and the net's turn ends this much
# before its period: the refresh holds the rate asked for despite the updates' jitter (with half this
# margin, a stream that keeps both cores busy stretched the median interval to the period:
# bench/realtime.py, large room); mesh_publisher schedules with it, mesh_rate_hz's description names it
MESH_PERIOD_MARGIN = 0.10

GLOBAL_PARAMS: tuple[Param, ...] = (
    Param("sensors", ["tof", "stereo"], "sensor names, sensor 1 first (alpha is the weight of sensor 1)"),
    Param("rgb_sensors", ["stereo"],
          "sensors whose feature net also takes the colour image (as the weights were trained)"),
    Param("pose_type", "pose_stamped", "where poses come from: pose_stamped | odometry | transform_stamped (the "
          "pose topics), or tf (each depth image's frame_id looked up in fixed_frame on /tf and /tf_static)",
          choices=tuple(p.value for p in PoseType)),
    Param("fixed_frame", "map", "frame the poses are given in; frame_id of every output"),
    Param("voxel_size_m", 0.01, "voxel side length in metres", lo=0.001, hi=10.0),
    Param("band_m", 0.1, "length of the ray segment integrated around each depth measurement, metres; at least "
          "two voxels (sampled at most a voxel apart: 11 samples, more for voxels finer than band_m / 10)",
          lo=0.001, hi=10.0),
    Param("working_width", 256, "images are resized to this width (K scaled); 0 = native", lo=0, hi=8192),
    Param("working_height", 0,
          "images are resized to this height; 0 = native, or keep the aspect ratio if the width is set",
          lo=0, hi=8192),
    Param("queue_size", 30, "frames per sensor waiting for their pose; the oldest is dropped beyond this",
          lo=1, hi=100000),
    Param("max_lag_s", 0.25, "when integration falls behind, frames more than this (sensor time) older than their "
          "sensor's newest are set aside (see behind_buffer_mb), which bounds the latency; 0 = never", lo=0.0,
          hi=3600.0, runtime=True),
    Param("behind_buffer_mb", 256.0, "frames set aside by max_lag_s are kept, up to this much memory, and integrated "
          "once no image came for max_lag_s (the sensors pause or stop), so the map loses nothing to a busy spell; "
          "beyond it they are skipped (dropped as behind); 0 = skip them at once", lo=0.0, hi=1e6, runtime=True),
    Param("pose_buffer_size", 2000, "poses kept per sensor for interpolation", lo=2, hi=10_000_000),
    Param("pose_tolerance_s", 0.1, "max time between a depth stamp and the poses interpolated around it", lo=0.0,
          hi=60.0, lo_open=True, runtime=True),
    Param("pose_max_wait_s", 1.0,
          "a frame waits this long (sensor time) for a pose after its stamp, or for its first camera_info, then is "
          "dropped",
          lo=0.0, hi=600.0, lo_open=True, runtime=True),
    Param("color_tolerance_s", 0.02, "max stamp difference between a depth image and the colour image matched to it",
          lo=0.0, hi=10.0, runtime=True),
    Param("time_jump_s", 1.0, "a stamp this far from its stream's timeline (past or future) is dropped as bad_stamp; "
          "it does not move the timeline", lo=0.0, hi=3600.0, lo_open=True, runtime=True),
    Param("restart_confirm_msgs", 5, "time restarted (a bag looping) once every stream continued on a new timeline "
          "for this many messages ...", lo=1, hi=10000, runtime=True),
    Param("restart_confirm_s", 0.5, "... spanning this much of the new timeline (with use_sim_time, /clock "
          "jumping back confirms it at once)", lo=0.0, hi=600.0, runtime=True),
    Param("on_time_jump", "keep", "what a confirmed restart of time does to the map: keep | reset",
          choices=ON_TIME_JUMP, runtime=True),
    _rate("integrate_rate_hz", 30.0, "rate of the timer that integrates queued frames"),
    _rate("mesh_rate_hz", 1.0, "rate of mesh updates (alpha, fusion, meshing of the changed blocks); the node "
          f"schedules them with a period {MESH_PERIOD_MARGIN:.0%} shorter, so that their jitter does not take the "
          "refresh below this rate"),
    Param("alpha_budget_s", 0.5, "seconds per mesh update spent re-evaluating the sensor weighting (after the update "
          "is published; the next one shows it); blocks left over wait for the next turn (see alpha_order); "
          "0 = no limit", lo=0.0, hi=600.0, runtime=True),
    Param("alpha_order", "longest_waiting", "which blocks a short alpha budget judges first: longest_waiting (blocks "
          "with a mesh first, and among them those whose last change is oldest; blocks still in view wait until they "
          "settle; then the others, never judged ones first, and when the sensors pause, those with the most voxels "
          "near a sensor's surface first) | latest (those the latest frames reached)",
          choices=("longest_waiting", "latest")),
    Param("mesh_display_cell_m", 0.03, "~/mesh shows a display mesh whose vertices are merged on a grid of this "
          "size (per block; the map and ~/save_mesh keep full resolution): a snapshot of a room stays a few tens of "
          "MB for subscribers over Wi-Fi; 0 (or not above voxel_size_m) = full resolution",
          lo=0.0, hi=1.0, runtime=True),
    Param("mesh_message_max_mb", 16.0, "a ~/mesh update larger than this goes out in parts (each holds whole "
          "blocks; applied in order they are the whole update): a reader must keep that many messages (KEEP_ALL, or "
          "a history as deep as the parts; a latched reader of depth 1 loses all but the last) or this must be "
          "raised; larger parts cost the DDS writer up to three times this much memory", lo=1.0, hi=2048.0,
          runtime=True),
    Param("mesh_colors", "weighting", "vertex colours of ~/mesh: weighting (amber = sensor 1 trusted, blue = sensor "
          "2) | camera (the colour images, averaged on a grid of twice the voxel size; the weighting where no "
          "camera colour was seen)", choices=("weighting", "camera"), runtime=True),
    _rate("weights_rate_hz", 0.2, "rate of ~/weights clouds (the whole map: heavier than a mesh update); each goes "
          "with a mesh update, so at most mesh_rate_hz"),
    Param("alpha_precision", "auto", "weighting-net arithmetic: auto (bfloat16 where the CPU has bfloat16 "
          "instructions, else int8 where torch has oneDNN's int8 convolutions, else float32) | float32 | bfloat16 | "
          "int8 (needs the weights' calibration, see README)", choices=("auto", "float32", "bfloat16", "int8")),
    Param("feature_precision", "float32", "feature-net arithmetic: auto (bfloat16 where the CPU has bfloat16 "
          "instructions, else float32) | float32 | bfloat16", choices=("auto", "float32", "bfloat16")),
    _rate("status_rate_hz", 1.0, "rate of /diagnostics and ~/status"),
    Param("diagnostics_window_s", 5.0, "rates are measured over this recent window; a WARN clears this long after "
          "its cause ends; a subscribed topic silent this long gets a warning", lo=0.1, hi=3600.0, runtime=True),
    Param("stale_after_s", 2.0, "a stream that received messages and then none for this long is STALE",
          lo=0.1, hi=3600.0, runtime=True),
    Param("weights_band_m", 0.02,
          "~/weights holds voxels with |fused TSDF| at most this (near the surface); 0 = all observed",
          lo=0.0, hi=100.0, runtime=True),
    Param("output_dir", "senfunet_output", "directory ~/save_mesh writes PLY files into", runtime=True),
    Param("map_file", "map.pt", "file ~/save_map writes and ~/load_map reads (relative: in output_dir)",
          runtime=True),
    Param("weights", "default", "network weights: 'default' (shipped; its weighting net also reads the sensors' "
          "TSDFs), 'paper' (the shipped paper-exact model), a .pt path, or 'none' (untrained)"),
    Param("device", "cpu", "torch device: cpu | cuda (falls back to cpu with a warning)"),
    Param("save_on_shutdown", False, "write the PLY files into output_dir when the node stops (into a new "
          "temporary folder, named in the log, if output_dir cannot be written)", runtime=True),
    Param("max_map_blocks", -1, "memory bound in 8^3-voxel blocks: past it, the blocks farthest from the sensor are "
          "evicted: their final meshes stay on ~/mesh and in save_mesh, their voxels go to disk (the temporary "
          "directory, $TMPDIR) until a sensor sees them again; -1 = half of this machine's memory (or of its "
          "container's limit); 0 = unbounded",
          lo=-1, hi=2**31 - 1),
    Param("min_new_block_samples", 16, "a frame allocates a block the map does not hold yet "
          "only where at least this many of its ray samples land (flying pixels and far noise would otherwise fill "
          "memory with nearly empty blocks); their samples are dropped and counted (engine.counters."
          "sparse_dropped_samples on ~/status); blocks in the map take every sample; 0 = allocate every touched block",
          lo=0, hi=1_000_000),
    Param("tsdf_fusion", False, "also keep the plain TSDF Fusion baseline (save_mesh adds tsdf_fusion.ply; "
          "costs integration time and memory)"),
)

SENSOR_PARAMS: tuple[Param, ...] = (
    Param("{sensor}.depth_topic", "/{sensor}/depth", "depth image topic (32FC1 metres or 16UC1 millimetres; a name "
          "ending in /compressedDepth is sensor_msgs/CompressedImage as image_transport writes it)"),
    Param("{sensor}.color_topic", "/{sensor}/color", "colour image topic (rgb8, bgr8, mono8; a name ending in "
          "/compressed is sensor_msgs/CompressedImage jpeg/png); empty = none"),
    Param("{sensor}.camera_info_topic", "/{sensor}/camera_info", "camera_info topic of the depth image"),
    Param("{sensor}.pose_topic", "/{sensor}/pose", "pose topic (unused with pose_type tf)"),
    Param("{sensor}.T_body_camera", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], "the camera's optical frame in the frame "
          "the pose topic gives (x y z qx qy qz qw; e.g. base_link of an Odometry), or with pose_type tf in the "
          "depth image's frame_id (a driver naming camera_link, x forward, instead of its optical frame, z "
          "forward: 0 0 0 -0.5 0.5 -0.5 0.5); identity = the pose is the camera's"),
    Param("{sensor}.depth_min_m", 0.1, "depth below this is ignored, metres", lo=0.0, hi=1000.0, runtime=True),
    Param("{sensor}.depth_max_m", 3.0, "depth beyond this is ignored, metres (at 1 cm voxels and 256 px, rays beyond "
          "~3 m are > 2 voxels apart and noise spreads samples over many sparse blocks: memory and time, little "
          "surface)",
          lo=0.0, hi=1000.0, lo_open=True, runtime=True),
)


def _fill(value: Any, sensor: str) -> Any:
    return value.replace("{sensor}", sensor) if isinstance(value, str) else value


def param_table(sensors: Sequence[str] | None = None) -> dict[str, Param]:
    """Every parameter name -> its Param (per-sensor names expanded, defaults filled in)."""
    if sensors is None:
        sensors = GLOBAL_PARAMS[0].default
    out = {p.name: p for p in GLOBAL_PARAMS}
    for sensor in sensors:
        for p in SENSOR_PARAMS:
            name = _fill(p.name, sensor)
            out[name] = Param(name, _fill(p.default, sensor), p.help, p.lo, p.hi, p.choices, p.runtime, p.lo_open)
    return out


def expanded_defaults(sensors: Sequence[str] | None = None) -> dict[str, tuple[Any, str]]:
    """Every parameter name -> (default, help), with per-sensor names expanded."""
    return {name: (p.default, p.help) for name, p in param_table(sensors).items()}


# parameters every rclpy node has, or that ROS tools add: not the node's own, never unknown
_ROS_PARAMETERS = ("use_sim_time", "start_type_description_service", "qos_overrides.")


def unknown_parameters(names: Iterable[str], sensors: Sequence[str] | None = None) -> list[str]:
    """The names that are not parameters of the node (with these sensors), each with the closest
    parameter name when there is one: "voxel_sise_m (did you mean voxel_size_m?)"."""
    import difflib

    known = list(expanded_defaults(sensors))
    out = []
    for name in sorted(set(names) - set(known)):
        if name.startswith(_ROS_PARAMETERS):
            continue
        close = difflib.get_close_matches(name, known, n=1)
        out.append(f"{name} (did you mean {close[0]}?)" if close else name)
    return out


@dataclass(frozen=True)
class SensorSettings:
    name: str
    depth_topic: str
    color_topic: str
    camera_info_topic: str
    pose_topic: str
    depth_min_m: float
    depth_max_m: float
    T_body_camera: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)  # x y z qx qy qz qw


@dataclass(frozen=True)
class Settings:
    """Parameter values after declaration and checking."""

    values: dict[str, Any]  # every parameter by name
    sensors: tuple[SensorSettings, ...]

    def __getattr__(self, name: str) -> Any:  # settings.voxel_size_m etc.
        try:
            return self.__dict__["values"][name]
        except KeyError:
            raise AttributeError(name) from None

    @property
    def sensor_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.sensors)

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> Settings:
        """Settings from checked values (see `check`)."""
        sensors = tuple(
            SensorSettings(name=s, depth_topic=values[f"{s}.depth_topic"], color_topic=values[f"{s}.color_topic"],
                           camera_info_topic=values[f"{s}.camera_info_topic"], pose_topic=values[f"{s}.pose_topic"],
                           depth_min_m=values[f"{s}.depth_min_m"], depth_max_m=values[f"{s}.depth_max_m"],
                           T_body_camera=tuple(values[f"{s}.T_body_camera"]))
            for s in values["sensors"])
        return cls(values=dict(values), sensors=sensors)


def coerce(name: str, value: Any, default: Any) -> Any:
    """Values in the type of their default, so `mesh_rate_hz: 1` in YAML works; ValueError for
    what cannot be read as that type ('abc' for a number)."""
    try:
        if isinstance(default, bool):
            if isinstance(value, str):
                text = value.strip().lower()
                if text not in ("1", "true", "yes", "on", "0", "false", "no", "off"):
                    raise ValueError("use true or false")
                return text in ("1", "true", "yes", "on")
            if isinstance(value, (int, float)) and not isinstance(value, bool) and value not in (0, 1):
                raise ValueError("use true or false")  # 0.5 or 2 are no switch: a value for another parameter?
            return bool(value)
        if isinstance(default, int):
            if isinstance(value, str):  # PyYAML reads 2e6 as text; rcl as 2000000.0
                value = float(value) if not value.strip().lstrip("+-").isdigit() else int(value)
            if isinstance(value, float) and not value.is_integer():
                raise ValueError("not a whole number")
            return int(value)
        if isinstance(default, float):
            if isinstance(value, bool):  # true is no number: a value for another parameter?
                raise ValueError("a number, not true or false")
            return float(value)
        if isinstance(default, list):
            if isinstance(value, (str, bytes)):
                raise ValueError("expected a list")
            if default and isinstance(default[0], float):
                return [float(v) for v in value]
            return [str(v) for v in value]
        if isinstance(value, (list, tuple)):
            raise ValueError("expected a single value, not a list")
        return str(value)
    except (TypeError, ValueError) as err:
        kind = type(default).__name__
        raise ValueError(f"parameter '{name}' = {value!r} is not {_a(kind)} {kind}: {err}") from err


def check(values: dict[str, Any]) -> None:
    """Reject values the node cannot run with, saying which and why."""
    sensors = values["sensors"]
    if len(sensors) != 2 or len(set(sensors)) != 2:
        raise ValueError(f"parameter 'sensors' needs two distinct names, got {sensors}")
    for sensor in sensors:
        # a name goes into topics (/<name>/depth), parameter names and file names (<name>.ply)
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", sensor):
            raise ValueError(f"parameter 'sensors': {sensor!r} is not a usable sensor name: use letters, digits and "
                             "'_', not a digit first (it names the sensor's topics /<name>/depth..., its parameters "
                             "<name>.* and its mesh file <name>.ply)")
        if sensor in RESERVED_SENSOR_NAMES:
            raise ValueError(f"parameter 'sensors': '{sensor}' names an output (the fused mesh is mesh.ply, the "
                             "baseline tsdf_fusion.ply): one would overwrite the other; choose another name")
    table = param_table(sensors)
    for name, p in table.items():
        p.check(name, values[name])
    unknown_rgb = [name for name in values["rgb_sensors"] if name not in sensors]
    if unknown_rgb:  # sensors renamed, rgb_sensors left at its default: no feature net would take colour
        raise ValueError(f"parameter 'rgb_sensors' names {unknown_rgb}, not among sensors {list(sensors)}; list the "
                         "sensors whose feature net takes colour ([] for none)")
    from senfunet_core.networks import resolve_weights

    resolve_weights(values["weights"] or "none")  # InputError (a ValueError) naming the choices
    if values["band_m"] < 2 * values["voxel_size_m"]:
        # the samples in front of a surface and those behind it must reach different voxels, or no cell
        # holds both signs and nothing is meshed
        raise ValueError(f"band_m ({values['band_m']} m) must be at least two voxels (2 x voxel_size_m = "
                         f"{2 * values['voxel_size_m']:g} m): a narrower one seldom reaches the voxels on both "
                         "sides of a surface, so little or nothing is meshed; raise band_m (the paper: 10 voxels)")
    _check_topics(values)
    for sensor in sensors:
        lo, hi = values[f"{sensor}.depth_min_m"], values[f"{sensor}.depth_max_m"]
        if not 0 <= lo < hi:
            # (at run time one `ros2 param set` at a time: moving the range past the other end needs that end first)
            raise ValueError(f"{sensor}: depth range [{lo}, {hi}] m is empty; set {sensor}.depth_min_m < "
                             f"{sensor}.depth_max_m (to move the range at run time, set the end it moves towards "
                             "first, or both in one set_parameters_atomically call)")
        extrinsic = values[f"{sensor}.T_body_camera"]
        if len(extrinsic) != 7:
            raise ValueError(f"parameter '{sensor}.T_body_camera' needs 7 numbers (x y z qx qy qz qw), "
                             f"got {len(extrinsic)}")
        from senfunet_ros.geometry import transform_from_tq

        transform_from_tq(extrinsic[:3], extrinsic[3:], f"parameter '{sensor}.T_body_camera'")
    map_file = values["map_file"]
    if os.path.basename(map_file.strip()) in ("", ".", ".."):  # no name, a folder (".", "..", a trailing "/")
        raise ValueError(f"parameter 'map_file' = {map_file!r} names no file; give a file name such as map.pt "
                         "(relative: in output_dir)")
    from senfunet_ros.pipeline import mesh_paths

    meshes = [path.name for path in mesh_paths(Path(), sensors=values["sensors"], tsdf_fusion=True).values()]
    if Path(map_file).name in meshes:
        raise ValueError(f"parameter 'map_file' = {map_file!r} has the name of a mesh ~/save_mesh writes "
                         f"({', '.join(meshes)}): the map and that mesh would overwrite each other; name the map "
                         "e.g. map.pt")
    if not values["output_dir"].strip():
        raise ValueError("parameter 'output_dir' is empty; give a folder (relative: in the node's working "
                         "directory), e.g. senfunet_output")
    if values["time_jump_s"] < values["pose_max_wait_s"]:
        raise ValueError(f"time_jump_s ({values['time_jump_s']} s) must be at least pose_max_wait_s "
                         f"({values['pose_max_wait_s']} s): poses that lag the images by up to pose_max_wait_s would "
                         "be off the images' timeline and dropped as bad_stamp")


def _check_topics(values: dict[str, Any]) -> None:
    """ValueError naming the parameter of a topic that is no ROS topic name ('/front cam/depth', ''):
    rclpy would refuse it when the node subscribes, with an exception of its own and a traceback."""
    from rclpy.validate_topic_name import validate_topic_name

    for sensor in values["sensors"]:
        for stream in ("depth", "color", "camera_info", "pose"):
            name = f"{sensor}.{stream}_topic"
            topic = values[name]
            if not topic and (stream == "color" or (stream == "pose" and values["pose_type"] == PoseType.TF.value)):
                continue  # no colour; no pose topic with poses from TF
            try:
                validate_topic_name(topic)
            except Exception as err:  # noqa: BLE001 (rclpy's InvalidTopicNameException, not a ValueError)
                why = str(err).splitlines()[0].removeprefix("Invalid topic name: ")
                raise ValueError(f"parameter '{name}' = {topic!r} is not a topic name: {why}") from None
    # one depth stream fused as two sensors (a parameter file's copy-paste slip) is no second sensor; a pose or
    # colour topic may serve both (one odometry for a rig, with each sensor's T_body_camera)
    depth_of: dict[str, str] = {}
    for sensor in values["sensors"]:  # as given: 'depth' and '/depth' differ in a namespace
        topic = values[f"{sensor}.depth_topic"]
        if topic in depth_of:
            raise ValueError(f"parameters '{depth_of[topic]}.depth_topic' and '{sensor}.depth_topic' name the same "
                             f"topic {values[f'{sensor}.depth_topic']!r}: one depth stream would be fused as two "
                             "sensors; give each sensor its own depth topic")
        depth_of[topic] = sensor


def validate(current: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """The values after `changes` (name -> new raw value), coerced and checked: ValueError with the
    reason for an unknown name, a read-only one, a value of the wrong type or out of range."""
    table = param_table(current["sensors"])
    values = dict(current)
    for name, raw in changes.items():
        p = table.get(name)
        if p is None:
            raise ValueError(f"unknown parameter '{name}'")
        value = coerce(name, raw, p.default)
        if not p.runtime and value != current[name]:
            raise ValueError(f"parameter '{name}' cannot change while the node runs; restart the node with it")
        values[name] = value
    check(values)
    return values


def as_declared_types(parameters: list[Any], table: dict[str, Param]) -> list[Any]:
    """rclpy Parameters set at run time, with integers given for float parameters (`mesh_rate_hz: 4`,
    `[0, 0, 0, 0, 0, 0, 1]`) as floats: rclpy's dynamic typing would otherwise make the parameter an
    integer one for typed clients from then on."""
    from rclpy.parameter import Parameter

    out = []
    for p in parameters:
        default = table[p.name].default if p.name in table else None
        if p.type_ is Parameter.Type.INTEGER and isinstance(default, float):
            p = Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
        elif (p.type_ is Parameter.Type.INTEGER_ARRAY and isinstance(default, list) and default
              and isinstance(default[0], float)):
            p = Parameter(p.name, Parameter.Type.DOUBLE_ARRAY, [float(v) for v in p.value])
        out.append(p)
    return out


def type_error(parameters: list[Any], table: dict[str, Param]) -> str | None:
    """Why a run-time change of these rclpy Parameters (the node's own) is refused for its types: one
    is unset (`ros2 param delete`: rclpy would undeclare it for good), or of another type than its
    declared one (a bool for a rate); None when every type is right."""
    from rclpy.parameter import Parameter

    for p in parameters:
        if p.type_ is Parameter.Type.NOT_SET:
            return f"parameter '{p.name}' cannot be deleted (unset); set a value instead"
        declared = Parameter.Type.from_parameter_value(table[p.name].default)
        if p.type_ is not declared:
            declared_name, given_name = declared.name.lower(), p.type_.name.lower()
            return f"parameter '{p.name}' is {_a(declared_name)} {declared_name}, not {_a(given_name)} {given_name}"
    return None


def declare(node: Any) -> Settings:
    """Declare every parameter on an rclpy node and read them back. Descriptors carry the help,
    the range, the choices and read_only for what cannot change at run time."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
    from rclpy.exceptions import ParameterException

    def one(p: Param) -> Any:
        descriptor = ParameterDescriptor(description=p.help, read_only=not p.runtime,
                                         additional_constraints=" | ".join(p.choices),
                                         # YAML integers for float parameters (and the like) are coerced, not refused;
                                         # the on-set callback checks types
                                         dynamic_typing=True)
        if isinstance(p.default, float) and p.lo is not None and p.hi is not None:
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(p.lo), to_value=float(p.hi))]
        elif isinstance(p.default, int) and not isinstance(p.default, bool) and p.lo is not None and p.hi is not None:
            descriptor.integer_range = [IntegerRange(from_value=int(p.lo), to_value=int(p.hi), step=1)]
        try:
            value = node.declare_parameter(p.name, p.default, descriptor).value
        except ParameterException as err:  # a value given at start-up (-p, a file) outside the range
            raise ValueError(f"parameter {p.name}: {err}") from None
        if value is None:  # rcl reads an empty list ([] in a file or -p) as a parameter without a value (NOT_SET)
            value = [] if isinstance(p.default, list) else p.default
        return coerce(p.name, value, p.default)

    values: dict[str, Any] = {}
    for p in GLOBAL_PARAMS:
        values[p.name] = one(p)
    for name, p in param_table(values["sensors"]).items():  # per-sensor names depend on the sensors parameter
        if name not in values:
            values[name] = one(p)
    check(values)
    return Settings.from_values(values)


def colourless_note(sensor: SensorSettings, why: str) -> str:
    """What it means that a sensor of rgb_sensors gets no colour (`why`: no colour topic, none in the bag)."""
    return (f"{sensor.name}'s feature net takes colour (rgb_sensors) but {why}: its frames are fused with black "
            "colour, not as the weights were trained; set "
            f"{sensor.name}.color_topic to its colour images, or leave {sensor.name} out of rgb_sensors with "
            "weights trained that way")


def colourless_sensors(settings: Settings) -> list[str]:
    """Notes for the sensors of rgb_sensors without a colour topic."""
    return [colourless_note(sensor, f"{sensor.name}.color_topic is empty") for sensor in settings.sensors
            if sensor.name in settings.rgb_sensors and not sensor.color_topic]


def live_lag(settings: Settings) -> dict[str, Any]:
    """The live node's IngestConfig fields for lag: max_lag_s and the set-aside memory (behind_buffer_mb)."""
    return {"max_lag_s": settings.max_lag_s, "set_aside_bytes": int(settings.behind_buffer_mb * 2**20)}


def _a(noun: str) -> str:
    """The indefinite article before `noun`."""
    return "an" if noun[:1] in "aeiou" else "a"


def ingest_config(settings: Settings, **overrides: Any) -> Any:  # senfunet_ros.ingest.IngestConfig
    """Ingest configured by the node's parameters (the node and replay both use this); `overrides`
    replace fields. Frames are never skipped for lag here (offline readers take them all); the live
    node passes max_lag_s and set_aside_bytes (`live_lag`) from its parameters."""
    import dataclasses

    from senfunet_ros.ingest import IngestConfig

    s = settings
    config = IngestConfig(
        sensors=s.sensor_names,
        working_size=(s.working_width, s.working_height),
        queue_size=s.queue_size,
        pose_buffer_size=s.pose_buffer_size,
        pose_tolerance_s=s.pose_tolerance_s,
        pose_max_wait_s=s.pose_max_wait_s,
        color_tolerance_s=s.color_tolerance_s,
        time_jump_s=s.time_jump_s,
        restart_confirm_msgs=s.restart_confirm_msgs,
        restart_confirm_s=s.restart_confirm_s,
        pose_parser=PoseType(s.pose_type).parse,
        T_body_camera=sensor_extrinsics(s),
        fixed_frame=s.fixed_frame,  # where TF lookups go, the node's own TF lookup (tf=) too
        reset_on_time_jump=s.on_time_jump == "reset",
        voxel_size_m=s.voxel_size_m,  # a sensor's pixels further apart than 1.5 voxels are said (holes)
        depth_range_m={sensor.name: (sensor.depth_min_m, sensor.depth_max_m) for sensor in s.sensors},
        raw_depth=frozenset(sensor.name for sensor in s.sensors if names_raw_image(sensor.depth_topic)),
    )
    if PoseType(s.pose_type) is PoseType.TF and "tf" not in overrides:  # replay: /tf and /tf_static from the bag
        from senfunet_ros.tf import TfBuffer

        config = dataclasses.replace(config, tf=TfBuffer(max_gap_s=s.pose_tolerance_s))
    return dataclasses.replace(config, **overrides)


def sensor_extrinsics(settings: Settings) -> dict[str, Any]:
    """sensor -> T_body_camera 4x4, for the sensors whose pose topic is not the camera's (not identity)."""
    import numpy as np

    from senfunet_ros.geometry import transform_from_tq

    out = {}
    for sensor in settings.sensors:
        T = transform_from_tq(sensor.T_body_camera[:3], sensor.T_body_camera[3:], f"{sensor.name}.T_body_camera")
        if not np.array_equal(T, np.eye(4)):
            out[sensor.name] = T
    return out


def device_fallback(settings: Settings) -> str | None:
    """Why the networks do not run on the device parameter `device` names (CUDA asked for and absent:
    `engine_config` falls back to the cpu), to say to the user; None when they do."""
    from senfunet_core.networks import choose_device

    return choose_device(settings.device, cpu_fallback=True).fallback_reason


def engine_config(settings: Settings, **overrides: Any) -> Any:
    """EngineConfig as the node builds it (device 'cuda' falls back to 'cpu' when there is none);
    `overrides` replace fields (replay keeps the TSDF Fusion baseline and float32 alpha)."""
    import dataclasses

    from senfunet_core.engine import EngineConfig
    from senfunet_core.integrator import samples_along_band
    from senfunet_core.machine import usable_cpus
    from senfunet_core.networks import choose_device

    s = settings
    device = str(choose_device(s.device, cpu_fallback=True).device)
    n_samples, n_samples_behind = samples_along_band(s.voxel_size_m, s.band_m)
    config = EngineConfig(
        sensors=s.sensor_names,
        sensor_uses_rgb=tuple(name in s.rgb_sensors for name in s.sensor_names),
        depth_min_m=tuple(sensor.depth_min_m for sensor in s.sensors),
        depth_max_m=tuple(sensor.depth_max_m for sensor in s.sensors),
        voxel_size_m=s.voxel_size_m,
        band_m=s.band_m,
        n_samples=n_samples,  # at most a voxel apart, whatever the voxel size
        n_samples_behind=n_samples_behind,
        device=device,
        alpha_voxels="surface",  # the exact fused mesh for the least weighting-net work
        alpha_threads=usable_cpus(),  # a container's CPU quota too: threads beyond it only wait for each other
        alpha_dtype=alpha_dtype(s.alpha_precision, device, int8=True),
        alpha_order=s.alpha_order,
        feature_dtype=alpha_dtype(s.feature_precision, device),
        tsdf_fusion=s.tsdf_fusion,
        max_blocks=s.max_map_blocks,
        min_new_block_samples=s.min_new_block_samples,
    )
    return dataclasses.replace(config, **overrides)


def configure_engine(engine: Any, settings: Settings) -> None:
    """The engine's run-time settings (its sensors' depth limits) from the parameters as they are now."""
    import dataclasses

    engine.config = dataclasses.replace(engine.config,
                                        depth_min_m=tuple(sensor.depth_min_m for sensor in settings.sensors),
                                        depth_max_m=tuple(sensor.depth_max_m for sensor in settings.sensors))


def alpha_dtype(precision: str, device: str, *, int8: bool = False) -> str:
    """The engine's alpha_dtype (or feature_dtype) for parameter alpha_precision (feature_precision):
    'auto' picks bfloat16 on CPUs with native bfloat16 (oneDNN's check); elsewhere on the CPU int8
    where `int8` (the weighting net) and torch has working int8 convolutions; float32 else (and on
    CUDA, where it is cheap anyway)."""
    if precision != "auto":
        return precision
    import torch

    native = device == "cpu" and torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()
    if native:
        return "bfloat16"
    if int8 and device == "cpu":
        from senfunet_core.weighting_int8 import int8_available

        return "int8" if int8_available() else "float32"
    return "float32"


def engine_weights(settings: Settings) -> str | None:
    """The weights file the engine loads for parameter `weights` (None: untrained networks)."""
    from senfunet_core.networks import resolve_weights

    path = resolve_weights(settings.weights or "none")
    return None if path is None else str(path)
