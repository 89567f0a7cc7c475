"""The map bound on long runs and large rooms: what the bound keeps when things go wrong."""
from __future__ import annotations

import errno
import io
import logging
import re
import tempfile

import numpy as np
import pytest

import senfunet_core.spill as spill_module
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
    # on ~/status from the start, as the README names it (it appeared with the first failure)
    assert engine.counters["spill_failures"] == 0 and engine.counters["spill_failing"] == 0
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


def _centroids(meshes) -> np.ndarray:
    """Centroids of the triangles with an area (those at corners exactly 0 show nothing)."""
    parts = []
    for mesh in meshes:
        t = mesh.vertices[mesh.faces].astype(np.float64)
        area = np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
        parts.append(t[area > 1e-10].mean(axis=1))
    return np.concatenate(parts) if parts else np.zeros((0, 3))


def test_revisits_under_a_small_bound_keep_every_seam_and_no_stale_archived_mesh():
    """The camera goes back and forth between two spheres, seeing each partly again: blocks leave and
    come back while their neighbours stay on disk or in memory. The fused mesh (extracted, as a late
    subscriber's snapshot, and as the updates build it) is the unbounded engine's: no triangle of a cell
    between a block in memory and one on disk is lost when one of them comes back, and no archived mesh
    is shown where the live mesh has the cell (within half a voxel: a seam whose corner block is on disk
    shows the cell as it was when that block left)."""
    from scipy.spatial import cKDTree

    sequence = ([[(SPHERE_C, T)] for T in SPHERE_VIEWS[:3]] + [[v] for v in far_views(3)]
                + [[(SPHERE_C, SPHERE_VIEWS[5])]] + [[v] for v in far_views(6)[3:5]]
                + [[(SPHERE_C, SPHERE_VIEWS[8])], [(SPHERE_C, SPHERE_VIEWS[1])]])

    def run(max_blocks):
        engine, shown = engine_for_tests(max_blocks=max_blocks), {}
        for views in sequence:
            integrate_views(engine, views)
            update = engine.update()
            for key in update.removed:
                shown.pop(tuple(key), None)
            shown.update(update.changed)
        return engine, shown

    (reference, reference_shown), (bounded, bounded_shown) = run(0), run(170)
    assert bounded.stats()["restored_blocks"] > 100
    for mine, theirs in ((bounded.extract_mesh("fused"), reference.extract_mesh("fused")),
                         (bounded.block_meshes().as_dict().values(), reference.block_meshes().as_dict().values()),
                         (bounded_shown.values(), reference_shown.values())):
        mine, theirs = (_centroids([m] if hasattr(m, "faces") else m) for m in (mine, theirs))
        missing = int((cKDTree(mine).query(theirs)[0] > 0.005).sum())
        extra = int((cKDTree(theirs).query(mine)[0] > 0.005).sum())
        assert missing <= 0.001 * len(theirs) and extra <= 0.001 * len(theirs), (missing, extra, len(theirs))
        assert len(cKDTree(mine).query_pairs(1e-6)) <= len(cKDTree(theirs).query_pairs(1e-6))  # no duplicates


def test_an_update_never_sends_a_block_in_memory_without_its_live_mesh():
    """Every block an update sends (or deletes) that is in memory was re-meshed by it: a block's marker
    is its live mesh and what is left of its archived one, never the archived part alone."""
    sequence = ([[(SPHERE_C, T)] for T in SPHERE_VIEWS[:3]] + [[v] for v in far_views(3)]
                + [[(SPHERE_C, SPHERE_VIEWS[5])]] + [[v] for v in far_views(6)[3:5]]
                + [[(SPHERE_C, SPHERE_VIEWS[8])], [(SPHERE_C, SPHERE_VIEWS[1])]])
    engine = engine_for_tests(max_blocks=170)
    meshed: list = []
    block_meshes = engine._block_meshes

    def recording(slots, coords, **kwargs):
        meshed.append({tuple(k) for k in coords.tolist()})
        return block_meshes(slots, coords, **kwargs)

    engine._block_meshes = recording
    for views in sequence:
        integrate_views(engine, views)
        meshed.clear()
        update = engine.update()
        live = {tuple(k) for k in engine.grid.coords[: engine.grid.n_blocks].numpy().tolist()}
        sent = set(update.changed) | set(map(tuple, update.removed))
        assert not (sent & live) - set().union(*meshed)


