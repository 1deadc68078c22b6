"""Placement hypotheses for the sparse stage: survive a wrong initial box (paper Sec. 5.3 "Initialization").

The paper initialises translation and scale from the object's 3D box (Sec. 5.1) and searches only the
rotation. On real captures that box can be 10-40 cm off and a factor 2 wrong in scale; the local
optimisation then cannot recover (the 10 cm truncation of Eg misses the landmarks, and the silhouettes
pull the shape into the part of the object it already covers). This module proposes placements from the
object's own evidence and scores them all in one batched pass; the sparse stage then compares the best few
with its exact energy next to the input box's own candidates (so the input placement is never lost).

Hypotheses (centre, scale, yaw):

- centre: the input box centre; the least-squares intersection of the rays through the detection boxes'
  centres (robust: Huber-reweighted, views whose detection touches the image border left out), or where the
  rays do not cross (a camera turning in place) the median of the landmarks in the detections' visual hull
  near the box (`landmark_centre`: a point of the visible surface, measured where a depth image comes); and
  points on the mean viewing direction through it (every 15 cm up to +-60 cm: depth is the weakly constrained
  direction of a walk, and an association box placed from one side can be decimetres off along it);
- scale: per centre and yaw, the median over views of observed / predicted detection-box diagonal (the
  projected size is nearly linear in the scale at a fixed centre; one fixed-point refinement), times
  {1/1.25, 1, 1.25}; and the input box's scale;
- yaw: the sparse stage's yaw candidates.

Score (lower is better), per hypothesis over all views at once:

    score = ws * (E_out + E_box) + wg * Eg_wide [+ w_floor * E_floor + w_height * E_size]

- E_out: the points -> mask half of the silhouette term Es (distance-transform lookup of the projected
  points, box diagonals), as in `sparse._Batch.silhouette` (truncation-aware: nothing beyond an image side
  the detection touches);
- E_floor, E_size: the support priors of `support.py` (beyond the paper), when a floor height / height range
  is given;
- E_box: mean absolute difference between the sides of the projected points' 2D box and the detection's
  box, in box diagonals; sides at the image border are skipped (truncated detections). A cheap stand-in
  for the mask -> points half of Es (which needs nearest neighbours per hypothesis) that penalises too
  small or displaced shapes, which E_out alone does not;
- Eg_wide: the geometry term (landmarks -> nearest surface point) truncated at `truncation` (0.3 m, three
  times the sparse stage's 10 cm: a wider basin), over the landmarks in the detections' visual hull
  (`on_silhouettes`: on the mask in most views that see them) near any hypothesis, the same set for all
  of them so that scores compare. The hull test, not a box, decides which landmarks are the object's: a
  wrong box would otherwise select the wrong ones, and a too large one floor and clutter points that
  reward too large placements.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from frodo_common.geometry import Box3D, yaw_matrix
from frodo_optim.adam import Adam
from frodo_optim import support

DEPTH_OFFSETS = (-0.6, -0.45, -0.3, -0.15, 0.15, 0.3, 0.45, 0.6)   # metres along the mean viewing direction
SCALE_FACTORS = (1 / 1.25, 1.0, 1.25)         # around the silhouette scale
SCALE_RANGE = (1 / 3, 3.0)                    # hypotheses' scales relative to the input box scale


@dataclass
class Hypothesis:
    """One placement: x_world = scale * R(yaw) * x_norm + translation; `source` names where it came from."""

    yaw: float
    translation: np.ndarray
    scale: float
    source: str
    score: float


def detection_boxes(views, crop_margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Detection boxes (V, 4) (u0, v0, u1, v1, pixels) recovered from the views' crops, and (V, 4) bool:
    that side touches the image border (the detection may be truncated there).

    `sparse.view_from_mask` grows the mask's box by crop_margin * size + 2 pixels per side.
    """
    crop = np.array([v.crop for v in views], dtype=np.float64)
    size = (crop[:, 2:] - crop[:, :2] - 4.0) / (1.0 + 2.0 * crop_margin)
    lo = crop[:, :2] + crop_margin * size + 2.0
    boxes = np.concatenate([lo, lo + size], 1)
    wh = np.array([v.image_size for v in views], dtype=np.float64)
    border = np.stack([boxes[:, 0] <= 1, boxes[:, 1] <= 1, boxes[:, 2] >= wh[:, 0] - 1, boxes[:, 3] >= wh[:, 1] - 1], 1)
    return boxes, border


