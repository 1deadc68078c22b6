"""Public API of the association stage (paper Sec. 5.1 and supplement "DP-mean based Line Segment Clustering",
Algorithm 1; "Detection Pruning"), numpy/scipy, no ROS. The code lives in one module per concern:

- `config`: `AssociationConfig`, `CONFIG_DOC`, `ASSOCIATION_DTYPE`;
- `segments`: ray segments of detections, point-to-segment distances, least-squares DP-means centres,
  gated Hungarian assignment;
- `boxes`: upright 3D boxes (`Box3D`), their projection, clipping, IoU and the multi-view least-squares fit;
- `pruning`: detection pruning (size, occlusion, overlap);
- `tracker`: `Associator` (incremental DP-means, merges, confirmation, deferred truncated rule, box refits,
  pruning flags) and `detections_from_instances`.

Importing from `frodo_association.core` keeps working for every name listed in `__all__`.
"""
from __future__ import annotations

from frodo_association.boxes import Box3D, box_iou, canonical_yaw, clip_boxes, fit_box, project_boxes
from frodo_association.config import ASSOCIATION_DTYPE, CONFIG_DOC, AssociationConfig
from frodo_association.pruning import prune_detections
from frodo_association.segments import (box_segments, clip_segments_to_heights, depth_intervals, gated_assignment,
                                        lsq_center, lsq_centers, point_segment_distance)
from frodo_association.tracker import AssociationUpdate, Associator, ObjectTrack, detections_from_instances

__all__ = ['ASSOCIATION_DTYPE', 'CONFIG_DOC', 'AssociationConfig', 'AssociationUpdate', 'Associator', 'Box3D',
           'ObjectTrack', 'box_iou', 'box_segments', 'canonical_yaw', 'clip_boxes', 'clip_segments_to_heights',
           'depth_intervals', 'detections_from_instances', 'fit_box', 'gated_assignment', 'lsq_center', 'lsq_centers',
           'point_segment_distance', 'project_boxes', 'prune_detections']
