from __future__ import annotations

import numpy as np
import pytest
import torch

from senfunet_core.block_store import BlockStore
from senfunet_core.grid import BlockGrid, block_keys


@pytest.mark.parametrize("dtype", [torch.float16, torch.float32])
def test_observed_voxels_counts_voxels_any_sensor_weighted(dtype: torch.dtype):
    """The in-place count equals the count over the stacked pools, for one or two channels and for
    float16 (counted on the bit patterns) and float32 pools; blocks past n_blocks do not count."""
    grid = BlockGrid({"weight0": (), "weight1": ()}, initial_capacity=64, dtypes={"weight0": dtype, "weight1": dtype})
    store = BlockStore(grid)
    rng = np.random.default_rng(3)
    grid.allocate_keys(torch.unique(block_keys(torch.from_numpy(rng.integers(-50, 50, (40, 3))))))
    n = grid.n_blocks
    for name in ("weight0", "weight1"):
        values = torch.from_numpy(rng.choice([0.0, -0.0, 0.5, 1.0, 2048.0], size=(n, 512)).astype(np.float32))
        grid.pools[name][:n] = values.to(dtype)
        grid.pools[name][n:] = 1.0  # not a block (yet): never counted
    both = int(((grid.pools["weight0"][:n] > 0) | (grid.pools["weight1"][:n] > 0)).sum())
    only_first = int((grid.pools["weight0"][:n] > 0).sum())
    assert 0 < only_first < both < n * 512
    assert store.observed_voxels(["weight0", "weight1"]) == both
    assert store.observed_voxels(["weight0"]) == only_first
