"""Row types of the graph's stamped tables (PointCloud2 records, docs/ARCHITECTURE.md "Internal topics"): the one
home of every schema, so no package imports another's node for a dtype."""
from __future__ import annotations

import numpy as np

CODE_DIM = 64
"""Length of a shape code (the paper's 64-D embedding)."""

ASSOCIATION_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('label', '<u2'), ('object_id', '<i4'),
                              ('kept', 'u1'), ('bbox', '<f4', (4,))])
"""/frodo/associations: object centre (world; NaN when not associated), the detection's instance label, object id
(-1: not associated), kept (passed pruning), box (x0, y0, x1, y1)."""

CODES_DTYPE = np.dtype([('object_id', '<i4'), ('label', '<u2'), ('code', '<f4', (CODE_DIM,))])
"""/frodo/codes: per kept associated detection of a frame, its encoder code."""

OBJECT_CODES_DTYPE = np.dtype([('object_id', '<i4'), ('category', '<u2'), ('num_views', '<u4'),
                               ('code', '<f4', (CODE_DIM,))])
"""/frodo/object_codes: per object its fused code (Sec. 5.2), COCO category and detections fused."""

STATES_DTYPE = np.dtype([('object_id', '<i4'), ('category', '<u2'), ('stage', 'u1'), ('num_views', '<u4'),
                         ('scale', '<f8'), ('pose', '<f8', (16,)), ('box', '<f8', (7,)),
                         ('code', '<f4', (CODE_DIM,)), ('seconds', '<f4'), ('stage_reason', 'u1')])
"""/frodo/object_states: per reconstructed object its stage, pose (row-major 4x4), box (centre, size, yaw), code,
optimiser seconds and stage reason (`frodo_optim.states.StageReason`)."""
