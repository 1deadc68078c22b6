"""Small robust least squares, several starts at once (numpy, no ROS): the solver of the 3D box fit
(`boxes.fit_box`).

`scipy.optimize.least_squares` (trust-region reflective) spent ~13 ms of CPU per box fit on this project's
2-core VM, about two thirds of it in its own Python bookkeeping for a problem of 6-7 parameters and ~100
residuals, and a cold fit ran it twice (two yaw starts). This solver minimises the same objective, the soft-L1
cost sum_i f^2 (sqrt(1 + (r_i / f)^2) - 1) of all residuals r_i (scipy's loss='soft_l1', f_scale=f), under
box bounds, for S starting points in one batched Levenberg-Marquardt iteration:

- step: (H + m mu diag(H)) delta = -g for each m in damping_factors, all tried in one call of the residual
  function and the best kept; g = J^T diag(rho') r is the gradient and H = J^T diag(rho' + 2 rho'' z) J,
  z = (r / f)^2, the Gauss-Newton matrix of the robust cost (for soft-L1 rho' + 2 rho'' z = (1 + z)^-3/2: the
  same second-order loss correction as scipy's); mu becomes the best step's damping / 3, or x40 when no step
  lowers the cost;
- bounds: a variable at a bound whose descent direction points outwards is held fixed for the step, and the
  trial point is clipped to the bounds (projected Levenberg-Marquardt);
- stop per start: relative cost decrease below ftol, step below xtol * (xtol + |p|), or max_evals evaluations;
  only the starts still running are evaluated.

Same objective, different path: on a nonconvex fit (the extreme corner of a box edge switches, yaw has a basin
per quarter turn) the two solvers can end in different local minima. On 247 box fits recorded from the
benchmark walks and two handheld scenes, from the same inputs, this one ended within 0.1 % of scipy's cost in
194, lower in 41, higher in 12 (`docs/experiments/frodo_association_history.md`, "Latency").
"""
from __future__ import annotations

from typing import Callable

import numpy as np


def soft_l1_cost(r: np.ndarray, f_scale: float) -> np.ndarray:
    """Soft-L1 cost per start: sum over the last axis of f^2 (sqrt(1 + (r / f)^2) - 1). r: (S, M) -> (S,)."""
    return f_scale ** 2 * np.sum(np.sqrt(1.0 + (r / f_scale) ** 2) - 1.0, axis=-1)


def soft_l1_least_squares(fun: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], p0: np.ndarray,
                          lower: np.ndarray, upper: np.ndarray, f_scale: float, max_evals: int = 60,
                          ftol: float = 1e-8, xtol: float = 1e-8,
                          damping_factors: tuple[float, ...] = (0.1, 1.0, 10.0), initial_damping: float = 1.0
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Minimise the soft-L1 cost of fun's residuals from S starts at once (projected Levenberg-Marquardt).

    fun: p (N, P) -> (residuals (N, M), Jacobian (N, M, P)); p0: (S, P) starts (inside the bounds);
    lower, upper: (P,) bounds (+-inf where free). Each iteration tries the steps of the damping mu times each of
    damping_factors in one call of fun (N = running starts * len(damping_factors); on these small problems the
    call costs little more than one step) and keeps the best; max_evals bounds the calls of fun.
    Returns (solutions (S, P), costs (S,)).
    """
    p = np.clip(np.array(p0, dtype=np.float64, ndmin=2), lower, upper)
    n_start, n_par = p.shape
    factors = np.asarray(damping_factors, dtype=np.float64)
    n_try = len(factors)
    r, J = (np.array(x) for x in fun(p))
    cost = soft_l1_cost(r, f_scale)
    mu = np.full(n_start, initial_damping)
    active = np.ones(n_start, dtype=bool)
    eye = np.eye(n_par)
    for _ in range(max_evals - 1):
        run = np.nonzero(active)[0]                  # only the starts still running are stepped and evaluated
        if len(run) == 0:
            break
        p_r, r_r, J_r, cost_r = p[run], r[run], J[run], cost[run]
        z1 = 1.0 + (r_r / f_scale) ** 2                                # (R, M)
        Jt = J_r.transpose(0, 2, 1)
        g = (Jt @ (r_r / np.sqrt(z1))[..., None])[..., 0]              # (R, P) gradient of the cost
        H = Jt @ (J_r * (z1 ** -1.5)[..., None])                       # (R, P, P) Gauss-Newton, loss curvature
        # Variables at a bound that the descent direction would push through are held for this step.
        held = ((p_r <= lower) & (g > 0)) | ((p_r >= upper) & (g < 0))
        free = (~held).astype(np.float64)
        diag = np.maximum(np.einsum('spp->sp', H), 1e-12) * free
        mus = mu[run, None] * factors[None, :]                         # (R, T)
        A = (H * free[:, :, None] * free[:, None, :])[:, None] \
            + (mus[..., None] * diag[:, None, :] + (1.0 - free)[:, None, :])[..., None] * eye
        rhs = np.broadcast_to((g * free)[:, None, :, None], (len(run), n_try, n_par, 1))
        trial = np.clip(p_r[:, None] - np.linalg.solve(A, rhs)[..., 0], lower, upper)   # (R, T, P)
        r_t, J_t = fun(trial.reshape(-1, n_par))
        with np.errstate(over='ignore', invalid='ignore'):               # a wild trial step is just rejected
            cost_t = soft_l1_cost(r_t, f_scale)
        cost_t = np.where(np.isfinite(cost_t), cost_t, np.inf).reshape(len(run), n_try)
        k = np.arange(len(run))
        best = np.argmin(cost_t, axis=1)
        cost_b = cost_t[k, best]
        accept = cost_b < cost_r
        small_step = np.linalg.norm(trial[k, best] - p_r, axis=1) <= xtol * (xtol + np.linalg.norm(p_r, axis=1))
        small_gain = accept & (cost_r - cost_b <= ftol * cost_r)
        took, pick = run[accept], (k * n_try + best)[accept]
        p[took], r[took], J[took], cost[took] = trial[k, best][accept], r_t[pick], J_t[pick], cost_b[accept]
        mu[run] = np.where(accept, np.maximum(mus[k, best] / 3.0, 1e-9), np.minimum(mu[run] * factors[-1] * 4.0, 1e9))
        active[run] = ~(small_step | small_gain | (mu[run] >= 1e9))
    return p, cost
