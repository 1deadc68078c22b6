"""Shared pieces of the dataset converters: the source model every reader fills, options, summary, image I/O,
keyframe selection and resampling to the output camera.

A reader (`scannet.py`, `redwood.py`, `tum.py`, `folder.py`) turns a dataset folder into a `Source`: the
colour camera, optional depth camera, lazily loaded frames with camera-to-world poses in the dataset's own
world frame, optional ground-truth meshes and a count of what it had to skip. `writer.write_bag` then picks
keyframes, aligns gravity, resamples and writes the contract bag.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from frodo_common.geometry import backproject_pixels

# Stamps of datasets without absolute timestamps start here (same origin as `frodo synth`).
DEFAULT_START_NS = 1_700_000_000_000_000_000


class ConvertError(RuntimeError):
    """The input cannot be converted: missing or unknown layout, mismatched counts, no usable frame."""


@dataclass
class GroundTruthObject:
    """A ground-truth object mesh in the dataset's world frame: class name (CONTRACT.md marker ns), id, mesh."""

    class_name: str
    object_id: int
    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)


@dataclass
class SourceFrame:
    """One dataset frame, loaded lazily.

    index: the dataset's frame number; stamp_ns: its time; pose: (4, 4) T_world_camera (colour optical frame)
    in the dataset world, or None when the dataset has no valid pose for it.
    color(): RGB uint8 (H, W, 3); depth(): metres float32 (Hd, Wd), 0 = no measurement (None: no depth);
    instances(): contract-encoded uint16 (Hl, Wl) `coco_id * 256 + k` (None: no instances).
    Loaders raise on unreadable files; the writer skips such frames and counts them.
    """

    index: int
    stamp_ns: int
    pose: np.ndarray | None
    color: Callable[[], np.ndarray]
    depth: Callable[[], np.ndarray] | None = None
    instances: Callable[[], np.ndarray] | None = None


@dataclass
class Source:
    """A dataset sequence as read: cameras, frames, optional ground truth and what the reader skipped.

    K_color (3, 3) and color_size (width, height) describe the colour images; `dist` are plumb_bob distortion
    coefficients of the colour camera (k1, k2, p1, p2, k3; None or zeros = undistorted). K_depth/depth_size
    describe the depth images and T_color_depth (4, 4) maps depth-camera to colour-camera coordinates (None =
    the depth is registered to colour already). label_size: (width, height) of the instance images.
    world_up: the dataset world's up axis when known (ScanNet: +z), else None.
    skipped: reason -> count of frames the reader dropped; notes: facts worth printing in the summary.
    """

    format: str
    frames: list[SourceFrame]
    K_color: np.ndarray
    color_size: tuple[int, int]
    dist: np.ndarray | None = None
    K_depth: np.ndarray | None = None
    depth_size: tuple[int, int] | None = None
    T_color_depth: np.ndarray | None = None
    label_size: tuple[int, int] | None = None
    ground_truth: list[GroundTruthObject] = field(default_factory=list)
    world_up: np.ndarray | None = None
    skipped: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def skip(self, reason: str, count: int = 1) -> None:
        """Count `count` frames dropped for `reason`."""
        if count:
            self.skipped[reason] = self.skipped.get(reason, 0) + count


@dataclass
class ConvertOptions:
    """What to write (defaults in brackets; the CLI flags of `frodo convert` map one to one).

    views: keyframes spread evenly over the usable frames (the paper's protocol uses 35) [all];
    every: take every K-th usable frame (before `views`) [1]; max_frames: stop after this many frames [no limit];
    resize: output (width, height), or a float scale of the colour resolution [colour resolution, or the
    label resolution when instances are written and `instances_at` = 'labels'];
    instances_at: 'labels' (colour resized down to the instance images, intrinsics scaled) or 'color'
    (instances resized up to the colour, nearest neighbour) ['labels'];
    gravity: 'auto' (dataset default: none for ScanNet, whose world is z up; else a floor fit when there is
    depth, else the cameras' mean up), 'none', 'floor' (on depth, or on ORB landmarks without depth),
    'camera', or 'up' with `up` = the dataset's up vector;
    landmarks: 'auto' (depth if the dataset has depth, else none), 'depth', 'features' (ORB, opt-in: it lowered
    F1 on the measured scenes), 'none';
    landmark_stride, landmark_voxel, landmark_min_views: depth landmarks from every N-th pixel, pooled in
    voxels of this size (m), kept once seen in this many keyframes [4, 0.03, 2] (see `landmarks.py`);
    depth, instances, ground_truth: write these optional topics when the dataset has them [True];
    fps: frame rate for datasets without timestamps [30] (intrinsics are reader options: see each reader).
    """

    views: int | None = None
    every: int = 1
    max_frames: int | None = None
    resize: tuple[int, int] | float | None = None
    instances_at: str = 'labels'
    gravity: str = 'auto'
    up: tuple[float, float, float] | None = None
    landmarks: str = 'auto'
    landmark_stride: int = 4
    landmark_voxel: float = 0.03
    landmark_min_views: int = 2
    max_depth: float = 6.0
    slam_every: int = 5
    depth: bool = True
    instances: bool = True
    ground_truth: bool = True
    fps: float = 30.0
    start_ns: int = DEFAULT_START_NS
    world_frame: str = 'world'
    camera_frame: str = 'camera_color_optical_frame'
    compression: str = 'zstd'


