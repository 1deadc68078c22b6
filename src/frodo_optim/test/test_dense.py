"""Dense stage (paper Sec. 5.3 "Dense Optimization"): energies' gradients against finite differences, the
implicit surface-point derivative dx/dz, photometric visibility, rollback, and a refinement that helps."""
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from frodo_common.evaluation import point_metrics, sample_surface
from frodo_common.geometry import look_at
from frodo_datasets.render import Material, Renderer, RenderObject, intrinsics
from frodo_optim.dense import (ACTIVE_LOGIT, DenseConfig, Rays, dense_silhouette, distinct_starts,
                               foreground_probability, implicit_surface_points, make_rays, pyramid_levels, refine_dense, refine_dense_starts,
                               sdf_distance, so3_exp, surface_bounds, vjp_points)
from frodo_optim.photometric import (LABEL_OBJECT, ViewBatch, dense_view_from_frame, photometric_energy, visible)
from frodo_optim.sparse import pose_matrix
from frodo_shape.meshing import grid_points, marching_cubes, sdf_grid
from frodo_shape.prior import ShapePrior

W, H = 160, 120


@pytest.fixture(scope='module')
def prior():
    torch.manual_seed(0)
    return ShapePrior.load('furniture', device='cpu')


@pytest.fixture(scope='module')
def scene(prior):
    """A training chair at a known pose, textured, seen by 8 cameras on a circle (colour, labels, depth)."""
    chairs = [i for i, c in enumerate(prior.training_classes) if c == 'chair']
    code = prior.training_codes[chairs[3]].numpy()
    mesh = prior.mesh(code, resolution=48)
    yaw, s = 0.7, 0.5
    t = np.array([1.5, -0.5, -s * mesh.bounds[0, 2]])
    T = pose_matrix(yaw, t, s)
    world = mesh.copy().apply_transform(T)
    renderer = Renderer([RenderObject(world, Material(color=(0.8, 0.3, 0.2), kind='checker',
                                                      color2=(0.2, 0.3, 0.8), scale=6), label=1)])
    K = intrinsics(W, H, 60.0)
    centre = world.bounds.mean(0)
    views = []
    for k in range(8):
        a = 2 * np.pi * k / 8 + 0.3
        Twc = look_at(centre + np.array([2.2 * np.cos(a), 2.2 * np.sin(a), 0.9]), centre)
        out = renderer.render(K, Twc, W, H, shadows=False)
        views.append(dense_view_from_frame(K, Twc, out.labels == 1, None, out.rgb, out.depth, size=64))
    other = prior.training_codes[chairs[7]].numpy()
    return {'code': code, 'T': T, 'views': views, 'other': other, 'mesh': world}


def _volume(prior, code, res=24):
    grid = sdf_grid(lambda p: prior.sdf_numpy(p, code), res, coarse=1)
    return torch.as_tensor(np.ascontiguousarray(grid.transpose(2, 1, 0)))[None, None]


def test_dense_view_data(scene):
    v = scene['views'][0]
    assert v.labels.shape == (64, 64) and v.rgb.shape == (64, 64, 3) and v.depth.shape == (64, 64)
    assert v.nbytes() < 30000
    assert (v.labels == LABEL_OBJECT).mean() > 0.1 and v.depth_points.shape[1] == 3
    assert pyramid_levels(200, 200, 40, 400) == [2, 1, 0] and pyramid_levels(10, 10, 40, 400) == [0]
    assert dense_view_from_frame(np.eye(3), np.eye(4), np.zeros((5, 5), bool), None, None) is None


def test_depth_points_lie_on_the_object(prior, scene):
    """Back-projected masked depth is on the true surface: |SDF| (metres) about zero."""
    T = torch.as_tensor(scene['T'], dtype=torch.float32)
    s = torch.linalg.norm(T[:3, 0])
    pts = torch.as_tensor(scene['views'][0].depth_points)
    e = sdf_distance(prior, pts, torch.as_tensor(scene['code']), T[:3, :3] / s, T[:3, 3], s, 0.1)
    assert float(e) < 0.1      # mean |SDF| below 1 cm


