"""Capture-condition randomisation of the encoder's training crops (issue 9, item 5; beyond the paper).

The paper's encoder (Sec. 5.2) is trained on renders with perturbed crop boxes. Detections of a handheld
capture differ from such renders in ways a crop shows directly, so each training crop may also get:

- truncation: the object cut by a simulated image border (pixels beyond it are zeroed, as `square_crop` pads
  them; the colour jitter and noise that follow make them near-constant rather than exactly 0), the crop
  re-centred on what is left, as the pipeline crops the visible mask's box;
- occlusion: a textured patch over part of the object (a table edge in front of a chair, clutter, a person),
  removed from the mask as an instance mask of the occluded object would be;
- mask errors: a ragged boundary (smooth noise of a few pixels on the signed distance), holes, bleeding;
- optics and sensor: Gaussian or motion blur, vignetting, exposure (gamma), stronger noise.

Every option is off at its default (`CropAugmentation()`), and then `augment_crop` draws exactly the random
numbers of the paper-style augmentation alone, so older encoder configs reproduce.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import cv2
import numpy as np

from frodo_shape.crops import square_crop


@dataclass
class CropAugmentation:
    """Probabilities and strengths of the per-crop randomisation (`augment:` in an encoder config)."""
    jitter: float = 0.08            # box edge noise, fraction of the box side (paper-style)
    p_truncate: float = 0.0         # a simulated image border cuts the object ...
    truncate_max: float = 0.55      # ... removing up to this fraction of the box along the cut axis
    p_occlude: float = 0.0          # a textured occluder covers part of the object
    occlude_max: float = 0.45       # ... up to this fraction of the box side
    p_mask_noise: float = 0.0       # ragged mask boundary, holes or bleeding
    mask_noise_px: float = 3.0      # boundary noise amplitude (pixels of the training crop)
    p_blur: float = 0.0             # Gaussian or motion blur
    p_vignette: float = 0.0
    p_exposure: float = 0.0         # gamma 0.6-1.6 and stronger sensor noise

    @classmethod
    def from_dict(cls, d: dict | None) -> 'CropAugmentation':
        d = dict(d or {})
        unknown = set(d) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f'unknown augment keys {sorted(unknown)}; known: {[f.name for f in fields(cls)]}')
        return cls(**{k: float(v) for k, v in d.items()})

    def to_dict(self) -> dict:
        return asdict(self)


def _box_of(mask: np.ndarray):
    ys, xs = np.nonzero(mask)
    return np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=np.float64)


def truncate(image: np.ndarray, mask: np.ndarray, box: np.ndarray, rng: np.random.Generator, max_cut: float):
    """Cut the object at a random border (one side, sometimes two), zeroing what lies beyond it.

    Returns (image, mask, box of the visible mask) or the inputs when too little would remain.
    """
    cut_image, cut_mask = image.copy(), mask.copy()
    sides = rng.choice(4, size=1 + int(rng.uniform() < 0.3), replace=False)
    for side in sides:
        frac = rng.uniform(0.1, max_cut)
        x0, y0, x1, y1 = box
        if side == 0:      # left border
            cut = max(int(round(x0 + frac * (x1 - x0))), 0)
            cut_image[:, :cut], cut_mask[:, :cut] = 0, False
        elif side == 1:    # right border
            cut = max(int(round(x1 - frac * (x1 - x0))), 0)
            cut_image[:, cut:], cut_mask[:, cut:] = 0, False
        elif side == 2:    # top border
            cut = max(int(round(y0 + frac * (y1 - y0))), 0)
            cut_image[:cut], cut_mask[:cut] = 0, False
        else:              # bottom border (close range: chair legs below the image)
            cut = max(int(round(y1 - frac * (y1 - y0))), 0)
            cut_image[cut:], cut_mask[cut:] = 0, False
    if cut_mask.sum() < 0.25 * mask.sum() or cut_mask.sum() < 50:
        return image, mask, box  # too little left: keep the whole view
    return cut_image, cut_mask, _box_of(cut_mask)


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A plain or smoothly varying colour patch (h, w, 3) float32 in [0, 255]."""
    c1, c2 = rng.uniform(0, 255, 3), rng.uniform(0, 255, 3)
    low = rng.uniform(0, 1, (int(rng.integers(2, 6)), int(rng.integers(2, 6)), 1))
    t = cv2.resize(low.astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)[..., None]
    return np.clip(c1 + np.clip(t, 0, 1) * (c2 - c1) * rng.uniform(0, 1), 0, 255).astype(np.float32)


