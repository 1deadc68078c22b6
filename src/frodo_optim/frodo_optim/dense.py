"""Dense optimisation stage (paper Sec. 5.3 "Dense Optimization", supplement "Dense Shape Code Optimization").

Starting from the sparse stage's code and pose, the DeepSDF branch Gd(z, x) of the joint decoder is
optimised together with a 7-DoF pose x_world = s * R * x_norm + t (R = exp([w]) R0, any rotation, as the paper;
with `upright`, w = (0, 0, w_z): a rotation about gravity only).
Per iteration:

1. an adaptively sampled SDF volume (`frodo_shape.meshing.sdf_grid`: coarse grid, re-evaluated near the
   zero level set), evaluated without gradients, and a proxy mesh by marching cubes; its vertices (a fixed
   number, `surface_points`) are the surface points of the photometric term. Between full evaluations only
   the volume's points within `grid_band` of the surface are evaluated again (`meshing.update_band`; the code
   moves a little per step), until the summed change could have moved a kept value into the active band;
2. the energy  E = ws Es + wp Ep + wg Eg + wd Ed + wr Er  with
   - Es, dense silhouette (paper Eq. 7/8): per pixel the foreground probability accumulated along its ray
     from the SDF samples taken as logits, H = 1 - prod_i sig(zeta * f(x_i)), step `ray_step` (paper r/50),
     compared with the observed mask by the pixel-wise likelihood -log(H Pf + (1 - H)(1 - Pf)). Pixels come
     from a detection pyramid (levels l with r_min^2 < w h / 4^l < r_max^2, coarse to fine over the
     iterations; a level's target is the mask averaged over its pixel footprint); `rays_per_view` pixels
     per view and level are drawn once (seeded). Unknown pixels (other detections, outside the image) are
     left out. With a registered depth image (`free_space`, beyond the paper) a pixel off the mask that
     measures a surface is known only in front of it: its ray ends `free_space_margin` before that depth
     (`Rays.limit`), and other detections' pixels count up to their surface. The SDF along rays is read
     from the volume (trilinear), so the decoder runs once per grid
     point, not once per ray sample (the paper's reason for the proxy volume: cost independent of views);
     rays are clipped to the surface's box and blocks of the volume outside the active band are not read
     (`surface_bounds`, `_read_volume`: those samples add log sig(zeta f) ~ 0);
   - Ep, photometric (paper Eq. 4) on the proxy surface points, `photometric.photometric_energy`, with
     back-face and z-buffer visibility;
   - Eg, geometric: SLAM landmarks of the object (`optim_node`: the sparse stage's visual-hull set,
     `SparseResult.landmarks`), |SDF| at the landmark in metres, truncated;
   - Ed, registered depth (CONTRACT v1.1, beyond the paper): |SDF| at back-projected masked depth pixels,
     truncated;
   - Er, code regulariser as in the sparse stage;
   - E_floor, E_size (beyond the paper, `support.py`): the object's lowest surface points on the floor and its
     height in its class's range, on the proxy mesh's lowest and highest vertices moved by the implicit
     rule (so code, rotation, translation and scale all feel them); only when a floor height / height range
     is passed.
3. gradients: pose through the ray/point coordinates; code through
   - the volume: dEs/dG at the grid samples (autograd through the trilinear reads), pushed through the
     decoder as one vector-Jacobian product on the band of grid points with non-zero gradient;
   - the surface points: x(z) with dx/dz = -(df/dx)^+ df/dz (supplement, after Atzmon et al.), i.e.
     `implicit_surface_points`;
   - the SDF at landmarks / depth points directly.
4. Adam step; the state with the lowest energy on a fixed check set (finest pyramid level) is kept, the
   initial (sparse) state included, so a diverging or useless run rolls back to the sparse result.
"""
from __future__ import annotations

import math
import time
from typing import Generator, Sequence
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
import torch
import torch.nn.functional as F

from frodo_optim.adam import Adam
from frodo_optim import support
from frodo_optim.photometric import LABEL_OBJECT, LABEL_UNKNOWN, DenseView, ViewBatch, photometric_energy
from frodo_optim.sparse import code_statistics, select_views, slam_points_near
from frodo_shape.meshing import grid_points, marching_cubes, sdf_grid, update_band

# Ray samples with |zeta f| below this carry the silhouette gradient; beyond it log-sigmoid is flat (its slope
# is below 1e-5 on the outside; deep inside, H is saturated), so those samples enter as constants.
ACTIVE_LOGIT = 12.0
SUPPORT_VERTICES = 16   # lowest / highest proxy-mesh vertices that carry E_floor and E_size


