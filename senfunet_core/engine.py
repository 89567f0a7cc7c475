"""The SenFuNet engine: the networks and a few verbs over the map.

    engine = SenFuNet(EngineConfig(), weights="default")
    engine.integrate("tof", depth_m, K, T_world_camera)        # at sensor rate
    update = engine.update()                                    # alpha, fusion, meshing of changed blocks
    mesh = engine.extract_mesh("fused")                         # or a sensor name, or "tsdf_fusion"

Rooms: the map's blocks and per-block flags live in `block_store.BlockStore`; which blocks the
weighting net must judge, and judging them, in `alpha_scheduler.AlphaScheduler`; the final meshes
of evicted blocks in `mesh_archive.MeshArchive`, and their voxels in `spill.BlockSpill` (on disk).
This module holds the verbs, the locks, the map bound and meshing.

Incremental update: a frame marks the blocks it touched, and every voxel accumulates how much its
weighting-net inputs drifted (see `alpha`). `update` re-evaluates alpha within 2 voxels of a
drifted one, where alpha matters (EngineConfig.alpha_voxels; the result equals evaluating the net
over the whole grid there); then it re-meshes every block whose cells read a changed alpha or TSDF
(the changed blocks and their -x, -y, -z neighbours, since a block's cells reach one voxel into its
+x, +y, +z neighbours).

Threading model (the one place it is described):
- Threads: an integrating thread calls `prepare`/`integrate`; an updating thread calls `update`,
  `refresh_alpha`, the extractions, `save`, `reset`; one feature-net worker thread (module-wide)
  runs the 2D nets; with `alpha_threads` > 1, that many alpha threads (per engine) evaluate the
  weighting net's batches for an update that has no time budget (or an idle catch-up,
  `refresh_alpha(until_frame=True)`), while the updating thread waits for them in order and writes
  their results. Several threads may integrate, and several may
  update: the locks serialise them.
- The update lock (`_updating`) serialises updates, extractions, saves and evictions; it owns the
  alpha scheduler's order, the mesh archive and the set of meshed blocks.
- The data lock guards the grid's contents and the per-block flags: integration holds it while its
  kernels run, an update while it takes the frames' drift, writes alpha or evicts. An update (or
  its alpha threads, which write nothing) reads input windows without it (and `stats` counts
  voxels without it): a block integrated meanwhile is marked again and re-read by the next update,
  and pools that grow meanwhile stay valid for whoever still holds the old ones. Evictions wait
  for the batches being evaluated.
- Lock order: update lock, then data lock. Integration never takes the update lock while holding
  the data lock; past the map's hard bound it releases the data lock, takes the eviction condition,
  and either evicts itself (the update lock free: tried without blocking) or waits on the condition,
  which every eviction and every release of the update lock notifies. Nobody takes the condition
  while holding the data lock, so the waiter may evict under it. No thread polls.
"""
from __future__ import annotations

import collections
import contextlib
import logging
import os
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, fields, replace
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from . import networks
from .alpha_scheduler import AlphaBatch, AlphaScheduler
from .block_store import BlockStore, Eviction
from .errors import InputError
from .fusion import WINDOW_BASE, WINDOW_FUSED, WINDOW_SENSOR, fuse, mesh_windows
from .grid import BlockGrid, block_keys, keys_to_coords
from .integrator import IntegratorConfig, check_frame, check_key_range, integrate_frame, valid_depth_mask
from .memory import large_allocations_outside_the_heap, release_free_memory
from .mesh_archive import MeshArchive
from .mesher import BlockMeshes, BlockTriangles, Mesh, StreamingWeld, marching_cubes_blocks, to_mesh
from .spill import BlockSpill

log = logging.getLogger("senfunet.engine")

TSDF_FUSION = "tsdf_fusion"
FUSED = "fused"
# Neighbour-table codes of the blocks whose marching-cubes cells read a block: itself and its
# -x, -y, -z neighbours (code 9*(dx+1) + 3*(dy+1) + (dz+1), offsets in {-1, 0}).
_MESH_READER_CODES = np.array([9 * dx + 3 * dy + dz for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)])
# ... and of the blocks a block's cells read: itself and its +x, +y, +z neighbours
_MESH_READ_CODES = np.array([9 * dx + 3 * dy + dz for dx in (1, 2) for dy in (1, 2) for dz in (1, 2)])
# integrate() itself drops far blocks once the map exceeds max_blocks by this factor (updates do it first)
_HARD_BOUND = 1.25
# One thread runs the feature nets (of every engine in the process), so that a frame's feature net
# overlaps the kernels of the frame before it (see `prepare`) and the kernel that locates its samples.
_FEATURE_WORKER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="senfunet-features")


