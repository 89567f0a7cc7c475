"""The weighting net in int8 (`senfunet_core.weighting_int8`): the shipped weights' calibrations,
closeness to float32 on the shipped model, and the fall-back to float32 that says why."""
from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from senfunet_core.alpha import weighting_windows, window_value_ranges
from senfunet_core.alpha_evaluator import surface_windows
from senfunet_core.engine import EngineConfig, SenFuNet
from senfunet_core.grid import as_stored
from senfunet_core.networks import N_FEATURES, NAMED_WEIGHTS
from senfunet_core.weighting_int8 import calibration_path, file_sha256, int8_available, load_calibration
from senfunet_ros.replay import bag_frames

REPO = Path(__file__).resolve().parents[2]
needs_int8 = pytest.mark.skipif(not int8_available(), reason="this torch or CPU has no oneDNN int8 convolutions")


@pytest.mark.parametrize("name", sorted(NAMED_WEIGHTS))
def test_every_shipped_weights_file_has_its_int8_calibration(name):
    """A retrained model without `scripts/calibrate_int8.py` run again would run the node in float32."""
    calibration, why = load_calibration(NAMED_WEIGHTS[name])
    assert calibration is not None, why
    assert calibration.weights_sha256 == file_sha256(NAMED_WEIGHTS[name])
    assert 0 < calibration.layer_1_max < 1e3 and 0 < calibration.layer_2_max < 1e3


@pytest.fixture(scope="module")
def sample_engine():
    """The shipped model with G in int8 after the sample's first frames."""
    engine = SenFuNet(EngineConfig(alpha_dtype="int8", max_blocks=0))
    for frame in bag_frames(REPO / "bags" / "sim_room", 24):
        engine.integrate(frame.sensor, frame.depth_m, frame.K, frame.T_world_camera, frame.rgb)
    return engine


def test_8_bit_windows_are_the_float_windows_coded(sample_engine):
    """What the windows' kernel writes for G in int8 equals the float32 windows coded in their ranges
    (`grid.as_stored`), absent neighbours included."""
    evaluator = sample_engine.alpha.evaluator
    neighbours = sample_engine.store.neighbours(np.arange(min(sample_engine.grid.n_blocks, 96)))
    assert (neighbours < 0).any()  # blocks at the map's edge: some windows reach where no block is
    values = weighting_windows(neighbours, *evaluator.inputs())
    codes = weighting_windows(neighbours, *evaluator.inputs(), out=np.empty(values.size, np.uint8), depth_max_m=4.0)
    ranges = window_value_ranges(N_FEATURES, with_tsdf=True, depth_max_m=4.0)
    assert values.shape[-1] == len(ranges) == 14
    want = np.stack([as_stored(values[..., c], np.uint8, value_range=tuple(ranges[c])) for c in range(len(ranges))],
                    axis=-1)
    np.testing.assert_array_equal(codes, want)
    assert len(np.unique(codes[..., N_FEATURES - 1])) > 20  # depths spread over the codes


@needs_int8
def test_int8_alpha_is_close_to_float32_on_the_shipped_model(sample_engine):
    """On the sample's first frames, G in int8 against float32 on every block alpha matters for."""
    engine = sample_engine
    assert engine.alpha.evaluator.int8_net is not None and engine.stats()["alpha_arithmetic"] == "int8"
    diffs = []
    with torch.inference_mode():
        for x in surface_windows(engine.alpha.evaluator):
            diffs.append((engine.alpha.evaluator.int8_net(x) - engine.weighting_net.infer(x)).abs().flatten())
    diff = torch.cat(diffs)
    assert len(diff) > 100_000
    assert 0 < float(diff.mean()) < 0.02 and float(torch.quantile(diff[::7], 0.99)) < 0.15


@needs_int8
def test_int8_without_a_calibration_runs_float32_and_says_why(tmp_path, caplog):
    weights = tmp_path / "mine.pt"
    shutil.copy(NAMED_WEIGHTS["default"], weights)
    config = EngineConfig(alpha_dtype="int8", max_blocks=0)
    with caplog.at_level(logging.WARNING, logger="senfunet"):
        engine = SenFuNet(config, weights=weights)
    assert engine.alpha.evaluator.int8_net is None and engine.stats()["alpha_arithmetic"] == "float32"
    assert "no int8 calibration mine.int8.json" in caplog.text and "runs in float32" in caplog.text
    # a calibration of other weights is refused too
    shutil.copy(calibration_path(NAMED_WEIGHTS["paper"]), calibration_path(weights))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="senfunet"):
        assert SenFuNet(config, weights=weights).alpha.evaluator.int8_net is None
    assert "measured for other weights" in caplog.text
    # and with its own, int8 runs
    shutil.copy(calibration_path(NAMED_WEIGHTS["default"]), calibration_path(weights))
    assert SenFuNet(config, weights=weights).alpha.evaluator.int8_net is not None


@needs_int8
def test_the_node_picks_int8_for_the_weighting_net_alone_where_the_cpu_has_no_bfloat16():
    from senfunet_ros.params import alpha_dtype

    native = torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()
    assert alpha_dtype("auto", "cpu", int8=True) == ("bfloat16" if native else "int8")
    assert alpha_dtype("auto", "cpu") == ("bfloat16" if native else "float32")  # the feature nets: never int8
    assert alpha_dtype("float32", "cpu", int8=True) == "float32"
    assert alpha_dtype("auto", "cuda", int8=True) == "float32"


@needs_int8
def test_a_saved_map_keeps_g_in_int8_with_its_calibration(sample_engine, tmp_path, caplog):
    """A map's weights have no calibration file beside them: the map carries it."""
    from senfunet_core.map_file import load_map, save_map

    save_map(sample_engine, tmp_path / "map.pt")
    with caplog.at_level(logging.WARNING, logger="senfunet"):
        loaded = load_map(tmp_path / "map.pt")
    assert loaded.config.alpha_dtype == "int8" and "float32" not in caplog.text
    assert loaded.alpha.evaluator.int8_net.calibration == sample_engine.alpha.evaluator.int8_net.calibration
    x = next(surface_windows(loaded.alpha.evaluator))
    with torch.inference_mode():
        torch.testing.assert_close(loaded.alpha.evaluator.int8_net(x), sample_engine.alpha.evaluator.int8_net(x))
