"""The sparse block grid: hash-table lookups, growth, neighbour tables and half-precision kernels."""
from __future__ import annotations

from pathlib import Path

import numba
import numpy as np
import pytest
import torch

from senfunet_core import grid as G
from senfunet_core.grid import BlockGrid, block_keys, masked_neighbours, neighbour_table


def _codec(encode, decode):
    @numba.njit
    def enc(x, out):
        for i in range(x.shape[0]):
            out[i] = encode(x[i])

    @numba.njit
    def dec(bits, out):
        for i in range(bits.shape[0]):
            out[i] = decode(bits[i])

    return enc, dec


@pytest.mark.parametrize("which", ["hardware", "software"])
def test_half_conversions_match_numpy(which):
    encode, decode = ((G._f32_to_f16_hw, G._f16_to_f32_hw) if which == "hardware"
                      else (G._f32_to_f16_soft, G._f16_to_f32_soft))
    if which == "hardware" and not G._hardware_half():
        pytest.skip("this CPU has no half-precision conversions")
    enc, dec = _codec(encode, decode)
    rng = np.random.default_rng(0)
    x = (rng.standard_normal(200_000) * 10.0 ** rng.uniform(-9, 5, 200_000)).astype(np.float32)
    edges = np.array([0.0, -0.0, np.inf, -np.inf, 65504, 65519.99, 65520, -65520, 2**-24, 2**-25, 3 * 2**-26,
                      2**-14, -(2**-14) * (1 - 2**-12), 1 + 2**-11, 1 + 3 * 2**-11], np.float32)
    x = np.concatenate([x, edges])
    got = np.empty(len(x), np.int16)
    enc(x, got)
    with np.errstate(over="ignore"):
        want = x.astype(np.float16).view(np.int16)
    np.testing.assert_array_equal(got, want)
    nan = np.empty(1, np.int16)
    enc(np.array([np.nan], np.float32), nan)
    assert np.isnan(nan.view(np.float16)[0])
    every = np.arange(-32768, 32768).astype(np.int16)
    values = np.empty(len(every), np.float32)
    dec(every, values)
    np.testing.assert_array_equal(values, every.view(np.float16).astype(np.float32))


def test_allocate_lookup_and_growth():
    grid = BlockGrid({"a": (), "b": (2,)}, initial_capacity=16, fill={"a": 0.5})
    rng = np.random.default_rng(1)
    coords = torch.from_numpy(rng.integers(-3000, 3000, (20_000, 3)))
    keys = torch.unique(block_keys(coords))
    first = grid.allocate_keys(keys[:100])
    grid.pools["b"][first] = 7.0  # must survive the growth below
    slots = grid.allocate_keys(keys)  # grows the pools and rehashes the table several times
    assert grid.n_blocks == len(keys) and grid.capacity >= len(keys)
    assert torch.equal(slots[:100], first)
    assert sorted(slots.tolist()) == list(range(len(keys)))
    assert torch.equal(grid.lookup_keys(keys), slots)
    assert torch.equal(block_keys(grid.coords[slots]), keys)
    assert bool((grid.pools["b"][first] == 7.0).all()) and bool((grid.pools["a"][slots] == 0.5).all())
    absent = block_keys(torch.tensor([[4000, 0, 0], [-4000, 5, 5]]))
    assert grid.lookup_keys(absent).tolist() == [-1, -1]
    assert grid.hash_table.max_blocks() >= grid.n_blocks


def test_remove_blocks_keeps_the_survivors_and_zeroes_freed_slots():
    grid = BlockGrid({"a": (), "f": (5,)}, initial_capacity=64, dtypes={"f": torch.float16})
    rng = np.random.default_rng(2)
    keys = torch.unique(block_keys(torch.from_numpy(rng.integers(-50, 50, (300, 3)))))
    slots = grid.allocate_keys(keys)
    grid.pools["a"][slots] = (slots.to(torch.float32) + 1.0).view(-1, 1)  # each block remembers its slot
    features = torch.from_numpy(rng.uniform(-1, 1, (len(keys), 512, 5))).to(torch.float16)
    grid.pools["f"][slots] = features  # and has its own voxels
    value_of = {int(k): float(slots[i]) + 1.0 for i, k in enumerate(keys)}
    victims = np.arange(0, len(keys), 3)
    n_before = grid.n_blocks
    grid.remove_blocks(victims)
    assert grid.n_blocks == n_before - len(victims)
    survivors = torch.from_numpy(np.setdiff1d(np.arange(len(keys)), victims))
    new_slots = grid.lookup_keys(keys[survivors])
    assert sorted(new_slots.tolist()) == list(range(grid.n_blocks))
    assert grid.pools["a"][new_slots, 0].tolist() == [value_of[int(k)] for k in keys[survivors]]
    assert torch.equal(grid.pools["f"][new_slots], features[survivors])
    assert grid.lookup_keys(keys[torch.from_numpy(victims)]).tolist() == [-1] * len(victims)
    assert bool((grid.pools["a"][grid.n_blocks:n_before] == 0).all())
    assert bool((grid.pools["f"][grid.n_blocks:n_before] == 0).all())


