"""`senfunet_core.files`: files written whole or not at all (maps and meshes); folders held in RAM."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from senfunet_core.errors import InputError
from senfunet_core.files import atomic_file, memory_filesystem


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


def test_files_written_whole_are_readable_by_other_users(tmp_path: Path) -> None:
    """`demo --live-mesh`'s live_mesh.ply and `simulate --gt`'s mesh were 0600 (the temporary file's mode):
    every file written through atomic_file is 0644 now, as the meshes, maps and stats are."""
    from senfunet_core.mesher import Mesh
    from senfunet_core.ply import write_ply

    with atomic_file(tmp_path / "stats.json") as file:
        file.write(b"{}")
    triangle = Mesh(np.eye(3, dtype=np.float32), np.array([[0, 1, 2]], np.int32))
    write_ply(tmp_path / "live_mesh.ply", triangle)
    assert {p.name: p.stat().st_mode & 0o777 for p in tmp_path.iterdir()} == {"stats.json": 0o644,
                                                                              "live_mesh.ply": 0o644}



def test_atomic_file_writes_a_links_target_and_never_replaces_a_pipe_or_a_device(tmp_path: Path) -> None:
    """A save to a path that is a FIFO, a device or a socket put a regular file in its place (as root, a
    map_file of /dev/null replaced the machine's /dev/null); a symbolic link was replaced by a file,
    its target left with the earlier map."""
    import os
    import stat

    fifo = tmp_path / "fifo.pt"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="no regular file"), atomic_file(fifo) as file:
        file.write(b"map")
    assert stat.S_ISFIFO(fifo.lstat().st_mode) and sorted(p.name for p in tmp_path.iterdir()) == ["fifo.pt"]
    target = tmp_path / "maps" / "map.pt"
    target.parent.mkdir()
    target.write_bytes(b"earlier map")
    link = tmp_path / "latest.pt"
    link.symlink_to(target)
    with atomic_file(link) as file:
        file.write(b"new map")
    assert link.is_symlink() and target.read_bytes() == b"new map"
    dangling = tmp_path / "next.pt"
    dangling.symlink_to(tmp_path / "maps" / "next_target.pt")
    with atomic_file(dangling) as file:
        file.write(b"first")
    assert dangling.is_symlink() and (tmp_path / "maps" / "next_target.pt").read_bytes() == b"first"
    for folder_name in (tmp_path / "missing" / "..", tmp_path / "."):
        with pytest.raises(InputError, match="folder"), atomic_file(folder_name):
            pass
    assert not (tmp_path / "missing").exists()

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


def test_a_folder_on_a_file_system_in_memory_is_told_apart(tmp_path: Path, monkeypatch, caplog) -> None:
    """/tmp as tmpfs (Debian 13, Fedora, Arch; and /dev/shm everywhere): the map bound's evicted voxels
    and meshes went there and still took RAM, which the bound is meant to free, unsaid. The folder's
    file system is the one of the longest mount point holding it."""
    import logging
    import tempfile

    from senfunet_core.engine import EngineConfig, SenFuNet

    mounts = tmp_path / "mounts"
    mounts.write_text("/dev/vda / ext4 rw 0 0\ntmpfs /tmp tmpfs rw 0 0\n/dev/vdb /tmp/disk ext4 rw 0 0\n"
                      "tmpfs /run/user/1000 tmpfs rw 0 0\n/dev/vdc /mnt/my\\040disk ext4 rw 0 0\n")
    assert memory_filesystem("/tmp/senfunet", mounts=mounts) == "tmpfs"
    assert memory_filesystem("/tmp/disk/spill", mounts=mounts) is None
    assert memory_filesystem("/tmpfoo", mounts=mounts) is None  # a prefix of the name is no mount point
    assert memory_filesystem("/mnt/my disk/x", mounts=mounts) is None
    assert memory_filesystem("/home", mounts=mounts) is None
    if memory_filesystem("/dev/shm") != "tmpfs":
        pytest.skip("/dev/shm is no tmpfs here")
    monkeypatch.setattr(tempfile, "tempdir", "/dev/shm")
    with caplog.at_level(logging.WARNING, logger="senfunet.engine"):
        SenFuNet(EngineConfig(max_blocks=1000), weights=None)
    assert any("/dev/shm" in r.getMessage() and "set TMPDIR" in r.getMessage() for r in caplog.records), caplog.text
