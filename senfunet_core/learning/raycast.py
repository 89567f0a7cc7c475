"""Exact ray casting of pinhole views of a scene: depth, normals, surface ids and a textured,
lit colour image.

Cameras use the optical frame (z forward, x right, y down) and `T_world_camera` maps camera
coordinates to world coordinates. Ray directions are built with a camera-frame z component of 1,
so the ray parameter of a hit *is* its z-depth."""
from __future__ import annotations

import functools

import cv2
import numpy as np

from ..errors import InputError
from .geometry import _local_xyz, _prim_aabb, _prim_sdf
from .scenes import Primitive, Scene

TEXTURE_TILE = 256  # texels per side of a periodic texture tile


def intrinsics(width: int = 256, height: int = 256, fov_deg: float = 90.0) -> np.ndarray:
    """Pinhole K (3x3 float64): horizontal field of view fov_deg, square pixels, centred."""
    f = (width / 2.0) / np.tan(np.deg2rad(fov_deg) / 2.0)
    return np.array([[f, 0, (width - 1) / 2.0], [0, f, (height - 1) / 2.0], [0, 0, 1]], dtype=np.float64)


def intrinsics_scaled(K: np.ndarray, s: int) -> np.ndarray:
    """K of an image s times larger covering the same field of view (pixel centres preserved)."""
    K2 = np.array(K, dtype=np.float64)
    K2[0, 0] *= s
    K2[1, 1] *= s
    K2[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    K2[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    return K2


def _translation(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


@functools.lru_cache(maxsize=8)
def _camera_rays(K_key: tuple, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame ray directions (x, y) as (H, W) float32 with z = 1 (hit parameter == z-depth)."""
    K = np.array(K_key).reshape(3, 3)
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return ((u - K[0, 2]) / K[0, 0]).astype(np.float32), ((v - K[1, 2]) / K[1, 1]).astype(np.float32)


@functools.lru_cache(maxsize=16)
def _textures(scene: Scene) -> np.ndarray:
    """Atlas (S*(T+2), T+2) float32 of periodic texture tiles with a 1-texel wrap border."""
    T = TEXTURE_TILE
    fy = np.fft.fftfreq(T)[:, None]
    fx = np.fft.fftfreq(T)[None, :]
    f = np.sqrt(fx ** 2 + fy ** 2)
    tiles = []
    for s in scene.surfaces:
        rng = np.random.default_rng(s.texture_seed)
        beta = rng.uniform(0.6, 1.2) if not s.texture_poor else 3.0
        spec = np.fft.fft2(rng.standard_normal((T, T))) / np.maximum(f, 1.0 / T) ** beta
        spec[f > 0.4] = 0  # no detail finer than ~2.5 texels
        tex = np.real(np.fft.ifft2(spec))
        if s.pattern == 1 and not s.texture_poor:
            k = int(rng.integers(4, 24))
            ang = np.arange(T) * 2 * np.pi * k / T
            tex = tex / tex.std() + 0.8 * np.sin(ang)[None, :]
        elif s.pattern == 2 and not s.texture_poor:
            cell = int(rng.choice([16, 32, 64]))
            vals = rng.standard_normal((T // cell, T // cell))
            tex = tex / tex.std() + 0.9 * np.kron(vals, np.ones((cell, cell)))
            tex[::cell, :] -= 2.0  # grout / plank gaps
        tex = (tex - tex.mean()) / max(tex.std(), 1e-9)
        tile = np.clip(1.0 + s.contrast * tex, 0.2, 2.0).astype(np.float32)
        tiles.append(np.pad(tile, 1, mode="wrap"))
    return np.concatenate(tiles, 0)


def _proj_rect(prim: Primitive, R_cw: np.ndarray, t_cw: np.ndarray, K: np.ndarray, w: int, h: int):
    """Pixel rectangle (v0, v1, u0, u1) that may contain the primitive, None if surely not visible."""
    c = np.asarray(prim.center_m)
    r = np.asarray(prim.size_m)
    if prim.kind == "box":
        ext = np.abs(np.cos(prim.yaw_rad)) * r[0] + np.abs(np.sin(prim.yaw_rad)) * r[1]
        eyt = np.abs(np.sin(prim.yaw_rad)) * r[0] + np.abs(np.cos(prim.yaw_rad)) * r[1]
        r = np.array([ext, eyt, r[2]])
    corners = c + r * np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    pc = corners @ R_cw.T + t_cw
    z = pc[:, 2]
    if np.all(z <= 1e-3):
        return None
    if np.any(z <= 1e-3):
        return (0, h, 0, w)
    u = K[0, 0] * pc[:, 0] / z + K[0, 2]
    vv = K[1, 1] * pc[:, 1] / z + K[1, 2]
    u0, u1 = int(max(np.floor(u.min()) - 1, 0)), int(min(np.ceil(u.max()) + 2, w))
    v0, v1 = int(max(np.floor(vv.min()) - 1, 0)), int(min(np.ceil(vv.max()) + 2, h))
    if u0 >= u1 or v0 >= v1:
        return None
    return (v0, v1, u0, u1)


def _intersect(prim: Primitive, o: np.ndarray, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray) -> np.ndarray:
    """Ray parameter of the first hit in front of the origin (inf where none)."""
    q = o - np.asarray(prim.center_m)
    if prim.yaw_rad != 0.0:
        c, s = np.float32(np.cos(prim.yaw_rad)), np.float32(np.sin(prim.yaw_rad))
        q = np.array([c * q[0] + s * q[1], -s * q[0] + c * q[1], q[2]])
        dx, dy = c * dx + s * dy, -s * dx + c * dy
    q = q.astype(np.float32)
    if prim.kind == "box":
        nears, fars = [], []
        for qa, da, ha in ((q[0], dx, prim.size_m[0]), (q[1], dy, prim.size_m[1]), (q[2], dz, prim.size_m[2])):
            # a ray parallel to a slab gets +-huge parameters with the right signs
            inv = np.float32(1.0) / np.where(da == 0, np.float32(1e-20), da)
            t1 = (np.float32(-ha) - qa) * inv
            t2 = (np.float32(ha) - qa) * inv
            nears.append(np.minimum(t1, t2))
            fars.append(np.maximum(t1, t2))
        tn = np.maximum(np.maximum(nears[0], nears[1]), nears[2])
        tf = np.minimum(np.minimum(fars[0], fars[1]), fars[2])
        return np.where((tn <= tf) & (tn > 1e-6), tn, np.float32(np.inf))
    r = np.float32(prim.size_m[0])
    if prim.kind == "sphere":
        a = dx * dx + dy * dy + dz * dz
        b = q[0] * dx + q[1] * dy + q[2] * dz
        disc = b * b - a * np.float32(q @ q - r * r)
        with np.errstate(invalid="ignore"):
            t = (-b - np.sqrt(disc)) / a
        return np.where((disc >= 0) & (t > 1e-6), t, np.float32(np.inf))
    # vertical cylinder: side (quadratic in xy) and the cap facing the ray
    hz = np.float32(prim.size_m[2])
    a = dx * dx + dy * dy
    b = q[0] * dx + q[1] * dy
    disc = b * b - a * np.float32(q[0] ** 2 + q[1] ** 2 - r * r)
    with np.errstate(invalid="ignore", divide="ignore"):
        ts = (-b - np.sqrt(disc)) / a
        zs = q[2] + ts * dz
        t_side = np.where((disc >= 0) & (a > 0) & (ts > 1e-6) & (np.abs(zs) <= hz), ts, np.float32(np.inf))
        tc = (np.where(dz > 0, -hz, hz) - q[2]) / dz
        xc = q[0] + tc * dx
        yc = q[1] + tc * dy
        t_cap = np.where((dz != 0) & (tc > 1e-6) & (xc * xc + yc * yc <= r * r), tc, np.float32(np.inf))
    return np.minimum(t_side, t_cap)


def _normals_and_uv(prim: Primitive, x: np.ndarray, y: np.ndarray, z: np.ndarray):
    """World normals (3 arrays) and texture coordinates (u, v) of surface points of a primitive."""
    qx, qy, qz = _local_xyz(prim, x, y, z)
    zero = np.zeros_like(qx)
    if prim.kind == "box":
        hx, hy, hz = prim.size_m
        ex, ey, ez = np.abs(qx) - hx, np.abs(qy) - hy, np.abs(qz) - hz
        dom = np.where((ex >= ey) & (ex >= ez), 0, np.where(ey >= ez, 1, 2))
        nx = np.where(dom == 0, np.sign(qx), zero)
        ny = np.where(dom == 1, np.sign(qy), zero)
        nz = np.where(dom == 2, np.sign(qz), zero)
    elif prim.kind == "sphere":
        rn = np.maximum(np.sqrt(qx * qx + qy * qy + qz * qz), 1e-12)
        nx, ny, nz = qx / rn, qy / rn, qz / rn
        ax, ay, az = np.abs(nx), np.abs(ny), np.abs(nz)
        dom = np.where((ax >= ay) & (ax >= az), 0, np.where(ay >= az, 1, 2))
    else:
        r, hz = prim.size_m[0], prim.size_m[2]
        rad = np.maximum(np.sqrt(qx * qx + qy * qy), 1e-12)
        cap = np.abs(np.abs(qz) - hz) < np.abs(rad - r)
        nx = np.where(cap, zero, qx / rad)
        ny = np.where(cap, zero, qy / rad)
        nz = np.where(cap, np.sign(qz), zero)
        dom = np.where(cap, 2, 0)
        # unwrap the side into (arc length, z) so its texture is not smeared
        qx, qy = np.where(cap, qx, 0), np.where(cap, qy, np.arctan2(qy, qx) * r)
    c, s = float(np.cos(prim.yaw_rad)), float(np.sin(prim.yaw_rad))
    nx, ny = c * nx - s * ny, s * nx + c * ny
    # texture coordinates: the two local coordinates across the dominant normal axis
    u = np.where(dom == 0, qy, qx)
    v = np.where(dom == 2, qy, qz)
    return (nx, ny, nz), (u, v)


def _room_exit(scene: Scene, o: np.ndarray, d: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameter where each ray leaves the room (the nearest of the 6 planes: the camera is
    inside) and the axis of that plane."""
    L = scene.room_size_m
    depth: np.ndarray | None = None
    axis = np.zeros(0, np.int8)  # replaced on the first axis
    for a in range(3):
        da = np.where(d[a] == 0, np.float32(1e-20), d[a])
        ta = np.where(da > 0, np.float32(L[a] - o[a]), np.float32(-o[a])) / da
        if depth is None:
            depth, axis = ta, np.zeros(ta.shape, np.int8)
        else:
            closer = ta < depth
            depth = np.where(closer, ta, depth)
            axis = np.where(closer, np.int8(a), axis)
    assert depth is not None  # set by the first of the 3 axes
    return depth, axis


def _nearest_primitives(scene: Scene, T: np.ndarray, K: np.ndarray, width: int, height: int, d: tuple,
                        depth: np.ndarray) -> tuple[np.ndarray, list[tuple[int, tuple]]]:
    """Lowers `depth` where a primitive is hit first; the primitive id per pixel (-1 = room) and
    the (primitive, screen rectangle) pairs that won pixels."""
    dx, dy, dz = d
    o = T[:3, 3].copy()
    pid = np.full(dx.shape, -1, np.int32)
    R_cw, t_cw = T[:3, :3].T, -T[:3, :3].T @ o
    won: list[tuple[int, tuple]] = []
    for i, prim in enumerate(scene.primitives):
        rect = _proj_rect(prim, R_cw, t_cw, K, width, height)
        if rect is None:
            continue
        v0, v1, u0, u1 = rect
        sl = (slice(v0, v1), slice(u0, u1))
        t = _intersect(prim, o, dx[sl], dy[sl], dz[sl])
        closer = t < depth[sl]
        if np.any(closer):
            depth[sl] = np.where(closer, t, depth[sl])
            pid[sl] = np.where(closer, i, pid[sl])
            won.append((i, sl))
    return pid, won


def _shade(scene: Scene, p: tuple, n: tuple, uv: tuple, surf: np.ndarray) -> np.ndarray:
    """Colour image (H, W, 3) uint8: albedo x periodic texture x (ambient + Lambertian point lights)."""
    (px, py, pz), (nx, ny, nz), (u, v) = p, n, uv
    atlas = _textures(scene)
    Tt = np.float32(TEXTURE_TILE)
    inv_texel = np.take(np.array([1.0 / s_.texel_m for s_ in scene.surfaces], np.float32), surf)
    tu = u * inv_texel
    tu -= np.floor(tu / Tt) * Tt  # periodic tile (cheaper than np.mod)
    tv = v * inv_texel
    tv -= np.floor(tv / Tt) * Tt
    tv += (surf * (TEXTURE_TILE + 2)).astype(np.float32)
    mod = cv2.remap(atlas, tu + 1, tv + 1, cv2.INTER_LINEAR)
    shade = np.full(px.shape, scene.ambient, np.float32)
    for lx, ly, lz in scene.lights_m:
        vx, vy, vz = lx - px, ly - py, lz - pz
        dist2 = vx * vx + vy * vy + vz * vz
        lam = np.maximum(nx * vx + ny * vy + nz * vz, 0) / np.sqrt(dist2)
        shade += scene.light_level * lam / (1.0 + dist2 / 6.25)
    intensity = mod * shade * 255.0
    albedo = np.array([s_.color_rgb for s_ in scene.surfaces], np.float32)
    return cv2.convertScaleAbs(cv2.merge([np.take(albedo[:, c], surf) * intensity for c in range(3)]))


def _room_surface_frame(axis: np.ndarray, d: tuple, p: tuple) -> tuple[np.ndarray, ...]:
    """Where the room is hit: the normal along the exit axis against the ray (3 arrays), texture
    coordinates in the wall plane (u, v) and the surface (floor, ceiling, x0, x1, y0, y1: 0-5)."""
    (dx, dy, dz), (px, py, pz) = d, p
    one = np.float32(1)
    nx = np.where(axis == 0, np.where(dx > 0, -one, one), 0).astype(np.float32)
    ny = np.where(axis == 1, np.where(dy > 0, -one, one), 0).astype(np.float32)
    nz = np.where(axis == 2, np.where(dz > 0, -one, one), 0).astype(np.float32)
    u = np.where(axis == 0, py, px)
    v = np.where(axis == 2, py, pz)
    surf = np.where(axis == 2, np.where(dz < 0, 0, 1),
                    np.where(axis == 0, np.where(dx < 0, 2, 3), np.where(dy < 0, 4, 5))).astype(np.int32)
    return nx, ny, nz, u, v, surf


def render_view(scene: Scene, T_world_camera: np.ndarray, K: np.ndarray, width: int, height: int,
                *, with_rgb: bool = True, with_other_distance: bool = False) -> dict[str, np.ndarray]:
    """Exact ray casting of one pinhole view (vectorised over rays, looping over primitives).

    Returns depth_m (H,W) float32 z-depth, normal_cam (H,W,3) float32 unit normals facing the
    camera, surface_id (H,W) int32, primitive_id (H,W) int32 (-1 = room), cos_incidence (H,W)
    float32 |cos(normal, ray)|, and if with_rgb: rgb (H,W,3) uint8 (albedo x texture x
    Lambertian point lights + ambient); if with_other_distance: other_distance_m (H,W) float32, the
    distance from the hit point to the nearest other surface (another room plane or primitive),
    capped at OTHER_DISTANCE_CAP_M (ToF multipath is strong in concave corners).
    """
    T = np.asarray(T_world_camera, dtype=np.float64)
    if T.shape != (4, 4):
        raise InputError(f"T_world_camera must be 4x4, got {T.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise InputError(f"K must be 3x3, got {K.shape}")
    R = T[:3, :3].astype(np.float32)
    o = T[:3, 3].copy()
    ox, oy, oz = (float(c) for c in o)  # python floats keep the float32 arrays float32
    xc, yc = _camera_rays(tuple(K.ravel()), int(width), int(height))
    dx = R[0, 0] * xc + R[0, 1] * yc + R[0, 2]
    dy = R[1, 0] * xc + R[1, 1] * yc + R[1, 2]
    dz = R[2, 0] * xc + R[2, 1] * yc + R[2, 2]
    d = (dx, dy, dz)

    depth, axis = _room_exit(scene, o, d)
    pid, won = _nearest_primitives(scene, T, K, width, height, d, depth)

    px, py, pz = ox + dx * depth, oy + dy * depth, oz + dz * depth
    nx, ny, nz, u, v, surf = _room_surface_frame(axis, d, (px, py, pz))
    # primitives overwrite the pixels they won (only inside their screen rectangles)
    for i, sl in won:
        m = pid[sl] == i
        if not np.any(m):
            continue
        prim = scene.primitives[i]
        (nx[sl][m], ny[sl][m], nz[sl][m]), (u[sl][m], v[sl][m]) = _normals_and_uv(prim, px[sl][m], py[sl][m],
                                                                                  pz[sl][m])
        surf[sl][m] = prim.surface
    rn = np.sqrt(dx * dx + dy * dy + dz * dz)
    cosi = (nx * dx + ny * dy + nz * dz) / rn
    flip = np.where(cosi > 0, np.float32(-1), np.float32(1))  # normals face the camera
    nx, ny, nz = nx * flip, ny * flip, nz * flip
    normal_cam = np.stack([R[0, j] * nx + R[1, j] * ny + R[2, j] * nz for j in range(3)], -1)
    out = {
        "depth_m": depth.astype(np.float32),
        "normal_cam": normal_cam.astype(np.float32),
        "surface_id": surf,
        "primitive_id": pid,
        "cos_incidence": np.abs(cosi).astype(np.float32),
    }
    if with_other_distance:
        out["other_distance_m"] = _other_surface_distance(scene, px, py, pz, axis, (dx, dy, dz), pid)
    if with_rgb:
        out["rgb"] = _shade(scene, (px, py, pz), (nx, ny, nz), (u, v), surf)
    return out


OTHER_DISTANCE_CAP_M = 0.5


def _other_surface_distance(scene: Scene, px: np.ndarray, py: np.ndarray, pz: np.ndarray, axis: np.ndarray,
                            d: tuple, pid: np.ndarray) -> np.ndarray:
    """Per hit point, the distance to the nearest surface other than the hit one (capped)."""
    lx, ly, lz = scene.room_size_m
    cap = np.float32(OTHER_DISTANCE_CAP_M)
    room_hit = pid < 0
    out = np.full(px.shape, cap, np.float32)
    for a, (coord, size) in enumerate(((px, lx), (py, ly), (pz, lz))):
        hit_axis = room_hit & (axis == a)
        for plane, dist in ((0, coord), (1, size - coord)):  # the plane at 0 and the one at size
            hit_this = hit_axis & ((d[a] > 0) == bool(plane))
            out = np.where(hit_this, out, np.minimum(out, dist.astype(np.float32)))
    flat = (px.ravel(), py.ravel(), pz.ravel())
    pid_flat = pid.ravel()
    res = out.ravel()
    for i, prim in enumerate(scene.primitives):
        lo, hi = _prim_aabb(prim)
        near = np.flatnonzero((flat[0] >= lo[0] - cap) & (flat[0] <= hi[0] + cap) & (flat[1] >= lo[1] - cap)
                              & (flat[1] <= hi[1] + cap) & (flat[2] >= lo[2] - cap) & (flat[2] <= hi[2] + cap)
                              & (pid_flat != i))
        if len(near):
            dist = _prim_sdf(prim, flat[0][near], flat[1][near], flat[2][near]).astype(np.float32)
            res[near] = np.minimum(res[near], np.maximum(dist, 0))
    return res.reshape(px.shape)
