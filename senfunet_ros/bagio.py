"""Reading and writing recordings without ROS: rosbag2 folders (mcap or sqlite3) and bare `.mcap` files.

Reading gives raw CDR bytes per message in recorded (log-time) order, across the files of a split
recording too (their times may overlap); a rosbag2 folder is read through its files' own topic
tables where metadata.yaml disagrees with them (`BagReader.note` says so). Turning them into
message objects is the caller's job (replay deserialises them into rclpy classes, play publishes the bytes as they
are). Writing turns a simulated `Sequence` into the contract's topic layout (../shared/DESIGN.md):

    /<s>/camera_info   sensor_msgs/msg/CameraInfo   before each depth image, same stamp
    /<s>/depth         sensor_msgs/msg/Image        tof: 16UC1 millimetres, stereo: 32FC1 metres (NaN invalid)
    /stereo/color      sensor_msgs/msg/Image        rgb8 left image, same stamp as its depth
    /<s>/pose          geometry_msgs/msg/PoseStamped  optical frame in `map`, its own rate

Convention: times are integer nanoseconds. `log_time_ns` is when the recorder received a message
(what /clock replays); header stamps are sensor times. Every message of a written bag has its
own log time (stamp plus a per-stream latency, ties broken by 1 ns), so mcap and sqlite3 copies
of one bag come back in the same order.

Errors: `BagError` (one line saying which file or topic is wrong and what to do) when a bag cannot
be opened or written; `BagBrokenError` from `BagReader.messages` when a bag breaks midway (the
messages before the break have been yielded). A truncated `.mcap` without its summary is read
sequentially up to the break. Compressed storage is read as rosbags and the mcap library read it
(mcap chunks in zstd or lz4; rosbag2's zstd file and message modes; file-compressed `.mcap.zstd` and
`.db3.zstd` files without their metadata.yaml are decompressed into a temporary folder first);
another compression is a BagError that says to convert the bag. A folder that is not whole as its
metadata.yaml says (no or an unreadable metadata.yaml, files it lacks or does not list, an empty
file, an sqlite3 write-ahead log, an MCAP without its index) is read file by file (`_open_parts`);
damage read past midway is in `BagReader.read_notes`.
"""
from __future__ import annotations

import heapq
import importlib
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, NamedTuple
from collections.abc import Callable, Collection, Iterable, Iterator

import numpy as np

if TYPE_CHECKING:
    from senfunet_core.learning.simulator import Sequence

__all__ = [
    "BagError",
    "BagBrokenError",
    "TopicInfo",
    "BagMessage",
    "BagReader",
    "open_bag",
    "bag_storage_file",
    "message_class",
    "absolute_topic",
    "normalize_msgtype",
    "is_cdr",
    "write_sequence_bag",
    "copy_bag",
    "DEFAULT_START_NS",
    "STORAGES",
]

STORAGES = ("mcap", "sqlite3")
# Simulated time 0 is written as this wall time (2023-11-14): ROS treats time 0 as "no clock yet".
DEFAULT_START_NS = 1_700_000_000 * 1_000_000_000
# Recorder latency per stream (stamp -> log time): colour before the stereo matcher's depth.
_LATENCY_NS = {"pose": 2_000_000, "camera_info": 4_000_000, "color": 6_000_000,
               "depth_tof": 8_000_000, "depth_stereo": 25_000_000}


class BagError(ValueError):
    """A bag cannot be read or written. str(err) is one line: which file or topic, what to do.

    A ValueError (bad input), so callers that report bad parameters report bad bags too."""


class BagBrokenError(BagError):
    """The bag broke midway (truncated or corrupt); `messages_read` messages came before the break."""

    def __init__(self, message: str, messages_read: int) -> None:
        super().__init__(message)
        self.messages_read = messages_read


@dataclass(frozen=True)
class TopicInfo:
    name: str
    msgtype: str  # ROS 2 spelling, e.g. sensor_msgs/msg/Image; the most recorded one if several
    count: int  # messages recorded, every type (from the bag's index; 0 if unknown)
    msgdef: str = ""  # message definition text, if the bag stores it
    digest: str = ""  # RIHS01 type hash, if the bag stores it
    types: dict[str, int] = field(default_factory=dict)  # every type recorded on the topic -> messages
    latched: bool = False  # recorded with transient-local durability (e.g. /tf_static)


def _topic_infos(connections: Iterable[tuple[str, str, int, str, str, bool]]) -> dict[str, TopicInfo]:
    """TopicInfo per topic from its connections (topic, type, messages, definition, digest, latched):
    a topic recorded twice sums its counts; one recorded with several types names the most recorded."""
    grouped: dict[str, list[tuple[str, str, int, str, str, bool]]] = {}
    for conn in connections:
        grouped.setdefault(conn[0], []).append(conn)
    infos = {}
    for topic, conns in grouped.items():
        types: dict[str, int] = {}
        for _, msgtype, count, *_ in conns:
            name = normalize_msgtype(msgtype)
            types[name] = types.get(name, 0) + count
        main = max(types, key=lambda t: types[t])
        first = next(c for c in conns if normalize_msgtype(c[1]) == main)
        infos[topic] = TopicInfo(topic, main, sum(types.values()), first[3], first[4], types,
                                 any(c[5] for c in conns))
    return infos


class BagMessage(NamedTuple):
    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes  # CDR, with its 4-byte encapsulation header


_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"


def is_cdr(data: bytes) -> bool:
    """Whether a payload starts as ROS 2's serialised messages do: a CDR encapsulation header (0, then
    0-3: plain or parameter-list CDR, big or little endian). ROS 1 or JSON payloads do not."""
    return len(data) >= 4 and data[0] == 0 and data[1] <= 3


def _payload(data: bytes) -> bytes:
    """A message's bytes, a zstd frame decompressed: rosbag2's message compression, read without the
    metadata.yaml that says so (a bare .mcap/.db3, or a folder whose metadata.yaml is gone); CDR never
    starts with zstd's magic number."""
    if data[:4] == _ZSTD_MAGIC:
        try:
            return _zstd_decompress(data)
        except Exception:  # noqa: BLE001 (zstandard.ZstdError): left as it is, and counted where it fails
            return data
    return data


