"""Per-frame depth without ROS: the contract's encodings decoded, and which readings count as usable."""
import numpy as np

from frodo_common.frames import MIN_DEPTH, depth_to_metres, usable_depth


def test_usable_depth_keeps_readings_beyond_the_minimum_and_marks_the_rest_missing():
    metres = depth_to_metres(np.array([[0, 30, 50, 51, 1500]], np.uint16))     # millimetres
    usable = usable_depth(metres)
    assert usable.dtype == np.float32 and usable.shape == metres.shape
    assert np.isnan(usable[0, :3]).all()                  # none, nearer than and at MIN_DEPTH
    assert np.allclose(usable[0, 3:], [0.051, 1.5]) and MIN_DEPTH == 0.05
    assert np.isnan(usable_depth(np.array([np.nan, np.inf, -1.0]))).all()
