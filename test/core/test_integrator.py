"""The compiled integration (engine path) against the reference tensor functions (training path)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from senfunet_core.grid import BLOCK, BlockGrid
from senfunet_core.integrator import (IntegratorConfig, aggregate_pixel_values, frame_samples, integrate_frame,
                                      locate_frame_samples, valid_depth_mask)
from senfunet_core.learning.training import keys_to_voxels

SIZE = 64
K = np.array([[40.0, 0, (SIZE - 1) / 2], [0, 40.0, (SIZE - 1) / 2], [0, 0, 1.0]])
CONFIG = IntegratorConfig(voxel_size_m=0.01, border_px=4)
RANGE = (0.1, 5.0)


def pose(yaw: float, x: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    T[:3, 3] = (x, 0.02, -0.5)
    return T


def frame(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A tilted, bumpy wall ~1 m away with invalid pixels, and 5 feature channels."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:SIZE, 0:SIZE].astype(np.float32)
    depth = 1.0 + 0.004 * u + 0.05 * np.sin(v / 5.0) + rng.normal(0, 0.005, (SIZE, SIZE))
    depth = depth.astype(np.float32)
    depth[rng.random((SIZE, SIZE)) < 0.05] = 0.0
    depth[3, 7] = np.nan
    features = rng.standard_normal((5, SIZE, SIZE)).astype(np.float32)
    return depth, features


def reference(frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> dict[tuple, tuple]:
    """Running averages per voxel with the reference functions: voxel -> (tsdf, weight, features)."""
    state: dict[tuple, list] = {}
    for depth, features, T in frames:
        d = torch.nan_to_num(torch.from_numpy(depth))
        valid = valid_depth_mask(d, CONFIG.border_px, *RANGE)
        samples = frame_samples(d, valid, torch.from_numpy(K), torch.from_numpy(T), CONFIG)
        pixel = torch.from_numpy(features).flatten(1)[:, samples.pixel_index].T
        voxel_features = aggregate_pixel_values(samples, pixel).numpy()
        for voxel, tsdf, f in zip(map(tuple, keys_to_voxels(samples.keys).tolist()), samples.tsdf_m.numpy(),
                                  voxel_features):
            old = state.setdefault(voxel, [0.0, 0.0, np.zeros(5)])
            w = old[1]
            old[0] = (w * old[0] + tsdf) / (w + 1)
            old[2] = (w * old[2] + f) / (w + 1)
            old[1] = w + 1
    return state


def compiled(frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> tuple[BlockGrid, dict[tuple, tuple]]:
    channels = {"tsdf_base": (), "weight_base": (), "tsdf0": (), "weight0": (), "feat0": (5,)}
    dtypes = {name: torch.float16 for name in channels if name.startswith(("feat", "weight"))}
    grid = BlockGrid(channels, initial_capacity=64, dtypes=dtypes)  # small: growth happens mid-frame
    for depth, features, T in frames:
        integrate_frame(grid, np.nan_to_num(depth), features, K, T, RANGE, CONFIG, ("tsdf0", "weight0", "feat0"))
    n = grid.n_blocks
    r = torch.arange(BLOCK)
    local = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(1, -1, 3)
    voxels = (grid.coords[:n].unsqueeze(1) * BLOCK + local).reshape(-1, 3)
    weight = grid.pools["weight0"][:n].reshape(-1).float()
    seen = weight > 0
    values = zip(map(tuple, voxels[seen].tolist()), grid.pools["tsdf0"][:n].reshape(-1)[seen].tolist(),
                 weight[seen].tolist(), grid.pools["feat0"][:n].reshape(-1, 5)[seen].float().numpy())
    return grid, {v: (t, w, f) for v, t, w, f in values}


def test_compiled_integration_equals_the_reference():
    frames = [(*frame(i), pose(0.05 * i, 0.03 * i)) for i in range(3)]
    want = reference(frames)
    grid, got = compiled(frames)
    assert len(want) > 20_000
    common = want.keys() & got.keys()
    # the same voxels, up to rounding ties at a voxel boundary (float64 in both, summed in another order)
    assert len(common) >= 0.999 * max(len(want), len(got))
    tsdf_error = max(abs(got[v][0] - want[v][0]) for v in common)
    assert tsdf_error < 1e-6
    assert all(got[v][1] == want[v][1] for v in common)
    features_error = max(np.abs(got[v][2] - want[v][2]).max() for v in common)
    assert features_error < 2e-3  # float16 storage, rounded once per frame
    # the TSDF Fusion baseline saw the same (single-sensor) frames
    n = grid.n_blocks
    np.testing.assert_array_equal(grid.pools["weight_base"][:n].numpy(), grid.pools["weight0"][:n].numpy())
    np.testing.assert_allclose(grid.pools["tsdf_base"][:n].numpy(), grid.pools["tsdf0"][:n].numpy(), atol=1e-6)


def test_a_full_hash_table_grows_with_the_blocks_not_with_the_pools(monkeypatch):
    """A frame that fills the hash table mid-frame grows it to fit the blocks (a small table stays in
    cache), not to the pools' capacity, which is large and costs nothing until used."""
    import senfunet_core.grid as grid_module

    monkeypatch.setattr(grid_module, "_INITIAL_TABLE", 16)  # full after 8 blocks, early in the frame
    grid = BlockGrid({"tsdf0": (), "weight0": (), "feat0": (5,)}, initial_capacity=1 << 15)
    depth, features = frame(0)
    integrate_frame(grid, np.nan_to_num(depth), features, K, pose(0.0, 0.0), RANGE, CONFIG,
                    ("tsdf0", "weight0", "feat0"))
    assert grid.n_blocks > 8 and grid.capacity == 1 << 15
    assert len(grid.hash_table.keys) <= 4 * (grid.n_blocks + 1024)
    assert (grid.lookup_keys(torch.from_numpy(grid.slot_keys[:grid.n_blocks])).numpy()
            == np.arange(grid.n_blocks)).all()


