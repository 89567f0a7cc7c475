"""The mesh archive's storage (mesh_chunks) and its per-cell rule (mesh_archive) against plain references."""
from __future__ import annotations

import numpy as np
import pytest

from senfunet_core.block_mesher import joined
from senfunet_core.mesh_archive import MeshArchive, drop_meshable, blocks_around, union
from senfunet_core.mesh_chunks import MeshChunks, packed_keys as packed
from senfunet_core.mesher import BlockMeshes, Mesh

VOXEL = 0.01


def random_mesh(rng: np.random.Generator, key: tuple[int, int, int], n_faces: int) -> Mesh:
    """Triangles inside block `key` and its +1 neighbours (as marching cubes' cells reach)."""
    n_vertices = n_faces + 2
    origin = np.array(key) * 8 * VOXEL
    vertices = (origin + rng.uniform(0, 9 * VOXEL, (n_vertices, 3))).astype(np.float32)
    faces = rng.integers(0, n_vertices, (n_faces, 3)).astype(np.int32)
    return Mesh(vertices, faces, rng.random((n_vertices, 3)).astype(np.float32))


def random_batch(rng: np.random.Generator, n_keys: int, key_range: int) -> dict[tuple[int, int, int], Mesh]:
    keys = {tuple(k) for k in rng.integers(-key_range, key_range, (n_keys, 3)).tolist()}
    return {key: random_mesh(rng, key, int(rng.integers(1, 40))) for key in keys}


def assert_same(mesh: Mesh, expected: Mesh) -> None:
    np.testing.assert_array_equal(mesh.vertices, expected.vertices)
    np.testing.assert_array_equal(mesh.faces, expected.faces)
    np.testing.assert_array_equal(mesh.colors, expected.colors)


def test_chunks_hold_what_a_dict_holds_through_puts_removals_merges_and_files(tmp_path):
    """Random puts (replacing keys held before) and removals, with chunks small enough that they merge,
    move to files and are rewritten: every read equals a dict's, and what stays in RAM is bounded."""
    rng = np.random.default_rng(3)
    seal_bytes = 20_000
    chunks = MeshChunks(directory=str(tmp_path), seal_bytes=seal_bytes)
    reference: dict[tuple[int, int, int], Mesh] = {}
    most_in_memory = 0
    for step in range(120):
        batch = random_batch(rng, int(rng.integers(1, 30)), key_range=12)
        removed = [k for k in reference if rng.random() < 0.02 and k not in batch]
        chunks.put(BlockMeshes.from_meshes(batch), removed=packed(removed) if removed else None)
        reference.update(batch)
        for key in removed:
            del reference[key]
        most_in_memory = max(most_in_memory, chunks.bytes_in_memory)
        if step % 20 == 19:
            assert len(chunks) == len(reference)
            assert chunks.n_faces == sum(m.n_faces for m in reference.values())
            held = chunks.select(packed(list(reference))).as_dict()
            assert held.keys() == reference.keys()
            for key, mesh in reference.items():
                assert_same(held[key], mesh)
    every = BlockMeshes.concatenate(list(chunks.parts())).as_dict()
    assert every.keys() == reference.keys()
    for key in reference:
        assert_same(every[key], reference[key])
    some = sorted(reference)[::3] + [(99, 99, 99)]  # one never held
    selected = chunks.select(packed(some)).as_dict()
    assert selected.keys() == set(some[:-1])
    # most of it went to files, read through memory maps, and RAM held a few chunks' worth at most
    assert chunks.bytes_on_disk > 4 * seal_bytes
    assert any(isinstance(part.vertices, np.memmap) for part in (c.meshes for c in chunks._chunks))
    assert most_in_memory < 4 * seal_bytes


def test_a_chunk_that_cannot_be_written_stays_in_memory_and_is_counted(tmp_path):
    chunks = MeshChunks(directory=str(tmp_path / "missing"), seal_bytes=5_000)
    rng = np.random.default_rng(4)
    batch = random_batch(rng, 60, key_range=20)
    chunks.put(BlockMeshes.from_meshes(batch))
    assert chunks.seal_failures >= 1 and chunks.bytes_on_disk == 0
    held = chunks.select(packed(list(batch))).as_dict()
    for key, mesh in batch.items():
        assert_same(held[key], mesh)


