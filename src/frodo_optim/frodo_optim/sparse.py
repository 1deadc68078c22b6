"""Sparse optimisation stage (paper Sec. 5.3, "Initialization" and "Sparse Optimization"); torch + numpy only.

Per object, the 2048 surface points Gs(z) of the prior's point decoder (paper Sec. 4, PSGN branch) are
placed by an upright similarity x_world = s * R(yaw) * x_norm + t and compared with the object's
detections in a bounded set of views:

    E = ws * Es + wg * Eg + wr * Er

- Es (silhouette, paper "Es"): symmetric 2D chamfer between the projected points and the instance mask,
  per view, in units of the detection's box diagonal (resolution independent). The points -> mask half
  reads a distance transform of the mask (cropped around the detection, `DT_SIZE`^2 cells, bilinear,
  differentiable); the mask -> points half matches `mask_samples` pixels sampled on the mask to their
  nearest projected point (nearest neighbours found without gradient, distances with gradient).
  Pixels outside the image or covered by *other* detections are "unknown" (distance 0): a truncated
  or occluded object is not pulled into its visible part. With a registered depth image (`free_space`,
  beyond the paper) so is a point that lies more than `free_space_margin` behind the surface measured at its
  pixel: hidden by it (clutter, a missed detection), it would not be seen.
- Eg (geometry, paper "Eg"): one-sided 3D chamfer from SLAM landmarks inside the object's box to the
  surface points, truncated at `geometry_truncation` metres and divided by it. Beyond the paper
  (`landmark_filter`): only those in the detections' visual hull (`placement.on_silhouettes`), the set
  returned as `SparseResult.landmarks` for the dense stage. With a depth image the object's masked depth
  points join the landmarks (`depth_points`, `with_depth_points`; beyond the paper).
- Er (code regulariser, paper ||z||^2 / sigma^2): mean over dimensions of ((z - mu) / sigma)^2 with mu,
  sigma the per-dimension mean and spread of the prior's training codes (the paper's zero-mean prior,
  for codes that are not centred).
- Ep (photometric consistency, paper Eq. 4): Huber colour differences of the points between each view and
  its next views, visible points only (`photometric.py`), when colour views are passed (weight w_photometric).
- E_floor, E_size, E_facing (beyond the paper, `support.py`): the object's lowest points on the estimated floor
  plane (when `floor_height` is given), its metric height inside its class's range (when `height_range` is
  given) and its front towards the table it stands at (when `facing` is given); weights w_floor, w_height,
  w_facing.

Truncation (beyond the paper): a projected point beyond an image side that the detection touches is
unknown (the object may continue there), so the points -> mask half does not pull a truncated object back
into the image (`truncation_aware`).

Initialisation (paper: "exhaustive search for the best rotation about the gravity direction"):
translation and scale from the association's 3D box (as `core.place_from_box`: scale = box height over
the decoded shape's height, the shape's box centre at the box centre), yaw = the best of
`yaw_candidates` evenly spaced angles under the energy above with the initial code; next to these, the
placement hypotheses of `placement.py` (centre and scale from the detections, for a wrong box). Then code,
yaw, translation and log-scale are optimised jointly with Adam for a fixed number of iterations, from the
best box start, the best hypothesis and the best code restart (`code_restarts`: the lowest-energy training
codes, beyond the paper); a hypothesis or restart replaces the box run only when clearly better on the same
landmarks (`placement_margin` lower in total, silhouette term no worse). The state with the lowest energy
seen (the initial one included) is returned, so a diverging run falls back, and the input box placement is
returned with a reason when nothing lower than it is found.
"""
from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field
from enum import Enum
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import distance_transform_edt

from frodo_common.frames import usable_depth
from frodo_common.geometry import Box3D
from frodo_optim.adam import Adam
from frodo_optim.photometric import checked_view_inputs, photometric_energy

from frodo_optim import placement, support

DT_SIZE = 64          # cells per side of a view's distance-transform crop
DT_MARGIN = 0.6       # the crop extends this fraction of the box size beyond each side of the detection box
STOP_POLL = 16        # code-restart scoring polls should_stop every this many energies (~35-75 ms on a 2-core CPU)


@dataclass
class SparseConfig:
    """Parameters of the sparse stage (the node's `sparse_*` parameters)."""

    iterations: int = 40
    max_views: int = 16
    mask_samples: int = 96
    point_samples: int = 384          # projected points matched against mask samples (subset of the 2048)
    yaw_candidates: int = 24
    w_silhouette: float = 1.0
    w_geometry: float = 0.5
    w_code: float = 0.01
    w_photometric: float = 0.0        # Ep (photometric.py); needs refine(..., photometric=ViewBatch)
    geometry_truncation: float = 0.1  # metres
    lr_code: float = 0.02             # beyond 0.005: lets the code leave the encoder's
                                      # (docs/experiments/frodo_optim_history.md, "Code freedom")
    lr_translation: float = 0.01      # metres per step (Adam)
    lr_yaw: float = 0.02              # radians per step
    lr_log_scale: float = 0.01
    optimise_code: bool = True
    placement_search: bool = True     # also start from placement.py's hypotheses (a wrong box); false: box only
    placement_keep: int = 6           # hypotheses compared with the exact energy
    placement_truncation: float = 0.3  # metres, Eg truncation when scoring hypotheses (wider basin)
    placement_margin: float = 0.05    # a hypothesis must end this fraction below the box start's energy to win
    truncation_aware: bool = True     # points beyond an image side the detection touches: unknown (no cost)
    w_floor: float = 0.05             # E_floor (support.py); needs refine(..., floor_height=h)
    floor_tolerance: float = 0.05     # metres: E_floor = huber((bottom - floor) / floor_tolerance)
    w_height: float = 1.0             # E_size (support.py); needs refine(..., height_range=(lo, hi))
    w_facing: float = 0.1             # E_facing (support.py), times support.one_sided_share; needs refine(..., facing=)
    code_restarts: int = 4            # also start from the best of the k lowest-energy training codes (0: off)
    restart_screen_views: int = 8     # training codes and their yaws are screened on this many views (0: all views)
    restart_screen_keep: int = 3      # the screen keeps this many times code_restarts candidates for the exact energy
    landmark_filter: bool = True      # box starts and dense stage too use only visual-hull landmarks (False: paper)
    landmark_tolerance: float = 0.06  # box diagonals off the mask a landmark may project (placement.on_silhouettes)
    depth_points: int = 1024          # registered-depth points of the object's masks joining the landmarks of Eg (0: off)
    free_space: bool = True           # with depth: a point off the mask costs nothing behind the surface measured there
    free_space_margin: float = 0.05   # metres in front of that surface within which the point still costs
    seed: int = 0


