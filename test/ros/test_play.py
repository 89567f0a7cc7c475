"""`senfunet play` over real DDS, and play + the live node in separate processes against replay."""
from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from senfunet_ros.bagio import copy_bag, open_bag

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "bags" / "sim_room"


@pytest.fixture(scope="module")
def prefix(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The sample's first second."""
    with open_bag(SAMPLE) as reader:
        stop = reader.start_ns + 1_000_000_000
    return copy_bag(SAMPLE, tmp_path_factory.mktemp("play") / "prefix", stop_ns=stop)


class _Listener:
    """A private rclpy context with reliable subscriptions to the bag's topics and /clock."""

    def __init__(self, topics: dict[str, str], latched: frozenset[str] = frozenset()) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock

        from senfunet_ros.bagio import message_class

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("play_listener", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.counts = {t: 0 for t in topics}
        self.clock_ns: list[int] = []
        qos = QoSProfile(depth=500, reliability=ReliabilityPolicy.RELIABLE)
        latched_qos = QoSProfile(depth=500, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)  # as tf2 subscribes /tf_static
        for topic, msgtype in topics.items():
            self.node.create_subscription(message_class(msgtype), topic, self._counter(topic),
                                          latched_qos if topic in latched else qos)
        self.node.create_subscription(Clock, "/clock", self._on_clock, QoSProfile(depth=500))

    def _counter(self, topic: str):  # noqa: ANN202
        def callback(_msg) -> None:  # noqa: ANN001
            self.counts[topic] += 1
        return callback

    def _on_clock(self, msg) -> None:  # noqa: ANN001
        self.clock_ns.append(msg.clock.sec * 1_000_000_000 + msg.clock.nanosec)

    def spin_while(self, condition, timeout: float) -> None:  # noqa: ANN001
        deadline = time.monotonic() + timeout
        while condition() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def _play(bag: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "senfunet_ros.cli", "play", str(bag), "--wait-subscribers", "15",
                             *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _play_to(listener: _Listener, bag: Path, counts: dict[str, int], *extra: str) -> tuple[int, str]:
    """Play the bag to the listener until play ends and the listener has `counts` (or 5 s more);
    closes the listener. Returns play's exit code and stderr."""
    try:
        proc = _play(bag, *extra)
        listener.spin_while(lambda: proc.poll() is None, timeout=60)
        listener.spin_while(lambda: listener.counts != counts, timeout=5)
        _, stderr = proc.communicate(timeout=10)
    finally:
        listener.close()
    return proc.returncode, stderr



def test_play_skips_a_clock_errors_gap_and_a_topic_ros_cannot_name(prefix: Path, tmp_path: Path, ros_domain_id: int):
    """Three messages logged at time 0 (a recorder whose clock was not yet set): play waited the decades
    to the next log time; a topic named '/stereo/color-raw' (no valid ROS 2 name): play died with a
    traceback. Now the gap is played without waiting and said, the topic left out and said."""
    import odd_bags

    bag = odd_bags.clock_error_and_bad_name(prefix, tmp_path / "bag")
    with open_bag(prefix) as reader:
        topics = {t: i.msgtype for t, i in reader.topics.items() if t != "/stereo/color"}
        counts = {t: i.count for t, i in reader.topics.items() if t != "/stereo/color"}
    assert len(topics) >= 4
    listener = _Listener(topics)
    started = time.monotonic()
    returncode, stderr = _play_to(listener, bag, counts, "--rate", "4")
    assert returncode == 0, stderr
    assert time.monotonic() - started < 45 and listener.counts == counts
    assert "/stereo/color-raw is no valid ROS 2 topic name" in stderr and "Traceback" not in stderr
    assert "the log times jump from 0.000 s" in stderr

@pytest.mark.parametrize("clock_topic", ["/clock", "clock"])
def test_a_bags_recorded_clock_is_the_only_clock_play_publishes(prefix: Path, tmp_path: Path, ros_domain_id: int,
                                                                 clock_topic: str):
    """A simulation's recording holds /clock (or `clock`, the same topic): play published it and a /clock
    of its own from the log times, and every use_sim_time subscriber saw time jump to and fro (400 times
    a pass). A recorded clock that stops early while the other topics go on (here `clock`'s, after 0.2 s
    of 1 s) is said; one that pauses with every topic (here `/clock`'s, 1 s halfway) is not."""
    import odd_bags

    stops = clock_topic == "clock"
    bag = odd_bags.with_recorded_clock(prefix, tmp_path / "bag", sim_start_ns=100_000_000_000, topic=clock_topic,
                                       clock_for_ns=200_000_000 if stops else None,
                                       pause_ns=0 if stops else 1_000_000_000)
    with open_bag(bag) as reader:
        topics = {t: i.msgtype for t, i in reader.topics.items() if t != clock_topic}
        counts = {t: i.count for t, i in reader.topics.items() if t != clock_topic}
        recorded = reader.topics[clock_topic].count
    listener = _Listener(topics)
    returncode, stderr = _play_to(listener, bag, counts, "--rate", "2")
    assert returncode == 0, stderr
    clock = listener.clock_ns
    assert len(clock) == recorded and clock == sorted(clock), (len(clock), recorded)
    assert 100_000_000_000 <= clock[0] and clock[-1] < (100_200_000_000 if stops else 102_000_000_000)
    assert "the bag has /clock" in stderr
    assert ("the recorded clock stopped at log time" in stderr) == stops, stderr


def test_play_publishes_every_message_with_clock(prefix: Path, ros_domain_id: int):
    with open_bag(prefix) as reader:
        topics = {t: i.msgtype for t, i in reader.topics.items()}
        counts = {t: i.count for t, i in reader.topics.items()}
        start_ns, end_ns, duration = reader.start_ns, reader.end_ns, reader.duration_s
    listener = _Listener(topics)
    returncode, stderr = _play_to(listener, prefix, counts, "--rate", "2")
    assert returncode == 0, stderr
    assert listener.counts == counts
    clock = listener.clock_ns
    assert clock == sorted(clock) and start_ns <= clock[0] and clock[-1] <= end_ns
    assert clock[-1] - clock[0] > 0.9 * duration * 1e9  # recorded time, not wall time
    assert f"published {sum(counts.values())} messages" in stderr


def test_play_offers_transient_local_where_the_recording_was_latched(prefix: Path, tmp_path: Path,
                                                                    ros_domain_id: int):
    """A topic recorded from a latched publisher (transient-local, as /tf_static is) reaches a
    transient-local subscriber, which a volatile writer would not match."""
    from rosbags.rosbag2 import Writer

    from senfunet_ros.bagio import latched_qos

    latched = tmp_path / "latched"
    with open_bag(prefix) as reader, Writer(latched, version=9) as writer:
        infos, conns = reader.topics, {}
        for msg in reader.messages({"/tof/camera_info"}):
            if msg.topic not in conns:
                info = infos[msg.topic]
                conns[msg.topic] = writer.add_connection(msg.topic, msg.msgtype, msgdef=info.msgdef, rihs01=info.digest,
                                                         offered_qos_profiles=latched_qos())
            writer.write(conns[msg.topic], msg.log_time_ns, msg.data)
    with open_bag(latched) as reader:
        assert reader.topics["/tof/camera_info"].latched
        counts = {t: i.count for t, i in reader.topics.items()}
    listener = _Listener({"/tof/camera_info": "sensor_msgs/msg/CameraInfo"}, latched=frozenset({"/tof/camera_info"}))
    returncode, stderr = _play_to(listener, latched, counts, "--rate", "4")
    assert returncode == 0 and listener.counts == counts and counts["/tof/camera_info"] > 0, stderr


def test_play_loop_restarts_the_clock(prefix: Path, ros_domain_id: int):
    with open_bag(prefix) as reader:
        topics = {"/tof/pose": reader.topics["/tof/pose"].msgtype}
    listener = _Listener(topics)
    try:
        proc = _play(prefix, "--rate", "4", "--loop", "--topics", "/tof/pose")

        def restarted() -> bool:
            c = listener.clock_ns
            return any(b < a for a, b in zip(c, c[1:]))

        listener.spin_while(lambda: not restarted() and proc.poll() is None, timeout=60)
        assert restarted() and proc.poll() is None
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=20)
    finally:
        listener.close()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode in (0, 130)


@pytest.fixture(scope="module")
def large_room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 s of a simulated 8.4 x 7.2 m room (both sensors at 5 Hz, 128 x 128)."""
    from senfunet_core.learning import simulator as sim
    from senfunet_ros.bagio import write_sequence_bag

    scene = sim.make_scene(77, room_size_m=(8.4, 7.2, 2.6))
    sequence = sim.simulate_sequence(scene, 77, duration_s=4.0, tof_rate_hz=5.0, stereo_rate_hz=5.0, width=128,
                                     height=128)
    return write_sequence_bag(sequence, tmp_path_factory.mktemp("large") / "room")


def assert_live_mesh_is_replays(bag: Path, params_yaml: str, tmp_path: Path, domain_id: int, *,
                                bound: int = 0) -> None:
    """Once the stream has ended, the node fused every frame and its weighting net caught up, the
    mesh a subscriber to ~/mesh receives is replay's mesh.ply of the same bag without a map bound
    (F >= 99 at 2 cm), and so is ~/save_mesh's; with `bound` the node runs with that map bound."""
    from senfunet_core.metrics import mesh_metrics
    from senfunet_core.ply import read_ply
    from senfunet_ros.replay import replay_bag

    params, unbounded = tmp_path / "params.yaml", tmp_path / "unbounded.yaml"
    params.write_text(params_yaml + (f"    max_map_blocks: {bound}\n" if bound else ""))
    unbounded.write_text(params_yaml + "    max_map_blocks: 0\n")
    out = tmp_path / "demo"
    proc = subprocess.run([sys.executable, "-m", "senfunet_ros.cli", "demo", "--bag", str(bag), "--out", str(out),
                           "--params", str(params), "--rate", "0.5", "--domain-id", str(domain_id),
                           "--timeout", "500", "--live-mesh", "--no-render"], capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr + (out / "node.log").read_text(errors="replace")
    replayed = replay_bag(bag, tmp_path / "replay", params=unbounded, progress=False)
    assert replayed.ok, replayed.error
    assert replayed.stats["engine"]["evicted_blocks"] == 0
    offline = replayed.meshes["mesh"].vertices
    live, saved = read_ply(out / "live_mesh.ply"), read_ply(out / "mesh.ply")
    assert live.n_faces > 10000
    if bound:
        assert "map bound: evicted" in (out / "node.log").read_text(errors="replace")
    for name, mesh in (("~/mesh", live), ("~/save_mesh", saved)):
        agreement = mesh_metrics(mesh.vertices, offline, tau_m=0.02)
        assert agreement["F"] >= 99.0, (name, agreement, proc.stdout)


@pytest.mark.slow
def test_mesh_on_the_topic_equals_replay(prefix: Path, tmp_path: Path, ros_domain_id: int):
    """The sample's first second, default settings but a full-resolution ~/mesh."""
    assert_live_mesh_is_replays(prefix, "senfunet:\n  ros__parameters:\n    mesh_display_cell_m: 0.0\n", tmp_path,
                                ros_domain_id)


@pytest.mark.slow
def test_mesh_on_the_topic_equals_replay_on_a_large_room(large_room: Path, tmp_path: Path, ros_domain_id: int):
    """An 8.4 x 7.2 m room at its native 128 x 128 and 2-cm voxels (to fit the suite's time), with a
    full-resolution ~/mesh, and a map bound of 2500 blocks, under half of what the room needs, against
    an unbounded replay: evicted blocks keep their meshes, seams included, and come back from disk
    when seen again, so the live mesh is still replay's."""
    assert_live_mesh_is_replays(large_room, "senfunet:\n  ros__parameters:\n    mesh_display_cell_m: 0.0\n"
                                "    voxel_size_m: 0.02\n    working_width: 0\n", tmp_path, ros_domain_id,
                                bound=2500)


def test_demo_fuses_every_frame_of_the_sample_bag(tmp_path: Path, ros_domain_id: int):
    """The README's command, `senfunet demo` (the node and play as two processes over DDS), with the
    node's default parameters: every depth image of the sample bag crosses DDS and is fused, and the
    saved mesh is written and rendered. (With Python's default 5 ms GIL switch interval the busy node
    took its messages so late that 20-40 % of the frames were lost.) That the mesh is replay's:
    test_mesh_on_the_topic_equals_replay."""
    from collections import Counter

    out = tmp_path / "demo"
    proc = subprocess.run([sys.executable, "-m", "senfunet_ros.cli", "demo", "--out", str(out),
                           "--domain-id", str(ros_domain_id), "--timeout", "400"],
                          capture_output=True, text=True, timeout=500)
    assert proc.returncode == 0, proc.stdout + proc.stderr + (out / "node.log").read_text(errors="replace")
    assert f"fused mesh: {out / 'mesh.ply'}" in proc.stdout
    assert f"rendering:  {out / 'mesh.png'}" in proc.stdout
    assert (out / "mesh.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    fused = dict(re.findall(r"^senfunet demo: (\w+): (\d+) of \d+ frames fused\b", proc.stdout, re.MULTILINE))
    with open_bag(SAMPLE) as bag:
        in_bag = Counter(m.topic.split("/")[1] for m in bag.messages([t for t in bag.topics if t.endswith("/depth")]))
    assert {s: int(n) for s, n in fused.items()} == dict(in_bag), proc.stdout


def test_demo_saves_what_the_node_fused_when_play_breaks_on_a_damaged_bag(tmp_path: Path, ros_domain_id: int):
    """A bag cut short (a killed recording): play publishes what it can read and exits 2 where it breaks. The
    demo then stopped at `play failed`, leaving node.log and play.log: what the node fused was thrown away.
    Now the node still fuses its queue and saves the mesh, and the demo names it beside play's error (exit 1)."""
    from odd_bags import cut_short
    from sensor_bags import params_file, two, write_bag

    recording = two(duration_s=1.0)
    bag = cut_short(write_bag(recording, tmp_path / "plain"), tmp_path / "cut")
    params = params_file(tmp_path / "params.yaml", recording, weights="none", voxel_size_m=0.04, working_width=48)
    out = tmp_path / "demo"
    proc = subprocess.run([sys.executable, "-m", "senfunet_ros.cli", "demo", "--bag", str(bag), "--out", str(out),
                           "--params", str(params), "--domain-id", str(ros_domain_id), "--no-render", "--rate", "1",
                           "--timeout", "200"], capture_output=True, text=True, timeout=300)
    said = proc.stdout + proc.stderr
    assert proc.returncode == 1, said + (out / "node.log").read_text(errors="replace")
    assert "play failed (code 2)" in said and "the file breaks after" in said, said
    assert f"{out / 'mesh.ply'} holds what the node fused of the bag up to where play stopped" in said, said
    fused = dict(re.findall(r"^senfunet demo: (\w+): (\d+) of \d+ frames fused\b", proc.stdout, re.MULTILINE))
    assert set(fused) == {"tof", "stereo"} and min(map(int, fused.values())) > 0, said
    assert (out / "mesh.ply").stat().st_size > 0


def test_a_demo_that_can_fuse_nothing_fails_saying_why(tmp_path: Path, ros_domain_id: int):
    """A bag whose topics are not the node's: the demo said "0 of 0 frames fused", wrote empty meshes and
    exited 0, the cause only in node.log. It now refuses such a bag at once, as replay does (exit 2, the
    bag's topics and the parameters to set). A bag whose every frame the node drops (negative depths)
    now exits 2 after the run, naming the node's warnings."""
    from sensor_bags import Camera, params_file, two, write_bag

    def demo(recording, name: str, **params) -> tuple[int, str]:  # noqa: ANN001
        bag = write_bag(recording, tmp_path / name)
        values = {"weights": "none", "voxel_size_m": 0.04, "working_width": 48, **params}
        out = tmp_path / f"{name}_demo"
        proc = subprocess.run([sys.executable, "-m", "senfunet_ros.cli", "demo", "--bag", str(bag), "--out", str(out),
                               "--params", str(params_file(tmp_path / f"{name}.yaml", recording, **values)),
                               "--domain-id", str(ros_domain_id), "--no-render", "--rate", "2", "--timeout", "200"],
                              capture_output=True, text=True, timeout=300)
        return proc.returncode, proc.stdout + proc.stderr

    code, said = demo(two(duration_s=0.5), "elsewhere", **{"tof.depth_topic": "/elsewhere/depth"})
    assert code == 2 and "no messages on /elsewhere/depth" in said and "tof.depth_topic" in said, said
    assert "starting the node" not in said, said
    negative = two(Camera("tof", depth_offset_m=-5.0), Camera("stereo", x_m=0.05, depth_offset_m=-5.0),
                   duration_s=0.5)
    code, said = demo(negative, "negative")
    assert code == 2 and "the node fused no frame of" in said and "is empty" in said, said
    assert "all_invalid" in said, said  # the node's warning, quoted


def test_large_shm_profile_unless_fast_dds_is_configured(tmp_path: Path, monkeypatch):
    """Play, the node and the tests give their participants the packaged large shared-memory
    profile, and leave a user's own Fast DDS setup (or another RMW) alone."""
    import xml.etree.ElementTree as ET

    from senfunet_ros.dds import PROFILE, use_large_shm_profile

    segment = ET.parse(PROFILE).getroot().find(".//{*}segment_size")
    assert segment is not None and int(segment.text) >= 16 << 20
    monkeypatch.chdir(tmp_path)
    env: dict[str, str] = {}
    assert use_large_shm_profile(env) == PROFILE and env == {"FASTRTPS_DEFAULT_PROFILES_FILE": str(PROFILE)}
    for preset in ({"FASTRTPS_DEFAULT_PROFILES_FILE": "mine.xml"}, {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"},
                   {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}):
        env = dict(preset)
        assert use_large_shm_profile(env) is None and env == preset
    (tmp_path / "DEFAULT_FASTRTPS_PROFILES.xml").write_text("<profiles/>")
    assert use_large_shm_profile({}) is None


@pytest.mark.parametrize("odd", ["split_overlapping", "db3_with_disagreeing_metadata"])
def test_play_publishes_the_bags_of_other_writers_whole_and_in_time_order(prefix: Path, tmp_path: Path,
                                                                          ros_domain_id: int, odd: str):
    """A split recording whose files overlap in time: /clock never goes back (a node would see a
    restart at each file). A db3 whose metadata.yaml disagrees with its topic table: every topic
    is published, the latched one as latched."""
    import odd_bags

    bag = getattr(odd_bags, odd)(prefix, tmp_path / "bag")
    with open_bag(prefix) as reader:
        topics = {t: i.msgtype for t, i in reader.topics.items()}
        counts = {t: i.count for t, i in reader.topics.items()}
    latched = frozenset({"/tof/camera_info"}) if odd == "db3_with_disagreeing_metadata" else frozenset()
    listener = _Listener(topics, latched=latched)
    returncode, stderr = _play_to(listener, bag, counts, "--rate", "4")
    assert returncode == 0, stderr
    assert listener.counts == counts
    assert listener.clock_ns == sorted(listener.clock_ns) and listener.clock_ns
