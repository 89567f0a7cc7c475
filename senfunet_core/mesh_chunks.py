"""Block meshes by block key in chunks whose cost does not grow with their number: the mesh archive's storage.

A long run under a map bound archives the meshes of ever more evicted blocks. One array of them all
would be copied whole at every eviction and held in RAM outside the bound; here each `put` is a
new chunk, and chunks of similar size merge (each mesh is copied a logarithmic number of times).
A chunk of `seal_bytes` or more is written to an unlinked temporary file and read through one
memory map (the kernel pages it in and out; the file vanishes with the process), up to
`MAX_CHUNK_BYTES` a chunk, so that few files stay open and no merge holds more than that. A chunk
most of whose blocks were replaced is rewritten with the rest. Blocks are found by binary search
in each chunk's sorted keys: no per-key Python objects.

Single-threaded: its one owner (the mesh archive, under the engine's update lock) serialises calls.
"""
from __future__ import annotations

import dataclasses
import logging
import tempfile
from collections.abc import Iterator

import numpy as np
import torch

from .grid import block_keys
from .mesher import BlockMeshes

__all__ = ["FIELD_NAMES", "MeshChunks", "SEAL_BYTES", "packed_keys"]

log = logging.getLogger(__name__)

SEAL_BYTES = 32 << 20  # a chunk this large goes to disk: what stays in RAM is at most a few times it
MAX_CHUNK_BYTES_PER_SEAL = 8  # chunks merge up to this many times seal_bytes
_FIELDS = (("keys", np.int64), ("vertices", np.float32), ("colors", np.float32), ("faces", np.int32),
           ("vertex_offsets", np.int64), ("face_offsets", np.int64))
FIELD_NAMES = tuple(name for name, _ in _FIELDS)  # BlockMeshes' arrays, in its order
_ALIGN = 64  # bytes: where each array starts in a chunk's file


