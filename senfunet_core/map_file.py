"""A map on disk: the whole engine state (config, grids, networks, the archived meshes of evicted
blocks and the blocks spilled to disk) in one file, written atomically, and read back, whatever
earlier version of the format wrote it.

    save_map(engine, "map.pt")
    engine = load_map("map.pt")       # the next update re-sends the whole mesh
"""
from __future__ import annotations

import logging
import time
import zipfile
from collections.abc import Callable
from dataclasses import asdict, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .engine import EngineConfig, SenFuNet, int8_weighting
from .errors import InputError
from .files import atomic_file
from .grid import BlockGrid, block_keys, decode_saved_features, encode_alpha, encode_features, keys_to_coords
from .integrator import REACH_ALL
from .spill import BlockSpill, spilled_rows
from .weighting_int8 import Int8Calibration

__all__ = ["RUN_FIELDS", "save_map", "load_map"]

# how an engine runs, not what its grids and networks mean: a map loaded into a running process (the
# node) runs with the caller's, so that its parameters say what runs
RUN_FIELDS = ("depth_min_m", "depth_max_m", "device", "alpha_batch_blocks", "mesh_batch_blocks", "torch_threads",
              "alpha_threads", "alpha_voxels", "alpha_order", "alpha_dtype", "feature_dtype", "max_blocks",
              "min_new_block_samples")

log = logging.getLogger("senfunet.map_file")


def save_map(engine: SenFuNet, path: str | Path) -> None:
    """The whole engine state (config, grids, networks, archive, spill) in one file, written
    atomically; thread-safe, as frames keep being integrated. Alpha is saved as it stands, with the
    blocks the weighting net still owes (`alpha_stale`): the loaded map judges them. (Judging them
    first held the map from mesh updates and the other services for the whole backlog: tens of
    seconds on a room during a stream.)"""
    with engine.update_lock.held():
        engine.alpha.schedule()  # the changes integrated since the last schedule: stale blocks too
        with engine.data_lock:
            n = engine.grid.n_blocks
            state = {
                "format": "senfunet-engine-1",
                "config": asdict(engine.config),
                "grid": _grid_state(engine.grid),
                "feature_nets": [net.state_dict() for net in engine.feature_nets],
                "weighting_net": engine.weighting_net.state_dict(),
                "frames_integrated": dict(engine.frames_integrated),
                # what the net owes, per block in the grid's order: its stale level, whether it ever judged it
                "alpha_stale": torch.from_numpy(engine.store.stale[:n].copy()),
                "alpha_evaluated": torch.from_numpy(engine.store.evaluated[:n].copy()),
                "archive": {k: torch.from_numpy(np.ascontiguousarray(v))
                            for k, v in engine.archive.state_dict().items()},
                # what evictions did, beside what they left (archive, spill): ~/status counts on
                "evictions": {**engine.bound.tallies(),
                              "restored_blocks": engine.grid.spill.restored if engine.grid.spill is not None else 0},
            }
            if engine.alpha.evaluator.int8_net is not None:  # its calibration goes with G's weights
                state["int8_calibration"] = asdict(engine.alpha.evaluator.int8_net.calibration)
            if engine.grid.spill is not None:
                state["spill"] = {k: torch.from_numpy(v) for k, v in engine.grid.spill.state_dict().items()}
    with atomic_file(path) as file:
        try:
            torch.save(state, file)
        except RuntimeError as err:  # torch reports a write that failed (a full disk) as "unexpected pos"
            if not isinstance(err.__context__, OSError):
                raise
            raise OSError(err.__context__.errno, f"cannot write {path}: {err.__context__.strerror}") from err