@dataclass
class View:
    """One kept associated detection: camera (K, T_world_camera) and the mask in compact form.

    mask_uv (M, 2) float32 pixels sampled on the mask; dt (DT_SIZE, DT_SIZE) float16 distance to the mask
    (units of the box diagonal, 0 on the mask and where unknown) over the crop `crop` = (u0, v0, u1, v1);
    diag: detection box diagonal in pixels; image_size (width, height); other (DT_SIZE, DT_SIZE) bool: cells
    on another detection (None: none), which the landmark selection (`placement.on_silhouettes`) tells apart
    from the object's own mask; depth (DT_SIZE, DT_SIZE) float16 registered depth over the crop (camera z,
    metres; NaN: none) or None.
    """

    K: np.ndarray
    T_world_camera: np.ndarray
    mask_uv: np.ndarray
    dt: np.ndarray
    crop: tuple[float, float, float, float]
    diag: float
    image_size: tuple[int, int]
    other: np.ndarray | None = None
    depth: np.ndarray | None = None

    def nbytes(self) -> int:
        return (self.mask_uv.nbytes + self.dt.nbytes + (0 if self.other is None else self.other.nbytes)
                + (0 if self.depth is None else self.depth.nbytes) + 200)


class SparseStatus(Enum):
    """How `refine` ended (a value for callers to act on; `SparseResult.reason` is the text for people)."""

    OPTIMISED = 'optimised'              # a placement below the input's energy was found
    INPUT_KEPT = 'input kept'            # ok, but nothing lower than the input placement was found
    INVALID_INPUT = 'invalid input'      # non-finite code or box, or decoded points not finite
    NO_VIEWS = 'no usable views'
    NON_FINITE_ENERGY = 'non-finite energy'
    INTERRUPTED = 'interrupted'          # should_stop() said so (polled every iteration): nothing kept, run it again


@dataclass
class SparseResult:
    """Outcome of `refine`. `ok` False: the initial estimate is returned unchanged; `status` says why (`reason`
    in words)."""

    code: np.ndarray
    T_world_object: np.ndarray
    scale: float
    yaw: float
    translation: np.ndarray
    ok: bool = True
    reason: str = ''
    status: SparseStatus = SparseStatus.OPTIMISED
    energies: dict[str, float] = field(default_factory=dict)
    initial_energies: dict[str, float] = field(default_factory=dict)
    init_yaw: float = 0.0
    placement: str = ''               # the initial placement that won ('input box', 'ray centre, ...')
    input_energy: float = math.nan    # energy of the input box placement (best of its 4 symmetric yaws)
    iterations: int = 0               # of the chosen run
    total_iterations: int = 0         # of every run (box start, placement hypothesis, code restart)
    best_iteration: int = 0
    views: int = 0
    seconds: float = 0.0
    landmarks: np.ndarray | None = None  # (N, 3) the visual-hull landmarks used (`landmark_filter`), for the dense stage
    # End states (code, T_world_object, placement) of the other runs (box start, placement hypothesis, code
    # restart) that were not chosen: further starts for the dense stage (`dense.refine_dense_starts`)
    alternatives: list[tuple[np.ndarray, np.ndarray, str]] = field(default_factory=list)