def test_implicit_surface_derivative_matches_finite_differences(prior, scene):
    """dx/dz = -(df/dx)^+ df/dz: moving the code by eps moves the surface along the normal by that much."""
    z0 = torch.as_tensor(scene['code'])
    mesh = prior.mesh(scene['code'], resolution=48)
    x0 = torch.as_tensor(mesh.vertices[::97][:40], dtype=torch.float32)
    # project the marching-cubes vertices onto the decoder's zero level set first (Newton along the gradient)
    sdf = lambda x, z: prior.decoder.sdf(z[None], x[None])[0]  # noqa: E731
    for _ in range(5):
        x, g = implicit_surface_points(sdf, x0, z0)
        x0 = x0 - g * (sdf(x0, z0) / g.square().sum(-1))[:, None].detach()
    direction = torch.randn(z0.shape, generator=torch.Generator().manual_seed(1))
    direction = direction / direction.norm() * 0.05 * z0.norm()
    # analytic: d/dalpha x(z0 + alpha dz) at 0, by autograd through implicit_surface_points
    alpha = torch.zeros((), requires_grad=True)
    x, g = implicit_surface_points(sdf, x0, z0 + alpha * direction)
    analytic = torch.stack([torch.stack([torch.autograd.grad(x[p, i], alpha, retain_graph=True)[0]
                                         for i in range(3)]) for p in range(len(x))])
    np.testing.assert_allclose(x.detach().numpy(), x0.numpy())     # values unchanged
    # finite difference: where the line x0 + r n meets the level set of z0 + eps dz (Newton in r)
    eps = 1e-2
    n = g / g.norm(dim=-1, keepdim=True)
    with torch.no_grad():
        r = torch.zeros(len(x0))
        for _ in range(20):
            p = x0 + r[:, None] * n
            f = sdf(p, z0 + eps * direction)
            gp = torch.func.vmap(torch.func.grad(lambda q: sdf(q[None], z0 + eps * direction)[0]))(p)
            r = r - f / (gp * n).sum(-1)
    numeric = r[:, None] * n / eps
    err = (analytic - numeric).norm(dim=-1)
    assert float(err.median()) < 0.1 * float(numeric.norm(dim=-1).median()) + 1e-4
    assert float(analytic.norm(dim=-1).median()) > 1e-4        # the code really moves the surface


def _fd_check(fn, x: torch.Tensor, eps: float, rtol: float, n_dirs: int = 3):
    """Directional derivatives of a scalar fn at x: autograd vs central differences."""
    x = x.detach().clone().requires_grad_(True)
    grad = torch.autograd.grad(fn(x), x)[0]
    gen = torch.Generator().manual_seed(3)
    for _ in range(n_dirs):
        d = torch.randn(x.shape, generator=gen, dtype=x.dtype)
        d = d / d.norm()
        with torch.no_grad():
            numeric = (fn(x + eps * d) - fn(x - eps * d)) / (2 * eps)
        analytic = (grad * d).sum()
        assert abs(float(analytic) - float(numeric)) <= rtol * max(abs(float(numeric)), 1e-3), (float(analytic), float(numeric))


def test_dense_silhouette_gradients(prior, scene):
    """Es is differentiable in the pose and in the SDF volume; gradients match finite differences."""
    cfg = DenseConfig(rays_per_view=48, ray_step=0.05, sharpness=30.0)
    rays = make_rays(scene['views'][:4], cfg, 1, torch.Generator().manual_seed(0))[0]
    volume = _volume(prior, scene['other'])
    T = torch.as_tensor(pose_matrix(0.8, scene['T'][:3, 3] + [0.03, 0, 0], 0.52), dtype=torch.float64)
    rays64 = Rays(*(x.double() for x in (rays.origin, rays.direction, rays.target, rays.weight)))
    vol64 = volume.double()

    def energy_pose(p):      # p = (axis-angle (3), translation (3), log-scale)
        R = so3_exp(p[:3]) @ (T[:3, :3] / 0.52)
        return dense_silhouette(vol64, R, p[3:6], torch.exp(p[6]), rays64, cfg.ray_step, cfg.sharpness, 0.95)

    p0 = torch.cat([torch.zeros(3, dtype=torch.float64), T[:3, 3], torch.tensor([math.log(0.52)], dtype=torch.float64)])
    assert 0 < float(energy_pose(p0)) < 5
    _fd_check(energy_pose, p0, 1e-4, 0.05)

    def energy_volume(v):
        return dense_silhouette(v, T[:3, :3] / 0.52, T[:3, 3], torch.tensor(0.52, dtype=torch.float64), rays64,
                                cfg.ray_step, cfg.sharpness, 0.95)
    _fd_check(energy_volume, vol64, 1e-4, 0.05)
    # the silhouette prefers the true shape at the true pose over another chair at a wrong pose
    Tt = torch.as_tensor(scene['T'], dtype=torch.float64)
    st = torch.linalg.norm(Tt[:3, 0])
    true = dense_silhouette(_volume(prior, scene['code']).double(), Tt[:3, :3] / st, Tt[:3, 3], st, rays64,
                            cfg.ray_step, cfg.sharpness, 0.95)
    assert float(true) < float(energy_pose(p0))


