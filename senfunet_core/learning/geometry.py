"""Signed distances of a scene and the ground truth derived from them: the SDF (> 0 in free
space), the GT TSDF truncated at +-band/2 (at points or on whole voxel blocks) and the GT mesh."""
from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..mesher import Mesh
from .scenes import Primitive, Scene


def _box_sdf(x: np.ndarray, y: np.ndarray, z: np.ndarray, half) -> np.ndarray:
    """Exact SDF of an axis-aligned box centred at 0 (local coordinates as separate arrays)."""
    dx, dy, dz = np.abs(x) - half[0], np.abs(y) - half[1], np.abs(z) - half[2]
    outside = np.sqrt(np.maximum(dx, 0) ** 2 + np.maximum(dy, 0) ** 2 + np.maximum(dz, 0) ** 2)
    return outside + np.minimum(np.maximum(np.maximum(dx, dy), dz), 0)


def _local_xyz(prim: Primitive, x: np.ndarray, y: np.ndarray, z: np.ndarray):
    cx, cy, cz = prim.center_m
    qx, qy, qz = x - cx, y - cy, z - cz
    if prim.yaw_rad != 0.0:
        c, s = float(np.cos(prim.yaw_rad)), float(np.sin(prim.yaw_rad))
        qx, qy = c * qx + s * qy, -s * qx + c * qy
    return qx, qy, qz


