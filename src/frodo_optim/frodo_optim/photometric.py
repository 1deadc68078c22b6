"""Photometric consistency Ep (paper Sec. 5.3, Eq. 4) and the per-view image data it reads; torch + numpy only.

    Ep = 1 / (N |X|) sum_i sum_x || I_R(pi(T_cw^R x)) - I_S_i(pi(T_cw^S_i x)) ||_huber

Every view of the (time-ordered) set serves as a reference R in turn, with its `neighbours` next views as
sources S_i ("nearby frames"); all pairs are evaluated at once (no per-view Python loop). A point only
contributes to a pair when it is visible in both views:

- self-occlusion: a z-buffer of the object's own points per view on a coarse cell grid over the crop; a
  point is visible when its depth is within `occlusion_tolerance` (object-scale units) of the nearest
  point in its cell, and, when surface normals are given (dense stage), when it faces the camera;
- occlusion by other objects and leaving the detection: the pixel must be labelled as this object's mask.

Colours are the detection crops stored per view (`DenseView.rgb`, area-averaged, so slightly blurred,
which widens the basin), sampled bilinearly: the gradient reaches the points through the image gradient.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from frodo_common.frames import usable_depth
from frodo_common.geometry import backproject_pixels

LABEL_BACKGROUND, LABEL_OBJECT, LABEL_UNKNOWN = 0, 1, 2


@dataclass
class DenseView:
    """One associated detection for the dense and photometric terms (kept next to the sparse `View`).

    crop (u0, v0, u1, v1): square around the detection box grown by `margin` per side, in image pixels
    (pixel i covers [i - 0.5, i + 0.5));
    labels (S, S) uint8 over the crop: 0 background, 1 this object, 2 unknown (other detections, outside the
    image); rgb (S, S, 3) uint8 area-averaged colour over the crop or None; box (w, h) of the detection in
    pixels; depth_points (N, 3) float32 world points back-projected from registered depth on the mask, or None;
    depth (S, S) float16 registered depth over the crop (camera z, metres; NaN: no measurement) or None: where
    it measures a surface that is not this object's, the dense silhouette knows the ray free up to it only.
    """

    K: np.ndarray
    T_world_camera: np.ndarray
    crop: tuple[float, float, float, float]
    labels: np.ndarray
    rgb: np.ndarray | None
    box: tuple[float, float]
    depth_points: np.ndarray | None = None
    depth: np.ndarray | None = None

    def nbytes(self) -> int:
        return (self.labels.nbytes + (self.rgb.nbytes if self.rgb is not None else 0)
                + (self.depth_points.nbytes if self.depth_points is not None else 0)
                + (self.depth.nbytes if self.depth is not None else 0) + 300)


def _resample(img: np.ndarray, x0: int, y0: int, side: int, size: int, mode: str) -> np.ndarray:
    """The square pixel window img[y0:y0+side, x0:x0+side] ((H, W) or (H, W, C)) resampled to (size, size[, C]).

    Pixels outside the image read LABEL_UNKNOWN ('nearest', labels; NaN for a float image) or 0 ('area', colour).
    The same values as
    torch's `interpolate` modes of those names, in numpy: views are cut in the optimiser node's executor
    callbacks, and torch there would start an OpenMP team beside the optimiser's (`frodo_common.torch_threads`).
    """
    h, w = img.shape[:2]
    outside = 0 if mode != 'nearest' else np.nan if np.issubdtype(img.dtype, np.floating) else LABEL_UNKNOWN
    window = np.full((side, side) + img.shape[2:], outside, dtype=img.dtype)
    sx0, sy0, sx1, sy1 = max(0, x0), max(0, y0), min(w, x0 + side), min(h, y0 + side)
    if sx1 > sx0 and sy1 > sy0:
        window[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0] = img[sy0:sy1, sx0:sx1]
    if mode == 'nearest':
        # torch: source index floor(i * (in / out)), computed in float32
        scale = np.float32(side) / np.float32(size)
        idx = np.minimum(np.floor(np.arange(size, dtype=np.float32) * scale).astype(np.int64), side - 1)
        return window[idx][:, idx]
    # 'area' is adaptive average pooling: output i averages inputs floor(i * in / out) .. ceil((i + 1) * in / out)
    # (integer sums, exact; then divided by the window's height and width in float32, as torch does)
    i = np.arange(size)
    lo, hi = (i * side) // size, ((i + 1) * side + size - 1) // size
    sums = window.astype(np.int64)
    for axis in (0, 1):
        cum = np.concatenate([np.zeros_like(sums.take([0], axis)), np.cumsum(sums, axis=axis)], axis=axis)
        sums = cum.take(hi, axis) - cum.take(lo, axis)
    n = (hi - lo).astype(np.float32)
    n_rows, n_cols = (n[:, None, None], n[None, :, None]) if window.ndim == 3 else (n[:, None], n[None, :])
    out = sums.astype(np.float32) / n_rows / n_cols
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def checked_view_inputs(K, T_world_camera, mask: np.ndarray):
    """(K (3, 3), T (4, 4) float64, mask bool (H, W), ys, xs of its pixels), or None when the camera is not
    finite or the mask is not 2-D or has fewer than 4 pixels (a view no stage can use)."""
    mask = np.asarray(mask, dtype=bool)
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(T_world_camera, dtype=np.float64)
    if mask.ndim != 2 or K.shape != (3, 3) or T.shape != (4, 4) or not (np.isfinite(K).all() and np.isfinite(T).all()):
        return None
    ys, xs = np.nonzero(mask)
    if len(xs) < 4:
        return None
    return K, T, mask, ys, xs


def dense_view_from_frame(K, T_world_camera, mask: np.ndarray, unknown: np.ndarray | None, rgb: np.ndarray | None,
                          depth_m: np.ndarray | None = None, size: int = 128, margin: float = 0.25,
                          depth_points: int = 128, rng: np.random.Generator | None = None) -> DenseView | None:
    """DenseView of one detection from full-resolution data; None when the mask or camera is unusable.

    mask (H, W) bool; unknown (H, W) bool (other detections); rgb (H, W, 3) uint8 or None;
    depth_m (H, W) float metres registered to the colour image (0 / NaN = none) or None.
    """
    checked = checked_view_inputs(K, T_world_camera, mask)
    if checked is None:
        return None
    K, T, mask, ys, xs = checked
    x0, y0, x1, y1 = xs.min(), ys.min(), xs.max() + 1, ys.max() + 1
    bw, bh = float(x1 - x0), float(y1 - y0)
    # square pixel window (one scale for u and v); pixel i covers [i - 0.5, i + 0.5)
    side = int(math.ceil(max(bw, bh) * (1 + 2 * margin)))
    wx0, wy0 = int(round((x0 + x1 - 1) / 2 - side / 2 + 0.5)), int(round((y0 + y1 - 1) / 2 - side / 2 + 0.5))
    crop = (wx0 - 0.5, wy0 - 0.5, wx0 - 0.5 + side, wy0 - 0.5 + side)
    labels = np.zeros(mask.shape, np.uint8)
    if unknown is not None:
        labels[np.asarray(unknown, dtype=bool)] = LABEL_UNKNOWN
    labels[mask] = LABEL_OBJECT
    lab = _resample(labels, wx0, wy0, side, size, 'nearest')
    colour = None
    if rgb is not None and np.asarray(rgb).shape[:2] == mask.shape:
        colour = _resample(np.asarray(rgb, dtype=np.uint8)[..., :3], wx0, wy0, side, size, 'area')
    pts = depth = None
    if depth_m is not None and np.asarray(depth_m).shape == mask.shape:
        usable = usable_depth(depth_m)
        depth = _resample(usable, wx0, wy0, side, size, 'nearest').astype(np.float16)
        d = usable[ys, xs].astype(np.float64)
        ok = np.isfinite(d)
        if ok.sum() >= 4:
            rng = rng if rng is not None else np.random.default_rng(0)
            pick = rng.choice(np.flatnonzero(ok), size=min(depth_points, int(ok.sum())), replace=False)
            pts = backproject_pixels(K, T, xs[pick].astype(np.float64), ys[pick].astype(np.float64),
                                     d[pick]).astype(np.float32)
    return DenseView(K, T, tuple(float(c) for c in crop), lab, colour, (bw, bh), pts, depth)


def huber(x: torch.Tensor, delta: float) -> torch.Tensor:
    """Elementwise Huber norm (quadratic below delta, linear above, continuous slope)."""
    a = x.abs()
    return torch.where(a < delta, 0.5 * a.square(), delta * (a - 0.5 * delta))


class ViewBatch:
    """DenseViews stacked as tensors: cameras, crops, label and colour images (V views, crops S x S)."""

    def __init__(self, views: list[DenseView], device='cpu'):
        T_cw = np.stack([np.linalg.inv(v.T_world_camera) for v in views])
        f32 = dict(dtype=torch.float32, device=device)
        self.V = len(views)
        self.R = torch.as_tensor(T_cw[:, :3, :3], **f32)                          # (V, 3, 3) world -> camera
        self.t = torch.as_tensor(T_cw[:, :3, 3], **f32)                            # (V, 3)
        self.K = torch.as_tensor(np.stack([v.K for v in views]), **f32)            # (V, 3, 3)
        self.R_wc = torch.as_tensor(np.stack([v.T_world_camera[:3, :3] for v in views]), **f32)
        self.centre = torch.as_tensor(np.stack([v.T_world_camera[:3, 3] for v in views]), **f32)   # (V, 3)
        crop = np.array([v.crop for v in views], dtype=np.float32)
        self.crop_lo = torch.as_tensor(crop[:, :2], device=device)[:, None]       # (V, 1, 2)
        self.crop_hi = torch.as_tensor(crop[:, 2:], device=device)[:, None]
        self.labels = torch.as_tensor(np.stack([v.labels for v in views]), device=device)   # (V, S, S) uint8
        self.box = torch.as_tensor(np.array([v.box for v in views], dtype=np.float32), device=device)  # (V, 2)
        self.has_rgb = all(v.rgb is not None for v in views)
        self.rgb = (torch.as_tensor(np.stack([v.rgb for v in views]), **f32).permute(0, 3, 1, 2) / 255.0
                    if self.has_rgb else None)                                     # (V, 3, S, S)
        self.size = int(self.labels.shape[-1])

    def project(self, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World points (P, 3) or per-view (V, P, 3) -> pixels (V, P, 2), depth (V, P)."""
        eq = 'vij,pj->vpi' if pts.ndim == 2 else 'vij,vpj->vpi'
        pc = torch.einsum(eq, self.R, pts) + self.t[:, None]
        z = pc[..., 2]
        uv = pc[..., :2] / z.clamp_min(1e-3)[..., None] * self.K[:, None, [0, 1], [0, 1]] + self.K[:, None, :2, 2]
        return uv, z

    def crop_coords(self, uv: torch.Tensor) -> torch.Tensor:
        """Pixels (V, P, 2) -> grid_sample coordinates in [-1, 1] over each view's crop (align_corners=False)."""
        return (uv - self.crop_lo) / (self.crop_hi - self.crop_lo) * 2 - 1

    def label_at(self, uv: torch.Tensor) -> torch.Tensor:
        """Label (V, P) uint8 at pixels (V, P, 2) (nearest cell); outside the crop: background."""
        g = self.crop_coords(uv)
        cell = ((g + 1) / 2 * self.size).floor().long()
        inside = ((cell >= 0) & (cell < self.size)).all(-1)
        cell = cell.clamp(0, self.size - 1)
        flat = self.labels.reshape(self.V, -1)
        lab = torch.gather(flat, 1, cell[..., 1] * self.size + cell[..., 0])
        return torch.where(inside, lab, torch.zeros_like(lab))

    def colour_at(self, uv: torch.Tensor) -> torch.Tensor:
        """Colours (V, P, 3) in [0, 1] at pixels (V, P, 2), bilinear (differentiable in uv)."""
        g = self.crop_coords(uv)
        return F.grid_sample(self.rgb, g[:, None], mode='bilinear', padding_mode='border',
                             align_corners=False)[:, :, 0].permute(0, 2, 1)


