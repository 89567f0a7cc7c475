"""The SenFuNet engine: owns the sparse grids and the networks; a few verbs.

    engine = SenFuNet(EngineConfig(), weights="default")
    engine.integrate("tof", depth_m, K, T_world_camera)        # at sensor rate
    update = engine.update()                                    # alpha, fusion, meshing of changed blocks
    mesh = engine.extract_mesh("fused")                         # or a sensor name, or "tsdf_fusion"

Incremental update: a frame marks the blocks it touched. `update` re-evaluates the weighting
net on those blocks and their 26 neighbours (alpha depends on inputs within 2 voxels, less than
a block), each with a 2-voxel halo, which equals evaluating it over the whole grid; then it
re-meshes every block whose cells read a changed alpha or TSDF (the changed blocks and their
-x, -y, -z neighbours, since a block's cells reach one voxel into its +x, +y, +z neighbours).
"""
from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from . import networks
from .errors import InputError
from .fusion import fuse
from .grid import BLOCK, BLOCK_VOXELS, NEIGHBOUR_OFFSETS, BlockGrid, local_grid
from .integrator import (IntegratorConfig, aggregate_pixel_values, check_frame, frame_samples, integrate_into,
                         running_average, valid_depth_mask, voxel_slots)
from .mesher import Mesh, marching_cubes_blocks, to_mesh, weld

log = logging.getLogger("senfunet.engine")

TSDF_FUSION = "tsdf_fusion"
FUSED = "fused"
# Blocks whose cells read a block: itself and its -x, -y, -z neighbours.
# A block with at least this many alpha targets is evaluated densely (~1.5 ms per block, all 512
# voxels) instead of by sparse gathers (~20-40 us per target on this CPU).
_DENSE_ALPHA_TARGETS = 48
_STORAGE_DTYPES = {"float32": torch.float32, "float16": torch.float16}
_MESH_READERS = torch.tensor([[-dx, -dy, -dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)])


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
    device: str = "cpu"  # "cpu" or "cuda"
    alpha_batch_blocks: int = 512  # blocks per weighting-net batch (memory vs. speed)
    mesh_batch_blocks: int = 4096  # blocks per marching-cubes call
    seed: int = 0  # initialisation of untrained networks
    torch_threads: int = 1  # torch intra-op threads the engine sets (0: leave torch's setting); 1 fits 2 shared cores
    storage_dtype: str = "float16"  # feature and weight-counter pools ("float16" halves them; counters stay exact)
    alpha_voxels: str = "all"  # which voxels near a change get alpha re-evaluated: "all" (equals the whole-grid
    #   evaluation on every voxel); "observed" (observed voxels: all that fusion, filter, meshes and clouds read);
    #   "surface" (corners of cells whose 8 corners are observed and whose sensor TSDFs straddle 0: all that the
    #   fused mesh, its filter and its colours read; alpha elsewhere may be stale)
    alpha_tolerance: float = 0.0  # re-evaluate alpha around a voxel only once its inputs drifted more than this
    #                               (max-norm over [F, tanh(W)], summed over frames); 0 = exact

    @property
    def integrator(self) -> IntegratorConfig:
        return IntegratorConfig(self.voxel_size_m, self.band_m, self.n_samples, self.n_samples_behind, self.w_max,
                                self.border_px)

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
        if self.storage_dtype not in _STORAGE_DTYPES:
            raise InputError(f"storage_dtype must be one of {sorted(_STORAGE_DTYPES)}, got '{self.storage_dtype}'")
        if self.storage_dtype == "float16" and self.w_max > 2048:
            raise InputError("w_max above 2048 needs storage_dtype float32 (float16 counts exactly only to 2048)")
        if self.alpha_voxels not in ("all", "observed", "surface"):
            raise InputError(f"alpha_voxels must be 'all', 'observed' or 'surface', got '{self.alpha_voxels}'")
        if not self.alpha_tolerance >= 0 or self.torch_threads < 0:
            raise InputError("alpha_tolerance must be >= 0 and torch_threads >= 0")


