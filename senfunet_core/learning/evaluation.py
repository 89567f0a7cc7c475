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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..grid import BLOCK, BLOCK_VOXELS
from ..metrics import format_table, grid_metrics, mesh_metrics

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
TAU_M = 0.02
HELD_OUT_SEEDS = (1001, 1002, 1003, 1004, 1005, 1006)  # never used for training (training uses < 1000)


def observed_gt_vertices(engine, gt_vertices: np.ndarray) -> np.ndarray:
    """GT mesh vertices whose nearest voxel was observed by any sensor (weight_base > 0)."""
    v = np.asarray(gt_vertices, np.float64).reshape(-1, 3)
    if len(v) == 0:
        return v.astype(np.float32)
    grid = engine.grid
    vox = torch.from_numpy(np.round(v / engine.config.voxel_size_m).astype(np.int64))
    blocks = torch.div(vox, BLOCK, rounding_mode="floor")
    local = vox - blocks * BLOCK
    slots = grid.lookup(blocks)
    flat = slots.clamp(min=0) * BLOCK_VOXELS + local[:, 0] * 64 + local[:, 1] * 8 + local[:, 2]
    weight = grid.pools["weight_base"].reshape(-1)[flat.to(grid.device)].cpu()
    keep = (slots >= 0) & (weight > 0)
    return v[keep.numpy()].astype(np.float32)


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


def method_metrics(engine, scene, gt_vertices_cropped: np.ndarray, methods=METHODS, band_m: float | None = None,
                   tau_m: float = TAU_M) -> dict[str, dict[str, float]]:
    """The paper's seven metrics for each method read from an engine that integrated a scene."""
    band = engine.config.band_m if band_m is None else band_m
    truth = GridTruth(engine, scene, band)
    out: dict[str, dict[str, float]] = {}
    for method in methods:
        which, filtered = _which(method)
        centres, tsdf = engine.voxel_values(which, filtered=filtered)
        row = grid_metrics(tsdf, truth.at(centres))
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
    return {METHOD_LABELS.get(k, k): v for k, v in rows.items()}


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
    seeds: tuple[int, ...] = HELD_OUT_SEEDS[:3]
    duration_s: float = 3.0
    tof_rate_hz: float = 15.0
    stereo_rate_hz: float = 20.0
    frame_stride: int = 3  # integrate every k-th frame of each sensor (the paper validates on every 10th)
    async_tof_divisors: tuple[int, ...] = (2, 3)  # ToF at 1/2 and 1/3 of the stereo rate
    cache_dir: str | None = "~/.cache/senfunet"
    figure_scene: int = 0  # index into seeds
    room_size_m: tuple[float, float, float] | None = None  # None: each seed's random room (tests: a small one)
    image_size: tuple[int, int] = (256, 256)


@dataclass
class EvaluationResult:
    rows: dict[str, dict[str, float]]
    per_scene: list[dict[str, dict[str, float]]]
    async_rows: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)
    frames_used: list[dict[str, int]] = field(default_factory=list)
    seconds: float = 0.0
    weights_source: str = ""


def _engine(weights):
    from ..engine import EngineConfig, SenFuNet

    return SenFuNet(EngineConfig(), weights=weights)


