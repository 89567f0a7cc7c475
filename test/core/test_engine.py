"""The engine against analytic geometry: TSDF values, fusion, filter, incremental alpha, meshes, state."""
from __future__ import annotations

import itertools
import logging
import math
import subprocess
import sys
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
import torch
import zstandard
from scipy.spatial import cKDTree

from senfunet_core import networks
from senfunet_core.alpha import near_surface_voxels
from senfunet_core.engine import EngineConfig, SenFuNet, warm_up
from senfunet_core.errors import InputError
from senfunet_core.fusion import fuse
from senfunet_core.grid import (ALPHA_UNKNOWN, BLOCK, block_keys, decode_alpha, decode_features,
                                decode_saved_features, encode_alpha, encode_features, voxel_centres)
from senfunet_core.mesher import Mesh, weld
from senfunet_core.map_file import load_map, save_map
from senfunet_core.readout import voxel_values, weight_cloud
from senfunet_core.spill import spilled_rows

VOXEL = 0.01


class VirtualClock:
    """Stands in for the engine's `time` module: perf_counter and monotonic move only when a test
    advances them, so a time budget counts fake seconds whatever the machine's load."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def perf_counter(self) -> float:
        return self.now_s

    def monotonic(self) -> float:
        return self.now_s

    def __getattr__(self, name: str):
        return getattr(time, name)


def pinhole(f_px: float, size: int = 128) -> np.ndarray:
    c = (size - 1) / 2
    return np.array([[f_px, 0, c], [0, f_px, c], [0, 0, 1.0]])


def look_at(eye, target, up=(0, 0, 1)) -> np.ndarray:
    """Camera-to-world pose of an optical frame (z forward, x right, y down) at eye looking at target."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    if abs(np.dot(z, up)) > 0.99:
        up = np.array([0, 1.0, 0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def ray_directions_world(K, T, size):
    v, u = np.mgrid[0:size, 0:size].astype(float)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    return d_cam @ T[:3, :3].T  # z-component 1 in camera frame: t along it is the z-depth


def render_sphere(centre, radius, K, T, size=128) -> np.ndarray:
    d = ray_directions_world(K, T, size)
    o = T[:3, 3]
    oc = o - np.asarray(centre)
    a = (d * d).sum(-1)
    b = 2 * (d @ oc)
    c = oc @ oc - radius**2
    disc = b * b - 4 * a * c
    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
    return np.where(disc > 0, t, 0).astype(np.float32)


def render_plane_z(z_plane, K, T, size=128) -> np.ndarray:
    """Depth of the horizontal plane z = z_plane (camera looking down)."""
    d = ray_directions_world(K, T, size)
    t = (z_plane - T[2, 3]) / d[..., 2]
    return np.where(t > 0, t, 0).astype(np.float32)


def constant_alpha(engine: SenFuNet, alpha: float) -> None:
    """Make the weighting net output `alpha` everywhere (a known weighting for the fusion tests); the
    blocks fused so far are re-evaluated by the next update."""
    with torch.no_grad():
        engine.weighting_net.conv3.weight.zero_()
        engine.weighting_net.conv3.bias.fill_(math.log(alpha / (1 - alpha)))
    with engine.data_lock:
        engine.store.stale[: engine.grid.n_blocks] = 2


def engine_for_tests(worker_setup=None, **overrides) -> SenFuNet:
    config = replace(EngineConfig(sensor_uses_rgb=(False, False), depth_min_m=(0.05, 0.05)), **overrides)
    return SenFuNet(config, weights=None, worker_setup=worker_setup)


SPHERE_C, SPHERE_R = np.array([0.0, 0.0, 0.0]), 0.3


def fibonacci_directions(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    polar, azimuth = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1)


SPHERE_VIEWS = [look_at(SPHERE_C + 0.9 * d, SPHERE_C) for d in fibonacci_directions(26)]
SPHERE_K = pinhole(160.0)  # rays denser than voxels: every voxel near the surface gets a sample


@pytest.fixture(scope="module")
def sphere_engine() -> SenFuNet:
    engine = engine_for_tests()
    K = SPHERE_K
    for T in SPHERE_VIEWS:
        depth = render_sphere(SPHERE_C, SPHERE_R, K, T)
        for sensor in engine.config.sensors:  # identical frames: every voxel is in C12, nothing filtered
            engine.integrate(sensor, depth, K, T)
    return engine


def test_plane_tsdf_matches_analytic_distance():
    engine = engine_for_tests()
    K = pinhole(400.0)  # narrow field of view: the projective distance is close to the true one
    T = look_at((0.03, 0.02, 1.0), (0.03, 0.02, 0.0))
    engine.integrate("tof", render_plane_z(0.0, K, T), K, T)
    centres, tsdf = voxel_values(engine, "tof")
    expected = centres[:, 2]  # signed distance to the plane z = 0, positive on the camera side
    near = np.abs(expected) <= 0.03
    assert near.sum() > 1000
    err = np.abs(tsdf[near] - expected[near])
    assert err.max() < VOXEL
    assert err.mean() < 0.3 * VOXEL
    # samples are written from +band/2 in front to 3 voxels behind the surface (stored as float16:
    # the nearest float16 value)
    assert tsdf.max() == np.float16(0.05)
    assert tsdf.min() == np.float16(-0.03)


def test_flying_pixels_do_not_allocate_blocks_and_the_engine_counts_their_samples():
    K, T = pinhole(100.0), look_at((0, 0, 1.0), (0, 0, 0))
    depth = render_plane_z(0.004, K, T)  # a floor about 1 m below the camera: dense blocks
    rng = np.random.default_rng(0)
    v, u = rng.integers(12, 116, (2, 60))
    depth[v, u] = rng.uniform(2.0, 4.5, 60).astype(np.float32)  # isolated far pixels (behind the floor)
    every = engine_for_tests(min_new_block_samples=0, tsdf_fusion=False)
    policy = engine_for_tests(min_new_block_samples=32, tsdf_fusion=False)
    for engine in (every, policy):
        engine.integrate("tof", depth, K, T)
    dropped = policy.stats()
    assert dropped["sparse_dropped_samples"] == policy.counters["sparse_dropped_samples"] > 0
    assert dropped["sparse_dropped_blocks"] == policy.counters["sparse_dropped_blocks"] > 0
    assert every.counters["sparse_dropped_samples"] == 0
    assert dropped["blocks"] + dropped["sparse_dropped_blocks"] == every.stats()["blocks"]
    assert dropped["occupancy"] > every.stats()["occupancy"]
    # the floor's blocks are all there: the same mesh
    floor_every, floor_policy = every.extract_mesh("tof"), policy.extract_mesh("tof")
    assert floor_policy.n_faces == floor_every.n_faces > 1000
    with pytest.raises(InputError, match="min_new_block_samples"):
        engine_for_tests(min_new_block_samples=-1)


def test_sphere_tsdf_matches_analytic_distance():
    # The TSDF is projective (distance along the ray): it equals the true distance where rays meet
    # the surface head-on, so compare where the surface faces the camera within 30 degrees.
    engine = engine_for_tests()
    K = pinhole(200.0)
    eye = np.array([0.0, -1.0, 0.2])
    T = look_at(eye, SPHERE_C)
    engine.integrate("tof", render_sphere(SPHERE_C, SPHERE_R, K, T), K, T)
    centres, tsdf = voxel_values(engine, "tof")
    radial = centres - SPHERE_C
    expected = np.linalg.norm(radial, axis=1) - SPHERE_R
    towards_camera = eye - centres
    cos_incidence = np.sum(radial * towards_camera, axis=1) / (
        np.linalg.norm(radial, axis=1) * np.linalg.norm(towards_camera, axis=1))
    near = (np.abs(expected) <= 0.02) & (cos_incidence > math.cos(math.radians(30)))
    assert near.sum() > 1000
    err = np.abs(tsdf[near] - expected[near])
    assert err.max() < VOXEL
    assert err.mean() < 0.3 * VOXEL


def test_sphere_mesh_is_one_closed_surface(sphere_engine):
    mesh = sphere_engine.extract_mesh("fused")
    v, f = mesh.vertices, mesh.faces
    assert mesh.n_faces > 5000
    assert len(np.unique(v, axis=0)) == len(v)  # no duplicate vertices at block seams
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    unique_edges, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)  # closed, manifold
    assert len(v) - len(unique_edges) + len(f) == 2  # Euler characteristic of a sphere
    radii = np.linalg.norm(v - SPHERE_C, axis=1)
    assert np.abs(radii - SPHERE_R).max() < VOXEL
    # spans many blocks, so seams were really crossed
    assert len(np.unique(np.floor(v / (BLOCK * VOXEL)), axis=0)) > 50


def test_incremental_block_meshes_equal_whole_mesh():
    engine = engine_for_tests()
    K = SPHERE_K
    shown: dict = {}
    for T in SPHERE_VIEWS[:5]:
        depth = render_sphere(SPHERE_C, SPHERE_R, K, T)
        engine.integrate("tof", depth, K, T)
        engine.integrate("stereo", depth + 0.004, K, T)
        update = engine.update()
        for key in update.removed:
            shown.pop(key)
        shown.update(update.changed)
    snapshot = engine.block_meshes().as_dict()  # what a late subscriber gets
    assert snapshot.keys() == shown.keys()
    for key, mesh in shown.items():
        np.testing.assert_array_equal(snapshot[key].vertices, mesh.vertices)
        np.testing.assert_array_equal(snapshot[key].faces, mesh.faces)
    whole = engine.extract_mesh("fused")
    joined = join_block_meshes(list(shown.values()))
    assert joined.n_faces == whole.n_faces > 1000
    np.testing.assert_allclose(np.unique(joined.vertices, axis=0), np.unique(whole.vertices, axis=0), atol=1e-5)


def test_a_block_a_late_subscribers_snapshot_showed_is_deleted_when_its_mesh_vanishes():
    """The node sends a late subscriber the whole mesh (block_meshes) just after an update while frames
    keep coming: blocks integrated in between were in the snapshot but not among the blocks the updates
    knew they had shown, so when their mesh vanished (the surface moved on) no update deleted it, and
    every subscriber kept the stale triangles."""
    engine = engine_for_tests()
    K = pinhole(160.0)

    def wall(z_m: float, frames: int = 1) -> None:  # both sensors see a wall z_m ahead
        for _ in range(frames):
            for sensor in engine.config.sensors:
                engine.integrate(sensor, np.full((128, 128), z_m, np.float32), K, np.eye(4))

    wall(0.30)
    engine.update()
    wall(0.57)  # integrated while that update is published: in the snapshot alone
    shown = engine.block_meshes().as_dict()  # after a DELETEALL, what every subscriber shows
    wall(0.54, frames=3)  # the wall moves back into the blocks before: those at 0.57 hold no surface any more
    update = engine.update()
    for key in update.removed:
        shown.pop(key)
    shown.update(update.changed)
    assert set(shown) == set(engine.block_meshes().as_dict())


def test_an_update_meshed_on_several_threads_equals_one_meshed_on_one(monkeypatch):
    """update(mesh_threads=2): the changed blocks' meshes in shares on the alpha threads, the same
    meshes in the same order as one thread's batches."""
    import threading

    import senfunet_core.engine as engine_module

    monkeypatch.setattr(engine_module, "_MIN_THREAD_BLOCKS", 16)
    one, several = engine_for_tests(), engine_for_tests(alpha_threads=2, mesh_batch_blocks=64)
    meshing_threads: set[str] = set()
    block_meshes = several.mesher.block_meshes
    # the first two shares on the alpha threads wait for each other: on a loaded machine one pool thread
    # could otherwise take both before the other starts
    meet, arrivals = threading.Barrier(2, timeout=60), itertools.count()

    def recorded(*args, **kwargs):
        name = threading.current_thread().name
        meshing_threads.add(name)
        if name.startswith("senfunet-alpha") and next(arrivals) < 2:
            meet.wait()
        return block_meshes(*args, **kwargs)

    several.mesher.block_meshes = recorded
    for T in SPHERE_VIEWS[:3]:
        depth = render_sphere(SPHERE_C, SPHERE_R, SPHERE_K, T)
        for engine in (one, several):
            engine.integrate("tof", depth, SPHERE_K, T)
            engine.integrate("stereo", depth + 0.004, SPHERE_K, T)
        expected, got = one.update(), several.update(mesh_threads=2)
        assert len(expected.meshes) > 64
        for name in ("keys", "vertices", "faces", "colors", "vertex_offsets", "face_offsets"):
            np.testing.assert_array_equal(getattr(got.meshes, name), getattr(expected.meshes, name))
        assert got.removed == expected.removed
    assert {"senfunet-alpha_0", "senfunet-alpha_1"} <= meshing_threads  # (a round's rest: the updating thread)


def join_block_meshes(pieces: list[Mesh]) -> Mesh:
    """Per-block meshes (as the node publishes them) welded into one."""
    offsets = np.cumsum([0] + [m.n_vertices for m in pieces])
    vertices = np.concatenate([m.vertices for m in pieces]).astype(np.float64) / VOXEL
    faces = np.concatenate([m.faces + o for m, o in zip(pieces, offsets)])
    vertices, faces, _ = weld(vertices, faces)
    return Mesh((vertices * VOXEL).astype(np.float32), faces)


def dense_alpha(engine: SenFuNet) -> dict[tuple, float]:
    """The weighting net over one dense grid covering every block plus a zero margin (the paper's way)."""
    grid = engine.grid
    coords = grid.coords[: grid.n_blocks]
    lo = coords.min(0).values * BLOCK - 3
    hi = (coords.max(0).values + 1) * BLOCK + 3
    dims = (hi - lo).tolist()
    channels = []
    for i in range(2):
        feat = torch.zeros((*dims, networks.N_FEATURES))
        weight = torch.zeros(dims)
        tsdf = torch.zeros(dims)
        for slot in range(grid.n_blocks):
            o = (coords[slot] * BLOCK - lo).tolist()
            sl = (slice(o[0], o[0] + BLOCK), slice(o[1], o[1] + BLOCK), slice(o[2], o[2] + BLOCK))
            feat[sl] = decode_features(grid.pools[f"feat{i}"][slot]).view(BLOCK, BLOCK, BLOCK, -1)
            weight[sl] = grid.pools[f"weight{i}"][slot].view(BLOCK, BLOCK, BLOCK)
            tsdf[sl] = grid.pools[f"tsdf{i}"][slot].view(BLOCK, BLOCK, BLOCK)
        channels.append((feat, weight, tsdf))
    tsdfs = [c[2] for c in channels] if engine.config.weighting_tsdf_input else None
    x = networks.weighting_input([c[0] for c in channels], [c[1] for c in channels], tsdfs, engine.config.band_m)
    with torch.no_grad():
        alpha = engine.weighting_net(x.permute(3, 0, 1, 2).unsqueeze(0), pad=True)[0, 0]
    return alpha, lo


@pytest.mark.parametrize("tsdf_input", [False, True])
def test_incremental_alpha_equals_whole_grid_alpha(tsdf_input):
    engine = engine_for_tests(weighting_tsdf_input=tsdf_input)
    assert engine.weighting_net.conv1.in_channels == (14 if tsdf_input else 12)
    with torch.no_grad():  # larger random weights than the default init, so alpha varies a lot
        for p in engine.weighting_net.parameters():
            p.mul_(3.0)
    K = SPHERE_K
    for i, T in enumerate(SPHERE_VIEWS[:4]):
        depth = render_sphere(SPHERE_C, SPHERE_R, K, T)
        engine.integrate("tof" if i % 2 == 0 else "stereo", depth, K, T)
        engine.update()  # incremental: only the blocks touched since the previous update
    alpha, lo = dense_alpha(engine)
    grid = engine.grid
    incremental = decode_alpha(grid.pools["alpha"][: grid.n_blocks]).view(-1, BLOCK, BLOCK, BLOCK)
    worst = 0.0
    spread = []
    for slot in range(grid.n_blocks):
        o = (grid.coords[slot] * BLOCK - lo).tolist()
        whole = alpha[o[0]:o[0] + BLOCK, o[1]:o[1] + BLOCK, o[2]:o[2] + BLOCK]
        worst = max(worst, float((whole - incremental[slot]).abs().max()))
        spread.append(whole)
    # the grid stores alpha in steps of 1/254 (grid.encode_alpha): within half a step of the
    # whole-grid value, a whole one next to 0.5 (which keeps its side), plus the float32 rounding of
    # another summation order
    assert worst < 1 / 254 + 1e-5
    assert float(torch.stack(spread).std()) > 0.01  # alpha is not trivially constant


def test_fusion_equation_on_c12_c1_c2():
    engine = engine_for_tests(border_px=0)
    constant_alpha(engine, 0.3)
    K = pinhole(200.0)
    T = look_at((0, 0, 1.0), (0, 0, 0))
    depth_1 = render_plane_z(0.0, K, T)
    depth_2 = render_plane_z(0.02, K, T)
    depth_1[:, 80:] = 0  # sensor 1 sees the left part, sensor 2 the right part: C1, C12 and C2 all exist
    depth_2[:, :48] = 0
    engine.integrate("tof", depth_1, K, T)
    engine.integrate("stereo", depth_2, K, T)
    grid = engine.grid
    n = grid.n_blocks
    v1, w1 = grid.pools["tsdf0"][:n].flatten(), grid.pools["weight0"][:n].flatten()
    v2, w2 = grid.pools["tsdf1"][:n].flatten(), grid.pools["weight1"][:n].flatten()
    centres = voxel_centres(grid.coords[:n], VOXEL).reshape(-1, 3).numpy()
    keys_by_position = {tuple(np.round(c / VOXEL).astype(int)): i for i, c in enumerate(centres)}
    got_centres, got = voxel_values(engine, "fused", filtered=False)
    idx = np.array([keys_by_position[tuple(np.round(c / VOXEL).astype(int))] for c in got_centres])
    v1, w1, v2, w2 = (t.float().numpy()[idx] for t in (v1, w1, v2, w2))
    c12, c1, c2 = (w1 > 0) & (w2 > 0), (w1 > 0) & (w2 == 0), (w1 == 0) & (w2 > 0)
    assert c12.sum() > 100 and c1.sum() > 100 and c2.sum() > 100
    a = np.float32(np.rint(0.3 * 254)) / np.float32(254)  # alpha as the grid stores it (grid.encode_alpha)
    np.testing.assert_allclose(got[c12], a * v1[c12] + (1 - a) * v2[c12], atol=1e-6)
    np.testing.assert_allclose(got[c1], v1[c1], atol=1e-7)
    np.testing.assert_allclose(got[c2], v2[c2], atol=1e-7)
    # the outlier filter: alpha 0.3 < 0.5 drops exactly the sensor-1-only voxels
    kept, _ = voxel_values(engine, "fused", filtered=True)
    assert len(kept) == int(c12.sum() + c2.sum())
    constant_alpha(engine, 0.7)  # the net changed: alpha is re-evaluated everywhere
    kept, _ = voxel_values(engine, "fused", filtered=True)
    assert len(kept) == int(c12.sum() + c1.sum())


def test_stored_alpha_stays_on_its_side_of_one_half():
    alpha = np.array([0.5 - 1e-5, 0.5, 0.5 + 1e-5, 0.25, 0.9, np.nan, 0.0, 1.0, 0.3 + 1 / 508], np.float32)
    codes = encode_alpha(alpha)
    assert codes.dtype == np.uint8 and codes[5] == ALPHA_UNKNOWN
    stored = decode_alpha(torch.from_numpy(codes)).numpy()
    assert stored[0] < 0.5 and stored[1] == 0.5 and stored[2] > 0.5  # the filter decides as on float32
    np.testing.assert_array_equal(codes[[3, 4, 6, 7]], np.rint(alpha[[3, 4, 6, 7]] * 254))  # elsewhere: nearest step
    assert np.isnan(stored[5]) and stored[6] == 0.0 and stored[7] == 1.0
    assert np.all(np.abs(stored[[0, 1, 2, 3, 4, 6, 7, 8]] - alpha[[0, 1, 2, 3, 4, 6, 7, 8]]) <= 1 / 254 + 1e-7)
    assert np.all(np.abs(stored[3:5] - alpha[3:5]) <= 0.5 / 254 + 1e-7)


def test_outlier_filter_boundaries():
    v1 = torch.tensor([0.1, 0.1, 0.1, 0.0, 0.0, 0.0, 0.2, 0.0])
    w1 = torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 2.0, 0.0])
    v2 = torch.tensor([0.0, 0.0, 0.0, -0.1, -0.1, -0.1, -0.2, 0.0])
    w2 = torch.tensor([0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 3.0, 0.0])
    alpha = torch.tensor([0.49, 0.5, 0.51, 0.49, 0.5, 0.51, 0.25, 0.9])
    out = fuse(v1, w1, v2, w2, alpha, apply_filter=True)
    assert out.observed.tolist() == [False, True, True, True, True, False, True, False]
    assert out.tsdf_m[6].item() == pytest.approx(0.25 * 0.2 + 0.75 * -0.2)
    assert fuse(v1, w1, v2, w2, alpha, apply_filter=False).observed.tolist() == [True] * 7 + [False]


