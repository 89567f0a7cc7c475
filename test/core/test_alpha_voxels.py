"""Voxel-granular weighting net ("surface" mode): the targets and their alpha against the
block-with-halo evaluation (which equals the whole-grid net, see test_engine.py)."""
from __future__ import annotations

import numpy as np
import torch

from senfunet_core import alpha
from senfunet_core.alpha import (evaluate_gathers, holds_surface_targets, surface_targets, target_gathers,
                                 weighting_windows)
from senfunet_core.engine import EngineConfig, SenFuNet
from senfunet_core.grid import decode_features, neighbour_table, packed_words
from test_equivalence import K, frames


def _engine(tsdf_input: bool) -> SenFuNet:
    config = EngineConfig(depth_min_m=(0.05, 0.05), depth_max_m=(1.5, 1.5), border_px=2,
                          weighting_tsdf_input=tsdf_input)
    engine = SenFuNet(config, weights=None)
    with torch.no_grad():
        for p in engine.weighting_net.parameters():
            p.mul_(3.0)
    for sensor, depth, rgb, T in frames(4):
        engine.integrate(sensor, depth, K, T, rgb)
    return engine


def test_surface_targets_are_the_corners_of_cells_that_can_hold_triangles():
    engine = _engine(False)
    grid = engine.grid
    slots = np.arange(grid.n_blocks)
    nb = neighbour_table(*grid.hash_table, grid.slot_keys, slots)
    views = engine.store.views("tsdf0", "weight0", "tsdf1", "weight1")
    targets = surface_targets(nb, *views)
    # a minority of the voxels of the blocks that hold targets
    assert 0 < targets.sum() < 0.5 * targets.any(axis=1).sum() * 512
    # brute force on the dense volume: corners of cells with 8 observed corners and a sign change
    coords = grid.coords[: grid.n_blocks].numpy()
    lo_block = coords.min(axis=0) - 1
    shape = tuple((coords.max(axis=0) - lo_block + 2) * 8)
    seen = np.zeros(shape, bool)
    lo, hi = np.full(shape, np.inf, np.float32), np.full(shape, -np.inf, np.float32)
    for s in range(2):
        tsdf = grid.pools[f"tsdf{s}"][: grid.n_blocks].numpy().reshape(-1, 8, 8, 8)
        observed = grid.pools[f"weight{s}"][: grid.n_blocks].float().numpy().reshape(-1, 8, 8, 8) > 0
        for b, c in enumerate(coords - lo_block):
            region = tuple(slice(8 * a, 8 * a + 8) for a in c)
            seen[region] |= observed[b]
            lo[region] = np.where(observed[b], np.minimum(lo[region], tsdf[b]), lo[region])
            hi[region] = np.where(observed[b], np.maximum(hi[region], tsdf[b]), hi[region])
    corners = [(dx, dy, dz) for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)]
    def shifted(a, d):
        return a[d[0]:a.shape[0] - 1 + d[0], d[1]:a.shape[1] - 1 + d[1], d[2]:a.shape[2] - 1 + d[2]]
    cell = np.logical_and.reduce([shifted(seen, d) for d in corners])
    cell &= np.minimum.reduce([shifted(lo, d) for d in corners]) <= 0
    cell &= np.maximum.reduce([shifted(hi, d) for d in corners]) >= 0
    expected = np.zeros(shape, bool)
    for d in corners:
        expected[d[0]:shape[0] - 1 + d[0], d[1]:shape[1] - 1 + d[1], d[2]:shape[2] - 1 + d[2]] |= cell
    for b, c in enumerate(coords - lo_block):
        region = tuple(slice(8 * a, 8 * a + 8) for a in c)
        np.testing.assert_array_equal(targets[b].reshape(8, 8, 8), expected[region])
    # the whole-block check (which stops at a block's first target) agrees on which blocks hold any
    holds = holds_surface_targets(nb, *views)
    assert 0 < holds.sum() < len(holds)
    np.testing.assert_array_equal(holds, targets.any(axis=1))


