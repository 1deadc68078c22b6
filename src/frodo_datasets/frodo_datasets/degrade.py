"""Degradations of synthetic observations: instance-mask noise, camera pose noise, image noise (numpy).

The renderer gives perfect masks and poses; these functions make them look like a detector's and a SLAM
system's output so the graph is tested under realistic errors:
- masks: per-instance erosion/dilation (boundary errors), wavy outlines, holes, bleeding into neighbours,
  dropped detections (misses), class flips (confusions) and spurious blobs of any known class (false
  positives);
- poses: white per-frame noise plus a random-walk drift on the *published* pose (rendering uses the
  true pose);
- images: additive Gaussian pixel noise.
All randomness comes from the caller's `numpy.random.Generator`.
"""
from __future__ import annotations

from dataclasses import dataclass
import cv2
import numpy as np

from frodo_common.categories import CATEGORIES
from frodo_common.geometry import make_transform


@dataclass
class MaskNoise:
    """Detector-like errors on a contract instance image.

    morph_px: each instance is eroded or dilated by a random radius in [-morph_px, morph_px] pixels.
    drop_rate: probability that an instance is missed in a frame.
    wrong_class_rate: probability that a kept instance gets another class (from `spurious_classes`).
    spurious_rate: expected number (Poisson) of spurious elliptic blobs per frame, drawn on background pixels.
    spurious_classes: COCO ids for class flips and spurious blobs (default: every known category).
    Real-capture boundary errors (`wobble_boundary`, `punch_holes`, `bleed`):
    boundary_px: std (pixels) of a smooth random displacement of each mask outline (ragged, wavy edges);
    hole_rate: expected number (Poisson) of holes per instance (thin parts and low-contrast patches a
      detector misses), each 5-20 % of the mask's size;
    bleed_px: each instance spills up to this many pixels into its neighbours and the background on one
      side (a random half-plane through its centroid), overwriting what is there.
    """

    morph_px: int = 0
    drop_rate: float = 0.0
    wrong_class_rate: float = 0.0
    spurious_rate: float = 0.0
    spurious_classes: tuple[int, ...] = tuple(c.coco_id for c in CATEGORIES)
    boundary_px: float = 0.0
    hole_rate: float = 0.0
    bleed_px: int = 0

    @property
    def active(self) -> bool:
        return bool(self.morph_px or self.drop_rate or self.wrong_class_rate or self.spurious_rate
                    or self.boundary_px or self.hole_rate or self.bleed_px)


@dataclass
class PoseNoise:
    """Noise on published camera poses: white noise (rot_deg, trans_m: std per axis, per frame) and a random
    walk drift (drift_rot_deg, drift_trans_m: std of the per-frame increment; with `drift_per_second` the
    std of the increment over one second of capture, so the drift reached at the end of a sequence does not
    depend on how many keyframes it is sampled at)."""

    rot_deg: float = 0.0
    trans_m: float = 0.0
    drift_rot_deg: float = 0.0
    drift_trans_m: float = 0.0
    drift_per_second: bool = False

    @property
    def active(self) -> bool:
        return bool(self.rot_deg or self.trans_m or self.drift_rot_deg or self.drift_trans_m)


