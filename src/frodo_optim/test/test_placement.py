"""Placement hypotheses (frodo_optim.placement): the sparse stage recovers a held-out object from a box 30 cm off
and half / twice its size, and never returns a placement with a higher energy than its input box."""
import dataclasses
import math

import numpy as np
import pytest
import torch
import trimesh

from frodo_common.geometry import look_at
from frodo_datasets.render import Material, Renderer, RenderObject, intrinsics
from frodo_datasets.shapes.library import eval_families, generate
from frodo_optim import placement
from frodo_optim.sparse import (DT_MARGIN, SparseConfig, _Batch, box_init, pose_matrix, refine, slam_points_near,
                                view_from_mask)
from frodo_shape.crops import square_crop
from frodo_shape.prior import ShapePrior

W, H = 240, 180


@pytest.fixture(scope='module')
def prior():
    torch.manual_seed(0)
    return ShapePrior.load('furniture', device='cpu')


@pytest.fixture(scope='module')
def scene(prior):
    """A chair of a held-out family (never in the prior's training set) on the floor, 12 views on a
    100-degree arc, its encoder code (mean of 3 crops), landmarks on it, on a neighbour and on the floor."""
    rng = np.random.default_rng(7)
    mesh = generate('chair', 7, eval_families('chair')[0])
    yaw, centre = 0.9, np.array([0.6, -0.4, -mesh.bounds[0, 2]])
    T = np.eye(4)
    T[:3, :3] = trimesh.transformations.rotation_matrix(yaw, [0, 0, 1])[:3, :3]
    T[:3, 3] = centre
    world = mesh.copy().apply_transform(T)
    renderer = Renderer([RenderObject(world, Material.random(rng), label=1)])
    K = intrinsics(W, H, 60.0)
    target = world.bounds.mean(0)
    views, crops, masks = [], [], []
    for k in range(12):
        a = 0.3 + math.radians(100) * k / 11
        eye = target + np.array([2.4 * math.cos(a), 2.4 * math.sin(a), 0.0])
        eye[2] = 1.45
        out = renderer.render(K, look_at(eye, target), W, H, shadows=False)
        mask = out.labels == 1
        views.append(view_from_mask(K, look_at(eye, target), mask, 96, rng=rng))
        if k % 4 == 0:
            ys, xs = np.nonzero(mask)
            c, m = square_crop(out.rgb, mask, (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1), 128, 0.1)
            crops.append(c)
            masks.append(m)
    code = prior.encode(np.stack(crops), np.stack(masks)).mean(0)
    neighbour = generate('dining table', 3).apply_translation([centre[0] + 1.1, centre[1], 0.4])
    slam = np.concatenate([trimesh.sample.sample_surface(world, 200, seed=1)[0],
                           trimesh.sample.sample_surface(neighbour, 100, seed=2)[0],
                           np.c_[rng.uniform(-2, 2, (100, 2)), np.zeros(100)]]) + rng.normal(0, 0.01, (400, 3))
    lo, hi = mesh.bounds
    return {'code': code, 'views': views, 'slam': slam, 'box': (target, hi - lo, yaw), 'world': world}


def _placed(prior, result):
    pts = prior.decode_points(result.code)[0].detach().numpy().astype(np.float64)
    return pts @ result.T_world_object[:3, :3].T + result.T_world_object[:3, 3]


def _errors(prior, result, scene):
    placed = _placed(prior, result)
    lo, hi = scene['world'].bounds
    centre = np.linalg.norm((placed.min(0) + placed.max(0)) / 2 - (lo + hi) / 2)
    return centre, (placed.max(0) - placed.min(0))[2] / (hi - lo)[2]


def test_detection_boxes_and_ray_centre(scene):
    views = scene['views']
    boxes, border = placement.detection_boxes(views, DT_MARGIN)
    for v, b in zip(views, boxes):   # the mask samples lie inside the recovered box (+1 px of jitter)
        assert (v.mask_uv >= b[:2] - 1e-3).all() and (v.mask_uv <= b[2:] + 1).all()
        assert b[2] - v.mask_uv[:, 0].max() < 0.15 * (b[2] - b[0]) + 2
    assert not border.any()
    centre = placement.ray_centre(views, boxes, border)
    assert np.linalg.norm(centre - scene['box'][0]) < 0.1, centre - scene['box'][0]
    parallel = [views[0]] * 3     # one ray three times: no intersection
    assert placement.ray_centre(parallel, boxes[:1].repeat(3, 0), border[:1].repeat(3, 0)) is None


