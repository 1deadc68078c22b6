"""Ray segments and DP-means centres (paper Sec. 5.1, supplement "DP-mean based Line Segment Clustering",
Algorithm 1), numpy/scipy, no ROS.

Observation. The ray through a detection's 2D box centre points at the object centre. An object of metric
size S at optical depth d spans about f*S/d pixels, so a box whose larger side spans `a` in normalised image
units (a = max(w/fx, h/fy)) puts the object at d = S / a. The class size range [S_min, S_max]
(`frodo_common.categories`) turns this into a depth interval [S_min / a, S_max / a], widened by
`depth_margin` on both sides (foreshortening, diagonals seen in the box, imperfect masks) and clamped to
[min_depth, max_depth]. The ray cut to that interval is the 3D segment the object centre lies on. With
`objects_on_floor` the segment is further cut to the heights an object centre can have, floor_height +
[S_min / 4, S_max / 2 * (1 + depth_margin)] (the centre of an upright object is at half its height).

Clustering. DP-means with segments as observations and 3D points as centres (Algorithm 1): the distance of
a segment to a centre is the point-to-segment distance; a segment farther than the cluster penalty
lambda from every centre of its class opens a new cluster at its midpoint; a centre is the point
minimising the sum of squared distances to its member segments (`lsq_centers`, at most
`max_center_segments` per cluster).

Conventions: boxes (x0, y0, x1, y1) in pixel-edge coordinates (pixel (u, v) is the centre of column u, row
v); world frame gravity aligned, z up; `T_world_camera` is the camera pose (optical frame).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import linear_sum_assignment


def depth_intervals(boxes: np.ndarray, K: np.ndarray, size_ranges: np.ndarray, margin: float,
                    min_depth: float, max_depth: float) -> np.ndarray:
    """Optical-depth interval of each detection's object centre.

    boxes: (N, 4) pixel boxes; K: (3, 3); size_ranges: (N, 2) metric (S_min, S_max) per detection.
    Returns (N, 2) (d_min, d_max) with d = S / max(w / fx, h / fy), widened by `margin`, clamped.
    """
    a = np.maximum((boxes[:, 2] - boxes[:, 0]) / K[0, 0], (boxes[:, 3] - boxes[:, 1]) / K[1, 1])
    a = np.maximum(a, 1e-6)
    d = size_ranges / a[:, None] * np.array([1.0 - margin, 1.0 + margin])
    return np.clip(d, min_depth, max_depth)


def box_segments(boxes: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray, size_ranges: np.ndarray,
                 margin: float = 0.3, min_depth: float = 0.3, max_depth: float = 20.0) -> np.ndarray:
    """World segments (N, 2, 3) (start, end) on the rays through the box centres, cut to the depth intervals.

    boxes: (N, 4); K: (3, 3); T_world_camera: (4, 4); size_ranges: (N, 2).
    """
    centres = np.stack([(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2], axis=1)
    d_cam = np.stack([(centres[:, 0] - K[0, 2]) / K[0, 0], (centres[:, 1] - K[1, 2]) / K[1, 1],
                      np.ones(len(centres))], axis=1)      # z = 1: a point at optical depth d is d * d_cam
    depth = depth_intervals(boxes, K, size_ranges, margin, min_depth, max_depth)
    pts_cam = d_cam[:, None, :] * depth[:, :, None]        # (N, 2, 3)
    return pts_cam @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]


def clip_segments_to_heights(segments: np.ndarray, z_min: np.ndarray, z_max: np.ndarray) -> np.ndarray:
    """Cut segments (N, 2, 3) to the parts with z_min <= z <= z_max (each (N,)); a segment with no such part
    is returned unchanged (its detection does not fit the height prior; the clustering decides)."""
    a, b = segments[:, 0], segments[:, 1]
    dz = b[:, 2] - a[:, 2]
    flat = np.abs(dz) < 1e-9
    safe = np.where(flat, 1.0, dz)
    s1, s2 = (z_min - a[:, 2]) / safe, (z_max - a[:, 2]) / safe
    inside = (a[:, 2] >= z_min) & (a[:, 2] <= z_max)
    lo = np.where(flat, np.where(inside, 0.0, np.inf), np.minimum(s1, s2))
    hi = np.where(flat, np.where(inside, 1.0, -np.inf), np.maximum(s1, s2))
    lo, hi = np.maximum(lo, 0.0), np.minimum(hi, 1.0)
    ok = lo <= hi
    lo, hi = np.where(ok, lo, 0.0), np.where(ok, hi, 1.0)
    ab = b - a
    return np.stack([a + lo[:, None] * ab, a + hi[:, None] * ab], axis=1)


def point_segment_distance(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distances (N, M) between segments (N, 2, 3) and points (M, 3)."""
    a = segments[:, 0][:, None, :]
    ab = (segments[:, 1] - segments[:, 0])[:, None, :]
    denom = np.maximum(np.sum(ab * ab, axis=2), 1e-12)
    t = np.clip(np.sum((points[None] - a) * ab, axis=2) / denom, 0.0, 1.0)
    return np.linalg.norm(points[None] - (a + t[..., None] * ab), axis=2)


