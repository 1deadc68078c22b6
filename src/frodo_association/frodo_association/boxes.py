"""Upright 3D boxes from 2D detection boxes over several views: projection, clipping, IoU and the least-squares
fit (numpy/scipy, no ROS).

Boxes. Each published object gets an upright 3D box (centre, size (dx, dy, dz), yaw about gravity z), in
the spirit of QuadricSLAM's boxes from 2D detections: initialised at the cluster centre with the class
size prior and refined by soft-L1 least squares (`robust_lsq`, analytic Jacobian) so that the projected box
corners match the 2D detection boxes, edge by edge (edges at the image border are truncated and left
out), with a weak pull to the cluster centre; objects stand on the floor plane z = floor_height when
`objects_on_floor`. Boxes are refitted (`Associator.refine_boxes`, bounded per frame) when an object has
grown by `box_refit_growth` since its last fit, from its kept detections when pruning leaves enough.

Conventions: boxes (x0, y0, x1, y1) in pixel-edge coordinates (pixel (u, v) is the centre of column u, row
v); world frame gravity aligned, z up; `T_world_camera` is the camera pose (optical frame).
"""
from __future__ import annotations


import cv2
import numpy as np

from frodo_association.robust_lsq import soft_l1_least_squares
from frodo_common.geometry import Box3D

# Corner offsets of a unit box, in the corner order of frodo_common.geometry.box_corners.
# Typical upright dimensions (long side, short side, height) in metres per COCO class: common real furniture
# (ScanNet/Redwood chairs 0.45-0.6 m wide, 0.8-1 m tall; dining tables 0.72-0.78 m tall). Used as the class
# shape prior of the box fit and to complete truncated detections; frodo_common.categories gives the range of
# the largest extent.
CLASS_SHAPES: dict[int, tuple[float, float, float]] = {
    62: (0.5, 0.5, 0.9),      # chair
    63: (1.9, 0.9, 0.85),     # couch
    65: (2.0, 1.6, 0.6),      # bed
    67: (1.5, 0.9, 0.75),     # dining table
}

_BOX_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64) / 2
POINT_OUTSIDE_SCALE = 0.25          # m: a surface point this far outside the box counts 0.76 of it, farther ones little more
_EDGE_AXIS = np.array([0, 1, 0, 1])                  # image axis (u, v) of the box edges (min u, min v, max u, max v)


