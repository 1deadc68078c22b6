"""rosbag2-compatible MCAP files: writer and tolerant reader (CONTRACT.md "Bags").

Written files follow what rosbag2's MCAP plugin writes: profile `ros2`, `ros2msg` schemas named
`pkg/msg/Type`, `cdr` channels with `offered_qos_profiles` metadata, log time = header stamp, and the
`rosbag2` metadata record (`serialized_metadata`, bag metadata version 9). Messages are serialised with
rclpy's own CDR type support; schema texts come from the rosbags Jazzy type store.
"""
from __future__ import annotations

import importlib
import os
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Iterable, Iterator

import yaml
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from rclpy.serialization import deserialize_message, serialize_message

from frodo_common import topics

# rosbag2 writes "infinite" durations as this (sec, nsec) pair.
_INFINITE = {'sec': 9223372036, 'nsec': 854775807}


class BagError(RuntimeError):
    """A bag cannot be opened or written."""


def qos_yaml(reliable: bool = True, transient_local: bool = False, depth: int = 100) -> str:
    """`offered_qos_profiles` YAML (metadata version 9 string enums) for one publisher."""
    profile = {
        'history': 'keep_last', 'depth': int(depth),
        'reliability': 'reliable' if reliable else 'best_effort',
        'durability': 'transient_local' if transient_local else 'volatile',
        'deadline': dict(_INFINITE), 'lifespan': dict(_INFINITE), 'liveliness': 'automatic',
        'liveliness_lease_duration': dict(_INFINITE), 'avoid_ros_namespace_conventions': False,
    }
    return yaml.safe_dump([profile], sort_keys=False)


def type_name(msg: Any) -> str:
    """`pkg/msg/Type` of a ROS message instance."""
    module = type(msg).__module__.split('.')
    return f'{module[0]}/msg/{type(msg).__name__}'


def message_class(name: str):
    """Message class for `pkg/msg/Type` (or `pkg/Type`); raises BagError when not installed."""
    parts = name.split('/')
    if len(parts) not in (2, 3):
        raise BagError(f'bad message type name {name!r}')
    try:
        return getattr(importlib.import_module(f'{parts[0]}.msg'), parts[-1])
    except (ImportError, AttributeError):
        raise BagError(f'message type {name} is not installed') from None


def schema_text(name: str) -> str:
    """Concatenated `ros2msg` definition of a type and its dependencies."""
    from rosbags.typesys import Stores, get_typestore
    text, _ = get_typestore(Stores.ROS2_JAZZY).generate_msgdef(name, ros_version=2)
    return text


class BagWriter:
    """Write ROS 2 messages to a rosbag2-compatible MCAP file.

    >>> with BagWriter('out.mcap') as bag:
    ...     bag.write('/camera/pose', pose_msg, stamp_ns)
    """

    def __init__(self, path: str | os.PathLike, compression: str = 'zstd', chunk_size: int = 1 << 20):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: BinaryIO = open(self.path, 'wb')
        comp = {'zstd': CompressionType.ZSTD, 'lz4': CompressionType.LZ4, 'none': CompressionType.NONE}[compression]
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp)
        self._writer.start(profile='ros2', library='frodo_common.bag')
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str, str]] = {}
        self._counts: dict[str, int] = {}
        self._first_ns: int | None = None
        self._last_ns = 0
        self._closed = False

    def add_topic(self, topic: str, msgtype: str, qos: str | None = None) -> None:
        """Register a topic (done automatically on first write with default reliable/volatile QoS)."""
        if topic in self._channels:
            return
        if msgtype not in self._schemas:
            self._schemas[msgtype] = self._writer.register_schema(msgtype, 'ros2msg', schema_text(msgtype).encode())
        qos = qos if qos is not None else qos_yaml()
        cid = self._writer.register_channel(topic, 'cdr', self._schemas[msgtype], {'offered_qos_profiles': qos})
        self._channels[topic] = (cid, msgtype, qos)
        self._counts[topic] = 0

    def write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        """Serialise and write one message with log time = publish time = stamp_ns."""
        self.write_raw(topic, type_name(msg), serialize_message(msg), stamp_ns)

    def write_raw(self, topic: str, msgtype: str, data: bytes, stamp_ns: int) -> None:
        """Write already CDR-serialised bytes."""
        self.add_topic(topic, msgtype)
        cid, registered, _ = self._channels[topic]
        if registered != msgtype:
            raise BagError(f'topic {topic} has type {registered}, cannot write {msgtype}')
        self._writer.add_message(cid, log_time=int(stamp_ns), data=data, publish_time=int(stamp_ns),
                                 sequence=self._counts[topic])
        self._counts[topic] += 1
        self._first_ns = stamp_ns if self._first_ns is None else min(self._first_ns, stamp_ns)
        self._last_ns = max(self._last_ns, stamp_ns)

    def _metadata(self) -> str:
        start = self._first_ns or 0
        duration = self._last_ns - start if self._first_ns is not None else 0
        total = sum(self._counts.values())
        info = {
            'version': 9, 'storage_identifier': 'mcap',
            'duration': {'nanoseconds': duration}, 'starting_time': {'nanoseconds_since_epoch': start},
            'message_count': total,
            'topics_with_message_count': [
                {'topic_metadata': {'name': topic, 'type': msgtype, 'serialization_format': 'cdr',
                                    'offered_qos_profiles': qos, 'type_description_hash': ''},
                 'message_count': self._counts[topic]}
                for topic, (_, msgtype, qos) in self._channels.items()],
            'compression_format': '', 'compression_mode': '',
            'relative_file_paths': [self.path.name],
            'files': [{'path': self.path.name, 'starting_time': {'nanoseconds_since_epoch': start},
                       'duration': {'nanoseconds': duration}, 'message_count': total}],
            'custom_data': {}, 'ros_distro': 'jazzy',
        }
        return yaml.safe_dump({'rosbag2_bagfile_information': info}, sort_keys=False)

    def close(self) -> None:
        """Write the rosbag2 metadata record and the MCAP summary; idempotent."""
        if self._closed:
            return
        self._writer.add_metadata('rosbag2', {'serialized_metadata': self._metadata(), 'ROS_DISTRO': 'jazzy'})
        self._writer.finish()
        self._file.close()
        self._closed = True

    def __enter__(self) -> 'BagWriter':
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class BagMessage:
    """One message as stored: topic, type name, log time (ns) and CDR bytes."""

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes

    def decode(self) -> Any:
        """Deserialise into the rclpy message class."""
        return deserialize_message(self.data, message_class(self.msgtype))


