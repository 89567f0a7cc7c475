"""The paper's evaluation on simulated held-out scenes: the results table, the asynchronous test
and the comparison figure (`senfunet evaluate`).

For each scene the engine integrates the same frames once; the five methods are read from it:
  - `tof`, `stereo`: each sensor's own TSDF grid V_i (the paper's single-sensor rows),
  - `tsdf_fusion`: both sensors integrated into one grid (the classic baseline),
  - `senfunet_nofilter`: the fused grid without the outlier filter,
  - `senfunet`: the fused grid with the learned outlier filter.
Grid metrics (MSE, MAD, IoU, Acc) are computed on each method's own observed voxels against the
GT TSDF (truncated at +-band/2). Mesh metrics (F, P, R, tau = 0.02 m) compare each method's
mesh vertices with the GT mesh vertices, the GT mesh cropped to the surface the trajectory
observed: a GT vertex is kept when its nearest voxel was observed by at least one sensor. The
crop is the same for every method, so a method that drops true surface still loses recall.
"""
from __future__ import annotations

import functools
import math
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any
from pathlib import Path

import numpy as np
import torch

from ..grid import BLOCK, BLOCK_VOXELS, block_keys, within_key_range
from ..metrics import grid_metrics, mesh_metrics
from ..networks import N_FEATURE_CHANNELS
from ..readout import voxel_values

METHODS = ("tof", "stereo", "tsdf_fusion", "senfunet_nofilter", "senfunet")
METHOD_LABELS = {
    "tof": "ToF only",
    "stereo": "Stereo only",
    "tsdf_fusion": "TSDF Fusion (both sensors)",
    "senfunet_nofilter": "SenFuNet w/o outlier filter",
    "senfunet": "SenFuNet",
}
ASYNC_METHODS = ("tof", "stereo", "tsdf_fusion", "senfunet")
COLUMNS = ["MSE", "MAD", "IoU", "Acc", "F", "P", "R"]
GRID_COLUMNS = ("MSE", "MAD", "IoU", "Acc")
TAU_M = 0.02
# Validation rooms: every choice (training recipes, checkpoints, which weights ship) is made on these
# (the training configs' val_scenes). Held-out rooms: never trained or validated on, scored once at the
# end. Seeds 1001-1006 and 4001-4008, the earlier held-out sets, steered earlier work and are retired.
VALIDATION_SEEDS = (900, 901, 902, 903, 904, 905)
HELD_OUT_SEEDS = (6001, 6002, 6003, 6004, 6005, 6006, 6007, 6008)
SEED_SETS = {"validation": VALIDATION_SEEDS, "held-out": HELD_OUT_SEEDS}
# ablation rows (the networks changed, everything else as the main SenFuNet row)
ABLATION_LABELS = {
    "abl_features_seeded": "SenFuNet, feature nets at their seeded initialisation",
    "abl_features_zeroed": "SenFuNet, learned feature channels zeroed",
    "abl_other_paper": "SenFuNet paper-exact model (G without TSDF input, 12 inputs)",
    "abl_other_default": "SenFuNet default model (G with TSDF input, 14 inputs)",
}


def observed_gt_vertices(engine, gt_vertices: np.ndarray) -> np.ndarray:
    """GT mesh vertices whose nearest voxel was observed by any sensor (a sensor's weight > 0; the same
    voxels as the TSDF Fusion baseline's weight > 0, which an engine without the baseline lacks). A
    vertex that is NaN or inf, or beyond the map's reach (`grid.within_key_range`), was not observed."""
    v = np.asarray(gt_vertices, np.float64).reshape(-1, 3)
    v = v[np.isfinite(v).all(axis=1)]
    nearest = np.round(v / engine.config.voxel_size_m)  # float: a far vertex's would not fit in int64
    reachable = within_key_range(np.floor(nearest / BLOCK))
    v, nearest = v[reachable], nearest[reachable]
    if len(v) == 0:
        return v.astype(np.float32)
    grid = engine.grid
    vox = torch.from_numpy(nearest.astype(np.int64))
    blocks = torch.div(vox, BLOCK, rounding_mode="floor")
    local = vox - blocks * BLOCK
    slots = grid.lookup(blocks)
    flat = slots.clamp(min=0) * BLOCK_VOXELS + local[:, 0] * 64 + local[:, 1] * 8 + local[:, 2]
    flat = flat.to(grid.device)
    observed = torch.zeros(len(flat), dtype=torch.bool)
    for i in range(len(engine.config.sensors)):
        observed |= (grid.pools[f"weight{i}"].reshape(-1)[flat] > 0).cpu()
    keep = ((slots >= 0) & observed).numpy()
    if grid.spill is not None and len(grid.spill):  # under a map bound: the blocks it evicted were observed too
        away = np.flatnonzero((slots < 0).numpy())
        keep[away] = _observed_on_disk(grid, blocks[away].numpy(), local[away].numpy(), len(engine.config.sensors))
    return v[keep].astype(np.float32)