# the DDS or C++ type name a writer may record instead of the ROS one: sensor_msgs::msg::dds_::Image_,
# sensor_msgs::msg::Image
_DDS_TYPE_NAME = re.compile(r"^(\w+)::(\w+)::(?:dds_::)?([A-Za-z0-9]+)_?$")


def absolute_topic(topic: str) -> str:
    """A topic as the bag names it, absolute: a recorder may write 'tof/depth' for /tof/depth (relative
    names are in the root namespace, as the node's and play's)."""
    return topic if topic.startswith("/") else f"/{topic}"


def normalize_msgtype(msgtype: str) -> str:
    """`pkg/Name` (ROS 1 style), `pkg::msg::dds_::Name_` (DDS) and `pkg::msg::Name` (C++) -> `pkg/msg/Name`;
    ROS 2 names unchanged."""
    dds = _DDS_TYPE_NAME.match(msgtype)
    if dds:
        return "/".join(dds.groups())
    parts = msgtype.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return msgtype


def message_class(msgtype: str) -> type:
    """The rclpy message class of `pkg/msg/Name`; BagError if it is not installed."""
    parts = normalize_msgtype(msgtype).split("/")
    if len(parts) != 3 or not all(parts):
        raise BagError(f"message type '{msgtype}' is not a ROS 2 type name (pkg/msg/Name)")
    package, kind, name = parts
    try:
        module = importlib.import_module(f"{package}.{kind}")
        cls = getattr(module, name)
    except (ImportError, AttributeError):
        raise BagError(
            f"message type '{msgtype}' is unknown here; install its package "
            f"(pip install ros-jazzy-{package.replace('_', '-')}) or leave the topic out"
        ) from None
    return cls


# --------------------------------------------------------------------------------------------
# Reading


def bag_storage_file(path: str | Path) -> Path:
    """The storage file of a one-file bag: the `.mcap`/`.db3` inside a folder, or the file itself."""
    path = Path(path)
    if path.is_file():
        return path
    files = sorted([*path.glob("*.mcap"), *path.glob("*.db3")])
    if len(files) != 1:
        raise BagError(f"{path}: expected one .mcap or .db3 file in the bag folder, found {len(files)}")
    return files[0]


class _Source:
    """One way of reading a bag: topics up front, then messages in recorded order."""

    storage: str
    topics: dict[str, TopicInfo]
    message_count: int
    start_ns: int
    end_ns: int
    note: str | None = None  # what was not as it should be, yet read

    def messages(self, topics: Collection[str] | None) -> Iterator[BagMessage]:
        raise NotImplementedError

    def read_notes(self) -> list[str]:
        """What reading the messages found not as it should be, yet read past (so far)."""
        return []

    def close(self) -> None:
        pass


class _RosbagsSource(_Source):
    """rosbags' reader: rosbag2 folders of either storage and bare .mcap/.db3 files (indexed).

    A folder's files are read through their own topic tables, which are what the recorder wrote with
    the messages (rosbag2 reads them so too): where metadata.yaml disagrees (another writer's offered
    QoS or type hash), rosbags would leave that topic's messages out without a word. The files of a
    split recording are merged in log-time order (their times may overlap)."""

    def __init__(self, path: Path) -> None:
        from rosbags.rosbag2 import Reader

        self._reader = Reader(path)
        self._reader.open()
        reader = self._reader
        if path.is_file():
            self.storage = "mcap" if path.suffix == ".mcap" else "sqlite3"
        else:
            self.storage = _folder_storage(path)
        self.message_count = int(reader.message_count)
        self.start_ns = int(reader.start_time) if self.message_count else 0
        self.end_ns = int(reader.end_time) if self.message_count else 0
        # a folder's storage files (rosbags' DirectoryReader), or the one file
        self._files: list[Any] = list(getattr(reader.storage, "storages", None) or [reader.storage])
        self._unzip = _zstd_decompress if reader.compression_mode == "message" else None
        self._read_notes: list[str] = []
        listed, in_files = list(reader.connections), [conn for file in self._files for conn in file.connections]
        self.topics = _topic_infos(_connection_rows(listed, in_files))
        disagree = _disagreements(listed, in_files)
        self.note = (f"{path / 'metadata.yaml'} disagrees with the bag's files on {', '.join(disagree)} (offered QoS, "
                     "type hash or the topic itself): read as the files record them" if disagree else None)

    def messages(self, topics: Collection[str] | None) -> Iterator[BagMessage]:
        streams = [self._file_messages(file, topics) for file in self._files]
        if len(streams) == 1:
            yield from streams[0]
        else:  # a split recording: in log-time order across its files, whose times may overlap
            yield from heapq.merge(*streams, key=lambda msg: msg.log_time_ns)

    def _file_messages(self, file: Any, topics: Collection[str] | None) -> Iterator[BagMessage]:
        """One file's messages through its index; an MCAP file whose index is damaged goes on in file
        order from where the index failed (`_McapStreamSource`), and one with a damaged chunk with the
        chunks after it, through the index (`_mcap_chunk_messages`), each said in `read_notes`."""
        conns = [c for c in file.connections if topics is None or c.topic in topics]
        if not conns:
            return
        yielded = _Yielded()
        try:
            for conn, timestamp, data in file.messages(conns):
                data = _payload(data) if self._unzip is None else self._unzip(data)
                msg = BagMessage(conn.topic, normalize_msgtype(conn.msgtype), int(timestamp), bytes(data))
                yielded.add(msg)
                yield msg
        except Exception as err:
            path = Path(str(getattr(file, "path", "")))
            if path.suffix != ".mcap" or not path.is_file():
                raise
            self._note(f"{path}: its index broke ({_describe(err)}) after {_ns_text(yielded.last_ns)}: read on in "
                       "file order from there")
            try:
                for msg in _McapStreamSource(path).messages(topics):
                    if yielded.new(msg):
                        yield msg
            except BagBrokenError as broken:  # a damaged chunk: the chunks after it, through the index
                damaged: list[str] = []
                try:
                    for msg in _mcap_chunk_messages(path, topics, after_ns=yielded.last_ns, damaged=damaged):
                        if yielded.new(msg):
                            yield msg
                except Exception:  # noqa: BLE001 (no usable index either): the break as file order met it
                    raise broken from None
                self._note(f"{path}: damaged chunks left out, the others read: {'; '.join(damaged)}"
                           if damaged else str(broken))

    def _note(self, note: str) -> None:
        if note not in self._read_notes:  # said once, however often the bag is read
            self._read_notes.append(note)

    def read_notes(self) -> list[str]:
        return list(self._read_notes)

    def close(self) -> None:
        self._reader.close()


