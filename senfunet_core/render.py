"""Headless mesh pictures: a z-buffer rasteriser (numba) plus matplotlib (Agg) layout.

Used by the demo and the docs figures. Each triangle is rasterised exactly at pixel centres (the
centres of its bounding box that pass the barycentric test), nearest depth per pixel, so even a
room's mesh of millions of triangles renders as a solid surface.
"""
from __future__ import annotations

import os
from collections.abc import Sequence

import numba
import numpy as np

from .errors import InputError
from .mesher import Mesh

_BACKGROUND = np.array([1.0, 1.0, 1.0])
_DEFAULT_GREY = np.array([0.72, 0.72, 0.72], np.float32)
_FOV_DEG = 45.0  # vertical field of view of the default camera


def _look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """T_world_camera for an optical-frame camera (z forward, x right, y down) at `eye`."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight along `up`: any perpendicular will do
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def default_camera(meshes: Sequence[Mesh], aspect: float, view: tuple[float, float] | None = None) -> np.ndarray:
    """T_world_camera looking at the common bounding-box centre from outside, whole scene in view.

    `view` is (azimuth_deg, elevation_deg) around the world z axis (z up); default (-60, 45).
    """
    pts = [np.asarray(m.vertices, np.float64).reshape(-1, 3) for m in meshes]
    pts = [p[np.isfinite(p).all(axis=1)] for p in pts]
    pts = [p for p in pts if len(p)]
    if not pts:
        lo, hi = np.zeros(3), np.ones(3)
    else:
        allp = np.concatenate(pts)
        lo, hi = allp.min(axis=0), allp.max(axis=0)
    centre = (lo + hi) / 2
    hi = np.maximum(hi, lo + 1e-3)  # flat or single-point scenes still get a finite view
    az, el = np.deg2rad(view if view is not None else (-60.0, 45.0))
    direction = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    T = _look_at(centre + direction, centre, np.array([0.0, 0.0, 1.0]))
    # Back the camera off along its axis just enough that all 8 box corners are inside both
    # fields of view: moving along z leaves a corner's x, y unchanged, so this is exact.
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    cc = (corners - centre) @ T[:3, :3]  # camera-frame coordinates with the eye at the centre
    tan_v = np.tan(np.deg2rad(_FOV_DEG) / 2) / 1.06  # ~6% margin around the scene
    tan_h = tan_v * aspect
    back = float(np.max(np.maximum(np.abs(cc[:, 0]) / tan_h, np.abs(cc[:, 1]) / tan_v) - cc[:, 2]))
    T[:3, 3] = centre - back * T[:3, 2]
    return T


def rasterize(mesh: Mesh, T_world_camera: np.ndarray, width: int, height: int,
              fov_deg: float = _FOV_DEG) -> np.ndarray:
    """Render one mesh to an (height, width, 3) float RGB image in 0..1 (white background).

    Flat Lambertian shading from face normals (two-sided, light at the camera's upper left)
    times barycentrically interpolated vertex colours; grey when the mesh has no colours.
    """
    img = np.tile(_BACKGROUND, (height, width, 1))
    V = np.asarray(mesh.vertices, np.float64).reshape(-1, 3)
    F = np.asarray(mesh.faces, np.int64).reshape(-1, 3)
    if len(F) == 0 or len(V) == 0:
        return img
    T_cw = np.linalg.inv(T_world_camera)
    Vc = V @ T_cw[:3, :3].T + T_cw[:3, 3]
    f = (height / 2) / np.tan(np.deg2rad(fov_deg) / 2)
    near = 1e-4
    z = Vc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = f * Vc[:, 0] / z + width / 2
        v = f * Vc[:, 1] / z + height / 2

    # Triangles with a vertex behind the near plane are dropped (no clipping: the default
    # camera always sees the whole scene in front of it).
    zf = z[F]
    keep = (zf > near).all(axis=1) & np.isfinite(zf).all(axis=1)
    uf, vf = u[F], v[F]
    # (per-column minimum and maximum: numpy's reductions along a row of 3 are slow)
    x0 = np.floor(np.minimum(np.minimum(uf[:, 0], uf[:, 1]), uf[:, 2]) - 0.5).astype(np.int64) + 1  # first pixel
    x1 = np.floor(np.maximum(np.maximum(uf[:, 0], uf[:, 1]), uf[:, 2]) - 0.5).astype(np.int64)  # whose centre >= min
    y0 = np.floor(np.minimum(np.minimum(vf[:, 0], vf[:, 1]), vf[:, 2]) - 0.5).astype(np.int64) + 1
    y1 = np.floor(np.maximum(np.maximum(vf[:, 0], vf[:, 1]), vf[:, 2]) - 0.5).astype(np.int64)
    keep &= (x1 >= 0) & (y1 >= 0) & (x0 < width) & (y0 < height)
    x0, y0 = np.maximum(x0, 0), np.maximum(y0, 0)
    x1, y1 = np.minimum(x1, width - 1), np.minimum(y1, height - 1)
    keep &= (x1 >= x0) & (y1 >= y0)
    # Signed doubled area; zero-area triangles cover nothing.
    den = (uf[:, 1] - uf[:, 0]) * (vf[:, 2] - vf[:, 0]) - (uf[:, 2] - uf[:, 0]) * (vf[:, 1] - vf[:, 0])
    keep &= np.abs(den) > 1e-12
    tri = np.flatnonzero(keep)
    if tri.size == 0:
        return img

    zbuf = np.full(width * height, np.inf)
    fbuf = np.full(width * height, -1, np.int64)
    b1buf = np.zeros(width * height)
    b2buf = np.zeros(width * height)
    _zbuffer(tri, x0, x1, y0, y1, np.ascontiguousarray(uf), np.ascontiguousarray(vf), np.ascontiguousarray(zf), den,
             width, zbuf, fbuf, b1buf, b2buf)

    hit = np.flatnonzero(fbuf >= 0)
    if hit.size == 0:
        return img
    hf = fbuf[hit]
    # Face normals in the camera frame; shade both sides alike (open meshes show their backs).
    tv = Vc[F[hf]]
    n = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
    light = np.array([-0.4, -0.6, -1.0])  # towards the upper left of and behind the viewer
    light /= np.linalg.norm(light)
    shade = 0.25 + 0.75 * np.abs(n @ light)

    if mesh.colors is not None and len(mesh.colors) == len(V):
        C = np.asarray(mesh.colors, np.float64)
        fb1, fb2 = b1buf[hit, None], b2buf[hit, None]
        # Colour at the pixel from the screen-space barycentrics (good enough for display).
        col = (1 - fb1 - fb2) * C[F[hf, 0]] + fb1 * C[F[hf, 1]] + fb2 * C[F[hf, 2]]
        col = np.clip(col, 0.0, 1.0)
    else:
        col = np.broadcast_to(_DEFAULT_GREY, (hit.size, 3))
    flat = img.reshape(-1, 3)
    flat[hit] = col * shade[:, None]
    return img


@numba.njit(cache=True, nogil=True)
def _zbuffer(tri: np.ndarray, x0: np.ndarray, x1: np.ndarray, y0: np.ndarray, y1: np.ndarray, uf: np.ndarray,
             vf: np.ndarray, zf: np.ndarray, den: np.ndarray, width: int, zbuf: np.ndarray, fbuf: np.ndarray,
             b1buf: np.ndarray, b2buf: np.ndarray) -> None:
    """Each triangle of `tri`, in order, at the pixel centres of its bounding box [x0, x1] x [y0, y1]
    inside it (barycentrics with inclusive edges, so adjacent triangles leave no cracks): where its
    perspective-correct depth (1/z interpolated in screen space) is nearer than zbuf's, it takes the
    pixel (zbuf, fbuf: its index, b1buf/b2buf: its barycentrics there). A tie keeps the earlier."""
    eps = -1e-7
    for k in range(tri.size):
        t = tri[k]
        u0, u1, u2 = uf[t, 0], uf[t, 1], uf[t, 2]
        v0, v1, v2 = vf[t, 0], vf[t, 1], vf[t, 2]
        d = den[t]
        for py in range(y0[t], y1[t] + 1):
            pv = py + 0.5
            for px in range(x0[t], x1[t] + 1):
                pu = px + 0.5
                b1 = ((pu - u0) * (v2 - v0) - (u2 - u0) * (pv - v0)) / d
                b2 = ((u1 - u0) * (pv - v0) - (pu - u0) * (v1 - v0)) / d
                b0 = 1.0 - b1 - b2
                if b0 >= eps and b1 >= eps and b2 >= eps:
                    depth = 1.0 / (b0 / zf[t, 0] + b1 / zf[t, 1] + b2 / zf[t, 2])
                    pixel = py * width + px
                    if depth < zbuf[pixel]:
                        zbuf[pixel] = depth
                        fbuf[pixel] = t
                        b1buf[pixel] = b1
                        b2buf[pixel] = b2


def render_mesh_png(meshes: list[Mesh] | Mesh, path: str | os.PathLike, *, titles: list[str] | None = None,
                    view: tuple[float, float] | np.ndarray | None = None,
                    width_px: int = 800, height_px: int = 600) -> None:
    """Save a PNG of width_px x height_px showing the meshes side by side, same camera for all.

    `view`: None for the default camera (looking down at ~45 degrees at the common bounding-box
    centre, everything in view), (azimuth_deg, elevation_deg) to choose the direction, or a
    4x4 T_world_camera (optical frame, 45 degree vertical field of view).
    """
    # Figure + the Agg canvas directly (not pyplot): no display, no global backend switch.
    from matplotlib.figure import Figure
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    if isinstance(meshes, Mesh):
        meshes = [meshes]
    meshes = list(meshes)
    if not meshes:
        raise InputError("render_mesh_png: no meshes given")
    if titles is not None and len(titles) != len(meshes):
        raise InputError(f"render_mesh_png: {len(titles)} titles for {len(meshes)} meshes")
    if width_px < len(meshes) or height_px < 8:
        raise InputError(f"render_mesh_png: image {width_px}x{height_px} too small for {len(meshes)} panels")

    n = len(meshes)
    title_h = 28 if titles else 0
    panel_h = height_px - title_h
    # Integer panel widths that add up to width_px, so no panel is resampled.
    edges = np.linspace(0, width_px, n + 1).round().astype(int)
    panel_w = int(np.diff(edges).min())
    if view is not None and np.asarray(view).shape == (4, 4):
        T = np.asarray(view, np.float64)
    else:
        T = default_camera(meshes, panel_w / panel_h, None if view is None else tuple(view))

    dpi = 100
    fig = Figure(figsize=(width_px / dpi, height_px / dpi), dpi=dpi, facecolor="white")
    FigureCanvasAgg(fig)
    for i, m in enumerate(meshes):
        w = int(edges[i + 1] - edges[i])
        img = rasterize(m, T, w, panel_h)
        ax = fig.add_axes((edges[i] / width_px, 0.0, w / width_px, panel_h / height_px))
        ax.imshow(img, interpolation="nearest", aspect="auto")
        ax.set_axis_off()
        if titles:
            fig.text((edges[i] + w / 2) / width_px, 1.0 - (title_h / 2) / height_px, titles[i],
                     ha="center", va="center", fontsize=11)
    fig.savefig(os.fspath(path), dpi=dpi, facecolor="white", format="png")
