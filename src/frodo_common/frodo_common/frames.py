"""Per-frame sensor data without ROS: the one depth decoder (contract v1.1 depth encodings)."""
from __future__ import annotations

import numpy as np


def depth_to_metres(depth: np.ndarray) -> np.ndarray:
    """Contract depth (16UC1 millimetres as uint16, or 32FC1 metres; 0 or NaN = none) as float32 metres with
    NaN = none. depth: (H, W) -> (H, W)."""
    d = np.asarray(depth).astype(np.float32)
    if np.asarray(depth).dtype == np.uint16:
        d /= 1000.0
    d[~(d > 0)] = np.nan
    return d
