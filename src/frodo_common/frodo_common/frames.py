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


MIN_DEPTH = 0.05    # metres: nearer readings are sensor noise (a camera sees nothing this close)


def usable_depth(depth_m: np.ndarray) -> np.ndarray:
    """Registered depth in metres (H, W) as float32 with NaN wherever there is no usable reading (none, NaN,
    or nearer than MIN_DEPTH)."""
    d = np.asarray(depth_m, dtype=np.float32)
    return np.where(np.isfinite(d) & (d > MIN_DEPTH), d, np.nan).astype(np.float32)
