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


def test_atomic_file_is_on_disk_before_it_takes_the_name(tmp_path: Path, monkeypatch) -> None:
    """The rename came without an fsync: a robot switched off right after a save (save_on_shutdown) could
    find mesh.ply or map.pt empty or half written under its final name (the rename on disk, the data
    not yet). The data is synced before the file takes the name; a sync that fails (a full disk found
    late) leaves the earlier file."""
    import errno
    import os

    target = tmp_path / "mesh.ply"
    target.write_bytes(b"earlier")
    events: list[str] = []
    fsync, replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: (events.append("fsync"), fsync(fd))[1])
    monkeypatch.setattr(os, "replace", lambda *args: (events.append("replace"), replace(*args))[1])
    with atomic_file(target) as file:
        file.write(b"whole")
    assert events == ["fsync", "replace"] and target.read_bytes() == b"whole"

    def no_room(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", no_room)
    with pytest.raises(OSError, match="No space left"), atomic_file(target) as file:
        file.write(b"next")
    assert target.read_bytes() == b"whole" and [p.name for p in tmp_path.iterdir()] == ["mesh.ply"]
