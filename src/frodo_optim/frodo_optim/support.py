"""Physical priors of the sparse and dense stages (beyond the paper; issue 9 item 4).

The paper's energy (Sec. 5.3, Eq. 3) has silhouette, photometric, landmark and code terms only. Nothing in
it knows that chairs and tables stand on the floor or how tall furniture is, and on hand-held captures
(close range, objects cut by the image border, few textured landmarks) that freedom is what the optimiser
uses badly: a shape too tall for its footprint is fitted 20-30 % too large and sunk below the floor so that
its silhouettes still cover the masks (measured: tables 28 cm below the floor at 1.3x the true scale on the
real-capture tuning set). Two soft terms rule these placements out:

- **E_floor** (support): the object's lowest surface points lie on the floor plane z = h_f (world z up,
  CONTRACT.md). Bottom b = mean z of the `k` lowest points; E_floor = huber((b - h_f) / tolerance), with
  huber(x) = x^2 for |x| <= 1 and 2|x| - 1 beyond (a wrong floor estimate costs linearly, not
  quadratically). Both directions count: sunk objects and floating ones.
- **E_size** (class height): the object's metric height H (extent of its points along z) lies in its
  class's range [H_min, H_max] (`frodo_common.categories.Category.height_range`, shared with the
  association): E_size = relu(log(H / H_max))^2 + relu(log(H_min / H))^2, zero inside the range.

- **E_facing** (a chair at a table faces it): for an object of a class in `FACES` whose footprint lies within
  `max_gap` of a table's (`facing_direction`), E_facing = (1 - cos a) / 2, a the horizontal angle between the
  object's front (+x of the normalised frame, ARCHITECTURE.md) and the inward normal of the table side nearest to
  it: 0 facing the table, 1 turned away. A walk past a table sees the chairs behind it as backrests above the top
  and legs below it; the seat is hidden by the table, and a chair facing the table or turned away from it fits
  those views alike (issue 27, the real kitchen's "chairs seen only as backrests behind the table"). The term
  breaks that tie the way dining and desk chairs stand; a flip costs the sparse energy up to w_facing (0.1).
  Only views from one side leave that tie: the weight is scaled by `one_sided_share`, 1 - (the arc of
  directions from the object that holds its cameras) / 180 degrees, so views of front and back decide alone.

The floor height h_f is estimated from the scene, not assumed (`floor_height`): the median bottom of the
association's boxes of floor-standing classes (robust to a few wrong boxes), refined to the densest
horizontal layer of landmarks near it when there is one (the floor's own texture points).
"""
from __future__ import annotations

import math
from typing import Iterable

import numpy as np
import torch

from frodo_common.categories import BY_NAME
from frodo_common.geometry import bearing_span, box_corners, yaw_matrix

FLOOR_CLASSES = ('chair', 'dining table', 'couch', 'bed')   # stand on the floor (an object on a table does not)
FACES = {'chair': ('dining table',)}                         # a chair at a table faces it (E_facing)


