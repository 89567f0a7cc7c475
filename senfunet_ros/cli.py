"""The `senfunet` command: one entry point, one module per sub-command in `senfunet_ros.commands`.

Each command module defines `HELP` (one line), `add_arguments(parser)` and `run(args) -> int`.
Modules are imported only when their command runs, so `senfunet simulate` never loads rclpy.
"""
from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS = ("node", "replay", "play", "simulate", "train", "evaluate", "demo")
DESCRIPTION = "SenFuNet-ROS: fuse the depth of two sensors (e.g. ToF + stereo) into one 3D mesh, learned weighting."
EPILOG = """examples:
  senfunet demo                                          the sample bag live through the node; mesh + PNG in out/demo
  senfunet replay bags/sim_room --out out/replay         offline: out/replay/mesh.ply and stats.json
  senfunet node --params config/default.yaml             the live node
`senfunet COMMAND --help` gives each command's options."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="senfunet", description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"senfunet_ros.commands.{name}")
        except ModuleNotFoundError as err:
            if err.name != f"senfunet_ros.commands.{name}":
                raise
            continue  # command not available in this build
        command = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(command)
        command.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--ros-args" in argv and "--" not in argv[:argv.index("--ros-args")]:
        # `senfunet node --ros-args -p ...`, as ros2 run takes it: the ROS arguments follow a '--' for argparse
        argv.insert(argv.index("--ros-args"), "--")
    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("senfunet: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