def test_every_mesh_is_copied_a_logarithmic_number_of_times(monkeypatch):
    """Putting n batches one by one copies each mesh O(log n) times (not once per put, as one array of
    them all would): counted at the copy every chunk is made by."""
    import senfunet_core.mesh_chunks as mc

    made_rows = []
    new_chunk = mc._new_chunk
    monkeypatch.setattr(mc, "_new_chunk", lambda meshes, **kw: made_rows.append(len(meshes)) or new_chunk(meshes, **kw))
    chunks = MeshChunks(seal_bytes=1 << 40)  # never on disk: the merging alone
    rng = np.random.default_rng(5)
    n_batches, per_batch = 256, 10
    for i in range(n_batches):
        keys = [(i, j, 0) for j in range(per_batch)]
        chunks.put(BlockMeshes.from_meshes({k: random_mesh(rng, k, 4) for k in keys}))
    assert len(chunks) == n_batches * per_batch
    copies_per_mesh = sum(made_rows) / len(chunks)
    assert copies_per_mesh <= np.log2(n_batches) + 2
    assert len(chunks._chunks) <= np.log2(n_batches) + 2


def test_archive_reads_equal_the_rule_over_the_whole_archive(tmp_path):
    """`visible` looks for meshable cells only next to blocks in memory, `held` and `union` work on
    packed keys: each equals the plain rule over every archived block."""
    rng = np.random.default_rng(6)
    archive = MeshArchive(directory=str(tmp_path), seal_bytes=30_000)
    in_memory = np.sort(packed(rng.integers(-6, 6, (150, 3))))
    for _ in range(10):
        archive.add(BlockMeshes.from_meshes(random_batch(rng, 40, key_range=10)), in_memory, VOXEL)
    assert archive.chunks.bytes_on_disk > 0
    every = archive.meshes()
    expected = drop_meshable(every, in_memory, VOXEL).as_dict()
    visible = archive.visible(in_memory, VOXEL).as_dict()
    assert visible.keys() == expected.keys() and len(expected) < len(every)  # some cells are dropped
    for key in expected:
        assert_same(visible[key], expected[key])
    coords = rng.integers(-10, 10, (20, 3))
    around = {tuple((c + np.array(d) - 1).tolist()) for c in coords for d in np.ndindex(3, 3, 3)}
    assert archive.held(blocks_around(coords)) == archive.held(coords, around=True) == around & set(every.as_dict())
    assert not MeshArchive().held(coords, around=True)
    live = BlockMeshes.from_meshes(random_batch(rng, 50, key_range=10))
    joined = union(live, every).as_dict()
    live_d, every_d = live.as_dict(), every.as_dict()
    assert joined.keys() == live_d.keys() | every_d.keys()
    for key, mesh in joined.items():
        parts = [m for m in (live_d.get(key), every_d.get(key)) if m is not None]
        assert mesh.n_faces == sum(p.n_faces for p in parts)
        np.testing.assert_array_equal(mesh.vertices, np.concatenate([p.vertices for p in parts]))


