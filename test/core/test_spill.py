"""The spill of evicted blocks: rows come back bit for bit, by key, however often they move."""
from __future__ import annotations

import numpy as np
import pytest

from senfunet_core import spill as spill_module
from senfunet_core.spill import BlockSpill


def rows_of(keys: np.ndarray, seed: int) -> list[np.ndarray]:
    """Per channel, one row per block (float32 TSDF-like, float16 features), mostly empty."""
    rng = np.random.default_rng(seed)
    n = len(keys)
    tsdf = (rng.uniform(-1, 1, (n, 512)) * (rng.random((n, 512)) < 0.3)).astype(np.float32)
    features = rng.normal(size=(n, 512, 5)).astype(np.float16)
    return [tsdf, features]


def empty_like(rows: list[np.ndarray]) -> list[np.ndarray]:
    return [np.zeros_like(r) for r in rows]


def test_blocks_come_back_by_key_and_only_once():
    spill = BlockSpill()
    keys = np.array([11, 7, 3_000_000_000], np.int64)
    rows = rows_of(keys, 0)
    spill.put(keys, rows)
    assert len(spill) == 3 and 7 in spill and 8 not in spill and spill.nbytes > 0
    asked = np.array([5, 3_000_000_000, 11], np.int64)  # 5 was never spilled
    out = empty_like(rows_of(asked, 1))
    found = spill.take(asked, out)
    assert found.tolist() == [False, True, True]
    for channel, original in zip(out, rows):
        assert not channel[0].any()
        np.testing.assert_array_equal(channel[1], original[2])
        np.testing.assert_array_equal(channel[2], original[0])
    assert len(spill) == 1 and spill.restored == 2
    assert not spill.take(asked, empty_like(out)).any()  # taken back: gone from the spill


def test_a_block_spilled_again_comes_back_as_last_spilled():
    spill = BlockSpill()
    keys = np.array([1, 2], np.int64)
    spill.put(keys, rows_of(keys, 0))
    newer = rows_of(keys[:1], 1)
    spill.put(keys[:1], newer)
    out = empty_like(newer)
    assert spill.take(keys[:1], out).all()
    np.testing.assert_array_equal(out[0], newer[0])


@pytest.mark.parametrize("via", ["state_dict", "compaction"])
def test_state_dict_and_compaction_keep_every_block(via, monkeypatch):
    spill = BlockSpill()
    keys = np.arange(40, dtype=np.int64) * 3
    rows = rows_of(keys, 2)
    spill.put(keys, rows)
    if via == "state_dict":
        state = spill.state_dict()
        spill = BlockSpill()
        spill.load_state_dict(state)
    else:  # taking half the blocks back rewrites the file without them
        monkeypatch.setattr(spill_module, "_COMPACT_MIN_BYTES", 0)
        spill.take(keys[:20], empty_like(rows_of(keys[:20], 3)))
        assert spill.nbytes == sum(length for _, length in spill._blobs.index.values())
        keys, rows = keys[20:], [r[20:] for r in rows]
    out = empty_like(rows)
    assert spill.take(keys[::-1].copy(), [o[::-1] for o in out]).all()
    for channel, original in zip(out, rows):
        np.testing.assert_array_equal(channel, original)


def test_a_failed_write_spills_nothing_and_says_what_to_do(tmp_path, monkeypatch):
    """A full disk: put raises an error naming the place and the remedies, and the spill holds what
    it held before (the caller keeps those blocks in memory)."""
    spill = BlockSpill(str(tmp_path))
    keys = np.array([1, 2], np.int64)
    spill.put(keys[:1], rows_of(keys[:1], 0))
    nbytes = spill.nbytes
    file = spill._blobs._open()

    def full(_data: bytes) -> int:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(file, "write", full)
    with pytest.raises(OSError, match=f"in {tmp_path}: .*No space left.*TMPDIR.*max_map_blocks"):
        spill.put(keys, rows_of(keys, 1))
    assert len(spill) == 1 and 2 not in spill and spill.nbytes == nbytes
    monkeypatch.undo()
    out = empty_like(rows_of(keys[:1], 2))
    assert spill.take(keys[:1], out).all()
    np.testing.assert_array_equal(out[0], rows_of(keys[:1], 0)[0])


def test_a_compaction_on_a_full_disk_keeps_the_blobs_still_held(monkeypatch, caplog):
    """Blocks taken back left holes; the compaction that copies the rest into a fresh file met a full
    disk: the OSError left the spill on the fresh file with only the blobs copied so far (the others
    lost) and reached the grid's block allocation (`take`). The old file now stays, holes and all."""
    import io
    import tempfile

    from test_map_bound_large import _FillingDisk

    room: list[int | None] = [None]
    temporary_file = tempfile.TemporaryFile

    def on_the_disk(*args, buffering: int = -1, **kwargs):
        raw = _FillingDisk(temporary_file(*args, buffering=0, **kwargs), room)
        return raw if buffering == 0 else io.BufferedRandom(raw)

    monkeypatch.setattr(spill_module.tempfile, "TemporaryFile", on_the_disk)
    monkeypatch.setattr(spill_module, "_COMPACT_MIN_BYTES", 0)
    spill = BlockSpill()
    keys = np.arange(100, dtype=np.int64) * 7
    rows = rows_of(keys, seed=3)
    spill.put(keys, rows)
    room[0] = 1000  # a fresh file gets 1000 bytes: the disk is full
    back = empty_like(rows)
    assert spill.take(keys[:60], [r[:60] for r in back]).all()  # most of them: a compaction is due
    assert len(spill) == 40 and spill.holds(keys[60:]).all()
    rest = empty_like([r[60:] for r in rows])
    assert spill.take(keys[60:], rest).all()
    assert all(np.array_equal(a, b[60:]) for a, b in zip(rest, rows))
    assert sum("could not be written" in r.getMessage() for r in caplog.records) == 1