def _observed_on_disk(grid, blocks: np.ndarray, local: np.ndarray, n_sensors: int,
                      chunk_blocks: int = 1024) -> np.ndarray:
    """Per voxel (its block's key and place in it) outside the blocks in memory: whether a sensor observed it
    in the block the map bound spilled to disk (read there, in chunks of blocks, and left there)."""
    keys = block_keys(torch.from_numpy(blocks)).numpy()
    unique, inverse = np.unique(keys, return_inverse=True)
    in_voxel = local[:, 0] * 64 + local[:, 1] * 8 + local[:, 2]
    observed_voxels = np.zeros((len(unique), BLOCK_VOXELS), bool)
    weights = [list(grid.pools).index(f"weight{i}") for i in range(n_sensors)]  # the spill reads every channel
    for start in range(0, len(unique), chunk_blocks):
        part = unique[start:start + chunk_blocks]
        rows = [np.empty((len(part), *pool.shape[1:]), pool.numpy().dtype) for pool in grid.pools.values()]
        found = grid.spill.peek(part, rows)
        for channel in weights:
            observed_voxels[start:start + len(part)] |= (rows[channel] > 0) & found[:, None]
    return observed_voxels[inverse.reshape(-1), in_voxel]


def _which(method: str) -> tuple[str, bool]:
    if method == "senfunet":
        return "fused", True
    if method == "senfunet_nofilter":
        return "fused", False
    return method, True


class GridTruth:
    """The GT TSDF at every voxel of an engine's blocks, computed once (per block, with the scene's
    primitives culled) and looked up for any method's observed voxel centres."""

    def __init__(self, engine, scene, band_m: float) -> None:
        from .simulator import gt_tsdf_blocks

        self.engine = engine
        self.n_blocks = engine.grid.n_blocks
        coords = engine.grid.coords[: self.n_blocks].numpy()
        self.values = gt_tsdf_blocks(scene, coords, engine.config.voxel_size_m, band_m, BLOCK).reshape(-1)
        self.band_m = band_m

    def for_engine(self, engine, scene) -> GridTruth:
        """This truth for another engine that integrated the same frames: shared when its blocks sit in
        the same slots (the block layout does not depend on the networks), else computed afresh."""
        coords = engine.grid.coords[: engine.grid.n_blocks]
        if engine.grid.n_blocks != self.n_blocks or not torch.equal(coords, self.engine.grid.coords[: self.n_blocks]):
            return GridTruth(engine, scene, self.band_m)
        other = object.__new__(GridTruth)
        other.__dict__.update(self.__dict__, engine=engine)
        return other

    def at(self, centres_m: np.ndarray) -> np.ndarray:
        if len(centres_m) == 0:
            return np.zeros(0, np.float32)
        vox = torch.from_numpy(np.round(np.asarray(centres_m, np.float64) / self.engine.config.voxel_size_m)
                               .astype(np.int64))
        blocks = torch.div(vox, BLOCK, rounding_mode="floor")
        local = vox - blocks * BLOCK
        slots = self.engine.grid.lookup(blocks)
        if bool((slots < 0).any()) or bool((slots >= self.n_blocks).any()):
            raise RuntimeError("voxel outside the blocks the ground truth was computed for")
        flat = slots * BLOCK_VOXELS + local[:, 0] * 64 + local[:, 1] * 8 + local[:, 2]
        return self.values[flat.numpy()]


