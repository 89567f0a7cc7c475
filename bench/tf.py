"""What a robot's TF tree costs the node: its handling of /tf messages against their deserialisation
(rosbags', as replay reads /tf: what any reader pays before the node's code runs), in one run.

A robot's tree: odom -> base_link, an arm of `--joints` moving joints in a chain, `--wheels` wheels on
the base, all in each message (as robot_state_publisher and an odometry publish them), at `--rate-hz`.
Printed: CPU time per message of each, per transform of the node's, their ratio, and the share of a
core the node's handling takes at that rate. Prints only.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from senfunet_ros.ingest import Ingest, IngestConfig  # noqa: E402
from senfunet_ros.tf import TfBuffer  # noqa: E402


def robot_messages(n_messages: int, *, joints: int, wheels: int, rate_hz: float) -> list[bytes]:
    """Serialized tf2_msgs/TFMessage of the robot's moving links, one per 1 / rate_hz seconds."""
    types = _typestore().types
    Header, Time = types["std_msgs/msg/Header"], types["builtin_interfaces/msg/Time"]
    Vector3, Quaternion = types["geometry_msgs/msg/Vector3"], types["geometry_msgs/msg/Quaternion"]
    Transform, TransformStamped = types["geometry_msgs/msg/Transform"], types["geometry_msgs/msg/TransformStamped"]
    links = [("odom", "base_link")] + [("base_link" if j == 0 else f"arm_{j - 1}", f"arm_{j}") for j in range(joints)]
    links += [("base_link", f"wheel_{w}") for w in range(wheels)]
    messages = []
    for k in range(n_messages):
        sec, nanosec = divmod(1_700_000_000_000_000_000 + int(k * 1e9 / rate_hz), 1_000_000_000)
        transforms = []
        for i, (parent, child) in enumerate(links):
            angle = 0.01 * k + 0.1 * i
            transforms.append(TransformStamped(
                header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=parent), child_frame_id=child,
                transform=Transform(translation=Vector3(x=0.001 * k if i == 0 else 0.1, y=0.0, z=0.05),
                                    rotation=Quaternion(x=0.0, y=0.0, z=math.sin(angle / 2), w=math.cos(angle / 2)))))
        messages.append(bytes(_typestore().serialize_cdr(types[TF](transforms=transforms), TF)))
    return messages


TF = "tf2_msgs/msg/TFMessage"


def _typestore():  # noqa: ANN202 (rosbags' typestore)
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--joints", type=int, default=30)
    parser.add_argument("--wheels", type=int, default=4)
    parser.add_argument("--rate-hz", type=float, default=100.0)
    parser.add_argument("--messages", type=int, default=2000)
    args = parser.parse_args()
    data = robot_messages(args.messages, joints=args.joints, wheels=args.wheels, rate_hz=args.rate_hz)
    n_transforms = 1 + args.joints + args.wheels
    start = time.process_time()
    store = _typestore()
    decoded = [store.deserialize_cdr(d, TF) for d in data]
    deserialise_s = (time.process_time() - start) / len(data)
    ingest = Ingest(IngestConfig(sensors=("tof", "stereo"), tf=TfBuffer(), fixed_frame="odom"))
    start = time.process_time()
    for msg in decoded:
        ingest.add_tf(msg, static=False)
    handle_s = (time.process_time() - start) / len(data)
    print(f"{args.messages} /tf messages of {n_transforms} transforms (odom -> base_link, an arm of {args.joints} "
          f"joints, {args.wheels} wheels), CPU time per message:")
    print(f"  rosbags deserialisation: {deserialise_s * 1e3:.3f} ms")
    print(f"  the node's handling:     {handle_s * 1e3:.3f} ms ({handle_s / n_transforms * 1e6:.1f} us per transform), "
          f"{handle_s / deserialise_s:.2f}x the deserialisation")
    print(f"  at {args.rate_hz:g} Hz: the node's handling takes {handle_s * args.rate_hz:.3f} of a core, "
          f"deserialisation {deserialise_s * args.rate_hz:.3f}")


if __name__ == "__main__":
    main()
