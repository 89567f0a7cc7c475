"""The node's map services and its map bound (max_map_blocks), without DDS."""
from __future__ import annotations

import builtins
import errno
import io
import logging
import os
import struct
import sys
import threading
import time
import zipfile
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "core"))

from senfunet_core.engine import SenFuNet  # noqa: E402
from senfunet_core.map_file import save_map  # noqa: E402
from senfunet_ros import params as P  # noqa: E402
from senfunet_ros.ingest import Ingest  # noqa: E402
from senfunet_ros.map_services import MapServices  # noqa: E402
from senfunet_ros.mesh_publisher import UpdateSignal  # noqa: E402
from senfunet_ros.pipeline import Pipeline  # noqa: E402
from senfunet_ros.replay import ingest_config  # noqa: E402
from senfunet_ros.params_file import load_settings  # noqa: E402
from test_engine import SPHERE_C, SPHERE_VIEWS, far_views, integrate_views  # noqa: E402


def test_load_map_keeps_the_nodes_map_bound(tmp_path):
    """A map saved without a bound (replay --compare, max_map_blocks 0), loaded by ~/load_map into a node
    started with max_map_blocks 165: the node's bound holds from then on, not the file's."""
    params = tmp_path / "p.yaml"
    params.write_text("senfunet:\n  ros__parameters:\n    max_map_blocks: 165\n    weights: none\n"
                      f"    output_dir: {tmp_path}\n    rgb_sensors: []\n    tof:\n      depth_min_m: 0.05\n"
                      "    stereo:\n      depth_min_m: 0.05\n")
    settings = load_settings(params)
    saved = SenFuNet(P.engine_config(settings, max_blocks=0), weights=None)
    integrate_views(saved, [(SPHERE_C, SPHERE_VIEWS[0])])
    save_map(saved, tmp_path / "map.pt")
    pipeline = Pipeline(SenFuNet(P.engine_config(settings), weights=None), Ingest(ingest_config(settings)))
    services = MapServices(pipeline, lambda: settings, SimpleNamespace(lock=threading.Lock(), resend_all=lambda: None,
                                                                    updates=UpdateSignal()),
                           logging.getLogger("test"))
    reply = services.load_map(None, SimpleNamespace(success=None, message=None))
    assert reply.success, reply.message
    engine = pipeline.engine
    assert engine.max_blocks == 165
    integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[1:3]] + far_views(3))
    engine.update()
    assert engine.grid.n_blocks <= 165 and engine.stats()["evicted_blocks"] > 0
    # saved with blocks on disk, and loaded again: the reply counts them (it gave the blocks in memory alone)
    spilled = len(engine.grid.spill)
    assert spilled > 0 and services.save_map(None, SimpleNamespace(success=None, message=None)).success
    reply = services.load_map(None, SimpleNamespace(success=None, message=None))
    assert reply.success and f"blocks in memory and {spilled} on disk" in reply.message, reply.message


