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


def test_neighbours_taken_without_the_lock_while_the_grid_grows_find_every_block():
    """Alpha threads and meshing look up neighbours without the data lock while integration adds
    blocks: each growth of the hash table must hand them a complete table (a table filled in place
    showed them existing blocks as absent, and keys of one table with slots of the other)."""
    import threading

    grid = BlockGrid({"a": ()}, initial_capacity=16)
    store = BlockStore(grid)
    cube = torch.stack(torch.meshgrid(*[torch.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3)
    slots = grid.allocate_keys(block_keys(cube)).numpy()
    inner = slots[((cube >= 1) & (cube <= 2)).all(dim=1).numpy()]  # all 27 neighbours in the cube
    expected = store.neighbours(inner)
    assert (expected >= 0).all()
    rng = np.random.default_rng(2)
    far = torch.unique(block_keys(torch.from_numpy(rng.integers(100, 3000, (300_000, 3)))))  # no neighbours of it
    wrong: list[np.ndarray] = []
    reads = [0]
    done = threading.Event()

    def read() -> None:
        while not done.is_set():
            got = store.neighbours(inner)
            reads[0] += 1
            if not np.array_equal(got, expected):
                wrong.append(got)

    reader = threading.Thread(target=read)
    reader.start()
    try:
        for start in range(0, len(far), 5000):  # the table doubles several times meanwhile
            grid.allocate_keys(far[start:start + 5000])
    finally:
        done.set()
        reader.join()
    assert grid.n_blocks == len(cube) + len(far) and len(grid.hash_table.keys) >= 2 * grid.n_blocks and reads[0] > 100
    assert not wrong


def test_blocks_a_frame_is_still_allocating_are_absent_for_neighbours():
    """Integration adds a frame's new blocks to the hash table before the allocation policy may drop
    them or move them to other slots, and commits them after: until then a reader without the lock
    must not take their slots (it would read another block's voxels there, as current)."""
    from senfunet_core import grid as grid_module

    grid = BlockGrid({"a": ()}, initial_capacity=64)
    store = BlockStore(grid)
    centre = grid.allocate_keys(block_keys(torch.tensor([[5, 5, 5]]))).numpy()
    new_key = block_keys(torch.tensor([[6, 5, 5]])).numpy()
    state = np.array([grid.n_blocks, grid.hash_table.max_blocks()], np.int64)
    added = np.empty(1, np.int64)
    assert grid_module._add_many(*grid.hash_table, new_key, state, grid.slot_keys, added) == 1
    code = 9 * 2 + 3 * 1 + 1  # +x
    assert store.neighbours(centre)[0, code] == -1  # added, not committed
    grid.commit_new_blocks(int(state[0]))
    assert store.neighbours(centre)[0, code] == added[0] == 1