def expected_reach(voxels: np.ndarray) -> int:
    """Bits of the neighbour blocks (code 9 (dx+1) + 3 (dy+1) + dz+1) with a voxel within 2 of one
    of these local voxel indices, by distance: per axis, from the voxel to that block's 8 voxels."""
    bits = 0
    for local in voxels.tolist():
        xyz = (local >> 6, (local >> 3) & 7, local & 7)
        for code in range(27):
            d = (code // 9 - 1, (code // 3) % 3 - 1, code % 3 - 1)
            gap = [max(8 * di - c, c - (8 * di + 7), 0) for di, c in zip(d, xyz)]
            if max(gap) <= 2:
                bits |= 1 << code
    return bits


def test_reach_names_the_blocks_around_changed_and_new_voxels():
    """Per touched block, integration reports the blocks within 2 voxels (the weighting net's reach)
    of its voxels first observed or whose TSDF changed sign ([1]), and of the others it changed ([0])."""
    depth, features = frame(0)
    T = pose(0.0, 0.0)
    grid = BlockGrid({"tsdf0": (), "weight0": (), "feat0": (5,)}, initial_capacity=1 << 12,
                     dtypes={"weight0": torch.float16, "feat0": torch.float16})
    checked = 0
    for scale in (1.0, 0.5):  # the first frame observes every voxel anew; the second moves the features
        before = {name: grid.pools[name].clone() for name in grid.pools}
        update = integrate_frame(grid, depth, features * scale, K, T, RANGE, CONFIG, ("tsdf0", "weight0", "feat0"))
        for slot, (changed, renewed) in zip(update.touched_slots.tolist(), update.reach.tolist()):
            old_w, new_w = before["weight0"][slot].float(), grid.pools["weight0"][slot].float()
            old_t, new_t = before["tsdf0"][slot], grid.pools["tsdf0"][slot]
            new = ((old_w == 0) & (new_w > 0)) | ((old_w > 0) & ((old_t < 0) != (new_t < 0)))
            moved = (old_w != new_w) | (old_t != new_t) | (before["feat0"][slot] != grid.pools["feat0"][slot]).any(-1)
            assert renewed == expected_reach(np.flatnonzero(new.numpy()))
            assert changed == expected_reach(np.flatnonzero((moved & ~new).numpy()))
            checked += changed != 0
    assert checked > 20  # the second frame changed voxels in many blocks


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_clean_depth_equals_the_reference_mask(dtype):
    """prepare's one pass: the depth with NaN and inf at 0, and the deepest pixel the reference mask
    (`valid_depth_mask`) keeps, on frames with invalid values, values at the range's ends and a border."""
    from senfunet_core.integrator import clean_depth

    rng = np.random.default_rng(3)
    for trial in range(20):
        depth = rng.uniform(-1.0, 8.0, (24, 31)).astype(dtype)
        depth[rng.random(depth.shape) < 0.1] = np.nan
        depth[rng.random(depth.shape) < 0.05] = np.inf
        depth[rng.random(depth.shape) < 0.05] = RANGE[1]
        if trial % 5 == 0:  # nothing valid
            depth[:] = RANGE[1] + 1.0
        clean, deepest = clean_depth(depth, CONFIG.border_px, *RANGE)
        want = torch.nan_to_num(torch.from_numpy(depth.astype(np.float32)), nan=0.0, posinf=0.0, neginf=0.0)
        valid = valid_depth_mask(want, CONFIG.border_px, *RANGE)
        np.testing.assert_array_equal(clean, want.numpy())
        assert deepest == (float(want[valid].max()) if bool(valid.any()) else -1.0)


def test_splitting_a_frame_between_two_threads_changes_no_bit(monkeypatch):
    import senfunet_core.integrator as integrator

    frames = [(*frame(i), pose(0.05 * i, 0.03 * i)) for i in range(3)]
    monkeypatch.setattr(integrator, "SPLIT_MIN_SAMPLES", 10 ** 9)
    whole, _ = compiled(frames)
    monkeypatch.setattr(integrator, "SPLIT_MIN_SAMPLES", 0)
    split, _ = compiled(frames)
    n = whole.n_blocks
    assert n == split.n_blocks and n > 50
    for name, pool in whole.pools.items():  # no NaN in these pools: equal values are equal bits
        assert torch.equal(pool[:n], split.pools[name][:n]), name


def flying_pixel_frame(seed: int) -> np.ndarray:
    """A wall ~1 m away over the left half of the image; on the right half, isolated pixels far
    away at random depths (flying pixels), every other pixel invalid."""
    rng = np.random.default_rng(seed)
    depth = np.zeros((SIZE, SIZE), np.float32)
    depth[:, : SIZE // 2] = 1.0 + rng.normal(0, 0.002, (SIZE, SIZE // 2))
    v, u = np.nonzero(rng.random((SIZE, SIZE // 2)) < 0.04)
    depth[v, u + SIZE // 2] = rng.uniform(2.0, 4.5, len(v))
    return depth


def samples_per_block(depth: np.ndarray, T: np.ndarray) -> dict[tuple, int]:
    """Block -> how many of the frame's ray samples fall in it (located on a fresh grid, no policy)."""
    grid = BlockGrid({"a": ()}, initial_capacity=64)
    offsets_m = CONFIG.sample_offsets().numpy().astype(np.float64) * CONFIG.step_m
    located = locate_frame_samples(grid, depth, K, T, depth_range_m=RANGE, border_px=CONFIG.border_px,
                                   offsets_m=offsets_m, voxel_size_m=CONFIG.voxel_size_m)
    counts = np.bincount(located.sample_touched[: located.n_pixels * len(offsets_m)], minlength=located.n_touched)
    coords = grid.coords[torch.from_numpy(located.touched_slots[: located.n_touched])]
    return dict(zip(map(tuple, coords.tolist()), counts.tolist()))


def test_allocation_policy_keeps_flying_pixels_out_of_new_blocks_and_counts_them():
    depth, T = flying_pixel_frame(0), pose(0.0, 0.0)
    counts = samples_per_block(depth, T)
    features = np.ones((5, SIZE, SIZE), np.float32)
    minimum = 40
    dense = {block for block, n in counts.items() if n >= minimum}
    sparse = {block: n for block, n in counts.items() if n < minimum}
    assert len(dense) > 10 and len(sparse) > 20  # the frame has both, or the test proves nothing
    channels = {"tsdf0": (), "weight0": (), "feat0": (5,)}
    dtypes = {"weight0": torch.float16, "feat0": torch.float16}
    every = BlockGrid(channels, initial_capacity=1 << 12, dtypes=dtypes)
    integrate_frame(every, depth, features, K, T, RANGE, CONFIG, ("tsdf0", "weight0", "feat0"))
    policy = replace(CONFIG, min_new_block_samples=minimum)
    grid = BlockGrid(channels, initial_capacity=64, dtypes=dtypes)  # small: grows mid-frame, before the policy
    update = integrate_frame(grid, depth, features, K, T, RANGE, policy, ("tsdf0", "weight0", "feat0"))
    assert {tuple(c) for c in grid.coords[: grid.n_blocks].tolist()} == dense
    assert update.dropped_blocks == len(sparse)
    assert update.dropped_samples == sum(sparse.values())
    assert sorted(update.touched_slots.tolist()) == list(range(grid.n_blocks))
    # the kept blocks took every one of their samples: the same voxels as without the policy
    slots = every.lookup(grid.coords[: grid.n_blocks])
    for name in ("tsdf0", "weight0", "feat0"):
        assert torch.equal(grid.pools[name][: grid.n_blocks], every.pools[name][slots]), name
    # a later frame's few samples: those in blocks that exist are all taken, the rest follow the policy
    sparse_again = np.zeros_like(depth)
    sparse_again[::9, : SIZE // 2 : 9] = depth[::9, : SIZE // 2 : 9]
    counts = samples_per_block(sparse_again, T)
    few_in_existing = [block for block, n in counts.items() if block in dense and n < minimum]
    assert len(few_in_existing) > 5
    slots = grid.lookup(torch.tensor(few_in_existing))
    before = grid.pools["weight0"][slots].float().sum(dim=1)
    total_before = grid.pools["weight0"][: grid.n_blocks].float().sum()
    update = integrate_frame(grid, sparse_again, features, K, T, RANGE, policy, ("tsdf0", "weight0", "feat0"))
    assert update.dropped_samples == sum(n for block, n in counts.items() if block not in dense and n < minimum)
    assert bool((grid.pools["weight0"][slots].float().sum(dim=1) > before).all())
    assert float(grid.pools["weight0"][: grid.n_blocks].float().sum() - total_before) == update.voxels_updated


def test_a_frame_outside_the_key_range_is_refused_from_its_first_sample():
    """Samples beyond the grid's key range (the engine checks poses before, this is the kernel's own
    guard): InputError and nothing allocated, even when the very first sample is out of range."""
    import pytest

    from senfunet_core.errors import InputError

    depth, _ = frame(0)
    T = pose(0.0, 0.0)
    T[:3, 3] = (60_000.0, 0.0, 0.0)  # far beyond the key range (+-5 km at 1 cm voxels)
    grid = BlockGrid({"weight0": ()}, initial_capacity=64)
    with pytest.raises(InputError, match="5 km"):
        locate_frame_samples(grid, np.nan_to_num(depth), K, T, depth_range_m=RANGE, border_px=CONFIG.border_px,
                             offsets_m=CONFIG.sample_offsets().numpy().astype(np.float64) * CONFIG.step_m,
                             voxel_size_m=CONFIG.voxel_size_m)
    assert grid.n_blocks == 0


def test_spilled_blocks_seen_by_a_frame_that_outgrows_the_grid_come_back_with_their_voxels():
    """A frame that fills the grid mid-frame grows it with the blocks it added still uncommitted: the
    allocation policy then judges them all, spilled blocks among them still on disk (kept, and given
    their voxels back at the commit). The same frames on a grid large enough not to grow give the
    same blocks and voxels (committing mid-frame lost sparsely seen spilled blocks and gave moved
    ones another block's rows)."""
    from senfunet_core.block_store import BlockStore
    from senfunet_core.spill import BlockSpill

    size = 160
    intrinsics = np.array([[80.0, 0, (size - 1) / 2], [0, 80.0, (size - 1) / 2], [0, 0, 1.0]])
    v, u = np.mgrid[0:size, 0:size].astype(np.float32)
    wall = (1.0 + 0.002 * u + 0.03 * np.sin(v / 7.0)).astype(np.float32)
    top = np.where(v < 40, wall, 0.0).astype(np.float32)  # the first frame: the top rows
    second = wall.copy()  # the whole wall, with flying pixels, the top rows seen sparsely
    rng = np.random.default_rng(1)
    flying = rng.random((size, size)) < 0.03
    second[flying] -= rng.uniform(0.1, 0.3, int(flying.sum())).astype(np.float32)
    second[4:40:3, :] = 0.0
    features = np.ones((size * size, 5), np.float32)
    policy = replace(CONFIG, min_new_block_samples=16)
    channels = ("tsdf0", "weight0", "feat0")

    def run(capacity: int) -> tuple[dict[int, np.ndarray], int]:
        grid = BlockGrid({"tsdf0": (), "weight0": (), "feat0": (5,)}, initial_capacity=capacity,
                         dtypes={"weight0": torch.float16, "feat0": torch.float16})
        grid.spill = BlockSpill()
        store = BlockStore(grid)
        integrate_frame(grid, top, features, intrinsics, np.eye(4), RANGE, policy, channels)
        store.grow_flags()
        store.remove(np.arange(grid.n_blocks))  # every block to the spill
        if capacity > 1 << 12:
            grid.reserve(1 << 14)  # room for the second frame: no growth during it
        capacity_before = grid.capacity
        update = integrate_frame(grid, second, features, intrinsics, np.eye(4), RANGE, policy, channels)
        assert update.dropped_blocks > 100 and len(grid.spill) == 0
        grew = grid.capacity > capacity_before
        return {int(k): grid.pools["weight0"][s].numpy().copy()
                for s, k in enumerate(grid.slot_keys[: grid.n_blocks])}, grew

    without_growth, grew = run(1 << 16)
    assert not grew
    with_growth, grew = run(64)
    assert grew
    assert with_growth.keys() == without_growth.keys()
    assert all(np.array_equal(with_growth[k], without_growth[k]) for k in without_growth)


@pytest.mark.parametrize("voxel_size_m, band_m", [(0.01, 0.1), (0.005, 0.1), (0.002, 0.1), (0.05, 0.1), (0.01, 0.3)])
def test_samples_along_the_band_are_at_most_a_voxel_apart(voxel_size_m: float, band_m: float):
    """The paper's 11 samples (3 written behind) where they are a voxel apart or closer; more, the same
    share behind the surface, where they would skip voxels."""
    from senfunet_core.integrator import samples_along_band

    n_samples, behind = samples_along_band(voxel_size_m, band_m)
    config = IntegratorConfig(voxel_size_m, band_m, n_samples, behind)
    assert config.step_m <= voxel_size_m * (1 + 1e-9)
    assert n_samples >= 11 and n_samples % 2 == 1 and 0 < behind <= (n_samples - 1) // 2
    assert behind / ((n_samples - 1) // 2) == pytest.approx(0.6, abs=0.05)
    if band_m / 10 <= voxel_size_m:
        assert (n_samples, behind) == (11, 3)


@pytest.mark.parametrize("voxel_size_m", [0.01, 0.005, 0.0025])
def test_the_allocation_threshold_keeps_lone_rays_out_and_surfaces_in_at_fine_voxels(voxel_size_m: float):
    """min_new_block_samples (16) was chosen at 1 cm voxels, where one ray writes at most 9 samples. Finer
    voxels take more samples along the band (samples_along_band: 17 written at 5 mm, 33 at 2.5 mm), but
    samples a voxel apart cross a block (8 voxels) along at most 8 * sqrt(3) ~ 13.9 voxels: a lone ray
    (a flying pixel), even along a block's diagonal, still allocates no block, and a surface whose pixels
    lie up to 3 voxels apart keeps its blocks. The threshold means the same at these voxel sizes."""
    from senfunet_core.integrator import samples_along_band

    n_samples, behind = samples_along_band(voxel_size_m, 0.1)
    config = IntegratorConfig(voxel_size_m, 0.1, n_samples, behind, border_px=0, min_new_block_samples=16)
    assert (n_samples - 1) // 2 + behind + 1 >= (9 if voxel_size_m == 0.01 else 17)
    channels = ("tsdf0", "weight0", "feat0")

    def blocks(depth: np.ndarray, intrinsics: np.ndarray, T: np.ndarray) -> set[tuple[int, ...]]:
        grid = BlockGrid({"tsdf0": (), "weight0": (), "feat0": (5,)}, initial_capacity=64,
                         dtypes={"weight0": torch.float16, "feat0": torch.float16})
        integrate_frame(grid, depth, np.ones((depth.size, 5), np.float32), intrinsics, T, RANGE, config, channels)
        return {tuple(c) for c in grid.coords[: grid.n_blocks].tolist()}

    # one valid pixel, its ray along a block's diagonal (the most samples one ray can leave in a block)
    axis = np.ones(3) / np.sqrt(3)
    right = np.cross([0.0, 1.0, 0.0], axis)
    right /= np.linalg.norm(right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, np.cross(axis, right), axis], axis=1)
    one = np.zeros((5, 5), np.float32)
    rng = np.random.default_rng(0)
    for _ in range(100):
        one[2, 2] = rng.uniform(1.0, 1.2)
        T[:3, 3] = rng.uniform(0.0, BLOCK * voxel_size_m, 3)
        assert not blocks(one, np.array([[10.0, 0, 2], [0, 10.0, 2], [0, 0, 1]]), T)
    # a wall with its pixels 3 voxels apart: its surface blocks inside the image's edge are allocated
    size, focal = 96, 48.0
    intrinsics = np.array([[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1.0]])
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    wall = 3 * voxel_size_m * focal * (1.0 + 0.002 * u)
    points = np.stack([(u - intrinsics[0, 2]) / focal * wall, (v - intrinsics[1, 2]) / focal * wall, wall], axis=-1)
    inner = points[8:-8, 8:-8].reshape(-1, 3)  # blocks at the image's edge are seen in part, at any voxel size
    surface = {tuple(b) for b in np.floor(inner / (BLOCK * voxel_size_m)).astype(int).tolist()}
    kept = blocks(wall.astype(np.float32), intrinsics, np.eye(4))
    assert len(surface & kept) >= 0.99 * len(surface), (len(surface & kept), len(surface))


def test_a_frame_beyond_the_key_range_blames_the_pose_or_the_intrinsics_whichever_puts_it_there():
    """A camera_info with its principal point at 1e6 px fans the rays out kilometres wide: the refusal
    named the pose's units, which were fine."""
    import pytest

    from senfunet_core.errors import InputError
    from senfunet_core.integrator import check_key_range

    K_far = np.array([[100.0, 0.0, 1e6], [0.0, 100.0, 1e6], [0.0, 0.0, 1.0]])
    with pytest.raises(InputError, match="check the camera_info's K") as raised:
        check_key_range(4.0, K_far, np.eye(4), (48, 64), 0.1)
    assert "cx 1e+06" in str(raised.value)
    T_far = np.eye(4)
    T_far[0, 3] = 6000.0
    with pytest.raises(InputError, match="the camera is 6000 m from it.*pose's units"):
        check_key_range(4.0, np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]), T_far, (48, 64), 0.1)
    check_key_range(4.0, np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]), np.eye(4), (48, 64), 0.1)
