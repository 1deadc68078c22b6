"""Real-capture regime of the synthetic world: camera and sensor effects, and the `frodo synth` presets.

The project's plain synthetic bags are clean in ways real captures are not (issue 9). The scene-level
conditions live where the scene is built (`scene.compose_scene`: chairs pushed under tables, clutter on
tables, held-out furniture families; `scene.HandheldPath`: close range, keyframes spread over a long
path), the detector-level ones in `degrade` (mask outlines, holes, bleeding; pose drift); this module has
the camera and sensor effects applied to each rendered frame (numpy / OpenCV, no ROS):

- `CaptureEffects`: auto-exposure gain and white balance changes between keyframes, vignetting,
  signal-dependent sensor noise (Poisson-Gaussian), motion blur from the camera's motion during the
  exposure, radial lens distortion (images, masks and depth warped consistently; `d` in camera_info);
- `kinect_depth`: Kinect-like depth noise and holes for the optional depth topic (CONTRACT v1.1);
- `texture_strength`: how much texture a surface point has (sparse SLAM only finds landmarks there);
- `PRESETS` / `preset_kwargs`: `clean` (today's defaults), `handheld` (all conditions at realistic levels) and
  `realwalk` (the `handheld` conditions on an inside-out walk through the middle of a room, issue 27).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from frodo_common.geometry import backproject_pixels, invert_transform, project_points


@dataclass
class CaptureEffects:
    """Camera effects on each frame (all off by default).

    exposure_std: std of the log gain of the auto exposure, drawn per frame (keyframes are seconds apart,
      so independent draws); white_balance_std: std of the per-channel log gain.
    vignetting: relative brightness lost at the image corners (falloff with the squared radius).
    shot_noise, read_noise: Poisson-Gaussian sensor noise, variance = shot_noise * I + read_noise^2 with I
      the intensity in 0..255 (applied after exposure, so dark frames are noisier relative to signal).
    motion_blur_s: exposure time in seconds; the image is blurred along the mean optical flow of the scene
      between the frame's pose and the pose `motion_blur_s` later (a linear kernel: a simplified model that
      ignores the flow's variation over the image); hand_shake_dps: std of an extra random angular velocity
      (deg/s) during the exposure. Needs a continuous trajectory (the `handheld` scene).
    distortion: plumb_bob (k1, k2) of the lens; images, masks and depth are warped with it and camera_info
      carries d = (k1, k2, 0, 0, 0). The graph reads only K (it assumes undistorted images), so this is off
      in the `handheld` preset.
    depth_noise: with depth output, Kinect-like noise and holes (`kinect_depth`) instead of exact depth.
    """

    exposure_std: float = 0.0
    white_balance_std: float = 0.0
    vignetting: float = 0.0
    shot_noise: float = 0.0
    read_noise: float = 0.0
    motion_blur_s: float = 0.0
    hand_shake_dps: float = 0.0
    distortion: tuple[float, float] = (0.0, 0.0)
    depth_noise: bool = False

    @property
    def photometric(self) -> bool:
        return bool(self.exposure_std or self.white_balance_std or self.vignetting or self.shot_noise
                    or self.read_noise)


# ---------------------------------------------------------------- photometric effects
def vignette_gain(width: int, height: int, strength: float) -> np.ndarray:
    """Brightness factor (H, W): 1 at the image centre, 1 - strength at the corners (quadratic in radius)."""
    v, u = np.mgrid[:height, :width].astype(np.float64)
    r2 = ((u - (width - 1) / 2) ** 2 + (v - (height - 1) / 2) ** 2) / (((width - 1) / 2) ** 2 + ((height - 1) / 2) ** 2)
    return 1.0 - strength * r2


def photometric(rgb: np.ndarray, effects: CaptureEffects, rng: np.random.Generator) -> np.ndarray:
    """Exposure gain, white balance, vignetting and sensor noise on an RGB image (H, W, 3) uint8 -> uint8.

    Gains act on the intensities and saturate at 255 (overexposed highlights clip like a real sensor's)."""
    img = rgb.astype(np.float64)
    gain = np.exp(rng.normal(0, effects.exposure_std)) if effects.exposure_std else 1.0
    balance = np.exp(rng.normal(0, effects.white_balance_std, 3)) if effects.white_balance_std else np.ones(3)
    img = img * gain * balance
    if effects.vignetting:
        img *= vignette_gain(rgb.shape[1], rgb.shape[0], effects.vignetting)[:, :, None]
    img = np.clip(img, 0, 255)
    if effects.shot_noise or effects.read_noise:
        sigma = np.sqrt(effects.shot_noise * img + effects.read_noise ** 2)
        img = img + rng.normal(size=img.shape) * sigma
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def blur_vector(K: np.ndarray, depth: np.ndarray, T_start: np.ndarray, T_end: np.ndarray,
                max_points: int = 500) -> np.ndarray:
    """Mean image motion (2,) in pixels of the visible surface between camera poses T_start and T_end
    (both T_world_camera (4, 4)), from the z-depth image (H, W) of the start view (0 = no surface; those
    pixels count as 5 m away)."""
    h, w = depth.shape
    v, u = np.mgrid[:h:max(1, h // 20), :w:max(1, w // 25)]
    z = depth[v, u].astype(np.float64)
    z[z <= 0] = 5.0
    u, v, z = u.ravel().astype(np.float64), v.ravel().astype(np.float64), z.ravel()
    world = backproject_pixels(K, T_start, u[:max_points], v[:max_points], z[:max_points])
    uv, zz = project_points(K, invert_transform(T_end), world)
    ok = zz > 0.05
    if not ok.any():
        return np.zeros(2)
    return np.mean(uv[ok] - np.stack([u, v], axis=1)[:max_points][ok], axis=0)


def motion_blur(rgb: np.ndarray, motion_px: np.ndarray) -> np.ndarray:
    """Blur an image (H, W, 3) uint8 with a line kernel along `motion_px` (2,) (its length in pixels)."""
    length = float(np.linalg.norm(motion_px))
    if length < 1.0:
        return rgb
    size = int(np.ceil(length)) | 1
    kernel = np.zeros((size, size), np.float32)
    c = size // 2
    d = np.asarray(motion_px, float) / length * (length / 2)
    cv2.line(kernel, (int(round(c - d[0])), int(round(c - d[1]))), (int(round(c + d[0])), int(round(c + d[1]))), 1.0, 1,
             cv2.LINE_AA)
    kernel /= kernel.sum()
    return cv2.filter2D(rgb, -1, kernel, borderType=cv2.BORDER_REFLECT)


def shaken_pose(T_world_camera: np.ndarray, shake_dps: float, exposure_s: float, rng: np.random.Generator) -> np.ndarray:
    """T_world_camera rotated about its centre by a random angular velocity (std `shake_dps` deg/s per axis)
    held for `exposure_s` seconds (hand tremor during the exposure)."""
    R, _ = cv2.Rodrigues(rng.normal(0, np.radians(shake_dps) * exposure_s, 3).reshape(3, 1))
    out = np.array(T_world_camera, dtype=np.float64)
    out[:3, :3] = out[:3, :3] @ R
    return out


# ---------------------------------------------------------------- lens distortion
def distortion_maps(K: np.ndarray, distortion: tuple[float, float], width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (H, W) float32 that turn an ideal pinhole image into the image of a lens with plumb_bob
    (k1, k2): for each distorted pixel, where its ray lands in the pinhole image."""
    v, u = np.mgrid[:height, :width].astype(np.float64)
    xd, yd = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    k1, k2 = distortion
    x, y = xd.copy(), yd.copy()
    for _ in range(30):  # fixed-point inversion of x_d = x (1 + k1 r^2 + k2 r^4)
        r2 = x * x + y * y
        factor = 1 + k1 * r2 + k2 * r2 * r2
        x, y = xd / factor, yd / factor
    return (x * K[0, 0] + K[0, 2]).astype(np.float32), (y * K[1, 1] + K[1, 2]).astype(np.float32)


def distort(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray], nearest: bool = False) -> np.ndarray:
    """Apply `distortion_maps` to an image (colour bilinear; labels and depth with `nearest`)."""
    return cv2.remap(image, maps[0], maps[1], cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


# ---------------------------------------------------------------- depth sensor
def kinect_depth(depth: np.ndarray, rng: np.random.Generator, near: float = 0.4, far: float = 4.5,
                 edge_jump: float = 0.05, edge_drop: float = 0.7, dropout: float = 0.02) -> np.ndarray:
    """Structured-light-like depth (H, W) float32 metres (0 = no measurement) from exact z-depth (H, W).

    Axial noise std 1.2 mm + 1.9 mm (z - 0.4)^2 (Nguyen, Izadi, Lovell 2012, Kinect v1), no return closer
    than `near` or farther than `far`, holes at depth discontinuities (a neighbour more than `edge_jump` m
    away: dropped with probability `edge_drop`, dilated by one pixel) and blotchy dropouts covering about
    `dropout` of the image (thresholded smooth noise), quantised to millimetres.
    """
    z = depth.astype(np.float64)
    out = z + rng.normal(size=z.shape) * (0.0012 + 0.0019 * (z - 0.4) ** 2)
    valid = (z >= near) & (z <= far)
    jump = np.zeros(z.shape, bool)
    jump[:, 1:] |= np.abs(np.diff(z, axis=1)) > edge_jump
    jump[:, :-1] |= np.abs(np.diff(z, axis=1)) > edge_jump
    jump[1:, :] |= np.abs(np.diff(z, axis=0)) > edge_jump
    jump[:-1, :] |= np.abs(np.diff(z, axis=0)) > edge_jump
    jump = cv2.dilate(jump.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    valid &= ~(jump & (rng.uniform(size=z.shape) < edge_drop))
    if dropout > 0:
        blobs = cv2.GaussianBlur(rng.normal(size=z.shape).astype(np.float32), (0, 0), 3.0)
        valid &= blobs < np.quantile(blobs, 1 - dropout)
    return np.where(valid, np.round(out * 1000) / 1000, 0.0).astype(np.float32)


# ---------------------------------------------------------------- sparse SLAM landmarks
def texture_strength(material, points: np.ndarray, step: float = 0.01) -> np.ndarray:
    """Albedo gradient magnitude (N,) per metre / 100 at points (N, 3): the mean absolute albedo change
    over `step` metres along x, y and z. Zero on plain surfaces; feature-based SLAM finds no landmarks there."""
    base = material.albedo(points)
    change = [np.abs(material.albedo(points + step * np.eye(3)[i]) - base).mean(axis=1) for i in range(3)]
    return np.mean(change, axis=0)


# ---------------------------------------------------------------- presets
def preset_kwargs(name: str) -> dict[str, Any]:
    """SynthConfig keyword arguments of a preset: 'clean' (the defaults: exact masks, poses and images),
    'handheld' (every real-capture condition at realistic levels; see the README's table) or 'realwalk' (the
    'handheld' camera, detector and sensor conditions on the walk the real captures of issue 27 are: furniture
    along the walls of a room, the camera walking through its middle looking outwards, `scene.InsideOutPath`,
    35 keyframes over 35 s, nearly every chair pushed under a table on the side away from the camera, more
    clutter on the tops)."""
    from frodo_datasets.degrade import MaskNoise, PoseNoise
    from frodo_datasets.render import Realism

    if name == 'clean':
        return {}
    if name == 'handheld':
        return dict(
            scene='handheld', frames=35, tuck_chairs=0.7, clutter=3,
            mask_noise=MaskNoise(morph_px=2, drop_rate=0.08, wrong_class_rate=0.02, spurious_rate=0.05,
                                 boundary_px=1.5, hole_rate=0.4, bleed_px=5),
            pose_noise=PoseNoise(rot_deg=0.15, trans_m=0.004, drift_rot_deg=0.05, drift_trans_m=0.003,
                                 drift_per_second=True),
            realism=Realism(ao_samples=4, soft_shadow_deg=3.0, specular=0.25),
            capture=CaptureEffects(exposure_std=0.25, white_balance_std=0.04, vignetting=0.35, shot_noise=0.6,
                                   read_noise=2.0, motion_blur_s=1 / 30, hand_shake_dps=3.0, depth_noise=True),
            slam_texture_min=0.02, slam_density=200.0, slam_noise_m=0.015)
    if name == 'realwalk':
        return {**preset_kwargs('handheld'), 'scene': 'insideout', 'frames': 35, 'tuck_chairs': 0.9, 'clutter': 4}
    raise ValueError(f'unknown preset {name!r}; presets: {", ".join(PRESETS)}')


PRESETS = ('clean', 'handheld', 'realwalk')