def _log_background_every_sample(volume, R, t, s, rays, step, sharpness):
    """log prod sig(zeta f) per ray (V, N), read at every lattice sample inside the cube (no clipping, no skipping)."""
    o = (rays.origin - t) @ R / s
    d = rays.direction @ R
    d = d / torch.linalg.norm(d, dim=-1, keepdim=True)
    t1, t2 = (-1 - o) / d, (1 - o) / d
    t_near = torch.minimum(t1, t2).amax(-1).clamp_min(0)
    t_far = torch.maximum(t1, t2).amin(-1)
    if rays.limit is not None:   # camera depth -> distance along the unit direction in the object frame
        t_far = torch.minimum(t_far, rays.limit * torch.linalg.norm(rays.direction, dim=-1) / s)
    k = torch.arange(int(math.ceil(2 * math.sqrt(3) / step)), dtype=o.dtype) + 0.5
    ts = t_near[..., None] + k * step
    valid = (ts < t_far[..., None]) & (t_far > t_near)[..., None]
    x = o[..., None, :] + ts[..., None] * d[..., None, :]
    f = torch.nn.functional.grid_sample(volume, x.reshape(1, -1, 1, 1, 3), align_corners=True,
                                        padding_mode='border').reshape(valid.shape)
    return (torch.nn.functional.logsigmoid(sharpness * f) * valid).sum(-1)


def _silhouette_every_sample(volume, R, t, s, rays, step, sharpness, confidence):
    """Es from `_log_background_every_sample`."""
    H = 1 - torch.exp(_log_background_every_sample(volume, R, t, s, rays, step, sharpness))
    pf = confidence * rays.target + (1 - confidence) * (1 - rays.target)
    nll = -torch.log((H * pf + (1 - H) * (1 - pf)).clamp_min(1e-6))
    return ((nll * rays.weight).sum(1) / rays.weight.sum(1).clamp_min(1.0)).mean()


def _slab_volume(resolution: int, half_thickness: float) -> torch.Tensor:
    """SDF volume (grid_sample layout) of a horizontal slab |z| < half_thickness (normalised units)."""
    z = grid_points(resolution)[..., 2]
    return torch.as_tensor(np.ascontiguousarray((np.abs(z) - half_thickness).transpose(2, 1, 0)))[None, None]


def test_foreground_probability_of_a_slab_and_its_thin_limit():
    """Eq. 8: a ray through a thick slab is foreground, one passing beside it is not; a slab thinner than the volume's
    cells reads as partly transparent (what `bench_dense.py opacity` measures on the prior's shapes), and less so
    on a finer volume."""
    cfg = DenseConfig()
    d = torch.tensor([[[0.0, math.cos(0.6), -math.sin(0.6)], [0.0, 0.0, -1.0]]])
    origin = torch.tensor([[[0.0, -2.0 * math.cos(0.6), 2.0 * math.sin(0.6)], [0.0, 0.0, 2.0]]])
    ones = torch.ones(1, 2)
    rays = Rays(origin, d, ones, ones)
    beside = Rays(torch.tensor([[[0.0, -2.0, 0.5]]]), torch.tensor([[[0.0, 1.0, 0.0]]]), ones[:, :1], ones[:, :1])
    pose = (torch.eye(3), torch.zeros(3), torch.tensor(1.0))
    thick = foreground_probability(_slab_volume(32, 0.2), *pose, rays, cfg.ray_step, cfg.sharpness)
    assert (thick > 0.999).all()
    above = foreground_probability(_slab_volume(32, 0.2), *pose, beside, cfg.ray_step, cfg.sharpness)
    assert above[0, 0] < 1e-3                                               # level, 0.3 above the slab
    thin = {r: foreground_probability(_slab_volume(r, 0.015), *pose, rays, cfg.ray_step, cfg.sharpness)
            for r in (32, 128)}
    assert (thin[32] < 0.95).all() and (thin[32] < thin[128]).all()


def test_free_space_ray_ends_at_its_measured_surface():
    """A ray known only up to a measured surface (`Rays.limit`, camera depth along a direction that is not unit
    length, at scale 1 and 2) sees the slab behind that surface as nothing, and the slab in front of it whole."""
    cfg = DenseConfig()
    origin, d = torch.tensor([[[0.0, 0.0, 2.0]]]), torch.tensor([[[0.0, 0.5, -1.0]]])   # camera depth = height drop
    ones = torch.ones(1, 1)
    for scale, top in ((1.0, 1.8), (2.0, 1.6)):          # the slab |z| < 0.2 (normalised) reaches 0.2 s in the world
        pose = (torch.eye(3), torch.zeros(3), torch.tensor(scale))
        H = {limit: float(foreground_probability(_slab_volume(32, 0.2), *pose,
                                                 Rays(origin, d, ones, ones, torch.full((1, 1), limit)),
                                                 cfg.ray_step, cfg.sharpness)) for limit in (top - 0.1, top + 0.15)}
        assert H[top - 0.1] < 0.01 and H[top + 0.15] > 0.99


