"""The SenFuNet engine: the networks and a few verbs over the map.

    engine = SenFuNet(EngineConfig(), weights="default")
    engine.integrate("tof", depth_m, K, T_world_camera)        # at sensor rate
    update = engine.update()                                    # alpha, fusion, meshing of changed blocks
    mesh = engine.extract_mesh("fused")                         # or a sensor name, or "tsdf_fusion"

Rooms: the map's blocks and per-block flags live in `block_store.BlockStore`; which blocks the
weighting net must judge, and when, in `alpha_scheduler.AlphaScheduler` (judging a batch in
`alpha_evaluator.AlphaEvaluator`); marching cubes
over blocks in `block_mesher.BlockMesher`; the map bound (which blocks leave memory, their final
meshes in `mesh_archive.MeshArchive`, their voxels in `spill.BlockSpill` on disk) in
`map_bound.MapBound`. This module holds the verbs, the networks and the locks.

Incremental update: a frame marks the blocks it touched, and which blocks lie within 2 voxels of
its voxels whose weighting-net inputs changed (see `alpha`). `update` re-evaluates alpha there,
where alpha matters (EngineConfig.alpha_voxels; the result equals evaluating the net
over the whole grid there); then it re-meshes every block whose cells read a changed alpha or TSDF
(the changed blocks and their -x, -y, -z neighbours, since a block's cells reach one voxel into its
+x, +y, +z neighbours).

Threading model (the one place it is described):
- Threads: an integrating thread calls `prepare_frame`/`integrate`; an updating thread calls `update`,
  `refresh_alpha`, the extractions, `map_file.save_map`, `reset`; one feature-net worker thread (module-wide,
  "senfunet-features") runs the 2D nets; one voxel-update thread (module-wide, "senfunet-update") takes a
  share of a large frame's blocks (`integrator.update_voxels`) while the integrating thread holds the data
  lock, which it lets go only once that share is written; with `alpha_threads` > 1, that many alpha threads
  ("senfunet-alpha", per engine, owned by its `AlphaScheduler`) evaluate the weighting net's batches for an
  update that has no time budget (or an idle catch-up, `refresh_alpha(until_frame=True)`), and for an
  eviction that integration waits for (`MapBound.evict`: the integrating thread evicts, or the map is past
  the hard bound), while the updating (or evicting) thread waits for them in order and writes their
  results; they also mesh the batches of an `update(mesh_threads=...)` (no frame waiting) and, in an
  idle catch-up, count the voxels near a surface that order it (`AlphaScheduler.order`), reading the
  grid as the updating thread does. A reading thread (the live node's weights thread) may call
  `readout.weight_cloud`, which takes no update lock and holds the data lock a slice of blocks at a
  time, found by key (so an eviction or a frame between two slices goes on). Several threads may
  integrate, and several may update: the locks serialise them. The alpha threads start at the priority of the
  thread that first needs them and then run the constructor's `worker_setup` (the live node's
  lowers them to its mesh thread's). The engine's parts (`AlphaScheduler`,
  `BlockMesher`, `MapBound`) start no thread of their own besides those alpha threads, and take only
  the data lock they are given.
- The update lock (`update_lock.UpdateLock`) serialises updates, extractions, saves and evictions; it owns the
  alpha scheduler's order, the map bound (its archive) and the set of meshed blocks.
- The data lock guards the grid's contents and the per-block flags: integration holds it while its
  kernels run, an update while it takes the frames' changes, writes alpha or evicts. An update (or
  its alpha threads, which write nothing) reads input windows without it (and `stats` counts
  voxels without it): a block integrated meanwhile is marked again and re-read by the next update,
  and pools that grow meanwhile stay valid for whoever still holds the old ones, as does the hash
  table, which a growing grid replaces by a complete new one (`BlockGrid.hash_table`); the blocks
  a frame is still allocating (the allocation policy may drop or move them) count as absent there
  (`BlockStore.neighbours`). Evictions wait for the batches being evaluated.
- Lock order: update lock, then data lock. Integration never takes the update lock while holding
  the data lock; past the map's hard bound it releases the data lock and either evicts itself (the
  update lock free: tried without blocking) or waits until woken by an eviction's slice (an update's
  eviction removes its victims slice by slice and wakes the waiters after each, so a waiter goes on
  once the map is under the hard bound, not when the whole eviction ends) or a release of the update lock
  (`UpdateLock.wait_for_eviction`). Nobody waits for that while holding the data lock,
  so the waiter may evict under it. No thread polls.
"""
from __future__ import annotations

import logging
import tempfile
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from . import networks
from .alpha_scheduler import AlphaScheduler
from .block_mesher import FUSED, TSDF_FUSION, BlockMesher
from .block_store import BlockStore, Eviction
from .errors import InputError
from .files import memory_filesystem
from .grid import ALPHA_UNKNOWN, BlockGrid, block_keys, keys_to_coords, warm_up_lookups
from .integrator import REACH_ALL, IntegratorConfig, check_frame, check_key_range, clean_depth, integrate_frame
from .map_bound import MapBound, memory_bound_blocks
from .machine import memory_budget
from .memory import release_free_memory
from .mesh_archive import MeshArchive, as_mesh, union
from .mesher import BlockMeshes, Mesh, StreamingWeld
from .spill import BlockSpill
from .stage_times import StageTimes
from .update_lock import UpdateLock
from .weighting_int8 import Int8Calibration, Int8WeightingNet, input_ranges, int8_available, load_calibration