def test_running_average_and_weight_clip():
    engine = engine_for_tests(w_max=3.0)
    K = pinhole(400.0)
    T = look_at((0, 0, 1.0), (0, 0, 0))
    planes_z = (0.0, -0.01, -0.02, -0.03, -0.04)  # moving away: the voxel at z=0 stays in front
    for z in planes_z:
        engine.integrate("tof", render_plane_z(z, K, T), K, T)
    weights = engine.grid.pools["weight0"][: engine.grid.n_blocks]
    assert weights.max().item() == 3.0
    # a voxel seen by every frame: average with the clipped weight, (W*V + v) / (W + 1), W <= 3
    centres, tsdf = voxel_values(engine, "tof")
    probe = np.argmin(np.linalg.norm(centres - np.array([0.0, 0.0, 0.0]), axis=1))
    expected = 0.0
    for i, z in enumerate(planes_z):
        w = min(i, 3)
        expected = (w * expected - z) / (w + 1)
    assert tsdf[probe] == pytest.approx(expected, abs=1e-5)


def test_a_map_saved_before_the_net_judged_it_is_judged_once_loaded(tmp_path):
    """~/save_map judged the weighting net's whole backlog first, holding the map from mesh updates and
    the other services for tens of seconds on a room during a stream. The map is now saved as it stands,
    with what the net owes, and the loaded map judges it: the same mesh as judging before saving."""
    engine = engine_for_tests()
    integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[:6]])
    judged_before = engine.counters.get("alpha_voxels", 0)
    save_map(engine, tmp_path / "map.pt")
    assert engine.counters.get("alpha_voxels", 0) == judged_before  # nothing judged by the save
    loaded = load_map(tmp_path / "map.pt")
    assert (loaded.store.stale[: loaded.grid.n_blocks] > 0).sum() > 0
    want, got = engine.extract_mesh("fused"), loaded.extract_mesh("fused")
    assert want.n_faces > 0
    np.testing.assert_array_equal(want.vertices, got.vertices)
    np.testing.assert_array_equal(want.faces, got.faces)


def test_save_and_load_give_identical_meshes(sphere_engine, tmp_path):
    path = tmp_path / "state.pt"
    save_map(sphere_engine, path)
    loaded = load_map(path)
    for which in ("fused", "tof", "tsdf_fusion"):
        a, b = sphere_engine.extract_mesh(which), loaded.extract_mesh(which)
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
    # a resumed session re-sends its whole mesh on the first update
    update = loaded.update()
    assert join_block_meshes(list(update.changed.values())).n_faces == sphere_engine.extract_mesh("fused").n_faces
    # replay's last mesh frees the map before its weld: the same mesh, and an empty engine after it
    last = loaded.extract_mesh("fused", then_reset=True)
    np.testing.assert_array_equal(last.vertices, sphere_engine.extract_mesh("fused").vertices)
    np.testing.assert_array_equal(last.faces, sphere_engine.extract_mesh("fused").faces)
    assert loaded.grid.n_blocks == 0 and loaded.extract_mesh("fused").n_faces == 0
    with pytest.raises(InputError, match="no such map file"):
        load_map(tmp_path / "missing.pt")
    partial = {k: v for k, v in torch.load(path, weights_only=True).items() if k != "feature_nets"}
    torch.save(partial, tmp_path / "partial.pt")
    with pytest.raises(InputError, match="incomplete engine state .no feature_nets"):
        load_map(tmp_path / "partial.pt")