def load_map(path: str | Path, *, run_config: EngineConfig | None = None,
             worker_setup: Callable[[], object] | None = None) -> SenFuNet:
    """An engine with the state `save_map` wrote; the next update re-sends the whole mesh.
    worker_setup: as for `SenFuNet`. run_config: the caller's settings, whose RUN_FIELDS (arithmetic,
    threads, scheduling, the map bound, the allocation policy) the engine takes instead of those the
    map was saved with; int8 alpha needs the calibration saved with the map (float32 without it,
    said in the log)."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such map file (save_map writes one)")
    # torch.save writes a zip archive: anything else (a PLY, a file cut short) would get torch's own
    # error, which names weights_only and advises loading the file unsafely, or a bare "[Errno 22]";
    # torch.load does not check the archive's checksums: a file damaged inside loaded as a wrong map
    if path.is_file():  # an unreadable one: the OSError here
        try:
            with zipfile.ZipFile(path) as archive:
                damaged = archive.testzip()
        except (zipfile.BadZipFile, EOFError):
            raise InputError(f"{path} is not a map (~/save_map writes one: a zip archive), or it is damaged (cut "
                             "short?)") from None
        if damaged is not None:
            raise InputError(f"{path} is damaged: its part {damaged} fails its checksum (changed since it was "
                             "written: an incomplete copy, a failing disk?); load another copy of the map")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        made = state.get("format") if isinstance(state, dict) else None
        if isinstance(made, str) and made.startswith("senfunet-engine-") and made != "senfunet-engine-1":
            raise InputError(f"{path} is a map of another version of SenFuNet ({made}; this one reads "
                             "senfunet-engine-1): load it with the version that saved it, or fuse the recording again "
                             "(play it to the node, then ~/save_map)")
        if made != "senfunet-engine-1":  # another torch file (weights, a checkpoint)
            raise InputError(f"{path} is not a SenFuNet engine state (~/save_map writes one); set parameter "
                             "map_file to such a map")
        missing = [key for key in ("config", "grid", "feature_nets", "weighting_net", "frames_integrated")
                   if key not in state]
        if missing:
            raise InputError(f"{path} is an incomplete engine state (no {', '.join(missing)}); save the map again")
    except (InputError, MemoryError):  # a file too large for the memory left is no damaged file
        raise
    except Exception as err:  # torch's own words (a zip of something else: "[enforce fail at ...]") say neither
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise InputError(f"{path} is not a map ~/save_map wrote, or it is damaged ({reason}); set parameter "
                         "map_file to a map ~/save_map wrote") from err
    known = {f.name for f in fields(EngineConfig)}
    config_values: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v
                                     for k, v in state["config"].items() if k in known}
    config = EngineConfig(**config_values)
    if run_config is not None:
        config = replace(config, **{name: getattr(run_config, name) for name in RUN_FIELDS})
    saved_calibration = state.get("int8_calibration")
    if config.alpha_dtype == "int8" and not isinstance(saved_calibration, dict):
        log.warning("%s was saved with the weighting net in %s, without its int8 calibration: the net runs in "
                    "float32", path, state["config"].get("alpha_dtype", "float32"))
        config = replace(config, alpha_dtype="float32")
    # G's int8 form is built once its weights are loaded, from the calibration saved with them
    engine = SenFuNet(replace(config, alpha_dtype="float32") if config.alpha_dtype == "int8" else config,
                      weights=None, worker_setup=worker_setup)
    for net, net_state in zip(engine.feature_nets, state["feature_nets"]):
        net.load_state_dict(net_state)
    engine.weighting_net.load_state_dict(state["weighting_net"])
    if config.alpha_dtype == "int8":
        assert isinstance(saved_calibration, dict)
        int8_net = int8_weighting(engine.weighting_net, config, calibration=Int8Calibration(**saved_calibration))
        engine.alpha.evaluator.int8_net = int8_net
        engine.config = replace(engine.config, alpha_dtype="int8" if int8_net is not None else "float32")
    engine.weights_source = f"{path} (saved state)"
    grid_state, spill_loads = _grid_state_for(engine.grid, path, state)
    _load_grid_state(engine.grid, grid_state)
    drifted = np.flatnonzero(_drifted_blocks(grid_state))  # slots follow the saved order
    engine.store.alpha_pending[drifted] = True
    engine.store.reach_renewed[drifted] = REACH_ALL
    if spill_loads:
        if engine.grid.spill is None:
            engine.grid.spill = BlockSpill()
        engine.grid.spill.load_state_dict({k: v.numpy() for k, v in state["spill"].items()})
        engine.grid.spill.restored = int(state.get("evictions", {}).get("restored_blocks", 0))
    engine.frames_integrated.update(state["frames_integrated"])
    engine.bound.restore_tallies(state.get("evictions", {}))  # maps saved before they were kept: none
    if engine.bound.evictions:
        engine.counters.update(evicted_blocks=engine.bound.evicted_blocks, evictions=engine.bound.evictions)
    if "archive" in state:
        engine.archive.load_state_dict({k: v.numpy() for k, v in state["archive"].items()})
        engine.bound.newly_archived = [engine.archive.meshes()]  # re-sent with the whole mesh
    engine.store.grow_flags()
    engine.store.evaluated[: engine.grid.n_blocks] = True  # alpha is part of the saved state
    if "alpha_stale" in state:  # what the net still owed when the map was saved (maps before this: nothing)
        owed = state["alpha_stale"].numpy()
        engine.store.stale[: len(owed)] = np.maximum(engine.store.stale[: len(owed)], owed)
        engine.store.evaluated[: len(owed)] = state["alpha_evaluated"].numpy()
        engine.store.last_change_s[np.flatnonzero(owed)] = time.monotonic()  # its wait starts with the load
    engine.store.mesh_pending[: engine.grid.n_blocks] = True
    return engine


def _grid_state(grid: BlockGrid) -> dict:
    """The blocks in use: their coordinates and every pool's rows (copies)."""
    n = grid.n_blocks
    return {"coords": grid.coords[:n].clone(), **{f"pool.{k}": v[:n].clone() for k, v in grid.pools.items()}}


