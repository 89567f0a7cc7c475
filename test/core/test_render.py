"""Headless rendering: right size, solid surface, panels reflect their meshes."""
from __future__ import annotations

import numpy as np
from matplotlib.image import imread

from senfunet_core.mesher import Mesh
from senfunet_core.render import render_mesh_png


def _sphere(n_lat: int = 30, n_lon: int = 60, r: float = 0.5, centre=(0.0, 0.0, 0.0)) -> Mesh:
    th = np.linspace(0, np.pi, n_lat + 1)
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    t, p = np.meshgrid(th, ph, indexing="ij")
    v = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3) * r + centre
    i, j = np.meshgrid(np.arange(n_lat), np.arange(n_lon), indexing="ij")
    a, b = i * n_lon + j, i * n_lon + (j + 1) % n_lon
    c, d = a + n_lon, b + n_lon
    f = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return Mesh(v.astype(np.float32), f.astype(np.int32), None)


def _background(img: np.ndarray) -> np.ndarray:
    return np.all(img[..., :3] > 0.99, axis=-1)


def test_single_sphere_png(tmp_path):
    p = tmp_path / "s.png"
    render_mesh_png(_sphere(), p, width_px=320, height_px=240)
    img = imread(p)
    assert img.shape[:2] == (240, 320)
    bg = _background(img)
    assert 0.05 < 1 - bg.mean() < 0.9  # something drawn, not everything
    # Solid, not a point cloud: the central region is fully covered and shaded (varying grey).
    centre = img[100:140, 140:180, :3]
    assert not _background(centre).any()
    assert centre[..., 0].std() > 0.005


def test_dense_sphere_has_no_holes(tmp_path):
    # ~200k triangles, most smaller than a pixel: the silhouette interior must be fully covered.
    p = tmp_path / "dense.png"
    render_mesh_png(_sphere(300, 340), p, width_px=200, height_px=200)
    img = imread(p)
    ys, xs = np.nonzero(~_background(img))
    cy, cx = ys.mean(), xs.mean()
    r = 0.8 * (ys.max() - ys.min()) / 2
    yy, xx = np.mgrid[:200, :200]
    inner = (yy - cy) ** 2 + (xx - cx) ** 2 < r * r
    assert not _background(img)[inner].any()


def test_panels_differ_only_when_meshes_differ(tmp_path):
    s = _sphere()
    moved = Mesh(s.vertices + np.float32([0.6, 0.0, 0.0]), s.faces,
                 np.tile(np.float32([0.9, 0.2, 0.2]), (s.n_vertices, 1)))
    same, diff = tmp_path / "same.png", tmp_path / "diff.png"
    render_mesh_png([s, s], same, titles=["a", "a"], width_px=400, height_px=200)
    render_mesh_png([s, moved], diff, titles=["a", "b"], width_px=400, height_px=200)
    a, b = imread(same)[..., :3], imread(diff)[..., :3]
    assert a.shape[:2] == b.shape[:2] == (200, 400)
    np.testing.assert_array_equal(a[:, :200], a[:, 200:])
    assert np.abs(b[30:, :200] - b[30:, 200:]).mean() > 0.01
    # The coloured panel shows red (R well above G) where the grey one cannot.
    right = b[30:, 200:]
    assert ((right[..., 0] - right[..., 1]) > 0.2).any()
    assert not ((b[30:, :200, 0] - b[30:, :200, 1]) > 0.2).any()
