"""2D object detection for FroDO (paper Sec. 5.1, "Object Detection and Data Association"): instance
image filtering and the torchvision Mask R-CNN backend (numpy/torch, no ROS).

Instance images use the contract's `/camera/instances` encoding (CONTRACT.md): a `uint16` (H, W) array
whose pixel is `coco_id * 256 + k` (k = 1..255 numbers the instances of one frame, 0 = background).
Boxes are (x0, y0, x1, y1) in pixel-edge coordinates: pixel (u, v) is the centre of column u and row v
(the projection convention of `frodo_common.geometry.project_points`), so a mask covering columns
u0..u1 spans x0 = u0 - 0.5 to x1 = u1 + 0.5.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import find_objects

from frodo_common.categories import split_instance_label

REFERENCE_SIZE = (640, 480)
"""Image size (width, height) at which the pixel thresholds of `FilterConfig` and of the association's
`AssociationConfig` are given; other resolutions scale them (`resolution_scale`)."""

MASKRCNN_CHECKPOINT = 'maskrcnn_resnet50_fpn_v2_coco-73cbd019.pth'
MASKRCNN_URL = f'https://download.pytorch.org/models/{MASKRCNN_CHECKPOINT}'
FRAGMENT_POLICIES = ('keep', 'largest', 'drop')


def resolution_scale(width: float, height: float) -> float:
    """Length scale of an image of (width, height) relative to REFERENCE_SIZE: sqrt(W * H / (640 * 480)).

    Pixel lengths given at the reference resolution are multiplied by it, pixel areas by its square, so a
    threshold keeps its meaning as a fraction of the image (0.5 at 320x240, 2 at 1280x960)."""
    return float(np.sqrt(width * height / (REFERENCE_SIZE[0] * REFERENCE_SIZE[1])))


class WeightsNotFoundError(FileNotFoundError):
    """The Mask R-CNN checkpoint is not on disk (nothing is downloaded at run time)."""


@dataclass(frozen=True)
class FilterConfig:
    """Which instances of a frame are kept.

    Size thresholds are in pixels of a 640x480 image (REFERENCE_SIZE) and scale with the image size: at
    W x H, lengths by s = sqrt(W * H / (640 * 480)) and areas by s^2 (`resolution_scale`), e.g. at 320x240
    min_area 400 -> 100 px and min_box_side 16 -> 8 px.

    classes: COCO ids kept; None keeps every class.
    min_area: instances with fewer mask pixels (at 640x480) are dropped (tiny, unreliable detections).
    min_box_side: instances whose box is narrower or lower than this (pixels at 640x480) are dropped.
    drop_truncated: drop instances whose mask comes within `border_margin` pixels of the image border
        (plain pixels, not scaled).
    min_fragment_fraction: connected components smaller than this fraction of the instance's area are
        removed as specks (0 keeps every component).
    fragment_policy: instances still in several pieces after speck removal: 'keep' all pieces,
        keep only the 'largest', or 'drop' the instance.
    """

    classes: tuple[int, ...] | None = (62, 67)
    min_area: int = 400
    min_box_side: int = 16
    drop_truncated: bool = False
    border_margin: int = 2
    min_fragment_fraction: float = 0.05
    fragment_policy: str = 'keep'

    def __post_init__(self):
        if self.fragment_policy not in FRAGMENT_POLICIES:
            raise ValueError(f'fragment_policy must be one of {FRAGMENT_POLICIES}, got {self.fragment_policy!r}')


@dataclass(frozen=True)
class Detection:
    """One kept instance: its pixel value in the instance image, class, box and area."""

    label: int
    coco_id: int
    bbox: tuple[float, float, float, float]
    area: int
    truncated: bool


def mask_box(rows: np.ndarray, cols: np.ndarray) -> tuple[float, float, float, float]:
    """Box (x0, y0, x1, y1) in pixel-edge coordinates of the pixels (rows (N,), cols (N,)), N > 0."""
    return (float(cols.min()) - 0.5, float(rows.min()) - 0.5, float(cols.max()) + 0.5, float(rows.max()) + 0.5)


def instance_boxes(instances: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Labels, boxes and areas of every instance in an instance image.

    instances: (H, W) uint16. Returns (labels (N,) int64 ascending, boxes (N, 4) float64 pixel-edge
    coordinates, areas (N,) int64). One histogram and one `scipy.ndimage.find_objects` pass.
    """
    counts = np.bincount(instances.ravel(), minlength=1)
    labels = np.nonzero(counts)[0]
    labels = labels[labels > 0]
    if len(labels) == 0:
        return labels.astype(np.int64), np.zeros((0, 4)), np.zeros(0, np.int64)
    lut = np.zeros(len(counts), dtype=np.int32)
    lut[labels] = np.arange(1, len(labels) + 1)
    slices = find_objects(lut[instances])
    boxes = np.array([[sl[1].start - 0.5, sl[0].start - 0.5, sl[1].stop - 0.5, sl[0].stop - 0.5] for sl in slices])
    return labels.astype(np.int64), boxes, counts[labels].astype(np.int64)


