"""Breadth-first order of the optimiser's work (issue 28): every object gets its fused mesh before any object
gets a sparse stage, every sparse stage comes before any dense stage, and among objects at the same stage an
object's first run of it goes before re-runs (new input for an object refined already), then the one seen first
goes first: what a robot saw first is refined first, and an object whose code changes with every frame does not
keep the others from their first mesh. Pure Python, no ROS.

A job is (object, stage). `request(oid)` (new input for the object: its box or code changed) starts its
pipeline again from the fused stage; `advance(oid, stage)` queues the stage after one that ended; a dense
stage that should wait until nothing else does is `defer`red and comes back when the queue is otherwise
empty (then it runs whatever its re-run rule says: `pop` marks it forced).
"""
from __future__ import annotations

from dataclasses import dataclass

STAGES = ('fused', 'sparse', 'dense')
RANK = {name: i for i, name in enumerate(STAGES)}


@dataclass(frozen=True)
class Job:
    """One stage of one object; forced: a deferred dense stage that runs now because nothing else waits."""

    object_id: int
    stage: str
    forced: bool = False


class StageQueue:
    """Jobs by (stage, first seen); at most one queued stage per object (the earliest asked for)."""

    def __init__(self) -> None:
        self._queued: dict[int, str] = {}        # object -> next stage to run
        self._deferred: set[int] = set()         # objects whose dense stage waits for an empty queue
        self._first_seen: dict[int, int] = {}    # object -> order of its first request
        self._completed: dict[int, set[str]] = {}  # object -> stages it has finished at least once
        self._seen = 0

    def _order(self, object_id: int) -> int:
        if object_id not in self._first_seen:
            self._first_seen[object_id] = self._seen
            self._seen += 1
        return self._first_seen[object_id]

    def request(self, object_id: int, stage: str = 'fused') -> None:
        """Queue the object from `stage` on (its inputs changed); an earlier stage already queued stays."""
        self._order(object_id)
        self._deferred.discard(object_id)
        current = self._queued.get(object_id)
        if current is None or RANK[stage] < RANK[current]:
            self._queued[object_id] = stage

    def advance(self, object_id: int, finished: str) -> None:
        """Queue the stage after `finished`, unless the object was re-requested meanwhile (its queued stage is then
        at or before this one) or `finished` was the last stage."""
        self._completed.setdefault(object_id, set()).add(finished)
        following = RANK[finished] + 1
        if following < len(STAGES) and object_id not in self._queued:
            self._queued[object_id] = STAGES[following]

    def defer(self, object_id: int) -> None:
        """Hold the object's dense stage until nothing else waits."""
        if object_id not in self._queued:
            self._deferred.add(object_id)

    def discard(self, object_id: int) -> None:
        """Forget the object's queued work (its track is gone)."""
        self._queued.pop(object_id, None)
        self._deferred.discard(object_id)
        self._completed.pop(object_id, None)

    def pop(self) -> Job | None:
        """The next job: the earliest stage first, then an object's first run of that stage before re-runs, then
        the object seen first; a deferred dense stage (forced) only when nothing else is queued; None when there
        is no work."""
        if self._queued:
            object_id = min(self._queued, key=lambda oid: (RANK[self._queued[oid]],
                                                           self._queued[oid] in self._completed.get(oid, ()),
                                                           self._first_seen[oid]))
            return Job(object_id, self._queued.pop(object_id))
        if self._deferred:
            object_id = min(self._deferred, key=self._first_seen.__getitem__)
            self._deferred.discard(object_id)
            return Job(object_id, 'dense', forced=True)
        return None

    def waiting_before(self, stage: str) -> bool:
        """Whether a job of an earlier stage than `stage` is queued (a running `stage` job should yield to it)."""
        return any(RANK[s] < RANK[stage] for s in self._queued.values())

    def waiting(self) -> dict[str, int]:
        """Objects waiting per stage (deferred dense stages counted under 'dense')."""
        counts = {name: 0 for name in STAGES}
        for stage in self._queued.values():
            counts[stage] += 1
        counts['dense'] += len(self._deferred - set(self._queued))
        return counts

    def queued(self, stage: str) -> list[int]:
        """The objects whose next queued stage is `stage` (deferred dense stages not included)."""
        return [oid for oid, s in self._queued.items() if s == stage]

    def objects(self) -> set[int]:
        """Every object with queued or deferred work."""
        return set(self._queued) | self._deferred

    def __len__(self) -> int:
        return len(self.objects())

    def __bool__(self) -> bool:
        return bool(self._queued or self._deferred)
