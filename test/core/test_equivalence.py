"""The engine's shortcuts against the straightforward computation.

The straightforward computation is `EngineConfig(alpha_voxels="all")`: the weighting net
re-evaluated on every block within 2 voxels of any change (which equals the whole-grid
evaluation, see test_engine.py). The shortcuts:
- alpha_voxels="surface": only blocks holding corners of cells that can hold fused triangles ->
  identical fused mesh (vertices, faces, colours), stale alpha elsewhere;
- bfloat16 arithmetic in the nets, int8 in the weighting net -> a fused mesh close to the exact one
  (`assert_close_to_exact`).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from senfunet_core.engine import EngineConfig, SenFuNet
from senfunet_core.alpha_evaluator import surface_windows
from senfunet_core.grid import decode_alpha, decode_features
from senfunet_core.weighting_int8 import Int8Calibration, Int8WeightingNet, calibrate, input_ranges, int8_available

VOXEL = 0.01
SIZE = 96
K = np.array([[60.0, 0, (SIZE - 1) / 2], [0, 60.0, (SIZE - 1) / 2], [0, 0, 1.0]])
CENTRE = np.array([0.0, 0.0, 0.0])
RADIUS = 0.3
FLOOR_Z = -0.3


def look_at(eye, target, up=(0, 0, 1)) -> np.ndarray:
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def render(T: np.ndarray) -> np.ndarray:
    """z-depth of a sphere standing on a floor plane."""
    v, u = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1) @ T[:3, :3].T
    o = T[:3, 3]
    oc = o - CENTRE
    a, b, c = (d * d).sum(-1), 2 * (d @ oc), oc @ oc - RADIUS ** 2
    disc = b * b - 4 * a * c
    t_sphere = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    t_floor = np.where(d[..., 2] < -1e-6, (FLOOR_Z - o[2]) / np.where(d[..., 2] < -1e-6, d[..., 2], -1), np.inf)
    t = np.minimum(t_sphere, t_floor)
    return np.where(np.isfinite(t), t, 0).astype(np.float32)


def frames(n: int = 6):
    """Both sensors from views around the object: sensor 2 noisier and with outliers, so alpha and
    the filter matter."""
    rng = np.random.default_rng(7)
    out = []
    for i in range(n):
        angle = 2 * math.pi * i / n
        T = look_at((1.0 * math.cos(angle), 1.0 * math.sin(angle), 0.5), CENTRE)
        depth = render(T)
        tof = depth + rng.normal(0, 0.002, depth.shape).astype(np.float32) * (depth > 0)
        stereo = depth + rng.normal(0, 0.006, depth.shape).astype(np.float32) * (depth > 0)
        outliers = rng.random(depth.shape) < 0.02
        stereo[outliers] *= rng.uniform(0.7, 1.3, int(outliers.sum())).astype(np.float32)
        rgb = rng.integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8)
        out += [("tof", tof, None, T), ("stereo", stereo, rgb, T)]
    return out


def run(int8: Int8Calibration | None = None, **overrides):
    """The engine after the frames, with updates as the node runs them; `int8`: G in int8 with this
    calibration (of these weights)."""
    config = replace(EngineConfig(depth_min_m=(0.05, 0.05), depth_max_m=(1.5, 1.5), border_px=2), **overrides)
    engine = SenFuNet(config, weights=None)
    with torch.no_grad():  # larger weights than the default init: alpha spreads around 0.5, the filter acts
        for p in engine.weighting_net.parameters():
            p.mul_(3.0)
    if int8 is not None:
        engine.alpha.evaluator.int8_net = Int8WeightingNet(engine.weighting_net, int8,
                                                           input_ranges(engine.weighting_net, config.depth_max_m))
    shown = {}
    for i, (sensor, depth, rgb, T) in enumerate(frames()):
        engine.integrate(sensor, depth, K, T, rgb)
        if i % 3 == 2:  # incremental updates, as the node runs them
            update = engine.update()
            for key in update.removed:
                shown.pop(key, None)
            shown.update(update.changed)
    update = engine.update()
    for key in update.removed:
        shown.pop(key, None)
    shown.update(update.changed)
    return engine, shown


@pytest.fixture(scope="module")
def exact():
    return run(alpha_voxels="all")


@pytest.fixture(scope="module")
def surface():
    return run(alpha_voxels="surface")


def sorted_mesh(mesh):
    """Vertices (with colours) and faces in a canonical order, to compare meshes exactly."""
    order = np.lexsort(mesh.vertices.T[::-1])
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    faces = np.sort(rank[mesh.faces], axis=1)
    faces = faces[np.lexsort(faces.T[::-1])]
    return mesh.vertices[order], mesh.colors[order], faces


@pytest.mark.parametrize("mode", ["surface", "surface_voxels"])
def test_surface_mode_gives_the_exact_fused_mesh(exact, surface, mode):
    engine, shown = surface if mode == "surface" else run(alpha_voxels=mode)
    ref, ref_shown = exact
    a, b = sorted_mesh(engine.extract_mesh("fused")), sorted_mesh(ref.extract_mesh("fused"))
    assert len(b[2]) > 2000
    np.testing.assert_array_equal(a[2], b[2])  # same triangles
    # "surface" evaluates the same convolutions on the same stored inputs: the same alpha bits.
    # "surface_voxels" sums in another order (gathered products): an alpha within float32 rounding of
    # the block convolution's can round to the neighbouring 8-bit code in the grid, one step (1/254)
    # of alpha (and of a vertex colour), which moves a vertex by that times the sensors' TSDF difference.
    vertex_atol, colour_atol = (1e-6, 1e-4) if mode == "surface" else (1e-5, 1.5 / 254)
    np.testing.assert_allclose(a[0], b[0], atol=vertex_atol)  # same vertices
    np.testing.assert_allclose(a[1], b[1], atol=colour_atol)  # same colours (alpha at the vertices)
    # the incremental block meshes (what the node publishes) are the same too
    assert set(shown) == set(ref_shown)
    for key, mesh in ref_shown.items():
        assert mesh.n_faces == shown[key].n_faces
    # far less work (the allocation policy keeps most of the blocks without surface out of both maps)
    assert engine.counters["alpha_voxels"] < 0.6 * ref.counters["alpha_voxels"]


def test_alpha_threads_evaluate_the_same_alpha():
    """Updates without a time budget evaluate several batches at once (alpha_threads): every voxel's
    alpha, what was evaluated and the fused mesh are the same, bit for bit, as one batch at a time."""
    one, _ = run(alpha_voxels="surface", alpha_batch_blocks=4)
    several, _ = run(alpha_voxels="surface", alpha_batch_blocks=4, alpha_threads=3)
    n = one.grid.n_blocks
    assert several.grid.n_blocks == n
    alpha_one, alpha_several = (decode_alpha(engine.grid.pools["alpha"][:n]) for engine in (one, several))
    assert alpha_one.isfinite().sum() > 10_000
    torch.testing.assert_close(alpha_several, alpha_one, rtol=0, atol=0, equal_nan=True)
    for counter in ("alpha_blocks", "alpha_voxels", "alpha_flops"):
        assert several.counters[counter] == one.counters[counter] > 0
    a, b = sorted_mesh(several.extract_mesh("fused")), sorted_mesh(one.extract_mesh("fused"))
    np.testing.assert_array_equal(a[2], b[2])
    np.testing.assert_array_equal(a[0], b[0])


def assert_close_to_exact(engine, ref, *, within_voxel: float = 0.995) -> None:
    """Every vertex of either fused mesh lies within 1 mm of the other's for >= 99% of them and
    within 1 voxel for a share `within_voxel` of them; the face counts differ by at most 1%."""
    mesh, ref_mesh = engine.extract_mesh("fused"), ref.extract_mesh("fused")
    assert ref_mesh.n_faces > 2000
    d1, _ = cKDTree(ref_mesh.vertices).query(mesh.vertices)
    d2, _ = cKDTree(mesh.vertices).query(ref_mesh.vertices)
    d = np.concatenate([d1, d2])
    assert np.mean(d <= 0.001) >= 0.99
    assert np.mean(d <= VOXEL) >= within_voxel
    assert abs(mesh.n_faces - ref_mesh.n_faces) <= 0.01 * ref_mesh.n_faces


def test_bfloat16_alpha_keeps_the_mesh_close(exact, surface):
    """alpha_dtype="bfloat16" (the node's choice on CPUs with bfloat16 instructions): alpha within
    0.02 of float32 and the fused mesh close to the exact one."""
    # on both cores: batches in threads give the same alpha (test_alpha_threads_evaluate_the_same_alpha),
    # and a CPU without bfloat16 instructions emulates them slowly
    engine, _ = run(alpha_voxels="surface", alpha_dtype="bfloat16", alpha_threads=2)
    same_schedule = surface[0]
    n = engine.grid.n_blocks
    alpha, same_alpha = (decode_alpha(e.grid.pools["alpha"][:n]) for e in (engine, same_schedule))
    evaluated = torch.isfinite(alpha)  # surface mode: blocks that can hold triangles
    diff = (alpha - same_alpha).abs()[evaluated]
    assert len(diff) > 10_000 and 0 < float(diff.max()) < 0.02  # not float32 arithmetic, but close to it
    assert_close_to_exact(engine, exact[0])


@pytest.mark.skipif(not int8_available(), reason="this torch or CPU has no oneDNN int8 convolutions")
def test_int8_alpha_keeps_the_mesh_close(exact, surface):
    """alpha_dtype="int8" (the node's choice on CPUs without bfloat16 instructions), calibrated on the
    same scene: alpha close to float32's and the fused mesh close to the exact one, a little less
    than bfloat16's on this scene of steep weights (3x the initial ones) and 2% outliers: all but 1%
    of the vertices within a voxel (where the outlier filter's threshold falls the other way)."""
    ref = exact[0]
    calibration = calibrate(ref.weighting_net, surface_windows(ref.alpha.evaluator), weights_sha256="",
                            calibrated_on="test")
    engine, _ = run(int8=calibration, alpha_voxels="surface")
    n = engine.grid.n_blocks
    alpha, same_alpha = (decode_alpha(e.grid.pools["alpha"][:n]) for e in (engine, surface[0]))
    evaluated = torch.isfinite(alpha)
    diff = (alpha - same_alpha).abs()[evaluated]
    assert len(diff) > 10_000 and 0 < float(diff.mean()) < 0.02  # 8-bit arithmetic, close to float32's
    assert_close_to_exact(engine, ref, within_voxel=0.99)


def test_bfloat16_features_keep_the_mesh_close(exact):
    """feature_dtype="bfloat16" (the node's choice on CPUs with bfloat16 instructions): the fused
    features differ from float32's, but little, and the fused mesh is close to the exact one."""
    engine, _ = run(alpha_voxels="all", feature_dtype="bfloat16")
    ref = exact[0]
    n = engine.grid.n_blocks
    assert ref.grid.n_blocks == n
    for s in range(2):
        observed = engine.grid.pools[f"weight{s}"][:n] > 0
        ours, exact_features = (decode_features(e.grid.pools[f"feat{s}"][:n]) for e in (engine, ref))
        diff = (ours - exact_features).abs()[observed]
        assert observed.sum() > 10_000 and 0 < float(diff.max()) and float(diff.mean()) < 0.01
    assert_close_to_exact(engine, ref)