def _clean_fragments(mask: np.ndarray, cfg: FilterConfig) -> np.ndarray | None:
    """Remove specks from a boolean crop (h, w); apply the fragment policy; None drops the instance."""
    n, comp, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:  # background + one component
        return mask
    sizes = stats[1:, cv2.CC_STAT_AREA]
    keep = sizes >= cfg.min_fragment_fraction * sizes.sum()
    if keep.sum() > 1:
        if cfg.fragment_policy == 'drop':
            return None
        if cfg.fragment_policy == 'largest':
            keep = np.zeros_like(keep)
            keep[np.argmax(sizes)] = True
    lut = np.concatenate([[False], keep])
    return lut[comp]


def filter_instances(instances: np.ndarray, cfg: FilterConfig) -> tuple[np.ndarray, list[Detection]]:
    """Apply the instance filters of `cfg` to an instance image (size thresholds scaled to its resolution).

    instances: (H, W) uint16 contract instance image. Returns (filtered (H, W) uint16 image with the
    dropped instances and specks set to 0 and kept pixel values unchanged, kept detections sorted by label).
    """
    if instances.ndim != 2 or instances.dtype != np.uint16:
        raise ValueError(f'instance image must be (H, W) uint16, got {instances.shape} {instances.dtype}')
    h, w = instances.shape
    out = np.zeros_like(instances)
    detections: list[Detection] = []
    scale = resolution_scale(w, h)
    min_area, min_side = max(cfg.min_area * scale ** 2, 1), cfg.min_box_side * scale
    labels, boxes, _ = instance_boxes(instances)
    for label, box in zip(labels, boxes):
        coco_id, _ = split_instance_label(label)
        if cfg.classes is not None and coco_id not in cfg.classes:
            continue
        c0, r0, c1, r1 = int(box[0] + 0.5), int(box[1] + 0.5), int(box[2] - 0.5), int(box[3] - 0.5)
        crop = instances[r0:r1 + 1, c0:c1 + 1] == label
        if cfg.min_fragment_fraction > 0 or cfg.fragment_policy != 'keep':
            crop = _clean_fragments(crop, cfg)
            if crop is None:
                continue
        rows, cols = np.nonzero(crop)
        area = len(rows)
        if area < min_area:
            continue
        bbox = mask_box(rows + r0, cols + c0)
        if min(bbox[2] - bbox[0], bbox[3] - bbox[1]) < min_side:
            continue
        m = cfg.border_margin
        truncated = bbox[0] < m or bbox[1] < m or bbox[2] > w - m or bbox[3] > h - m
        if truncated and cfg.drop_truncated:
            continue
        out[rows + r0, cols + c0] = label
        detections.append(Detection(int(label), coco_id, bbox, area, bool(truncated)))
    return out, detections


