"""The box fit's solver (`robust_lsq`) and the batched box projection's analytic Jacobian."""
import numpy as np
from scipy.optimize import least_squares

from frodo_association.boxes import _box_projection
from frodo_association.robust_lsq import soft_l1_cost, soft_l1_least_squares


def _exp_fit_problem(seed: int):
    """y = a exp(b x) + c with 10 % gross outliers: smooth, nonlinear, robust loss matters."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 2, 60)
    y = 1.5 * np.exp(-0.8 * x) + 0.3 + rng.normal(0, 0.02, len(x))
    y[rng.choice(len(x), 6, replace=False)] += rng.normal(0, 1.0, 6)

    def res(p):                                  # p: (P,) -> (M,)
        return p[0] * np.exp(p[1] * x) + p[2] - y

    def jac(p):
        e = np.exp(p[1] * x)
        return np.stack([e, p[0] * x * e, np.ones_like(x)], axis=1)

    def batched(ps):                             # (N, P) -> (N, M), (N, M, P); wild trial steps overflow
        with np.errstate(over='ignore', invalid='ignore'):
            return np.stack([res(p) for p in ps]), np.stack([jac(p) for p in ps])
    return res, jac, batched


def test_same_minimum_as_scipy_soft_l1():
    for seed in range(5):
        res, jac, batched = _exp_fit_problem(seed)
        p0 = np.array([[1.0, -0.3, 0.0], [2.0, -1.5, 0.5]])
        ours, cost = soft_l1_least_squares(batched, p0, np.full(3, -np.inf), np.full(3, np.inf), f_scale=0.05,
                                           max_evals=200, ftol=1e-12)
        for s in range(2):
            ref = least_squares(res, p0[s], jac=jac, loss='soft_l1', f_scale=0.05, xtol=1e-12, ftol=1e-12,
                                gtol=1e-12, max_nfev=2000)
            assert np.allclose(ours[s], ref.x, atol=1e-5), (seed, s, ours[s], ref.x)
            # scipy's cost is 0.5 * sum(rho) with rho = 2 f^2 (sqrt(1 + (r/f)^2) - 1): the same objective.
            assert abs(cost[s] - ref.cost) <= 1e-9 * max(ref.cost, 1.0)
            assert abs(soft_l1_cost(res(ref.x)[None], 0.05)[0] - ref.cost) < 1e-12


def test_bounds_hold_and_active_bound_is_the_constrained_minimum():
    res, jac, batched = _exp_fit_problem(0)
    lower, upper = np.array([-np.inf, -np.inf, 0.4]), np.full(3, np.inf)      # c is 0.3 unconstrained
    ours, _ = soft_l1_least_squares(batched, np.array([[1.0, -0.3, 1.0]]), lower, upper, f_scale=0.05,
                                    max_evals=200, ftol=1e-12)
    ref = least_squares(res, [1.0, -0.3, 1.0], jac=jac, bounds=(lower, upper), loss='soft_l1', f_scale=0.05,
                        xtol=1e-12, ftol=1e-12, gtol=1e-12)
    assert ours[0, 2] == 0.4
    assert np.allclose(ours[0], ref.x, atol=1e-5)


def test_box_projection_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    n_v = 6
    yaw = rng.uniform(-np.pi, np.pi, n_v)
    eyes = np.stack([4 * np.cos(yaw), 4 * np.sin(yaw), np.full(n_v, 1.2)], axis=1)
    R = np.zeros((n_v, 3, 3))
    for i, e in enumerate(eyes):                                   # cameras looking at the origin, y down
        fwd = -e / np.linalg.norm(e)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        R[i] = np.stack([right, np.cross(fwd, right), fwd])
    t = -np.einsum('vij,vj->vi', R, eyes)
    f = np.full((n_v, 2), 500.0)
    c = np.tile([320.0, 240.0], (n_v, 1))
    for floor in (0.0, None):
        p = np.array([[0.1, -0.2] + ([] if floor is not None else [0.4]) + [-0.5, -0.9, -0.2, 0.35],
                      [-0.3, 0.1] + ([] if floor is not None else [0.6]) + [-0.2, -0.4, -0.6, -0.6]])
        boxes, jac = _box_projection(p, R, t, f, c, floor, with_jacobian=True)
        assert boxes.shape == (2, n_v, 4) and jac.shape == (2, n_v, 4, p.shape[1])
        assert np.allclose(_box_projection(p, R, t, f, c, floor), boxes)
        eps = 1e-6
        for k in range(p.shape[1]):
            step = np.zeros_like(p)
            step[:, k] = eps
            numeric = (_box_projection(p + step, R, t, f, c, floor) - _box_projection(p - step, R, t, f, c, floor)) \
                / (2 * eps)
            assert np.allclose(jac[..., k], numeric, atol=1e-4 * np.abs(numeric).max() + 1e-6), (floor, k)