def test_compact_channels_round_trip_and_float32_map_files_still_load(sphere_engine, tmp_path):
    grid = sphere_engine.grid
    n = grid.n_blocks
    features = {name for name in grid.pools if name.startswith("feat")}
    assert features == {"feat0", "feat1"}
    assert {grid.pools[name].dtype for name in features} == {torch.int8}
    assert grid.pools["alpha"].dtype == torch.uint8
    assert {pool.dtype for name, pool in grid.pools.items() if name not in features | {"alpha"}} == {torch.float16}
    # per voxel, 6 half-precision values (2 x (TSDF, weight), the baseline's TSDF and weight), alpha
    # in a byte and 2 x 4 bytes of features (4 in 6 bits, the depth's 8-bit code); per block, its
    # coordinates, key and up to 4 hash-table entries
    assert grid.bytes_per_block() == 512 * (2 * 6 + 1 + 2 * 4) + 3 * 8 + 8 + 4 * 16
    path = tmp_path / "state.pt"
    save_map(sphere_engine, path)
    loaded = load_map(path)
    assert loaded.grid.n_blocks == n
    for name, pool in grid.pools.items():  # bit for bit (alpha's NaN where never evaluated included)
        assert torch.equal(pool[:n].view(torch.int8), loaded.grid.pools[name][:n].view(torch.int8)), name
    # a map file written when features were float16 (5 per voxel): loads, each feature rounded to 6 bits
    state = torch.load(path, weights_only=True)
    for name in sorted(features):
        half = decode_features(state["grid"][f"pool.{name}"]).half()
        assert half.shape == (n, 512, 5)
        half[..., :4] = half[..., :4] + 0.01 * (half[..., :4] != 0)  # off the 6-bit steps
        state["grid"][f"pool.{name}"] = half
    old_features = tmp_path / "float16_features_state.pt"
    torch.save(state, old_features)
    from_half = load_map(old_features)
    for name in sorted(features):
        got = decode_features(from_half.grid.pools[name][:n])
        want = state["grid"][f"pool.{name}"].float()
        assert torch.equal(got[..., 4], decode_features(encode_features(want))[..., 4]), name  # depth to its code
        assert float((got[..., :4] - want[..., :4]).abs().max()) <= 0.5 / 31 + 1e-6, name
        assert not torch.equal(got[..., :4], want[..., :4])
    # map files written when the learned features were int8 (steps of 1/127) and the depth float16
    # bits (n + 1 bytes a voxel) or its 8-bit code (n bytes): load with the same learned features
    # (they came from 6-bit values) and the depth rounded to its code
    for depth_bytes in (2, 1):
        state = torch.load(path, weights_only=True)
        for name in sorted(features):
            values = decode_features(state["grid"][f"pool.{name}"])
            learned = torch.round(values[..., :4] * 127).to(torch.int8)
            depth = values[..., 4:] + 0.002 * (values[..., 4:] != 0)  # off the 8-bit steps
            depth = depth.half().view(torch.int8) if depth_bytes == 2 else encode_features(
                torch.cat([values[..., :4], depth], dim=-1))[..., -1:]
            state["grid"][f"pool.{name}"] = torch.cat([learned, depth], dim=-1)
        earlier = tmp_path / f"int8_features_state_{depth_bytes}.pt"
        torch.save(state, earlier)
        from_earlier = load_map(earlier)
        for name in sorted(features):
            got = decode_features(from_earlier.grid.pools[name][:n])
            assert torch.equal(got[..., :4], decode_features(grid.pools[name][:n])[..., :4]), name
            saved = decode_saved_features(state["grid"][f"pool.{name}"], 5)
            assert torch.equal(got[..., 4:], decode_features(encode_features(saved))[..., 4:]), name
            assert depth_bytes == 1 or not torch.equal(got[..., 4:], saved[..., 4:])
    # a map file written when TSDFs, alpha and a per-voxel drift were float32: loads, TSDFs rounded
    # to float16, alpha to its 8-bit code, and the blocks where a voxel had drifted marked for the net
    state = torch.load(path, weights_only=True)
    rng = np.random.default_rng(0)
    wide = {}
    for name in ("tsdf0", "tsdf1", "alpha"):
        values = state["grid"][f"pool.{name}"].float() if name != "alpha" else decode_alpha(state["grid"]["pool.alpha"])
        values = values + torch.from_numpy(rng.uniform(-1e-4, 1e-4, values.shape).astype(np.float32)) * (values != 0)
        state["grid"][f"pool.{name}"] = wide[name] = values  # not representable in float16
    wide["alpha"][0, :10] = float("nan")  # not evaluated
    drifted = torch.from_numpy(rng.uniform(size=(n, 512)) < 0.002)
    state["grid"]["pool.drift"] = drifted.float() * 0.01
    assert 0 < int(drifted.any(dim=1).sum()) < n
    old = tmp_path / "float32_state.pt"
    torch.save(state, old)
    from_old = load_map(old)
    for name, values in wide.items():
        got = from_old.grid.pools[name][:n]
        if name == "alpha":
            assert got.dtype == torch.uint8 and torch.equal(got, torch.from_numpy(encode_alpha(values.numpy())))
            assert int((got == ALPHA_UNKNOWN).sum()) == 10 and bool(torch.isfinite(values).any())
        else:
            assert got.dtype == torch.float16
            assert torch.equal(got.view(torch.int16), values.half().view(torch.int16)), name
    assert np.array_equal(from_old.store.alpha_pending[:n], drifted.any(dim=1).numpy())
    assert (from_old.store.reach_renewed[:n][drifted.any(dim=1).numpy()] == (1 << 27) - 1).all()
    assert from_old.extract_mesh("tof").n_faces > 1000


def grid_snapshot(engine: SenFuNet) -> list[torch.Tensor]:
    return [engine.grid.coords[: engine.grid.n_blocks].clone()] + [
        p[: engine.grid.n_blocks].clone() for p in engine.grid.pools.values()]


@pytest.mark.parametrize("mutate, message", [
    (lambda d, K, T, rgb: (d[None], K, T, rgb), "2-D"),
    (lambda d, K, T, rgb: (d.astype(np.uint16), K, T, rgb), "float32"),
    (lambda d, K, T, rgb: (d, K * np.array([[0, 1, 1], [1, 1, 1], [1, 1, 1]]), T, rgb), "focal"),
    (lambda d, K, T, rgb: (d, -K, T, rgb), "focal"),
    (lambda d, K, T, rgb: (d, K[:2], T, rgb), "3x3"),
    (lambda d, K, T, rgb: (d, K, np.full((4, 4), np.nan), rgb), "finite"),
    (lambda d, K, T, rgb: (d, K, T * 2, rgb), "rigid"),
    (lambda d, K, T, rgb: (d, K, T, np.zeros((10, 10, 3), np.uint8)), "rgb"),
    (lambda d, K, T, rgb: (d, K, T, np.zeros((*d.shape, 3), np.float32)), "rgb"),
])
def test_bad_input_raises_and_leaves_grids_untouched(sphere_engine, mutate, message):
    K = SPHERE_K
    T = SPHERE_VIEWS[0]
    depth = render_sphere(SPHERE_C, SPHERE_R, K, T)
    before = grid_snapshot(sphere_engine)
    args = mutate(depth, K, T, None)
    with pytest.raises(ValueError, match=message):
        sphere_engine.integrate("tof", *args)
    with pytest.raises(ValueError, match="unknown sensor"):
        sphere_engine.integrate("lidar", depth, K, T)
    for a, b in zip(before, grid_snapshot(sphere_engine)):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True)  # unjudged alpha is NaN


def test_invalid_depth_pixels_are_skipped():
    engine = engine_for_tests(border_px=0)
    K = pinhole(200.0)
    T = look_at((0, 0, 1.0), (0, 0, 0))
    depth = render_plane_z(0.0, K, T)
    bad = depth.copy()
    bad[::3, ::3] = np.nan
    bad[1::3, ::3] = np.inf
    bad[2::3, ::3] = -1.0
    bad[::3, 1::3] = 0.0
    assert engine.integrate("tof", np.full_like(depth, np.nan), K, T) == 0
    engine.integrate("tof", bad, K, T)
    centres, tsdf = voxel_values(engine, "tof")
    assert np.all(np.isfinite(tsdf)) and len(tsdf) > 1000
    reference = engine_for_tests(border_px=0)
    good_only = np.where(np.isfinite(bad) & (bad > 0), bad, 0).astype(np.float32)
    reference.integrate("tof", good_only, K, T)
    assert len(voxel_values(reference, "tof")[1]) == len(tsdf)


