"""Triangle meshes and marching cubes over sparse blocks.

Marching cubes here is our own: the triangulation table is generated at import time from the
rules below (`_build_tables`), and a numba kernel (`_kernel`) meshes a whole batch of blocks in
one call, without a Python step per block (bench/mesher.py measures it against scikit-image).

Conventions of the extracted surface (TSDF level 0):
- A corner is *inside* when its value is < 0; a value of exactly 0 counts as outside (free). The
  same test decides every edge and every cell, so the mesh stays closed; a vertex can then land
  exactly on a sample (t = 0 or 1), where `weld` merges the vertices of the edges meeting there.
- A vertex on the grid edge from sample lo to sample hi (hi = lo + one step along the edge's axis)
  sits at lo + t, t = v_lo / (v_lo - v_hi), computed in float64 always from the lower end; its
  global coordinate is float(global index of lo) + t. Two blocks sharing an edge therefore give
  bit-identical vertices, whatever the batching.
- Ambiguous cell faces (two diagonal corners inside, the other two outside) are resolved by the
  face's bilinear saddle (asymptotic decider): the inside corners are connected across the face
  iff |v_a * v_b| > |v_c * v_d| for the inside diagonal (a, b) and the outside diagonal (c, d).
  The rule reads only the face's 4 values (exact float64 products), so the two cells sharing a
  face agree and the union of blocks is watertight.
- Faces are counter-clockwise seen from the free side: the normal (v1 - v0) x (v2 - v0) points
  towards increasing TSDF.
"""
from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np
from numba.extending import register_jitable

from .errors import InputError


@dataclass
class Mesh:
    """A triangle mesh in world coordinates (metres)."""

    vertices: np.ndarray  # Nx3 float32
    faces: np.ndarray  # Mx3 int32, counter-clockwise seen from the free side
    colors: np.ndarray | None = None  # Nx3 float32 RGB in 0..1

    @staticmethod
    def empty() -> Mesh:
        return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32))

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])


def cell_mask(observed: np.ndarray) -> np.ndarray:
    """B x n^3 observed corners -> B x (n-1)^3 cells whose 8 corners are all observed."""
    o = observed
    cells = o[:, :-1, :-1, :-1] & o[:, 1:, :-1, :-1] & o[:, :-1, 1:, :-1] & o[:, :-1, :-1, 1:]
    return cells & o[:, 1:, 1:, :-1] & o[:, 1:, :-1, 1:] & o[:, :-1, 1:, 1:] & o[:, 1:, 1:, 1:]


@dataclass
class BlockTriangles:
    """Marching-cubes output of a batch of B blocks, before splitting or welding.

    Vertices and faces are grouped by block in batch order: block b owns the vertices
    vertex_offsets[b]:vertex_offsets[b+1] and the faces face_offsets[b]:face_offsets[b+1], and its
    faces index only its own vertices (indices into the whole vertex array).
    """

    vertices_vox: np.ndarray  # Vx3 float64 global voxel coordinates
    faces: np.ndarray  # Fx3 int64 into vertices_vox
    vertex_values: np.ndarray | None  # V float64 interpolated extra value (e.g. alpha) or None
    vertex_offsets: np.ndarray  # B+1 int64
    face_offsets: np.ndarray  # B+1 int64

    def spread(self, blocks: np.ndarray, n_blocks: int) -> BlockTriangles:
        """This batch's triangles as those of a batch of n_blocks blocks in which its block i is block
        blocks[i] (increasing) and the others have none."""
        if len(blocks) == n_blocks:
            return self
        offsets = []
        for own in (self.vertex_offsets, self.face_offsets):
            counts = np.zeros(n_blocks, np.int64)
            counts[blocks] = np.diff(own)
            offsets.append(np.concatenate([[0], np.cumsum(counts)]).astype(np.int64))
        return BlockTriangles(self.vertices_vox, self.faces, self.vertex_values, *offsets)

    @functools.cached_property
    def vertex_block(self) -> np.ndarray:
        """V int64: the block (index in the batch) of each vertex, non-decreasing."""
        return _block_of(self.vertex_offsets)

    @functools.cached_property
    def face_block(self) -> np.ndarray:
        """F int64: the block of each face, non-decreasing."""
        return _block_of(self.face_offsets)


def _block_of(offsets: np.ndarray) -> np.ndarray:
    return np.repeat(np.arange(len(offsets) - 1, dtype=np.int64), np.diff(offsets))


# -- the triangulation table, generated ---------------------------------------------------------------
#
# Cube corner c has local offset (c & 1, c >> 1 & 1, c >> 2 & 1); a case is the 8-bit mask of the
# inside corners (bit c set when corner c is < 0). Edge e runs from corner _EDGE_LO[e] one step
# along axis _EDGE_AXIS[e]. Face f = 2 * axis + side is the cube face where that axis' offset is
# `side`; its corners in canonical order (c00, c10, c01, c11) span its two other axes u < v.
#
# For every case and every choice on its ambiguous faces, `_cell_triangles`: takes the crossed
# edges; pairs them on each face (2 crossed edges: one segment; 4: one segment around each inside
# corner when the inside corners are separated, around each outside corner when connected);
# orients each segment so that, seen from outside the cube, the outside corners are on its left
# (the surface normal then points to the outside, i.e. to increasing TSDF); chains the segments
# into closed loops (each crossed edge starts one segment and ends one); and triangulates each
# loop, as a fan where possible. A chord between two vertices on a common cube face (only
# possible on an ambiguous face whose two segments belong to one loop) could also be used by the
# neighbouring cell across that face, giving an edge with 4 triangles: such a chord is allowed
# only between the two segment *starts*; the neighbour traverses the shared segments reversed, so
# it can only join the other two vertices.

