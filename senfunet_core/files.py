"""Files written whole or not at all; whether a folder lies in memory; what a YAML file has wrong, in one line."""
from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from .errors import InputError


FILE_MODE = 0o644  # files written whole: maps, meshes, statistics


@contextlib.contextmanager
def atomic_file(path: str | Path) -> Iterator[BinaryIO]:
    """A binary file to write `path` through: a temporary file in the same folder (so that the
    final rename stays on one file system) that replaces `path` when the block ends, once its data is
    on disk (fsync), and is removed when it raises; the file is FILE_MODE (a temporary file's 0600 would
    keep meshes and maps from other users and tools). A symbolic link's target is written (the link
    stays). InputError when `path` is a folder, or exists and is no regular file (a pipe, a device:
    the rename would put a file in its place)."""
    path = Path(path)
    if path.is_dir() or path.name in ("", ".", ".."):
        raise InputError(f"{path} is a folder; give a file path")
    if path.is_symlink():
        path = Path(os.path.realpath(path))
        if path.is_dir():
            raise InputError(f"{path} (where the link points) is a folder; give a file path")
    if path.exists() and not path.is_file():
        raise InputError(f"{path} exists and is no regular file (a pipe, a device or a socket?): it is not "
                         "replaced; give the path of a regular file or of a new one")
    directory = path.parent if str(path.parent) else Path(".")
    directory.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        os.fchmod(fd, FILE_MODE)
        with os.fdopen(fd, "wb") as file:
            yield file
            # on disk before its name: a robot switched off after a save (save_on_shutdown) could find the
            # final name on an empty or half-written file (the rename reached the disk, the data not yet)
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


_MEMORY_FILESYSTEMS = ("tmpfs", "ramfs")


def memory_filesystem(folder: str | Path, *, mounts: Path = Path("/proc/self/mounts")) -> str | None:
    """The file system type when `folder` lies on one held in RAM (tmpfs, ramfs: /tmp on many
    distributions), else None (also when the mounts cannot be read). Files there take memory."""
    try:
        table = [line.split() for line in mounts.read_text().splitlines()]
    except OSError:
        return None
    real = os.path.realpath(folder)
    # the longest mount point holding the folder (the last of equal ones: mounted over the others)
    best: tuple[int, str] | None = None
    for fields in table:
        if len(fields) < 3:
            continue
        point = fields[1].replace("\\040", " ")
        inside = real == point or real.startswith(point.rstrip("/") + "/")
        if inside and (best is None or len(point) >= best[0]):
            best = (len(point), fields[2])
    return best[1] if best is not None and best[1] in _MEMORY_FILESYSTEMS else None


def yaml_error_text(err: Exception) -> str:
    """What a yaml.YAMLError says, in one line, with where: "not valid YAML (line 4, column 1): ..."."""
    mark = getattr(err, "problem_mark", None)
    where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
    problem = getattr(err, "problem", None) or str(err).splitlines()[0]
    return f"not valid YAML{where}: {problem}"