def masks_to_instances(masks: np.ndarray, labels: np.ndarray, scores: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Paint binary masks into a contract instance image, higher scores on top.

    masks: (N, H, W) bool; labels: (N,) COCO ids; scores: (N,). Instance k = 1..N numbers the masks by
    decreasing score (at most 255 are kept). Returns (H, W) uint16.
    """
    out = np.zeros(shape, dtype=np.uint16)
    order = np.argsort(-np.asarray(scores), kind='stable')[:255]
    for k, i in reversed(list(enumerate(order, start=1))):  # paint lowest score first
        out[masks[i]] = (int(labels[i]) << 8) | k
    return out


def default_weights_path() -> Path:
    """Where torchvision's hub cache keeps the Mask R-CNN v2 COCO checkpoint ($TORCH_HOME/hub/checkpoints)."""
    import torch.hub
    return Path(torch.hub.get_dir()) / 'checkpoints' / MASKRCNN_CHECKPOINT


def resolve_weights(weights_path: str | os.PathLike | None) -> Path:
    """The checkpoint file to load: `weights_path` if given, else the torchvision hub cache location.

    Raises WeightsNotFoundError naming the file to download and where to put it.
    """
    path = Path(weights_path).expanduser() if weights_path else default_weights_path()
    if not path.is_file():
        raise WeightsNotFoundError(
            f'Mask R-CNN weights not found at {path}. Nothing is downloaded at run time: download '
            f'{MASKRCNN_URL} and either pass its path as the weights_path parameter or place it at '
            f'{default_weights_path()} (i.e. $TORCH_HOME/hub/checkpoints/).')
    return path


class MaskRCNNDetector:
    """torchvision `maskrcnn_resnet50_fpn_v2` (COCO) producing contract instance images.

    weights_path: checkpoint file ('' or None: the torchvision hub cache location).
    device: torch device string ('cpu', 'cuda', 'cuda:0').
    score_threshold: detections with a lower score are dropped.
    mask_threshold: soft mask probability above which a pixel belongs to the instance (0.5 in Mask R-CNN).
    classes: COCO ids kept (None: all).
    min_size, max_size: the network's input resize (torchvision defaults 800 / 1333); smaller is faster.
    model: an already built torchvision Mask R-CNN (tests pass a randomly initialised one); when given,
        no weights are loaded.
    """

    def __init__(self, weights_path: str | os.PathLike | None = None, device: str = 'cpu',
                 score_threshold: float = 0.7, mask_threshold: float = 0.5, classes: tuple[int, ...] | None = None,
                 min_size: int = 800, max_size: int = 1333, model=None):
        import torch
        import torchvision
        self.torch = torch
        self.device = torch.device(device)
        self.score_threshold = float(score_threshold)
        self.mask_threshold = float(mask_threshold)
        self.classes = None if classes is None else tuple(int(c) for c in classes)
        if model is None:
            path = resolve_weights(weights_path)
            model = torchvision.models.detection.maskrcnn_resnet50_fpn_v2(
                weights=None, weights_backbone=None, min_size=int(min_size), max_size=int(max_size))
            model.load_state_dict(torch.load(path, map_location='cpu', weights_only=True))
        self.model = model.to(self.device).eval()

    def detect(self, rgb: np.ndarray) -> np.ndarray:
        """Instance image (H, W) uint16 of an RGB uint8 image (H, W, 3)."""
        torch = self.torch
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f'expected an RGB uint8 image (H, W, 3), got {rgb.shape} {rgb.dtype}')
        x = torch.from_numpy(np.ascontiguousarray(rgb)).to(self.device).permute(2, 0, 1).float() / 255.0
        with torch.inference_mode():
            out = self.model([x])[0]
        scores = out['scores'].cpu().numpy()
        labels = out['labels'].cpu().numpy()
        keep = scores >= self.score_threshold
        if self.classes is not None:
            keep &= np.isin(labels, self.classes)
        masks = (out['masks'][torch.from_numpy(keep).to(out['masks'].device), 0] > self.mask_threshold).cpu().numpy()
        return masks_to_instances(masks, labels[keep], scores[keep], rgb.shape[:2])
