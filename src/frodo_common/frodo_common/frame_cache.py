"""Stamp-matched frame cache: collects the messages of one frame (same header stamp) with bounded memory."""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Iterable


@dataclass
class Frame:
    """Everything received for one stamp, keyed by part name ('image', 'pose', 'detections', ...)."""

    stamp_ns: int
    parts: dict[str, Any] = field(default_factory=dict)

    def has(self, names: Iterable[str]) -> bool:
        """True when every named part is present."""
        return all(n in self.parts for n in names)


class FrameCache:
    """Frames by stamp, oldest evicted first once more than `capacity` are held.

    `add` returns the frame when it becomes complete for `required` parts (exactly once per stamp),
    so a node processes a frame as soon as its last part arrives, whatever the arrival order.
    Camera info is not per frame: it is held as the latest value (`camera_info`).
    """

    def __init__(self, required: Iterable[str], capacity: int = 400):
        self.required = tuple(required)
        self.capacity = int(capacity)
        self.frames: OrderedDict[int, Frame] = OrderedDict()
        self.completed: set[int] = set()
        self.evicted_incomplete = 0
        self.camera_info = None

    def add(self, stamp_ns: int, name: str, value: Any) -> Frame | None:
        """Store a part; return the frame if this part completed it, else None."""
        frame = self.frames.get(stamp_ns)
        if frame is None:
            frame = self.frames[stamp_ns] = Frame(stamp_ns)
            self._evict()
        frame.parts[name] = value
        if stamp_ns not in self.completed and frame.has(self.required):
            self.completed.add(stamp_ns)
            return frame
        return None

    def get(self, stamp_ns: int) -> Frame | None:
        """The frame for a stamp, if still held."""
        return self.frames.get(stamp_ns)

    def complete_frames(self) -> list[Frame]:
        """Held frames that have every required part, oldest first."""
        return [f for s, f in self.frames.items() if s in self.completed]

    def _evict(self) -> None:
        while len(self.frames) > self.capacity:
            stamp, _ = self.frames.popitem(last=False)
            if stamp not in self.completed:
                self.evicted_incomplete += 1
            self.completed.discard(stamp)

    def __len__(self) -> int:
        return len(self.frames)