@dataclass
class ConvertSummary:
    """What `frodo convert` wrote: frames in/out, skipped frames by reason, topic counts, camera, gravity."""

    output: Path
    format: str
    frames_in: int
    frames_written: int
    size: tuple[int, int]
    K: np.ndarray
    counts: dict[str, int]
    skipped: dict[str, int]
    gravity: str
    landmarks: str
    ground_truth: int
    notes: list[str] = field(default_factory=list)
    T_aligned_dataset: np.ndarray | None = None  # the gravity alignment applied to poses, landmarks, ground truth

    def text(self) -> str:
        """Human-readable summary (printed by the CLI)."""
        K = self.K
        lines = [f'wrote {self.output} ({self.output.stat().st_size / 1e6:.2f} MB) from a {self.format} sequence: '
                 f'{self.frames_written} of {self.frames_in} frames, {self.size[0]}x{self.size[1]}, '
                 f'fx {K[0, 0]:.1f} fy {K[1, 1]:.1f} cx {K[0, 2]:.1f} cy {K[1, 2]:.1f}',
                 f'  gravity: {self.gravity}', f'  landmarks: {self.landmarks}',
                 f'  ground truth objects: {self.ground_truth}']
        lines += [f'  {topic:<42} {n:>5}' for topic, n in self.counts.items()]
        if self.skipped:
            lines.append('  skipped: ' + ', '.join(f'{n} {reason}' for reason, n in self.skipped.items()))
        lines += [f'  note: {n}' for n in self.notes]
        return '\n'.join(lines)


# ---------------------------------------------------------------- file helpers
def natural_key(path: Path) -> tuple:
    """Sort key that orders `2.jpg` before `10.jpg`."""
    return tuple(int(t) if t.isdigit() else t for t in re.split(r'(\d+)', path.name))


def list_images(folder: Path, suffixes: Sequence[str] = ('.png', '.jpg', '.jpeg')) -> list[Path]:
    """Image files of a folder in natural order."""
    return sorted((p for p in folder.iterdir() if p.suffix.lower() in suffixes), key=natural_key)


def leading_int(path: Path) -> int | None:
    """First integer in a file name (`0000012-000000400000.jpg` -> 12, `frame-7.png` -> 7), None if none."""
    m = re.search(r'\d+', path.stem)
    return int(m.group()) if m else None


def read_color(path: Path) -> np.ndarray:
    """RGB uint8 (H, W, 3) from an image file; raises OSError when missing or undecodable."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise OSError(f'cannot read colour image {path}')
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def decode_color(data: bytes, what: str) -> np.ndarray:
    """RGB uint8 from encoded (JPEG/PNG) bytes."""
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise OSError(f'cannot decode colour image of {what}')
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: Path, factor: float) -> np.ndarray:
    """Depth in metres float32 (H, W) from a 16-bit PNG storing `factor` units per metre (0 = no measurement)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise OSError(f'cannot read depth image {path}')
    if img.ndim != 2 or img.dtype != np.uint16:
        raise OSError(f'depth image {path} is {img.dtype} with shape {img.shape}, expected a 16-bit single channel PNG')
    return img.astype(np.float32) / float(factor)


def read_matrix(path: Path, shape: tuple[int, int] = (4, 4)) -> np.ndarray:
    """A whitespace-separated matrix text file (e.g. ScanNet `pose/N.txt`); raises ConvertError if malformed."""
    try:
        values = np.array(path.read_text().split(), dtype=np.float64)
    except (OSError, ValueError) as err:
        raise ConvertError(f'cannot read matrix file {path}: {err}') from None
    if values.size != shape[0] * shape[1]:
        raise ConvertError(f'{path}: expected {shape[0]}x{shape[1]} numbers, found {values.size}')
    return values.reshape(shape)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ConvertError(f'cannot read image {path}')
    return img.shape[1], img.shape[0]


def valid_pose(T: np.ndarray | None) -> bool:
    """A finite rigid 4x4 (ScanNet marks lost tracking with -inf poses)."""
    if T is None or T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(np.allclose(R.T @ R, np.eye(3), atol=1e-3) and np.linalg.det(R) > 0)


# ---------------------------------------------------------------- keyframes
def select_keyframes(n: int, views: int | None = None, every: int = 1, max_frames: int | None = None) -> list[int]:
    """Indices into `n` usable frames: every `every`-th, then `views` of them spread evenly (first and last
    included), then at most `max_frames`."""
    if every < 1:
        raise ValueError('every must be >= 1')
    idx = list(range(0, n, every))
    if views is not None:
        if views < 1:
            raise ValueError('views must be >= 1')
        if views < len(idx):
            picks = np.unique(np.round(np.linspace(0, len(idx) - 1, views)).astype(int))
            idx = [idx[i] for i in picks]
    if max_frames is not None:
        idx = idx[:max_frames]
    return idx


