"""Offline replay (senfunet_ros.replay): storages agree byte for byte, stats, metrics."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from senfunet_ros.bagio import copy_bag, open_bag

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "bags" / "sim_room"
SAMPLE_GT = REPO / "bags" / "sim_room_gt.ply"
WEIGHTS = REPO / "senfunet_core" / "weights" / "tof_stereo.pt"
MESHES = ("mesh", "tof", "stereo", "tsdf_fusion")
# Much coarser than the defaults so three replays stay fast; the shipped weights still load.
SMALL_PARAMS = "senfunet:\n  ros__parameters:\n    working_width: 64\n    voxel_size_m: 0.04\n"


def _prefix(src: Path, dst: Path, seconds: float) -> Path:
    with open_bag(src) as reader:
        stop = reader.start_ns + int(seconds * 1e9)
    return copy_bag(src, dst, stop_ns=stop)


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("replay")


@pytest.fixture(scope="module")
def prefix(work: Path) -> Path:
    """The sample's first second, as an mcap rosbag2 folder."""
    return _prefix(SAMPLE, work / "prefix", 1.0)


@pytest.fixture(scope="module")
def small_params(work: Path) -> Path:
    path = work / "small.yaml"
    path.write_text(SMALL_PARAMS)
    return path


@pytest.fixture(scope="module")
def cli_replay(prefix: Path, small_params: Path, work: Path) -> tuple[subprocess.CompletedProcess, Path]:
    """`senfunet replay` of the mcap prefix with --gt, as a user runs it."""
    out = work / "out_mcap"
    proc = subprocess.run([sys.executable, "-m", "senfunet_ros.cli", "replay", str(prefix), "--out", str(out),
                           "--params", str(small_params), "--gt", str(SAMPLE_GT)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc, out


def test_replay_outputs_stats_and_metrics(cli_replay: tuple[subprocess.CompletedProcess, Path]):
    proc, out = cli_replay
    for name in MESHES:
        assert (out / f"{name}.ply").stat().st_size > 1000
    stats = json.loads((out / "stats.json").read_text())
    assert stats["complete"] and stats["error"] is None
    for sensor, expected in (("tof", 15), ("stereo", 19)):
        c = stats["sensors"][sensor]
        assert c["received"] == c["integrated"] and abs(c["integrated"] - expected) <= 2
        assert c["dropped_total"] == 0 and c["pending_at_end"] == 0
        assert set(c["dropped"]) >= {"pose_timeout", "queue_full", "no_camera_info"}
    assert stats["topics"]["/stereo/color"]["stream"] == "color"
    assert set(stats["metrics"]) == set(MESHES)
    assert all(0 < stats["metrics"][m]["F"] <= 100 for m in MESHES)
    for key in ("integrate_s", "integrate_per_frame_ms", "extract_s", "write_s", "metrics_s", "total_s"):
        assert key in stats["timings"]
    assert re.search(r"^tof: (\d+) of \1 frames fused$", proc.stdout, re.M), proc.stdout
    assert "| mesh |" in proc.stdout and "| tsdf_fusion |" in proc.stdout  # the metrics table
    assert "replay" in proc.stderr  # the progress bar


def test_mcap_sqlite3_and_bare_mcap_give_the_same_mesh_bytes(
        cli_replay: tuple[subprocess.CompletedProcess, Path], prefix: Path, small_params: Path, work: Path):
    from senfunet_ros.replay import replay_bag

    _, out_mcap = cli_replay
    sqlite = copy_bag(prefix, work / "prefix_sqlite3", storage="sqlite3")
    bare = next(prefix.glob("*.mcap"))
    for bag, name in ((sqlite, "sqlite3"), (bare, "bare")):
        result = replay_bag(bag, work / f"out_{name}", params=small_params, progress=False)
        assert result.ok, result.error
        for mesh in MESHES:  # a different process and storage, the same bytes: deterministic
            assert (work / f"out_{name}" / f"{mesh}.ply").read_bytes() == (out_mcap / f"{mesh}.ply").read_bytes(), \
                f"{name}: {mesh}.ply differs from the mcap replay"


@pytest.mark.skipif(not WEIGHTS.is_file(), reason=f"no trained weights at {WEIGHTS} yet")
def test_fused_mesh_beats_tsdf_fusion(work: Path):
    """With the shipped weights and the default parameters, SenFuNet beats its own TSDF Fusion
    in F-score against the ground truth (cropped to the observed surface, as `senfunet evaluate`)."""
    from senfunet_ros.replay import replay_bag

    bag = _prefix(SAMPLE, work / "prefix_short", 0.6)  # 20 frames: the full-resolution replay is the slow part
    result = replay_bag(bag, work / "out_default", gt=SAMPLE_GT, progress=False)
    assert result.ok, result.error
    assert result.stats["weights"] == str(WEIGHTS)
    metrics = result.stats["metrics"]
    assert metrics["mesh"]["F"] > metrics["tsdf_fusion"]["F"], metrics


# -- parameters -------------------------------------------------------------------------------


def test_settings_from_file_match_the_node_defaults(tmp_path: Path):
    from senfunet_ros import params as P
    from senfunet_ros.replay import load_settings

    defaults = load_settings()
    from_file = load_settings(REPO / "config" / "default.yaml")
    assert from_file.values == defaults.values == {k: v for k, (v, _) in P.expanded_defaults().items()}
    wildcard = tmp_path / "p.yaml"
    wildcard.write_text("/**:\n  ros__parameters:\n    voxel_size_m: 2\n    tof:\n      depth_topic: /cam/depth\n")
    settings = load_settings(wildcard)
    assert settings.voxel_size_m == 2.0 and settings.sensors[0].depth_topic == "/cam/depth"
    typo = tmp_path / "typo.yaml"
    typo.write_text("senfunet:\n  ros__parameters:\n    voxel_sise_m: 0.02\n")
    with pytest.raises(ValueError, match="unknown parameter.*voxel_sise_m"):
        load_settings(typo)
