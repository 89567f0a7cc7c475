"""The map bound: past `max_blocks`, the blocks farthest from the camera leave memory, not the mesh.

An eviction takes the map down to 90% of the bound (so that it does not happen every update), in
slices (SLICE_OF_BOUND of the bound each) unless the integrating thread evicts. A slice picks the
blocks farthest from the last camera position, those the latest frames touched last, evaluates
the weighting net where their final fused meshes read a stale alpha and where alpha reads their
voxels, meshes them, and archives those meshes (`mesh_archive`) with the seam triangles of the
staying blocks' cells that read them; then the store drops the blocks, their voxels going to the
grid's spill (`spill`) to come back when a frame reaches them again.

When evictions run and which locks they hold is the engine's business (see its threading model):
`MapBound.evict` is called with the update lock held and takes the data lock it is given only to
pick each slice's victims, to redo what a frame changed meanwhile, and to remove them; it has the
weighting net judge on the alpha threads side by side while integration waits for it.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from .alpha_scheduler import AlphaScheduler
from .block_mesher import MESH_READ_CODES, MESH_READER_CODES, BlockMesher, with_seams
from .block_store import BlockStore, Eviction
from .mesh_archive import MeshArchive, drop_meshable
from .mesh_chunks import packed_keys
from .machine import MemoryBudget, memory_budget
from .mesher import BlockMeshes

__all__ = ["HARD_BOUND", "MapBound", "memory_bound_blocks"]

log = logging.getLogger("senfunet.engine")

# integration itself has blocks evicted once the map exceeds max_blocks by this factor (updates do it first)
HARD_BOUND = 1.25
# the blocks the latest this many frames touched are evicted last: they are in view wherever the camera
# looks, while the blocks nearest it may lie behind it
RECENT_FRAMES = 10
# an eviction removes its victims in slices of this share of the bound: an integration waiting at the
# hard bound waits for one slice (its judging and meshing), not for all of them
SLICE_OF_BOUND = 0.05


def memory_bound_blocks(bytes_per_block: int, *, memory_fraction: float = 0.5,
                        budget: MemoryBudget | None = None) -> int:
    """How many blocks fit in `memory_fraction` of the memory this process may use (at most 80% of
    what is available now; `memory.memory_budget`: the machine's, or its container's limit): the
    default map bound follows the machine, not a fixed count."""
    budget = budget or memory_budget()
    usable = min(memory_fraction * budget.total_bytes, 0.8 * budget.available_bytes)
    return max(1024, int(usable // bytes_per_block))


class MapBound:
    """Evicts blocks past `max_blocks` (0: no bound), keeping their final meshes in `archive`."""

    def __init__(self, store: BlockStore, alpha: AlphaScheduler, mesher: BlockMesher, data_lock: threading.RLock, *,
                 max_blocks: int, voxel_size_m: float, alpha_batch_blocks: int) -> None:
        self.store = store
        self.alpha = alpha
        self.mesher = mesher
        self._data_lock = data_lock
        self.max_blocks = max_blocks
        self.voxel_size_m = voxel_size_m
        self.alpha_batch_blocks = alpha_batch_blocks
        self.archive = MeshArchive()  # final meshes of evicted blocks
        self.newly_archived: list[BlockMeshes] = []  # archived since the last update took them
        self.pruned_keys: set[tuple[int, int, int]] = set()  # archived meshes an eviction pruned (ditto)
        self.camera_m = np.zeros(3)  # the last integrated frame's camera centre: what is near it stays
        self._frame_s = np.nan  # when the last frame touched its blocks (their store.touched_s)
        # ... and the latest RECENT_FRAMES frames: what they touched stays before what is nearest the camera
        self._recent_frames_s: deque[float] = deque(maxlen=RECENT_FRAMES)
        self._frame_blocks = 0  # how many blocks it touched
        self.evicted_blocks = 0
        self.evictions = 0
        self.unarchived: list[BlockMeshes] = []  # final meshes of evicted blocks the archive could not take yet
        self.archive_failures = 0  # ... how often that happened
        self.spill_failures = 0  # evictions abandoned because the spill could not be written (blocks kept)
        self._retry_at_blocks = 0  # after such a failure: no eviction is tried until the map holds this many
        self.evicted_in_view = 0  # evicted blocks that the sensors' latest frames had reached
        self._judged, self._judge_s = 0, 0.0  # the current eviction's: blocks the net judged, and how long

    def clear(self) -> None:
        """Forget the archive and the camera (the map was reset)."""
        self.archive.clear()
        self.newly_archived = []
        self.unarchived = []
        self.pruned_keys = set()
        self.camera_m = np.zeros(3)
        self._frame_s, self._frame_blocks = np.nan, 0
        self._recent_frames_s.clear()
        self.evicted_blocks = self.evictions = self.evicted_in_view = 0  # of the map that was
        self._retry_at_blocks = 0

    def frame_integrated(self, *, camera_m: np.ndarray, touched_s: float, n_touched: int) -> None:
        """A frame was integrated (data lock held): the blocks near its camera stay. Its blocks are
        stamped `touched_s` in the store: should the bound evict one of them, it is smaller than a
        frame's view and thrashes."""
        self.camera_m = camera_m
        self._frame_s, self._frame_blocks = touched_s, n_touched
        self._recent_frames_s.append(touched_s)

    def over_hard_bound(self) -> bool:
        """Integration outgrew the bound by HARD_BOUND: an eviction is due before it goes on."""
        return (self.max_blocks > 0 and self.store.n_blocks > HARD_BOUND * self.max_blocks
                and self.store.n_blocks >= self._retry_at_blocks)

    def tallies(self) -> dict[str, int]:
        """What evictions did to this map (a saved map keeps them, `restore_tallies`)."""
        return {"evicted_blocks": self.evicted_blocks, "evictions": self.evictions,
                "evicted_in_view_blocks": self.evicted_in_view}

    def restore_tallies(self, tallies: dict[str, int]) -> None:
        self.evicted_blocks = int(tallies.get("evicted_blocks", 0))
        self.evictions = int(tallies.get("evictions", 0))
        self.evicted_in_view = int(tallies.get("evicted_in_view_blocks", 0))

    def take_pruned(self) -> set[tuple[int, int, int]]:
        """The archived blocks evictions pruned since the last call (the next update re-sends them)."""
        pruned, self.pruned_keys = self.pruned_keys, set()
        return pruned

    def take_archived(self) -> BlockMeshes:
        """The meshes archived since the last call (the next update sends them)."""
        archived = BlockMeshes.concatenate(self.newly_archived)
        self.newly_archived = []
        return archived

    def evict(self, *, integration_waits: bool = False, removed: Callable[[], None] | None = None,
              budget_s: float | None = None) -> Eviction | None:
        """Evict the blocks farthest from the camera if the map holds more than `max_blocks` (see
        the module docstring); None when it does not. Their neighbours' cells that reached into them
        are re-meshed without them by the next update (so a snapshot equals what the updates sent).

        The victims go in slices of SLICE_OF_BOUND of the bound, each picked, judged, meshed and
        removed in turn, `removed()` called after each: an integration waiting at the hard bound
        goes on after the first slice, not after the whole eviction (in one slice when the caller is
        the integrating thread itself). The net judges on the alpha
        threads side by side while integration waits for it (`integration_waits`: the caller is
        the integrating thread; or the map is past the hard bound), else on this thread alone.
        `budget_s`: no further slice once this long has passed, unless the map is past the hard bound
        (a live mesh update: its refresh waits for about one slice past it, not the whole eviction;
        the next update goes on)."""
        store = self.store
        if self.unarchived:  # final meshes an earlier eviction could not archive (`_archive`), less the
            # cells of blocks that came back since (the live mesh has them); theirs counted as in memory, as
            # when an eviction archives its victims
            with self._data_lock:
                in_memory = np.sort(store.grid.slot_keys[: store.n_blocks])
            waiting, self.unarchived = BlockMeshes.concatenate(self.unarchived), []
            self._archive(drop_meshable(waiting, in_memory, self.voxel_size_m), waiting.keys,
                          np.union1d(in_memory, packed_keys(waiting.keys)), again=True)
        if self.max_blocks <= 0 or store.n_blocks <= self.max_blocks or store.n_blocks < self._retry_at_blocks:
            return None
        t0 = time.perf_counter()
        # what integration adds meanwhile stays for the next eviction: this one ends
        left = store.n_blocks - int(0.9 * self.max_blocks)
        # one slice when the integrating thread evicts: nobody else waits, and each slice costs a pick,
        # seam meshes and a removal
        slice_blocks = left if integration_waits else max(self.alpha_batch_blocks,
                                                          int(SLICE_OF_BOUND * self.max_blocks))
        eviction: Eviction | None = None
        self._judged, self._judge_s, slices = 0, 0.0, 0
        while left > 0:
            part = self._evict_slice(min(left, slice_blocks),
                                     side_by_side=lambda: integration_waits or self.over_hard_bound())
            if part is None:  # the spill could not be written: what was removed so far stays removed
                break
            eviction = part if eviction is None else eviction.then(part)
            left -= len(part.dropped_keys)
            slices += 1
            if removed is not None:
                removed()
            if budget_s is not None and time.perf_counter() - t0 >= budget_s and not self.over_hard_bound():
                break
        if eviction is None:
            return None
        self.evictions += 1
        spill = store.grid.spill
        log.info("map bound: evicted %d blocks farthest from the camera (max_blocks %d; %d evicted so far, their "
                 "final meshes kept: %d archived blocks; their voxels on disk until seen again: %d blocks, %.0f MB) "
                 "in %.2f s (%d slices; the net judged %d blocks around them in %.2f s)", len(eviction.dropped_keys),
                 self.max_blocks, self.evicted_blocks, len(self.archive),
                 len(spill) if spill is not None else 0, (spill.nbytes if spill is not None else 0) / 1e6,
                 time.perf_counter() - t0, slices, self._judged, self._judge_s)
        return eviction

    @property
    def spill_failing(self) -> bool:
        """Whether the latest eviction was abandoned for its spill (until one goes through)."""
        return self._retry_at_blocks > 0

    def _abandon(self, count: int, err: OSError) -> None:
        """An eviction whose spill cannot be written: the blocks stay in memory (nothing is lost, nothing
        archived); tried again once the map grew by a tenth of the bound, not at every frame and update."""
        self.spill_failures += 1
        self._retry_at_blocks = self.store.n_blocks + max(1, self.max_blocks // 10)
        log.error("map bound: eviction of %d blocks abandoned, they stay in memory (the map now exceeds max_blocks "
                  "%d): %s. Tried again when the map holds %d blocks; counted as spill_failures", count,
                  self.max_blocks, err, self._retry_at_blocks)

    def _evict_slice(self, count: int, *, side_by_side: Callable[[], bool]) -> Eviction | None:
        """Evict the `count` blocks farthest from the camera (`evict`'s slice); None when the spill
        could not be written (the blocks stay)."""
        store = self.store
        if store.grid.spill is not None:
            try:  # a spill that cannot take them: known before the victims are judged and meshed (seconds)
                store.grid.spill.check_room(count, store.grid.bytes_per_block())
            except OSError as err:
                self._abandon(count, err)
                return None
        with self._data_lock:
            victims = store.farthest(self.camera_m, keep=store.n_blocks - count, voxel_size_m=self.voxel_size_m,
                                     touched_since_s=self._recent_frames_s[0] if self._recent_frames_s else np.inf)
            in_view = int((store.touched_s[victims] >= self._frame_s).sum())
            victim_coords = store.grid.coords[victims].numpy()  # copies (fancy index)
            around_victims = store.neighbours(victims)
            read = around_victims[:, MESH_READ_CODES]  # the blocks the victims' cells read
            readers = around_victims[:, MESH_READER_CODES]  # the blocks whose cells read victims
            readers = np.setdiff1d(readers[readers >= 0], victims)
            scope = store.neighbours(np.union1d(victims, readers))[:, MESH_READ_CODES]
            # every block whose alpha the final meshes read, and every block whose alpha reads the victims'
            # voxels: judged now, with them; judged after they left, a later slice's final meshes (or the
            # live ones) would read an alpha that lacks them
            around = np.unique(np.concatenate([scope[scope >= 0], around_victims[around_victims >= 0]]))
        # Judged and meshed without the data lock, so that integration goes on meanwhile (slots move
        # only in evictions, which the update lock serialises) ...
        self.alpha.schedule()
        # (a block found to hold no voxel alpha matters for, and not stale since, still holds none)
        unjudged = around[(store.stale[around] > 0) | ~(store.evaluated[around] | store.no_targets[around])]
        archived = self._final_meshes(victims, victim_coords, unjudged, side_by_side)
        with self._data_lock:
            # ... and again, under it, where a frame changed them in the meantime
            touched = around[store.alpha_pending[around]]
            self.alpha.schedule()
            changed = np.union1d(touched, around[store.stale[around] > 0])
            if len(changed):
                again = np.flatnonzero(np.isin(read, changed).any(axis=1))
                redone = {tuple(key) for key in victim_coords[again].tolist()}
                older = [key not in redone for key in map(tuple, archived.keys.tolist())]
                # (integration waits for the data lock held here: judged side by side)
                archived = BlockMeshes.concatenate([archived.select(np.flatnonzero(older)),
                                                    self._final_meshes(victims[again], victim_coords[again],
                                                                       around[store.stale[around] > 0],
                                                                       lambda: True)])
            archived = with_seams(archived, self.mesher.seam_meshes(readers, victim_coords))
            in_memory = np.sort(store.grid.slot_keys[: store.n_blocks])  # the victims still among them
            try:  # first: a spill that cannot be written leaves the store as it was
                eviction = store.remove(victims)
            except OSError as err:
                self._abandon(len(victim_coords), err)
                return None
            self._retry_at_blocks = 0
        # The archive is the update lock's (held): changed without the data lock, so that integration goes on
        # meanwhile. Archived triangles of cells whose corners were all in memory until now (a block came back
        # since the last update) go: the final meshes just made have those cells; what a victim had archived
        # from an earlier eviction, for cells its new mesh cannot have (a corner block still on disk), stays.
        self._archive(archived, victim_coords, in_memory)
        self.evicted_blocks += len(victim_coords)
        if in_view:
            if not self.evicted_in_view:
                log.warning("map bound: max_blocks %d is smaller than what a frame sees: %d of the %d blocks "
                            "evicted were reached by the latest frame (which touched %d blocks), so they come back "
                            "from disk at once and the map thrashes; raise max_map_blocks well above that (-1 follows "
                            "this machine's memory). Counted as evicted_in_view_blocks; warned once.",
                            self.max_blocks, in_view, len(victim_coords), self._frame_blocks)
            self.evicted_in_view += in_view
        return eviction

    def _archive(self, meshes: BlockMeshes, coords: np.ndarray, in_memory: np.ndarray, *, again: bool = False
                 ) -> None:
        """Archive evicted blocks' final meshes (`coords`: the blocks', `in_memory`: the sorted packed
        keys of the blocks in memory, these among them). Out of memory, they wait in `unarchived`
        (counted on ~/status; logged once while any wait) and are tried again (`again`) at the next
        eviction check: their voxels already left, so these meshes are all that is left of the blocks
        until the sensors see them again."""
        try:
            near = self.archive.held(coords, around=True)
            self.archive.prune(near, in_memory, self.voxel_size_m)
            self.pruned_keys |= near  # the next update shows what is left of them
            self.archive.add(meshes, in_memory, self.voxel_size_m)
        except MemoryError:
            first = not again and not self.unarchived  # of a spell short of memory: logged once
            self.unarchived.append(meshes)
            self.archive_failures += 1
            log.log(logging.ERROR if first else logging.DEBUG,
                    "map bound: out of memory while archiving the final meshes of %d evicted blocks: ~/mesh, "
                    "~/save_mesh and ~/save_map lack them until an eviction check archives them (tried at each "
                    "mesh update; counted as unarchived_blocks on ~/status). Lower max_map_blocks or free memory.",
                    len(meshes))
            return
        self.newly_archived.append(meshes)

    def _final_meshes(self, slots: np.ndarray, coords: np.ndarray, unjudged: np.ndarray,
                      side_by_side: Callable[[], bool]) -> BlockMeshes:
        """Fused, filtered meshes of blocks about to be evicted, alpha first evaluated on the blocks
        `unjudged` (those the meshes read whose alpha is stale or was never evaluated; on the alpha
        threads while `side_by_side()`, see `AlphaScheduler.judge`)."""
        started = time.perf_counter()
        self._judged += self.alpha.judge(unjudged, side_by_side=side_by_side)
        self._judge_s += time.perf_counter() - started
        size = self.mesher.batch_blocks
        return BlockMeshes.concatenate([self.mesher.block_meshes(slots[i:i + size], coords[i:i + size])
                                        for i in range(0, len(slots), size)])