def test_a_loaded_map_runs_as_the_nodes_parameters_say_and_what_it_cannot_take_is_said(tmp_path):
    """A map saved by an engine with other run-time settings (alpha order, allocation policy, arithmetic)
    and without the TSDF Fusion baseline, loaded by ~/load_map into a node with the defaults and seed-1
    networks: it took the file's settings and networks, the parameters still said the node's, and
    ~/save_mesh left an earlier map's tsdf_fusion.ply beside the new meshes without a word. Now the
    run-time settings are the node's, and the reply says whose networks run and that the map keeps no
    baseline (the node's parameter asks for one), as ~/save_mesh's reply says that file is an earlier
    map's."""
    params = tmp_path / "p.yaml"
    params.write_text("senfunet:\n  ros__parameters:\n    weights: none\n    alpha_precision: float32\n"
                      f"    tsdf_fusion: true\n    output_dir: {tmp_path}\n    rgb_sensors: []\n    tof:\n"
                      "      depth_min_m: 0.05\n    stereo:\n      depth_min_m: 0.05\n")
    settings = load_settings(params)
    node_config = P.engine_config(settings)
    saved = SenFuNet(P.engine_config(settings, alpha_order="latest", min_new_block_samples=0, tsdf_fusion=False,
                                     alpha_dtype="bfloat16", seed=1), weights=None)
    integrate_views(saved, [(SPHERE_C, SPHERE_VIEWS[0])])
    save_map(saved, tmp_path / "map.pt")
    (tmp_path / "tsdf_fusion.ply").write_bytes(b"an earlier map's")
    pipeline = Pipeline(SenFuNet(node_config, weights=None), Ingest(ingest_config(settings)))
    services = MapServices(pipeline, lambda: settings, SimpleNamespace(lock=threading.Lock(), resend_all=lambda: None,
                                                                    updates=UpdateSignal()),
                           logging.getLogger("test"))
    reply = services.load_map(None, SimpleNamespace(success=None, message=None))
    assert reply.success, reply.message
    config = pipeline.engine.config
    assert (config.alpha_order, config.min_new_block_samples, config.alpha_dtype) == (
        node_config.alpha_order, node_config.min_new_block_samples, "float32")
    assert pipeline.engine.alpha.alpha_order == node_config.alpha_order
    assert "networks saved in it" in reply.message and "without a TSDF Fusion baseline" in reply.message, reply.message
    reply = services.save_mesh(None, SimpleNamespace(success=None, message=None))
    assert reply.success and f"{tmp_path / 'tsdf_fusion.ply'} is an earlier map's" in reply.message, reply.message


def test_save_mesh_says_the_per_sensor_meshes_leave_out_evicted_blocks(tmp_path):
    """~/save_mesh under a bound: the per-sensor PLY files hold only the blocks in memory (the fused one has
    the evicted blocks' final meshes): said in the log and in the service's reply, not silently."""
    params = tmp_path / "p.yaml"
    params.write_text("senfunet:\n  ros__parameters:\n    max_map_blocks: 165\n    weights: none\n"
                      f"    output_dir: {tmp_path}\n    rgb_sensors: []\n    tof:\n      depth_min_m: 0.05\n"
                      "    stereo:\n      depth_min_m: 0.05\n")
    settings = load_settings(params)
    logged: list[tuple[str, str]] = []
    pipeline = Pipeline(SenFuNet(P.engine_config(settings), weights=None), Ingest(ingest_config(settings)),
                        log=lambda level, text: logged.append((level, text)))
    integrate_views(pipeline.engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]] + far_views(2))
    pipeline.engine.update()
    assert len(pipeline.engine.grid.spill) > 0
    services = MapServices(pipeline, lambda: settings, SimpleNamespace(lock=threading.Lock(), resend_all=lambda: None,
                                                                    updates=UpdateSignal()),
                           logging.getLogger("test"))
    reply = services.save_mesh(None, SimpleNamespace(success=None, message=None))
    assert reply.success and "evicted" in reply.message
    assert any(level == "warning" and "tof.ply" in text and "evicted" in text for level, text in logged)


def test_save_mesh_lets_mesh_updates_through_while_the_net_catches_up(tmp_path):
    """~/save_mesh on a map the weighting net has not judged yet: it judges in turns of half a mesh
    period with a mesh update after each (before, the updates waited for the whole catch-up), and writes
    the exact fused mesh all the same."""
    from senfunet_core.ply import read_ply

    params = tmp_path / "p.yaml"
    params.write_text("senfunet:\n  ros__parameters:\n    weights: none\n    mesh_rate_hz: 20.0\n"
                      f"    output_dir: {tmp_path}\n    rgb_sensors: []\n    tof:\n      depth_min_m: 0.05\n"
                      "    stereo:\n      depth_min_m: 0.05\n")
    settings = load_settings(params)
    pipeline = Pipeline(SenFuNet(P.engine_config(settings, alpha_threads=1), weights=None),
                        Ingest(ingest_config(settings)))
    engine = pipeline.engine
    integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS] + far_views(4))
    mesh_timer = SimpleNamespace(lock=threading.Lock(), resend_all=lambda: None, updates=UpdateSignal())
    services = MapServices(pipeline, lambda: settings, mesh_timer, logging.getLogger("test"))
    saving = threading.Event()
    stop = threading.Event()
    updates_while_saving = []

    def mesh_updates() -> None:  # the node's mesh timer: an update without the net's turn, its end signalled
        while not stop.wait(0.05):
            engine.update(alpha_budget_s=0.0)
            if saving.is_set():
                updates_while_saving.append(time.monotonic())
            mesh_timer.updates.ended()

    timer = threading.Thread(target=mesh_updates)
    timer.start()
    try:
        saving.set()
        reply = services.save_mesh(None, SimpleNamespace(success=None, message=None))
        saving.clear()
    finally:
        stop.set()
        timer.join()
    assert reply.success, reply.message
    assert engine.counters["alpha_blocks"] > 3 * engine.config.alpha_batch_blocks  # several turns' worth
    assert len(updates_while_saving) >= 3
    saved = read_ply(tmp_path / "mesh.ply")
    exact = engine.extract_mesh("fused")
    assert saved.n_faces == exact.n_faces > 0 and np.allclose(saved.vertices, exact.vertices, atol=1e-6)


