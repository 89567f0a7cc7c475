"""SenFuNet engine: learned online fusion of depth sensors on sparse voxel blocks. No ROS in here.

The public surface, importable from this package:
- `SenFuNet`, `EngineConfig`, `MeshUpdate`: the engine (`engine`): integrate depth frames, update
  the fused map, extract meshes, save and load its state.
- `Mesh`, `BlockMeshes`: triangle meshes, whole or per block (`mesher`); `read_ply`, `write_ply`
  (`ply`); `render_mesh_png` (`render`); `mesh_metrics`, `grid_metrics` (`metrics`).
- `choose_device`: the one decision of the torch device the networks run on (`networks`).
- `SenFuNetError`, `InputError`: what the engine raises on purpose (`errors`).

Modules by concern: `engine` schedules (integration, weighting, meshing, eviction) over the map
`grid` (sparse blocks, hash table, pools) and keeps the final meshes of evicted blocks in
`mesh_archive`; `integrator`, `alpha`, `fusion` and `mesher` hold the kernels of each step;
`networks` the learned parts. `learning/` is offline tooling (simulator, training, evaluation)
that nothing at run time imports.

Names are imported on first use, so `import senfunet_core.errors` does not load torch or numba.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__all__ = [
    "SenFuNet", "EngineConfig", "MeshUpdate",
    "Mesh", "BlockMeshes", "read_ply", "write_ply", "render_mesh_png", "mesh_metrics", "grid_metrics",
    "choose_device",
    "SenFuNetError", "InputError",
]

_HOME = {
    "SenFuNet": "engine", "EngineConfig": "engine", "MeshUpdate": "engine",
    "Mesh": "mesher", "BlockMeshes": "mesher", "read_ply": "ply", "write_ply": "ply", "render_mesh_png": "render",
    "mesh_metrics": "metrics", "grid_metrics": "metrics", "choose_device": "networks",
    "SenFuNetError": "errors", "InputError": "errors",
}

if TYPE_CHECKING:
    from .engine import EngineConfig, MeshUpdate, SenFuNet
    from .errors import InputError, SenFuNetError
    from .mesher import BlockMeshes, Mesh
    from .metrics import grid_metrics, mesh_metrics
    from .networks import choose_device
    from .ply import read_ply, write_ply
    from .render import render_mesh_png


def __getattr__(name: str) -> Any:
    module = _HOME.get(name)
    if module is None:
        raise AttributeError(f"module 'senfunet_core' has no attribute '{name}'")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
