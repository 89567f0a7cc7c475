"""Files written whole or not at all (`senfunet_core.files`): maps and meshes."""
from __future__ import annotations

from pathlib import Path

import pytest

from senfunet_core.errors import InputError
from senfunet_core.files import atomic_file


def test_atomic_file_replaces_the_file_whole_or_leaves_it_and_no_trace(tmp_path: Path) -> None:
    target = tmp_path / "map.pt"
    with atomic_file(target) as file:
        file.write(b"first")
    assert target.read_bytes() == b"first"
    with pytest.raises(RuntimeError), atomic_file(target) as file:
        file.write(b"second, half")
        raise RuntimeError("disk full")
    assert target.read_bytes() == b"first" and [p.name for p in tmp_path.iterdir()] == ["map.pt"]
    with pytest.raises(InputError, match="folder"), atomic_file(tmp_path):
        pass
    assert not [p for p in tmp_path.parent.iterdir() if p.name.startswith(f".{tmp_path.name}.")]
    with atomic_file(tmp_path / "new" / "mesh.ply") as file:  # missing folders are made
        file.write(b"ply")
    assert (tmp_path / "new" / "mesh.ply").read_bytes() == b"ply"