def _prim_sdf(prim: Primitive, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    qx, qy, qz = _local_xyz(prim, x, y, z)
    if prim.kind == "box":
        return _box_sdf(qx, qy, qz, prim.size_m)
    if prim.kind == "sphere":
        return np.sqrt(qx * qx + qy * qy + qz * qz) - prim.size_m[0]
    # vertical capped cylinder: 2D box sdf in (radial, axial)
    dr = np.sqrt(qx * qx + qy * qy) - prim.size_m[0]
    dz = np.abs(qz) - prim.size_m[2]
    return np.sqrt(np.maximum(dr, 0) ** 2 + np.maximum(dz, 0) ** 2) + np.minimum(np.maximum(dr, dz), 0)


def _room_sdf(scene: Scene, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Distance to the nearest wall plane, positive inside the room (exact in free space; behind
    the walls only the sign matters)."""
    lx, ly, lz = scene.room_size_m
    return np.minimum(np.minimum(np.minimum(x, lx - x), np.minimum(y, ly - y)), np.minimum(z, lz - z))


def scene_sdf(scene: Scene, points_m: np.ndarray) -> np.ndarray:
    """Signed distance (N,) float32: > 0 in free space, < 0 inside walls and objects."""
    p = np.asarray(points_m, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"points_m must be (N, 3), got {p.shape}")
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    d = _room_sdf(scene, x, y, z)
    for prim in scene.primitives:
        d = np.minimum(d, _prim_sdf(prim, x, y, z))
    return d.astype(np.float32)


def _prim_aabb(prim: Primitive) -> tuple[np.ndarray, np.ndarray]:
    """World axis-aligned bounding box (lo, hi) of a primitive."""
    c = np.asarray(prim.center_m, np.float64)
    r = np.asarray(prim.size_m, np.float64)
    if prim.kind == "box" and prim.yaw_rad != 0.0:
        ca, sa = abs(np.cos(prim.yaw_rad)), abs(np.sin(prim.yaw_rad))
        r = np.array([ca * r[0] + sa * r[1], sa * r[0] + ca * r[1], r[2]])
    return c - r, c + r


def gt_tsdf(scene: Scene, points_m: np.ndarray, band_m: float = 0.1) -> np.ndarray:
    """Ground-truth TSDF (N,) float32: scene_sdf clipped to +-band_m / 2.

    Equal to np.clip(scene_sdf(...)) but faster: a primitive's SDF is evaluated only at points
    within band_m / 2 of its bounding box (elsewhere it exceeds the truncation and cannot win)."""
    p = np.asarray(points_m, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"points_m must be (N, 3), got {p.shape}")
    half = band_m / 2
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    d = _room_sdf(scene, x, y, z)
    for prim in scene.primitives:
        lo, hi = _prim_aabb(prim)
        near = np.flatnonzero((x >= lo[0] - half) & (x <= hi[0] + half) & (y >= lo[1] - half) & (y <= hi[1] + half)
                              & (z >= lo[2] - half) & (z <= hi[2] + half))
        if len(near):
            d[near] = np.minimum(d[near], _prim_sdf(prim, x[near], y[near], z[near]))
    return np.clip(d.astype(np.float32), -half, half).astype(np.float32)


def gt_tsdf_blocks(scene: Scene, block_coords: np.ndarray, voxel_size_m: float, band_m: float = 0.1,
                   block: int = 8) -> np.ndarray:
    """GT TSDF (B, block^3) float32 at the voxel centres of whole blocks (x-major local order, voxel
    (i, j, k) centred at (i, j, k) * voxel_size_m): gt_tsdf with the primitives culled per block."""
    bc = np.asarray(block_coords, np.int64).reshape(-1, 3)
    r = np.arange(block)
    local = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    vox = bc[:, None, :] * block + local[None]
    x, y, z = (vox[..., i] * float(voxel_size_m) for i in range(3))
    half = band_m / 2
    d = _room_sdf(scene, x, y, z)
    blo = bc * block * float(voxel_size_m)
    bhi = (bc * block + block - 1) * float(voxel_size_m)
    for prim in scene.primitives:
        lo, hi = _prim_aabb(prim)
        sel = np.flatnonzero(np.all(bhi >= lo - half, axis=1) & np.all(blo <= hi + half, axis=1))
        if len(sel):
            d[sel] = np.minimum(d[sel], _prim_sdf(prim, x[sel], y[sel], z[sel]))
    return np.clip(d.astype(np.float32), -half, half).astype(np.float32)


def _surface_blocks(scene: Scene, v: float, bs: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Blocks of bs^3 voxels that may hold surface: all block keys (N, 3), the active ones' indices
    (A,) and which of the room and the primitives can be the nearest surface in each ((1 + P), A)."""
    room = np.asarray(scene.room_size_m)
    lo = -np.ones(3, int)  # one block below 0 so the floor and walls are inside the grid
    hi = np.ceil((room + 2 * v) / (bs * v)).astype(int)
    ba, bb, bc = np.meshgrid(*[np.arange(lo[i], hi[i]) for i in range(3)], indexing="ij")
    bkeys = np.stack([ba.ravel(), bb.ravel(), bc.ravel()], -1)
    cx, cy, cz = ((bkeys * bs + bs / 2) * v).T  # centre of the 9^3 samples 8a..8a+8
    radius = bs / 2 * v * np.sqrt(3)
    per = np.stack([_room_sdf(scene, cx, cy, cz)] + [_prim_sdf(p, cx, cy, cz) for p in scene.primitives], 0)
    dmin = per.min(0)
    act = np.nonzero(np.abs(dmin) < radius + v)[0]
    # primitive k can be the nearest somewhere in block b only if sdf_k(c) - r <= min(c) + r
    relevant = per[:, act] <= (dmin[act] + 2 * radius + 1e-9)[None]
    return bkeys, act, relevant


def gt_mesh(scene: Scene, voxel_size_m: float = 0.01) -> Mesh:
    """Marching cubes of the SDF at level 0 (faces counter-clockwise seen from free space).

    Coarse pass on 8^3-voxel blocks (SDF is 1-Lipschitz: a block whose centre is farther from
    every surface than its half diagonal holds no surface), fine pass only in the other blocks and
    only with the primitives that can be the nearest there.
    """
    v = float(voxel_size_m)
    if not v > 0:
        raise InputError(f"voxel_size_m must be > 0, got {voxel_size_m}")
    bs = 8
    bkeys, act, relevant = _surface_blocks(scene, v, bs)
    n_act = len(act)
    if n_act == 0:
        return Mesh.empty()
    # active blocks stacked along axis 0 (9 sample layers each); the mask skips the cubes that
    # would bridge two unrelated blocks
    offs = np.arange(bs + 1, dtype=np.float32)
    corner = bkeys[act] * bs  # sample index of each block's first sample
    cf = corner.astype(np.float32)
    vf = np.float32(v)
    gx = (cf[:, 0, None, None, None] + offs[:, None, None]) * vf
    gy = (cf[:, 1, None, None, None] + offs[None, :, None]) * vf
    gz = (cf[:, 2, None, None, None] + offs[None, None, :]) * vf
    shape = (n_act, bs + 1, bs + 1, bs + 1)
    gx, gy, gz = (np.broadcast_to(g, shape) for g in (gx, gy, gz))
    vol: np.ndarray = np.full(shape, np.inf, np.float32)
    for k in range(relevant.shape[0]):
        blocks_k = np.nonzero(relevant[k])[0]
        if len(blocks_k) == 0:
            continue
        xk, yk, zk = gx[blocks_k], gy[blocks_k], gz[blocks_k]
        dk = _room_sdf(scene, xk, yk, zk) if k == 0 else _prim_sdf(scene.primitives[k - 1], xk, yk, zk)
        vol[blocks_k] = np.minimum(vol[blocks_k], dk)
    vol = vol.reshape(n_act * (bs + 1), bs + 1, bs + 1).astype(np.float32)
    mask = np.ones(vol.shape, bool)
    mask[0::bs + 1] = False  # skimage skips the cube between layer 8 of one block and 0 of the next

    from skimage.measure import marching_cubes

    verts, faces, _, _ = marching_cubes(vol, level=0.0, gradient_direction="descent", allow_degenerate=False,
                                        mask=mask)
    blk = np.minimum(np.floor(verts[:, 0] / (bs + 1)).astype(np.int64), n_act - 1)
    local = verts - np.stack([blk * (bs + 1), 0 * blk, 0 * blk], 1)
    grid = corner[blk] + local  # voxel units
    world = grid * v
    # weld the copies of vertices on shared block faces (one int64 key: 20 bits per axis)
    q = np.round((grid + bs) * 1024).astype(np.int64)
    key = (q[:, 0] << 40) | (q[:, 1] << 20) | q[:, 2]
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return Mesh(world[first].astype(np.float32), faces[keep].astype(np.int32), None)
