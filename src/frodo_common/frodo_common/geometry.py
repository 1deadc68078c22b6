"""Rigid and similarity transforms, quaternions, pinhole projection, rays and upright boxes (numpy, no ROS).

Conventions (CONTRACT.md): world z up; camera optical frame x right, y down, z forward;
`T_a_b` maps points from frame b to frame a; quaternions are (x, y, z, w).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) from a quaternion (x, y, z, w); normalises the input."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f'invalid quaternion {q}')
    x, y, z, w = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternion (x, y, z, w) with w >= 0 from a rotation matrix (3, 3)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.trace(R)
    if t > 0:
        s = np.sqrt(t + 1.0) * 2
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def make_transform(R: np.ndarray | None = None, t=None, scale: float = 1.0) -> np.ndarray:
    """4x4 similarity transform x -> scale * R x + t."""
    T = np.eye(4)
    T[:3, :3] = (np.eye(3) if R is None else np.asarray(R, dtype=np.float64)) * float(scale)
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 similarity transform (uniform scale allowed)."""
    T = np.asarray(T, dtype=np.float64)
    A = T[:3, :3]
    s2 = np.sum(A[:, 0] ** 2)
    A_inv = A.T / s2
    out = np.eye(4)
    out[:3, :3] = A_inv
    out[:3, 3] = -A_inv @ T[:3, 3]
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points (N, 3) -> (N, 3)."""
    points = np.asarray(points, dtype=np.float64)
    return points @ T[:3, :3].T + T[:3, 3]


def yaw_matrix(yaw: float) -> np.ndarray:
    """Rotation (3, 3) about world z (gravity axis) by `yaw` radians."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_world_camera (4, 4) of an optical-frame camera at `eye` looking at `target`."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError('look_at: viewing direction is parallel to up')
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_transform(np.stack([x, y, z], axis=1), eye)


def project_points(K: np.ndarray, T_camera_world: np.ndarray, points: np.ndarray):
    """Project world points (N, 3) with intrinsics K (3, 3).

    Returns (uv (N, 2) pixel coordinates, depth (N,) along the optical axis).
    Points behind the camera get depth <= 0; callers mask them.
    """
    pc = transform_points(T_camera_world, points)
    z = pc[:, 2]
    safe = np.where(np.abs(z) < 1e-9, 1e-9, z)
    uv = (pc[:, :2] / safe[:, None]) @ np.asarray(K)[:2, :2].T + np.asarray(K)[:2, 2]
    return uv, z


def backproject_pixels(K: np.ndarray, T_world_camera: np.ndarray, u: np.ndarray, v: np.ndarray,
                      z: np.ndarray) -> np.ndarray:
    """World points (N, 3) of pixels (u, v) (N,) at optical depths z (N,): the inverse of `project_points`."""
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    return cam @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]


def pixel_rays(K: np.ndarray, T_world_camera: np.ndarray, uv: np.ndarray):
    """World rays through pixels uv (N, 2): returns (origin (3,), unit directions (N, 3))."""
    uv = np.atleast_2d(np.asarray(uv, dtype=np.float64))
    K = np.asarray(K, dtype=np.float64)
    d_cam = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], axis=1)
    d_world = d_cam @ np.asarray(T_world_camera)[:3, :3].T
    d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
    return np.asarray(T_world_camera)[:3, 3].copy(), d_world


def box_corners(center, size, yaw: float) -> np.ndarray:
    """Corners (8, 3) of an upright box with `size` (dx, dy, dz) rotated by `yaw` about z."""
    half = np.asarray(size, dtype=np.float64) / 2
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    return (signs * half) @ yaw_matrix(yaw).T + np.asarray(center, dtype=np.float64)


def bearing_span(points, centre) -> float:
    """The smallest arc (degrees, 0-360) of horizontal directions from `centre` that holds every point (N, 3)
    (e.g. the cameras that saw an object: a few degrees on a walk past it, over 180 from all around); NaN rows are
    left out, fewer than two points give 0."""
    offsets = np.asarray(points, dtype=np.float64).reshape(-1, 3)[:, :2] - np.asarray(centre, np.float64)[:2]
    offsets = offsets[np.isfinite(offsets).all(axis=1)]
    if len(offsets) < 2:
        return 0.0
    bearings = np.sort(np.arctan2(offsets[:, 1], offsets[:, 0]))
    gaps = np.diff(np.append(bearings, bearings[0] + 2 * np.pi))
    return float(np.degrees(2 * np.pi - gaps.max()))


@dataclass(eq=False)
class Box3D:
    """The project's one 3D box: upright, centre (3,) and size (dx, dy, dz) (3,) in metres, yaw about world z
    (radians; the association keeps it in [-pi/4, pi/4)). Unpacks as `center, size, yaw = box`, so code written
    for the (centre, size, yaw) triple takes it as is; messages carry it as a CUBE marker
    (`conversions.box_to_marker` / `marker_to_box`), tables as 7 floats."""

    center: np.ndarray
    size: np.ndarray
    yaw: float

    def __post_init__(self) -> None:
        self.center = np.asarray(self.center, dtype=np.float64).reshape(3)
        self.size = np.asarray(self.size, dtype=np.float64).reshape(3)
        self.yaw = float(self.yaw)

    def __iter__(self) -> Iterator:
        return iter((self.center, self.size, self.yaw))

    def corners(self) -> np.ndarray:
        """(8, 3) world corners."""
        return box_corners(self.center, self.size, self.yaw)

    def same_as(self, other: 'Box3D') -> bool:
        """Exactly the same box (a re-sent one), not merely a close one."""
        return bool(np.array_equal(self.center, other.center) and np.array_equal(self.size, other.size)
                    and self.yaw == other.yaw)


def box_iou_2d(a, b) -> float:
    """IoU of two axis-aligned 2D boxes (x0, y0, x1, y1)."""
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    area = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / area) if area > 0 else 0.0