def ray_centre(views, boxes: np.ndarray, border: np.ndarray, huber: float = 0.1) -> np.ndarray | None:
    """Least-squares intersection (3,) of the rays through the detection boxes' centres, or None.

    Views with a truncated detection are left out when at least two others remain; three Huber-reweighted
    passes (threshold `huber` metres of point-to-ray distance) limit the pull of occluded or mis-associated
    views. None when the rays do not fix a point (fewer than two, or nearly parallel).
    """
    keep = ~border.any(1)
    if keep.sum() < 2:
        keep = np.ones(len(views), bool)
    origins, dirs = [], []
    for v, b, k in zip(views, boxes, keep):
        if not k:
            continue
        d_cam = np.array([((b[0] + b[2]) / 2 - v.K[0, 2]) / v.K[0, 0], ((b[1] + b[3]) / 2 - v.K[1, 2]) / v.K[1, 1], 1.0])
        d = v.T_world_camera[:3, :3] @ d_cam
        origins.append(v.T_world_camera[:3, 3])
        dirs.append(d / np.linalg.norm(d))
    if len(origins) < 2:
        return None
    o, d = np.array(origins), np.array(dirs)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]                      # (N, 3, 3) orthogonal to each ray
    w = np.ones(len(o))
    centre = None
    for _ in range(3):
        A = np.einsum('n,nij->ij', w, proj)
        if np.linalg.eigvalsh(A)[0] < 1e-3 * w.sum():                           # rays (nearly) parallel
            return None
        centre = np.linalg.solve(A, np.einsum('n,nij,nj->i', w, proj, o))
        dist = np.linalg.norm(np.einsum('nij,nj->ni', proj, centre - o), axis=1)
        w = np.where(dist <= huber, 1.0, huber / np.maximum(dist, 1e-9))
    in_front = np.einsum('ni,ni->n', centre - o, d) > 0.1
    return centre if in_front.mean() > 0.5 else None


def landmark_centre(hull: np.ndarray, centre, reach: float, min_points: int = 10) -> np.ndarray | None:
    """The median (3,) of the visual-hull landmarks (`on_silhouettes`) within `reach` metres (horizontally) of the
    input box centre, or None with fewer than `min_points`: a point on the object's visible surface. Where the
    rays through the detections are nearly parallel (a walk that turns in place; `ray_centre` None) it is the
    only anchor along the view besides the box, and with a depth image it is measured, not inferred."""
    p = np.asarray(hull, dtype=np.float64).reshape(-1, 3)
    p = p[np.linalg.norm(p[:, :2] - np.asarray(centre, dtype=np.float64)[:2], axis=1) < reach]
    return np.median(p, axis=0) if len(p) >= min_points else None


def in_box(points: np.ndarray, center, size, yaw: float, margin: float = 0.0, floor_gap: float | None = None) -> np.ndarray:
    """(N,) bool: points (N, 3) inside the upright box grown by `margin` metres (floor_gap: the bottom is raised by
    this instead of lowered by the margin)."""
    local = (np.asarray(points, dtype=np.float64) - np.asarray(center, dtype=np.float64)) @ yaw_matrix(yaw)  # R^T d
    half = np.asarray(size, dtype=np.float64) / 2
    bottom = -half[2] + floor_gap if floor_gap is not None else -half[2] - margin
    return (np.abs(local[:, 0]) < half[0] + margin) & (np.abs(local[:, 1]) < half[1] + margin) & \
        (local[:, 2] > bottom) & (local[:, 2] < half[2] + margin)