def _services(tmp_path: Path, **values: object) -> tuple[MapServices, Pipeline, list[str]]:
    """MapServices over a small fused sphere, its parameters `values` on top of the test's."""
    params = tmp_path / "p.yaml"
    params.write_text("senfunet:\n  ros__parameters:\n    weights: none\n"
                      f"    output_dir: {tmp_path}\n    rgb_sensors: []\n    tof:\n      depth_min_m: 0.05\n"
                      "    stereo:\n      depth_min_m: 0.05\n"
                      + "".join(f"    {name}: {value}\n" for name, value in values.items()))
    settings = load_settings(params)
    pipeline = Pipeline(SenFuNet(P.engine_config(settings), weights=None), Ingest(ingest_config(settings)))
    integrate_views(pipeline.engine, [(SPHERE_C, SPHERE_VIEWS[0])])
    errors: list[str] = []
    logger = SimpleNamespace(info=lambda text: None, warning=errors.append, error=errors.append)
    services = MapServices(pipeline, lambda: settings, SimpleNamespace(lock=threading.Lock(), resend_all=lambda: None,
                                                                    updates=UpdateSignal()),
                           logger)
    return services, pipeline, errors


def _call(handler: Any) -> Any:
    return handler(None, SimpleNamespace(success=None, message=None))


def test_load_map_of_a_map_damaged_inside_says_so_and_keeps_the_map(tmp_path):
    """A map whose bytes changed after ~/save_map wrote it (an incomplete copy, a failing disk): torch.load
    does not check the archive's checksums, so ~/load_map replaced the node's map by the damaged one and
    replied success."""
    services, pipeline, errors = _services(tmp_path, map_file="damaged.pt")
    assert _call(services.save_map).success
    before = pipeline.engine.extract_mesh("fused")
    path = tmp_path / "damaged.pt"
    with zipfile.ZipFile(path) as archive:
        member = max(archive.infolist(), key=lambda info: info.file_size)  # a grid pool's bytes
    data = bytearray(path.read_bytes())
    name_len, extra_len = struct.unpack("<HH", data[member.header_offset + 26:member.header_offset + 30])
    start = member.header_offset + 30 + name_len + extra_len + member.file_size // 2
    data[start:start + 64] = bytes(b ^ 0xFF for b in data[start:start + 64])
    path.write_bytes(bytes(data))
    reply = _call(services.load_map)
    assert not reply.success and f"{path} is damaged" in reply.message, reply.message
    assert errors and "damaged" in errors[-1]
    after = pipeline.engine.extract_mesh("fused")  # the node's map stays
    assert after.n_faces == before.n_faces and np.array_equal(after.vertices, before.vertices)


