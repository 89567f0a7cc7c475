"""Procedural indoor scenes, two simulated depth sensors (ToF and stereo) and exact ground truth.

Pure numpy + OpenCV; no ROS. Everything is deterministic for a seed.

Convention: world z up, metres. Cameras use the optical frame (z forward, x right, y down) and
`T_world_camera` maps camera coordinates to world coordinates. Depth is z-depth, float32, 0 =
invalid. Ray directions are built with a camera-frame z component of 1, so the ray parameter of
a hit *is* its z-depth.

Scene geometry: the room interior is the box [0, Lx] x [0, Ly] x [0, Lz] (floor at z = 0).
Furniture is a union of boxes (rotated about z), vertical cylinders and spheres; shelves and
tables are built of several boxes. `scene_sdf` is > 0 in free space.
"""
from __future__ import annotations

import dataclasses
import functools
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from senfunet_core.errors import InputError
from senfunet_core.mesher import Mesh

__all__ = [
    "Primitive", "Surface", "Scene", "make_scene", "scene_sdf", "gt_tsdf", "gt_mesh",
    "SensorFrame", "Sequence", "simulate_sequence", "render_view", "intrinsics",
    "write_dataset", "load_dataset", "simulate_tof_depth", "simulate_stereo_depth", "SENSORS", "STEREO_BASELINE_M",
    "TOF_OFFSET_X_M",
]

SENSORS = ("tof", "stereo")
STEREO_BASELINE_M = 0.1  # right camera sits +0.1 m along the left camera's x axis
TOF_OFFSET_X_M = -0.05  # ToF optical frame relative to the stereo left camera, along its x axis
TOF_RANGE_M = (0.2, 5.0)
KINECT_BF = 35130.0  # Handa et al.: disparity [px] = 35130 / depth [mm]
SGBM_BLOCK_SIZE = 5  # small block: keeps thin furniture parts; P1/P2 follow OpenCV's 8*bs^2, 32*bs^2
SGBM_NUM_DISPARITIES = 64
TEXTURE_TILE = 256  # texels per side of a periodic texture tile
ROOM_SURFACES = 6  # surfaces 0..5: floor, ceiling, wall x=0, wall x=Lx, wall y=0, wall y=Ly


# --------------------------------------------------------------------------------------------
# Scene description
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Primitive:
    """One solid. box: size_m = half extents in its yawed frame; cylinder: (radius, radius,
    half height), axis vertical; sphere: (radius, radius, radius)."""

    kind: str  # "box" | "cylinder" | "sphere"
    center_m: tuple[float, float, float]
    size_m: tuple[float, float, float]
    yaw_rad: float
    surface: int  # index into Scene.surfaces
    item: int  # furniture item this part belongs to


@dataclass(frozen=True)
class Surface:
    """Appearance of a surface: albedo times a periodic procedural texture."""

    color_rgb: tuple[float, float, float]  # albedo 0..1
    texture_poor: bool
    contrast: float  # std of the texture modulation (near 0 for texture-poor surfaces)
    texel_m: float  # size of one texel in metres
    pattern: int  # 0 noise, 1 noise + stripes, 2 planks/tiles
    texture_seed: int
    ir_reflectivity: float = 0.6  # what the ToF's infrared illumination gets back (0..1; dark materials < 0.15)


@dataclass(frozen=True)
class Scene:
    """A room with furniture, its appearance and the per-scene sensor variation."""

    seed: int
    room_size_m: tuple[float, float, float]
    primitives: tuple[Primitive, ...]
    surfaces: tuple[Surface, ...]
    item_kinds: tuple[str, ...]  # "box", "shelf", "table", "cylinder", "sphere" per item
    corridor_xy_m: tuple[tuple[float, float], ...]  # closed loop kept free for the trajectory
    corridor_radius_m: float
    lights_m: tuple[tuple[float, float, float], ...]
    light_level: float  # scales the point lights (dim rooms give noisy, low-contrast images)
    ambient: float
    tof_noise_scale: float  # multiplies Handa's disparity noise std (1/6 px); ~5 as in the paper
    tof_shuffle_px: float  # std of the pixel shuffling offset
    tof_speckle_fraction: float  # random dropouts
    tof_flying_fraction: float  # fraction of edge pixels that become flying pixels
    tof_grazing_cos: float  # |cos(normal, ray)| below this -> dropout
    stereo_image_noise: float  # grey-level noise std added to each stereo image
    stereo_uniqueness: int  # SGBM uniqueness ratio (higher = fewer, safer matches)
    stereo_speckle_window: int
    tof_multipath_m: float = 0.0  # ToF depth overestimate in concave corners (multipath interference), at the corner
    tof_min_signal: float = 0.0  # ToF dropout where reflectivity * cos(incidence) / depth^2 [1/m^2] is below this


