"""`Player`: publish a contract bag (ROS 2 MCAP) on the live graph, in stamp order and at the bag's pace.

Messages are published as the stored CDR bytes (no decode), each topic with the QoS its publisher
offered when the bag was recorded (transient local for latched topics). A truncated or partly corrupt
bag plays every readable message; `problems` lists what was skipped.
"""
from __future__ import annotations

import os
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable, Iterable, Sequence

import yaml
from mcap.reader import make_reader
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from tqdm import tqdm

from frodo_common import topics
from frodo_common.bag import BagError, BagMessage, BagReader, message_class
from frodo_common.conversions import ns_to_stamp

# Contract inputs without which the graph does nothing: what `wait_for_subscribers` waits for by default.
REQUIRED_INPUTS = (topics.IMAGE, topics.CAMERA_INFO, topics.POSE)


class PlayerError(RuntimeError):
    """A bag cannot be played as asked (missing file, bad remap, unknown topic)."""


@dataclass
class PlayStats:
    """What one `Player.play()` did."""

    published: Counter = field(default_factory=Counter)  # {output topic: messages}
    loops: int = 0
    seconds: float = 0.0
    interrupted: bool = False
    paced_seconds: float = 0.0   # time held back by `Backpressure` (rate 0)
    pacing_abandoned: bool = False  # the graph stopped taking frames for `patience` s; played on unpaced

    @property
    def total(self) -> int:
        """Messages published over all topics."""
        return sum(self.published.values())


@dataclass
class Backpressure:
    """Flow control for rate 0: hold the next image while the graph has taken more than `max_backlog`
    fewer images than were sent.

    Why: at rate 0 a bag is published far faster than a loaded graph takes it; reliable KEEP_LAST
    queues (depth 100 on both ends) then overwrite frames nobody has read yet, and whole stretches of a
    bag never reach the optimiser. `frames_taken()` returns the image count of the slowest node (from
    its `/diagnostics` counters) or None when unknown (no pacing). If that count does not move for
    `patience` seconds (a node died or hangs), playback goes on unpaced and says so.
    """

    frames_taken: Callable[[], int | None]
    max_backlog: int = 30
    patience: float = 15.0


def parse_remaps(items: Iterable[str]) -> dict[str, str]:
    """{from: to} from `FROM:=TO` strings; raises PlayerError on bad syntax."""
    remaps: dict[str, str] = {}
    for item in items:
        source, sep, target = item.partition(':=')
        if not sep or not source.strip() or not target.strip() or ':=' in target:
            raise PlayerError(f'bad remap {item!r}: expected FROM:=TO, e.g. /camera/pose:=/robot/pose')
        remaps[_absolute(source.strip())] = _absolute(target.strip())
    return remaps


def _absolute(name: str) -> str:
    return name if name.startswith('/') else '/' + name


def qos_from_offered(text: str, topic: str) -> QoSProfile:
    """QoS for republishing a topic from its `offered_qos_profiles` YAML (rosbag2 string or int enums).

    Like `ros2 bag play`: reliable / transient local only when every recorded publisher offered it.
    """
    profiles = yaml.safe_load(text) or []
    if not profiles:
        return default_qos(topic)
    reliable = all(p.get('reliability') in ('reliable', 1) for p in profiles)
    latched = all(p.get('durability') in ('transient_local', 1) for p in profiles)
    depth = max(int(p.get('depth') or 0) for p in profiles) or 10
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def default_qos(topic: str) -> QoSProfile:
    """QoS when the bag records none (truncated file): latched for ground truth, frame QoS otherwise."""
    return topics.LATCHED_QOS if topic == topics.GROUND_TRUTH else topics.FRAME_QOS


def offered_qos_texts(reader: BagReader) -> dict[str, str]:
    """{topic: offered_qos_profiles YAML} from the rosbag2 metadata record, else the MCAP summary."""
    record = reader.metadata.get('rosbag2', {}).get('serialized_metadata')
    if record:
        info = yaml.safe_load(record).get('rosbag2_bagfile_information', {})
        return {t['topic_metadata']['name']: t['topic_metadata'].get('offered_qos_profiles', '')
                for t in info.get('topics_with_message_count', [])}
    try:
        with open(reader.path, 'rb') as f:
            summary = make_reader(f).get_summary()
    except Exception:  # noqa: BLE001 - damaged file: no summary, defaults apply
        return {}
    if summary is None:
        return {}
    return {c.topic: c.metadata.get('offered_qos_profiles', '') for c in summary.channels.values()}