@pytest.mark.parametrize("seal_bytes", [1 << 40, 20_000])
def test_archive_prune_and_add_keep_what_cells_still_need(tmp_path, seal_bytes):
    """prune drops a block's meshable triangles and forgets a block left empty; add keeps, beside a
    block's new mesh, the old triangles of cells not all in memory."""
    rng = np.random.default_rng(7)
    archive = MeshArchive(directory=str(tmp_path), seal_bytes=seal_bytes)
    first = random_batch(rng, 80, key_range=6)
    archive.add(BlockMeshes.from_meshes(first), np.zeros(0, np.int64), VOXEL)
    in_memory = np.sort(packed(list(first)[:40] + [(k[0] + 1, k[1] + 1, k[2] + 1) for k in list(first)[:40]]))
    expected = drop_meshable(BlockMeshes.from_meshes(first), in_memory, VOXEL).as_dict()
    archive.prune(set(first), in_memory, VOXEL)
    assert set(archive.meshes().as_dict()) == set(expected) and len(expected) < len(first)
    selected = archive.select(expected).as_dict()
    for key in expected:
        assert_same(selected[key], expected[key])
    assert all(key in archive for key in expected) and not any(key in archive for key in set(first) - set(expected))
    again = {key: random_mesh(rng, key, 5) for key in list(first)[:20]}
    archive.add(BlockMeshes.from_meshes(again), in_memory, VOXEL)
    selected = archive.select(again).as_dict()
    for key, mesh in again.items():
        held = selected[key]
        old = expected.get(key)
        kept = drop_meshable(BlockMeshes.from_meshes({key: old}), in_memory, VOXEL) if old is not None else None
        assert held.n_faces == mesh.n_faces + (kept.face_offsets[-1] if kept is not None else 0)


def test_archive_state_round_trips_from_its_files(tmp_path):
    """A saved map takes the archive whole, its memory-mapped chunks included, as writable arrays."""
    rng = np.random.default_rng(8)
    archive = MeshArchive(directory=str(tmp_path), seal_bytes=10_000)
    for _ in range(6):
        archive.add(BlockMeshes.from_meshes(random_batch(rng, 30, key_range=9)), np.zeros(0, np.int64), VOXEL)
    assert archive.chunks.bytes_on_disk > 0
    state = archive.state_dict()
    assert all(not isinstance(a, np.memmap) and a.flags.writeable for a in state.values())
    loaded = MeshArchive()
    loaded.load_state_dict(state)
    expected, got = archive.meshes().as_dict(), loaded.meshes().as_dict()
    assert got.keys() == expected.keys() and len(got) == len(archive)
    for key in expected:
        assert_same(got[key], expected[key])


def test_rewriting_two_mostly_dead_chunks_that_merge_keeps_every_mesh():
    """One put leaves two chunks mostly dead, and the first one's rewrite merges with the second: the
    second must not be rewritten again from the list taken before (it raised ValueError, an eviction's
    archive update failing after its blocks had left memory)."""
    rng = np.random.default_rng(5)
    chunks = MeshChunks()
    big = {(i, 0, 0): random_mesh(rng, (i, 0, 0), 2) for i in range(100)}
    small = {(i, 1, 0): random_mesh(rng, (i, 1, 0), 2) for i in range(40)}
    chunks.put(BlockMeshes.from_meshes(big))
    chunks.put(BlockMeshes.from_meshes(small))
    assert len(chunks._chunks) == 2  # too different in size to merge
    removed = list(big)[:60] + list(small)[:25]
    chunks.put(BlockMeshes.concatenate([]), removed=packed(removed))
    reference = {key: mesh for key, mesh in {**big, **small}.items() if key not in removed}
    assert len(chunks) == len(reference) and chunks.n_faces == 2 * len(reference)
    held = chunks.select(packed(list(reference))).as_dict()
    assert held.keys() == reference.keys()
    for key, mesh in reference.items():
        assert_same(held[key], mesh)


def test_a_face_triangle_belongs_to_the_cell_in_the_block_it_is_archived_under():
    """A triangle on the face between two cells of different blocks was counted as either cell's:
    archived under block A (its cell there, the other in block B), it went when A was evicted before
    B and prune ran with B alone in memory, though B's mesh need not have it. Its block tells."""
    voxel = VOXEL
    z_m = 24 * voxel  # the face between cells z = 23 (block z 2) and z = 24 (block z 3)
    triangle = Mesh(np.array([[284.2, 8.2, 24.0], [284.8, 8.3, 24.0], [284.4, 8.9, 24.0]], np.float32) * voxel,
                    np.array([[0, 1, 2]], np.int32))
    assert float(triangle.vertices[0, 2]) == pytest.approx(z_m)
    below, above = (35, 1, 2), (35, 1, 3)
    for key, survives_with_above_alone in ((below, True), (above, False)):
        archive = MeshArchive()
        archive.add(BlockMeshes.from_meshes({key: triangle}), np.zeros(0, np.int64), voxel)
        archive.prune({key}, np.sort(packed([above])), voxel)  # block z 2 is on disk, z 3 in memory
        assert (key in archive) == survives_with_above_alone, key
        archive.prune({key}, np.sort(packed([below, above])), voxel)  # both in memory: the live mesh has it
        assert key not in archive