def test_weight_cloud_reports_each_voxel_where_it_is_with_its_own_alpha_and_weights():
    """The net says alpha = 0.8 everywhere; stereo sees the left half of what ToF sees, from the same
    poses: every stereo voxel is a ToF voxel, some ToF voxels are not stereo ones, and the voxels
    near the surface lie on the sphere."""
    engine = engine_for_tests()
    constant_alpha(engine, 0.8)
    K = SPHERE_K
    for T in SPHERE_VIEWS[:6]:
        depth = render_sphere(SPHERE_C, SPHERE_R, K, T)
        engine.integrate("tof", depth, K, T)
        half = depth.copy()
        half[:, depth.shape[1] // 2:] = 0
        engine.integrate("stereo", half, K, T)
    cloud = weight_cloud(engine)
    n = len(cloud.positions_m)
    assert n > 1000 and cloud.alpha.shape == (n,) and cloud.weights.shape == (n, 2)
    # the net's output as the grid stores it (float16), not another channel
    np.testing.assert_allclose(cloud.alpha, np.rint(0.8 * 254) / 254, atol=1e-7)  # as stored (grid.encode_alpha)
    tof, stereo = cloud.weights[:, 0], cloud.weights[:, 1]
    assert np.all(tof >= stereo) and np.any((tof > 0) & (stereo == 0)) and np.any(stereo > 0)
    near = weight_cloud(engine, max_abs_tsdf_m=VOXEL)
    assert 0 < len(near.positions_m) < n
    radius_m = np.linalg.norm(near.positions_m - SPHERE_C, axis=1)
    assert np.abs(radius_m - SPHERE_R).max() < 1.5 * VOXEL  # voxel centres in metres, in the world frame



def whole_map_weight_rows(engine: SenFuNet, max_abs_tsdf_m: float | None) -> dict[int, np.ndarray]:
    """Per block key, its weight-cloud rows (x, y, z, alpha, weights) as the whole map reads them with
    torch under both locks (what `weight_cloud` returned before it read the map in slices)."""
    with engine.update_lock.held(), engine.data_lock:
        slots = torch.arange(engine.grid.n_blocks)
        blocks = engine.mesher.whole_blocks(slots, engine.mesher.channels("fused"))
        coords = engine.grid.coords[slots].clone()
    centres = voxel_centres(coords, engine.config.voxel_size_m)
    weights = torch.stack([blocks["weight0"], blocks["weight1"]], dim=-1)
    keep = (weights > 0).any(dim=-1) & torch.isfinite(blocks["alpha"])
    if max_abs_tsdf_m is not None:
        keep &= engine.mesher.values(blocks, "fused", filtered=False)[0].abs() <= max_abs_tsdf_m
    rows = torch.cat([centres, blocks["alpha"].unsqueeze(-1), weights], dim=-1)
    return {key: rows[b][keep[b]].numpy() for b, key in enumerate(block_keys(coords).tolist())}


def cloud_rows(cloud) -> np.ndarray:
    return np.concatenate([cloud.positions_m, cloud.alpha[:, None], cloud.weights], axis=1)


def cloud_blocks(cloud, voxel_m: float) -> np.ndarray:
    """The block key of each point of a weight cloud."""
    voxels = torch.from_numpy(np.rint(cloud.positions_m / voxel_m).astype(np.int64))
    return block_keys(torch.div(voxels, BLOCK, rounding_mode="floor")).numpy()


class ReleaseHook:
    """Stands in for an engine's data lock: the same lock, and `between()` is called in the thread
    that lets it go, each time it does (while that thread holds nothing of the engine)."""

    def __init__(self, lock, between) -> None:
        self._lock = lock
        self._between = between

    def __enter__(self):
        self._lock.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self._lock.release()
        self._between()

    def acquire(self, *args, **kwargs):
        return self._lock.acquire(*args, **kwargs)

    def release(self) -> None:
        self._lock.release()


def test_weight_cloud_equals_the_whole_map_read_under_both_locks_slice_by_slice():
    """Judged blocks and blocks the net has not judged yet (left out); every slice size gives the
    rows of the whole-map read, in its order, bit for bit."""
    engine = engine_for_tests()
    K = SPHERE_K
    for i, T in enumerate(SPHERE_VIEWS[:8]):
        depth = render_sphere(SPHERE_C, SPHERE_R, K, T)
        engine.integrate("tof", depth, K, T)
        if i % 2:
            engine.integrate("stereo", depth * np.float32(1.01), K, T)
        if i == 4:
            engine.update()  # the later frames' new voxels wait for the net: alpha NaN
    for band in (None, 0.02, VOXEL):
        expected = np.concatenate(list(whole_map_weight_rows(engine, band).values()))
        assert len(expected) > 1000 and np.any(expected[:, 4] != expected[:, 5])
        for slice_blocks in (1, 7, 100_000):
            cloud = weight_cloud(engine, band, refresh_alpha=False, slice_blocks=slice_blocks)
            assert cloud.positions_m.dtype == cloud.alpha.dtype == cloud.weights.dtype == np.float32
            np.testing.assert_array_equal(cloud_rows(cloud), expected)
    with engine.data_lock:
        assert np.isnan(decode_alpha(engine.grid.pools["alpha"][: engine.grid.n_blocks]).numpy()).any()


def test_weight_cloud_lets_integration_and_updates_in_between_its_slices():
    """While a cloud is being built, another thread takes the update lock and integrates a frame into
    the blocks it reads: the cloud holds each block as one of the two maps has it, those read before
    the frame as before, those after as after."""
    engine = engine_for_tests()
    K = SPHERE_K
    for T in SPHERE_VIEWS[:4]:
        for sensor in engine.config.sensors:
            engine.integrate(sensor, render_sphere(SPHERE_C, SPHERE_R, K, T), K, T)
    engine.update()
    before = whole_map_weight_rows(engine, None)
    other: dict[str, object] = {}
    builder = threading.current_thread()
    releases = []

    def meanwhile() -> None:  # another thread's update lock and frame
        with engine.update_lock.held(wait=False) as held:
            other["update_lock"] = held
            T = SPHERE_VIEWS[0]
            other["voxels"] = engine.integrate("tof", render_sphere(SPHERE_C, SPHERE_R, K, T) * np.float32(0.99), K, T)

    def between() -> None:
        if threading.current_thread() is not builder:
            return
        releases.append(len(releases))
        if len(releases) == 3:  # the keys, then two slices read
            thread = threading.Thread(target=meanwhile)
            thread.start()
            thread.join(timeout=120)  # a guard against a deadlock (the builder holding a lock), not a timing
            other["finished"] = not thread.is_alive()

    snapshot = block_keys(engine.grid.coords[: engine.grid.n_blocks]).tolist()  # the blocks in slot order
    engine.data_lock = ReleaseHook(engine.data_lock, between)
    cloud = weight_cloud(engine, refresh_alpha=False, slice_blocks=5)
    engine.data_lock = engine.data_lock._lock
    assert other.get("finished") and other["update_lock"] is True and other["voxels"] > 0
    assert len(releases) > 3  # slices were read after the frame
    after = whole_map_weight_rows(engine, None)
    keys = cloud_blocks(cloud, VOXEL)
    rows = cloud_rows(cloud)
    order = list(dict.fromkeys(keys.tolist()))  # the blocks in the order read
    assert order == [key for key in snapshot if len(before[key])]  # in slot order; none lost
    read_before = set(snapshot[:10])  # the first two slices' blocks
    as_before = as_after = 0
    for key in order:
        block = rows[keys == key]
        if key in read_before:
            np.testing.assert_array_equal(block, before[key])
        else:
            np.testing.assert_array_equal(block, after[key])
        as_before += np.array_equal(block, before[key]) and not np.array_equal(block, after[key])
        as_after += np.array_equal(block, after[key]) and not np.array_equal(block, before[key])
    assert as_before and as_after  # the frame changed blocks on both sides of the hold it came in

def test_reset_empties_the_map(tmp_path):
    engine = engine_for_tests()
    K = SPHERE_K
    T = SPHERE_VIEWS[0]
    for sensor in engine.config.sensors:
        engine.integrate(sensor, render_sphere(SPHERE_C, SPHERE_R, K, T), K, T)
    assert engine.update().changed
    engine.reset()
    update = engine.update()
    assert update.cleared and not update.changed
    assert engine.extract_mesh("tof").n_faces == 0


def test_core_imports_no_ros():
    code = ("import sys, senfunet_core.engine, senfunet_core.integrator, senfunet_core.mesher;"
            "bad = [m for m in sys.modules if m.split('.')[0] in "
            "('rclpy', 'sensor_msgs', 'geometry_msgs', 'visualization_msgs', 'rosbags', 'senfunet_ros')];"
            "print(bad); sys.exit(1 if bad else 0)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_weighting_net_has_the_paper_parameter_count():
    net = networks.WeightingNet()
    assert sum(p.numel() for p in net.parameters()) == 24257
    for uses_rgb, expected in ((False, 1668), (True, 1776)):
        assert sum(p.numel() for p in networks.FeatureNet(uses_rgb).parameters()) == expected


def test_alpha_budget_defers_work_and_holds_back_single_sensor_voxels():
    """With no time for the weighting net, alpha stays NaN (not evaluated): the update's mesh
    shows only what both sensors saw; a refresh without a budget catches up exactly, and the next
    update shows it (the live node's order: update, publish, refresh_alpha)."""
    engine, reference = engine_for_tests(), engine_for_tests()
    K = SPHERE_K
    for e in (engine, reference):
        for i, T in enumerate(SPHERE_VIEWS[:4]):
            depth = render_sphere(SPHERE_C, SPHERE_R, K, T)
            if i % 2:
                depth[:, : depth.shape[1] // 2] = 0  # sensor 2 sees half: C1 voxels exist
            e.integrate("tof" if i % 2 == 0 else "stereo", depth, K, T)
    held = engine.update(alpha_budget_s=0.0)
    engine.refresh_alpha(0.0)
    n = engine.grid.n_blocks
    assert bool((engine.grid.pools["alpha"][:n] == ALPHA_UNKNOWN).all())
    assert engine.counters["alpha_backlog_blocks"] > 0
    full = reference.update()
    assert 0 < len(held.meshes.faces) < len(full.meshes.faces)  # C1 voxels held back
    assert np.isfinite(held.meshes.colors).all()
    engine.refresh_alpha()  # no budget: everything evaluated
    assert engine.counters["alpha_backlog_blocks"] == 0
    np.testing.assert_array_equal(engine.grid.pools["alpha"][:n].numpy(), reference.grid.pools["alpha"][:n].numpy())
    caught_up = engine.update(alpha_budget_s=0.0)
    assert len(caught_up.meshes) == len(full.meshes)
    np.testing.assert_array_equal(caught_up.meshes.faces, full.meshes.faces)
    np.testing.assert_allclose(caught_up.meshes.vertices, full.meshes.vertices, atol=1e-6)


FAR_C = np.array([3.0, 0.0, 0.0])  # the map bound tests' second sphere, 3 m from the first


def far_views(n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(centre, T_world_camera) views of the sphere at FAR_C, as SPHERE_VIEWS see the first one."""
    return [(FAR_C, look_at(FAR_C + 0.9 * (T[:3, 3] - SPHERE_C), FAR_C)) for T in SPHERE_VIEWS[:n]]


def integrate_views(engine: SenFuNet, views: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """Both sensors see the same depth image of each (centre, T_world_camera) view."""
    for centre, T in views:
        depth = render_sphere(centre, SPHERE_R, SPHERE_K, T)
        engine.integrate("tof", depth, SPHERE_K, T)
        engine.integrate("stereo", depth, SPHERE_K, T)


def test_max_blocks_evicts_the_blocks_farthest_from_the_camera_and_keeps_their_mesh(tmp_path):
    """The memory bound: past max_blocks, the blocks farthest from the last camera are evicted; the
    blocks kept hold exactly what an unbounded engine holds for them, and are found again; the
    evicted blocks' final meshes stay shown and saved: the fused mesh equals the unbounded one."""
    views = [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]] + far_views(2)  # the far sphere seen last
    reference = engine_for_tests()
    integrate_views(reference, views)
    reference.update()
    n_all = reference.grid.n_blocks
    bounded = engine_for_tests(max_blocks=int(0.7 * n_all))
    shown: dict = {}
    for i, (centre, T) in enumerate(views):
        integrate_views(bounded, [(centre, T)])
        if i == 1:  # the first sphere is meshed (and shown) before the far one comes
            shown.update(bounded.update().changed)
    update = bounded.update()
    grid = bounded.grid
    assert grid.n_blocks <= int(0.9 * bounded.config.max_blocks)
    kept = grid.coords[: grid.n_blocks]
    camera = torch.from_numpy(views[-1][1][:3, 3])

    def distance(coords: torch.Tensor) -> torch.Tensor:
        return ((coords.double() * BLOCK + 3.5) * VOXEL - camera).norm(dim=1)

    everything = reference.grid.coords[:n_all]
    dropped = everything[reference.grid.lookup(everything).numpy() >= 0][
        ~np.isin(block_keys(everything).numpy(), block_keys(kept).numpy())]
    assert len(dropped) == n_all - grid.n_blocks > 0
    assert float(distance(kept).max()) <= float(distance(dropped).min())  # the nearest blocks are kept
    dropped_keys = set(map(tuple, dropped.tolist()))
    assert not dropped_keys & set(update.removed)  # subscribers keep showing the evicted blocks
    archived = bounded.archive.meshes().as_dict()
    assert set(archived) <= dropped_keys and len(archived) > 0.5 * len(dropped_keys & set(shown))
    for key in archived:  # the final mesh reached subscribers (sent again, or unchanged)
        assert key in update.changed or key in shown
    slots = reference.grid.lookup(kept)
    assert bool((slots >= 0).all())
    assert torch.equal(grid.lookup(kept), torch.arange(grid.n_blocks))  # the hash table knows the moved blocks
    for name in ("tsdf0", "weight0", "feat0"):
        assert torch.equal(grid.pools[name][: grid.n_blocks], reference.grid.pools[name][slots]), name
    # the whole fused mesh, archive included, is the unbounded engine's
    full, kept_mesh = reference.extract_mesh("fused"), bounded.extract_mesh("fused")
    assert full.n_faces > 1000 and kept_mesh.n_faces == full.n_faces, (kept_mesh.n_faces, full.n_faces)

    def centroids(mesh):
        return mesh.vertices[mesh.faces].mean(axis=1)

    gap, _ = cKDTree(centroids(full)).query(centroids(kept_mesh))
    assert float(gap.max()) < 1e-5
    gap, _ = cKDTree(centroids(kept_mesh)).query(centroids(full))  # and no seam along the eviction front
    assert float(gap.max()) < 1e-5
    assert bounded.stats()["archived_blocks"] == len(archived)
    save_map(bounded, tmp_path / "map.pt")  # a saved map keeps the archive
    loaded = load_map(tmp_path / "map.pt")
    assert loaded.extract_mesh("fused").n_faces == kept_mesh.n_faces
    assert set(loaded.block_meshes().as_dict()) == set(bounded.block_meshes().as_dict())


def test_integration_keeps_the_map_bound_between_updates():
    K = SPHERE_K
    engine = engine_for_tests(max_blocks=60)
    for T in SPHERE_VIEWS[:6]:  # ~300 blocks' worth, and no update in between
        engine.integrate("tof", render_sphere(SPHERE_C, SPHERE_R, K, T), K, T)
        assert engine.grid.n_blocks <= 1.25 * 60 or engine.counters.get("evicted_blocks", 0) == 0
    assert engine.counters["evicted_blocks"] > 0 and engine.grid.n_blocks <= 1.25 * 60
    update = engine.update()
    assert engine.grid.n_blocks <= 60 and isinstance(update.removed, list)


def test_a_bound_smaller_than_a_frames_view_is_warned_about_once_and_counted(caplog):
    """Evicting blocks the latest frame reached means they come back at once (the map thrashes):
    warned once, counted; a bound the camera moved away from evicts only what it left behind."""
    caplog.set_level(logging.WARNING, logger="senfunet.engine")
    near, far = [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]], far_views(2)
    thrashing = engine_for_tests(max_blocks=60)  # a view of the sphere reaches about 110 blocks
    for views in (near, far):
        integrate_views(thrashing, views)
        thrashing.update()
    warnings = [r.getMessage() for r in caplog.records if "smaller than what a frame sees" in r.getMessage()]
    assert len(warnings) == 1 and "max_blocks 60" in warnings[0] and "max_map_blocks" in warnings[0]
    assert 0 < thrashing.stats()["evicted_in_view_blocks"] <= thrashing.stats()["evicted_blocks"]
    caplog.clear()
    moving_on = engine_for_tests(max_blocks=165)  # both spheres: about 280 blocks
    for views in (near, far):
        integrate_views(moving_on, views)
        moving_on.update()
    stats = moving_on.stats()
    assert stats["evicted_blocks"] > 50 and stats["evicted_in_view_blocks"] == 0
    assert not any("smaller than what a frame sees" in r.getMessage() for r in caplog.records)


def test_the_bound_keeps_what_the_latest_frames_see_before_what_lies_behind_the_camera(caplog):
    """Victims went by distance from the camera alone: a camera looking at a far surface, with an old
    one just behind it, had the surface in view evicted (and back at once: thrashing, and the warning
    about a bound smaller than a frame's view, at bounds well above it). The blocks the latest frames
    touched now go last."""
    caplog.set_level(logging.WARNING, logger="senfunet.engine")
    behind = [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]]
    eye = SPHERE_C + np.array([0.6, 0.0, 0.0])  # 0.3 m from the first sphere, 2.1 m from the far one
    ahead = [(FAR_C, look_at(eye + offset, FAR_C)) for offset in 0.05 * fibonacci_directions(6)]
    probe, probe_behind = engine_for_tests(), engine_for_tests()
    integrate_views(probe, ahead)
    integrate_views(probe_behind, behind)
    n_ahead = probe.grid.n_blocks
    # both spheres exceed the bound (the update evicts), not its hard bound (integration does not)
    engine = engine_for_tests(max_blocks=int((n_ahead + probe_behind.grid.n_blocks) / 1.2))
    integrate_views(engine, behind)
    n_behind = engine.grid.n_blocks
    integrate_views(engine, ahead)  # 12 frames: more than map_bound.RECENT_FRAMES
    assert 1.25 * engine.config.max_blocks > engine.grid.n_blocks > engine.config.max_blocks
    assert 0.9 * engine.config.max_blocks > n_ahead  # the bound holds what the camera sees
    engine.update()
    stats = engine.stats()
    assert 0 < stats["evicted_blocks"] <= n_behind and stats["evicted_in_view_blocks"] == 0
    kept = engine.grid.coords[: engine.grid.n_blocks]
    assert bool((probe.grid.lookup(kept) >= 0).sum() == n_ahead)  # every block in view stayed
    assert not any("smaller than what a frame sees" in r.getMessage() for r in caplog.records)


def test_eviction_tallies_belong_to_the_map_reset_and_saved_with_it(tmp_path):
    """~/reset emptied the archive and the spill but kept the evictions' tallies (evicted blocks more
    than spilled plus restored), and a loaded map began them at 0 beside its archive and spill."""
    engine = engine_for_tests(max_blocks=165)  # both spheres: about 280 blocks
    for views in ([(SPHERE_C, T) for T in SPHERE_VIEWS[:2]], far_views(2), [(SPHERE_C, SPHERE_VIEWS[0])]):
        integrate_views(engine, views)  # away and back: some evicted blocks come back from disk
        engine.update()
    keys = ("evicted_blocks", "evicted_in_view_blocks", "spilled_blocks", "restored_blocks", "archived_blocks")
    before = {key: engine.stats()[key] for key in keys}
    assert before["evicted_blocks"] == before["spilled_blocks"] + before["restored_blocks"] > 0
    assert before["restored_blocks"] > 0 and engine.counters["evicted_blocks"] == before["evicted_blocks"]
    save_map(engine, tmp_path / "map.pt")
    loaded = load_map(tmp_path / "map.pt")
    assert {key: loaded.stats()[key] for key in keys} == before
    assert loaded.counters["evicted_blocks"] == before["evicted_blocks"]
    engine.reset()
    assert all(engine.stats()[key] == 0 for key in keys) and "evicted_blocks" not in engine.counters


def test_integration_past_the_hard_bound_during_an_update_is_served_between_batches():
    """Integration that outgrows the hard bound while an update runs waits only for the update's
    next batch boundary, where the update evicts and carries on with the blocks that moved. What a
    subscriber builds from the updates is the map's mesh: no evicted block is shown, none is missing."""
    import threading
    import time

    K = SPHERE_K
    # A sphere seen first (low slots; the victims), a second one 3 m from it (its last blocks move
    # into the freed slots while the update has them pending), a third one seen during the update.
    far = SPHERE_C + [3.0, 0.0, 0.0]
    # every touched block allocated: the block counts this test is built on
    engine = engine_for_tests(max_blocks=320, mesh_batch_blocks=8, alpha_batch_blocks=8, min_new_block_samples=0)

    def integrate(centre: np.ndarray, views: list[np.ndarray]) -> None:
        for T in views:
            depth = render_sphere(centre, SPHERE_R, K, T)
            engine.integrate("tof", depth, K, T)
            engine.integrate("stereo", depth, K, T)

    integrate(far, [look_at(far + 0.9 * (T[:3, 3] - SPHERE_C), far) for T in SPHERE_VIEWS[:3]])
    integrate(SPHERE_C, SPHERE_VIEWS[:1])
    hard_bound = 1.25 * engine.config.max_blocks
    assert engine.grid.n_blocks <= engine.config.max_blocks  # no eviction when the update starts
    mesh_batch, evict = engine.mesher.triangles, engine._evict
    beside = SPHERE_C + [0.0, 1.0, 0.0]  # the blocks of the second sphere are not touched again
    worker = threading.Thread(target=integrate, args=(beside, [look_at(beside + [0.0, 0.0, 0.9], beside)]))
    dropped_mid_update: list[np.ndarray] = []

    def first_batch_starts_integration(slots, which, filtered):
        if worker.ident is None:
            worker.start()
            deadline = time.monotonic() + 60
            while engine.grid.n_blocks <= hard_bound and time.monotonic() < deadline:
                time.sleep(0.01)  # until the worker outgrew the bound (it now waits for a safe point)
        return mesh_batch(slots, which, filtered)

    def recorded_eviction(**options):
        eviction = evict(**options)
        if eviction is not None:
            dropped_mid_update.append(eviction.dropped_keys)
        return eviction

    engine.mesher.triangles, engine._evict = first_batch_starts_integration, recorded_eviction
    first = engine.update()
    worker.join(timeout=120)
    assert not worker.is_alive()
    engine.mesher.triangles, engine._evict = mesh_batch, evict
    assert len(dropped_mid_update) == 1, "no eviction at a safe point"
    # the evicted blocks' final meshes are sent (from the archive), not lost
    sent_evicted = np.isin(block_keys(torch.from_numpy(first.meshes.keys)).numpy(), dropped_mid_update[0])
    assert sent_evicted.sum() == len(engine.archive) > 0
    archived = set(engine.archive.meshes().as_dict())
    for key, mesh in first.changed.items():  # each mesh lies in its block: the moved blocks were followed
        corner = np.array(key) * BLOCK * VOXEL
        low = corner - (VOXEL if key in archived else 0.0)  # with the seam cells of the blocks before it
        assert ((mesh.vertices >= low - 1e-6) & (mesh.vertices <= corner + (BLOCK + 1) * VOXEL + 1e-6)).all()

    shown = dict(first.changed)
    second = engine.update()
    for key in second.removed:
        shown.pop(key, None)
    shown.update(second.changed)
    expected = engine.block_meshes().as_dict()
    assert set(shown) == set(expected) and len(expected) > 50
    for key, mesh in expected.items():
        np.testing.assert_array_equal(shown[key].faces, mesh.faces)
        np.testing.assert_allclose(shown[key].vertices, mesh.vertices)


def _two_spheres_one_scheduled_before(engine: SenFuNet) -> int:
    """A far sphere integrated and scheduled (refresh_alpha(0): nothing evaluated), then a near one
    integrated: returns the slot count after the far sphere (the near sphere's blocks come after)."""
    K = SPHERE_K
    far = SPHERE_C + [3.0, 0.0, 0.0]
    far_view = look_at(far + 0.9 * (SPHERE_VIEWS[0][:3, 3] - SPHERE_C), far)
    for centre, T in ((far, far_view), (SPHERE_C, SPHERE_VIEWS[0])):
        depth = render_sphere(centre, SPHERE_R, K, T)
        engine.integrate("tof", depth, K, T)
        engine.integrate("stereo", depth, K, T)
        if centre is far:
            engine.refresh_alpha(0.0)
            n_far = engine.grid.n_blocks
    return n_far


def _judge_two_batches(engine: SenFuNet, monkeypatch, *, idle: bool = False) -> np.ndarray:
    """refresh_alpha with a budget that runs exactly two batches (on a fake clock, each batch takes
    0.3 s of it, the budget is 0.65 s: a third would end past it), as an idle catch-up (until a frame
    comes) if `idle`; returns the slots judged so far."""
    import senfunet_core.alpha_scheduler as scheduler_module

    clock = VirtualClock()
    monkeypatch.setattr(scheduler_module, "time", clock)
    infer = engine.weighting_net.infer  # what the scheduler runs the net through on the CPU

    def slow_infer(*args, **kwargs):
        clock.now_s += 0.3
        return infer(*args, **kwargs)

    engine.weighting_net.infer = slow_infer
    engine.refresh_alpha(0.65, until_frame=idle)
    assert clock.now_s == pytest.approx(0.6)
    return np.flatnonzero(engine.store.evaluated[: engine.grid.n_blocks])


@pytest.mark.parametrize("alpha_order", ["latest", "longest_waiting"])
def test_a_budget_serves_the_blocks_its_order_puts_first(monkeypatch, alpha_order):
    """"latest": the blocks the latest frames reached (the near sphere's); "longest_waiting": those
    whose last change is oldest (the far sphere's, reached by an earlier schedule)."""
    engine = engine_for_tests(alpha_batch_blocks=16, alpha_order=alpha_order)
    n_far = _two_spheres_one_scheduled_before(engine)
    assert engine.grid.n_blocks - n_far > 32
    evaluated = _judge_two_batches(engine, monkeypatch)
    assert len(evaluated) == 32
    if alpha_order == "latest":
        assert evaluated.min() >= n_far  # the near sphere's, reached last
    else:
        assert evaluated.max() < n_far  # the far sphere's, waiting since the first schedule


@pytest.mark.parametrize("alpha_order", ["latest", "longest_waiting"])
def test_blocks_of_equal_rank_are_judged_in_the_order_of_their_keys(alpha_order):
    """One frame's blocks, scheduled together, all of one rank: they are judged in key order (side
    by side in space, so that a batch's windows share their neighbours), not in the slot order
    they were allocated in."""
    engine = engine_for_tests(alpha_order=alpha_order)
    depth = render_sphere(SPHERE_C, SPHERE_R, SPHERE_K, SPHERE_VIEWS[0])
    engine.integrate("tof", depth, SPHERE_K, SPHERE_VIEWS[0])
    engine.refresh_alpha(0.0)  # scheduled, nothing judged
    order = engine.alpha.order()
    assert sorted(order.tolist()) == list(range(engine.grid.n_blocks))
    keys = engine.grid.slot_keys[order]
    assert (np.diff(keys) > 0).all()
    assert (np.diff(engine.grid.slot_keys[: engine.grid.n_blocks]) < 0).any()  # slot order is another


def test_blocks_judged_together_go_in_the_order_of_their_keys(monkeypatch):
    """The blocks the map bound has judged before an eviction (`AlphaScheduler.judge`) go to the
    net in key order too, whatever order they are given in, and each is judged once."""
    engine = engine_for_tests(alpha_batch_blocks=16)
    depth = render_sphere(SPHERE_C, SPHERE_R, SPHERE_K, SPHERE_VIEWS[0])
    engine.integrate("tof", depth, SPHERE_K, SPHERE_VIEWS[0])
    batches: list[np.ndarray] = []
    evaluate = engine.alpha.evaluate

    def recorded(slots: np.ndarray):
        batches.append(slots.copy())
        return evaluate(slots)

    monkeypatch.setattr(engine.alpha, "evaluate", recorded)
    given = np.random.default_rng(0).permutation(engine.grid.n_blocks)
    judged = engine.alpha.judge(given, side_by_side=lambda: False)
    assert len(batches) > 1 and judged > 0
    keys = engine.grid.slot_keys[np.concatenate(batches)]
    assert len(keys) == len(given) and (np.diff(keys) > 0).all()


@pytest.mark.parametrize("schedule_s", [0.4, 0.8])
def test_scheduling_the_changes_counts_in_the_budget(monkeypatch, schedule_s):
    """A budget is seconds from the call: on a large map scheduling the frames' changes takes a
    batch's time, and a turn that left it out ran past the mesh period it was given. On a fake
    clock each batch takes 0.3 s: with a budget of 0.65 s, scheduling that takes 0.4 s leaves time
    for one batch, not two; scheduling that takes all of it (0.8 s) still leaves the first batch,
    which always runs (the net never stalls while frames come)."""
    engine = engine_for_tests(alpha_batch_blocks=16)
    _two_spheres_one_scheduled_before(engine)
    assert engine.store.alpha_pending[: engine.grid.n_blocks].any()  # the near sphere waits to be scheduled
    import senfunet_core.alpha_scheduler as scheduler_module

    clock = VirtualClock()
    monkeypatch.setattr(scheduler_module, "time", clock)
    schedule = engine.alpha.schedule

    def slow_schedule() -> None:
        clock.now_s += schedule_s
        schedule()

    monkeypatch.setattr(engine.alpha, "schedule", slow_schedule)
    infer = engine.weighting_net.infer

    def slow_infer(*args, **kwargs):
        clock.now_s += 0.3
        return infer(*args, **kwargs)

    engine.weighting_net.infer = slow_infer
    engine.refresh_alpha(0.65)
    assert clock.now_s == pytest.approx(schedule_s + 0.3)
    assert engine.store.evaluated[: engine.grid.n_blocks].sum() == 16


@pytest.mark.parametrize("idle", [False, True])
def test_longest_waiting_judges_the_blocks_with_a_mesh_first(monkeypatch, idle):
    """A far sphere seen by one sensor (no mesh while its alpha is unknown: the filter holds
    single-sensor voxels back) has waited longer than a near sphere both sensors saw, which has a
    mesh; a short budget still judges the near sphere's meshed blocks first, while frames come and
    once they pause: they are what a subscriber sees (a stale alpha shows a stale surface)."""
    engine = engine_for_tests(alpha_batch_blocks=16)
    K = SPHERE_K
    far = SPHERE_C + [3.0, 0.0, 0.0]
    far_view = look_at(far + 0.9 * (SPHERE_VIEWS[0][:3, 3] - SPHERE_C), far)
    engine.integrate("tof", render_sphere(far, SPHERE_R, K, far_view), K, far_view)
    engine.refresh_alpha(0.0)  # scheduled first, nothing judged
    n_far = engine.grid.n_blocks
    depth = render_sphere(SPHERE_C, SPHERE_R, K, SPHERE_VIEWS[0])
    engine.integrate("tof", depth, K, SPHERE_VIEWS[0])
    engine.integrate("stereo", depth, K, SPHERE_VIEWS[0])
    engine.update(alpha_budget_s=0)  # meshed, not judged
    meshed = engine.store.meshed[: engine.grid.n_blocks]
    assert not meshed[:n_far].any() and meshed[n_far:].sum() > 32
    evaluated = _judge_two_batches(engine, monkeypatch, idle=idle)
    assert len(evaluated) == 32 and meshed[evaluated].all()


def test_longest_waiting_judges_never_judged_blocks_without_a_mesh_before_judged_ones(monkeypatch):
    """Without a mesh, a block the net never judged may hold surface that one sensor alone saw (the
    filter holds it back until the net judges it), one judged before and changed since rarely does:
    a sphere seen by one sensor and judged, then seen again, waits behind a second one-sensor sphere
    seen later and never judged."""
    engine = engine_for_tests(alpha_batch_blocks=16)
    K = SPHERE_K

    def one_sensor_view(centre, view):
        T = look_at(centre + 0.9 * (view[:3, 3] - SPHERE_C), centre)
        engine.integrate("tof", render_sphere(centre, SPHERE_R, K, T), K, T)

    judged_sphere, new_sphere = SPHERE_C + [3.0, 0.0, 0.0], SPHERE_C + [-3.0, 0.0, 0.0]
    one_sensor_view(judged_sphere, SPHERE_VIEWS[0])
    engine.refresh_alpha(None)  # judged
    n_judged = engine.grid.n_blocks
    one_sensor_view(judged_sphere, SPHERE_VIEWS[0])  # seen again: its inputs changed
    engine.refresh_alpha(0.0)  # scheduled first
    assert engine.grid.n_blocks == n_judged
    one_sensor_view(new_sphere, SPHERE_VIEWS[0])
    engine.update(alpha_budget_s=0)
    assert not engine.store.meshed[: engine.grid.n_blocks].any()
    engine.alpha.schedule()  # the new sphere's blocks stale too (the refresh below would do it first)
    stale_before = engine.store.stale[: engine.grid.n_blocks].copy()
    assert (stale_before[:n_judged] > 0).sum() > 32 and (stale_before[n_judged:] == 3).sum() > 32
    _judge_two_batches(engine, monkeypatch)
    judged = np.flatnonzero((stale_before > 0) & (engine.store.stale[: engine.grid.n_blocks] == 0))
    assert len(judged) == 32 and judged.min() >= n_judged


def test_the_idle_catch_up_judges_never_judged_blocks_without_a_mesh_with_the_most_surface_first(monkeypatch):
    """Once the sensors pause, among blocks without a mesh, those the net never judged with the most
    voxels near a sensor's surface go first, however long the others waited: the filter holds back
    the surface one sensor alone saw until the net judges it. Two one-sensor spheres, the second
    seen after the first was scheduled."""
    engine = engine_for_tests(alpha_batch_blocks=16)
    K = SPHERE_K
    spheres = (SPHERE_C + [3.0, 0.0, 0.0], SPHERE_C + [-3.0, 0.0, 0.0])
    for centre in spheres:
        T = look_at(centre + 0.9 * (SPHERE_VIEWS[0][:3, 3] - SPHERE_C), centre)
        engine.integrate("tof", render_sphere(centre, SPHERE_R, K, T), K, T)
        if centre is spheres[0]:
            engine.refresh_alpha(0.0)  # scheduled first: waiting longer
            n_first = engine.grid.n_blocks
    engine.update(alpha_budget_s=0)
    n = engine.grid.n_blocks
    assert not engine.store.meshed[:n].any() and n - n_first > 32
    judged = _judge_two_batches(engine, monkeypatch, idle=True)
    views = engine.store.views("tsdf0", "weight0", "tsdf1", "weight1")
    near = near_surface_voxels(np.arange(n), *views, engine.config.voxel_size_m)
    assert len(judged) == 32 and judged.max() >= n_first  # not simply the longest waiting
    assert near[judged].min() >= np.delete(near, judged).max()


def sphere_view_on_a_fake_clock(monkeypatch) -> tuple[SenFuNet, VirtualClock, np.ndarray]:
    """An engine whose clock the test sets (at 0 s), with one view of the sphere from both sensors;
    returns it, the clock and the view's depth (SPHERE_K, SPHERE_VIEWS[0])."""
    import senfunet_core.engine as engine_module

    clock = VirtualClock()
    monkeypatch.setattr(engine_module, "time", clock)
    engine = engine_for_tests()
    depth = render_sphere(SPHERE_C, SPHERE_R, SPHERE_K, SPHERE_VIEWS[0])
    engine.integrate("tof", depth, SPHERE_K, SPHERE_VIEWS[0])
    engine.integrate("stereo", depth, SPHERE_K, SPHERE_VIEWS[0])
    return engine, clock, depth


def test_stats_say_how_long_the_meshed_surface_waits_for_the_weighting_net(monkeypatch):
    """The live goal "every meshed block judged within 3 s of its last change" is measured by
    stats(): meshed blocks whose alpha is not up to date, and how long since the change they wait
    for (on a fake clock: from the frame, whether the change was scheduled yet or not)."""
    engine, clock, depth = sphere_view_on_a_fake_clock(monkeypatch)
    clock.now_s = 1.0
    engine.update(alpha_budget_s=0)  # meshed, not judged, the change not even scheduled
    clock.now_s = 2.5
    stats = engine.stats()
    assert stats["meshed_blocks"] > 0 and stats["meshed_blocks_alpha_current"] == 0
    assert stats["meshed_blocks_unjudged_over_3s"] == 0 and stats["oldest_unjudged_change_s"] == 2.5
    engine.alpha.schedule()  # scheduled, not judged: stale, still waiting since the frame
    clock.now_s = 4.0
    stats = engine.stats()
    assert stats["meshed_blocks_unjudged_over_3s"] == stats["meshed_blocks"] > 0
    assert stats["oldest_unjudged_change_s"] == 4.0
    engine.update()  # judged: nothing waits
    stats = engine.stats()
    assert stats["meshed_blocks_alpha_current"] == stats["meshed_blocks"]
    assert stats["meshed_blocks_unjudged_over_3s"] == 0 and stats["oldest_unjudged_change_s"] == 0.0


def test_the_wait_counts_from_the_last_frame_that_changed_a_block(monkeypatch):
    """"Within 3 s of its last change": of the frames one schedule takes, the latest that reached a
    block is its last change, not the oldest (a view seen for the whole mesh period would otherwise
    count as waiting since the period began)."""
    engine, clock, depth = sphere_view_on_a_fake_clock(monkeypatch)
    engine.update(alpha_budget_s=0)  # meshed, not judged
    clock.now_s = 0.9
    engine.integrate("stereo", depth, SPHERE_K, SPHERE_VIEWS[0])  # the same view again: the same blocks change
    clock.now_s = 2.0
    assert engine.stats()["oldest_unjudged_change_s"] == pytest.approx(1.1)  # not scheduled yet
    engine.alpha.schedule()
    clock.now_s = 3.5
    stats = engine.stats()
    assert stats["meshed_blocks"] > 0 and stats["meshed_blocks_alpha_current"] == 0
    assert stats["oldest_unjudged_change_s"] == pytest.approx(2.6)  # since 0.9 s, not since 0 s
    assert stats["meshed_blocks_unjudged_over_3s"] == 0
    clock.now_s = 4.0
    assert engine.stats()["meshed_blocks_unjudged_over_3s"] == stats["meshed_blocks"]


def test_the_scheduler_keeps_no_state_per_schedule(monkeypatch):
    """How long alpha waits is kept per block (the map's size), not per schedule: a node that
    schedules once a second for a week would otherwise hold, and copy on every status, a value per
    schedule. Many schedules of the same view leave the scheduler's state the same size; the wait
    still counts from the frame that made the block stale."""
    import senfunet_core.engine as engine_module

    clock = VirtualClock()
    monkeypatch.setattr(engine_module, "time", clock)
    engine = engine_for_tests()
    K, T = SPHERE_K, SPHERE_VIEWS[0]
    depth = render_sphere(SPHERE_C, SPHERE_R, K, T)

    def state_size() -> int:
        return sum(v.nbytes if isinstance(v, np.ndarray) else len(v) if isinstance(v, (list, dict, set)) else 0
                   for v in (*vars(engine.alpha).values(), *vars(engine.store).values()))

    engine.integrate("tof", depth, K, T)
    engine.integrate("stereo", depth, K, T)
    engine.update(alpha_budget_s=0)  # meshed, alpha not judged
    engine.alpha.schedule()
    size = state_size()
    for i in range(50):
        clock.now_s = float(i + 1)
        engine.integrate("stereo", depth, K, T)
        engine.alpha.schedule()
    assert engine.alpha.schedules == 51 and state_size() == size
    clock.now_s = 55.0
    stats = engine.stats()
    # nothing judged: every meshed block has waited at least since the last frame (50 s)
    assert stats["meshed_blocks_unjudged_over_3s"] == stats["meshed_blocks"] > 0
    assert 5.0 <= stats["oldest_unjudged_change_s"] <= 55.0


def test_alpha_is_written_when_the_data_lock_is_free_not_waited_for_per_batch(monkeypatch):
    """Integration holding the data lock does not stall the weighting net: the batches evaluated
    meanwhile are written once the lock is free. The budget runs on a fake clock (each batch takes
    0.125 s of it: a budget of 0.4 s runs exactly three); the lock is held from the first batch
    until the third has run, so an engine that waited for the lock per batch would reach the
    second batch only after the holder gave up (and fail the checks below)."""
    import threading

    import senfunet_core.alpha_scheduler as scheduler_module

    engine = engine_for_tests(alpha_batch_blocks=8)
    _two_spheres_one_scheduled_before(engine)
    engine.refresh_alpha(0.0)  # the near sphere scheduled too
    n = engine.grid.n_blocks
    clock = VirtualClock()
    monkeypatch.setattr(scheduler_module, "time", clock)
    take, holding, release = threading.Event(), threading.Event(), threading.Event()

    def hold_the_lock() -> None:
        take.wait(timeout=30)
        with engine.data_lock:
            holding.set()
            release.wait(timeout=10)  # only a failing engine lets this time out
            holding.clear()

    infer = engine.weighting_net.infer
    batches: list[tuple[bool, int]] = []  # per batch: the lock held by the holder? blocks written so far

    def batch_while_the_lock_is_held(*args, **kwargs):
        if not take.is_set():
            take.set()
            assert holding.wait(timeout=30)
        batches.append((holding.is_set(), int(engine.store.evaluated[:n].sum())))
        clock.now_s += 0.125
        out = infer(*args, **kwargs)
        if len(batches) == 3:
            release.set()
        return out

    holder = threading.Thread(target=hold_the_lock)
    holder.start()
    engine.weighting_net.infer = batch_while_the_lock_is_held
    engine.refresh_alpha(0.4)
    holder.join(timeout=30)
    assert len(batches) == 3
    assert all(held for held, _ in batches)  # the net went on while integration held the lock
    assert all(written == 0 for _, written in batches)  # and wrote nothing under it
    evaluated = engine.store.evaluated[:n]
    assert evaluated.sum() > 8  # more than one batch, all written once the lock was free
    alpha = decode_alpha(engine.grid.pools["alpha"][:n]).numpy()
    assert np.isfinite(alpha[evaluated]).all() and bool((engine.store.stale[:n][evaluated] == 0).all())


def test_the_default_map_bound_follows_the_machines_memory():
    """max_blocks=-1: as many blocks as fit in half of this machine's memory, at what a block costs."""
    import os

    from senfunet_core.map_bound import memory_bound_blocks

    engine = engine_for_tests(max_blocks=-1)
    per_block = engine.grid.bytes_per_block()
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    assert engine.max_blocks == memory_bound_blocks(per_block)
    assert 1024 <= engine.max_blocks <= 0.5 * total / per_block
    # what a block costs covers its rows and its share of the hash table (at most 4 entries a block
    # past the initial table)
    T = SPHERE_VIEWS[0]
    engine.integrate("tof", render_sphere(SPHERE_C, SPHERE_R, SPHERE_K, T), SPHERE_K, T)
    grid = engine.grid
    table_bytes = grid.hash_table.keys.nbytes + grid.hash_table.slots.nbytes
    assert grid.n_blocks > 10 and grid.nbytes() - table_bytes <= grid.n_blocks * per_block
    entry_bytes = grid.hash_table.keys.itemsize + grid.hash_table.slots.itemsize
    assert len(grid.hash_table.keys) <= max(4096, 4 * grid.n_blocks) and per_block - 4 * entry_bytes > 512 * 8
    with pytest.raises(InputError, match="max_blocks"):
        EngineConfig(max_blocks=-2).validate()


@pytest.mark.parametrize("alpha_threads,frame_in_batch", [(1, 0), (2, 0), (2, 2)])
def test_idle_catch_up_yields_to_the_next_frame(alpha_threads, frame_in_batch):
    """refresh_alpha(None, until_frame=True), the node's catch-up when the sensors pause, stops
    after the batches under way once a frame is integrated (during its first batch, or its third,
    when batches wait queued behind those under way: they are withdrawn); the rest stays stale for
    the next update, counted as its backlog, and a plain refresh finishes it."""
    engine = engine_for_tests(alpha_batch_blocks=2, alpha_threads=alpha_threads)
    K = SPHERE_K
    for T in SPHERE_VIEWS[:3]:
        engine.integrate("tof", render_sphere(SPHERE_C, SPHERE_R, K, T), K, T)
    evaluate = engine.alpha.evaluate
    frame = render_sphere(SPHERE_C, SPHERE_R, K, SPHERE_VIEWS[3])
    batches = []

    def evaluate_while_a_frame_arrives(slots):
        if len(batches) == frame_in_batch:
            engine.integrate("stereo", frame, K, SPHERE_VIEWS[3])
        batches.append(len(slots))
        return evaluate(slots)

    engine.alpha.evaluate = evaluate_while_a_frame_arrives
    engine.refresh_alpha(None, until_frame=True)
    assert frame_in_batch + 1 <= len(batches) <= frame_in_batch + 2 * alpha_threads
    assert engine.counters["alpha_backlog_blocks"] > 10
    # the backlog is what is still stale (the new frame's changes are scheduled by the next refresh)
    assert engine.counters["alpha_backlog_blocks"] == np.count_nonzero(engine.store.stale[: engine.grid.n_blocks])
    engine.refresh_alpha(None)
    assert engine.counters["alpha_backlog_blocks"] == 0
    assert len(batches) > 10


def test_catch_up_withdraws_the_batches_queued_when_a_frame_comes():
    """With two alpha threads, batches wait queued behind the two under way (a thread that finishes
    takes the next at once); when a frame comes, those not started are withdrawn and stay stale,
    counted in the backlog."""
    import threading

    engine = engine_for_tests(alpha_batch_blocks=2, alpha_threads=2)
    K = SPHERE_K
    for T in SPHERE_VIEWS[:3]:
        engine.integrate("tof", render_sphere(SPHERE_C, SPHERE_R, K, T), K, T)
    evaluate = engine.alpha.evaluate
    release = threading.Event()
    started: list[int] = []

    def evaluate_held(slots):  # the first two batches at once, the next two held until the frame came
        started.append(len(started))
        if len(started) > 2:
            release.wait(10)
        return evaluate(slots)

    asked = []

    def until_frame() -> bool:  # asked before the first batch and after each: the frame comes after the second
        asked.append(True)
        if len(asked) < 3:
            return False
        threading.Timer(0.3, release.set).start()  # after the queued batch was withdrawn
        return True

    engine.alpha.evaluate = evaluate_held
    refresh = engine.alpha.refresh(None, until_frame=until_frame, eviction_due=lambda: False, evict=lambda: None)
    # batches 0 and 1, then 2, 3 and 4 queued: the two threads take 2 and 3 as they come free (unless the
    # frame came first), and 4, behind them, is withdrawn
    assert 2 <= len(started) <= 4
    stale = np.count_nonzero(engine.alpha.store.stale[: engine.grid.n_blocks])
    assert refresh.backlog == stale > 2


def with_float16_depth_packing(state: dict, grid) -> dict:
    """A saved engine state as an earlier version wrote it: feature rows of n + 1 bytes (learned
    features int8 in steps of 1/127, the depth as float16 bits), in the grid and in the spill's blobs."""
    def repack(rows: torch.Tensor) -> torch.Tensor:
        values = decode_features(rows)
        return torch.cat([torch.round(values[..., :-1] * 127).to(torch.int8),
                          values[..., -1:].half().view(torch.int8)], dim=-1)

    names = list(grid.pools)
    for name in names:
        if name.startswith("feat"):
            state["grid"][f"pool.{name}"] = repack(state["grid"][f"pool.{name}"])
    keys, rows = spilled_rows({k: v.numpy() for k, v in state["spill"].items()})
    sizes = [pool[0].numel() * pool.element_size() for pool in grid.pools.values()]
    columns = np.split(rows, np.cumsum(sizes)[:-1], axis=1)
    for i, name in enumerate(names):
        if name.startswith("feat"):
            packed = torch.from_numpy(columns[i].copy()).view(torch.int8).reshape(len(keys), 512, -1)
            columns[i] = repack(packed).reshape(len(keys), -1).view(torch.uint8).numpy()
    compressor = zstandard.ZstdCompressor()
    blobs = [compressor.compress(np.concatenate(row).tobytes()) for row in zip(*columns)]
    state["spill"] = {"keys": torch.from_numpy(keys), "lengths": torch.tensor([len(b) for b in blobs]),
                      "blobs": torch.from_numpy(np.frombuffer(b"".join(blobs), np.uint8).copy())}
    return state


@pytest.mark.parametrize("min_new_block_samples", [0, 300])
def test_evicted_blocks_come_back_from_disk_when_seen_again(tmp_path, min_new_block_samples):
    """A bounded engine spills evicted blocks' voxels to disk; when the sensors come back to them,
    the blocks continue from what they held (however few samples reach them: they are not new to
    the allocation policy): every block then holds exactly what an unbounded engine holds for it,
    and the two hold the same blocks, also across save and load of the bounded engine in between,
    and when the map was saved by an earlier version with another row layout (its spilled blocks
    load into memory, converted)."""
    near_views = [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]]
    back_views = [(SPHERE_C, T) for T in SPHERE_VIEWS[:3]]

    def integrate(engine: SenFuNet, views) -> None:
        integrate_views(engine, views)
        engine.update()

    reference = engine_for_tests(min_new_block_samples=min_new_block_samples)
    for views in (near_views, far_views(2), back_views):
        integrate(reference, views)
    bounded = engine_for_tests(max_blocks=int(0.6 * reference.grid.n_blocks),
                               min_new_block_samples=min_new_block_samples)
    integrate(bounded, near_views)
    integrate(bounded, far_views(2))  # the near sphere's blocks go to disk
    spilled = bounded.stats()["spilled_blocks"]
    assert spilled > 50
    path = tmp_path / "map.pt"
    save_map(bounded, path)
    earlier = tmp_path / "map_float16_depth.pt"  # as saved when the depth feature was float16 bits
    torch.save(with_float16_depth_packing(torch.load(path, weights_only=True), bounded.grid), earlier)
    from_earlier = load_map(earlier)  # its spilled blocks come back into memory, converted
    assert from_earlier.grid.n_blocks == bounded.grid.n_blocks + spilled and not len(from_earlier.grid.spill or [])
    for engine in (bounded, load_map(path), from_earlier):
        integrate(engine, back_views)  # ... and come back
        stats = engine.stats()
        assert stats["restored_blocks"] > (0.5 * spilled if engine is not from_earlier else -1)
        assert stats["evicted_blocks"] > 0
        grid = engine.grid
        slots = reference.grid.lookup(grid.coords[: grid.n_blocks])
        assert bool((slots >= 0).all())
        on_disk = engine.grid.spill.state_dict()["keys"]
        live = block_keys(grid.coords[: grid.n_blocks]).numpy()
        everything = block_keys(reference.grid.coords[: reference.grid.n_blocks]).numpy()
        assert np.array_equal(np.sort(np.concatenate([live, on_disk])), np.sort(everything))
        for name in ("tsdf0", "weight0", "feat0", "tsdf1", "weight1", "feat1", "tsdf_base", "weight_base"):
            assert torch.equal(grid.pools[name][: grid.n_blocks], reference.grid.pools[name][slots]), name
        # and the fused mesh (archived meshes of the evicted blocks included) is the unbounded one's
        mine, theirs = engine.extract_mesh("fused"), reference.extract_mesh("fused")
        assert mine.n_faces == theirs.n_faces > 1000
        assert np.mean(cKDTree(theirs.vertices).query(mine.vertices)[0] < 1e-6) > 0.999


