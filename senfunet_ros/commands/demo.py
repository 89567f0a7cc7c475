"""`senfunet demo`: the sample bag through `senfunet play` and the live node over real DDS.

Starts `senfunet node --use-sim-time` and `senfunet play BAG` as two processes on a private
ROS_DOMAIN_ID, follows the node's ~/status until the bag is played and every queued frame is
fused, calls ~/save_mesh, renders the fused mesh (next to TSDF Fusion) to a PNG and prints where
both are. A bag that breaks midway (play exits with an error) still gets the mesh of what was played,
said with play's error, and exit code 1.
"""
from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

from . import SAMPLE_BAG, sample_bag

HELP = "fuse the sample bag live: node + play over DDS, save the mesh, render a PNG of it"

NODE = "senfunet"  # the node's name: its services and topics live under /senfunet/


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--bag", metavar="BAG", help=f"bag to play (default: bags/{SAMPLE_BAG} of this clone)")
    parser.add_argument("--out", default="out/demo", metavar="DIR", help="output folder (default out/demo)")
    parser.add_argument("--params", metavar="FILE",
                        help="node parameter file (default: the built-in defaults); the demo sets output_dir (--out), "
                        "queue_size (--queue-size), max_lag_s 0 and tsdf_fusion true over it")
    parser.add_argument("--rate", type=float, default=0.25, metavar="R", help="playback speed factor (default 0.25)")
    parser.add_argument("--queue-size", type=int, default=400, metavar="N",
                        help="the node's queue_size parameter (default 400: a slow CPU falls behind instead of "
                        "dropping frames, and the demo waits until every frame is fused)")
    parser.add_argument("--domain-id", type=int, metavar="N",
                        help="ROS_DOMAIN_ID to use (default: a random private one)")
    parser.add_argument("--timeout", type=float, default=900.0, metavar="S",
                        help="give up after S seconds (default 900)")
    parser.add_argument("--no-render", action="store_true", help="skip the PNG")
    parser.add_argument("--live-mesh", action="store_true",
                        help="also write live_mesh.ply: what a subscriber to ~/mesh sees once the node has fused "
                             "every frame and the weighting net has caught up (before ~/save_mesh)")


class DemoError(Exception):
    pass


def _say(text: str) -> None:
    print(f"senfunet demo: {text}", flush=True)


def _node_topics_in(bag: Path, params: str | None) -> list[str]:
    """The bag's topics the node takes, as the bag names them; BagError (replay's) when the bag lacks
    one the node needs, naming what it has and what to set."""
    from senfunet_ros.bagio import open_bag
    from senfunet_ros.params_file import load_settings
    from senfunet_ros.replay import TopicRouter

    settings = load_settings(params)
    with open_bag(bag) as reader:
        return sorted(TopicRouter(settings, reader.topics, bag).topics)


def _tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""


def _stop(proc: subprocess.Popen | None, timeout: float = 15.0) -> None:
    """SIGINT (the node shuts down cleanly), then terminate, then kill."""
    if proc is None or proc.poll() is not None:
        return
    for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 5.0)):
        proc.send_signal(sig)
        try:
            proc.wait(wait)
            return
        except subprocess.TimeoutExpired:
            continue
    proc.kill()
    proc.wait()