def _occluded_view(view, depth: float):
    """The view with the lower half of its mask behind an undetected occluder at camera depth `depth`: labelled
    background there, with that depth."""
    labels, measured = view.labels.copy(), view.depth.copy()
    rows = np.nonzero((labels == LABEL_OBJECT).any(axis=1))[0]
    hidden = (labels == LABEL_OBJECT) & (np.arange(len(labels))[:, None] > (rows[0] + rows[-1]) / 2)
    labels[hidden], measured[hidden] = 0, depth
    return replace(view, labels=labels, depth=measured)


def test_free_space_keeps_an_undetected_occluder_from_carving_the_object(prior, scene):
    """With depth, mask pixels lost to an undetected occluder in front of the object (labelled background, their
    depth nearer than the object) cost the true shape nothing more; without free space they do, as they carve
    away what they hide. Off the mask the depth changes nothing: the object lies in front of the background."""
    T = torch.as_tensor(scene['T'], dtype=torch.float32)
    s = torch.linalg.norm(T[:3, 0])
    volume = _volume(prior, scene['code'], 32)

    def energy(views, free_space):
        cfg = DenseConfig(free_space=free_space)
        rays = make_rays(views, cfg, 1, torch.Generator().manual_seed(0))[0]
        return float(dense_silhouette(volume, T[:3, :3] / s, T[:3, 3], s, rays, cfg.ray_step, cfg.sharpness,
                                      cfg.mask_confidence))

    clear = scene['views'][:4]
    hidden = [_occluded_view(v, 1.0) for v in clear]
    assert energy(hidden, False) > energy(clear, False) + 0.2
    assert energy(hidden, True) < energy(clear, True) + 0.02
    assert abs(energy(clear, True) - energy(clear, False)) < 1e-6


def test_level_rays_know_pixels_off_the_mask_up_to_their_depth(scene):
    """`_level_rays` with free space: off the mask, a pixel with depth d is known up to d - margin (another
    detection's pixels too, which count then); without depth, background is known whole and another detection's
    pixels not at all; mask pixels are whole rays."""
    from frodo_optim.dense import _level_rays
    from frodo_optim.photometric import LABEL_UNKNOWN
    view = scene['views'][0]
    labels, depth = view.labels.copy(), np.full(view.labels.shape, np.nan, np.float16)
    labels[:8] = LABEL_UNKNOWN
    depth[:4], depth[-4:] = 1.5, 3.0
    view = replace(view, labels=labels, depth=depth)
    S = len(labels)
    uv, fg, weight, limit = _level_rays(view, 0, S * S, torch.Generator().manual_seed(0), 0.05)
    cell = ((uv - torch.tensor(view.crop[:2])) / (view.crop[2] - view.crop[0]) * S).long()
    row = cell[:, 1]
    unknown_measured, unknown_blank = row < 4, (row >= 4) & (row < 8)
    assert torch.allclose(limit[unknown_measured], torch.tensor(1.45)) and (weight[unknown_measured] == 1).all()
    assert (weight[unknown_blank] == 0).all() and torch.isinf(limit[unknown_blank]).all()
    off_mask = (row >= S - 4) & (fg == 0)
    assert off_mask.any() and torch.allclose(limit[off_mask], torch.tensor(2.95))
    assert torch.isinf(limit[fg > 0]).all()
    assert torch.isinf(_level_rays(view, 0, 64, torch.Generator().manual_seed(0))[3]).all()   # free space off