class _Yielded:
    """The messages a read has yielded, as far as a second read of the same file, from where the first
    broke, must know them: the last log time, and the messages at it."""

    def __init__(self) -> None:
        self.last_ns = -1
        self._at_last: set[tuple[str, bytes]] = set()

    def add(self, msg: BagMessage) -> None:
        if msg.log_time_ns != self.last_ns:
            self.last_ns, self._at_last = msg.log_time_ns, set()
        self._at_last.add((msg.topic, msg.data))

    def new(self, msg: BagMessage) -> bool:
        """Whether the read has not yielded it (it is now counted as yielded)."""
        seen = msg.log_time_ns == self.last_ns and (msg.topic, msg.data) in self._at_last
        if msg.log_time_ns < self.last_ns or seen:
            return False
        self.add(msg)
        return True


def _mcap_chunk_messages(path: Path, topics: Collection[str] | None, *, after_ns: int, damaged: list[str]
                         ) -> Iterator[BagMessage]:
    """An indexed MCAP's messages chunk by chunk through its index, each chunk's in log-time order, from
    the chunks that end at or after `after_ns`; a chunk that cannot be read or fails its checksum (damaged)
    is left out and named in `damaged`. Raises when the file has no usable index."""
    from mcap.reader import ReadDataStream, breakup_chunk, make_reader
    from mcap.records import Chunk, Message

    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
        if summary is None or not summary.chunk_indexes:
            raise BagError(f"{path}: no chunk index")
        for index in sorted(summary.chunk_indexes, key=lambda c: (c.message_start_time, c.chunk_start_offset)):
            if index.message_end_time < after_ns:
                continue
            try:
                f.seek(index.chunk_start_offset + 1 + 8)  # past the record's opcode and length
                records = breakup_chunk(Chunk.read(ReadDataStream(f)), validate_crc=True)
            except Exception as err:  # noqa: BLE001 (a damaged chunk: decompression, checksum, framing)
                damaged.append(f"log times {index.message_start_time * 1e-9:.3f} s to "
                               f"{index.message_end_time * 1e-9:.3f} s ({_describe(err)})")
                continue
            for record in sorted((r for r in records if isinstance(r, Message)), key=lambda r: r.log_time):
                channel = summary.channels.get(record.channel_id)
                if channel is None or (topics is not None and channel.topic not in topics):
                    continue
                schema = summary.schemas.get(channel.schema_id)
                yield BagMessage(channel.topic, normalize_msgtype(schema.name if schema else ""), int(record.log_time),
                                 _payload(bytes(record.data)))


def _ns_text(log_time_ns: int) -> str:
    return "its first message" if log_time_ns < 0 else f"log time {log_time_ns * 1e-9:.3f} s"


def _zstd_decompress(data: bytes) -> bytes:
    """One message of a bag recorded with compression_mode message (zstd frames)."""
    import zstandard

    return zstandard.ZstdDecompressor().decompressobj().decompress(bytes(data))


def _connection_rows(listed: list[Any], in_files: list[Any]) -> Iterator[tuple[str, str, int, str, str, bool]]:
    """`_topic_infos` rows of rosbags connections: the listed ones (metadata.yaml's, with their counts;
    a bare file's own), latched as the files record it, then those only the files have."""
    for conn in listed:
        recorded = [c for c in in_files if c.topic == conn.topic] or [conn]
        yield (conn.topic, conn.msgtype, int(conn.msgcount), getattr(conn.msgdef, "data", "") or "", conn.digest or "",
               any(_latched(getattr(c.ext, "offered_qos_profiles", ())) for c in recorded))
    known = {(conn.topic, normalize_msgtype(conn.msgtype)) for conn in listed}
    for conn in in_files:
        if (conn.topic, normalize_msgtype(conn.msgtype)) not in known:
            yield (conn.topic, conn.msgtype, int(conn.msgcount), getattr(conn.msgdef, "data", "") or "",
                   conn.digest or "", _latched(getattr(conn.ext, "offered_qos_profiles", ())))


def _disagreements(listed: list[Any], in_files: list[Any]) -> list[str]:
    """The topics a file records otherwise than metadata.yaml lists them (rosbags matches the two
    on topic, type, offered QoS and type hash, and reads nothing of a topic that differs)."""
    out = []
    for conn in in_files:
        same = any(c.topic == conn.topic and c.msgtype == conn.msgtype and c.ext == conn.ext
                   and (not c.digest or not conn.digest or c.digest == conn.digest) for c in listed)
        if not same and conn.topic not in out:
            out.append(conn.topic)
    return out


def _folder_storage(path: Path) -> str:
    try:
        from ruamel.yaml import YAML

        meta = YAML(typ="safe").load((path / "metadata.yaml").read_text())
        return str(meta["rosbag2_bagfile_information"]["storage_identifier"])
    except Exception:
        return "unknown"