def _voxel_keys(centres_m: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """One int64 per voxel centre (21 bits per axis)."""
    v = np.round(np.asarray(centres_m, np.float64) / voxel_size_m).astype(np.int64) + (1 << 20)
    return (v[:, 0] << 42) | (v[:, 1] << 21) | v[:, 2]


def common_grid_metrics(pred_tsdf_m: np.ndarray, gt_tsdf_m: np.ndarray, band_m: float) -> dict[str, float]:
    """Grid metrics on a common voxel set where a method may have no value (NaN: not observed or
    removed by the outlier filter): such a voxel counts as an error, with the largest error the
    truncation allows (band_m) in MSE and MAD, as wrong in Acc and as a miss of the GT occupancy in
    IoU. `kept` is the share of the set the method has values for."""
    pred = np.asarray(pred_tsdf_m, np.float64).ravel()
    gt = np.asarray(gt_tsdf_m, np.float64).ravel()
    n = pred.size
    if n == 0:
        return {"MSE": math.nan, "MAD": math.nan, "IoU": math.nan, "Acc": math.nan, "kept": math.nan, "n": 0}
    kept = np.isfinite(pred)
    err = np.where(kept, pred - np.where(kept, gt, 0.0), band_m)
    pred_in, gt_in = kept & (pred < 0), gt < 0
    correct = kept & (pred_in == gt_in)
    tn = int(np.count_nonzero(pred_in & gt_in))
    fp = int(np.count_nonzero(~pred_in & gt_in))
    fn = int(np.count_nonzero(~gt_in & (pred_in | ~kept)))
    denom = tn + fp + fn
    return {"MSE": float(np.mean(err * err)), "MAD": float(np.mean(np.abs(err))),
            "IoU": tn / denom if denom else math.nan, "Acc": float(np.mean(correct)),
            "kept": float(np.mean(kept)), "n": n}


def method_metrics(engine, scene, gt_vertices_cropped: np.ndarray, methods=METHODS, band_m: float | None = None,
                   tau_m: float = TAU_M, *, common: bool = False,
                   truth: GridTruth | None = None) -> dict[str, dict[str, float]]:
    """The paper's seven metrics for each method read from an engine that integrated a scene.

    Grid metrics on each method's own observed voxels (the paper's protocol); with common, also
    on the voxels TSDF Fusion observed (`common_grid_metrics`), as "<metric>_common"."""
    band = engine.config.band_m if band_m is None else band_m
    truth = GridTruth(engine, scene, band) if truth is None else truth
    vs = engine.config.voxel_size_m
    if common:
        ref_centres, _ = voxel_values(engine, "tsdf_fusion", filtered=True)
        ref_keys = _voxel_keys(ref_centres, vs)
        order = np.argsort(ref_keys)
        ref_keys, ref_gt = ref_keys[order], truth.at(ref_centres)[order]
    out: dict[str, dict[str, float]] = {}
    for method in methods:
        which, filtered = _which(method)
        centres, tsdf = voxel_values(engine, which, filtered=filtered)
        row = grid_metrics(tsdf, truth.at(centres))
        if common:
            pred = np.full(len(ref_keys), np.nan)
            keys = _voxel_keys(centres, vs)
            at = np.clip(np.searchsorted(ref_keys, keys), 0, max(len(ref_keys) - 1, 0))
            hit = (ref_keys[at] == keys) if len(ref_keys) else np.zeros(len(keys), bool)
            pred[at[hit]] = tsdf[hit]
            row.update({f"{k}_common": v for k, v in common_grid_metrics(pred, ref_gt, band).items()})
        mesh = engine.extract_mesh(which, filtered=filtered)
        row.update(mesh_metrics(mesh.vertices, gt_vertices_cropped, tau_m))
        out[method] = row
    return out


def integrate_frames(engine, frames, sensor_stride: dict[str, int] | None = None) -> dict[str, int]:
    """Integrate frames in stamp order (every k-th frame of a sensor with sensor_stride); counts per sensor."""
    counts: dict[str, int] = {}
    seen: dict[str, int] = {}
    for frame in frames:
        i = seen.get(frame.sensor, 0)
        seen[frame.sensor] = i + 1
        if sensor_stride and i % sensor_stride.get(frame.sensor, 1):
            continue
        engine.integrate(frame.sensor, frame.depth_m, frame.K, frame.T_world_camera, rgb=frame.rgb)
        counts[frame.sensor] = counts.get(frame.sensor, 0) + 1
    return counts


def mean_rows(per_scene: list[dict[str, dict[str, float]]]) -> dict[str, dict[str, float]]:
    """Average each method's metrics over scenes (NaNs ignored)."""
    rows: dict[str, dict[str, float]] = {}
    for method in per_scene[0]:
        if method == "frames":
            rows[method] = {k: float(np.mean([s[method][k] for s in per_scene])) for k in per_scene[0][method]}
            continue
        rows[method] = {}
        for col in per_scene[0][method]:
            vals = [s[method][col] for s in per_scene if not math.isnan(float(s[method][col]))]
            rows[method][col] = float(np.mean(vals)) if vals else math.nan
    return rows


def labelled(rows: dict[str, dict[str, float]]) -> dict[str, dict[str, float]]:
    return {METHOD_LABELS.get(k, ABLATION_LABELS.get(k, k)): v for k, v in rows.items()}


def bar_check(rows: dict[str, dict[str, float]]) -> dict[str, bool]:
    """Issue 3's bar on the averaged table."""
    f = {m: rows[m]["F"] for m in rows}
    best_single = max(f["tof"], f["stereo"])
    return {
        "F >= TSDF Fusion + 10": f["senfunet"] >= f["tsdf_fusion"] + 10,
        "F >= best single sensor + 3": f["senfunet"] >= best_single + 3,
        "MAD < TSDF Fusion": rows["senfunet"]["MAD"] < rows["tsdf_fusion"]["MAD"],
    }


# --------------------------------------------------------------------------------------------
# Cached simulation
# --------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def simulator_version() -> str:
    """Short hash of what the simulator produces on a small probe: cached datasets are keyed by it.

    The probe (a scene description, one short two-sensor recording at a small resolution, GT TSDF
    and GT mesh samples) changes whenever the simulator's output does, and only then: moving or
    refactoring its code keeps the cache valid."""
    import hashlib

    from . import simulator
    from .scenes import _scene_to_json

    digest = hashlib.sha1()
    scene = simulator.make_scene(7)
    digest.update(_scene_to_json(scene).encode())
    seq = simulator.simulate_sequence(scene, 7, duration_s=0.15, tof_rate_hz=20.0, stereo_rate_hz=20.0,
                                      pose_rate_hz=50.0, width=96, height=48)
    for frame in seq.frames:
        digest.update(np.ascontiguousarray(frame.depth_m).tobytes())
        digest.update(np.ascontiguousarray(frame.T_world_camera).tobytes())
        if frame.rgb is not None:
            digest.update(np.ascontiguousarray(frame.rgb).tobytes())
    for sensor in simulator.SENSORS:
        digest.update(np.ascontiguousarray(seq.pose_T_world_camera[sensor]).tobytes())
    digest.update(simulator.gt_tsdf_blocks(scene, np.array([[0, 0, 0], [10, 12, 5]]), 0.01, 0.1).tobytes())
    digest.update(np.ascontiguousarray(simulator.gt_mesh(scene, 0.1).vertices).tobytes())
    return digest.hexdigest()[:10]


def cached_sequence(seed: int, *, duration_s: float, tof_rate_hz: float, stereo_rate_hz: float,
                    cache_dir: str | Path | None, log=print, room_size_m: tuple | None = None,
                    image_size: tuple[int, int] = (256, 256)):
    """simulate_sequence(make_scene(seed), seed, ...), stored under cache_dir and reloaded from there."""
    from . import simulator

    if cache_dir is not None:
        name = f"{simulator_version()}_s{seed}_d{duration_s:g}_t{tof_rate_hz:g}_st{stereo_rate_hz:g}"
        if room_size_m is not None or tuple(image_size) != (256, 256):
            name += f"_r{'x'.join(f'{v:g}' for v in room_size_m or ())}_i{image_size[0]}x{image_size[1]}"
        folder = Path(cache_dir).expanduser() / "sim" / name
        if (folder / "done").is_file():
            return simulator.load_dataset(folder)
    t0 = time.perf_counter()
    seq = simulator.simulate_sequence(simulator.make_scene(seed, room_size_m=room_size_m), seed, duration_s=duration_s,
                                      tof_rate_hz=tof_rate_hz, stereo_rate_hz=stereo_rate_hz,
                                      width=image_size[0], height=image_size[1])
    if log:
        log(f"simulated scene {seed}: {len(seq.frames)} frames in {time.perf_counter() - t0:.1f} s")
    if cache_dir is not None:
        simulator.write_dataset(seq, folder)
        (folder / "done").write_text("ok\n")
    return seq


def cached_gt_mesh_vertices(scene, voxel_size_m: float, cache_dir: str | Path | None) -> np.ndarray:
    from . import simulator

    if cache_dir is not None:
        path = Path(cache_dir).expanduser() / "gt" / f"{simulator_version()}_s{scene.seed}_v{voxel_size_m:g}.npy"
        if path.is_file():
            return np.load(path)
    vertices = simulator.gt_mesh(scene, voxel_size_m).vertices
    if cache_dir is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, vertices)
    return vertices


