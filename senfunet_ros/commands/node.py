"""`senfunet node`: the live fusion node with a parameter file."""
from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

HELP = "run the live fusion node (subscribes to the sensors, publishes ~/mesh, ~/weights, ~/status)"


def _error(text: str) -> int:
    """An error, on stderr; the exit code 2."""
    print(f"senfunet node: {text}", file=sys.stderr)
    return 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--params", "--params-file", dest="params", metavar="YAML",
                        help="ROS parameter file (ros__parameters under 'senfunet'), e.g. config/default.yaml")
    parser.add_argument("--use-sim-time", action="store_true", help="follow /clock (for `senfunet play`)")
    parser.add_argument("ros_args", nargs=argparse.REMAINDER,
                        help="further ROS arguments after --, e.g. -- --ros-args -p voxel_size_m:=0.02")


def node_fqn(ros_args: Sequence[str]) -> str:
    """The node's namespace and name as the remappings among `ros_args` set them (`__ns:=/robot1`,
    `__node:=fusion`): the parameter file sections it gets depend on both."""
    from senfunet_ros.params import NODE_NAME

    namespace, name = "", NODE_NAME
    for arg in ros_args:  # -r __ns:=/robot1, or one for this node alone (senfunet:__ns:=/robot1)
        for key in ("__ns:=", "__node:="):
            target, _, value = arg.partition(key)
            if key in arg and target in ("", f"{NODE_NAME}:"):
                namespace, name = (value.strip("/"), name) if key == "__ns:=" else (namespace, value)
    return f"/{namespace}/{name}" if namespace else f"/{name}"


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    ros_args: list[str] = []
    if args.params:
        path = Path(args.params)
        if not path.is_file():
            return _error(f"parameter file {path} not found; pass e.g. --params config/default.yaml")
        from senfunet_ros.params_file import load_settings

        try:  # the node would take the file's sections for it and ignore what it does not know: refuse it here
            load_settings(path, node_sections_only=True, node_fqn=node_fqn(args.ros_args or ()))
        except ValueError as err:
            return _error(str(err))
        ros_args += ["--params-file", str(path)]
    if args.use_sim_time:
        ros_args += ["-p", "use_sim_time:=true"]
    from senfunet_ros.node import main  # rclpy and torch load only when the node runs

    extra = [a for a in (args.ros_args or []) if a not in ("--", "--ros-args")]
    ros_args += extra
    return main(["senfunet", "--ros-args", *ros_args] if ros_args else ["senfunet"])
