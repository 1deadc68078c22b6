"""Helpers for tests of the command line: small contract bags, stand-in nodes, polling."""
from __future__ import annotations

import os
import time
from typing import Callable

import numpy as np
from visualization_msgs.msg import MarkerArray

from frodo_bringup.graph import GraphNode
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.bag import BagWriter, qos_yaml

BAG_START_NS = 1_700_000_000_000_000_000

# Optimiser settings that make a whole demo-bag reconstruction take seconds (tests of wiring and outcomes, not
# of accuracy): few iterations, one dense start, coarse grids.
FAST_OPTIM_PARAMS = """
optim_node:
  ros__parameters:
    sparse_iterations: 4
    sparse_yaw_candidates: 8
    sparse_code_restarts: 0
    dense_iterations: 2
    dense_starts: 1
    dense_grid_resolution: 16
    mesh_resolution: 40
"""


def stub(name: str) -> GraphNode:
    """A graph entry running `frodo_bringup.stub_node` under the node name `name`."""
    return GraphNode(name, 'frodo_bringup.stub_node', 'frodo_bringup')


def write_contract_bag(path: str | os.PathLike, frames: int = 10, period: float = 0.1, ground_truth: bool = True,
                       width: int = 8, height: int = 6, instances: bool = False) -> list[int]:
    """A small contract bag (images, camera info, poses, optional ground truth, optional empty instance images:
    what `frodo run` needs with the `external` detection backend); returns the frame stamps."""
    stamps = [BAG_START_NS + int(i * period * 1e9) for i in range(frames)]
    K = np.array([[10.0, 0, width / 2], [0, 10.0, height / 2], [0, 0, 1]])
    with BagWriter(path) as bag:
        if ground_truth:
            bag.add_topic(topics.GROUND_TRUTH, 'visualization_msgs/msg/MarkerArray',
                          qos_yaml(transient_local=True, depth=1))
            vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
            marker = conv.mesh_to_marker(vertices, np.array([[0, 1, 2]]), 'chair', 1, stamps[0], 'world')
            bag.write(topics.GROUND_TRUTH, MarkerArray(markers=[marker]), stamps[0])
        for i, stamp in enumerate(stamps):
            image = np.full((height, width, 3), i % 256, np.uint8)
            bag.write(topics.CAMERA_INFO, conv.make_camera_info(K, width, height, stamp, 'camera'), stamp)
            bag.write(topics.IMAGE, conv.numpy_to_image(image, 'rgb8', stamp, 'camera'), stamp)
            bag.write(topics.POSE, conv.make_pose_stamped(np.eye(4), stamp, 'world'), stamp)
            if instances:
                bag.write(topics.INSTANCES, conv.numpy_to_image(np.zeros((height, width), np.uint16), '16UC1', stamp,
                                                                'camera'), stamp)
    return stamps


def wait_until(predicate: Callable[[], bool], timeout: float, period: float = 0.05) -> bool:
    """Poll `predicate` until it is true (returns True) or `timeout` seconds passed (returns False)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period)
    return predicate()