@dataclasses.dataclass(eq=False)
class _Chunk:
    meshes: BlockMeshes  # in RAM, or memory-mapped from its file
    packed: np.ndarray  # its packed block keys (`grid.block_keys`), sorted
    order: np.ndarray  # the row of each of them in `meshes`
    alive: np.ndarray  # per row: False once a later put replaced it
    on_disk: bool = False

    @property
    def nbytes(self) -> int:
        return _nbytes(self.meshes)

    def alive_meshes(self) -> BlockMeshes:
        """The blocks not replaced (copies, or the chunk's own arrays when it has no dead block)."""
        return self.meshes if self.alive.all() else self.meshes.select(np.flatnonzero(self.alive))

    def rows(self, packed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(which of these keys are alive here, their rows)."""
        if not len(self.packed):
            return np.zeros(len(packed), bool), np.zeros(0, np.int64)
        at = np.minimum(np.searchsorted(self.packed, packed), len(self.packed) - 1)
        rows = self.order[at]
        found = (self.packed[at] == packed) & self.alive[rows]
        return found, rows[found]


def _nbytes(meshes: BlockMeshes) -> int:
    return sum(getattr(meshes, name).nbytes for name in FIELD_NAMES)


def packed_keys(coords: np.ndarray) -> np.ndarray:
    """Block coordinates (... x 3, any array, memory-mapped ones too) -> `grid.block_keys` (int64, flat)."""
    return block_keys(torch.from_numpy(np.array(coords, np.int64).reshape(-1, 3))).numpy()


def _new_chunk(meshes: BlockMeshes, *, on_disk: bool) -> _Chunk:
    packed = packed_keys(meshes.keys)
    order = np.argsort(packed, kind="stable")
    return _Chunk(meshes, packed[order], order, np.ones(len(packed), bool), on_disk=on_disk)


def _on_disk(parts: list[BlockMeshes], directory: str | None) -> BlockMeshes:
    """These meshes, joined, written to an unlinked temporary file and read back through one memory map."""
    bases = {name: np.cumsum([0] + [getattr(p, name)[-1] for p in parts])
             for name in ("vertex_offsets", "face_offsets")}
    layout = []
    with tempfile.TemporaryFile(dir=directory) as file:  # the map keeps the file until it goes
        for name, dtype in _FIELDS:
            start = -(-file.tell() // _ALIGN) * _ALIGN
            file.seek(start)
            if name in bases:  # each part's offsets from where the parts before it end
                pieces = [getattr(p, name)[:-1] + base for p, base in zip(parts, bases[name])] + [bases[name][-1:]]
            else:
                pieces = [getattr(p, name) for p in parts]
            for piece in pieces:
                np.ascontiguousarray(piece, dtype).tofile(file)
            rows = sum(len(piece) for piece in pieces)
            layout.append((start, dtype, (rows, 3) if name not in bases else (rows,)))
        file.flush()
        raw = np.memmap(file, dtype=np.uint8, mode="r")
    return BlockMeshes(*(raw[start:start + int(np.prod(shape)) * np.dtype(dtype).itemsize].view(dtype).reshape(shape)
                         for start, dtype, shape in layout))


class MeshChunks:
    """Packed block key -> mesh: `put` replaces and removes, `select` reads, `parts` is every one."""

    def __init__(self, *, directory: str | None = None, seal_bytes: int = SEAL_BYTES) -> None:
        self.directory = directory  # of the temporary files (None: the system's temporary directory)
        self.seal_bytes = seal_bytes
        self._chunks: list[_Chunk] = []
        self.n_blocks = 0
        self.n_faces = 0
        self.seal_failures = 0  # chunks kept in RAM because their file could not be written

    def __len__(self) -> int:
        return self.n_blocks

    @property
    def bytes_in_memory(self) -> int:
        return sum(c.packed.nbytes + c.alive.nbytes + (0 if c.on_disk else c.nbytes) for c in self._chunks)

    @property
    def bytes_on_disk(self) -> int:
        return sum(c.nbytes for c in self._chunks if c.on_disk)

    def find(self, packed: np.ndarray) -> list[tuple[_Chunk, np.ndarray, np.ndarray]]:
        """Per chunk holding some of these packed keys: (chunk, which keys, their rows)."""
        packed = np.asarray(packed, np.int64)
        hits = []
        for chunk in self._chunks:
            found, rows = chunk.rows(packed)
            if len(rows):
                hits.append((chunk, found, rows))
        return hits

    def select(self, packed: np.ndarray) -> BlockMeshes:
        """The meshes of those of these packed keys that are held (copies, in chunk order)."""
        return BlockMeshes.concatenate([chunk.meshes.select(rows) for chunk, _, rows in self.find(packed)])

    def parts(self) -> Iterator[BlockMeshes]:
        """Every held mesh, chunk by chunk (read-only: copies, or views of the chunks)."""
        for chunk in list(self._chunks):
            yield chunk.alive_meshes()

    def put(self, meshes: BlockMeshes, *, removed: np.ndarray | None = None) -> None:
        """Hold these meshes (a key held before is replaced; keys unique within `meshes`) and forget the
        `removed` packed keys."""
        chunk = self._chunk([meshes]) if len(meshes) else None
        gone = [chunk.packed] if chunk is not None else []
        if removed is not None:
            gone.append(np.asarray(removed, np.int64))
        if not gone:
            return
        for old, _, rows in self.find(np.unique(np.concatenate(gone))):
            old.alive[rows] = False
            self.n_blocks -= len(rows)
            self.n_faces -= int(np.diff(old.meshes.face_offsets)[rows].sum())
        if chunk is not None:
            self._append(chunk)
        # a chunk most of whose blocks were replaced is rewritten with the rest (dead ones go); looked for
        # again after each rewrite: appending the rewritten chunk may merge it with another one due (which
        # then leaves the list with its dead blocks gone)
        while (due := next((c for c in self._chunks if 2 * int(c.alive.sum()) < len(c.alive)), None)) is not None:
            # (made before the old one goes: a copy that fails, out of memory, loses nothing)
            rewritten = self._chunk([due.alive_meshes()]) if due.alive.any() else None
            self._chunks.remove(due)
            self.n_blocks -= int(due.alive.sum())
            self.n_faces -= int(np.diff(due.meshes.face_offsets)[due.alive].sum())
            if rewritten is not None:
                self._append(rewritten)

    def clear(self) -> None:
        self._chunks = []
        self.n_blocks = self.n_faces = 0

    def _append(self, chunk: _Chunk) -> None:
        """Add a chunk of keys not held; merge the last two chunks while the one before the last is at most
        twice the last (sizes fall geometrically: each mesh is copied O(log n) times) and together they fit
        in a chunk (`_chunk` puts what reaches `seal_bytes` in a file)."""
        self._chunks.append(chunk)
        self.n_blocks += len(chunk.alive)
        self.n_faces += int(chunk.meshes.face_offsets[-1])
        chunks = self._chunks
        while (len(chunks) >= 2 and chunks[-2].nbytes <= 2 * chunks[-1].nbytes
               and chunks[-2].nbytes + chunks[-1].nbytes <= MAX_CHUNK_BYTES_PER_SEAL * self.seal_bytes):
            # made before the two go: a merge that fails (out of memory) loses neither
            merged = self._chunk([chunks[-2].alive_meshes(), chunks[-1].alive_meshes()])
            del chunks[-2:]
            chunks.append(merged)

    def _chunk(self, parts: list[BlockMeshes]) -> _Chunk:
        """A chunk of these meshes, in a file if they take `seal_bytes` or more and it can be written."""
        if sum(_nbytes(p) for p in parts) >= self.seal_bytes:
            try:
                return _new_chunk(_on_disk(parts, self.directory), on_disk=True)
            except OSError as err:  # warned once, counted (the archive's stats)
                self.seal_failures += 1
                log.log(logging.WARNING if self.seal_failures == 1 else logging.DEBUG,
                        "mesh archive: evicted blocks' meshes stay in memory, their file could not be written "
                        "(%s); free space in %s (warned once, counted as archive_seal_failures)",
                        err, self.directory or tempfile.gettempdir())
        return _new_chunk(BlockMeshes.concatenate(parts), on_disk=False)