def _group_sum(values: np.ndarray, group: np.ndarray, n_groups: int, idx: np.ndarray | None = None) -> np.ndarray:
    """Sums of values (N, ...) per group (N,) in 0..n_groups-1 -> (n_groups, ...), one bincount. idx: the flat
    bin of every element of values (`_group_bins`), when the caller sums several arrays of that shape."""
    flat = values.reshape(len(values), math.prod(values.shape[1:]))   # not -1: N may be 0
    k = flat.shape[1]
    if idx is None:
        idx = _group_bins(group, k)
    return np.bincount(idx, flat.ravel(), minlength=n_groups * k).reshape((n_groups,) + values.shape[1:])


def _group_bins(group: np.ndarray, k: int) -> np.ndarray:
    """Flat bincount bins (N * k,) of the elements of an (N, k) array summed per group (N,)."""
    return (group[:, None] * k + np.arange(k)).ravel()


def lsq_centers(segments: np.ndarray, group: np.ndarray, n_groups: int, prior_weight: float = 1e-3,
                max_iter: int = 10) -> np.ndarray:
    """Per group, the point minimising the sum of squared distances to its segments.

    segments: (N, 2, 3); group: (N,) in 0..n_groups-1. Returns (n_groups, 3) (NaN for an empty group).
    Active-set least squares, all groups at once: a segment whose closest point is interior acts as its
    infinite line (residual projector I - u u^T), one whose closest point is an end acts as that end point
    (projector I); solve the 3x3 normal equations of every group, update the active sets, repeat until they
    are stable. A weak pull (`prior_weight` per segment) towards the group's mean midpoint fixes the
    position along near-parallel segments, and gives the midpoint for a single segment.
    """
    a, b = segments[:, 0], segments[:, 1]
    ab = b - a
    length2 = np.maximum(np.einsum('ij,ij->i', ab, ab), 1e-12)
    u = ab / np.sqrt(length2)[:, None]
    uu = u[:, :, None] * u[:, None, :]                                  # (N, 3, 3)
    line_rhs = a - u * np.einsum('ij,ij->i', u, a)[:, None]             # (I - u u^T) a
    count = np.bincount(group, minlength=n_groups).astype(np.float64)
    w = prior_weight * count
    prior = w[:, None] * _group_sum(0.5 * (a + b), group, n_groups) / np.maximum(count, 1)[:, None]
    diag = (count + w + (count == 0))[:, None, None] * np.eye(3)       # empty groups stay solvable
    state = np.zeros(len(segments), dtype=np.int8)                      # 0 interior, -1 start, 1 end
    x = np.zeros((n_groups, 3))
    bins9, bins3 = _group_bins(group, 9), _group_bins(group, 3)
    for _ in range(max_iter):
        line = state == 0
        A = diag - _group_sum(uu * line[:, None, None], group, n_groups, bins9)
        anchor = np.where(line[:, None], line_rhs, np.where((state < 0)[:, None], a, b))
        x = np.linalg.solve(A, (_group_sum(anchor, group, n_groups, bins3) + prior)[..., None])[..., 0]
        t = np.einsum('ij,ij->i', x[group] - a, ab) / length2
        new_state = np.where(t <= 0.0, -1, np.where(t >= 1.0, 1, 0)).astype(np.int8)
        if np.array_equal(new_state, state):
            break
        state = new_state
    x[count == 0] = np.nan
    return x


def lsq_center(segments: np.ndarray, prior_weight: float = 1e-3) -> np.ndarray:
    """Point (3,) minimising the sum of squared distances to segments (N, 2, 3) (see `lsq_centers`)."""
    return lsq_centers(segments, np.zeros(len(segments), dtype=np.int64), 1, prior_weight)[0]