def visible(batch: ViewBatch, uv: torch.Tensor, depth: torch.Tensor, tolerance: torch.Tensor | float,
            normals_world: torch.Tensor | None = None, points_world: torch.Tensor | None = None) -> torch.Tensor:
    """(V, P) bool: point projects onto this object's mask and is not hidden by the object itself.

    Self-occlusion by a per-view z-buffer (scatter-min of depth) on a C x C cell grid over the crop, C chosen
    from the point count (about 2 front points per cell); `tolerance` in metres.
    """
    with torch.no_grad():
        P = uv.shape[1]
        C = int(max(8, round(0.5 * math.sqrt(P))))
        g = (batch.crop_coords(uv) + 1) / 2
        cell = (g * C).floor().long()
        inside = ((cell >= 0) & (cell < C)).all(-1) & (depth > 0.05)
        cell = cell.clamp(0, C - 1)
        idx = cell[..., 1] * C + cell[..., 0]                                         # (V, P)
        d = torch.where(inside, depth, torch.full_like(depth, float('inf')))
        zbuf = torch.full((batch.V, C * C), float('inf'), dtype=d.dtype, device=uv.device).scatter_reduce(1, idx, d, 'amin')
        front = d <= torch.gather(zbuf, 1, idx) + tolerance
        ok = inside & front & (batch.label_at(uv) == LABEL_OBJECT)
        if normals_world is not None and points_world is not None:
            to_cam = batch.centre[:, None] - points_world[None]                       # (V, P, 3)
            ok &= (to_cam * normals_world[None]).sum(-1) > 0
        return ok