class _McapStreamSource(_Source):
    """Sequential reading of an .mcap file without a summary (recording killed, file truncated, or a
    writer that writes none) or that rosbags refuses.

    A first pass finds the channels and counts messages up to the break; `messages` then yields
    them in file order and raises BagBrokenError where the file breaks.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.storage = "mcap"
        self._channels: dict[int, tuple[str, str]] = {}
        counts: dict[int, int] = {}
        self.start_ns, self.end_ns = 0, 0
        self.break_error: str | None = None
        first = True
        backwards, furthest_back_ns = 0, 0  # log times that go back in file order (a writer that does not sort)
        try:
            for record in self._records():
                name = type(record).__name__
                if name == "Message":
                    counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
                    if first:
                        self.start_ns, first = record.log_time, False
                    if record.log_time < self.end_ns:
                        backwards += 1
                        furthest_back_ns = max(furthest_back_ns, self.end_ns - record.log_time)
                    self.end_ns = max(self.end_ns, record.log_time)
        except Exception as err:  # the break: remember it, messages() raises it in order
            if self._data_ended:  # past the messages: only the summary (the index) is cut
                self.note = (f"{path}: its summary (the index after the messages) is cut short "
                             f"({_describe(err)}): every message was read, in file order")
            else:
                self.break_error = _describe(err)
        if backwards:  # no index to sort them by: said, not sorted behind the reader's back
            order = (f"{path}: its messages' log times go back {backwards} time(s) in file order (by up to "
                     f"{furthest_back_ns * 1e-9:.3f} s); without an index they are read in file order, as written "
                     "(sort the file, e.g. with the mcap CLI's mcap sort, to read them in time order)")
            self.note = f"{self.note}; {order}" if self.note else order
        self.message_count = sum(counts.values())
        self.topics = _topic_infos((topic, msgtype, counts.get(cid, 0), self._schema_text.get(cid, ""), "",
                                    _latched(self._qos.get(cid, "")))
                                   for cid, (topic, msgtype) in self._channels.items())

    def _records(self) -> Iterator[Any]:
        from mcap.records import Channel, DataEnd, Schema
        from mcap.stream_reader import StreamReader

        self._data_ended = False  # past the data section (a DataEnd record): what follows is the summary
        schemas: dict[int, tuple[str, str]] = {}
        self._schema_text: dict[int, str] = {}
        self._qos: dict[int, str] = {}
        with self.path.open("rb") as stream:
            for record in StreamReader(stream, record_size_limit=2**31, validate_crcs=True).records:
                if isinstance(record, Schema):
                    schemas[record.id] = (record.name, record.data.decode("utf-8", "replace"))
                elif isinstance(record, Channel):
                    msgtype, text = schemas.get(record.schema_id, ("", ""))
                    self._channels[record.id] = (record.topic, normalize_msgtype(msgtype))
                    self._schema_text[record.id] = text
                    self._qos[record.id] = str((record.metadata or {}).get("offered_qos_profiles", ""))
                elif isinstance(record, DataEnd):
                    self._data_ended = True
                yield record

    def messages(self, topics: Collection[str] | None) -> Iterator[BagMessage]:
        read = 0
        try:
            for record in self._records():
                if type(record).__name__ != "Message":
                    continue
                read += 1
                topic, msgtype = self._channels.get(record.channel_id, ("", ""))
                if topics is None or topic in topics:
                    yield BagMessage(topic, msgtype, int(record.log_time), _payload(bytes(record.data)))
        except Exception as err:
            if self._data_ended:  # the summary is cut, not the messages (said in the note)
                return
            raise BagBrokenError(f"{self.path}: the file breaks after {read} messages ({_describe(err)}); "
                                 "it was truncated or damaged, e.g. a recording that was killed", read) from None
        if self.break_error is not None:  # pragma: no cover - the first pass saw it, so the second does too
            raise BagBrokenError(f"{self.path}: the file breaks after {read} messages ({self.break_error})", read)


def _latched(offered_qos_profiles: Any) -> bool:
    """Whether a recording's offered QoS (rosbags' Qos objects, or rosbag2's YAML text) was
    transient-local: what a latched publisher such as tf2's static broadcaster offers."""
    if isinstance(offered_qos_profiles, str):
        return re.search(r"durability:\s*(1|transient_local)\b", offered_qos_profiles.lower()) is not None
    return any(getattr(getattr(q, "durability", None), "name", "") == "TRANSIENT_LOCAL"
               for q in offered_qos_profiles or ())


class _MergedSource(_Source):
    """A split recording's files read together, in log-time order across them (their times may
    overlap: a recorder that split by size while messages of one topic were late)."""

    def __init__(self, sources: list[_Source]) -> None:
        self._sources = sources
        self.storage = sources[0].storage
        self.message_count = sum(source.message_count for source in sources)
        counted = [source for source in sources if source.message_count]
        self.start_ns = min((source.start_ns for source in counted), default=0)
        self.end_ns = max((source.end_ns for source in counted), default=0)
        self.topics = _topic_infos((topic, msgtype, n, info.msgdef, info.digest, info.latched)
                                   for source in sources for topic, info in source.topics.items()
                                   for msgtype, n in info.types.items())

    def messages(self, topics: Collection[str] | None) -> Iterator[BagMessage]:
        """In log-time order; a file that breaks midway ends its own messages, not the others': they are
        read to their ends, then its BagBrokenError is raised."""
        breaks: list[BagBrokenError] = []

        def until_broken(source: _Source) -> Iterator[BagMessage]:
            try:
                yield from source.messages(topics)
            except BagBrokenError as err:
                breaks.append(err)

        read = 0
        for msg in heapq.merge(*map(until_broken, self._sources), key=lambda msg: msg.log_time_ns):
            read += 1
            yield msg
        if breaks:
            raise BagBrokenError(f"{'; '.join(map(str, breaks))} (its recording's other files were read to their ends)",
                                 read)

    def read_notes(self) -> list[str]:
        return [note for source in self._sources for note in source.read_notes()]

    def close(self) -> None:
        for source in self._sources:
            source.close()