def test_an_evicted_block_whose_final_mesh_is_empty_is_deleted_from_the_subscribers():
    """A block shown by an update, judged by the net before its eviction and found to hold nothing the
    filter keeps, is archived as nothing: the next update deletes its marker (subscribers showed its
    stale surface forever, which neither ~/save_mesh nor a late subscriber's snapshot has)."""
    from test_engine import SPHERE_K, SPHERE_R, constant_alpha, render_sphere

    engine = engine_for_tests(max_blocks=165)
    constant_alpha(engine, 0.9)  # ToF-only voxels trusted, and only the ToF sees the near sphere
    for T in SPHERE_VIEWS[:2]:
        engine.integrate("tof", render_sphere(SPHERE_C, SPHERE_R, SPHERE_K, T), SPHERE_K, T)
    shown: dict = {}

    def apply(update) -> None:
        for key in update.removed:
            shown.pop(tuple(key), None)
        shown.update(update.changed)

    apply(engine.update())
    near = set(shown)
    constant_alpha(engine, 0.1)  # then distrusted
    integrate_views(engine, far_views(2))  # the near sphere is evicted
    apply(engine.update(alpha_budget_s=0))
    assert engine.stats()["evicted_blocks"] > 50
    in_memory = set(map(tuple, engine.grid.coords[: engine.grid.n_blocks].numpy().tolist()))
    assert not [key for key in near & set(shown) if key not in in_memory and key not in engine.archive]
    assert set(shown) == set(engine.block_meshes().as_dict())  # what subscribers show is the snapshot


def test_the_archive_grows_without_holding_the_data_lock(monkeypatch):
    """Archiving merges the archive's chunks and may write one to disk: integration must not wait for it."""
    from senfunet_core.mesh_archive import MeshArchive

    engine = engine_for_tests(max_blocks=165)
    held = []
    add = MeshArchive.add

    def recording(self, *args, **kwargs):
        held.append(engine.data_lock._is_owned())
        return add(self, *args, **kwargs)

    monkeypatch.setattr(MeshArchive, "add", recording)
    integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]] + far_views(2))
    engine.update()
    assert held and not any(held)


def test_a_bound_of_one_block_evicts_every_block_and_keeps_the_mesh(caplog):
    """max_blocks 1 (smaller than any frame's view): 90% of the bound is no block at all, so every block
    goes; the eviction must not fail (numpy's argpartition was asked for the (n)th of n blocks, which
    raised ValueError at every update and at integration past the hard bound), it is warned about and
    counted as in view, and the fused mesh keeps the evicted surface."""
    caplog.set_level(logging.WARNING, logger="senfunet.engine")
    engine = engine_for_tests(max_blocks=1)
    integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]])  # past the hard bound: evicts itself
    update = engine.update()
    stats = engine.stats()
    assert engine.grid.n_blocks <= 1 and stats["evicted_blocks"] > 100
    assert stats["evicted_in_view_blocks"] > 0 and any("max_blocks 1 " in r.getMessage() for r in caplog.records)
    assert len(update.changed) > 0 and engine.extract_mesh("fused").n_faces > 1000


def test_an_archive_out_of_memory_keeps_the_evicted_meshes_and_archives_them_later(monkeypatch, caplog):
    """Archiving an eviction's final meshes ran out of memory after the blocks' voxels had left: the
    MemoryError failed the frame or the update, and those blocks' meshes were gone from ~/mesh and the
    saved mesh until the sensors saw them again, counted nowhere. They now wait (logged as an error,
    counted as unarchived_blocks), the updates go on, and the next eviction check archives them: the
    fused mesh is then the one of a run that never ran out of memory. A retry that fails too is not
    logged again (it is tried at every update)."""
    from senfunet_core.mesh_archive import MeshArchive

    def run(fail: bool):
        engine = engine_for_tests(max_blocks=165)
        integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]])
        engine.update()
        add = MeshArchive.add
        if fail:
            def out_of_memory(self, *args, **kwargs):
                raise MemoryError("Unable to allocate 64. MiB for an array (test)")
            monkeypatch.setattr(MeshArchive, "add", out_of_memory)
        integrate_views(engine, far_views(2))  # past the hard bound: evicts (does not raise)
        update = engine.update()
        engine.update()  # tried again, still out of memory: logged once
        waiting = engine.stats()["unarchived_blocks"]
        monkeypatch.setattr(MeshArchive, "add", add)
        engine.update()  # archives them
        return engine, update, waiting

    caplog.set_level(logging.ERROR, logger="senfunet.engine")
    reference, _, _ = run(False)
    engine, failed_update, waiting = run(True)
    assert waiting > 0 and engine.bound.archive_failures >= 1
    assert sum("out of memory while archiving" in r.getMessage() for r in caplog.records) == 1
    assert engine.frames_integrated == {"tof": 4, "stereo": 4} and len(failed_update.changed) > 0
    assert engine.stats()["unarchived_blocks"] == 0 and engine.stats()["evicted_blocks"] > 0
    assert len(engine.archive) == len(reference.archive)
    mesh, expected = engine.extract_mesh("fused"), reference.extract_mesh("fused")
    assert mesh.n_faces == expected.n_faces and np.allclose(np.sort(_centroids([mesh]), axis=0),
                                                            np.sort(_centroids([expected]), axis=0), atol=1e-5)


