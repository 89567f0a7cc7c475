"""`senfunet replay` without --compare names the comparison meshes an earlier run left in --out."""
from __future__ import annotations

import argparse
from pathlib import Path

from senfunet_ros.commands.replay import _stale_meshes
from senfunet_ros.replay import ReplayResult


def test_stale_comparison_meshes_are_named(tmp_path: Path):
    for name in ("mesh", "tof", "stereo", "tsdf_fusion", "other"):
        (tmp_path / f"{name}.ply").write_bytes(b"")
    result = ReplayResult(stats={"sensors": {"tof": {}, "stereo": {}}},
                          files={"mesh": tmp_path / "mesh.ply", "stats": tmp_path / "stats.json"})
    args = argparse.Namespace(out=str(tmp_path), compare=False)
    assert _stale_meshes(result, args) == ["stereo.ply", "tof.ply", "tsdf_fusion.ply"]
    result.files.update({n: tmp_path / f"{n}.ply" for n in ("tof", "stereo", "tsdf_fusion")})
    assert _stale_meshes(result, argparse.Namespace(out=str(tmp_path), compare=True)) == []
