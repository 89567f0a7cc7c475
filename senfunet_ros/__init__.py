"""The thin ROS 2 layer around `senfunet_core`: messages in, numpy to the engine, meshes out.

Modules: `conversions` (messages <-> numpy, one module per concern), `geometry` (rotations and
poses), `ingest` (messages -> posed frames, per-stream timelines), `params` (the parameter table),
`node` (the live node), `replay` and `bagio` (recordings), `dds` (transport settings) and `cli`
with `commands` (the `senfunet` entry point). Submodules are imported on use: `senfunet simulate`
never loads rclpy.
"""

__all__ = ["bagio", "cli", "conversions", "dds", "geometry", "ingest", "node", "params", "replay"]