class Player:
    """Publish a bag's messages on `node` with the original timing scaled by `rate` (0: as fast as possible).

    >>> player = Player(node, 'scene.mcap', rate=2.0)
    >>> player.wait_for_subscribers(timeout=10.0)   # nothing is lost at startup
    >>> stats = player.play()
    """

    def __init__(self, node: Node, bag: str | os.PathLike, rate: float = 1.0, start_offset: float = 0.0,
                 loop: bool = False, remaps: dict[str, str] | None = None, topics: Sequence[str] | None = None,
                 clock: bool = False, ground_truth: bool = False, progress: bool = True):
        if rate < 0:
            raise PlayerError(f'rate must be >= 0 (0 = as fast as possible), got {rate}')
        if start_offset < 0:
            raise PlayerError(f'start offset must be >= 0 s, got {start_offset}')
        try:
            self.reader = BagReader(bag)
        except BagError as err:
            raise PlayerError(str(err)) from None
        self.node = node
        self.rate = rate
        self.loop = loop
        self.progress = progress
        self.remaps = dict(remaps or {})
        self.problems: list[str] = []
        self._publishers: dict[str, Publisher] = {}
        self._backpressure: Backpressure | None = None
        self._images_sent = 0
        self._messages = self._select(topics, ground_truth, start_offset)
        self.problems += self.reader.problems
        if not self.reader.topics():
            raise PlayerError(f'{self.reader.path} has no readable messages'
                              + (f' ({"; ".join(self.reader.problems)})' if self.reader.problems else ''))
        self._clock_pub = node.create_publisher(Clock, '/clock', 10) if clock else None
        self._create_publishers()

    # ------------------------------------------------------------------ setup
    def _select(self, wanted: Sequence[str] | None, ground_truth: bool, start_offset: float) -> list[BagMessage]:
        available = self.reader.topics()
        if wanted is not None:
            wanted_set = {_absolute(t) for t in wanted}
            missing = sorted(wanted_set - set(available))
            if missing:
                raise PlayerError(f'topic(s) {", ".join(missing)} not in {self.reader.path.name}; '
                                  f'it has {", ".join(sorted(available)) or "no readable messages"}')
        else:
            wanted_set = {t for t in available if ground_truth or t != topics.GROUND_TRUTH}
        for source in self.remaps:
            if source not in available:
                self.problems.append(f'remap source {source} is not a topic of the bag')
        messages = list(self.reader.messages(wanted_set))
        if messages and start_offset > 0:
            first = messages[0].log_time_ns + int(start_offset * 1e9)
            messages = [m for m in messages if m.log_time_ns >= first]
        return messages

    def _create_publishers(self) -> None:
        qos_texts = offered_qos_texts(self.reader)
        for topic, (msgtype, _) in sorted(self.reader.topics().items()):
            if not any(m.topic == topic for m in self._messages):
                continue
            try:
                cls = message_class(msgtype)
            except BagError as err:
                self.problems.append(f'{topic}: {err}; its messages are skipped')
                continue
            text = qos_texts.get(topic)
            qos = qos_from_offered(text, topic) if text else default_qos(topic)
            self._publishers[topic] = self.node.create_publisher(cls, self.output_topic(topic), qos)
        self._messages = [m for m in self._messages if m.topic in self._publishers]

    # ------------------------------------------------------------------ queries
    def output_topic(self, topic: str) -> str:
        """The topic a bag topic is published on (after remapping)."""
        return self.remaps.get(topic, topic)

    @property
    def output_topics(self) -> list[str]:
        """Topics this player publishes on."""
        return [self.output_topic(t) for t in self._publishers]

    @property
    def message_count(self) -> int:
        """Messages one pass of `play()` publishes."""
        return len(self._messages)

    @property
    def duration(self) -> float:
        """Seconds of bag time one pass covers."""
        if not self._messages:
            return 0.0
        return (self._messages[-1].log_time_ns - self._messages[0].log_time_ns) / 1e9

    def unmatched_topics(self, wanted: Iterable[str] | None = None) -> list[str]:
        """Output topics not yet matched with every subscriber the graph shows, or with none while `wanted`.

        `wanted` defaults to the played required contract inputs (image, camera info, pose).
        """
        if wanted is None:
            wanted = [self.output_topic(t) for t in REQUIRED_INPUTS if t in self._publishers]
        wanted = set(wanted)
        unmatched = []
        for topic, publisher in self._publishers.items():
            output = self.output_topic(topic)
            matched = publisher.get_subscription_count()
            if matched < self.node.count_subscribers(output) or (output in wanted and matched == 0):
                unmatched.append(output)
        return unmatched

    def wait_for_subscribers(self, timeout: float, wanted: Iterable[str] | None = None,
                             stop: threading.Event | None = None, settle: float = 0.0) -> list[str]:
        """Wait until `unmatched_topics(wanted)` is empty (nothing is lost at startup); returns what is left.

        With `settle` > 0, the match counts must also stay unchanged for `settle` seconds: discovery reports
        the subscriptions of one node one by one, so a first full match may still miss some of them.
        """
        wanted = list(wanted) if wanted is not None else None
        deadline = time.monotonic() + timeout
        stop = stop or threading.Event()
        counts, since = None, time.monotonic()
        while True:
            unmatched = self.unmatched_topics(wanted)
            now = time.monotonic()
            current = {t: p.get_subscription_count() for t, p in self._publishers.items()}
            if unmatched or current != counts:
                counts, since = current, now
            if (not unmatched and now - since >= settle) or now >= deadline or stop.is_set():
                return unmatched
            stop.wait(0.05)

    def missing_required(self) -> list[str]:
        """Required contract inputs (REQUIRED_INPUTS) the bag has no readable message on."""
        return self.reader.missing_topics(REQUIRED_INPUTS)

    def played_topics(self, candidates: Iterable[str]) -> list[str]:
        """The output names of those `candidates` (bag topic names) this player publishes."""
        return [self.output_topic(t) for t in candidates if t in self._publishers]

    # ------------------------------------------------------------------ playback
    def play(self, stop: threading.Event | None = None, backpressure: Backpressure | None = None) -> PlayStats:
        """Publish every selected message (again and again with `loop`) until done or `stop` is set;
        at rate 0 with `backpressure`, no faster than the graph takes the images."""
        stop = stop or threading.Event()
        stats = PlayStats()
        self._backpressure = backpressure if self.rate == 0 else None
        self._images_sent = 0
        started = time.monotonic()
        with tqdm(total=None if self.loop else self.message_count, unit='msg', file=sys.stderr,
                  desc=self.reader.path.name, disable=not self.progress, dynamic_ncols=True) as bar:
            while not stop.is_set():
                self._play_once(stop, stats, bar)
                if stop.is_set():
                    break
                stats.loops += 1
                if not self.loop or not self._messages:
                    break
        stats.interrupted = stop.is_set()
        self._flush()
        stats.seconds = time.monotonic() - started
        return stats

    def _play_once(self, stop: threading.Event, stats: PlayStats, bar: tqdm) -> None:
        if not self._messages:
            return
        first_ns = self._messages[0].log_time_ns
        wall_start = time.monotonic()
        last_clock_ns = -1
        for message in self._messages:
            if self.rate > 0:
                due = wall_start + (message.log_time_ns - first_ns) / 1e9 / self.rate
                delay = due - time.monotonic()
                if delay > 0 and stop.wait(delay):
                    return
            elif stop.is_set():
                return
            if message.topic == topics.IMAGE and self._backpressure is not None:
                self._wait_for_graph(stop, stats)
                self._images_sent += 1
            if self._clock_pub is not None and message.log_time_ns > last_clock_ns:
                self._clock_pub.publish(Clock(clock=ns_to_stamp(message.log_time_ns)))
                last_clock_ns = message.log_time_ns
            self._publishers[message.topic].publish(message.data)
            stats.published[self.output_topic(message.topic)] += 1
            bar.update(1)

    def _wait_for_graph(self, stop: threading.Event, stats: PlayStats) -> None:
        """Block while the graph is more than `max_backlog` images behind (see `Backpressure`)."""
        pressure = self._backpressure
        started = last_change = time.monotonic()
        last_taken = None
        while not stop.is_set():
            taken = pressure.frames_taken()
            if taken is None or self._images_sent - taken <= pressure.max_backlog:
                break
            now = time.monotonic()
            if taken != last_taken:
                last_taken, last_change = taken, now
            elif now - last_change > pressure.patience:
                stats.pacing_abandoned = True
                self._backpressure = None
                self.problems.append(f'the graph took no image for {pressure.patience:.0f} s at image '
                                     f'{self._images_sent}; playing the rest unpaced (frames may be lost)')
                break
            stop.wait(0.02)
        stats.paced_seconds += time.monotonic() - started

    def _flush(self, timeout: float = 2.0) -> None:
        """Wait (bounded) until reliable subscribers acknowledged what was sent."""
        for publisher in self._publishers.values():
            publisher.wait_for_all_acked(Duration(seconds=timeout))

    def close(self) -> None:
        """Destroy the publishers (the node stays)."""
        for publisher in self._publishers.values():
            self.node.destroy_publisher(publisher)
        if self._clock_pub is not None:
            self.node.destroy_publisher(self._clock_pub)
        self._publishers.clear()
