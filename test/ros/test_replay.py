"""Offline replay (senfunet_ros.replay): storages agree byte for byte, stats, metrics."""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from senfunet_ros.bagio import copy_bag, open_bag
from senfunet_ros.cli import build_parser
from senfunet_ros.commands.replay import _stale_meshes
from senfunet_ros.replay import ReplayResult, replay_bag
from senfunet_ros.params_file import load_settings

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
                           "--params", str(small_params), "--gt", str(SAMPLE_GT), "--compare"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc, out


def test_a_run_that_fuses_nothing_names_the_earlier_runs_mesh_it_leaves(prefix: Path, small_params: Path, work: Path):
    """A replay into a folder with an earlier run's mesh.ply, with parameters that drop every frame: the
    new stats.json said no mesh, and the old mesh.ply stayed beside it, unmentioned."""
    out = work / "fused_nothing"
    out.mkdir()
    (out / "mesh.ply").write_bytes(b"an earlier run's mesh")
    params = work / "drop_all.yaml"
    params.write_text(small_params.read_text() + "    pose_tolerance_s: 0.000001\n")
    proc = subprocess.run([sys.executable, "-m", "senfunet_ros.cli", "replay", str(prefix), "--out", str(out),
                           "--params", str(params)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 2 and (out / "mesh.ply").read_bytes() == b"an earlier run's mesh"
    assert f"mesh.ply in {out} is from an earlier run, not this one; delete it" in proc.stderr, proc.stderr


def test_a_replay_into_a_folder_another_replay_is_writing_to_is_refused(prefix: Path, small_params: Path,
                                                                         work: Path):
    """Two replays into one --out at once left one run's mesh.ply beside the other's stats.json. While
    another process holds the folder (as a running replay does), `senfunet replay` into it stops before
    fusing, says why, and writes nothing; once that process has ended, the folder is free."""
    out = work / "busy"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys\nfrom pathlib import Path\nfrom senfunet_ros.replay import _out_lock\n"
        f"with _out_lock(Path({str(out)!r})):\n    print('held', flush=True)\n    sys.stdin.read()\n")],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        replay = [sys.executable, "-m", "senfunet_ros.cli", "replay", str(prefix), "--out", str(out),
                  "--params", str(small_params)]
        proc = subprocess.run(replay, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 2, proc.stdout + proc.stderr
        assert "another senfunet replay is writing to this folder now" in proc.stderr, proc.stderr
        assert list(out.iterdir()) == []
    finally:
        holder.communicate(input="", timeout=60)
    proc = subprocess.run(replay, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0 and (out / "mesh.ply").is_file(), proc.stdout + proc.stderr


def test_a_folder_on_a_file_system_without_locks_is_replayed_into_unguarded(prefix: Path, small_params: Path,
                                                                             work: Path, monkeypatch):
    """Some network file systems refuse locks (ENOLCK): replay then writes as it did before it held
    its folder, rather than failing."""
    import errno

    from senfunet_ros import replay as replay_module

    def no_locks(fd: int, operation: int) -> None:
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(replay_module.fcntl, "flock", no_locks)
    result = replay_bag(prefix, work / "no_locks", params=small_params, progress=False)
    assert result.error is None and (work / "no_locks" / "mesh.ply").is_file()


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
    for m in MESHES:  # F is the harmonic mean of the P and R beside it (all rounded to 4 places)
        p, r = stats["metrics"][m]["P"], stats["metrics"][m]["R"]
        assert stats["metrics"][m]["F"] == pytest.approx(2 * p * r / (p + r), abs=2e-3)
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
        result = replay_bag(bag, work / f"out_{name}", params=small_params, progress=False, compare=True)
        assert result.ok, result.error
        for mesh in MESHES:  # a different process and storage, the same bytes: deterministic
            assert (work / f"out_{name}" / f"{mesh}.ply").read_bytes() == (out_mcap / f"{mesh}.ply").read_bytes(), \
                f"{name}: {mesh}.ply differs from the mcap replay"


def test_metrics_are_those_of_the_written_meshes_against_the_observed_ground_truth(
        cli_replay: tuple[subprocess.CompletedProcess, Path], prefix: Path, small_params: Path, work: Path,
        monkeypatch: pytest.MonkeyPatch):
    """Each mesh's F, P, R are mesh_metrics of the PLY file written for it against the GT cropped to
    the observed surface (the crop captured as replay computes it), in-process and from the CLI."""
    import numpy as np

    from senfunet_core.learning import evaluation
    from senfunet_core.metrics import mesh_metrics
    from senfunet_core.ply import read_ply
    from senfunet_ros.replay import replay_bag

    crops: list[np.ndarray] = []
    crop = evaluation.observed_gt_vertices

    def capture(*args, **kwargs):
        crops.append(crop(*args, **kwargs))
        return crops[-1]

    monkeypatch.setattr(evaluation, "observed_gt_vertices", capture)
    out = work / "out_metrics"
    result = replay_bag(prefix, out, params=small_params, gt=SAMPLE_GT, progress=False, compare=True)
    assert result.ok, result.error
    assert len(crops) == 1
    n_gt = read_ply(SAMPLE_GT).n_vertices
    assert 0 < len(crops[0]) < n_gt  # cropped, not empty
    assert result.stats["gt"]["vertices_observed"] == len(crops[0]) and result.stats["gt"]["vertices"] == n_gt
    metrics = result.stats["metrics"]
    for name in MESHES:
        expected = mesh_metrics(read_ply(out / f"{name}.ply").vertices, crops[0])
        assert metrics[name] == {k: round(float(v), 4) for k, v in expected.items()}, name
    # against the wrong place (the mesh moved 17 cm, tau 2 cm) the same mesh scores a fraction of it
    assert metrics["mesh"]["F"] > 3 * mesh_metrics(read_ply(out / "mesh.ply").vertices + 0.1, crops[0])["F"]
    cli_stats = json.loads((cli_replay[1] / "stats.json").read_text())
    assert cli_stats["metrics"] == metrics  # the CLI reports the same numbers for the same bag


def test_comparison_meshes_are_opt_in_and_do_not_change_the_fused_mesh(
        cli_replay: tuple[subprocess.CompletedProcess, Path], prefix: Path, small_params: Path, work: Path):
    """Without --compare, replay writes the fused mesh and stats only, and integrates no baseline;
    the fused mesh is byte for byte the one written with --compare."""
    from senfunet_ros.replay import replay_bag

    out = work / "out_plain"
    result = replay_bag(prefix, out, params=small_params, progress=False)
    assert result.ok, result.error
    assert sorted(p.name for p in out.iterdir()) == ["mesh.ply", "stats.json"]
    assert (out / "mesh.ply").read_bytes() == (cli_replay[1] / "mesh.ply").read_bytes()


def test_replay_keeps_the_map_bound_and_the_mesh(prefix: Path, work: Path):
    """Replay honours max_map_blocks as the node does: past it, far blocks are evicted (meshes kept,
    voxels spilled to disk and restored when seen again), and the fused mesh stays the unbounded one's."""
    from senfunet_core.metrics import mesh_metrics
    from senfunet_ros.replay import replay_bag

    unbounded = replay_bag(prefix, work / "unbounded", params=_params(work, "unbounded", max_map_blocks=0),
                           progress=False)
    assert unbounded.ok, unbounded.error
    blocks = unbounded.stats["engine"]["blocks"]
    bounded = replay_bag(prefix, work / "bounded", params=_params(work, "bounded", max_map_blocks=blocks // 3),
                         progress=False)
    assert bounded.ok, bounded.error
    engine = bounded.stats["engine"]
    assert engine["evicted_blocks"] > blocks // 3 and engine["blocks"] <= 1.25 * (blocks // 3)
    assert engine["restored_blocks"] > 0
    # Alpha near a block that is on disk is judged without its voxels, so the meshes differ a little
    # there (here a third of the map stays and most blocks go to disk and back several times).
    a, b = bounded.meshes["mesh"], unbounded.meshes["mesh"]
    assert abs(a.n_faces - b.n_faces) <= 0.02 * b.n_faces
    assert mesh_metrics(a.vertices, b.vertices, tau_m=0.04)["F"] > 99.5  # one voxel


def _params(work: Path, name: str, **values: object) -> Path:
    path = work / f"{name}.yaml"
    path.write_text(SMALL_PARAMS + "".join(f"    {k}: {v}\n" for k, v in values.items()))
    return path


@pytest.mark.slow
@pytest.mark.skipif(not WEIGHTS.is_file(), reason=f"no trained weights at {WEIGHTS} yet")
def test_fused_mesh_beats_tsdf_fusion(work: Path):
    """With the shipped weights and the default parameters, SenFuNet beats its own TSDF Fusion
    in F-score against the ground truth (cropped to the observed surface, as `senfunet evaluate`)."""
    from senfunet_ros.replay import replay_bag

    bag = _prefix(SAMPLE, work / "prefix_short", 0.6)  # 20 frames: the full-resolution replay is the slow part
    result = replay_bag(bag, work / "out_default", gt=SAMPLE_GT, progress=False, compare=True)
    assert result.ok, result.error
    assert result.stats["weights"] == str(WEIGHTS)
    metrics = result.stats["metrics"]
    assert metrics["mesh"]["F"] > metrics["tsdf_fusion"]["F"], metrics


# -- parameters -------------------------------------------------------------------------------


def test_replay_says_that_parameter_tsdf_fusion_takes_compare(prefix: Path, work: Path):
    """tsdf_fusion: true in the parameter file is the node's switch; replay without --compare writes no
    tsdf_fusion.ply and says that --compare does."""
    from replays import replay_in_process

    params = work / "tsdf_fusion.yaml"
    params.write_text(SMALL_PARAMS + "    tsdf_fusion: true\n")
    proc = replay_in_process(prefix, work / "out_tsdf_param", params)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "parameter tsdf_fusion is for the node" in proc.stderr and "with --compare" in proc.stderr
    assert not (work / "out_tsdf_param" / "tsdf_fusion.ply").exists()


def test_settings_from_file_match_the_node_defaults(tmp_path: Path):
    from senfunet_ros import params as P
    from senfunet_ros.params_file import load_settings

    defaults = load_settings()
    from_file = load_settings(REPO / "config" / "default.yaml")
    assert from_file.values == defaults.values == {k: v for k, (v, _) in P.expanded_defaults().items()}
    wildcard = tmp_path / "p.yaml"
    wildcard.write_text("/**:\n  ros__parameters:\n    voxel_size_m: 0.02\n    tof:\n      depth_topic: /cam/depth\n")
    settings = load_settings(wildcard)
    assert settings.voxel_size_m == 0.02 and settings.sensors[0].depth_topic == "/cam/depth"
    typo = tmp_path / "typo.yaml"
    typo.write_text("senfunet:\n  ros__parameters:\n    voxel_sise_m: 0.02\n")
    with pytest.raises(ValueError, match=r"unknown parameter.*voxel_sise_m \(did you mean voxel_size_m\?\)"):
        load_settings(typo)
    other_node = tmp_path / "other.yaml"  # the live node, named senfunet, would get none of it
    other_node.write_text("senfunet_node:\n  ros__parameters:\n    voxel_size_m: 0.05\n")
    assert load_settings(other_node).voxel_size_m == 0.05  # replay takes a file's only section
    with pytest.raises(ValueError, match="'senfunet_node'.* for other nodes"):
        load_settings(other_node, node_sections_only=True)
    for bad in (typo, other_node):  # `senfunet node` refuses them before it starts
        proc = subprocess.run([sys.executable, "-m", "senfunet_ros.cli", "node", "--params", str(bad)],
                              capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2 and ("voxel_sise_m" in proc.stderr or "senfunet_node" in proc.stderr), proc.stderr


def test_values_are_read_as_ros_reads_them_and_a_switch_takes_no_number():
    """PyYAML reads 2e6 as text, rcl as 2000000.0: `max_map_blocks: 2e6` was refused by the check and taken
    by the node. `tsdf_fusion: 0.5` became true and `voxel_size_m: true` 1 m, unsaid (a value meant for
    the next line?)."""
    from senfunet_ros import params as P
    from senfunet_ros.cli import build_parser
    from senfunet_ros.params_file import load_settings

    assert load_settings(None, {"max_map_blocks": "2e6"}).max_map_blocks == 2_000_000
    for name, value in (("tsdf_fusion", 0.5), ("save_on_shutdown", 2), ("voxel_size_m", True)):
        with pytest.raises(ValueError, match=name):
            P.coerce(name, value, P.expanded_defaults()[name][0])
    assert load_settings(None, {"tsdf_fusion": 1}).tsdf_fusion is True
    # ROS's own spelling of the option works too
    assert build_parser().parse_args(["node", "--params-file", "config/default.yaml"]).params == "config/default.yaml"


def test_parameter_files_are_read_as_ros_reads_them(tmp_path: Path):
    """What rcl applies, these apply too: sections nested under namespaces (`robot1: senfunet:`, `/**:
    senfunet:`) and several YAML documents were refused ("no 'senfunet: ros__parameters:' section",
    and a false error at the node's start). What rcl refuses (the node died in rclpy.init with a
    traceback) is refused with what to write instead: a list mixing integers and decimals, the
    natural way to write an extrinsic, and YAML aliases."""
    from senfunet_ros.params_file import load_settings

    nested = tmp_path / "nested.yaml"
    nested.write_text("robot1:\n  senfunet:\n    ros__parameters:\n      voxel_size_m: 0.02\n"
                      "/**:\n  senfunet:\n    ros__parameters:\n      band_m: 0.2\n")
    settings = load_settings(nested, node_sections_only=True, node_fqn="/robot1/senfunet")
    assert (settings.voxel_size_m, settings.band_m) == (0.02, 0.2)
    assert load_settings(nested, node_sections_only=True).voxel_size_m != 0.02  # /senfunet gets only /**'s
    documents = tmp_path / "documents.yaml"
    documents.write_text("senfunet:\n  ros__parameters:\n    voxel_size_m: 0.02\n---\n"
                         "senfunet:\n  ros__parameters:\n    band_m: 0.2\n")
    assert (load_settings(documents).voxel_size_m, load_settings(documents).band_m) == (0.02, 0.2)
    mixed = tmp_path / "mixed.yaml"
    mixed.write_text("senfunet:\n  ros__parameters:\n    tof:\n      T_body_camera: [0.1, 0, 0, 0, 0, 0, 1]\n")
    with pytest.raises(ValueError, match=r"tof.T_body_camera .* mixes float and int .*decimal point"):
        load_settings(mixed)
    robots = tmp_path / "robots.yaml"  # replay has no node name: "the node, named '/senfunet', would ignore them"
    robots.write_text("/robot1/senfunet:\n  ros__parameters:\n    voxel_size_m: 0.02\n"
                      "/robot2/senfunet:\n  ros__parameters:\n    voxel_size_m: 0.03\n")
    with pytest.raises(ValueError, match="several for other nodes.*copy the one to use into a file of its own"):
        load_settings(robots)
    shared = tmp_path / "shared.yaml"  # a section for every node holds other nodes' parameters too
    shared.write_text("/**:\n  ros__parameters:\n    robot_name: rover\n    voxel_size_m: 0.02\n")
    assert load_settings(shared, node_sections_only=True).voxel_size_m == 0.02
    shared.write_text("/**:\n  ros__parameters:\n    robot_name: rover\n    voxel_sise_m: 0.02\n")
    with pytest.raises(ValueError, match=r"voxel_sise_m \(did you mean voxel_size_m\?\)"):  # ours: a typo
        load_settings(shared)
    near_miss = tmp_path / "near_miss.yaml"  # said "no 'senfunet: ros__parameters:' section", of a file that has one
    near_miss.write_text("senfunet:\n  ros_parameters:\n    voxel_size_m: 0.02\n")
    with pytest.raises(ValueError, match=r"no parameters under 'ros__parameters:' \('senfunet' holds \['ros_param"):
        load_settings(near_miss)
    alias = tmp_path / "alias.yaml"
    alias.write_text("senfunet:\n  ros__parameters:\n    tof: &range\n      depth_max_m: 4.0\n    stereo: *range\n")
    with pytest.raises(ValueError, match="YAML alias"):
        load_settings(alias)
    for bad, says in ((mixed, "decimal point"), (alias, "YAML alias")):  # `senfunet node` refuses them, no traceback
        proc = subprocess.run([sys.executable, "-m", "senfunet_ros.cli", "node", "--params", str(bad)],
                              capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2 and says in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    # given to ROS directly, past the check: rcl's refusal, said plainly
    proc = subprocess.run([sys.executable, "-m", "senfunet_ros.cli", "node", "--", "--ros-args", "--params-file",
                           str(mixed)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "cannot start: ROS refused" in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr


def test_node_engine_config_runs_on_the_cpu_when_cuda_is_asked_for_and_absent(tmp_path: Path, monkeypatch):
    import torch

    from senfunet_ros import params as P
    from senfunet_ros.params_file import load_settings

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    file = tmp_path / "cuda.yaml"
    file.write_text("/**:\n  ros__parameters:\n    device: cuda\n")
    settings = load_settings(file)
    assert settings.device == "cuda"
    assert P.engine_config(settings).device == "cpu"
    said: list[str] = []  # and replay says so, as the parameter's help promises (it fell back silently)
    prefix = _prefix(SAMPLE, tmp_path / "prefix", 0.3)
    replay_bag(prefix, tmp_path / "out", params=file, progress=False, log=said.append)
    assert "note: device 'cuda' requested but CUDA is not available: using cpu" in said, said


def test_weights_parameter_takes_a_shipped_name_or_a_path_and_refuses_the_rest(tmp_path: Path):
    from senfunet_core.networks import NAMED_WEIGHTS, weights_tsdf_input
    from senfunet_ros import params as P
    from senfunet_ros.params_file import load_settings

    paper = P.engine_weights(load_settings(None, {"weights": "paper"}))
    assert paper == str(NAMED_WEIGHTS["paper"]) and not weights_tsdf_input(paper)  # the 12-input G
    assert P.engine_weights(load_settings(None, {"weights": "none"})) is None
    assert P.engine_weights(load_settings(None, {"weights": paper})) == paper
    with pytest.raises(ValueError, match="default.*paper"):
        load_settings(None, {"weights": str(tmp_path / "missing.pt")})
    # a file that is no weights file: torch's own words advised loading it unsafely, or said only "101"
    import torch

    from senfunet_core.errors import InputError
    from senfunet_core.networks import load_weights, make_networks

    text, other = tmp_path / "notes.pt", tmp_path / "other.pt"
    text.write_text("not weights")
    torch.save({"step": 3}, other)
    for path, says in ((text, "not a zip archive"), (other, "no feature_nets")):
        with pytest.raises(InputError, match="not SenFuNet weights|not a SenFuNet weights file") as raised:
            load_weights(path, *make_networks((False, True)))
        assert says in str(raised.value) and "weights_only" not in str(raised.value), raised.value


@pytest.mark.parametrize("value", ["0", "-3", "two"])
def test_threads_below_one_is_refused(value, capsys):
    with pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args(["replay", "bag", "--out", "out", "--threads", value])
    assert exit_info.value.code == 2
    assert "--threads: must be a whole number >= 1" in capsys.readouterr().err


def test_threads_default_and_value():
    assert build_parser().parse_args(["replay", "bag", "--out", "out"]).threads == 1
    assert build_parser().parse_args(["replay", "bag", "--out", "out", "--threads", "2"]).threads == 2



def test_out_that_is_a_file_is_refused_at_once(tmp_path):
    target = tmp_path / "afile"
    target.write_text("keep me\n")
    t0 = time.monotonic()
    with pytest.raises(ValueError, match="is a file; pass a folder"):
        replay_bag(SAMPLE, target, progress=False)
    assert time.monotonic() - t0 < 10.0  # not after fusing the bag (~20-60 s)
    assert target.read_text() == "keep me\n"


def test_out_below_a_file_is_refused_at_once(tmp_path):
    (tmp_path / "afile").write_text("")
    with pytest.raises(ValueError, match="cannot create the folder"):
        replay_bag(SAMPLE, tmp_path / "afile" / "sub", progress=False)


def test_stale_comparison_meshes_are_named(tmp_path: Path):
    for name in ("mesh", "tof", "stereo", "tsdf_fusion", "other"):
        (tmp_path / f"{name}.ply").write_bytes(b"")
    result = ReplayResult(stats={"sensors": {"tof": {}, "stereo": {}}},
                          files={"mesh": tmp_path / "mesh.ply", "stats": tmp_path / "stats.json"})
    args = argparse.Namespace(out=str(tmp_path), compare=False)
    assert _stale_meshes(result, args) == ["stereo.ply", "tof.ply", "tsdf_fusion.ply"]
    result.files.update({n: tmp_path / f"{n}.ply" for n in ("tof", "stereo", "tsdf_fusion")})
    assert _stale_meshes(result, argparse.Namespace(out=str(tmp_path), compare=True)) == []


def test_binary_file_named(tmp_path):
    bad = tmp_path / "bag.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n\xff\xfe")
    with pytest.raises(ValueError, match=r"bag\.mcap: not a text file; pass a YAML parameter file"):
        load_settings(bad)


def test_yaml_error_names_the_line(tmp_path):
    bad = tmp_path / "p.yaml"
    bad.write_text("senfunet:\n  ros__parameters:\n    voxel_size_m: [oops\n")
    with pytest.raises(ValueError, match=r"p\.yaml: not valid YAML \(line \d+, column \d+\)"):
        load_settings(bad)


def test_a_disk_that_fills_while_stats_json_is_written_leaves_no_half_file(prefix: Path, small_params: Path,
                                                                           tmp_path: Path, monkeypatch):
    """stats.json was written in place (Path.write_text): a disk that filled while it was written left the
    first half of it under its name, looking like a replay's stats. It is written whole or not at all,
    as the meshes are (and the error says why: no space left)."""
    import errno
    import io
    import os

    out = tmp_path / "out"
    real_open, real_fdopen = io.open, os.fdopen

    class HalfWritten:  # the disk fills halfway through the file: the first half is written, then ENOSPC
        def __init__(self, file):
            self._file = file

        def write(self, data):
            self._file.write(data[: len(data) // 2])
            raise OSError(errno.ENOSPC, "No space left on device")

        def __getattr__(self, name):
            return getattr(self._file, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self._file.close()

    def is_stats(name: str) -> bool:
        return Path(name).name == "stats.json" or Path(name).name.startswith(".stats.json.")

    def opening(file, *args, **kwargs):  # Path.write_text
        opened = real_open(file, *args, **kwargs)
        return HalfWritten(opened) if isinstance(file, (str, Path)) and is_stats(str(file)) else opened

    def fd_opening(fd, *args, **kwargs):  # files.atomic_file's temporary file
        opened = real_fdopen(fd, *args, **kwargs)
        return HalfWritten(opened) if is_stats(os.readlink(f"/proc/self/fd/{fd}")) else opened

    monkeypatch.setattr(io, "open", opening)
    monkeypatch.setattr(os, "fdopen", fd_opening)
    with pytest.raises(OSError, match="No space left on device"):
        replay_bag(prefix, out, params=small_params, progress=False)
    monkeypatch.undo()
    assert sorted(p.name for p in out.iterdir()) == ["mesh.ply"]  # no stats.json, whole or half; no temporary file
