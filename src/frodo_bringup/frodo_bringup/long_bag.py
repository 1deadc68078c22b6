"""Long inputs made from a short bag: its frames again and again, each copy's stamps shifted so that they keep
increasing (a plain loop would repeat stamps, which the nodes drop as duplicates).

- `repeat_bag` writes the copies to a new MCAP file (tests: a bag that plays for tens of seconds).
- `RepeatingPlayer` publishes them without ever holding more than the source bag in memory (soak runs:
  10,000 frames of the demo bag are 3.9 GB of CDR, far more than a Player, which keeps a bag's messages in
  memory, should hold).

Stamps are shifted in the CDR bytes themselves: every frame topic of the contract (and /slam/points) begins
with a std_msgs/Header, whose stamp (int32 sec, uint32 nanosec) follows the 4-byte encapsulation header.
`shift_stamp` checks the encapsulation and that the message starts with a Header (by type).
"""
from __future__ import annotations

import math
import os
import struct
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from frodo_bringup.player import Player, PlayerError
from frodo_common import topics
from frodo_common.bag import BagMessage, BagReader, BagWriter

# Message types whose first field is std_msgs/Header (their stamp can be shifted in place).
HEADER_FIRST = ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CameraInfo', 'sensor_msgs/msg/PointCloud2',
                'geometry_msgs/msg/PoseStamped', 'visualization_msgs/msg/MarkerArray')
_ENCAPSULATIONS = {b'\x00\x01': '<', b'\x00\x00': '>'}   # CDR little / big endian


def shift_stamp(message: BagMessage, delta_ns: int) -> BagMessage:
    """`message` with its log time and header stamp `delta_ns` later (CDR bytes patched, not re-encoded)."""
    if message.msgtype not in HEADER_FIRST:
        raise ValueError(f'{message.topic}: {message.msgtype} does not start with a std_msgs/Header; '
                         f'cannot shift its stamp (types that can: {", ".join(HEADER_FIRST)})')
    order = _ENCAPSULATIONS.get(bytes(message.data[:2]))
    if order is None:
        raise ValueError(f'{message.topic}: not plain CDR (encapsulation {bytes(message.data[:4]).hex()})')
    sec, nanosec = struct.unpack_from(f'{order}iI', message.data, 4)
    stamp = sec * 1_000_000_000 + nanosec + delta_ns
    data = bytearray(message.data)
    struct.pack_into(f'{order}iI', data, 4, stamp // 1_000_000_000, stamp % 1_000_000_000)
    return BagMessage(message.topic, message.msgtype, message.log_time_ns + delta_ns, bytes(data))


def copy_period_ns(messages: Sequence[BagMessage]) -> int:
    """Stamp shift between copies: the source's span plus its median image interval, so copies follow each
    other at the bag's own frame rate."""
    images = sorted(m.log_time_ns for m in messages if m.topic == topics.IMAGE)
    step = int(np.median(np.diff(images))) if len(images) > 1 else 100_000_000
    return messages[-1].log_time_ns - messages[0].log_time_ns + step


class RepeatedMessages(Sequence):
    """The messages of `base` (one copy, in log-time order) repeated until `frames` images, copy k shifted by
    k * `period_ns`; generated on access (nothing is copied up front)."""

    def __init__(self, base: Sequence[BagMessage], frames: int, period_ns: int | None = None):
        self.base = list(base)
        self.per_copy = sum(m.topic == topics.IMAGE for m in self.base)
        if not self.per_copy:
            raise PlayerError('the bag to repeat has no image on ' + topics.IMAGE)
        if frames < 1:
            raise PlayerError(f'frames must be >= 1, got {frames}')
        self.frames = int(frames)
        self.period_ns = int(period_ns if period_ns is not None else copy_period_ns(self.base))
        self.copies = math.ceil(self.frames / self.per_copy)
        # The last copy ends with its `last_images`-th image (and what shares that image's log time or precedes it).
        last_images = self.frames - (self.copies - 1) * self.per_copy
        image_times = [m.log_time_ns for m in self.base if m.topic == topics.IMAGE]
        self._last_end_ns = image_times[last_images - 1]
        self._last_count = sum(m.log_time_ns <= self._last_end_ns for m in self.base)

    def __len__(self) -> int:
        return (self.copies - 1) * len(self.base) + self._last_count

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(index)
        copy, i = divmod(index, len(self.base))
        return self._shifted(self.base[i], copy)

    def __iter__(self) -> Iterator[BagMessage]:
        for copy in range(self.copies):
            for message in self.base:
                if copy == self.copies - 1 and message.log_time_ns > self._last_end_ns:
                    return
                yield self._shifted(message, copy)

    def _shifted(self, message: BagMessage, copy: int) -> BagMessage:
        return message if copy == 0 else shift_stamp(message, copy * self.period_ns)


class RepeatingPlayer(Player):
    """A `Player` of `frames` images: the bag's messages (ground truth left out) repeated with shifted stamps
    (`RepeatedMessages`); same constructor as Player plus `frames`, so `run_bag(player_factory=...)` can use it."""

    def __init__(self, node, bag: str | os.PathLike, frames: int, **kwargs):
        if kwargs.get('loop'):
            raise PlayerError('RepeatingPlayer does not loop: it plays `frames` images')
        super().__init__(node, bag, **kwargs)
        for message in self._messages:   # fail before playing, not at copy 2
            if message.topic != topics.GROUND_TRUTH:
                shift_stamp(message, 0)
        self._messages = RepeatedMessages(self._messages, frames)


def repeat_bag(source: str | os.PathLike, path: str | os.PathLike, copies: int) -> Path:
    """Write the messages of `source` (ground truth left out) `copies` times in a row to `path`, copy k's stamps
    k * `copy_period_ns` later; returns `path`."""
    base = [m for m in BagReader(source).messages() if m.topic != topics.GROUND_TRUTH]
    repeated = RepeatedMessages(base, copies * sum(m.topic == topics.IMAGE for m in base))
    with BagWriter(path) as bag:
        for message in repeated:
            bag.write_raw(message.topic, message.msgtype, message.data, message.log_time_ns)
    return Path(path)