@dataclass
class MeshUpdate:
    """What changed in the fused mesh since the previous update."""

    changed: dict[tuple[int, int, int], Mesh] = field(default_factory=dict)  # block key -> its whole mesh
    removed: list[tuple[int, int, int]] = field(default_factory=list)  # blocks whose mesh vanished
    cleared: bool = False  # the map was reset before this update: drop everything shown so far


@dataclass
class WeightCloud:
    positions_m: np.ndarray  # Nx3 float32 voxel centres
    alpha: np.ndarray  # N float32 sensor weighting (weight of sensor 1)
    weights: np.ndarray  # N x n_sensors float32 weight counters


def _window_reduce(x: torch.Tensor, k: int, op) -> torch.Tensor:
    """B x S x S x S -> B x (S-k+1)^3: `op` (logical_or, logical_and, minimum, maximum) over each
    k^3 window, as three separable passes of shifted slices (much faster than max_pool3d on CPU)."""
    for dim in (1, 2, 3):
        m = x.shape[dim] - k + 1
        out = x.narrow(dim, 0, m)
        for i in range(1, k):
            out = op(out, x.narrow(dim, i, m))
        x = out
    return x


def resolve_device(name: str) -> torch.device:
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise InputError(f"device '{name}' requested but CUDA is not available; use device 'cpu'")
    return torch.device(name)


