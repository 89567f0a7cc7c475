"""PLY mesh files: binary little-endian writing, ASCII and binary reading.

`write_ply` writes exactly one layout (float32 x, y, z; optional uchar red, green, blue; faces as
`list uchar int vertex_indices`). `read_ply` reads that plus the common variants other tools
write (double coordinates, ushort or float colours, other list count and index types, extra
properties and elements, ASCII or big-endian files). Only triangle faces are supported.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .files import atomic_file
from .mesher import Mesh

# PLY scalar type names (old and new spellings) -> numpy type codes without byte order.
_PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}

_FACE_LIST_NAMES = ("vertex_indices", "vertex_index")


# ----------------------------------------------------------------------------------------------
# Writing


_CHUNK_ROWS = 1 << 18  # rows per write


def write_ply(path: str | os.PathLike, mesh: Mesh) -> None:
    """Write `mesh` as a binary little-endian PLY file, atomically (temp file + rename)."""
    path = Path(path)
    vertices = np.asarray(mesh.vertices, dtype=np.float32).reshape(-1, 3)
    faces = np.asarray(mesh.faces).reshape(-1, 3)
    n_v, n_f = vertices.shape[0], faces.shape[0]
    if faces.size and (faces.min() < 0 or faces.max() >= n_v):
        raise InputError(f"cannot write {path}: face indices outside 0..{n_v - 1}")
    colors = mesh.colors
    has_color = colors is not None and len(colors) > 0
    if has_color and np.asarray(colors).shape != (n_v, 3):
        raise InputError(f"cannot write {path}: colors have shape {np.asarray(colors).shape}, need ({n_v}, 3)")

    header = ["ply", "format binary_little_endian 1.0", "comment written by senfunet_core",
              f"element vertex {n_v}", "property float x", "property float y", "property float z"]
    vfields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if has_color:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
        vfields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    header += [f"element face {n_f}", "property list uchar int vertex_indices", "end_header"]

    def vertex_rows(start: int, stop: int) -> np.ndarray:
        rec = np.empty(stop - start, dtype=np.dtype(vfields))  # packed (no alignment padding)
        v = vertices[start:stop]
        rec["x"], rec["y"], rec["z"] = v[:, 0], v[:, 1], v[:, 2]
        if has_color:
            # Round to the nearest 1/255 so a read-back is within half a step of the input.
            assert colors is not None
            c8 = np.clip(np.rint(np.asarray(colors[start:stop], np.float64) * 255.0), 0, 255).astype(np.uint8)
            rec["red"], rec["green"], rec["blue"] = c8[:, 0], c8[:, 1], c8[:, 2]
        return rec

    def face_rows(start: int, stop: int) -> np.ndarray:
        rec = np.empty(stop - start, dtype=np.dtype([("n", "u1"), ("idx", "<i4", (3,))]))
        rec["n"] = 3
        rec["idx"] = faces[start:stop]
        return rec

    with atomic_file(path) as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        # in chunks: records (and float64 colours) of a whole large mesh at once would be a
        # replay's memory peak
        for rows, n in ((vertex_rows, n_v), (face_rows, n_f)):
            for start in range(0, n, _CHUNK_ROWS):
                rows(start, min(start + _CHUNK_ROWS, n)).tofile(f)


# ----------------------------------------------------------------------------------------------
# Reading


@dataclass
class _Property:
    name: str
    dtype: str  # numpy code without byte order, e.g. "f4"
    count_dtype: str | None = None  # set for list properties


@dataclass
class _Element:
    name: str
    count: int
    props: list[_Property] = field(default_factory=list)


def _parse_header(path: Path, data: bytes) -> tuple[str, list[_Element], int]:
    """Return (format, elements, offset of the body)."""
    if not data.startswith(b"ply"):
        raise InputError(f"{path}: not a PLY file (does not start with 'ply')")
    end = data.find(b"end_header")
    if end < 0:
        raise InputError(f"{path}: truncated or not a PLY file (no 'end_header')")
    # The body starts after the line break that follows end_header (\n or \r\n).
    body = data.find(b"\n", end)
    if body < 0:
        raise InputError(f"{path}: truncated after 'end_header'")
    body += 1
    fmt = None
    elements: list[_Element] = []
    for lineno, raw in enumerate(data[:end].decode("ascii", errors="replace").splitlines()[1:], start=2):
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
                if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
                    raise InputError(f"{path}: unknown PLY format '{fmt}'")
            elif words[0] == "element":
                elements.append(_Element(words[1], int(words[2])))
                if elements[-1].count < 0:
                    raise ValueError("negative count")
            elif words[0] == "property":
                if not elements:
                    raise ValueError("property before any element")
                if words[1] == "list":
                    elements[-1].props.append(_Property(words[4], _PLY_TYPES[words[3]], _PLY_TYPES[words[2]]))
                else:
                    elements[-1].props.append(_Property(words[2], _PLY_TYPES[words[1]]))
            else:
                raise ValueError(f"unknown keyword '{words[0]}'")
        except InputError:
            raise
        except (IndexError, KeyError, ValueError) as exc:
            raise InputError(f"{path}: bad PLY header line {lineno} '{raw.strip()}' ({exc})") from None
    if fmt is None:
        raise InputError(f"{path}: PLY header has no 'format' line")
    return fmt, elements, body


def _binary_element(path: Path, el: _Element, buf: memoryview, off: int, bo: str) -> tuple[np.ndarray, int]:
    """Read one binary element as a structured array; return it and the offset after it.

    Lists are read with a fixed stride taken from the first row's counts, then every row's
    counts are checked; triangle meshes (the only kind we accept) always have a fixed stride.
    """
    def need(nbytes: int) -> None:
        if off + nbytes > len(buf):
            raise InputError(f"{path}: truncated file: element '{el.name}' needs {off + nbytes} bytes, "
                             f"file body has {len(buf)}")

    fields: list[tuple] = []
    pos = off
    for p in el.props:
        if p.count_dtype is None:
            fields.append((p.name, bo + p.dtype))
            pos += np.dtype(p.dtype).itemsize
        else:
            cdt = np.dtype(bo + p.count_dtype)
            n = 0
            if el.count:
                # Peek at the first row's count for this list.
                if pos + cdt.itemsize > len(buf):
                    raise InputError(f"{path}: truncated file inside element '{el.name}'")
                n = int(np.frombuffer(buf, cdt, 1, pos)[0])
            fields.append((p.name + "__n", cdt.str))
            fields.append((p.name, bo + p.dtype, (n,)))
            pos += cdt.itemsize + n * np.dtype(p.dtype).itemsize
    dt = np.dtype(fields)
    need(dt.itemsize * el.count)
    arr = np.frombuffer(buf, dt, el.count, off)
    for p in el.props:
        if p.count_dtype is not None and el.count:
            counts = arr[p.name + "__n"]
            bad = np.flatnonzero(counts != counts[0])
            if bad.size:
                # The first mismatching row was read at the right offset (all rows before it had
                # the same size), so its count is real.
                i = int(bad[0])
                if el.name == "face" and p.name in _FACE_LIST_NAMES:
                    raise InputError(f"{path}: face {i} has {int(counts[i])} vertices; "
                                     "only triangle meshes are supported")
                raise InputError(f"{path}: element '{el.name}' list '{p.name}' has varying lengths; not supported")
    return arr, off + dt.itemsize * el.count


def _ascii_body(path: Path, elements: list[_Element], text: bytes) -> dict[str, dict[str, np.ndarray]]:
    """Parse an ASCII body into {element: {property: array}}; only vertex and face are kept."""
    lines = text.decode("ascii", errors="replace").splitlines()
    lines = [ln for ln in lines if ln.strip()]
    out: dict[str, dict[str, np.ndarray]] = {}
    row = 0
    for el in elements:
        if row + el.count > len(lines):
            raise InputError(f"{path}: truncated file: element '{el.name}' needs {el.count} lines, "
                             f"{len(lines) - row} left")
        rows = lines[row:row + el.count]
        row += el.count
        if el.name not in ("vertex", "face"):
            continue
        cols: dict[str, list] = {p.name: [] for p in el.props}
        for i, ln in enumerate(rows):
            words = ln.split()
            k = 0
            try:
                for p in el.props:
                    if p.count_dtype is None:
                        cols[p.name].append(float(words[k]))
                        k += 1
                    else:
                        n = int(words[k])
                        if el.name == "face" and p.name in _FACE_LIST_NAMES and n != 3:
                            raise InputError(f"{path}: face {i} has {n} vertices; only triangle meshes are supported")
                        cols[p.name].append([float(w) for w in words[k + 1:k + 1 + n]])
                        if len(cols[p.name][-1]) != n:
                            raise IndexError("short list")
                        k += 1 + n
            except InputError:  # a ValueError too: keep its specific message
                raise
            except (IndexError, ValueError):
                raise InputError(f"{path}: bad or truncated {el.name} line {i}: '{ln.strip()}'") from None
        out[el.name] = {}
        for p in el.props:
            if p.count_dtype is None:
                out[el.name][p.name] = np.asarray(cols[p.name], dtype=np.float64).astype(p.dtype)
            elif el.name == "face" and p.name in _FACE_LIST_NAMES:
                out[el.name][p.name] = np.asarray(cols[p.name], dtype=np.float64).reshape(-1, 3).astype(np.int64)
    return out


def _to_float_color(c: np.ndarray) -> np.ndarray:
    """Scale integer colour channels to 0..1 by their type's maximum; floats pass through."""
    if np.issubdtype(c.dtype, np.integer):
        return c.astype(np.float32) / np.float32(np.iinfo(c.dtype).max)
    return c.astype(np.float32)