def _parse_status(msg) -> dict[str, dict[str, int]]:  # noqa: ANN001 - diagnostic_msgs/DiagnosticArray
    """Per-sensor counters from the node's ~/status (statuses named 'senfunet: <sensor>')."""
    out: dict[str, dict[str, int]] = {}
    for status in msg.status:
        if not status.name.startswith("senfunet: ") or status.name.endswith(": pipeline"):
            continue
        values = {}
        for kv in status.values:
            try:
                values[kv.key] = int(kv.value)
            except ValueError:
                pass
        out[status.name.split(": ", 1)[1]] = values
    return out


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    bag = Path(args.bag) if args.bag else sample_bag()
    if not bag.exists():
        _say(f"bag {bag} not found; regenerate the sample with `bash scripts/make_sample_bag.sh` or pass --bag")
        return 2
    if args.params and not Path(args.params).is_file():
        _say(f"parameter file {args.params} not found")
        return 2
    if not args.rate > 0:
        _say(f"--rate must be > 0, got {args.rate}")
        return 2
    try:  # replay's check: a bag without the node's topics is said now, not after a run that fuses nothing
        topics = _node_topics_in(bag, args.params)
    except (ValueError, OSError) as err:  # BagError and InputError are ValueErrors
        _say(str(err))
        return 2
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    for stale in ("mesh.ply", "mesh.png"):
        (out / stale).unlink(missing_ok=True)
    domain = args.domain_id if args.domain_id is not None else random.randint(1, 101)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    _say(f"ROS_DOMAIN_ID={domain}; logs in {out}")
    demo = _Demo(args, bag, out, topics)
    signal.signal(signal.SIGTERM, _interrupt)  # rclpy takes over SIGINT/SIGTERM while it is initialised
    try:
        mesh_path = demo.run()
    except DemoError as err:
        _say(str(err))
        return 1
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: stop the node and play, no traceback
        _say("interrupted; stopping the node and play")
        return 0
    finally:
        demo.stop()
    if demo.unfused and len(demo.unfused) == len(demo.status):
        warnings = sorted({line.split("]: ", 1)[-1] for line in _tail(demo.node_log, 400).splitlines()
                           if "[WARN]" in line or "[ERROR]" in line})
        played = f" ({demo.play_failed}: see above)" if demo.play_failed else ""
        _say(f"the node fused no frame of {bag}{played}, so {mesh_path} is empty; what the node said:\n"
             + "\n".join(f"  {w}" for w in warnings[:10])
             + f"\n(the node's whole log: {demo.node_log})")
        return 2
    if demo.unfused:
        _say(f"note: {', '.join(demo.unfused)} fused no frame (see above and {demo.node_log}), so the mesh holds "
             "only the surface the other sensor saw alone and the weighting net trusts")
    png = None
    if not args.no_render:
        png = out / "mesh.png"
        _render(out, png, sensors=_sensor_names(args.params))
    print(f"fused mesh: {mesh_path}")
    if png is not None:
        print(f"rendering:  {png}")
    if demo.play_failed:  # said again last: the mesh holds only what was played before play broke
        _say(f"{demo.play_failed} (see above): {mesh_path} holds what the node fused of the bag up to where play "
             f"stopped; play's log: {demo.play_log}")
        return 1
    return 0


