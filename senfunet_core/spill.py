"""Evicted blocks' voxel data on disk, until the sensors reach them again.

The map bound (EngineConfig.max_blocks) evicts the blocks farthest from the sensors. Their rows of
every grid channel go here, compressed, into an anonymous temporary file (it vanishes with the
process); when a frame's samples land in such a block again, the grid takes its rows back instead of
starting the block empty (`BlockGrid.commit_new_blocks`), so the block goes on averaging where it
left off and the bounded map fuses what an unbounded one does. Saved maps include the spilled blocks.

Single-threaded by itself: the engine's data lock serialises its users.
"""
from __future__ import annotations

import tempfile
from typing import IO

import numpy as np
import zstandard

__all__ = ["BlockSpill", "spilled_rows"]

# Rewrite the file once the space of taken blocks exceeds both this and the space still in use.
_COMPACT_MIN_BYTES = 64 << 20


class BlockSpill:
    """Block rows by block key: `put` when evicted, `take` when allocated again."""

    def __init__(self, directory: str | None = None) -> None:
        self._directory = directory
        self._file: IO[bytes] | None = None
        self._index: dict[int, tuple[int, int]] = {}  # key -> (offset, length) in the file
        self._end = 0  # bytes written
        self._dead = 0  # bytes of blocks taken back since the last compaction
        self.restored = 0  # blocks taken back so far
        self._compressor = zstandard.ZstdCompressor(level=1)  # fast: evictions hold the engine's data lock
        self._decompressor = zstandard.ZstdDecompressor()

    def __len__(self) -> int:
        return len(self._index)

    def __contains__(self, key: int) -> bool:
        return int(key) in self._index

    @property
    def nbytes(self) -> int:
        """Bytes on disk held by spilled blocks (compressed)."""
        return self._end - self._dead

    def holds(self, keys: np.ndarray) -> np.ndarray:
        """Which of these block keys are spilled (bool per key)."""
        index = self._index
        return np.fromiter((key in index for key in keys.tolist()), np.bool_, len(keys))

    def put(self, keys: np.ndarray, rows: list[np.ndarray]) -> None:
        """Spill blocks: keys (N int64) and, per channel, its N rows (any dtype, N first)."""
        if len(keys) == 0:
            return
        flat = [np.ascontiguousarray(r).reshape(len(keys), -1).view(np.uint8) for r in rows]
        previous = {key: self._index.get(key) for key in keys.tolist()}  # to undo a failed write
        end, dead = self._end, self._dead
        try:
            file = self._open()
            file.seek(self._end)
            for n, key in enumerate(keys.tolist()):
                blob = self._compressor.compress(b"".join(channel[n].tobytes() for channel in flat))
                file.write(blob)
                if key in self._index:  # spilled before and not taken back: the newer rows win
                    self._dead += self._index[key][1]
                self._index[key] = (self._end, len(blob))
                self._end += len(blob)
        except OSError as err:  # none of them spilled: the caller keeps the blocks in memory
            for key, entry in previous.items():
                if entry is None:
                    self._index.pop(key, None)
                else:
                    self._index[key] = entry
            self._end, self._dead = end, dead
            where = self._directory or tempfile.gettempdir()
            raise OSError(f"cannot write evicted blocks to the spill file in {where}: {err}; free disk space "
                          "there, point TMPDIR at a disk with room, or raise the map bound (max_map_blocks)") from err

    def take(self, keys: np.ndarray, rows: list[np.ndarray]) -> np.ndarray:
        """Restore the spilled blocks among `keys` into `rows` (per channel, N rows each, written in
        place) and forget them here; returns which of the N were restored."""
        found = self.holds(keys)
        if not found.any():
            return found
        assert self._file is not None
        flat = [r.reshape(len(keys), -1).view(np.uint8) for r in rows]
        if not all(np.may_share_memory(f, r) for f, r in zip(flat, rows)):
            raise ValueError("take() writes into `rows`: pass views whose rows reshape without a copy")
        sizes = [channel.shape[1] for channel in flat]
        for n in np.flatnonzero(found).tolist():
            offset, length = self._index.pop(int(keys[n]))
            self._file.seek(offset)
            data = np.frombuffer(self._decompressor.decompress(self._file.read(length)), np.uint8)
            start = 0
            for channel, size in zip(flat, sizes):
                channel[n] = data[start:start + size]
                start += size
            self._dead += length
        self.restored += int(found.sum())
        if self._dead > max(_COMPACT_MIN_BYTES, self._end - self._dead):
            self._compact()
        return found

    def clear(self) -> None:
        if self._file is not None:
            self._file.close()
        self._file = None
        self._index.clear()
        self._end = self._dead = 0

    def state_dict(self) -> dict[str, np.ndarray]:
        """Keys, lengths and the compressed blobs, for a saved map."""
        keys = np.fromiter(self._index, np.int64, len(self._index))
        lengths = np.array([self._index[k][1] for k in keys.tolist()], np.int64)
        blobs = np.empty(int(lengths.sum()), np.uint8)
        start = 0
        for key, length in zip(keys.tolist(), lengths.tolist()):
            blobs[start:start + length] = np.frombuffer(self._read(key), np.uint8)
            start += length
        return {"keys": keys, "lengths": lengths, "blobs": blobs}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.clear()
        file = self._open()
        data = np.ascontiguousarray(state["blobs"], np.uint8)
        file.write(data.tobytes())
        offsets = np.concatenate([[0], np.cumsum(state["lengths"])[:-1]]).astype(np.int64)
        for key, offset, length in zip(state["keys"].tolist(), offsets.tolist(), state["lengths"].tolist()):
            self._index[key] = (offset, length)
        self._end = len(data)

    def _read(self, key: int) -> bytes:
        assert self._file is not None
        offset, length = self._index[key]
        self._file.seek(offset)
        return self._file.read(length)

    def _open(self) -> IO[bytes]:
        if self._file is None:
            self._file = tempfile.TemporaryFile(prefix="senfunet-spill-", dir=self._directory)
        return self._file

    def _compact(self) -> None:
        """Copy the blocks still spilled into a fresh file (taken ones leave holes), one at a time."""
        old, index = self._file, self._index
        self._file, self._index, self._end, self._dead = None, {}, 0, 0
        file = self._open()
        assert old is not None
        for key, (offset, length) in index.items():
            old.seek(offset)
            file.write(old.read(length))
            self._index[key] = (self._end, length)
            self._end += length
        old.close()


def spilled_rows(state: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The blocks of a saved spill (`BlockSpill.state_dict`): their keys (N int64) and rows, decompressed
    (N x row bytes, uint8: each channel's row after the other, in the channel order they were put with)."""
    decompressor = zstandard.ZstdDecompressor()
    ends = np.cumsum(state["lengths"])
    blobs = np.ascontiguousarray(state["blobs"], np.uint8)
    rows = [np.frombuffer(decompressor.decompress(blobs[end - length:end].tobytes()), np.uint8)
            for end, length in zip(ends.tolist(), np.asarray(state["lengths"]).tolist())]
    return np.asarray(state["keys"], np.int64), np.stack(rows) if rows else np.zeros((0, 0), np.uint8)
