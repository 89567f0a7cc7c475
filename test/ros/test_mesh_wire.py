"""~/mesh on the wire: the display mesh is decimated per block (the map and ~/save_mesh keep full
resolution), so a late subscriber's snapshot of the sample room stays small."""
from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "bags" / "sim_room"
SNAPSHOT_MAX_BYTES = 30_000_000


@pytest.mark.slow
def test_sample_room_snapshot_is_small_and_saved_mesh_full(capsys: pytest.CaptureFixture) -> None:
    from senfunet_core.decimate import decimate_block_meshes
    from senfunet_core.engine import SenFuNet
    from senfunet_ros import conversions as conv
    from senfunet_ros import params as P
    from senfunet_ros.ingest import Ingest
    from senfunet_ros.pipeline import Pipeline
    from senfunet_ros.replay import _fuse
    from senfunet_ros.params_file import load_settings

    settings = load_settings()  # the node's defaults
    engine = SenFuNet(P.engine_config(settings, alpha_dtype="float32"), weights=P.engine_weights(settings))
    pipeline = Pipeline(engine, Ingest(P.ingest_config(settings)))
    _fuse(SAMPLE, settings, pipeline, progress=False, log=lambda text: None)
    engine.update()
    meshes = engine.block_meshes()

    def snapshot_bytes(m: object) -> int:
        return sum(len(part) for part in conv.marker_array_messages(m, (), stamp_ns=1, frame_id="map",
                                                                    delete_all_first=True))

    full = snapshot_bytes(meshes)
    display = decimate_block_meshes(meshes, settings.mesh_display_cell_m)
    shown = snapshot_bytes(display)
    with capsys.disabled():
        print(f"\nsample room snapshot: full {full / 1e6:.1f} MB ({len(meshes.faces)} triangles), display "
              f"{shown / 1e6:.1f} MB ({len(display.faces)} triangles) at mesh_display_cell_m "
              f"{settings.mesh_display_cell_m}")
    assert shown < SNAPSHOT_MAX_BYTES < full
    assert len(display) == len(meshes)  # one marker per block still
    assert engine.extract_mesh("fused").n_faces >= len(meshes.faces) * 0.9  # the saved mesh: full resolution