def floor_height(boxes: Iterable, landmarks: np.ndarray | None = None, search: float = 0.15, layer: float = 0.02,
                 min_layer_points: int = 20, lowest_fraction: float = 0.5) -> float | None:
    """Floor height (m, world z) from the bottoms of floor-standing objects' boxes and landmarks; None if no box.

    boxes: (centre (3,), size (3,), yaw) of the objects (association boxes of FLOOR_CLASSES).
    The median bottom is the estimate; when `landmarks` (N, 3) hold horizontal layers of at least
    `min_layer_points` points `layer` metres thick within `search` metres of it, the lowest layer holding at least
    `lowest_fraction` of the densest one's points gives the floor (its densest window's median z): the floor's own
    points are a direct measurement, the box bottoms an inference of the association (which may itself assume a
    floor). The lowest, not the densest: object parts near the floor (pedestal feet, stretchers, a skirting
    board) form layers above it, never below (room `realcapture-tune2-8209`: a layer 11 cm up held more points
    than the floor's and lifted every object off the floor).
    """
    bottoms = [float(c[2]) - 0.5 * float(s[2]) for c, s, _ in boxes
               if np.isfinite(np.asarray(c, dtype=np.float64)).all() and np.isfinite(np.asarray(s, dtype=np.float64)).all()]
    if not bottoms:
        return None
    floor = float(np.median(bottoms))
    if landmarks is not None and len(landmarks):
        z = np.asarray(landmarks, dtype=np.float64).reshape(-1, 3)[:, 2]
        z = np.sort(z[np.isfinite(z) & (np.abs(z - floor) <= search + layer)])
        if len(z) >= min_layer_points:
            hi = np.searchsorted(z, z + layer, side='right')       # points in [z_i, z_i + layer]
            counts = hi - np.arange(len(z))
            dense = np.flatnonzero(counts >= max(min_layer_points, lowest_fraction * counts.max()))
            if len(dense):
                lowest = int(dense[0])
                # the layer's peak: the densest window starting within one layer thickness of its lowest one
                i = lowest + int(np.argmax(counts[lowest:hi[lowest]]))
                floor = float(np.median(z[i:hi[i]]))
    return floor


def bottom(world_pts: torch.Tensor, k: int = 2) -> torch.Tensor:
    """Mean z (...) of the k lowest of the world points (..., P, 3) (differentiable; robust to a stray point)."""
    k = max(1, min(int(k), world_pts.shape[-2]))
    return world_pts[..., 2].topk(k, dim=-1, largest=False).values.mean(-1)


def huber(x: torch.Tensor) -> torch.Tensor:
    """x^2 for |x| <= 1, 2|x| - 1 beyond (continuous value and slope)."""
    a = x.abs()
    return torch.where(a <= 1, x * x, 2 * a - 1)


def floor_energy(world_pts: torch.Tensor, floor: float, tolerance: float = 0.05, k: int = 2) -> torch.Tensor:
    """E_floor (...): huber((bottom - floor) / tolerance) of world points (..., P, 3)."""
    return huber((bottom(world_pts, k) - float(floor)) / float(tolerance))


def height_energy(world_pts: torch.Tensor, height_range: tuple[float, float]) -> torch.Tensor:
    """E_size (...): squared log-distance of the points' (..., P, 3) z extent to [h_min, h_max] (0 inside)."""
    h = (world_pts[..., 2].amax(-1) - world_pts[..., 2].amin(-1)).clamp_min(1e-6)
    lo, hi = (float(v) for v in height_range)
    return torch.relu(torch.log(h / hi)).square() + torch.relu(torch.log(lo / h)).square()


def scene_floor(tracks: dict, landmarks: np.ndarray | None = None) -> float | None:
    """`floor_height` of the association's tracks {id: (class name, (centre, size, yaw))} of FLOOR_CLASSES."""
    return floor_height([box for name, box in tracks.values() if name in FLOOR_CLASSES], landmarks)


def class_height_range(class_name: str) -> tuple[float, float] | None:
    """The class's metric height range (`Category.height_range`), None for an unknown class or no range."""
    category = BY_NAME.get(class_name)
    if category is None or not np.isfinite(category.height_range[1]):
        return None
    return category.height_range


