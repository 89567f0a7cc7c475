"""senfunet_core.colors: camera colour averaged per cell."""
from __future__ import annotations

import numpy as np

from senfunet_core.colors import ColorGrid, unproject


def test_running_mean_per_cell_and_unknown_cells() -> None:
    grid = ColorGrid(0.1)
    grid.add(np.array([[0.01, 0.02, 0.03], [0.05, 0.05, 0.05], [1.0, 1.0, 1.0]]),
             np.array([[255, 0, 0], [155, 0, 100], [0, 255, 0]], np.uint8))
    grid.add(np.array([[0.02, 0.02, 0.02], [-0.05, 0.0, 0.0]]), np.array([[255, 0, 0], [0, 0, 255]], np.uint8))
    got = grid.lookup(np.array([[0.09, 0.09, 0.09], [1.05, 1.05, 1.05], [-0.01, 0.0, 0.0], [5.0, 5.0, 5.0]]))
    assert np.allclose(got[0], [(255 + 155 + 255) / 3 / 255, 0, 100 / 3 / 255])
    assert np.allclose(got[1], [0, 1, 0]) and np.allclose(got[2], [0, 0, 1])
    assert np.isnan(got[3]).all() and len(grid) == 3
    grid.clear()
    assert np.isnan(grid.lookup(np.zeros((1, 3)))).all()


def test_unproject_puts_pixels_where_the_camera_saw_them() -> None:
    depth = np.full((4, 6), 2.0, np.float32)
    depth[0, 0] = 0.0  # invalid
    K = np.array([[10.0, 0, 2.5], [0, 10.0, 1.5], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [1.0, 0.0, 0.0]
    points, pixels = unproject(depth, K, T, stride=1)
    assert len(points) == 23 and (pixels[:, 0] * 6 + pixels[:, 1] != 0).all()
    row, col = pixels[0]
    assert np.allclose(points[0], [1.0 + (col - 2.5) / 10 * 2, (row - 1.5) / 10 * 2, 2.0])