def test_a_frame_reaching_blocks_while_they_are_evicted_is_in_their_final_mesh():
    """Evicted blocks are judged and meshed without the data lock; a frame that reaches them in
    the meantime is integrated, and their archived meshes are redone with it: they equal the
    meshes of an unbounded engine that fused the same frames."""
    K = SPHERE_K
    views = [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]] + far_views(2)
    late_T = SPHERE_VIEWS[2]  # the near sphere again, arriving during the eviction
    late = render_sphere(SPHERE_C, SPHERE_R, K, late_T)
    reference = engine_for_tests()
    integrate_views(reference, views)
    n_all = reference.grid.n_blocks
    reference.integrate("tof", late, K, late_T)
    reference.update()
    bounded = engine_for_tests(max_blocks=int(0.85 * n_all))  # below the hard bound: the update evicts
    integrate_views(bounded, views)
    assert bounded.stats()["evicted_blocks"] == 0
    evaluate = bounded.alpha.evaluate

    def evaluate_while_a_frame_arrives(slots):
        if bounded.counters.get("evictions", 0) == 0 and bounded.frames_integrated["tof"] == 4:
            bounded.integrate("tof", late, K, late_T)
        return evaluate(slots)

    bounded.alpha.evaluate = evaluate_while_a_frame_arrives
    bounded.update()
    assert bounded.frames_integrated["tof"] == 5 and bounded.stats()["evicted_blocks"] > 0
    archived = bounded.archive.meshes().as_dict()
    expected = reference.block_meshes().as_dict()
    near = [key for key in archived if np.linalg.norm(np.array(key) * BLOCK * VOXEL) < 1.0]
    assert len(near) > 30
    for key in near:
        assert archived[key].n_faces == expected[key].n_faces, key
        np.testing.assert_allclose(archived[key].vertices, expected[key].vertices, atol=1e-5)