# --------------------------------------------------------------------------------------------
# The whole evaluation
# --------------------------------------------------------------------------------------------
@dataclass
class EvaluationConfig:
    seeds: tuple[int, ...] = VALIDATION_SEEDS
    duration_s: float = 3.0
    tof_rate_hz: float = 15.0
    stereo_rate_hz: float = 20.0
    frame_stride: int = 3  # integrate every k-th frame of each sensor (the paper validates on every 10th)
    async_tof_divisors: tuple[int, ...] = (2, 3)  # ToF at 1/2 and 1/3 of the stereo rate
    cache_dir: str | None = "~/.cache/senfunet"
    figure_scene: int = 0  # index into seeds
    room_size_m: tuple[float, float, float] | None = None  # None: each seed's random room (tests: a small one)
    image_size: tuple[int, int] = (256, 256)
    ablations: bool = False  # also the networks' ablation rows (ABLATION_LABELS)
    seed_set: str = "validation"  # what the seeds are, for the report: "validation", "held-out" or "custom"


@dataclass
class EvaluationResult:
    rows: dict[str, dict[str, float]]
    per_scene: list[dict[str, dict[str, float]]]
    async_rows: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)
    frames_used: list[dict[str, int]] = field(default_factory=list)
    seconds: float = 0.0
    weights_source: str = ""
    other_weights_source: str = ""  # the other shipped model in the ablation rows ("" when none ran)


