"""`senfunet node`: the live fusion node with a parameter file."""
from __future__ import annotations

import argparse
import sys

HELP = "run the live fusion node (subscribes to the sensors, publishes ~/mesh, ~/weights, ~/status)"


def _error(text: str) -> int:
    """An error, on stderr; the exit code 2."""
    print(f"senfunet node: {text}", file=sys.stderr)
    return 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--params", metavar="YAML", help="ROS parameter file (ros__parameters under 'senfunet'), "
                        "e.g. config/default.yaml")
    parser.add_argument("--use-sim-time", action="store_true", help="follow /clock (for `senfunet play`)")
    parser.add_argument("ros_args", nargs=argparse.REMAINDER,
                        help="further ROS arguments after --, e.g. -- --ros-args -p voxel_size_m:=0.02")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    ros_args: list[str] = []
    if args.params:
        path = Path(args.params)
        if not path.is_file():
            return _error(f"parameter file {path} not found; pass e.g. --params config/default.yaml")
        if not any(arg.startswith("__node:=") for arg in args.ros_args or ()):  # else another node's section
            from senfunet_ros.replay import load_settings

            try:  # the node would take the file's section and ignore what it does not know: refuse it here
                load_settings(path, node_sections_only=True)
            except ValueError as err:
                return _error(str(err))
        ros_args += ["--params-file", str(path)]
    if args.use_sim_time:
        ros_args += ["-p", "use_sim_time:=true"]
    from senfunet_ros.node import main  # rclpy and torch load only when the node runs

    extra = [a for a in (args.ros_args or []) if a not in ("--", "--ros-args")]
    ros_args += extra
    return main(["senfunet", "--ros-args", *ros_args] if ros_args else ["senfunet"])