_CORNER_OFFSET = [(c & 1, (c >> 1) & 1, (c >> 2) & 1) for c in range(8)]
_EDGE_LO = [lo for axis in range(3) for lo in range(8) if not (lo >> axis) & 1]
_EDGE_AXIS = [axis for axis in range(3) for lo in range(8) if not (lo >> axis) & 1]
_EDGE_HI = [lo | 1 << axis for lo, axis in zip(_EDGE_LO, _EDGE_AXIS)]


def _face_corners(f: int) -> list[int]:
    axis, side = divmod(f, 2)
    u, v = (a for a in range(3) if a != axis)
    c00 = side << axis
    return [c00, c00 | 1 << u, c00 | 1 << v, c00 | 1 << u | 1 << v]


_FACE_CORNERS = [_face_corners(f) for f in range(6)]
_FACE_EDGES = [[e for e in range(12) if _EDGE_LO[e] in _FACE_CORNERS[f] and _EDGE_HI[e] in _FACE_CORNERS[f]]
               for f in range(6)]
_EDGE_FACES = [frozenset(f for f in range(6) if e in _FACE_EDGES[f]) for e in range(12)]
_EDGE_MIDPOINT = [tuple(0.5 if a == _EDGE_AXIS[e] else float(x) for a, x in enumerate(_CORNER_OFFSET[_EDGE_LO[e]]))
                  for e in range(12)]


def _cross(a, b) -> tuple[float, float, float]:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _ambiguous_faces(inside: list[bool]) -> list[int]:
    """Faces whose diagonal corners agree and adjacent corners differ (all 4 face edges crossed)."""
    out = []
    for f in range(6):
        c00, c10, c01, c11 = (inside[c] for c in _FACE_CORNERS[f])
        if c00 == c11 and c10 == c01 and c00 != c10:
            out.append(f)
    return out


def _cell_triangles(inside: list[bool], connected: dict[int, bool]) -> list[tuple[int, int, int]]:
    """Triangles (as edge triples, counter-clockwise seen from outside) of one cell.

    connected[f]: on ambiguous face f, whether the inside corners are joined across the face.
    """
    crossed = [e for e in range(12) if inside[_EDGE_LO[e]] != inside[_EDGE_HI[e]]]
    is_crossed = set(crossed)
    nxt: dict[int, int] = {}
    starts: set[tuple[int, int]] = set()  # (face, edge starting a segment on that face)
    for f in range(6):
        on_face = [e for e in _FACE_EDGES[f] if e in is_crossed]
        if not on_face:
            continue
        if len(on_face) == 2:
            segments = [tuple(on_face)]
        else:  # ambiguous face: cut off each corner of the separated kind
            cut_inside = not connected[f]
            segments = [tuple(e for e in on_face if c in (_EDGE_LO[e], _EDGE_HI[e]))
                        for c in _FACE_CORNERS[f] if inside[c] == cut_inside]
        axis, side = divmod(f, 2)
        normal = [0.0, 0.0, 0.0]
        normal[axis] = 1.0 if side else -1.0  # outward normal of the face
        for p, q in segments:
            pp, qq = _EDGE_MIDPOINT[p], _EDGE_MIDPOINT[q]
            left = _cross(normal, [b - a for a, b in zip(pp, qq)])
            outside_corner = _CORNER_OFFSET[_EDGE_HI[p] if inside[_EDGE_LO[p]] else _EDGE_LO[p]]
            if sum(x * (c - a) for x, c, a in zip(left, outside_corner, pp)) < 0:
                p, q = q, p
            assert p not in nxt, "two segments leave one edge"
            nxt[p] = q
            starts.add((f, p))
    assert sorted(nxt) == crossed and sorted(nxt.values()) == crossed, "segments do not form loops"

    def chord_ok(a: int, b: int) -> bool:  # see the comment above _CORNER_OFFSET
        common = _EDGE_FACES[a] & _EDGE_FACES[b]
        return not common or all((f, a) in starts and (f, b) in starts for f in common)

    triangles: list[tuple[int, int, int]] = []
    todo = set(crossed)
    while todo:
        loop = [min(todo)]
        while nxt[loop[-1]] != loop[0]:
            loop.append(nxt[loop[-1]])
        todo -= set(loop)
        found = _triangulate(loop, chord_ok)
        assert found is not None, f"no triangulation of loop {loop}"
        triangles += found
    return triangles


def _triangulate(poly: list[int], chord_ok) -> list[tuple[int, int, int]] | None:
    """Triangles of a polygon (in its order) whose diagonals all pass chord_ok: a fan when one
    works, else any valid triangulation."""
    m = len(poly)
    if m == 3:
        return [(poly[0], poly[1], poly[2])]
    for s in range(m):
        apex = poly[s]
        ring = poly[s:] + poly[:s]
        if all(chord_ok(apex, ring[k]) for k in range(2, m - 1)):
            return [(apex, ring[k], ring[k + 1]) for k in range(1, m - 1)]
    for k in range(2, m):  # the triangle on side (poly[0], poly[1]) with apex poly[k]
        if (k > 2 and not chord_ok(poly[1], poly[k])) or (k < m - 1 and not chord_ok(poly[k], poly[0])):
            continue
        left = _triangulate(poly[1:k + 1], chord_ok) if k > 2 else []
        right = _triangulate(poly[k:] + poly[:1], chord_ok) if k < m - 1 else []
        if left is not None and right is not None:
            return [(poly[0], poly[1], poly[k])] + left + right
    return None