def _room_surface(rng: np.random.Generator, poor: bool, seed: int) -> Surface:
    color = tuple(float(c) for c in np.clip(rng.uniform(0.35, 0.85) + rng.normal(0, 0.08, 3), 0.1, 0.95))
    return _surface(rng, color, poor, seed)


def _surface(rng: np.random.Generator, color: tuple, poor: bool, seed: int) -> Surface:
    return Surface(
        color_rgb=(float(color[0]), float(color[1]), float(color[2])),
        texture_poor=bool(poor),
        contrast=float(rng.uniform(0.0, 0.006) if poor else rng.uniform(0.18, 0.4)),
        texel_m=float(rng.uniform(0.006, 0.014)),
        pattern=int(rng.integers(0, 3)),
        texture_seed=int(seed),
    )


def _corridor(rng: np.random.Generator, room: np.ndarray) -> np.ndarray:
    """A closed, smooth loop around the room centre, 0.9-1.9 m from the walls where the room allows
    (the device walks it; the margin sets the viewing distance to the near walls)."""
    lx, ly = room[0], room[1]
    margin = rng.uniform(0.9, 1.9)
    a = max(lx / 2 - margin, 0.25)
    b = max(ly / 2 - margin, 0.25)
    phi = np.linspace(0, 2 * np.pi, 256, endpoint=False)
    # superellipse (exponent 3) -> rounded rectangle; small radial wobble for variety
    p = 3.0
    c, s = np.cos(phi), np.sin(phi)
    x = a * np.sign(c) * np.abs(c) ** (2 / p)
    y = b * np.sign(s) * np.abs(s) ** (2 / p)
    wobble = 1 + 0.06 * np.sin(2 * phi + rng.uniform(0, 2 * np.pi))
    return np.stack([lx / 2 + x * wobble, ly / 2 + y * wobble], 1)