def test_warm_up_under_a_bound_smaller_than_its_frame_leaves_no_eviction_behind(caplog):
    """The node warms its kernels up on a synthetic frame and then resets the map; under max_map_blocks 1 that
    frame was evicted (twice), so ~/status counted evictions that never happened, and the one warning about
    a bound smaller than a frame's view spoke of the synthetic frame, not of the sensors'."""
    from senfunet_core.engine import warm_up

    caplog.set_level(logging.WARNING, logger="senfunet.engine")
    engine = engine_for_tests(max_blocks=1)
    warm_up(engine)
    stats = engine.stats()
    assert stats["evicted_blocks"] == stats["evicted_in_view_blocks"] == 0 and "evictions" not in engine.counters
    assert engine.max_blocks == engine.bound.max_blocks == 1 and not caplog.records
    integrate_views(engine, [(SPHERE_C, SPHERE_VIEWS[0])])
    engine.update()
    warned = [r.getMessage() for r in caplog.records if "smaller than what a frame sees" in r.getMessage()]
    assert len(warned) == 1 and int(re.search(r"which touched (\d+) blocks", warned[0]).group(1)) > 100  # the sphere's
    assert engine.stats()["evicted_blocks"] == engine.stats()["spilled_blocks"] + engine.stats()["restored_blocks"]


class _FillingDisk(io.RawIOBase):
    """A file on a disk that fills at `room[0]` bytes: a write takes what fits, the next raises ENOSPC."""

    def __init__(self, file: io.FileIO, room: list[int | None]) -> None:
        self._file, self._room = file, room

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        return self._file.readinto(buffer)

    def write(self, data) -> int:
        size, room = memoryview(data).nbytes, self._room[0]
        if room is not None and self._file.tell() + size > room:
            if self._file.tell() >= room:
                raise OSError(errno.ENOSPC, "No space left on device")
            size = room - self._file.tell()
        return self._file.write(memoryview(data).cast("B")[:size])

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._file.seek(offset, whence)

    def tell(self) -> int:
        return self._file.tell()

    def close(self) -> None:
        self._file.close()
        super().close()


def test_a_spill_without_room_is_known_before_the_victims_are_judged(monkeypatch, tmp_path):
    """A full spill disk: each retry judged and meshed thousands of victims (seconds, integration
    waiting) before the write failed. The room is checked first; nothing is judged for an eviction
    that cannot be written. A spill folder removed while the node runs (a temp cleaner) is made again."""
    class NoRoom:
        f_bavail, f_frsize = 1, 4096

    folder = tmp_path / "tmp"
    monkeypatch.setattr(spill_module.tempfile, "tempdir", str(folder))  # TMPDIR, gone before the first spill
    for room in (False, True):
        engine = engine_for_tests(max_blocks=165)
        integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]])
        engine.update()
        with monkeypatch.context() as patch:
            if not room:
                patch.setattr(spill_module.os, "statvfs", lambda fd: NoRoom())
            integrate_views(engine, far_views(2))
            engine.update()
        if room:
            assert folder.is_dir() and engine.grid.n_blocks <= 165 and engine.stats()["evicted_blocks"] > 0
        else:
            assert engine.counters["spill_failures"] >= 1 and engine.stats()["evicted_blocks"] == 0
            assert engine.bound._judged == 0 and engine.grid.n_blocks > 165


