"""`/frodo/object_states`: the optimiser's per-object state as a stamped table (PointCloud2), and its
conversion to the per-object records of `objects.json` (CONTRACT.md "Files written by the command line")."""
from __future__ import annotations

import numpy as np

from frodo_common.categories import category_by_id

OBJECT_STATES = '/frodo/object_states'
STAGES = ('fused', 'sparse', 'dense')
STATES_DTYPE = np.dtype([('object_id', '<i4'), ('category', '<u2'), ('stage', 'u1'), ('num_views', '<u4'),
                         ('scale', '<f8'), ('pose', '<f8', (16,)), ('box', '<f8', (7,)),
                         ('code', '<f4', (64,)), ('seconds', '<f4')])


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
            'timings': {'optimiser_s': float(row['seconds'])},
        }
    return out