def evaluate(weights="default", config: EvaluationConfig = EvaluationConfig(), figure_path: str | Path | None = None,
             log=print) -> EvaluationResult:
    """Run the table, the asynchronous test and (optionally) the figure."""
    t0 = time.perf_counter()
    per_scene, frames_used = [], []
    async_scenes: dict[str, list] = {f"1/{d}": [] for d in config.async_tof_divisors}
    weights_source = ""
    for index, seed in enumerate(config.seeds):
        seq = cached_sequence(seed, duration_s=config.duration_s, tof_rate_hz=config.tof_rate_hz,
                              stereo_rate_hz=config.stereo_rate_hz, cache_dir=config.cache_dir, log=log,
                              room_size_m=config.room_size_m, image_size=config.image_size)
        gt_vertices = cached_gt_mesh_vertices(seq.scene, 0.01, config.cache_dir)
        stride = {"tof": config.frame_stride, "stereo": config.frame_stride}
        engine = _engine(weights)
        weights_source = engine.weights_source
        frames_used.append(integrate_frames(engine, seq.frames, stride))
        gt_crop = observed_gt_vertices(engine, gt_vertices)
        per_scene.append(method_metrics(engine, seq.scene, gt_crop))
        if log:
            r = per_scene[-1]
            log(f"scene {seed}: F tof {r['tof']['F']:.1f} stereo {r['stereo']['F']:.1f} tsdf {r['tsdf_fusion']['F']:.1f} "
                f"senfunet {r['senfunet']['F']:.1f} (no filter {r['senfunet_nofilter']['F']:.1f}); MAD cm "
                f"tsdf {100 * r['tsdf_fusion']['MAD']:.2f} senfunet {100 * r['senfunet']['MAD']:.2f}")
        if figure_path is not None and index == config.figure_scene:
            write_figure(engine, figure_path, seq.scene)
        del engine
        for d in config.async_tof_divisors:
            # ToF at 1/d of the stereo rate: keep every (stride * rate_ratio)-th ToF frame
            tof_stride = max(1, round(config.frame_stride * d * config.tof_rate_hz / config.stereo_rate_hz))
            engine = _engine(weights)
            used = integrate_frames(engine, seq.frames, {"tof": tof_stride, "stereo": config.frame_stride})
            rows = method_metrics(engine, seq.scene, observed_gt_vertices(engine, gt_vertices), methods=ASYNC_METHODS)
            rows["frames"] = {"tof": used.get("tof", 0), "stereo": used.get("stereo", 0)}
            async_scenes[f"1/{d}"].append(rows)
            del engine
    result = EvaluationResult(mean_rows(per_scene), per_scene,
                              {k: mean_rows(v) for k, v in async_scenes.items() if v}, frames_used,
                              time.perf_counter() - t0, weights_source)
    return result


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


def results_markdown(result: EvaluationResult, config: EvaluationConfig, command: str, notes: str = "") -> str:
    lines = ["# Results", "",
             f"Generated by `{command}` in {result.seconds:.0f} s on {machine_description()}.", "",
             f"Weights: `{result.weights_source}`. Held-out scenes (seeds never used in training): "
             f"{', '.join(str(s) for s in config.seeds)}; {config.duration_s:g} s each, ToF {config.tof_rate_hz:g} Hz, "
             f"stereo {config.stereo_rate_hz:g} Hz, every {config.frame_stride}. frame of each sensor integrated "
             f"(frames per scene: {', '.join(str(f) for f in result.frames_used)}).", "",
             "## Table (mean over the held-out scenes)", "",
             format_table(labelled(result.rows), COLUMNS)]
    checks = bar_check(result.rows)
    lines += ["Issue 3's bar: " + "; ".join(f"{k}: {'met' if v else 'NOT met'}" for k, v in checks.items()) + ".", ""]
    lines += ["## Per scene", ""]
    for seed, rows in zip(config.seeds, result.per_scene):
        lines += [f"Scene {seed}:", "", format_table(labelled(rows), COLUMNS)]
    if result.async_rows:
        lines += ["## Asynchronous sensors", "",
                  f"Stereo at {config.stereo_rate_hz / config.frame_stride:.3g} Hz effective; ToF at a half and a third of it "
                  "(frames dropped from the same sequences), mean over the same scenes.", ""]
        for name, rows in result.async_rows.items():
            rows = dict(rows)
            frames = rows.pop("frames", {})
            lines += [f"ToF at {name} of the stereo rate (mean frames integrated per scene: ToF "
                      f"{frames.get('tof', float('nan')):.0f}, stereo {frames.get('stereo', float('nan')):.0f}):", "",
                      format_table(labelled(rows), COLUMNS)]
    lines += ["## Protocol", "",
              "- Grid metrics on each method's observed voxels (after the outlier filter for SenFuNet) against "
              "the GT TSDF truncated at +-5 cm; MSE in 1e-4 m^2, MAD in cm.",
              "- Mesh metrics: vertices of the marching-cubes mesh (cells with all 8 corners observed) against the "
              "vertices of the GT mesh (marching cubes of the exact SDF at 1 cm), tau = 2 cm. The GT mesh is "
              "cropped to the observed part of the scene: a GT vertex is kept when its nearest voxel was observed "
              "by at least one sensor. The same crop is used for every method.",
              "- Figure: `docs/figures/evaluation.png` (scene "
              f"{config.seeds[config.figure_scene]}): ToF, stereo, TSDF Fusion, SenFuNet, and SenFuNet coloured "
              "by the sensor weighting alpha (amber: alpha = 1, ToF trusted; blue: alpha = 0, stereo trusted). For display only the meshes are cropped to the room (0.5 m margin) with the ceiling removed.", ""]
    if notes:
        lines += [notes.rstrip(), ""]
    return "\n".join(lines)