# ------------------------------------------------------------------ view data
def view_from_mask(K, T_world_camera, mask: np.ndarray, n_samples: int = 128, unknown: np.ndarray | None = None,
                   rng: np.random.Generator | None = None, depth_m: np.ndarray | None = None) -> View | None:
    """Compact view data from a full-resolution boolean mask; None if the mask or camera is unusable.

    unknown: optional bool (H, W), pixels whose state is unknown (other detections, possible occluders);
    depth_m: optional (H, W) registered depth, metres (0 / NaN: none), kept on the crop's grid (`View.depth`).
    """
    checked = checked_view_inputs(K, T_world_camera, mask)
    if checked is None:
        return None
    K, T, mask, ys, xs = checked
    rng = rng if rng is not None else np.random.default_rng(0)
    h, w = mask.shape
    x0, y0, x1, y1 = xs.min(), ys.min(), xs.max() + 1, ys.max() + 1
    diag = float(math.hypot(x1 - x0, y1 - y0))
    pick = rng.choice(len(xs), size=n_samples, replace=len(xs) < n_samples)
    mask_uv = np.stack([xs[pick], ys[pick]], 1).astype(np.float32) + rng.random((n_samples, 2), dtype=np.float32)
    mx, my = DT_MARGIN * (x1 - x0) + 2, DT_MARGIN * (y1 - y0) + 2
    crop = (x0 - mx, y0 - my, x1 + mx, y1 + my)
    # distance transform at full resolution inside the (clipped) crop, then sampled on the DT_SIZE grid
    cx0, cy0 = int(max(0, math.floor(crop[0]))), int(max(0, math.floor(crop[1])))
    cx1, cy1 = int(min(w, math.ceil(crop[2]))), int(min(h, math.ceil(crop[3])))
    sub = mask[cy0:cy1, cx0:cx1]
    dist = distance_transform_edt(~sub).astype(np.float32) / max(diag, 1.0)
    other_sub = None
    if unknown is not None:
        other_sub = np.asarray(unknown, dtype=bool)[cy0:cy1, cx0:cx1] & ~sub
        dist[other_sub] = 0.0
    gu = crop[0] + (np.arange(DT_SIZE) + 0.5) * (crop[2] - crop[0]) / DT_SIZE
    gv = crop[1] + (np.arange(DT_SIZE) + 0.5) * (crop[3] - crop[1]) / DT_SIZE
    iu, iv = np.floor(gu).astype(int), np.floor(gv).astype(int)
    inside = ((iv >= 0) & (iv < h))[:, None] & ((iu >= 0) & (iu < w))[None, :]
    dt = np.zeros((DT_SIZE, DT_SIZE), np.float32)          # outside the image: unknown
    ii, jj = np.nonzero(inside)
    dt[ii, jj] = dist[iv[ii] - cy0, iu[jj] - cx0]
    other = None
    if other_sub is not None and other_sub.any():
        other = np.zeros((DT_SIZE, DT_SIZE), bool)
        other[ii, jj] = other_sub[iv[ii] - cy0, iu[jj] - cx0]
    depth = None
    if depth_m is not None and np.shape(depth_m) == mask.shape:
        depth = np.full((DT_SIZE, DT_SIZE), np.nan, np.float16)
        depth[ii, jj] = usable_depth(np.asarray(depth_m)[iv[ii], iu[jj]])
    return View(K, T, mask_uv, dt.astype(np.float16), tuple(float(c) for c in crop), diag, (int(w), int(h)), other,
                depth)


def select_views(views: list, max_views: int) -> list:
    """At most max_views views spread evenly over the list (kept in order)."""
    if len(views) <= max_views:
        return list(views)
    idx = np.unique(np.round(np.linspace(0, len(views) - 1, max_views)).astype(int))
    return [views[i] for i in idx]


# ------------------------------------------------------------------ energy
class _Batch:
    """Views stacked as tensors. truncation_aware: points beyond an image side that the detection touches
    cost nothing in the points -> mask half (unknown, like pixels outside the image inside the crop).
    free_space_margin (metres; None: off): with the views' registered depth, a point that lies more than this
    behind the surface measured at its pixel costs nothing there either (beyond the paper): hidden by what was
    measured (an undetected occluder, another detection, the object's own front), it would not be seen."""

    def __init__(self, views: list[View], truncation_aware: bool = True, free_space_margin: float | None = None):
        T_cw = np.stack([np.linalg.inv(v.T_world_camera) for v in views])
        self.R = torch.as_tensor(T_cw[:, :3, :3], dtype=torch.float32)            # (V, 3, 3)
        self.t = torch.as_tensor(T_cw[:, :3, 3], dtype=torch.float32)              # (V, 3)
        K = np.stack([v.K for v in views])
        self.f = torch.as_tensor(K[:, [0, 1], [0, 1]], dtype=torch.float32)       # (V, 2)
        self.c = torch.as_tensor(K[:, :2, 2], dtype=torch.float32)                 # (V, 2)
        self.mask_uv = torch.as_tensor(np.stack([v.mask_uv for v in views]))      # (V, M, 2)
        self.mask_u, self.mask_v = self.mask_uv[..., 0].contiguous(), self.mask_uv[..., 1].contiguous()
        self.dt = torch.as_tensor(np.stack([v.dt for v in views]).astype(np.float32))[:, None]       # (V, 1, S, S)
        self.other = torch.as_tensor(np.stack([np.zeros(v.dt.shape, bool) if v.other is None else v.other
                                               for v in views]).astype(np.float32))[:, None]          # (V, 1, S, S)
        crop = np.array([v.crop for v in views], dtype=np.float32)
        self.crop_lo = torch.as_tensor(crop[:, :2])[:, None]                       # (V, 1, 2)
        self.crop_hi = torch.as_tensor(crop[:, 2:])[:, None]
        self.diag = torch.as_tensor([v.diag for v in views], dtype=torch.float32)[:, None]  # (V, 1)
        self.image_wh = torch.as_tensor(np.array([v.image_size for v in views], dtype=np.float32))[:, None]  # (V, 1, 2)
        _, border = placement.detection_boxes(views, DT_MARGIN)
        self.border = torch.as_tensor(border & truncation_aware)[:, None]           # (V, 1, 4) u0, v0, u1, v1
        self.depth, self.free_space_margin = None, free_space_margin
        if free_space_margin is not None and any(v.depth is not None for v in views):
            depth = np.stack([np.full(v.dt.shape, np.inf, np.float32) if v.depth is None
                              else np.nan_to_num(v.depth.astype(np.float32), nan=np.inf) for v in views])
            self.depth = torch.as_tensor(depth)[:, None]                                # (V, 1, S, S), inf: none

    def unknown(self, uv: torch.Tensor) -> torch.Tensor:
        """(V, P) bool: pixels uv (V, P, 2) beyond an image side that the view's detection touches."""
        beyond = torch.cat([uv < 0, uv >= self.image_wh], -1)                        # (V, P, 4)
        return (beyond & self.border).any(-1)

    def project(self, pts: torch.Tensor, with_depth: bool = False):
        """World points (P, 3) -> pixels (V, P, 2) and a validity mask (V, P) (in front of the camera), and with
        with_depth their camera depths (V, P)."""
        pc = torch.einsum('vij,pj->vpi', self.R, pts) + self.t[:, None]
        z = pc[..., 2]
        valid = z > 0.05
        uv = pc[..., :2] / z.clamp_min(0.05)[..., None] * self.f[:, None] + self.c[:, None]
        return (uv, valid, z) if with_depth else (uv, valid)

    def silhouette(self, pts: torch.Tensor, subset: torch.Tensor) -> torch.Tensor:
        """Symmetric 2D chamfer (mean over views), distances in box diagonals."""
        uv, valid, z = self.project(pts, with_depth=True)
        # points -> mask: distance transform lookup, plus the distance outside the crop
        g = (uv - self.crop_lo) / (self.crop_hi - self.crop_lo) * 2 - 1                 # (V, P, 2)
        inner = F.grid_sample(self.dt, g[:, None], mode='bilinear', padding_mode='border',
                              align_corners=False)[:, 0, 0]                              # (V, P)
        out = torch.maximum(self.crop_lo - uv, uv - self.crop_hi).clamp_min(0)
        outside = (out.square().sum(-1) + 1e-6).sqrt() - 1e-3
        known = ~self.unknown(uv)
        if self.depth is not None:
            with torch.no_grad():   # only inside the crop: beyond it nothing was measured for this view
                measured = F.grid_sample(self.depth, g[:, None].detach(), mode='nearest', padding_mode='border',
                                         align_corners=False)[:, 0, 0]
                in_crop = (g.detach().abs() <= 1).all(-1)
                known &= ~(in_crop & (measured < z.detach() - self.free_space_margin))
        d_pm = (inner + outside / self.diag) * known.float()
        valid_f = valid.float()
        e_pm = (d_pm * valid_f).sum(1) / valid_f.sum(1).clamp_min(1.0)
        # mask -> points: nearest projected point (subset) for every mask sample
        sub_uv, sub_valid = uv[:, subset], valid[:, subset]
        with torch.no_grad():   # per coordinate: ~10x faster than a (V, M, S, 2) difference tensor
            su = torch.where(sub_valid, sub_uv[..., 0], torch.full_like(sub_uv[..., 0], 1e7))
            d2 = (self.mask_u[:, :, None] - su[:, None, :]).square_()
            d2.add_((self.mask_v[:, :, None] - sub_uv[..., 1].contiguous()[:, None, :]).square_())  # (V, M, S)
            nearest = d2.min(2).indices    # (V, M); min(dim) is ~2x faster than argmin on the CPU
        matched = torch.gather(sub_uv, 1, nearest[..., None].expand(-1, -1, 2))
        e_mp = ((self.mask_uv - matched).square().sum(-1) + 1e-6).sqrt().mean(1) / self.diag[:, 0]
        return (e_pm + e_mp).mean()