def _load_grid_state(grid: BlockGrid, grid_state: dict) -> None:
    """The grid holds the blocks of this state (`_grid_state`, or `_grid_state_for` of an earlier
    version's) and no others; feature pools saved with another packing are converted."""
    grid.clear()
    slots = grid.allocate_keys(block_keys(grid_state["coords"]))
    for name, pool in grid.pools.items():
        saved = grid_state[f"pool.{name}"]
        if pool.dtype == torch.int8 and saved.shape[-1] != pool.shape[-1]:  # saved by an earlier version
            saved = encode_features(decode_saved_features(saved, grid.channel_shapes[name][0]))
        pool[slots] = saved.to(pool.dtype)


def _grid_state_for(grid: BlockGrid, path: Path, state: dict) -> tuple[dict, bool]:
    """The grid state of a saved map in this version's layout, and whether its spill can be loaded
    as it is. Maps saved by earlier versions hold alpha as float16 values (converted here) and a
    per-voxel drift channel (`_drifted_blocks`); other feature packings convert in `_load_grid_state`.
    A spill written with another row layout cannot be read block by block later: its blocks come back
    into memory here, converted with the others (the map bound evicts them again)."""
    grid_state = dict(state["grid"])
    saved = {name[len("pool."):]: pool for name, pool in grid_state.items() if name.startswith("pool.")}
    saved_layout = [(name, int(np.prod(pool.shape[1:])) * pool.element_size()) for name, pool in saved.items()]
    layout = [(name, pool[0].numel() * pool.element_size()) for name, pool in grid.pools.items()]
    spill = {k: v.numpy() for k, v in state["spill"].items()} if "spill" in state else None
    spill_loads = spill is not None and len(spill["keys"]) > 0 and saved_layout == layout
    if spill is not None and len(spill["keys"]) and not spill_loads:
        keys, rows = spilled_rows(spill)
        sizes = [size for _, size in saved_layout]
        if rows.shape[1] != sum(sizes):
            raise InputError(f"{path}: its spilled blocks hold {rows.shape[1]} bytes each where its channels "
                             f"need {sum(sizes)}: the file is damaged; replay the recording to rebuild the map")
        columns = np.split(rows, np.cumsum(sizes)[:-1], axis=1)
        for (name, pool), column in zip(saved.items(), columns):
            back = torch.from_numpy(column.copy()).view(pool.dtype).reshape(len(keys), *pool.shape[1:])
            grid_state[f"pool.{name}"] = torch.cat([pool, back])
        grid_state["coords"] = torch.cat([grid_state["coords"], keys_to_coords(torch.from_numpy(keys))])
        log.info("%s: %d blocks it had spilled to disk were saved in an earlier layout: loaded into memory "
                 "(past the map bound they go back to disk at the next update)", path, len(keys))
    if grid_state["pool.alpha"].dtype != torch.uint8:
        grid_state["pool.alpha"] = torch.from_numpy(encode_alpha(grid_state["pool.alpha"].float().numpy()))
    return grid_state, spill_loads


def _drifted_blocks(grid_state: dict) -> np.ndarray:
    """Which blocks of a saved grid state (from a version that kept a per-voxel drift channel) had
    inputs that changed since alpha was last scheduled there (bool per block; none without it)."""
    drift = grid_state.get("pool.drift")
    if drift is None:
        return np.zeros(len(grid_state["coords"]), bool)
    return (drift.reshape(len(drift), -1) != 0).any(dim=1).numpy()
