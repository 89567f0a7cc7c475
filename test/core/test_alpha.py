"""The scheduling kernels of senfunet_core.alpha against plain numpy on random neighbourhoods."""
from __future__ import annotations

import numpy as np

from senfunet_core.alpha import near_surface_voxels, surface_targets


def _random_neighbourhood(rng: np.random.Generator) -> tuple[np.ndarray, list[np.ndarray]]:
    """A block (neighbour code 13) with a random subset of its 26 neighbours, random TSDFs near 0
    and sparse weights; returns the 1 x 27 neighbour table and the flat pools."""
    exists = rng.random(27) < 0.7
    exists[13] = True
    neighbours = np.full((1, 27), -1, np.int64)
    neighbours[0, exists] = rng.permutation(int(exists.sum()))
    n_voxels = int(exists.sum()) * 512
    sign = rng.choice([-1.0, 1.0])
    flipped = rng.choice([0.0, 0.0002, 0.01])  # share of voxels on the other side of the surface
    pools = []
    for _ in range(2):
        tsdf = (sign * rng.uniform(0.001, 0.05, n_voxels)).astype(np.float32)
        tsdf[rng.random(n_voxels) < flipped] *= -1.0
        seen = rng.random(n_voxels) < rng.uniform(0.3, 1.0)
        pools += [tsdf, np.where(seen, 3.0, 0.0).astype(np.float16).view(np.int16)]
    return neighbours, pools


def _surface_reference(neighbours: np.ndarray, pools: list[np.ndarray]) -> np.ndarray:
    """Dense 24^3 neighbourhood, then every cell with a corner in the centre block: 8^3 mask of the
    centre block's voxels that are corners of a cell with 8 observed corners and a sign change."""
    lo = np.full((24, 24, 24), np.inf, np.float32)
    hi = np.full((24, 24, 24), -np.inf, np.float32)
    for tsdf, weight in zip(pools[0::2], pools[1::2]):
        for code in range(27):
            slot = neighbours[0, code]
            if slot < 0:
                continue
            dx, dy, dz = code // 9, (code // 3) % 3, code % 3
            values = tsdf[slot * 512:(slot + 1) * 512].reshape(8, 8, 8)
            observed = weight[slot * 512:(slot + 1) * 512].view(np.float16).reshape(8, 8, 8) > 0
            box = np.s_[8 * dx:8 * dx + 8, 8 * dy:8 * dy + 8, 8 * dz:8 * dz + 8]
            lo[box] = np.where(observed, np.minimum(lo[box], values), lo[box])
            hi[box] = np.where(observed, np.maximum(hi[box], values), hi[box])
    window_lo, window_hi = lo[7:17, 7:17, 7:17], hi[7:17, 7:17, 7:17]
    corners = [np.s_[a:a + 9, b:b + 9, c:c + 9] for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    seen = np.all([np.isfinite(window_lo[s]) for s in corners], axis=0)
    cell_lo = np.min([window_lo[s] for s in corners], axis=0)
    cell_hi = np.max([window_hi[s] for s in corners], axis=0)
    cells = seen & (cell_lo <= 0) & (cell_hi >= 0)  # 9^3, lower corner at local -1..7
    corner_of = np.zeros((10, 10, 10), bool)  # local -1..8
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                corner_of[a:a + 9, b:b + 9, c:c + 9] |= cells
    return corner_of[1:9, 1:9, 1:9]


def test_surface_targets_match_a_dense_reference() -> None:
    rng = np.random.default_rng(7)
    outcomes = []
    for _ in range(200):
        neighbours, pools = _random_neighbourhood(rng)
        expected = _surface_reference(neighbours, pools)
        np.testing.assert_array_equal(surface_targets(neighbours, *pools)[0].reshape(8, 8, 8), expected)
        outcomes.append(expected.any())
    assert 20 < sum(outcomes) < 180  # blocks with and without targets were exercised


def test_near_surface_voxels_match_a_numpy_count() -> None:
    """Per block, the voxels a sensor observed within the limit of its surface, with the TSDF pools
    as float32 and as float16 bits."""
    rng = np.random.default_rng(8)
    counts = []
    for _ in range(20):
        neighbours, pools = _random_neighbourhood(rng)
        slots = rng.permutation(neighbours[neighbours >= 0])
        tsdf_1, weight_1, tsdf_2, weight_2 = pools
        near = np.zeros(len(tsdf_1), bool)
        for tsdf, weight in ((tsdf_1, weight_1), (tsdf_2, weight_2)):
            near |= (weight.view(np.float16) > 0) & (np.abs(tsdf) < 0.01)
        expected = near.reshape(-1, 512)[slots].sum(axis=1)
        np.testing.assert_array_equal(near_surface_voxels(slots, *pools, 0.01), expected)
        half_1, half_2 = (tsdf.astype(np.float16).view(np.int16) for tsdf in (tsdf_1, tsdf_2))
        half_counts = near_surface_voxels(slots, half_1, weight_1, half_2, weight_2, 0.01)
        np.testing.assert_allclose(half_counts, expected, atol=4)
        counts += expected.tolist()
    assert 0 < min(counts) and max(counts) < 512  # blocks with partly observed surface
