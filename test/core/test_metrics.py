"""Grid and mesh metrics against hand-computed values."""
from __future__ import annotations

import math

import numpy as np
import pytest

from senfunet_core.metrics import format_table, grid_metrics, mesh_metrics


def test_grid_metrics_hand_example():
    pred = np.array([-0.02, -0.01, 0.03, 0.00, 0.01])
    gt = np.array([-0.01, 0.01, 0.02, -0.02, 0.01])
    # errors: -0.01, -0.02, 0.01, 0.02, 0 -> MSE = (1+4+1+4+0)e-4 / 5 = 2e-4, MAD = 0.06 / 5 = 0.012
    # classes: tn (both < 0), fn (pred < 0 <= gt), tp, fp (pred = 0 counts as >= 0, gt < 0), tp
    # -> tn=1, tp=2, fp=1, fn=1: IoU = 1/3, Acc = 3/5
    m = grid_metrics(pred, gt)
    assert m["MSE"] == pytest.approx(2e-4)
    assert m["MAD"] == pytest.approx(0.012)
    assert m["IoU"] == pytest.approx(1 / 3)
    assert m["Acc"] == pytest.approx(0.6)
    assert m["n"] == 5


def test_grid_metrics_empty_gives_nan():
    m = grid_metrics(np.array([]), np.array([]))
    assert all(math.isnan(m[k]) for k in ("MSE", "MAD", "IoU", "Acc"))


def _grid_points(n: int = 10, spacing: float = 0.1) -> np.ndarray:
    g = np.arange(n) * spacing
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)


def test_mesh_metrics_identity_and_shifts():
    gt = _grid_points()
    assert mesh_metrics(gt, gt) == {"F": 100.0, "P": 100.0, "R": 100.0}
    shift = np.array([0.01, 0.0, 0.0])
    assert mesh_metrics(gt + shift, gt)["F"] == pytest.approx(100.0)
    # 0.05 m off: nearest GT vertex is 0.05 m away (grid spacing 0.1 m), beyond tau = 0.02 m.
    far = mesh_metrics(gt + 5 * shift, gt)
    assert far == {"F": 0.0, "P": 0.0, "R": 0.0}


def test_mesh_metrics_partial_overlap():
    gt = np.stack([np.arange(10.0), np.zeros(10), np.zeros(10)], 1)  # x = 0..9, 1 m apart
    pred = np.stack([np.r_[np.arange(5.0, 10.0), np.arange(100.0, 115.0)], np.zeros(20), np.zeros(20)], 1)
    # pred: 5 of 20 vertices near GT -> P = 25 %; GT: 5 of 10 covered -> R = 50 %; F = 2*25*50/75
    m = mesh_metrics(pred, gt)
    assert m["P"] == pytest.approx(25.0)
    assert m["R"] == pytest.approx(50.0)
    assert m["F"] == pytest.approx(100.0 / 3)


def test_mesh_metrics_empty_prediction():
    assert mesh_metrics(np.zeros((0, 3)), _grid_points(3)) == {"F": 0.0, "P": 0.0, "R": 0.0}


def test_format_table_units():
    rows = {"fused": {"MSE": 2e-4, "MAD": 0.012, "IoU": 1 / 3, "Acc": 0.6, "F": 33.3333},
            "tof": {"MSE": float("nan"), "MAD": 0.02, "IoU": 0.5, "Acc": 0.75, "F": 50.0}}
    t = format_table(rows, ["MSE", "MAD", "IoU", "Acc", "F"])
    lines = t.strip().splitlines()
    assert len(lines) == 4
    assert "1e-4 m²" in lines[0] and "MAD (cm)" in lines[0] and "Acc (%)" in lines[0]
    assert lines[2] == "| fused | 2.00 | 1.20 | 0.333 | 60.00 | 33.33 |"
    assert lines[3].startswith("| tof | - | 2.00 |")
