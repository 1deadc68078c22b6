"""Sparse landmarks for `/slam/points` when a dataset ships no SLAM map, so the sparse stage's geometric
term (paper Sec. 5.3, "SLAM points") has input.

- From depth (`DepthLandmarks`): every `stride`-th valid depth pixel of a keyframe (a regular grid) is
  back-projected into the world; points are pooled in a voxel grid over all keyframes so far, and a voxel
  becomes a landmark (the mean of its points) once seen in `min_views` keyframes, as a SLAM landmark is
  mapped once tracked in several frames.
- From image features (`FeatureLandmarks`, for sequences without depth): ORB features of consecutive
  keyframes are matched (mutual nearest neighbours, Lowe ratio 0.8), triangulated with the known poses (DLT),
  and kept when in front of both cameras, with a reprojection error under 2 px and at least 1 degree of
  parallax; the same voxel pooling then merges repeated triangulations, and `min_views` counts the keyframe
  pairs that produced a point in a voxel.
Both return the whole current map (M, 3) in the world frame.
"""
from __future__ import annotations

import cv2
import numpy as np

from frodo_datasets.convert.common import backproject


class VoxelMap:
    """Points pooled per voxel: mean position and the number of distinct views that contributed."""

    def __init__(self, voxel: float):
        self.voxel = float(voxel)
        self._keys = np.zeros(0, dtype=np.int64)
        self._sums = np.zeros((0, 3))
        self._counts = np.zeros(0, dtype=np.int64)  # points
        self._views = np.zeros(0, dtype=np.int64)   # distinct contributing views

    def _encode(self, points: np.ndarray) -> np.ndarray:
        q = np.floor(points / self.voxel).astype(np.int64) + (1 << 20)
        return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]

    def add_view(self, points: np.ndarray) -> None:
        """Add one view's world points (N, 3)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        points = points[np.all(np.isfinite(points), axis=1)]
        if not len(points):
            return
        keys = self._encode(points)
        ukeys, inv = np.unique(keys, return_inverse=True)
        sums = np.zeros((len(ukeys), 3))
        np.add.at(sums, inv, points)
        counts = np.bincount(inv, minlength=len(ukeys))
        all_keys = np.concatenate([self._keys, ukeys])
        merged, minv = np.unique(all_keys, return_inverse=True)
        new_sums = np.zeros((len(merged), 3))
        np.add.at(new_sums, minv, np.concatenate([self._sums, sums]))
        new_counts = np.bincount(minv, weights=np.concatenate([self._counts, counts]), minlength=len(merged))
        new_views = np.bincount(minv, weights=np.concatenate([self._views, np.ones(len(ukeys), np.int64)]),
                                minlength=len(merged))
        self._keys, self._sums = merged, new_sums
        self._counts, self._views = new_counts.astype(np.int64), new_views.astype(np.int64)

    def points(self, min_views: int = 1) -> np.ndarray:
        """Landmarks (M, 3): means of the voxels seen in at least `min_views` views."""
        keep = self._views >= min_views
        return self._sums[keep] / self._counts[keep, None]


class DepthLandmarks:
    """Landmarks from registered depth (see module docstring)."""

    def __init__(self, stride: int = 4, voxel: float = 0.03, min_views: int = 2, max_depth: float = 6.0):
        self.stride, self.min_views, self.max_depth = int(stride), int(min_views), float(max_depth)
        self.map = VoxelMap(voxel)
        self.views = 0

    def add(self, depth: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray) -> None:
        """Add a keyframe: depth (H, W) metres registered to the camera K, pose (4, 4)."""
        self.map.add_view(backproject(depth, K, T_world_camera, self.stride, self.max_depth))
        self.views += 1

    def points(self) -> np.ndarray:
        """The current map (M, 3); a single keyframe's points count when there is only one."""
        return self.map.points(min(self.min_views, max(self.views, 1)))


class FeatureLandmarks:
    """Landmarks triangulated from ORB matches between consecutive keyframes (see module docstring)."""

    def __init__(self, voxel: float = 0.03, min_views: int = 1, max_features: int = 1500,
                 max_reprojection_px: float = 2.0, min_parallax_deg: float = 1.0, max_depth: float = 20.0):
        # small border and patch so that low-resolution images keep features near their edges
        self.orb = cv2.ORB_create(nfeatures=max_features, edgeThreshold=15, patchSize=15, fastThreshold=10)
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self.map = VoxelMap(voxel)
        self.min_views, self.max_reprojection_px = int(min_views), float(max_reprojection_px)
        self.min_parallax = np.radians(min_parallax_deg)
        self.max_depth = float(max_depth)
        self._prev: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self.pairs = 0

    def add(self, rgb: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray) -> None:
        """Add a keyframe: RGB (H, W, 3) uint8 seen by an undistorted camera K with pose (4, 4)."""
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        kps, desc = self.orb.detectAndCompute(grey, None)
        if desc is None or len(kps) < 8:
            self._prev = None
            return
        uv = np.array([k.pt for k in kps], dtype=np.float64)
        if self._prev is not None:
            self.map.add_view(self._triangulate(self._prev, (uv, desc, K, T_world_camera)))
            self.pairs += 1
        self._prev = (uv, desc, K, T_world_camera)

    def _triangulate(self, a, b) -> np.ndarray:
        uv_a, desc_a, K_a, T_a = a
        uv_b, desc_b, K_b, T_b = b
        knn = self.matcher.knnMatch(desc_a, desc_b, k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
        if good:  # mutual: b's best match in a must point back
            back = {m.queryIdx: m.trainIdx for m in self.matcher.match(desc_b, desc_a)}
            good = [m for m in good if back.get(m.trainIdx) == m.queryIdx]
        if len(good) < 8:
            return np.zeros((0, 3))
        ia = np.array([m.queryIdx for m in good])
        ib = np.array([m.trainIdx for m in good])
        P_a = K_a @ np.linalg.inv(T_a)[:3]
        P_b = K_b @ np.linalg.inv(T_b)[:3]
        X = cv2.triangulatePoints(P_a, P_b, uv_a[ia].T, uv_b[ib].T)
        X = (X[:3] / X[3]).T
        ok = np.all(np.isfinite(X), axis=1)
        for P, uv, T in ((P_a, uv_a[ia], T_a), (P_b, uv_b[ib], T_b)):
            x = np.c_[X, np.ones(len(X))] @ P.T
            z = (np.c_[X, np.ones(len(X))] @ np.linalg.inv(T)[:3].T)[:, 2]
            with np.errstate(invalid='ignore', divide='ignore'):
                err = np.linalg.norm(x[:, :2] / x[:, 2:3] - uv, axis=1)
            ok &= (z > 0.05) & (z < self.max_depth) & (err < self.max_reprojection_px)
        ra, rb = X - T_a[:3, 3], X - T_b[:3, 3]
        cos = np.sum(ra * rb, axis=1) / np.maximum(np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-12)
        ok &= cos < np.cos(self.min_parallax)
        return X[ok]

    def points(self) -> np.ndarray:
        """The current map (M, 3)."""
        return self.map.points(self.min_views)
