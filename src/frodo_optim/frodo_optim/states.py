"""`/frodo/object_states`: the optimiser's per-object state as a stamped table (PointCloud2), and its
conversion to the per-object records of `objects.json` (CONTRACT.md "Files written by the command line")."""
from __future__ import annotations

from enum import IntEnum

import numpy as np

from frodo_common.categories import category_by_id
from frodo_common.schemas import STATES_DTYPE  # noqa: F401 - the table's row type, re-exported

OBJECT_STATES = '/frodo/object_states'
STAGES = ('fused', 'sparse', 'dense')


class StageReason(IntEnum):
    """Why an object is at its stage (objects.json `stage_reason`, as its `text`); the value travels in the
    /frodo/object_states table, so members are only ever appended."""

    IN_PROGRESS = 0              # a later stage is still to run for this object
    ALL_STAGES_DONE = 1          # dense result accepted
    SPARSE_DISABLED = 2
    SPARSE_FAILED = 3            # no usable views, invalid input, the refined code decodes to no surface
    DENSE_DISABLED = 4
    DENSE_NOT_BETTER = 5         # dense energy not lowered: rolled back to the sparse result
    DENSE_FAILED = 6             # no usable views, no surface, non-finite input or energy
    DENSE_TIME_LIMIT = 7         # dense result accepted, stopped by dense_max_seconds
    DENSE_INTERRUPTED = 8        # the optimiser stopped (shutdown) during the dense stage; best state so far kept

    @property
    def text(self) -> str:
        return _REASON_TEXT[self]

    @classmethod
    def from_text(cls, text: str | None) -> 'StageReason':
        """The member whose `text` is `text` (IN_PROGRESS for an unknown or missing one)."""
        return next((r for r in cls if r.text == text), cls.IN_PROGRESS)


_REASON_TEXT = {
    StageReason.IN_PROGRESS: 'in progress', StageReason.ALL_STAGES_DONE: 'all stages done',
    StageReason.SPARSE_DISABLED: 'sparse stage disabled', StageReason.SPARSE_FAILED: 'sparse stage failed',
    StageReason.DENSE_DISABLED: 'dense stage disabled', StageReason.DENSE_NOT_BETTER: 'dense not better than sparse',
    StageReason.DENSE_FAILED: 'dense stage failed', StageReason.DENSE_TIME_LIMIT: 'dense time limit',
    StageReason.DENSE_INTERRUPTED: 'dense interrupted',
}
STAGE_REASONS = tuple(r.text for r in StageReason)   # objects.json texts, by table value



def states_to_records(table: np.ndarray) -> dict[int, dict]:
    """Table of STATES_DTYPE -> {object id: JSON-ready record} (pose 4x4 object-to-world, box, code, ...)."""
    out = {}
    for row in table:
        category = category_by_id(int(row['category']))
        box = row['box']
        out[int(row['object_id'])] = {
            'id': int(row['object_id']),
            'class': category.name if category else f'coco_{int(row["category"])}',
            'pose': np.asarray(row['pose'], dtype=float).reshape(4, 4).tolist(),
            'scale': float(row['scale']),
            'box': {'center': box[:3].tolist(), 'size': box[3:6].tolist(), 'yaw': float(box[6])},
            'code': [float(v) for v in row['code']],
            'num_views': int(row['num_views']),
            'stage': STAGES[int(row['stage'])],
            'stage_reason': (STAGE_REASONS[int(row['stage_reason'])] if 'stage_reason' in (table.dtype.names or ())
                             and int(row['stage_reason']) < len(STAGE_REASONS) else None),
            'timings': {'optimiser_s': float(row['seconds'])},
        }
    return out


def estimates_table(estimates) -> np.ndarray:
    """Table of STATES_DTYPE of `core.ObjectEstimate`s (in the order given): what /frodo/object_states carries."""
    table = np.zeros(len(estimates), dtype=STATES_DTYPE)
    for i, est in enumerate(estimates):
        center, size, yaw = est.box
        table[i] = (est.object_id, est.category, STAGES.index(est.stage), est.num_views, est.scale,
                    est.T_world_object.ravel(), np.r_[center, size, yaw], est.code, sum(est.timings.values()),
                    int(est.stage_reason))
    return table
