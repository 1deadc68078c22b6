"""Support priors (frodo_optim.support, beyond the paper): floor estimate, E_floor, E_size (values, gradients
against finite differences), the class height ranges shared through frodo_common, the truncation-aware
silhouette of the sparse stage, and E_facing (footprint gaps, the side of the table a chair stands at)."""
import math

import numpy as np
import pytest
import torch

from frodo_common.categories import BY_NAME, CATEGORIES
from frodo_optim import support
from frodo_optim.sparse import _Batch, view_from_mask


def _box(bottom: float, height: float, x: float = 0.0):
    return (np.array([x, 0.0, bottom + height / 2]), np.array([0.5, 0.5, height]), 0.0)


def test_floor_height_is_the_median_box_bottom_robust_to_a_wrong_box():
    boxes = [_box(0.10, 0.9), _box(0.11, 0.75, 1.0), _box(0.09, 0.8, 2.0), _box(-0.5, 1.3, 3.0)]
    assert support.floor_height(boxes) == pytest.approx(0.095)
    assert support.floor_height([]) is None
    assert support.floor_height([(np.array([0, 0, np.nan]), np.ones(3), 0.0)]) is None


def test_floor_height_snaps_to_the_densest_landmark_layer_near_the_boxes():
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(-2, 2, (200, 2)), 0.14 + rng.normal(0, 0.003, 200)]
    clutter = rng.uniform([-2, -2, 0.2], [2, 2, 1.5], (300, 3))            # objects, walls: no layer
    boxes = [_box(0.10, 0.9), _box(0.11, 0.75, 1.0)]
    assert support.floor_height(boxes, np.concatenate([floor, clutter])) == pytest.approx(0.14, abs=0.005)
    # too few points in a layer, or the layer too far from the boxes: the box bottoms stand
    assert support.floor_height(boxes, np.concatenate([floor[:10], clutter])) == pytest.approx(0.105)
    far = floor + [0, 0, 0.5]
    assert support.floor_height(boxes, far) == pytest.approx(0.105)


def test_floor_height_takes_the_lowest_dense_layer_not_a_denser_one_above_it():
    # realcapture-tune2-8209: feet and stretchers 11 cm up held more landmarks than the floor
    rng = np.random.default_rng(1)
    floor = np.c_[rng.uniform(-2, 2, (90, 2)), rng.normal(0, 0.004, 90)]
    parts = np.c_[rng.uniform(-1, 1, (150, 2)), 0.11 + rng.normal(0, 0.004, 150)]
    noise = np.c_[rng.uniform(-2, 2, (6, 2)), rng.uniform(-0.15, -0.03, 6)]     # a few stray points below
    boxes = [_box(0.0, 0.9), _box(0.0, 0.75, 1.0)]
    assert support.floor_height(boxes, np.concatenate([floor, parts, noise])) == pytest.approx(0.0, abs=0.005)
    # a layer with too few points (under half the densest) does not count as the floor
    assert support.floor_height(boxes, np.concatenate([floor[:30], parts])) == pytest.approx(0.11, abs=0.005)


def test_floor_energy_values_and_both_directions():
    pts = torch.tensor([[0.0, 0.0, 0.30], [0.1, 0.0, 0.31], [0.0, 0.2, 0.9], [0.3, 0.1, 0.5]], dtype=torch.float64)
    assert float(support.bottom(pts, k=2)) == pytest.approx(0.305)
    assert float(support.floor_energy(pts, 0.305, 0.05, k=2)) == pytest.approx(0.0)
    assert float(support.floor_energy(pts, 0.305 - 0.025, 0.05, k=2)) == pytest.approx(0.25)    # floating
    assert float(support.floor_energy(pts, 0.305 + 0.025, 0.05, k=2)) == pytest.approx(0.25)    # sunk
    assert float(support.floor_energy(pts, 0.305 - 0.2, 0.05, k=2)) == pytest.approx(7.0)       # linear beyond
    batched = torch.stack([pts, pts + torch.tensor([0, 0, 0.1], dtype=torch.float64)])
    assert support.floor_energy(batched, 0.305, 0.05).shape == (2,)