@dataclass(frozen=True)
class EngineConfig:
    """Engine settings. Tuples hold one value per sensor, in sensor order (sensor 1 first)."""

    sensors: tuple[str, ...] = ("tof", "stereo")  # sensor names; alpha weights sensor 1
    sensor_uses_rgb: tuple[bool, ...] = (False, True)  # feature net takes RGB too (stereo-type sensors)
    depth_min_m: tuple[float, ...] = (0.1, 0.1)  # valid depth range per sensor
    depth_max_m: tuple[float, ...] = (5.0, 5.0)
    voxel_size_m: float = 0.01  # voxel side length
    band_m: float = 0.1  # ray segment sampled around each measurement
    n_samples: int = 11  # samples along the band
    n_samples_behind: int = 3  # samples written behind the surface
    w_max: float = 500.0  # weight counter clip
    border_px: int = 10  # masked image border
    device: str = "cpu"  # where the networks run: "cpu" or "cuda" (the grids stay in CPU memory)
    alpha_batch_blocks: int = 128  # blocks per weighting-net batch (memory vs. how long readers hold the grid)
    mesh_batch_blocks: int = 2048  # blocks per marching-cubes call
    seed: int = 0  # initialisation of untrained networks
    torch_threads: int = 1  # torch intra-op threads the engine sets (0: leave torch's setting); 1 fits 2 shared cores
    alpha_threads: int = 1  # threads evaluating weighting-net batches side by side in updates without a time budget
    #                         (extraction, saving, catch-up); each batch stays on one thread, so alpha is the same
    alpha_voxels: str = "all"  # where alpha near a change is re-evaluated: "all" (equals the whole-grid
    #   evaluation on every voxel); "surface" (blocks holding corners of cells whose 8 corners are observed and whose
    #   sensor TSDFs straddle 0: all that the fused mesh, its filter and its colours read; alpha elsewhere may be
    #   stale); "surface_voxels" (those corners alone, voxel by voxel: less arithmetic, more gathering)
    alpha_dtype: str = "float32"  # weighting-net arithmetic: "float32", or "bfloat16" (faster on CPUs with
    #                               bfloat16 instructions, alpha close to float32's; see test_equivalence.py)
    max_blocks: int = 0  # memory bound: past this many blocks, each update evicts the blocks farthest from the
    #   last camera position (down to 90%), and so does integration past 1.25x, keeping their final fused meshes
    #   (mesh_archive); 0 = no bound; -1 = from the machine's memory (`memory_bound_blocks`)
    tsdf_fusion: bool = True  # also integrate every frame into one plain TSDF grid: the "tsdf_fusion" baseline
    #                           (one more running average per sample and 6 bytes per voxel)
    alpha_tolerance: float = 0.0  # re-evaluate alpha around a voxel only once its inputs drifted more than this
    #                               (max-norm over [F, tanh(W)], summed over frames); 0 = exact
    min_new_block_samples: int = 16  # allocation policy: a frame allocates a block only where at least this many of
    #   its ray samples land; samples in blocks not allocated are dropped and counted (counters
    #   "sparse_dropped_samples", "sparse_dropped_blocks"); blocks already in the map take every sample. 0 = allocate
    #   every touched block. The default was chosen on the validation rooms (bench/allocation_policy.py): one
    #   isolated ray writes fewer samples than that (at most (n_samples - 1) / 2 + n_samples_behind + 1), so a new
    #   block needs two rays or more; larger thresholds started to lose far surfaces (mean F fell), smaller ones kept
    #   far more nearly empty blocks at no gain in F
    weighting_tsdf_input: bool = False  # the weighting net also reads the sensors' TSDFs (a departure from the
    #   paper, networks.WeightingNet); set from the weights file when it records it

    @property
    def integrator(self) -> IntegratorConfig:
        return IntegratorConfig(self.voxel_size_m, self.band_m, self.n_samples, self.n_samples_behind, self.w_max,
                                self.border_px, self.min_new_block_samples)

    def validate(self) -> None:
        n = len(self.sensors)
        if n != 2:
            raise InputError(f"SenFuNet fuses exactly 2 sensors, got {n}: {self.sensors}")
        if len(set(self.sensors)) != n or FUSED in self.sensors or TSDF_FUSION in self.sensors:
            raise InputError(f"sensor names must be distinct and not '{FUSED}'/'{TSDF_FUSION}': {self.sensors}")
        for name in ("sensor_uses_rgb", "depth_min_m", "depth_max_m"):
            if len(getattr(self, name)) != n:
                raise InputError(f"{name} needs one value per sensor ({n}), got {getattr(self, name)}")
        if self.voxel_size_m <= 0 or self.band_m <= 0 or self.n_samples < 2 or self.w_max < 1:
            raise InputError("voxel_size_m, band_m must be > 0, n_samples >= 2, w_max >= 1")
        if not 0 <= self.n_samples_behind <= (self.n_samples - 1) // 2:
            raise InputError("n_samples_behind must be between 0 and (n_samples - 1) / 2")
        if self.w_max > 2048:
            raise InputError("w_max must be at most 2048 (weight counters are float16, exact up to 2048)")
        if self.alpha_dtype not in ("float32", "bfloat16"):
            raise InputError(f"alpha_dtype must be 'float32' or 'bfloat16', got '{self.alpha_dtype}'")
        if self.alpha_voxels not in ("all", "surface", "surface_voxels"):
            raise InputError(f"alpha_voxels must be 'all', 'surface' or 'surface_voxels', got '{self.alpha_voxels}'")
        if self.max_blocks < -1:
            raise InputError(f"max_blocks must be >= 0 (0 = no bound) or -1 (from the machine's memory), "
                             f"got {self.max_blocks}")
        if self.min_new_block_samples < 0:
            raise InputError(f"min_new_block_samples must be >= 0 (0 = allocate every touched block), "
                             f"got {self.min_new_block_samples}")
        if not self.alpha_tolerance >= 0 or self.torch_threads < 0 or self.alpha_threads < 1:
            raise InputError("alpha_tolerance must be >= 0, torch_threads >= 0 and alpha_threads >= 1")


@dataclass
class MeshUpdate:
    """What changed in the fused mesh since the previous update."""

    meshes: BlockMeshes = field(default_factory=lambda: BlockMeshes.concatenate([]))  # changed blocks' whole meshes
    removed: list[tuple[int, int, int]] = field(default_factory=list)  # blocks whose mesh vanished
    cleared: bool = False  # the map was reset before this update: drop everything shown so far

    @property
    def changed(self) -> dict[tuple[int, int, int], Mesh]:
        """Block key -> its whole mesh, for every changed block."""
        return self.meshes.as_dict()


@dataclass
class PreparedFrame:
    """A checked frame whose feature net is running (`SenFuNet.prepare`)."""

    sensor_index: int
    depth_m: np.ndarray  # float32, NaN and inf set to 0
    K: np.ndarray
    T_world_camera: np.ndarray
    features: Future | None  # of the 5 x H x W pixel features; None when no pixel is valid
    checks_s: float  # time `prepare` took (counted as integration)


@dataclass
class WeightCloud:
    positions_m: np.ndarray  # Nx3 float32 voxel centres
    alpha: np.ndarray  # N float32 sensor weighting (weight of sensor 1)
    weights: np.ndarray  # N x n_sensors float32 weight counters


def _done(value: Any) -> Future:
    """A future that already holds `value`."""
    future: Future = Future()
    future.set_result(value)
    return future


def _joined(meshes: list[Mesh]) -> Mesh:
    """One mesh of several (vertices not shared between them)."""
    if len(meshes) == 1:
        return meshes[0]
    starts = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    colors = [m.colors if m.colors is not None else np.ones((len(m.vertices), 3), np.float32) for m in meshes]
    return Mesh(np.concatenate([m.vertices for m in meshes]),
                np.concatenate([m.faces + start for m, start in zip(meshes, starts)]).astype(np.int32),
                np.concatenate(colors))


def _with_seams(archived: BlockMeshes, seams: dict[tuple[int, int, int], Mesh]) -> BlockMeshes:
    """The evicted blocks' meshes with the seam triangles that go with them (`SenFuNet._seam_meshes`)."""
    if not seams:
        return archived
    meshes = archived.as_dict()
    for block, seam in seams.items():
        meshes[block] = _joined([meshes[block], seam]) if block in meshes else seam
    return BlockMeshes.from_meshes(meshes)


