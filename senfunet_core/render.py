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

    zbuf = np.full(width * height, np.inf)
    fbuf = np.full(width * height, -1, np.int64)
    b1buf = np.zeros(width * height)
    b2buf = np.zeros(width * height)
    _zbuffer(F, u, v, z, width, height, near, zbuf, fbuf, b1buf, b2buf)

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
def _zbuffer(faces: np.ndarray, u: np.ndarray, v: np.ndarray, z: np.ndarray, width: int, height: int, near: float,
             zbuf: np.ndarray, fbuf: np.ndarray, b1buf: np.ndarray, b2buf: np.ndarray) -> None:
    """Each triangle of `faces`, in order (u, v: its corners' pixel coordinates, z: their depths), at
    the pixel centres of its bounding box inside it (barycentrics with inclusive edges, so adjacent
    triangles leave no cracks): where its perspective-correct depth (1/z interpolated in screen
    space) is nearer than zbuf's, it takes the pixel (zbuf, fbuf: its index, b1buf/b2buf: its
    barycentrics there). A tie keeps the earlier. Triangles with a corner behind the near plane are
    dropped (no clipping: the default camera sees the whole scene in front of it), as are those
    without area."""
    eps = -1e-7
    for t in range(faces.shape[0]):
        i0, i1, i2 = faces[t, 0], faces[t, 1], faces[t, 2]
        z0, z1, z2 = z[i0], z[i1], z[i2]
        if not (z0 > near and z1 > near and z2 > near and np.isfinite(z0) and np.isfinite(z1) and np.isfinite(z2)):
            continue
        u0, u1, u2 = u[i0], u[i1], u[i2]
        v0, v1, v2 = v[i0], v[i1], v[i2]
        # the pixels whose centres lie within the triangle's box
        x_first = max(int(np.floor(min(u0, u1, u2) - 0.5)) + 1, 0)
        x_last = min(int(np.floor(max(u0, u1, u2) - 0.5)), width - 1)
        y_first = max(int(np.floor(min(v0, v1, v2) - 0.5)) + 1, 0)
        y_last = min(int(np.floor(max(v0, v1, v2) - 0.5)), height - 1)
        d = (u1 - u0) * (v2 - v0) - (u2 - u0) * (v1 - v0)  # signed doubled area
        if x_last < x_first or y_last < y_first or abs(d) <= 1e-12:
            continue
        for py in range(y_first, y_last + 1):
            pv = py + 0.5
            for px in range(x_first, x_last + 1):
                pu = px + 0.5
                b1 = ((pu - u0) * (v2 - v0) - (u2 - u0) * (pv - v0)) / d
                b2 = ((u1 - u0) * (pv - v0) - (pu - u0) * (v1 - v0)) / d
                b0 = 1.0 - b1 - b2
                if b0 >= eps and b1 >= eps and b2 >= eps:
                    depth = 1.0 / (b0 / z0 + b1 / z1 + b2 / z2)
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
