"""The map bound on long runs and large rooms: what the bound keeps when things go wrong."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from senfunet_core.spill import BlockSpill
from test_engine import SPHERE_C, SPHERE_VIEWS, engine_for_tests, far_views, integrate_views


def test_a_spill_that_cannot_be_written_keeps_the_blocks_and_the_updates_going(monkeypatch, caplog):
    """A full disk: the eviction is abandoned (logged as an error, counted), the blocks stay in memory
    and are not archived; integration and updates go on without raising; once the disk has room the
    bound is kept again."""
    caplog.set_level(logging.ERROR, logger="senfunet.engine")
    engine = engine_for_tests(max_blocks=165)
    integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]])
    engine.update()
    put = BlockSpill.put

    def full(self, keys, rows):
        raise OSError(28, "cannot write evicted blocks to the spill file: No space left on device")

    monkeypatch.setattr(BlockSpill, "put", full)
    integrate_views(engine, far_views(2))  # past the hard bound: does not raise
    assert engine.frames_integrated == {"tof": 4, "stereo": 4}
    engine.update()
    engine.update()
    assert engine.grid.n_blocks > 165 and len(engine.archive) == 0
    assert engine.counters["spill_failures"] >= 1 and engine.stats()["evicted_blocks"] == 0
    assert any("No space left" in r.getMessage() for r in caplog.records)
    live = set(map(tuple, engine.grid.coords[: engine.grid.n_blocks].numpy().tolist()))
    assert not live & set(engine.archive.meshes().as_dict())
    monkeypatch.setattr(BlockSpill, "put", put)
    integrate_views(engine, far_views(4)[2:])
    engine.update()
    assert engine.grid.n_blocks <= 165 and engine.stats()["evicted_blocks"] > 0