def test_an_eviction_integration_waits_for_judges_on_the_alpha_threads():
    """Integration past the hard bound with no update running evicts itself: the weighting net then
    judged the victims' surroundings on that one thread while the other core idled. It now judges
    them on the alpha threads side by side, and the archived meshes are what one thread gives."""
    import threading

    views = [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]] + far_views(2)
    meshes = []
    for threads in (1, 2):
        engine = engine_for_tests(max_blocks=100, alpha_threads=threads)
        evaluate, judged_on = engine.alpha.evaluate, set()

        def recorded(slots, evaluate=evaluate, judged_on=judged_on):
            judged_on.add(threading.current_thread().name.split("_")[0])
            return evaluate(slots)

        engine.alpha.evaluate = recorded
        integrate_views(engine, views)  # no update: integration evicts
        assert engine.stats()["evicted_blocks"] > 0
        if threads == 2:
            assert "senfunet-alpha" in judged_on, judged_on
        meshes.append(engine.archive.meshes().as_dict())
        engine.alpha.stop_workers()
    assert meshes[0].keys() == meshes[1].keys() and len(meshes[0]) > 10
    for key, mesh in meshes[0].items():
        assert np.array_equal(mesh.vertices, meshes[1][key].vertices), key


def test_integration_waiting_at_the_hard_bound_goes_on_after_the_first_slice_of_an_eviction(monkeypatch):
    """An update's eviction judges and meshes its victims slice by slice and removes each slice as it
    goes: an integration that outgrew the hard bound meanwhile goes on once a slice brought the map
    under it, while the eviction carries on (it waited for the whole eviction)."""
    import threading

    from senfunet_core import map_bound

    small_r, beside = 0.1, SPHERE_C + np.array([0.0, 1.0, 0.0])  # the late frame: a small sphere
    late_T = look_at(beside + [0.0, 0.0, 0.6], beside)
    late = render_sphere(beside, small_r, SPHERE_K, late_T)
    views = [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]] + far_views(2)
    probe = engine_for_tests(min_new_block_samples=0)
    integrate_views(probe, views)
    n_start = probe.grid.n_blocks
    probe.integrate("tof", late, SPHERE_K, late_T)
    late_blocks = probe.grid.n_blocks - n_start
    # the late frame takes the map past the hard bound by half its blocks; one slice brings it back
    hard_bound = n_start + late_blocks // 2
    max_blocks = int(hard_bound / map_bound.HARD_BOUND)
    monkeypatch.setattr(map_bound, "SLICE_OF_BOUND", late_blocks / max_blocks, raising=False)
    slice_blocks = max(8, int(map_bound.SLICE_OF_BOUND * max_blocks))
    assert max_blocks < n_start and n_start - int(0.9 * max_blocks) > 2 * slice_blocks  # several slices
    engine = engine_for_tests(max_blocks=max_blocks, alpha_batch_blocks=8, min_new_block_samples=0)
    integrate_views(engine, views)
    assert engine.grid.n_blocks == n_start and engine.stats()["evicted_blocks"] == 0

    blocked, released, eviction_ended = threading.Event(), threading.Event(), threading.Event()
    over_hard_bound, remove, block_meshes, evict = (engine.bound.over_hard_bound, engine.store.remove,
                                                    engine.mesher.block_meshes, engine.bound.evict)
    worker = threading.Thread(target=lambda: (engine.integrate("tof", late, SPHERE_K, late_T), released.set()))
    removals: list[int] = []
    released_mid_eviction: list[bool] = []

    def watched_over_hard_bound() -> bool:
        over = over_hard_bound()
        if over and threading.current_thread() is worker:
            blocked.set()  # the worker holds the wake-up condition from here until it waits on it
        return over

    def watched_remove(victims):
        removals.append(len(victims))
        return remove(victims)

    def first_slice_lets_a_frame_in(slots, coords):
        if worker.ident is None:  # the first slice: the late frame comes, and waits at the hard bound
            worker.start()
            assert blocked.wait(timeout=120)
        elif removals and not released_mid_eviction:  # a later slice: the frame went on meanwhile
            released_mid_eviction.append(released.wait(timeout=120) and not eviction_ended.is_set())
        return block_meshes(slots, coords)

    def recorded_evict(**kwargs):
        eviction = evict(**kwargs)
        eviction_ended.set()
        return eviction

    engine.bound.over_hard_bound = watched_over_hard_bound
    engine.store.remove, engine.mesher.block_meshes = watched_remove, first_slice_lets_a_frame_in
    engine.bound.evict = recorded_evict
    engine.update()
    worker.join(timeout=120)
    assert not worker.is_alive() and released.is_set()
    assert released_mid_eviction == [True], (removals, released_mid_eviction)
    assert len(removals) > 1 and engine.bound.evictions == 1
    assert engine.grid.n_blocks <= max_blocks


