"""The complete object map from the optimiser workers' shares (no rclpy).

CONTRACT.md: `/frodo/objects` is "the current object map, complete in every message" (reliable, transient
local, depth 1), so an outside listener that keeps only the latest message (RViz with depth 1, a robot stack)
must find every object in it. With several optimiser workers (optim_node `worker_index` k of `worker_count` N)
each worker reconstructs only its share of the objects (id % N == k). So workers 1..N-1 publish their share
(the very messages a lone optimiser publishes: its objects and DELETEs of the ones it dropped) on their own
internal topics (`frodo_common.topics.object_share_topic`, latched: one writer per topic, so a late or restarted
reader gets every worker's last share), and worker 0 merges them with its own share and publishes the complete
map on `/frodo/objects`, `/frodo/boxes` and `/frodo/object_states`. With one worker nothing is merged.

Why worker 0 merges, and not every worker nor a separate process: one writer of `/frodo/objects` keeps its
latched message the complete map (with a writer per worker, a depth-1 late joiner would keep whichever latched
message came last, possibly from a worker that had not yet heard all shares), costs one copy of the meshes on
the wire instead of N, and adds no process. What survives a SIGKILL under `--on-failure restart` + `--resume`:
a killed worker k >= 1 -> worker 0 keeps its last share (the map stays complete) and takes the share the
restarted worker republishes from its saved map. A killed worker 0 -> `/frodo/objects` has no writer until the
restart (listeners keep the last complete map, only a listener joining in that window gets nothing); the
restarted worker 0 has its own share from its saved map and, from the latched share topics, every other
worker's last share, and publishes the complete map again.

Markers are held as `marker_wire` items: a Marker, or (marker, points (N, 3)) for a mesh whose points stay an
array (shares are read raw and the merged map is written from arrays; no Point message per vertex).

Each worker's share replaces its previous one as a whole (keyed by worker, then by (class, object id)), so a
worker that restarted without the objects it had (no `--resume`) retracts them with its first share; the
merged map's own DELETEs (for every (class, id) it published and no longer has) come from `Retractions`, as a
lone optimiser's do.
"""
from __future__ import annotations

from typing import Sequence, Union

import numpy as np
from visualization_msgs.msg import Marker

from frodo_common import conversions as conv

# The marker outputs a worker shares (contract topics /frodo/objects and /frodo/boxes).
MARKER_KINDS = ('objects', 'boxes')
# The per-object table a worker shares (/frodo/object_states).
TABLE_KIND = 'object_states'
SHARE_KINDS = MARKER_KINDS + (TABLE_KIND,)

MarkerKey = tuple[str, int]   # (ns = class name, object id): a marker's identity for RViz and the contract
MarkerItem = Union[Marker, tuple[Marker, np.ndarray]]   # a marker, or a marker and its points as an array


def item_marker(item: MarkerItem) -> Marker:
    """The Marker of a marker item."""
    return item[0] if isinstance(item, tuple) else item


class Retractions:
    """The (class, object id) keys of a marker map that were published once and are gone now.

    Every message of the map repeats a DELETE for each of them (never DELETEALL), so a listener that missed a
    message, or keys markers by (ns, id) and saw an object's class change, still drops them.
    """

    def __init__(self) -> None:
        self.published: set[MarkerKey] = set()
        self.retracted: set[MarkerKey] = set()

    def update(self, current: set[MarkerKey]) -> list[MarkerKey]:
        """Note the keys of the message about to be published; returns the retracted keys, by (id, class)."""
        self.retracted = (self.retracted | (self.published - current)) - current
        self.published = set(current)
        return sorted(self.retracted, key=lambda key: (key[1], key[0]))