def _finite_difference(f, x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    g = torch.zeros_like(x)
    flat = x.reshape(-1)
    for i in range(flat.numel()):
        old = float(flat[i])
        flat[i] = old + eps
        up = float(f(x))
        flat[i] = old - eps
        down = float(f(x))
        flat[i] = old
        g.reshape(-1)[i] = (up - down) / (2 * eps)
    return g


@pytest.mark.parametrize('floor', [0.0, 0.29, 0.5])     # sunk (linear part), near (quadratic part), floating
def test_floor_energy_gradient_matches_finite_differences(floor):
    rng = np.random.default_rng(1)
    pts = torch.tensor(rng.uniform([-0.3, -0.3, 0.25], [0.3, 0.3, 1.0], (40, 3)), dtype=torch.float64)
    x = pts.clone().requires_grad_(True)
    support.floor_energy(x, floor, 0.05).backward()
    fd = _finite_difference(lambda p: support.floor_energy(p, floor, 0.05), pts.clone())
    assert torch.allclose(x.grad, fd, atol=1e-5)
    assert (x.grad[:, 2] != 0).sum() == 2          # only the two lowest points carry the gradient


@pytest.mark.parametrize('scale', [0.3, 1.0, 2.5])
def test_height_energy_is_zero_inside_the_range_and_its_gradient_matches_finite_differences(scale):
    rng = np.random.default_rng(2)
    pts = torch.tensor(rng.uniform([-0.3, -0.3, 0.0], [0.3, 0.3, 0.8], (30, 3)), dtype=torch.float64) * scale
    h = float(pts[:, 2].max() - pts[:, 2].min())
    e = float(support.height_energy(pts, (0.4, 1.35)))
    expected = max(0.0, math.log(h / 1.35)) ** 2 + max(0.0, math.log(0.4 / h)) ** 2
    assert e == pytest.approx(expected)
    assert (e == 0.0) == (0.4 <= h <= 1.35)
    x = pts.clone().requires_grad_(True)
    support.height_energy(x, (0.4, 1.35)).backward()
    fd = _finite_difference(lambda p: support.height_energy(p, (0.4, 1.35)), pts.clone())
    assert torch.allclose(x.grad, fd, atol=1e-5)


def test_height_ranges_are_shared_through_the_categories():
    for c in CATEGORIES:
        lo, hi = c.height_range
        assert 0 < lo < hi < 3.0
    assert BY_NAME['chair'].height_range[1] >= 1.28          # procedural office chairs with head rests
    assert BY_NAME['dining table'].height_range[0] <= 0.4    # coffee tables


def test_truncation_aware_silhouette_ignores_points_beyond_the_border_the_detection_touches():
    """A mask cut by the right image border: points beyond that border cost nothing in the points -> mask
    half; beyond the left border (the detection does not touch it) they still do."""
    K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
    mask = np.zeros((120, 160), bool)
    mask[40:80, 120:160] = True                      # touches the right border only
    view = view_from_mask(K, np.eye(4), mask, 64, rng=np.random.default_rng(0))
    aware, plain = _Batch([view], True), _Batch([view], False)
    assert aware.border.tolist() == [[[False, False, True, False]]]
    uv = torch.tensor([[[200.0, 60.0], [-40.0, 60.0], [140.0, 60.0]]])   # beyond right, beyond left, on the mask
    assert aware.unknown(uv).tolist() == [[True, False, False]]
    assert not plain.unknown(uv).any()
    # a point 1 m to the right of the mask (far beyond the crop and the right border) at 2 m depth
    beyond = torch.tensor([[1.5, 0.0, 2.0]] * 8, dtype=torch.float32)
    subset = torch.arange(8)
    assert float(aware.silhouette(beyond, subset)) < float(plain.silhouette(beyond, subset))


def test_footprint_gap_is_zero_for_overlapping_boxes_and_the_distance_otherwise():
    table = (np.array([0.0, 0.0, 0.4]), np.array([1.6, 0.8, 0.8]), 0.0)
    chair = lambda x, y, yaw=0.0: (np.array([x, y, 0.45]), np.array([0.5, 0.5, 0.9]), yaw)
    assert support.footprint_gap(chair(0.0, 0.5), table) == 0.0                     # tucked under the side
    assert support.footprint_gap(chair(0.0, 1.0), table) == pytest.approx(0.35)     # 1.0 - 0.4 - 0.25
    assert support.footprint_gap(table, chair(0.0, 1.0)) == pytest.approx(0.35)
    assert support.footprint_gap(chair(1.3, 0.9), table) == pytest.approx(math.hypot(0.25, 0.25))   # corner to corner
    # turned 45 degrees, its corner towards the table: the corner's distance
    turned = chair(0.0, 0.4 + 0.1 + 0.25 * math.sqrt(2), math.pi / 4)
    assert support.footprint_gap(turned, table) == pytest.approx(0.1)


def test_a_chair_at_a_table_faces_the_side_it_stands_at():
    yaw = 0.5                                                 # the table turned; its long side along (cos, sin)
    c, s = math.cos(yaw), math.sin(yaw)
    along, across = np.array([c, s]), np.array([-s, c])
    table = ('dining table', (np.array([2.0, 1.0, 0.4]), np.array([1.6, 0.8, 0.8]), yaw))

    def chair_at(offset, size=0.5):
        xy = np.array([2.0, 1.0]) + offset
        return (np.array([xy[0], xy[1], 0.45]), np.array([size, size, 0.9]), 0.1)

    # behind its long side (tucked under it or a little away), at its end: the side's inward normal
    assert support.facing_direction('chair', chair_at(0.45 * across), [table]) == pytest.approx(-across)
    assert support.facing_direction('chair', chair_at(-0.8 * across), [table]) == pytest.approx(across)
    assert support.facing_direction('chair', chair_at(1.0 * along), [table]) == pytest.approx(-along)
    # too far from every table, no table, or no facing rule for the class: none
    assert support.facing_direction('chair', chair_at(1.5 * across), [table]) is None
    assert support.facing_direction('chair', chair_at(0.45 * across), [('chair', table[1])]) is None
    assert support.facing_direction('dining table', chair_at(0.45 * across), [table]) is None
    nan_box = (np.full(3, np.nan), np.ones(3), 0.0)
    assert support.facing_direction('chair', nan_box, [table]) is None
    assert support.facing_direction('chair', chair_at(0.45 * across), [('dining table', nan_box)]) is None
    # the nearest of two tables
    other = ('dining table', (np.array([2.0, 1.0, 0.4]) + np.r_[1.2 * across, 0.0], np.array([1.6, 0.8, 0.8]), yaw))
    assert support.facing_direction('chair', chair_at(0.75 * across, 0.3), [table, other]) == pytest.approx(across)
    assert support.facing_direction('chair', chair_at(0.75 * across, 0.3), [table]) == pytest.approx(-across)


def test_facing_energy_is_zero_facing_one_turned_away_and_batched():
    d = np.array([0.0, 1.0])
    fronts = torch.tensor([[0.0, 2.0], [0.0, -1.0], [3.0, 0.0], [1.0, 1.0]])
    assert support.facing_energy(fronts, d).tolist() == pytest.approx([0.0, 1.0, 0.5, 0.5 - 0.5 / math.sqrt(2)])


def _cameras(azimuths_deg, centre=(1.0, -2.0, 0.0), radius=2.5):
    a = np.radians(azimuths_deg)
    return np.c_[centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a), np.full(len(a), 1.4)]


def test_the_facing_prior_weighs_by_how_one_sided_the_views_are():
    """E_facing's share falls from 1 (views from one direction) to 0 at an arc of 180 degrees (views of front and
    back; the arc: frodo_common.geometry.bearing_span)."""
    centre = np.array([1.0, -2.0, 0.4])
    assert support.one_sided_share(_cameras([10, 40]), centre) == pytest.approx(1 - 30 / 180)
    assert support.one_sided_share(_cameras([0, 100, 200]), centre) == 0.0
    # a stage's weight: none without a finite direction to face or with the term off
    toward = np.array([1.0, 0.0])
    assert support.facing_weight(0.1, toward, _cameras([10, 40]), centre) == pytest.approx(0.1 * (1 - 30 / 180))
    assert support.facing_weight(0.1, None, _cameras([10, 40]), centre) == 0.0
    assert support.facing_weight(0.1, np.array([np.nan, 0.0]), _cameras([10, 40]), centre) == 0.0
    assert support.facing_weight(0.0, toward, _cameras([10, 40]), centre) == 0.0
