"""Bag reading and writing (senfunet_ros.bagio), the sample bag, and each bad bag's one-line error."""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from replays import replay_commands, replay_in_process

from senfunet_ros.bagio import BagBrokenError, BagError, copy_bag, normalize_msgtype, open_bag, write_sequence_bag

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "bags" / "sim_room"
SAMPLE_GT = REPO / "bags" / "sim_room_gt.ply"
CONTRACT_TOPICS = {
    "/tof/depth": "sensor_msgs/msg/Image",
    "/tof/camera_info": "sensor_msgs/msg/CameraInfo",
    "/tof/pose": "geometry_msgs/msg/PoseStamped",
    "/stereo/depth": "sensor_msgs/msg/Image",
    "/stereo/color": "sensor_msgs/msg/Image",
    "/stereo/camera_info": "sensor_msgs/msg/CameraInfo",
    "/stereo/pose": "geometry_msgs/msg/PoseStamped",
}
# Small and fast: the bad-bag replays only need to get as far as the engine.
TINY_PARAMS = "senfunet:\n  ros__parameters:\n    working_width: 64\n    voxel_size_m: 0.04\n    weights: none\n"


def _digest(bag: Path) -> list[tuple[str, int, str]]:
    with open_bag(bag) as reader:
        return [(m.topic, m.log_time_ns, hashlib.sha1(m.data).hexdigest()) for m in reader.messages()]