@dataclass
class _FolderFiles:
    """A rosbag2 folder's storage files as found, against what its metadata.yaml says."""

    files: list[Path]  # .mcap, .db3 and their file-compressed .zstd forms, in recording order
    unlisted: list[Path]  # of them, those metadata.yaml does not list (a recorder killed after a split)
    missing: list[str]  # names metadata.yaml lists that are not in the folder
    metadata_problem: str | None  # a metadata.yaml that cannot be read: why
    has_metadata: bool


_STORAGE_SUFFIXES = (".mcap", ".db3")
_ZIPPED = (".mcap.zstd", ".db3.zstd")  # rosbag2's file compression: each storage file in one zstd frame


def _folder_files(folder: Path) -> _FolderFiles:
    """The storage files of a rosbag2 folder in recording order: as metadata.yaml lists them, then (by
    name) those it does not list; without a usable metadata.yaml, all by name."""
    present = sorted(part for part in folder.iterdir()
                     if part.is_file() and part.name.endswith(_STORAGE_SUFFIXES + _ZIPPED))
    # a file-compressed part beside its decompressed copy (`zstd -d` keeps the .zstd): one file, read once
    plain_names = {part.name for part in present}
    present = [part for part in present if part.name.removesuffix(".zstd") == part.name
               or part.name.removesuffix(".zstd") not in plain_names]
    meta_path = folder / "metadata.yaml"
    if not meta_path.is_file():
        return _FolderFiles(present, [], [], None, False)
    try:
        from ruamel.yaml import YAML

        meta = YAML(typ="safe").load(meta_path.read_text())
        names = [Path(str(name)).name for name in meta["rosbag2_bagfile_information"].get("relative_file_paths") or []]
        if not names:
            raise ValueError("it lists no storage file: cut short?")
    except Exception as err:  # noqa: BLE001 (empty, cut short, not YAML, not rosbag2's)
        problem = "it is empty" if not meta_path.read_bytes().strip() else _describe(err)
        return _FolderFiles(present, [], [], f"its metadata.yaml cannot be read ({problem})", True)
    by_name = {part.name: part for part in present}
    names = [name.removesuffix(".zstd") if name.removesuffix(".zstd") in by_name else name for name in names]
    listed = [by_name[name] for name in names if name in by_name]
    unlisted = [part for part in present if part.name not in names]
    return _FolderFiles(listed + unlisted, unlisted, [name for name in names if name not in by_name], None, True)


def _wal_file(db3: Path) -> Path | None:
    """The write-ahead log beside an sqlite3 file, if it holds anything: rosbag2's resilient preset
    writes in WAL mode, and a recorder killed then leaves committed messages in it, which a reader
    opening the file immutable (as rosbags does) never sees."""
    wal = db3.with_name(db3.name + "-wal")
    return wal if db3.suffix == ".db3" and wal.is_file() and wal.stat().st_size > 0 else None


def _describe(err: BaseException) -> str:
    if type(err).__name__ == "EndOfFile":  # mcap's reader says nothing more
        return "unexpected end of file"
    text = str(err).strip().rstrip(".") or type(err).__name__
    return text.splitlines()[0]


def _is_ros1_bag(path: Path) -> bool:
    """A ROS 1 bag file (its '#ROSBAG V2.0' header), which no rosbag2 reader takes."""
    try:
        with path.open("rb") as file:
            return file.read(9) == b"#ROSBAG V"
    except OSError:
        return False


def _mcap_is_unindexed(path: Path) -> bool:
    """True if an .mcap file starts right but has no summary section to index it: it lacks its
    footer (a truncated recording), or its footer points at no summary (a writer that writes none;
    its messages need not be in time order, which only an index lets a reader sort)."""
    magic = b"\x89MCAP0\r\n"
    footer_size = 1 + 8 + 8 + 8 + 4  # opcode, record length, summary_start, summary_offset_start, crc
    try:
        with path.open("rb") as f:
            head = f.read(8)
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - 8 - footer_size))
            footer = f.read(footer_size)
            tail = f.read(8)
    except OSError:
        return False
    if head != magic:
        return False
    if tail != magic:
        return True
    summary_start = int.from_bytes(footer[9:17], "little")
    return footer[:1] == b"\x02" and summary_start == 0


def _open_source(path: Path) -> _Source:
    """How to read `path` (a rosbag2 folder, a bare .mcap or .db3 file, or a split recording's
    folder), opened; its `note` says how, when not the normal way. BagError says what is wrong."""
    if not path.exists():
        raise BagError(f"{path}: no such bag; pass a rosbag2 folder (with metadata.yaml) or a .mcap file")
    if path.is_dir():
        return _open_folder(path)
    if path.suffix in _STORAGE_SUFFIXES:
        if _wal_file(path) is not None:
            return _open_parts([path], [])
        return _open_rosbags(path)
    if path.name.endswith(_ZIPPED):
        return _open_parts([path], [f"{path} is compressed"])
    if _is_ros1_bag(path):
        raise BagError(f"{path}: a ROS 1 bag; convert it to rosbag2 first: "
                       f"rosbags-convert --src {path} --dst {path.with_suffix('')}")
    raise BagError(f"{path}: not a bag; pass a rosbag2 folder or a .mcap file")