def project_boxes(K: np.ndarray, T_camera_world: np.ndarray, corners: np.ndarray,
                  near: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """2D boxes (not clipped to the image) of 3D boxes seen by F cameras.

    K: (F, 3, 3); T_camera_world: (F, 4, 4); corners: (O, 8, 3) world corners. Returns (boxes (F, O, 4),
    valid (F, O)): a box is invalid when a corner is closer than `near` (the object reaches behind the camera).
    """
    # Batched matmul with the corners on the last (contiguous) axis: 2-3x faster than an einsum at 200 frames.
    pc = T_camera_world[:, None, :3, :3] @ corners.transpose(0, 2, 1)[None] + T_camera_world[:, None, :3, 3:]
    z = pc[:, :, 2]                                                     # (F, O, 8)
    xy = pc[:, :, :2] / np.maximum(z, near)[:, :, None]                 # (F, O, 2, 8)
    f = np.stack([K[:, 0, 0], K[:, 1, 1]], axis=1)[:, None]             # (F, 1, 2); f > 0: min/max commute
    c = np.stack([K[:, 0, 2], K[:, 1, 2]], axis=1)[:, None]
    boxes = np.concatenate([xy.min(axis=3) * f + c, xy.max(axis=3) * f + c], axis=-1)
    return boxes, np.all(z > near, axis=2)


def clip_boxes(boxes: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Boxes (..., O, 4) clipped to images of sizes (..., 2) (width, height)."""
    lim = np.concatenate([sizes, sizes], axis=-1)[..., None, :] - 0.5
    return np.clip(boxes, -0.5, lim)


def _box_intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ix = np.clip(np.minimum(a[..., 2], b[..., 2]) - np.maximum(a[..., 0], b[..., 0]), 0, None)
    iy = np.clip(np.minimum(a[..., 3], b[..., 3]) - np.maximum(a[..., 1], b[..., 1]), 0, None)
    return ix * iy


def box_area(a: np.ndarray) -> np.ndarray:
    """Area of boxes (..., 4) = (min u, min v, max u, max v)."""
    return (a[..., 2] - a[..., 0]) * (a[..., 3] - a[..., 1])


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of boxes a (..., 4) and b (..., 4), broadcast over the leading axes (vectorised
    `frodo_common.geometry.box_iou_2d`)."""
    inter = _box_intersection(a, b)
    union = box_area(a) + box_area(b) - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def box_inside_fraction(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Fraction of the area of boxes a (..., 4) inside boxes b (..., 4), broadcast (0 for an empty a)."""
    area = box_area(a)
    return np.where(area > 0, _box_intersection(a, b) / np.maximum(area, 1e-12), 0.0)


def footprint_overlap(a: Box3D, b: Box3D) -> float:
    """Area of the intersection of two upright boxes' floor footprints (rotated rectangles) over the smaller
    footprint's area, in [0, 1]."""
    rects = [((float(x.center[0]), float(x.center[1])), (float(x.size[0]), float(x.size[1])), float(np.degrees(x.yaw)))
             for x in (a, b)]
    kind, pts = cv2.rotatedRectangleIntersection(*rects)
    if kind == cv2.INTERSECT_NONE or pts is None:
        return 0.0
    inter = cv2.contourArea(cv2.convexHull(pts))
    return float(inter / max(min(a.size[0] * a.size[1], b.size[0] * b.size[1]), 1e-9))


def canonical_yaw(size: np.ndarray, yaw: float) -> tuple[np.ndarray, float]:
    """Equivalent (size, yaw) with yaw in [-pi/4, pi/4): a quarter turn swaps dx and dy."""
    size = np.asarray(size, dtype=np.float64).copy()
    quarter = int(np.floor((yaw + np.pi / 4) / (np.pi / 2)))
    yaw = yaw - quarter * np.pi / 2
    if quarter % 2:
        size[[0, 1]] = size[[1, 0]]
    return size, float(yaw)


def _box_projection(p: np.ndarray, R: np.ndarray, t: np.ndarray, f: np.ndarray, c: np.ndarray,
                    floor_height: float | None, with_jacobian: bool = False,
                    near_axis: tuple[np.ndarray, np.ndarray] | None = None):
    """Projected 2D boxes of upright 3D boxes (and their Jacobians w.r.t. the box parameters), S boxes at once.

    p: (S, P) = (cx, cy, [cz], log dx, log dy, log dz, yaw) per box (cz omitted when boxes stand on
    floor_height); R: (V, 3, 3), t: (V, 3) camera-from-world; f, c: (V, 2) focal lengths and principal points.
    Returns boxes (S, V, 4) = (min u, min v, max u, max v) over the 8 corners, or (boxes, jacobian (S, V, 4, P))
    with `with_jacobian` (each edge follows its extreme corner). With `near_axis` = (a (N, 3), b (N,)) also the
    least a_n . X + b_n over each box's corners X (world) for each of the N rows (S, N) (and its Jacobian
    (S, N, P)), appended.
    """
    on_floor = floor_height is not None
    n_s, n_p = p.shape
    n_v = len(R)
    size = np.exp(p[:, -4:-1])                                          # (S, 3)
    cos, sin = np.cos(p[:, -1]), np.sin(p[:, -1])
    rot = np.zeros((n_s, 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = cos, -sin, sin, cos, 1.0
    center = np.empty((n_s, 3))
    center[:, :2] = p[:, :2]
    center[:, 2] = floor_height + size[:, 2] / 2 if on_floor else p[:, 2]
    # Corners along the last axis throughout: the arg reductions run over contiguous memory.
    local = _BOX_SIGNS.T * size[:, :, None]                             # (S, 3, 8) corner offsets, box frame
    world = rot @ local + center[:, :, None]                            # (S, 3, 8) corners, world frame
    pc = R @ world[:, None] + t[:, :, None]                             # (S, V, 3, 8) camera frame
    z = np.maximum(pc[:, :, 2], 0.05)                                   # (S, V, 8)
    xy = pc[:, :, :2] / z[:, :, None]                                   # (S, V, 2, 8)
    uv = xy * f[:, :, None] + c[:, :, None]
    corner = np.concatenate([uv.argmin(axis=3), uv.argmax(axis=3)], axis=2)   # (S, V, 4) extreme corner per edge
    s_idx = np.arange(n_s)[:, None, None]
    v_idx = np.arange(n_v)[None, :, None]
    boxes = uv[s_idx, v_idx, _EDGE_AXIS, corner]                        # (S, V, 4)
    if near_axis is not None:
        reach = near_axis[0] @ world + near_axis[1][None, :, None]      # (S, V, 8)
        nearest = reach.argmin(axis=2)                                  # (S, V)
        near = reach.min(axis=2)
    if not with_jacobian:
        return (boxes, near) if near_axis is not None else boxes
    n_c = 2 if on_floor else 3
    dX = np.zeros((n_s, 3, 8, n_p))                                     # d world corner / d p
    dX[:, np.arange(n_c), :, np.arange(n_c)] = 1.0
    dX[:, :, :, n_c:n_c + 3] = rot[:, :, None, :] * local.transpose(0, 2, 1)[:, None, :, :]
    if on_floor:
        dX[:, 2, :, n_c + 2] += size[:, 2:3] / 2
    dX[:, 0, :, -1] = -sin[:, None] * local[:, 0] - cos[:, None] * local[:, 1]
    dX[:, 1, :, -1] = cos[:, None] * local[:, 0] - sin[:, None] * local[:, 1]
    dpc = (R @ dX.reshape(n_s, 1, 3, 8 * n_p)).reshape(n_s, n_v, 3, 8, n_p)   # (S, V, 3, 8, P) camera frame
    # Derivatives of the 4 extreme corners only (each edge follows its corner: u = f x / z + c).
    jac = (dpc[s_idx, v_idx, _EDGE_AXIS, corner] - xy[s_idx, v_idx, _EDGE_AXIS, corner][..., None]
           * dpc[s_idx, v_idx, 2, corner]) * (f[:, _EDGE_AXIS] / z[s_idx, v_idx, corner])[..., None]
    if near_axis is not None:
        near_jac = np.einsum('vk,svkp->svp', near_axis[0], dX[s_idx[..., 0], :, nearest])   # (S, V, P)
        return boxes, jac, near, near_jac
    return boxes, jac                                                   # (S, V, 4), (S, V, 4, P)


def _horizontal_reach(R: np.ndarray, t: np.ndarray, K: np.ndarray, boxes: np.ndarray,
                      surface_depth: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """The surface term's measure of "how near": distance from the camera along its viewing direction projected
    onto the floor plane. Returns ((a (V, 3), b (V,)) with a . X + b that distance for a world point X, and the
    visible surfaces' distance (V,): the point at optical depth surface_depth on the ray through the detection
    box's centre.

    Horizontal, not optical depth: a camera at eye height looks down at the furniture, so a tall box's top
    corners are optically nearer than its footprint by (height difference) x sin(pitch). With the nearest corner's
    optical depth a 1.2 m chair seen from 1.5 m at 20 degrees pitch could sit 0.45 m behind its visible surface
    without breaking the bound (realwalk-tune 8407: a chair behind a table, fitted 0.54 m too far)."""
    forward = R[:, 2, :].copy()                                        # camera z axis in the world, per view
    forward[:, 2] = 0.0
    forward /= np.maximum(np.linalg.norm(forward, axis=1, keepdims=True), 1e-6)
    eye = -np.einsum('vji,vj->vi', R, t)                                # camera centre, world
    centre_px = np.stack([(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2, np.ones(len(boxes))], 1)
    ray = np.einsum('vji,vj->vi', R, np.linalg.solve(K, centre_px[..., None])[..., 0])   # world, camera z = 1
    return (forward, -np.einsum('vk,vk->v', forward, eye)), surface_depth * np.einsum('vk,vk->v', forward, ray)


def _outside_residuals(p: np.ndarray, points: np.ndarray, floor_height: float | None) -> tuple[np.ndarray, np.ndarray]:
    """How far each of the points (M, 3) lies outside each upright box p (S, P) (`_box_projection`'s
    parameters) along the box's axes: residuals (S, 3M) (x, y, z per point; 0 inside; with a floor, z only above
    the top) and their Jacobian (S, 3M, P)."""
    on_floor = floor_height is not None
    n_s, n_p = p.shape
    n_c = 2 if on_floor else 3
    size = np.exp(p[:, n_c:n_c + 3])                                    # (S, 3)
    cos, sin = np.cos(p[:, -1])[:, None], np.sin(p[:, -1])[:, None]
    dx, dy = points[None, :, 0] - p[:, 0:1], points[None, :, 1] - p[:, 1:2]     # (S, M)
    local_x, local_y = cos * dx + sin * dy, -sin * dx + cos * dy
    sign_x, sign_y = np.sign(local_x), np.sign(local_y)
    out_x = np.abs(local_x) - size[:, 0:1] / 2
    out_y = np.abs(local_y) - size[:, 1:2] / 2
    jac = np.zeros((n_s, points.shape[0], 3, n_p))
    jac[:, :, 0, 0], jac[:, :, 0, 1] = -sign_x * cos, -sign_x * sin
    jac[:, :, 0, n_c] = -size[:, 0:1] / 2
    jac[:, :, 0, -1] = sign_x * local_y
    jac[:, :, 1, 0], jac[:, :, 1, 1] = sign_y * sin, -sign_y * cos
    jac[:, :, 1, n_c + 1] = -size[:, 1:2] / 2
    jac[:, :, 1, -1] = -sign_y * local_x
    if on_floor:
        out_z = points[None, :, 2] - floor_height - size[:, 2:3]          # above the top only
        jac[:, :, 2, n_c + 2] = -size[:, 2:3]
    else:
        local_z = points[None, :, 2] - p[:, 2:3]
        out_z = np.abs(local_z) - size[:, 2:3] / 2
        jac[:, :, 2, 2] = -np.sign(local_z)
        jac[:, :, 2, n_c + 2] = -size[:, 2:3] / 2
    out = np.stack([out_x, out_y, out_z], axis=2)                       # (S, M, 3)
    # Saturated at POINT_OUTSIDE_SCALE: what is left of a mask's bleed onto the background behind (a metre out)
    # must not pull the box's far side out; the object's own points lie within a few centimetres of it.
    x = np.maximum(out, 0.0) / POINT_OUTSIDE_SCALE
    return ((POINT_OUTSIDE_SCALE * np.tanh(x)).reshape(n_s, -1),
            (jac * ((out > 0) / np.cosh(x) ** 2)[..., None]).reshape(n_s, -1, n_p))


def fit_box(K: np.ndarray, T_camera_world: np.ndarray, boxes: np.ndarray, edge_valid: np.ndarray,
            size_range: tuple[float, float], init_center: np.ndarray, floor_height: float | None = None,
            size_prior_weight: float = 0.05, anchor_weight: float = 1.0, init: Box3D | None = None,
            shape: tuple[float, float, float] | None = None, height_prior_weight: float = 0.0,
            truncation_hinge: bool = True, surface_depth: np.ndarray | None = None, surface_weight: float = 0.0,
            surface_slack: float = 0.1, bottom_below_weight: float = 1.0, points: np.ndarray | None = None,
            points_weight: float = 0.0) -> Box3D:
    """Upright 3D box whose projection matches 2D detection boxes over several views.

    K: (V, 3, 3); T_camera_world: (V, 4, 4); boxes: (V, 4) detection boxes; edge_valid: (V, 4) bool, False
    for truncated edges; size_range: the class's (S_min, S_max); init_center: (3,) (the cluster centre);
    floor_height: the box bottom is fixed at this z when given; init: a previous box to start from.
    Residuals: per valid edge, (projected box edge - detection edge) / detection box diagonal, soft-L1
    loss; with `truncation_hinge`, per cut edge (edge_valid False: on the image border, or against a nearer mask)
    the same difference when the projected edge lies inside it, else 0 (the object reaches at least that far:
    without this a table never seen whole was fitted as a small box around its visible end); plus
    size_prior_weight * log(size / prior) per dimension with prior = sqrt(S_min * S_max), and
    anchor_weight * (centre - init_center) (metres) per free centre coordinate. With a class `shape` (long, short,
    height) and height_prior_weight > 0 the prior is (sqrt(long * short), sqrt(long * short), height) instead, the
    height residual weighted by height_prior_weight. With surface_depth (V,) (the optical depth of each detection's
    visible surface, NaN: unknown) and surface_weight > 0, per known depth surface_weight * max(0, the box's nearest
    corner - surface_slack - the surface) (metres, horizontal distances along the view: `_horizontal_reach`): the
    object reaches at least as near as its visible surface. One
    sided, because a surface depth from landmarks inside a mask may lie on the background behind the object; without
    it an object whose lower part is hidden (its bottom edge above the floor contact) is fitted far behind its
    surface along the view. With a floor, a detection's bottom-edge residual is scaled by bottom_below_weight where
    the box's projection reaches below it (a detection may end above the floor contact unflagged: legs its mask
    misses, an unlabelled occluder; it may not end below it). With points (M, 3) (world, on the object's visible
    surface: `evidence.mask_points`) and points_weight > 0, per point and box axis points_weight * sqrt(V / M) *
    (how far the point lies outside the box along that axis, m; with a floor, above the top only): the box holds
    the surface it was seen by, the points' term weighing about as much as one residual per view.
    Analytic Jacobian (the extreme corner of each edge). Starts: yaw 0 and pi/4 (a box is symmetric under quarter
    turns) at init_center with the prior size; with `init`, that box and the yaw-0 start.
    """
    prior = np.full(3, np.sqrt(size_range[0] * size_range[1]))
    weights = np.full(3, size_prior_weight)
    if shape is not None and height_prior_weight > 0:
        prior = np.array([np.sqrt(shape[0] * shape[1])] * 2 + [shape[2]])
        weights[2] = height_prior_weight
    diag = np.maximum(np.hypot(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]), 1.0)
    R = T_camera_world[:, :3, :3]
    t = T_camera_world[:, :3, 3]
    f = np.stack([K[:, 0, 0], K[:, 1, 1]], axis=1)
    c = np.stack([K[:, 0, 2], K[:, 1, 2]], axis=1)
    on_floor = floor_height is not None
    n_center = 2 if on_floor else 3
    prior_jac = np.zeros((3 + n_center, n_center + 4))
    prior_jac[:3, n_center:n_center + 3] = np.diag(weights)
    prior_jac[3:, :n_center] = anchor_weight * np.eye(n_center)
    anchor = np.asarray(init_center, dtype=np.float64)[:n_center]

    # A cut edge (image border, nearer mask) only bounds the object from inside: the projected edge must not fall
    # inside it (one-sided: min edges <= the detection's, max edges >= it).
    cut = ~edge_valid if truncation_hinge else np.zeros_like(edge_valid)
    outward = np.array([1.0, 1.0, -1.0, -1.0])                          # sign of (proj - box) that is inside
    bottom = np.array([0.0, 0.0, 0.0, 1.0 if on_floor else 0.0])

    known = np.zeros(len(boxes), bool) if surface_depth is None or surface_weight <= 0 \
        else np.isfinite(np.asarray(surface_depth, dtype=np.float64))
    # the surface bound's measure, for the views with a known surface only (the others cost nothing per step)
    reach_axis, surface = _horizontal_reach(R[known], t[known], K[known], boxes[known],
                                            np.asarray(surface_depth, dtype=np.float64)[known]) \
        if known.any() else (None, np.zeros(0))

    pts = np.zeros((0, 3)) if points is None or points_weight <= 0 else np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    pts_w = points_weight * np.sqrt(len(boxes) / max(len(pts), 1))

    def residuals_and_jacobian(p):                                     # p: (S, P) -> (S, M), (S, M, P)
        if reach_axis is None:
            proj, jac = _box_projection(p, R, t, f, c, floor_height, with_jacobian=True)
            near, near_jac = np.zeros((len(p), 0)), np.zeros((len(p), 0, p.shape[1]))
        else:
            proj, jac, near, near_jac = _box_projection(p, R, t, f, c, floor_height, with_jacobian=True,
                                                        near_axis=reach_axis)
        err = (proj - boxes) / diag[:, None]
        inside = (err * outward > 0).astype(np.float64)
        scale = 1.0 + bottom * (1.0 - inside) * (bottom_below_weight - 1.0)
        behind = near - surface_slack - surface                            # > 0: box farther than its surface
        active = surface_weight * (behind > 0)
        r = np.concatenate([(err * scale)[:, edge_valid], (err * inside)[:, cut], active * behind,
                            weights * (p[:, n_center:n_center + 3] - np.log(prior)),
                            anchor_weight * (p[:, :n_center] - anchor)], axis=1)
        jac = jac / diag[:, None, None]
        jac = np.concatenate([(jac * scale[..., None])[:, edge_valid], (jac * inside[..., None])[:, cut],
                              near_jac * active[..., None],
                              np.broadcast_to(prior_jac, (len(p),) + prior_jac.shape)], axis=1)
        if not len(pts):
            return r, jac
        outside, outside_jac = _outside_residuals(p, pts, floor_height)
        return np.concatenate([r, pts_w * outside], axis=1), np.concatenate([jac, pts_w * outside_jac], axis=1)

    lo_size, hi_size = np.log(0.05), np.log(size_range[1] * 1.2)
    lower = np.concatenate([np.full(n_center, -np.inf), np.full(3, lo_size), [-np.inf]])
    upper = np.concatenate([np.full(n_center, np.inf), np.full(3, hi_size), [np.inf]])
    clip = (np.log(0.06), np.log(size_range[1] * 1.15))
    starts = [np.concatenate([init_center[:n_center], np.clip(np.log(prior), *clip), [yaw]])
              for yaw in (0.0, np.pi / 4)]
    if init is not None:
        # Warm start from the previous box, plus a fresh start at yaw 0: a box first fitted from a few views can
        # sit in the wrong quarter-turn basin, and the warm start alone keeps it there (walk seeds 100-129: 2-3 of
        # 103 boxes 36-43 deg off with it, none with the fresh start; scipy's solver from the warm start: 1).
        starts = [np.concatenate([init.center[:n_center], np.clip(np.log(init.size), *clip), [init.yaw]]), starts[0]]
    # All starts in one batched solve; ftol 1e-5: 1e-6 took 13 % more evaluations on the benchmark walks' fits for
    # evaluation figures within 0.002 m and 0.2 deg (docs/experiments/frodo_association_history.md, "Latency").
    solutions, costs = soft_l1_least_squares(residuals_and_jacobian, np.array(starts), lower, upper, f_scale=0.05,
                                             max_evals=50, ftol=1e-5)
    best = solutions[int(np.argmin(costs))]
    size = np.exp(best[n_center:n_center + 3])
    center = np.array([best[0], best[1], floor_height + size[2] / 2 if on_floor else best[2]])
    size, yaw = canonical_yaw(size, float(best[-1]))
    return Box3D(center, size, yaw)