def test_clipped_and_skipped_silhouette_equals_reading_every_sample(prior, scene):
    """Rays clipped to the surface's box, empty blocks skipped and saturated rays held constant (issue 28) leave Es
    and its gradients as reading every sample does: the samples left out are all outside the active band (log
    sig(zeta f) ~ 0), and on a ray with log prod sig < -ACTIVE_LOGIT (H ~ 1) no sample has a slope that counts."""
    cfg = DenseConfig()
    rays = make_rays(scene['views'], cfg, 1, torch.Generator().manual_seed(0))[0]
    grid = sdf_grid(lambda p: prior.sdf_numpy(p, scene['other']), 32, coarse=2)
    volume = torch.as_tensor(np.ascontiguousarray(grid.transpose(2, 1, 0)))[None, None]
    verts = torch.as_tensor(marching_cubes(grid).vertices, dtype=torch.float32)
    bounds = surface_bounds(verts, cfg.sharpness, 2 / 31)
    assert float((bounds[1] - bounds[0]).prod()) < 8          # the box is smaller than the cube
    T = torch.as_tensor(pose_matrix(0.8, scene['T'][:3, 3] + [0.03, 0, 0], 0.52), dtype=torch.float32)
    pose = [torch.zeros(3, requires_grad=True), T[:3, 3].clone().requires_grad_(True)]
    energies, grads = [], []
    for fn, extra in ((dense_silhouette, (bounds,)), (_silhouette_every_sample, ())):
        vol = volume.clone().requires_grad_(True)
        e = fn(vol, so3_exp(pose[0]) @ (T[:3, :3] / 0.52), pose[1], torch.tensor(0.52), rays, cfg.ray_step,
               cfg.sharpness, cfg.mask_confidence, *extra)
        energies.append(float(e.detach()))
        grads.append(torch.cat([g.reshape(-1) for g in torch.autograd.grad(e, [vol, *pose])]))
    assert 0.05 < energies[1] < 5 and abs(energies[0] - energies[1]) < 1e-4 * energies[1]
    assert float(torch.linalg.norm(grads[0] - grads[1])) < 1e-3 * float(torch.linalg.norm(grads[1]))
    with torch.no_grad():
        log_background = _log_background_every_sample(volume, T[:3, :3] / 0.52, T[:3, 3], torch.tensor(0.52), rays,
                                                      cfg.ray_step, cfg.sharpness)
    assert float((log_background < -ACTIVE_LOGIT).float().mean()) > 0.1       # the scene has saturated rays


def test_code_gradient_from_the_heaviest_band_points_equals_the_whole_band(prior, scene):
    """dEs/dz from the band points that hold all but 1e-5 of sum |dEs/dG| (issue 28) is the whole band's, from
    far fewer points; with no tail dropped every point with a gradient near the surface is used."""
    cfg = DenseConfig()
    rays = make_rays(scene['views'], cfg, 1, torch.Generator().manual_seed(0))[0]
    code = scene['other']
    grid = sdf_grid(lambda p: prior.sdf_numpy(p, code), 32, coarse=2)
    cell = 2 / 31
    volume = torch.as_tensor(np.ascontiguousarray(grid.transpose(2, 1, 0)))[None, None].requires_grad_(True)
    T = torch.as_tensor(pose_matrix(0.8, scene['T'][:3, 3] + [0.03, 0, 0], 0.52), dtype=torch.float32)
    dense_silhouette(volume, T[:3, :3] / 0.52, T[:3, 3], torch.tensor(0.52), rays, cfg.ray_step, cfg.sharpness,
                     cfg.mask_confidence).backward()
    gv = volume.grad[0, 0].permute(2, 1, 0).reshape(-1)
    values = torch.as_tensor(grid).reshape(-1)
    xyz = torch.as_tensor(grid_points(32).reshape(-1, 3))

    def code_gradient(idx):
        z = torch.as_tensor(code).clone().requires_grad_(True)
        return torch.autograd.grad((prior.decoder.sdf(z[None], xyz[idx][None])[0] * gv[idx]).sum(), z)[0]

    whole = vjp_points(gv, values, 3 * cell, 10**6, 0.0)
    assert len(whole) == int(((gv != 0) & (values.abs() < 3 * cell)).sum()) > 500
    kept = vjp_points(gv, values, 3 * cell, 10**6, 1e-5)
    assert len(kept) < 0.8 * len(whole)
    mass = gv.double().abs()
    dropped = mass[whole].sum() - mass[kept].sum()
    assert 0 <= float(dropped) < 1e-5 * float(mass[whole].sum())
    assert float(gv[kept].abs().min()) >= float(gv[whole[~torch.isin(whole, kept)]].abs().max())
    g_whole, g_kept = code_gradient(whole), code_gradient(kept)
    assert float(torch.linalg.norm(g_kept - g_whole)) < 1e-3 * float(torch.linalg.norm(g_whole))
    assert len(vjp_points(gv, values, 3 * cell, 100, 1e-5)) == 100      # the bound on the count still holds


def test_photometric_gradient_and_visibility(prior, scene):
    batch = ViewBatch(scene['views'][:4])
    pts = torch.as_tensor(scene['mesh'].sample(600, seed=0), dtype=torch.float64)
    uv, depth = batch.project(pts.float())
    vis = visible(batch, uv, depth, 0.03)
    # from every view roughly the front half of the surface is visible, never all of it
    frac = vis.float().mean(1)
    assert bool(((frac > 0.15) & (frac < 0.8)).all()), frac
    # true surface points are photo-consistent; displaced ones much less so
    e_true = photometric_energy(batch, pts.float())
    e_off = photometric_energy(batch, pts.float() + torch.tensor([0.05, 0.0, 0.0]))
    assert float(e_true) < 0.6 * float(e_off)
    # gradient wrt the points, visibility held fixed (it is piecewise constant: a point changing visibility
    # between the two finite-difference evaluations makes a jump): finite differences of a smooth shift
    batch64 = ViewBatch(scene['views'][:4])
    for k in ('R', 't', 'K', 'R_wc', 'centre', 'crop_lo', 'crop_hi', 'rgb'):
        setattr(batch64, k, getattr(batch64, k).double())
    base = pts + torch.tensor([0.02, 0.0, 0.0], dtype=torch.float64)
    base_vis = visible(batch64, *batch64.project(base), 0.03)

    def energy(shift):
        return photometric_energy(batch64, base + shift, visibility=base_vis)
    _fd_check(energy, torch.zeros(3, dtype=torch.float64), 1e-5, 0.1)