# Contract per-frame input topics: one message per stamp, so a repeated stamp there is a duplicate.
FRAME_TOPICS = (topics.IMAGE, topics.CAMERA_INFO, topics.POSE, topics.INSTANCES, topics.DEPTH)
# The first bytes of every MCAP file, and of the other formats users most often pass by mistake.
MCAP_MAGIC = b'\x89MCAP0\r\n'
_OTHER_FORMATS = ((b'SQLite format 3\x00', 'a rosbag2 SQLite (.db3) bag; convert it to MCAP first, e.g. '
                   '`ros2 bag convert` or `rosbags-convert --dst-storage mcap`'),
                  (b'#ROSBAG V2.0', 'a ROS 1 bag; convert it to a ROS 2 MCAP first, e.g. `rosbags-convert`'))


def _open_error(path: Path, head: bytes) -> str | None:
    """Why `path` (whose first bytes are `head`) is not an MCAP file, or None when it starts like one."""
    if head.startswith(MCAP_MAGIC):
        return None
    for magic, what in _OTHER_FORMATS:
        if head.startswith(magic):
            return f'{path} is {what}'
    if not head:
        return f'{path} is empty (expected a ROS 2 .mcap bag)'
    return f'{path} is not an MCAP file (it starts with {head[:8]!r}, not {MCAP_MAGIC!r}); expected a ROS 2 .mcap bag'


def resolve_bag_path(path: str | os.PathLike) -> Path:
    """The .mcap file of `path`: the file itself, or the single .mcap in a rosbag2 bag directory."""
    path = Path(path)
    if path.is_dir():
        files = sorted(path.glob('*.mcap'))
        if len(files) != 1:
            raise BagError(f'{path} is a directory with {len(files)} .mcap files; pass the .mcap file to play')
        return files[0]
    if not path.is_file():
        raise BagError(f'bag not found: {path} (expected a ROS 2 .mcap file)')
    return path