def _seg_dist(points: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Distance from 2D points (N,2) to a closed polyline."""
    a = loop
    b = np.roll(loop, -1, 0)
    ab = b - a
    ap = points[:, None, :] - a[None]
    t = np.clip((ap * ab[None]).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12)[None], 0, 1)
    d = ap - t[..., None] * ab[None]
    return np.sqrt((d * d).sum(-1)).min(1)


def make_scene(seed: int, *, room_size_m: tuple[float, float, float] | None = None,
               texture_poor_fraction: float | None = None) -> Scene:
    """Random room (3-7 x 3-6 x 2.4-3 m) with 4-12 furniture items kept clear of the walk loop."""
    rng = np.random.default_rng([seed, 1])
    if room_size_m is None:
        room = np.array([rng.uniform(3.0, 7.0), rng.uniform(3.0, 6.0), rng.uniform(2.4, 3.0)])
    else:
        room = np.asarray(room_size_m, float)
        if room.shape != (3,) or np.any(room < 2.0):
            raise InputError(f"room_size_m must be 3 sizes >= 2 m, got {room_size_m}")
    poor_frac = rng.uniform(0.1, 0.6) if texture_poor_fraction is None else float(texture_poor_fraction)
    if not 0.0 <= poor_frac <= 1.0:
        raise InputError(f"texture_poor_fraction must be in [0, 1], got {texture_poor_fraction}")
    lx, ly, lz = (float(v) for v in room)
    corridor = _corridor(rng, room)
    corridor_radius = 0.6  # furniture keeps this far from the loop; device sdf stays > 0.4 m

    surfaces: list[Surface] = []
    seed_base = int(rng.integers(0, 2**31))

    def new_surface(color: tuple | None = None, poor: bool | None = None) -> int:
        poor = bool(rng.random() < poor_frac) if poor is None else poor
        if color is None:
            color = tuple(np.clip(rng.uniform(0.15, 0.9, 3), 0, 1))
        surfaces.append(_surface(rng, tuple(color), poor, seed_base + len(surfaces)))
        return len(surfaces) - 1

    for _ in range(ROOM_SURFACES):
        surfaces.append(_room_surface(rng, bool(rng.random() < poor_frac), seed_base + len(surfaces)))
    # at least one texture-poor surface per scene: a wall when none came out texture-poor
    if not any(s.texture_poor for s in surfaces):
        k = int(rng.integers(2, 6))
        surfaces[k] = _room_surface(rng, True, seed_base + k)

    prims: list[Primitive] = []
    kinds: list[str] = []
    footprints: list[tuple[float, float, float]] = []  # (x, y, radius) for overlap rejection
    n_items = int(rng.integers(4, 13))
    attempts = 0
    while len(kinds) < n_items and attempts < 400:
        attempts += 1
        kind = str(rng.choice(["box", "shelf", "table", "cylinder", "sphere"], p=[0.3, 0.2, 0.2, 0.15, 0.15]))
        against_wall = kind == "shelf" or (kind == "box" and rng.random() < 0.6)
        if kind == "shelf":
            w, d, h = rng.uniform(0.6, 1.4), rng.uniform(0.25, 0.4), rng.uniform(1.0, min(2.2, lz - 0.2))
        elif kind == "box":
            w, d, h = rng.uniform(0.3, 1.6), rng.uniform(0.3, 0.9), rng.uniform(0.3, 1.2)
        elif kind == "table":
            w, d, h = rng.uniform(0.6, 1.6), rng.uniform(0.5, 0.9), rng.uniform(0.65, 0.8)
        elif kind == "cylinder":
            r = rng.uniform(0.1, 0.35)
            w, d, h = 2 * r, 2 * r, rng.uniform(0.3, 1.8)
        else:
            r = rng.uniform(0.12, 0.35)
            w, d, h = 2 * r, 2 * r, 2 * r
        if against_wall:
            wall = int(rng.integers(0, 4))
            wall_m = lx if wall < 2 else ly
            along = rng.uniform(0.1 + w / 2, wall_m - 0.1 - w / 2) if wall_m > w + 0.2 else None
            if along is None:
                continue
            gap = 0.01 + d / 2
            # yaw so the item's local +y (its front) faces into the room
            if wall == 0:
                x, y, yaw = along, gap, 0.0
            elif wall == 1:
                x, y, yaw = along, ly - gap, np.pi
            elif wall == 2:
                x, y, yaw = gap, along, -np.pi / 2
            else:
                x, y, yaw = lx - gap, along, np.pi / 2
        else:
            x, y = rng.uniform(0.2, lx - 0.2), rng.uniform(0.2, ly - 0.2)
            yaw = rng.uniform(-np.pi, np.pi)
        radius = 0.5 * np.hypot(w, d)
        # the item's footprint (bounding circle) must fit in the room and stay off the loop
        if not against_wall and (x - radius < 0.02 or y - radius < 0.02
                                 or x + radius > lx - 0.02 or y + radius > ly - 0.02):
            continue
        if _seg_dist(np.array([[x, y]]), corridor)[0] < corridor_radius + radius:
            continue
        if any(np.hypot(x - fx, y - fy) < radius + fr + 0.05 for fx, fy, fr in footprints):
            continue
        item = len(kinds)
        sid = new_surface()
        c, s = np.cos(yaw), np.sin(yaw)

        def box(lx_: float, ly_: float, lz_: float, hx: float, hy: float, hz: float, surf: int = sid) -> None:
            # local offset (lx_, ly_) in the item's yawed frame
            prims.append(Primitive("box", (float(x + c * lx_ - s * ly_), float(y + s * lx_ + c * ly_), float(lz_)),
                                   (float(hx), float(hy), float(hz)), float(yaw), surf, item))

        if kind == "box":
            box(0, 0, h / 2, w / 2, d / 2, h / 2)
        elif kind == "shelf":
            t = 0.02
            box(-w / 2 + t / 2, 0, h / 2, t / 2, d / 2, h / 2)  # sides
            box(w / 2 - t / 2, 0, h / 2, t / 2, d / 2, h / 2)
            box(0, -d / 2 + t / 2, h / 2, w / 2 - t, t / 2, h / 2)  # back panel against the wall
            n_boards = int(rng.integers(3, 6))
            for zb in np.linspace(0.05, h - t / 2, n_boards):
                box(0, 0, zb, w / 2 - t, d / 2, t / 2)
            for _ in range(int(rng.integers(0, 4))):  # a few "books" in their own colour
                bw = rng.uniform(0.1, 0.3)
                zb = float(rng.choice(np.linspace(0.05, h - t / 2, n_boards)[:-1]))
                bh = rng.uniform(0.12, 0.22)
                box(rng.uniform(-w / 2 + bw / 2 + t, w / 2 - bw / 2 - t), 0, zb + t / 2 + bh / 2,
                    bw / 2, d / 2 - 0.03, bh / 2, new_surface())
        elif kind == "table":
            t = rng.uniform(0.03, 0.06)
            box(0, 0, h - t / 2, w / 2, d / 2, t / 2)
            leg = 0.025
            legs_surf = new_surface()
            for sx in (-1, 1):
                for sy in (-1, 1):
                    box(sx * (w / 2 - 2 * leg), sy * (d / 2 - 2 * leg), (h - t) / 2, leg, leg, (h - t) / 2, legs_surf)
            if rng.random() < 0.5:  # something on the table
                r = rng.uniform(0.06, 0.15)
                prims.append(Primitive("sphere", (float(x), float(y), float(h + r)), (r, r, r), 0.0, new_surface(),
                                       item))
        elif kind == "cylinder":
            prims.append(Primitive("cylinder", (float(x), float(y), float(h / 2)), (w / 2, w / 2, h / 2), 0.0, sid,
                                   item))
        else:
            prims.append(Primitive("sphere", (float(x), float(y), float(h / 2)), (w / 2, w / 2, w / 2), 0.0, sid, item))
        kinds.append(kind)
        footprints.append((x, y, radius))

    n_lights = int(rng.integers(1, 4))
    lights = tuple((float(rng.uniform(0.2, lx - 0.2)), float(rng.uniform(0.2, ly - 0.2)), lz - 0.05)
                   for _ in range(n_lights))
    # What real sites vary beyond the layout, drawn from their own stream (the layout above keeps its
    # draws): the amount of texture (contrast of the textured surfaces), and for the ToF the
    # infrared reflectivity of each material (painted walls and ceiling are bright in the infrared;
    # some floors and furniture are dark: far noisier ToF depth, dropouts when the return is weak),
    # multipath in concave corners and the weakest return it still measures.
    extra = np.random.default_rng([seed, 4])
    texture_scale = extra.uniform(0.45, 1.25)
    dark_fraction = extra.uniform(0.0, 0.5)
    for k, surf in enumerate(surfaces):
        if 1 <= k < ROOM_SURFACES:  # ceiling and walls
            ir = extra.uniform(0.45, 0.95)
        else:
            ir = extra.uniform(0.03, 0.12) if extra.random() < dark_fraction else extra.uniform(0.3, 0.95)
        contrast = surf.contrast if surf.texture_poor else min(surf.contrast * texture_scale, 0.5)
        surfaces[k] = dataclasses.replace(surf, contrast=float(contrast), ir_reflectivity=float(ir))
    tof_multipath_m = float(extra.uniform(0.0, 0.05))
    tof_min_signal = float(extra.uniform(0.002, 0.01))
    return Scene(
        seed=int(seed),
        room_size_m=(lx, ly, lz),
        primitives=tuple(prims),
        surfaces=tuple(surfaces),
        item_kinds=tuple(kinds),
        corridor_xy_m=tuple((float(a), float(b)) for a, b in corridor),
        corridor_radius_m=corridor_radius,
        lights_m=lights,
        light_level=float(rng.uniform(0.35, 1.3)),
        ambient=float(rng.uniform(0.12, 0.35)),
        tof_noise_scale=float(rng.uniform(3.0, 7.0)),
        tof_shuffle_px=float(rng.uniform(0.3, 0.8)),
        tof_speckle_fraction=float(rng.uniform(0.002, 0.03)),
        tof_flying_fraction=float(rng.uniform(0.3, 0.9)),
        tof_grazing_cos=float(rng.uniform(0.08, 0.2)),
        stereo_image_noise=float(rng.uniform(0.5, 4.0)),
        stereo_uniqueness=int(rng.integers(3, 15)),
        stereo_speckle_window=int(rng.integers(20, 150)),
        tof_multipath_m=tof_multipath_m,
        tof_min_signal=tof_min_signal,
    )


def _scene_to_json(scene: Scene) -> str:
    return json.dumps(asdict(scene))


def _scene_from_json(text: str) -> Scene:
    d = json.loads(text)

    def tup(v):  # JSON lists back to (nested) tuples
        return tuple(tup(x) for x in v) if isinstance(v, list) else v

    d = {k: tup(v) for k, v in d.items()}
    d["primitives"] = tuple(Primitive(**{k: tup(v) for k, v in p.items()}) for p in json.loads(text)["primitives"])
    d["surfaces"] = tuple(Surface(**{k: tup(v) for k, v in s.items()}) for s in json.loads(text)["surfaces"])
    return Scene(**d)


# --------------------------------------------------------------------------------------------
# Signed distances
# --------------------------------------------------------------------------------------------
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
    for k in range(per.shape[0]):
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


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------
def intrinsics(width: int = 256, height: int = 256, fov_deg: float = 90.0) -> np.ndarray:
    """Pinhole K (3x3 float64): horizontal field of view fov_deg, square pixels, centred."""
    f = (width / 2.0) / np.tan(np.deg2rad(fov_deg) / 2.0)
    return np.array([[f, 0, (width - 1) / 2.0], [0, f, (height - 1) / 2.0], [0, 0, 1]], dtype=np.float64)


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

    # the room: the ray leaves through the nearest of the 6 planes (the camera is inside)
    L = scene.room_size_m
    depth = None
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
    pid = np.full(dx.shape, -1, np.int32)  # -1 = room
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

    # room: normal along the exit axis against the ray, texture coordinates in the wall plane;
    # surfaces floor, ceiling, x0, x1, y0, y1
    px, py, pz = ox + dx * depth, oy + dy * depth, oz + dz * depth
    one = np.float32(1)
    nx = np.where(axis == 0, np.where(dx > 0, -one, one), 0).astype(np.float32)
    ny = np.where(axis == 1, np.where(dy > 0, -one, one), 0).astype(np.float32)
    nz = np.where(axis == 2, np.where(dz > 0, -one, one), 0).astype(np.float32)
    u = np.where(axis == 0, py, px)
    v = np.where(axis == 2, py, pz)
    surf = np.where(axis == 2, np.where(dz < 0, 0, 1),
                    np.where(axis == 0, np.where(dx < 0, 2, 3), np.where(dy < 0, 4, 5))).astype(np.int32)
    # primitives overwrite the pixels they won (only inside their screen rectangles)
    for i, sl in won:
        m = pid[sl] == i
        if not np.any(m):
            continue
        prim = scene.primitives[i]
        (nx[sl][m], ny[sl][m], nz[sl][m]), (u[sl][m], v[sl][m]) = _normals_and_uv(prim, px[sl][m], py[sl][m], pz[sl][m])
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
        out["rgb"] = cv2.convertScaleAbs(cv2.merge([np.take(albedo[:, c], surf) * intensity for c in range(3)]))
    return out


OTHER_DISTANCE_CAP_M = 0.5
MULTIPATH_RANGE_M = 0.08  # the ToF multipath overestimate decays as exp(-distance to the other surface / this)


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


# --------------------------------------------------------------------------------------------
# Sensors
# --------------------------------------------------------------------------------------------
def _tof_depth(view: dict, K: np.ndarray, scene: Scene, rng: np.random.Generator) -> np.ndarray:
    """Kinect-style noise (Handa et al., scaled) on a true z-depth image; 0 = invalid.

    On top of Handa's model: multipath (depth overestimated near concave corners, when the view
    holds `other_distance_m`), noise growing as 1 / sqrt(infrared reflectivity) (dark materials are
    several times noisier) and dropouts where the return reflectivity * cos / z^2 is too weak."""
    z = view["depth_m"].astype(np.float32)
    h, w = z.shape
    cosi = view["cos_incidence"]
    reflectivity = np.array([sf.ir_reflectivity for sf in scene.surfaces], np.float32)[view["surface_id"]]
    if scene.tof_multipath_m > 0 and "other_distance_m" in view:
        z = z + np.float32(scene.tof_multipath_m) * np.exp(-view["other_distance_m"] / np.float32(MULTIPATH_RANGE_M))
    # pixel shuffling: each pixel reads the true depth at a Gaussian-shifted location
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    su = u + rng.normal(0, scene.tof_shuffle_px, (h, w)).astype(np.float32)
    sv = v + rng.normal(0, scene.tof_shuffle_px, (h, w)).astype(np.float32)
    zs = cv2.remap(z, su, sv, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    cs = cv2.remap(cosi, su, sv, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    rs = cv2.remap(reflectivity, su, sv, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    # flying pixels: near depth discontinuities take a value between fore- and background
    kernel = np.ones((3, 3), np.uint8)
    zmax = cv2.dilate(zs, kernel)
    zmin = cv2.erode(zs, kernel)
    edge = (zmax - zmin) > (0.05 + 0.05 * zs)
    fly = edge & (rng.random((h, w)) < scene.tof_flying_fraction)
    zs = np.where(fly, zmin + rng.random((h, w)).astype(np.float32) * (zmax - zmin), zs)
    # disparity noise and 1/8 px quantisation: error grows ~ z^2
    disp = KINECT_BF / (np.maximum(zs, 1e-3) * 1000.0)
    noise_gain = np.clip(np.sqrt(0.5 / np.maximum(rs, 1e-3)), 0.8, 4.0)  # 1 at reflectivity 0.5
    disp = disp + rng.normal(0, scene.tof_noise_scale / 6.0, (h, w)) * noise_gain
    disp = np.round(disp * 8.0) / 8.0
    with np.errstate(divide="ignore"):
        zn = np.where(disp > 0, KINECT_BF / np.maximum(disp, 1e-6) / 1000.0, 0.0)
    # dropouts: grazing angles (more likely the flatter), random speckles, out of range
    graze = (cs < scene.tof_grazing_cos) | ((cs < 2 * scene.tof_grazing_cos) & (rng.random((h, w)) < 0.3))
    speckle = rng.random((h, w)) < scene.tof_speckle_fraction
    weak = rs * cs < scene.tof_min_signal * zs * zs
    bad = graze | speckle | weak | (zn < TOF_RANGE_M[0]) | (zn > TOF_RANGE_M[1]) | (disp <= 0)
    return np.where(bad, 0.0, zn).astype(np.float32)


def _stereo_grey(view: dict, scene: Scene, rng: np.random.Generator, width: int, height: int) -> tuple:
    """2x render -> area downsample (antialias) -> rgb and noisy greyscale."""
    rgb = cv2.resize(view["rgb"], (width, height), interpolation=cv2.INTER_AREA)
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    grey += rng.normal(0, scene.stereo_image_noise, grey.shape).astype(np.float32)
    return rgb, np.clip(np.round(grey), 0, 255).astype(np.uint8)


def _sgbm(scene: Scene) -> cv2.StereoSGBM:
    bs = SGBM_BLOCK_SIZE
    return cv2.StereoSGBM.create(minDisparity=0, numDisparities=SGBM_NUM_DISPARITIES, blockSize=bs,
                                 P1=8 * bs * bs, P2=32 * bs * bs, disp12MaxDiff=1, preFilterCap=31,
                                 uniquenessRatio=scene.stereo_uniqueness,
                                 speckleWindowSize=scene.stereo_speckle_window, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_HH)


def _stereo_depth(scene: Scene, T_left: np.ndarray, K: np.ndarray, width: int, height: int,
                  rng: np.random.Generator, sgbm: cv2.StereoSGBM) -> tuple[np.ndarray, np.ndarray]:
    K2 = intrinsics_scaled(K, 2)
    T_right = T_left @ _translation(STEREO_BASELINE_M, 0, 0)
    left = render_view(scene, T_left, K2, 2 * width, 2 * height)
    right = render_view(scene, T_right, K2, 2 * width, 2 * height)
    rgb_l, g_l = _stereo_grey(left, scene, rng, width, height)
    _, g_r = _stereo_grey(right, scene, rng, width, height)
    disp = sgbm.compute(g_l, g_r).astype(np.float32) / 16.0
    with np.errstate(divide="ignore"):
        depth = np.where(disp > 0, K[0, 0] * STEREO_BASELINE_M / np.maximum(disp, 1e-6), 0.0)
    return depth.astype(np.float32), rgb_l


def simulate_tof_depth(scene: Scene, T_world_camera: np.ndarray, K: np.ndarray, width: int, height: int,
                       rng: np.random.Generator) -> np.ndarray:
    """One ToF depth image (H,W) float32 (0 = invalid) seen from the ToF optical frame pose."""
    view = render_view(scene, T_world_camera, K, width, height, with_rgb=False,
                       with_other_distance=scene.tof_multipath_m > 0)
    return _tof_depth(view, K, scene, rng)


def simulate_stereo_depth(scene: Scene, T_world_camera: np.ndarray, K: np.ndarray, width: int, height: int,
                          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One SGBM depth image (H,W) float32 (0 = invalid) and the left rgb, from the left camera pose."""
    return _stereo_depth(scene, np.asarray(T_world_camera, np.float64), K, width, height, rng, _sgbm(scene))


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