def test_stats_counts_the_voxels_without_holding_the_data_lock():
    """Integration waits for the data lock: the statistics' whole-grid count must not hold it."""
    import threading

    engine = engine_for_tests()
    K = pinhole(400.0)
    T = look_at((0.03, 0.02, 1.0), (0.03, 0.02, 0.0))
    engine.integrate("tof", render_plane_z(0.0, K, T), K, T)
    count = engine.store.observed_voxels
    lock_free_while_counting: list[bool] = []

    def observed_voxels(channels: list[str]) -> int:
        def try_lock() -> None:  # another thread, as the integrating one
            got = engine.data_lock.acquire(timeout=2.0)
            if got:
                engine.data_lock.release()
            lock_free_while_counting.append(got)

        other = threading.Thread(target=try_lock)
        other.start()
        other.join()
        return count(channels)

    engine.store.observed_voxels = observed_voxels  # type: ignore[method-assign]
    stats = engine.stats()
    assert lock_free_while_counting == [True]
    assert stats["observed_voxels"] == count(["weight0", "weight1"]) > 1000


def test_an_engine_is_freed_without_the_cycle_collector():
    """The node freezes what exists when it starts spinning (node.spin: gc.freeze), so an engine
    replaced by ~/load_map must go by reference counting alone: no part of it may refer back to it,
    and its alpha threads (started by an update without a budget) must neither keep its map nor
    outlive it."""
    import gc
    import threading
    import weakref

    before = set(threading.enumerate())
    engine = engine_for_tests(max_blocks=100, alpha_threads=2)  # a map bound: its parts (archive, spill) too
    integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]])
    engine.update()
    engine.extract_mesh()
    alpha_threads = [t for t in set(threading.enumerate()) - before if t.name.startswith("senfunet-alpha")]
    assert engine.alpha._executor is not None and alpha_threads
    gone, grid_gone = weakref.ref(engine), weakref.ref(engine.grid)
    enabled = gc.isenabled()
    gc.disable()
    try:
        del engine
        assert gone() is None, "a reference cycle keeps the engine alive"
        assert grid_gone() is None, "something keeps the engine's grid alive"
    finally:
        if enabled:
            gc.enable()
    for thread in alpha_threads:  # a freed pool's idle threads are woken to end
        thread.join(timeout=10)
    assert not any(t.is_alive() for t in alpha_threads)


def _kernel_signatures() -> dict[str, int]:
    """Compiled signatures of every numba kernel of the engine's modules."""
    import numba

    from senfunet_core import alpha, fusion, grid, integrator, mesher

    return {f"{module.__name__}.{name}": len(kernel.signatures) for module in (alpha, fusion, grid, integrator, mesher)
            for name, kernel in vars(module).items() if isinstance(kernel, numba.core.registry.CPUDispatcher)}