def _disk(shape, centre, radius):
    v, u = np.mgrid[:shape[0], :shape[1]]
    return (u + 0.5 - centre[0]) ** 2 + (v + 0.5 - centre[1]) ** 2 < radius ** 2


def test_landmarks_hidden_by_a_neighbour_are_kept_a_neighbours_own_are_not():
    """`on_silhouettes` with other detections: views where a landmark falls on another detection do not count,
    unless it lies in a neighbour's box (then they count against it: a chair's seat under a table top)."""
    K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
    own, hidden, under = [0.0, 0.0, 0.0], [0.0, 0.0, 0.1], [0.0, 0.0, -0.1]
    neighbour_box = (np.array(under), np.full(3, 0.1), 0.0)       # holds `under` only
    views = []
    for k in range(4):
        a = math.radians(35 * k)
        T = look_at([3 * math.cos(a), 3 * math.sin(a), 1.5], [0, 0, 0])
        T_cw = np.linalg.inv(T)
        uv = [(K @ (T_cw[:3, :3] @ p + T_cw[:3, 3]))[:2] / (T_cw[:3, :3] @ p + T_cw[:3, 3])[2] for p in (own, hidden, under)]
        other = np.zeros((120, 160), bool)
        if k < 2:     # another detection over `hidden` and `under` in two of the four views
            other = _disk(other.shape, uv[1], 2.5) | _disk(other.shape, uv[2], 2.5)
        mask = _disk(other.shape, uv[0], 20) & ~other
        views.append(view_from_mask(K, T, mask, 64, other, np.random.default_rng(k)))
    assert [v.other is not None for v in views] == [True, True, False, False]
    points = np.array([own, hidden, under])
    batch = _Batch(views)
    np.testing.assert_allclose(placement.on_silhouettes(points, views, batch, [neighbour_box]), [own, hidden], atol=1e-6)
    # without the neighbour's box, `under` is hidden in two views like `hidden`, and kept
    assert len(placement.on_silhouettes(points, views, batch)) == 3
    assert placement.in_box(points, *neighbour_box).tolist() == [False, False, True]


@pytest.mark.parametrize('shift, factor', [(0.3, 2.0), (0.3, 0.5)])
def test_recovers_a_box_30cm_off_and_twice_or_half_the_size(prior, scene, shift, factor):
    centre, size, yaw = scene['box']
    wrong = (centre + shift * np.array([math.cos(2.0), math.sin(2.0), 0.0]), size * factor, yaw)
    res = refine(prior, scene['code'], wrong, scene['views'], scene['slam'], SparseConfig(seed=0))
    assert res.ok and res.placement != 'input box', (res.placement, res.reason)
    centre_err, scale = _errors(prior, res, scene)
    def recovered(err, s):
        return err < 0.06 and abs(s - 1) < 0.2

    assert recovered(centre_err, scale), (centre_err, scale, res.placement)
    # the box-only initialisation (the previous behaviour) does not recover by the same standard: the placement
    # search is what does (box-only ends 9-10 cm / x1.25 off at (0.3, 2.0), depending on the CPU's float kernels)
    old = refine(prior, scene['code'], wrong, scene['views'], scene['slam'],
                 SparseConfig(seed=0, placement_search=False))
    old_err, old_scale = _errors(prior, old, scene)
    assert not recovered(old_err, old_scale), (old_err, old_scale)
    assert res.energies['total'] < old.energies['total']