def test_geometry_term_gradient(prior, scene):
    T = torch.as_tensor(scene['T'], dtype=torch.float32)
    s = torch.linalg.norm(T[:3, 0])
    pts = torch.as_tensor(scene['mesh'].sample(200, seed=0), dtype=torch.float32)
    z = torch.as_tensor(scene['other'])
    assert float(sdf_distance(prior, pts, torch.as_tensor(scene['code']), T[:3, :3] / s, T[:3, 3], s, 0.1)) < \
        float(sdf_distance(prior, pts, z, T[:3, :3] / s, T[:3, 3], s, 0.1))

    def energy(zz):
        return sdf_distance(prior, pts.double(), zz, (T[:3, :3] / s).double(), T[:3, 3].double(), s.double(), 0.1)
    prior.decoder.double()
    try:
        _fd_check(energy, z.double(), 1e-5, 0.05)
    finally:
        prior.decoder.float()


def _surface_distance(prior, code_a, T_a, code_b, T_b) -> float:
    """Chamfer distance (cm, the contract's metric) between two decoded, posed surfaces."""
    pts = [sample_surface(prior.mesh(code, resolution=40).apply_transform(T), 3000)
           for code, T in ((code_a, T_a), (code_b, T_b))]
    return point_metrics(pts[0], pts[1])[2]


def test_dense_refinement_improves_a_perturbed_start(prior, scene):
    """From another chair's code (mixed) and a shifted pose the dense stage gets closer to the true chair: in
    energy, position and surface (codes are not compared: different codes can decode to near-equal shapes)."""
    code0 = (0.5 * scene['code'] + 0.5 * scene['other']).astype(np.float32)
    T0 = pose_matrix(0.8, scene['T'][:3, 3] + [0.04, -0.03, 0.0], 0.52)
    cfg = DenseConfig(iterations=12, grid_resolution=24, rays_per_view=96, w_photometric=0.5, w_depth=0.5)
    res = refine_dense(prior, code0, T0, scene['views'], config=cfg)
    assert res.improved, res.reason
    assert res.energies['total'] < res.initial_energies['total']
    assert res.views == len(scene['views']) and res.iterations == 12 and res.seconds_per_iteration > 0
    assert len(res.check_energies) == 13 and min(res.check_energies) == res.energies['total']
    assert res.check_energies[res.best_iteration] == res.energies['total']
    err0 = np.linalg.norm(T0[:3, 3] - scene['T'][:3, 3])
    assert np.linalg.norm(res.translation - scene['T'][:3, 3]) < err0
    before = _surface_distance(prior, code0, T0, scene['code'], scene['T'])
    after = _surface_distance(prior, res.code, res.T_world_object, scene['code'], scene['T'])
    assert after < 0.8 * before, (after, before)


def test_rollback_keeps_the_input_when_dense_cannot_help(prior, scene):
    """At the true state with absurd step sizes every step is worse: the input comes back, improved=False."""
    cfg = DenseConfig(iterations=3, grid_resolution=24, rays_per_view=64, lr_code=2.0, lr_translation=0.5,
                      lr_rotation=1.0, lr_log_scale=0.5)
    res = refine_dense(prior, scene['code'], scene['T'], scene['views'], config=cfg)
    assert not res.improved and 'sparse kept' in res.reason
    np.testing.assert_allclose(res.T_world_object, scene['T'])
    np.testing.assert_array_equal(res.code, scene['code'])
    # degenerate input: reason, no exception
    bad = refine_dense(prior, scene['code'], np.full((4, 4), np.nan), scene['views'])
    assert not bad.improved and 'non-finite' in bad.reason
    none = refine_dense(prior, scene['code'], scene['T'], [])
    assert not none.improved and none.reason == 'no usable views'