# ---------------------------------------------------------------- resampling to the output camera
def scale_intrinsics(K: np.ndarray, from_size: tuple[int, int], to_size: tuple[int, int]) -> np.ndarray:
    """K of an image resized from (w, h) to (w', h') (pixel centres at integer coordinates)."""
    sx, sy = to_size[0] / from_size[0], to_size[1] / from_size[1]
    K2 = np.array(K, dtype=np.float64, copy=True)
    K2[0, 0] *= sx
    K2[1, 1] *= sy
    K2[0, 1] *= sx
    K2[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K2[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K2


def undistort_maps(K: np.ndarray, dist, size: tuple[int, int]):
    """cv2.remap maps taking an image with plumb_bob `dist` to the undistorted pinhole K (same K, same size);
    None when there is no distortion."""
    if dist is None or not np.any(np.asarray(dist) != 0):
        return None
    K = np.asarray(K, dtype=np.float64)
    return cv2.initUndistortRectifyMap(K, np.asarray(dist, np.float64), None, K, tuple(size), cv2.CV_32FC1)


def resize_color(rgb: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Area-averaged when shrinking, bilinear when growing."""
    if (rgb.shape[1], rgb.shape[0]) == tuple(size):
        return rgb
    shrink = size[0] < rgb.shape[1]
    return cv2.resize(rgb, tuple(size), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def resize_nearest(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resize (labels, instance ids)."""
    if (img.shape[1], img.shape[0]) == tuple(size):
        return img
    return cv2.resize(img, tuple(size), interpolation=cv2.INTER_NEAREST)


def register_depth(depth: np.ndarray, K_depth: np.ndarray, K_out: np.ndarray, out_size: tuple[int, int],
                   T_out_depth: np.ndarray | None = None) -> np.ndarray:
    """Depth (Hd, Wd) metres seen by the depth camera -> depth (H, W) registered to the output colour camera.

    With no rotation/translation between the cameras (T_out_depth None or identity; ScanNet's exported
    extrinsics, depth already registered to colour) the views differ only by intrinsics, so each output
    pixel looks up the depth pixel along the same ray (nearest neighbour; z is unchanged). Otherwise the
    depth pixels are back-projected, moved into the colour camera and splatted with a z-buffer (holes stay 0).
    """
    w, h = out_size
    if T_out_depth is None or np.allclose(T_out_depth, np.eye(4), atol=1e-6):
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        H = np.asarray(K_depth, np.float64) @ np.linalg.inv(K_out)
        x = H[0, 0] * u + H[0, 1] * v + H[0, 2]
        y = H[1, 0] * u + H[1, 1] * v + H[1, 2]
        return cv2.remap(depth.astype(np.float32), x.astype(np.float32), y.astype(np.float32),
                         interpolation=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if depth.shape[1] < w or depth.shape[0] < h:  # splat at least one point per output pixel: upsample first
        up = (max(w, depth.shape[1]), max(h, depth.shape[0]))
        K_depth = scale_intrinsics(K_depth, (depth.shape[1], depth.shape[0]), up)
        depth = resize_nearest(depth, up)
    vs, us = np.nonzero(depth > 0)
    z = depth[vs, us].astype(np.float64)
    pts = np.stack([(us - K_depth[0, 2]) / K_depth[0, 0] * z, (vs - K_depth[1, 2]) / K_depth[1, 1] * z, z], axis=1)
    pts = pts @ T_out_depth[:3, :3].T + T_out_depth[:3, 3]
    front = pts[:, 2] > 1e-6
    pts = pts[front]
    uo = np.round(K_out[0, 0] * pts[:, 0] / pts[:, 2] + K_out[0, 2]).astype(np.int64)
    vo = np.round(K_out[1, 1] * pts[:, 1] / pts[:, 2] + K_out[1, 2]).astype(np.int64)
    inside = (uo >= 0) & (uo < w) & (vo >= 0) & (vo < h)
    out = np.full(h * w, np.inf)
    np.minimum.at(out, vo[inside] * w + uo[inside], pts[inside, 2])
    out[~np.isfinite(out)] = 0.0
    return out.reshape(h, w).astype(np.float32)


def backproject(depth: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray, stride: int = 8,
                max_depth: float = np.inf) -> np.ndarray:
    """World points (N, 3) of every `stride`-th valid depth pixel (grid subsampling), depth < max_depth."""
    sub = depth[::stride, ::stride]
    vs, us = np.nonzero((sub > 0) & (sub < max_depth) & np.isfinite(sub))
    z = sub[vs, us].astype(np.float64)
    u, v = us * stride, vs * stride
    return backproject_pixels(K, T_world_camera, u, v, z)
