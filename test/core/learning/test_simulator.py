"""Tests of the procedural simulator: ground truth consistency, rendering, determinism, sensor realism."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from senfunet_core.learning import geometry, raycast
from senfunet_core.learning import simulator as sim


def _empty_room(seed: int = 0, size=(4.0, 3.0, 2.6)) -> sim.Scene:
    return dataclasses.replace(sim.make_scene(seed, room_size_m=size), primitives=())


def _look(pos, forward) -> np.ndarray:
    """Camera-to-world pose at pos looking along a horizontal direction (optical frame)."""
    z = np.asarray(forward, float) / np.linalg.norm(forward)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, pos
    return T


def _unproject(depth: np.ndarray, K: np.ndarray, T: np.ndarray) -> np.ndarray:
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    m = depth > 0
    z = depth[m].astype(np.float64)
    pc = np.stack([(u[m] - K[0, 2]) / K[0, 0] * z, (v[m] - K[1, 2]) / K[1, 1] * z, z], 1)
    return pc @ T[:3, :3].T + T[:3, 3]


def test_intrinsics():
    K = sim.intrinsics()
    assert K[0, 0] == pytest.approx(128.0) and K[1, 1] == pytest.approx(128.0)
    assert K[0, 2] == pytest.approx(127.5) and K[1, 2] == pytest.approx(127.5)


def test_gt_mesh_agrees_with_sdf():
    scene = sim.make_scene(1)
    voxel = 0.04
    mesh = sim.gt_mesh(scene, voxel)
    assert mesh.n_faces > 1000 and mesh.vertices.dtype == np.float32 and mesh.faces.dtype == np.int32
    assert np.abs(sim.scene_sdf(scene, mesh.vertices)).max() < 0.6 * voxel
    # faces are counter-clockwise seen from free space: the normal points to larger sdf
    v = mesh.vertices.astype(np.float64)
    f = mesh.faces
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    c = v[f].mean(1)
    up = sim.scene_sdf(scene, c + 0.005 * n) - sim.scene_sdf(scene, c - 0.005 * n)
    assert np.mean(up > 0) > 0.95  # thin boards (2 cm < voxel) give a few odd faces
    # every furniture part appears in the mesh: some vertex on each primitive's surface
    for prim in scene.primitives[:5]:
        x, y, z = (mesh.vertices[:, i].astype(np.float64) for i in range(3))
        assert np.abs(geometry._prim_sdf(prim, x, y, z)).min() < 0.6 * voxel


def test_sdf_analytic_distances():
    room = _empty_room(size=(4.0, 3.0, 2.6))
    offsets = np.array([-0.2, -0.05, 0.0, 0.03, 0.3, 1.0])
    wall = np.stack([offsets, np.full(6, 1.5), np.full(6, 1.3)], 1)  # along the normal of wall x = 0
    np.testing.assert_allclose(sim.scene_sdf(room, wall), offsets, atol=1e-6)
    assert np.all(sim.gt_tsdf(room, wall, band_m=0.1) == np.clip(offsets, -0.05, 0.05).astype(np.float32))
    box = sim.Primitive("box", (2.0, 1.5, 0.5), (0.4, 0.3, 0.5), np.pi / 6, 0, 0)
    scene = dataclasses.replace(room, primitives=(box,))
    normal = np.array([np.cos(np.pi / 6), np.sin(np.pi / 6), 0.0])  # local +x face of the yawed box
    face_centre = np.array([2.0, 1.5, 0.5]) + 0.4 * normal
    pts = face_centre + offsets[:5, None] * normal  # (the floor is nearer than 0.5 m beyond)
    np.testing.assert_allclose(sim.scene_sdf(scene, pts), np.clip(offsets[:5], -0.3, None), atol=1e-5)
    sph = sim.Primitive("sphere", (1.0, 1.0, 1.0), (0.25, 0.25, 0.25), 0.0, 0, 0)
    cyl = sim.Primitive("cylinder", (3.0, 2.0, 0.6), (0.2, 0.2, 0.6), 0.0, 0, 0)
    scene = dataclasses.replace(room, primitives=(sph, cyl))
    pts = np.array([[1.0, 1.0, 1.5], [1.0, 1.0, 1.1], [3.5, 2.0, 0.6], [3.0, 2.0, 1.5]])
    np.testing.assert_allclose(sim.scene_sdf(scene, pts), [0.25, -0.15, 0.3, 0.3], atol=1e-6)


@pytest.mark.parametrize("seed", [0, 4])
def test_render_depth_lies_on_surfaces(seed):
    scene = sim.make_scene(seed)
    traj = sim.Trajectory(scene, seed, 0.0, 3.0)
    K = sim.intrinsics(128, 96, 80.0)
    for T in traj(np.array([0.5, 2.5])):
        out = sim.render_view(scene, T, K, 128, 96)
        depth = out["depth_m"]
        assert depth.shape == (96, 128) and depth.dtype == np.float32 and np.all(depth > 0)
        assert out["rgb"].shape == (96, 128, 3) and out["rgb"].dtype == np.uint8
        pts = _unproject(depth, K, T)
        assert np.abs(sim.scene_sdf(scene, pts)).max() < 1e-3
        n = out["normal_cam"]
        np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-4)


def test_render_wall_at_known_distance():
    room = _empty_room(size=(4.0, 3.0, 2.6))
    T = _look([1.25, 1.5, 1.3], [-1, 0, 0])  # wall x = 0 at 1.25 m, fills the 90 deg view
    out = sim.render_view(room, T, sim.intrinsics(), 256, 256)
    np.testing.assert_allclose(out["depth_m"], 1.25, atol=1e-5)
    assert np.all(out["surface_id"] == 2)
    np.testing.assert_allclose(out["normal_cam"][128, 128], [0, 0, -1], atol=1e-5)


def _frames_equal(a: sim.Sequence, b: sim.Sequence) -> bool:
    if len(a.frames) != len(b.frames):
        return False
    for fa, fb in zip(a.frames, b.frames):
        if fa.sensor != fb.sensor or fa.stamp_s != fb.stamp_s or not np.array_equal(fa.depth_m, fb.depth_m):
            return False
        if not np.array_equal(fa.T_world_camera, fb.T_world_camera):
            return False
        if (fa.rgb is None) != (fb.rgb is None) or (fa.rgb is not None and not np.array_equal(fa.rgb, fb.rgb)):
            return False
    return all(np.array_equal(a.pose_T_world_camera[s], b.pose_T_world_camera[s]) for s in sim.SENSORS)


def test_deterministic_per_seed():
    assert sim.make_scene(7) == sim.make_scene(7)
    assert sim.make_scene(7) != sim.make_scene(8)
    kw = {"duration_s": 0.3, "width": 128, "height": 96}
    a = sim.simulate_sequence(sim.make_scene(7), 3, **kw)
    b = sim.simulate_sequence(sim.make_scene(7), 3, **kw)
    assert len(a.frames) > 5 and _frames_equal(a, b)
    c = sim.simulate_sequence(sim.make_scene(7), 4, **kw)
    assert not _frames_equal(a, c)


def _wall_scene(poor: bool) -> sim.Scene:
    room = _empty_room(seed=2, size=(5.0, 4.0, 2.6))
    surfaces = list(room.surfaces)
    surfaces[2] = dataclasses.replace(surfaces[2], texture_poor=poor, contrast=0.003 if poor else 0.3, pattern=0)
    return dataclasses.replace(room, surfaces=tuple(surfaces), light_level=1.0, ambient=0.25,
                               stereo_image_noise=2.0, stereo_uniqueness=10, tof_noise_scale=5.0)


def test_stereo_fails_on_texture_poor_wall_tof_does_not():
    K = sim.intrinsics()
    T = _look([1.5, 2.0, 1.3], [-1, 0, 0])
    bad = {}
    for poor in (False, True):
        scene = _wall_scene(poor)
        depth, rgb = sim.simulate_stereo_depth(scene, T, K, 256, 256, np.random.default_rng(0))
        assert rgb.shape == (256, 256, 3) and rgb.dtype == np.uint8
        roi = depth[40:216, 80:216]  # away from the left border SGBM cannot match
        bad[poor] = np.mean((roi <= 0) | (np.abs(roi - 1.5) > 0.1))
        tof = sim.simulate_tof_depth(scene, T @ raycast._translation(sim.TOF_OFFSET_X_M, 0, 0), K, 256, 256,
                                     np.random.default_rng(0))
        assert np.mean(tof[40:216, 40:216] > 0) > 0.9  # ToF does not care about texture
    assert bad[False] < 0.2, bad
    assert bad[True] > 0.5, bad


def test_tof_error_grows_with_distance():
    scene = _wall_scene(False)
    K = sim.intrinsics()
    std = []
    for dist in (1.0, 2.5, 4.5):
        T = _look([dist, 2.0, 1.3], [-1, 0, 0])
        tof = sim.simulate_tof_depth(scene, T, K, 256, 256, np.random.default_rng(1))
        roi = tof[64:192, 64:192]
        valid = roi > 0
        assert valid.mean() > 0.7  # far away some noisy samples leave the 5 m range
        std.append(np.std(roi[valid] - dist))
    assert std[0] < std[1] < std[2], std
    assert std[2] > 3 * std[0]


def test_stamps_and_pose_streams():
    seq = sim.simulate_sequence(sim.make_scene(3), 1, duration_s=1.0, width=96, height=96)
    tof = np.array([f.stamp_s for f in seq.frames if f.sensor == "tof"])
    st = np.array([f.stamp_s for f in seq.frames if f.sensor == "stereo"])
    assert len(tof) == 15 and len(st) == 20
    assert np.all(np.diff([f.stamp_s for f in seq.frames]) > 0)  # sorted, never equal
    assert np.abs(tof[:, None] - st[None, :]).min() > 0
    frame_stamps = np.concatenate([tof, st])
    for sensor in sim.SENSORS:
        ps = seq.pose_stamps_s[sensor]
        assert ps.min() < frame_stamps.min() and ps.max() > frame_stamps.max()
        assert np.abs(ps[:, None] - frame_stamps[None, :]).min() > 0
        assert np.all(np.diff(ps) > 0)
        assert seq.pose_T_world_camera[sensor].shape == (len(ps), 4, 4)
    # the ToF sits 5 cm to the left (-x) of the stereo left camera on the same rigid device
    f_tof = next(f for f in seq.frames if f.sensor == "tof")
    T_st = sim.Trajectory(seq.scene, 1, -0.1, 1.1)(np.array([f_tof.stamp_s]))[0]
    rel = np.linalg.inv(T_st) @ f_tof.T_world_camera
    np.testing.assert_allclose(rel[:3, 3], [sim.TOF_OFFSET_X_M, 0, 0], atol=1e-9)
    for f in seq.frames:
        assert f.depth_m.dtype == np.float32 and f.depth_m.shape == (96, 96)
        assert (f.rgb is None) == (f.sensor == "tof")


@pytest.mark.parametrize("seed", range(6))
def test_trajectory_is_walkable(seed):
    scene = sim.make_scene(seed)
    T = sim.Trajectory(scene, seed, 0.0, 10.0)(np.arange(0, 10, 1 / 15))
    pos = T[:, :3, 3]
    assert sim.scene_sdf(scene, pos).min() > 0.4
    step = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert step.max() < 0.1
    cos = np.clip((np.einsum("nij,nij->n", T[1:, :3, :3], T[:-1, :3, :3]) - 1) / 2, -1, 1)
    assert np.degrees(np.arccos(cos)).max() < 6.0
    assert np.all(np.abs(pos[:, 2] - 1.5) < 0.25)
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", T[:, :3, :3], T[:, :3, :3]),
                               np.tile(np.eye(3), (len(T), 1, 1)),
                               atol=1e-9)
    assert np.all(T[:, 2, 2] < 0)  # looking slightly down


def test_scenes_vary():
    scenes = [sim.make_scene(s) for s in range(10)]
    for sc in scenes:
        lx, ly, lz = sc.room_size_m
        assert 3 <= lx <= 7 and 3 <= ly <= 6 and 2.4 <= lz <= 3
        assert 4 <= len(sc.item_kinds) <= 12
        assert any(s.texture_poor for s in sc.surfaces)
    assert len({round(s.tof_noise_scale, 3) for s in scenes}) == 10


def test_dataset_round_trip(tmp_path):
    seq = sim.simulate_sequence(sim.make_scene(2), 5, duration_s=0.25, width=96, height=64)
    sim.write_dataset(seq, tmp_path / "ds", gt_voxel_size_m=0.05)
    back = sim.load_dataset(tmp_path / "ds")
    assert back.scene == seq.scene
    assert _frames_equal(seq, back)
    for s in sim.SENSORS:
        np.testing.assert_array_equal(back.pose_stamps_s[s], seq.pose_stamps_s[s])
    for fa, fb in zip(seq.frames, back.frames):
        assert fb.depth_m.dtype == np.float32 and np.array_equal(fa.K, fb.K)
    mesh = np.load(tmp_path / "ds" / "gt_mesh.npz")
    assert mesh["vertices"].shape[1] == 3 and mesh["faces"].dtype == np.int32 and len(mesh["faces"]) > 100


def test_gt_tsdf_fast_paths_equal_the_clipped_sdf():
    scene = sim.make_scene(4)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.3, 1.1, (20000, 3)) * np.asarray(scene.room_size_m)
    np.testing.assert_array_equal(sim.gt_tsdf(scene, pts, 0.1), np.clip(sim.scene_sdf(scene, pts), -0.05, 0.05))
    blocks = rng.integers(-2, 70, (300, 3))
    r = np.arange(8)
    local = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    centres = ((blocks[:, None, :] * 8 + local[None]) * 0.01).reshape(-1, 3)
    np.testing.assert_allclose(sim.gt_tsdf_blocks(scene, blocks, 0.01, 0.1).reshape(-1),
                               sim.gt_tsdf(scene, centres, 0.1), atol=1e-6)
    # the GT TSDF crosses zero on the GT mesh
    mesh = sim.gt_mesh(scene, 0.02)
    assert np.abs(sim.gt_tsdf(scene, mesh.vertices, 0.1)).max() < 0.6 * 0.02


def _tof_errors(scene, T, rows, cols):
    K = sim.intrinsics()
    truth = sim.render_view(scene, T, K, 256, 256, with_rgb=False)["depth_m"][rows, cols]
    errs = []
    for seed in range(4):
        tof = sim.simulate_tof_depth(scene, T, K, 256, 256, np.random.default_rng(seed))[rows, cols]
        errs.append(np.where(tof > 0, tof - truth, np.nan))
    return np.concatenate([e.ravel() for e in errs])


def test_tof_dark_materials_are_noisier_and_corners_read_too_far():
    T = _look([2.0, 2.0, 1.3], [-1, 0, 0])  # wall x = 0 at 2 m; the floor corner in the lower image rows
    base = dataclasses.replace(_wall_scene(False), tof_multipath_m=0.0, tof_min_signal=0.0, tof_speckle_fraction=0.0)
    surfaces = list(base.surfaces)
    centre = (slice(100, 156), slice(100, 156))
    errs = {}
    for name, reflectivity in (("bright", 0.8), ("dark", 0.05)):
        surfaces[2] = dataclasses.replace(surfaces[2], ir_reflectivity=reflectivity)
        errs[name] = _tof_errors(dataclasses.replace(base, surfaces=tuple(surfaces)), T, *centre)
    assert np.nanstd(errs["dark"]) > 2.5 * np.nanstd(errs["bright"]), {k: np.nanstd(v) for k, v in errs.items()}
    # multipath: near the wall-floor corner the ToF reads too far, in the middle of the wall it does not
    surfaces[2] = dataclasses.replace(surfaces[2], ir_reflectivity=0.8)
    quiet = dataclasses.replace(base, surfaces=tuple(surfaces), tof_noise_scale=0.3, tof_shuffle_px=0.0,
                                tof_flying_fraction=0.0, tof_multipath_m=0.05)
    K = sim.intrinsics()
    view = sim.render_view(quiet, T, K, 256, 256, with_rgb=False, with_other_distance=True)
    near_corner = (view["surface_id"] == 2) & (view["other_distance_m"] < 0.03)
    far_from_all = (view["surface_id"] == 2) & (view["other_distance_m"] > 0.45)
    assert near_corner.sum() > 100 and far_from_all.sum() > 1000
    tof = sim.simulate_tof_depth(quiet, T, K, 256, 256, np.random.default_rng(0))
    err = np.where(tof > 0, tof - view["depth_m"], np.nan)
    assert np.nanmean(err[near_corner]) > 0.03 and abs(np.nanmean(err[far_from_all])) < 0.01
    # a weak return (dark and far) is dropped
    weak = dataclasses.replace(quiet, tof_min_signal=0.01)
    surfaces[2] = dataclasses.replace(surfaces[2], ir_reflectivity=0.03)
    weak = dataclasses.replace(weak, surfaces=tuple(surfaces))
    assert np.mean(sim.simulate_tof_depth(weak, T, K, 256, 256, np.random.default_rng(0))[centre] > 0) < 0.05


def test_sites_vary_in_texture_infrared_and_multipath():
    scenes = [sim.make_scene(s) for s in range(12)]
    dark = [sum(s.ir_reflectivity < 0.15 for s in sc.surfaces) for sc in scenes]
    assert min(dark) == 0 and max(dark) >= 3
    assert all(sc.surfaces[k].ir_reflectivity >= 0.45 for sc in scenes for k in range(1, 6))  # walls, ceiling
    multipath = [sc.tof_multipath_m for sc in scenes]
    assert min(multipath) < 0.01 and max(multipath) > 0.03
    contrast = [np.mean([s.contrast for s in sc.surfaces if not s.texture_poor]) for sc in scenes]
    assert max(contrast) > 1.8 * min(contrast)