def _engine(weights):
    from ..engine import EngineConfig, SenFuNet

    return SenFuNet(EngineConfig(), weights=weights)


class ZeroFeatureNet(torch.nn.Module):
    """A feature net whose learned channels are all 0 (the raw depth is still appended)."""

    def __init__(self, uses_rgb: bool) -> None:
        super().__init__()
        self.uses_rgb = uses_rgb

    def forward(self, depth_m: torch.Tensor, rgb01: torch.Tensor | None = None) -> torch.Tensor:
        zeros = torch.zeros_like(depth_m).expand(-1, N_FEATURE_CHANNELS, -1, -1)
        return torch.cat([zeros, depth_m], dim=1)


def _ablation_engines(weights) -> dict[str, Callable[[], Any] | None]:
    """Ablation name -> a function making its engine (None: the same as the main row): the same
    weights with the feature nets at their seeded initialisation or with zeroed learned channels,
    and the other shipped model."""
    from .. import networks

    path = networks.resolve_weights(weights)
    if path is None:
        return {}
    state = torch.load(path, map_location="cpu", weights_only=True)
    init_seed = int(state.get("meta", {}).get("config", {}).get("init_seed", 0))

    def seeded():
        engine = _engine(path)
        seeded_nets, _ = networks.make_networks(engine.config.sensor_uses_rgb, init_seed)
        engine.feature_nets.load_state_dict(seeded_nets.state_dict())
        return engine

    def zeroed():
        engine = _engine(path)
        engine.feature_nets = torch.nn.ModuleList(ZeroFeatureNet(net.uses_rgb) for net in engine.feature_nets)
        return engine

    seeded_nets, _ = networks.make_networks(tuple(state.get("sensor_uses_rgb", (False, True))), init_seed)
    untrained = all(torch.equal(a, b) for net, saved in zip(seeded_nets, state["feature_nets"])
                    for a, b in zip(net.state_dict().values(), saved.values()))
    # feature nets that were never trained: the seeded row is the main row (no second run needed)
    makers = {"abl_features_seeded": None if untrained else seeded, "abl_features_zeroed": zeroed}
    other = "paper" if networks.weights_tsdf_input(path) else "default"
    other_path = networks.NAMED_WEIGHTS[other]
    if other_path.is_file() and other_path.resolve() != path.resolve():
        makers[f"abl_other_{other}"] = lambda: _engine(other_path)
    return makers


