"""Procedural indoor scenes: a room with furniture, its surfaces' appearance and the per-scene
sensor variation. Deterministic for a seed.

Convention: world z up, metres. The room interior is the box [0, Lx] x [0, Ly] x [0, Lz] (floor at
z = 0). Furniture is a union of boxes (rotated about z), vertical cylinders and spheres; shelves and
tables are built of several boxes."""
from __future__ import annotations

import dataclasses
import json
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ..errors import InputError

ROOM_SURFACES = 6  # surfaces 0..5: floor, ceiling, wall x=0, wall x=Lx, wall y=0, wall y=Ly


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


CORRIDOR_RADIUS_M = 0.6  # furniture keeps this far from the walk loop; the device's sdf stays > 0.4 m
ITEM_KINDS = ("box", "shelf", "table", "cylinder", "sphere")
ITEM_KIND_P = (0.3, 0.2, 0.2, 0.15, 0.15)


def _room_size(rng: np.random.Generator, room_size_m: tuple[float, float, float] | None) -> np.ndarray:
    if room_size_m is None:
        return np.array([rng.uniform(3.0, 7.0), rng.uniform(3.0, 6.0), rng.uniform(2.4, 3.0)])
    room = np.asarray(room_size_m, float)
    if room.shape != (3,) or np.any(room < 2.0):
        raise InputError(f"room_size_m must be 3 sizes >= 2 m, got {room_size_m}")
    return room


class _Furnisher:
    """Surfaces and furniture of one room, drawn from the scene's random stream in a fixed order."""

    def __init__(self, rng: np.random.Generator, poor_fraction: float, room: np.ndarray,
                 corridor: np.ndarray) -> None:
        self.rng = rng
        self.poor_fraction = poor_fraction
        self.room = room
        self.corridor = corridor
        self.seed_base = int(rng.integers(0, 2**31))
        self.surfaces: list[Surface] = []
        self.prims: list[Primitive] = []
        self.kinds: list[str] = []
        self.footprints: list[tuple[float, float, float]] = []  # (x, y, radius) for overlap rejection

    def room_surfaces(self) -> None:
        """Floor, ceiling and the 4 walls; at least one of them texture-poor."""
        rng = self.rng
        for _ in range(ROOM_SURFACES):
            poor = bool(rng.random() < self.poor_fraction)
            self.surfaces.append(_room_surface(rng, poor, self.seed_base + len(self.surfaces)))
        if not any(s.texture_poor for s in self.surfaces):  # a wall when none came out texture-poor
            k = int(rng.integers(2, 6))
            self.surfaces[k] = _room_surface(rng, True, self.seed_base + k)

    def new_surface(self) -> int:
        rng = self.rng
        poor = bool(rng.random() < self.poor_fraction)
        color = np.clip(rng.uniform(0.15, 0.9, 3), 0, 1)
        self.surfaces.append(_surface(rng, tuple(color), poor, self.seed_base + len(self.surfaces)))
        return len(self.surfaces) - 1

    def furnish(self, n_items: int, *, max_attempts: int = 400) -> None:
        attempts = 0
        while len(self.kinds) < n_items and attempts < max_attempts:
            attempts += 1
            kind = str(self.rng.choice(list(ITEM_KINDS), p=list(ITEM_KIND_P)))
            against_wall = kind == "shelf" or (kind == "box" and self.rng.random() < 0.6)
            w, d, h = self._item_size(kind)
            pose = self._wall_pose(w, d) if against_wall else self._free_pose()
            if pose is None:
                continue
            x, y, yaw = pose
            radius = 0.5 * np.hypot(w, d)
            if self._fits(x, y, radius, against_wall):
                self._add_item(kind, x, y, yaw, (w, d, h))
                self.footprints.append((x, y, radius))

    def _item_size(self, kind: str) -> tuple[float, float, float]:
        """Width, depth and height of an item of this kind."""
        uniform, lz = self.rng.uniform, self.room[2]
        if kind == "shelf":
            return uniform(0.6, 1.4), uniform(0.25, 0.4), uniform(1.0, min(2.2, lz - 0.2))
        if kind == "box":
            return uniform(0.3, 1.6), uniform(0.3, 0.9), uniform(0.3, 1.2)
        if kind == "table":
            return uniform(0.6, 1.6), uniform(0.5, 0.9), uniform(0.65, 0.8)
        r = uniform(0.1, 0.35) if kind == "cylinder" else uniform(0.12, 0.35)
        return 2 * r, 2 * r, (uniform(0.3, 1.8) if kind == "cylinder" else 2 * r)

    def _wall_pose(self, w: float, d: float) -> tuple[float, float, float] | None:
        """Against a random wall, its front (local +y) facing into the room; None when it does not fit."""
        lx, ly = float(self.room[0]), float(self.room[1])
        wall = int(self.rng.integers(0, 4))
        length = lx if wall < 2 else ly
        if length <= w + 0.2:
            return None
        along = self.rng.uniform(0.1 + w / 2, length - 0.1 - w / 2)
        gap = 0.01 + d / 2
        return ((along, gap, 0.0), (along, ly - gap, np.pi), (gap, along, -np.pi / 2),
                (lx - gap, along, np.pi / 2))[wall]

    def _free_pose(self) -> tuple[float, float, float]:
        lx, ly = float(self.room[0]), float(self.room[1])
        x, y = self.rng.uniform(0.2, lx - 0.2), self.rng.uniform(0.2, ly - 0.2)
        return x, y, self.rng.uniform(-np.pi, np.pi)

    def _fits(self, x: float, y: float, radius: float, against_wall: bool) -> bool:
        """The footprint (bounding circle) lies in the room, off the walk loop, apart from the other items."""
        lx, ly = float(self.room[0]), float(self.room[1])
        if not against_wall and (x - radius < 0.02 or y - radius < 0.02 or x + radius > lx - 0.02
                                 or y + radius > ly - 0.02):
            return False
        if _seg_dist(np.array([[x, y]]), self.corridor)[0] < CORRIDOR_RADIUS_M + radius:
            return False
        return not any(np.hypot(x - fx, y - fy) < radius + fr + 0.05 for fx, fy, fr in self.footprints)

    def _add_item(self, kind: str, x: float, y: float, yaw: float, size: tuple[float, float, float]) -> None:
        item = len(self.kinds)
        part = _ItemParts(self, item, x, y, yaw, self.new_surface())
        w, d, h = size
        if kind == "box":
            part.box(0, 0, h / 2, w / 2, d / 2, h / 2)
        elif kind == "shelf":
            part.shelf(w, d, h)
        elif kind == "table":
            part.table(w, d, h)
        else:  # cylinder, sphere: one primitive, vertical axis
            half_z = h / 2 if kind == "cylinder" else w / 2
            self.prims.append(Primitive(kind, (float(x), float(y), float(h / 2)), (w / 2, w / 2, half_z), 0.0,
                                        part.surface, item))
        self.kinds.append(kind)


