"""The node's map services and its map bound (max_map_blocks), without DDS."""
from __future__ import annotations

import logging
import sys
import threading
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "core"))

from senfunet_core.engine import SenFuNet  # noqa: E402
from senfunet_core.map_file import save_map  # noqa: E402
from senfunet_ros import params as P  # noqa: E402
from senfunet_ros.ingest import Ingest  # noqa: E402
from senfunet_ros.map_services import MapServices  # noqa: E402
from senfunet_ros.pipeline import Pipeline  # noqa: E402
from senfunet_ros.replay import ingest_config, load_settings  # noqa: E402
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
    services = MapServices(pipeline, lambda: settings, SimpleNamespace(lock=threading.Lock(), resend_all=lambda: None),
                           logging.getLogger("test"))
    reply = services.load_map(None, SimpleNamespace(success=None, message=None))
    assert reply.success, reply.message
    engine = pipeline.engine
    assert engine.max_blocks == 165
    integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[1:3]] + far_views(3))
    engine.update()
    assert engine.grid.n_blocks <= 165 and engine.stats()["evicted_blocks"] > 0


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
    services = MapServices(pipeline, lambda: settings, SimpleNamespace(lock=threading.Lock(), resend_all=lambda: None),
                           logging.getLogger("test"))
    reply = services.save_mesh(None, SimpleNamespace(success=None, message=None))
    assert reply.success and "evicted" in reply.message
    assert any(level == "warning" and "tof.ply" in text and "evicted" in text for level, text in logged)
