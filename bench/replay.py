"""`senfunet replay` against Open3D's TSDF fusion, side by side in one run (issue 13 item 6).

    .venv/bin/pip install -r bench/requirements.txt      # open3d, bench-only
    .venv/bin/python bench/replay.py                      # sample bag and a large simulated room
    .venv/bin/python bench/replay.py --cases sample --no-write

Each side is one whole command in a child process, timed from its start to its exit, with its
peak RSS (wait4's rusage):
- ours: `senfunet replay BAG --out DIR` with the default parameters (the fused mesh and stats.json;
  no --compare);
- Open3D: the same bag's depth frames of both sensors (read and decoded by our bag reader, the same
  work replay does) integrated into one `t.geometry.VoxelBlockGrid` (1 cm voxels, 8^3 blocks, the
  same truncation band), then `extract_triangle_mesh` and a PLY written.
The ratio of the two wall times is the figure; absolute times drift on a shared machine.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench._common import ROOT, command, machine, simulated_bag, write_section  # noqa: E402

GOAL_RATIO = 1.5


def timed_child(argv: list[str]) -> dict:
    """Run a command; its wall time, peak RSS and exit code."""
    start = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    wall_s = time.perf_counter() - start
    out, err = proc.stdout.read(), proc.stderr.read()  # type: ignore[union-attr]
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed ({proc.returncode}):\n{out}\n{err}")
    return {"wall_s": wall_s, "peak_rss_bytes": usage.ru_maxrss * 1024, "stdout": out}


def open3d_child(bag: Path, out: Path) -> None:
    """The Open3D side (runs in its own process)."""
    import numpy as np
    import open3d as o3d
    import open3d.core as o3c

    from senfunet_ros.bagio import open_bag
    from senfunet_ros.ingest import Frame, Ingest
    from senfunet_ros.replay import TopicRouter, ingest_config
    from senfunet_ros.params_file import load_settings

    settings = load_settings(None)
    device = o3c.Device("CPU:0")
    vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
                                        attr_channels=((1), (1)), voxel_size=settings.voxel_size_m,
                                        block_resolution=8, block_count=50000, device=device)
    trunc = 0.5 * settings.band_m / settings.voxel_size_m  # the same band: +-band/2
    depth_max = max(sensor.depth_max_m for sensor in settings.sensors)
    frames = 0
    with open_bag(bag) as reader:
        router = TopicRouter(settings, reader.topics, bag)
        ingest = Ingest(ingest_config(settings))
        for msg in reader.messages(router.topics):
            decoded = router.decode(msg)
            if decoded is None:
                continue
            router.dispatch(ingest, *decoded)
            for frame in ingest.pop_ready():
                if not isinstance(frame, Frame):
                    continue
                depth = np.nan_to_num(frame.depth_m, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
                image = o3d.t.geometry.Image(o3c.Tensor(depth, device=device))
                intrinsic = o3c.Tensor(frame.K, o3c.float64)
                extrinsic = o3c.Tensor(np.linalg.inv(frame.T_world_camera), o3c.float64)
                coords = vbg.compute_unique_block_coordinates(image, intrinsic, extrinsic, depth_scale=1.0,
                                                              depth_max=depth_max, trunc_voxel_multiplier=trunc)
                vbg.integrate(coords, image, intrinsic, extrinsic, depth_scale=1.0, depth_max=depth_max,
                              trunc_voxel_multiplier=trunc)
                frames += 1
    mesh = vbg.extract_triangle_mesh()
    o3d.t.io.write_triangle_mesh(str(out / "open3d.ply"), mesh)
    print(json.dumps({"frames": frames, "version": o3d.__version__, "faces": int(mesh.triangle.indices.shape[0])}))


def run_case(name: str, bag: Path) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        ours = timed_child([sys.executable, "-m", "senfunet_ros.cli", "replay", str(bag), "--out",
                            f"{tmp}/ours", "--no-progress"])
        stats = json.loads(Path(f"{tmp}/ours/stats.json").read_text())
        theirs = timed_child([sys.executable, __file__, "--open3d-child", str(bag), "--out", tmp])
        theirs.update(json.loads(theirs.pop("stdout").strip().splitlines()[-1]))
    ours.pop("stdout")
    frames = sum(c["integrated"] for c in stats["sensors"].values())
    return {"case": name, "bag": str(bag), "ours": ours, "open3d": theirs, "frames": frames,
            "engine": stats["engine"], "timings": stats["timings"]}


def report(results: list[dict]) -> str:
    lines = [f"Machine: {machine()}", "", f"Command: `{command()}`", "",
             "Whole commands, each in its own process: `senfunet replay BAG --out DIR` (default parameters: "
             "the fused mesh and stats.json) against Open3D's VoxelBlockGrid TSDF fusion of both sensors' "
             "frames of the same bag (read by our bag reader, 1 cm voxels, 8^3 blocks, the same band), "
             "mesh extraction and PLY writing included.", "",
             "| | " + " | ".join(r["case"] for r in results) + " |", "|---" * (len(results) + 1) + "|"]

    def row(label: str, fn) -> None:
        lines.append(f"| {label} | " + " | ".join(fn(r) for r in results) + " |")

    row("bag", lambda r: f"`{Path(r['bag']).name}`, {r['frames']} depth frames fused")
    row("senfunet replay: wall time (s)", lambda r: f"{r['ours']['wall_s']:.1f}")
    row("- integration / mesh extraction incl. weighting net (s)",
        lambda r: f"{r['timings']['integrate_s']:.1f} / {sum(r['timings']['extract_s'].values()):.1f}")
    row(f"Open3D {results[0]['open3d']['version']}: wall time (s)", lambda r: f"{r['open3d']['wall_s']:.1f}")
    row("**replay / Open3D**", lambda r: f"**{r['ours']['wall_s'] / r['open3d']['wall_s']:.2f}x**")
    row("peak RSS: replay / Open3D (GB)",
        lambda r: f"{r['ours']['peak_rss_bytes'] / 1e9:.2f} / {r['open3d']['peak_rss_bytes'] / 1e9:.2f}")
    row("blocks / observed voxels", lambda r: f"{r['engine']['blocks']} / {r['engine']['observed_voxels']}")
    row("grid bytes per observed voxel", lambda r: f"{r['engine']['bytes_per_observed_voxel']:.0f}")
    lines += ["", f"Goal of issue 13: replay at most {GOAL_RATIO}x Open3D's time:"]
    for r in results:
        ratio = r["ours"]["wall_s"] / r["open3d"]["wall_s"]
        lines.append(f"- {r['case']}: {'met' if ratio <= GOAL_RATIO else 'NOT met'} ({ratio:.2f}x)")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bag", default=str(ROOT / "bags" / "sim_room"))
    ap.add_argument("--cases", nargs="+", default=["sample", "large"], choices=["sample", "large"])
    ap.add_argument("--large-room", type=float, nargs=3, default=[8.4, 7.2, 2.6], metavar=("X", "Y", "Z"))
    ap.add_argument("--large-seconds", type=float, default=40.0)
    ap.add_argument("--large-seed", type=int, default=4244)
    ap.add_argument("--cache", default=str(ROOT / "bench" / ".cache"))
    ap.add_argument("--no-write", dest="write", action="store_false")
    ap.add_argument("--open3d-child", metavar="BAG", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.open3d_child:
        open3d_child(Path(args.open3d_child), Path(args.out))
        return
    try:
        import open3d  # noqa: F401
    except ImportError:
        sys.exit("bench/replay.py needs open3d: .venv/bin/pip install -r bench/requirements.txt")
    bags = {"sample": Path(args.bag)}
    if "large" in args.cases:
        bags["large"] = simulated_bag(Path(args.cache), name="replay", seed=args.large_seed,
                                      room=tuple(args.large_room), seconds=args.large_seconds, tof_rate_hz=15,
                                      stereo_rate_hz=10)
    results = []
    for case in args.cases:
        results.append(run_case(case, bags[case]))
        print(json.dumps({k: v for k, v in results[-1].items() if k != "timings"}), flush=True)
    text = report(results)
    print(text)
    if args.write:
        write_section("Replay against Open3D", text)


if __name__ == "__main__":
    main()