def _build_tables() -> dict[str, np.ndarray]:
    """Kernel tables: for case c (inside mask), its ambiguous faces amb_face[c, :amb_count[c]];
    entry case_offset[c] + s holds the triangles when bit a of s says the inside corners of
    ambiguous face a are connected: tri_count[entry] triangles, edges tri_edge[entry, 3t:3t+3]."""
    case_offset = np.zeros(257, np.int32)
    amb_count = np.zeros(256, np.int32)
    amb_face = np.full((256, 6), -1, np.int32)
    entries: list[list[tuple[int, int, int]]] = []
    for case in range(256):
        inside = [bool(case >> c & 1) for c in range(8)]
        ambiguous = _ambiguous_faces(inside)
        amb_count[case] = len(ambiguous)
        amb_face[case, :len(ambiguous)] = ambiguous
        case_offset[case] = len(entries)
        for sub in range(1 << len(ambiguous)):
            entries.append(_cell_triangles(inside, {f: bool(sub >> a & 1) for a, f in enumerate(ambiguous)}))
    case_offset[256] = len(entries)
    max_tris = max(len(t) for t in entries)
    tri_count = np.array([len(t) for t in entries], np.int32)
    tri_edge = np.zeros((len(entries), 3 * max_tris), np.int32)  # padded with edge 0
    for i, tris in enumerate(entries):
        flat = [e for tri in tris for e in tri]
        tri_edge[i, :len(flat)] = flat
    return {"case_offset": case_offset, "amb_count": amb_count, "amb_face": amb_face,
            "face_corner": np.array(_FACE_CORNERS, np.int32), "tri_count": tri_count, "tri_edge": tri_edge,
            "edge_lo": np.array(_EDGE_LO, np.int32), "edge_axis": np.array(_EDGE_AXIS, np.int32),
            "corner_offset": np.array(_CORNER_OFFSET, np.int64)}


_TABLES = _build_tables()


# -- the kernel ------------------------------------------------------------------------------------


_DE_BRUIJN = 0x03F79D71B4CB0A89  # index of the lowest set bit x & -x: _LOW_BIT[(x & -x) * _DE_BRUIJN >> 58 & 63]
_LOW_BIT = np.zeros(64, np.int64)
for _i in range(64):
    _LOW_BIT[((1 << _i) * _DE_BRUIJN % (1 << 64)) >> 58] = _i
del _i


class _Kernel(NamedTuple):
    """The compiled marching cubes for blocks of n^3 samples, with what its callers need."""

    fill: Callable[..., None]  # fill(tsdf, observed, origin, extra, has_extra, tables, out, counts)
    tables: tuple[np.ndarray, ...]  # the kernel's lookup tables, in the order `fill` unpacks them
    max_block_v: int  # at most this many vertices per block
    max_block_f: int  # and this many faces (plus the unconditional rows, see block_triangles)