# --------------------------------------------------------------------------------------------
# Trajectory
# --------------------------------------------------------------------------------------------
class _Trajectory:
    """Device (= stereo left optical frame) pose as a smooth function of time.

    Walks the scene's corridor loop at 0.1-0.85 m/s (slowing in tight turns so the path turns at
    most ~20 deg/s), looking sideways into the room with a slowly varying yaw offset, at 1.5 m
    (+- ~0.15), pitched ~10-25 deg down. Dense 2 ms samples, linearly interpolated.
    """

    def __init__(self, scene: Scene, seed: int, t0: float, t1: float):
        rng = np.random.default_rng([seed, 2])
        loop = np.asarray(scene.corridor_xy_m)
        seg = np.linalg.norm(np.roll(loop, -1, 0) - loop, axis=1)
        s_knots = np.concatenate([[0], np.cumsum(seg)])
        length = s_knots[-1]
        loop_c = np.vstack([loop, loop[:1]])
        step = np.diff(loop_c, axis=0)  # segment i: knot i -> knot i+1
        hk = np.unwrap(np.arctan2(step[:, 1], step[:, 0]))
        heading = np.append(hk, hk[-1] + (np.angle(np.exp(1j * (hk[0] - hk[-1])))))  # close the loop
        kappa = np.abs(np.gradient(heading, s_knots))
        self.dt = 0.002
        # always start at a fixed time, so the pose at a stamp does not depend on the window asked for
        start = min(t0, -1.0)
        self.t = np.arange(start, t1 + 0.25 + self.dt, self.dt)
        n = len(self.t)
        tt = self.t

        def smooth(amp: float, fmin: float, fmax: float, k: int = 3) -> np.ndarray:
            out = np.zeros(n)
            for _ in range(k):
                out += np.sin(2 * np.pi * rng.uniform(fmin, fmax) * tt + rng.uniform(0, 2 * np.pi))
            return amp * out / k

        v0 = rng.uniform(0.5, 0.8)
        speed = np.clip(v0 + smooth(0.5, 0.03, 0.12), 0.1, 0.85)  # walking with slow scanning phases
        direction = 1.0 if rng.random() < 0.5 else -1.0
        s = np.empty(n)
        s[0] = rng.uniform(0, length)
        max_turn = np.deg2rad(35.0) * 0.6
        for i in range(1, n):  # 1 scalar op per 2 ms sample; cheap
            k = np.interp(s[i - 1] % length, s_knots, kappa)
            vi = min(speed[i], max_turn / max(k, 1e-6))
            s[i] = s[i - 1] + direction * vi * self.dt
        sm = np.mod(s, length)
        x = np.interp(sm, s_knots, loop_c[:, 0])
        y = np.interp(sm, s_knots, loop_c[:, 1])
        hd = np.interp(sm, s_knots, heading) + (0 if direction > 0 else np.pi)
        # unwrap the path heading over time (the loop closes with a 2 pi jump)
        hd = np.unwrap(hd)
        # lateral wobble off the loop (small: stays in the corridor)
        lat = smooth(0.08, 0.05, 0.2)
        x = x + lat * -np.sin(hd)
        y = y + lat * np.cos(hd)
        side = rng.choice([-1.0, 1.0])  # look to the inside or the outside of the loop, swinging between
        yaw_off = side * np.deg2rad(rng.uniform(20, 70)) + smooth(np.deg2rad(80), 0.04, 0.12)
        yaw = hd + yaw_off
        yaw = np.convolve(np.pad(yaw, 50, mode="edge"), np.ones(101) / 101, "valid")  # 0.2 s smoothing
        z = 1.5 + smooth(0.15, 0.02, 0.1) + 0.01 * np.sin(2 * np.pi * 1.8 * tt)  # slow + step bob
        pitch = np.deg2rad(-15.0) + smooth(np.deg2rad(8), 0.03, 0.12)
        roll = smooth(np.deg2rad(2), 0.05, 0.2)
        self.pos = np.stack([x, y, z], 1)
        self.ang = np.stack([yaw, pitch, roll], 1)

    def __call__(self, stamps_s: np.ndarray) -> np.ndarray:
        """(M,4,4) poses of the device at stamps_s."""
        st = np.atleast_1d(np.asarray(stamps_s, float))
        pos = np.stack([np.interp(st, self.t, self.pos[:, i]) for i in range(3)], 1)
        yaw, pitch, roll = (np.interp(st, self.t, self.ang[:, i]) for i in range(3))
        fwd = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], 1)
        right = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], 1)
        down = np.cross(fwd, right)
        # roll about the forward axis
        cr, sr = np.cos(roll)[:, None], np.sin(roll)[:, None]
        x_ax = cr * right + sr * down
        y_ax = -sr * right + cr * down
        T = np.tile(np.eye(4), (len(st), 1, 1))
        T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = x_ax, y_ax, fwd, pos
        return T