def _compact_offsets(offsets: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Offsets of the kept blocks' ranges when the dropped blocks' ranges are empty."""
    return np.concatenate([[offsets[0]], offsets[keep + 1]]).astype(np.int64)


def memory_bound_blocks(bytes_per_block: int, *, memory_fraction: float = 0.5) -> int:
    """How many blocks fit in `memory_fraction` of this machine's memory (at most 80% of what is
    available now): the default map bound follows the machine, not a fixed count."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    available = total
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    available = int(line.split()[1]) * 1024
    except OSError:
        pass
    budget = min(memory_fraction * total, 0.8 * available)
    return max(1024, int(budget // bytes_per_block))


class SenFuNet:
    """Learned two-sensor TSDF fusion on sparse voxel blocks, plus the plain TSDF Fusion baseline."""

    _cleared: bool  # reset since the last mesh update (set by _reset_state, which __init__ calls)
    _newly_archived: list[BlockMeshes]  # evicted blocks' final meshes, sent by the next update

    def __init__(self, config: EngineConfig = EngineConfig(), weights: str | Path | None = "default") -> None:
        config.validate()
        self.config = config
        large_allocations_outside_the_heap()  # the net's batch tensors: else a heap as deep as several stays
        self.device = networks.choose_device(config.device, cpu_fallback=False).device
        if config.torch_threads > 0 and torch.get_num_threads() != config.torch_threads:
            torch.set_num_threads(config.torch_threads)
        self.weights_source = "random initialisation (untrained)"
        if weights == "default":
            if networks.DEFAULT_WEIGHTS.is_file():
                weights = networks.DEFAULT_WEIGHTS
            else:
                log.warning("no shipped weights at %s: using untrained networks", networks.DEFAULT_WEIGHTS)
                weights = None
        if weights is not None and networks.weights_tsdf_input(weights) != config.weighting_tsdf_input:
            config = replace(config, weighting_tsdf_input=networks.weights_tsdf_input(weights))
            self.config = config
        self.feature_nets, self.weighting_net = networks.make_networks(config.sensor_uses_rgb, config.seed,
                                                                       config.weighting_tsdf_input)
        if weights is not None:
            networks.load_weights(weights, self.feature_nets, self.weighting_net)
            self.weights_source = str(weights)
        self.feature_nets.to(self.device).eval()
        self.weighting_net.to(self.device).eval()
        # drift: per voxel, how much its weighting-net inputs changed since alpha around it was evaluated
        channels: dict[str, tuple[int, ...]] = {"alpha": (), "drift": ()}
        if config.tsdf_fusion:
            channels.update({"tsdf_base": (), "weight_base": ()})
        for i in range(len(config.sensors)):
            channels.update({f"tsdf{i}": (), f"weight{i}": (), f"feat{i}": (networks.N_FEATURES,)})
        # Every channel in half precision: weight counters stay exact up to 2048 (w_max); TSDF values
        # within the band keep a relative precision of 2^-11, far below the sensors' noise; alpha is a
        # weighting in [0, 1] (NaN: not evaluated). Kernels read them through grid.load_f32. The
        # learned features lie in [-1, 1]: int8 (steps of 1/127), the depth feature float16, packed
        # in one int8 pool (grid.FEATURE_SCALE, read through grid.load_feature / decode_features).
        dtypes = {name: torch.int8 if name.startswith("feat") else torch.float16 for name in channels}
        # alpha NaN until evaluated: C12 averaged, the filter holds single-sensor voxels back (see fusion)
        self.store = BlockStore(BlockGrid(channels, dtypes=dtypes, fill={"alpha": float("nan")}))
        self.grid = self.store.grid
        self.max_blocks = config.max_blocks  # the map bound in force (resolved from memory for -1)
        if config.max_blocks == -1:
            self.max_blocks = memory_bound_blocks(self.grid.bytes_per_block())
            log.info("map bound: %d blocks (half of this machine's memory at %d bytes a block)", self.max_blocks,
                     self.grid.bytes_per_block())
        if self.max_blocks > 0:  # evicted blocks go to disk, and come back when the sensors reach them again
            self.grid.spill = BlockSpill()
            self.grid.restored_fill = {"drift": float("inf")}  # alpha within 2 voxels of them is re-judged
        self.archive = MeshArchive()  # final meshes of evicted blocks (owned by the update lock)
        # Writers of the grid (integration, alpha) hold the data lock; the update's readers do not:
        # a block integrated while it is read is marked again and re-read by the next update, and
        # pools that grow meanwhile stay valid for whoever still holds the old ones.
        self._data_lock = threading.RLock()
        self._scratch: dict[str, np.ndarray] = {}  # integration's working arrays (used under the data lock)
        self._update_lock = threading.RLock()  # one update or extraction at a time
        self.alpha = AlphaScheduler(self.store, self.weighting_net, self._data_lock, alpha_voxels=config.alpha_voxels,
                                    alpha_dtype=config.alpha_dtype, alpha_tolerance=config.alpha_tolerance,
                                    tsdf_input=config.weighting_tsdf_input, band_m=config.band_m, device=self.device)
        self._alpha_executor: ThreadPoolExecutor | None = None  # alpha_threads > 1: evaluates batches of updates
        # integration past the hard bound waits on this until an eviction (or the running update) ends
        self._eviction_done = threading.Condition()  # reentrant: an evicting waiter notifies
        self.counters = {"alpha_voxels": 0, "alpha_blocks": 0, "mesh_blocks": 0, "sparse_dropped_samples": 0,
                         "sparse_dropped_blocks": 0}
        self.timings_s: dict[str, float] = {}  # stage -> seconds of its last run
        self.total_s: dict[str, float] = {}  # stage -> seconds summed over all runs
        self.frames_integrated = {name: 0 for name in config.sensors}
        self._reset_state()

    # -- verbs ------------------------------------------------------------------------------------
    @torch.inference_mode()
    def integrate(self, sensor: str, depth_m: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray,
                  rgb: np.ndarray | None = None) -> int:
        """Integrate one depth frame (H x W float32 metres) of `sensor`; returns the voxels updated.

        Invalid pixels (0, NaN, inf, negative, out of range, image border) are skipped. Raises
        InputError (grids untouched) for wrong shapes, dtypes, intrinsics or poses.
        """
        return self.integrate_prepared(self.prepare(sensor, depth_m, K, T_world_camera, rgb))

    def prepare(self, sensor: str, depth_m: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray,
                rgb: np.ndarray | None = None) -> PreparedFrame:
        """First half of `integrate`: check the frame (InputError as there) and start its feature
        net in the worker thread. A caller holding the next frame prepares it before integrating
        the current one, so that the feature net runs while the current frame's kernels do."""
        t0 = time.perf_counter()
        s = self._sensor_index(sensor)
        check_frame(depth_m, K, T_world_camera, rgb)
        cfg = self.config
        depth = np.nan_to_num(np.asarray(depth_m, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        valid = valid_depth_mask(torch.from_numpy(depth), cfg.border_px, cfg.depth_min_m[s], cfg.depth_max_m[s])
        if not bool(valid.any()):
            return PreparedFrame(s, depth, K, T_world_camera, None, time.perf_counter() - t0)
        check_key_range(depth[valid.numpy()].max(), K, T_world_camera, depth.shape, cfg.band_m)
        features = _FEATURE_WORKER.submit(self._pixel_features, s, depth, rgb)
        return PreparedFrame(s, depth, K, T_world_camera, features, time.perf_counter() - t0)

    @torch.inference_mode()
    def integrate_prepared(self, frame: PreparedFrame) -> int:
        """Second half of `integrate`: the frame's kernels, under the data lock."""
        if frame.features is None:  # no valid pixel
            return 0
        s, cfg = frame.sensor_index, self.config
        t0 = time.perf_counter()
        with self._data_lock:
            update = integrate_frame(self.grid, frame.depth_m, frame.features.result, frame.K, frame.T_world_camera,
                                     (cfg.depth_min_m[s], cfg.depth_max_m[s]), cfg.integrator,
                                     (f"tsdf{s}", f"weight{s}", f"feat{s}"), scratch=self._scratch)
            self.store.grow_flags()
            self.store.alpha_pending[update.touched_slots] = True
            self.store.mesh_pending[update.touched_slots] = True  # the TSDF changed here, whatever alpha does
            self.frames_integrated[cfg.sensors[s]] += 1
            self.counters["sparse_dropped_samples"] += update.dropped_samples
            self.counters["sparse_dropped_blocks"] += update.dropped_blocks
            self._camera_m = np.asarray(frame.T_world_camera, np.float64)[:3, 3].copy()
        self._timed(integrate=frame.checks_s + time.perf_counter() - t0 - update.waited_s)
        if self._eviction_due():
            self._wait_for_eviction()
        return update.voxels_updated

    @torch.inference_mode()
    def update(self, alpha_budget_s: float | None = None) -> MeshUpdate:
        """Alpha, fusion and meshing over the blocks changed since the last update.

        alpha_budget_s: at most about this long re-evaluating alpha; the blocks left over keep their
        previous alpha until a later update, most recently reached first (where it was never
        evaluated, the mesh shows what both sensors saw, averaged: see fusion). None: all of them
        (exact, deterministic). The live node passes 0 and calls `refresh_alpha` after publishing: new
        geometry is shown sooner, and its alpha comes with the next update."""
        with self._updating():
            t0 = time.perf_counter()
            self._evict()
            if alpha_budget_s != 0:
                self._refresh_alpha(alpha_budget_s)
            t1 = time.perf_counter()
            with self._data_lock:
                slots = self._take_mesh_pending()
                coords = self.grid.coords[slots].numpy().copy()
            self.counters["mesh_blocks"] += len(slots)
            self.counters["mesh_blocks_last"] = len(slots)
            result = MeshUpdate(cleared=self._cleared)
            self._cleared = False
            live = self._block_meshes(slots, coords)
            has_faces = {tuple(k) for k in live.keys.tolist()}
            self.archive.replace(has_faces)
            # the evicted blocks' final meshes: subscribers keep showing them (unless live again)
            archived = BlockMeshes.concatenate(self._newly_archived)
            self._newly_archived = []
            not_live = [key not in has_faces for key in map(tuple, archived.keys.tolist())]
            archived = archived.select(np.flatnonzero(not_live))
            result.meshes = BlockMeshes.concatenate([live, archived])
            for key in map(tuple, coords.tolist()):
                if key not in has_faces and key in self._meshed:
                    self._meshed.discard(key)
                    if key not in self.archive:
                        result.removed.append(key)
            self._meshed.update(has_faces)
            self.counters["meshed_blocks"] = len(self._meshed)
            self._timed(alpha=t1 - t0, mesh=time.perf_counter() - t1)
            return result

    @torch.inference_mode()
    def refresh_alpha(self, budget_s: float | None = None, *, until_frame: bool = False) -> None:
        """Re-evaluate alpha where the inputs drifted, at most about budget_s seconds (None: all of
        it), and with `until_frame` only until a frame is integrated, on `alpha_threads` threads (an
        idle catch-up that yields to the sensors when they resume); the next update re-meshes the
        blocks whose alpha changed."""
        with self._updating():
            start = time.perf_counter()
            self._refresh_alpha(budget_s, until_frame=until_frame)
            self._timed(alpha=time.perf_counter() - start)

    @torch.inference_mode()
    def block_meshes(self) -> BlockMeshes:
        """The fused (filtered) mesh of every block, as `update` sends it, with alpha as it is now
        (nothing re-evaluated), and the archived meshes of evicted blocks: a snapshot for a
        subscriber that joins late."""
        with self._updating():
            with self._data_lock:
                slots = np.arange(self.grid.n_blocks)
                coords = self.grid.coords[: self.grid.n_blocks].numpy().copy()
            live = self._block_meshes(slots, coords)
            archived = self.archive.meshes(exclude={tuple(k) for k in live.keys.tolist()})
        return BlockMeshes.concatenate([live, archived])

    @torch.inference_mode()
    def extract_mesh(self, which: str = FUSED, filtered: bool = True) -> Mesh:
        """The whole mesh of `which`: "fused", a sensor name, or "tsdf_fusion" (the baseline). The
        fused mesh includes the archived meshes of blocks the map bound evicted (`archive`); the
        others cover the blocks in memory."""
        self._check_which(which)
        with self._updating():
            if which == FUSED:
                self._refresh_alpha()
                release_free_memory()  # the net's temporaries: the mesh's peak comes on top otherwise
            live_with_faces = []
            with self._data_lock:  # one consistent state of the whole map
                slots = np.arange(self.grid.n_blocks)
                coords = self.grid.coords[: self.grid.n_blocks].numpy().copy()
                # each batch goes into the weld's compact arrays at once (extraction's memory peak)
                welder = StreamingWeld(self.config.voxel_size_m, coords.min(axis=0, initial=0),
                                       coords.max(axis=0, initial=0))
                for start in range(0, len(slots), self.config.mesh_batch_blocks):
                    part = self._mesh_batch(slots[start:start + self.config.mesh_batch_blocks], which, filtered)
                    welder.add(part.vertices_vox, part.faces, part.vertex_values if which == FUSED else None)
                    live_with_faces.append(np.diff(part.face_offsets) > 0)
                    del part
            if which == FUSED and filtered and len(self.archive):
                live = np.concatenate(live_with_faces or [np.zeros(0, bool)])
                archived = self.archive.mesh(exclude={tuple(k) for k in coords[live].tolist()})
                if archived.n_faces:  # welded with the live mesh: colours instead of alpha
                    assert archived.colors is not None
                    welder.add_colored_m(archived.vertices, archived.faces, archived.colors)
        release_free_memory()  # the batches' buffers
        return welder.mesh()

    @torch.inference_mode()
    def voxel_values(self, which: str = FUSED, filtered: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Centres (N x 3, metres) and TSDF values (N) of the observed voxels of `which`."""
        self._check_which(which)
        with self._updating():
            if which == FUSED:
                self._refresh_alpha()
            with self._data_lock:
                slots = torch.arange(self.grid.n_blocks)
                tsdf, observed = self._values(self._whole_blocks(slots, self._channels(which)), which, filtered)
                centres = self.grid.voxel_centres(slots, self.config.voxel_size_m)
                return centres[observed].numpy(), tsdf[observed].numpy()

    @torch.inference_mode()
    def weight_cloud(self, max_abs_tsdf_m: float | None = None, refresh_alpha: bool = True) -> WeightCloud:
        """Voxels observed by any sensor whose alpha is known: position, alpha and each sensor's
        weight counter. With max_abs_tsdf_m, only voxels whose unfiltered fused |TSDF| is at most
        that. Without refresh_alpha, alpha is as the last updates left it (voxels the net has not
        judged yet are left out)."""
        with self._updating():
            if refresh_alpha:
                self._refresh_alpha()
            with self._data_lock:
                slots = torch.arange(self.grid.n_blocks)
                blocks = self._whole_blocks(slots, self._channels(FUSED))
                centres = self.grid.voxel_centres(slots, self.config.voxel_size_m)
        n = len(self.config.sensors)
        weights = torch.stack([blocks[f"weight{i}"] for i in range(n)], dim=-1)
        keep = (weights > 0).any(dim=-1) & torch.isfinite(blocks["alpha"])
        if max_abs_tsdf_m is not None:
            tsdf, _ = self._values(blocks, FUSED, filtered=False)
            keep &= tsdf.abs() <= max_abs_tsdf_m
        return WeightCloud(centres[keep].numpy(), blocks["alpha"][keep].numpy().astype(np.float32),
                           weights[keep].numpy().astype(np.float32))

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) every kernel on a small synthetic frame per sensor,
        then forget it: the first real frame and update then run at full speed."""
        size = 4 * self.config.border_px + 32
        K = np.array([[size / 2, 0, (size - 1) / 2], [0, size / 2, (size - 1) / 2], [0, 0, 1]], np.float64)
        depth = np.full((size, size), 0.5 * (self.config.depth_min_m[0] + self.config.depth_max_m[0]), np.float32)
        rgb = np.full((size, size, 3), 128, np.uint8)
        for sensor in self.config.sensors:
            self.integrate(sensor, depth, K, np.eye(4), rgb)
        self.update()
        self.extract_mesh(self.config.sensors[0])
        self.reset()
        self._cleared = False

    def networks_changed(self) -> None:
        """The networks' weights were changed in place: the next update re-evaluates alpha everywhere."""
        with self._data_lock:
            self.store.stale[: self.grid.n_blocks] = 2

    def reset(self) -> None:
        """Forget everything fused; the next update reports `cleared`."""
        with self._updating(), self._data_lock:
            self.store.clear()
            self.archive.clear()
            self.frames_integrated = {name: 0 for name in self.config.sensors}
            self._reset_state()
            self._cleared = True

    def save(self, path: str | Path) -> None:
        """The whole engine state (config, grids, networks) in one file, written atomically."""
        with self._updating():
            self._refresh_alpha()
            with self._data_lock:
                state = {
                    "format": "senfunet-engine-1",
                    "config": asdict(self.config),
                    "grid": self.grid.state_dict(),
                    "feature_nets": [net.state_dict() for net in self.feature_nets],
                    "weighting_net": self.weighting_net.state_dict(),
                    "frames_integrated": dict(self.frames_integrated),
                    "archive": {k: torch.from_numpy(np.ascontiguousarray(v))
                                for k, v in self.archive.state_dict().items()},
                }
                if self.grid.spill is not None:
                    state["spill"] = {k: torch.from_numpy(v) for k, v in self.grid.spill.state_dict().items()}
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        torch.save(state, tmp)
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path, device: str | None = None) -> SenFuNet:
        """An engine with the state `save` wrote; the next update re-sends the whole mesh."""
        path = Path(path)
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
            if state.get("format") != "senfunet-engine-1":
                raise InputError(f"{path} is not a SenFuNet engine state")
        except InputError:
            raise
        except Exception as err:
            raise InputError(f"cannot read engine state {path}: {err}") from err
        known = {f.name for f in fields(EngineConfig)}
        config_values: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v
                                         for k, v in state["config"].items() if k in known}
        config = EngineConfig(**config_values)
        if device is not None:
            config = replace(config, device=device)
        engine = cls(config, weights=None)
        for net, net_state in zip(engine.feature_nets, state["feature_nets"]):
            net.load_state_dict(net_state)
        engine.weighting_net.load_state_dict(state["weighting_net"])
        engine.weights_source = f"{path} (saved state)"
        engine.grid.load_state_dict(state["grid"])
        if "spill" in state and len(state["spill"]["keys"]):
            if engine.grid.spill is None:
                engine.grid.spill = BlockSpill()
            engine.grid.spill.load_state_dict({k: v.numpy() for k, v in state["spill"].items()})
        engine.frames_integrated.update(state["frames_integrated"])
        if "archive" in state:
            engine.archive.load_state_dict({k: v.numpy() for k, v in state["archive"].items()})
            engine._newly_archived = [engine.archive.meshes()]  # re-sent with the whole mesh
        engine.store.grow_flags()
        engine.store.evaluated[: engine.grid.n_blocks] = True  # alpha is part of the saved state
        engine.store.mesh_pending[: engine.grid.n_blocks] = True
        return engine

    def stats(self) -> dict:
        """Map size and memory, and how much of the meshed surface has its alpha: evaluated at least
        once (else its mesh averages the sensors, see fusion), and up to date (not stale)."""
        n = len(self.config.sensors)
        with self._updating():
            with self._data_lock:  # only the flags: integration waits for this lock
                nbytes = self.grid.nbytes()
                meshed = self.grid.lookup(torch.tensor(sorted(self._meshed), dtype=torch.int64).reshape(-1, 3)).numpy()
                meshed = meshed[meshed >= 0]
                evaluated = self.store.evaluated[meshed]
                current = evaluated & (self.store.stale[meshed] == 0)
                spill = self.grid.spill
                spilled = (len(spill), spill.nbytes, spill.restored) if spill is not None else (0, 0, 0)
            # counted without the data lock, as an update reads the grid: a frame integrated meanwhile
            # may or may not be in the count
            observed = self.store.observed_voxels([f"weight{i}" for i in range(n)])
        return {"blocks": self.grid.n_blocks, "observed_voxels": observed, "grid_bytes": nbytes,
                "bytes_per_observed_voxel": nbytes / max(observed, 1),
                "frames_integrated": dict(self.frames_integrated),
                "max_blocks": self.max_blocks, "evicted_blocks": self.counters.get("evicted_blocks", 0),
                "sparse_dropped_samples": self.counters["sparse_dropped_samples"],
                "sparse_dropped_blocks": self.counters["sparse_dropped_blocks"],
                "occupancy": observed / max(self.grid.n_blocks * 512, 1),
                "archived_blocks": len(self.archive), "archived_faces": self.archive.n_faces,
                "spilled_blocks": spilled[0], "spill_bytes": spilled[1], "restored_blocks": spilled[2],
                "meshed_blocks": len(meshed), "meshed_blocks_alpha_evaluated": int(evaluated.sum()),
                "meshed_blocks_alpha_current": int(current.sum())}

    # -- internals -------------------------------------------------------------------------------
    def _sensor_index(self, sensor: str) -> int:
        try:
            return self.config.sensors.index(sensor)
        except ValueError:
            raise InputError(f"unknown sensor '{sensor}'; configured sensors: {list(self.config.sensors)}") from None

    def _check_which(self, which: str) -> None:
        if which not in (FUSED, TSDF_FUSION, *self.config.sensors):
            raise InputError(f"unknown mesh '{which}'; choose {FUSED}, {TSDF_FUSION} "
                             f"or one of {list(self.config.sensors)}")
        if which == TSDF_FUSION and not self.config.tsdf_fusion:
            raise InputError("this engine keeps no TSDF Fusion baseline; create it with EngineConfig(tsdf_fusion=True)")

    def _reset_state(self) -> None:
        """The engine's own state beside the store (call with both locks held, or from __init__)."""
        self.store.clear_flags()
        self._camera_m = np.zeros(3)  # the last integrated frame's camera centre (the map bound keeps what is near)
        self._newly_archived = []
        self._meshed: set[tuple[int, int, int]] = set()
        self._cleared = False

    def _pixel_features(self, s: int, depth_m: np.ndarray, rgb: np.ndarray | None) -> np.ndarray:
        """5 x H x W features of one frame (in the feature worker thread)."""
        start = time.perf_counter()
        net = self.feature_nets[s]
        depth = torch.from_numpy(depth_m).to(self.device)
        rgb01 = None
        if net.uses_rgb:
            if rgb is None:
                rgb01 = torch.zeros((1, 3, *depth.shape), device=self.device)
            else:
                rgb01 = torch.from_numpy(rgb).to(self.device).permute(2, 0, 1).unsqueeze(0).float() / 255.0
        with torch.inference_mode():
            features = net(depth.view(1, 1, *depth.shape), rgb01)[0].cpu().numpy()
        self._timed(feature_net=time.perf_counter() - start)
        return features

    def _timed(self, **stages: float) -> None:
        self.timings_s.update(stages)
        for name, seconds in stages.items():
            self.total_s[name] = self.total_s.get(name, 0.0) + seconds

    def _refresh_alpha(self, budget_s: float | None = None, *, until_frame: bool = False) -> None:
        """Re-evaluate alpha on the stale blocks in the scheduler's order (`AlphaScheduler.order`),
        batch by batch; each batch first drops the blocks that hold no voxel alpha matters for
        (checked here, not when scheduling, so that a budget also bounds the checking). With a
        budget (seconds), stop after the batch that exhausts it, and with `until_frame` after the
        batch during which a frame was integrated: the rest stays stale for later. Without a
        budget or with `until_frame` (no frame is coming), `alpha_threads` batches are evaluated at
        once (each single-threaded, so alpha does not depend on how many). Between batches, where
        no evaluated batch waits to be written, it evicts when integration outgrew the bound."""
        cfg = self.config
        self.alpha.schedule()
        order = self.alpha.order()
        start = time.perf_counter()
        done = voxels = 0
        # batches evaluated at once: one while frames come (integration needs the other core)
        ahead = cfg.alpha_threads if budget_s is None or until_frame else 1
        # Results are written whenever the data lock is free, not waited for batch by batch: time
        # spent waiting for integration's kernels would come out of the net's budget.
        results: list[AlphaBatch] = []
        evaluating: collections.deque[Future[AlphaBatch]] = collections.deque()
        frames_at_start = sum(self.frames_integrated.values())
        left = order[:0]
        while len(order) or evaluating:
            if len(order) and ((budget_s is not None and time.perf_counter() - start > budget_s)
                               or (until_frame and sum(self.frames_integrated.values()) != frames_at_start)):
                order, left = order[:0], order  # evaluate no more; the batches under way are written
            if self._eviction_due():
                results += [future.result() for future in evaluating]  # read before slots move
                evaluating.clear()
                self.alpha.write(results, wait=True)
                eviction = self._evict()
                if eviction is not None:
                    order, _ = eviction.follow(order)
            while len(order) and len(evaluating) < ahead:
                batch, order = order[:cfg.alpha_batch_blocks], order[cfg.alpha_batch_blocks:]
                evaluating.append(self._alpha_pool().submit(self.alpha.evaluate, batch) if ahead > 1
                                  else _done(self.alpha.evaluate(batch)))
            if not evaluating:
                continue
            results.append(evaluating.popleft().result())
            done += int(results[-1].holds.sum())
            voxels += len(results[-1].voxels)
            self.alpha.write(results, wait=False)
        self.alpha.write(results, wait=True)
        self.counters["alpha_blocks"] += done
        self.counters["alpha_voxels"] += voxels
        self.counters["alpha_flops"] = self.alpha.flops
        self.counters["alpha_backlog_blocks"] = len(left)

    def _alpha_pool(self) -> ThreadPoolExecutor:
        """The threads that evaluate weighting-net batches side by side (created on first use)."""
        if self._alpha_executor is None:
            self._alpha_executor = ThreadPoolExecutor(self.config.alpha_threads, thread_name_prefix="senfunet-alpha")
        return self._alpha_executor

    def _wait_for_eviction(self) -> None:
        """Integration outgrew the hard bound (updates come too rarely to keep the bound): evict now
        or, while an update runs, wait until it has evicted at its next safe point, between two
        batches (not for the whole update, which can take a second). Whoever ends an eviction or an
        update notifies `_eviction_done`; the waiter holds its lock from the failed try to the wait,
        so no notification falls in between."""
        with self._eviction_done:
            while self._eviction_due():
                if self._update_lock.acquire(blocking=False):
                    try:
                        self._evict()
                    finally:
                        self._update_lock.release()
                else:
                    self._eviction_done.wait()

    def _notify_eviction_waiters(self) -> None:
        with self._eviction_done:
            self._eviction_done.notify_all()

    @contextlib.contextmanager
    def _updating(self) -> Iterator[None]:
        """Hold the update lock (one update, extraction or save at a time); on leaving, wake an
        integration waiting for an eviction (it may now evict itself)."""
        with self._update_lock:
            yield
        self._notify_eviction_waiters()

    def _eviction_due(self) -> bool:
        """Integration outgrew the hard bound and waits: an update evicts at its next safe point
        (between two batches, where it holds no slot)."""
        return self.max_blocks > 0 and self.grid.n_blocks > _HARD_BOUND * self.max_blocks

    def _evict(self) -> Eviction | None:
        """With a map bound, evict the blocks farthest from the last camera position once the map
        holds more (down to 90%, so that it does not happen every update). The evicted blocks'
        final fused meshes, with alpha evaluated where it was stale, go to the archive (the next
        update sends them; they stay in snapshots and saved meshes), and their voxels to the spill
        (`spill`), which gives them back when a frame reaches them again. Their neighbours'
        marching-cubes cells that reached into the evicted blocks are re-meshed without them (so a
        snapshot equals what the updates sent); the triangles of those cells go to the archive with
        the evicted blocks (`_seam_meshes`), so no seam opens along the eviction front. Call with
        the update lock held; the data lock is held only to pick the victims, to redo what a frame
        changed meanwhile, and to remove them, not while they are first judged and meshed."""
        if self.max_blocks <= 0 or self.grid.n_blocks <= self.max_blocks:
            return None
        t0 = time.perf_counter()
        store = self.store
        with self._data_lock:
            victims = store.farthest(self._camera_m, keep=int(0.9 * self.max_blocks),
                                     voxel_size_m=self.config.voxel_size_m)
            victim_coords = self.grid.coords[victims].numpy()  # copies (fancy index)
            around_victims = store.neighbours(victims)
            read = around_victims[:, _MESH_READ_CODES]  # the blocks the victims' cells read
            readers = around_victims[:, _MESH_READER_CODES]  # the blocks whose cells read victims
            readers = np.setdiff1d(readers[readers >= 0], victims)
            scope = store.neighbours(np.union1d(victims, readers))[:, _MESH_READ_CODES]
            around = np.unique(scope[scope >= 0])  # every block whose alpha the final meshes read
        # Judged and meshed without the data lock, so that integration goes on meanwhile (slots move
        # only in evictions, which need the update lock, held here) ...
        self.alpha.schedule()
        unjudged = around[(store.stale[around] > 0) | ~store.evaluated[around]]
        archived = self._final_meshes(victims, victim_coords, unjudged)
        with self._data_lock:
            # ... and again, under it, where a frame changed them in the meantime
            touched = around[store.alpha_pending[around]]
            self.alpha.schedule()
            changed = np.union1d(touched, around[store.stale[around] > 0])
            if len(changed):
                again = np.flatnonzero(np.isin(read, changed).any(axis=1))
                redone = {tuple(key) for key in victim_coords[again].tolist()}
                older = [key not in redone for key in map(tuple, archived.keys.tolist())]
                archived = BlockMeshes.concatenate([archived.select(np.flatnonzero(older)),
                                                    self._final_meshes(victims[again], victim_coords[again],
                                                                       around[store.stale[around] > 0])])
            archived = _with_seams(archived, self._seam_meshes(readers, victim_coords))
            self.archive.add(archived)
            self._newly_archived.append(archived)
            eviction = store.remove(victims)
        self.counters["evicted_blocks"] = self.counters.get("evicted_blocks", 0) + len(victim_coords)
        self.counters["evictions"] = self.counters.get("evictions", 0) + 1
        self._meshed.difference_update(map(tuple, victim_coords.tolist()))
        spill = self.grid.spill
        log.info("map bound: evicted %d blocks farthest from the camera (max_blocks %d; %d evicted so far, their "
                 "final meshes kept: %d archived blocks; their voxels on disk until seen again: %d blocks, %.0f MB) "
                 "in %.2f s", len(victim_coords), self.max_blocks, self.counters["evicted_blocks"], len(self.archive),
                 len(spill) if spill is not None else 0, (spill.nbytes if spill is not None else 0) / 1e6,
                 time.perf_counter() - t0)
        self._notify_eviction_waiters()
        return eviction

    def _final_meshes(self, slots: np.ndarray, coords: np.ndarray, unjudged: np.ndarray) -> BlockMeshes:
        """Fused, filtered meshes of blocks about to be evicted, alpha first evaluated on the blocks
        `unjudged` (those the meshes read whose alpha is stale or was never evaluated)."""
        cfg = self.config
        batches = [self.alpha.evaluate(unjudged[start:start + cfg.alpha_batch_blocks])
                   for start in range(0, len(unjudged), cfg.alpha_batch_blocks)]
        self.alpha.write(batches, wait=True)
        return BlockMeshes.concatenate([
            self._to_block_meshes(self._mesh_batch(slots[i:i + cfg.mesh_batch_blocks], FUSED, filtered=True),
                                  coords[i:i + cfg.mesh_batch_blocks])
            for i in range(0, len(slots), cfg.mesh_batch_blocks)])

    def _seam_meshes(self, readers: np.ndarray, victim_coords: np.ndarray) -> dict[tuple[int, int, int], Mesh]:
        """The triangles of the cells of blocks staying (`readers`) that read blocks about to be
        evicted, by the evicted block they go with (the least key among those a cell reads): once
        the readers are re-meshed without the evicted voxels, the archive shows these instead (data
        lock held, before the removal)."""
        size, voxel_size_m = self.config.mesh_batch_blocks, self.config.voxel_size_m
        victim_keys = np.sort(block_keys(torch.from_numpy(victim_coords)).numpy())
        seams: dict[tuple[int, int, int], list[Mesh]] = {}
        for start in range(0, len(readers), size):
            tris = self._mesh_batch(readers[start:start + size], FUSED, filtered=True)
            if len(tris.faces) == 0:
                continue
            # a triangle's cell: the floor of its centroid (strictly inside the cell it came from)
            cell = np.floor(tris.vertices_vox[tris.faces].mean(axis=1)).astype(np.int64)
            owner = np.full(len(cell), np.iinfo(np.int64).max)
            for corner in np.ndindex(2, 2, 2):  # the blocks of the cell's 8 corners
                key = block_keys(torch.from_numpy(np.floor_divide(cell + np.array(corner), 8))).numpy()
                evicted = np.isin(key, victim_keys)
                owner[evicted] = np.minimum(owner[evicted], key[evicted])
            seam = np.flatnonzero(owner < np.iinfo(np.int64).max)
            owners = np.unique(owner[seam])
            for key, block in zip(owners.tolist(), keys_to_coords(torch.from_numpy(owners)).tolist()):
                faces = tris.faces[seam[owner[seam] == key]]
                used, local = np.unique(faces, return_inverse=True)
                values = tris.vertex_values[used] if tris.vertex_values is not None else None
                mesh = to_mesh(tris.vertices_vox[used], local.reshape(-1, 3), voxel_size_m, values)
                seams.setdefault(tuple(block), []).append(mesh)
        return {block: _joined(parts) for block, parts in seams.items()}

    def _block_meshes(self, slots: np.ndarray, coords: np.ndarray) -> BlockMeshes:
        """Fused, filtered meshes of the given blocks (coords: their block keys); blocks without
        triangles, or evicted meanwhile, are left out."""
        parts, evicted = [], []
        size = self.config.mesh_batch_blocks
        while len(slots):
            if self._eviction_due():
                eviction = self._evict()
                assert eviction is not None  # _eviction_due()
                slots, kept = eviction.follow(slots)
                coords = coords[kept]
                evicted.append(eviction.dropped_keys)
            (batch, slots), (batch_coords, coords) = (slots[:size], slots[size:]), (coords[:size], coords[size:])
            parts.append(self._to_block_meshes(self._mesh_batch(batch, FUSED, filtered=True), batch_coords))
        meshes = BlockMeshes.concatenate(parts)
        if evicted:  # blocks meshed in an earlier batch may be gone: they must not be shown
            gone = np.isin(block_keys(torch.from_numpy(meshes.keys)).numpy(), np.concatenate(evicted))
            meshes = meshes.select(np.flatnonzero(~gone))
        return meshes

    def _to_block_meshes(self, tris: BlockTriangles, coords: np.ndarray) -> BlockMeshes:
        """One marching-cubes batch as per-block meshes in metres (blocks without triangles left out)."""
        v_start, f_start = tris.vertex_offsets, tris.face_offsets
        # the whole batch at once; blocks without triangles have empty ranges
        whole = to_mesh(tris.vertices_vox, tris.faces - np.repeat(v_start[:-1], np.diff(f_start))[:, None],
                        self.config.voxel_size_m, tris.vertex_values)
        keep = np.flatnonzero(np.diff(f_start) > 0)
        assert whole.colors is not None  # alpha colours: the fused mesh interpolates alpha
        return BlockMeshes(coords[keep], whole.vertices, whole.colors, whole.faces,
                           _compact_offsets(v_start, keep), _compact_offsets(f_start, keep))

    def _take_mesh_pending(self) -> np.ndarray:
        """Blocks to re-mesh: those whose cells read a changed block (call with the data lock held)."""
        pending = np.flatnonzero(self.store.mesh_pending[: self.grid.n_blocks])
        if len(pending) == 0:
            return pending
        self.store.mesh_pending[pending] = False
        readers = self.store.neighbours(pending)[:, _MESH_READER_CODES]
        return np.unique(readers[readers >= 0])

    def _channels(self, which: str) -> list[str]:
        """The channels `_values` reads for `which`."""
        if which == FUSED:
            return ["tsdf0", "weight0", "tsdf1", "weight1", "alpha"]
        if which == TSDF_FUSION:
            return ["tsdf_base", "weight_base"]
        s = self._sensor_index(which)
        return [f"tsdf{s}", f"weight{s}"]

    def _whole_blocks(self, slots: torch.Tensor, names: list[str]) -> dict[str, torch.Tensor]:
        """The channels of whole blocks, as float32 (the pools hold float16)."""
        return {name: self.grid.pools[name][slots].float() for name in names}

    def _values(self, blocks: dict[str, torch.Tensor], which: str, filtered: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """TSDF and observed mask of `which` from per-voxel channel tensors."""
        if which == FUSED:
            fused = fuse(blocks["tsdf0"], blocks["weight0"], blocks["tsdf1"], blocks["weight1"], blocks["alpha"],
                         apply_filter=filtered)
            return fused.tsdf_m, fused.observed
        if which == TSDF_FUSION:
            return blocks["tsdf_base"], blocks["weight_base"] > 0
        s = self._sensor_index(which)
        return blocks[f"tsdf{s}"], blocks[f"weight{s}"] > 0

    def _mesh_batch(self, slots: np.ndarray, which: str, filtered: bool) -> BlockTriangles:
        """Marching cubes over the given blocks of `which` (reads the grid without the data lock)."""
        grid = self.grid
        t0 = time.perf_counter()
        neighbours = self.store.neighbours(slots)
        if which == FUSED:
            mode, names = WINDOW_FUSED, ("tsdf0", "weight0", "tsdf1", "weight1", "alpha")
        else:
            mode = WINDOW_BASE if which == TSDF_FUSION else WINDOW_SENSOR
            tsdf, weight = self._channels(which)
            names = (tsdf, weight, tsdf, weight, "alpha")
        tsdf, observed, alpha = mesh_windows(neighbours, mode, filtered, *self.store.views(*names))
        origins = grid.coords[slots].numpy() * 8
        t1 = time.perf_counter()
        triangles = marching_cubes_blocks(tsdf, observed, origins, alpha if which == FUSED else None)
        self._timed(fusion=t1 - t0, marching_cubes=time.perf_counter() - t1)
        return triangles