def test_voxel_evaluation_equals_the_block_evaluation_at_the_targets():
    for tsdf_input in (False, True):
        engine = _engine(tsdf_input)
        grid = engine.grid
        slots = np.arange(grid.n_blocks)
        nb = neighbour_table(*grid.hash_table, grid.slot_keys, slots)
        targets = surface_targets(nb, *engine.store.views("tsdf0", "weight0", "tsdf1", "weight1"))
        holding = np.flatnonzero(targets.any(axis=1))
        windows = weighting_windows(nb[holding], *engine.alpha.evaluator.inputs())
        x = torch.from_numpy(windows).permute(0, 4, 1, 2, 3)
        with torch.no_grad():
            block_alpha = engine.weighting_net(x, pad=False).reshape(len(holding), 512).numpy()
        inputs, gather_1, gather_2, voxels = target_gathers(nb[holding], targets[holding],
                                                            *engine.alpha.evaluator.inputs())
        with torch.no_grad():
            alpha = evaluate_gathers(engine.weighting_net, inputs, gather_1, gather_2)
        assert len(alpha) == targets.sum() > 1000
        expected = np.zeros(grid.n_blocks * 512, np.float32)
        expected.reshape(-1, 512)[holding] = block_alpha
        np.testing.assert_allclose(alpha, expected[voxels], atol=2e-6)
        assert alpha.std() > 0.05  # the weights spread alpha: a wrong gather would show


def test_windows_written_to_a_reused_buffer_as_bfloat16_equal_torch_rounding_of_the_float32_windows():
    engine = _engine(True)
    grid = engine.grid
    nb = neighbour_table(*grid.hash_table, grid.slot_keys, np.arange(grid.n_blocks))
    expected = weighting_windows(nb, *engine.alpha.evaluator.inputs())
    assert (expected == 0).any() and (expected != 0).mean() > 0.1  # missing neighbours and inputs both
    want_bits = torch.from_numpy(expected).to(torch.bfloat16).view(torch.int16).numpy().view(np.uint16)
    for dtype, want in ((np.float32, expected), (np.uint16, want_bits)):
        buffer = np.full(expected.size + 7, 12345, dtype)  # an earlier batch's leftovers: all overwritten
        got = weighting_windows(nb, *engine.alpha.evaluator.inputs(), out=buffer)
        np.testing.assert_array_equal(got, want)
        assert np.shares_memory(got, buffer)
    # packed features (looked up in tables) and the same features stored unpacked, as float32 values
    features_1, weight_1, features_2, weight_2, *rest = engine.alpha.evaluator.inputs()
    n_voxels = grid.n_blocks * 512  # the blocks in use (the pools hold more)
    unpacked = [decode_features(torch.from_numpy(f).reshape(len(weight_1), -1)[:n_voxels]).numpy().reshape(-1)
                for f in (features_1, features_2)]
    weight_1, weight_2 = weight_1[:n_voxels], weight_2[:n_voxels]
    assert features_1.dtype == np.int8
    np.testing.assert_array_equal(weighting_windows(nb, unpacked[0], weight_1, unpacked[1], weight_2, *rest), expected)


def test_packed_rows_read_as_words_give_the_windows_of_the_rows_read_byte_by_byte():
    engine = _engine(True)
    grid = engine.grid
    nb = neighbour_table(*grid.hash_table, grid.slot_keys, np.arange(grid.n_blocks))
    inputs = engine.alpha.evaluator.inputs()
    features_1, weight_1, features_2, weight_2, tsdf_1, tsdf_2, tsdf_scale = inputs
    assert packed_words(features_1, len(weight_1)).dtype == np.uint32  # the engine's packing is read as words
    for dtype in (np.float32, np.uint16, np.uint8):
        by_words = weighting_windows(nb, *inputs, out=np.empty(nb.shape[0] * 12**3 * 14, dtype), depth_max_m=5.0)
        by_bytes = np.full(by_words.size, 123, dtype)
        alpha._fill_windows(by_bytes, nb, features_1, weight_1, features_2, weight_2, tsdf_1, tsdf_2,
                            *alpha._window_tables(np.dtype(dtype), tsdf_scale, 5, True, 5.0))
        assert (by_words != 0).mean() > 0.1
        np.testing.assert_array_equal(by_bytes.reshape(by_words.shape), by_words)