def test_load_map_of_a_map_that_cannot_be_read_says_why(tmp_path, monkeypatch):
    """A map the node may not read (another user's, mode 0600): the check for a zip archive took the
    refused open for a file that is no map and replied "is not a map ... or it is damaged"."""
    services, pipeline, _ = _services(tmp_path)
    assert _call(services.save_map).success
    path = tmp_path / "map.pt"
    path.chmod(0o000)  # refuses the open unless the tests run as root: then the open is refused by hand
    real_open = io.open

    def refusing_open(file: Any, *args: Any, **kwargs: Any) -> Any:
        if str(file) == str(path):
            raise PermissionError(errno.EACCES, "Permission denied", str(file))
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(io, "open", refusing_open)
    monkeypatch.setattr(builtins, "open", refusing_open)
    blocks = pipeline.engine.grid.n_blocks
    reply = _call(services.load_map)
    monkeypatch.undo()
    path.chmod(0o644)
    assert not reply.success and "Permission denied" in reply.message and str(path) in reply.message, reply.message
    assert "not a map" not in reply.message, reply.message
    assert pipeline.engine.grid.n_blocks == blocks


class _FullDisk:
    """A file on a disk that fills after `room` bytes: writes past it raise ENOSPC, as the kernel does."""

    def __init__(self, file: Any, room: int) -> None:
        self._file, self._room = file, room

    def write(self, data: Any) -> int:
        size = memoryview(data).nbytes
        if size > self._room:
            raise OSError(errno.ENOSPC, "No space left on device")
        self._room -= size
        return self._file.write(data)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._file, name)

    def __enter__(self) -> _FullDisk:
        return self

    def __exit__(self, *exc: object) -> None:
        self._file.close()


def test_save_map_on_a_full_disk_says_so_and_keeps_the_earlier_map_file(tmp_path, monkeypatch):
    """~/save_map when the disk fills while the map is written: torch turns the failed write into its own
    error, and the reply said "[enforce fail at inline_container.cc:...] . unexpected pos 400704 vs 598",
    nothing of a full disk. The earlier map file stays whole, no temporary file is left."""
    services, pipeline, _ = _services(tmp_path)
    assert _call(services.save_map).success
    path = tmp_path / "map.pt"
    earlier = path.read_bytes()
    integrate_views(pipeline.engine, [(SPHERE_C, SPHERE_VIEWS[1])])
    real_fdopen = os.fdopen
    monkeypatch.setattr(os, "fdopen", lambda *args, **kwargs: _FullDisk(real_fdopen(*args, **kwargs), 100_000))
    reply = _call(services.save_map)
    monkeypatch.undo()
    assert not reply.success and "No space left on device" in reply.message and str(path) in reply.message, \
        reply.message
    assert "unexpected pos" not in reply.message, reply.message
    assert path.read_bytes() == earlier and sorted(p.name for p in tmp_path.iterdir()) == ["map.pt", "p.yaml"]


def test_services_that_run_out_of_memory_say_so_and_keep_the_map(tmp_path, monkeypatch):
    """A bare MemoryError (an allocation of Python bytes, torch.load of a map too large for the memory
    left) has no text: ~/save_mesh replied "saving failed: ; check parameter output_dir" and ~/load_map
    "cannot read engine state ...: ", as if the file were damaged."""
    import senfunet_core.map_file
    import senfunet_core.ply

    services, pipeline, _ = _services(tmp_path)
    assert _call(services.save_map).success
    faces = pipeline.engine.extract_mesh("fused").n_faces

    def no_memory(*args: Any, **kwargs: Any) -> Any:
        raise MemoryError()

    monkeypatch.setattr(senfunet_core.ply, "write_ply", no_memory)
    monkeypatch.setattr(senfunet_core.map_file.torch, "load", no_memory)
    for handler in (services.save_mesh, services.load_map):
        reply = _call(handler)
        assert not reply.success and "out of memory" in reply.message and ": ;" not in reply.message, reply.message
        assert "cannot read" not in reply.message, reply.message
    monkeypatch.undo()
    assert pipeline.engine.extract_mesh("fused").n_faces == faces


