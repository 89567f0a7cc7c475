"""Real-time benchmark (issue 6): the live node, fed from a bag, on this machine.

    .venv/bin/python bench/realtime.py                    # sample bag + large room, writes docs/performance.md
    .venv/bin/python bench/realtime.py --cases sample --no-write

The node under test is the real `FusionNode` with its default parameters, spun by a
MultiThreadedExecutor in this process exactly as `senfunet node` spins it (integration timer,
mesh timer with the weighting-net budget, status timer). Bag messages are deserialised with
rclpy and handed to the node's `Ingest` the way its subscription callbacks hand them over (that
is the "conversion" stage); DDS transport itself is not part of the measurement. Two modes, each
in its own process so that peak RSS is that run's:

- `throughput`: messages are handed over as fast as the node takes them (the feeder waits while
  more than a few frames are queued, so memory stays bounded): sustained ingest = frames
  integrated / wall time, with mesh updates running at their rate meanwhile.
- `realtime`: messages are handed over at their recorded times (1x; `--rate 0.7`: 0.7x, slower
  sensors, written to its own section of docs/performance.md): mesh update interval,
  frame-to-mesh latency per frame (a depth image's arrival -> publication of the first mesh update
  begun after it was integrated, as the node itself reports on ~/status), frames dropped, weighting-net
  backlog; 5 s after the stream, the map's mesh as ~/mesh gives a subscriber then, scored against
  `senfunet replay`'s mesh.ply of the same bag (F at 2 cm; the replay runs after the node is gone,
  once per case). Run `--repeats` times (3): on a shared 2-core machine one run's share of frames
  integrated on arrival swings widely, so the table shows the median run and the spread follows it.

Open3D's VoxelBlockGrid TSDF integration (1 cm voxels, 8^3 blocks, same truncation; the fast CPU
fusion a user would otherwise pick) is timed on the same frames when `open3d` is importable
(bench/requirements.txt).
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench._common import (LARGE_ROOM_M, LARGE_ROOM_SECONDS, LARGE_ROOM_SEED, ROOT, command,  # noqa: E402
                           large_room_bag, machine, min_median_max, write_section)

if TYPE_CHECKING:
    from senfunet_core.engine import MeshUpdate

MODES = ("throughput", "realtime")
_BACKLOG_FRAMES = 4  # throughput mode: the feeder waits while this many frames are queued


def bag_path(args: argparse.Namespace, case: str) -> Path:
    if case == "sample":
        return Path(args.bag)
    return large_room_bag(Path(args.cache), seed=args.large_seed, room_m=tuple(args.large_room),
                          seconds=args.large_seconds)


@contextlib.contextmanager
def bag_messages(path: Path, max_seconds: float) -> Iterator[tuple[Iterator, object, float]]:
    """(messages, router, seconds): the bag's routed messages, read as they are needed (a bag held
    in memory would count in the peak RSS), up to max_seconds after the first (0 = all)."""
    from senfunet_ros.bagio import open_bag
    from senfunet_ros.replay import TopicRouter
    from senfunet_ros.params_file import load_settings

    with open_bag(path) as bag:
        router = TopicRouter(load_settings(None), bag.topics, path)
        seconds = bag.duration_s if max_seconds <= 0 else min(bag.duration_s, max_seconds)
        end_ns = bag.start_ns + int(seconds * 1e9)
        yield (m for m in bag.messages(router.topics) if m.log_time_ns <= end_ns), router, seconds


def run_node_case(args: argparse.Namespace) -> dict:
    """One case in one mode, in this (child) process."""
    import rclpy
    from rclpy.parameter import Parameter

    from senfunet_ros.node import FusionNode, prepare_process, spin

    from senfunet_ros.dds import use_large_shm_profile

    use_large_shm_profile()
    prepare_process()  # as the node's main() does
    rclpy.init()
    overrides = {f"{s}.{k}_topic": f"/senfunet_bench_{os.getpid()}/{s}/{k}"  # nothing else talks to it
                 for s in ("tof", "stereo") for k in ("depth", "color", "camera_info", "pose")}
    if args.mode == "throughput":  # nothing may expire or be skipped while the feeder waits on the node
        # (the ranges allowed; a restart is a jump longer than the pose wait, time_jump_s >= pose_max_wait_s)
        overrides.update(pose_max_wait_s=600.0, time_jump_s=600.0, pose_buffer_size=100_000, max_lag_s=0.0)
    for given in args.param:
        name, _, value = given.partition("=")
        overrides[name] = yaml.safe_load(value)
    node = FusionNode(namespace="bench", parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
    published = PublishedMesh.following(node.mesh_publisher) if compare_with_replay(args) else None
    spinner = threading.Thread(target=spin, args=(node,), daemon=True)
    spinner.start()
    ingest, engine = node.ingest, node.engine
    conversion_s, frames_sent, peak_queue = 0.0, 0, 0
    with bag_messages(bag_path(args, args.case), args.max_seconds) as (messages, router, bag_s):
        t0_bag = None
        start = time.monotonic()
        cpu_start = time.process_time()
        for msg in messages:
            t0_bag = msg.log_time_ns if t0_bag is None else t0_bag
            if args.mode == "realtime":
                delay = (msg.log_time_ns - t0_bag) / 1e9 / args.rate - (time.monotonic() - start)
                if delay > 0:
                    time.sleep(delay)
            else:  # frames may also wait for a later pose only this feeder delivers: never wait long
                waited = time.monotonic() + 0.2
                while sum(ingest.ledger.queue_depths().values()) > _BACKLOG_FRAMES and time.monotonic() < waited:
                    time.sleep(0.002)
            t = time.perf_counter()
            decoded = router.decode(msg)
            if decoded is not None:
                router.dispatch(ingest, *decoded)
                frames_sent += sum(stream == "depth" for _, stream in decoded[0].targets)
            conversion_s += time.perf_counter() - t
            peak_queue = max(peak_queue, sum(ingest.ledger.queue_depths().values()))

    stream_end = time.monotonic()  # the last message handed over

    def settled() -> bool:
        c = ingest.ledger.counters()
        return all(v["integrated"] + sum(v["dropped"].values()) >= v["received"] for v in c.values())

    def five_seconds_after() -> tuple[int, dict, int, LiveMap | None]:
        """5 s after the stream: the process's peak RSS so far, the map's stats, the blocks still to
        judge and, to compare with replay, the mesh a subscriber to ~/mesh holds then (what the
        updates published so far) and the state of the map's blocks. Nothing here takes the engine's
        update lock or re-meshes the map: the node's updates go on as they would without the benchmark."""
        peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
        live = None
        if published is not None:
            store = engine.store
            n = store.n_blocks  # read without the lock: a frame set aside may still be integrated
            live = LiveMap(published.vertices(), engine.config.voxel_size_m, store.grid.coords[:n].numpy().copy(),
                           store.evaluated[:n].copy(), store.meshed[:n].copy())
        return peak_rss, engine.stats(), engine.counters.get("alpha_backlog_blocks", 0), live

    after = None
    while not settled() and time.monotonic() < stream_end + 600:
        if after is None and time.monotonic() >= stream_end + 5.0:  # set-aside frames still being integrated
            after = five_seconds_after()
        time.sleep(0.01)
    integrated_at = time.monotonic()
    cpu_s = time.process_time() - cpu_start  # every thread of the process: the node's and the feeder's
    # the map's state when the last frame was integrated, as ~/status has it (stats waits for an update
    # or a turn of the net under way), and the stage times until then
    stats = engine.stats()
    total = dict(engine.total_s)
    timings = {name: t.total_s for name, t in node.timings.items()}
    alpha_counters = dict(engine.counters)
    # the node's own update that holds the last frames (its timer runs on): taken, then published
    while node.latency.pending() and time.monotonic() < integrated_at + 30:
        time.sleep(0.01)
    taken_by = time.monotonic()
    while (not node.latency.updates or node.latency.updates[-1][0] < taken_by) and time.monotonic() < taken_by + 30:
        time.sleep(0.01)
    wall_s = integrated_at - start
    counters = ingest.ledger.counters()
    frames = sum(c["integrated"] for c in counters.values())
    dropped: dict[str, int] = {}
    for c in counters.values():
        for reason, n in c["dropped"].items():
            if n:
                dropped[reason] = dropped.get(reason, 0) + n
    updates = list(node.latency.updates)
    intervals = np.diff([u[0] for u in updates]) if len(updates) > 1 else np.array([np.nan])
    latencies = list(node.latency.frames_s)  # per frame: its arrival -> the update that published it
    late = list(node.latency.set_aside_s)  # ... of the frames set aside while integration was behind
    if after is None:  # the node's timers run on: its weighting net catches up once no frame comes
        time.sleep(max(0.0, stream_end + 5.0 - time.monotonic()))
        after = five_seconds_after()
    peak_rss, after_stats, after_backlog, live_map = after
    caught_up_s = caught_up_after(engine, settled, stream_end, timeout_s=_CATCH_UP_TIMEOUT_S)
    result = {
        "case": args.case, "mode": args.mode, "bag_seconds": bag_s, "wall_seconds": wall_s,
        "alpha_arithmetic": stats["alpha_arithmetic"],
        "frames_sent": frames_sent, "frames_integrated": frames, "dropped": dropped,
        "frames_set_aside": sum(c["set_aside"] for c in counters.values()),
        "ingest_fps": frames / wall_s, "peak_queue_frames": peak_queue, "process_cpu_s": cpu_s,
        "stage_s": {
            "conversion": conversion_s,
            "feature nets": total.get("feature_net", 0.0),
            "integration": total.get("integrate", 0.0),
            "alpha (weighting net)": total.get("alpha", 0.0),
            "fusion": total.get("fusion", 0.0),
            "marching cubes": total.get("marching_cubes", 0.0),
            # (each summed over the threads that meshed: an update's "mesh" is its wall time)
            "block meshes": (total.get("block_meshes", 0.0) - total.get("fusion", 0.0)
                             - total.get("marching_cubes", 0.0)),
            "message building": timings["encode"],
            "publishing": timings["publish"],
        },
        "mesh_updates": len(updates),
        "update_interval_s": {"median": float(np.median(intervals)), "max": float(np.max(intervals)),
                              # where the longest gap ended, in seconds after the stream (negative: during it)
                              "max_ends_s": (float(updates[int(np.argmax(intervals)) + 1][0] - stream_end)
                                             if len(updates) > 1 else float("nan"))},
        "latency_s": median_max(latencies),
        "latency_set_aside_s": median_max(late),
        "alpha_blocks": alpha_counters["alpha_blocks"],
        "alpha_backlog_blocks": alpha_counters.get("alpha_backlog_blocks", 0),
        "meshed_blocks": stats["meshed_blocks"], "meshed_alpha_evaluated": stats["meshed_blocks_alpha_evaluated"],
        "meshed_alpha_current": stats["meshed_blocks_alpha_current"],
        "unjudged_over_3s": stats["meshed_blocks_unjudged_over_3s"],
        "oldest_unjudged_s": stats["oldest_unjudged_change_s"],
        "peak_rss_bytes": peak_rss,  # until 5 s after the stream
        "published_copy_bytes": published.nbytes if published is not None else 0,  # this benchmark's, in peak_rss
        "blocks": stats["blocks"], "observed_voxels": stats["observed_voxels"],
        "evicted_blocks": stats["evicted_blocks"], "archived_blocks": stats["archived_blocks"],
        "spilled_blocks": stats["spilled_blocks"], "restored_blocks": stats["restored_blocks"],
        "after_5s_meshed": after_stats["meshed_blocks"], "after_5s_current": after_stats["meshed_blocks_alpha_current"],
        "after_5s_unjudged_over_3s": after_stats["meshed_blocks_unjudged_over_3s"],
        "after_5s_backlog_blocks": after_backlog,
        "bytes_per_observed_voxel": stats["bytes_per_observed_voxel"],
        "caught_up_s": caught_up_s,
    }
    rclpy.try_shutdown()  # ends the executor's spin
    spinner.join(timeout=10)
    node.destroy_node()
    if live_map is not None:
        del node, engine, ingest  # the node's map is freed before replay builds its own
        result.update(live_vs_replay_scores(args, live_map))
    return result