@dataclass
class DenseConfig:
    """Parameters of the dense stage (the node's `dense_*` parameters)."""

    iterations: int = 40
    max_views: int = 16
    max_seconds: float = 30.0          # wall-clock bound per object; the best state so far is kept
    grid_resolution: int = 32          # proxy volume / marching cubes over [-1, 1]^3 (normalised frame)
    grid_coarse: int = 2               # coarse-to-fine factor of the adaptive volume
    surface_points: int = 1024         # proxy-mesh vertices used by Ep
    rays_per_view: int = 384           # pixels per view and pyramid level
    ray_step: float = 0.04             # normalised units: the unit cube's side (2) / 50
    sharpness: float = 100.0           # zeta, per normalised SDF unit
    r_min: float = 40.0                # detection pyramid bounds (paper: 40, 400 px)
    r_max: float = 400.0
    mask_confidence: float = 0.95      # Pf on the mask, 1 - Pf off it
    w_silhouette: float = 1.0
    w_photometric: float = 2.0
    w_geometry: float = 0.5
    w_depth: float = 0.5
    free_space: bool = True            # with depth: a pixel off the mask is background only in front of its depth
    free_space_margin: float = 0.05    # metres before the measured depth where that ray stops (`_level_rays`)
    w_code: float = 0.01
    w_floor: float = 0.05              # E_floor (support.py); needs refine_dense(..., floor_height=h)
    floor_tolerance: float = 0.05      # metres
    w_height: float = 1.0              # E_size (support.py); needs refine_dense(..., height_range=(lo, hi))
    w_facing: float = 0.1              # E_facing (support.py), times support.one_sided_share; needs facing=
    geometry_truncation: float = 0.1   # metres (Eg, Ed)
    photometric_neighbours: int = 2
    huber_delta: float = 0.1
    occlusion_tolerance: float = 0.1   # normalised units (times the scale: metres)
    lr_code: float = 0.02
    lr_translation: float = 0.005
    lr_rotation: float = 0.01
    upright: bool = False              # True: rotate about gravity (world z) only; False: any rotation (paper)
    lr_log_scale: float = 0.005
    optimise_code: bool = True
    min_improvement: float = 0.0       # relative drop of the check energy needed to accept the dense result
    band_points: int = 8192            # most grid points in the code vector-Jacobian product
    vjp_tail: float = 1e-5             # ... less the smallest |dEs/dG| that sum to under this fraction of all
    grid_band: float = 0.25            # normalised: re-evaluate only the grid within this of the surface (0: all)
    screen_iterations: int = 10        # several starts: run each this long, then continue only those near the best
    screen_margin: float = 0.0         # ... those whose check energy so far is within this of the lowest (0: the
                                       # lowest only; 0.005 let all three go on in some live runs, for the same F1)
    start_separation: float = 0.02     # metres: a start whose placed surface is closer to an earlier one's is skipped
    seed: int = 0


class DenseStop(Enum):
    """Why `refine_dense` stopped (a value for callers to act on; `DenseResult.reason` is the text for people).
    Orthogonal to `DenseResult.improved`: a run stopped by the time limit or an interruption may have improved."""

    COMPLETED = 'completed'                  # every iteration ran
    TIME_LIMIT = 'time limit'                # DenseConfig.max_seconds reached
    INTERRUPTED = 'interrupted'              # should_stop() said so (a stopping node)
    SCREENED_OUT = 'screened out'            # one of several starts, ended after screening (never the result)
    NO_SURFACE = 'no surface'                # the code of some iteration decodes to no surface
    NON_FINITE_ENERGY = 'non-finite energy'
    NO_VIEWS = 'no usable views'
    INVALID_INPUT = 'invalid input'          # non-finite code or pose


@dataclass
class DenseResult:
    """Outcome of `refine_dense`. improved False: keep the input (sparse) estimate; `stop` and `reason` say why."""

    code: np.ndarray
    T_world_object: np.ndarray
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    improved: bool = False
    reason: str = ''
    stop: DenseStop = DenseStop.COMPLETED
    energies: dict[str, float] = field(default_factory=dict)
    initial_energies: dict[str, float] = field(default_factory=dict)
    iterations: int = 0               # of this run (of the chosen start after `refine_dense_starts`)
    total_iterations: int = 0         # of every start (`refine_dense_starts`; 0 from `refine_dense`)
    best_iteration: int = 0
    views: int = 0
    seconds: float = 0.0
    seconds_per_iteration: float = 0.0
    check_energies: list[float] = field(default_factory=list)   # of every iteration of this run, in order

    @property
    def yaw(self) -> float:
        return float(math.atan2(self.rotation[1, 0], self.rotation[0, 0]))


# ------------------------------------------------------------------ geometry helpers
def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation (3, 3) of an axis-angle vector w (3,) (Rodrigues), differentiable also at w = 0."""
    theta2 = (w * w).sum()
    theta = torch.sqrt(theta2 + 1e-12)
    zero = w.new_zeros(())
    Kx = torch.stack([torch.stack([zero, -w[2], w[1]]), torch.stack([w[2], zero, -w[0]]),
                      torch.stack([-w[1], w[0], zero])])
    a = torch.where(theta2 > 1e-8, torch.sin(theta) / theta, 1 - theta2 / 6)
    b = torch.where(theta2 > 1e-8, (1 - torch.cos(theta)) / (theta2 + 1e-12), 0.5 - theta2 / 24)
    return torch.eye(3, dtype=w.dtype, device=w.device) + a * Kx + b * (Kx @ Kx)


def implicit_surface_points(sdf_fn, x0: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Surface points x(z) (P, 3) equal to x0 in value, differentiable in z by the implicit-function rule.

    sdf_fn(x (P, 3), z (C,)) -> (P,). On the level set f(x(z), z) = const, so df/dx dx/dz + df/dz = 0 and
    the minimum-norm solution is dx/dz = -(df/dx)^+ df/dz = -g (df/dz) / |g|^2 with g = df/dx (along the
    normal). Implemented as x0 - g (f(x0, z) - f(x0, z).detach()) / |g|^2. Returns (x (P, 3), g (P, 3)).
    """
    with torch.enable_grad():
        xg = x0.detach().clone().requires_grad_(True)
        g = torch.autograd.grad(sdf_fn(xg, z.detach()).sum(), xg)[0]
    f = sdf_fn(x0.detach(), z)
    step = (f - f.detach()) / (g.square().sum(-1) + 1e-9)
    return x0.detach() - g * step[:, None], g


# ------------------------------------------------------------------ rays of the detection pyramid
@dataclass
class Rays:
    """Pixels as rays: origin (V, N, 3) and direction (V, N, 3) in the world (a point at camera depth z is
    origin + z direction), target (V, N) mask fraction, weight (V, N) (0 for unknown pixels), limit (V, N) the
    camera depth up to which the ray is known (inf: all of it; `_level_rays`) or None (every ray whole)."""

    origin: torch.Tensor
    direction: torch.Tensor
    target: torch.Tensor
    weight: torch.Tensor
    limit: torch.Tensor | None = None

    def to(self, device) -> 'Rays':
        return Rays(*(x.to(device) if x is not None else None
                      for x in (self.origin, self.direction, self.target, self.weight, self.limit)))