# --------------------------------------------------------------------------------------------
# Sequences
# --------------------------------------------------------------------------------------------
@dataclass
class SensorFrame:
    """One depth image of one sensor. depth_m: 0 = invalid. T_world_camera: true pose at stamp_s."""

    sensor: str  # "tof" | "stereo"
    stamp_s: float
    depth_m: np.ndarray  # (H,W) float32
    rgb: np.ndarray | None  # (H,W,3) uint8 left colour image (stereo), None (tof)
    K: np.ndarray  # (3,3) float64
    T_world_camera: np.ndarray  # (4,4) float64


@dataclass
class Sequence:
    """A recording: frames of both sensors sorted by stamp, and one pose stream per sensor."""

    scene: Scene
    frames: list[SensorFrame] = field(default_factory=list)
    pose_stamps_s: dict[str, np.ndarray] = field(default_factory=dict)  # sensor -> (M,)
    pose_T_world_camera: dict[str, np.ndarray] = field(default_factory=dict)  # sensor -> (M,4,4)


def _sensor_offset(sensor: str) -> np.ndarray:
    return _translation(TOF_OFFSET_X_M, 0, 0) if sensor == "tof" else np.eye(4)


def _avoid(stamps: np.ndarray, others: np.ndarray, min_gap_s: float = 2e-4) -> np.ndarray:
    """Nudge stamps that come within min_gap_s of any of `others` (so they never coincide)."""
    stamps = stamps.copy()
    if len(others) == 0:
        return stamps
    srt = np.sort(others)
    for _ in range(4):
        j = np.clip(np.searchsorted(srt, stamps), 1, len(srt) - 1)
        near = np.minimum(np.abs(stamps - srt[j - 1]), np.abs(stamps - srt[j]))
        clash = near < min_gap_s
        if not np.any(clash):
            break
        stamps[clash] += 2.5 * min_gap_s
    return stamps