class _Demo:
    """The two child processes and a small rclpy node that watches ~/status and calls ~/save_mesh."""

    def __init__(self, args: argparse.Namespace, bag: Path, out: Path, topics: list[str]) -> None:
        self.args, self.bag, self.out = args, bag, out
        self.topics = topics  # the bag's topics the node takes: play waits for the node's subscriptions to them
        self.deadline = time.monotonic() + args.timeout
        self.cli = [sys.executable, "-m", "senfunet_ros.cli"]
        self.node_log, self.play_log = out / "node.log", out / "play.log"
        self.node_proc: subprocess.Popen | None = None
        self.play_proc: subprocess.Popen | None = None
        self.status: dict[str, dict[str, int]] = {}  # latest per-sensor counters from ~/status
        self.status_count = 0
        self.pipeline_values: dict[str, str] = {}  # the node's "senfunet: pipeline" status
        self.play_failed = ""  # why play exited with an error (a bag that breaks midway), or ""
        self.unfused: list[str] = []  # the sensors that fused no frame

    def _spawn(self, cmd: list[str], log_path: Path) -> subprocess.Popen:
        with log_path.open("w") as log:
            return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=os.environ.copy())

    def stop(self) -> None:
        _stop(self.play_proc)
        _stop(self.node_proc)

    def _check(self, what: str) -> None:
        import rclpy

        if not rclpy.ok():  # rclpy's SIGINT/SIGTERM handler shut the context down: an interruption
            raise KeyboardInterrupt
        if self.node_proc is not None and self.node_proc.poll() is not None:
            raise DemoError(f"the node exited (code {self.node_proc.returncode}) {what}; "
                            f"its log ({self.node_log}):\n{_tail(self.node_log)}")
        if time.monotonic() > self.deadline:
            raise DemoError(f"timed out {what} (--timeout {self.args.timeout:g} s); logs in {self.out}")

    def _on_status(self, msg) -> None:  # noqa: ANN001 - DiagnosticArray
        for status in msg.status:
            if status.name == "senfunet: pipeline":
                self.pipeline_values = {kv.key: kv.value for kv in status.values}
        parsed = _parse_status(msg)
        if parsed:
            self.status = parsed
            self.status_count += 1

    def _progress(self) -> str:
        return ", ".join(f"{s}: {c.get('integrated', 0)} of {c.get('received', 0)} frames fused"
                         for s, c in sorted(self.status.items()))

    def _clock_after_bag(self, node):  # noqa: ANN001, ANN202 - rclpy Node in, callable out
        """A function that keeps /clock running on from the bag's end (at the playback rate).

        `senfunet play`, like `ros2 bag play`, stops /clock when the bag ends; a node whose timers
        follow sim time would then stand still with frames in its queues. The demo keeps sim time
        going until the mesh is saved, as a simulator or a robot would.
        """
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock

        from senfunet_ros.bagio import open_bag

        with open_bag(self.bag) as reader:
            end_ns = reader.end_ns
        pub = node.create_publisher(Clock, "/clock", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        msg = Clock()
        start = time.monotonic()

        def tick() -> None:
            now_ns = end_ns + int((time.monotonic() - start) * self.args.rate * 1e9)
            msg.clock.sec, msg.clock.nanosec = divmod(now_ns, 1_000_000_000)
            pub.publish(msg)

        return tick

    def run(self) -> Path:
        """Node up, bag played, queues drained, mesh saved; returns the fused mesh's path."""
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from std_srvs.srv import Trigger

        from senfunet_ros.dds import shut_down_rclpy

        args = self.args
        node_cmd = [*self.cli, "node", "--use-sim-time"]
        if args.params:
            node_cmd += ["--params", str(args.params)]
        # every frame fused (a slow CPU falls behind instead of skipping), and TSDF Fusion kept for the picture
        node_cmd += ["--", "-p", f"output_dir:={self.out}", "-p", f"queue_size:={args.queue_size}",
                     "-p", "max_lag_s:=0.0", "-p", "tsdf_fusion:=true"]
        self.node_proc = self._spawn(node_cmd, self.node_log)
        rclpy.init(args=None)
        node = rclpy.create_node("senfunet_demo", start_parameter_services=False)
        try:
            node.create_subscription(DiagnosticArray, f"/{NODE}/status", self._on_status,
                                     QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
            save = node.create_client(Trigger, f"/{NODE}/save_mesh")
            _say("starting the node (loads torch and the weights)...")
            while not save.wait_for_service(timeout_sec=0.5):
                self._check("while starting")
            _say(f"node up; playing {self.bag} at rate {args.rate:g}")
            self.play_proc = self._spawn([*self.cli, "play", str(self.bag), "--rate", str(args.rate), "--topics",
                                          *self.topics,
                                          "--wait-subscribers", "20"], self.play_log)
            last_print = time.monotonic()
            while self.play_proc.poll() is None:
                rclpy.spin_once(node, timeout_sec=0.2)
                self._check("while playing")
                if time.monotonic() - last_print > 10.0 and self.status:
                    last_print = time.monotonic()
                    _say("  " + self._progress())
            if self.play_proc.returncode != 0:  # what the node fused of what was played is still saved
                self.play_failed = f"play failed (code {self.play_proc.returncode})"
                _say(f"{self.play_failed}:\n{_tail(self.play_log)}")
                _say("saving what the node fused of the bag up to there; waiting for its queued frames...")
            else:
                _say("bag played; waiting for the node to fuse its queued frames...")
            tick_clock = self._clock_after_bag(node)
            stable, previous = 0, None
            while stable < 2:  # two status reports in a row: queues empty, counters unchanged
                before = self.status_count
                while self.status_count == before:
                    tick_clock()
                    rclpy.spin_once(node, timeout_sec=0.05)
                    self._check("while fusing")
                if time.monotonic() - last_print > 10.0:
                    last_print = time.monotonic()
                    _say("  " + self._progress())
                snapshot = {s: (c.get("integrated"), c.get("received")) for s, c in self.status.items()}
                idle = all(c.get("queue_depth", 1) == 0 for c in self.status.values())
                stable = stable + 1 if idle and snapshot == previous else 0
                previous = snapshot
            if args.live_mesh:
                self._save_live_mesh(node, tick_clock)
            _say("saving the mesh (~/save_mesh)...")
            future = save.call_async(Trigger.Request())
            while not future.done():
                tick_clock()
                rclpy.spin_once(node, timeout_sec=0.05)
                self._check("while saving")
            response = future.result()
            if not response.success:
                raise DemoError(f"{self.play_failed} (see above), and " * bool(self.play_failed)
                                + f"~/save_mesh failed: {response.message}")
            for sensor, c in sorted(self.status.items()):
                dropped = {k[len("dropped."):]: v for k, v in c.items() if k.startswith("dropped.") and v}
                line = f"{sensor}: {c.get('integrated', 0)} of {c.get('received', 0)} frames fused"
                if dropped:
                    line += "; dropped: " + ", ".join(f"{v} {k}" for k, v in dropped.items())
                _say(line)
            self.unfused = sorted(sensor for sensor, c in self.status.items() if not int(c.get("integrated", 0)))
        except Exception:
            if not rclpy.ok():  # the context went away under a spin or a call: Ctrl-C or SIGTERM
                raise KeyboardInterrupt from None
            raise
        finally:
            node.destroy_node()
            shut_down_rclpy()
        return self.out / "mesh.ply"


    def _save_live_mesh(self, node, tick_clock) -> None:  # noqa: ANN001 - rclpy Node, callable
        """Wait until the weighting net has judged every block and the mesh updates meshed them all,
        then join ~/mesh as a late subscriber (the node sends its whole mesh) and write what arrives
        as live_mesh.ply."""
        import numpy as np
        import rclpy
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from visualization_msgs.msg import MarkerArray

        from senfunet_core.mesher import Mesh
        from senfunet_core.ply import write_ply
        from senfunet_ros.conversions import MARKER_DELETE, MARKER_DELETEALL, marker_array_from_cdr

        _say("waiting for the weighting net to judge every block...")
        caught_up = 0
        while caught_up < 3:  # three status reports in a row with no backlog: updates ran after the last batch
            before = self.status_count
            while self.status_count == before:
                tick_clock()
                rclpy.spin_once(node, timeout_sec=0.05)
                self._check("while the weighting net catches up")
            # every block judged, and meshed: a meshing budget leaves blocks for the next updates
            backlogs = [self.pipeline_values.get(key, "1") for key in ("alpha_backlog_blocks", "mesh_backlog_blocks")]
            caught_up = caught_up + 1 if backlogs == ["0", "0"] else 0
        markers: dict[tuple[str, int], np.ndarray] = {}
        last_message = [time.monotonic()]

        def on_mesh(data: bytes) -> None:  # raw: rclpy's deserialisation takes seconds for a room's mesh
            last_message[0] = time.monotonic()
            try:
                decoded = marker_array_from_cdr(data)
            except ValueError as err:  # another writer's broken message: the rest of the mesh still counts
                _say(f"skipped a ~/mesh message that does not decode ({err})")
                return
            for m in decoded:
                if m.action == MARKER_DELETEALL:
                    markers.clear()
                elif m.action == MARKER_DELETE:
                    markers.pop((m.ns, m.id), None)
                else:
                    markers[(m.ns, m.id)] = m.points_m.astype(np.float32)

        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        subscription = node.create_subscription(MarkerArray, f"/{NODE}/mesh", on_mesh, qos, raw=True)
        while not markers or time.monotonic() - last_message[0] < 3.0:  # the snapshot comes in parts
            tick_clock()
            rclpy.spin_once(node, timeout_sec=0.05)
            self._check("while receiving ~/mesh")
        node.destroy_subscription(subscription)
        points = np.concatenate(list(markers.values()))
        faces = np.arange(len(points), dtype=np.int32).reshape(-1, 3)
        write_ply(self.out / "live_mesh.ply", Mesh(points, faces))
        _say(f"~/mesh as a subscriber sees it: {self.out / 'live_mesh.ply'} ({len(faces)} triangles)")


def _cutaway(mesh):  # noqa: ANN001, ANN202 - Mesh in, Mesh out
    """Drop the top fifth of a room (the ceiling) so the picture looks inside. World z is up."""
    import numpy as np

    from senfunet_core.mesher import Mesh

    if mesh.n_faces == 0:
        return mesh
    z = mesh.vertices[:, 2]
    lo, hi = np.percentile(z, [1, 99])
    keep = (z[mesh.faces] <= lo + 0.8 * (hi - lo)).all(axis=1)
    return Mesh(mesh.vertices, mesh.faces[keep], mesh.colors)


def _sensor_names(params: str | None) -> tuple[str, ...]:
    """The node's sensors, in order, as the parameter file (or the defaults) names them."""
    from senfunet_ros.params_file import load_settings

    return tuple(load_settings(params).sensor_names)


def _render(out: Path, png: Path, *, sensors: tuple[str, ...]) -> None:
    """out's fused mesh beside its TSDF Fusion mesh; the fused mesh's colours are the sensor weighting
    (`mesher.alpha_colors`), which its title spells out."""
    from senfunet_core.ply import read_ply
    from senfunet_core.render import render_mesh_png

    fused = f"SenFuNet, live node: amber = {sensors[0]} trusted, blue = {sensors[1]} trusted"
    meshes, titles = [], []
    for stem, title in (("mesh", fused), ("tsdf_fusion", "TSDF Fusion of both sensors")):
        path = out / f"{stem}.ply"
        if path.exists():
            meshes.append(_cutaway(read_ply(path)))
            titles.append(title)
    render_mesh_png(meshes, png, titles=titles, width_px=1600, height_px=700)
