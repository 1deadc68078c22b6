"""Detection pruning (supplement "Detection Pruning"; numpy, no ROS).

Pruning (supplement "Detection Pruning"): a detection is kept when (1) its box is at least
min_box_width x min_box_height pixels (scaled to the resolution), (2) the IoU between it and the projection of its object's 3D box
is at least `occlusion_iou` (the projection is not clipped to the image, so truncation fails this test as
well as occlusion), and (3) its IoU with the (clipped) projected box of every other published object is at
most `overlap_iou`.

Pixel sizes (min_box_width, min_box_height) are given for a 640x480 image and scaled by
s = sqrt(W * H / (640 * 480)) for a W x H image (`frodo_detection.core.resolution_scale`); border_margin
is in plain pixels.
"""
from __future__ import annotations

import numpy as np

from frodo_association.boxes import box_iou, clip_boxes
from frodo_association.config import AssociationConfig
from frodo_detection.core import REFERENCE_SIZE


def prune_detections(det_boxes: np.ndarray, object_index: np.ndarray, object_boxes: np.ndarray,
                     object_valid: np.ndarray, image_sizes: np.ndarray, cfg: AssociationConfig) -> np.ndarray:
    """Detection pruning (supplement "Detection Pruning").

    det_boxes: (N, 4) detection boxes; object_index: (N,) column of each detection's own object in
    object_boxes (-1: no object or no 3D box yet: only the size test applies); object_boxes: (N, O, 4) the
    projected 3D boxes (not clipped) of the O objects, in each detection's frame; object_valid: (N, O)
    projection usable; image_sizes: (N, 2) (width, height) of each detection's image.
    (1) size: width >= min_box_width and height >= min_box_height (both scaled to the image size by
        `resolution_scale`);
    (2) occlusion: IoU(detection, own projected box) >= occlusion_iou; the projection is not clipped, so a
        detection truncated by the image border fails this test too (the paper's "occlusions or truncations");
    (3) overlap: IoU(detection, other object's projected box clipped to the image) <= overlap_iou.
    Returns kept (N,) bool.
    """
    w = det_boxes[:, 2] - det_boxes[:, 0]
    h = det_boxes[:, 3] - det_boxes[:, 1]
    scale = np.sqrt(np.prod(np.asarray(image_sizes, dtype=np.float64).reshape(-1, 2), axis=1)
                    / (REFERENCE_SIZE[0] * REFERENCE_SIZE[1]))                     # resolution_scale per row
    kept = (w >= cfg.min_box_width * scale) & (h >= cfg.min_box_height * scale)
    if object_boxes.shape[1] == 0:
        return kept
    rows = np.arange(len(det_boxes))
    own = object_index >= 0
    col = np.maximum(object_index, 0)
    own_iou = box_iou(det_boxes, object_boxes[rows, col])
    own_ok = object_valid[rows, col] & (own_iou >= cfg.occlusion_iou)
    other = np.where(object_valid, box_iou(det_boxes[:, None, :], clip_boxes(object_boxes, image_sizes)), 0.0)
    other[rows[own], col[own]] = 0.0
    return kept & (~own | own_ok) & (other.max(axis=1) <= cfg.overlap_iou)
