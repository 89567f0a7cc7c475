"""Bags as other writers and recorders leave them: a db3 whose metadata.yaml disagrees with its own
topic table, split recordings whose files overlap in time, compressed storage. Each is written from
a bag of ours (with rosbags, the mcap library, or by editing metadata.yaml as another tool would)."""
from __future__ import annotations

import io
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ruamel.yaml import YAML

from senfunet_ros.bagio import latched_qos, open_bag


def _rewrite(src: Path, dst: Path, *, storage: str = "sqlite3", compression: str = "",
             qos_topics: frozenset[str] = frozenset(), keep: slice = slice(None)) -> Path:
    """`src`'s messages (every one in `keep`) written by rosbags as a rosbag2 folder: `storage`,
    `compression` "" or "file" or "message" (zstd), latched QoS offered on `qos_topics`."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    writer = Writer(dst, version=9, storage_plugin=plugin)
    if compression:
        writer.set_compression(CompressionMode[compression.upper()], CompressionFormat.ZSTD)
    with open_bag(src) as reader, writer:
        infos, conns = reader.topics, {}
        for msg in list(reader.messages())[keep]:
            if msg.topic not in conns:
                info = infos[msg.topic]
                conns[msg.topic] = writer.add_connection(msg.topic, msg.msgtype, msgdef=info.msgdef, rihs01=info.digest,
                                                         offered_qos_profiles=latched_qos() if msg.topic in qos_topics
                                                         else [])
            writer.write(conns[msg.topic], msg.log_time_ns, msg.data)
    return dst


def _metadata(folder: Path) -> dict[str, Any]:
    return YAML(typ="safe").load((folder / "metadata.yaml").read_text())


def _write_metadata(folder: Path, meta: dict[str, Any]) -> None:
    text = io.StringIO()
    YAML().dump(meta, text)
    (folder / "metadata.yaml").write_text(text.getvalue())


def db3_with_disagreeing_metadata(src: Path, dst: Path) -> Path:
    """A db3 recorded with /tof/camera_info latched, whose metadata.yaml (rewritten by another tool)
    says /tof/camera_info is volatile and /tof/depth latched: rosbags reads nothing of a topic whose
    offered QoS differs between the two."""
    _rewrite(src, dst, qos_topics=frozenset({"/tof/camera_info"}))
    meta = _metadata(dst)
    info = meta["rosbag2_bagfile_information"]
    latched = next(t["topic_metadata"]["offered_qos_profiles"] for t in info["topics_with_message_count"]
                   if t["topic_metadata"]["name"] == "/tof/camera_info")
    assert latched, "rosbags wrote no QoS for the latched topic"
    for topic in info["topics_with_message_count"]:
        name = topic["topic_metadata"]["name"]
        if name in ("/tof/camera_info", "/tof/depth"):
            topic["topic_metadata"]["offered_qos_profiles"] = [] if name == "/tof/camera_info" else latched
    _write_metadata(dst, meta)
    return dst


def split_overlapping(src: Path, dst: Path, *, storage: str = "mcap", metadata: bool = True) -> Path:
    """A recording split in two files whose times overlap: every other message in each (as a
    recorder writing two streams to two files, or two recordings merged, leaves them)."""
    dst.mkdir()
    parts = [_rewrite(src, dst.parent / f"{dst.name}_part{i}", storage=storage, keep=slice(i, None, 2))
             for i in range(2)]
    metas = [_metadata(part)["rosbag2_bagfile_information"] for part in parts]
    for part, meta in zip(parts, metas):
        (part / meta["relative_file_paths"][0]).rename(dst / meta["relative_file_paths"][0])
        shutil.rmtree(part)
    if metadata:
        info = metas[0]
        info["relative_file_paths"] = [m["relative_file_paths"][0] for m in metas]
        info["files"] = [m["files"][0] for m in metas]
        info["message_count"] = sum(m["message_count"] for m in metas)
        counts = {t["topic_metadata"]["name"]: 0 for m in metas for t in m["topics_with_message_count"]}
        for m in metas:
            for t in m["topics_with_message_count"]:
                counts[t["topic_metadata"]["name"]] += t["message_count"]
        for t in info["topics_with_message_count"]:
            t["message_count"] = counts[t["topic_metadata"]["name"]]
        start = min(m["starting_time"]["nanoseconds_since_epoch"] for m in metas)
        end = max(m["starting_time"]["nanoseconds_since_epoch"] + m["duration"]["nanoseconds"] for m in metas)
        info["starting_time"]["nanoseconds_since_epoch"], info["duration"]["nanoseconds"] = start, end - start
        _write_metadata(dst, {"rosbag2_bagfile_information": info})
    return dst


def compressed(src: Path, dst: Path, how: str) -> Path:
    """`src` compressed as recorders compress: "mcap-lz4" or "mcap-zstd" (chunks of a bare .mcap,
    written by the mcap library), "db3-file" or "db3-message" (rosbag2's zstd compression modes)."""
    if how.startswith("db3-"):
        return _rewrite(src, dst, compression=how.removeprefix("db3-"))
    from mcap.writer import CompressionType, Writer

    with open_bag(src) as reader:
        topics, messages = reader.topics, list(reader.messages())
    dst = dst.with_suffix(".mcap")
    with dst.open("wb") as f:
        writer = Writer(f, compression=CompressionType.LZ4 if how == "mcap-lz4" else CompressionType.ZSTD,
                        chunk_size=64 * 1024)
        writer.start(profile="ros2", library="another recorder")
        channels = {t: writer.register_channel(t, "cdr", writer.register_schema(info.msgtype, "ros2msg",
                                                                                info.msgdef.encode()))
                    for t, info in topics.items()}
        for i, msg in enumerate(messages):
            writer.add_message(channels[msg.topic], msg.log_time_ns, msg.data, msg.log_time_ns, i)
        writer.finish()
    return dst


def clock_error_and_bad_name(src: Path, dst: Path) -> Path:
    """`src` as an mcap whose recorder logged a pose topic's first three messages at time 0 (a clock not
    yet set: the log times then jump by decades) and named the colour topic '/stereo/color-raw', a name
    that ROS 2 refuses (another middleware's bridge allowed it)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    with open_bag(src) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        infos, conns, zeroed = reader.topics, {}, 0
        for msg in reader.messages():
            topic = "/stereo/color-raw" if msg.topic == "/stereo/color" else msg.topic
            if topic not in conns:
                info = infos[msg.topic]
                conns[topic] = writer.add_connection(topic, msg.msgtype, msgdef=info.msgdef, rihs01=info.digest)
            log_time_ns = msg.log_time_ns
            if msg.topic == "/tof/pose" and zeroed < 3:
                log_time_ns, zeroed = 0, zeroed + 1
            writer.write(conns[topic], log_time_ns, msg.data)
    return dst


def with_recorded_clock(src: Path, dst: Path, *, sim_start_ns: int, topic: str = "/clock",
                        clock_for_ns: int | None = None, pause_ns: int = 0) -> Path:
    """`src` as a simulation's recording: a /clock topic (named `topic`; every 10 ms of log time) of the
    simulated time, which starts at sim_start_ns where the log times start (a Gazebo run recorded with its
    clock); clock_for_ns: the clock's publisher stops this long after the start; pause_ns: every topic,
    the clock too, pauses this long halfway (the simulation paused), the messages after it logged later."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    Clock, Time = store.types["rosgraph_msgs/msg/Clock"], store.types["builtin_interfaces/msg/Time"]
    with open_bag(src) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        infos, conns = reader.topics, {}
        clock = writer.add_connection(topic, "rosgraph_msgs/msg/Clock", typestore=store)
        next_tick_ns = reader.start_ns
        halfway_ns = (reader.start_ns + reader.end_ns) // 2

        def logged(log_ns: int) -> int:
            return log_ns + (pause_ns if log_ns >= halfway_ns else 0)

        for msg in reader.messages():
            while next_tick_ns <= msg.log_time_ns and (clock_for_ns is None
                                                       or next_tick_ns < reader.start_ns + clock_for_ns):
                sec, nanosec = divmod(sim_start_ns + next_tick_ns - reader.start_ns, 1_000_000_000)
                # (after the pause the clock resumes 5 ms after the other topics, as a restarted simulation's may)
                writer.write(clock, logged(next_tick_ns) + (5_000_000 if pause_ns and next_tick_ns >= halfway_ns
                                                            else 0), store.serialize_cdr(
                    Clock(clock=Time(sec=sec, nanosec=nanosec)), "rosgraph_msgs/msg/Clock"))
                next_tick_ns += 10_000_000
            if msg.topic not in conns:
                info = infos[msg.topic]
                conns[msg.topic] = writer.add_connection(msg.topic, msg.msgtype, msgdef=info.msgdef,
                                                         rihs01=info.digest)
            writer.write(conns[msg.topic], logged(msg.log_time_ns), msg.data)
    return dst


def spelled_both_ways(src: Path, dst: Path) -> Path:
    """Two recordings merged (as `mcap merge` or a converter leaves them): the first half of `src`'s
    time written by a tool that names topics without their leading '/' ('tof/depth'), the rest with it."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    with open_bag(src) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        middle_ns = reader.start_ns + int(reader.duration_s * 1e9) // 2
        infos, conns = reader.topics, {}
        for msg in reader.messages():
            topic = msg.topic.lstrip("/") if msg.log_time_ns < middle_ns else msg.topic
            if topic not in conns:
                info = infos[msg.topic]
                conns[topic] = writer.add_connection(topic, msg.msgtype, msgdef=info.msgdef, rihs01=info.digest)
            writer.write(conns[topic], msg.log_time_ns, msg.data)
    return dst


def cut_short(src: Path, dst: Path, *, share: float = 0.7) -> Path:
    """`src` as a killed recording leaves it: an unchunked mcap (rosbag2's fastwrite preset) in a folder
    without metadata.yaml, cut after `share` of its bytes."""
    from mcap.writer import Writer

    dst.mkdir()
    file = dst / f"{dst.name}_0.mcap"
    with open_bag(src) as reader, file.open("wb") as out:
        writer = Writer(out, use_chunking=False)
        writer.start(profile="ros2", library="rosbag2 fastwrite imitation")
        channels = {topic: writer.register_channel(topic, "cdr", writer.register_schema(
            info.msgtype, "ros2msg", info.msgdef.encode()), metadata={"offered_qos_profiles": ""})
            for topic, info in reader.topics.items()}
        for sequence, msg in enumerate(reader.messages()):
            writer.add_message(channels[msg.topic], msg.log_time_ns, msg.data, msg.log_time_ns, sequence)
        writer.finish()
    file.write_bytes(file.read_bytes()[:int(file.stat().st_size * share)])
    return dst


def with_damaged_messages(src: Path, dst: Path, damage: Callable[[str, int, bytes], bytes]) -> Path:
    """`src` with each message's bytes as `damage(topic, n, data)` gives them back (n: the message's index on
    its topic, from 0): a recorder or a disk that damaged some."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    with open_bag(src) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        infos, conns, counts = reader.topics, {}, {}
        for msg in reader.messages():
            if msg.topic not in conns:
                info = infos[msg.topic]
                conns[msg.topic] = writer.add_connection(msg.topic, msg.msgtype, msgdef=info.msgdef,
                                                         rihs01=info.digest)
            n = counts[msg.topic] = counts.get(msg.topic, -1) + 1
            writer.write(conns[msg.topic], msg.log_time_ns, damage(msg.topic, n, msg.data))
    return dst
