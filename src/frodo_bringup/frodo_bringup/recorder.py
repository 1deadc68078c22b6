"""`Recorder`: record live topics into a rosbag2-compatible MCAP file (CONTRACT.md "Bags").

Topics are discovered from the graph (types from `get_topic_names_and_types`), subscribed raw (CDR
bytes, no decode) with a QoS compatible with every publisher, and written with the publishers'
offered QoS as channel metadata. Log time = the message's header stamp when it has one, else the
receive time.
"""
from __future__ import annotations

import os
import struct
import threading
from collections import Counter
from typing import Sequence

import yaml
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.topic_endpoint_info import TopicEndpointInfo

from frodo_common.bag import BagError, BagWriter, message_class, qos_yaml

# Infrastructure topics left out of `--all` (name them explicitly to record them).
INFRASTRUCTURE_TOPICS = ('/rosout', '/parameter_events')
SUBSCRIPTION_DEPTH = 1000


def has_header(msg_class) -> bool:
    """True when a message type starts with a std_msgs/Header (so its CDR bytes begin with the stamp)."""
    field_types = list(msg_class.get_fields_and_field_types().values())
    return bool(field_types) and field_types[0] == 'std_msgs/Header'


def header_stamp_ns(data: bytes) -> int | None:
    """header.stamp in ns from the CDR bytes of a message that starts with a Header; None when unset."""
    if len(data) < 12:
        return None
    little_endian = data[1] & 1
    sec, nanosec = struct.unpack('<iI' if little_endian else '>iI', data[4:12])
    stamp = sec * 1_000_000_000 + nanosec
    return stamp if stamp > 0 else None


def offered_qos_text(infos: Sequence[TopicEndpointInfo]) -> str:
    """`offered_qos_profiles` YAML listing every publisher's QoS (what rosbag2 stores per channel)."""
    profiles = []
    for info in infos:
        qos = info.qos_profile
        latched = qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
        depth = qos.depth if qos.depth > 0 else (1 if latched else 100)
        profiles += yaml.safe_load(qos_yaml(reliable=qos.reliability == ReliabilityPolicy.RELIABLE,
                                            transient_local=latched, depth=depth))
    return yaml.safe_dump(profiles, sort_keys=False)


def subscription_qos(infos: Sequence[TopicEndpointInfo]) -> QoSProfile:
    """A QoS that matches every publisher: reliable / transient local only when all of them offer it."""
    reliable = bool(infos) and all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
    latched = bool(infos) and all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
    return QoSProfile(depth=SUBSCRIPTION_DEPTH, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


class Recorder:
    """Subscribe to the wanted topics of the live graph as they appear and write them to `path`.

    >>> recorder = Recorder(node, 'out.mcap', ['/camera/pose'])   # or all_topics=True
    >>> executor.spin_until_future_complete(...)                  # messages are written as they arrive
    >>> recorder.close()                                           # finalises the MCAP file
    """

    def __init__(self, node: Node, path: str | os.PathLike, topics: Sequence[str] = (),
                 all_topics: bool = False, discovery_period: float = 0.25):
        if not topics and not all_topics:
            raise BagError('nothing to record: name topics or use --all')
        self.node = node
        self.wanted = {t if t.startswith('/') else '/' + t for t in topics}
        self.all_topics = all_topics
        self.counts: Counter[str] = Counter()
        self.problems: list[str] = []
        self._writer = BagWriter(path)
        self._subscriptions: dict[str, object] = {}
        self._lock = threading.Lock()
        self._closed = False
        self.discover()
        self._timer = node.create_timer(discovery_period, self.discover)

    @property
    def path(self):
        """The MCAP file being written."""
        return self._writer.path

    @property
    def recorded_topics(self) -> list[str]:
        """Topics subscribed so far."""
        return sorted(self._subscriptions)

    def subscription(self, topic: str):
        """The recorder's subscription of `topic` (None when not subscribed or its type is unknown)."""
        return self._subscriptions.get(topic)

    def _is_wanted(self, topic: str) -> bool:
        if topic in self.wanted:
            return True
        return self.all_topics and topic not in INFRASTRUCTURE_TOPICS

    def discover(self) -> None:
        """Subscribe to wanted topics that have appeared (with at least one publisher) since the last call."""
        for topic, types in self.node.get_topic_names_and_types():
            if topic in self._subscriptions or not self._is_wanted(topic):
                continue
            publishers = self.node.get_publishers_info_by_topic(topic)
            if publishers:
                self._subscribe(topic, types[0], publishers)

    def _subscribe(self, topic: str, msgtype: str, publishers: Sequence[TopicEndpointInfo]) -> None:
        try:
            cls = message_class(msgtype)
        except BagError as err:
            self.problems.append(f'{topic}: {err}; not recorded')
            self._subscriptions[topic] = None
            return
        with self._lock:
            if self._closed:
                return
            self._writer.add_topic(topic, msgtype, offered_qos_text(publishers))
        stamped = has_header(cls)
        self._subscriptions[topic] = self.node.create_subscription(
            cls, topic, lambda data: self._write(topic, msgtype, stamped, data), subscription_qos(publishers),
            raw=True)
        self.node.get_logger().info(f'recording {topic} ({msgtype})')

    def _write(self, topic: str, msgtype: str, stamped: bool, data: bytes) -> None:
        log_time = header_stamp_ns(data) if stamped else None
        if log_time is None:
            log_time = self.node.get_clock().now().nanoseconds
        with self._lock:
            if self._closed:
                return
            self._writer.write_raw(topic, msgtype, data, log_time)
            self.counts[topic] += 1

    def close(self) -> None:
        """Stop recording and finalise the file (summary and rosbag2 metadata); idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._writer.close()
        self.node.destroy_timer(self._timer)
        for subscription in self._subscriptions.values():
            if subscription is not None:
                self.node.destroy_subscription(subscription)