def test_dense_starts_keep_the_lowest_energy_end_state(prior, scene):
    """Several starts: a far-off first start (the sparse result in a wrong basin) loses to a later start near the
    truth, which is then the result (marked improved even without a step); a worse later start never wins."""
    cfg = DenseConfig(iterations=3, grid_resolution=24, rays_per_view=64)
    far = pose_matrix(0.7 + 1.2, scene['T'][:3, 3] + [0.15, -0.1, 0.0], 0.4)
    near = (scene['code'], scene['T'])
    res, start = refine_dense_starts(prior, scene['other'], far, scene['views'], config=cfg,
                                     alternatives=[(*near, 'a start near the truth')], max_starts=2)
    assert start == 1 and res.improved and res.reason.startswith('start 1 of 2')
    first = refine_dense(prior, scene['other'], far, scene['views'], config=cfg)
    assert res.energies['total'] < first.energies['total']
    assert np.linalg.norm(res.translation - scene['T'][:3, 3]) < 0.05
    again, start = refine_dense_starts(prior, *near, scene['views'], config=cfg, alternatives=[(scene['other'], far)],
                                       max_starts=3)
    assert start == 0 and again.energies['total'] <= res.energies['total'] + 1e-6
    # max_starts 1 ignores the alternatives: the dense stage from the sparse result alone
    single, start = refine_dense_starts(prior, scene['other'], far, scene['views'], config=cfg,
                                        alternatives=[near], max_starts=1)
    assert start == 0 and single.reason == first.reason


def test_screened_starts_continue_only_those_near_the_best(prior, scene):
    """screen_iterations: every start runs that long, only those within screen_margin of the lowest energy run the
    rest, each exactly as if it had run alone; a start alike an earlier one (start_separation) is not run."""
    far = pose_matrix(0.7 + 1.2, scene['T'][:3, 3] + [0.15, -0.1, 0.0], 0.4)
    near = (scene['code'], scene['T'])
    alike = scene['T'].copy()
    alike[:3, 3] += [0.005, 0.0, 0.0]
    cfg = DenseConfig(iterations=4, grid_resolution=24, rays_per_view=64, screen_iterations=2, screen_margin=0.0)
    res, start = refine_dense_starts(prior, scene['other'], far, scene['views'], config=cfg,
                                     alternatives=[(*near, 'near the truth'), (scene['code'], alike)], max_starts=3)
    assert start == 1 and res.improved
    assert '1 of 2 starts continued after 2 iterations' in res.reason and '1 of 3 starts alike' in res.reason
    assert res.total_iterations == 2 + 4
    alone = refine_dense(prior, *near, scene['views'], config=cfg)
    np.testing.assert_array_equal(res.code, alone.code)
    assert res.check_energies == alone.check_energies and res.energies == alone.energies
    # a margin wider than the gap continues both: the same as running every start in full
    wide, start = refine_dense_starts(prior, scene['other'], far, scene['views'], config=replace(cfg, screen_margin=10.0),
                                      alternatives=[near], max_starts=2)
    full, full_start = refine_dense_starts(prior, scene['other'], far, scene['views'],
                                           config=replace(cfg, screen_iterations=0), alternatives=[near], max_starts=2)
    assert wide.total_iterations == full.total_iterations == 8 and start == full_start == 1
    np.testing.assert_array_equal(wide.code, full.code)


def test_distinct_starts_skips_a_start_whose_surface_lies_where_an_earlier_one_does(prior, scene):
    """Two starts are alike when their placed surfaces are within start_separation (mean chamfer): the same shape
    moved by 4 mm is, moved by 10 cm is not."""
    T = scene['T']
    shifted = T.copy()
    shifted[:3, 3] += [0.1, 0.0, 0.0]
    nudged = T.copy()
    nudged[:3, 3] += [0.0, 0.004, 0.0]
    starts = [(scene['code'], T), (scene['code'], nudged), (scene['code'], shifted), (scene['code'], nudged)]
    assert distinct_starts(prior, starts, 0.02) == [0, 2]
    assert distinct_starts(prior, starts, 0.0) == [0, 1, 2, 3]


def test_time_limit_bounds_the_stage(prior, scene):
    cfg = DenseConfig(iterations=200, grid_resolution=24, rays_per_view=64, max_seconds=0.5)
    code0 = (0.7 * scene['code'] + 0.3 * scene['other']).astype(np.float32)
    res = refine_dense(prior, code0, scene['T'], scene['views'], config=cfg)
    assert res.iterations < 200 and 'time limit' in res.reason