def _open_folder(path: Path) -> _Source:
    """A rosbag2 folder through rosbags when it is whole and as its metadata.yaml says; else its
    storage files one by one, together (`_open_parts`), with a note on what was not as it should be."""
    found = _folder_files(path)
    if not found.files:
        if found.has_metadata and found.missing:
            raise BagError(f"{path}: its metadata.yaml lists {', '.join(found.missing)}, and the folder holds none of "
                           "them; copy the recording's files into it")
        raise BagError(f"{path}: not a rosbag2 folder (no .mcap, .db3, .mcap.zstd or .db3.zstd file)")
    plain = [part for part in found.files if part.suffix in _STORAGE_SUFFIXES]
    whole = (found.has_metadata and found.metadata_problem is None and not found.missing and not found.unlisted
             and len(plain) in (0, len(found.files))  # all plain, or all file-compressed (rosbags decompresses)
             and not any(part.stat().st_size == 0 or _wal_file(part) or _mcap_is_unindexed(part) for part in plain))
    if whole:
        try:
            return _open_rosbags(path)
        except BagError as err:  # a metadata.yaml rosbags cannot take (keys missing): the files without it
            detail = str(err).removeprefix(f"{path}: ")
            if not re.search(r"metadata|yaml", detail, re.IGNORECASE):
                raise
            found.metadata_problem = f"its metadata.yaml cannot be read ({detail})"
    why = []
    if not found.has_metadata:
        why.append(f"{path} has no metadata.yaml")
    elif found.metadata_problem is not None:
        why.append(f"{path}: {found.metadata_problem}; reading its files without it (`ros2 bag reindex` rewrites it)")
    if found.missing:
        they = "it" if len(found.missing) == 1 else "they"
        why.append(f"{path}: its metadata.yaml lists {', '.join(found.missing)}, not in the folder: the recording "
                   f"lacks what {they} held (copy {they if they == 'it' else 'them'} into the folder to read it whole)")
    if found.unlisted and found.has_metadata and found.metadata_problem is None:
        why.append(f"{path}: its metadata.yaml does not list {', '.join(part.name for part in found.unlisted)} (a "
                   "recording cut short after a split? `ros2 bag reindex` rewrites it)")
    return _open_parts(found.files, why)


class _TemporarySource(_Source):
    """A source read (in part) from files made in a temporary folder (decompressed, or copied with their
    write-ahead log applied), which goes on close."""

    def __init__(self, inner: _Source, folder: tempfile.TemporaryDirectory, note: str | None) -> None:
        self._inner, self._folder = inner, folder
        self.storage, self.topics, self.message_count = inner.storage, inner.topics, inner.message_count
        self.start_ns, self.end_ns = inner.start_ns, inner.end_ns
        self.note = note

    def read_notes(self) -> list[str]:
        return self._inner.read_notes()

    def messages(self, topics: Collection[str] | None) -> Iterator[BagMessage]:
        return self._inner.messages(topics)

    def close(self) -> None:
        try:
            self._inner.close()
        finally:
            self._folder.cleanup()


def _open_parts(files: list[Path], why: list[str]) -> _Source:
    """Storage files read one by one and together in time order: each file-compressed one decompressed
    and each sqlite3 one with a write-ahead log copied with the log applied (both into a temporary
    folder), an empty or unreadable one left out (unless it is the only one), said in the note after
    `why` (the folder's problems). BagError when none can be read."""
    temporary: tempfile.TemporaryDirectory | None = None
    sources: list[_Source] = []
    notes = list(why)
    read: list[str] = []  # the files read
    left_out: list[str] = []
    unzipped: list[str] = []  # decompressed (file compression)
    logged: list[str] = []  # sqlite3 files with a write-ahead log
    try:
        for part in files:
            if part.stat().st_size == 0 and len(files) > 1:
                left_out.append(f"{part.name} (empty: a recorder killed as it began the file?)")
                continue
            readable = part
            try:
                if part.name.endswith(_ZIPPED) or _wal_file(part) is not None:
                    temporary = temporary or tempfile.TemporaryDirectory(prefix="senfunet-bag-")
                    readable = _readable_copy(part, Path(temporary.name))
                sources.append(_open_rosbags(readable))
            except BagError as err:  # one damaged file among several: the others are read
                # (named as the bag's file: the temporary copy is gone once the bag closes)
                error = BagError(str(err).replace(str(readable), str(part)))
                if len(files) == 1:
                    raise error from None
                left_out.append(f"{part.name} ({str(error).removeprefix(f'{part}: ')})")
                continue
            read.append(part.name)
            if readable is not part:
                (unzipped if part.name.endswith(_ZIPPED) else logged).append(part.name)
        if not sources:
            raise BagError(f"{files[0].parent}: none of its files can be read: {'; '.join(left_out)}")
    except BaseException:
        if temporary is not None:
            temporary.cleanup()
        raise
    inner = sources[0] if len(sources) == 1 else _MergedSource(sources)
    if unzipped:
        notes.append(f"reading {', '.join(unzipped)} decompressed into a temporary folder")
    for name in logged:
        notes.append(f"{name}-wal holds messages its database has not taken in yet (a recording killed in WAL mode, "
                     "as rosbag2's resilient preset writes): reading a copy with them")
    if len(sources) > 1:
        notes.append(f"{'' if notes else f'{files[0].parent}: '}reading its {len(sources)} files together, in time "
                     f"order ({', '.join(read)})")
    elif len(files) == 1 and why and temporary is None:
        notes.append(f"reading {files[0].name} directly")
    if left_out:
        notes.append(f"left out, unreadable: {'; '.join(left_out)}")
    notes += [inner.note] if inner.note else []
    note = "; ".join(notes) or None
    if temporary is None:
        inner.note = note
        return inner
    return _TemporarySource(inner, temporary, note)


def _readable_copy(part: Path, folder: Path) -> Path:
    """A storage file as rosbags can read it, in `folder`: decompressed (a .zstd file), or an sqlite3
    file copied with its write-ahead log, which opening it applies."""
    import shutil
    import sqlite3

    import zstandard

    out = folder / part.name.removesuffix(".zstd")
    try:
        if part.name.endswith(_ZIPPED):
            try:
                with part.open("rb") as source, out.open("wb") as target:
                    zstandard.ZstdDecompressor().copy_stream(source, target)
            except zstandard.ZstdError as err:
                raise BagError(f"{part}: cannot decompress it as zstd ({err}); is it a rosbag2 file-compressed "
                               "storage file?") from err
        else:
            shutil.copyfile(part, out)
        wal = _wal_file(part)
        if wal is not None:
            shutil.copyfile(wal, out.with_name(out.name + "-wal"))
            db = sqlite3.connect(out)  # opening takes in the log; the checkpoint writes it into the file
            try:
                db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            finally:
                db.close()
    except OSError as err:
        raise BagError(f"{part}: cannot make a readable copy in {folder} ({err}); free some space there, or "
                       "decompress it yourself (zstd -d) and pass the result") from err
    except sqlite3.Error as err:
        raise BagError(f"{part}: its write-ahead log cannot be applied ({err}); try `sqlite3 {part} .recover`") from err
    return out