def test_never_worse_than_the_input_placement(prior, scene):
    centre, size, yaw = scene['box']
    wrong = (centre + np.array([0.2, 0.1, 0.0]), size * 1.5, yaw)
    # nothing to search and no iterations: the input box placement comes back, with the reason
    res = refine(prior, scene['code'], wrong, scene['views'], scene['slam'],
                 SparseConfig(iterations=0, yaw_candidates=4, placement_search=False))
    assert res.ok and 'input placement kept' in res.reason, res.reason
    t, s = box_init(prior.decode_points(scene['code'])[0].detach().numpy().astype(np.float64), wrong[0], wrong[1], res.yaw)
    assert np.allclose(res.T_world_object, pose_matrix(res.yaw, t, s), atol=1e-5)
    assert min(abs(math.remainder(res.yaw - yaw - k * math.pi / 2, 2 * math.pi)) for k in range(4)) < 1e-6
    # a diverging optimisation from wrong hypotheses still ends at or below the input's energy
    wild = SparseConfig(iterations=6, lr_translation=3.0, lr_yaw=2.0, lr_log_scale=2.0, lr_code=3.0)
    res = refine(prior, scene['code'], wrong, scene['views'], scene['slam'], wild)
    assert res.energies['total'] <= res.input_energy + 1e-6
    assert np.isfinite(res.T_world_object).all()


def test_floor_and_height_priors_stop_a_sunk_oversized_placement(prior, scene):
    """The real-capture failure (a chair box 30 cm low and 1.36x too big): with the support priors (floor at
    z = 0, the chair height range) the result stands on the floor at about the true size."""
    from frodo_common.categories import BY_NAME
    centre, size, yaw = scene['box']
    wrong = (centre - np.array([0.0, 0.0, 0.3]), size * 1.36, yaw)
    res = refine(prior, scene['code'], wrong, scene['views'], scene['slam'], SparseConfig(seed=0),
                 floor_height=0.0, height_range=BY_NAME['chair'].height_range)
    placed = _placed(prior, res)
    centre_err, scale = _errors(prior, res, scene)
    assert abs(np.sort(placed[:, 2])[:2].mean()) < 0.05, np.sort(placed[:, 2])[:2]
    assert centre_err < 0.08 and abs(scale - 1) < 0.15, (centre_err, scale, res.placement)
    assert 'floor' in res.energies and 'height' in res.energies


def test_code_restarts_leave_a_wrong_code_for_a_nearby_training_code(prior, scene):
    """Input code halfway between the scene's code and a table's training code (an encoder that saw the chair
    badly): with restarts from the nearest training codes the energy ends lower than from the input code alone."""
    tables = [i for i, c in enumerate(prior.training_classes) if c == 'dining table']
    bad = (0.5 * np.asarray(scene['code']) + 0.5 * prior.training_codes[tables[0]].cpu().numpy()).astype(np.float32)
    cfg = SparseConfig(seed=0, placement_search=False, iterations=15)
    plain = refine(prior, bad, scene['box'], scene['views'], scene['slam'], cfg)
    restarted = refine(prior, bad, scene['box'], scene['views'], scene['slam'],
                       SparseConfig(seed=0, placement_search=False, iterations=15, code_restarts=4))
    assert restarted.energies['total'] <= plain.energies['total'] + 1e-6
    assert restarted.placement.startswith('training code'), restarted.placement
    # the run not chosen (from the box, with the input code) is handed on as a further dense start
    assert len(restarted.alternatives) == 1
    code, T, source = restarted.alternatives[0]
    assert source == 'box' and code.shape == bad.shape and np.isfinite(T).all()
    assert np.linalg.norm(T[:3, 3] - restarted.translation) > 1e-4 or not np.allclose(code, restarted.code)
    single = refine(prior, bad, scene['box'], scene['views'], scene['slam'], dataclasses.replace(cfg, code_restarts=0))
    assert single.alternatives == []       # one run only: nothing else to start from


