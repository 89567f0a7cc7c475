"""Camera colour on a sparse grid, for colouring a display mesh by what the cameras saw.

`ColorGrid(cell_m)` keeps, per cell of a grid, the running mean of the RGB of the pixels whose
depth landed in it. The fusion engine does not store colour (its feature nets read it, the map
does not keep it); this is a separate, coarse store fed with the frames that were integrated.

Convention: points in metres in the world frame; RGB uint8 in, float 0..1 out. Pure numpy: the
cells are a sorted int64 key array, merged per frame with searchsorted, no loop over pixels.
"""
from __future__ import annotations

import threading

import numpy as np

__all__ = ["ColorGrid", "unproject"]

_BITS = 21  # per axis in the packed key: +-1M cells (+-10 km at 1 cm)
_OFFSET = 1 << (_BITS - 1)


def _pack(cells: np.ndarray) -> np.ndarray:
    c = cells.astype(np.int64) + _OFFSET
    return (c[:, 0] << (2 * _BITS)) | (c[:, 1] << _BITS) | c[:, 2]


def unproject(depth_m: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray, *, stride: int = 2
              ) -> tuple[np.ndarray, np.ndarray]:
    """World points (N x 3) of the valid pixels of every `stride`-th row and column, and their
    (row, column) indices (N x 2), for looking up their colours."""
    rows, cols = np.mgrid[0:depth_m.shape[0]:stride, 0:depth_m.shape[1]:stride]
    z = depth_m[rows, cols]
    valid = np.isfinite(z) & (z > 0)
    rows, cols, z = rows[valid], cols[valid], z[valid].astype(np.float64)
    x = (cols - K[0, 2]) / K[0, 0] * z
    y = (rows - K[1, 2]) / K[1, 1] * z
    points = np.stack([x, y, z], 1) @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]
    return points, np.stack([rows, cols], 1)


class ColorGrid:
    """Thread-safe running mean of RGB per cell of `cell_m`."""

    def __init__(self, cell_m: float) -> None:
        if not cell_m > 0:
            raise ValueError(f"cell_m must be > 0, got {cell_m}")
        self.cell_m = float(cell_m)
        self._lock = threading.Lock()
        self.clear()

    def clear(self) -> None:
        with self._lock:
            self._keys = np.zeros(0, np.int64)  # sorted
            self._sums = np.zeros((0, 3), np.float64)
            self._counts = np.zeros(0, np.int64)

    def __len__(self) -> int:
        return len(self._keys)

    def add(self, points_m: np.ndarray, rgb: np.ndarray) -> None:
        """Points (N x 3) and their colours (N x 3 uint8)."""
        if len(points_m) == 0:
            return
        keys = _pack(np.floor(np.asarray(points_m) / self.cell_m))
        unique, inverse = np.unique(keys, return_inverse=True)
        sums = np.stack([np.bincount(inverse, rgb[:, c].astype(np.float64), len(unique)) for c in range(3)], 1)
        counts = np.bincount(inverse, minlength=len(unique))
        with self._lock:
            at = np.searchsorted(self._keys, unique)
            found = (at < len(self._keys)) & (self._keys[np.minimum(at, len(self._keys) - 1)] == unique) \
                if len(self._keys) else np.zeros(len(unique), bool)
            self._sums[at[found]] += sums[found]
            self._counts[at[found]] += counts[found]
            new = ~found
            if new.any():
                keys_all = np.concatenate([self._keys, unique[new]])
                order = np.argsort(keys_all, kind="stable")
                self._keys = keys_all[order]
                self._sums = np.concatenate([self._sums, sums[new]])[order]
                self._counts = np.concatenate([self._counts, counts[new]])[order]

    def lookup(self, points_m: np.ndarray) -> np.ndarray:
        """Mean colour (N x 3, 0..1) of each point's cell; NaN where no camera saw it."""
        out = np.full((len(points_m), 3), np.nan, np.float32)
        if len(points_m) == 0:
            return out
        keys = _pack(np.floor(np.asarray(points_m) / self.cell_m))
        with self._lock:
            if not len(self._keys):
                return out
            at = np.minimum(np.searchsorted(self._keys, keys), len(self._keys) - 1)
            found = self._keys[at] == keys
            out[found] = (self._sums[at[found]] / self._counts[at[found], None] / 255.0).astype(np.float32)
        return out
