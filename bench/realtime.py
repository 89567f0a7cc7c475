"""Real-time benchmark (issue 6): the sample bag and a larger simulated room through the engine as
the node schedules it, on this machine.

    .venv/bin/python bench/realtime.py                 # sample bag + large room, writes docs/performance.md
    .venv/bin/python bench/realtime.py --cases sample  # just the sample bag, no file written with --no-write

Each case runs in its own process (so peak RSS is that case's). Messages are read from the bag
first (disk I/O is not timed), then every message goes through the node's own path in recorded
order: Ingest (conversion: CDR -> numpy, pose interpolation), engine.integrate for every ready
frame, and every `--mesh-period` seconds of bag time engine.update() plus the MarkerArray CDR
encoding (message building). From the measured durations a single worker's live timeline is
replayed (work starts when its message has arrived and the worker is free) to get the mesh update
interval and the latency from a frame's arrival (its release by Ingest) to the end of the first
update that contains it. Open3D's VoxelBlockGrid TSDF integration is timed on the same frames
when `open3d` is importable (bench/requirements.txt).
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench._common import ROOT, command, machine, write_section  # noqa: E402


def large_bag(cache: Path, seed: int, room: tuple[float, float, float], seconds: float) -> Path:
    from senfunet_core import simulator as sim
    from senfunet_ros.bagio import write_sequence_bag

    path = cache / f"large_seed{seed}_{'x'.join(f'{v:g}' for v in room)}_{seconds:g}s"
    if not (path / "metadata.yaml").is_file():
        print(f"simulating {seconds:g} s in a {room} m room (seed {seed}) into {path} ...", flush=True)
        seq = sim.simulate_sequence(sim.make_scene(seed, room_size_m=room), seed, duration_s=seconds,
                                    tof_rate_hz=15, stereo_rate_hz=20)
        cache.mkdir(parents=True, exist_ok=True)
        write_sequence_bag(seq, path)
    return path


def run_case(args: argparse.Namespace) -> dict:
    from senfunet_core.engine import SenFuNet
    from senfunet_ros import conversions as conv
    from senfunet_ros.bagio import open_bag
    from senfunet_ros.ingest import Frame, Ingest
    from senfunet_ros.replay import TopicRouter, engine_config, engine_weights, ingest_config, load_settings

    if args.case == "sample":
        bag_path = Path(args.bag)
    else:
        bag_path = large_bag(Path(args.cache), args.large_seed, tuple(args.large_room), args.large_seconds)
    settings = load_settings(None)
    with open_bag(bag_path) as bag:
        router = TopicRouter(settings, bag.topics, bag_path)
        messages = list(bag.messages(router.topics))
    if args.max_seconds > 0:  # the first max_seconds of the bag only
        end = messages[0].log_time_ns + int(args.max_seconds * 1e9)
        messages = [m for m in messages if m.log_time_ns <= end]
    config = replace(engine_config(settings), alpha_voxels=args.alpha_voxels, alpha_tolerance=args.alpha_tolerance,
                     torch_threads=args.threads)
    engine = SenFuNet(config, weights=engine_weights(settings))
    ingest = Ingest(ingest_config(settings))
    t_start = messages[0].log_time_ns
    period_ns = int(args.mesh_period * 1e9)
    next_tick = t_start + period_ns
    events = []  # (ready_s, duration_s, kind, payload)
    stage = {k: 0.0 for k in ("conversion", "integration", "feature_nets", "alpha", "fusion+meshing", "messages")}
    frame_times = {s: [] for s in config.sensors}
    n_frames = 0
    fused_frames = []  # frames integrated since the last update: their ready times
    bag_s = (messages[-1].log_time_ns - t_start) / 1e9
    for msg in messages:
        now_s = (msg.log_time_ns - t_start) / 1e9
        while msg.log_time_ns >= next_tick:  # the node's mesh timer
            tick_s = (next_tick - t_start) / 1e9
            t0 = time.perf_counter()
            update = engine.update()
            t1 = time.perf_counter()
            conv.marker_array_cdr(update.changed, update.removed, stamp_ns=next_tick, frame_id="map",
                                  delete_all_first=update.cleared)
            t2 = time.perf_counter()
            stage["alpha"] += engine.timings_s.get("alpha", 0.0)
            stage["fusion+meshing"] += engine.timings_s.get("mesh", 0.0)
            stage["messages"] += t2 - t1
            events.append((tick_s, t2 - t0, "update", fused_frames))
            fused_frames = []
            next_tick += period_ns
        t0 = time.perf_counter()
        decoded = router.decode(msg)
        ready = []
        if decoded is not None:
            router.dispatch(ingest, *decoded)
            ready = [f for f in ingest.pop_ready() if isinstance(f, Frame)]
        t1 = time.perf_counter()
        stage["conversion"] += t1 - t0
        events.append((now_s, t1 - t0, "conversion", None))
        for frame in ready:
            t0 = time.perf_counter()
            engine.integrate(frame.sensor, frame.depth_m, frame.K, frame.T_world_camera, frame.rgb)
            dt = time.perf_counter() - t0
            ingest.mark_integrated(frame.sensor)
            frame_times[frame.sensor].append(dt)
            stage["integration"] += dt
            stage["feature_nets"] += engine.timings_s.get("feature_net", 0.0)
            events.append((now_s, dt, "integrate", None))
            fused_frames.append(now_s)
            n_frames += 1
    # the last update, for the frames after the last tick
    t0 = time.perf_counter()
    update = engine.update()
    t1 = time.perf_counter()
    conv.marker_array_cdr(update.changed, update.removed, stamp_ns=next_tick, frame_id="map")
    t2 = time.perf_counter()
    stage["alpha"] += engine.timings_s.get("alpha", 0.0)
    stage["fusion+meshing"] += engine.timings_s.get("mesh", 0.0)
    stage["messages"] += t2 - t1
    events.append(((next_tick - t_start) / 1e9, t2 - t0, "update", fused_frames))
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    stats = engine.stats()

    # a single worker's live timeline
    free = 0.0
    update_ends, latencies = [], []
    for ready_s, duration, kind, payload in sorted(events, key=lambda e: e[0]):
        start = max(ready_s, free)
        free = start + duration
        if kind == "update":
            update_ends.append(free)
            latencies += [free - r for r in payload]
    busy = sum(e[1] for e in events)
    intervals = np.diff(update_ends) if len(update_ends) > 1 else np.array([np.nan])
    stage["integration (rest)"] = stage["integration"] - stage["feature_nets"]
    result = {
        "case": args.case, "bag": str(bag_path.relative_to(ROOT) if bag_path.is_relative_to(ROOT) else bag_path),
        "bag_seconds": bag_s, "frames": n_frames, "busy_s": busy,
        "ingest_fps": n_frames / busy, "realtime_factor": bag_s / busy,
        "per_frame_ms": 1e3 * busy / max(n_frames, 1),
        "stages_ms_per_frame": {k: 1e3 * v / max(n_frames, 1) for k, v in stage.items()},
        "integrate_ms_median": {s: 1e3 * float(np.median(v)) for s, v in frame_times.items() if v},
        "update_interval_s": {"median": float(np.median(intervals)), "max": float(np.max(intervals))},
        "latency_s": {"median": float(np.median(latencies)), "max": float(np.max(latencies))},
        "peak_rss_bytes": peak_rss, "blocks": stats["blocks"], "observed_voxels": stats["observed_voxels"],
        "bytes_per_observed_voxel": stats["bytes_per_observed_voxel"],
        "alpha_voxels_evaluated": engine.counters["alpha_voxels"],
    }
    del engine
    result["open3d"] = time_open3d(messages, router, settings) if args.open3d else None
    return result


def time_open3d(messages, router, settings) -> dict | str:
    """Open3D VoxelBlockGrid TSDF integration (1 cm voxels, 8^3 blocks, same truncation) on the same frames."""
    try:
        import open3d as o3d
        import open3d.core as o3c
    except Exception as err:  # optional benchmark dependency
        return f"not available ({type(err).__name__})"
    from senfunet_ros.ingest import Frame, Ingest
    from senfunet_ros.replay import ingest_config

    ingest = Ingest(ingest_config(settings))
    device = o3c.Device("CPU:0")
    vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
                                        attr_channels=((1), (1)), voxel_size=0.01, block_resolution=8,
                                        block_count=200000, device=device)
    times = []
    for msg in messages:
        decoded = router.decode(msg)
        if decoded is None:
            continue
        router.dispatch(ingest, *decoded)
        for frame in ingest.pop_ready():
            if not isinstance(frame, Frame):
                continue
            depth = np.nan_to_num(frame.depth_m, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
            t0 = time.perf_counter()
            image = o3d.t.geometry.Image(o3c.Tensor(depth, device=device))
            intrinsic = o3c.Tensor(frame.K, o3c.float64)
            extrinsic = o3c.Tensor(np.linalg.inv(frame.T_world_camera), o3c.float64)
            coords = vbg.compute_unique_block_coordinates(image, intrinsic, extrinsic, depth_scale=1.0,
                                                          depth_max=5.0, trunc_voxel_multiplier=5.0)
            vbg.integrate(coords, image, intrinsic, extrinsic, depth_scale=1.0, depth_max=5.0,
                          trunc_voxel_multiplier=5.0)
            times.append(time.perf_counter() - t0)
    return {"version": o3d.__version__, "integrate_ms_median": 1e3 * float(np.median(times)),
            "integrate_ms_mean": 1e3 * float(np.mean(times)), "frames": len(times)}


def report(results: list[dict], args: argparse.Namespace) -> str:
    lines = [f"Machine: {machine()}", "", f"Command: `{command()}`", "",
             f"Engine: alpha_voxels={args.alpha_voxels}, alpha_tolerance={args.alpha_tolerance}, torch threads "
             f"{args.threads}; shipped weights if present; mesh update every {args.mesh_period:g} s of bag time; "
             "one worker does everything (conversion, integration, update, message building).", ""]
    head = "| | " + " | ".join(r["case"] for r in results) + " |"
    lines += [head, "|---" * (len(results) + 1) + "|"]

    def row(name, fn):
        lines.append(f"| {name} | " + " | ".join(fn(r) for r in results) + " |")

    row("bag", lambda r: f"`{r['bag']}` ({r['bag_seconds']:.1f} s)")
    row("depth frames (both sensors)", lambda r: str(r["frames"]))
    row("sustained ingest (frames/s)", lambda r: f"{r['ingest_fps']:.1f}")
    row("real-time factor (bag s / busy s)", lambda r: f"{r['realtime_factor']:.2f}")
    row("busy time per frame (ms)", lambda r: f"{r['per_frame_ms']:.1f}")
    for stage in results[0]["stages_ms_per_frame"]:
        if stage == "integration":
            continue
        row(f"- {stage} (ms/frame)", lambda r, s=stage: f"{r['stages_ms_per_frame'][s]:.1f}")
    row("integrate, median per sensor (ms)",
        lambda r: ", ".join(f"{s} {v:.0f}" for s, v in r["integrate_ms_median"].items()))
    row("mesh update interval, median / max (s)",
        lambda r: f"{r['update_interval_s']['median']:.2f} / {r['update_interval_s']['max']:.2f}")
    row("frame-to-mesh latency, median / max (s)",
        lambda r: f"{r['latency_s']['median']:.2f} / {r['latency_s']['max']:.2f}")
    row("peak RSS (GB)", lambda r: f"{r['peak_rss_bytes'] / 1e9:.2f}")
    row("blocks / observed voxels", lambda r: f"{r['blocks']} / {r['observed_voxels']}")
    row("bytes per observed voxel", lambda r: f"{r['bytes_per_observed_voxel']:.0f}")
    row("alpha evaluations (voxels)", lambda r: str(r["alpha_voxels_evaluated"]))

    def o3d_cell(r):
        o = r["open3d"]
        if not isinstance(o, dict):
            return o or "not run"
        ours = float(np.mean(list(r["integrate_ms_median"].values())))
        return f"{o['integrate_ms_median']:.1f} ms/frame (Open3D {o['version']}); ours / Open3D = {ours / o['integrate_ms_median']:.1f}x"

    row("Open3D VoxelBlockGrid integrate", o3d_cell)
    if len(results) == 2:
        ratio = results[1]["per_frame_ms"] / results[0]["per_frame_ms"]
        lines += ["", f"Per-frame cost, {results[1]['case']} over {results[0]['case']}: {ratio:.2f}x."]
    goals = ["", "Goals of issue 6 (>= 20 frames/s, mesh every <= 2 s, latency < 3 s, large/sample <= 1.25x, "
             "peak RSS < 2 GB on the large room):"]
    for r in results:
        goals.append(f"- {r['case']}: ingest {'met' if r['ingest_fps'] >= 20 else 'NOT met'}, "
                     f"update interval {'met' if r['update_interval_s']['max'] <= 2 else 'NOT met'}, "
                     f"latency {'met' if r['latency_s']['max'] < 3 else 'NOT met'}, "
                     f"RSS {'met' if r['peak_rss_bytes'] < 2e9 else 'NOT met'}")
    return "\n".join(lines + goals)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bag", default=str(ROOT / "bags" / "sim_room"))
    ap.add_argument("--cases", nargs="+", default=["sample", "large"], choices=["sample", "large"])
    ap.add_argument("--large-room", type=float, nargs=3, default=[12.0, 8.0, 2.8], metavar=("X", "Y", "Z"))
    ap.add_argument("--large-seconds", type=float, default=30.0)
    ap.add_argument("--large-seed", type=int, default=4243)
    ap.add_argument("--cache", default=str(ROOT / "bench" / ".cache"))
    ap.add_argument("--max-seconds", type=float, default=0.0, help="only the first seconds of each bag (0 = all)")
    ap.add_argument("--mesh-period", type=float, default=1.0)
    ap.add_argument("--alpha-voxels", default="surface", choices=["all", "observed", "surface"])
    ap.add_argument("--alpha-tolerance", type=float, default=0.02)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-open3d", dest="open3d", action="store_false")
    ap.add_argument("--no-write", dest="write", action="store_false")
    ap.add_argument("--case", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.case:  # child process: one case, JSON on the last line
        print(json.dumps(run_case(args)), flush=True)
        return
    results = []
    for case in args.cases:
        child = [sys.executable, __file__, *sys.argv[1:], "--case", case]
        out = subprocess.run(child, check=True, stdout=subprocess.PIPE, text=True).stdout
        results.append(json.loads(out.strip().splitlines()[-1]))
        print(json.dumps(results[-1], indent=1), flush=True)
    text = report(results, args)
    print(text)
    if args.write:
        write_section("Real time", text)


if __name__ == "__main__":
    main()