def occlude(image: np.ndarray, mask: np.ndarray, box: np.ndarray, rng: np.random.Generator, max_frac: float):
    """Cover part of the object with a textured rectangle or ellipse entering from one side of its box."""
    h, w = mask.shape
    x0, y0, x1, y1 = box
    bw, bh = x1 - x0, y1 - y0
    region = np.zeros((h, w), np.uint8)
    side = int(rng.integers(4))
    depth = rng.uniform(0.1, max_frac)            # how far into the box the occluder reaches
    extent = rng.uniform(0.4, 1.3)                # its length along that side, fraction of the box side
    if side in (0, 1):
        ext, off = extent * bh, rng.uniform(-0.2, 0.8) * bh
        xa = x0 - 0.3 * bw if side == 0 else x1 - depth * bw
        xb = x0 + depth * bw if side == 0 else x1 + 0.3 * bw
        ya, yb = y0 + off - ext / 2, y0 + off + ext / 2
    else:
        ext, off = extent * bw, rng.uniform(-0.2, 0.8) * bw
        ya = y0 - 0.3 * bh if side == 2 else y1 - depth * bh
        yb = y0 + depth * bh if side == 2 else y1 + 0.3 * bh
        xa, xb = x0 + off - ext / 2, x0 + off + ext / 2
    pts = (int(round(xa)), int(round(ya))), (int(round(xb)), int(round(yb)))
    if rng.uniform() < 0.5:
        cv2.rectangle(region, *pts, 1, thickness=-1)
    else:
        centre = ((pts[0][0] + pts[1][0]) // 2, (pts[0][1] + pts[1][1]) // 2)
        axes = (max(abs(pts[1][0] - pts[0][0]) // 2, 1), max(abs(pts[1][1] - pts[0][1]) // 2, 1))
        cv2.ellipse(region, centre, axes, float(rng.uniform(-20, 20)), 0, 360, 1, thickness=-1)
    cover = region.astype(bool)
    left = mask & ~cover
    if left.sum() < 0.4 * mask.sum() or left.sum() < 50:
        return image, mask, box
    out = image.astype(np.float32)
    out[cover] = _texture(rng, h, w)[cover] * rng.uniform(0.5, 1.0)
    return out.astype(np.uint8), left, _box_of(left)


def mask_noise(mask: np.ndarray, rng: np.random.Generator, amplitude: float) -> np.ndarray:
    """A ragged boundary (smooth noise added to the signed distance), holes, or bleeding (dilation)."""
    kind = rng.uniform()
    m8 = mask.astype(np.uint8)
    if kind < 0.6:
        inside = cv2.distanceTransform(m8, cv2.DIST_L2, 3)
        outside = cv2.distanceTransform(1 - m8, cv2.DIST_L2, 3)
        sd = inside - outside
        cells = int(rng.integers(4, 12))
        noise = cv2.resize(rng.normal(size=(cells, cells)).astype(np.float32), mask.shape[::-1],
                           interpolation=cv2.INTER_CUBIC)
        noisy = sd + amplitude * rng.uniform(0.3, 1.0) * noise > 0
        return noisy if noisy.sum() >= 30 else mask
    if kind < 0.8:
        out = m8.copy()
        ys, xs = np.nonzero(mask)
        for _ in range(int(rng.integers(1, 5))):
            i = int(rng.integers(len(xs)))
            r = int(rng.integers(2, 7))
            cv2.circle(out, (int(xs[i]), int(ys[i])), r, 0, thickness=-1)
        return out.astype(bool) if out.sum() >= 30 else mask
    k = int(rng.integers(3, 8))
    return cv2.dilate(m8, np.ones((k, k), np.uint8)).astype(bool)


def degrade(x: np.ndarray, rng: np.random.Generator, aug: CropAugmentation) -> np.ndarray:
    """Blur, vignetting and exposure on a float32 crop (H, W, 3) in [0, 255]."""
    if aug.p_blur > 0 and rng.uniform() < aug.p_blur:
        if rng.uniform() < 0.5:
            x = cv2.GaussianBlur(x, (0, 0), float(rng.uniform(0.5, 2.0)))
        else:  # motion blur: a line kernel of random length and angle
            n = int(rng.integers(3, 10))
            k = np.zeros((n, n), np.float32)
            k[n // 2] = 1.0
            rot = cv2.getRotationMatrix2D(((n - 1) / 2, (n - 1) / 2), float(rng.uniform(0, 180)), 1.0)
            k = cv2.warpAffine(k, rot, (n, n))
            x = cv2.filter2D(x, -1, k / max(k.sum(), 1e-6))
    if aug.p_vignette > 0 and rng.uniform() < aug.p_vignette:
        h, w = x.shape[:2]
        yy, xx = np.mgrid[0:h, 0:w]
        centre = rng.uniform(0.2, 0.8, 2) * (w, h)
        r2 = ((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2) / (0.5 * max(h, w)) ** 2
        x = x * (1 - rng.uniform(0.1, 0.5) * np.clip(r2, 0, 2) / 2)[..., None]
    if aug.p_exposure > 0 and rng.uniform() < aug.p_exposure:
        x = 255.0 * (np.clip(x, 0, 255) / 255.0) ** rng.uniform(0.6, 1.6)
        x = x + rng.normal(scale=rng.uniform(2, 10), size=x.shape)
    return x


def augment_crop(image: np.ndarray, mask: np.ndarray, box: np.ndarray, rng: np.random.Generator, size: int = 128,
                 margin: float = 0.1, aug: CropAugmentation | None = None):
    """A perturbed detection crop: paper-style (jittered box, resolution, mask erosion/dilation, colour and
    noise; Sec. 5.2) plus, where `aug` enables them, the capture conditions of this module.

    image (S, S, 3) uint8, mask (S, S) bool, box (4,) -> (crop (size, size, 3) uint8, mask (size, size) bool).
    """
    aug = aug or CropAugmentation()
    if aug.p_truncate > 0 and rng.uniform() < aug.p_truncate:
        image, mask, box = truncate(image, mask, box, rng, aug.truncate_max)
    if aug.p_occlude > 0 and rng.uniform() < aug.p_occlude:
        image, mask, box = occlude(image, mask, box, rng, aug.occlude_max)
    w, h = box[2] - box[0], box[3] - box[1]
    b = box + rng.normal(scale=aug.jitter, size=4) * np.array([w, h, w, h])
    crop, cmask = square_crop(image, mask, b, size, margin)
    if rng.uniform() < 0.5:  # lower effective resolution (small detections are upsampled in the pipeline)
        low = int(rng.integers(40, size))
        crop = cv2.resize(cv2.resize(crop, (low, low), interpolation=cv2.INTER_AREA), (size, size),
                          interpolation=cv2.INTER_LINEAR)
    if rng.uniform() < 0.3:  # imperfect instance masks
        k = np.ones((3, 3), np.uint8)
        op = cv2.erode if rng.uniform() < 0.5 else cv2.dilate
        cmask = op(cmask.astype(np.uint8), k, iterations=int(rng.integers(1, 3))).astype(bool)
    if aug.p_mask_noise > 0 and cmask.any() and rng.uniform() < aug.p_mask_noise:
        cmask = mask_noise(cmask, rng, aug.mask_noise_px)
    x = crop.astype(np.float32)
    x = (x - x.mean()) * rng.uniform(0.7, 1.3) + x.mean() * rng.uniform(0.7, 1.3)
    x = x * rng.uniform(0.9, 1.1, 3) + rng.normal(scale=3.0, size=x.shape)
    x = degrade(x, rng, aug)
    return np.clip(x, 0, 255).astype(np.uint8), cmask