def test_load_map_of_a_folder_says_it_is_a_folder(tmp_path):
    """map_file naming a folder (the folder of the maps, without the file): the reply said "no such map
    file" of a path that exists."""
    services, pipeline, _ = _services(tmp_path, map_file="maps")
    (tmp_path / "maps").mkdir()
    blocks = pipeline.engine.grid.n_blocks
    reply = _call(services.load_map)
    assert not reply.success and f"{tmp_path / 'maps'} is a folder" in reply.message, reply.message
    assert "no such" not in reply.message and "set parameter map_file" in reply.message, reply.message
    assert pipeline.engine.grid.n_blocks == blocks


def test_load_map_of_a_pipe_says_it_is_not_a_regular_file(tmp_path):
    """map_file naming a FIFO: the reply said "no such map file" of a path that exists (and opening
    one to read would wait for a writer)."""
    services, pipeline, _ = _services(tmp_path, map_file="map.pt")
    os.mkfifo(tmp_path / "map.pt")
    blocks = pipeline.engine.grid.n_blocks
    reply = _call(services.load_map)
    assert not reply.success and "is not a regular file" in reply.message, reply.message
    assert "no such" not in reply.message and pipeline.engine.grid.n_blocks == blocks


def test_load_map_of_another_version_or_another_torch_file_says_what_to_do(tmp_path):
    """A map a newer version wrote (another format), a tensor, the network weights: each was "not a
    SenFuNet engine state" (a newer map's user learnt neither why nor what to do) or, for a tensor,
    "cannot read engine state ...: 'Tensor' object has no attribute 'get'"."""
    import torch

    services, pipeline, _ = _services(tmp_path, map_file="other.pt")
    assert _call(services.save_map).success
    state = torch.load(tmp_path / "other.pt", weights_only=True)
    blocks = pipeline.engine.grid.n_blocks
    for saved, says in ((dict(state, format="senfunet-engine-2"), "another version of SenFuNet (senfunet-engine-2"),
                        (torch.zeros(3), "is not a SenFuNet engine state"),
                        ({"weights": torch.zeros(3)}, "is not a SenFuNet engine state")):
        torch.save(saved, tmp_path / "other.pt")
        reply = _call(services.load_map)
        assert not reply.success and says in reply.message, reply.message
        assert "fuse the recording again" in reply.message or "set parameter map_file" in reply.message, reply.message
        assert pipeline.engine.grid.n_blocks == blocks
    # a zip archive of something else: torch's "[enforce fail at inline_container.cc:...] file in archive is not in a
    # subdirectory" alone said neither what was wrong nor what to do
    with zipfile.ZipFile(tmp_path / "other.pt", "w") as archive:
        archive.writestr("readme.txt", "not a map")
    reply = _call(services.load_map)
    assert not reply.success and "is not a map ~/save_map wrote" in reply.message, reply.message
    assert "set parameter map_file" in reply.message and pipeline.engine.grid.n_blocks == blocks


def test_an_empty_map_does_not_replace_what_an_earlier_map_saved(tmp_path):
    """~/reset, then ~/save_mesh and ~/save_map: the empty map's files replaced the earlier map's
    (mesh.ply of a few hundred bytes, a map.pt of no blocks), with success replies. They are refused,
    the earlier files kept; into a folder without earlier files the empty map is saved as before."""
    services, pipeline, errors = _services(tmp_path)
    assert _call(services.save_mesh).success and _call(services.save_map).success
    earlier = {path.name: path.read_bytes() for path in tmp_path.glob("*") if path.suffix in (".ply", ".pt")}
    assert set(earlier) == {"mesh.ply", "tof.ply", "stereo.ply", "map.pt"}, set(earlier)
    assert _call(services.reset).success
    for handler, files in ((services.save_mesh, "mesh.ply"), (services.save_map, "map.pt")):
        reply = _call(handler)
        assert not reply.success and "the map is empty" in reply.message and files in reply.message, reply.message
        assert "~/load_map" in reply.message and errors[-1] == reply.message
    assert {name: (tmp_path / name).read_bytes() for name in earlier} == earlier
    elsewhere = services.save_meshes(tmp_path / "new")
    assert sorted(path.name for path in elsewhere) == sorted(name for name in earlier if name.endswith(".ply"))
    integrate_views(pipeline.engine, [(SPHERE_C, SPHERE_VIEWS[1])])  # fused again: saved over the earlier ones
    assert _call(services.save_mesh).success and _call(services.save_map).success