_CATCH_UP_TIMEOUT_S = 300.0


def caught_up_after(engine, settled, stream_end: float, *, timeout_s: float) -> float:
    """Seconds from the stream's end until the node had integrated every frame, its weighting net had
    judged every block it had to and an update had taken every block to mesh (its publication follows
    as that update ends): from then on ~/mesh is replay's mesh. NaN if not within timeout_s. Polls the
    map's flags without the lock, as ~/status's readers would see them."""
    store = engine.store
    while time.monotonic() < stream_end + timeout_s:
        n = store.n_blocks
        if (settled() and not store.stale[:n].any() and not store.mesh_pending[:n].any()
                and not store.mesh_due[:n].any()):
            return time.monotonic() - stream_end
        time.sleep(0.05)
    return float("nan")


def median_max(values: list[float]) -> dict[str, float]:
    """Median and maximum (NaN for none)."""
    if not values:
        return {"median": float("nan"), "max": float("nan")}
    return {"median": float(np.median(values)), "max": float(np.max(values))}


def compare_with_replay(args: argparse.Namespace) -> bool:
    """Whether this run compares the live mesh with replay's (realtime mode, whole bags)."""
    return args.mode == "realtime" and args.replay_check and args.max_seconds <= 0


class PublishedMesh:
    """The fused mesh as a subscriber to ~/mesh holds it: each block's vertices as the last update
    that changed the block published them, less the blocks updates removed. Kept by the benchmark
    from the updates the node's MeshPublisher sends (copies: they count in the process's RSS)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()  # the mesh thread adds, the benchmark's thread reads
        self._vertices: dict[tuple[int, int, int], np.ndarray] = {}

    @classmethod
    def following(cls, publisher) -> PublishedMesh:  # noqa: ANN001 (senfunet_ros.mesh_publisher.MeshPublisher)
        """One that takes every update `publisher` sends from now on."""
        from senfunet_core.engine import MeshUpdate

        published = cls()

        def taking(engine, update, whole: bool) -> None:  # noqa: ANN001 (the engine and its MeshUpdate)
            published.take(MeshUpdate(meshes=engine.block_meshes(), cleared=True) if whole else update)

        publisher.taps.append(taking)
        return published

    def take(self, update: MeshUpdate) -> None:
        meshes = update.meshes
        parts = np.split(meshes.vertices, meshes.vertex_offsets[1:-1])
        with self._lock:
            if update.cleared:
                self._vertices.clear()
            for key, vertices in zip(map(tuple, meshes.keys.tolist()), parts):
                self._vertices[key] = vertices.copy()  # not a view, which would keep the update's arrays
            for key in update.removed:
                self._vertices.pop(tuple(key), None)

    def vertices(self) -> np.ndarray:
        with self._lock:
            parts = list(self._vertices.values())
        return np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)

    @property
    def nbytes(self) -> int:
        with self._lock:
            return sum(v.nbytes for v in self._vertices.values())


@dataclasses.dataclass
class LiveMap:
    """The live mesh 5 s after the stream, and the state of the map's blocks then."""

    vertices: np.ndarray  # as a subscriber to ~/mesh holds it
    voxel_size_m: float
    coords: np.ndarray  # B x 3 block coordinates
    evaluated: np.ndarray  # B bool: judged by the weighting net at least once
    meshed: np.ndarray  # B bool: its fused mesh had triangles when last meshed

    def block_states(self, points: np.ndarray) -> np.ndarray:
        """Per point: 0 its block was never judged and shows no mesh, 1 never judged and meshed,
        2 judged, 3 no block holds it."""
        import torch

        from senfunet_core.grid import BLOCK, block_keys

        if len(self.coords) == 0:
            return np.full(len(points), 3)
        keys = block_keys(torch.from_numpy(self.coords)).numpy()
        order = np.argsort(keys)
        wanted = block_keys(torch.from_numpy(np.floor(points / (self.voxel_size_m * BLOCK)).astype(np.int64))).numpy()
        slot = order[np.minimum(np.searchsorted(keys[order], wanted), len(keys) - 1)]
        found = keys[slot] == wanted
        state = np.where(self.evaluated[slot], 2, np.where(self.meshed[slot], 1, 0))
        return np.where(found, state, 3)


