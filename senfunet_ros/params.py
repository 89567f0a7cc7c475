"""The node's parameters as data: one table of (name, default, help).

The help text becomes the ROS ParameterDescriptor description, `config/default.yaml` mirrors the
table (a test checks both), and `declare(node)` returns the values as a frozen `Settings`.
Names containing `{sensor}` exist once per entry of `sensors`, e.g. `tof.depth_topic`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

from senfunet_ros.conversions.poses import PoseType

__all__ = ["Param", "GLOBAL_PARAMS", "SENSOR_PARAMS", "NODE_NAME", "expanded_defaults", "Settings", "declare"]

NODE_NAME = "senfunet"
ON_TIME_JUMP = ("reset", "ignore")


@dataclass(frozen=True)
class Param:
    name: str
    default: Any
    help: str


GLOBAL_PARAMS: tuple[Param, ...] = (
    Param("sensors", ["tof", "stereo"], "sensor names, sensor 1 first (alpha is the weight of sensor 1)"),
    Param("rgb_sensors", ["stereo"], "sensors whose feature net also takes the colour image (as the weights were trained)"),
    Param("pose_type", "pose_stamped", "pose message type on every pose topic: pose_stamped | odometry | transform_stamped"),
    Param("fixed_frame", "map", "frame the poses are given in; frame_id of every output"),
    Param("voxel_size_m", 0.01, "voxel side length in metres"),
    Param("band_m", 0.1, "length of the ray segment integrated around each depth measurement, metres"),
    Param("working_width", 256, "images are resized to this width (K scaled); 0 = native"),
    Param("working_height", 0, "images are resized to this height; 0 = native, or keep the aspect ratio if the width is set"),
    Param("queue_size", 30, "frames per sensor waiting for their pose; the oldest is dropped beyond this"),
    Param("max_lag_s", 0.25, "when integration falls behind, frames more than this (sensor time) older than their "
          "sensor's newest are skipped, which bounds the latency; 0 = never skip"),
    Param("pose_buffer_size", 2000, "poses kept per sensor for interpolation"),
    Param("pose_tolerance_s", 0.1, "max time between a depth stamp and the poses interpolated around it"),
    Param("pose_max_wait_s", 1.0,
          "a frame waits this long (sensor time) for a pose after its stamp, or for its first camera_info, then is dropped"),
    Param("color_tolerance_s", 0.02, "max stamp difference between a depth image and the colour image matched to it"),
    Param("time_jump_s", 1.0, "a stamp this far behind the previous one of its stream means time jumped back (bag restart)"),
    Param("on_time_jump", "reset", "what a backward time jump does to the map: reset | ignore"),
    Param("integrate_rate_hz", 30.0, "rate of the timer that integrates queued frames"),
    Param("mesh_rate_hz", 1.0, "rate of mesh updates (alpha, fusion, meshing of the changed blocks)"),
    Param("alpha_budget_s", 0.2, "seconds per mesh update spent re-evaluating the sensor weighting (after the update "
          "is published; the next one shows it); blocks left over wait for the next turn (those the latest frames "
          "reached first); 0 = no limit"),
    Param("weights_rate_hz", 0.2, "rate of ~/weights clouds (the whole map: heavier than a mesh update)"),
    Param("alpha_precision", "auto", "weighting-net arithmetic: auto (bfloat16 where the CPU has bfloat16 "
          "instructions, else float32) | float32 | bfloat16"),
    Param("status_rate_hz", 1.0, "rate of ~/status diagnostics"),
    Param("weights_band_m", 0.02, "~/weights holds voxels with |fused TSDF| at most this (near the surface); 0 = all observed"),
    Param("output_dir", "senfunet_output", "directory ~/save_mesh writes PLY files into"),
    Param("weights", "default", "network weights file; 'default' = the shipped weights, 'none' = untrained"),
    Param("device", "cpu", "torch device: cpu | cuda (falls back to cpu with a warning)"),
    Param("save_on_shutdown", False, "write the PLY files into output_dir when the node stops"),
    Param("max_map_blocks", 40000, "memory bound: past this many 8^3-voxel blocks (~20 KB each; the sample room "
          "needs ~34k at 1 cm) the blocks farthest from the sensor are dropped; 0 = unbounded"),
    Param("tsdf_fusion", False, "also keep the plain TSDF Fusion baseline (save_mesh adds tsdf_fusion.ply; "
          "about 15% more integration time and memory)"),
)

SENSOR_PARAMS: tuple[Param, ...] = (
    Param("{sensor}.depth_topic", "/{sensor}/depth", "depth image topic (32FC1 metres or 16UC1 millimetres)"),
    Param("{sensor}.color_topic", "/{sensor}/color", "colour image topic (rgb8, bgr8, mono8); empty = none"),
    Param("{sensor}.camera_info_topic", "/{sensor}/camera_info", "camera_info topic of the depth image"),
    Param("{sensor}.pose_topic", "/{sensor}/pose", "pose of the sensor's optical frame in fixed_frame"),
    Param("{sensor}.depth_min_m", 0.1, "depth below this is ignored, metres"),
    Param("{sensor}.depth_max_m", 3.0, "depth beyond this is ignored, metres (at 1 cm voxels and 256 px, rays beyond "
          "~3 m are > 2 voxels apart and noise spreads samples over many sparse blocks: memory and time, little surface)"),
)


def _fill(value: Any, sensor: str) -> Any:
    return value.replace("{sensor}", sensor) if isinstance(value, str) else value


def expanded_defaults(sensors: Sequence[str] | None = None) -> dict[str, tuple[Any, str]]:
    """Every parameter name -> (default, help), with per-sensor names expanded."""
    if sensors is None:
        sensors = GLOBAL_PARAMS[0].default
    out = {p.name: (p.default, p.help) for p in GLOBAL_PARAMS}
    for sensor in sensors:
        for p in SENSOR_PARAMS:
            out[_fill(p.name, sensor)] = (_fill(p.default, sensor), p.help)
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


def coerce(name: str, value: Any, default: Any) -> Any:
    """Values in the type of their default, so `mesh_rate_hz: 1` in YAML works."""
    try:
        if isinstance(default, bool):
            if isinstance(value, str):
                return value.strip().lower() in ("1", "true", "yes", "on")
            return bool(value)
        if isinstance(default, int):
            return int(value)
        if isinstance(default, float):
            return float(value)
        if isinstance(default, list):
            return [str(v) for v in value]
        return str(value)
    except (TypeError, ValueError) as err:
        raise ValueError(f"parameter '{name}' = {value!r} is not a {type(default).__name__}: {err}") from err


def check(values: dict[str, Any]) -> None:
    """Reject values the node cannot run with, saying which and why."""
    sensors = values["sensors"]
    if len(sensors) != 2 or len(set(sensors)) != 2:
        raise ValueError(f"parameter 'sensors' needs two distinct names, got {sensors}")
    pose_types = [p.value for p in PoseType]
    if values["pose_type"] not in pose_types:
        raise ValueError(f"parameter 'pose_type' = {values['pose_type']!r}; use one of {pose_types}")
    if values["alpha_precision"] not in ("auto", "float32", "bfloat16"):
        raise ValueError(f"parameter 'alpha_precision' = {values['alpha_precision']!r}; use auto, float32 or bfloat16")
    if values["on_time_jump"] not in ON_TIME_JUMP:
        raise ValueError(f"parameter 'on_time_jump' = {values['on_time_jump']!r}; use one of {ON_TIME_JUMP}")
    for name in ("voxel_size_m", "band_m", "integrate_rate_hz", "mesh_rate_hz", "status_rate_hz", "weights_rate_hz",
                 "pose_tolerance_s", "pose_max_wait_s", "time_jump_s"):
        if not values[name] > 0:
            raise ValueError(f"parameter '{name}' must be > 0, got {values[name]}")
    if not values["max_lag_s"] >= 0:
        raise ValueError(f"parameter 'max_lag_s' must be >= 0 (0 = never skip), got {values['max_lag_s']}")
    if not values["alpha_budget_s"] >= 0:
        raise ValueError(f"parameter 'alpha_budget_s' must be >= 0 (0 = no limit), got {values['alpha_budget_s']}")
    if values["queue_size"] < 1 or values["working_width"] < 0 or values["working_height"] < 0:
        raise ValueError("queue_size must be >= 1 and working_width/height >= 0")
    if values["max_map_blocks"] < 0:
        raise ValueError(f"parameter 'max_map_blocks' must be >= 0 (0 = unbounded), got {values['max_map_blocks']}")
    for sensor in sensors:
        lo, hi = values[f"{sensor}.depth_min_m"], values[f"{sensor}.depth_max_m"]
        if not 0 <= lo < hi:
            raise ValueError(f"{sensor}: depth range [{lo}, {hi}] m is empty; set depth_min_m < depth_max_m")


def declare(node: Any) -> Settings:
    """Declare every parameter on an rclpy node (help as the descriptor) and read them back."""
    from rcl_interfaces.msg import ParameterDescriptor

    def one(name: str, default: Any, help_text: str) -> Any:
        # dynamic typing: YAML integers for float parameters (and the like) are coerced, not refused
        descriptor = ParameterDescriptor(description=help_text, dynamic_typing=True)
        value = node.declare_parameter(name, default, descriptor).value
        return coerce(name, default if value is None else value, default)

    values: dict[str, Any] = {}
    for p in GLOBAL_PARAMS:
        values[p.name] = one(p.name, p.default, p.help)
    for sensor in values["sensors"]:  # per-sensor names depend on the sensors parameter
        for p in SENSOR_PARAMS:
            name = _fill(p.name, sensor)
            values[name] = one(name, _fill(p.default, sensor), p.help)
    check(values)
    sensors = tuple(
        SensorSettings(
            name=s,
            depth_topic=values[f"{s}.depth_topic"],
            color_topic=values[f"{s}.color_topic"],
            camera_info_topic=values[f"{s}.camera_info_topic"],
            pose_topic=values[f"{s}.pose_topic"],
            depth_min_m=values[f"{s}.depth_min_m"],
            depth_max_m=values[f"{s}.depth_max_m"],
        )
        for s in values["sensors"]
    )
    return Settings(values=values, sensors=sensors)


def ingest_config(settings: Settings, **overrides: Any) -> Any:  # senfunet_ros.ingest.IngestConfig
    """Ingest configured by the node's parameters (the node and replay both use this); `overrides`
    replace fields. Frames are never skipped for lag here (offline readers take them all); the live
    node passes max_lag_s from its parameter."""
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
        pose_parser=PoseType(s.pose_type).parse,
    )
    return dataclasses.replace(config, **overrides)


def engine_config(settings: Settings, **overrides: Any) -> Any:
    """EngineConfig as the node builds it (device 'cuda' falls back to 'cpu' when there is none);
    `overrides` replace fields (replay keeps the TSDF Fusion baseline and float32 alpha)."""
    import dataclasses

    import torch

    from senfunet_core.engine import EngineConfig

    s = settings
    device = s.device
    if device.startswith("cuda") and not torch.cuda.is_available():
        device = "cpu"
    config = EngineConfig(
        sensors=s.sensor_names,
        sensor_uses_rgb=tuple(name in s.rgb_sensors for name in s.sensor_names),
        depth_min_m=tuple(sensor.depth_min_m for sensor in s.sensors),
        depth_max_m=tuple(sensor.depth_max_m for sensor in s.sensors),
        voxel_size_m=s.voxel_size_m,
        band_m=s.band_m,
        device=device,
        alpha_voxels="surface",  # the exact fused mesh for the least weighting-net work
        alpha_dtype=alpha_dtype(s.alpha_precision, device),
        tsdf_fusion=s.tsdf_fusion,
        max_blocks=s.max_map_blocks,
    )
    return dataclasses.replace(config, **overrides)


def alpha_dtype(precision: str, device: str) -> str:
    """The engine's alpha_dtype for parameter alpha_precision: 'auto' picks bfloat16 on CPUs with
    native bfloat16 (oneDNN's check), float32 elsewhere (and on CUDA, where it is cheap anyway)."""
    if precision != "auto":
        return precision
    import torch

    native = device == "cpu" and torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()
    return "bfloat16" if native else "float32"


def engine_weights(settings: Settings) -> str | None:
    return None if settings.weights.lower() in ("none", "") else settings.weights