@functools.cache
def _kernel(n: int) -> _Kernel:
    """The marching-cubes kernel for blocks of n^3 samples (2 <= n <= 16). n is a constant of the
    compiled code (numba caches one version per n): with n = 9 known, index arithmetic folds and
    the per-column loops unroll, which a variable n would prevent.

    Per block, each column (i, j) of n samples along z becomes two bit masks (inside, observed)
    with sample k at bit 4k; bit operations on them give the complete cells of each column of
    cells (`column_masks`), then the grid edges that need a vertex (crossed, in a complete cell:
    `block_vertices`), then the cells to triangulate (complete, with inside and outside corners:
    `block_triangles`), whose case (8 corner bits) is one byte of the four neighbouring columns'
    masks interleaved: corner dx + 2 dy + 4 dz of cell k is bit 4 (k + dz) + dx + 2 dy.
    """
    nn = n * n
    n3 = nn * n
    sample_bits = sum(1 << (4 * k) for k in range(n))  # bit 4k: sample k of a column
    cells_in_column = sum(1 << (4 * k) for k in range(n - 1))  # bit 4k: cell k of a column
    pad = n + 1
    T = _TABLES
    coff = (T["corner_offset"] @ np.array([nn, n, 1])).astype(np.int64)  # corner c's flat offset in a cell
    edge_key = T["edge_axis"] * n3 + coff[T["edge_lo"]]  # slot in edge_vertex of each cube edge
    tri_key = edge_key[T["tri_edge"]].astype(np.int64)  # the triangle table as edge_vertex slots
    max_block_v = 3 * n3  # at most one vertex per grid edge
    max_block_f = (n - 1) ** 3 * (tri_key.shape[1] // 3) + 4

    @register_jitable
    def column_masks(ts, ob, code, inside_col, observed_col, complete_col):
        """One block's column masks: inside_col, observed_col and complete_col (at pad + i n + j:
        bit 4k when cell (i, j, k) is complete; zero for i or j = n - 1 and in the padding, so
        neighbours need no bounds tests)."""
        for p in range(n3):  # (vectorises)
            code[p] = np.uint8(ts[p] < 0) | (np.uint8(ob[p]) << 1)
        for col in range(nn):
            base = col * n
            m: int | np.int64 = 0
            for k in range(n):
                m |= np.int64(code[base + k]) << (4 * k)
            inside_col[col] = m & sample_bits
            observed_col[col] = (m >> 1) & sample_bits
        for i in range(n - 1):
            for j in range(n - 1):
                c0 = i * n + j  # columns of the cell corners (dx, dy) = (0, 0), (1, 0), (0, 1), (1, 1)
                o = observed_col[c0] & observed_col[c0 + n] & observed_col[c0 + 1] & observed_col[c0 + n + 1]
                complete_col[c0 + pad] = o & (o >> 4) & cells_in_column

    @register_jitable
    def block_vertices(b, ts, origin, extra, has_extra, masks, edge_vertex, low_bit, out, nv):
        """Block b's vertices: grid edges (axis, lower sample (i, j, k)) crossed and in a complete
        cell, appended to out = (verts, values) from row nv, values interpolated from extra when
        has_extra; edge_vertex maps each edge to its row. Returns the new vertex count."""
        inside_col, complete_col = masks
        verts, values = out
        ox = origin[b, 0]
        oy = origin[b, 1]
        oz = origin[b, 2]
        for i in range(n):
            for j in range(n):
                c0 = i * n + j
                q = c0 + pad
                m = inside_col[c0]
                cxz = complete_col[q] | complete_col[q - 1]  # cells (by k) around the x edges of column (i, j)
                cy = complete_col[q] | complete_col[q - n]  # ... around its y edges
                cz = cxz | complete_col[q - n] | complete_col[q - n - 1]  # ... around its z edges
                ux = (m ^ inside_col[c0 + n]) & (cxz | cxz << 4)  # (inside_col is padded too)
                uy = (m ^ inside_col[c0 + 1]) & (cy | cy << 4)
                uz = (m ^ (m >> 4)) & cz
                used = ux | uy << 1 | uz << 2  # bit 4k + axis
                while used != 0:
                    bit = low_bit[((used & -used) * _DE_BRUIJN) >> 58 & 63]
                    used &= used - 1
                    axis = bit & 3
                    k = bit >> 2
                    lo = c0 * n + k
                    hi = lo + (nn if axis == 0 else n if axis == 1 else 1)
                    v_lo = np.float64(ts[lo])
                    s = v_lo / (v_lo - np.float64(ts[hi]))  # always from the lower sample
                    verts[nv, 0] = np.float64(ox + i)
                    verts[nv, 1] = np.float64(oy + j)
                    verts[nv, 2] = np.float64(oz + k)
                    verts[nv, axis] += s
                    if has_extra:
                        values[nv] = (1.0 - s) * np.float64(extra[b, lo]) + s * np.float64(extra[b, hi])
                    edge_vertex[axis * n3 + lo] = nv
                    nv += 1
        return nv

    @register_jitable
    def block_triangles(ts, inside_col, complete_col, edge_vertex, tables, faces, nf):
        """The block's triangles, appended to faces from row nf (each cell's case, its ambiguous
        faces decided by the asymptotic decider, then the table's triangles). Returns the new
        face count."""
        case_offset, amb_count, amb_face, face_corner, tri_count, tri_key, coff, low_bit = tables
        for i in range(n - 1):
            for j in range(n - 1):
                c0 = i * n + j
                m00 = inside_col[c0]
                m10 = inside_col[c0 + n]
                m01 = inside_col[c0 + 1]
                m11 = inside_col[c0 + n + 1]
                cases = m00 | m10 << 1 | m01 << 2 | m11 << 3  # bits 4k..4k+7: the case of cell k
                some = m00 | m10 | m01 | m11
                every = m00 & m10 & m01 & m11
                active = complete_col[c0 + pad] & (some | (some >> 4)) & ~(every & (every >> 4))
                while active != 0:
                    bit = low_bit[((active & -active) * _DE_BRUIJN) >> 58 & 63]
                    active &= active - 1
                    case = (cases >> bit) & 255  # bit c set: corner c = dx + 2 dy + 4 dz is inside
                    cell = c0 * n + (bit >> 2)
                    sub = 0
                    for a in range(amb_count[case]):
                        f = amb_face[case, a]
                        v00 = np.float64(ts[cell + coff[face_corner[f, 0]]])
                        v10 = np.float64(ts[cell + coff[face_corner[f, 1]]])
                        v01 = np.float64(ts[cell + coff[face_corner[f, 2]]])
                        v11 = np.float64(ts[cell + coff[face_corner[f, 3]]])
                        diag = v00 * v11  # products of float32 values: exact in float64
                        anti = v10 * v01
                        if (diag > anti) if v00 < 0 else (anti > diag):
                            sub |= 1 << a  # the inside corners are connected across face f
                    entry = case_offset[case] + sub
                    # the first 4 triangles unconditionally (fewer branches; extra rows are
                    # overwritten by later cells or lie beyond the returned count)
                    for t in range(4):
                        faces[nf + t, 0] = edge_vertex[cell + tri_key[entry, 3 * t]]
                        faces[nf + t, 1] = edge_vertex[cell + tri_key[entry, 3 * t + 1]]
                        faces[nf + t, 2] = edge_vertex[cell + tri_key[entry, 3 * t + 2]]
                    for t in range(4, tri_count[entry]):
                        faces[nf + t, 0] = edge_vertex[cell + tri_key[entry, 3 * t]]
                        faces[nf + t, 1] = edge_vertex[cell + tri_key[entry, 3 * t + 1]]
                        faces[nf + t, 2] = edge_vertex[cell + tri_key[entry, 3 * t + 2]]
                    nf += tri_count[entry]
        return nf

    @numba.njit(cache=True, nogil=True)
    def fill(tsdf, observed, origin, extra, has_extra, tables, out, counts):
        """Mesh blocks counts[0].. into the buffers out = (verts, values, faces, vertex_offsets,
        face_offsets) until one might not fit; counts: (next block, vertices, faces)."""
        verts, values, faces, vertex_offsets, face_offsets = out
        low_bit = tables[7]
        n_blocks = tsdf.shape[0]
        inside_col = np.zeros(nn + pad, np.int64)  # column (i, j): bit 4k when sample (i, j, k) is inside
        observed_col = np.empty(nn, np.int64)
        complete_col = np.zeros(nn + pad, np.int64)  # see column_masks
        edge_vertex = np.empty(3 * n3, np.int64)  # vertex of grid edge (axis, lower sample), this block
        code = np.empty(n3, np.uint8)  # per sample: bit 0 inside, bit 1 observed
        nv = counts[1]
        nf = counts[2]
        b = counts[0]
        while b < n_blocks:
            if nv + max_block_v > verts.shape[0] or nf + max_block_f > faces.shape[0]:
                break
            vertex_offsets[b] = nv
            face_offsets[b] = nf
            ts = tsdf[b]
            column_masks(ts, observed[b], code, inside_col, observed_col, complete_col)
            nv = block_vertices(b, ts, origin, extra, has_extra, (inside_col, complete_col), edge_vertex, low_bit,
                                (verts, values), nv)
            nf = block_triangles(ts, inside_col, complete_col, edge_vertex, tables, faces, nf)
            b += 1
        counts[0] = b
        counts[1] = nv
        counts[2] = nf

    tables = (T["case_offset"], T["amb_count"], T["amb_face"], T["face_corner"], T["tri_count"], tri_key, coff,
              _LOW_BIT)
    return _Kernel(fill, tables, max_block_v, max_block_f)


def marching_cubes_blocks(tsdf: np.ndarray, observed: np.ndarray, block_origin_vox: np.ndarray,
                          extra: np.ndarray | None = None) -> BlockTriangles:
    """Marching cubes at level 0 over B blocks at once (see the module docstring for the rules).

    tsdf, observed, extra: B x n x n x n (or B x n^3) samples, n = s + 1: each block's s^3 voxels
    plus one more layer from its +x, +y, +z neighbours, so every cell a block owns is complete and
    neighbouring blocks' meshes meet exactly (a vertex on a seam is computed from the same two
    samples by both). Only cells whose 8 corners are observed produce triangles.
    block_origin_vox: B x 3 int, the global voxel index of each block's local (0, 0, 0).
    extra: a per-sample value interpolated linearly along each vertex's edge (vertex_values).
    The returned arrays may be views of larger buffers.
    """
    tsdf = np.asarray(tsdf)
    n_blocks = tsdf.shape[0]
    n = 0
    if tsdf.ndim == 4 and tsdf.shape[1] == tsdf.shape[2] == tsdf.shape[3]:
        n = tsdf.shape[1]
    elif tsdf.ndim == 2:
        n = round(tsdf.shape[1] ** (1 / 3))
    if not 2 <= n <= 16 or tsdf.size != n_blocks * n**3:
        raise InputError(f"marching_cubes_blocks: tsdf must be B x n x n x n with 2 <= n <= 16, got {tsdf.shape}")
    if n_blocks == 0:
        z = np.zeros(n_blocks + 1, np.int64)
        return BlockTriangles(np.zeros((0, 3)), np.zeros((0, 3), np.int64), None if extra is None else np.zeros(0), z,
                              z.copy())
    shape = (n_blocks, n**3)
    values = np.ascontiguousarray(tsdf, dtype=np.float32).reshape(shape)
    obs = np.ascontiguousarray(observed, dtype=np.bool_).reshape(shape)
    origin = np.ascontiguousarray(block_origin_vox, dtype=np.int64).reshape(n_blocks, 3)
    if extra is None:
        ext = np.zeros((1, 1), np.float32)
    else:
        ext = np.ascontiguousarray(extra, dtype=np.float32).reshape(shape)
    kernel = _kernel(n)
    max_block_v, max_block_f = kernel.max_block_v, kernel.max_block_f
    has_extra = extra is not None
    # first guess of the output size (untouched capacity costs no memory; growing costs a copy):
    # a surface crossing a block makes far fewer vertices than the bound of one per grid edge
    cap_v = 128 * n_blocks + max_block_v
    cap_f = 2 * cap_v + max_block_f
    verts = np.empty((cap_v, 3))
    vals = np.empty(cap_v if has_extra else 1)
    faces = np.empty((cap_f, 3), np.int64)
    v_off = np.empty(n_blocks + 1, np.int64)
    f_off = np.empty(n_blocks + 1, np.int64)
    counts = np.zeros(3, np.int64)  # next block, vertices, faces
    while True:  # fill stops before a block that might not fit; the buffers grow (rarely) in between
        kernel.fill(values, obs, origin, ext, has_extra, kernel.tables, (verts, vals, faces, v_off, f_off), counts)
        if counts[0] == n_blocks:
            break
        nv, nf = int(counts[1]), int(counts[2])
        if nv + max_block_v > len(verts):
            verts = _grown(verts, nv)
            vals = _grown(vals, nv) if has_extra else vals
        if nf + max_block_f > len(faces):
            faces = _grown(faces, nf)
    nv, nf = int(counts[1]), int(counts[2])
    v_off[n_blocks] = nv
    f_off[n_blocks] = nf
    return BlockTriangles(verts[:nv], faces[:nf], vals[:nv] if has_extra else None, v_off, f_off)


def _grown(a: np.ndarray, used: int) -> np.ndarray:
    out = np.empty((2 * len(a),) + a.shape[1:], a.dtype)
    out[:used] = a[:used]
    return out


def weld(vertices_vox: np.ndarray, faces: np.ndarray, vertex_values: np.ndarray | None = None
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Merge the copies of a vertex made by neighbouring blocks and drop triangles that collapse.

    Every marching-cubes vertex lies on a grid edge: two of its voxel coordinates are integers.
    The edge (its lower end and axis) identifies the vertex. `marching_cubes_blocks` gives the
    copies bit-identical positions, but vertices that went through float32 (e.g. per-block meshes
    in metres) need the edge key; vertices within 1e-4 voxel of a sample merge into one (a sample
    exactly on the surface), and the triangles this collapses are dropped.
    """
    if len(vertices_vox) == 0:
        return vertices_vox, faces, vertex_values
    first, inverse = _unique_edges(*_edges(vertices_vox))
    faces = inverse.astype(faces.dtype, copy=False)[faces]  # the faces' index type (int32 halves them)
    values = None if vertex_values is None else vertex_values[first]
    return vertices_vox[first], faces[_proper(faces)], values


def _proper(faces: np.ndarray) -> np.ndarray:
    """Which welded faces keep three distinct vertices (the others collapsed)."""
    return (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])


def _edges(vertices_vox: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The grid edge of each vertex: its lower end (V x 3 int64) and axis (V: 0-2, or 3 for a
    vertex within 1e-4 voxel of a sample, identified by that sample)."""
    off_grid = np.abs(vertices_vox - np.round(vertices_vox))
    axis = np.argmax(off_grid, axis=1)
    on_node = off_grid.max(axis=1) < 1e-4  # the surface passes through a sample exactly
    del off_grid  # temporaries go as soon as they are used: welding is extraction's memory peak
    base = np.round(vertices_vox).astype(np.int64)
    rows = np.arange(len(base))
    base[rows, axis] = np.floor(vertices_vox[rows, axis]).astype(np.int64)
    base[on_node] = np.round(vertices_vox[on_node]).astype(np.int64)
    axis[on_node] = 3
    return base, axis


_COLOR_CHUNK = 1 << 20  # vertices StreamingWeld.mesh colours at a time


class StreamingWeld:
    """`weld` + `to_mesh` over marching-cubes batches added one at a time, for the whole map's mesh
    without holding every batch's float64 vertices and int64 faces at once (extraction's memory
    peak on a large map). Per vertex it keeps its edge key (int64), its position in metres
    (float32, as the mesh will hold it) and its value (float32); per face three int32 indices.
    The mesh equals `to_mesh(*weld(all vertices, all faces, all values))` byte for byte: the edge
    keys sort the same way (lexicographic in lower end, then axis), the first copy of each vertex
    is kept, and each kept vertex is converted exactly as there.

    block_coords_min / _max: the bounds of the blocks' coordinates, which bound the vertices'
    edges (packed into one int64 key where the extent allows, else kept as rows)."""

    def __init__(self, voxel_size_m: float, block_coords_min: np.ndarray, block_coords_max: np.ndarray,
                 block_size: int = 8) -> None:
        self.voxel_size_m = voxel_size_m
        self._low = np.asarray(block_coords_min, np.int64) * block_size - 1
        self._extent = (np.asarray(block_coords_max, np.int64) - block_coords_min + 1) * block_size + 3
        self._packed = float(np.prod(self._extent.astype(np.float64))) * 4 < 2.0**62
        self._keys: list[np.ndarray] = []
        self._vertices_m: list[np.ndarray] = []
        self._values: list[np.ndarray] = []
        self._colors: list[np.ndarray] = []
        self._faces: list[np.ndarray] = []
        self.n_vertices = 0

    def add(self, vertices_vox: np.ndarray, faces: np.ndarray, vertex_values: np.ndarray | None = None) -> None:
        """One batch: V x 3 voxel coordinates, F x 3 indices into them, V values (or None)."""
        base, axis = _edges(vertices_vox)
        if self._packed and len(base) and (np.any(base.min(axis=0) < self._low)
                                           or np.any(base.max(axis=0) - self._low >= self._extent)):
            self._unpack()  # beyond the bounds given (an archived block elsewhere): rows from now on
        if self._packed:
            self._keys.append(_pack_edges(base, axis, self._low, self._extent))
        else:
            self._keys.append(np.concatenate([base, axis[:, None]], axis=1))
        del base, axis
        self._vertices_m.append((vertices_vox * self.voxel_size_m).astype(np.float32))
        if vertex_values is not None:
            self._values.append(np.asarray(vertex_values, np.float32))
        index = np.int32 if self.n_vertices + len(vertices_vox) < np.iinfo(np.int32).max else np.int64
        self._faces.append((faces + self.n_vertices).astype(index))
        self.n_vertices += len(vertices_vox)

    def _unpack(self) -> None:
        """Packed keys -> rows (lower end x, y, z, axis), for vertices beyond the bounds."""
        e = self._extent
        for n, key in enumerate(self._keys):
            axis, rest = key % 4, key // 4
            z, rest = rest % e[2], rest // e[2]
            y, x = rest % e[1], rest // e[1]
            self._keys[n] = np.stack([x, y, z], axis=1) + self._low
            self._keys[n] = np.concatenate([self._keys[n], axis[:, None]], axis=1)
        self._packed = False

    def add_colored_m(self, vertices_m: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> None:
        """A mesh in metres with colours (an archived one), after every batch: the whole mesh then
        takes colours (`alpha_colors` of the batches' values) instead of values."""
        if self._values:
            self._colors.append(alpha_colors(np.concatenate(self._values)))
            self._values.clear()
        # in voxels as `weld` of the whole would see them: the quotient in the mesh's float32, then widened
        self.add((vertices_m / self.voxel_size_m).astype(np.float64), faces)
        self._colors.append(np.asarray(colors, np.float32))

    def mesh(self) -> Mesh:
        """The welded mesh; empties this weld. Each batch's arrays are let go as soon as they are
        used (this is extraction's memory peak, on top of the whole grid)."""
        if self.n_vertices == 0:
            return Mesh.empty()
        first, inverse = _first_and_inverse(self._keys)
        faces = np.empty((sum(len(f) for f in self._faces), 3), inverse.dtype)
        end = 0
        self._faces.reverse()
        while self._faces:  # each batch's faces to the welded vertices, degenerate ones dropped
            mapped = inverse[self._faces.pop()]
            mapped = mapped[_proper(mapped)]
            faces[end:end + len(mapped)] = mapped
            end += len(mapped)
        vertices = _take_firsts(self._vertices_m, first, inverse, np.empty((len(first), 3), np.float32))
        colors = None
        if self._colors:
            colors = _take_firsts(self._colors, first, inverse, np.empty((len(first), 3), np.float32))
        elif self._values:
            values = _take_firsts(self._values, first, inverse, np.empty(len(first), np.float32))
            colors = np.empty((len(first), 3), np.float32)
            for start in range(0, len(first), _COLOR_CHUNK):  # alpha_colors' temporaries stay small
                colors[start:start + _COLOR_CHUNK] = alpha_colors(values[start:start + _COLOR_CHUNK])
        self.n_vertices = 0
        return Mesh(vertices, faces[:end].astype(np.int32, copy=False), colors)


def _take_firsts(parts: list[np.ndarray], first: np.ndarray, inverse: np.ndarray, out: np.ndarray) -> np.ndarray:
    """out[u] = row first[u] of the parts' concatenation (inverse: each row's u), without that
    concatenation: the parts are let go one by one (emptying the list)."""
    offset = 0
    parts.reverse()
    while parts:
        part = parts.pop()
        ids = inverse[offset:offset + len(part)]
        kept = first[ids] == np.arange(offset, offset + len(part))
        out[ids[kept]] = part[kept]
        offset += len(part)
    return out


def _unique_edges(base: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """np.unique over the rows (base x, y, z, axis), lexicographic: the first row of each distinct
    key and each row's key index. The rows are packed into one int64 where their extent allows
    (a one-dimensional sort, several times faster than sorting rows)."""
    low = base.min(axis=0)
    extent = base.max(axis=0) - low + 1
    if float(extent[0]) * float(extent[1]) * float(extent[2]) * 4 < 2.0**62:
        return _first_and_inverse([_pack_edges(base, axis, low, extent)])
    return _first_and_inverse([np.concatenate([base, axis[:, None]], axis=1)])


def _pack_edges(base: np.ndarray, axis: np.ndarray, low: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """One int64 key per edge, ordered as the rows (lower end x, y, z, axis): lower ends within
    low .. low + extent - 1 (whose product times 4 the caller checked fits)."""
    shifted = base - low
    return ((shifted[:, 0] * extent[1] + shifted[:, 1]) * extent[2] + shifted[:, 2]) * 4 + axis


def _first_and_inverse(parts: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """np.unique(keys, return_index=True, return_inverse=True)'s index and inverse (the first row of
    each distinct key, in key order, and each row's key) for the keys of the parts concatenated,
    one int64 each (or rows, sorted as np.unique does), without its int64 temporaries: a stable
    argsort, the inverse as int32. Empties `parts`, so that the keys go once sorted."""
    keys = np.concatenate(parts) if len(parts) > 1 else parts[0]
    parts.clear()
    if keys.ndim == 2:  # rows (an extent beyond one int64 key): rare, np.unique over rows
        _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        return first, inverse.reshape(-1)
    order = np.argsort(keys, kind="stable")  # stable: the first copy of each key comes first
    sorted_keys = keys[order]
    del keys
    starts = np.empty(len(order), bool)
    starts[0] = True
    np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=starts[1:])
    del sorted_keys
    index = np.int32 if len(order) < np.iinfo(np.int32).max else np.int64
    inverse = np.empty(len(order), index)
    inverse[order] = np.cumsum(starts, dtype=index) - 1
    return order[starts], inverse


_SENSOR_1_COLOR = np.array([1.0, 0.72, 0.1], np.float32)  # amber
_SENSOR_2_COLOR = np.array([0.15, 0.4, 1.0], np.float32)  # blue


def alpha_colors(alpha: np.ndarray) -> np.ndarray:
    """Sensor weighting as colour: alpha 1 (trust sensor 1) amber, alpha 0 (sensor 2) blue."""
    a = np.clip(np.asarray(alpha, dtype=np.float32), 0, 1)[:, None]
    return a * _SENSOR_1_COLOR + (1 - a) * _SENSOR_2_COLOR


@numba.njit(cache=True, nogil=True)
def block_mesh_arrays(vertices_vox: np.ndarray, faces: np.ndarray, vertex_alpha: np.ndarray,
                      vertex_offsets: np.ndarray, face_offsets: np.ndarray, voxel_size_m: float
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A marching-cubes batch (`BlockTriangles`' arrays) as per-block mesh arrays in one pass: what
    `to_mesh` makes of it, with each block's faces indexing its own vertices: vertices in metres
    (float32), faces (int32) and `alpha_colors` (float32), the same values to the bit."""
    vertices = np.empty((vertices_vox.shape[0], 3), np.float32)
    colors = np.empty((vertices_vox.shape[0], 3), np.float32)
    for v in range(vertices_vox.shape[0]):
        a = np.float32(vertex_alpha[v])
        a = np.float32(0.0) if a < 0.0 else (np.float32(1.0) if a > 1.0 else a)  # NaN stays NaN, as np.clip
        for axis in range(3):
            vertices[v, axis] = np.float32(vertices_vox[v, axis] * voxel_size_m)
            colors[v, axis] = a * _SENSOR_1_COLOR[axis] + (np.float32(1.0) - a) * _SENSOR_2_COLOR[axis]
    local_faces = np.empty((faces.shape[0], 3), np.int32)
    for b in range(vertex_offsets.shape[0] - 1):
        for f in range(face_offsets[b], face_offsets[b + 1]):
            for corner in range(3):
                local_faces[f, corner] = faces[f, corner] - vertex_offsets[b]
    return vertices, local_faces, colors


def to_mesh(vertices_vox: np.ndarray, faces: np.ndarray, voxel_size_m: float, vertex_alpha: np.ndarray | None) -> Mesh:
    colors = None if vertex_alpha is None else alpha_colors(vertex_alpha)
    return Mesh((vertices_vox * voxel_size_m).astype(np.float32), faces.astype(np.int32), colors)


def _ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The indices starts[i] .. starts[i] + counts[i] - 1, range after range."""
    ends = np.cumsum(counts)
    return np.arange(ends[-1] if len(ends) else 0) + np.repeat(starts - (ends - counts), counts)


@dataclass
class BlockMeshes:
    """The meshes of many blocks in shared arrays, block after block (one marching-cubes batch,
    or several concatenated): cheap to hand around and to encode, a `Mesh` per block on demand."""

    keys: np.ndarray  # B x 3 int64 block coordinates
    vertices: np.ndarray  # V x 3 float32, metres
    colors: np.ndarray  # V x 3 float32 RGB in 0..1
    faces: np.ndarray  # F x 3 int32, indices into the block's own vertices
    vertex_offsets: np.ndarray  # B+1 int64: block b has vertices[vertex_offsets[b]:vertex_offsets[b+1]]
    face_offsets: np.ndarray  # B+1 int64

    def __len__(self) -> int:
        return len(self.keys)

    def mesh(self, b: int) -> Mesh:
        """Block b's mesh (views of the shared arrays)."""
        v = slice(self.vertex_offsets[b], self.vertex_offsets[b + 1])
        return Mesh(self.vertices[v], self.faces[self.face_offsets[b]:self.face_offsets[b + 1]], self.colors[v])

    def as_dict(self) -> dict[tuple[int, int, int], Mesh]:
        return {key: self.mesh(b) for b, key in enumerate(map(tuple, self.keys.tolist()))}

    def blocks(self, start: int, stop: int) -> BlockMeshes:
        """Blocks start..stop-1 (views of the shared arrays)."""
        v0, v1 = self.vertex_offsets[start], self.vertex_offsets[stop]
        f0, f1 = self.face_offsets[start], self.face_offsets[stop]
        return BlockMeshes(self.keys[start:stop], self.vertices[v0:v1], self.colors[v0:v1], self.faces[f0:f1],
                           self.vertex_offsets[start:stop + 1] - v0, self.face_offsets[start:stop + 1] - f0)

    def select(self, index: np.ndarray) -> BlockMeshes:
        """The blocks at these indices, in this order (copies)."""
        index = np.asarray(index, np.int64)
        v_counts, f_counts = np.diff(self.vertex_offsets)[index], np.diff(self.face_offsets)[index]
        return BlockMeshes(self.keys[index], self.vertices[_ranges(self.vertex_offsets[index], v_counts)],
                           self.colors[_ranges(self.vertex_offsets[index], v_counts)],
                           self.faces[_ranges(self.face_offsets[index], f_counts)],
                           np.concatenate([[0], np.cumsum(v_counts)]).astype(np.int64),
                           np.concatenate([[0], np.cumsum(f_counts)]).astype(np.int64))

    @staticmethod
    def concatenate(parts: list[BlockMeshes]) -> BlockMeshes:
        if not parts:
            z = np.zeros((0, 3), np.float32)
            return BlockMeshes(np.zeros((0, 3), np.int64), z, z.copy(), np.zeros((0, 3), np.int32),
                               np.zeros(1, np.int64), np.zeros(1, np.int64))
        if sum(len(p) > 0 for p in parts) <= 1:  # nothing to join: no copy
            return max(parts, key=len)
        v_base = np.cumsum([0] + [p.vertex_offsets[-1] for p in parts[:-1]])
        f_base = np.cumsum([0] + [p.face_offsets[-1] for p in parts[:-1]])
        return BlockMeshes(
            np.concatenate([p.keys for p in parts]), np.concatenate([p.vertices for p in parts]),
            np.concatenate([p.colors for p in parts]), np.concatenate([p.faces for p in parts]),
            np.concatenate([[0]] + [p.vertex_offsets[1:] + b for p, b in zip(parts, v_base)]).astype(np.int64),
            np.concatenate([[0]] + [p.face_offsets[1:] + b for p, b in zip(parts, f_base)]).astype(np.int64))

    @staticmethod
    def from_meshes(meshes: dict[tuple[int, int, int], Mesh]) -> BlockMeshes:
        """Meshes per block key -> one BlockMeshes, in key order (white where a mesh has no colours)."""
        keys = sorted(meshes)
        parts = [meshes[k] for k in keys]
        colors = [p.colors if p.colors is not None and len(p.colors) == len(p.vertices)
                  else np.ones((len(p.vertices), 3), np.float32) for p in parts]
        return BlockMeshes(
            np.array(keys, np.int64).reshape(-1, 3),
            np.concatenate([np.asarray(p.vertices, np.float32) for p in parts]) if parts
            else np.zeros((0, 3), np.float32),
            np.concatenate(colors).astype(np.float32) if parts else np.zeros((0, 3), np.float32),
            np.concatenate([np.asarray(p.faces) for p in parts]).astype(np.int32) if parts
            else np.zeros((0, 3), np.int32),
            np.cumsum([0] + [len(p.vertices) for p in parts], dtype=np.int64),
            np.cumsum([0] + [len(p.faces) for p in parts], dtype=np.int64))