def test_a_disk_that_fills_after_an_eviction_keeps_the_spilled_blocks_readable(monkeypatch):
    """The spill file was buffered: an eviction's last blobs stayed in the buffer after `put` returned, and
    a disk that filled then failed their flush at the next read, when a frame reached a spilled block
    (the frame raised from the grid's block allocation, which left the grid's hash table ahead of its
    blocks: the next frame crashed the process). The disk is simulated under the buffer, where the
    kernel refuses the writes."""
    room: list[int | None] = [None]
    files: list[_FillingDisk] = []
    temporary_file = tempfile.TemporaryFile

    def on_the_disk(*args, buffering: int = -1, **kwargs):
        if not kwargs.get("prefix", "").startswith("senfunet-spill-"):  # the mesh archive's files
            return temporary_file(*args, buffering=buffering, **kwargs)
        raw = _FillingDisk(temporary_file(*args, buffering=0, **kwargs), room)
        files.append(raw)
        return raw if buffering == 0 else io.BufferedRandom(raw)

    monkeypatch.setattr(spill_module.tempfile, "TemporaryFile", on_the_disk)
    engine = engine_for_tests(max_blocks=165)
    integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]] + far_views(2))
    engine.update()
    spill = engine.grid.spill
    assert spill is not None and len(spill) > 0 and len(files) == 1
    room[0] = files[0].tell() + 100  # the disk is full from now on, but for 100 bytes
    integrate_views(engine, [(SPHERE_C, SPHERE_VIEWS[0])])  # back at the first sphere: its blocks come back
    assert engine.frames_integrated == {"tof": 5, "stereo": 5} and spill.restored > 0
    spilled = len(spill)
    integrate_views(engine, far_views(4)[2:])
    engine.update()  # an eviction while the disk is full: abandoned, its blocks stay (a write taken in part too)
    assert engine.counters["spill_failures"] >= 1 and len(spill) == spilled
    room[0] = None
    integrate_views(engine, [(SPHERE_C, SPHERE_VIEWS[1])])
    engine.update()
    assert engine.frames_integrated == {"tof": 8, "stereo": 8} and engine.grid.n_blocks <= 165


def test_a_spill_that_fails_a_read_keeps_the_grid_whole(monkeypatch):
    """A frame reaching spilled blocks when the disk fails their read (EIO): the grid's block allocation
    raised with the blocks added to the hash table past the committed slots, and the next frame that
    reached them crashed the process (a segfault in the integration kernels). The frame is lost (it
    raises), the blocks stay spilled and come back with the next frame."""
    import torch

    engine = engine_for_tests(max_blocks=165)
    integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[:2]] + far_views(2))
    engine.update()
    spill = engine.grid.spill
    spilled = spill.state_dict()["keys"]
    assert len(spilled) > 0
    take = BlockSpill.take

    def failing_read(self, keys, rows):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(BlockSpill, "take", failing_read)
    with pytest.raises(OSError, match="Input/output error"):
        integrate_views(engine, [(SPHERE_C, SPHERE_VIEWS[0])])
    slots = engine.grid.lookup_keys(torch.from_numpy(spilled)).numpy()
    assert (slots < engine.grid.n_blocks).all()  # no key of a block not added
    assert len(spill) == len(spilled)
    monkeypatch.setattr(BlockSpill, "take", take)
    integrate_views(engine, [(SPHERE_C, SPHERE_VIEWS[0])])
    assert spill.restored > 0 and engine.frames_integrated == {"tof": 5, "stereo": 5}


def test_a_budgeted_update_evicts_in_turns_and_reaches_the_bound():
    """A live mesh update evicted down to the bound in one go: on a room-sized map the refresh waited for
    the whole eviction (30-40 s on ~/mesh). With the update's mesh budget, it evicts a slice at a time
    until the budget is spent; the next updates go on, until the map is within the bound."""
    whole = engine_for_tests(max_blocks=180, alpha_batch_blocks=8)
    in_turns = engine_for_tests(max_blocks=180, alpha_batch_blocks=8)
    for engine in (whole, in_turns):
        integrate_views(engine, [(SPHERE_C, T) for T in SPHERE_VIEWS[:5]])  # past the bound, not the hard bound
    before = in_turns.grid.n_blocks
    assert 180 < before < 225
    whole.update()
    assert whole.grid.n_blocks <= 180 and whole.bound.evictions == 1
    in_turns.update(mesh_budget_s=0.0)
    assert whole.grid.n_blocks < in_turns.grid.n_blocks < before and in_turns.bound.evictions == 1  # one slice
    updates = 1
    while in_turns.grid.n_blocks > 180 and updates < 20:
        in_turns.update(mesh_budget_s=0.0)
        updates += 1
    assert in_turns.grid.n_blocks <= 180 and updates > 1 and in_turns.bound.evictions == updates