def on_silhouettes(points: np.ndarray, views, batch, neighbour_boxes=(), tolerance: float = 0.03,
                   min_fraction: float = 0.75, min_views: int = 2) -> np.ndarray:
    """The landmarks (N, 3) -> (M, 3) that lie in the object's visual hull, independent of any box.

    A landmark is kept when, of the views that count for it, at least `min_views` do and at least `min_fraction`
    put it on the detection's mask (distance-transform value <= `tolerance` box diagonals inside the view's crop).
    A view counts when the landmark projects into its image, in front of the camera, except where it falls on
    another detection (`View.other`): there the neighbour may simply hide it (a chair in front of a low table),
    unless the landmark lies in a neighbour's box (`neighbour_boxes`, (centre, size, yaw)): then it is likely the
    neighbour's own (a chair pushed under a table, seen through the table top from above), and the view counts
    against it. Floor, wall, table-top clutter and neighbour landmarks fall off the mask in most views.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(1)]
    if len(p) == 0:
        return p.astype(np.float32)
    in_neighbour = np.zeros(len(p), bool)
    for centre, size, yaw in neighbour_boxes:
        in_neighbour |= in_box(p, centre, size, float(yaw))
    with torch.no_grad():
        uv, valid = batch.project(torch.as_tensor(p, dtype=torch.float32))                    # (V, N, 2), (V, N)
        wh = torch.as_tensor(np.array([v.image_size for v in views], dtype=np.float32))[:, None]
        in_image = valid & (uv >= 0).all(-1) & (uv < wh).all(-1)
        g = (uv - batch.crop_lo) / (batch.crop_hi - batch.crop_lo) * 2 - 1
        in_crop = (g.abs() <= 1).all(-1)
        d = F.grid_sample(batch.dt, g[:, None], mode='bilinear', padding_mode='border', align_corners=False)[:, 0, 0]
        on_other = in_crop & (F.grid_sample(batch.other, g[:, None], mode='nearest', padding_mode='border',
                                            align_corners=False)[:, 0, 0] > 0.5)
        on_mask = in_image & in_crop & (d <= tolerance) & ~on_other
        counted = in_image & (~on_other | torch.as_tensor(in_neighbour)[None])
        seen, on = counted.sum(0), on_mask.sum(0)
        keep = (seen >= min_views) & (on >= min_fraction * seen)
    return p[keep.numpy()].astype(np.float32)


def _rotations(yaws: torch.Tensor) -> torch.Tensor:
    """(Y,) -> (Y, 3, 3) rotations about z."""
    c, s = torch.cos(yaws), torch.sin(yaws)
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    return torch.stack([c, -s, zero, s, c, zero, zero, zero, one], 1).reshape(-1, 3, 3)


def _projected_boxes(batch, world: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World points (H, P, 3) -> their 2D boxes (H, V, 4) in every view and the pixels (V, H, P, 2)."""
    n_h, n_p = world.shape[:2]
    uv, _ = batch.project(world.reshape(-1, 3))                                 # (V, H*P, 2)
    uv = uv.reshape(uv.shape[0], n_h, n_p, 2)
    boxes = torch.cat([uv.amin(2), uv.amax(2)], -1).permute(1, 0, 2)             # (H, V, 4)
    return boxes, uv