def simulate_sequence(scene: Scene, seed: int, *, duration_s: float = 10.0, tof_rate_hz: float = 15.0,
                      stereo_rate_hz: float = 20.0, pose_rate_hz: float = 100.0, width: int = 256,
                      height: int = 256) -> Sequence:
    """Simulate both sensors over duration_s seconds (stamps in [0, duration_s))."""
    if duration_s <= 0 or min(tof_rate_hz, stereo_rate_hz, pose_rate_hz) <= 0:
        raise InputError("duration_s and the rates must be > 0")
    if width < SGBM_NUM_DISPARITIES + SGBM_BLOCK_SIZE or height < 16:
        # SGBM needs the image wider than its disparity range plus half a block
        raise InputError(f"images must be at least {SGBM_NUM_DISPARITIES + SGBM_BLOCK_SIZE} x 16, "
                         f"got {width} x {height}")
    rng = np.random.default_rng([seed, 3])
    pose_margin = 2.0 / pose_rate_hz + 0.02
    traj = _Trajectory(scene, seed, -pose_margin - 0.01, duration_s + pose_margin + 0.01)
    K = intrinsics(width, height)

    # asynchronous stamps: own rate, random phase, ~1 ms jitter, never equal to each other
    stamps: dict[str, np.ndarray] = {}
    for sensor, rate in (("tof", tof_rate_hz), ("stereo", stereo_rate_hz)):
        n = int(np.floor(duration_s * rate))
        st = (np.arange(n) + rng.uniform(0.05, 0.95)) / rate + rng.normal(0, 0.001, n)
        stamps[sensor] = np.sort(np.clip(st, 0, duration_s - 1e-3))
    stamps["stereo"] = _avoid(stamps["stereo"], stamps["tof"])
    all_frame_stamps = np.concatenate([stamps["tof"], stamps["stereo"]])

    seq = Sequence(scene=scene)
    for sensor in SENSORS:
        n = int(np.ceil((duration_s + 2 * pose_margin) * pose_rate_hz))
        ps = -pose_margin + (np.arange(n) + rng.uniform(0.1, 0.9)) / pose_rate_hz
        ps = _avoid(ps, all_frame_stamps)
        seq.pose_stamps_s[sensor] = ps
        seq.pose_T_world_camera[sensor] = traj(ps) @ _sensor_offset(sensor)

    sgbm = _sgbm(scene)
    frames = []
    for sensor in SENSORS:
        poses = traj(stamps[sensor]) @ _sensor_offset(sensor)
        for st, T in zip(stamps[sensor], poses):
            if sensor == "tof":
                view = render_view(scene, T, K, width, height, with_rgb=False,
                                   with_other_distance=scene.tof_multipath_m > 0)
                depth, rgb = _tof_depth(view, K, scene, rng), None
            else:
                depth, rgb = _stereo_depth(scene, T, K, width, height, rng, sgbm)
            frames.append(SensorFrame(sensor, float(st), depth, rgb, K.copy(), T))
    frames.sort(key=lambda f: f.stamp_s)
    seq.frames = frames
    return seq