_MIN_MESH_BLOCKS = 64  # blocks an update with a meshing budget re-meshes at least (and measures its time per block on)
_FIRST_MESH_BLOCKS = 256  # ... at most, before any time per block was measured
_MIN_THREAD_BLOCKS = 256  # blocks per meshing thread, at least: fewer cost more to hand over than they save
log = logging.getLogger("senfunet.engine")

# One thread runs the feature nets (of every engine in the process), so that a frame's feature net
# overlaps the kernels of the frame before it (see `prepare`) and the kernel that locates its samples.
_FEATURE_WORKER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="senfunet-features")


def _pixel_features(net: torch.nn.Module, times: StageTimes, depth_m: np.ndarray, rgb: np.ndarray | None
                    ) -> np.ndarray:
    """(H*W) x 5 features of one frame's pixels (in the feature worker thread)."""
    start = time.perf_counter()
    features = networks.pixel_feature_rows(net, depth_m, rgb)
    times.add(feature_net=time.perf_counter() - start)
    return features


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
    alpha_batch_blocks: int = 64  # blocks per weighting-net batch (memory vs. how long readers hold the grid and a
    #                               budget's granularity); at 64, a bfloat16 batch's first-layer output (64 x 10^3 x
    #                               32 x 2 bytes) stays under the node's 4 MB mmap threshold (node.limit_malloc):
    #                               reused from the heap, not mapped and faulted in anew for each batch. Batches of
    #                               128 ran int8 G faster per block (`bench/engine.py --alpha-batch-blocks`) but cost
    #                               the live node more CPU per frame while frames came (`bench/realtime.py`), CPU
    #                               that integration lacks
    mesh_batch_blocks: int = 2048  # blocks per marching-cubes call
    seed: int = 0  # initialisation of untrained networks
    torch_threads: int = 1  # torch intra-op threads the engine sets (0: leave torch's setting); 1 fits 2 shared cores
    alpha_threads: int = 1  # threads evaluating weighting-net batches side by side in updates without a time budget
    #                         (extraction, saving, catch-up); each batch stays on one thread, so alpha is the same
    alpha_voxels: str = "all"  # where alpha near a change is re-evaluated: "all" (equals the whole-grid
    #   evaluation on every voxel); "surface" (blocks holding corners of cells whose 8 corners are observed and whose
    #   sensor TSDFs straddle 0: all that the fused mesh, its filter and its colours read; alpha elsewhere may be
    #   stale); "surface_voxels" (those corners alone, voxel by voxel: less arithmetic, more gathering)
    alpha_order: str = "longest_waiting"  # which stale blocks a time budget serves first: "longest_waiting" (blocks
    #   with a mesh first, and among them those whose last change is oldest: blocks still in view wait until they
    #   settle, so each is judged about once) or
    #   "latest" (those the latest frames reached); see AlphaScheduler.order. Chosen with bench/alpha_order.py on a
    #   validation room: fewer meshed blocks wait more than 3 s for the net after their last change, and more are
    #   judged, for the same budget (docs/performance.md)
    alpha_dtype: str = "float32"  # weighting-net arithmetic: "float32", "bfloat16" (faster on CPUs with
    #                               bfloat16 instructions, alpha close to float32's; see test_equivalence.py) or
    #                               "int8" (faster elsewhere; weighting_int8, needs the weights' calibration:
    #                               float32 without it, said in the log)
    feature_dtype: str = "float32"  # feature-net arithmetic: "float32", or "bfloat16" (faster on CPUs with bfloat16
    #                                 instructions; features close to float32's, see test_equivalence.py)
    max_blocks: int = 0  # memory bound: past this many blocks, each update evicts the blocks farthest from the
    #   last camera position (down to 90%), and so does integration past 1.25x, keeping their final fused meshes
    #   (mesh_archive); 0 = no bound; -1 = from the machine's memory (`memory_bound_blocks`)
    tsdf_fusion: bool = True  # also integrate every frame into one plain TSDF grid: the "tsdf_fusion" baseline
    #                           (one more running average per sample and 4 bytes per voxel)
    min_new_block_samples: int = 16  # allocation policy: a frame allocates a block only where at least this many of
    #   its ray samples land; samples in blocks not allocated are dropped and counted (counters
    #   "sparse_dropped_samples", "sparse_dropped_blocks"); blocks already in the map take every sample. 0 = allocate
    #   every touched block. The default was chosen on the validation rooms (bench/allocation_policy.py): one
    #   isolated ray leaves fewer samples than that in a block (at most (n_samples - 1) / 2 + n_samples_behind + 1,
    #   9 at 1 cm voxels; with finer voxels, more samples along the band, but a voxel apart they cross a block along
    #   at most 8 * sqrt(3) ~ 14 voxels: test_integrator.py), so a new block needs two rays or more; larger
    #   thresholds started to lose far surfaces (mean F fell), smaller ones kept
    #   far more nearly empty blocks at no gain in F
    weighting_tsdf_input: bool = False  # the weighting net also reads the sensors' TSDFs (a departure from the
    #   paper, networks.WeightingNet); set from the weights file when it records it

    def sensor_index(self, sensor: str) -> int:
        try:
            return self.sensors.index(sensor)
        except ValueError:
            raise InputError(f"unknown sensor '{sensor}'; configured sensors: {list(self.sensors)}") from None

    def check_mesh_name(self, which: str) -> None:
        """InputError unless `which` names a mesh this engine keeps: fused, a sensor's or the baseline."""
        if which not in (FUSED, TSDF_FUSION, *self.sensors):
            raise InputError(f"unknown mesh '{which}'; choose {FUSED}, {TSDF_FUSION} or one of {list(self.sensors)}")
        if which == TSDF_FUSION and not self.tsdf_fusion:
            raise InputError("this engine keeps no TSDF Fusion baseline; create it with EngineConfig(tsdf_fusion=True)")

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
        if self.alpha_dtype not in ("float32", "bfloat16", "int8"):
            raise InputError(f"alpha_dtype must be 'float32', 'bfloat16' or 'int8', got '{self.alpha_dtype}'")
        if self.alpha_order not in ("latest", "longest_waiting"):
            raise InputError(f"alpha_order must be 'latest' or 'longest_waiting', got '{self.alpha_order}'")
        if self.feature_dtype not in ("float32", "bfloat16"):
            raise InputError(f"feature_dtype must be 'float32' or 'bfloat16', got '{self.feature_dtype}'")
        if self.alpha_voxels not in ("all", "surface", "surface_voxels"):
            raise InputError(f"alpha_voxels must be 'all', 'surface' or 'surface_voxels', got '{self.alpha_voxels}'")
        if self.max_blocks < -1:
            raise InputError(f"max_blocks must be >= 0 (0 = no bound) or -1 (from the machine's memory), "
                             f"got {self.max_blocks}")
        if self.min_new_block_samples < 0:
            raise InputError(f"min_new_block_samples must be >= 0 (0 = allocate every touched block), "
                             f"got {self.min_new_block_samples}")
        if self.torch_threads < 0 or self.alpha_threads < 1:
            raise InputError(f"torch_threads must be >= 0 and alpha_threads >= 1, got {self.torch_threads} "
                             f"and {self.alpha_threads}")


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
    """A checked frame whose feature net is running (`prepare_frame`)."""

    sensor_index: int
    depth_m: np.ndarray  # float32, NaN and inf set to 0
    K: np.ndarray
    T_world_camera: np.ndarray
    features: Future | None  # of the 5 x H x W pixel features; None when no pixel is valid
    checks_s: float  # time `prepare` took (counted as integration)

    @property
    def empty(self) -> bool:
        """No pixel is valid (within the sensor's depth range, inside the image border): integrating
        it changes nothing."""
        return self.features is None