def _scene_rows(weights, seq, gt_vertices: np.ndarray, config: EvaluationConfig, figure_path, log) -> tuple:
    """One scene: the methods' rows (and ablation rows), frames used, the engine's weights source."""
    stride = {"tof": config.frame_stride, "stereo": config.frame_stride}
    engine = _engine(weights)
    used = integrate_frames(engine, seq.frames, stride)
    gt_crop = observed_gt_vertices(engine, gt_vertices)
    rows = method_metrics(engine, seq.scene, gt_crop, common=True)
    if figure_path is not None:
        write_figure(engine, figure_path, seq.scene)
    source = engine.weights_source
    del engine
    for name, make in (_ablation_engines(weights).items() if config.ablations else ()):
        if make is None:
            rows[name] = dict(rows["senfunet"])
            continue
        engine = make()
        integrate_frames(engine, seq.frames, stride)
        rows[name] = method_metrics(engine, seq.scene, gt_crop, methods=("senfunet",), common=True)["senfunet"]
        if name.startswith("abl_other"):
            rows[name]["source"] = engine.weights_source
        del engine
    if log:
        r = rows
        log(f"scene {seq.scene.seed}: F tof {r['tof']['F']:.1f} stereo {r['stereo']['F']:.1f} "
            f"tsdf {r['tsdf_fusion']['F']:.1f} senfunet {r['senfunet']['F']:.1f} "
            f"(no filter {r['senfunet_nofilter']['F']:.1f})"
            + "".join(f"; {k[4:]} {v['F']:.1f}" for k, v in r.items() if k.startswith("abl_")))
    return rows, used, source


def _async_rows(weights, seq, gt_vertices: np.ndarray, config: EvaluationConfig, divisor: int) -> dict:
    """ToF at 1/divisor of the stereo rate: every (stride * rate_ratio)-th ToF frame."""
    tof_stride = max(1, round(config.frame_stride * divisor * config.tof_rate_hz / config.stereo_rate_hz))
    engine = _engine(weights)
    used = integrate_frames(engine, seq.frames, {"tof": tof_stride, "stereo": config.frame_stride})
    rows = method_metrics(engine, seq.scene, observed_gt_vertices(engine, gt_vertices), methods=ASYNC_METHODS)
    rows["frames"] = {"tof": used.get("tof", 0), "stereo": used.get("stereo", 0)}
    return rows


def evaluate(weights="default", config: EvaluationConfig | None = None, *, figure_path: str | Path | None = None,
             log=print, after_room=None) -> EvaluationResult:
    """Run the table (and ablation rows), the asynchronous test and (optionally) the figure.
    after_room(partial result): called after each room (a long run can report as it goes)."""
    config = config or EvaluationConfig()
    t0 = time.perf_counter()
    per_scene, frames_used = [], []
    async_scenes: dict[str, list] = {f"1/{d}": [] for d in config.async_tof_divisors}
    weights_source = other = ""
    for index, seed in enumerate(config.seeds):
        seq = cached_sequence(seed, duration_s=config.duration_s, tof_rate_hz=config.tof_rate_hz,
                              stereo_rate_hz=config.stereo_rate_hz, cache_dir=config.cache_dir, log=log,
                              room_size_m=config.room_size_m, image_size=config.image_size)
        gt_vertices = cached_gt_mesh_vertices(seq.scene, 0.01, config.cache_dir)
        figure = figure_path if index == config.figure_scene else None
        rows, used, weights_source = _scene_rows(weights, seq, gt_vertices, config, figure, log)
        per_scene.append(rows)
        frames_used.append(used)
        for d in config.async_tof_divisors:
            async_scenes[f"1/{d}"].append(_async_rows(weights, seq, gt_vertices, config, d))
        other = next((r[k].pop("source") for r in per_scene for k in r if "source" in r[k]), other)
        if after_room is not None:
            after_room(EvaluationResult(mean_rows(per_scene), list(per_scene),
                                        {k: mean_rows(v) for k, v in async_scenes.items() if v}, list(frames_used),
                                        time.perf_counter() - t0, weights_source, other))
    return EvaluationResult(mean_rows(per_scene), per_scene, {k: mean_rows(v) for k, v in async_scenes.items() if v},
                            frames_used, time.perf_counter() - t0, weights_source, other)