def test_sparse_stage_uses_the_photometric_term(prior, scene):
    """Ep in the sparse energy (paper Eq. 4): reported, and the refinement still converges near the truth."""
    from frodo_optim.sparse import SparseConfig, refine, view_from_mask
    views = []
    for v in scene['views']:   # sparse views from the dense views' labels (the crop's object pixels)
        mask = np.zeros((H, W), bool)
        u0, v0, u1, _ = v.crop
        S = v.labels.shape[0]
        ys, xs = np.nonzero(v.labels == LABEL_OBJECT)
        px = np.clip(np.round(u0 + (xs + 0.5) * (u1 - u0) / S).astype(int), 0, W - 1)
        py = np.clip(np.round(v0 + (ys + 0.5) * (u1 - u0) / S).astype(int), 0, H - 1)
        mask[py, px] = True
        views.append(view_from_mask(v.K, v.T_world_camera, mask, 96))
    lo, hi = scene['mesh'].bounds
    box = ((lo + hi) / 2, hi - lo, 0.7)
    cfg = SparseConfig(iterations=5, w_photometric=1.0, yaw_candidates=8)
    res = refine(prior, scene['code'], box, views, config=cfg, photometric=ViewBatch(scene['views']))
    assert res.ok and 'photometric' in res.energies and 0 <= res.energies['photometric'] < 0.05
    assert abs(math.atan2(math.sin(res.yaw - 0.7), math.cos(res.yaw - 0.7))) < 0.3


def test_dense_stage_stops_when_asked(prior, scene):
    calls = []
    res = refine_dense(prior, scene['code'], scene['T'], scene['views'],
                       config=DenseConfig(iterations=50, grid_resolution=20, rays_per_view=32),
                       should_stop=lambda: calls.append(1) or len(calls) >= 2)
    assert res.iterations <= 2 and 'interrupted' in res.reason


def test_floor_prior_lifts_a_sunk_start_towards_the_floor(prior, scene):
    """Support prior (beyond the paper): started 8 cm below the floor (the chair stands on z = 0), the dense stage
    with E_floor (floor_height=0) ends with its bottom nearer the floor than without it."""
    T0 = scene['T'].copy()
    T0[2, 3] -= 0.08
    cfg = DenseConfig(iterations=8, grid_resolution=24, rays_per_view=64, w_photometric=0.0, w_depth=0.0,
                      w_floor=1.0)
    mesh = prior.mesh(scene['code'], resolution=48)

    def bottom(res):
        return float(mesh.copy().apply_transform(res.T_world_object).bounds[0, 2])

    with_floor = refine_dense(prior, scene['code'], T0, scene['views'], config=cfg, floor_height=0.0,
                              height_range=(0.4, 1.35))
    without = refine_dense(prior, scene['code'], T0, scene['views'], config=cfg)
    assert 'floor' in with_floor.initial_energies and with_floor.initial_energies['floor'] > 1.0
    assert 'floor' not in without.initial_energies
    assert with_floor.improved and abs(bottom(with_floor)) < abs(bottom(without)) - 0.01, \
        (bottom(with_floor), bottom(without))


def test_upright_dense_stage_only_turns_about_gravity(prior, scene):
    """Option beyond the paper: with `upright` the rotation update is about world z only, so an upright start stays
    upright; with the paper's free rotation (default) the same start tilts."""
    code0 = (0.5 * scene['code'] + 0.5 * scene['other']).astype(np.float32)
    T0 = pose_matrix(0.8, scene['T'][:3, 3] + [0.04, -0.03, 0.0], 0.52)
    tilt = {}
    for upright in (True, False):
        cfg = DenseConfig(iterations=6, grid_resolution=24, rays_per_view=64, w_photometric=0.0, w_depth=0.5,
                          upright=upright)
        res = refine_dense(prior, code0, T0, scene['views'], config=cfg)
        tilt[upright] = float(np.degrees(np.arccos(np.clip(res.rotation[2, 2], -1.0, 1.0))))
    assert tilt[True] < 1e-3 and tilt[False] > 0.05, tilt


@pytest.mark.parametrize('side', [5, 64, 127, 128, 129, 200, 291, 383, 640])
def test_view_resampling_matches_torch_interpolate(side):
    """The numpy crops of a view (labels 'nearest', colour 'area') hold torch interpolate's values exactly."""
    from frodo_optim.photometric import _resample
    rng = np.random.default_rng(side)
    labels = rng.integers(0, 3, (side, side), dtype=np.uint8)
    rgb = rng.integers(0, 256, (side, side, 3), dtype=np.uint8)

    def torch_resample(img, mode):
        t = torch.from_numpy(img).float()
        t = t[None, None] if t.ndim == 2 else t.permute(2, 0, 1)[None]
        out = torch.nn.functional.interpolate(t, size=(128, 128), mode=mode)[0]
        out = out[0] if img.ndim == 2 else out.permute(1, 2, 0)
        return out.round().clamp(0, 255).numpy().astype(np.uint8)
    np.testing.assert_array_equal(_resample(labels, 0, 0, side, 128, 'nearest'), torch_resample(labels, 'nearest'))
    np.testing.assert_array_equal(_resample(rgb, 0, 0, side, 128, 'area'), torch_resample(rgb, 'area'))