def live_vs_replay_scores(args: argparse.Namespace, live: LiveMap) -> dict[str, float]:
    """F-score, precision and recall (2 cm) of the live mesh's vertices against `senfunet replay`'s
    mesh.ply of the same bag, default parameters (F: test_play's measure of live equals replay), and
    where replay's surface that the live mesh lacks lies: the share of those vertices by the state
    of their block in the live map (`LiveMap.block_states`)."""
    import tempfile

    from scipy.spatial import cKDTree

    from senfunet_core.metrics import mesh_metrics
    from senfunet_core.ply import read_ply
    from senfunet_ros.replay import replay_bag

    kept = Path(args.replay_dir) / "mesh.ply" if args.replay_dir else None
    if kept is not None and kept.is_file():  # an earlier run of this invocation replayed the same bag
        replay_vertices = read_ply(kept).vertices
    else:
        with tempfile.TemporaryDirectory() as out:
            replayed = replay_bag(bag_path(args, args.case), args.replay_dir or out, progress=False)
            if not replayed.ok:
                raise RuntimeError(f"replay of the {args.case} bag failed: {replayed.error}")
            replay_vertices = replayed.meshes["mesh"].vertices
    scores = mesh_metrics(live.vertices, replay_vertices, tau_m=0.02)
    lacks = np.ones(len(replay_vertices), bool)
    if len(live.vertices):
        lacks = ~np.isfinite(cKDTree(live.vertices).query(replay_vertices, distance_upper_bound=0.02)[0])
    lacking = live.block_states(replay_vertices[lacks])
    shares = np.bincount(lacking, minlength=4) / max(len(lacking), 1)
    return {"live_vs_replay_f": scores["F"], "live_vs_replay_p": scores["P"], "live_vs_replay_r": scores["R"],
            "lacking_unjudged_unmeshed": shares[0], "lacking_unjudged_meshed": shares[1],
            "lacking_judged": shares[2], "lacking_no_block": shares[3]}


