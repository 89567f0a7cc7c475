"""Evaluation on a tiny scene: every method row and every metric column is produced."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from senfunet_core.learning import evaluation as ev
from senfunet_core.readout import voxel_values
from senfunet_core.learning import report


@pytest.fixture(scope="module")
def tiny_result(tmp_path_factory):
    cfg = ev.EvaluationConfig(seeds=(7,), duration_s=0.25, frame_stride=1, async_tof_divisors=(2,), cache_dir=None,
                              room_size_m=(2.5, 2.5, 2.4), image_size=(128, 128), ablations=True, seed_set="custom")
    fig = tmp_path_factory.mktemp("fig") / "evaluation.png"
    partial = []
    result = ev.evaluate("default", cfg, figure_path=fig, log=None, after_room=partial.append)
    assert len(partial) == 1 and partial[0].rows["senfunet"]["F"] == result.rows["senfunet"]["F"]
    return cfg, result, fig


@pytest.mark.slow  # tiny_result evaluates a scene
def test_table_has_all_rows_and_columns(tiny_result):
    _, result, fig = tiny_result
    assert list(result.rows)[:len(ev.METHODS)] == list(ev.METHODS)
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


@pytest.mark.slow  # tiny_result evaluates a scene
def test_markdown_report(tiny_result):
    cfg, result, _ = tiny_result
    text = report.results_markdown(result, cfg, "senfunet evaluate --scenes 1")
    for label in ev.METHOD_LABELS.values():
        assert f"| {label} |" in text
    for header in ("MSE", "MAD", "IoU", "Acc", "F (%)", "P (%)", "R (%)"):
        assert header in text
    assert "senfunet evaluate --scenes 1" in text and "Asynchronous" in text
    for section in ("## Ablations", "## F-score spread over the rooms", "## Grid metrics on a common voxel set"):
        assert section in text
    assert "Partial" not in text
    two_rooms = dataclasses.replace(cfg, seeds=(7, 8))
    assert "Partial: 1 of 2 rooms" in report.results_markdown(result, two_rooms, "senfunet evaluate")
    assert set(ev.bar_check(result.rows)) == {"F >= TSDF Fusion + 10", "F >= best single sensor + 3",
                                              "MAD < TSDF Fusion"}


@pytest.mark.parametrize("tsdf_fusion", [True, False])  # replay without --compare has no TSDF Fusion grid
def test_gt_crop_keeps_only_observed_vertices(tsdf_fusion):
    from senfunet_core.engine import EngineConfig, SenFuNet

    engine = SenFuNet(EngineConfig(tsdf_fusion=tsdf_fusion), weights=None)
    depth = np.full((256, 256), 1.0, np.float32)  # a wall 1 m ahead; pixels 0.8 cm apart there
    K = np.array([[128.0, 0, 127.5], [0, 128.0, 127.5], [0, 0, 1]])
    engine.integrate("tof", depth, K, np.eye(4))
    on_plane = np.array([[0.0, 0.0, 1.0], [0.1, 0.05, 1.0]], np.float32)
    far = np.array([[3.0, 3.0, 3.0]], np.float32)
    kept = ev.observed_gt_vertices(engine, np.concatenate([on_plane, far]))
    assert len(kept) == 2 and np.allclose(kept, on_plane)
    # a NaN, an inf or a vertex in UTM coordinates, beyond the map's reach, was observed by no sensor: it
    # raised "points lie more than 5 km from the origin" (blaming the poses), and replay --gt lost its run
    unusable = np.array([[np.nan, 0.0, 1.0], [np.inf, 0.0, 1.0], [4.5e5, 5.4e6, 30.0], [1e300, 0.0, 0.0]])
    kept = ev.observed_gt_vertices(engine, np.concatenate([on_plane, unusable]))
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
        centres, tsdf = voxel_values(engine, which)
        want = simulator.gt_tsdf(scene, centres, 0.1)
        np.testing.assert_allclose(truth.at(centres), want, atol=1e-6)
        expected = grid_metrics(tsdf, want)
        assert rows[method]["MAD"] == pytest.approx(expected["MAD"], rel=1e-5) and rows[method]["n"] == expected["n"]


def test_ablation_rows_change_the_networks_only(tiny_result):
    """Seeded feature nets equal the shipped ones when those were never trained; zeroed channels
    change the result; every ablation row has the grid, mesh and common-set metrics."""
    from senfunet_core import networks

    _, result, _ = tiny_result
    rows = result.per_scene[0]
    assert {"abl_features_seeded", "abl_features_zeroed"} <= set(rows)
    state = __import__("torch").load(networks.DEFAULT_WEIGHTS, map_location="cpu", weights_only=True)
    seeded, _ = networks.make_networks((False, True), int(state["meta"]["config"].get("init_seed", 0)))
    untrained = all(bool((a == b).all()) for net, saved in zip(seeded, state["feature_nets"])
                    for a, b in zip(net.state_dict().values(), saved.values()))
    if untrained:
        assert rows["abl_features_seeded"]["F"] == rows["senfunet"]["F"]
    assert rows["abl_features_zeroed"]["n"] != rows["senfunet"]["n"]
    for row in (rows["abl_features_seeded"], rows["abl_features_zeroed"]):
        assert {"F", "MAD", "MAD_common", "kept_common"} <= set(row)


def test_common_grid_metrics_count_missing_voxels_as_errors():
    gt = np.array([0.02, -0.03, 0.01, -0.01])
    pred = np.array([0.02, -0.01, np.nan, np.nan])  # two kept (exact, and 2 cm off), two missing
    m = ev.common_grid_metrics(pred, gt, band_m=0.1)
    assert m["kept"] == 0.5 and m["n"] == 4
    assert m["MAD"] == pytest.approx((0 + 0.02 + 0.1 + 0.1) / 4)
    assert m["MSE"] == pytest.approx((0 + 0.02 ** 2 + 0.01 + 0.01) / 4)
    assert m["Acc"] == pytest.approx(0.5)  # the kept two have the right sign; the missing two are wrong
    # inside: voxel 1 found (tn); voxel 3 missing with GT inside (fp); voxel 2 missing with GT outside (fn)
    assert m["IoU"] == pytest.approx(1 / 3)
    full = ev.common_grid_metrics(gt, gt, band_m=0.1)
    assert full["MAD"] == 0 and full["Acc"] == 1 and full["kept"] == 1


def test_goal_check_and_spread():
    def scene(tof, stereo, tsdf, senfunet):
        return {"tof": {"F": tof}, "stereo": {"F": stereo}, "tsdf_fusion": {"F": tsdf}, "senfunet": {"F": senfunet}}

    rooms = [scene(60, 40, 50, 70), scene(50, 55, 45, 62)]
    goals = list(ev.goal_check(rooms).values())
    assert goals == [True, True]  # +10 and +7 over the better sensor; +18.5 over TSDF Fusion on average
    goals = list(ev.goal_check([*rooms, scene(70, 30, 68, 69)]).values())  # -1 in room 3; +12.67 on average
    assert goals == [False, False]
    st = ev.spread(rooms)["senfunet"]
    assert st["mean"] == 66 and st["min"] == 62 and st["max"] == 70 and st["std"] == pytest.approx(4)


def test_named_weights_resolve():
    from senfunet_core import networks
    from senfunet_core.errors import InputError

    assert networks.resolve_weights("default") == networks.DEFAULT_WEIGHTS
    assert networks.resolve_weights("none") is None and networks.resolve_weights(None) is None
    with pytest.raises(InputError, match="paper"):
        networks.resolve_weights("no_such_model")
    from senfunet_core.engine import EngineConfig, SenFuNet

    engine = SenFuNet(EngineConfig(), weights=networks.resolve_weights("paper"))  # the 12-input paper model
    assert not engine.config.weighting_tsdf_input and engine.weighting_net.conv1.in_channels == 12
    assert sum(p.numel() for p in engine.weighting_net.parameters()) == 24257


def test_gt_crop_under_a_map_bound_keeps_the_vertices_of_evicted_blocks():
    """`senfunet replay --gt` under a map bound (the node's max_map_blocks) cropped the GT to the observed
    voxels of the blocks in memory alone: the surface the bound had spilled to disk was cropped away, and
    the fused mesh's archived part counted as false (the 8 x 7 m room at 2 cm voxels, bound 10000: F 19.62
    against 37.94 unbounded, for meshes within 2 cm of each other everywhere). The spilled blocks count."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from test_engine import SPHERE_C, SPHERE_R, SPHERE_VIEWS, engine_for_tests, far_views, integrate_views

    views = [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]] + far_views(2)
    reference, bounded = engine_for_tests(), engine_for_tests(max_blocks=165)
    for engine in (reference, bounded):
        integrate_views(engine, views)
        engine.update()
    assert len(bounded.grid.spill) > 50
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(4000, 3))
    on_spheres = SPHERE_R * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    gt = np.concatenate([SPHERE_C + on_spheres, views[-1][0] + on_spheres]).astype(np.float32)
    expected = ev.observed_gt_vertices(reference, gt)
    assert len(expected) > 1000
    assert len(ev.observed_gt_vertices(bounded, gt)) == len(expected)
    assert len(bounded.grid.spill) > 50  # looked at, left on disk