class BagReader:
    """Tolerant reader of ROS 2 MCAP files.

    Opening checks at once that the file is an MCAP with the `ros2` profile (BagError otherwise: not an
    MCAP, a .db3 or ROS 1 bag, another profile). Reading streams the records: a chunk whose CRC or
    compression is damaged is skipped and reading goes on with the next one; damaged record framing or a
    truncated file ends the scan, keeping every message before it. Messages on channels that are not
    cdr/ros2msg are skipped. On the contract's per-frame topics (`FRAME_TOPICS`) a second message with the
    same stamp is dropped as a duplicate. Messages are sorted by log time (files written out of order
    still play in stamp order). Everything skipped, dropped or reordered is listed in `problems`.
    """

    def __init__(self, path: str | os.PathLike, unique_stamp_topics: Iterable[str] = FRAME_TOPICS):
        self.path = resolve_bag_path(path)
        self.unique_stamp_topics = frozenset(unique_stamp_topics)
        self.problems: list[str] = []
        self.profile: str | None = None
        self.metadata: dict[str, dict[str, str]] = {}
        self._messages: list[BagMessage] | None = None
        self._check_header()

    def _check_header(self) -> None:
        """Raise BagError unless the file starts with the MCAP magic and a Header record of profile ros2."""
        from mcap.records import Header
        with open(self.path, 'rb') as f:
            error = _open_error(self.path, f.read(16))
            if error is not None:
                raise BagError(error)
            f.seek(0)
            try:
                header = next(iter(StreamReader(f, skip_magic=False).records))
            except Exception as err:  # noqa: BLE001 - any parse failure of the first record
                raise BagError(f'{self.path}: damaged MCAP header ({type(err).__name__}: {err})') from None
        if not isinstance(header, Header):
            raise BagError(f'{self.path}: the MCAP file does not start with a Header record')
        self.profile = header.profile
        if header.profile not in ('ros2', ''):
            raise BagError(f'{self.path}: MCAP profile is {header.profile!r}, not "ros2": not a ROS 2 bag '
                           '(messages must be CDR with ros2msg schemas)')
        if header.profile == '':
            self.problems.append('MCAP profile is empty (expected "ros2"); reading cdr channels anyway')

    def _scan(self) -> list[BagMessage]:
        from mcap.records import Chunk, Metadata
        from mcap.stream_reader import breakup_chunk
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        out: list[BagMessage] = []
        skipped: Counter[str] = Counter()
        damaged_chunks = 0

        def take(record) -> None:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Metadata):
                self.metadata[record.name] = dict(record.metadata)
            elif isinstance(record, Message):
                channel = channels.get(record.channel_id)
                schema = schemas.get(channel.schema_id) if channel is not None else None
                if channel is None:
                    skipped[f'channel {record.channel_id} (not defined)'] += 1
                elif channel.message_encoding != 'cdr' or schema is None or schema.encoding != 'ros2msg':
                    skipped[f'{channel.topic} (encoding {channel.message_encoding!r}, schema '
                            f'{schema.encoding if schema is not None else None!r}; expected cdr/ros2msg)'] += 1
                else:
                    out.append(BagMessage(channel.topic, schema.name, record.log_time, record.data))

        with open(self.path, 'rb') as f:
            try:
                for record in StreamReader(f, skip_magic=False, emit_chunks=True).records:
                    if isinstance(record, Chunk):
                        try:
                            inner = breakup_chunk(record, validate_crc=True)
                        except Exception:  # noqa: BLE001 - a damaged chunk is skipped, the next one is read
                            damaged_chunks += 1
                            continue
                        for sub in inner:
                            take(sub)
                    else:
                        take(record)
            except Exception as err:  # noqa: BLE001 - damaged framing ends the scan, kept messages stay
                self.problems.append(f'stopped reading at damaged data ({type(err).__name__}: {err}); '
                                     f'{len(out)} messages before it were kept')
        if damaged_chunks:
            self.problems.append(f'{damaged_chunks} damaged chunk(s) skipped (CRC or compression error); '
                                 'the messages in them are lost, the rest was read')
        for what, n in sorted(skipped.items()):
            self.problems.append(f'{n} message(s) on {what} skipped')
        return self._order(out)

    def _order(self, messages: list[BagMessage]) -> list[BagMessage]:
        """Sort by log time (stable), drop repeated stamps on per-frame topics; report both."""
        out_of_order = sum(1 for a, b in zip(messages, messages[1:]) if b.log_time_ns < a.log_time_ns)
        if out_of_order:
            self.problems.append(f'{out_of_order} message(s) stored out of log-time order; played in stamp order')
        messages.sort(key=lambda m: m.log_time_ns)
        seen: set[tuple[str, int]] = set()
        kept: list[BagMessage] = []
        duplicates: Counter[str] = Counter()
        for m in messages:
            if m.topic in self.unique_stamp_topics:
                key = (m.topic, m.log_time_ns)
                if key in seen:
                    duplicates[m.topic] += 1
                    continue
                seen.add(key)
            kept.append(m)
        for topic, n in sorted(duplicates.items()):
            self.problems.append(f'{topic}: {n} message(s) with an already seen stamp dropped (duplicates)')
        return kept

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
        """Messages in log-time order, optionally only of some topics."""
        if self._messages is None:
            self._messages = self._scan()
        wanted = set(topics) if topics is not None else None
        return (m for m in self._messages if wanted is None or m.topic in wanted)

    def topics(self) -> dict[str, tuple[str, int]]:
        """{topic: (type, message count)} of the readable messages."""
        out: dict[str, tuple[str, int]] = {}
        for m in self.messages():
            out[m.topic] = (m.msgtype, out.get(m.topic, (m.msgtype, 0))[1] + 1)
        return out

    def missing_topics(self, required: Iterable[str]) -> list[str]:
        """Those `required` topics without a single readable message."""
        available = self.topics()
        return [t for t in required if t not in available]