class _Interrupted(Exception):
    """should_stop said so while the code restarts were scored."""


def _rot(yaw: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(yaw), torch.sin(yaw)
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    return torch.stack([torch.stack([c, -s, zero]), torch.stack([s, c, zero]), torch.stack([zero, zero, one])])


def _geometry(world_pts: torch.Tensor, slam: torch.Tensor | None, trunc: float) -> torch.Tensor:
    if slam is None or len(slam) == 0:
        return world_pts.new_zeros(())
    with torch.no_grad():
        nearest = torch.cdist(slam, world_pts).min(1).indices
    d = torch.linalg.norm(slam - world_pts[nearest] + 1e-9, dim=1)
    return d.clamp(max=trunc).mean() / trunc


def with_depth_points(slam_points: np.ndarray | None, depth_points: Sequence[np.ndarray | None],
                      limit: int) -> np.ndarray | None:
    """The landmarks of Eg with the object's registered-depth points (per view (N_i, 3) or None, the masks'
    back-projected pixels of `photometric.dense_view_from_frame`) added, at most `limit` of them evenly spread.

    Beyond the paper, whose Eg has sparse SLAM points only: a depth image is a dense, exact map of the object's
    visible surface, and the same truncated chamfer takes it (points of a mask's bleed cost at most the
    truncation). Without it the sparse stage places a table from its silhouettes and a handful of landmarks."""
    given = [np.asarray(p, np.float32).reshape(-1, 3) for p in depth_points if p is not None and len(p)]
    if limit <= 0 or not given:
        return slam_points
    depth = np.concatenate(given)
    if len(depth) > limit:
        depth = depth[np.linspace(0, len(depth) - 1, limit).round().astype(np.int64)]
    if slam_points is None or not len(slam_points):
        return depth
    return np.concatenate([np.asarray(slam_points, np.float32).reshape(-1, 3), depth])


def slam_points_near(points: np.ndarray | None, center, size, yaw: float, margin: float = 0.1) -> np.ndarray:
    """SLAM landmarks inside the upright box grown by `margin` metres (not below its floor + 2 cm)."""
    if points is None or len(points) == 0:
        return np.zeros((0, 3), np.float32)
    p = np.asarray(points, dtype=np.float64)
    p = p[np.isfinite(p).all(1)]
    return p[placement.in_box(p, center, size, yaw, margin, floor_gap=0.02)].astype(np.float32)


# ------------------------------------------------------------------ stage
def pose_matrix(yaw: float, translation, scale: float) -> np.ndarray:
    """T_world_object (4, 4) of an upright similarity."""
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = scale * np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    T[:3, 3] = np.asarray(translation, dtype=np.float64)
    return T


def box_init(points_norm: np.ndarray, center, size, yaw: float) -> tuple[np.ndarray, float]:
    """(translation, scale) placing the shape's box centre at the box centre, scale = box height / shape height."""
    lo, hi = points_norm.min(0), points_norm.max(0)
    scale = float(max(size[2], 1e-6) / max(hi[2] - lo[2], 1e-6))
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return np.asarray(center, dtype=np.float64) - scale * R @ ((lo + hi) / 2), scale


def code_statistics(training_codes) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean, std) per dimension of the prior's training codes (the Er prior)."""
    codes = torch.as_tensor(training_codes, dtype=torch.float32).cpu()
    return codes.mean(0), codes.std(0).clamp_min(1e-3)