class _ItemParts:
    """Builds one furniture item from boxes placed in the item's yawed frame."""

    def __init__(self, furnisher: _Furnisher, item: int, x: float, y: float, yaw: float, surface: int) -> None:
        self.f, self.item, self.x, self.y, self.yaw, self.surface = furnisher, item, x, y, yaw, surface
        self.c, self.s = np.cos(yaw), np.sin(yaw)

    def box(self, lx_: float, ly_: float, lz_: float, hx: float, hy: float, hz: float,
            surface: int | None = None) -> None:
        """A box with half extents (hx, hy, hz) at local offset (lx_, ly_) and height lz_."""
        c, s = self.c, self.s
        centre = (float(self.x + c * lx_ - s * ly_), float(self.y + s * lx_ + c * ly_), float(lz_))
        self.f.prims.append(Primitive("box", centre, (float(hx), float(hy), float(hz)), float(self.yaw),
                                      self.surface if surface is None else surface, self.item))

    def shelf(self, w: float, d: float, h: float) -> None:
        rng, t = self.f.rng, 0.02
        self.box(-w / 2 + t / 2, 0, h / 2, t / 2, d / 2, h / 2)  # sides
        self.box(w / 2 - t / 2, 0, h / 2, t / 2, d / 2, h / 2)
        self.box(0, -d / 2 + t / 2, h / 2, w / 2 - t, t / 2, h / 2)  # back panel against the wall
        n_boards = int(rng.integers(3, 6))
        for zb in np.linspace(0.05, h - t / 2, n_boards):
            self.box(0, 0, zb, w / 2 - t, d / 2, t / 2)
        for _ in range(int(rng.integers(0, 4))):  # a few "books" in their own colour
            bw = rng.uniform(0.1, 0.3)
            zb = float(rng.choice(np.linspace(0.05, h - t / 2, n_boards)[:-1]))
            bh = rng.uniform(0.12, 0.22)
            self.box(rng.uniform(-w / 2 + bw / 2 + t, w / 2 - bw / 2 - t), 0, zb + t / 2 + bh / 2,
                     bw / 2, d / 2 - 0.03, bh / 2, self.f.new_surface())

    def table(self, w: float, d: float, h: float) -> None:
        rng = self.f.rng
        t = rng.uniform(0.03, 0.06)
        self.box(0, 0, h - t / 2, w / 2, d / 2, t / 2)
        leg = 0.025
        legs_surface = self.f.new_surface()
        for sx in (-1, 1):
            for sy in (-1, 1):
                self.box(sx * (w / 2 - 2 * leg), sy * (d / 2 - 2 * leg), (h - t) / 2, leg, leg, (h - t) / 2,
                         legs_surface)
        if rng.random() < 0.5:  # something on the table
            r = rng.uniform(0.06, 0.15)
            self.f.prims.append(Primitive("sphere", (float(self.x), float(self.y), float(h + r)), (r, r, r), 0.0,
                                          self.f.new_surface(), self.item))