def read_ply(path: str | os.PathLike) -> Mesh:
    """Read a triangle mesh from an ASCII or binary PLY file."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    fmt, elements, body_off = _parse_header(path, data)
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise InputError(f"{path}: PLY has no 'vertex' element")

    if fmt == "ascii":
        parsed = _ascii_body(path, elements, data[body_off:])
        vcols = parsed["vertex"]
        fcols = parsed.get("face", {})
    else:
        bo = "<" if fmt == "binary_little_endian" else ">"
        buf = memoryview(data)[body_off:]
        off = 0
        vcols, fcols = {}, {}
        for el in elements:
            arr, off = _binary_element(path, el, buf, off, bo)
            if el.name == "vertex":
                vcols = {p.name: arr[p.name] for p in el.props if p.count_dtype is None}
            elif el.name == "face":
                fcols = {p.name: arr[p.name] for p in el.props if p.name in _FACE_LIST_NAMES}
            # Elements after the last of vertex/face are not needed (and may hold lists of
            # varying length we cannot read vectorised), so stop there.
            if not {"vertex", "face"} & set(names[names.index(el.name) + 1:]):
                break

    for axis in ("x", "y", "z"):
        if axis not in vcols:
            raise InputError(f"{path}: vertex element has no '{axis}' property")
    vertices = np.stack([vcols["x"], vcols["y"], vcols["z"]], axis=1).astype(np.float32)
    n_v = vertices.shape[0]

    colors = None
    for r, g, b in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if r in vcols and g in vcols and b in vcols:
            colors = np.stack([_to_float_color(vcols[r]), _to_float_color(vcols[g]), _to_float_color(vcols[b])], axis=1)
            break

    faces = np.zeros((0, 3), np.int32)
    if fcols:
        idx = next(iter(fcols.values()))
        faces = np.asarray(idx).reshape(-1, 3).astype(np.int64)
        if faces.size and (faces.min() < 0 or faces.max() >= n_v):
            raise InputError(f"{path}: face indices outside 0..{n_v - 1}")
        faces = faces.astype(np.int32)
    elif "face" in names and next(e for e in elements if e.name == "face").count > 0:
        raise InputError(f"{path}: face element has no 'vertex_indices' list")
    return Mesh(vertices, faces, colors)