def run_open3d(args: argparse.Namespace) -> dict | str:
    """Open3D's VoxelBlockGrid integration on the same frames as our integration (median ms per frame)."""
    try:
        import open3d as o3d
        import open3d.core as o3c
    except Exception as err:  # optional benchmark dependency
        return f"not available ({type(err).__name__}: pip install -r bench/requirements.txt)"
    from senfunet_core.engine import SenFuNet
    from senfunet_ros.ingest import Frame, Ingest
    from senfunet_ros.replay import engine_config, ingest_config
    from senfunet_ros.params_file import load_settings

    settings = load_settings(None)
    ingest = Ingest(ingest_config(settings))
    frames: list[Frame] = []
    with bag_messages(bag_path(args, args.case), args.max_seconds) as (messages, router, _):
        for msg in messages:
            decoded = router.decode(msg)
            if decoded is not None:
                router.dispatch(ingest, *decoded)
                frames += [f for f in ingest.pop_ready() if isinstance(f, Frame)]
            if len(frames) >= args.open3d_frames:
                break
    frames = frames[: args.open3d_frames]
    device = o3c.Device("CPU:0")
    vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
                                        attr_channels=((1), (1)), voxel_size=0.01, block_resolution=8,
                                        block_count=400000, device=device)
    theirs = []
    for frame in frames:
        depth = np.nan_to_num(frame.depth_m, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
        t0 = time.perf_counter()
        image = o3d.t.geometry.Image(o3c.Tensor(depth, device=device))
        intrinsic = o3c.Tensor(frame.K, o3c.float64)
        extrinsic = o3c.Tensor(np.linalg.inv(frame.T_world_camera), o3c.float64)
        coords = vbg.compute_unique_block_coordinates(image, intrinsic, extrinsic, depth_scale=1.0, depth_max=5.0,
                                                      trunc_voxel_multiplier=5.0)
        vbg.integrate(coords, image, intrinsic, extrinsic, depth_scale=1.0, depth_max=5.0, trunc_voxel_multiplier=5.0)
        theirs.append(time.perf_counter() - t0)
    del vbg
    engine = SenFuNet(engine_config(settings))
    ours = []
    for frame in frames:
        t0 = time.perf_counter()
        engine.integrate(frame.sensor, frame.depth_m, frame.K, frame.T_world_camera, frame.rgb)
        ours.append(time.perf_counter() - t0)
    skip = 2  # first calls: compilation and allocation
    return {"version": o3d.__version__, "frames": len(frames), "threads": o3d.utility.get_num_threads()
            if hasattr(o3d.utility, "get_num_threads") else None,
            "open3d_ms": 1e3 * float(np.median(theirs[skip:])), "ours_ms": 1e3 * float(np.median(ours[skip:]))}


def on_arrival_share(run: dict) -> float:
    """The share of the depth frames sent that were integrated on arrival (not set aside)."""
    return (run["frames_integrated"] - run["frames_set_aside"]) / max(run["frames_sent"], 1)


def median_run(runs: list[dict]) -> dict:
    """The run in the middle by frames integrated on arrival (a run, not a mix of runs: its figures fit
    together); the upper middle of an even number."""
    return sorted(runs, key=on_arrival_share)[len(runs) // 2]


def spread_lines(realtime_runs: dict[str, list[dict]]) -> list[str]:
    """Per case, the realtime runs' figures from run to run (each the same command on the same bag)."""
    if not any(len(runs) > 1 for runs in realtime_runs.values()):
        return []
    lines = ["", "Run to run (the `realtime` columns above show the median run by frames integrated on arrival; "
             "each run is the same command on the same bag, in its own process, one after the other):"]
    spread = min_median_max

    for case, runs in realtime_runs.items():
        parts = [f"frames integrated on arrival {spread([100 * on_arrival_share(r) for r in runs], '{:.0f}%')}",
                 f"latency median {spread([r['latency_s']['median'] for r in runs], '{:.2f} s')}",
                 f"mesh update interval median {spread([r['update_interval_s']['median'] for r in runs], '{:.2f} s')}",
                 f"meshed blocks waiting more than 3 s for the net when the last frame was integrated "
                 f"{spread([r['unjudged_over_3s'] for r in runs], '{:.0f}')}",
                 "process CPU per frame "
                 + spread([1e3 * r["process_cpu_s"] / max(r["frames_integrated"], 1) for r in runs], "{:.1f} ms")]
        if all("live_vs_replay_f" in r for r in runs):
            parts.append("F against replay 5 s after the stream "
                         + spread([r["live_vs_replay_f"] for r in runs], "{:.1f}"))
        lines.append(f"- {case}, {len(runs)} runs, min / median / max: " + "; ".join(parts))
    return lines


def report(results: dict[str, dict[str, dict]], args: argparse.Namespace,
           realtime_runs: dict[str, list[dict]] | None = None) -> str:
    from senfunet_ros.mesh_publisher import MIN_TURN_S
    from senfunet_ros.params import GLOBAL_PARAMS, MESH_PERIOD_MARGIN

    cases = list(results)
    default = {p.name: p.default for p in GLOBAL_PARAMS}
    bound = {-1: "half of the machine's memory", 0: "none"}.get(default["max_map_blocks"],
                                                               f"{default['max_map_blocks']} blocks")
    lines = [f"Machine: {machine()}", "", f"Command: `{command()}`", "",
             "The real `FusionNode` with its default parameters (config/default.yaml: mesh updates at "
             f"{default['mesh_rate_hz']:g} Hz (scheduled with a period {MESH_PERIOD_MARGIN:.0%} shorter), "
             "weighting-net budget "
             f"{default['alpha_budget_s']:g} s per update (within the mesh period, at least "
             f"{MIN_TURN_S:g} s), "
             f"alpha on surface blocks, frames more than {default['max_lag_s']:g} s behind set aside (up to "
             f"{default['behind_buffer_mb']:g} MB, integrated once no image came for that long), mesh updates on "
             f"both cores when no frame waits, the net's catch-up for the rest of each mesh period after an update "
             f"no frame came during, map bound {bound}, malloc arenas capped at 2, allocations from 4 MB mapped), "
             "spun by a MultiThreadedExecutor in "
             "the benchmark process; bag messages deserialised with rclpy and handed to its Ingest as its "
             "subscriptions do. `throughput`: as fast as the node takes them; `realtime`: at their recorded "
             + ("times. " if args.rate == 1.0 else f"times divided by {args.rate:g} ({args.rate:g}x the recorded "
                "rate: slower sensors, the same images). ")
             + "Stage times are summed until the last frame was integrated and divided by the frames "
             "integrated; they are wall "
             "times, so threads waiting for a core count too. The process CPU time (user + system, every thread, "
             "the feeder's deserialisation included) from the first message until every frame was integrated or "
             "dropped, divided by the frames integrated, is what the node's work costs the cores."
             + (f" Parameters set otherwise: {', '.join(args.param)}." if args.param else ""), ""]
    head = "| | " + " | ".join(f"{c} ({m})" for c in cases for m in results[c]) + " |"
    lines += [head, "|---" * (1 + sum(len(results[c]) for c in cases)) + "|"]
    runs = [results[c][m] for c in cases for m in results[c]]

    def row(name, fn):
        cells = (fn(r) if isinstance(r, dict) and "case" in r else "-" for r in runs)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")

    def frames_per_s(r: dict) -> float:
        """The depth frames per second handed over: the bag's, at `--rate` in realtime mode."""
        return r["frames_sent"] / r["bag_seconds"] * (args.rate if r["mode"] == "realtime" else 1.0)

    def streamed(r: dict) -> str:
        if args.rate == 1.0 or r["mode"] != "realtime":
            return ""
        return f", streamed in {r['bag_seconds'] / args.rate:.1f} s ({frames_per_s(r):.1f} depth frames/s)"

    row("bag", lambda r: f"{r['bag_seconds']:.1f} s, {r['frames_sent']} depth frames{streamed(r)}")
    row("weighting net arithmetic (alpha_precision)", lambda r: r.get("alpha_arithmetic", "-"))
    row("frames integrated (of them set aside while behind, integrated later) / dropped",
        lambda r: f"{r['frames_integrated']} ({r['frames_set_aside']}) / "
        + (", ".join(f"{k} {v}" for k, v in r["dropped"].items()) or "0"))
    row("**sustained ingest (frames/s)**", lambda r: f"{r['ingest_fps']:.1f}")
    for stage in next(iter(runs))["stage_s"]:
        row(f"- {stage} (ms/frame)", lambda r, s=stage: f"{1e3 * r['stage_s'][s] / max(r['frames_integrated'], 1):.1f}")
    row("CPU time per frame, all stages (ms)",
        lambda r: f"{1e3 * sum(r['stage_s'].values()) / max(r['frames_integrated'], 1):.1f}")
    row("process CPU time per frame, all threads (ms)",
        lambda r: f"{1e3 * r['process_cpu_s'] / max(r['frames_integrated'], 1):.1f}")
    # the cores the stream's work asks for at the rate it was streamed: above the machine's, integration falls
    # behind (the weighting net's judging of what is still stale after the last frame comes on top)
    row(f"... times the frames per second streamed (realtime; the bag's, throughput): cores the stream needs "
        f"(this machine: {len(os.sched_getaffinity(0))})",
        lambda r: f"{r['process_cpu_s'] / max(r['frames_integrated'], 1) * frames_per_s(r):.2f}")

    def gap_end(seconds: float) -> str:
        return f"{abs(seconds):.1f} s {'after' if seconds >= 0 else 'before'} the stream's end"

    row("mesh updates; interval median / max (s)", lambda r: f"{r['mesh_updates']}; "
        f"{r['update_interval_s']['median']:.2f} / {r['update_interval_s']['max']:.2f} (the longest ending "
        f"{gap_end(r['update_interval_s'].get('max_ends_s', float('nan')))})")
    row("frame-to-mesh latency over frames not set aside, median / max (s)",
        lambda r: f"{r['latency_s']['median']:.2f} / {r['latency_s']['max']:.2f}")
    row("... over the frames set aside, median / max (s)", lambda r: "-" if not r["frames_set_aside"]
        else f"{r['latency_set_aside_s']['median']:.2f} / {r['latency_set_aside_s']['max']:.2f}")
    row("peak frames queued", lambda r: str(r["peak_queue_frames"]))
    row("alpha: blocks evaluated / left for later", lambda r: f"{r['alpha_blocks']} / {r['alpha_backlog_blocks']}")
    row("meshed blocks when the last frame was integrated: alpha evaluated / up to date",
        lambda r: f"{r['meshed_blocks']}: {100 * r['meshed_alpha_evaluated'] / max(r['meshed_blocks'], 1):.0f}% / "
        f"{100 * r['meshed_alpha_current'] / max(r['meshed_blocks'], 1):.0f}%")
    row("... alpha waiting more than 3 s after a change; the oldest wait (s)",
        lambda r: f"{100 * r['unjudged_over_3s'] / max(r['meshed_blocks'], 1):.0f}%; {r['oldest_unjudged_s']:.1f}")
    row("5 s after the stream: meshed blocks with alpha up to date; waiting more than 3 s; blocks still to judge",
        lambda r: f"{r['after_5s_meshed']}: {100 * r['after_5s_current'] / max(r['after_5s_meshed'], 1):.0f}%; "
        f"{100 * r['after_5s_unjudged_over_3s'] / max(r['after_5s_meshed'], 1):.0f}%; {r['after_5s_backlog_blocks']}")
    row("every frame integrated, every block judged and taken by a mesh update (from then on ~/mesh is "
        "replay's mesh): seconds after the stream",
        lambda r: f"{r['caught_up_s']:.1f}" if r['caught_up_s'] == r['caught_up_s'] else f"> {_CATCH_UP_TIMEOUT_S:g}")
    row("5 s after the stream: the live mesh (as a subscriber to ~/mesh holds it) against replay's mesh.ply, F at 2 cm "
        "(precision / recall: replay's surface the live mesh lacks)",
        lambda r: f"{r['live_vs_replay_f']:.1f} ({r['live_vs_replay_p']:.1f} / {r['live_vs_replay_r']:.1f})"
        if "live_vs_replay_f" in r else "-")
    row("... where replay's surface the live mesh lacks lies: blocks never judged without a mesh (mostly surface "
        "one sensor alone saw: shown once judged) / never judged with a mesh / judged / not in the map",
        lambda r: " / ".join(f"{100 * r[key]:.0f}%" for key in ("lacking_unjudged_unmeshed", "lacking_unjudged_meshed",
                                                                 "lacking_judged", "lacking_no_block"))
        if "lacking_judged" in r else "-")
    row("peak RSS until 5 s after the stream (GB); of it, the benchmark's copy of the published mesh (GB)",
        lambda r: f"{r['peak_rss_bytes'] / 1e9:.2f}" + (f"; {r['published_copy_bytes'] / 1e9:.2f}"
                                                        if r.get("published_copy_bytes") else ""))
    row("blocks / observed voxels", lambda r: f"{r['blocks']} / {r['observed_voxels']}")
    row("blocks evicted / meshes archived / on disk at the end / restored from disk",
        lambda r: f"{r['evicted_blocks']} / {r['archived_blocks']} / {r['spilled_blocks']} / {r['restored_blocks']}")
    row("bytes per observed voxel", lambda r: f"{r['bytes_per_observed_voxel']:.0f}")
    lines.append("")
    for case in cases:
        o = results[case].get("open3d")
        if isinstance(o, dict):
            lines.append(f"Open3D {o['version']} VoxelBlockGrid integration, {case}, {o['frames']} frames: "
                         f"{o['open3d_ms']:.1f} ms per frame; ours (feature net + integration) {o['ours_ms']:.1f} ms; "
                         f"ours / Open3D = {o['ours_ms'] / o['open3d_ms']:.1f}x.")
        elif o is not None:
            lines.append(f"Open3D, {case}: {o}.")
    lines += spread_lines(realtime_runs or {})
    goal_lines = ["", "Goals of issue 6:"]
    for case in cases:
        t, r = results[case].get("throughput"), results[case].get("realtime")
        if t:
            goal_lines.append(f"- {case}: >= 20 frames/s sustained: {'met' if t['ingest_fps'] >= 20 else 'NOT met'} "
                              f"({t['ingest_fps']:.1f})")
        if r:
            goal_lines.append(f"- {case}: mesh updated at least every 2 s: "
                              f"{'met' if r['update_interval_s']['max'] <= 2 else 'NOT met'} "
                              f"(max {r['update_interval_s']['max']:.2f} s); frame-to-mesh latency under 3 s: "
                              f"{'met' if r['latency_s']['max'] < 3 else 'NOT met'} "
                              f"(max {r['latency_s']['max']:.2f} s)")
    slower = "" if args.rate == 1.0 else f"; issue 13 asks them at the recorded rate, these at {args.rate:g}x it"
    goal_lines += ["", f"Goals of issue 13 (live at the sensors' rate; the median run{slower}):"]
    for case in cases:
        r = results[case].get("realtime")
        if not r:
            continue
        share = on_arrival_share(r)  # not set aside (those came late, after the stream or a pause)
        rate_hz = 1.0 / r["update_interval_s"]["median"]
        goal_lines.append(
            f"- {case}: frames integrated on arrival >= 95%: {'met' if share >= 0.95 else 'NOT met'} "
            f"({100 * share:.0f}%; {100 * r['frames_integrated'] / max(r['frames_sent'], 1):.0f}% with the frames "
            f"set aside); "
            f"every meshed block judged within 3 s of its last change: "
            f"{'met' if r['unjudged_over_3s'] == 0 else 'NOT met'} ({r['unjudged_over_3s']} blocks waited longer when "
            f"the last frame was integrated); latency median (frames not set aside) <= 1.5 s: "
            f"{'met' if r['latency_s']['median'] <= 1.5 else 'NOT met'} "
            f"({r['latency_s']['median']:.2f} s); mesh refresh >= 1 Hz: {'met' if rate_hz >= 1.0 else 'NOT met'} "
            f"({rate_hz:.2f} Hz, median interval)"
            + (f"; 5 s after the stream, live mesh equals replay's (F >= 99 at 2 cm): "
               f"{'met' if r['live_vs_replay_f'] >= 99 else 'NOT met'} (F {r['live_vs_replay_f']:.1f})"
               if "live_vs_replay_f" in r else ""))
    if all(case in results and "throughput" in results[case] for case in ("sample", "large")):
        def per_frame(r):
            return sum(r["stage_s"].values()) / max(r["frames_integrated"], 1)
        ratio = per_frame(results["large"]["throughput"]) / per_frame(results["sample"]["throughput"])
        goal_lines.append(f"- per-frame CPU cost, large room over sample room: {ratio:.2f}x "
                          f"({'met' if ratio <= 1.25 else 'NOT met'}, goal <= 1.25x)")
    for case in cases:
        if case == "large":
            every_run = [r for r in results[case].values() if isinstance(r, dict) and "case" in r]
            every_run += (realtime_runs or {}).get(case, [])
            rss = max(r["peak_rss_bytes"] for r in every_run)  # the highest of every run
            goal_lines.append(f"- peak RSS on the large room under 2 GB: {'met' if rss < 2e9 else 'NOT met'} "
                              f"({rss / 1e9:.2f} GB, the benchmark's copy of the published mesh included)")
    return "\n".join(lines + goal_lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bag", default=str(ROOT / "bags" / "sim_room"))
    ap.add_argument("--cases", nargs="+", default=["sample", "large"], choices=["sample", "large"])
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--large-room", type=float, nargs=3, default=list(LARGE_ROOM_M), metavar=("X", "Y", "Z"))
    ap.add_argument("--large-seconds", type=float, default=LARGE_ROOM_SECONDS)
    ap.add_argument("--large-seed", type=int, default=LARGE_ROOM_SEED)
    ap.add_argument("--cache", default=str(ROOT / "bench" / ".cache"))
    ap.add_argument("--max-seconds", type=float, default=0.0, help="only the first seconds of each bag (0 = all)")
    ap.add_argument("--open3d-frames", type=int, default=60, help="frames for the Open3D comparison (0 = skip it)")
    ap.add_argument("--rate", type=float, default=1.0,
                    help="realtime mode: the recorded times divided by this (0.5: half speed, slower sensors)")
    ap.add_argument("--no-write", dest="write", action="store_false")
    ap.add_argument("--no-replay-check", dest="replay_check", action="store_false",
                    help="skip replaying each bag to compare the live mesh with replay's (realtime mode)")
    ap.add_argument("--repeats", type=int, default=3,
                    help="realtime mode: runs per case (the table shows the median run, the spread follows it)")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                    help="a node parameter other than its default (YAML value), e.g. alpha_precision=float32")
    ap.add_argument("--case", help=argparse.SUPPRESS)
    ap.add_argument("--replay-dir", help=argparse.SUPPRESS)
    ap.add_argument("--mode", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.rate <= 0:
        ap.error("--rate must be positive")
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")
    if args.case:  # child process: one case in one mode, JSON on the last line
        result = run_open3d(args) if args.mode == "open3d" else run_node_case(args)
        print(json.dumps(result), flush=True)
        return
    results: dict[str, dict] = {}
    realtime_runs: dict[str, list[dict]] = {}
    with tempfile.TemporaryDirectory() as replays:
        for case in args.cases:
            bag_path(args, case)  # simulate the large room once, before anything is timed
            results[case] = {}
            for mode in list(args.modes) + (["open3d"] if args.open3d_frames > 0 else []):
                # one replay per case for the runs' live-vs-replay scores: the same code and bag give the same mesh
                child = [sys.executable, __file__, *sys.argv[1:], "--case", case, "--mode", mode,
                         "--replay-dir", str(Path(replays) / case)]
                runs = []
                for run in range(args.repeats if mode == "realtime" else 1):
                    out = subprocess.run(child, check=True, stdout=subprocess.PIPE, text=True).stdout
                    runs.append(json.loads(out.strip().splitlines()[-1]))
                    print(f"{case} {mode} (run {run + 1}): {json.dumps(runs[-1])}", flush=True)
                if mode == "realtime":
                    realtime_runs[case] = runs
                    runs = [median_run(runs)]
                results[case][mode] = runs[0]
    text = report(results, args, realtime_runs)
    print(text)
    if args.write:  # the recorded rate's section, or one per slower rate
        write_section("Real time" if args.rate == 1.0 else f"Real time at {args.rate:g}x the recorded rate", text)


if __name__ == "__main__":
    main()
