"""`senfunet simulate`: a simulated two-sensor recording as a dataset folder, and optionally as a bag."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "simulate a room scanned by a ToF and a stereo camera: dataset folder, optionally a rosbag2 bag"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=0, help="scene and sensor-noise seed (default 0)")
    parser.add_argument("--duration", type=float, default=10.0, metavar="S", help="seconds of recording (default 10)")
    parser.add_argument("--out", metavar="DIR", help="dataset folder to write (frames, poses, GT mesh); this, --bag or "
                        "--gt is needed")
    parser.add_argument("--bag", metavar="PATH",
                        help="also write the stream as a rosbag2 folder in the ROS topic layout")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="bag storage (default mcap)")
    parser.add_argument("--no-compress", action="store_true", help="mcap: do not zstd-compress the chunks")
    parser.add_argument("--gt", metavar="PLY", help="also write the ground-truth mesh as a PLY file here")
    parser.add_argument("--gt-voxel", type=float, default=0.02, metavar="M",
                        help="voxel size of the ground-truth meshes, metres (default 0.02)")
    parser.add_argument("--tof-rate", type=float, default=15.0, metavar="HZ", help="ToF frame rate (default 15)")
    parser.add_argument("--stereo-rate", type=float, default=20.0, metavar="HZ", help="stereo frame rate (default 20)")
    parser.add_argument("--pose-rate", type=float, default=100.0, metavar="HZ", help="pose stream rate (default 100)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from senfunet_core.errors import InputError
    from senfunet_core.learning import simulator as sim
    from senfunet_core.ply import write_ply
    from senfunet_ros.bagio import BagError, write_sequence_bag

    if not (args.out or args.bag or args.gt):
        print("senfunet simulate: nothing to write; pass --out DIR (the dataset), --bag PATH or --gt PLY",
              file=sys.stderr)
        return 2
    bag = Path(args.bag) if args.bag else None
    if bag is not None and bag.exists():
        print(f"senfunet simulate: {bag} exists already; remove it or choose another --bag path", file=sys.stderr)
        return 2
    try:
        scene = sim.make_scene(args.seed)
        print(f"senfunet simulate: seed {args.seed}, room {' x '.join(f'{v:.1f}' for v in scene.room_size_m)} m, "
              f"{args.duration:g} s", file=sys.stderr)
        seq = sim.simulate_sequence(scene, args.seed, duration_s=args.duration, tof_rate_hz=args.tof_rate,
                                    stereo_rate_hz=args.stereo_rate, pose_rate_hz=args.pose_rate)
        if args.out:
            sim.write_dataset(seq, Path(args.out), gt_voxel_size_m=args.gt_voxel)
            print(f"dataset: {args.out} ({len(seq.frames)} frames)")
        if args.gt:
            write_ply(args.gt, sim.gt_mesh(scene, args.gt_voxel))
            print(f"ground truth mesh: {args.gt}")
        if bag is not None:
            with tqdm(total=len(seq.frames), unit="frame", desc="bag", disable=args.no_progress,
                      file=sys.stderr) as bar:
                write_sequence_bag(seq, bag, storage=args.storage, compress=not args.no_compress,
                                   progress=lambda done, total: bar.update(done - bar.n))
            size = sum(f.stat().st_size for f in bag.rglob("*") if f.is_file())
            print(f"bag: {bag} ({args.storage}, {size / 1e6:.1f} MB)")
    except (InputError, BagError, OSError) as err:
        print(f"senfunet simulate: {err}", file=sys.stderr)
        return 2
    return 0