# Paper values of the training settings (section 4 and supplementary C), to report deviations.
PAPER_TRAINING = {"chunk_size": 64, "min_update_voxels": 2000, "max_chunk_tries": 600, "lr": 1e-4,
                  "accumulate_frames": 20, "clip_grad_norm": 1.0, "reset_probability": 0.01,
                  "lambda1": 1 / 60, "lambda2": 1 / 600, "eta_m": 0.04}


def training_notes(weights_source: str) -> str:
    """Training provenance and deviations from the paper, read from the weights file's metadata (the
    training config, with its `deviations`: setting or topic -> reason)."""
    path = Path(weights_source)
    if not path.is_file():
        return "## Training\n\nUntrained (randomly initialised) networks.\n"
    state = torch.load(path, map_location="cpu", weights_only=True)
    meta = state.get("meta", {})
    cfg = meta.get("config", {})
    reasons = dict(cfg.get("deviations") or {})
    scenes = list(cfg.get("train_scenes", []))
    scene_text = (f"{len(scenes)} scenes (seeds {min(scenes)}-{max(scenes)})" if scenes else "?")
    val = meta.get("val_scenes", meta.get("val_scene", "?"))
    lines = ["## Training", "",
             f"Weights trained by `senfunet train --config config/train_tof_stereo.yaml` (wall time and command in the "
             f"config header): {meta.get('trained_steps', '?')} training frames, {meta.get('optimizer_steps', '?')} "
             f"optimizer steps. Training data: {scene_text}, {cfg.get('duration_s', '?')} s each, ToF "
             f"{float(cfg.get('tof_rate_hz', float('nan'))):.3g} Hz and stereo "
             f"{float(cfg.get('stereo_rate_hz', float('nan'))):.3g} Hz. The checkpoint is the one with the best "
             f"mean fused F-score margin over the better single sensor on validation scenes {val} (never trained on, "
             f"not among the held-out scenes): fused F {meta.get('val_F', float('nan')):.2f}, margin "
             f"{meta.get('val_margin', float('nan')):+.2f}, TSDF Fusion {meta.get('val_tsdf_F', float('nan')):.2f}.", "",
             "All three loss terms are the paper's (L1 to the GT TSDF on C12, L_in and L_out on C1 and C2 with eta, "
             "each normalised by its own voxel count), as are the chunk rule (>= 2000 updated voxels, <= 600 tries), "
             "the accumulation, the gradient clipping and the random resets. Deviations from the paper's training, "
             "with their reasons:", ""]
    listed = set()
    for key, paper in PAPER_TRAINING.items():
        if key in cfg and not math.isclose(float(cfg[key]), float(paper), rel_tol=1e-6):
            listed.add(key)
            lines.append(f"- `{key}` = {cfg[key]:g} (paper {paper:g}): {reasons.get(key, 'see the config header')}.")
    for key, reason in reasons.items():
        if key not in listed and key not in PAPER_TRAINING:
            value = f" = {cfg[key]}" if key in cfg else ""
            lines.append(f"- `{key}`{value}: {reason}.")
            listed.add(key)
    if not listed:
        lines.append("- none.")
    return "\n".join(lines) + "\n"