def refine(prior, code, box, views: list[View], slam_points: np.ndarray | None = None,
           config: SparseConfig | None = None, init_yaw: float | None = None, photometric=None,
           floor_height: float | None = None, height_range: tuple[float, float] | None = None,
           code_class: str | None = None, neighbour_boxes=(), should_stop=None,
           facing: np.ndarray | None = None) -> SparseResult:
    """Yaw search + joint code/pose optimisation of one object (paper Sec. 5.3).

    prior: anything with `decode_points(codes) -> (N, 2048, 3)` torch (differentiable) and `training_codes`.
    code (C,): the fused code; box (centre, size, yaw): the association's box; views: `View`s (at most
    config.max_views are used, spread evenly); slam_points (N, 3) world landmarks or None.
    init_yaw: if given, skip the exhaustive search and start from this yaw (warm start).
    photometric: optional `photometric.ViewBatch` of the object's colour views for Ep (weight w_photometric).
    floor_height: world z of the floor (`support.floor_height`) for E_floor; height_range: the class's metric
    height range (`Category.height_range`) for E_size; None: term off. code_class: the object's class; code
    restarts (`code_restarts`) then draw only that class's training codes. neighbour_boxes: the other objects'
    boxes (centre, size, yaw), for the landmark selection (`placement.on_silhouettes`). facing: the unit horizontal
    direction (2,) the object's front should take (`support.facing_direction`; None: E_facing off). should_stop: optional
    callable polled after the initial search, every iteration of the stage's runs and every `STOP_POLL` energies of
    the code-restart scoring (a node that has cheaper work waiting): True ends the stage at once with status
    INTERRUPTED and ok=False (nothing of it is kept; the caller runs it again later).
    Never raises on bad input: returns the box placement with ok=False and a reason.
    """
    cfg = config or SparseConfig()
    start = time.perf_counter()
    center, size, box_yaw = Box3D(*box)        # a Box3D or a (centre, size, yaw) triple
    code = np.asarray(code, dtype=np.float32)
    device = getattr(prior, 'device', 'cpu')

    def fallback(status: SparseStatus, reason: str, yaw: float = box_yaw, pts=None) -> SparseResult:
        t, s = np.asarray(center, dtype=np.float64), 1.0
        if pts is not None and np.isfinite(pts).all() and np.isfinite(center).all() and np.isfinite(size).all():
            t, s = box_init(pts, center, size, yaw)
        return SparseResult(code, pose_matrix(yaw, t, s), float(s), float(yaw), np.asarray(t), ok=False,
                            reason=reason, status=status, init_yaw=float(yaw), views=len(views), seconds=time.perf_counter() - start)

    if not (np.isfinite(code).all() and np.isfinite(center).all() and np.isfinite(size).all()
            and np.isfinite(box_yaw) and np.all(size > 0)):
        return fallback(SparseStatus.INVALID_INPUT, 'non-finite code or box')
    views = [v for v in views if v is not None and np.isfinite(v.K).all() and np.isfinite(v.T_world_camera).all()
             and len(v.mask_uv) > 0 and np.isfinite(v.mask_uv).all() and np.isfinite(v.dt).all()]
    views = select_views(views, cfg.max_views)
    with torch.no_grad():
        pts0 = prior.decode_points(code).float().cpu()[0]
    if not torch.isfinite(pts0).all():
        return fallback(SparseStatus.INVALID_INPUT, 'decoded points are not finite')
    if not views:
        return fallback(SparseStatus.NO_VIEWS, 'no usable views', pts=pts0.numpy())

    gen = torch.Generator().manual_seed(int(cfg.seed))
    free_space = cfg.free_space_margin if cfg.free_space else None
    batch = _Batch(views, cfg.truncation_aware, free_space)
    use_floor = floor_height is not None and math.isfinite(float(floor_height)) and cfg.w_floor > 0
    use_height = height_range is not None and cfg.w_height > 0
    w_facing = support.facing_weight(cfg.w_facing, facing, [np.asarray(v.T_world_camera)[:3, 3] for v in views], center)
    use_facing = w_facing > 0
    subset = torch.randperm(pts0.shape[0], generator=gen)[:min(cfg.point_samples, pts0.shape[0])]
    everything = torch.arange(len(subset))
    mu, sigma = code_statistics(prior.training_codes)
    pts0_np = pts0.numpy().astype(np.float64)

    def energy(pts_norm, z, yaw, t, log_s, landmarks, screen=None):
        """The stage's energy; screen: a `_Batch` of fewer views, and every term on the point subset only (the
        code restarts' cheap screen)."""
        if screen is not None:
            pts_norm = pts_norm[subset]
        world = torch.exp(log_s) * pts_norm @ _rot(yaw).T + t
        terms = {'silhouette': batch.silhouette(world, subset) if screen is None else screen.silhouette(world, everything),
                 'geometry': _geometry(world, landmarks, cfg.geometry_truncation),
                 'code': (((z - mu) / sigma) ** 2).mean()}
        total = cfg.w_silhouette * terms['silhouette'] + cfg.w_geometry * terms['geometry'] + cfg.w_code * terms['code']
        if use_floor:     # beyond the paper: furniture stands on the floor (support.py)
            terms['floor'] = support.floor_energy(world, floor_height, cfg.floor_tolerance)
            total = total + cfg.w_floor * terms['floor']
        if use_height:    # beyond the paper: metric height inside the class's range (support.py)
            terms['height'] = support.height_energy(world, height_range)
            total = total + cfg.w_height * terms['height']
        if use_facing:    # beyond the paper: a chair at a table faces it (support.py); front = +x of the object
            terms['facing'] = support.facing_energy(torch.stack([torch.cos(yaw), torch.sin(yaw)]), facing)
            total = total + w_facing * terms['facing']
        if photometric is not None and cfg.w_photometric > 0:   # paper Eq. 4, visibility-aware (photometric.py)
            terms['photometric'] = photometric_energy(photometric, world, tolerance=0.1 * torch.exp(log_s).detach())
            total = total + cfg.w_photometric * terms['photometric']
        return total, terms

    z0 = torch.as_tensor(code)
    # ---- initialisation: exhaustive yaw search about gravity with the box's translation and scale, plus the
    # placement hypotheses of placement.py (for a wrong box); the box's four symmetric yaws (the input
    # placement) are always candidates
    if init_yaw is None or not np.isfinite(init_yaw):
        n = max(1, int(cfg.yaw_candidates))
        yaws = box_yaw + 2 * np.pi * np.arange(n) / n
    else:
        yaws = np.array([float(init_yaw)])
    candidates = [(float(y), *box_init(pts0_np, center, size, y), 'input box') for y in box_yaw + np.pi / 2 * np.arange(4)]
    candidates += [(float(y), *box_init(pts0_np, center, size, y), 'box') for y in yaws]
    if cfg.placement_search and len(yaws) > 1:
        candidates += [(h.yaw, h.translation, h.scale, h.source) for h in placement.search(
            pts0_np, (center, size, box_yaw), views, batch, slam_points, yaws, crop_margin=DT_MARGIN,
            w_silhouette=cfg.w_silhouette, w_geometry=cfg.w_geometry, truncation=cfg.placement_truncation,
            keep=cfg.placement_keep, seed=cfg.seed, floor_height=floor_height if use_floor else None,
            w_floor=cfg.w_floor, floor_tolerance=cfg.floor_tolerance,
            height_range=height_range if use_height else None, w_height=cfg.w_height,
            facing=facing if use_facing else None, w_facing=w_facing)]
    # landmarks. Hypotheses and code restarts use one common set: those near the input box or the best hypothesis
    # that lie in the detections' visual hull (placement.on_silhouettes), so that clutter, floor and neighbour
    # points in a too large region do not favour the placement that covers them. The box starts use those near
    # the input box: with `landmark_filter` also only the visual-hull ones (else all: the paper's setting), so
    # that they do not pull the surface towards other things either. Every run's end state is compared on the
    # common set (below), never on the set it descended with.
    def tensor(points):
        return torch.as_tensor(points) if len(points) >= 5 and cfg.w_geometry > 0 else None

    n_box = 4 + len(yaws)
    near_input = slam_points_near(slam_points, center, size, box_yaw, margin=0.1 * float(np.max(size)) + 0.05)
    neighbours = neighbour_boxes if cfg.landmark_filter else ()
    box_set = placement.on_silhouettes(near_input, views, batch, neighbours, cfg.landmark_tolerance) \
        if cfg.landmark_filter else near_input
    common = box_set
    if len(candidates) > n_box:
        c_h, sz_h, y_h = placement.placed_box(pts0_np, *candidates[n_box][:3])
        near_h = slam_points_near(slam_points, c_h, sz_h, y_h, margin=0.1 * float(np.max(sz_h)) + 0.05)
        common = placement.on_silhouettes(np.unique(np.concatenate([near_input, near_h]), axis=0), views, batch,
                                          neighbours, cfg.landmark_tolerance)
    slam_input, slam_common = tensor(box_set), tensor(common)
    scores = []
    with torch.no_grad():
        for k, (yaw, t, s, _) in enumerate(candidates):
            e, _ = energy(pts0, z0, torch.tensor(yaw), torch.as_tensor(t, dtype=torch.float32),
                          torch.tensor(math.log(s)), slam_input if k < n_box else slam_common)
            scores.append(float(e) if torch.isfinite(e) else np.inf)
    if not np.isfinite(scores).any():
        return fallback(SparseStatus.NON_FINITE_ENERGY, 'energy is not finite for any yaw candidate', pts=pts0_np)
    first_input = int(np.argmin(scores[:4]))
    input_energy = scores[first_input]

    def interrupted() -> bool:
        return should_stop is not None and bool(should_stop())

    # ---- joint optimisation of code, yaw, translation, log-scale (Adam, fixed iterations) from the best box start
    # (the box-only initialisation), from the best placement hypothesis and from the best code restart, if any
    def descend(yaw0: float, t0, s0: float, z_start: torch.Tensor, landmarks):
        """(best state, initial terms, iterations done), or None when should_stop said so."""
        z = z_start.clone().requires_grad_(cfg.optimise_code)
        yaw = torch.tensor(yaw0, requires_grad=True)
        t = torch.as_tensor(t0, dtype=torch.float32).clone().requires_grad_(True)
        log_s = torch.tensor(math.log(s0), requires_grad=True)
        groups = [{'params': [yaw], 'lr': cfg.lr_yaw}, {'params': [t], 'lr': cfg.lr_translation},
                  {'params': [log_s], 'lr': cfg.lr_log_scale}]
        if cfg.optimise_code:
            groups.append({'params': [z], 'lr': cfg.lr_code})
        opt = Adam(groups)
        best = None
        initial_terms = None
        done = 0
        for it in range(int(cfg.iterations) + 1):
            if interrupted():
                return None
            pts = prior.decode_points(z.to(device)).float().cpu()[0] if cfg.optimise_code else pts0
            total, terms = energy(pts, z, yaw, t, log_s, landmarks)
            if initial_terms is None:
                initial_terms = {k: float(v.detach()) for k, v in terms.items()} | {"total": float(total.detach())}
            if not torch.isfinite(total):
                break
            if best is None or float(total.detach()) < best[0]:
                best = (float(total.detach()), it, z.detach().clone(), float(yaw.detach()), t.detach().clone().double().numpy(),
                        float(log_s.detach()), {k: float(v.detach()) for k, v in terms.items()} | {"total": float(total.detach())})
            if it == int(cfg.iterations):
                break
            opt.zero_grad()
            total.backward()
            opt.step()
            done = it + 1
        return best, initial_terms, done

    starts = [int(np.argmin(scores[:n_box]))] + ([n_box + int(np.argmin(scores[n_box:]))] if len(scores) > n_box else [])
    runs = []
    for k in starts:
        run = descend(*candidates[k][:3], z0, slam_input if k < n_box else slam_common)
        if run is None:
            return fallback(SparseStatus.INTERRUPTED, f'interrupted in run {len(runs) + 1}')
        runs.append((run, candidates[k]))
    # ---- code restarts (beyond the paper): the encoder's code of an unseen design can be a different shape
    # than the silhouettes show, and Adam steps near it do not leave its basin. Every training code (of the
    # object's class when known) is scored at the input box (shape-specific box fit) with the best box start's
    # yaw and its opposite; the `code_restarts` best are then scored at every yaw candidate, and Adam also runs
    # from the best of those
    if cfg.code_restarts > 0 and cfg.optimise_code:
        train = torch.as_tensor(prior.training_codes, dtype=torch.float32).cpu()
        classes = list(getattr(prior, 'training_classes', []))
        pool = [i for i in range(len(train)) if code_class is None or len(classes) != len(train) or classes[i] == code_class]
        yaw_box = candidates[starts[0]][0]

        # The screen: the energy on `restart_screen_views` of the views (spread evenly), its landmark term on the
        # point subset, costs a fraction of the exact one and ranks alike; only its `restart_screen_keep` x
        # code_restarts best candidates of each pass are scored exactly
        # (docs/experiments/frodo_optim_history.md, "Screened code restarts")
        n_screen = int(cfg.restart_screen_views)
        screen = _Batch(select_views(views, n_screen), cfg.truncation_aware, free_space) \
            if 0 < n_screen < len(views) else None
        keep = max(1, int(cfg.restart_screen_keep)) * int(cfg.code_restarts)

        evaluations = itertools.count()

        def code_energy(i: int, pts_i: torch.Tensor, y: float, screened: bool = False) -> float:
            if next(evaluations) % STOP_POLL == 0 and interrupted():
                raise _Interrupted
            t_i, s_i = box_init(pts_i.numpy().astype(np.float64), center, size, y)
            e, _ = energy(pts_i, train[i], torch.tensor(y), torch.as_tensor(t_i, dtype=torch.float32),
                          torch.tensor(math.log(s_i)), slam_common, screen if screened else None)
            return float(e) if torch.isfinite(e) else math.inf

        def lowest(candidates: list[tuple[int, float]], count: int) -> list[tuple[float, int, float]]:
            """The `count` (code, yaw) candidates of lowest exact energy, (energy, code, yaw) in order; with a
            screen, only the screen's `keep` best are scored exactly."""
            if screen is not None and len(candidates) > keep:
                screened = sorted((code_energy(i, decoded[i], y, True), n) for n, (i, y) in enumerate(candidates))
                candidates = [candidates[n] for _, n in screened[:keep]]
            return sorted((code_energy(i, decoded[i], y), i, y) for i, y in candidates)[:count]

        with torch.no_grad():
            decoded = {}
            for chunk in np.array_split(np.array(pool), max(1, len(pool) // 32)):
                pts_c = prior.decode_points(train[chunk].to(device)).float().cpu()
                decoded.update({int(i): p for i, p in zip(chunk, pts_c) if torch.isfinite(p).all()})
            # every code at the best box start's yaw and its opposite; then the best codes at every yaw candidate
            try:
                coarse = lowest([(i, y) for i in decoded for y in (yaw_box, yaw_box + math.pi)], 2 * int(cfg.code_restarts))
                codes = list(dict.fromkeys(i for _, i, _ in coarse))[:int(cfg.code_restarts)]
                fine = lowest([(i, float(y)) for i in codes for y in yaws], 1)
            except _Interrupted:
                return fallback(SparseStatus.INTERRUPTED, 'interrupted while scoring the code restarts')
            best_restart = None
            if fine:
                e, i, y = fine[0]
                t_i, s_i = box_init(decoded[i].numpy().astype(np.float64), center, size, y)
                best_restart = (e, i, (y, t_i, s_i, f'training code {i}'))
        if best_restart is not None and math.isfinite(best_restart[0]):
            run = descend(*best_restart[2][:3], train[best_restart[1]], slam_common)
            if run is None:
                return fallback(SparseStatus.INTERRUPTED, 'interrupted in the code restart\'s run')
            runs.append((run, best_restart[2]))

    # ---- which run: each end state is scored on the common landmark set; a hypothesis or restart replaces the box
    # run only when it is clearly better: `placement_margin` lower in total and no worse in the silhouette term
    # (a wrong code fits the silhouettes about equally well at several scales: near ties keep the box)
    def common_terms(state) -> dict[str, float]:
        _, _, z, yaw, t, log_s, _ = state
        with torch.no_grad():
            pts = prior.decode_points(z.to(device)).float().cpu()[0] if cfg.optimise_code else pts0
            total, terms = energy(pts, z, torch.tensor(yaw), torch.as_tensor(t, dtype=torch.float32),
                                  torch.tensor(log_s), slam_common)
        return {k: float(v) for k, v in terms.items()} | {'total': float(total)}

    chosen = 0
    if len(runs) > 1 and runs[0][0][0] is not None:
        reference = common_terms(runs[0][0][0])
        y_in, t_in, s_in = candidates[first_input][:3]
        input_common = common_terms((0, 0, z0, y_in, t_in, math.log(s_in), {}))['total']
        best_total = min(reference['total'] * (1.0 - cfg.placement_margin), input_common)
        for k, ((state, _, _), _) in enumerate(runs[1:], 1):
            if state is None:
                continue
            c = common_terms(state)
            if c['total'] < best_total and c['silhouette'] <= reference['silhouette']:
                chosen, best_total = k, c['total']
    elif runs[0][0][0] is None:
        chosen = next((k for k, r in enumerate(runs) if r[0][0] is not None), 0)
    (best, initial_terms, done), start_candidate = runs[chosen]
    yaw0, source = start_candidate[0], start_candidate[3]
    reason, status = '', SparseStatus.OPTIMISED
    if best is None:   # no finite state in any run: keep the input placement
        best = (input_energy, 0, z0, *candidates[first_input][:2], math.log(candidates[first_input][2]), {})
    best_e, best_it, zb, yb, tb, lsb, terms_b = best
    if chosen > 0:     # compared on the common landmarks: report those energies, the input's included
        terms_b, input_energy = common_terms(best), input_common
    s = math.exp(lsb)
    # never worse than the input: the box run must end below the input placement's energy (same landmarks); a
    # hypothesis or restart has already ended below the input placement on the common landmarks
    if chosen == 0 and not best_e < input_energy:
        yb, tb, s = candidates[first_input][:3]
        zb, reason = z0, f'input placement kept (energy {input_energy:.4f}, nothing lower found)'
        status = SparseStatus.INPUT_KEPT
    yb = float(math.atan2(math.sin(yb), math.cos(yb)))
    alternatives = [(state[2].cpu().numpy().astype(np.float32), pose_matrix(state[3], state[4], math.exp(state[5])),
                     candidate[3]) for k, ((state, _, _), candidate) in enumerate(runs) if k != chosen and state is not None]
    return SparseResult(zb.cpu().numpy().astype(np.float32), pose_matrix(yb, tb, s), float(s), yb, np.asarray(tb),
                        reason=reason, status=status, energies=terms_b, initial_energies=initial_terms, init_yaw=yaw0,
                        placement=source, input_energy=input_energy, iterations=done,
                        total_iterations=sum(run[0][2] for run in runs),
                        best_iteration=best_it, views=len(views), seconds=time.perf_counter() - start,
                        landmarks=np.asarray(common if chosen > 0 else box_set, np.float32) if cfg.landmark_filter else None,
                        alternatives=alternatives)


class ViewStore:
    """Bounded per-object view memory for the sparse stage (keys (stamp_ns, label) -> View, owner, kept flag).

    Every detection's view is stored, also before the association confirms its object (owner -1), because
    the association assigns ids to past frames later (re-sends). An object keeps at most `per_object` views:
    past that, every second one (in stamp order) is dropped, so the kept views stay spread over the
    trajectory. At most `capacity` views in all: the oldest unowned ones go first, then the oldest.
    """

    def __init__(self, per_object: int = 64, capacity: int = 2000):
        self.per_object = max(2, int(per_object))
        self.capacity = max(1, int(capacity))
        self.views: dict[tuple[int, int], View] = {}
        self.owner: dict[tuple[int, int], tuple[int, bool]] = {}

    def add(self, stamp: int, label: int, object_id: int, kept: bool, view: View) -> None:
        key = (int(stamp), int(label))
        self.views[key] = view
        self.owner[key] = (int(object_id), bool(kept))
        self._thin(int(object_id))
        while len(self.views) > self.capacity:
            unowned = [k for k, (o, _) in self.owner.items() if o < 0]
            self._drop(min(unowned) if unowned else min(self.views))

    def assign(self, stamp: int, owners: dict[int, tuple[int, bool]]) -> None:
        """New (object id, kept) per label of a stamp's stored views (labels not listed: unowned)."""
        changed = set()
        for key in [k for k in self.views if k[0] == stamp]:
            self.owner[key] = owners.get(key[1], (-1, False))
            changed.add(self.owner[key][0])
        for oid in changed:
            self._thin(oid)

    def views_of(self, object_id: int, fill_to: int = 0) -> list[View]:
        """The object's kept views in stamp order; with fewer than `fill_to` kept ones, its associated views that
        pruning rejected (cut by the border, overlapping another object: the silhouette terms allow for both)
        fill up to fill_to, spread evenly over the sequence. With 35 keyframes a table never seen whole keeps
        only the 3 views the association guarantees it, of 13-20 it was detected in."""
        return [self.views[k] for k in self.keys_of(object_id, fill_to)]

    def keys_of(self, object_id: int, fill_to: int = 0) -> list[tuple[int, int]]:
        """The (stamp_ns, label) keys of the views `views_of` returns, in the same order."""
        keys = sorted(self.views)
        kept = [k for k in keys if self.owner.get(k) == (object_id, True)]
        pruned = [k for k in keys if self.owner.get(k) == (object_id, False)]
        missing = fill_to - len(kept)
        if missing > 0 and pruned:
            pick = np.unique(np.linspace(0, len(pruned) - 1, min(missing, len(pruned))).round().astype(int))
            kept = sorted(kept + [pruned[i] for i in pick])
        return kept

    def _thin(self, object_id: int) -> None:
        if object_id < 0:
            return
        mine = sorted(k for k, (o, _) in self.owner.items() if o == object_id)
        if len(mine) > self.per_object:
            for k in mine[1::2]:
                self._drop(k)

    def _drop(self, key) -> None:
        self.views.pop(key, None)
        self.owner.pop(key, None)

    def __len__(self) -> int:
        return len(self.views)
