"""Depth along the rays of detections, from a registered depth image or from sparse SLAM landmarks (issue 9:
"landmarks, and depth where present, inside the mask to fix depth along the rays"; numpy/OpenCV, no ROS).

Per detection the result is the optical depth of the object's visible surface, d_s (NaN when there is not
enough evidence):
- depth image (contract v1.1 `/camera/depth/image_raw`, registered to colour): the median depth over the mask
  eroded by `erode_px` (drops the boundary errors and most bleeding of real masks), when at least
  `min_pixels` pixels have a measurement;
- landmarks (`/slam/points`, the whole map in the world frame): the map points projecting inside the eroded
  mask, in front of the camera. The map does not say which points the frame saw, so points on the object's far
  side and on the background behind it project into the mask too: the visible surface is the low
  `landmark_quantile` of their depths, when at least `min_landmarks` project there.
The association (`tracker.Associator.add_frame(surface_depth=...)`) turns d_s into a short segment on the
detection's ray: the object centre lies between d_s - `surface_slack` and d_s + the class's horizontal extent.
"""
from __future__ import annotations

import cv2
import numpy as np


def _eroded_masks(instances: np.ndarray, labels: np.ndarray, erode_px: int) -> np.ndarray:
    """(H, W) label image with each instance eroded by erode_px (an instance that would vanish is kept whole)."""
    if erode_px <= 0:
        return instances
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode_px + 1, 2 * erode_px + 1))
    out = np.zeros_like(instances)
    for lab in labels:
        mask = (instances == lab).astype(np.uint8)
        eroded = cv2.erode(mask, kernel)
        out[(eroded if eroded.any() else mask) > 0] = lab
    return out


def depth_image_to_metres(depth: np.ndarray) -> np.ndarray:
    """Contract depth (16UC1 millimetres or 32FC1 metres, 0 or NaN = none) as float32 metres with NaN = none."""
    d = depth.astype(np.float32)
    if depth.dtype == np.uint16:
        d = d / 1000.0
    d[~(d > 0)] = np.nan
    return d


def mask_depths(instances: np.ndarray, labels: np.ndarray, depth_m: np.ndarray, erode_px: int = 3,
                min_pixels: int = 20) -> np.ndarray:
    """Median depth (N,) of each instance label's eroded mask (NaN: fewer than min_pixels measurements).

    instances: (H, W) uint16; labels: (N,); depth_m: (H, W) metres, NaN = no measurement (`depth_image_to_metres`).
    """
    out = np.full(len(labels), np.nan)
    if depth_m.shape != instances.shape:
        raise ValueError(f'depth {depth_m.shape} does not match the detections {instances.shape}')
    eroded = _eroded_masks(instances, labels, erode_px)
    for k, lab in enumerate(labels):
        d = depth_m[eroded == lab]
        d = d[np.isfinite(d)]
        if len(d) >= min_pixels:
            out[k] = float(np.median(d))
    return out


def landmark_depths(instances: np.ndarray, labels: np.ndarray, points_world: np.ndarray, K: np.ndarray,
                    T_camera_world: np.ndarray, erode_px: int = 3, min_landmarks: int = 3,
                    quantile: float = 0.25, min_depth: float = 0.2) -> np.ndarray:
    """Visible-surface depth (N,) of each instance from the landmarks (P, 3) projecting inside its eroded mask:
    the `quantile` of their depths (NaN: fewer than min_landmarks)."""
    out = np.full(len(labels), np.nan)
    if len(points_world) == 0 or len(labels) == 0:
        return out
    h, w = instances.shape
    pc = points_world @ T_camera_world[:3, :3].T + T_camera_world[:3, 3]
    front = pc[:, 2] > min_depth
    pc = pc[front]
    u = np.round(K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]).astype(np.int64)
    v = np.round(K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (v >= 0) & (u < w) & (v < h)
    u, v, z = u[inside], v[inside], pc[inside, 2]
    hit = _eroded_masks(instances, labels, erode_px)[v, u]
    for k, lab in enumerate(labels):
        d = z[hit == lab]
        if len(d) >= min_landmarks:
            out[k] = float(np.quantile(d, quantile))
    return out


def surface_depths(instances: np.ndarray, labels: np.ndarray, K: np.ndarray, T_camera_world: np.ndarray,
                   depth_m: np.ndarray | None = None, points_world: np.ndarray | None = None, erode_px: int = 3,
                   min_pixels: int = 20, min_landmarks: int = 3, landmark_quantile: float = 0.25) -> np.ndarray:
    """Per detection the visible-surface depth (N,): from the depth image where it has enough pixels, else from
    the landmarks, else NaN. Either source may be None."""
    out = np.full(len(labels), np.nan)
    if depth_m is not None:
        out = mask_depths(instances, labels, depth_m, erode_px, min_pixels)
    missing = ~np.isfinite(out)
    if points_world is not None and missing.any():
        out[missing] = landmark_depths(instances, labels[missing], points_world, K, T_camera_world, erode_px,
                                       min_landmarks, landmark_quantile)
    return out
