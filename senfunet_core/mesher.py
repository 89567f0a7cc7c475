"""Triangle meshes and marching cubes over sparse blocks."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Mesh:
    """A triangle mesh in world coordinates (metres)."""

    vertices: np.ndarray  # Nx3 float32
    faces: np.ndarray  # Mx3 int32, counter-clockwise seen from the free side
    colors: np.ndarray | None = None  # Nx3 float32 RGB in 0..1

    @staticmethod
    def empty() -> "Mesh":
        return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32))

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])
