"""Evaluation metrics of the paper (supplementary D) and a Markdown table for reports.

Grid metrics compare TSDF values on observed voxels; mesh metrics compare mesh vertices with a
distance threshold. Units: MSE in m^2, MAD in m, IoU and Acc as fractions in 0..1, F/P/R in
percent. `format_table` rescales to the paper's table units and says so in the header.
"""
from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from scipy.spatial import cKDTree

from .errors import InputError


def grid_metrics(tsdf_m: np.ndarray, gt_tsdf_m: np.ndarray) -> dict[str, float]:
    """MSE (m^2), MAD (m), IoU and Acc (fractions) of predicted vs GT TSDF on observed voxels.

    Both inputs are the already-masked 1-D value arrays (same length). Occupancy is by sign:
    a voxel is "inside" (negative class) when its value is < 0. Following the paper,
    IoU = tn / (tn + fp + fn), i.e. the IoU of the inside (occupied) region, and
    Acc = (tn + tp) / N. Empty input gives NaN for every metric and n = 0.
    """
    pred = np.asarray(tsdf_m, dtype=np.float64).ravel()
    gt = np.asarray(gt_tsdf_m, dtype=np.float64).ravel()
    if pred.shape != gt.shape:
        raise InputError(f"grid_metrics: {pred.size} predicted values but {gt.size} GT values")
    n = pred.size
    if n == 0:
        return {"MSE": math.nan, "MAD": math.nan, "IoU": math.nan, "Acc": math.nan, "n": 0}
    err = pred - gt
    pred_in, gt_in = pred < 0, gt < 0
    tn = int(np.count_nonzero(pred_in & gt_in))
    tp = int(np.count_nonzero(~pred_in & ~gt_in))
    fp = int(np.count_nonzero(~pred_in & gt_in))
    fn = int(np.count_nonzero(pred_in & ~gt_in))
    denom = tn + fp + fn
    return {
        "MSE": float(np.mean(err * err)),
        "MAD": float(np.mean(np.abs(err))),
        # No inside voxel in either grid: IoU of two empty sets is undefined.
        "IoU": tn / denom if denom else math.nan,
        "Acc": (tn + tp) / n,
        "n": n,
    }


def _fraction_within(query: np.ndarray, ref: np.ndarray, tau_m: float) -> float:
    """Percent of `query` points with a `ref` point within `tau_m` (inclusive)."""
    if len(query) == 0:
        return math.nan
    if len(ref) == 0:
        return 0.0
    tree = cKDTree(ref)
    # distance_upper_bound lets the tree prune early; misses come back as inf.
    d, _ = tree.query(query, k=1, distance_upper_bound=tau_m * (1 + 1e-9), workers=-1)
    return 100.0 * float(np.count_nonzero(d <= tau_m)) / len(query)


def mesh_metrics(pred_vertices: np.ndarray, gt_vertices: np.ndarray, tau_m: float = 0.02) -> dict[str, float]:
    """F-score, precision and recall (percent) of predicted vs GT mesh vertices at threshold tau.

    P: share of predicted vertices within tau of a GT vertex; R: share of GT vertices within
    tau of a predicted vertex; F: their harmonic mean (0 when both are 0). An empty
    prediction scores 0 on all three.
    """
    pred = np.asarray(pred_vertices, dtype=np.float64).reshape(-1, 3)
    gt = np.asarray(gt_vertices, dtype=np.float64).reshape(-1, 3)
    if not tau_m > 0:
        raise InputError(f"mesh_metrics: tau_m must be > 0, got {tau_m}")
    if len(pred) == 0:
        return {"F": 0.0, "P": 0.0, "R": 0.0}
    if len(gt) == 0:
        raise InputError("mesh_metrics: the GT mesh has no vertices")
    p = _fraction_within(pred, gt, tau_m)
    r = _fraction_within(gt, pred, tau_m)
    f = 2 * p * r / (p + r) if p + r > 0 else 0.0
    return {"F": f, "P": p, "R": r}


# column key -> (header with unit, scale applied to the stored value, format)
_COLUMN_FORMATS: dict[str, tuple[str, float, str]] = {
    "MSE": ("MSE (1e-4 m²) ↓", 1e4, "{:.2f}"),
    "MAD": ("MAD (cm) ↓", 1e2, "{:.2f}"),
    "IoU": ("IoU [0,1] ↑", 1.0, "{:.3f}"),
    "Acc": ("Acc (%) ↑", 1e2, "{:.2f}"),
    "F": ("F (%) ↑", 1.0, "{:.2f}"),
    "P": ("P (%) ↑", 1.0, "{:.2f}"),
    "R": ("R (%) ↑", 1.0, "{:.2f}"),
    "n": ("voxels", 1.0, "{:.0f}"),
}


def _cell(column: str, value: float | None) -> str:
    if value is None:
        return "-"
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    if math.isnan(v):
        return "-"
    if column in _COLUMN_FORMATS:
        _, scale, fmt = _COLUMN_FORMATS[column]
        return fmt.format(v * scale)
    return f"{v:.4g}"


def format_table(rows: Mapping[str, Mapping[str, float | None]], columns: list[str]) -> str:
    """A Markdown table: one row per entry of `rows` (name -> metrics), one column per key.

    Known metrics are shown in the paper's units (MSE in 1e-4 m², MAD in cm, IoU in 0..1,
    Acc/F/P/R in %), named in the header; missing or NaN values show as '-'.
    """
    headers = ["method"] + [_COLUMN_FORMATS[c][0] if c in _COLUMN_FORMATS else c for c in columns]
    lines = ["| " + " | ".join(headers) + " |",
             "| " + " | ".join(["---"] + ["---:"] * len(columns)) + " |"]
    for name, metrics in rows.items():
        cells = [str(name)] + [_cell(c, metrics.get(c)) for c in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