# --------------------------------------------------------------------------------------------
# Dataset files
# --------------------------------------------------------------------------------------------
def write_dataset(seq: Sequence, folder: str | Path, *, gt_voxel_size_m: float = 0.02) -> None:
    """Write scene.json, <sensor>.npz (frames), poses_<sensor>.npz and gt_mesh.npz into folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "scene.json").write_text(_scene_to_json(seq.scene))
    for sensor in SENSORS:
        fr = [f for f in seq.frames if f.sensor == sensor]
        arrays: dict[str, Any] = {  # Any: numpy's stub of savez_compressed types **kwds as its own options
            "stamp_s": np.array([f.stamp_s for f in fr], np.float64),
            "depth_m": np.stack([f.depth_m for f in fr]).astype(np.float32) if fr else np.zeros((0, 0, 0), np.float32),
            "K": np.stack([f.K for f in fr]) if fr else np.zeros((0, 3, 3)),
            "T_world_camera": np.stack([f.T_world_camera for f in fr]) if fr else np.zeros((0, 4, 4)),
        }
        rgbs = [f.rgb for f in fr if f.rgb is not None]
        if fr and len(rgbs) == len(fr):
            arrays["rgb"] = np.stack(rgbs).astype(np.uint8)
        np.savez_compressed(folder / f"{sensor}.npz", **arrays)
        if sensor in seq.pose_stamps_s:
            np.savez_compressed(folder / f"poses_{sensor}.npz", stamp_s=seq.pose_stamps_s[sensor],
                                T_world_camera=seq.pose_T_world_camera[sensor])
    mesh = gt_mesh(seq.scene, gt_voxel_size_m)
    np.savez_compressed(folder / "gt_mesh.npz", vertices=mesh.vertices, faces=mesh.faces)


def load_dataset(folder: str | Path) -> Sequence:
    """Inverse of write_dataset (the GT mesh is read separately: np.load(folder / 'gt_mesh.npz'))."""
    folder = Path(folder)
    scene = _scene_from_json((folder / "scene.json").read_text())
    seq = Sequence(scene=scene)
    frames = []
    for sensor in SENSORS:
        path = folder / f"{sensor}.npz"
        if path.exists():
            with np.load(path) as z:  # each array read once (indexing the NpzFile re-reads it)
                arrays = {k: z[k] for k in z.files}
            rgb = arrays.get("rgb")
            for i in range(len(arrays["stamp_s"])):
                frames.append(SensorFrame(sensor, float(arrays["stamp_s"][i]), arrays["depth_m"][i],
                                          None if rgb is None else rgb[i], arrays["K"][i],
                                          arrays["T_world_camera"][i]))
        ppath = folder / f"poses_{sensor}.npz"
        if ppath.exists():
            with np.load(ppath) as z:
                seq.pose_stamps_s[sensor] = z["stamp_s"]
                seq.pose_T_world_camera[sensor] = z["T_world_camera"]
    frames.sort(key=lambda f: f.stamp_s)
    seq.frames = frames
    return seq