@pytest.fixture(scope="module")
def prefix(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The sample's first 0.6 s as an mcap rosbag2 folder."""
    with open_bag(SAMPLE) as reader:
        stop = reader.start_ns + 600_000_000
    return copy_bag(SAMPLE, tmp_path_factory.mktemp("bags") / "prefix", stop_ns=stop)


@pytest.fixture(scope="module")
def tiny_params(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("params") / "tiny.yaml"
    path.write_text(TINY_PARAMS)
    return path


def _replay(bag: Path | str, out: Path, params: Path) -> subprocess.CompletedProcess:
    """The replay command in this process; test_missing_path runs it as a process."""
    return replay_in_process(bag, out, params, compare=True)


def _one_line_error(proc: subprocess.CompletedProcess) -> str:
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("senfunet replay: ")
    return lines[0]


# -- the sample -------------------------------------------------------------------------------


def test_sample_bag_layout_and_size():
    size = sum(f.stat().st_size for f in SAMPLE.rglob("*") if f.is_file())
    assert size + SAMPLE_GT.stat().st_size < 30e6
    with open_bag(SAMPLE) as reader:
        assert reader.storage == "mcap"
        assert {t: i.msgtype for t, i in reader.topics.items()} == CONTRACT_TOPICS
        counts = {t: i.count for t, i in reader.topics.items()}
        duration = reader.duration_s
    assert 12 <= counts["/tof/depth"] / duration <= 16  # asynchronous ~15 Hz ToF
    assert 15 <= counts["/stereo/depth"] / duration <= 21  # ~15-20 Hz stereo with colour
    assert counts["/stereo/color"] == counts["/stereo/depth"]
    assert counts["/tof/camera_info"] == counts["/tof/depth"]
    assert counts["/tof/pose"] / duration > 90  # pose stream at its own rate


def test_sample_message_contents(prefix: Path):
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import CameraInfo, Image

    from senfunet_ros import conversions as conv

    depth_stamps: dict[str, list[int]] = {"tof": [], "stereo": []}
    with open_bag(prefix) as reader:
        log_times = []
        for msg in reader.messages():
            log_times.append(msg.log_time_ns)
            sensor, stream = msg.topic.strip("/").split("/")
            if stream == "depth":
                image = deserialize_message(msg.data, Image)
                depth = conv.depth_from_image(image)
                assert image.encoding == ("16UC1" if sensor == "tof" else "32FC1")
                assert depth.shape == (256, 256) and 0.1 < np.median(depth[depth > 0]) < 6.0
                depth_stamps[sensor].append(conv.stamp_to_ns(image.header.stamp))
            elif stream == "color":
                assert deserialize_message(msg.data, Image).encoding == "rgb8"
            elif stream == "camera_info":
                info = deserialize_message(msg.data, CameraInfo)
                K, size = conv.intrinsics_from_camera_info(info)
                assert size == (256, 256) and K[0, 0] == pytest.approx(128.0)
            elif stream == "pose":
                from geometry_msgs.msg import PoseStamped

                assert deserialize_message(msg.data, PoseStamped).header.frame_id == "map"
    assert all(b > a for a, b in zip(log_times, log_times[1:]))  # each message its own log time
    assert not set(depth_stamps["tof"]) & set(depth_stamps["stereo"])  # asynchronous sensors


def test_storages_and_bare_mcap_read_identically(prefix: Path, tmp_path: Path):
    sqlite = copy_bag(prefix, tmp_path / "prefix_sqlite3", storage="sqlite3")
    bare = next(prefix.glob("*.mcap"))
    reference = _digest(prefix)
    assert len(reference) > 100
    with open_bag(sqlite) as reader:
        assert reader.storage == "sqlite3"
    assert _digest(sqlite) == reference
    assert _digest(bare) == reference


def test_folder_without_metadata_reads_its_file(prefix: Path, tmp_path: Path):
    folder = tmp_path / "no_metadata"
    folder.mkdir()
    mcap = next(prefix.glob("*.mcap"))
    (folder / mcap.name).write_bytes(mcap.read_bytes())
    with open_bag(folder) as reader:
        assert reader.note and "metadata.yaml" in reader.note
    assert _digest(folder) == _digest(prefix)


def _mcap_as_another_writer_writes_it(src: Path, dst: Path, *, extra: list[tuple[str, str, bytes]] = (),
                                      profile: str = "ros2", indexed: bool = False, dds_type_names: bool = False
                                      ) -> list[tuple[str, int, str]]:
    """The bag rewritten with the mcap library (by default without a summary: no index), two
    messages of different topics swapped out of time order, and `extra` (topic, type, data)
    messages appended; returns what was written, as _digest gives it. `dds_type_names`: schemas
    named as DDS names the types (sensor_msgs::msg::dds_::Image_)."""
    from mcap.writer import IndexType, Writer

    with open_bag(src) as reader:
        topics, messages = reader.topics, list(reader.messages())
    messages[10], messages[11] = messages[11], messages[10]
    assert messages[10].topic != messages[11].topic and messages[10].log_time_ns > messages[11].log_time_ns
    with dst.open("wb") as f:
        writer = Writer(f) if indexed else Writer(f, index_types=IndexType.NONE, repeat_channels=False,
                                                  repeat_schemas=False, use_statistics=False, use_summary_offsets=False)
        writer.start(profile=profile, library="another writer")
        channels: dict[tuple[str, str], int] = {}

        def channel(topic: str, msgtype: str, msgdef: str) -> int:
            if (topic, msgtype) not in channels:
                package, kind, name = msgtype.split("/")
                schema = writer.register_schema(f"{package}::{kind}::dds_::{name}_" if dds_type_names else msgtype,
                                                "ros2msg", msgdef.encode())
                channels[(topic, msgtype)] = writer.register_channel(topic, "cdr", schema)
            return channels[(topic, msgtype)]

        last_ns = messages[-1].log_time_ns
        written = [(m.topic, m.msgtype, m.log_time_ns, m.data) for m in messages]
        written += [(topic, msgtype, last_ns + i + 1, data) for i, (topic, msgtype, data) in enumerate(extra)]
        for i, (topic, msgtype, log_ns, data) in enumerate(written):
            writer.add_message(channel(topic, msgtype, topics[topic].msgdef if topic in topics and
                                       msgtype == topics[topic].msgtype else "uint8 x"), log_ns, data, log_ns, i)
        writer.finish()
    return [(topic, log_ns, hashlib.sha1(data).hexdigest()) for topic, _, log_ns, data in written]


def test_mcap_of_another_writer_without_an_index_or_profile_reads_in_file_order(prefix: Path, tmp_path: Path,
                                                                                 tiny_params: Path):
    """An MCAP without a summary whose messages are slightly out of time order (as the format
    allows), or whose profile is not 'ros2', is read whole, in file order, not called damaged."""
    unindexed = tmp_path / "unindexed.mcap"
    written = _mcap_as_another_writer_writes_it(prefix, unindexed)
    assert _digest(unindexed) == written
    with open_bag(unindexed) as reader:  # read as written, and said (it was unsaid)
        assert reader.note and "log times go back 1 time(s) in file order" in reader.note, reader.note
    no_profile = tmp_path / "no_profile.mcap"
    written = _mcap_as_another_writer_writes_it(prefix, no_profile, profile="", indexed=True)
    with open_bag(no_profile) as reader:
        assert reader.note and "file order" in reader.note
    assert _digest(no_profile) == written
    ref, got = _replay(prefix, tmp_path / "ref", tiny_params), _replay(unindexed, tmp_path / "got", tiny_params)
    assert ref.returncode == 0 and got.returncode == 0, got.stderr
    assert ref.stdout.splitlines()[:2] == got.stdout.splitlines()[:2]  # the same frames fused


def test_types_recorded_with_their_dds_names_are_the_ros_types(prefix: Path, tmp_path: Path, tiny_params: Path):
    """A writer that names the types as DDS does (sensor_msgs::msg::dds_::CameraInfo_): the bag
    reads and replays as the same bag with ROS type names (it was refused, the type 'unknown here')."""
    dds = tmp_path / "dds.mcap"
    _mcap_as_another_writer_writes_it(prefix, dds, indexed=True, dds_type_names=True)
    with open_bag(prefix) as reader:
        expected = {topic: info.msgtype for topic, info in reader.topics.items()}
    with open_bag(dds) as reader:
        assert {topic: info.msgtype for topic, info in reader.topics.items()} == expected
    ref, got = _replay(prefix, tmp_path / "ref", tiny_params), _replay(dds, tmp_path / "got", tiny_params)
    assert got.returncode == 0 and ref.stdout.splitlines()[:2] == got.stdout.splitlines()[:2], got.stderr
    for spelling in ("sensor_msgs::msg::dds_::Image_", "sensor_msgs::msg::dds_::Image", "sensor_msgs::msg::Image"):
        assert normalize_msgtype(spelling) == "sensor_msgs/msg/Image"


def test_a_topic_recorded_with_two_types_fuses_the_type_the_node_takes_and_says_so(prefix: Path, tmp_path: Path,
                                                                                    tiny_params: Path):
    """Two recordings merged: /tof/depth holds Image and a few CompressedImage messages (the minority
    registered last). Each message is read as its own type: the Image frames are fused as without
    them, the others left out and named."""
    import json

    from senfunet_ros.replay import TopicRouter
    from senfunet_ros.params_file import load_settings

    compressed = "sensor_msgs/msg/CompressedImage"
    mixed = tmp_path / "mixed.mcap"
    _mcap_as_another_writer_writes_it(prefix, mixed, extra=[("/tof/depth", compressed, b"\x00\x01\x00\x00")] * 3)
    with open_bag(mixed) as reader:
        info = reader.topics["/tof/depth"]
        assert info.msgtype == "sensor_msgs/msg/Image" and info.types[compressed] == 3 and info.count > 3
        router = TopicRouter(load_settings(tiny_params), reader.topics, mixed)
        assert router.other_types == {"/tof/depth": {compressed: 3}}
        decoded = [router.decode(m) for m in reader.messages({"/tof/depth"})]
    assert sum(d is None for d in decoded) == 3 and not router.undecodable
    ref, got = _replay(prefix, tmp_path / "ref", tiny_params), _replay(mixed, tmp_path / "got", tiny_params)
    assert got.returncode == 0 and ref.stdout.splitlines()[:2] == got.stdout.splitlines()[:2], got.stderr
    assert f"left out (3 {compressed})" in got.stderr
    stats = json.loads((tmp_path / "got" / "stats.json").read_text())
    assert stats["topics"]["/tof/depth"]["other_types"] == {compressed: 3}


def test_a_split_recording_without_metadata_or_with_a_part_cut_short_reads_its_files_together(prefix: Path,
                                                                                             tmp_path: Path):
    """A recording split in two .mcap files: read whole without metadata.yaml, and up to the break
    when the recorder was killed while writing the second."""
    from mcap.writer import Writer

    with open_bag(prefix) as reader:
        topics, messages = reader.topics, list(reader.messages())
    folder = tmp_path / "split"
    folder.mkdir()
    halves = [messages[: len(messages) // 2], messages[len(messages) // 2:]]
    for i, part in enumerate(halves):
        with (folder / f"split_{i}.mcap").open("wb") as f:
            writer = Writer(f)
            writer.start(profile="ros2", library="a recorder")
            channels = {t: writer.register_channel(t, "cdr", writer.register_schema(
                info.msgtype, "ros2msg", info.msgdef.encode())) for t, info in topics.items()}
            for j, m in enumerate(part):
                writer.add_message(channels[m.topic], m.log_time_ns, m.data, m.log_time_ns, j)
            writer.finish()
    with open_bag(folder) as reader:
        assert reader.note and "2 files together, in time order" in reader.note
        assert reader.message_count == len(messages) and reader.topics["/tof/depth"].count == topics["/tof/depth"].count
    assert _digest(folder) == _digest(prefix)
    second = folder / "split_1.mcap"
    second.write_bytes(second.read_bytes()[: second.stat().st_size // 2])  # the recorder was killed
    with open_bag(folder) as reader:
        read = 0
        with pytest.raises(BagBrokenError, match="split_1.mcap"):
            for _ in reader.messages():
                read += 1
    assert len(halves[0]) < read < len(messages)


def test_write_sequence_bag_round_trip(tmp_path: Path):
    from senfunet_core.learning import simulator as sim
    from senfunet_ros.replay import TopicRouter, ingest_config
    from senfunet_ros.params_file import load_settings
    from senfunet_ros.ingest import Frame, Ingest

    scene = sim.make_scene(5)
    seq = sim.simulate_sequence(scene, 5, duration_s=0.25, tof_rate_hz=15, stereo_rate_hz=20)
    bags = {storage: write_sequence_bag(seq, tmp_path / storage, storage=storage) for storage in ("mcap", "sqlite3")}
    assert _digest(bags["mcap"]) == _digest(bags["sqlite3"])
    with pytest.raises(BagError, match="exists already"):
        write_sequence_bag(seq, bags["mcap"])
    # Through the node's message handling, every frame comes back with its pose and depth.
    settings = load_settings()
    ingest = Ingest(ingest_config(settings))
    frames: list[Frame] = []
    with open_bag(bags["mcap"]) as reader:
        router = TopicRouter(settings, reader.topics, bags["mcap"])
        for msg in reader.messages(router.topics):
            router.dispatch(ingest, *router.decode(msg))
            frames += [f for f in ingest.pop_ready() if isinstance(f, Frame)]
    frames.sort(key=lambda f: f.stamp_ns)  # frames leave Ingest when posed, per sensor in order
    assert [(f.sensor, round(f.stamp_ns * 1e-9 - 1_700_000_000, 6)) for f in frames] == \
        [(f.sensor, round(f.stamp_s, 6)) for f in seq.frames]
    for got, want in zip(frames, seq.frames):
        assert np.abs(got.T_world_camera - want.T_world_camera).max() < 1e-3
        tolerance = 6e-4 if want.sensor == "tof" else 1e-6  # ToF is stored in whole millimetres
        assert np.abs(got.depth_m - want.depth_m).max() <= tolerance
        assert (got.rgb is None) == (want.rgb is None)


# -- bad bags: one line, no traceback, exit code 2 ----------------------------------------------


def test_missing_path(tmp_path: Path, tiny_params: Path):
    """The command itself (a process): one line, no traceback, exit code 2."""
    line = _one_line_error(replay_commands((tmp_path / "nope", tmp_path / "out", tiny_params), compare=True,
                                           timeout_s=300)[0])
    assert "nope: no such bag" in line


@pytest.mark.parametrize("name, content, expected", [
    ("garbage.mcap", os.urandom(4096), "garbage.mcap: not a readable bag"),
    ("garbage.db3", b"SQLite format 2\x00" + bytes(4080), "garbage.db3: not an sqlite3 database"),
    ("notes.txt", b"hello", "notes.txt: not a bag"),
])
def test_corrupt_files(tmp_path: Path, tiny_params: Path, name: str, content: bytes, expected: str):
    path = tmp_path / name
    path.write_bytes(content)
    assert expected in _one_line_error(_replay(path, tmp_path / "out", tiny_params))


def test_empty_folder(tmp_path: Path, tiny_params: Path):
    (tmp_path / "empty").mkdir()
    assert "not a rosbag2 folder" in _one_line_error(_replay(tmp_path / "empty", tmp_path / "out", tiny_params))


@pytest.mark.parametrize("as_folder", [False, True])
def test_truncated_mcap_writes_what_was_fused(prefix: Path, tmp_path: Path, tiny_params: Path, as_folder: bool):
    data = next(prefix.glob("*.mcap")).read_bytes()
    if as_folder:  # a recording killed mid-way: metadata.yaml claims more than the file holds
        bag = tmp_path / "killed"
        bag.mkdir()
        (bag / "metadata.yaml").write_text((prefix / "metadata.yaml").read_text())
        (bag / f"{prefix.name}.mcap").write_bytes(data[: int(len(data) * 0.6)])
    else:
        bag = tmp_path / "cut.mcap"
        bag.write_bytes(data[: int(len(data) * 0.6)])
    out = tmp_path / "out"
    if as_folder:  # in-process: the replay core reports the break and still writes the meshes
        from senfunet_ros.replay import replay_bag

        result = replay_bag(bag, out, params=tiny_params, progress=False, compare=True)
        assert not result.ok and "breaks after" in result.error
    else:  # the command: one line, exit code 2
        line = _one_line_error(_replay(bag, out, tiny_params))
        assert "breaks after" in line and "wrote the meshes fused so far" in line
    for name in ("mesh", "tof", "stereo", "tsdf_fusion"):
        assert (out / f"{name}.ply").stat().st_size > 0
    import json

    stats = json.loads((out / "stats.json").read_text())
    assert stats["complete"] is False and "breaks after" in stats["error"]
    assert 0 < stats["sensors"]["tof"]["integrated"] < 10


def test_truncated_mcap_raises_broken_error_midway(prefix: Path, tmp_path: Path):
    data = next(prefix.glob("*.mcap")).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with open_bag(cut) as reader:
        read = 0
        with pytest.raises(BagBrokenError) as info:
            for _ in reader.messages():
                read += 1
    assert info.value.messages_read == read > 0


def test_bag_without_expected_topics(prefix: Path, tmp_path: Path, tiny_params: Path):
    """A bag of one sensor: the missing topics, and that SenFuNet needs a second sensor's depth (the
    error sent the user to name the bag's topics in the parameters, of a bag without them)."""
    tof_only = copy_bag(prefix, tmp_path / "tof_only", topics=["/tof/depth", "/tof/camera_info", "/tof/pose"])
    line = _one_line_error(_replay(tof_only, tmp_path / "out", tiny_params))
    assert "no messages on /stereo/camera_info, /stereo/depth, /stereo/pose" in line
    assert "no other image topic to take as stereo's depth: SenFuNet fuses the depth of two sensors" in line
    assert "--params" not in line


def test_missing_topics_name_the_parameters_to_set(prefix: Path):
    """A topic the parameters name that the bag lacks: the error names the parameter to change, and
    with pose_type tf on a bag of pose topics, says the bag has no /tf and which pose topics it has."""
    from senfunet_ros.replay import TopicRouter
    from senfunet_ros.params_file import load_settings

    with open_bag(prefix) as reader:
        topics = dict(reader.topics)
    with pytest.raises(BagError) as info:
        TopicRouter(load_settings(overrides={"tof.depth_topic": "/camera/depth"}), topics, prefix)
    assert "no messages on /camera/depth" in str(info.value)
    assert "set tof.depth_topic to the bag's topics with --params" in str(info.value)
    # a bag without any camera_info: naming the parameters to set sent the user after topics it does not have
    without_info = {t: i for t, i in topics.items() if not t.endswith("camera_info")}
    with pytest.raises(BagError) as info:
        TopicRouter(load_settings(), without_info, prefix)
    assert ("no sensor_msgs/msg/CameraInfo topic to take as tof and stereo's: the node takes each sensor's "
            "intrinsics (K) from its camera_info" in str(info.value)) and "--params" not in str(info.value)
    without_stereo_info = {t: i for t, i in topics.items() if t != "/stereo/camera_info"}
    with pytest.raises(BagError) as info:  # one missing: another sensor's may be meant
        TopicRouter(load_settings(), without_stereo_info, prefix)
    assert "set stereo.camera_info_topic to the bag's topics with --params" in str(info.value)
    with pytest.raises(BagError) as info:
        TopicRouter(load_settings(overrides={"pose_type": "tf"}), topics, prefix)
    assert "no messages on /tf" in str(info.value)
    assert ("which the bag does not have; it has pose topics (/stereo/pose, /tof/pose): set pose_type: pose_stamped"
            in str(info.value))


def _bag_with_custom_depth_type(path: Path, prefix: Path) -> Path:
    """The prefix, but /tof/depth recorded as a message type nobody has installed."""
    from rosbags.rosbag2 import Writer

    with open_bag(prefix) as reader, Writer(path, version=9) as writer:
        conns = {}
        for msg in reader.messages():
            if msg.topic not in conns:
                info = reader.topics[msg.topic]
                if msg.topic == "/tof/depth":
                    conns[msg.topic] = writer.add_connection(msg.topic, "acme_msgs/msg/DepthImage",
                                                             msgdef="float32[] depth\n", rihs01="RIHS01_" + "0" * 64)
                else:
                    conns[msg.topic] = writer.add_connection(msg.topic, msg.msgtype, msgdef=info.msgdef,
                                                             rihs01=info.digest)
            writer.write(conns[msg.topic], msg.log_time_ns, msg.data)
    return path


def test_unknown_message_type(prefix: Path, tmp_path: Path, tiny_params: Path):
    bag = _bag_with_custom_depth_type(tmp_path / "custom", prefix)
    line = _one_line_error(_replay(bag, tmp_path / "out", tiny_params))
    assert "topic /tof/depth has type acme_msgs/msg/DepthImage, unknown here," in line
    assert "sensor_msgs/msg/Image" in line


def test_wrong_pose_type_names_the_parameter(prefix: Path, tmp_path: Path):
    from senfunet_ros.replay import TopicRouter
    from senfunet_ros.params_file import load_settings

    with open_bag(prefix) as reader:
        topics = dict(reader.topics)
    topics["/tof/pose"] = topics["/tof/pose"].__class__("/tof/pose", "nav_msgs/msg/Odometry", 10)
    with pytest.raises(BagError, match="set pose_type: odometry"):
        TopicRouter(load_settings(), topics, prefix)
    TopicRouter(load_settings(overrides={"pose_type": "odometry", "stereo.pose_topic": "/tof/pose"}), topics, prefix)


def test_play_bad_bags(prefix: Path, tmp_path: Path):
    def play(bag: Path) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "senfunet_ros.cli", "play", str(bag)],
                              capture_output=True, text=True, timeout=120)

    proc = play(tmp_path / "missing")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip() == f"senfunet play: {tmp_path / 'missing'}: no such bag; " \
        "pass a rosbag2 folder (with metadata.yaml) or a .mcap file"
    only_custom = tmp_path / "only_custom"
    from rosbags.rosbag2 import Writer

    with Writer(only_custom, version=9) as writer:
        conn = writer.add_connection("/x", "acme_msgs/msg/Thing", msgdef="int32 a\n", rihs01="RIHS01_" + "0" * 64)
        writer.write(conn, 1, b"\x00\x01\x00\x00\x01\x00\x00\x00")
    proc = play(only_custom)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip() == f"senfunet play: {only_custom}: none of its topics has a message type installed " \
        "here (acme_msgs/msg/Thing); install their packages (pip install ros-jazzy-<package>)"


def test_ros1_bag_is_named_with_the_conversion(tmp_path):
    bag = tmp_path / "robot.bag"
    bag.write_bytes(b"#ROSBAG V2.0\nE\x00\x00\x00")
    with pytest.raises(BagError, match=r"a ROS 1 bag; convert it to rosbag2 first: rosbags-convert --src .*robot\.bag"):
        with open_bag(bag):
            pass


def test_other_files_are_still_not_a_bag(tmp_path):
    other = tmp_path / "notes.txt"
    other.write_text("hello")
    with pytest.raises(BagError, match="not a bag"):
        with open_bag(other):
            pass


# -- bags of other writers ----------------------------------------------------------------------


def test_a_db3_whose_metadata_disagrees_with_its_topic_table_is_read_as_the_file_records_it(prefix: Path,
                                                                                          tmp_path: Path,
                                                                                          tiny_params: Path):
    """rosbags matches metadata.yaml's topics to the db3's own by offered QoS too, and read nothing of
    a topic whose QoS differed (the camera_info of a sensor: none of its frames fused). The file's own
    table is what the recorder wrote with the messages: every message is read, latched as the file
    says, with a note naming the topics."""
    from odd_bags import db3_with_disagreeing_metadata

    bag = db3_with_disagreeing_metadata(prefix, tmp_path / "db3")
    with open_bag(bag) as reader:
        assert reader.note and "metadata.yaml disagrees" in reader.note
        assert "/tof/camera_info" in reader.note and "/tof/depth" in reader.note
        assert reader.topics["/tof/camera_info"].latched and not reader.topics["/tof/depth"].latched
    assert _digest(bag) == _digest(prefix)
    ref, got = _replay(prefix, tmp_path / "ref", tiny_params), _replay(bag, tmp_path / "got", tiny_params)
    assert got.returncode == 0 and ref.stdout.splitlines()[:2] == got.stdout.splitlines()[:2], got.stdout + got.stderr
    assert "metadata.yaml disagrees" in got.stderr


@pytest.mark.parametrize("storage, metadata", [("mcap", True), ("sqlite3", True), ("mcap", False)])
def test_a_split_recording_whose_files_overlap_in_time_is_read_in_time_order(prefix: Path, tmp_path: Path,
                                                                             storage: str, metadata: bool):
    """rosbag2 folders (or a folder of files without metadata.yaml) whose files hold interleaved
    times: one message sequence in log-time order, as recorded, not file after file."""
    from odd_bags import split_overlapping

    bag = split_overlapping(prefix, tmp_path / "split", storage=storage, metadata=metadata)
    assert len(list(bag.iterdir())) == 2 + metadata
    with open_bag(bag) as reader:
        assert reader.message_count == len(_digest(prefix))
    assert _digest(bag) == _digest(prefix)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_split_recording_whose_metadata_lists_only_its_first_file_is_read_whole(prefix: Path, tmp_path: Path,
                                                                                 storage: str):
    """A recorder killed after a split leaves a metadata.yaml that lists (and counts) only the first
    file: the second was skipped without a word (replay fused half the frames, exit code 0). The files
    metadata.yaml does not list are read too, and the note says so."""
    from odd_bags import _metadata, _write_metadata, split_overlapping

    bag = split_overlapping(prefix, tmp_path / "split", storage=storage)
    meta = _metadata(bag)
    info = meta["rosbag2_bagfile_information"]
    info["relative_file_paths"], info["files"] = info["relative_file_paths"][:1], info["files"][:1]
    info["message_count"] = info["files"][0]["message_count"]
    _write_metadata(bag, meta)
    with open_bag(bag) as reader:
        assert reader.note is not None and "does not list" in reader.note and "reindex" in reader.note, reader.note
    assert _digest(bag) == _digest(prefix)


@pytest.mark.parametrize("how", ["mcap-lz4", "mcap-zstd", "db3-file", "db3-message"])
def test_compressed_bags_read_whole(prefix: Path, tmp_path: Path, how: str):
    from odd_bags import compressed

    assert _digest(compressed(prefix, tmp_path / "bag", how)) == _digest(prefix)


def test_file_compressed_storage_without_metadata_reads_whole(prefix: Path, tmp_path: Path):
    """rosbag2's file compression (x.db3.zstd, x.mcap.zstd) in a folder without metadata.yaml, or as a
    bare file: decompressed into a temporary folder (gone once the reader closes), then read."""
    import zstandard
    from odd_bags import compressed

    db3 = compressed(prefix, tmp_path / "db3", "db3-file")
    (db3 / "metadata.yaml").unlink()
    mcap = tmp_path / "mcap"
    mcap.mkdir()
    plain = next(prefix.glob("*.mcap"))
    (mcap / f"{plain.name}.zstd").write_bytes(zstandard.ZstdCompressor().compress(plain.read_bytes()))
    reference = _digest(prefix)
    folders = Path(tempfile.gettempdir()).glob
    for bag in (db3, next(db3.glob("*.db3.zstd")), mcap, next(mcap.iterdir())):
        before = set(folders("senfunet-bag-*"))
        with open_bag(bag) as reader:
            assert reader.note and "decompressed into a temporary folder" in reader.note, bag
            unpacked = set(folders("senfunet-bag-*")) - before
            assert unpacked
        assert not any(folder.exists() for folder in unpacked)
        assert _digest(bag) == reference, bag
    (mcap / "broken.db3.zstd").write_bytes(b"not zstd at all")
    with pytest.raises(BagError, match="cannot decompress it as zstd"):
        open_bag(mcap / "broken.db3.zstd")


def test_a_compression_rosbags_cannot_read_is_named_with_what_to_do(prefix: Path, tmp_path: Path, tiny_params: Path):
    from odd_bags import compressed

    bag = compressed(prefix, tmp_path / "lz4", "db3-file")
    meta = (bag / "metadata.yaml").read_text()
    (bag / "metadata.yaml").write_text(meta.replace("compression_format: zstd", "compression_format: lz4"))
    line = _one_line_error(_replay(bag, tmp_path / "out", tiny_params))
    assert "Compression format 'lz4' is not supported" in line and "convert" in line and "damaged" not in line


def test_a_topic_named_for_two_sensors_feeds_both(tmp_path: Path) -> None:
    """One pose topic for both sensors (one /odom of the robot, each sensor placed by T_body_camera): the
    router kept one route per topic, so the topic fed the sensor named last and the other fused nothing,
    with exit code 0 (the live node subscribes it once per sensor)."""
    from senfunet_core.learning import simulator as sim
    from senfunet_ros.ingest import Frame, Ingest
    from senfunet_ros.params_file import load_settings
    from senfunet_ros.replay import TopicRouter, ingest_config

    seq = sim.simulate_sequence(sim.make_scene(5), 5, duration_s=0.25, tof_rate_hz=15, stereo_rate_hz=20)
    bag = write_sequence_bag(seq, tmp_path / "bag")
    params = tmp_path / "params.yaml"
    params.write_text("senfunet:\n  ros__parameters:\n    stereo:\n      pose_topic: /tof/pose\n")
    settings = load_settings(params)
    ingest = Ingest(ingest_config(settings))
    frames: list[Frame] = []
    with open_bag(bag) as reader:
        router = TopicRouter(settings, reader.topics, bag)
        for msg in reader.messages(router.topics):
            router.dispatch(ingest, *router.decode(msg))
            frames += [f for f in ingest.pop_ready() if isinstance(f, Frame)]
    counters = ingest.ledger.counters()
    assert counters["tof"]["pose_received"] == counters["stereo"]["pose_received"] > 0
    for sensor in ("tof", "stereo"):
        assert sum(f.sensor == sensor for f in frames) == sum(f.sensor == sensor for f in seq.frames) > 0


def test_message_compressed_bag_without_its_metadata_is_decompressed_and_non_cdr_data_is_named(tmp_path: Path) -> None:
    """rosbag2's per-message zstd compression, read without the metadata.yaml that says so (a bare .mcap
    passed on its own): every message was 'could not be decoded'. Zstd frames are now decompressed (CDR
    never starts with zstd's magic number). A payload that is not CDR at all (ROS 1 or JSON data) is
    named as such when it fails to decode."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    from senfunet_core.learning import simulator as sim
    from senfunet_ros.bagio import BagMessage
    from senfunet_ros.params_file import load_settings
    from senfunet_ros.replay import TopicRouter

    seq = sim.simulate_sequence(sim.make_scene(5), 5, duration_s=0.1, tof_rate_hz=15, stereo_rate_hz=20)
    plain = write_sequence_bag(seq, tmp_path / "plain")
    with open_bag(plain) as reader:
        topics, messages = dict(reader.topics), list(reader.messages())
    writer = Writer(tmp_path / "compressed", version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    with writer:
        connections = {topic: writer.add_connection(topic, info.msgtype, msgdef=info.msgdef, rihs01=info.digest)
                       for topic, info in topics.items()}
        for msg in messages:
            writer.write(connections[msg.topic], msg.log_time_ns, msg.data)
    (tmp_path / "compressed" / "metadata.yaml").unlink()
    (bare,) = (tmp_path / "compressed").glob("*.mcap")
    with open_bag(bare) as reader:
        assert [(m.topic, m.data) for m in reader.messages()] == [(m.topic, m.data) for m in messages]
    router = TopicRouter(load_settings(), topics, plain)
    pose = next(m for m in messages if m.topic == "/tof/pose")
    assert router.decode(pose) is not None and not router.undecodable
    assert router.decode(BagMessage(pose.topic, pose.msgtype, pose.log_time_ns, b'{"pose": {}}')) is None
    assert router.undecodable == {"/tof/pose": 1} and router.not_cdr == {"/tof/pose"}


def test_the_router_says_what_an_engineers_bag_and_parameters_lack(prefix: Path, tmp_path: Path) -> None:
    """A colour topic listed with no message was routed (fused black, no note, as if colour came); a
    camera_info listed with none was 'no messages on /tof/camera_info; the bag has: ... /tof/camera_info';
    a relative topic name in the parameters was not found; a bag with /tf but no pose topics did not
    point at pose_type tf."""
    import dataclasses

    from senfunet_ros.params_file import load_settings
    from senfunet_ros.replay import TopicRouter

    with open_bag(prefix) as reader:
        topics = dict(reader.topics)
    settings = load_settings()
    router = TopicRouter(settings, {**topics, "/stereo/color": dataclasses.replace(topics["/stereo/color"], count=0)},
                         prefix)
    assert "/stereo/color" not in router.routes and "/tof/depth" in router.routes
    empty_info = {**topics, "/tof/camera_info": dataclasses.replace(topics["/tof/camera_info"], count=0)}
    with pytest.raises(BagError, match=r"/tof/camera_info listed, but recorded without a message: a latched"):
        TopicRouter(settings, empty_info, prefix)
    params = tmp_path / "relative.yaml"
    params.write_text("senfunet:\n  ros__parameters:\n    tof:\n      depth_topic: tof/depth\n")
    assert "/tof/depth" in TopicRouter(load_settings(params), topics, prefix).routes
    tf = dataclasses.replace(topics["/tof/pose"], name="/tf", msgtype="tf2_msgs/msg/TFMessage", types={})
    without_poses = {t: info for t, info in topics.items() if not t.endswith("/pose")} | {"/tf": tf}
    with pytest.raises(BagError, match="the bag has /tf: for poses from TF, set pose_type: tf"):
        TopicRouter(settings, without_poses, prefix)


# -- recordings as recorders leave them when killed, and files damaged in place ---------------------------------


def test_a_db3_recorded_in_wal_mode_and_killed_is_read_with_its_log(prefix: Path, tmp_path: Path):
    """rosbag2's resilient preset writes sqlite3 in WAL mode; a recorder killed then leaves committed
    messages in x.db3-wal. Read immutable, as rosbags opens it, half the bag was gone without a word
    (or, with metadata.yaml, refused as damaged). A copy with the log applied is read; the bag's own
    files stay as they are."""
    import shutil
    import sqlite3

    db3 = copy_bag(prefix, tmp_path / "full", storage="sqlite3", compress=False)
    bag = tmp_path / "killed"
    shutil.copytree(db3, bag)
    (db,) = bag.glob("*.db3")
    with sqlite3.connect(db) as conn:  # the first half in the file, the rest committed to the log only
        stamps = sorted(t for (t,) in conn.execute("select timestamp from messages"))
        middle = stamps[len(stamps) // 2]
        conn.execute("delete from messages where timestamp >= ?", (middle,))
    conn.close()
    conn = sqlite3.connect(db)
    conn.execute("vacuum")
    conn.execute("pragma journal_mode=WAL")
    conn.close()
    subprocess.run([sys.executable, "-c", f"""
import os, sqlite3
conn = sqlite3.connect({str(db)!r})
conn.execute('pragma wal_autocheckpoint=0')
conn.execute("attach {str(next(db3.glob('*.db3')))!r} as full")
conn.execute('insert into messages select * from full.messages where timestamp >= {middle}')
conn.commit()
os._exit(0)  # killed: no checkpoint
"""], check=True)
    wal = db.with_name(db.name + "-wal")
    assert wal.stat().st_size > 0
    before = {part.name: part.read_bytes() for part in bag.iterdir()}
    for path in (bag, db):
        with open_bag(path) as reader:
            assert reader.note and f"{db.name}-wal holds messages" in reader.note, reader.note
        assert _digest(path) == _digest(prefix), path
    assert {part.name: part.read_bytes() for part in bag.iterdir()} == before


def test_a_split_recording_with_an_empty_or_missing_part_or_a_broken_metadata_reads_what_is_there(prefix: Path,
                                                                                                    tmp_path: Path):
    """A recorder killed right after a split leaves an empty newest file; an empty or half-written
    metadata.yaml; a part not copied with the rest: each refused the whole bag as damaged. The
    files that can be read are, and the note names what was not."""
    import shutil

    from odd_bags import _metadata, split_overlapping

    whole = split_overlapping(prefix, tmp_path / "split")
    first, second = _metadata(whole)["rosbag2_bagfile_information"]["relative_file_paths"]
    reference = _digest(whole)
    assert reference == _digest(prefix)

    empty_part = tmp_path / "empty_part"
    shutil.copytree(whole, empty_part)
    (empty_part / "split_2.mcap").write_bytes(b"")
    empty_meta, half_meta = tmp_path / "empty_meta", tmp_path / "half_meta"
    for bag, text in ((empty_meta, ""), (half_meta, (whole / "metadata.yaml").read_text()[:300])):
        shutil.copytree(whole, bag)
        (bag / "metadata.yaml").write_text(text)
    for bag, said in ((empty_part, "split_2.mcap (empty"), (empty_meta, "metadata.yaml cannot be read (it is empty)"),
                      (half_meta, "metadata.yaml cannot be read")):
        with open_bag(bag) as reader:
            assert reader.note and said in reader.note, reader.note
        assert _digest(bag) == reference, bag

    missing = tmp_path / "missing"
    shutil.copytree(whole, missing)
    (missing / second).unlink()
    with open_bag(missing) as reader:
        assert reader.note and f"lists {second}, not in the folder" in reader.note, reader.note
    with open_bag(whole / first) as reader:
        only_first = [(m.topic, m.log_time_ns, hashlib.sha1(m.data).hexdigest()) for m in reader.messages()]
    assert _digest(missing) == only_first and 0 < len(only_first) < len(reference)


def test_an_mcap_whose_index_is_damaged_or_cut_reads_every_message(prefix: Path, tmp_path: Path):
    """An indexed MCAP whose chunk index points wrong (the data intact) broke the read at that chunk,
    and one cut inside its summary (every message and the data end present: a recorder killed while
    closing) was called broken: both are read whole, in file order where the index fails, and said."""
    import shutil
    import struct

    from mcap.reader import make_reader

    (mcap,) = prefix.glob("*.mcap")
    data = mcap.read_bytes()
    with mcap.open("rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 3
    offset = struct.pack("<Q", chunks[2].chunk_start_offset)
    field_at = data.rfind(offset)
    assert field_at > chunks[-1].chunk_start_offset  # in the summary
    bad_index = tmp_path / "bad_index"
    shutil.copytree(prefix, bad_index)
    (bad_index / mcap.name).write_bytes(data[:field_at] + struct.pack("<Q", chunks[2].chunk_start_offset + 12345)
                                        + data[field_at + 8:])
    with open_bag(bad_index) as reader:
        assert _digest(bad_index) == _digest(prefix)
        read = list(reader.messages())
        assert len(read) == reader.message_count
        (note,) = reader.read_notes()
        assert "its index broke" in note and "read on in file order" in note, note
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) - 100])
    with open_bag(cut) as reader:
        assert reader.note and "its summary (the index after the messages) is cut short" in reader.note
    assert _digest(cut) == _digest(prefix)


def test_a_file_compressed_part_beside_its_decompressed_copy_is_read_once(prefix: Path, tmp_path: Path):
    """`zstd -d x.db3.zstd` keeps the .zstd file: the folder held the part twice, read as two files of a
    split recording, and every frame after the first came twice (half dropped as duplicates)."""
    import zstandard
    from odd_bags import compressed

    bag = compressed(prefix, tmp_path / "db3", "db3-file")
    (zipped,) = bag.glob("*.db3.zstd")
    zipped.with_suffix("").write_bytes(zstandard.ZstdDecompressor().decompress(zipped.read_bytes(),
                                                                               max_output_size=1 << 30))
    assert _digest(bag) == _digest(prefix)
    (bag / "metadata.yaml").unlink()
    assert _digest(bag) == _digest(prefix)


def test_an_unreadable_compressed_part_is_named_as_the_bags_file(prefix: Path, tmp_path: Path):
    """A file-compressed part that decompresses into a damaged database is left out, the other part read;
    the note named the temporary copy (gone once the bag closed) in the sqlite3 command it advised."""
    import zstandard
    from odd_bags import split_overlapping

    bag = split_overlapping(prefix, tmp_path / "split", storage="sqlite3", metadata=False)
    first, second = sorted(bag.glob("*.db3"))
    data = second.read_bytes()
    (bag / f"{second.name}.zstd").write_bytes(zstandard.ZstdCompressor().compress(data[: len(data) // 2]))
    second.unlink()
    with open_bag(bag) as reader:
        note = reader.note or ""
        read = [(m.topic, m.log_time_ns, hashlib.sha1(m.data).hexdigest()) for m in reader.messages()]
    assert f"left out, unreadable: {second.name}.zstd" in note and "senfunet-bag-" not in note, note
    assert f"{second.name}.zstd decompressed" not in note and f"{bag / second.name}.zstd" in note, note
    assert read == _digest(first) and read


def test_a_split_recordings_file_that_breaks_midway_ends_only_its_own_messages(prefix: Path, tmp_path: Path):
    """Two files of interleaved times, the first cut short (damaged): the read ended at its break for
    both, although the second held the rest of the recording. The second is read to its end, then the
    break is raised, naming the file."""
    from odd_bags import split_overlapping

    bag = split_overlapping(prefix, tmp_path / "split", metadata=False)
    first, second = sorted(bag.glob("*.mcap"))
    with open_bag(second) as reader:
        of_second = [(m.topic, m.log_time_ns) for m in reader.messages()]
    first.write_bytes(first.read_bytes()[: first.stat().st_size // 2])
    read = []
    with open_bag(bag) as reader, pytest.raises(BagBrokenError, match=f"{first.name}.*other files were read") as info:
        for m in reader.messages():
            read.append((m.topic, m.log_time_ns))
    assert set(of_second) <= set(read) and info.value.messages_read == len(read) > len(of_second)


def test_an_mcap_with_a_damaged_chunk_reads_the_chunks_after_it(prefix: Path, tmp_path: Path):
    """A chunk of an indexed MCAP damaged in place (its compressed data's header overwritten): the read
    broke there, through the index and in file order alike, and the chunks after it were lost. They are
    read through the index, the damaged chunk left out and named."""
    import shutil

    from mcap.reader import make_reader

    (mcap,) = prefix.glob("*.mcap")
    data = bytearray(mcap.read_bytes())
    with mcap.open("rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    damaged = chunks[2]
    at = data.index(b"\x28\xb5\x2f\xfd", damaged.chunk_start_offset)  # the chunk's zstd frame
    assert len(chunks) >= 4 and at < damaged.chunk_start_offset + damaged.chunk_length
    data[at:at + 4] = bytes(4)
    bag = tmp_path / "damaged"
    shutil.copytree(prefix, bag)
    (bag / mcap.name).write_bytes(bytes(data))
    with open_bag(bag) as reader:
        read = [(m.topic, m.log_time_ns, hashlib.sha1(m.data).hexdigest()) for m in reader.messages()]
        notes = reader.read_notes()
    assert any("damaged chunks left out, the others read: log times" in note for note in notes), notes
    kept = [m for m in _digest(prefix) if not damaged.message_start_time <= m[1] <= damaged.message_end_time]
    assert read == kept and read[-1] == _digest(prefix)[-1]


def test_play_takes_topics_with_or_without_their_leading_slash(prefix: Path):
    """`senfunet play --topics tof/pose` was refused ("no topic tof/pose"), though everywhere else
    'tof/pose' is '/tof/pose'; a topic the bag lacks is still refused, named as a topic."""
    from senfunet_ros.commands.play import _message_classes

    said: list[str] = []
    with open_bag(prefix) as reader:
        assert set(_message_classes(reader, ["tof/pose", "/tof/depth"], said.append)) == {"/tof/pose", "/tof/depth"}
        with pytest.raises(BagError, match="no topic /tof/colour"):
            _message_classes(reader, ["tof/colour"], said.append)
