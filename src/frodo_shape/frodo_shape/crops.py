"""Object crops for the image encoder (paper Sec. 5.2): square, padded crops around a detection box."""
from __future__ import annotations

import cv2
import numpy as np


def square_crop(image: np.ndarray, mask: np.ndarray, bbox, size: int = 128, margin: float = 0.1):
    """Crop a square window around `bbox` (x0, y0, x1, y1), padding with zeros outside the image.

    image: (H, W, 3) uint8; mask: (H, W) bool. Returns (crop (size, size, 3) uint8, mask (size, size) bool).
    The window side is the box's longer side times (1 + 2 * margin), centred on the box.
    """
    x0, y0, x1, y1 = (float(v) for v in bbox)
    side = max(x1 - x0, y1 - y0, 2.0) * (1 + 2 * margin)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    # Affine map from the crop window to the output square (handles borders by constant padding).
    scale = size / side
    A = np.array([[scale, 0, size / 2 - scale * cx], [0, scale, size / 2 - scale * cy]], dtype=np.float64)
    crop = cv2.warpAffine(image, A, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    crop_mask = cv2.warpAffine(mask.astype(np.uint8), A, (size, size), flags=cv2.INTER_NEAREST,
                               borderMode=cv2.BORDER_CONSTANT).astype(bool)
    return crop, crop_mask