class SenFuNet:
    """Learned two-sensor TSDF fusion on sparse voxel blocks, plus the plain TSDF Fusion baseline."""

    def __init__(self, config: EngineConfig = EngineConfig(), weights: str | Path | None = "default") -> None:
        config.validate()
        self.config = config
        self.device = resolve_device(config.device)
        if config.torch_threads > 0 and torch.get_num_threads() != config.torch_threads:
            torch.set_num_threads(config.torch_threads)
        self.feature_nets, self.weighting_net = networks.make_networks(config.sensor_uses_rgb, config.seed)
        self.weights_source = "random initialisation (untrained)"
        if weights == "default":
            if networks.DEFAULT_WEIGHTS.is_file():
                weights = networks.DEFAULT_WEIGHTS
            else:
                log.warning("no shipped weights at %s: using untrained networks", networks.DEFAULT_WEIGHTS)
                weights = None
        if weights is not None:
            networks.load_weights(weights, self.feature_nets, self.weighting_net)
            self.weights_source = str(weights)
        self.feature_nets.to(self.device).eval()
        self.weighting_net.to(self.device).eval()
        channels: dict[str, tuple[int, ...]] = {"tsdf_base": (), "weight_base": (), "alpha": ()}
        for i in range(len(config.sensors)):
            channels.update({f"tsdf{i}": (), f"weight{i}": (), f"feat{i}": (networks.N_FEATURES,)})
        storage = _STORAGE_DTYPES[config.storage_dtype]
        dtypes = {name: storage for name in channels if name.startswith(("feat", "weight"))}
        self.grid = BlockGrid(channels, self.device, dtypes=dtypes)
        self._drift = torch.zeros(0, device=self.device)  # per voxel (slot*512+local): input change since its alpha
        self.counters = {"alpha_voxels": 0, "alpha_blocks": 0, "mesh_blocks": 0}
        self.timings_s: dict[str, float] = {}
        self.frames_integrated = {name: 0 for name in config.sensors}
        self._reset_pending()

    # -- verbs ------------------------------------------------------------------------------------
    @torch.inference_mode()
    def integrate(self, sensor: str, depth_m: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray,
                  rgb: np.ndarray | None = None) -> int:
        """Integrate one depth frame (H x W float32 metres) of `sensor`; returns the voxels updated.

        Invalid pixels (0, NaN, inf, negative, out of range, image border) are skipped. Raises
        InputError (grids untouched) for wrong shapes, dtypes, intrinsics or poses.
        """
        s = self._sensor_index(sensor)
        check_frame(depth_m, K, T_world_camera, rgb)
        cfg = self.config
        t0 = time.perf_counter()
        depth = torch.from_numpy(np.ascontiguousarray(depth_m, dtype=np.float32)).to(self.device)
        depth = torch.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0).clamp_(min=0.0)
        valid = valid_depth_mask(depth, cfg.border_px, cfg.depth_min_m[s], cfg.depth_max_m[s])
        if not bool(valid.any()):
            return 0
        K_t = torch.as_tensor(np.asarray(K, dtype=np.float64), device=self.device)
        T_t = torch.as_tensor(np.asarray(T_world_camera, dtype=np.float64), device=self.device)
        samples = frame_samples(depth, valid, K_t, T_t, cfg.integrator)
        flat = voxel_slots(self.grid, samples.keys)  # may raise InputError before anything is written
        t1 = time.perf_counter()
        pixel_features = self._pixel_features(s, depth, rgb).flatten(1)[:, samples.pixel_index].T  # P x 5
        voxel_features = aggregate_pixel_values(samples, pixel_features)
        t2 = time.perf_counter()
        self._integrate_sensor(s, flat, samples.tsdf_m, voxel_features)
        integrate_into(self.grid, flat, "tsdf_base", "weight_base", samples.tsdf_m, cfg.w_max)
        self._alpha_changed.append(torch.unique_consecutive(flat // BLOCK_VOXELS))
        self.frames_integrated[sensor] += 1
        t3 = time.perf_counter()
        self.timings_s.update(integrate_samples=t1 - t0, feature_net=t2 - t1, integrate_update=t3 - t2)
        return int(flat.numel())

    @torch.inference_mode()
    def update(self) -> MeshUpdate:
        """Alpha, fusion and meshing over the blocks changed since the last update."""
        t0 = time.perf_counter()
        self._refresh_alpha()
        t1 = time.perf_counter()
        slots = self._take_mesh_pending()
        self.counters["mesh_blocks"] += int(slots.numel())
        self.counters["mesh_blocks_last"] = int(slots.numel())
        result = MeshUpdate(cleared=self._cleared)
        self._cleared = False
        for start in range(0, slots.numel(), self.config.mesh_batch_blocks):
            batch = slots[start:start + self.config.mesh_batch_blocks]
            tris = self._mesh_batch(batch, FUSED, filtered=True)
            coords = self.grid.coords[batch].tolist()
            order = np.argsort(tris.vertex_block, kind="stable")
            v_starts = np.searchsorted(tris.vertex_block[order], np.arange(len(batch) + 1))
            f_order = np.argsort(tris.face_block, kind="stable")
            f_starts = np.searchsorted(tris.face_block[f_order], np.arange(len(batch) + 1))
            remap = np.empty(len(order), np.int64)
            for b, key in enumerate(map(tuple, coords)):
                vertex_ids = order[v_starts[b]:v_starts[b + 1]]
                face_ids = f_order[f_starts[b]:f_starts[b + 1]]
                if len(face_ids) == 0:
                    if key in self._meshed:
                        self._meshed.discard(key)
                        result.removed.append(key)
                    continue
                remap[vertex_ids] = np.arange(len(vertex_ids))
                faces = remap[tris.faces[face_ids]]
                alpha = tris.vertex_values[vertex_ids]
                result.changed[key] = to_mesh(tris.vertices_vox[vertex_ids], faces, self.config.voxel_size_m, alpha)
                self._meshed.add(key)
        self.timings_s.update(alpha=t1 - t0, mesh=time.perf_counter() - t1)
        return result

    @torch.inference_mode()
    def extract_mesh(self, which: str = FUSED, filtered: bool = True) -> Mesh:
        """The whole mesh of `which`: "fused", a sensor name, or "tsdf_fusion" (the baseline)."""
        self._check_which(which)
        if which == FUSED:
            self._refresh_alpha()
        parts = []
        slots = torch.arange(self.grid.n_blocks, device=self.device)
        for start in range(0, slots.numel(), self.config.mesh_batch_blocks):
            parts.append(self._mesh_batch(slots[start:start + self.config.mesh_batch_blocks], which, filtered))
        if not parts:
            return Mesh.empty()
        offsets = np.cumsum([0] + [len(p.vertices_vox) for p in parts])
        vertices = np.concatenate([p.vertices_vox for p in parts])
        faces = np.concatenate([p.faces + o for p, o in zip(parts, offsets)])
        values = np.concatenate([p.vertex_values for p in parts]) if which == FUSED else None
        vertices, faces, values = weld(vertices, faces, values)
        return to_mesh(vertices, faces, self.config.voxel_size_m, values)

    @torch.inference_mode()
    def voxel_values(self, which: str = FUSED, filtered: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Centres (N x 3, metres) and TSDF values (N) of the observed voxels of `which`."""
        self._check_which(which)
        if which == FUSED:
            self._refresh_alpha()
        slots = torch.arange(self.grid.n_blocks, device=self.device)
        tsdf, observed = self._values(self._whole_blocks(slots, self._channels(which)), which, filtered)
        centres = self.grid.voxel_centres(slots, self.config.voxel_size_m)
        return centres[observed].cpu().numpy(), tsdf[observed].cpu().numpy()

    @torch.inference_mode()
    def weight_cloud(self, max_abs_tsdf_m: float | None = None) -> WeightCloud:
        """Voxels observed by any sensor: position, alpha and each sensor's weight counter.
        With max_abs_tsdf_m, only voxels whose unfiltered fused |TSDF| is at most that."""
        self._refresh_alpha()
        slots = torch.arange(self.grid.n_blocks, device=self.device)
        blocks = self._whole_blocks(slots, self._channels(FUSED))
        n = len(self.config.sensors)
        weights = torch.stack([blocks[f"weight{i}"] for i in range(n)], dim=-1)
        keep = (weights > 0).any(dim=-1)
        if max_abs_tsdf_m is not None:
            tsdf, _ = self._values(blocks, FUSED, filtered=False)
            keep &= tsdf.abs() <= max_abs_tsdf_m
        centres = self.grid.voxel_centres(slots, self.config.voxel_size_m)
        return WeightCloud(centres[keep].cpu().numpy(), blocks["alpha"][keep].cpu().numpy().astype(np.float32),
                           weights[keep].cpu().numpy().astype(np.float32))

    def reset(self) -> None:
        """Forget everything fused; the next update reports `cleared`."""
        self.grid.clear()
        self._drift = torch.zeros(0, device=self.device)
        self.frames_integrated = {name: 0 for name in self.config.sensors}
        self._reset_pending()
        self._cleared = True

    def save(self, path: str | Path) -> None:
        """The whole engine state (config, grids, networks) in one file, written atomically."""
        self._refresh_alpha()
        state = {
            "format": "senfunet-engine-1",
            "config": asdict(self.config),
            "grid": self.grid.state_dict(),
            "feature_nets": [net.state_dict() for net in self.feature_nets],
            "weighting_net": self.weighting_net.state_dict(),
            "frames_integrated": dict(self.frames_integrated),
        }
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        torch.save(state, tmp)
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path, device: str | None = None) -> "SenFuNet":
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
        config_values = {k: tuple(v) if isinstance(v, list) else v for k, v in state["config"].items() if k in known}
        config = EngineConfig(**config_values)
        if device is not None:
            config = replace(config, device=device)
        engine = cls(config, weights=None)
        for net, net_state in zip(engine.feature_nets, state["feature_nets"]):
            net.load_state_dict(net_state)
        engine.weighting_net.load_state_dict(state["weighting_net"])
        engine.weights_source = f"{path} (saved state)"
        engine.grid.load_state_dict(state["grid"])
        engine.frames_integrated.update(state["frames_integrated"])
        engine._mesh_pending.append(torch.arange(engine.grid.n_blocks, device=engine.device))
        return engine

    def stats(self) -> dict:
        n = len(self.config.sensors)
        weights = torch.stack([self.grid.pools[f"weight{i}"][: self.grid.n_blocks] for i in range(n)])
        observed = int((weights > 0).any(dim=0).sum())
        nbytes = self.grid.nbytes()
        return {"blocks": self.grid.n_blocks, "observed_voxels": observed, "grid_bytes": nbytes,
                "bytes_per_observed_voxel": nbytes / max(observed, 1), "frames_integrated": dict(self.frames_integrated)}

    # -- internals -------------------------------------------------------------------------------
    def _sensor_index(self, sensor: str) -> int:
        try:
            return self.config.sensors.index(sensor)
        except ValueError:
            raise InputError(f"unknown sensor '{sensor}'; configured sensors: {list(self.config.sensors)}") from None

    def _check_which(self, which: str) -> None:
        if which not in (FUSED, TSDF_FUSION, *self.config.sensors):
            raise InputError(f"unknown mesh '{which}'; choose {FUSED}, {TSDF_FUSION} or one of {list(self.config.sensors)}")

    def _reset_pending(self) -> None:
        self._alpha_pending: list[torch.Tensor] = []  # blocks to re-evaluate entirely (e.g. the net changed)
        self._alpha_changed: list[torch.Tensor] = []  # blocks integrated into: re-evaluate around their drift
        self._mesh_pending: list[torch.Tensor] = []
        self._meshed: set[tuple[int, int, int]] = set()
        self._cleared = False

    def _pixel_features(self, s: int, depth: torch.Tensor, rgb: np.ndarray | None) -> torch.Tensor:
        """5 x H x W features of one frame."""
        net = self.feature_nets[s]
        rgb01 = None
        if net.uses_rgb:
            if rgb is None:
                rgb01 = torch.zeros((1, 3, *depth.shape), device=self.device)
            else:
                rgb01 = torch.from_numpy(rgb).to(self.device).permute(2, 0, 1).unsqueeze(0).float() / 255.0
        return net(depth.view(1, 1, *depth.shape), rgb01)[0]

    def _integrate_sensor(self, s: int, flat: torch.Tensor, tsdf_update: torch.Tensor,
                          feature_update: torch.Tensor) -> None:
        """integrate_into for one sensor's TSDF, weight and features (same running averages), reading
        each pool once, and accumulating each voxel's weighting-net input change into `_drift`."""
        pools = self.grid.pools
        tsdf, weight = pools[f"tsdf{s}"].view(-1), pools[f"weight{s}"].view(-1)
        feature = pools[f"feat{s}"].view(-1, networks.N_FEATURES)
        old_weight = weight[flat].float()
        old_features = feature[flat].float()
        new_features = running_average(old_features, old_weight, feature_update).to(feature.dtype)
        feature[flat] = new_features
        old_tsdf = tsdf[flat]
        new_tsdf = running_average(old_tsdf, old_weight, tsdf_update)
        tsdf[flat] = new_tsdf
        new_weight = torch.clamp(old_weight + 1, max=self.config.w_max)
        weight[flat] = new_weight.to(weight.dtype)
        self._ensure_drift_capacity()
        change = (new_features.float() - old_features).abs_().amax(dim=1)
        change = torch.maximum(change, (torch.tanh(new_weight) - torch.tanh(old_weight)).abs_())
        change = torch.maximum(change, (new_tsdf - old_tsdf).abs_())
        # events that can add a voxel to the observed or surface sets (first observation, TSDF sign
        # change) always refresh alpha around it, whatever the tolerance: a voxel that joins these
        # sets never keeps an alpha it was not evaluated with
        joins = (old_weight == 0) | (torch.signbit(new_tsdf) != torch.signbit(old_tsdf))
        change = torch.where(joins, torch.full_like(change, float("inf")), change)
        self._drift.index_put_((flat,), change, accumulate=True)

    def _ensure_drift_capacity(self) -> None:
        needed = self.grid.capacity * BLOCK_VOXELS
        if self._drift.numel() < needed:
            grown = torch.zeros(needed, device=self.device)
            grown[: self._drift.numel()] = self._drift
            self._drift = grown

    def _refresh_alpha(self) -> None:
        """Re-evaluate alpha wherever a weighting-net input changed within 2 voxels (more than
        `alpha_tolerance`, summed since the voxel's inputs were last used)."""
        if not self._alpha_pending and not self._alpha_changed:
            return
        changed = torch.unique(torch.cat(self._alpha_pending + self._alpha_changed))
        forced = torch.unique(torch.cat(self._alpha_pending)) if self._alpha_pending else changed[:0]
        self._alpha_pending, self._alpha_changed = [], []
        self._ensure_drift_capacity()
        tol = self.config.alpha_tolerance
        drift = self._drift.view(-1, BLOCK_VOXELS)
        if forced.numel():
            drift[forced] = float("inf")
        dirty = drift[changed] > tol  # C x 512
        keep = dirty.any(dim=1)
        changed_dirty, dirty = changed[keep], dirty[keep]
        # neighbour blocks reached by a dirty voxel's 5^3 neighbourhood
        d = dirty.view(-1, BLOCK, BLOCK, BLOCK)
        halo = networks.WEIGHTING_HALO
        lo_x, hi_x = d[:, :halo].flatten(1).any(1), d[:, -halo:].flatten(1).any(1)
        reach = []
        for ox, oy, oz in NEIGHBOUR_OFFSETS.tolist():
            sub = d
            sub = sub[:, :halo] if ox < 0 else sub[:, -halo:] if ox > 0 else sub
            sub = sub[:, :, :halo] if oy < 0 else sub[:, :, -halo:] if oy > 0 else sub
            sub = sub[:, :, :, :halo] if oz < 0 else sub[:, :, :, -halo:] if oz > 0 else sub
            reach.append(sub.flatten(1).any(1))
        del lo_x, hi_x
        reach = torch.stack(reach, dim=1)  # C x 27
        neighbours = self.grid.neighbour_slots(changed_dirty)
        targets = neighbours[reach & (neighbours >= 0)]
        slots = torch.unique(targets)
        if self.config.alpha_voxels != "all":
            self._alpha_observed(slots, tol, surface_only=self.config.alpha_voxels == "surface")
        else:
            self._alpha_blocks(slots)
        # the inputs of these voxels are now the ones alpha was evaluated with
        drift[changed_dirty] = torch.where(dirty, torch.zeros((), device=self.device), drift[changed_dirty])
        self.counters["alpha_blocks"] += int(slots.numel())
        self._mesh_pending.append(changed)  # the TSDF changed here, whatever alpha did
        self._mesh_pending.append(slots)

    def _weighting_inputs(self, batch: torch.Tensor) -> torch.Tensor:
        """B x 12 x 12^3 weighting-net input windows (each block with a 2-voxel halo), float32."""
        n = len(self.config.sensors)
        names = [name for i in range(n) for name in (f"feat{i}", f"weight{i}")]
        halo = networks.WEIGHTING_HALO
        size = BLOCK + 2 * halo
        gathered = [g.float() for g in self.grid.gather(batch, names, -halo, size)]
        x = networks.weighting_input(gathered[0::2], gathered[1::2])  # B x size^3 x 12
        return x

    def _alpha_blocks(self, slots: torch.Tensor) -> None:
        """Alpha on every voxel of the given blocks (dense convolutions on halo-padded windows)."""
        alpha_pool = self.grid.pools["alpha"]
        size = BLOCK + 2 * networks.WEIGHTING_HALO
        for start in range(0, slots.numel(), self.config.alpha_batch_blocks):
            batch = slots[start:start + self.config.alpha_batch_blocks]
            x = self._weighting_inputs(batch)
            x = x.view(len(batch), size, size, size, -1).permute(0, 4, 1, 2, 3).contiguous()
            alpha_pool[batch] = self.weighting_net(x, pad=False).reshape(len(batch), BLOCK_VOXELS)
            self.counters["alpha_voxels"] += int(batch.numel()) * BLOCK_VOXELS

    def _window(self, neighbours: torch.Tensor, name: str, lo: int, size: int) -> torch.Tensor:
        """B x size^3 (x channel shape) of pool `name` around each block (neighbours: B x 27 slots),
        zeros where no block exists."""
        code, index = local_grid(lo, size, self.device)
        voxel_slot = neighbours[:, code]
        pool = self.grid.pools[name]
        flat = voxel_slot.clamp(min=0) * BLOCK_VOXELS + index.unsqueeze(0)
        values = pool.view(-1, *pool.shape[2:])[flat]
        present = (voxel_slot >= 0).view(*voxel_slot.shape, *([1] * (values.dim() - 2)))
        return values * present.to(values.dtype) if values.dtype != torch.bool else values & present

    def _surface_voxels(self, neighbours: torch.Tensor) -> torch.Tensor:
        """B x 512: voxels that are a corner of a cell whose 8 corners are observed and whose
        corner TSDFs (each sensor's, where observed) include values <= 0 and >= 0. Only these
        cells can produce fused triangles, whatever alpha is (the fused value lies between V1 and V2)."""
        size, b = BLOCK + 2, neighbours.shape[0]
        shape = (b, size, size, size)
        lo = hi = observed = None
        for i in range(len(self.config.sensors)):
            tsdf = self._window(neighbours, f"tsdf{i}", -1, size).view(shape)
            seen = (self._window(neighbours, f"weight{i}", -1, size) > 0).view(shape)
            v_lo = torch.where(seen, tsdf, torch.full_like(tsdf, float("inf")))
            v_hi = torch.where(seen, tsdf, torch.full_like(tsdf, float("-inf")))
            lo = v_lo if lo is None else torch.minimum(lo, v_lo)
            hi = v_hi if hi is None else torch.maximum(hi, v_hi)
            observed = seen if observed is None else observed | seen
        cells = (_window_reduce(observed, 2, torch.logical_and) & (_window_reduce(lo, 2, torch.minimum) <= 0)
                 & (_window_reduce(hi, 2, torch.maximum) >= 0))  # B x 9^3 cells
        return _window_reduce(cells, 2, torch.logical_or).reshape(b, BLOCK_VOXELS)

    def _alpha_observed(self, slots: torch.Tensor, tol: float, surface_only: bool = False) -> None:
        """Alpha on the observed voxels of the given blocks within 2 voxels of a changed input
        (with surface_only: only those `_surface_voxels` marks), as sparse convolutions: gather
        the 3^3 neighbourhoods, one matrix product per layer."""
        grid, halo = self.grid, networks.WEIGHTING_HALO
        size, inner = BLOCK + 2 * halo, BLOCK + 2  # input window 12^3, hidden window 10^3
        net = self.weighting_net
        w1 = net.conv1.weight.permute(2, 3, 4, 1, 0).reshape(-1, net.conv1.out_channels)  # 27*12 x 32
        w2 = net.conv2.weight.permute(2, 3, 4, 1, 0).reshape(-1, net.conv2.out_channels)  # 27*32 x 16
        w3 = net.conv3.weight.reshape(net.conv3.out_channels, -1).T  # 16 x 1
        r3 = torch.arange(3, device=self.device)
        off_in = (r3.view(3, 1, 1) * size * size + r3.view(1, 3, 1) * size + r3.view(1, 1, 3)).reshape(-1)
        off_hid = (r3.view(3, 1, 1) * inner * inner + r3.view(1, 3, 1) * inner + r3.view(1, 1, 3)).reshape(-1)
        code, index = local_grid(-halo, size, self.device)
        n = len(self.config.sensors)
        alpha_flat = grid.pools["alpha"].view(-1)
        chunk = 32768
        for start in range(0, slots.numel(), self.config.alpha_batch_blocks):
            batch = slots[start:start + self.config.alpha_batch_blocks]
            neighbours = grid.neighbour_slots(batch)
            # targets: observed voxels whose 5^3 receptive field holds a changed input
            window = neighbours[:, code]
            dirty = (self._drift[window.clamp(min=0) * BLOCK_VOXELS + index.unsqueeze(0)] > tol) & (window >= 0)
            near = _window_reduce(dirty.view(-1, size, size, size), 2 * halo + 1, torch.logical_or)
            target = near.reshape(-1, BLOCK_VOXELS)
            observed = grid.pools["weight0"][batch] > 0
            for i in range(1, n):
                observed |= grid.pools[f"weight{i}"][batch] > 0
            target &= observed
            if surface_only:
                has = target.any(dim=1)
                batch, neighbours, target = batch[has], neighbours[has], target[has]
                if batch.numel():
                    target &= self._surface_voxels(neighbours)
            count = target.sum(dim=1)
            dense = count >= _DENSE_ALPHA_TARGETS  # cheaper as one dense block evaluation (exact too)
            if bool(dense.any()):
                self._alpha_blocks(batch[dense])
            has = (count > 0) & ~dense
            batch, neighbours, target = batch[has], neighbours[has], target[has]
            b = batch.numel()
            if b == 0:
                continue
            # weighting-net inputs of the 12^3 windows: B*12^3 x 12
            parts = []
            for i in range(n):
                parts.append(self._window(neighbours, f"feat{i}", -halo, size).float())
                parts.append(torch.tanh(self._window(neighbours, f"weight{i}", -halo, size).float()).unsqueeze(-1))
            x = torch.cat(parts, dim=-1).reshape(b * size ** 3, -1)
            # hidden-layer positions the targets read: their 3^3 neighbourhoods in the 10^3 window
            t_pad = F.pad(target.view(b, BLOCK, BLOCK, BLOCK), (2, 2, 2, 2, 2, 2))
            hidden_needed = _window_reduce(t_pad, 3, torch.logical_or).reshape(b, -1)  # B x 10^3
            hb, hp = torch.nonzero(hidden_needed, as_tuple=True)
            hx, hy, hz = hp // (inner * inner), (hp // inner) % inner, hp % inner
            base = hb * size ** 3 + hx * size * size + hy * size + hz
            hidden = torch.zeros((b * inner ** 3, w1.shape[1]), device=self.device)
            hidden_rows = hb * inner ** 3 + hp
            for c0 in range(0, base.numel(), chunk):
                rows = base[c0:c0 + chunk]
                patches = x[(rows.unsqueeze(1) + off_in.unsqueeze(0)).view(-1)].view(rows.numel(), -1)
                hidden[hidden_rows[c0:c0 + chunk]] = torch.relu_(torch.addmm(net.conv1.bias, patches, w1))
            tb, tp = torch.nonzero(target, as_tuple=True)
            tx, ty, tz = tp // (BLOCK * BLOCK), (tp // BLOCK) % BLOCK, tp % BLOCK
            tbase = tb * inner ** 3 + tx * inner * inner + ty * inner + tz
            out = torch.empty(tbase.numel(), device=self.device)
            for c0 in range(0, tbase.numel(), chunk):
                rows = tbase[c0:c0 + chunk]
                patches = hidden[(rows.unsqueeze(1) + off_hid.unsqueeze(0)).view(-1)].view(rows.numel(), -1)
                h2 = torch.relu_(torch.addmm(net.conv2.bias, patches, w2))
                out[c0:c0 + chunk] = torch.sigmoid_(torch.addmm(net.conv3.bias, h2, w3)).squeeze(1)
            alpha_flat[batch[tb] * BLOCK_VOXELS + tp] = out
            self.counters["alpha_voxels"] += int(tbase.numel())

    def _take_mesh_pending(self) -> torch.Tensor:
        if not self._mesh_pending:
            return torch.zeros(0, dtype=torch.int64, device=self.device)
        changed = torch.unique(torch.cat(self._mesh_pending))
        self._mesh_pending = []
        return self.grid.dilate(changed, _MESH_READERS)

    def _channels(self, which: str) -> list[str]:
        """The channels `_values` reads for `which`."""
        if which == FUSED:
            return ["tsdf0", "weight0", "tsdf1", "weight1", "alpha"]
        if which == TSDF_FUSION:
            return ["tsdf_base", "weight_base"]
        s = self._sensor_index(which)
        return [f"tsdf{s}", f"weight{s}"]

    def _whole_blocks(self, slots: torch.Tensor, names: list[str]) -> dict[str, torch.Tensor]:
        return {name: self.grid.pools[name][slots] for name in names}

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

    def _mesh_batch(self, slots: torch.Tensor, which: str, filtered: bool):
        names = self._channels(which)
        gathered = dict(zip(names, self.grid.gather(slots, names, 0, BLOCK + 1)))
        tsdf, observed = self._values(gathered, which, filtered)
        n = BLOCK + 1
        shape = (len(slots), n, n, n)
        extra = gathered["alpha"].reshape(shape).cpu().numpy() if which == FUSED else None
        return marching_cubes_blocks(tsdf.reshape(shape).cpu().numpy(), observed.reshape(shape).cpu().numpy(),
                                     (self.grid.coords[slots] * BLOCK).cpu().numpy(), extra)
