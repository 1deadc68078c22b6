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

From a depth image the visible surface is also kept as points (`mask_points`, world frame): the box fit keeps
them inside the object's box (`boxes.fit_box(points=...)`), so that a table top seen from above gives the box
its footprint and height, not only the depth of its near edge. Landmarks give no points: those inside a mask
lie on the background as often as on the object.
"""
from __future__ import annotations

import cv2
import numpy as np

from frodo_association.tracker import class_shape
from frodo_common.categories import category_by_id
from frodo_common.geometry import backproject_pixels


def _eroded_pixels(instances: np.ndarray, labels: np.ndarray, erode_px: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per label the (rows, columns) of its mask eroded by erode_px, in raster order (an instance that would vanish
    is kept whole). Each mask is eroded in its own bounding box (padded by erode_px + 1), not in the whole image:
    the same pixels, at a fraction of the cost for several detections in a large image."""
    h, w = instances.shape
    flat = instances.ravel()
    where = np.flatnonzero(np.isin(flat, labels))
    order = np.argsort(flat[where], kind='stable')                       # raster order kept within a label
    values, starts = np.unique(flat[where[order]], return_index=True)
    groups = dict(zip(values.tolist(), np.split(where[order], starts[1:])))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode_px + 1, 2 * erode_px + 1)) \
        if erode_px > 0 else None
    out = []
    for lab in labels:
        index = groups.get(int(lab), np.zeros(0, np.int64))
        v, u = np.divmod(index, w)
        if kernel is not None and len(index):
            pad = erode_px + 1
            v0, u0 = max(int(v.min()) - pad, 0), max(int(u.min()) - pad, 0)
            v1, u1 = min(int(v.max()) + pad + 1, h), min(int(u.max()) + pad + 1, w)
            crop = (instances[v0:v1, u0:u1] == lab).astype(np.uint8)
            ev, eu = np.nonzero(cv2.erode(crop, kernel))
            if len(ev):
                v, u = ev + v0, eu + u0
        out.append((v, u))
    return out


def _eroded_masks(instances: np.ndarray, labels: np.ndarray, erode_px: int) -> np.ndarray:
    """(H, W) label image with each instance eroded by erode_px (`_eroded_pixels`)."""
    out = np.zeros_like(instances)
    for lab, (v, u) in zip(labels, _eroded_pixels(instances, labels, erode_px)):
        out[v, u] = lab
    return out


def mask_depths(instances: np.ndarray, labels: np.ndarray, depth_m: np.ndarray, erode_px: int = 3,
                min_pixels: int = 20) -> np.ndarray:
    """Median depth (N,) of each instance label's eroded mask (NaN: fewer than min_pixels measurements).

    instances: (H, W) uint16; labels: (N,); depth_m: (H, W) metres, NaN = no measurement (`frodo_common.frames.depth_to_metres`).
    """
    out = np.full(len(labels), np.nan)
    if depth_m.shape != instances.shape:
        raise ValueError(f'depth {depth_m.shape} does not match the detections {instances.shape}')
    for k, (v, u) in enumerate(_eroded_pixels(instances, labels, erode_px)):
        d = depth_m[v, u]
        d = d[np.isfinite(d)]
        if len(d) >= min_pixels:
            out[k] = float(np.median(d))
    return out


def mask_points(instances: np.ndarray, labels: np.ndarray, depth_m: np.ndarray, K: np.ndarray,
                T_world_camera: np.ndarray, reach: np.ndarray, per_detection: int = 16, erode_px: int = 3,
                min_pixels: int = 20) -> np.ndarray:
    """Points (N, per_detection, 3) (world, float32; NaN rows: none) of each instance's visible surface: pixels of
    its eroded mask with a depth measurement, back-projected, evenly spread over the mask in raster order.

    Pixels more than `reach` (N,) metres (about the object's extent) nearer or farther than the mask's median
    depth are left out: what remains of a mask's bleed onto the background or a nearer object after the
    erosion. An instance with fewer than min_pixels measurements gets none.
    """
    out = np.full((len(labels), per_detection, 3), np.nan, np.float32)
    if depth_m.shape != instances.shape:
        raise ValueError(f'depth {depth_m.shape} does not match the detections {instances.shape}')
    for k, (v, u) in enumerate(_eroded_pixels(instances, labels, erode_px)):
        z = depth_m[v, u]
        ok = np.isfinite(z) & (z > 0)
        if np.count_nonzero(ok) < min_pixels:
            continue
        ok &= np.abs(z - np.median(z[ok])) <= reach[k]
        v, u, z = v[ok], u[ok], z[ok]
        pick = np.unique(np.linspace(0, len(z) - 1, per_detection).round().astype(np.int64))
        out[k, :len(pick)] = backproject_pixels(K, T_world_camera, u[pick], v[pick], z[pick])
    return out


