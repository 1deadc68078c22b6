"""`/frodo/object_states`: the optimiser's per-object state as a stamped table (PointCloud2), and its
conversion to the per-object records of `objects.json` (CONTRACT.md "Files written by the command line")."""
from __future__ import annotations

import numpy as np

from frodo_common.categories import category_by_id

OBJECT_STATES = '/frodo/object_states'
STAGES = ('fused', 'sparse', 'dense')
# Why an object is at its stage (objects.json `stage_reason`); the index travels in the table.
STAGE_REASONS = (
    'in progress',                     # a later stage is still to run for this object
    'all stages done',                 # dense result accepted
    'sparse stage disabled',
    'sparse stage failed',             # no usable views, invalid input, ... (details on /diagnostics)
    'dense stage disabled',
    'dense not better than sparse',    # dense energy not lowered: rolled back to the sparse result
    'dense stage failed',              # no usable views, no surface, non-finite input
    'dense time limit',                # dense result accepted, stopped by dense_max_seconds
)
STATES_DTYPE = np.dtype([('object_id', '<i4'), ('category', '<u2'), ('stage', 'u1'), ('num_views', '<u4'),
                         ('scale', '<f8'), ('pose', '<f8', (16,)), ('box', '<f8', (7,)),
                         ('code', '<f4', (64,)), ('seconds', '<f4'), ('stage_reason', 'u1')])


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
