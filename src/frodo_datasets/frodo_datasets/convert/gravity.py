"""Gravity alignment of a dataset's world frame (CONTRACT.md: world z up, gravity along -z).

Three ways to find the dataset's up direction, all returning one rigid transform `T_aligned_dataset` that the
writer applies to every pose, landmark and ground-truth mesh:
- `--up x,y,z`: the user states it (`align_up`: the smallest rotation taking it to +z);
- camera: the mean of the cameras' "up" axes (-y of the optical frame), right for hand-held or robot
  sequences where the camera is held roughly level (`camera_up`);
- floor: a RANSAC plane fit on 3D points (depth back-projections or landmarks): among the planes whose normal
  is within 30 degrees of the camera up, those with at least half the inliers of the best one are candidates,
  and the lowest of them (furthest below the cameras) is the floor; its least-squares normal becomes +z
  and the floor is moved to z = 0 (`fit_floor`, `align_floor`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def rotation_to_z(up: np.ndarray) -> np.ndarray:
    """Smallest rotation (3, 3) taking the direction `up` to +z (Rodrigues)."""
    a = np.asarray(up, dtype=np.float64)
    n = np.linalg.norm(a)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f'up vector {list(a)} has no direction')
    a = a / n
    z = np.array([0.0, 0.0, 1.0])
    c = float(a @ z)
    if c < -1 + 1e-12:  # pointing down: half turn about x
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(a, z)
    V = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + V + V @ V / (1 + c)


def align_up(up: np.ndarray) -> np.ndarray:
    """T_aligned_dataset (4, 4) rotating the dataset's `up` to +z (no translation)."""
    T = np.eye(4)
    T[:3, :3] = rotation_to_z(up)
    return T


def camera_up(poses: list[np.ndarray]) -> np.ndarray:
    """Mean up direction (3,) of optical-frame cameras T_world_camera: their -y axes, normalised."""
    ups = np.array([-T[:3, 1] for T in poses])
    mean = ups.mean(axis=0)
    n = np.linalg.norm(mean)
    if n < 1e-6:
        raise ValueError('camera up axes cancel out; give --up or use --gravity floor')
    return mean / n


@dataclass
class FloorPlane:
    """Plane n . x + d = 0 with unit normal n pointing to the cameras; inliers: count of supporting points."""

    normal: np.ndarray
    d: float
    inliers: int


def fit_floor(points: np.ndarray, cam_up: np.ndarray, cam_centres: np.ndarray, threshold: float = 0.03,
              max_angle_deg: float = 30.0, iterations: int = 500, seed: int = 0) -> FloorPlane:
    """RANSAC floor plane of `points` (N, 3) (see module docstring); raises ValueError when none is found."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 50:
        raise ValueError(f'floor fit needs at least 50 points, got {len(pts)}')
    rng = np.random.default_rng(seed)
    cos_max = np.cos(np.radians(max_angle_deg))
    candidates: list[tuple[int, np.ndarray, float]] = []
    for _ in range(iterations):
        a, b, c = pts[rng.choice(len(pts), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        n /= norm
        if n @ cam_up < 0:
            n = -n
        if n @ cam_up < cos_max:
            continue
        d = -float(n @ a)
        if float(n @ (cam_centres.mean(axis=0))) + d <= 0:  # cameras must be above the plane
            continue
        count = int(np.count_nonzero(np.abs(pts @ n + d) < threshold))
        candidates.append((count, n, d))
    if not candidates:
        raise ValueError('no roughly horizontal plane below the cameras found in the points')
    best = max(c[0] for c in candidates)
    strong = [c for c in candidates if c[0] >= 0.5 * best]
    # the lowest plane: a plane n . x + d = 0 with n ~ up lies at height -d
    _, n, d = min(strong, key=lambda c: -c[2])
    inl = pts[np.abs(pts @ n + d) < threshold]
    centroid = inl.mean(axis=0)
    _, _, vt = np.linalg.svd(inl - centroid, full_matrices=False)
    normal = vt[2] if vt[2] @ n > 0 else -vt[2]
    return FloorPlane(normal, -float(normal @ centroid), len(inl))


def align_floor(plane: FloorPlane) -> np.ndarray:
    """T_aligned_dataset (4, 4): floor normal -> +z and the floor plane -> z = 0."""
    T = align_up(plane.normal)
    T[2, 3] = plane.d  # a floor point p has normal . p = -d, so after rotating its z is -d
    return T