def depth_points(instances: np.ndarray, labels: np.ndarray, depth_m: np.ndarray, K: np.ndarray,
                 T_world_camera: np.ndarray, cfg, evidence) -> np.ndarray:
    """`mask_points` with the association's settings (`AssociationConfig` cfg, `EvidenceConfig` evidence), each
    instance's reach its class's typical horizontal diagonal: what the association node, the offline pipeline and the
    evaluation pass to `Associator.add_frame(surface_points=...)`."""
    reach = np.array([np.hypot(*class_shape(int(lab) >> 8, c.size_range)[:2]) if c is not None else 0.0
                      for lab, c in zip(labels, map(category_by_id, labels >> 8))])
    return mask_points(instances, labels, depth_m, K, T_world_camera, reach, cfg.box_points_per_detection,
                       evidence.evidence_erode_px, evidence.evidence_min_pixels)


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


def contact_edges(instances: np.ndarray, labels: np.ndarray, boxes: np.ndarray,
                  surface_depth: np.ndarray | None = None, gap_px: int = 2, band_px: int = 2, min_pixels: int = 3,
                  min_fraction: float = 0.1, depth_slack: float = 0.1) -> np.ndarray:
    """Box edges (N, 4) (min u, min v, max u, max v) where the instance's mask meets another instance's.

    Such an edge may be where a nearer object hides this one (a chair pushed under a table ends at the table
    top), so like an edge on the image border it only says the object reaches at least that far. An edge is in
    contact when min_fraction (and at least min_pixels) of the mask's outermost band_px pixels on that side lie
    within gap_px of another instance that may be in front of it (a corner touching does not count): with surface
    depths (N,) (`surface_depths`, NaN: unknown) an instance whose visible surface is more than depth_slack behind
    this one's cannot hide it and does not count.
    instances: (H, W) uint16 label image; labels: (N,); boxes: (N, 4) pixel-edge boxes (`instance_boxes`).
    """
    out = np.zeros((len(labels), 4), dtype=bool)
    h, w = instances.shape
    kernel = np.ones((2 * gap_px + 1, 2 * gap_px + 1), np.uint8)
    for k, (lab, box) in enumerate(zip(labels, boxes)):
        u0, v0 = max(int(np.floor(box[0] + 0.5)) - gap_px, 0), max(int(np.floor(box[1] + 0.5)) - gap_px, 0)
        u1, v1 = min(int(np.ceil(box[2] - 0.5)) + gap_px + 1, w), min(int(np.ceil(box[3] - 0.5)) + gap_px + 1, h)
        window = instances[v0:v1, u0:u1]
        own = window == lab
        if not own.any():
            continue
        other = (window != 0) & ~own
        if surface_depth is not None and np.isfinite(surface_depth[k]):
            behind = labels[np.isfinite(surface_depth) & (surface_depth > surface_depth[k] + depth_slack)]
            other &= ~np.isin(window, behind)
        near_other = cv2.dilate(other.astype(np.uint8), kernel) > 0
        touching = own & near_other
        cols, rows = np.nonzero(own.any(axis=0))[0], np.nonzero(own.any(axis=1))[0]
        sides = (np.s_[:, :cols[0] + band_px], np.s_[:rows[0] + band_px, :],
                 np.s_[:, cols[-1] - band_px + 1:], np.s_[rows[-1] - band_px + 1:, :])
        for e, side in enumerate(sides):
            n_touch = np.count_nonzero(touching[side])
            out[k, e] = n_touch >= max(min_pixels, min_fraction * np.count_nonzero(own[side]))
    return out