def test_save_map_below_a_file_names_the_file_in_the_way(tmp_path):
    """map_file /etc/hostname/map.pt: the reply was mkdir's "[Errno 17] File exists: '/etc/hostname'"."""
    (tmp_path / "a_file").write_text("")
    services, _, _ = _services(tmp_path, map_file=str(tmp_path / "a_file" / "maps" / "map.pt"))
    reply = _call(services.save_map)
    assert not reply.success and f"{tmp_path / 'a_file'} is a file, not a folder" in reply.message, reply.message
    assert "check parameters output_dir and map_file" in reply.message


def test_save_mesh_into_a_file_and_save_map_onto_a_pipe_say_what_is_in_the_way(tmp_path):
    """output_dir naming a file: ~/save_mesh replied mkdir's bare "[Errno 17] File exists"; map_file naming
    a FIFO: ~/save_map put a regular file in its place and replied "wrote"."""
    import os
    import stat

    (tmp_path / "a_file").write_text("")
    os.mkfifo(tmp_path / "pipe.pt")
    services, _, _ = _services(tmp_path, output_dir=str(tmp_path / "a_file"), map_file=str(tmp_path / "pipe.pt"))
    reply = _call(services.save_mesh)
    assert not reply.success and f"{tmp_path / 'a_file'} is a file, not a folder" in reply.message, reply.message
    reply = _call(services.save_map)
    assert not reply.success and "no regular file" in reply.message, reply.message
    assert stat.S_ISFIFO((tmp_path / "pipe.pt").lstat().st_mode)


def test_a_bound_given_up_for_a_spill_that_cannot_be_written_warns_on_the_status(tmp_path, monkeypatch):
    """Every eviction abandoned (a full spill disk) let the map grow to twice its bound while /diagnostics
    stayed OK: the only signs were ERROR lines in the log. The pipeline's status now warns while the map
    is over its bound for that reason, and clears once an eviction goes through."""
    import senfunet_core.spill as spill_module
    from senfunet_ros.health import HealthMonitor
    from senfunet_ros.node import LatencyStats
    from senfunet_ros.status import StatusReport

    class NoRoom:
        f_bavail, f_frsize = 1, 4096

    params = tmp_path / "p.yaml"
    params.write_text("senfunet:\n  ros__parameters:\n    max_map_blocks: 165\n    weights: none\n"
                      f"    output_dir: {tmp_path}\n    rgb_sensors: []\n")
    settings = load_settings(params)
    engine = SenFuNet(P.engine_config(settings), weights=None)
    sensors = {"tof": ("depth",), "stereo": ("depth",)}
    report = StatusReport(Pipeline(engine, Ingest(ingest_config(settings))),
                          HealthMonitor(sensors, window_s=60.0, stale_after_s=60.0), {}, LatencyStats(),
                          topics={s: {"depth": f"/{s}/depth"} for s in sensors}, hardware_id="/senfunet",
                          warn=lambda key, text: None, logger=None)
    monkeypatch.setattr("senfunet_ros.status.ENGINE_STATS_PERIOD_S", 0.0)

    def pipeline_status() -> Any:
        return next(s for s in report.message("map").status if s.name.endswith("pipeline"))

    integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]])
    engine.update()
    with monkeypatch.context() as patch:
        patch.setattr(spill_module.os, "statvfs", lambda fd: NoRoom())
        integrate_views(engine, far_views(2))
        engine.update()
    status = pipeline_status()
    assert status.level == b"\x01" and "over its bound max_map_blocks 165" in status.message, status.message
    integrate_views(engine, far_views(4)[2:])
    engine.update()
    assert engine.grid.n_blocks <= 165 and pipeline_status().level == b"\x00"
    # over the bound between updates, as a map is in normal running, with a spill that works again: OK
    integrate_views(engine, far_views(5)[4:])
    assert 165 < engine.grid.n_blocks and pipeline_status().level == b"\x00"
