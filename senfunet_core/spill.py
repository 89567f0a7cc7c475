"""Evicted blocks' voxel data on disk, until the sensors reach them again.

The map bound (EngineConfig.max_blocks) evicts the blocks farthest from the sensors. Their rows of
every grid channel go here, compressed, into an anonymous temporary file (it vanishes with the
process); when a frame's samples land in such a block again, the grid takes its rows back instead of
starting the block empty (`BlockGrid.commit_new_blocks`), so the block goes on averaging where it
left off and the bounded map fuses what an unbounded one does. Saved maps include the spilled blocks.
`BlockSpill` turns block rows into compressed blobs and back; `BlobFile` keeps the blobs by key in
the file and rewrites it when the blocks taken back leave too many holes.

Single-threaded by itself: the engine's data lock serialises its users.
"""
from __future__ import annotations

import errno
import logging
import os
import tempfile
from collections.abc import Iterable
from typing import IO

import numpy as np
import zstandard

__all__ = ["BlobFile", "BlockSpill", "spilled_rows"]

log = logging.getLogger("senfunet.engine")

# Rewrite the file once the space of dropped blobs exceeds both this and the space still in use.
_COMPACT_MIN_BYTES = 64 << 20


class BlobFile:
    """Byte strings by key in an anonymous temporary file (it vanishes with the process): appended
    after the others, read back, dropped; the file is rewritten without the dropped ones once they
    take more space than `_COMPACT_MIN_BYTES` and than the ones still held."""

    def __init__(self, directory: str | None = None) -> None:
        self.directory = directory
        self.index: dict[int, tuple[int, int]] = {}  # key -> (offset, length) in the file
        self._file: IO[bytes] | None = None
        self._end = 0  # bytes written
        self._dead = 0  # bytes of blobs dropped or replaced since the last compaction
        self.compact_failures = 0  # compactions abandoned (a full disk): the file kept its holes

    @property
    def nbytes(self) -> int:
        """Bytes on disk of the blobs held."""
        return self._end - self._dead

    def append(self, blobs: Iterable[tuple[int, bytes | memoryview]]) -> None:
        """Write these (key, blob) after the others; a key held already gets the newer blob. All or
        none: after an OSError the file holds what it held before (and the error is raised)."""
        previous: dict[int, tuple[int, int] | None] = {}  # to undo a failed write
        end, dead = self._end, self._dead
        try:
            file = self._open()
            file.seek(self._end)
            for key, blob in blobs:
                if file.write(blob) != len(blob):  # a disk that fills takes part of a write
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                entry = self.index.get(key)
                previous.setdefault(key, entry)
                if entry is not None:
                    self._dead += entry[1]
                self.index[key] = (self._end, len(blob))
                self._end += len(blob)
        except OSError:
            for key, entry in previous.items():
                if entry is None:
                    self.index.pop(key, None)
                else:
                    self.index[key] = entry
            self._end, self._dead = end, dead
            raise

    def read(self, key: int) -> bytes:
        assert self._file is not None
        offset, length = self.index[key]
        self._file.seek(offset)
        return self._file.read(length)

    def drop(self, keys: Iterable[int]) -> None:
        """Forget these keys' blobs (the file is compacted when their holes are due)."""
        for key in keys:
            self._dead += self.index.pop(key)[1]
        if self._dead > max(_COMPACT_MIN_BYTES, self._end - self._dead):
            self._compact()

    def clear(self) -> None:
        if self._file is not None:
            self._file.close()
        self._file = None
        self.index.clear()
        self._end = self._dead = 0

    def _open(self) -> IO[bytes]:
        if self._file is None:
            # a temporary folder a cleaner removed while the node ran: made again, as it was
            os.makedirs(self.directory or tempfile.gettempdir(), exist_ok=True)
            # unbuffered: a write that fails (a full disk) fails in `append`, which undoes it; a buffered
            # one failed at a later flush, in `read` under a frame's block allocation, the blobs unreadable
            self._file = tempfile.TemporaryFile(buffering=0, prefix="senfunet-spill-", dir=self.directory)
        return self._file

    def check_room(self, nbytes: int) -> None:
        """OSError unless the file can be opened and its disk has `nbytes` free (what a write of that
        much would need), so that a caller learns it before the work whose result it would write."""
        file = self._open()
        try:
            descriptor = file.fileno()
        except (OSError, ValueError):  # not a file of the operating system's: its room is unknown
            return
        free = os.statvfs(descriptor)
        if free.f_bavail * free.f_frsize < nbytes:
            raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} ({free.f_bavail * free.f_frsize / 1e6:.0f} MB "
                          f"free, {nbytes / 1e6:.0f} MB needed)")

    def _compact(self) -> None:
        """Copy the blobs still held into a fresh file (dropped ones leave holes), one at a time. When the
        fresh file cannot be written (a full disk) the old one stays, holes and all."""
        old, index, end, dead = self._file, self.index, self._end, self._dead
        self._file, self.index, self._end, self._dead = None, {}, 0, 0
        assert old is not None
        try:
            file = self._open()
            for key, (offset, length) in index.items():
                old.seek(offset)
                if file.write(old.read(length)) != length:  # a disk that fills takes part of a write
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                self.index[key] = (self._end, length)
                self._end += length
        except OSError as err:
            if self._file is not None:
                self._file.close()
            self._file, self.index, self._end, self._dead = old, index, end, dead
            self.compact_failures += 1
            log.log(logging.WARNING if self.compact_failures == 1 else logging.DEBUG,
                    "spill: the file of evicted blocks keeps the holes of the blocks taken back, its compacted "
                    "copy could not be written (%s); free space in %s (warned once)", err,
                    self.directory or tempfile.gettempdir())
            return
        old.close()