def search(points_norm: np.ndarray, box, views, batch, slam_points: np.ndarray | None, yaws: np.ndarray, *,
           crop_margin: float, w_silhouette: float, w_geometry: float, truncation: float = 0.3, keep: int = 6,
           starts: int = 16, steps: int = 25, point_samples: int = 128, landmark_samples: int = 128,
           seed: int = 0, floor_height: float | None = None, w_floor: float = 0.0, floor_tolerance: float = 0.05,
           height_range: tuple[float, float] | None = None, w_height: float = 0.0,
           facing: np.ndarray | None = None, w_facing: float = 0.0) -> list[Hypothesis]:
    """Placement hypotheses of one object, best first (at most `keep`; empty when nothing scores finite).

    Every (centre, scale, yaw) of the grid in the module docstring is scored at once; the `starts` best
    (at most two yaws per centre and scale) then descend `steps` Adam steps in centre and log-scale on the
    same score (batched; yaw fixed), which turns the grid's coarse centres and scales into silhouette- and
    landmark-consistent ones; the results are scored again, near-duplicates dropped.

    points_norm (P, 3): the decoded shape (normalised frame); box (centre, size, yaw): the input box;
    views: the sparse stage's `View`s and batch: their `sparse._Batch`; slam_points (N, 3) world landmarks or
    None; yaws (Y,): yaw candidates. floor_height / height_range / facing (and their weights): the support priors
    of `support.py` (E_floor, E_size, E_facing) added to the score, as in the sparse energy; None: off.
    """
    rng = np.random.default_rng(seed)
    pts = np.asarray(points_norm, dtype=np.float64)
    if len(pts) > point_samples:
        pts = pts[rng.choice(len(pts), point_samples, replace=False)]
    lo, hi = pts.min(0), pts.max(0)
    mid, extent = (lo + hi) / 2, np.maximum(hi - lo, 1e-6)
    centre_b, size_b, _ = Box3D(*box)          # a Box3D or a (centre, size, yaw) triple
    scale_b = float(size_b[2] / extent[2])
    boxes_obs, border = detection_boxes(views, crop_margin)

    centres, names = [centre_b], ['input box']
    reach = 3.0 * max(float(size_b.max()), 0.5)
    hull = on_silhouettes(slam_points, views, batch) if w_geometry > 0 and slam_points is not None \
        and len(slam_points) else np.zeros((0, 3), np.float32)
    cams = np.array([v.T_world_camera[:3, 3] for v in views])
    # the landmarks' median only where the rays give no centre: next to a ray centre it made the search noisier
    # (docs/experiments/frodo_optim_history.md, "Facing prior and landmark centre")
    name, anchor = 'ray centre', ray_centre(views, boxes_obs, border)
    if anchor is None or not np.linalg.norm(anchor - centre_b) < reach:
        name, anchor = 'landmark centre', landmark_centre(hull, centre_b, reach)
    if anchor is not None and np.linalg.norm(anchor - centre_b) < reach:
        look = (anchor - cams).mean(0)
        look[2] = 0.0
        centres.append(anchor)
        names.append(name)
        if np.linalg.norm(look) > 1e-6:
            look /= np.linalg.norm(look)
            for off in DEPTH_OFFSETS:
                centres.append(anchor + off * look)
                names.append(f'{name} {100 * off:+.0f} cm')
    C, Y = len(centres), len(yaws)
    centres_t = torch.as_tensor(np.array(centres), dtype=torch.float32)                        # (C, 3)
    local = torch.as_tensor(pts - mid, dtype=torch.float32)                                    # (P, 3)
    rot = _rotations(torch.as_tensor(np.asarray(yaws, dtype=np.float64), dtype=torch.float32))  # (Y, 3, 3)
    shape_y = torch.einsum('yij,pj->ypi', rot, local)                                          # (Y, P, 3)

    obs = torch.as_tensor(boxes_obs, dtype=torch.float32)                                      # (V, 4)
    diag = batch.diag[:, 0]                                                                    # (V,)
    side_ok = torch.as_tensor(~border, dtype=torch.float32)                                    # (V, 4)
    obs_diag = torch.linalg.norm(obs[:, 2:] - obs[:, :2], dim=1)
    whole = torch.as_tensor(~border.any(1))
    if int(whole.sum()) < 2:
        whole = torch.ones_like(whole)

    with torch.no_grad():   # silhouette scale per (centre, yaw): observed / predicted box diagonal, twice
        s_sil = torch.full((C, Y), scale_b)
        for _ in range(2):
            world = s_sil[..., None, None] * shape_y[None] + centres_t[:, None, None]          # (C, Y, P, 3)
            pred, _ = _projected_boxes(batch, world.reshape(C * Y, -1, 3))
            pred_diag = torch.linalg.norm(pred[..., 2:] - pred[..., :2], dim=-1).clamp_min(1.0)
            ratio = (obs_diag[None] / pred_diag)[:, whole].median(1).values.reshape(C, Y)
            s_sil = (s_sil * ratio).clamp(scale_b * SCALE_RANGE[0], scale_b * SCALE_RANGE[1])
    scales = torch.cat([s_sil[..., None] * torch.tensor(SCALE_FACTORS), torch.full((C, Y, 1), scale_b)], -1)
    S = scales.shape[-1]

    marks_t = None
    if w_geometry > 0 and slam_points is not None and len(slam_points):
        marks = _landmarks(hull, centres, float(scales.max()) * extent / 2, rng, landmark_samples)
        marks_t = torch.as_tensor(marks, dtype=torch.float32) if len(marks) >= 5 else None

    def score(centre: torch.Tensor, log_s: torch.Tensor, yaw_idx: torch.Tensor) -> torch.Tensor:
        """Hypotheses (H, 3), (H,), (H,) long -> score (H,) (differentiable in centre and log_s)."""
        world = log_s.exp()[:, None, None] * shape_y[yaw_idx] + centre[:, None]                # (H, P, 3)
        pred, uv = _projected_boxes(batch, world)
        flat = uv.flatten(1, 2)                                                                 # (V, H*P, 2)
        # E_out: points outside the mask (distance-transform lookup + distance outside the crop), as in Es
        g = (flat - batch.crop_lo) / (batch.crop_hi - batch.crop_lo) * 2 - 1
        inner = F.grid_sample(batch.dt, g[:, None], mode='bilinear', padding_mode='border', align_corners=False)[:, 0, 0]
        out = torch.maximum(batch.crop_lo - flat, flat - batch.crop_hi).clamp_min(0)
        d_out = (inner + (out.square().sum(-1) + 1e-6).sqrt() / batch.diag) * (~batch.unknown(flat)).float()  # (V, H*P)
        e_out = d_out.reshape(len(views), len(centre), -1).mean(2).mean(0)                      # (H,)
        # E_box: sides of the projected box vs the detection's, box diagonals, truncated at 0.3 (a side cut
        # by an occluder must not dominate), sides on the image border skipped
        side = ((pred - obs[None]).abs() / diag[None, :, None]).clamp(max=0.3) * side_ok[None]
        e_box = (side.sum(2) / side_ok.sum(1).clamp_min(1.0)[None]).mean(1)                    # (H,)
        total = w_silhouette * (e_out + e_box)
        if marks_t is not None:
            with torch.no_grad():   # nearest neighbours without gradient, their distances with (cheap backward)
                nearest = torch.cdist(marks_t[None].expand(len(world), -1, -1), world).min(2).indices   # (H, L)
            matched = torch.gather(world, 1, nearest[..., None].expand(-1, -1, 3))
            d = ((marks_t[None] - matched).square().sum(-1) + 1e-9).sqrt()                     # (H, L)
            total = total + w_geometry * d.clamp(max=truncation).mean(1) / truncation
        if floor_height is not None and w_floor > 0:
            total = total + w_floor * support.floor_energy(world, floor_height, floor_tolerance)
        if height_range is not None and w_height > 0:
            total = total + w_height * support.height_energy(world, height_range)
        if facing is not None and w_facing > 0:
            total = total + w_facing * support.facing_energy(rot[yaw_idx][:, :2, 0], facing)
        return total

    # grid: every (centre, scale, yaw), in chunks
    c_idx, s_idx, y_idx = torch.meshgrid(torch.arange(C), torch.arange(S), torch.arange(Y), indexing='ij')
    c_idx, s_idx, y_idx = c_idx.flatten(), s_idx.flatten(), y_idx.flatten()
    grid_log_s = scales[c_idx, y_idx, s_idx].log()
    with torch.no_grad():
        grid = torch.cat([score(centres_t[c], ls, y) for c, ls, y in
                          zip(c_idx.split(128), grid_log_s.split(128), y_idx.split(128))])
    picked, per_pair = [], {}
    for h in torch.argsort(grid).tolist():
        pair = (int(c_idx[h]), int(s_idx[h]))
        if torch.isfinite(grid[h]) and per_pair.get(pair, 0) < 2:
            per_pair[pair] = per_pair.get(pair, 0) + 1
            picked.append(h)
            if len(picked) >= starts:
                break
    if not picked:
        return []
    picked_t = torch.tensor(picked)
    centre = centres_t[c_idx[picked_t]].clone().requires_grad_(True)
    log_s = grid_log_s[picked_t].clone().requires_grad_(True)
    yaw_idx = y_idx[picked_t]
    opt = Adam([{'params': [centre], 'lr': 0.02}, {'params': [log_s], 'lr': 0.03}])
    for _ in range(steps):
        opt.zero_grad()
        score(centre, log_s, yaw_idx).sum().backward()
        opt.step()
    with torch.no_grad():
        final = score(centre, log_s, yaw_idx)
    chosen: list[Hypothesis] = []
    for k in torch.argsort(final).tolist():
        value = float(final[k])
        c, sc, y = centre[k].detach().double().numpy(), math.exp(float(log_s[k].detach())), int(yaw_idx[k])
        if not math.isfinite(value) or any(h.yaw == float(yaws[y]) and abs(math.log(h.scale / sc)) < 0.03 and
                                           np.linalg.norm(h.translation + h.scale * _yaw(h.yaw) @ mid - c) < 0.03
                                           for h in chosen):
            continue
        h = picked[k]
        kind = 'box scale' if int(s_idx[h]) == S - 1 else f'silhouette scale x{SCALE_FACTORS[int(s_idx[h])]:.2f}'
        chosen.append(Hypothesis(float(yaws[y]), c - sc * _yaw(float(yaws[y])) @ mid, sc,
                                 f'{names[int(c_idx[h])]}, {kind}, descended', value))
        if len(chosen) >= keep:
            break
    return chosen