def _open_rosbags(path: Path) -> _Source:
    """A rosbag2 folder or one storage file through rosbags; an MCAP file without an index (or that
    rosbags refuses) read sequentially. BagError says what is wrong."""
    import sqlite3

    from rosbags.rosbag2 import ReaderError

    mcap_file = path if path.suffix == ".mcap" else None
    if path.is_dir() and _folder_storage(path) == "mcap":
        try:
            mcap_file = bag_storage_file(path)
        except BagError:
            mcap_file = None
    if mcap_file is not None and _mcap_is_unindexed(mcap_file):
        stream = _McapStreamSource(mcap_file)
        if not stream.topics:
            raise BagError(f"{mcap_file}: truncated before any topic was recorded; nothing to read")
        return stream
    try:
        return _RosbagsSource(path)
    except FileNotFoundError as err:
        raise BagError(f"{path}: {_describe(err)}") from None
    except Exception as err:  # the storage libraries raise many kinds on what they cannot read
        refusal = err
    if mcap_file is not None:  # an MCAP rosbags refuses (e.g. its profile is not 'ros2'): read it as written
        source: _McapStreamSource | None = None
        try:
            source = _McapStreamSource(mcap_file)
        except Exception:  # noqa: BLE001 (then rosbags' refusal is the error)
            pass
        if source is not None and source.topics and source.break_error is None:
            source.note = f"{mcap_file}: read in file order ({_describe(refusal)})"
            return source
    if isinstance(refusal, ReaderError) and "not supported" in str(refusal):  # e.g. a compression rosbags lacks
        raise BagError(f"{path}: {_describe(refusal)}; convert the bag to an uncompressed or zstd-compressed "
                       "rosbag2 first (ros2 bag convert, or rosbags-convert)") from None
    if isinstance(refusal, (ReaderError, sqlite3.Error, OSError, KeyError, ValueError, TypeError)):
        what = "an sqlite3 database" if path.suffix == ".db3" else "a readable bag"
        salvage = (f" (sqlite3's `sqlite3 {path} .recover | sqlite3 recovered.db3` salvages what a cut or damaged "
                   "database still holds)" if path.suffix == ".db3" else "")
        raise BagError(f"{path}: not {what}: {_describe(refusal)}; "
                       f"the file is damaged or not a rosbag2 recording{salvage}") from None
    raise BagError(f"{path}: cannot read the bag: {_describe(refusal)}") from None