class MapMerger:
    """Holds each worker's latest share and builds the complete map's messages from them.

    Not thread-safe: the optimiser node calls it under one lock from its worker thread (its own share) and
    its executor (the other workers' shares).
    """

    def __init__(self, worker_count: int) -> None:
        if worker_count < 1:
            raise ValueError(f'worker_count must be at least 1, got {worker_count}')
        self.worker_count = worker_count
        # kind -> per worker {(class, id): its latest ADD marker item}
        self.markers: dict[str, list[dict[MarkerKey, MarkerItem]]] = {
            kind: [{} for _ in range(worker_count)] for kind in MARKER_KINDS}
        self.tables: list[np.ndarray | None] = [None] * worker_count
        self.heard: set[int] = set()
        self.retractions = {kind: Retractions() for kind in MARKER_KINDS}

    def _check_worker(self, worker: int) -> None:
        if not 0 <= worker < self.worker_count:
            raise ValueError(f'worker {worker} is not in 0..{self.worker_count - 1}')

    def put_markers(self, kind: str, worker: int, items: Sequence[MarkerItem]) -> None:
        """A worker's share of `kind` ('objects' or 'boxes'; its markers as items) replaces its previous one (its
        ADD markers; its DELETEs are of objects it no longer has, which the replacement drops already)."""
        self._check_worker(worker)
        if kind not in MARKER_KINDS:
            raise ValueError(f'kind must be one of {MARKER_KINDS}, got {kind!r}')
        markers = [item_marker(item) for item in items]
        if any(m.action == Marker.DELETEALL for m in markers):
            raise ValueError(f'worker {worker} sent DELETEALL on its {kind} share (a share holds ADDs and DELETEs)')
        self.markers[kind][worker] = {(m.ns, m.id): item for m, item in zip(markers, items) if m.action == Marker.ADD}
        self.heard.add(worker)

    def merged_markers(self, kind: str, stamp_ns: int, frame: str) -> list[MarkerItem]:
        """The complete map of `kind`, as items: a DELETE (stamped `stamp_ns`) for every (class, id) published
        before and gone now, then every worker's ADD markers by (id, class). Call once per message published."""
        merged: dict[MarkerKey, MarkerItem] = {}
        for share in self.markers[kind]:
            merged.update(share)
        items: list[MarkerItem] = [conv.delete_marker(ns, oid, stamp_ns, frame)
                                   for ns, oid in self.retractions[kind].update(set(merged))]
        items.extend(merged[key] for key in sorted(merged, key=lambda key: (key[1], key[0])))
        return items

    def put_table(self, worker: int, table: np.ndarray) -> None:
        """A worker's `/frodo/object_states` table (structured array with `object_id`) replaces its previous one."""
        self._check_worker(worker)
        if table.dtype.names is None or 'object_id' not in table.dtype.names:
            raise ValueError(f'worker {worker} shared a state table without object_id (fields {table.dtype.names})')
        other = next((t for k, t in enumerate(self.tables) if t is not None and k != worker), None)
        if other is not None and other.dtype != table.dtype:
            raise ValueError(f'worker {worker} shared a state table with fields {table.dtype.names}, another worker '
                             f'{other.dtype.names} (different versions?)')
        self.tables[worker] = table
        self.heard.add(worker)

    def merged_table(self) -> np.ndarray | None:
        """Every worker's state rows by object id, or None while no worker has shared one."""
        tables = [t for t in self.tables if t is not None]
        if not tables:
            return None
        merged = np.concatenate(tables)
        return merged[np.argsort(merged['object_id'], kind='stable')]


class WorkerLoads:
    """Worker 0's record of the work the other workers have left, from their `/diagnostics`.

    CONTRACT.md "Done": the optimiser node reports `state` idle with `pending_objects` 0. With several workers
    the optimiser node (worker 0, which also publishes the merged map) speaks for all of them, so that a listener
    that watches only the optimiser node sees the whole optimiser: busy while any worker is busy or has not
    reported yet, its pending objects the sum over workers.
    """

    def __init__(self, worker_count: int) -> None:
        if worker_count < 1:
            raise ValueError(f'worker_count must be at least 1, got {worker_count}')
        self.worker_count = worker_count
        self.loads: dict[int, tuple[bool, int]] = {}   # worker k >= 1 -> (busy, pending objects) last reported

    def heard(self, worker: int, state: str, pending: int) -> None:
        """Worker `worker` (1..N-1) reported `state` ('idle' or 'busy') and `pending` objects."""
        if not 1 <= worker < self.worker_count:
            raise ValueError(f'worker {worker} is not in 1..{self.worker_count - 1}')
        self.loads[worker] = (state != 'idle', max(0, int(pending)))

    def combined(self, own_busy: bool, own_pending: int) -> dict[str, str | int]:
        """`state`, `pending_objects` of the whole optimiser and `pending_by_worker` ('?' for a worker not heard
        from yet), given worker 0's own."""
        busy = own_busy or len(self.loads) < self.worker_count - 1 or any(b for b, _ in self.loads.values())
        pending = own_pending + sum(p for _, p in self.loads.values())
        by_worker = [str(own_pending)] + [str(self.loads[k][1]) if k in self.loads else '?'
                                          for k in range(1, self.worker_count)]
        return {'state': 'busy' if busy else 'idle', 'pending_objects': pending,
                'pending_by_worker': ' '.join(by_worker)}
