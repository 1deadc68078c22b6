"""Bounded memory of the shape node: one code per associated detection, keyed (stamp ns, instance label),
and the object each detection belongs to (paper Sec. 5.2: an object's code is fused from its detections' codes).

Without a bound a long run grows by one 64-D code per detection for ever, and fusing every object's codes
each frame costs time in proportion (measured by `frodo bench --only soak`). So an object keeps at most
`per_object` codes: past that, every second one in stamp order is dropped, so the kept codes stay spread
over the trajectory (the mean of an even subsample, not of all codes); `num_views` still counts the dropped
ones. Codes of detections no longer assigned to any object are dropped by `forget_unassigned`.
"""
from __future__ import annotations

from collections import Counter

import numpy as np

Key = tuple[int, int]   # (stamp ns, instance label)


class CodeStore:
    """Codes by detection and their object assignment, at most `per_object` codes per object."""

    def __init__(self, per_object: int = 256):
        if per_object < 2:
            raise ValueError(f'per_object must be >= 2, got {per_object}')
        self.per_object = int(per_object)
        self.codes: dict[Key, np.ndarray] = {}
        self.assignment: dict[Key, int] = {}        # kept, associated detections only
        self.thinned: Counter[int] = Counter()      # object id -> codes dropped by the bound

    def __contains__(self, key: Key) -> bool:
        return key in self.codes

    def add(self, key: Key, code: np.ndarray) -> None:
        """Store the code (C,) of one detection."""
        self.codes[key] = np.asarray(code, dtype=np.float32)

    def assign_frame(self, stamp: int, owners: dict[int, int]) -> None:
        """The frame's detections now belong to `owners` ({label: object id}); labels not listed belong to none.
        Every listed label needs a stored code. Objects that grew past the bound are thinned."""
        for key in [k for k in self.assignment if k[0] == stamp]:
            del self.assignment[key]
        for label, oid in owners.items():
            key = (stamp, int(label))
            if key not in self.codes:
                raise KeyError(f'no code stored for detection {key}')
            self.assignment[key] = int(oid)
        for oid in set(owners.values()):
            self._thin(int(oid))

    def members(self) -> dict[int, list[Key]]:
        """Object id -> its detections' keys, in stamp order."""
        out: dict[int, list[Key]] = {}
        for key in sorted(self.assignment):
            out.setdefault(self.assignment[key], []).append(key)
        return out

    def num_views(self, oid: int, members: int) -> int:
        """Detections of an object: `members` held plus those dropped by the bound."""
        return members + self.thinned[oid]

    def forget_unassigned(self, keep_stamp) -> int:
        """Drop the codes of detections assigned to no object whose stamp `keep_stamp(stamp)` says is no longer
        needed (e.g. their frame left the cache, so no re-send can assign them again); returns how many."""
        gone = [k for k in self.codes if k not in self.assignment and not keep_stamp(k[0])]
        for key in gone:
            del self.codes[key]
        return len(gone)

    def _thin(self, oid: int) -> None:
        mine = sorted(k for k, o in self.assignment.items() if o == oid)
        if len(mine) > self.per_object:
            for key in mine[1::2]:
                del self.assignment[key]
                del self.codes[key]
            self.thinned[oid] += len(mine[1::2])

    def __len__(self) -> int:
        return len(self.codes)
