"""Default topic names (CONTRACT.md and docs/ARCHITECTURE.md) and the QoS profiles they use.

The names import without ROS (the offline pipeline and the configs use them); the QoS profiles `FRAME_QOS` and
`LATCHED_QOS` are built from rclpy on first use."""
from __future__ import annotations

# Contract inputs.
IMAGE = '/camera/color/image_raw'
CAMERA_INFO = '/camera/color/camera_info'
POSE = '/camera/pose'
INSTANCES = '/camera/instances'
DEPTH = '/camera/depth/image_raw'       # optional (v1.1): registered to colour, 16UC1 mm or 32FC1 m
SLAM_POINTS = '/slam/points'
GROUND_TRUTH = '/ground_truth/objects'
# Contract outputs.
OBJECTS = '/frodo/objects'
BOXES = '/frodo/boxes'
DIAGNOSTICS = '/diagnostics'
# Internal topics.
DETECTIONS = '/frodo/detections'
ASSOCIATIONS = '/frodo/associations'
TRACKS = '/frodo/tracks'
CODES = '/frodo/codes'
OBJECT_CODES = '/frodo/object_codes'
# Several optimiser workers: worker k >= 1 publishes its share of the object map under this prefix, worker 0
# merges the shares into the complete map of the contract topics (frodo_optim.merge; see object_share_topic).
OBJECT_SHARES = '/frodo/internal/object_shares'

def __getattr__(name: str):
    """FRAME_QOS: per-frame sensor streams, reliable so a bag played fast loses nothing, deep queue for bursts.
    LATCHED_QOS: latched state (object map, boxes, tracks, fused codes), late joiners get the latest message."""
    if name not in ('FRAME_QOS', 'LATCHED_QOS'):
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    profiles = {
        'FRAME_QOS': QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST),
        'LATCHED_QOS': QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                  durability=DurabilityPolicy.TRANSIENT_LOCAL, history=HistoryPolicy.KEEP_LAST),
    }
    globals().update(profiles)    # built once
    return profiles[name]

def object_share_topic(kind: str, worker: int) -> str:
    """Internal topic of optimiser worker `worker`'s share of `kind` ('objects', 'boxes' or 'object_states'),
    e.g. /frodo/internal/object_shares/worker_1/objects. One topic per worker and kind, latched (LATCHED_QOS):
    transient-local history is kept per writer, so one writer per topic makes a (re)started merger get every
    worker's last share, even with a depth-1 queue."""
    return f'{OBJECT_SHARES}/worker_{int(worker)}/{kind}'