class BagReader:
    """An open bag. Context manager; `messages()` yields `BagMessage`s in recorded order.

        with open_bag("bags/sim_room") as bag:
            print(bag.topics)
            for msg in bag.messages(topics={"/tof/depth"}):
                ...

    `open()` sets what the bag holds: `storage`, `topics`, `message_count`, `start_ns`, `end_ns`
    (log times), and `note` (how the bag was read, when not the normal way)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._source: _Source | None = None
        self.note: str | None = None
        self.storage = ""
        self.topics: dict[str, TopicInfo] = {}
        self.message_count = 0
        self.start_ns = 0
        self.end_ns = 0

    def open(self) -> BagReader:
        source = self._source = _open_source(self.path)
        self.note, self.storage, self.topics = source.note, source.storage, dict(source.topics)
        self.message_count, self.start_ns, self.end_ns = source.message_count, source.start_ns, source.end_ns
        return self

    def close(self) -> None:
        if self._source is not None:
            self._source.close()
            self._source = None

    def __enter__(self) -> BagReader:
        return self.open()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    @property
    def duration_s(self) -> float:
        return max(0, self.end_ns - self.start_ns) * 1e-9

    def read_notes(self) -> list[str]:
        """What reading the messages so far found damaged yet read past (an MCAP index that broke
        midway: the rest read in file order)."""
        return [] if self._source is None else self._source.read_notes()

    def messages(self, topics: Collection[str] | None = None) -> Iterator[BagMessage]:
        """Messages of `topics` (all if None) in recorded order. BagBrokenError where the bag breaks."""
        if self._source is None:
            raise BagError(f"{self.path}: bag is not open")
        read = 0
        iterator = self._source.messages(None if topics is None else set(topics))
        while True:
            try:
                msg = next(iterator)
            except StopIteration:
                return
            except BagBrokenError:
                raise
            except Exception as err:
                raise BagBrokenError(f"{self.path}: the bag breaks after {read} messages ({_describe(err)}); "
                                     "it was truncated or damaged", read) from None
            read += 1
            yield msg


def open_bag(path: str | Path) -> BagReader:
    """Open a bag for reading (a context manager). BagError says what is wrong with it."""
    return BagReader(path).open()


# --------------------------------------------------------------------------------------------
# Writing


def _writer(path: Path, storage: str, compress: bool) -> Any:
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    if storage not in STORAGES:
        raise BagError(f"storage '{storage}' is not supported; use one of {STORAGES}")
    if path.exists():
        raise BagError(f"{path} exists already; remove it or choose another bag path")
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
    if compress and storage == "mcap":  # zstd chunks inside the mcap file: still one plain .mcap
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    return writer


def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def write_sequence_bag(seq: Sequence, path: str | Path, *, storage: str = "mcap", compress: bool = True,
                       start_time_ns: int = DEFAULT_START_NS, fixed_frame: str = "map",
                       progress: Callable[[int, int], None] | None = None) -> Path:
    """Write a simulated sequence as a rosbag2 folder in the contract's topic layout; returns `path`.

    Frame stamps become `start_time_ns + stamp_s`. `progress(done, total)` is called per frame.
    """
    path = Path(path)
    store = _typestore()
    T = store.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Image, CameraInfo = T["sensor_msgs/msg/Image"], T["sensor_msgs/msg/CameraInfo"]
    RegionOfInterest = T["sensor_msgs/msg/RegionOfInterest"]
    PoseStamped, Pose = T["geometry_msgs/msg/PoseStamped"], T["geometry_msgs/msg/Pose"]
    Point, Quaternion = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]

    def header(stamp_ns: int, frame_id: str) -> Any:
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)

    def ns(stamp_s: float) -> int:
        return start_time_ns + int(round(stamp_s * 1e9))

    # (log_ns, order, topic, msgtype, message): built first, sorted, then written
    pending: list[tuple[int, int, str, str, Any]] = []
    order = 0

    def add(log_ns: int, topic: str, msgtype: str, msg: Any) -> None:
        nonlocal order
        pending.append((log_ns, order, topic, msgtype, msg))
        order += 1

    from senfunet_ros.geometry import quat_from_matrix

    for sensor, stamps in seq.pose_stamps_s.items():
        for stamp_s, T_wc in zip(stamps, seq.pose_T_world_camera[sensor]):
            q = quat_from_matrix(np.asarray(T_wc)[:3, :3])
            t = np.asarray(T_wc)[:3, 3]
            stamp = ns(float(stamp_s))
            msg = PoseStamped(header=header(stamp, fixed_frame),
                              pose=Pose(position=Point(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                                        orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                               w=float(q[3]))))
            add(stamp + _LATENCY_NS["pose"], f"/{sensor}/pose", "geometry_msgs/msg/PoseStamped", msg)

    frames = list(seq.frames)
    for frame in frames:
        s = frame.sensor
        stamp = ns(frame.stamp_s)
        optical = f"{s}_optical_frame"
        height, width = frame.depth_m.shape
        K = np.asarray(frame.K, dtype=np.float64)
        info = CameraInfo(
            header=header(stamp, optical), height=height, width=width, distortion_model="plumb_bob",
            d=np.zeros(5), k=K.reshape(-1).copy(), r=np.eye(3).reshape(-1),
            p=np.array([K[0, 0], 0, K[0, 2], 0, 0, K[1, 1], K[1, 2], 0, 0, 0, 1, 0], dtype=np.float64),
            binning_x=0, binning_y=0,
            roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        add(stamp + _LATENCY_NS["camera_info"], f"/{s}/camera_info", "sensor_msgs/msg/CameraInfo", info)
        depth = np.asarray(frame.depth_m, dtype=np.float32)
        valid = np.isfinite(depth) & (depth > 0)
        if s == "tof":  # 16UC1 millimetres, 0 invalid (what Kinect-type drivers publish)
            raw = np.where(valid, np.clip(np.rint(depth * 1000.0), 0, 65535), 0).astype("<u2")
            encoding, step = "16UC1", width * 2
        else:  # 32FC1 metres, NaN invalid (what stereo drivers publish)
            raw = np.where(valid, depth, np.nan).astype("<f4")
            encoding, step = "32FC1", width * 4
        image = Image(header=header(stamp, optical), height=height, width=width, encoding=encoding,
                      is_bigendian=0, step=step, data=raw.view(np.uint8).reshape(-1))
        add(stamp + _LATENCY_NS[f"depth_{'tof' if s == 'tof' else 'stereo'}"], f"/{s}/depth",
            "sensor_msgs/msg/Image", image)
        if frame.rgb is not None:
            rgb = np.ascontiguousarray(frame.rgb, dtype=np.uint8)
            color = Image(header=header(stamp, optical), height=rgb.shape[0], width=rgb.shape[1], encoding="rgb8",
                          is_bigendian=0, step=rgb.shape[1] * 3, data=rgb.reshape(-1))
            add(stamp + _LATENCY_NS["color"], f"/{s}/color", "sensor_msgs/msg/Image", color)

    pending.sort(key=lambda item: (item[0], item[1]))
    writer = _writer(path, storage, compress)
    connections: dict[str, Any] = {}
    last_ns = -1
    n_frames, done = len(frames), 0
    try:
        with writer:
            for log_ns, _, topic, msgtype, msg in pending:
                conn = connections.get(topic)
                if conn is None:
                    conn = connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
                log_ns = max(log_ns, last_ns + 1)  # every message its own log time
                last_ns = log_ns
                writer.write(conn, log_ns, store.serialize_cdr(msg, msgtype))
                if progress is not None and topic.endswith("/depth"):
                    done += 1
                    progress(done, n_frames)
    except OSError as err:
        raise BagError(f"{path}: cannot write the bag: {_describe(err)}") from None
    return path


def latched_qos() -> list[Any]:
    """The offered QoS of a latched publisher (reliable, transient-local, keep last 1), as rosbags
    records it."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    never = QosTime(0, 0)
    return [Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, never, never,
                QosLiveliness.AUTOMATIC, never, False)]


def copy_bag(src: str | Path, dst: str | Path, *, storage: str = "mcap", compress: bool = True,
             topics: Collection[str] | None = None, stop_ns: int | None = None,
             max_messages: int | None = None) -> Path:
    """Copy a bag (all or some topics, up to a log time or a message count) into a new rosbag2 folder."""
    dst = Path(dst)
    store = None
    with open_bag(src) as bag:
        infos = bag.topics
        writer = _writer(dst, storage, compress)
        connections: dict[str, Any] = {}
        written = 0
        with writer:
            for msg in bag.messages(topics):
                if stop_ns is not None and msg.log_time_ns >= stop_ns:
                    break
                if max_messages is not None and written >= max_messages:
                    break
                conn = connections.get(msg.topic)
                if conn is None:
                    info = infos[msg.topic]
                    qos = latched_qos() if info.latched else ()
                    if info.msgdef and info.digest:
                        conn = writer.add_connection(msg.topic, msg.msgtype, msgdef=info.msgdef, rihs01=info.digest,
                                                     offered_qos_profiles=qos)
                    else:
                        store = store or _typestore()
                        conn = writer.add_connection(msg.topic, msg.msgtype, typestore=store, offered_qos_profiles=qos)
                    connections[msg.topic] = conn
                writer.write(conn, msg.log_time_ns, msg.data)
                written += 1
    return dst