def test_warm_up_compiles_every_kernel_a_stream_calls():
    """A kernel first compiled in the middle of a stream stalls the node for seconds (GIL held):
    after warm_up, frames, updates and statistics compile nothing new."""
    engine = SenFuNet(EngineConfig(depth_min_m=(0.05, 0.05)), weights="default")
    warm_up(engine)
    before = _kernel_signatures()
    K = SPHERE_K
    rgb = np.full((128, 128, 3), 100, np.uint8)
    for T in SPHERE_VIEWS[:6]:
        depth = render_sphere(SPHERE_C, SPHERE_R, K, T)
        for sensor in engine.config.sensors:
            engine.integrate(sensor, depth + (0.004 if sensor == engine.config.sensors[1] else 0.0), K, T, rgb)
        engine.update(alpha_budget_s=0.0)
        engine.refresh_alpha(None)
    engine.update()
    assert engine.counters["alpha_blocks"] > 0 and engine.stats()["blocks"] > 0
    after = _kernel_signatures()
    assert {name: count for name, count in after.items() if count != before.get(name, 0)} == {}


def test_mesh_windows_written_to_reused_buffers_equal_fresh_ones(sphere_engine):
    """Every entry is written, where a neighbour block is missing too: a batch never sees the
    previous batch's leftovers in the buffers the mesher reuses."""
    from senfunet_core.fusion import WINDOW_FUSED, WINDOW_SENSOR, mesh_windows

    store = sphere_engine.store
    neighbours = store.neighbours(np.arange(sphere_engine.grid.n_blocks))
    assert (neighbours < 0).any()
    for which, names in ((WINDOW_FUSED, ("tsdf0", "weight0", "tsdf1", "weight1", "alpha")),
                         (WINDOW_SENSOR, ("tsdf0", "weight0", "tsdf0", "weight0", "alpha"))):
        fresh = mesh_windows(neighbours, which, True, *store.views(*names))
        size = len(neighbours) * 9**3 + 5
        dirty = (np.full(size, 7.0, np.float32), np.ones(size, np.bool_), np.full(size, 7.0, np.float32))
        reused = mesh_windows(neighbours, which, True, *store.views(*names), out=dirty)
        for got, want in zip(reused, fresh):
            np.testing.assert_array_equal(got, want)
        assert fresh[1].any() and not fresh[1].all()


def test_meshing_skips_blocks_without_an_observed_voxel_and_makes_the_triangles_of_every_window():
    """`BlockMesher.triangles` fills windows only for blocks with an observed voxel of their own
    (`blocks_with_observed`, which must agree with the windows' own voxels) and gives, block for
    block, the triangles marching cubes makes of every block's window."""
    from senfunet_core.block_mesher import FUSED, MESH_READ_CODES
    from senfunet_core.fusion import WINDOW_FUSED, WINDOW_SENSOR, blocks_with_observed, mesh_windows
    from senfunet_core.grid import ALPHA_UNKNOWN
    from senfunet_core.mesher import marching_cubes_blocks

    engine = engine_for_tests()
    for i, T in enumerate(SPHERE_VIEWS):  # the second sensor sees half the views: C1 voxels, and C12
        depth = render_sphere(SPHERE_C, SPHERE_R, SPHERE_K, T)
        for sensor in engine.config.sensors[: 1 + i % 2]:
            engine.integrate(sensor, depth, SPHERE_K, T)
    store, n = engine.store, engine.grid.n_blocks
    # alpha per block: not evaluated, for sensor 1, for sensor 2, or exactly one half
    codes = np.array([ALPHA_UNKNOWN, 200, 50, 127], np.uint8)[np.arange(n) % 4]
    alpha_pool = engine.grid.pools["alpha"]
    alpha_pool[:n] = torch.from_numpy(np.repeat(codes, 512).reshape(n, *alpha_pool.shape[1:]))
    slots = np.arange(n)
    fused = ("tsdf0", "weight0", "tsdf1", "weight1", "alpha")
    # (unfiltered, every block has a voxel a sensor saw: none is skipped)
    cases = [(FUSED, WINDOW_FUSED, fused, True, True), (FUSED, WINDOW_FUSED, fused, False, False),
             (engine.config.sensors[1], WINDOW_SENSOR, ("tsdf1", "weight1", "tsdf1", "weight1", "alpha"), True, True)]
    for which, mode, names, filtered, some_skipped in cases:
        views = store.views(*names)
        tsdf, observed, alpha = mesh_windows(store.neighbours(slots, MESH_READ_CODES), mode, filtered, *views)
        has_observed = blocks_with_observed(slots, mode, filtered, views[1], views[3], views[4])
        np.testing.assert_array_equal(has_observed, observed[:, :8, :8, :8].reshape(n, -1).any(axis=1))
        assert 0 < has_observed.sum() < n if some_skipped else has_observed.all(), (which, filtered)
        want = marching_cubes_blocks(tsdf, observed, engine.grid.coords[slots].numpy() * 8,
                                     alpha if which == FUSED else None)
        got = engine.mesher.triangles(slots, which, filtered)
        assert len(want.faces) > 0
        for field in ("vertices_vox", "faces", "vertex_values", "vertex_offsets", "face_offsets"):
            np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=f"{which} {field}")


def test_each_alpha_thread_runs_torch_on_one_thread_and_the_worker_setup_and_a_failing_one_leaves_it_working(caplog):
    import threading

    set_up: list[int] = []
    torch_threads: list[int] = []

    def setup() -> None:
        set_up.append(threading.get_native_id())
        torch_threads.append(torch.get_num_threads())
        raise OSError("no permission")

    before = torch.get_num_threads()
    try:  # torch on two threads where the engine runs: new threads would start with two as well
        engine = engine_for_tests(alpha_threads=2, torch_threads=2, worker_setup=setup)
        K, T = SPHERE_K, SPHERE_VIEWS[0]
        depth = render_sphere(SPHERE_C, SPHERE_R, K, T)
        engine.integrate("tof", depth, K, T)
        engine.integrate("stereo", depth, K, T)
        with caplog.at_level("WARNING", logger="senfunet.engine"):
            engine.update(mesh_threads=2)  # no budget: the batches run on the alpha threads
    finally:
        torch.set_num_threads(before)
    alpha_threads = {t.native_id for t in engine.alpha.workers()._threads}
    assert alpha_threads and set(set_up) == alpha_threads
    assert set(torch_threads) == {1}  # each batch on one core: the threads side by side use the others
    assert engine.stats()["meshed_blocks_alpha_current"] == engine.stats()["meshed_blocks"] > 0
    assert "alpha thread set-up failed" in caplog.text and "no permission" in caplog.text


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")
def test_the_alpha_threads_share_the_priority_of_the_thread_that_updates():
    """The alpha threads are started by the thread that first needs them after warm_up (not by the
    one that warmed the engine up), so the live node's idle mesh updates and catch-up, which run on
    them, stay at its mesh thread's low priority: a frame that comes meanwhile goes first."""
    import os
    import threading

    engine = engine_for_tests(alpha_threads=2)
    warm_up(engine)  # from this thread, at its priority
    K, T = SPHERE_K, SPHERE_VIEWS[0]
    depth = render_sphere(SPHERE_C, SPHERE_R, K, T)
    engine.integrate("tof", depth, K, T)
    engine.integrate("stereo", depth, K, T)
    here = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    def lowered_update() -> None:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), min(here + 3, 19))
        engine.update(mesh_threads=2)  # no budget: the batches run on the alpha threads

    worker = threading.Thread(target=lowered_update)
    worker.start()
    worker.join()
    alpha_threads = list(engine.alpha.workers()._threads)  # this engine's (other tests' engines have their own)
    assert alpha_threads and all(t.name.startswith("senfunet-alpha") for t in alpha_threads)
    assert {os.getpriority(os.PRIO_PROCESS, t.native_id) for t in alpha_threads} == {min(here + 3, 19)}


def test_an_eviction_during_an_update_leaves_the_meshed_flags_on_the_blocks_they_describe():
    """An update wrote each meshed block's `meshed` flag (which orders the weighting net's work) at the
    slot the block had when the update began; integration that outgrew the hard bound meanwhile has
    the update evict between batches, which moves blocks into the freed slots: the flags landed on
    other blocks and on slots past the map's end, which the next new blocks inherit."""
    import threading

    K = SPHERE_K
    far = SPHERE_C + [3.0, 0.0, 0.0]
    engine = engine_for_tests(max_blocks=320, mesh_batch_blocks=8, alpha_batch_blocks=8, min_new_block_samples=0)
    for centre, views in ((far, [look_at(far + 0.9 * (T[:3, 3] - SPHERE_C), far) for T in SPHERE_VIEWS[:3]]),
                          (SPHERE_C, SPHERE_VIEWS[:1])):
        integrate_views(engine, [(centre, T) for T in views])
    assert engine.grid.n_blocks <= engine.config.max_blocks  # no eviction when the update starts
    beside = SPHERE_C + [0.0, 1.0, 0.0]
    beside_T = look_at(beside + [0.0, 0.0, 0.9], beside)
    over_hard_bound, block_meshes = engine.bound.over_hard_bound, engine.mesher.block_meshes
    waiting = threading.Event()
    worker = threading.Thread(target=engine.integrate, args=("tof", render_sphere(beside, SPHERE_R, K, beside_T), K,
                                                             beside_T))

    def watched_over_hard_bound() -> bool:
        over = over_hard_bound()
        if over and threading.current_thread() is worker:
            waiting.set()  # the frame is in, and it waits for the update to evict
        return over

    def first_batch_lets_a_frame_in(slots, coords):
        if worker.ident is None:
            worker.start()
            assert waiting.wait(timeout=120)
        return block_meshes(slots, coords)

    engine.bound.over_hard_bound, engine.mesher.block_meshes = watched_over_hard_bound, first_batch_lets_a_frame_in
    engine.update()
    worker.join(timeout=120)
    assert not worker.is_alive() and engine.bound.evictions == 1
    n = engine.grid.n_blocks
    shown = np.isin(engine.grid.slot_keys[:n], engine._meshed)  # the blocks whose live mesh has triangles
    assert shown.sum() > 50
    np.testing.assert_array_equal(engine.store.meshed[:n], shown)
    assert not engine.store.meshed[n:].any()


def test_a_frame_that_fails_after_the_grid_grew_leaves_the_map_usable(monkeypatch):
    """A frame whose integration fails once the grid has grown (memory, a kernel's error) leaves the
    per-block flags as long as the grid: the next update and frame run as before."""
    import senfunet_core.engine as engine_module

    engine = engine_for_tests()
    K, T = SPHERE_K, SPHERE_VIEWS[0]
    engine.integrate("tof", render_sphere(SPHERE_C, SPHERE_R, K, T), K, T)
    capacity = engine.grid.capacity
    integrate_frame = engine_module.integrate_frame

    def grow_then_fail(grid, *args, **kwargs):
        grid.reserve(grid.capacity + 1)  # as a frame that reaches more blocks than the grid holds
        raise MemoryError("test: the frame fails after the grid grew")

    monkeypatch.setattr(engine_module, "integrate_frame", grow_then_fail)
    with pytest.raises(MemoryError):
        engine.integrate("stereo", render_sphere(SPHERE_C, SPHERE_R, K, T), K, T)
    assert engine.grid.capacity > capacity
    assert len(engine.store.stale) == engine.grid.capacity
    monkeypatch.setattr(engine_module, "integrate_frame", integrate_frame)
    engine.update()
    engine.integrate("stereo", render_sphere(SPHERE_C, SPHERE_R, K, T), K, T)
    assert engine.update().changed


def test_a_meshing_budget_leaves_the_rest_due_oldest_first_and_ends_at_the_unbudgeted_mesh(monkeypatch):
    """update(mesh_budget_s=...): each update re-meshes a bounded share, the blocks it leaves go first
    in the next updates (before those changed since), and once none is left the blocks shown equal
    what unbudgeted updates show."""
    import senfunet_core.engine as engine_module

    monkeypatch.setattr(engine_module, "_FIRST_MESH_BLOCKS", 32)
    monkeypatch.setattr(engine_module, "_MIN_MESH_BLOCKS", 16)
    exact, budgeted = engine_for_tests(), engine_for_tests()
    shown_exact: dict = {}
    shown: dict = {}

    def show(into: dict, update) -> None:
        for key in update.removed:
            into.pop(key)
        into.update(update.changed)

    left_before: set = set()
    for T in SPHERE_VIEWS[:3]:
        depth = render_sphere(SPHERE_C, SPHERE_R, SPHERE_K, T)
        for engine in (exact, budgeted):
            engine.integrate("tof", depth, SPHERE_K, T)
            engine.integrate("stereo", depth + 0.004, SPHERE_K, T)
        show(shown_exact, exact.update())
        update = budgeted.update(mesh_budget_s=1e-9)  # the least share: every update makes some progress
        meshed = budgeted.counters["mesh_blocks_last"]
        assert 0 < meshed <= 32 and budgeted.counters["mesh_backlog_blocks"] > 0
        if left_before:  # the blocks earlier updates left, before those this frame changed
            keys = {tuple(key) for key in budgeted.grid.coords[np.flatnonzero(
                budgeted.store.mesh_due[: budgeted.grid.n_blocks])].tolist()}
            if meshed <= len(left_before):
                assert set(update.changed) <= left_before
            else:
                assert not left_before & keys
        left_before = {tuple(key) for key in budgeted.grid.coords[np.flatnonzero(
            budgeted.store.mesh_due[: budgeted.grid.n_blocks])].tolist()}
        show(shown, update)
    assert len(shown) < len(shown_exact)
    for _ in range(1000):
        if not budgeted.counters["mesh_backlog_blocks"]:
            break
        show(shown, budgeted.update(mesh_budget_s=1e-9))
    assert budgeted.counters["mesh_backlog_blocks"] == 0 and not budgeted.store.mesh_due.any()
    assert shown.keys() == shown_exact.keys() and len(shown) > 64
    for key, mesh in shown_exact.items():
        np.testing.assert_array_equal(shown[key].vertices, mesh.vertices)
        np.testing.assert_array_equal(shown[key].faces, mesh.faces)