def _yaw(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def placed_box(points_norm: np.ndarray, yaw: float, translation, scale: float):
    """Upright world box (centre (3,), size (3,), yaw) of the shape points (P, 3) under a placement."""
    lo, hi = np.min(points_norm, 0), np.max(points_norm, 0)
    return np.asarray(translation, dtype=np.float64) + scale * _yaw(yaw) @ ((lo + hi) / 2), scale * (hi - lo), float(yaw)


def _landmarks(slam_points: np.ndarray, centres: list[np.ndarray], half_extent: np.ndarray,
               rng: np.random.Generator, limit: int) -> np.ndarray:
    """Landmarks (N, 3) that any hypothesis can reach: within the largest hypothesis' half-extent (plus the
    0.3 m truncation) of a hypothesis centre; at most `limit`, drawn at random."""
    p = np.asarray(slam_points, dtype=np.float64)
    p = p[np.isfinite(p).all(1)]
    radius = float(np.linalg.norm(half_extent[:2])) + 0.3
    near = np.zeros(len(p), bool)
    for c in centres:
        near |= (np.linalg.norm(p[:, :2] - c[:2], axis=1) < radius) & (np.abs(p[:, 2] - c[2]) < half_extent[2] + 0.3)
    p = p[near]
    if len(p) > limit:
        p = p[rng.choice(len(p), limit, replace=False)]
    return p.astype(np.float32)