@dataclass
class SeedRun:
    """One training seed's weights file: what the seed-spread table says about it."""
    path: Path
    sha256: str
    seed: int | None  # the training config's seed (None when the file does not record it)
    shipped: bool  # the file is the shipped default (senfunet_core/weights/tof_stereo.pt)
    record_val_F: float | None = None  # the mean validation F its training recorded (validation rooms only)


@dataclass
class SeedSpreadResult:
    runs: list[SeedRun]
    # per room: "tof", "stereo", "tsdf_fusion" rows (the same for every weights file) and "senfunet": one row per run
    per_scene: list[dict[str, Any]]
    seconds: float = 0.0


def describe_seed_run(path: Path, val_seeds: tuple[int, ...]) -> SeedRun:
    """A weights file's sha256, training seed and (when it was validated on val_seeds) recorded validation F."""
    import hashlib

    from .. import networks

    state = torch.load(path, map_location="cpu", weights_only=True)
    meta = state.get("meta", {})
    # a file made by starting from a checkpoint (--init-weights) records its seed in the starting point's config
    chain = [meta, *([meta["init"]["meta"]] if (meta.get("init") or {}).get("meta") else [])]
    seed = next((int(m["config"]["seed"]) for m in chain if "seed" in m.get("config", {})), None)
    recorded = None
    if list(meta.get("val_scenes", [])) == list(val_seeds) and "val_F" in meta:
        recorded = float(meta["val_F"])
    shipped = networks.DEFAULT_WEIGHTS.is_file() and path.resolve() == networks.DEFAULT_WEIGHTS.resolve()
    return SeedRun(path, hashlib.sha256(path.read_bytes()).hexdigest(), seed, shipped, recorded)


def seed_spread(weights: list[str | Path], config: EvaluationConfig, *, log=print,
                after_room: Callable[[SeedSpreadResult], None] | None = None) -> SeedSpreadResult:
    """The SenFuNet row of several weights files (the same recipe trained with different seeds) on the
    same rooms, with the single-sensor and TSDF Fusion rows once per room: those do not depend on the
    networks, and neither does the observed GT crop."""
    from .. import networks
    from ..errors import InputError

    paths = []
    for w in weights:
        path = networks.resolve_weights(w)
        if path is None:
            raise InputError("the seed spread compares trained weights files; 'none' is not one")
        paths.append(path)
    runs = [describe_seed_run(p, tuple(config.seeds)) for p in paths]
    stride = {"tof": config.frame_stride, "stereo": config.frame_stride}
    t0 = time.perf_counter()
    per_scene: list[dict[str, Any]] = []
    for seed in config.seeds:
        seq = cached_sequence(seed, duration_s=config.duration_s, tof_rate_hz=config.tof_rate_hz,
                              stereo_rate_hz=config.stereo_rate_hz, cache_dir=config.cache_dir, log=log,
                              room_size_m=config.room_size_m, image_size=config.image_size)
        gt_vertices = cached_gt_mesh_vertices(seq.scene, 0.01, config.cache_dir)
        room: dict[str, Any] = {}
        senfunet_rows = []
        crop: np.ndarray | None = None
        truth: GridTruth | None = None
        for path in paths:
            engine = _engine(path)
            integrate_frames(engine, seq.frames, stride)
            if crop is None or truth is None:
                crop = observed_gt_vertices(engine, gt_vertices)
                truth = GridTruth(engine, seq.scene, engine.config.band_m)
                rows = method_metrics(engine, seq.scene, crop, methods=("tof", "stereo", "tsdf_fusion", "senfunet"),
                                      truth=truth)
            else:
                truth = truth.for_engine(engine, seq.scene)
                rows = method_metrics(engine, seq.scene, crop, methods=("senfunet",), truth=truth)
            senfunet_rows.append(rows.pop("senfunet"))
            room.update(rows)
            del engine
        room["senfunet"] = senfunet_rows
        per_scene.append(room)
        if log:
            log(f"scene {seed}: F tof {room['tof']['F']:.1f} stereo {room['stereo']['F']:.1f} tsdf "
                f"{room['tsdf_fusion']['F']:.1f}; senfunet " + ", ".join(f"{r['F']:.1f}" for r in room["senfunet"]))
        if after_room is not None:
            after_room(SeedSpreadResult(runs, list(per_scene), time.perf_counter() - t0))
    return SeedSpreadResult(runs, per_scene, time.perf_counter() - t0)