def pyramid_levels(box_w: float, box_h: float, r_min: float, r_max: float) -> list[int]:
    """Levels l (coarse first) with r_min^2 < w h / 4^l < r_max^2 (supplement); [0] if the box is smaller."""
    area = max(box_w * box_h, 1.0)
    levels = [l for l in range(12) if r_min ** 2 < area / 4 ** l < r_max ** 2]
    return sorted(levels, reverse=True) or [0]


def _level_rays(view: DenseView, level: int, n: int, gen: torch.Generator, free_space_margin: float | None = None):
    """n pixels of one view at one pyramid level: (uv (n, 2), target (n,), weight (n,), limit (n,)).

    With free_space_margin (metres) and the view's registered depth, a pixel none of whose footprint is this
    object's mask but which measures a surface at camera depth d (the footprint's nearest) is known free only up
    to d - free_space_margin (limit; beyond the paper): the object may lie behind what was measured, hidden by
    an undetected occluder (clutter, a missed detection), where its mask has a hole, or behind another
    detection, whose pixels then count up to their surface instead of not at all. Elsewhere limit is inf."""
    u0, v0, u1, v1 = view.crop
    side = u1 - u0
    S = view.labels.shape[0]
    spacing = float(2 ** level)
    k = max(1, int(round(spacing / (side / S))))            # footprint of a level pixel in stored cells
    lab = torch.as_tensor(view.labels)
    maps = torch.stack([(lab == LABEL_OBJECT).float(), (lab == LABEL_UNKNOWN).float()])[None]
    if k > 1:  # the level's target: the mask averaged over the pixel footprint
        maps = F.avg_pool2d(maps, k, stride=1, padding=k // 2, count_include_pad=False)[..., :S, :S]
    m = max(1, int(side // spacing))
    idx = torch.randint(0, m * m, (n,), generator=gen) if m * m > n else torch.randperm(m * m, generator=gen)[:n]
    if len(idx) < n:
        idx = idx[torch.randint(0, len(idx), (n,), generator=gen)]
    uv = torch.stack([u0 + spacing * ((idx % m).float() + 0.5), v0 + spacing * ((idx // m).float() + 0.5)], -1)
    cell = ((uv - torch.tensor([u0, v0])) / side * S).long().clamp(0, S - 1)
    fg, unknown = maps[0, 0][cell[:, 1], cell[:, 0]], maps[0, 1][cell[:, 1], cell[:, 0]]
    weight, limit = (unknown < 0.5).float(), torch.full((len(uv),), math.inf)
    if free_space_margin is not None and view.depth is not None:
        depth = torch.as_tensor(view.depth.astype(np.float32))
        nearest = torch.where(torch.isfinite(depth), depth, torch.full_like(depth, math.inf))
        if k > 1:
            nearest = -F.max_pool2d(-nearest[None, None], k, stride=1, padding=k // 2)[0, 0, :S, :S]
        d = nearest[cell[:, 1], cell[:, 0]]
        free = (fg == 0) & torch.isfinite(d)
        weight = torch.where(free, torch.ones_like(weight), weight)
        limit = torch.where(free, d - free_space_margin, limit)
    return uv, fg, weight, limit


def make_rays(views: list[DenseView], cfg: DenseConfig, phases: int, gen: torch.Generator) -> list[Rays]:
    """One `Rays` per phase (coarse to fine); view v at phase p uses its level levels_v[p * len / phases]."""
    per_view = [pyramid_levels(v.box[0], v.box[1], cfg.r_min, cfg.r_max) for v in views]
    margin = cfg.free_space_margin if cfg.free_space else None
    out = []
    for p in range(phases):
        uvs, targets, weights, limits = [], [], [], []
        for v, levels in zip(views, per_view):   # setup only, not per iteration
            uv, fg, w, lim = _level_rays(v, levels[min(len(levels) - 1, p * len(levels) // phases)],
                                         cfg.rays_per_view, gen, margin)
            uvs.append(uv), targets.append(fg), weights.append(w), limits.append(lim)
        uv = torch.stack(uvs)                                                       # (V, N, 2)
        K = torch.as_tensor(np.stack([v.K for v in views]), dtype=torch.float32)
        R_wc = torch.as_tensor(np.stack([v.T_world_camera[:3, :3] for v in views]), dtype=torch.float32)
        ray_cam = torch.cat([(uv - K[:, None, :2, 2]) / K[:, None, [0, 1], [0, 1]], torch.ones_like(uv[..., :1])], -1)
        direction = torch.einsum('vij,vnj->vni', R_wc, ray_cam)
        origin = torch.as_tensor(np.stack([v.T_world_camera[:3, 3] for v in views]),
                                 dtype=torch.float32)[:, None].expand_as(direction)
        out.append(Rays(origin.contiguous(), direction, torch.stack(targets), torch.stack(weights),
                        torch.stack(limits)))
    return out


def dense_silhouette(volume: torch.Tensor, R: torch.Tensor, t: torch.Tensor, s: torch.Tensor, rays: Rays,
                     step: float, sharpness: float, confidence: float,
                     bounds: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Es (paper Eq. 7/8): mean over views of -log(H Pf + (1 - H)(1 - Pf)) over each view's known pixels, with H
    from `foreground_probability` (the same arguments)."""
    H = foreground_probability(volume, R, t, s, rays, step, sharpness, bounds)
    pf = confidence * rays.target + (1 - confidence) * (1 - rays.target)
    nll = -torch.log((H * pf + (1 - H) * (1 - pf)).clamp_min(1e-6))
    return ((nll * rays.weight).sum(1) / rays.weight.sum(1).clamp_min(1.0)).mean()


def foreground_probability(volume: torch.Tensor, R: torch.Tensor, t: torch.Tensor, s: torch.Tensor, rays: Rays,
                           step: float, sharpness: float,
                           bounds: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """H (V, N) (paper Eq. 8): each ray's foreground probability, 1 - prod sig(zeta f) over samples every `step`
    along the ray inside the cube.

    volume (1, 1, R, R, R): SDF grid indexed [z, y, x] over [-1, 1]^3 (grid_sample layout); R (3, 3), t (3,),
    s (): the object pose. Differentiable in the volume values and the pose; all samples are read once without
    gradient, only those with |zeta f| < ACTIVE_LOGIT on rays that are not saturated (log prod sig >=
    -ACTIVE_LOGIT) again with it (the others are constants: their slope, or the ray's dH, is below
    e^-ACTIVE_LOGIT; issue 28).
    bounds (lo (3,), hi (3,)): the part of the cube that is sampled (None: all of it); `surface_bounds` gives the
    box beyond which every sample is a constant near 0, so rays are clipped to it (a speed-up, issue 28).
    A part thinner than a few grid cells reads as partly transparent (its trilinear values barely negative):
    `bench/bench_dense.py opacity` measures how much on the prior's shapes.
    """
    o = (rays.origin - t) @ R / s                                                    # (V, N, 3) object frame
    d = rays.direction @ R
    d = d / torch.linalg.norm(d, dim=-1, keepdim=True)
    safe = torch.where(d.abs() < 1e-9, torch.full_like(d, 1e-9), d)
    t1, t2 = (-1 - o) / safe, (1 - o) / safe
    t_near = torch.minimum(t1, t2).amax(-1).clamp_min(0)
    t_far = torch.maximum(t1, t2).amin(-1)
    if bounds is not None:   # clipped on the cube's sample lattice: the samples kept are the unclipped ones
        b1, b2 = (bounds[0] - o) / safe, (bounds[1] - o) / safe
        t_box = torch.minimum(b1, b2).amax(-1)
        t_near = torch.maximum(t_near, t_near + torch.floor((t_box - t_near) / step) * step)
        t_far = torch.minimum(t_far, torch.maximum(b1, b2).amin(-1))
    # a ray known only up to a measured surface (`Rays.limit`, camera depth) ends there: in the object frame the
    # camera depth z lies at z |direction| / s along the unit direction
    if rays.limit is not None:
        t_far = torch.minimum(t_far, rays.limit * torch.linalg.norm(rays.direction, dim=-1) / s)
    hit = t_far > t_near
    V, N = o.shape[:2]
    with torch.no_grad():   # every sample once without gradient, flat: ray r has count[r] at t_near + (k + 1/2) step
        count = torch.where(hit, torch.ceil((t_far - t_near) / step - 0.5).clamp_min(0),
                            torch.zeros_like(t_near)).long().reshape(-1)
        ray = torch.repeat_interleave(torch.arange(V * N, device=o.device), count)
        first = torch.cumsum(count, 0) - count
        k = (torch.arange(len(ray), device=o.device) - first[ray]).to(o.dtype) + 0.5
        x = o.reshape(-1, 3)[ray] + (t_near.reshape(-1)[ray] + k * step)[:, None] * d.reshape(-1, 3)[ray]
        f = _read_volume(volume.detach(), x, ACTIVE_LOGIT / sharpness)
        # samples far from the surface have a flat log-sigmoid: constants; the band gets the gradient, except on
        # rays that are saturated (log of the background probability below -ACTIVE_LOGIT: H within e^-12 of 1,
        # so dH/dG of every sample on them is below that)
        log_sig = F.logsigmoid(sharpness * f)
        saturated = torch.zeros(V * N, dtype=o.dtype, device=o.device).index_add_(0, ray, log_sig) < -ACTIVE_LOGIT
        active = ((sharpness * f).abs() < ACTIVE_LOGIT) & ~saturated[ray]
        log_background = torch.zeros(V * N, dtype=o.dtype, device=o.device).index_add_(0, ray, log_sig * ~active)
    r_a, k_a = ray[active], k[active]
    if torch.is_grad_enabled() and len(r_a):
        x_a = o.reshape(-1, 3)[r_a] + (t_near.reshape(-1)[r_a] + k_a * step)[:, None] * d.reshape(-1, 3)[r_a]
        f_a = F.grid_sample(volume, x_a.reshape(1, -1, 1, 1, 3), mode='bilinear', padding_mode='border',
                            align_corners=True).reshape(-1)
    else:
        f_a = f[active]
    log_background = log_background.index_add(0, r_a, F.logsigmoid(sharpness * f_a)).reshape(V, N)
    return 1 - torch.exp(log_background)


BLOCK_CELLS = 4   # side of the blocks of `_read_volume`'s empty-space test, in grid cells


def _read_volume(volume: torch.Tensor, x: torch.Tensor, far: float) -> torch.Tensor:
    """Trilinear reads (without gradient) of volume (1, 1, R, R, R) at x (K, 3), skipping empty space: a sample in
    a block of BLOCK_CELLS^3 cells whose grid values are all >= far reads as 1 (a trilinear value there is >= far
    as well, so the sample is outside the active band either way and adds log sig(zeta f) ~ 0; issue 28)."""
    res = volume.shape[-1]
    blocks = -F.max_pool3d(F.pad(-volume, (0, BLOCK_CELLS,) * 3, value=-math.inf), BLOCK_CELLS + 1, BLOCK_CELLS)[0, 0]
    nb = blocks.shape[-1]
    b = ((x + 1) * (0.5 * (res - 1) / BLOCK_CELLS)).long().clamp_(0, nb - 1)
    keep = torch.nonzero(blocks[b[:, 2], b[:, 1], b[:, 0]] < far).squeeze(1)
    f = torch.ones(len(x), dtype=volume.dtype, device=volume.device)
    if len(keep):
        f[keep] = F.grid_sample(volume, x[keep].reshape(1, -1, 1, 1, 3), mode='bilinear', padding_mode='border',
                                align_corners=True).reshape(-1)
    return f


def vjp_points(grad: torch.Tensor, values: torch.Tensor, near: float, most: int, tail: float) -> torch.Tensor:
    """Indices of the grid points that enter the code's vector-Jacobian product dEs/dz = sum_i dEs/dG_i dG_i/dz:
    those with a non-zero gradient `grad` and |SDF value| < near, largest |grad| first, at most `most`, less the
    smallest ones whose |grad| sums to under `tail` of the total (on the demo walk 99.999 % of it sits in 45 % of
    the points, so the product costs half as much for a relative change of the sum of at most `tail`; issue 28)."""
    idx = torch.nonzero((grad != 0) & (values.abs() < near)).squeeze(1)
    if not len(idx):
        return idx
    mass, order = torch.sort(grad[idx].abs().double(), descending=True)        # float64: float32 sums drift by ~1e-5
    kept = int(torch.searchsorted(torch.cumsum(mass, 0), (1 - tail) * mass.sum())) + 1 if tail > 0 else len(idx)
    return idx[order[:min(kept, len(idx), most)]]


def surface_bounds(vertices: torch.Tensor, sharpness: float, cell: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The box (lo (3,), hi (3,)) in the normalised frame outside which the silhouette's samples are constants:
    the surface's bounding box grown by the active band (|zeta f| < ACTIVE_LOGIT, assuming |f| grows at least
    like the distance) and one grid cell (trilinear reads), within [-1, 1]^3."""
    margin = ACTIVE_LOGIT / sharpness + cell
    return ((vertices.amin(0) - margin).clamp(-1, 1), (vertices.amax(0) + margin).clamp(-1, 1))


def sdf_distance(prior, points_world: torch.Tensor, z: torch.Tensor, R, t, s, truncation: float) -> torch.Tensor:
    """Mean truncated |SDF| in metres (divided by the truncation) of world points (M, 3); 0 if none.

    Points outside the decoder's cube [-1, 1]^3 add their distance to it (the decoder is untrained there).
    """
    if points_world is None or len(points_world) == 0:
        return z.new_zeros(())
    x = (points_world - t) @ R / s
    inside = x.clamp(-1, 1)
    f = prior.decoder.sdf(z[None], inside[None])[0]
    d = s * (f.abs() + torch.linalg.norm(x - inside, dim=-1))
    return d.clamp(max=truncation).mean() / truncation


# ------------------------------------------------------------------ stage
class _RunClock:
    """Seconds a run has been running, not counting its pauses (other starts running in between)."""

    def __init__(self):
        self._spent, self._since = 0.0, time.perf_counter()

    def seconds(self) -> float:
        return self._spent + (time.perf_counter() - self._since if self._since is not None else 0.0)

    def pause(self) -> None:
        self._spent, self._since = self.seconds(), None

    def resume(self) -> None:
        self._since = time.perf_counter()


def distinct_starts(prior, starts: Sequence[tuple], separation: float) -> list[int]:
    """Indices of the starts (code, T_world_object) to run: in order, each whose placed surface (the point decoder's
    2048 points, in the world) is at least `separation` metres (symmetric mean chamfer) from every start kept before
    it. Why: the sparse stage's runs often end in one place (on the demo walk its three end states lie 0.9-2.9 cm
    apart and their dense results within 0.5 points of F1@5cm), and a dense run from there costs as much again."""
    if len(starts) < 2 or separation <= 0:
        return list(range(len(starts)))
    with torch.no_grad():
        points = prior.decode_points(np.stack([np.asarray(c, np.float32) for c, _ in starts])).float().cpu()
    transforms = torch.as_tensor(np.stack([np.asarray(T, np.float64) for _, T in starts]), dtype=torch.float32)
    world = points @ transforms[:, :3, :3].transpose(1, 2) + transforms[:, None, :3, 3]
    kept = [0]
    for j in range(1, len(starts)):
        if all(_chamfer(world[j], world[i]) >= separation for i in kept):
            kept.append(j)
    return kept


def _chamfer(a: torch.Tensor, b: torch.Tensor) -> float:
    d = torch.cdist(a, b)
    return 0.5 * float(d.amin(1).mean() + d.amin(0).mean())


def refine_dense_starts(prior, code, T_world_object: np.ndarray, views: list[DenseView],
                        slam_points: np.ndarray | None = None, box=None, config: DenseConfig | None = None,
                        should_stop=None, floor_height: float | None = None,
                        height_range: tuple[float, float] | None = None,
                        alternatives: Sequence[tuple] = (), max_starts: int = 1,
                        facing: np.ndarray | None = None) -> tuple[DenseResult, int]:
    """The dense stage from the sparse result (code, T_world_object) and from up to max_starts - 1 further starts,
    the (code, T_world_object, ...) of `alternatives` (`SparseResult.alternatives`; beyond the paper); returns
    (the result with the lowest check energy, its start index: 0 = the sparse result).

    Why: on real captures the dense stage ends in a start-dependent basin (the same object from two sparse
    estimates ended 20-35 points of F1@5cm apart), and its check energy -- same views, rays, landmarks and
    priors for every start -- picked the better end state 7 times in 10 (docs/experiments/frodo_optim_history.md,
    "Dense starts").
    Cost (issue 28): a start within `config.start_separation` of an earlier one is not run (`distinct_starts`);
    with `config.screen_iterations` N > 0 every start runs N iterations, and only those whose lowest check energy
    so far is within `config.screen_margin` of the lowest of all go on, each exactly as if it had run alone.
    A later start wins only with a check energy below the first start's best (which is never above the sparse
    result's own), so the result is never worse, by the energy, than the dense stage from the sparse result.
    A result from a later start is marked improved (it replaces the sparse estimate) even if its own run did
    not lower its energy. Other arguments as `refine_dense`.
    """
    cfg = config or DenseConfig()
    candidates = [(code, T_world_object)] + [tuple(a[:2]) for a in alternatives][:max(0, int(max_starts) - 1)]
    index = distinct_starts(prior, candidates, float(cfg.start_separation))
    runs = [_dense_run(prior, *candidates[i], views, slam_points, box, cfg, should_stop, floor_height, height_range,
                       facing) for i in index]
    screen = int(cfg.screen_iterations)
    screening = len(runs) > 1 and 0 < screen < int(cfg.iterations)
    energies: list[list[float]] = [[] for _ in runs]
    results: list[DenseResult | None] = [None] * len(runs)

    def advance(i: int, until: int | None = None, stop: bool = False) -> None:
        """Run start i until it has computed the check energy of iteration `until` (None: to its end); stop: end it."""
        while results[i] is None and (stop or until is None or len(energies[i]) <= until):
            try:
                energies[i].append(runs[i].send(True if stop else None))
            except StopIteration as end:
                results[i] = end.value

    started = 0
    for i in range(len(runs)):
        if i and should_stop is not None and should_stop():
            break
        advance(i, screen if screening else None)
        started += 1
    continued = started
    if screening:
        lowest = {i: min(energies[i], default=math.inf) if results[i] is None else _check(results[i])
                  for i in range(started)}
        floor = min(lowest.values())
        for i in range(started):
            advance(i, None, stop=lowest[i] > floor + float(cfg.screen_margin))
        continued = sum(r.stop is not DenseStop.SCREENED_OUT for r in results[:started])
    done = [r for r in results if r is not None]
    best = min(range(len(done)), key=lambda i: (_check(done[i]), i))
    if not _check(done[best]) < _check(done[0]):
        best = 0
    chosen = done[best]
    if screening and started > 1:
        chosen.reason = f'{continued} of {started} starts continued after {screen} iterations: {chosen.reason}'
    if len(index) < len(candidates):
        chosen.reason = f'{len(candidates) - len(index)} of {len(candidates)} starts alike, not run; {chosen.reason}'
    if best > 0:
        chosen.improved = True
        chosen.reason = f'start {index[best]} of {len(candidates)} (E {_check(done[0]):.3f} from the sparse result): ' \
                        f'{chosen.reason}'
    chosen.seconds = sum(r.seconds for r in done)
    chosen.total_iterations = sum(r.iterations for r in done)
    if started < len(runs) or any(r.stop is DenseStop.INTERRUPTED for r in done):
        chosen.stop = DenseStop.INTERRUPTED     # not every start ran to its end: say so, whichever won
    return chosen, index[best]


def _check(r: DenseResult) -> float:
    e = r.energies.get('total', math.inf)
    return e if math.isfinite(e) else math.inf


def refine_dense(prior, code, T_world_object: np.ndarray, views: list[DenseView], slam_points: np.ndarray | None = None,
                 box=None, config: DenseConfig | None = None, should_stop=None, floor_height: float | None = None,
                 height_range: tuple[float, float] | None = None, facing: np.ndarray | None = None) -> DenseResult:
    """Dense code + 7-DoF pose refinement of one object from its sparse estimate (paper Sec. 5.3).

    prior: `ShapePrior` (decoder.sdf, sdf_numpy, training_codes); code (C,), T_world_object (4, 4) similarity:
    the sparse result; views: `DenseView`s (at most config.max_views, spread evenly); slam_points (N, 3) world
    landmarks or None; box (centre, size, yaw) to select landmarks (None: all landmarks within the object's
    cube). should_stop: optional callable polled every iteration (a stopping node ends the stage at once,
    keeping the best state so far). floor_height (world z) / height_range (m) / facing (unit horizontal (2,)):
    the support priors E_floor / E_size / E_facing (`support.py`, weights w_floor / w_height / w_facing); None:
    off. Never raises on bad input: returns the input with improved=False and a reason.
    """
    return _finish(_dense_run(prior, code, T_world_object, views, slam_points, box, config, should_stop, floor_height,
                              height_range, facing))


def _finish(run: Generator[float, bool | None, DenseResult]) -> DenseResult:
    """Runs a `_dense_run` to its end; its result."""
    try:
        while True:
            run.send(None)
    except StopIteration as end:
        return end.value


def _dense_run(prior, code, T_world_object: np.ndarray, views: list[DenseView], slam_points: np.ndarray | None,
               box, config: DenseConfig | None, should_stop, floor_height: float | None,
               height_range: tuple[float, float] | None,
               facing: np.ndarray | None = None) -> Generator[float, bool | None, DenseResult]:
    """`refine_dense` as a generator, so that several starts can run in turns (`refine_dense_starts`): yields each
    iteration's check energy before its step and ends there with the result so far when sent True (SCREENED_OUT);
    returns the DenseResult. Its clock (time limit, seconds) counts only the time it runs."""
    cfg = config or DenseConfig()
    clock = _RunClock()
    code = np.asarray(code, dtype=np.float32)
    T0 = np.asarray(T_world_object, dtype=np.float64)
    s0 = float(np.linalg.norm(T0[:3, 0]))
    R0 = T0[:3, :3] / max(s0, 1e-12)

    def unchanged(stop: DenseStop, reason: str, **extra) -> DenseResult:
        return DenseResult(code, T0, s0, R0, T0[:3, 3].copy(), improved=False, reason=reason, stop=stop, views=len(views),
                           seconds=clock.seconds(), **extra)

    if not (np.isfinite(code).all() and np.isfinite(T0).all() and s0 > 0):
        return unchanged(DenseStop.INVALID_INPUT, 'non-finite code or pose')
    views = [v for v in views if v is not None and np.isfinite(v.K).all() and np.isfinite(v.T_world_camera).all()
             and (v.labels == LABEL_OBJECT).any()]
    views = select_views(views, cfg.max_views)
    if not views:
        return unchanged(DenseStop.NO_VIEWS, 'no usable views')

    dev = torch.device(getattr(prior, 'device', 'cpu'))
    gen = torch.Generator().manual_seed(int(cfg.seed))
    Rg = max(8, int(cfg.grid_resolution))
    phases = max(len(pyramid_levels(v.box[0], v.box[1], cfg.r_min, cfg.r_max)) for v in views)
    phase_rays = [r.to(dev) for r in make_rays(views, cfg, phases, gen)]
    check_rays = phase_rays[-1]
    batch = ViewBatch(views, dev)
    if box is not None:
        center, size, yaw = box
        slam = slam_points_near(slam_points, center, size, float(yaw), margin=0.1 * float(np.max(size)) + 0.05)
    else:
        slam = np.zeros((0, 3), np.float32) if slam_points is None else np.asarray(slam_points, np.float32)
    slam_t = torch.as_tensor(slam, device=dev) if len(slam) >= 5 and cfg.w_geometry > 0 else None
    depth = [v.depth_points for v in views if v.depth_points is not None and len(v.depth_points)]
    depth_t = None
    if depth and cfg.w_depth > 0:
        depth_t = torch.as_tensor(np.concatenate(depth), device=dev)
        if len(depth_t) > 2048:
            depth_t = depth_t[torch.randperm(len(depth_t), generator=gen)[:2048].to(dev)]
    mu, sigma = (x.to(dev) for x in code_statistics(prior.training_codes))
    use_floor = floor_height is not None and math.isfinite(float(floor_height)) and cfg.w_floor > 0
    use_height = height_range is not None and cfg.w_height > 0
    w_facing = support.facing_weight(cfg.w_facing, facing, [np.asarray(v.T_world_camera)[:3, 3] for v in views], T0[:3, 3])
    use_facing = w_facing > 0
    grid_xyz = torch.as_tensor(grid_points(Rg).reshape(-1, 3), device=dev)
    cell = 2.0 / (Rg - 1)

    def sdf_fn(x, zz):
        return prior.decoder.sdf(zz[None], x[None])[0]

    z = torch.as_tensor(code, device=dev).clone().requires_grad_(cfg.optimise_code)
    w = torch.zeros(3, device=dev, requires_grad=True)
    # Option: furniture stands upright in a gravity-aligned world. With any rotation free the real-capture outputs
    # lean by a median 3 deg (up to 13), yet holding them upright did not score better
    # (docs/experiments/frodo_optim_history.md, "Upright").
    axes = torch.tensor([0.0, 0.0, 1.0] if cfg.upright else [1.0, 1.0, 1.0], device=dev)
    t = torch.as_tensor(T0[:3, 3], dtype=torch.float32, device=dev).clone().requires_grad_(True)
    log_s = torch.tensor(math.log(s0), device=dev, requires_grad=True)
    R0_t = torch.as_tensor(R0, dtype=torch.float32, device=dev)
    groups = [{'params': [w], 'lr': cfg.lr_rotation}, {'params': [t], 'lr': cfg.lr_translation},
              {'params': [log_s], 'lr': cfg.lr_log_scale}]
    if cfg.optimise_code:
        groups.append({'params': [z], 'lr': cfg.lr_code})
    opt = Adam(groups)
    best, initial, done, reason_stop, stop, history = None, None, 0, '', DenseStop.COMPLETED, []
    iters = max(0, int(cfg.iterations))
    loop_start = clock.seconds()
    grid, drift = None, 0.0
    # a grid value kept from an earlier iteration stays outside the active band while its drift (bounded by the
    # summed largest change in the band) leaves it beyond ACTIVE_LOGIT / sharpness and one cell of the surface
    drift_limit = cfg.grid_band - ACTIVE_LOGIT / cfg.sharpness - cell
    for it in range(iters + 1):
        zc = z.detach()
        code_np = zc.cpu().numpy()
        if grid is None or drift_limit <= 0 or drift >= drift_limit:
            grid, drift = sdf_grid(lambda p: prior.sdf_numpy(p, code_np), Rg, coarse=max(1, int(cfg.grid_coarse))), 0.0
        else:
            grid, change = update_band(lambda p: prior.sdf_numpy(p, code_np), grid, cfg.grid_band)
            drift += change
        mesh = marching_cubes(grid)
        if len(mesh.vertices) == 0 or not np.isfinite(grid).all():
            reason_stop, stop = f'code of iteration {it} has no surface', DenseStop.NO_SURFACE
            break
        volume = torch.as_tensor(np.ascontiguousarray(grid.transpose(2, 1, 0)), device=dev)[None, None].requires_grad_(True)
        R = so3_exp(w * axes) @ R0_t
        s = torch.exp(log_s)
        rays = phase_rays[min(phases - 1, it * phases // max(iters, 1))]
        verts = torch.as_tensor(mesh.vertices, dtype=torch.float32, device=dev)
        bounds = surface_bounds(verts, cfg.sharpness, cell)
        terms = {'silhouette': dense_silhouette(volume, R, t, s, rays, cfg.ray_step, cfg.sharpness, cfg.mask_confidence,
                                                bounds)}
        if len(verts) > cfg.surface_points:
            verts = verts[torch.randperm(len(verts), generator=gen)[:cfg.surface_points].to(dev)]
        terms['photometric'] = z.new_zeros(())
        if cfg.w_photometric > 0 and batch.has_rgb:
            x, g = implicit_surface_points(sdf_fn, verts, z)
            world = s * x @ R.T + t
            normals = (g / torch.linalg.norm(g, dim=-1, keepdim=True).clamp_min(1e-9)) @ R.T
            terms['photometric'] = photometric_energy(batch, world, cfg.photometric_neighbours, cfg.huber_delta,
                                                      cfg.occlusion_tolerance * s.detach(), normals.detach())
        terms['geometry'] = sdf_distance(prior, slam_t, z, R, t, s, cfg.geometry_truncation) if slam_t is not None \
            else z.new_zeros(())
        terms['depth'] = sdf_distance(prior, depth_t, z, R, t, s, cfg.geometry_truncation) if depth_t is not None \
            else z.new_zeros(())
        terms['code'] = (((z - mu) / sigma) ** 2).mean()
        if use_floor or use_height:   # beyond the paper: the extreme vertices (in world z), moved by the implicit rule
            all_verts = torch.as_tensor(mesh.vertices, dtype=torch.float32, device=dev)
            with torch.no_grad():
                order = torch.argsort((s * all_verts @ R.T + t)[:, 2])
            k = min(len(order), SUPPORT_VERTICES)
            ends = all_verts[torch.cat([order[:k], order[-k:]])]
            x_ends, _ = implicit_surface_points(sdf_fn, ends, z)
            world_ends = s * x_ends @ R.T + t
            if use_floor:
                terms['floor'] = support.floor_energy(world_ends[:k], floor_height, cfg.floor_tolerance)
            if use_height:
                terms['height'] = support.height_energy(world_ends, height_range)
        if use_facing:   # beyond the paper: a chair at a table faces it (support.py); front = the object's +x
            terms['facing'] = support.facing_energy(R[:2, 0], facing)
        weights = {'silhouette': cfg.w_silhouette, 'photometric': cfg.w_photometric, 'geometry': cfg.w_geometry,
                   'depth': cfg.w_depth, 'code': cfg.w_code, 'floor': cfg.w_floor, 'height': cfg.w_height,
                   'facing': w_facing}
        total = sum(weights[k] * v for k, v in terms.items())
        with torch.no_grad():   # the check energy: same terms, silhouette on the fixed finest-level rays
            sil_check = terms['silhouette'] if rays is check_rays else dense_silhouette(
                volume, R, t, s, check_rays, cfg.ray_step, cfg.sharpness, cfg.mask_confidence, bounds)
            check = float(total - cfg.w_silhouette * terms['silhouette'] + cfg.w_silhouette * sil_check)
            values = {k: float(v) for k, v in terms.items()} | {'silhouette': float(sil_check), 'total': check}
        if initial is None:
            initial = values
        if not math.isfinite(check):
            reason_stop, stop = f'energy not finite at iteration {it}', DenseStop.NON_FINITE_ENERGY
            break
        history.append(check)
        if best is None or check < best[0]:
            best = (check, it, zc.clone(), R.detach().clone(), t.detach().clone(), float(log_s.detach()), values)
        if it == iters:
            break
        if clock.seconds() > cfg.max_seconds:
            reason_stop, stop = f'time limit {cfg.max_seconds:g}s after {it} iterations', DenseStop.TIME_LIMIT
            break
        if should_stop is not None and should_stop():
            reason_stop, stop = f'interrupted after {it} iterations', DenseStop.INTERRUPTED
            break
        clock.pause()
        screened_out = yield check
        clock.resume()
        if screened_out:
            reason_stop, stop = f'screened out after {it} iterations', DenseStop.SCREENED_OUT
            break
        opt.zero_grad()
        total.backward()
        if cfg.optimise_code and volume.grad is not None:
            # dEs/dz = sum_grid dEs/dG * dG/dz: one vector-Jacobian product on the band with non-zero gradient
            gv = volume.grad[0, 0].permute(2, 1, 0).reshape(-1)                     # back to [i, j, k] order
            idx = vjp_points(gv, torch.as_tensor(grid, device=dev).reshape(-1), 3 * cell, cfg.band_points,
                             cfg.vjp_tail)
            if len(idx):
                (sdf_fn(grid_xyz[idx], z) * gv[idx]).sum().backward()
        opt.step()
        done = it + 1
    per_it = (clock.seconds() - loop_start) / max(done + 1, 1)
    if best is None:
        return unchanged(stop, reason_stop or 'no iteration', initial_energies=initial or {})
    e_best, best_it, zb, Rb, tb, lsb, values_b = best
    sb = math.exp(lsb)
    T = np.eye(4)
    T[:3, :3] = sb * Rb.double().cpu().numpy()
    T[:3, 3] = tb.double().cpu().numpy()
    e0 = initial['total']
    improved = best_it > 0 and e_best < e0 - cfg.min_improvement * abs(e0)
    reason = (f'E {e0:.3f}->{e_best:.3f} at iteration {best_it}/{done}' if improved
              else f'dense did not lower the energy (E {e0:.3f}, best at iteration 0 of {done}); sparse kept')
    if reason_stop:
        reason += f'; stopped: {reason_stop}'
    if not improved:
        return unchanged(stop, reason, energies=values_b, initial_energies=initial, iterations=done, check_energies=history,
                         seconds_per_iteration=per_it)
    return DenseResult(zb.cpu().numpy().astype(np.float32), T, sb, Rb.double().cpu().numpy(), tb.double().cpu().numpy(),
                       True, reason, stop, values_b, initial, iterations=done, best_iteration=best_it, views=len(views),
                       seconds=clock.seconds(), seconds_per_iteration=per_it, check_energies=history)
