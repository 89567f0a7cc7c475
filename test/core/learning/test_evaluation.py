"""Evaluation on a tiny scene: every method row and every metric column is produced."""
from __future__ import annotations

import math

import numpy as np
import pytest

from senfunet_core.learning import evaluation as ev


@pytest.fixture(scope="module")
def tiny_result(tmp_path_factory):
    cfg = ev.EvaluationConfig(seeds=(1001,), duration_s=0.25, frame_stride=1, async_tof_divisors=(2,), cache_dir=None,
                              room_size_m=(2.5, 2.5, 2.4), image_size=(128, 128))
    fig = tmp_path_factory.mktemp("fig") / "evaluation.png"
    result = ev.evaluate(None, cfg, figure_path=fig, log=None)
    return cfg, result, fig


def test_table_has_all_rows_and_columns(tiny_result):
    cfg, result, fig = tiny_result
    assert list(result.rows) == list(ev.METHODS)
    for method, row in result.rows.items():
        for col in ev.COLUMNS:
            assert col in row and not math.isnan(row[col]), (method, col)
        assert 0 <= row["F"] <= 100 and 0 <= row["IoU"] <= 1 and row["MAD"] >= 0
    # the unfiltered fused grid keeps every observed voxel: at least as many as the filtered one
    assert result.rows["senfunet_nofilter"]["n"] >= result.rows["senfunet"]["n"]
    assert result.rows["tsdf_fusion"]["n"] >= max(result.rows["tof"]["n"], result.rows["stereo"]["n"])
    assert set(result.async_rows) == {"1/2"}
    assert set(ev.ASYNC_METHODS) <= set(result.async_rows["1/2"])
    assert fig.is_file() and fig.stat().st_size > 10_000


def test_markdown_report(tiny_result):
    cfg, result, _ = tiny_result
    text = ev.results_markdown(result, cfg, "senfunet evaluate --scenes 1")
    for label in ev.METHOD_LABELS.values():
        assert f"| {label} |" in text
    for header in ("MSE", "MAD", "IoU", "Acc", "F (%)", "P (%)", "R (%)"):
        assert header in text
    assert "senfunet evaluate --scenes 1" in text and "Asynchronous" in text
    assert set(ev.bar_check(result.rows)) == {"F >= TSDF Fusion + 10", "F >= best single sensor + 3", "MAD < TSDF Fusion"}


def test_gt_crop_keeps_only_observed_vertices():
    from senfunet_core.engine import EngineConfig, SenFuNet

    engine = SenFuNet(EngineConfig(), weights=None)
    depth = np.full((256, 256), 1.0, np.float32)  # a wall 1 m ahead; pixels 0.8 cm apart there
    K = np.array([[128.0, 0, 127.5], [0, 128.0, 127.5], [0, 0, 1]])
    engine.integrate("tof", depth, K, np.eye(4))
    on_plane = np.array([[0.0, 0.0, 1.0], [0.1, 0.05, 1.0]], np.float32)
    far = np.array([[3.0, 3.0, 3.0]], np.float32)
    kept = ev.observed_gt_vertices(engine, np.concatenate([on_plane, far]))
    assert len(kept) == 2 and np.allclose(kept, on_plane)


def test_grid_truth_lookup_equals_gt_tsdf_at_the_voxel_centres():
    from senfunet_core.engine import EngineConfig, SenFuNet
    from senfunet_core.learning import simulator
    from senfunet_core.metrics import grid_metrics

    scene = simulator.make_scene(1001, room_size_m=(2.5, 2.5, 2.4))
    seq = simulator.simulate_sequence(scene, 1001, duration_s=0.15, width=128, height=128)
    engine = SenFuNet(EngineConfig(), weights=None)
    ev.integrate_frames(engine, seq.frames)
    truth = ev.GridTruth(engine, scene, 0.1)
    gt_vertices = ev.observed_gt_vertices(engine, simulator.gt_mesh(scene, 0.02).vertices)
    rows = ev.method_metrics(engine, scene, gt_vertices, methods=("tof", "senfunet"))
    for method, which in (("tof", "tof"), ("senfunet", "fused")):
        centres, tsdf = engine.voxel_values(which)
        want = simulator.gt_tsdf(scene, centres, 0.1)
        np.testing.assert_allclose(truth.at(centres), want, atol=1e-6)
        expected = grid_metrics(tsdf, want)
        assert rows[method]["MAD"] == pytest.approx(expected["MAD"], rel=1e-5) and rows[method]["n"] == expected["n"]
