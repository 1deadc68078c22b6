"""Stamp-matched frame cache: collects the messages of one frame (same header stamp) with bounded memory."""
from __future__ import annotations

import time
from collections import Counter, OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any, Iterable


@dataclass
class Frame:
    """Everything received for one stamp, keyed by part name ('image', 'pose', 'detections', ...)."""

    stamp_ns: int
    parts: dict[str, Any] = field(default_factory=dict)
    received: float = field(default_factory=time.monotonic)   # wall clock of its first part

    def has(self, names: Iterable[str]) -> bool:
        """True when every named part is present."""
        return all(n in self.parts for n in names)


class CompletedStamps:
    """The stamps of completed frames, bounded: the newest `capacity` are held; an older stamp counts as
    completed when it is not newer than the newest one forgotten (`watermark`).

    Why: nodes pop a frame from the cache as soon as it is processed but keep its stamp marked complete (a
    re-send for it is then recognised, and a late part does not start a frame again); one stamp per frame
    for ever grew without bound on long runs. Stamps more than `capacity` frames old are answered by the
    watermark: a part that old is too late to complete a frame anyway.
    """

    def __init__(self, capacity: int):
        self.capacity = max(1, int(capacity))
        self._stamps: set[int] = set()
        self._order: deque[int] = deque()
        self.watermark: int | None = None

    def add(self, stamp: int) -> None:
        if stamp in self._stamps:
            return
        self._stamps.add(stamp)
        self._order.append(stamp)
        while len(self._order) > self.capacity:
            old = self._order.popleft()
            if old in self._stamps:
                self._stamps.discard(old)
                self.watermark = old if self.watermark is None else max(self.watermark, old)

    def discard(self, stamp: int) -> None:
        self._stamps.discard(stamp)   # its place in _order goes when it reaches the front

    def __contains__(self, stamp: int) -> bool:
        return stamp in self._stamps or (self.watermark is not None and stamp <= self.watermark)

    def __len__(self) -> int:
        return len(self._stamps)


class FrameCache:
    """Frames by stamp, oldest evicted first once more than `capacity` are held.

    `add` returns the frame when it becomes complete for `required` parts (exactly once per stamp),
    so a node processes a frame as soon as its last part arrives, whatever the arrival order.
    Camera info is not per frame: it is held as the latest value (`camera_info`).

    What never completes is accounted for, so a node can say what it missed (a node started late, a
    silent upstream topic): frames evicted incomplete (`evicted_incomplete`, their missing parts in
    `missing_parts`) and, via `missed()`, frames still held incomplete although newer stamps have
    arrived `stale_after_ns` later and the frame has waited `stale_after_s` of wall-clock time (a bag
    played as fast as possible spans seconds of stamps in a fraction of a second, so stamps alone would
    call a part that is merely queued "missed"). A part received twice for one stamp counts in
    `duplicates`.
    """

    def __init__(self, required: Iterable[str], capacity: int = 400, stale_after_ns: int = 2_000_000_000,
                 stale_after_s: float = 5.0, completed_capacity: int | None = None):
        self.required = tuple(required)
        self.capacity = int(capacity)
        self.stale_after_ns = int(stale_after_ns)
        self.stale_after_s = float(stale_after_s)
        self.frames: OrderedDict[int, Frame] = OrderedDict()
        # Completed stamps remembered (default 10 x capacity; `CompletedStamps`): bounded on long runs.
        self.completed = CompletedStamps(completed_capacity if completed_capacity is not None else 10 * self.capacity)
        self.evicted_incomplete = 0
        self.missing_parts: Counter[str] = Counter()
        self.duplicates = 0
        self.newest_ns: int | None = None
        self.camera_info = None

    def add(self, stamp_ns: int, name: str, value: Any) -> Frame | None:
        """Store a part; return the frame if this part completed it, else None."""
        self.newest_ns = stamp_ns if self.newest_ns is None else max(self.newest_ns, stamp_ns)
        frame = self.frames.get(stamp_ns)
        if frame is None:
            frame = self.frames[stamp_ns] = Frame(stamp_ns)
            self._evict()
        elif name in frame.parts:
            self.duplicates += 1
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

    def missed(self) -> tuple[int, Counter]:
        """(frames that never completed, {part: how many of them lack it}): evicted incomplete ones plus
        held incomplete ones older than the newest stamp by more than `stale_after_ns` and held for
        `stale_after_s` seconds."""
        parts = Counter(self.missing_parts)
        count = self.evicted_incomplete
        if self.newest_ns is not None:
            limit = self.newest_ns - self.stale_after_ns
            waited_since = time.monotonic() - self.stale_after_s
            for stamp, frame in list(self.frames.items()):
                if stamp < limit and stamp not in self.completed and frame.received <= waited_since:
                    count += 1
                    parts.update(n for n in self.required if n not in frame.parts)
        return count, parts

    def _evict(self) -> None:
        while len(self.frames) > self.capacity:
            stamp, frame = self.frames.popitem(last=False)
            if stamp not in self.completed:
                self.evicted_incomplete += 1
                self.missing_parts.update(n for n in self.required if n not in frame.parts)
            self.completed.discard(stamp)

    def __len__(self) -> int:
        return len(self.frames)