def photometric_energy(batch: ViewBatch, points_world: torch.Tensor, neighbours: int = 2, delta: float = 0.1,
                       tolerance: torch.Tensor | float = 0.03, normals_world: torch.Tensor | None = None,
                       visibility: torch.Tensor | None = None) -> torch.Tensor:
    """Ep (paper Eq. 4) of world points (P, 3) over all (reference, next `neighbours` views) pairs.

    Huber (delta on [0, 1] colour) of the colour difference, per channel, averaged over pairs x points that
    are visible in both views. 0 when no colour or no pair has a common visible point. `visibility` (V, P)
    bool replaces the z-buffer test (e.g. held fixed while checking gradients: the test is piecewise constant).
    """
    if not batch.has_rgb or batch.V < 2:
        return points_world.new_zeros(())
    uv, depth = batch.project(points_world)
    vis = visibility if visibility is not None else visible(batch, uv, depth, tolerance, normals_world,
                                                                 points_world)        # (V, P)
    colours = batch.colour_at(uv)                                                    # (V, P, 3)
    k = max(1, min(int(neighbours), batch.V - 1))
    ref = torch.arange(batch.V, device=uv.device).repeat_interleave(k)
    src = ref + torch.arange(1, k + 1, device=uv.device).repeat(batch.V)
    keep = src < batch.V
    ref, src = ref[keep], src[keep]
    both = (vis[ref] & vis[src]).float()                                             # (pairs, P)
    r = huber(colours[ref] - colours[src], delta).mean(-1)                           # (pairs, P)
    return (r * both).sum() / both.sum().clamp_min(1.0)