def _footprint(box) -> np.ndarray:
    """(4, 2) corners of an upright box's (centre, size, yaw) footprint, in order around it."""
    center, size, yaw = box
    return box_corners(center, size, float(yaw))[[0, 4, 6, 2], :2]      # bottom corners (-,-) (+,-) (+,+) (-,+)


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances (N,) of points (N, 2) to the segment a-b."""
    ab = b - a
    t = np.clip((p - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def footprint_gap(a, b) -> float:
    """Horizontal distance (m) between the footprints of two upright boxes (centre, size, yaw); 0 where they
    overlap. Two convex polygons overlap unless an edge normal of one separates them; apart, their distance is
    that of a corner of one to an edge of the other."""
    pa, pb = _footprint(a), _footprint(b)
    separated = False
    for poly in (pa, pb):
        for k in range(2):
            edge = poly[k + 1] - poly[k]
            normal = np.array([-edge[1], edge[0]])
            if (pa @ normal).max() < (pb @ normal).min() or (pb @ normal).max() < (pa @ normal).min():
                separated = True
    if not separated:
        return 0.0
    return float(min(_point_segment_distance(p, q[k], q[(k + 1) % 4]).min()
                     for p, q in ((pa, pb), (pb, pa)) for k in range(4)))


def facing_direction(class_name: str, box, tracks: Iterable, max_gap: float = 0.3) -> np.ndarray | None:
    """The unit horizontal direction (2,) an object of `class_name` with the upright box (centre, size, yaw) is
    expected to face (E_facing), or None: the inward normal of the side nearest to the box centre of the nearest
    table (a class in FACES[class_name]) among `tracks` [(class name, box)] whose footprint is within `max_gap`
    metres of the object's (chairs tucked under it: 0)."""
    faced = FACES.get(class_name, ())
    own_center = np.asarray(tuple(box)[0], dtype=np.float64)
    if not faced or not np.isfinite(own_center).all():
        return None
    tables = [tuple(other) for name, other in tracks if name in faced]
    near = [(footprint_gap(box, other), other) for other in tables
            if np.isfinite(np.asarray(other[0], dtype=np.float64)).all()
            and np.isfinite(np.asarray(other[1], dtype=np.float64)).all()]
    near = [(gap, other) for gap, other in near if gap <= max_gap]
    if not near:
        return None
    _, (center, size, yaw) = min(near, key=lambda g: g[0])
    axes = yaw_matrix(float(yaw))[:2, :2].T        # rows: the table's own x and y axes in the world
    local = axes @ (own_center[:2] - np.asarray(center, dtype=np.float64)[:2])
    side = int(np.argmin(0.5 * np.asarray(size, dtype=np.float64)[:2] - np.abs(local)))
    return -math.copysign(1.0, local[side]) * axes[side]


def facing_energy(front_xy: torch.Tensor, direction) -> torch.Tensor:
    """E_facing (...): (1 - cos a) / 2 of the angle a between horizontal front vectors (..., 2) (any length) and
    the unit direction (2,) to face."""
    d = torch.as_tensor(np.asarray(direction, dtype=np.float32), dtype=front_xy.dtype, device=front_xy.device)
    cos = (front_xy * d).sum(-1) / front_xy.norm(dim=-1).clamp_min(1e-9)
    return 0.5 * (1.0 - cos)


def one_sided_share(camera_centres: np.ndarray, centre) -> float:
    """The share (0-1) of w_facing that E_facing gets: 1 - the arc of directions from the object that holds its
    cameras (`geometry.bearing_span`, degrees) / 180, at least 0. The tie it breaks
    (front or back, with the seat hidden) is left only by views from one side; views from opposite sides see
    front and back, and there a prior strong enough for the one-sided case overrode them (realcapture-tune2,
    docs/experiments/frodo_optim_history.md). On the tuning sets the chairs at tables are seen over 2-43 degrees
    on the walks (median 10) and 91-300 degrees on the handheld captures (median 254)."""
    return max(0.0, 1.0 - bearing_span(camera_centres, centre) / 180.0)


def facing_weight(weight: float, direction, camera_centres, centre) -> float:
    """E_facing's weight in a stage: `weight` times `one_sided_share` of its cameras about `centre`; 0 where there
    is no finite direction to face (None: no table near) or the weight is off."""
    if direction is None or not np.isfinite(direction).all() or weight <= 0:
        return 0.0
    return weight * one_sided_share(camera_centres, centre)