def _rotvec_matrix(v: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) of a rotation vector (3,) (Rodrigues)."""
    R, _ = cv2.Rodrigues(np.asarray(v, dtype=np.float64).reshape(3, 1))
    return R


class PoseNoiser:
    """Stateful pose corrupter (drift accumulates over calls): `noisy = noiser(T_world_camera)`.

    The error is applied in the world frame: T_noisy = E T with E = drift * white.
    """

    def __init__(self, noise: PoseNoise, rng: np.random.Generator):
        self.noise = noise
        self.rng = rng
        self._drift = np.eye(4)

    def __call__(self, T_world_camera: np.ndarray, dt: float = 1.0) -> np.ndarray:
        """Published pose (4, 4); `dt` = seconds since the previous call (used with `drift_per_second`)."""
        n = self.noise
        walk = np.sqrt(max(dt, 0.0)) if n.drift_per_second else 1.0
        step = make_transform(_rotvec_matrix(self.rng.normal(0, walk * np.radians(n.drift_rot_deg), 3)),
                              self.rng.normal(0, walk * n.drift_trans_m, 3))
        self._drift = step @ self._drift
        white = make_transform(_rotvec_matrix(self.rng.normal(0, np.radians(n.rot_deg), 3)),
                               self.rng.normal(0, n.trans_m, 3))
        # Rotate about the camera centre so rotation noise does not swing the camera around the origin.
        centre = np.asarray(T_world_camera)[:3, 3]
        E = self._drift @ make_transform(t=centre) @ white @ make_transform(t=-centre)
        return E @ np.asarray(T_world_camera, dtype=np.float64)


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def degrade_instances(instances: np.ndarray, noise: MaskNoise, rng: np.random.Generator) -> np.ndarray:
    """Apply `noise` to a contract instance image (H, W) uint16 (`category_id * 256 + k`, 0 = background).

    Returns a new image in the same encoding; k values stay unique within the frame.
    """
    out = np.zeros_like(instances)
    labels = [int(v) for v in np.unique(instances) if v != 0]
    used_k = {v & 0xFF for v in labels}
    for value in labels:
        if rng.random() < noise.drop_rate:
            continue
        mask = (instances == value).astype(np.uint8)
        r = int(rng.integers(-noise.morph_px, noise.morph_px + 1)) if noise.morph_px else 0
        if r > 0:
            mask = cv2.dilate(mask, _disk(r))
        elif r < 0:
            mask = cv2.erode(mask, _disk(-r))
        if noise.boundary_px:
            mask = wobble_boundary(mask, noise.boundary_px, rng)
        if noise.hole_rate:
            mask = punch_holes(mask, noise.hole_rate, rng)
        coco = value >> 8
        if noise.wrong_class_rate and rng.random() < noise.wrong_class_rate:
            others = [c for c in noise.spurious_classes if c != coco]
            coco = int(rng.choice(others)) if others else coco
        # Dilated masks do not overwrite pixels of instances already drawn (those are in front in the
        # original image as often as not; this keeps every instance a single label per pixel).
        out[(mask > 0) & (out == 0)] = (coco << 8) | (value & 0xFF)
        if noise.bleed_px:
            out[bleed(mask, noise.bleed_px, rng) > 0] = (coco << 8) | (value & 0xFF)
    h, w = instances.shape
    for _ in range(int(rng.poisson(noise.spurious_rate)) if noise.spurious_rate else 0):
        free = [k for k in range(1, 256) if k not in used_k]
        if not free:
            break
        k = int(rng.choice(free))
        used_k.add(k)
        blob = np.zeros((h, w), np.uint8)
        centre = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        axes = (int(rng.uniform(0.04, 0.2) * w), int(rng.uniform(0.04, 0.2) * h))
        cv2.ellipse(blob, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
        out[(blob > 0) & (out == 0)] = (int(rng.choice(noise.spurious_classes)) << 8) | k
    return out


def wobble_boundary(mask: np.ndarray, amplitude_px: float, rng: np.random.Generator,
                    wavelength_px: float = 12.0) -> np.ndarray:
    """Move the outline of a binary mask (H, W) uint8 by a smooth random field of std `amplitude_px` pixels
    (correlated over about `wavelength_px`): the ragged, wavy edges of a real detector's masks."""
    if not mask.any():
        return mask
    inside = cv2.distanceTransform(mask, cv2.DIST_L2, 3)
    outside = cv2.distanceTransform(1 - mask, cv2.DIST_L2, 3)
    signed = inside - outside  # > 0 inside, pixels from the outline
    field = cv2.GaussianBlur(rng.normal(size=mask.shape).astype(np.float32), (0, 0), wavelength_px / 2)
    field *= amplitude_px / max(float(field.std()), 1e-6)
    return (signed + field > 0).astype(np.uint8)


def punch_holes(mask: np.ndarray, rate: float, rng: np.random.Generator) -> np.ndarray:
    """Remove Poisson(`rate`) elliptic holes from a binary mask (H, W) uint8, each centred on a mask pixel
    with semi-axes 5-20 % of the mask's size (sqrt of its area)."""
    ys, xs = np.nonzero(mask)
    if not len(ys):
        return mask
    out = mask.copy()
    size = np.sqrt(len(ys))
    for _ in range(int(rng.poisson(rate))):
        i = int(rng.integers(len(ys)))
        axes = (max(1, int(rng.uniform(0.05, 0.2) * size)), max(1, int(rng.uniform(0.05, 0.2) * size)))
        cv2.ellipse(out, (int(xs[i]), int(ys[i])), axes, float(rng.uniform(0, 180)), 0, 360, 0, -1)
    return out


def bleed(mask: np.ndarray, radius_px: int, rng: np.random.Generator) -> np.ndarray:
    """Pixels (H, W) uint8 a mask spills over: its dilation by 1..`radius_px` minus the mask, on one side of
    a random line through its centroid (a detector bleeding into a neighbour with similar colour)."""
    ys, xs = np.nonzero(mask)
    if not len(ys):
        return np.zeros_like(mask)
    ring = cv2.dilate(mask, _disk(int(rng.integers(1, radius_px + 1)))) & (1 - mask)
    angle = rng.uniform(0, 2 * np.pi)
    v, u = np.mgrid[:mask.shape[0], :mask.shape[1]]
    side = (u - xs.mean()) * np.cos(angle) + (v - ys.mean()) * np.sin(angle) > 0
    return (ring.astype(bool) & side).astype(np.uint8)


def add_image_noise(rgb: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Additive Gaussian noise with std `sigma` (intensity units 0..255) on an RGB image (H, W, 3) uint8."""
    if sigma <= 0:
        return rgb
    noisy = rgb.astype(np.float32) + rng.normal(0, sigma, rgb.shape).astype(np.float32)
    return np.clip(noisy + 0.5, 0, 255).astype(np.uint8)