class SenFuNet:
    """Learned two-sensor TSDF fusion on sparse voxel blocks, plus the plain TSDF Fusion baseline."""


    def __init__(self, config: EngineConfig = EngineConfig(), weights: str | Path | None = "default", *,
                 worker_setup: Callable[[], object] | None = None) -> None:
        """worker_setup: run by each of the engine's alpha threads as it starts (the live node lowers
        their priority to its mesh thread's, whichever thread first needs them)."""
        config.validate()
        self.config = config
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
        for net in self.feature_nets:
            net.compute_dtype = getattr(torch, config.feature_dtype)
        self.weighting_net.to(self.device).eval()
        channels: dict[str, tuple[int, ...]] = {"alpha": ()}
        if config.tsdf_fusion:
            channels.update({"tsdf_base": (), "weight_base": ()})
        for i in range(len(config.sensors)):
            channels.update({f"tsdf{i}": (), f"weight{i}": (), f"feat{i}": (networks.N_FEATURES,)})
        # TSDFs and weights in half precision: weight counters stay exact up to 2048 (w_max); TSDF
        # values within the band keep a relative precision of 2^-11, far below the sensors' noise
        # (kernels read them through grid.load_f32). The learned features lie in [-1, 1]: 6 bits
        # (steps of 1/31), the depth feature an 8-bit float, packed in one int8 pool (grid.FEATURE_SCALE,
        # grid.encode_depth, read through grid.load_feature / decode_features). Alpha, a weighting
        # in [0, 1], in 8 bits (grid.encode_alpha).
        dtypes = {name: torch.int8 if name.startswith("feat") else torch.float16 for name in channels}
        dtypes["alpha"] = torch.uint8
        # alpha unknown until evaluated: C12 averaged, the filter holds single-sensor voxels back (see fusion)
        self.store = BlockStore(BlockGrid(channels, dtypes=dtypes, fill={"alpha": ALPHA_UNKNOWN}))
        self.grid = self.store.grid
        self.max_blocks = config.max_blocks  # the map bound in force (resolved from memory for -1)
        if config.max_blocks == -1:
            budget = memory_budget()
            self.max_blocks = memory_bound_blocks(self.grid.bytes_per_block(), budget=budget)
            log.info("map bound: %d blocks (half of %s, %.1f GB, at %d bytes a block)", self.max_blocks,
                     f"the memory limit of this process's cgroup ({budget.limited_by})" if budget.limited_by else
                     "this machine's memory", budget.total_bytes / 1e9, self.grid.bytes_per_block())
        if self.max_blocks > 0:  # evicted blocks go to disk, and come back when the sensors reach them again
            self.grid.spill = BlockSpill()
            in_memory = memory_filesystem(tempfile.gettempdir())
            if in_memory:
                log.warning("map bound: the temporary folder %s, where evicted blocks' voxels and meshes go, is a %s "
                            "in memory: they still take RAM there (and count against a container's limit); set TMPDIR "
                            "to a folder on a disk", tempfile.gettempdir(), in_memory)
        # Writers of the grid (integration, alpha) hold the data lock; the update's readers do not:
        # a block integrated while it is read is marked again and re-read by the next update, and
        # pools that grow meanwhile stay valid for whoever still holds the old ones.
        self.data_lock = threading.RLock()
        self._scratch: dict[str, np.ndarray] = {}  # integration's working arrays (used under the data lock)
        self.update_lock = UpdateLock()  # one update, extraction, save or eviction at a time
        self.times = StageTimes()
        self.timings_s = self.times.last_s  # stage -> seconds of its last run
        self.total_s = self.times.total_s  # stage -> seconds summed over all runs
        self.alpha = AlphaScheduler(self.store, self.weighting_net, self.data_lock, alpha_voxels=config.alpha_voxels,
                                    alpha_dtype=config.alpha_dtype,
                                    tsdf_input=config.weighting_tsdf_input, band_m=config.band_m,
                                    voxel_size_m=config.voxel_size_m, device=self.device,
                                    batch_blocks=config.alpha_batch_blocks, threads=config.alpha_threads,
                                    alpha_order=config.alpha_order, worker_setup=worker_setup,
                                    int8_net=int8_weighting(self.weighting_net, config, weights=weights))
        self.mesher = BlockMesher(self.store, sensors=config.sensors, voxel_size_m=config.voxel_size_m,
                                  mesh_batch_blocks=config.mesh_batch_blocks, times=self.times)
        self.bound = MapBound(self.store, self.alpha, self.mesher, self.data_lock, max_blocks=self.max_blocks,
                              voxel_size_m=config.voxel_size_m, alpha_batch_blocks=config.alpha_batch_blocks)
        self.archive: MeshArchive = self.bound.archive  # final meshes of evicted blocks (owned by the update lock)
        self.counters = {"alpha_voxels": 0, "alpha_blocks": 0, "mesh_blocks": 0, "sparse_dropped_samples": 0,
                         "sparse_dropped_blocks": 0, "mesh_backlog_blocks": 0, "spill_failures": 0, "spill_failing": 0}
        self.frames_integrated = {name: 0 for name in config.sensors}
        self._meshed = np.zeros(0, np.int64)  # sorted block keys of the blocks with a live mesh
        self._evicted_shown: list[np.ndarray] = []  # keys of evicted blocks that had a live mesh (see _evict)
        self._cleared = False  # reset since the last mesh update
        self._mesh_round = 0  # updates so far: the order of the blocks a meshing budget leaves (BlockStore.mesh_due)
        self._mesh_s_per_block: dict[int, float] = {}  # meshing threads -> recent seconds per block meshed

    # -- verbs ------------------------------------------------------------------------------------
    @torch.inference_mode()
    def integrate(self, sensor: str, depth_m: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray,
                  rgb: np.ndarray | None = None) -> int:
        """Integrate one depth frame (H x W float32 metres) of `sensor`; returns the voxels updated.

        Invalid pixels (0, NaN, inf, negative, out of range, image border) are skipped. Raises
        InputError (grids untouched) for wrong shapes, dtypes, intrinsics or poses.
        """
        return self.integrate_prepared(prepare_frame(self, sensor, depth_m, K, T_world_camera, rgb))

    @torch.inference_mode()
    def integrate_prepared(self, frame: PreparedFrame) -> int:
        """Second half of `integrate`: the frame's kernels, under the data lock."""
        if frame.features is None:  # no valid pixel
            return 0
        s, cfg = frame.sensor_index, self.config
        t0 = time.perf_counter()
        with self.data_lock:
            try:
                update = integrate_frame(self.grid, frame.depth_m, frame.features.result, frame.K,
                                         frame.T_world_camera, (cfg.depth_min_m[s], cfg.depth_max_m[s]),
                                         cfg.integrator, (f"tsdf{s}", f"weight{s}", f"feat{s}"), scratch=self._scratch)
            finally:  # the grid may have grown before a failure: the flags keep its length for the updates
                self.store.grow_flags()
            self.store.alpha_pending[update.touched_slots] = True
            self.store.reach_changed[update.touched_slots] |= update.reach[:, 0]
            self.store.reach_renewed[update.touched_slots] |= update.reach[:, 1]
            # blocks back from the spill: alpha around them was judged without them
            self.store.reach_renewed[self.grid.take_restored_slots()] = REACH_ALL
            touched_s = time.monotonic()
            self.store.touched_s[update.touched_slots] = touched_s
            self.store.mesh_pending[update.touched_slots] = True  # the TSDF changed here, whatever alpha does
            self.frames_integrated[cfg.sensors[s]] += 1
            self.counters["sparse_dropped_samples"] += update.dropped_samples
            self.counters["sparse_dropped_blocks"] += update.dropped_blocks
            self.bound.frame_integrated(camera_m=np.asarray(frame.T_world_camera, np.float64)[:3, 3].copy(),
                                        touched_s=touched_s, n_touched=len(update.touched_slots))
        self.times.add(integrate=frame.checks_s + time.perf_counter() - t0 - update.waited_s)
        if self.bound.over_hard_bound():  # updates come too rarely to keep the bound
            # (this thread evicts, or waits for the update that holds the update lock to do so)
            self.update_lock.wait_for_eviction(self.bound.over_hard_bound, lambda: self._evict(integration_waits=True))
        return update.voxels_updated

    @torch.inference_mode()
    def update(self, alpha_budget_s: float | None = None, *, mesh_threads: int = 1,
               mesh_budget_s: float | None = None) -> MeshUpdate:
        """Alpha, fusion and meshing over the blocks changed since the last update.

        alpha_budget_s: at most about this long re-evaluating alpha; the blocks left over keep their
        previous alpha until a later update, in `alpha_order` (where it was never
        evaluated, the mesh shows what both sensors saw, averaged: see fusion). None: all of them
        (exact, deterministic). The live node passes 0 and calls `refresh_alpha` after publishing: new
        geometry is shown sooner, and its alpha comes with the next update.
        mesh_threads: mesh on up to this many of the alpha threads at once (at most `alpha_threads`),
        for a caller that knows no frame waits for the cores (the live node, whenever none is queued:
        once its sensors pause, the blocks of the frames it set aside are meshed sooner).
        mesh_budget_s: re-mesh about as many blocks as take this long (judged by the last updates'
        time per block); the others stay due (`BlockStore.mesh_due`) and go first in the next updates,
        the longest-waiting first, so nothing is lost and, once they are all meshed, the mesh is what
        unbudgeted updates give. None: every block due (exact); `mesh_backlog_blocks` counts the rest.
        A budgeted update's eviction also stops taking slices once the budget is spent (`MapBound.evict`)."""
        with self.update_lock.held():
            t0 = time.perf_counter()
            self._evict(budget_s=mesh_budget_s)  # a budgeted update evicts in turns too
            if alpha_budget_s != 0:
                self._refresh_alpha(alpha_budget_s)
            t1 = time.perf_counter()
            with self.data_lock:
                pending = np.flatnonzero(self.store.mesh_pending[: self.grid.n_blocks])
                self.store.mesh_pending[pending] = False
                threads = min(mesh_threads, self.config.alpha_threads)
                self._mesh_round += 1
                max_blocks = None
                if mesh_budget_s is not None:
                    per_block_s = self._mesh_s_per_block.get(threads)
                    # no time per block measured yet: a first share small enough for any machine; at least
                    # _MIN_MESH_BLOCKS: every update makes progress
                    max_blocks = max(_MIN_MESH_BLOCKS, _FIRST_MESH_BLOCKS if per_block_s is None
                                     else int(mesh_budget_s / max(per_block_s, 1e-9)))
                slots, self.counters["mesh_backlog_blocks"] = mesh_share(
                    self.store.mesh_due, self.grid.n_blocks, self.mesher.mesh_readers(pending),
                    mesh_round=self._mesh_round, max_blocks=max_blocks)
                # blocks in memory that have an archived mesh near these: their markers show both, and
                # the archived part shrinks as neighbours come back (see below)
                pruned = self.bound.take_pruned()  # by evictions since the last update
                near = self.archive.held(self.grid.coords[slots].numpy(), around=True) | pruned
                if near:
                    found = self.grid.lookup(torch.tensor(sorted(near), dtype=torch.int64)).numpy()
                    slots = np.union1d(slots, found[found >= 0])
                coords = self.grid.coords[slots].numpy().copy()
            self.counters["mesh_blocks"] += len(slots)
            self.counters["mesh_blocks_last"] = len(slots)
            result = MeshUpdate(cleared=self._cleared)
            self._cleared = False
            evictions = self.bound.evictions
            t_mesh = time.perf_counter()
            live = self._block_meshes(slots, coords, threads=threads)
            if len(slots) >= _MIN_MESH_BLOCKS:  # fewer say more about the call's overhead than a block's cost
                per_block_s = (time.perf_counter() - t_mesh) / len(slots)
                # up at once, down halfway: a core taken by integration shows at once, a free one counts
                # only once it stays free (a budget overrun delays the refresh, a shortfall only this share)
                last = self._mesh_s_per_block.get(threads)
                self._mesh_s_per_block[threads] = (per_block_s if last is None or per_block_s > last
                                                   else 0.5 * (last + per_block_s))
            live_keys, changed_keys = (block_keys(torch.from_numpy(c)).numpy() for c in (live.keys, coords))
            # the evicted blocks' final meshes: subscribers keep showing them, a block's marker with its
            # live mesh, less the triangles of cells whose 8 corners are all in memory again (the live
            # meshes have those cells: each reader of a block that came back was re-meshed)
            archived_now = {tuple(k) for k in self.bound.take_archived().keys.tolist()}
            # (only those found before meshing: a block in memory is shown whole only if it was re-meshed)
            near = self.archive.held(near | archived_now) | (near & pruned)
            if near:
                with self.data_lock:
                    in_memory = np.sort(self.grid.slot_keys[: self.grid.n_blocks])
                self.archive.prune(near, in_memory, self.config.voxel_size_m)
            result.meshes = union(live, self.archive.select(near))
            has_faces = np.isin(changed_keys, live_keys)
            vanished = [tuple(key) for key in coords[~has_faces & np.isin(changed_keys, self._meshed)].tolist()]
            # evicted blocks that were shown and whose final mesh was empty (the net, judging them before
            # the eviction, filtered what was shown): their markers go
            evicted = [tuple(key) for key in keys_to_coords(torch.from_numpy(np.concatenate(
                self._evicted_shown or [np.zeros(0, np.int64)]))).tolist()]
            self._evicted_shown = []
            archived = self.archive.held(vanished + sorted(near) + evicted)
            live_set = set(map(tuple, live.keys.tolist()))  # archived meshes pruned away where nothing live shows
            removed = [key for key in vanished if key not in archived]
            removed += [key for key in sorted(near) + evicted if key not in archived and key not in live_set]
            result.removed = list(dict.fromkeys(removed))
            # (each key once, live ones among the changed: a sorted concatenation is the union, without
            # np.unique, which hashes int64 keys)
            self._meshed = np.sort(np.concatenate([np.setdiff1d(self._meshed, changed_keys, assume_unique=True),
                                                   live_keys]))
            self.counters["meshed_blocks"] = len(self._meshed)
            with self.data_lock:  # for the weighting net's order
                if self.bound.evictions != evictions:  # evicted between batches: blocks moved into the freed slots
                    now = self.grid.lookup_keys(torch.from_numpy(changed_keys)).numpy()
                    slots, has_faces = now[now >= 0], has_faces[now >= 0]
                self.store.meshed[slots] = has_faces
            self.times.add(alpha=t1 - t0, mesh=time.perf_counter() - t1)
            return result

    @torch.inference_mode()
    def refresh_alpha(self, budget_s: float | None = None, *, until_frame: bool = False) -> None:
        """Re-evaluate alpha where the inputs changed, at most about budget_s seconds (None: all of
        it), and with `until_frame` only until a frame is integrated, on `alpha_threads` threads (an
        idle catch-up that yields to the sensors when they resume); the next update re-meshes the
        blocks whose alpha changed."""
        with self.update_lock.held():
            start = time.perf_counter()
            self._refresh_alpha(budget_s, until_frame=until_frame)
            self.times.add(alpha=time.perf_counter() - start)

    @torch.inference_mode()
    def block_meshes(self) -> BlockMeshes:
        """The fused (filtered) mesh of every block, as `update` sends it, with alpha as it is now
        (nothing re-evaluated), and the archived meshes of evicted blocks: a snapshot for a
        subscriber that joins late. Its blocks count as shown from then on (an update deletes a
        block whose mesh vanishes)."""
        with self.update_lock.held():
            with self.data_lock:
                slots = np.arange(self.grid.n_blocks)
                coords = self.grid.coords[: self.grid.n_blocks].numpy().copy()
            live = self._block_meshes(slots, coords)
            # shown from now on: blocks integrated since the last update are too, and an update must
            # delete their meshes should they vanish
            self._meshed = np.union1d(self._meshed, block_keys(torch.from_numpy(live.keys)).numpy())
            self.counters["meshed_blocks"] = len(self._meshed)
            with self.data_lock:
                in_memory = np.sort(self.grid.slot_keys[: self.grid.n_blocks])
            archived = self.archive.visible(in_memory, self.config.voxel_size_m)
        return union(live, archived)

    @torch.inference_mode()
    def extract_mesh(self, which: str = FUSED, filtered: bool = True, *, then_reset: bool = False,
                     judge: bool = True) -> Mesh:
        """The whole mesh of `which`: "fused", a sensor name, or "tsdf_fusion" (the baseline). The
        fused mesh includes the archived meshes of blocks the map bound evicted (`archive`); the
        others cover the blocks in memory. `then_reset`: for a caller done with the map (replay's
        last mesh), `reset` once every block is meshed, so that the map's memory is free before the
        weld, extraction's peak. `judge`: the weighting net first judges what it has not reached (else
        the fused mesh is the map as it stands, as the live mesh shows it: a caller in a hurry)."""
        self.config.check_mesh_name(which)
        with self.update_lock.held():
            if which == FUSED and judge:
                self._refresh_alpha()
                self.alpha.evaluator.release_buffers()
                release_free_memory()  # the net's temporaries: the mesh's peak comes on top otherwise
            with self.data_lock:  # one consistent state of the whole map
                if then_reset:  # the channels this mesh does not read go first (the mesh's peak comes on top)
                    self.grid.channel_pools.release(set(self.grid.pools) - set(self.mesher.channels(which)))
                slots = np.arange(self.grid.n_blocks)
                coords = self.grid.coords[: self.grid.n_blocks].numpy().copy()
                # each batch goes into the weld's compact arrays at once (extraction's memory peak)
                welder = StreamingWeld(self.config.voxel_size_m, coords.min(axis=0, initial=0),
                                       coords.max(axis=0, initial=0))
                for part in self.mesher.batches(slots, which, filtered):
                    welder.add(part.vertices_vox, part.faces, part.vertex_values if which == FUSED else None)
                    del part
            if which == FUSED and filtered and len(self.archive):
                # without the triangles of cells the live mesh has (all 8 corners in memory)
                archived = as_mesh(self.archive.visible(np.sort(block_keys(torch.from_numpy(coords)).numpy()),
                                                        self.config.voxel_size_m))
                if archived.n_faces:  # welded with the live mesh: colours instead of alpha
                    assert archived.colors is not None
                    welder.add_colored_m(archived.vertices, archived.faces, archived.colors)
            if then_reset:
                self.reset()
        self.mesher.release_buffers()
        release_free_memory()  # the batches' buffers
        return welder.mesh()

    def reset(self, *, report_cleared: bool = True) -> None:
        """Forget everything fused; the next update reports `cleared` (unless not `report_cleared`:
        nothing was shown yet)."""
        with self.update_lock.held(), self.data_lock:
            self.store.clear()
            self.bound.clear()
            for name in ("evicted_blocks", "evictions"):  # the map's, as the spill and the archive (emptied)
                self.counters.pop(name, None)
            self.frames_integrated = {name: 0 for name in self.config.sensors}
            self._meshed = np.zeros(0, np.int64)
            self._evicted_shown = []
            self.counters["mesh_backlog_blocks"] = 0  # the due flags went with the blocks
            self._cleared = report_cleared

    def stats(self, *, wait: bool = True) -> dict | None:
        """Map size and memory, and how much of the meshed surface has its alpha: judged at least
        once (evaluated, or found to hold no voxel alpha matters for; else its mesh averages the
        sensors, see fusion), and up to date (not stale). wait=False: None at once while an update,
        extraction or save holds the map (a status publisher keeps what it had rather than wait)."""
        n = len(self.config.sensors)
        with self.update_lock.held(wait=wait) as held:
            if not held:
                return None
            with self.data_lock:  # only the flags: integration waits for this lock
                nbytes = self.store.nbytes()
                meshed = self.grid.lookup_keys(torch.from_numpy(self._meshed)).numpy()
                meshed = meshed[meshed >= 0]
                # judged: alpha evaluated, or the block found to hold no voxel it matters for
                evaluated = self.store.evaluated[meshed] | self.store.no_targets[meshed]
                current = evaluated & (self.store.stale[meshed] == 0) & ~self.store.alpha_pending[meshed]
                waiting_s = self.alpha.waiting_s(meshed[~current], time.monotonic())
                spill = self.grid.spill
                spilled = ((len(spill), spill.nbytes, spill.restored, spill.compact_failures) if spill is not None
                           else (0, 0, 0, 0))
            # counted without the data lock, as an update reads the grid: a frame integrated meanwhile
            # may or may not be in the count
            observed = self.store.observed_voxels([f"weight{i}" for i in range(n)])
        return {"blocks": self.grid.n_blocks, "observed_voxels": observed, "grid_bytes": nbytes,
                "bytes_per_observed_voxel": nbytes / max(observed, 1),
                "frames_integrated": dict(self.frames_integrated),
                # what G computes in (int8 asked for but unavailable runs float32)
                "alpha_arithmetic": ("int8" if self.alpha.evaluator.int8_net is not None
                                     else self.config.alpha_dtype.replace("int8", "float32")),
                "max_blocks": self.max_blocks, "evicted_blocks": self.bound.evicted_blocks,
                "evicted_in_view_blocks": self.bound.evicted_in_view,
                "sparse_dropped_samples": self.counters["sparse_dropped_samples"],
                "sparse_dropped_blocks": self.counters["sparse_dropped_blocks"],
                "occupancy": observed / max(self.grid.n_blocks * 512, 1),
                "archived_blocks": len(self.archive), "archived_faces": self.archive.chunks.n_faces,
                # the archive's meshes in RAM (the recent ones) and in its memory-mapped files (the rest)
                "archive_bytes_in_memory": self.archive.chunks.bytes_in_memory,
                "archive_bytes_on_disk": self.archive.chunks.bytes_on_disk,
                "archive_seal_failures": self.archive.chunks.seal_failures,
                # evicted blocks whose final meshes wait for memory to be archived (`MapBound._archive`)
                "unarchived_blocks": sum(len(meshes) for meshes in self.bound.unarchived),
                "spilled_blocks": spilled[0], "spill_bytes": spilled[1], "restored_blocks": spilled[2],
                "spill_compact_failures": spilled[3],
                "meshed_blocks": len(meshed), "meshed_blocks_alpha_evaluated": int(evaluated.sum()),
                "meshed_blocks_alpha_current": int(current.sum()),
                # how long the meshed surface waits for the weighting net after it changed
                "meshed_blocks_unjudged_over_3s": int((waiting_s > 3.0).sum()),
                "oldest_unjudged_change_s": float(np.nanmax(waiting_s, initial=0.0))}

    # -- internals -------------------------------------------------------------------------------
    def _refresh_alpha(self, budget_s: float | None = None, *, until_frame: bool = False) -> None:
        """`AlphaScheduler.refresh` with this engine's eviction points; with `until_frame`, until a
        frame is integrated."""
        frames_at_start = sum(self.frames_integrated.values())
        refresh = self.alpha.refresh(
            budget_s, until_frame=(lambda: sum(self.frames_integrated.values()) != frames_at_start) if until_frame
            else None, eviction_due=self.bound.over_hard_bound, evict=self._evict)
        self.counters["alpha_blocks"] += refresh.blocks
        self.counters["alpha_voxels"] += refresh.voxels
        self.counters["alpha_flops"] = self.alpha.flops
        self.counters["alpha_backlog_blocks"] = refresh.backlog

    def _evict(self, *, integration_waits: bool = False, budget_s: float | None = None) -> Eviction | None:
        """`MapBound.evict` (call with the update lock held; `integration_waits`: by the integrating
        thread; `budget_s`: its slices stop after about this long); the evicted blocks are no longer
        shown as live meshes (the archive shows them), and an integration waiting for it goes on
        after its first slice."""
        eviction = self.bound.evict(integration_waits=integration_waits, removed=self.update_lock.evicted,
                                    budget_s=budget_s)
        self.counters["spill_failures"] = self.bound.spill_failures
        self.counters["spill_failing"] = int(self.bound.spill_failing)
        if eviction is not None:
            self.counters["evicted_blocks"] = self.bound.evicted_blocks
            self.counters["evictions"] = self.bound.evictions
            # shown until now: the next update deletes those whose final mesh had no triangle (not archived)
            self._evicted_shown.append(eviction.dropped_keys[np.isin(eviction.dropped_keys, self._meshed)])
            self._meshed = np.setdiff1d(self._meshed, eviction.dropped_keys)
            self.update_lock.evicted()
        return eviction

    def _block_meshes(self, slots: np.ndarray, coords: np.ndarray, *, threads: int = 1) -> BlockMeshes:
        """Fused, filtered meshes of the given blocks (coords: their block keys), batch by batch
        (`threads` > 1: that many at once, in equal shares on the alpha threads), evicting between
        batches when integration outgrew the bound; blocks without triangles, or evicted meanwhile,
        are left out."""
        parts: list[BlockMeshes] = []
        evicted: list[np.ndarray] = []
        size = self.config.mesh_batch_blocks
        while len(slots):
            if self.bound.over_hard_bound():
                eviction = self._evict()  # None: the spill could not be written, the blocks stay
                if eviction is not None:
                    slots, kept = eviction.follow(slots)
                    coords = coords[kept]
                    evicted.append(eviction.dropped_keys)
            n = min(len(slots), size * threads)
            (batch, slots), (batch_coords, coords) = (slots[:n], slots[n:]), (coords[:n], coords[n:])
            if threads > 1 and n >= 2 * _MIN_THREAD_BLOCKS:  # equal shares: the round ends with its last share
                step = -(-n // min(threads, n // _MIN_THREAD_BLOCKS))
                parts += self.alpha.workers().map(self.mesher.block_meshes, *(
                    [array[i:i + step] for i in range(0, n, step)] for array in (batch, batch_coords)))
            else:
                parts.append(self.mesher.block_meshes(batch, batch_coords))
        meshes = BlockMeshes.concatenate(parts)
        if evicted:  # blocks meshed in an earlier batch may be gone: they must not be shown
            gone = np.isin(block_keys(torch.from_numpy(meshes.keys)).numpy(), np.concatenate(evicted))
            meshes = meshes.select(np.flatnonzero(~gone))
        return meshes


def mesh_share(due: np.ndarray, n_blocks: int, readers: np.ndarray, *, mesh_round: int, max_blocks: int | None
               ) -> tuple[np.ndarray, int]:
    """The blocks an update re-meshes (sorted slots) and how many are left for later: those earlier
    updates left (`due`: per slot, the round that left it, 0: none; the longest-waiting first), then
    `readers`, at most max_blocks of them (None: all). The rest are marked due in `due` with this
    `mesh_round` (`BlockStore.mesh_due`; call under the engine's data lock)."""
    left = np.flatnonzero(due[:n_blocks])
    if max_blocks is None and not len(left):
        return readers, 0
    left = left[np.argsort(due[left], kind="stable")]
    order = np.concatenate([left, np.setdiff1d(readers, left)])
    chosen, rest = (order, order[:0]) if max_blocks is None else (order[:max_blocks], order[max_blocks:])
    due[chosen] = 0
    due[rest[due[rest] == 0]] = mesh_round
    return np.sort(chosen), len(rest)


def int8_weighting(net: networks.WeightingNet, config: EngineConfig, *, weights: str | Path | None = None,
                   calibration: Int8Calibration | None = None) -> Int8WeightingNet | None:
    """G in int8 for config.alpha_dtype "int8" on the CPU, with this calibration or else the weights
    file's, or None (float32) with a warning that says why when it cannot be: no calibration, or no
    int8 convolutions in this torch."""
    if config.alpha_dtype != "int8":
        return None
    why = ""
    if calibration is None:
        calibration, why = (None, "untrained weights have no int8 calibration") if weights is None else (
            load_calibration(weights))
    if calibration is not None and not int8_available():
        calibration, why = None, "this torch or CPU has no working oneDNN int8 convolutions"
    if calibration is None or networks.choose_device(config.device, cpu_fallback=False).device.type != "cpu":
        log.warning("alpha_dtype int8: %s; the weighting net runs in float32", why or "int8 is for the CPU")
        return None
    log.info("weighting net in int8 (calibrated on %s)", calibration.calibrated_on)
    return Int8WeightingNet(net, calibration, input_ranges(net, config.depth_max_m))


def prepare_frame(engine: SenFuNet, sensor: str, depth_m: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray,
                  rgb: np.ndarray | None = None) -> PreparedFrame:
    """First half of `SenFuNet.integrate`: check the frame (InputError as there) and start its feature
    net in the worker thread; `integrate_prepared` is the second. A caller holding the next frame
    prepares it before integrating the current one, so that the feature net runs while the current
    frame's kernels do. Reads only the engine's configuration and networks: no lock."""
    t0 = time.perf_counter()
    cfg = engine.config
    s = cfg.sensor_index(sensor)
    check_frame(depth_m, K, T_world_camera, rgb)
    depth, deepest_m = clean_depth(depth_m, cfg.border_px, cfg.depth_min_m[s], cfg.depth_max_m[s])
    if deepest_m < 0:  # no valid pixel
        return PreparedFrame(s, depth, K, T_world_camera, None, time.perf_counter() - t0)
    check_key_range(deepest_m, K, T_world_camera, depth.shape, cfg.band_m)
    features = _FEATURE_WORKER.submit(_pixel_features, engine.feature_nets[s], engine.times, depth, rgb)
    return PreparedFrame(s, depth, K, T_world_camera, features, time.perf_counter() - t0)


def warm_up(engine: SenFuNet) -> None:
    """Compile (or load from numba's cache) every kernel on a small synthetic frame per sensor,
    then forget it: the first real frame and update then run at full speed."""
    size = 4 * engine.config.border_px + 32
    depth_m = 0.5 * (engine.config.depth_min_m[0] + engine.config.depth_max_m[0])
    # pixels half a voxel apart on the plane: cells with all corners observed, which the weighting
    # net's kernels need to run at all
    focal = 2.0 * depth_m / engine.config.voxel_size_m
    K = np.array([[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1]], np.float64)
    depth = np.full((size, size), depth_m, np.float32)
    rgb = np.full((size, size, 3), 128, np.uint8)
    # without the map bound: under one smaller than the synthetic frame's blocks, its evictions stayed in the
    # counters after the reset (evictions that never were) and took the one warning about a bound smaller
    # than a frame's view, with the synthetic frame's figures
    max_blocks, engine.bound.max_blocks = engine.bound.max_blocks, 0
    try:
        for sensor in engine.config.sensors:
            engine.integrate(sensor, depth, K, np.eye(4), rgb)
        engine.update()
        engine.extract_mesh(engine.config.sensors[0])
    finally:
        engine.bound.max_blocks = max_blocks
    warm_up_lookups()
    engine.reset(report_cleared=False)
    # the alpha threads the update started share the warming thread's priority: the first real
    # update starts them again from its own thread (the live node's mesh thread, of lower priority)
    engine.alpha.stop_workers()