def seed_summary(result: SeedSpreadResult) -> list[dict[str, float]]:
    """Per weights file over the rooms: mean and std of F, mean MAD, mean margin over the better single
    sensor and over TSDF Fusion, and in how many rooms F is above the better single sensor."""
    out = []
    for i in range(len(result.runs)):
        f = np.array([room["senfunet"][i]["F"] for room in result.per_scene])
        better = np.array([max(room["tof"]["F"], room["stereo"]["F"]) for room in result.per_scene])
        tsdf = np.array([room["tsdf_fusion"]["F"] for room in result.per_scene])
        out.append({"F": float(f.mean()), "F_std": float(f.std()),
                    "MAD": float(np.mean([room["senfunet"][i]["MAD"] for room in result.per_scene])),
                    "margin": float((f - better).mean()), "min_margin": float((f - better).min()),
                    "over_tsdf": float((f - tsdf).mean()), "rooms_above": int((f > better).sum()),
                    "rooms": len(f)})
    return out


def spread(per_scene: list[dict[str, dict[str, float]]], column: str = "F") -> dict[str, dict[str, float]]:
    """Per method: mean, standard deviation (over rooms), min and max of a metric."""
    out = {}
    for method in per_scene[0]:
        if method == "frames":
            continue
        values = np.array([s[method][column] for s in per_scene if method in s], np.float64)
        out[method] = {"mean": float(np.mean(values)), "std": float(np.std(values)), "min": float(np.min(values)),
                       "max": float(np.max(values))}
    return out


def goal_check(per_scene: list[dict[str, dict[str, float]]]) -> dict[str, bool]:
    """Issue 15's goals: in every room the fused F above the better single sensor; the mean F at
    least 15 points above TSDF Fusion."""
    margins = [s["senfunet"]["F"] - max(s["tof"]["F"], s["stereo"]["F"]) for s in per_scene]
    gain = float(np.mean([s["senfunet"]["F"] - s["tsdf_fusion"]["F"] for s in per_scene]))
    return {f"F > better single sensor in every room ({sum(m > 0 for m in margins)} of {len(margins)})":
            all(m > 0 for m in margins),
            f"mean F >= TSDF Fusion + 15 (+{gain:.2f})": gain >= 15}


def _display_crop(mesh, lo: np.ndarray, hi: np.ndarray, keep_colors: bool):
    """Faces whose vertices all lie inside [lo, hi] (for the figure), unused vertices dropped."""
    from ..mesher import Mesh

    v = np.asarray(mesh.vertices)
    inside = np.all((v >= lo) & (v <= hi), axis=1)
    faces = mesh.faces[inside[mesh.faces].all(axis=1)] if len(mesh.faces) else mesh.faces
    used = np.unique(faces)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    colors = mesh.colors[used] if keep_colors and mesh.colors is not None else None
    return Mesh(v[used].astype(np.float32), remap[faces].astype(np.int32), colors)


def write_figure(engine, path: str | Path, scene=None) -> None:
    """ToF, stereo, TSDF Fusion and SenFuNet meshes, and SenFuNet coloured by alpha, side by side.

    For display only, the meshes are cropped to the room (0.5 m margin around the walls) with the
    ceiling removed, so the camera looks into the room; the same crop for every panel.
    """
    from ..render import render_mesh_png

    meshes = [engine.extract_mesh("tof"), engine.extract_mesh("stereo"), engine.extract_mesh("tsdf_fusion"),
              engine.extract_mesh("fused"), engine.extract_mesh("fused")]
    if scene is not None:
        room = np.asarray(scene.room_size_m, np.float64)
        lo = np.array([-0.5, -0.5, -0.5])
        hi = np.array([room[0] + 0.5, room[1] + 0.5, room[2] - 0.25])
    else:
        lo, hi = np.full(3, -np.inf), np.full(3, np.inf)
    meshes = [_display_crop(m, lo, hi, keep_colors=(i == 4)) for i, m in enumerate(meshes)]
    titles = ["ToF", "Stereo", "TSDF Fusion", "SenFuNet", "Weighting: amber = ToF, blue = stereo"]
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    render_mesh_png(meshes, path, titles=titles, width_px=2000, height_px=440, view=(-60.0, 60.0))


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo, else what platform knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_description() -> str:
    import os

    cpu = cpu_model()
    return (f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, torch {torch.__version__} "
            f"(CPU, {torch.get_num_threads()} threads)")