def test_the_code_restart_screen_only_filters_the_exact_scoring(prior, scene):
    """The screen (energy on restart_screen_views of the 12 views, point subset) only chooses which candidates
    get the exact energy: keeping every candidate gives the unscreened result bit for bit, and the default
    screen keeps the same restart here."""
    tables = [i for i, c in enumerate(prior.training_classes) if c == 'dining table']
    bad = (0.5 * np.asarray(scene['code']) + 0.5 * prior.training_codes[tables[0]].cpu().numpy()).astype(np.float32)
    cfg = SparseConfig(seed=0, placement_search=False, iterations=5, code_restarts=4)
    exact = refine(prior, bad, scene['box'], scene['views'], scene['slam'], dataclasses.replace(cfg, restart_screen_views=0))
    screened = refine(prior, bad, scene['box'], scene['views'], scene['slam'], cfg)
    keep_all = refine(prior, bad, scene['box'], scene['views'], scene['slam'],
                      dataclasses.replace(cfg, restart_screen_keep=10_000))
    assert 0 < cfg.restart_screen_views < len(scene['views'])
    assert np.array_equal(keep_all.code, exact.code) and np.array_equal(keep_all.T_world_object, exact.T_world_object)
    restarts = [s for _, _, s in exact.alternatives] + [exact.placement]
    assert any(s.startswith('training code') for s in restarts)
    assert [s for _, _, s in screened.alternatives] + [screened.placement] == restarts


def test_sparse_stage_hands_its_visual_hull_landmarks_to_the_dense_stage(prior, scene):
    """With `landmark_filter` (default) the result carries the landmarks the winning run used: the chair's own
    (within 4 cm of its surface), although the box, 4x too wide, also holds the neighbouring table's; with the
    paper's setting there is no such set."""
    centre, size, yaw = scene['box']
    wide = (centre, size * np.array([4.0, 4.0, 1.0]), yaw)
    near = slam_points_near(scene['slam'], *wide, margin=0.1 * float(np.max(wide[1])) + 0.05)
    _, dist, _ = trimesh.proximity.closest_point(scene['world'], near.astype(np.float64))
    assert (dist < 0.04).mean() < 0.8        # premise: the box region holds many landmarks of other things
    cfg = SparseConfig(seed=0, placement_search=False, code_restarts=0, iterations=3)
    res = refine(prior, scene['code'], wide, scene['views'], scene['slam'], cfg)
    _, dist, _ = trimesh.proximity.closest_point(scene['world'], res.landmarks.astype(np.float64))
    assert len(res.landmarks) >= 100 and (dist < 0.04).mean() > 0.95, (len(res.landmarks), (dist < 0.04).mean())
    paper = refine(prior, scene['code'], wide, scene['views'], scene['slam'],
                   dataclasses.replace(cfg, landmark_filter=False))
    assert paper.ok and paper.landmarks is None


def test_a_camera_turning_in_place_places_the_object_at_its_landmarks(prior, scene):
    """A camera that only turns sees the chair along nearly one ray (no ray centre); the association box lies
    70 cm beyond the chair along the view and the landmarks cover only the side facing the camera (a depth image's
    points): the visible landmarks' median anchors the hypotheses and the chair is placed within 6 cm."""
    world, (target, size, yaw) = scene['world'], scene['box']
    renderer = Renderer([RenderObject(world, Material.random(np.random.default_rng(3)), label=1)])
    K = intrinsics(W, H, 60.0)
    eye = target + np.array([2.4 * math.cos(0.8), 2.4 * math.sin(0.8), 0.0])
    eye[2] = 1.45
    side = np.array([-math.sin(0.8), math.cos(0.8), 0.0])
    rng = np.random.default_rng(4)
    views = []
    for k in range(8):
        T = look_at(eye, target + (k / 7 - 0.5) * 0.6 * side)
        views.append(view_from_mask(K, T, renderer.render(K, T, W, H, shadows=False).labels == 1, 96, rng=rng))
    boxes, border = placement.detection_boxes(views, DT_MARGIN)
    assert placement.ray_centre(views, boxes, border) is None
    points, faces = trimesh.sample.sample_surface(world, 600, seed=5)
    facing = np.einsum('ij,ij->i', world.face_normals[faces], eye - points) > 0
    slam = points[facing] + rng.normal(0, 0.01, (int(facing.sum()), 3))
    look = (target - eye) * [1, 1, 0]
    wrong = (target + 0.7 * look / np.linalg.norm(look), size, yaw)
    res = refine(prior, scene['code'], wrong, views, slam, SparseConfig(seed=0))
    centre_err, _ = _errors(prior, res, scene)
    assert res.placement.startswith('landmark centre') and centre_err < 0.06, (res.placement, centre_err)