@pytest.mark.parametrize("shape, dtype", [((), torch.float32), ((3,), torch.float16), ((5,), torch.float16)])
def test_released_rows_read_zero_and_the_others_stay(shape: tuple[int, ...], dtype: torch.dtype):
    """Rows sizes that do not divide the page: the rows sharing a page with kept rows are zeroed
    by hand, the whole pages in between are given back (and read zero)."""
    pool, memory = G._zeros((40, 512, *shape), dtype)
    rng = np.random.default_rng(3)
    for start, stop in [(3, 17), (0, 40), (10, 11), (21, 39)]:
        pool.copy_(torch.from_numpy(rng.uniform(1, 2, pool.shape)).to(dtype))
        before = pool.clone()
        G._release_rows(pool, memory, start, stop)
        assert bool((pool[start:stop] == 0).all())
        assert torch.equal(pool[:start], before[:start]) and torch.equal(pool[stop:], before[stop:])


def test_neighbour_table_matches_coordinates():
    grid = BlockGrid({"a": ()}, initial_capacity=8)
    cube = torch.stack(torch.meshgrid(*[torch.arange(3)] * 3, indexing="ij"), -1).reshape(-1, 3)
    coords = torch.cat([cube, torch.tensor([[10, 10, 10]])])
    slots = grid.allocate_keys(block_keys(coords))
    table = neighbour_table(*grid.hash_table, grid.slot_keys, slots.numpy())
    index = {tuple(c): int(s) for c, s in zip(coords.tolist(), slots)}
    for row, c in zip(table, coords.tolist()):
        for code in range(27):
            offset = (code // 9 - 1, (code // 3) % 3 - 1, code % 3 - 1)
            assert row[code] == index.get(tuple(a + o for a, o in zip(c, offset)), -1)
    assert table[-1, 13] == slots[-1] and (np.delete(table[-1], 13) == -1).all()
    # a subset of the neighbours: those looked up as before, the others -1
    codes = np.array([13, 14, 22, 26])
    subset = neighbour_table(*grid.hash_table, grid.slot_keys, slots.numpy(), codes)
    np.testing.assert_array_equal(subset[:, codes], table[:, codes])
    assert (np.delete(subset, codes, axis=1) == -1).all() and (subset[:, codes] >= 0).sum() > len(coords)


def test_masked_neighbours_are_the_neighbour_tables_entries_the_masks_name():
    grid = BlockGrid({"a": ()}, initial_capacity=64)
    rng = np.random.default_rng(5)
    coords = torch.unique(torch.from_numpy(rng.integers(-3, 3, (150, 3))), dim=0)
    slots = grid.allocate_keys(block_keys(coords)).numpy()
    masks = rng.integers(0, 1 << 27, len(slots)).astype(np.int32)
    masks[::7] = 0  # blocks that reach nothing
    table = neighbour_table(*grid.hash_table, grid.slot_keys, slots)
    named = ((masks[:, None].astype(np.int64) >> np.arange(27)) & 1).astype(bool)
    want_sources, want_codes = np.nonzero(named & (table >= 0))
    sources, codes, targets = masked_neighbours(*grid.hash_table, grid.slot_keys, slots, masks)
    np.testing.assert_array_equal(sources, want_sources)
    np.testing.assert_array_equal(codes, want_codes)
    np.testing.assert_array_equal(targets, table[want_sources, want_codes])
    assert len(targets) > len(slots) and (named & (table < 0)).any()  # absent neighbours were named too


def test_keys_outside_the_range_are_refused():
    with pytest.raises(ValueError, match="5 km"):
        block_keys(torch.tensor([[1 << 17, 0, 0]]))


def test_dropping_uncommitted_new_blocks_keeps_every_other_key_findable():
    """drop_new_blocks on a crowded table (long probe runs): kept keys move down to contiguous
    slots, dropped keys vanish, the blocks that were there before are untouched."""
    grid = BlockGrid({"a": ()}, initial_capacity=4096)
    rng = np.random.default_rng(3)
    keys = torch.unique(block_keys(torch.from_numpy(rng.integers(-40, 40, (3000, 3)))))[:2000]
    old, new = keys[:1200], keys[1200:]
    grid.allocate_keys(old)
    n_before = grid.n_blocks
    # add the new keys as a kernel would (not committed), then drop every third one
    state = np.array([grid.n_blocks, grid.hash_table.max_blocks()], np.int64)
    for key in new.tolist():
        G.hash_find_or_add(*grid.hash_table, key, state, grid.slot_keys)
    keep = np.arange(len(new)) % 3 != 0
    moved = G.drop_new_blocks(*grid.hash_table, grid.slot_keys, n_before, keep)
    grid.commit_new_blocks(n_before + int(keep.sum()))
    assert grid.n_blocks == n_before + keep.sum()
    assert torch.equal(grid.lookup_keys(old), torch.arange(n_before))
    kept = grid.lookup_keys(new[torch.from_numpy(keep)])
    assert torch.equal(kept, torch.arange(n_before, grid.n_blocks))
    assert torch.equal(kept, torch.from_numpy(moved[keep]))
    assert (grid.lookup_keys(new[torch.from_numpy(~keep)]) == -1).all()
    assert torch.equal(block_keys(grid.coords[: grid.n_blocks]), torch.cat([old, new[torch.from_numpy(keep)]]))
    assert (grid.hash_table.keys != G.EMPTY_KEY).sum() == grid.n_blocks


def _cached_kernel(function):
    """numba.njit(cache=True): these kernels compile for two pool dtypes, tens of seconds a run
    uncached. numba renews a cached kernel when this file changes only, and they inline grid.py's
    functions: their cache is dropped when grid.py is newer, so they never run a stale grid."""
    here = Path(__file__)
    for index in (here.parent / "__pycache__").glob(f"{here.stem}.{function.__name__}-*.nbi"):
        if index.stat().st_mtime < Path(G.__file__).stat().st_mtime:
            index.unlink(missing_ok=True)
    return numba.njit(cache=True)(function)


@_cached_kernel
def _store_load_features(values, packed):
    n_voxels, n = values.shape
    back = np.empty_like(values)
    for v in range(n_voxels):
        for c in range(n):
            G.store_feature(packed, n, v, c, values[v, c])
    n_read = G.features_per_voxel(packed, n_voxels)
    for v in range(n_voxels):
        for c in range(n_read):
            back[v, c] = G.load_feature(packed, n_read, v, c)
    return back


@_cached_kernel
def _load_rows(pool, n_voxels, n):
    rows = np.empty((n_voxels, n), np.float32)
    for v in range(n_voxels):
        G.load_features(pool, n, v, rows[v])
    return rows


def test_packed_features_in_kernels_equal_encode_and_decode():
    """The kernels' packed feature storage (4 learned features in 6 bits, steps of 1/31, in 3 bytes;
    the depth as an 8-bit code) matches the torch encoder and decoder bit for bit: ties to even,
    clamping, depths out of range."""
    rng = np.random.default_rng(3)
    learned = rng.uniform(-1.0, 1.0, (500, 4)).astype(np.float32)
    learned[:20] = (np.arange(-10, 10)[:, None] + 0.5).astype(np.float32) / np.float32(31.0)  # ties
    learned[20:25] = [[1.2, -1.3, 1.0, -1.0]] * 5  # beyond the range: clamped to +-31
    depth = rng.uniform(0.01, 12.0, (500, 1)).astype(np.float32)
    depth[25:28, 0] = [-2.5, 40.0, np.float32(G.DEPTH_OF_CODE[100] + G.DEPTH_OF_CODE[101]) / 2]  # clamped; a tie
    values = np.concatenate([learned, depth], axis=1)
    packed = np.zeros(500 * 4, np.int8)
    back = _store_load_features(values, packed)
    encoded = G.encode_features(torch.from_numpy(values))
    assert encoded.dtype == torch.int8 and encoded.shape == (500, 4)
    assert np.array_equal(packed.reshape(500, 4), encoded.numpy())
    decoded = G.decode_features(encoded).numpy()
    assert np.array_equal(back, decoded)
    assert np.array_equal(_load_rows(packed, 500, 5), decoded)  # a whole row at once reads the same
    assert decoded[25:28, 4].tolist() == [0.0, G.DEPTH_MAX_M, G.DEPTH_OF_CODE[100]]  # tie to the even code
    assert np.abs(decoded[25:, :4] - learned[25:]).max() <= 0.5 / 31 + 1e-7
    assert set(np.rint(decoded[:20, :4] * 31).astype(int).ravel()) <= set(range(-10, 11, 2))  # ties to even
    assert decoded[20:25, :4].tolist() == [[1.0, -1.0, 1.0, -1.0]] * 5
    # a float16 feature pool takes the same calls, one value per feature
    half = np.zeros(500 * 5, np.int16)
    back_half = _store_load_features(values, half)
    assert np.array_equal(back_half, values.astype(np.float16).astype(np.float32))
    assert np.array_equal(_load_rows(half, 500, 5), back_half)


def test_depth_code_rounds_to_the_nearest_representable_depth():
    """The depth feature's 8-bit code: increasing, 0 m at code 0, and every depth in range goes to
    its nearest code (relative error at most 1/64 from 0.25 m, at most 1/256 m below)."""
    table = G.DEPTH_OF_CODE.astype(np.float64)
    assert table[0] == 0.0 and (np.diff(table) > 0).all() and table[-1] == G.DEPTH_MAX_M
    depth = np.random.default_rng(8).uniform(0.0, G.DEPTH_MAX_M, 20000).astype(np.float32)
    codes = np.array([G.encode_depth(d) for d in depth]).astype(np.int64) & 0xFF
    nearest = np.abs(depth[:, None].astype(np.float64) - table[None, :]).argmin(axis=1)
    got, best = table[codes], table[nearest]
    assert np.allclose(np.abs(got - depth), np.abs(best - depth), rtol=0, atol=1e-6)
    far = depth >= 0.25
    assert (np.abs(got - depth)[far] / depth[far]).max() <= 1 / 64 + 1e-6
    assert np.abs(got - depth)[~far].max() <= 1 / 256 + 1e-6


@_cached_kernel
def _blend_all(features, n, keep, add, sums, inv_count, changes):
    for v in range(changes.shape[0]):
        changes[v] = G.blend_features(features, n, v, keep[v], add[v], sums[v], inv_count[v])


@pytest.mark.parametrize("storage", ["packed int8", "float16 bits"])
def test_blended_features_match_the_reference_average(storage):
    """The kernels' running average of a voxel's features (the packed path works in stored integers)
    agrees with load, average in float32, store, for every feature, and reports the largest change."""
    rng = np.random.default_rng(5)
    n_voxels, n = 2000, 5
    start = np.concatenate([rng.uniform(-1, 1, (n_voxels, 4)), rng.uniform(0.2, 6, (n_voxels, 1))], 1)
    sums = np.concatenate([rng.uniform(-3, 3, (n_voxels, 4)), rng.uniform(0.6, 18, (n_voxels, 1))], 1)
    count = rng.integers(1, 4, n_voxels).astype(np.float32)
    sums = (sums * count[:, None] / 3).astype(np.float32)
    weight = rng.integers(0, 40, n_voxels).astype(np.float32)
    keep, add = weight / (weight + 1), 1 / (weight + 1)
    pool = np.zeros(n_voxels * 4, np.int8) if storage == "packed int8" else np.zeros(n_voxels * n, np.int16)
    _store_load_features(start.astype(np.float32), pool)
    reference = pool.copy()
    old = np.array([[G.load_feature(reference, n, v, c) for c in range(n)] for v in range(n_voxels)], np.float32)
    for v in range(n_voxels):
        for c in range(n):
            G.store_feature(reference, n, v, c, keep[v] * old[v, c] + add[v] * (sums[v, c] / count[v]))
    changes = np.empty(n_voxels, np.float32)
    _blend_all(pool, n, keep, add, sums, (1 / count).astype(np.float32), changes)
    new = np.array([[G.load_feature(pool, n, v, c) for c in range(n)] for v in range(n_voxels)], np.float32)
    expected = np.array([[G.load_feature(reference, n, v, c) for c in range(n)] for v in range(n_voxels)], np.float32)
    step = 1 / 31 if storage == "packed int8" else 0.0
    # the packed path rounds once in integer units: at most one step apart where a value sits on a tie
    assert np.abs(new - expected).max() <= step + 1e-6
    assert (new == expected).mean() > 0.99
    np.testing.assert_allclose(changes, np.abs(new - old).max(axis=1), atol=1e-6)
    assert changes.max() > 0.1  # the averages moved


def test_hash_table_follows_the_blocks_and_spreads_neighbours():
    """The table grows with the blocks it holds (a small table stays in cache) and neighbouring
    blocks, which differ in a few low bits of each axis field, land in distinct buckets."""
    grid = BlockGrid({"a": ()}, initial_capacity=1 << 16)
    x, y, z = np.meshgrid(np.arange(-60, 60), np.arange(-40, 40), np.arange(0, 3), indexing="ij")
    keys = torch.unique(block_keys(torch.from_numpy(np.stack([x, y, z], -1).reshape(-1, 3))))
    grid.allocate_keys(keys)
    assert len(grid.hash_table.keys) <= 4 * grid.n_blocks + 4096  # sized by the blocks, not the pools' capacity
    mask = len(grid.hash_table.keys) - 1
    homes = np.array([G._bucket(int(k), mask) for k in keys.tolist()])
    assert len(np.unique(homes)) > 0.7 * len(keys)
    assert torch.equal(grid.lookup_keys(keys), torch.arange(len(keys)))