def merge_segment_groups(segments: np.ndarray, group: np.ndarray, frames: np.ndarray, penalty: float,
                         prior_weight: float = 1e-3, locked: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Merge segment groups while the DP-means objective falls (sum of squared segment-to-centre distances plus
    penalty^2 per group): a group keeps its centre on its own segments, so a leader-opened singleton never
    dissolves by re-assignment alone, even where one centre fits it and its neighbour group within the penalty.

    segments (N, 2, 3); group (N,) in 0..G-1 or -1 (unassigned, left alone); frames (N,): two groups holding
    detections of one frame never merge (one object is detected at most once per frame); locked: optional (G,) bool
    per input group id, two locked groups never merge (with each other; a merged group is locked when one of its
    groups was). Greedy, the pair with the largest fall first; a merged centre must lie within `penalty` of each
    of its segments. Returns (group with consecutive ids in the order of the input ids, centres (G', 3))."""
    group = np.array(group, dtype=np.int64)
    locked_ids = set(np.nonzero(locked)[0].tolist()) if locked is not None else set()
    while True:
        ids = np.unique(group[group >= 0])
        members = [np.nonzero(group == g)[0] for g in ids]
        cost = [float(np.sum(point_segment_distance(lsq_center(segments[m], prior_weight)[None], segments[m]) ** 2))
                for m in members]
        best, pair = 0.0, None
        for i in range(len(ids)):
            for j in range(i + 1, len(ids)):
                both = np.concatenate([members[i], members[j]])
                if (ids[i] in locked_ids and ids[j] in locked_ids) or len(np.unique(frames[both])) < len(both):
                    continue
                d = point_segment_distance(lsq_center(segments[both], prior_weight)[None], segments[both])[:, 0]
                fall = penalty ** 2 + cost[i] + cost[j] - float(np.sum(d ** 2))
                if d.max() < penalty and fall > best:
                    best, pair = fall, (ids[i], ids[j])
        if pair is None:
            break
        group[group == pair[1]] = pair[0]
        if pair[1] in locked_ids:
            locked_ids.add(pair[0])
    ids, group_new = np.unique(group[group >= 0], return_inverse=True)
    out = np.full(len(group), -1, np.int64)
    out[group >= 0] = group_new
    centres = lsq_centers(segments[group >= 0], out[group >= 0], len(ids), prior_weight).reshape(-1, 3)
    return out, centres


def gated_assignment(cost: np.ndarray, gate: float) -> np.ndarray:
    """One-to-one assignment of rows to columns with cost < gate (Hungarian); (R,) column index or -1."""
    out = np.full(cost.shape[0], -1, dtype=np.int64)
    if cost.size == 0:
        return out
    big = 1e6
    rows, cols = linear_sum_assignment(np.where(cost < gate, cost, big))
    ok = cost[rows, cols] < gate
    out[rows[ok]] = cols[ok]
    return out


def ray_segments(boxes: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World segments (N, 2, 3) on the rays through the box centres between optical depths depth (N, 2)."""
    centres = np.stack([(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2], axis=1)
    d_cam = np.stack([(centres[:, 0] - K[0, 2]) / K[0, 0], (centres[:, 1] - K[1, 2]) / K[1, 1],
                      np.ones(len(centres))], axis=1)
    pts_cam = d_cam[:, None, :] * depth[:, :, None]
    return pts_cam @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]


def surface_intervals(surface_depth: np.ndarray, extent: np.ndarray, slack: float, min_depth: float,
                      max_depth: float) -> np.ndarray:
    """Optical-depth interval (N, 2) of the object centres behind visible surfaces at depth surface_depth (N,):
    [d_s - slack, d_s + extent] (extent (N,): how far behind its visible surface a centre can be), clamped."""
    d = np.stack([surface_depth - slack, surface_depth + extent], axis=1)
    return np.clip(d, min_depth, max_depth)


def complete_truncated_boxes(boxes: np.ndarray, edge_valid: np.ndarray, K: np.ndarray, center_depth: np.ndarray,
                             shapes: np.ndarray) -> np.ndarray:
    """Boxes (N, 4) extended beyond the image border on truncated sides (issue 9: truncation-aware rays).

    A box cut on one side of an axis (edge_valid (N, 4) False there, the opposite edge valid) is extended on the
    cut side to the class's typical projected extent at the centre's optical depth center_depth (N,):
    width fx * sqrt(long * short) / d, height fy * height / d (shapes (N, 3) = (long, short, height)); it is
    never shrunk. A box cut on both sides of an axis, or with NaN depth, keeps that axis.
    """
    out = boxes.copy()
    ok = np.isfinite(center_depth) & (center_depth > 0)
    d = np.where(ok, center_depth, 1.0)
    expect = np.stack([K[0, 0] * np.sqrt(shapes[:, 0] * shapes[:, 1]) / d, K[1, 1] * shapes[:, 2] / d], axis=1)
    for axis in (0, 1):
        lo, hi = edge_valid[:, axis], edge_valid[:, axis + 2]
        span = np.maximum(expect[:, axis], boxes[:, axis + 2] - boxes[:, axis])
        cut_lo = ok & ~lo & hi
        cut_hi = ok & lo & ~hi
        out[cut_lo, axis] = boxes[cut_lo, axis + 2] - span[cut_lo]
        out[cut_hi, axis + 2] = boxes[cut_hi, axis] + span[cut_hi]
    return out
