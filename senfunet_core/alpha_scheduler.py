"""Which blocks the weighting net must judge, in which order, and when; judging a batch is
`alpha_evaluator`'s.

Integration marks the blocks it touched (`BlockStore.alpha_pending`) and collects, per block, the
blocks within 2 voxels of its changed voxels (`BlockStore.reach_changed`, `reach_renewed`).
`schedule` turns those into stale blocks (`alpha.reach_levels`); `order` lists the stale blocks
(`EngineConfig.alpha_order`); `evaluate` runs the net on a batch of them where alpha matters
(`EngineConfig.alpha_voxels`, see `alpha`; `alpha_evaluator.AlphaEvaluator`); `write` stores the
results; `refresh` does all of it within a budget, on `alpha_threads` threads when it may. The
engine decides when (budgets, eviction points) and holds its locks as the threading model in
`engine` says: the scheduler takes the data lock it is given only around its reads of the reach
bits and its writes.
"""
from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from .alpha import near_surface_voxels, reach_levels
from .alpha_evaluator import AlphaBatch, AlphaEvaluator
from .block_store import BlockStore, Eviction
from .weighting_int8 import Int8WeightingNet

__all__ = ["AlphaScheduler", "Refresh"]

log = logging.getLogger("senfunet.engine")


@dataclass
class Refresh:
    """What one `AlphaScheduler.refresh` did."""

    blocks: int  # blocks judged (holding voxels alpha matters for)
    voxels: int  # voxels evaluated
    backlog: int  # stale blocks left for later (the budget ran out, or a frame came)


def _done(value: Any) -> Future:
    """A future that already holds `value`."""
    future: Future = Future()
    future.set_result(value)
    return future