def _site_variation(seed: int, surfaces: list[Surface]) -> tuple[float, float]:
    """What real sites vary beyond the layout, from the scene's own stream (the layout keeps its draws):
    the amount of texture (contrast of the textured surfaces), and for the ToF the infrared
    reflectivity of each material (painted walls and ceiling are bright in the infrared; some floors
    and furniture are dark: far noisier ToF depth, dropouts when the return is weak), multipath in
    concave corners and the weakest return it still measures. Updates surfaces; returns
    (tof_multipath_m, tof_min_signal)."""
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
    return float(extra.uniform(0.0, 0.05)), float(extra.uniform(0.002, 0.01))


def _sensor_variation(rng: np.random.Generator) -> dict[str, Any]:
    """Lighting and the per-scene sensor parameters (Scene fields), in the stream's fixed order."""
    return {"light_level": float(rng.uniform(0.35, 1.3)), "ambient": float(rng.uniform(0.12, 0.35)),
            "tof_noise_scale": float(rng.uniform(3.0, 7.0)), "tof_shuffle_px": float(rng.uniform(0.3, 0.8)),
            "tof_speckle_fraction": float(rng.uniform(0.002, 0.03)),
            "tof_flying_fraction": float(rng.uniform(0.3, 0.9)), "tof_grazing_cos": float(rng.uniform(0.08, 0.2)),
            "stereo_image_noise": float(rng.uniform(0.5, 4.0)), "stereo_uniqueness": int(rng.integers(3, 15)),
            "stereo_speckle_window": int(rng.integers(20, 150))}


def make_scene(seed: int, *, room_size_m: tuple[float, float, float] | None = None,
               texture_poor_fraction: float | None = None) -> Scene:
    """Random room (3-7 x 3-6 x 2.4-3 m) with 4-12 furniture items kept clear of the walk loop."""
    rng = np.random.default_rng([seed, 1])
    room = _room_size(rng, room_size_m)
    poor_frac = rng.uniform(0.1, 0.6) if texture_poor_fraction is None else float(texture_poor_fraction)
    if not 0.0 <= poor_frac <= 1.0:
        raise InputError(f"texture_poor_fraction must be in [0, 1], got {texture_poor_fraction}")
    lx, ly, lz = (float(v) for v in room)
    corridor = _corridor(rng, room)
    furnisher = _Furnisher(rng, poor_frac, room, corridor)
    furnisher.room_surfaces()
    furnisher.furnish(int(rng.integers(4, 13)))
    n_lights = int(rng.integers(1, 4))
    lights = tuple((float(rng.uniform(0.2, lx - 0.2)), float(rng.uniform(0.2, ly - 0.2)), lz - 0.05)
                   for _ in range(n_lights))
    tof_multipath_m, tof_min_signal = _site_variation(seed, furnisher.surfaces)
    return Scene(seed=int(seed), room_size_m=(lx, ly, lz), primitives=tuple(furnisher.prims),
                 surfaces=tuple(furnisher.surfaces), item_kinds=tuple(furnisher.kinds),
                 corridor_xy_m=tuple((float(a), float(b)) for a, b in corridor),
                 corridor_radius_m=CORRIDOR_RADIUS_M, lights_m=lights, **_sensor_variation(rng),
                 tof_multipath_m=tof_multipath_m, tof_min_signal=tof_min_signal)


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
