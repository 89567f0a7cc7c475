#!/usr/bin/env python3
"""Probe: do large best-effort images survive the trip between two processes on this machine?

A publisher process (reliable KEEP_LAST 50 by default, like the tests' streamer and `senfunet
play`) sends sensor_msgs/Image messages on one topic per --sizes entry ("SIZE[@RATE][/DEPTH]";
"rig" = the streamed node test's traffic: ToF 128x128 32FC1 depth + camera_info + 100 Hz pose,
stereo 16UC1 depth + rgb8 colour + camera_info + 100 Hz pose) to a subscriber process that spins
a MultiThreadedExecutor like the fusion node (best effort, KEEP_LAST, one mutually exclusive
callback group per subscription). Loads: --busy (threads in the subscriber's process holding the
GIL and the CPU), --hogs (CPU-bound processes), --stall MS,PERIOD (SIGSTOP/SIGCONT the whole
subscriber process: what a starved process looks like to its DDS threads).

Transport levers: --transport NAME (a Fast DDS XML profile, passed with
FASTRTPS_DEFAULT_PROFILES_FILE; --profile-side chooses which process gets it), --profile FILE,
--builtin-transports (FASTDDS_BUILTIN_TRANSPORTS); QoS levers: --pub-reliability, --pub-depth,
--sub-depth, per-topic /DEPTH. --handshake: stream only after the subscriber heard every topic.

  .venv/bin/python scripts/dds_probe.py --n 30 --sizes rig --stall 1000,2000               # 512 KB SHM
  .venv/bin/python scripts/dds_probe.py --n 30 --sizes rig --stall 1000,2000 --transport shm-big
  .venv/bin/python scripts/dds_probe.py --n 30 --sizes rig --busy mixed --hogs 2 --repeat 3

Each run prints per topic: received/sent, the lost sequence numbers, the median and worst delay
from publish to callback ("history overwrite possible" when the worst delay exceeds the reader's
depth in time: executor lag, not transport), and how long after the publisher's writers matched
the subscriber's readers matched them (> 0: messages sent in between are dropped by a
best-effort reader). Private ROS_DOMAIN_ID (--domain), ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

# ------------------------------------------------------------------------------------------------
# Fast DDS profiles (participant level; rmw_fastrtps loads the default participant profile)

_HEAD = '<?xml version="1.0" encoding="UTF-8"?>\n<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">\n'


def _profile(descriptors: str, ids: list[str]) -> str:
    transports = "".join(f"<transport_id>{i}</transport_id>" for i in ids)
    return (_HEAD + f"<transport_descriptors>{descriptors}</transport_descriptors>\n"
            '<participant profile_name="probe" is_default_profile="true"><rtps>'
            f"<userTransports>{transports}</userTransports>"
            "<useBuiltinTransports>false</useBuiltinTransports></rtps></participant>\n</profiles>\n")


def _shm(seg_bytes: int, queue: int = 512) -> str:
    return (f"<transport_descriptor><transport_id>shm</transport_id><type>SHM</type>"
            f"<segment_size>{seg_bytes}</segment_size><port_queue_capacity>{queue}</port_queue_capacity>"
            "</transport_descriptor>")


def _udp(buf_bytes: int | None = None) -> str:
    bufs = (f"<sendBufferSize>{buf_bytes}</sendBufferSize><receiveBufferSize>{buf_bytes}</receiveBufferSize>"
            if buf_bytes else "")
    return f"<transport_descriptor><transport_id>udp</transport_id><type>UDPv4</type>{bufs}</transport_descriptor>"


TRANSPORTS: dict[str, str | None] = {
    "default": None,  # builtin SHM (512 KB segment) + UDPv4
    "shm-512k": _profile(_shm(512 * 1024) + _udp(), ["shm", "udp"]),  # explicit default, as a control
    "shm-2m": _profile(_shm(2 * 1024 * 1024) + _udp(), ["shm", "udp"]),
    "shm-4m": _profile(_shm(4 * 1024 * 1024) + _udp(), ["shm", "udp"]),
    "shm-big": _profile(_shm(16 * 1024 * 1024) + _udp(), ["shm", "udp"]),
    "shm-big-q2048": _profile(_shm(16 * 1024 * 1024, 2048) + _udp(), ["shm", "udp"]),
    "shm-big-udp-big": _profile(_shm(16 * 1024 * 1024) + _udp(4 * 1024 * 1024), ["shm", "udp"]),
    "shm-only-big": _profile(_shm(16 * 1024 * 1024), ["shm"]),
    "udp-only": _profile(_udp(), ["udp"]),
    "udp-only-big": _profile(_udp(4 * 1024 * 1024), ["udp"]),
}

# the streamed test's traffic per sensor pair: ToF depth 128x128 32FC1 + camera_info + pose at 100 Hz,
# stereo depth 16UC1 + rgb8 colour + camera_info + pose at 100 Hz (images at --rate); the node's
# reader depths (30 for images and camera_info, 200 for poses)
RIG = "65536,400,100@100/200,32768,49152,400,100@100/200"


def _count(args: argparse.Namespace, rate: float) -> int:
    return int(round(args.n / args.rate * rate))


def _fastdds_warnings() -> None:
    """Fast DDS logs only errors by default; warnings show SHM overflows and the like."""
    import ctypes

    lib = ctypes.CDLL(str(Path(sys.prefix) / "lib" / "libfastrtps.so.2.14"))  # the venv's, as rclpy loads it
    lib._ZN8eprosima7fastdds3dds3Log12SetVerbosityENS2_4KindE(1)  # Log::Kind::Warning


# ------------------------------------------------------------------------------------------------
# subscriber process


def _busy(kind: str, stop: threading.Event) -> None:
    """Keep this process's CPU and GIL busy the way the node's work does."""
    import numpy as np

    if kind == "python":  # pure Python: holds the GIL, handing it over every switch interval
        while not stop.is_set():
            sum(i * i for i in range(50_000))
    elif kind == "numpy":  # many small array ops: GIL held between (short) C calls
        a = np.random.default_rng(0).random((64, 64, 64)).astype(np.float32)
        while not stop.is_set():
            for _ in range(20):
                b = np.sqrt(a * 1.5 + 0.1)
                a = (b / (1.0 + b)).astype(np.float32)
            np.argsort(a.reshape(-1)[:50_000])
    elif kind == "torch":  # conv nets: the GIL is released inside the ops
        import torch

        torch.set_num_threads(1)
        net = torch.nn.Sequential(*[torch.nn.Conv3d(8, 8, 3, padding=1) for _ in range(3)])
        x = torch.randn(1, 8, 24, 24, 24)
        with torch.no_grad():
            while not stop.is_set():
                net(x)
    elif kind == "mixed":  # the node: torch net + numpy + Python bookkeeping
        threads = [threading.Thread(target=_busy, args=(k, stop), daemon=True) for k in ("torch", "numpy")]
        for t in threads:
            t.start()
        _busy("python", stop)


def run_subscriber(args: argparse.Namespace) -> None:
    import rclpy
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    rclpy.init()
    node = rclpy.create_node("probe_sub")
    reliability = (ReliabilityPolicy.BEST_EFFORT if args.sub_reliability == "best_effort"
                   else ReliabilityPolicy.RELIABLE)
    lock = threading.Lock()
    got: dict[int, dict[int, float]] = {i: {} for i in range(len(args.topics))}  # topic -> seq -> delay
    warm = [False] * len(args.topics)

    def callback(i: int):  # noqa: ANN202
        def on_msg(msg: Image) -> None:
            now = time.time()
            seq = int(msg.header.frame_id)
            if seq < 0:
                warm[i] = True
                return
            sent = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            with lock:
                got[i][seq] = now - sent
            if args.cb_work_ms:  # decode like the node: bytes -> numpy (and some Python)
                import numpy as np

                t_end = time.perf_counter() + args.cb_work_ms / 1000
                np.frombuffer(bytes(msg.data), np.uint8).astype(np.float32).sum()
                while time.perf_counter() < t_end:
                    pass
        return on_msg

    subs = [node.create_subscription(Image, f"/probe/t{i}", callback(i),
                                     QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=args.depths[i],
                                                durability=DurabilityPolicy.VOLATILE, reliability=reliability),
                                     callback_group=MutuallyExclusiveCallbackGroup())
            for i in range(len(args.topics))]
    executor = MultiThreadedExecutor(num_threads=args.executor_threads)
    executor.add_node(node)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    stop = threading.Event()
    busy = [threading.Thread(target=_busy, args=(args.busy, stop), daemon=True)
            for _ in range(args.busy_threads if args.busy != "none" else 0)]
    matched_at: dict[int, float] = {}  # topic -> wall time this reader first counted a matched writer

    def watch_matches() -> None:
        while len(matched_at) < len(subs) and not stop.is_set():
            for i, sub in enumerate(subs):
                if i not in matched_at and sub.get_publisher_count() > 0:
                    matched_at[i] = time.time()
            time.sleep(0.002)
    threading.Thread(target=watch_matches, daemon=True).start()
    if args.load_during_discovery:
        for t in busy:
            t.start()
    print("READY", flush=True)
    # protocol on stdin/stdout with the orchestrator: WARM? -> WARM, DONE -> results
    for line in sys.stdin:
        cmd = line.strip()
        if cmd == "WARM?":
            deadline = time.monotonic() + 30
            while not all(warm) and time.monotonic() < deadline:
                time.sleep(0.02)
            print("WARM" if all(warm) else "COLD", flush=True)
        elif cmd == "BUSY" and not args.load_during_discovery:  # load once discovery is done
            for t in busy:
                t.start()
        elif cmd == "DONE":
            time.sleep(args.drain_s)  # stragglers still in reader histories
            break
    stop.set()
    with lock:
        result = {str(i): {"sent": _count(args, args.topics[i][1]), "received": len(g),
                           "lost": sorted(set(range(_count(args, args.topics[i][1]))) - set(g)),
                           "max_delay_s": round(max(g.values()), 3) if g else None,
                           "median_delay_s": round(sorted(g.values())[len(g) // 2], 3) if g else None,
                           "sub_matched_at": matched_at.get(i)}
                  for i, g in got.items()}
    print("RESULT " + json.dumps(result), flush=True)
    subs.clear()  # the subscriptions go before the node (and watch_matches stops)
    executor.shutdown(timeout_sec=2)
    node.destroy_node()
    rclpy.try_shutdown()


# ------------------------------------------------------------------------------------------------
# publisher process


def run_publisher(args: argparse.Namespace) -> None:
    import rclpy
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    rclpy.init()
    node = rclpy.create_node("probe_pub")
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=args.pub_depth, durability=DurabilityPolicy.VOLATILE,
                     reliability=ReliabilityPolicy.RELIABLE if args.pub_reliability == "reliable"
                     else ReliabilityPolicy.BEST_EFFORT)
    pubs = [node.create_publisher(Image, f"/probe/t{i}", qos) for i in range(len(args.topics))]
    images = [Image(height=1, width=size // 4, encoding="32FC1", step=size, data=bytes(size))
              for size, _ in args.topics]

    def publish(i: int, seq: int) -> None:
        msg = images[i]
        msg.header.frame_id = str(seq)
        now = time.time()
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(now), int((now % 1) * 1e9)
        pubs[i].publish(msg)

    deadline = time.monotonic() + 30
    while any(p.get_subscription_count() == 0 for p in pubs) and time.monotonic() < deadline:
        time.sleep(0.05)
    print(f"MATCHED {time.time()}", flush=True)
    if args.handshake:  # warm-up messages (seq -1) until the subscriber has heard every topic
        go = threading.Event()
        threading.Thread(target=lambda: (sys.stdin.readline(), go.set()), daemon=True).start()
        while not go.is_set():
            for i in range(len(pubs)):
                publish(i, -1)
            go.wait(0.1)
    else:
        sys.stdin.readline()
    events = sorted((seq / rate, i, seq) for i, (_, rate) in enumerate(args.topics)
                    for seq in range(_count(args, rate)))
    t0 = time.monotonic()
    for t, i, seq in events:
        delay = t0 + t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        publish(i, seq)
    if args.pub_reliability == "reliable":
        from rclpy.duration import Duration

        for p in pubs:
            p.wait_for_all_acked(Duration(seconds=2))
    print("SENT", flush=True)
    time.sleep(1.0)
    node.destroy_node()
    rclpy.try_shutdown()


# ------------------------------------------------------------------------------------------------
# orchestrator


def _hog(seconds: float) -> subprocess.Popen:
    code = f"import time\nend=time.monotonic()+{seconds}\nwhile time.monotonic()<end: pass\n"
    return subprocess.Popen([sys.executable, "-c", code])


def _expect(proc: subprocess.Popen, word: str, timeout: float = 60) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            raise RuntimeError(f"process exited before {word}")
        if line.startswith(word):
            return line
    raise RuntimeError(f"timed out waiting for {word}")


def run_once(args: argparse.Namespace, argv: list[str], env: dict[str, str]) -> dict:
    me = [sys.executable, os.path.abspath(__file__), *argv]
    hogs: list[subprocess.Popen] = []
    plain = {k: v for k, v in env.items() if k != "FASTRTPS_DEFAULT_PROFILES_FILE"}
    sub_env = env if args.profile_side in ("both", "sub") else plain
    pub_env = env if args.profile_side in ("both", "pub") else plain
    sub = subprocess.Popen([*me, "--role", "sub"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                           env=sub_env)
    pub = None
    try:
        _expect(sub, "READY")
        if args.load_during_discovery:
            hogs = [_hog(args.n / args.rate + 45) for _ in range(args.hogs)]
        pub = subprocess.Popen([*me, "--role", "pub"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                               env=pub_env)
        pub_matched_at = float(_expect(pub, "MATCHED").split()[1])
        sub.stdin.write("BUSY\n")
        sub.stdin.flush()
        if not args.load_during_discovery:
            hogs = [_hog(args.n / args.rate + 15) for _ in range(args.hogs)]
        if args.handshake:
            sub.stdin.write("WARM?\n")
            sub.stdin.flush()
            if not _expect(sub, "WARM").startswith("WARM"):
                raise RuntimeError("handshake failed")
        pub.stdin.write("GO\n")
        pub.stdin.flush()
        stop_stalls = threading.Event()
        if args.stall:
            stall_ms, period_ms = (float(v) for v in args.stall.split(","))

            def stall() -> None:
                while not stop_stalls.wait(max(0.0, period_ms - stall_ms) / 1000):
                    os.kill(sub.pid, signal.SIGSTOP)
                    time.sleep(stall_ms / 1000)
                    os.kill(sub.pid, signal.SIGCONT)
            threading.Thread(target=stall, daemon=True).start()
        try:
            _expect(pub, "SENT", timeout=args.n / args.rate + 60)
        finally:
            stop_stalls.set()
            time.sleep(stall_ms / 1000 if args.stall else 0)
            os.kill(sub.pid, signal.SIGCONT)
        sub.stdin.write("DONE\n")
        sub.stdin.flush()
        result = json.loads(_expect(sub, "RESULT")[len("RESULT "):])
        for res in result.values():  # > 0: the reader matched the writer after the writer matched the reader
            at = res.pop("sub_matched_at")
            res["sub_match_lag_s"] = None if at is None else round(at - pub_matched_at, 3)
        pub.wait(10)
        sub.wait(10)
        return result
    finally:
        for p in [*hogs, pub, sub]:
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--role", choices=("run", "pub", "sub"), default="run", help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, default=60, help="messages per topic at --rate: the run lasts n/rate s")
    ap.add_argument("--rate", type=float, default=6.0, help="messages per second per topic (default 6)")
    ap.add_argument("--sizes", default="65536,32768",
                    help="payload bytes per topic, comma separated, each optionally @RATE_HZ (default "
                    "65536,32768: ToF 128x128 32FC1 and stereo 128x128 16UC1, at --rate); 'rig' = the "
                    "streamed test's mix: " + RIG)
    ap.add_argument("--stall", metavar="MS,PERIOD_MS",
                    help="SIGSTOP the subscriber process for MS every PERIOD_MS (a starved process)")
    ap.add_argument("--fastdds-log", action="store_true", help="Fast DDS log verbosity Warning (to stderr)")
    ap.add_argument("--pub-reliability", choices=("reliable", "best_effort"), default="reliable")
    ap.add_argument("--pub-depth", type=int, default=50)
    ap.add_argument("--sub-reliability", choices=("reliable", "best_effort"), default="best_effort")
    ap.add_argument("--sub-depth", type=int, default=30)
    ap.add_argument("--executor-threads", type=int, default=6)
    ap.add_argument("--busy", choices=("none", "python", "numpy", "torch", "mixed"), default="none",
                    help="load in the subscriber's process")
    ap.add_argument("--busy-threads", type=int, default=1)
    ap.add_argument("--cb-work-ms", type=float, default=0.0, help="work per callback in the subscriber")
    ap.add_argument("--hogs", type=int, default=0, help="extra CPU-bound processes during the run")
    ap.add_argument("--load-during-discovery", action="store_true",
                    help="start --busy and --hogs before the publisher exists (default: once it matched)")
    ap.add_argument("--handshake", action="store_true",
                    help="publish warm-up messages until the subscriber heard every topic, then stream")
    ap.add_argument("--transport", choices=sorted(TRANSPORTS), default="default")
    ap.add_argument("--profile", help="a Fast DDS XML profile file (overrides --transport)")
    ap.add_argument("--profile-side", choices=("both", "pub", "sub"), default="both",
                    help="which process gets the profile (the SHM segment belongs to the sender)")
    ap.add_argument("--builtin-transports", help="FASTDDS_BUILTIN_TRANSPORTS value (e.g. LARGE_DATA, UDPv4, SHM)")
    ap.add_argument("--drain-s", type=float, default=3.0)
    ap.add_argument("--domain", type=int, default=int(os.environ.get("ROS_DOMAIN_ID", "0")) or 150)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--json", action="store_true", help="one JSON line per run")
    args = ap.parse_args()
    if args.sizes == "rig":
        args.sizes = RIG
    args.topics, args.depths = [], []
    for spec in str(args.sizes).split(","):  # SIZE[@RATE][/DEPTH]
        spec, _, depth = spec.partition("/")
        size, _, rate = spec.partition("@")
        args.topics.append((int(size), float(rate) if rate else args.rate))
        args.depths.append(int(depth) if depth else args.sub_depth)
    if args.fastdds_log:
        _fastdds_warnings()
    if args.role == "sub":
        run_subscriber(args)
        return 0
    if args.role == "pub":
        run_publisher(args)
        return 0

    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    tmp = None
    if args.profile:
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(Path(args.profile).resolve())
    elif TRANSPORTS[args.transport]:
        tmp = tempfile.NamedTemporaryFile("w", suffix=".xml", delete=False)
        tmp.write(TRANSPORTS[args.transport])
        tmp.close()
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = tmp.name
    if args.builtin_transports:
        env["FASTDDS_BUILTIN_TRANSPORTS"] = args.builtin_transports
    argv = [*sys.argv[1:], "--domain", str(args.domain)]  # the children ignore --repeat and --json
    config = {k: v for k, v in vars(args).items() if k not in ("role", "repeat", "json", "domain", "drain_s")}
    failures = 0
    try:
        for r in range(args.repeat):
            t0 = time.monotonic()
            try:
                result = run_once(args, argv, env)
            except RuntimeError as err:
                failures += 1
                print(json.dumps({"run": r, "error": str(err), **config}) if args.json else f"run {r}: {err}")
                continue
            if args.json:
                print(json.dumps({"run": r, "result": result, **config}), flush=True)
                continue
            parts = []
            for i, res in result.items():
                size, rate = args.topics[int(i)]
                overwrite_possible = res["max_delay_s"] is not None and res["max_delay_s"] > args.depths[int(i)] / rate
                lost = res["lost"]
                parts.append(f"{size}B@{rate:g}: {res['received']}/{res['sent']}"
                             + (f" lost {lost[:12]}{'...' if len(lost) > 12 else ''}" if lost else "")
                             + f" delay med {res['median_delay_s']} max {res['max_delay_s']} s"
                             + f" reader match lag {res['sub_match_lag_s']} s"
                             + (" (history overwrite possible)" if overwrite_possible else ""))
            print(f"run {r} ({time.monotonic() - t0:.0f} s): " + "; ".join(parts), flush=True)
    finally:
        if tmp is not None:
            os.unlink(tmp.name)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