class AlphaScheduler:
    """The weighting net's work over a `BlockStore` (see the module docstring)."""

    def __init__(self, store: BlockStore, net: Any, data_lock: threading.RLock, *, alpha_voxels: str,
                 alpha_dtype: str, tsdf_input: bool, band_m: float, voxel_size_m: float,
                 device: torch.device, batch_blocks: int, threads: int, alpha_order: str,
                 worker_setup: Callable[[], object] | None = None,
                 int8_net: Int8WeightingNet | None = None) -> None:
        self.store = store
        self.evaluator = AlphaEvaluator(store, net, alpha_voxels=alpha_voxels, alpha_dtype=alpha_dtype,
                                        tsdf_input=tsdf_input, band_m=band_m, device=device, int8_net=int8_net)
        self._data_lock = data_lock
        self.voxel_size_m = voxel_size_m
        self.batch_blocks = batch_blocks
        self.alpha_order = alpha_order
        self.threads = threads
        self._executor: ThreadPoolExecutor | None = None  # threads > 1: `workers`
        self.worker_setup = worker_setup  # run by each alpha thread as it starts (SenFuNet's worker_setup)
        self.schedules = 0  # schedules so far (BlockStore.last_reached counts in them)
        self.flops = 0  # weighting-net FLOPs written so far (for the benchmark's fraction of peak)

    def schedule(self) -> None:
        """Turn the changes of the blocks integrated since the last call into stale blocks: the
        blocks they reach (whether they hold voxels alpha matters for is checked when their turn
        comes, in `evaluate`)."""
        store = self.store
        with self._data_lock:  # atomic with integration: its reach is either taken now or next time
            changed = np.flatnonzero(store.alpha_pending[: store.n_blocks])
            if len(changed) == 0:
                return
            store.alpha_pending[changed] = False
            touched_s = store.touched_s[changed]
            renewed = store.reach_renewed[changed]
            reached = store.reach_changed[changed] | renewed
            store.reach_changed[changed] = 0
            store.reach_renewed[changed] = 0
        sources, codes, targets = store.reached(changed, reached)
        target_levels = reach_levels(renewed[sources], codes)
        level_of = np.zeros(int(targets.max(initial=-1)) + 1, np.int8)
        for level in range(1, int(target_levels.max(initial=0)) + 1):  # ascending: a block's highest level wins
            level_of[targets[target_levels == level]] = level
        candidates = np.flatnonzero(level_of)
        levels = level_of[candidates]
        last_change_s = np.full(len(level_of), -np.inf)
        np.maximum.at(last_change_s, targets, touched_s[sources])  # the latest frame that reached each
        with self._data_lock:
            self.schedules += 1
            # alpha NaN there: first, unless the block held nothing to evaluate when last checked
            levels[~store.evaluated[candidates] & ~store.no_targets[candidates]] = 3
            store.last_reached[candidates] = self.schedules
            store.last_change_s[candidates] = last_change_s[candidates]
            store.stale[candidates] = np.maximum(store.stale[candidates], levels)
            store.surface_voxels[candidates] = -1

    def waiting_s(self, slots: np.ndarray, now_s: float) -> np.ndarray:
        """How long alpha has waited on these blocks (whose alpha is not up to date) since their
        last change: the latest frame that reached them in the schedule that last made them stale,
        or, integrated into since the last schedule, the latest frame that did (a neighbour's change
        not scheduled yet is not known yet). Call with the data lock held."""
        store = self.store
        pending = store.alpha_pending[slots]
        return now_s - np.fmax(store.last_change_s[slots], np.where(pending, store.touched_s[slots], np.nan))

    def order(self, *, idle: bool = False) -> np.ndarray:
        """The stale blocks in the order they are judged (`alpha_order`): "latest", those the latest
        frames reached first (a budget that cannot keep up, as on a large room, goes to the part of
        the map being scanned); "longest_waiting", blocks with a mesh first (what a subscriber sees;
        the others' turn comes when those are judged, or when the sensors pause), and among them
        those whose last change is oldest first (blocks the sensors still see wait until they settle:
        each is judged about once, and the longest wait is the shortest); then the blocks without a
        mesh, never evaluated ones first, then those with newly observed or sign-changed voxels, then
        changed ones, each oldest first. Among meshed blocks reached by the same schedule (and in
        "latest"), the same three levels.

        `idle` (the sensors paused: the net catches up), "longest_waiting": among the blocks without
        a mesh, the never evaluated ones near a sensor's surface go first, those with the most such
        voxels first (`alpha.near_surface_voxels`, counted then: too costly while frames come). The
        outlier filter holds back the surface one sensor alone saw until the net judged it, so these
        blocks hold the surface the mesh lacks, the most of it first.

        Blocks of equal rank go in the order of their keys (x, then y, then z): a batch's blocks then
        lie side by side and share the neighbours their windows and surface checks read, which stay
        in the cache (slot order, the order blocks were allocated in, scatters them)."""
        store = self.store
        with self._data_lock:
            stale = np.flatnonzero(store.stale[: store.n_blocks])
            reached = store.last_reached[stale]
            levels = store.stale[stale].astype(np.int64)
            keys = store.grid.slot_keys[stale]
            if self.alpha_order == "latest":
                return stale[np.lexsort((keys, -levels, -reached))]
            meshed = store.meshed[stale]
            never_judged = ~meshed & (levels == 3)  # without a mesh
            uncounted = stale[never_judged & (store.surface_voxels[stale] < 0)] if idle else stale[:0]
            sensor_tsdfs = store.views("tsdf0", "weight0", "tsdf1", "weight1")
        surface = np.zeros(len(stale), np.int64)
        if idle:
            # counted without the lock, as `evaluate` reads the grid, on the evaluating threads: a block
            # integrated into meanwhile is counted again once a schedule made it stale again
            def count(part: np.ndarray) -> np.ndarray:
                return near_surface_voxels(part, *sensor_tsdfs, self.voxel_size_m)

            counts = (list(self.workers().map(count, np.array_split(uncounted, self.threads))) if self.threads > 1
                      else [count(uncounted)])
            with self._data_lock:
                store.surface_voxels[uncounted] = np.concatenate(counts)
                surface[never_judged] = store.surface_voxels[stale[never_judged]]
        group = np.where(meshed, 0, np.where(surface > 0, 1, 2))  # meshed, surface held back, the rest
        return stale[np.lexsort((keys, np.where(meshed, -levels, reached), np.where(meshed, reached, -levels),
                                 -surface, group))]

    def evaluate(self, slots: np.ndarray) -> AlphaBatch:
        """The weighting net on a batch (`AlphaEvaluator.evaluate`: without the data lock, writing
        nothing); `refresh` and the map bound evaluate through this."""
        return self.evaluator.evaluate(slots)

    def judge(self, slots: np.ndarray, *, side_by_side: Callable[[], bool]) -> int:
        """Evaluate and write all of these blocks (the map bound's victims' surroundings), batch by
        batch; while `side_by_side()` says so (integration waits for this: the cores are free), on
        the `threads` alpha threads at once, with as many more queued, else one batch at a time on
        this thread (integration has the other core). Each batch is one thread's, so alpha does not
        depend on how many. Batches go in the order of the blocks' keys, as `order` breaks its ties.
        Returns the blocks judged (holding voxels alpha matters for)."""
        slots = slots[np.argsort(self.store.grid.slot_keys[slots], kind="stable")]
        results: list[AlphaBatch] = []
        evaluating: collections.deque[Future[AlphaBatch]] = collections.deque()
        judged = 0

        def take(result: AlphaBatch) -> None:
            nonlocal judged
            judged += int(result.holds.sum())
            results.append(result)

        for start in range(0, len(slots), self.batch_blocks):
            batch = slots[start:start + self.batch_blocks]
            if self.threads > 1 and side_by_side():
                while len(evaluating) >= 2 * self.threads:  # the oldest first: results are written in order
                    take(evaluating.popleft().result())
                evaluating.append(self.workers().submit(self.evaluate, batch))
            else:
                while evaluating:
                    take(evaluating.popleft().result())
                take(self.evaluate(batch))
            self.write(results, wait=False)  # whenever the data lock is free: integration may hold it
        while evaluating:
            take(evaluating.popleft().result())
        self.write(results, wait=True)
        return judged

    def write(self, results: list[AlphaBatch], *, wait: bool) -> None:
        """Write evaluated batches (and empty `results`), if the data lock is free or `wait`. Where
        alpha matters in an evaluated block, it is up to date; a block without voxels alpha matters
        for is not stale either, and remembers it."""
        if not results or not self._data_lock.acquire(blocking=wait):
            return
        store = self.store
        try:
            for batch in results:
                pool = store.grid.pools["alpha"]
                pool.numpy().reshape(-1)[batch.voxels] = batch.alpha
                evaluated = batch.slots[batch.holds]
                store.stale[batch.slots] = 0
                store.no_targets[batch.slots] = ~batch.holds
                store.evaluated[evaluated] = True
                store.mesh_pending[evaluated] = True
                self.flops += batch.flops
        finally:
            self._data_lock.release()
        results.clear()

    def refresh(self, budget_s: float | None, *, until_frame: Callable[[], bool] | None,
                eviction_due: Callable[[], bool], evict: Callable[[], Eviction | None]) -> Refresh:
        """Re-evaluate alpha on the stale blocks in `order`, batch by batch; each batch first drops
        the blocks that hold no voxel alpha matters for (checked then, not when scheduling, so that
        a budget also bounds the checking). With a budget (seconds from the call: scheduling and
        ordering count in it), no batch is started that would end past it (judged by the last
        batch's time; the first always runs, unless the budget is 0), and with `until_frame` none
        once it says a frame was integrated (batches queued but not started are withdrawn): the rest
        stays stale for later.
        Without a budget or with `until_frame` (no frame is coming), `threads` batches are evaluated
        at once (each single-threaded, so alpha does not depend on how many), with as many more
        queued, so that a thread that finishes takes the next at once. Between batches, where no
        evaluated batch waits to be written, it calls `evict` when `eviction_due` (integration
        outgrew the map bound) and follows the blocks that moved."""
        start = time.perf_counter()  # scheduling and ordering count too: on a large map they take a batch's time
        self.schedule()
        order = self.order(idle=until_frame is not None)
        done = voxels = left = 0
        # batches evaluated at once: one while frames come (integration needs the other core)
        threads = self.threads if budget_s is None or until_frame is not None else 1
        in_flight = 2 * threads if threads > 1 else 1
        # Results are written whenever the data lock is free, not waited for batch by batch: time
        # spent waiting for integration's kernels would come out of the net's budget.
        results: list[AlphaBatch] = []
        evaluating: collections.deque[tuple[Future[tuple[AlphaBatch, float]], int]] = collections.deque()  # blocks
        batch_s = 0.0  # the last batch's time: one that would end past the budget is not started
        started = 0  # batches started: the first runs whatever the scheduling took (the net never stalls)
        while len(order) or evaluating:
            if len(order) and until_frame is not None and until_frame():
                left += len(order)  # evaluate no more; the batches under way are written
                order = order[:0]
                for queued in [entry for entry in evaluating if entry[0].cancel()]:
                    evaluating.remove(queued)
                    left += queued[1]
            if eviction_due():
                results += [future.result()[0] for future, _ in evaluating]  # read before slots move
                evaluating.clear()
                self.write(results, wait=True)
                eviction = evict()
                if eviction is not None:
                    order, _ = eviction.follow(order)
            # none queued before a batch's time is known (the budget could not be judged for it)
            while len(order) and len(evaluating) < (in_flight if batch_s else threads):
                # a new batch starts once the batches ahead of it on its thread have ended
                if budget_s is not None and (budget_s <= 0 or started and (
                        time.perf_counter() - start + batch_s * (len(evaluating) // threads + 1) > budget_s)):
                    left += len(order)
                    order = order[:0]
                    break
                batch, order = order[:self.batch_blocks], order[self.batch_blocks:]
                started += 1
                evaluating.append((self.workers().submit(self._timed_evaluate, batch) if threads > 1
                                   else _done(self._timed_evaluate(batch)), len(batch)))
            if not evaluating:
                continue
            result, batch_s = evaluating.popleft()[0].result()
            results.append(result)
            done += int(result.holds.sum())
            voxels += len(result.voxels)
            self.write(results, wait=False)
        self.write(results, wait=True)
        return Refresh(done, voxels, left)

    def _timed_evaluate(self, slots: np.ndarray) -> tuple[AlphaBatch, float]:
        """`evaluate` and the seconds it took."""
        started = time.perf_counter()
        return self.evaluate(slots), time.perf_counter() - started

    def workers(self) -> ThreadPoolExecutor:
        """The `threads` alpha threads that evaluate batches side by side (created on first use, by
        the thread that first needs them: they share its priority, then run `worker_setup`). The
        engine also meshes an idle update's batches on them, and `order` counts an idle catch-up's
        near-surface voxels there."""
        if self._executor is None:
            # the initializer refers to the set-up alone: a pool thread keeps it while it lives, and
            # through this scheduler it would keep the map, so that a dropped engine (~/load_map)
            # never went, nor its threads
            self._executor = ThreadPoolExecutor(self.threads, thread_name_prefix="senfunet-alpha",
                                                initializer=_set_up_alpha_thread, initargs=(self.worker_setup,))
        return self._executor

    def stop_workers(self) -> None:
        """End the alpha threads (the next use starts them again, from the thread that needs them)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None


def _set_up_alpha_thread(worker_setup: Callable[[], object] | None) -> None:
    """A new alpha thread: torch on one thread in it (the batches side by side use the cores; a
    thread's OpenMP team is its own, two threads each on every core would oversubscribe them), then
    `worker_setup`, whose failure is logged, not raised (a thread pool whose initializer raises
    refuses all later work)."""
    torch.set_num_threads(1)
    if worker_setup is None:
        return
    try:
        worker_setup()
    except Exception as err:  # noqa: BLE001 (any failure: the thread runs as it was started)
        log.warning("alpha thread set-up failed (the thread runs as started): %r", err)
