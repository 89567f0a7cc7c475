"""Procedural indoor scenes, two simulated depth sensors (ToF and stereo) and exact ground truth.

Pure numpy + OpenCV; no ROS. Everything is deterministic for a seed. This module gathers the
public names of the simulator's parts: `scenes` (procedural rooms), `geometry` (SDF, GT TSDF, GT
mesh), `raycast` (rendering), `sensors` (ToF and stereo depth), `trajectory` (the device's walk),
`sequences` (two-sensor recordings) and `datasets` (files).

Convention: world z up, metres. Cameras use the optical frame (z forward, x right, y down) and
`T_world_camera` maps camera coordinates to world coordinates. Depth is z-depth, float32, 0 =
invalid. Ray directions are built with a camera-frame z component of 1, so the ray parameter of
a hit *is* its z-depth.
"""
from __future__ import annotations

from .datasets import load_dataset, write_dataset
from .geometry import gt_mesh, gt_tsdf, gt_tsdf_blocks, scene_sdf
from .raycast import intrinsics, intrinsics_scaled, render_view
from .scenes import Primitive, Scene, Surface, make_scene
from .sensors import SENSORS, STEREO_BASELINE_M, TOF_OFFSET_X_M, simulate_stereo_depth, simulate_tof_depth
from .sequences import SensorFrame, Sequence, simulate_sequence
from .trajectory import Trajectory

__all__ = [
                      "SENSORS",
                      "STEREO_BASELINE_M",
                      "TOF_OFFSET_X_M",
                      "Primitive",
                      "Scene",
                      "SensorFrame",
                      "Sequence",
                      "Surface",
                      "Trajectory",
                      "gt_mesh",
                      "gt_tsdf",
                      "gt_tsdf_blocks",
                      "intrinsics",
                      "intrinsics_scaled",
                      "load_dataset",
                      "make_scene",
                      "render_view",
                      "scene_sdf",
                      "simulate_sequence",
                      "simulate_stereo_depth",
                      "simulate_tof_depth",
                      "write_dataset",
]