def test_a_block_evicted_again_and_again_beside_one_on_disk_keeps_its_archived_mesh_from_growing():
    """A block goes back and forth between memory and disk while its neighbour stays on disk (a long run
    under a map bound): each time it comes back an update prunes its archived mesh to the seam cell
    that reaches the neighbour, and each time it leaves its new mesh joins what is kept. The triangles
    that go take their vertices with them: the archived mesh stays the new mesh and the seam (every
    vertex used), however many times the block was evicted (it grew by a mesh's vertices each time)."""
    block = (0, 0, 0)  # its neighbour (1, 0, 0) stays on disk
    voxels = np.array([[3.2, 3.3, 3.1], [3.8, 3.4, 3.2], [3.4, 3.9, 3.6],  # a cell inside the block
                       [7.6, 3.2, 3.3], [7.7, 3.8, 3.4], [7.3, 3.4, 3.9]])  # the cell x 7..8: its corners x 8 on disk
    interior = Mesh((voxels[:3] * VOXEL).astype(np.float32), np.array([[0, 1, 2]], np.int32),
                    np.full((3, 3), 0.5, np.float32))
    seam = Mesh((voxels[3:] * VOXEL).astype(np.float32), np.array([[0, 1, 2]], np.int32),
                np.full((3, 3), 0.25, np.float32))
    in_memory = np.sort(packed([block]))
    archive = MeshArchive()
    archive.add(BlockMeshes.from_meshes({block: joined([interior, seam])}), in_memory, VOXEL)
    for _ in range(12):
        archive.prune({block}, in_memory, VOXEL)  # back in memory: the live mesh has the inside cell
        held = archive.select([block]).as_dict()[block]
        assert held.n_faces == 1 and len(held.vertices) == 3
        archive.add(BlockMeshes.from_meshes({block: interior}), in_memory, VOXEL)  # evicted again
        held = archive.select([block]).as_dict()[block]
        assert held.n_faces == 2 and len(held.vertices) == 6
        np.testing.assert_array_equal(np.sort(held.vertices[held.faces].reshape(-1, 3), axis=0),
                                      np.sort(np.concatenate([interior.vertices, seam.vertices]), axis=0))


def test_a_merge_that_runs_out_of_memory_loses_no_archived_mesh(monkeypatch):
    """Merging two chunks (up to MAX_CHUNK_BYTES_PER_SEAL * seal_bytes, 256 MB) popped both before the
    copy that joins them: a MemoryError in that copy lost the final meshes of every block they held,
    and the archive went on without them (map data dropped). Now the merge is made first."""
    import senfunet_core.mesh_chunks as mc

    chunks = MeshChunks(seal_bytes=1 << 40)
    rng = np.random.default_rng(6)
    first = {(0, j, 0): random_mesh(rng, (0, j, 0), 4) for j in range(10)}
    chunks.put(BlockMeshes.from_meshes(first))
    new_chunk = mc._new_chunk

    def no_memory(meshes, **kwargs):
        raise MemoryError("Unable to allocate 256. MiB for an array")

    monkeypatch.setattr(mc, "_new_chunk", lambda meshes, **kw: (no_memory if len(meshes) > 10 else new_chunk)(meshes,
                                                                                                            **kw))
    second = {(1, j, 0): random_mesh(rng, (1, j, 0), 4) for j in range(10)}
    with pytest.raises(MemoryError):
        chunks.put(BlockMeshes.from_meshes(second))  # its chunk is made, the merge with the first fails
    monkeypatch.undo()
    held = chunks.select(packed(list(first) + list(second))).as_dict()
    assert len(chunks) == len(held) == 20
    for key, mesh in {**first, **second}.items():
        assert_same(held[key], mesh)