class BlockSpill:
    """Block rows by block key: `put` when evicted, `take` when allocated again; each block's rows
    compressed into one blob of a `BlobFile`."""

    def __init__(self, directory: str | None = None) -> None:
        self._blobs = BlobFile(directory)
        self.restored = 0  # blocks taken back so far
        self._compressor = zstandard.ZstdCompressor(level=1)  # fast: evictions hold the engine's data lock
        self._decompressor = zstandard.ZstdDecompressor()

    def __len__(self) -> int:
        return len(self._blobs.index)

    def __contains__(self, key: int) -> bool:
        return int(key) in self._blobs.index

    @property
    def nbytes(self) -> int:
        """Bytes on disk held by spilled blocks (compressed)."""
        return self._blobs.nbytes

    @property
    def compact_failures(self) -> int:
        """Compactions of the file abandoned (a full disk): it keeps the holes of the blocks taken back."""
        return self._blobs.compact_failures

    def holds(self, keys: np.ndarray) -> np.ndarray:
        """Which of these block keys are spilled (bool per key)."""
        index = self._blobs.index
        return np.fromiter((key in index for key in keys.tolist()), np.bool_, len(keys))

    def check_room(self, n_blocks: int, block_nbytes: int) -> None:
        """OSError (as `put` raises it) unless `n_blocks` blocks of `block_nbytes` each, uncompressed (the
        most they take), can be spilled now: checked before an eviction judges and meshes them."""
        try:
            self._blobs.check_room(n_blocks * block_nbytes)
        except OSError as err:
            raise self._cannot_write(err) from err

    def _cannot_write(self, err: OSError) -> OSError:
        where = self._blobs.directory or tempfile.gettempdir()
        return OSError(f"cannot write evicted blocks to the spill file in {where}: {err}; free disk space there, "
                       "point TMPDIR at a disk with room (read when the node starts), or raise the map bound "
                       "(max_map_blocks)")

    def put(self, keys: np.ndarray, rows: list[np.ndarray]) -> None:
        """Spill blocks: keys (N int64) and, per channel, its N rows (any dtype, N first)."""
        if len(keys) == 0:
            return
        flat = [np.ascontiguousarray(r).reshape(len(keys), -1).view(np.uint8) for r in rows]
        try:  # spilled before and not taken back: the newer rows win
            self._blobs.append((key, self._compressor.compress(b"".join(channel[n].tobytes() for channel in flat)))
                               for n, key in enumerate(keys.tolist()))
        except OSError as err:  # none of them spilled: the caller keeps the blocks in memory
            raise self._cannot_write(err) from err

    def take(self, keys: np.ndarray, rows: list[np.ndarray]) -> np.ndarray:
        """Restore the spilled blocks among `keys` into `rows` (per channel, N rows each, written in
        place) and forget them here; returns which of the N were restored."""
        found = self.peek(keys, rows)
        taken = keys[found].tolist()
        self._blobs.drop(taken)
        self.restored += len(taken)
        return found

    def peek(self, keys: np.ndarray, rows: list[np.ndarray]) -> np.ndarray:
        """As `take`, but the blocks stay spilled: their rows read for a look (evaluation)."""
        found = self.holds(keys)
        if not found.any():
            return found
        flat = [r.reshape(len(keys), -1).view(np.uint8) for r in rows]
        if not all(np.may_share_memory(f, r) for f, r in zip(flat, rows)):
            raise ValueError("take() writes into `rows`: pass views whose rows reshape without a copy")
        sizes = [channel.shape[1] for channel in flat]
        for n in np.flatnonzero(found).tolist():
            data = np.frombuffer(self._decompressor.decompress(self._blobs.read(int(keys[n]))), np.uint8)
            start = 0
            for channel, size in zip(flat, sizes):
                channel[n] = data[start:start + size]
                start += size
        return found

    def clear(self) -> None:
        self._blobs.clear()
        self.restored = 0

    def state_dict(self) -> dict[str, np.ndarray]:
        """Keys, lengths and the compressed blobs, for a saved map."""
        index = self._blobs.index
        keys = np.fromiter(index, np.int64, len(index))
        lengths = np.array([index[k][1] for k in keys.tolist()], np.int64)
        blobs = np.empty(int(lengths.sum()), np.uint8)
        start = 0
        for key, length in zip(keys.tolist(), lengths.tolist()):
            blobs[start:start + length] = np.frombuffer(self._blobs.read(key), np.uint8)
            start += length
        return {"keys": keys, "lengths": lengths, "blobs": blobs}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.clear()
        data = np.ascontiguousarray(state["blobs"], np.uint8).data
        ends = np.cumsum(state["lengths"]).tolist()
        self._blobs.append((key, data[end - length:end])
                           for key, end, length in zip(state["keys"].tolist(), ends, state["lengths"].tolist()))


def spilled_rows(state: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The blocks of a saved spill (`BlockSpill.state_dict`): their keys (N int64) and rows, decompressed
    (N x row bytes, uint8: each channel's row after the other, in the channel order they were put with)."""
    decompressor = zstandard.ZstdDecompressor()
    ends = np.cumsum(state["lengths"])
    blobs = np.ascontiguousarray(state["blobs"], np.uint8)
    rows = [np.frombuffer(decompressor.decompress(blobs[end - length:end].tobytes()), np.uint8)
            for end, length in zip(ends.tolist(), np.asarray(state["lengths"]).tolist())]
    return np.asarray(state["keys"], np.int64), np.stack(rows) if rows else np.zeros((0, 0), np.uint8)
