"""Association node (paper Sec. 5.1; supplement "DP-mean based Line Segment Clustering", "Detection Pruning"):
per-frame detections -> object ids, 3D boxes and kept flags.

In:  /frodo/detections (16UC1 instance image), /camera/color/camera_info, /camera/pose (matched by stamp);
     optional: /camera/depth/image_raw (contract v1.1, registered, 16UC1 mm or 32FC1 m; kept by stamp, used
     when it came before its frame's detections) and /slam/points (the latest map): per detection the
     visible-surface depth inside its mask (`evidence.surface_depths`) fixes depth along its ray.
Out: /frodo/associations (PointCloud2 table, ASSOCIATION_DTYPE, the frame's stamp; re-sent with the original
     stamp when a frame's ids or kept flags change), /frodo/tracks (latched MarkerArray: one CUBE per published
     object, ns = class, id = object id; DELETE for objects merged away or withdrawn).
When no frame came for settle_after s, the association settles (`Associator.settle`) and publishes the result.
Frames with missing or invalid camera info / pose / detections are counted, reported and skipped.
"""
from __future__ import annotations

import time
from collections import OrderedDict, deque
from dataclasses import fields
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from visualization_msgs.msg import MarkerArray

from frodo_association.config import CONFIG_DOC, EVIDENCE_DOC, AssociationConfig, EvidenceConfig
from frodo_association.frames import FrameAssociator, config_from_values
from frodo_common.frames import depth_to_metres
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.categories import category_by_id
from frodo_common.frame_cache import FrameCache
from frodo_common.node import FrodoNode, run_node
from frodo_common.params import ParamSpec

PARAMS: tuple[ParamSpec, ...] = tuple(
    ParamSpec(f.name, getattr(AssociationConfig(), f.name), CONFIG_DOC[f.name]) for f in fields(AssociationConfig)) + tuple(
    ParamSpec(f.name, getattr(EvidenceConfig(), f.name), EVIDENCE_DOC[f.name]) for f in fields(EvidenceConfig)) + (
    ParamSpec('match_timeout', 2.0, 'Seconds (of stamp time) a frame waits for its missing part (detections or '
              'pose) once a newer frame is complete; then it is dropped and reported.'),
    ParamSpec('settle_after', 2.0, 'Seconds (wall clock) without a new frame after which the association settles '
              '(`Associator.settle`: a full pass, merges, and clusters still in view published on their consistent '
              'detections, as at the end of the input offline); 0: never.'),
    ParamSpec('camera_info_topic', topics.CAMERA_INFO, 'Camera intrinsics topic.'),
    ParamSpec('pose_topic', topics.POSE, 'Camera pose topic (T_world_camera, optical frame).'),
    ParamSpec('depth_topic', topics.DEPTH, "Optional registered depth (16UC1 mm or 32FC1 m) giving "
              "detections a visible-surface depth; '' disables."),
    ParamSpec('slam_points_topic', topics.SLAM_POINTS, "Optional SLAM landmarks (whole map per message) giving "
              "detections without depth a visible-surface depth; '' disables."),
)


class AssociationNode(FrodoNode):
    """Associates each frame's detections as soon as its detections and pose are in (and camera info is known)."""

    def __init__(self, **kwargs):
        super().__init__('association_node', PARAMS, **kwargs)
        p = self.params
        self.frame_associator = FrameAssociator(*config_from_values(p))
        self.associator = self.frame_associator.associator
        self.cache = FrameCache(('detections', 'pose'), int(p['frame_cache_size']))
        self.waiting: list[int] = []            # complete frames waiting for the first camera info
        self.latency_ms: deque[float] = deque(maxlen=200)   # recent add_frame times
        self.refine_ms: deque[float] = deque(maxlen=200)    # recent refine_boxes times
        self.evidence_ms: deque[float] = deque(maxlen=200)  # recent surface-depth times (frames with evidence)
        self.depth_cache: OrderedDict[int, np.ndarray] = OrderedDict()   # stamp -> depth (m, NaN = none)
        self.slam_points: np.ndarray | None = None
        self.sent_tracks: dict[int, str] = {}   # object id -> class name of the tracks last published
        self.last_frame_at: float | None = None   # monotonic time of the last associated frame, None: settled
        self.last_stamp = 0
        self.tracks_pub = self.create_publisher(MarkerArray, topics.TRACKS, topics.LATCHED_QOS)
        self.assoc_pub = self.create_publisher(PointCloud2, topics.ASSOCIATIONS, topics.FRAME_QOS)
        self.create_subscription(Image, topics.DETECTIONS, self.guarded(self._on_detections, 'detections'),
                                 topics.FRAME_QOS)
        self.create_subscription(PoseStamped, p['pose_topic'], self.guarded(self._on_pose, 'pose'), topics.FRAME_QOS)
        self.create_subscription(CameraInfo, p['camera_info_topic'], self.guarded(self._on_camera_info, 'camera_info'),
                                 topics.FRAME_QOS)
        if p['depth_topic']:
            self.create_subscription(Image, p['depth_topic'], self.guarded(self._on_depth, 'depth'), topics.FRAME_QOS)
        if p['slam_points_topic']:
            self.create_subscription(PointCloud2, p['slam_points_topic'], self.guarded(self._on_slam_points, 'slam_points'),
                                     topics.FRAME_QOS)
        if p['settle_after'] > 0:
            self.create_timer(min(0.5, p['settle_after']), self.guarded(self._settle_when_idle, 'settle'))

    # ------------------------------------------------------------ inputs
    def _on_detections(self, msg: Image) -> None:
        self.count('frames_received')
        self._add(conv.stamp_to_ns(msg.header.stamp), 'detections', msg)

    def _on_pose(self, msg: PoseStamped) -> None:
        self.count('poses_received')
        self._add(conv.stamp_to_ns(msg.header.stamp), 'pose', msg)

    def _on_depth(self, msg: Image) -> None:
        """Registered depth, kept by stamp (the latest 64) until its frame is associated."""
        self.count('depth_received')
        if msg.encoding not in ('16UC1', '32FC1'):
            raise conv.ConversionError(f'depth encoding must be 16UC1 (mm) or 32FC1 (m), got {msg.encoding!r}')
        self.depth_cache[conv.stamp_to_ns(msg.header.stamp)] = depth_to_metres(conv.image_to_numpy(msg))
        while len(self.depth_cache) > 64:
            self.depth_cache.popitem(last=False)

    def _on_slam_points(self, msg: PointCloud2) -> None:
        points = conv.cloud_to_xyz(msg)
        self.slam_points = points[np.isfinite(points).all(1)] if len(points) else points
        self.count('slam_maps_received')

    def _on_camera_info(self, msg: CameraInfo) -> None:
        K = conv.camera_info_to_K(msg)           # raises on invalid intrinsics: reported, the old info stays
        self.cache.camera_info = (K, (int(msg.width), int(msg.height)))
        waiting, self.waiting = self.waiting, []
        for stamp in waiting:
            frame = self.cache.get(stamp)
            if frame is not None:
                self._process(frame)

    def _add(self, stamp: int, part: str, msg) -> None:
        frame = self.cache.add(stamp, part, msg)
        if frame is None:
            return
        if self.cache.camera_info is None:
            self.waiting.append(stamp)
            self.count('frames_waiting_for_camera_info')
            self.report_error(f'frame {stamp}', f'no camera info yet on {self.params["camera_info_topic"]}; '
                              'frame held until it arrives', counter='warnings')
            return
        self._process(frame)
        self._expire(stamp)

    def _expire(self, now: int) -> None:
        """Drop held frames older than match_timeout before `now` that are still incomplete."""
        limit = now - int(self.params['match_timeout'] * 1e9)
        for stamp in [s for s, f in self.cache.frames.items() if s < limit and not f.has(self.cache.required)]:
            frame = self.cache.frames.pop(stamp)
            if 'detections' in frame.parts:
                self.count('frames_dropped')
                self.report_error(f'frame {stamp}', f'no pose received on {self.params["pose_topic"]}')
            else:
                self.count('poses_without_detections')

    # ------------------------------------------------------------ processing
    def _process(self, frame) -> None:
        """Associate one complete frame and publish its rows (and whatever earlier frames and tracks changed)."""
        stamp = frame.stamp_ns
        det_msg, pose_msg = frame.parts['detections'], frame.parts['pose']
        K, size = self.cache.camera_info
        try:
            if det_msg.encoding != '16UC1':
                raise conv.ConversionError(f'detections encoding must be 16UC1, got {det_msg.encoding!r}')
            instances = conv.image_to_numpy(det_msg)
            if instances.shape != (size[1], size[0]):
                raise conv.ConversionError(f'detections {instances.shape[1]}x{instances.shape[0]} do not match '
                                           f'camera_info {size[0]}x{size[1]}')
            T_world_camera = conv.pose_to_matrix(pose_msg.pose)
        except conv.ConversionError as err:
            self.count('frames_dropped')
            self.report_error(f'frame {stamp}', err)
            self.cache.frames.pop(stamp, None)
            return
        depth = self.depth_cache.pop(stamp, None)
        if depth is not None and depth.shape != instances.shape:
            self.report_error(f'frame {stamp}', f'depth {depth.shape[1]}x{depth.shape[0]} is not registered to the '
                              f'detections {instances.shape[1]}x{instances.shape[0]}; not used', counter='warnings')
            depth = None
        result = self.frame_associator.add(stamp, K, T_world_camera, size, instances, depth, self.slam_points)
        if result.evidence_ms is not None:
            self.evidence_ms.append(result.evidence_ms)
            self.count('frames_with_depth' if depth is not None else 'frames_with_landmarks')
        self.latency_ms.append(result.association_ms)
        self.refine_ms.append(result.refine_ms)
        self.cache.frames.pop(stamp, None)       # processed: free the images (the stamp stays marked complete)
        frame_id = self.params['world_frame']
        self.assoc_pub.publish(self._table_msg(result.update.table, stamp, frame_id))
        self.count('frames_published')
        self._republish(result.republish, frame_id)
        update = result.update
        self.count('merges', sum(1 for v in update.removed.values() if v >= 0))
        if result.tracks_changed:
            self._publish_tracks(stamp, frame_id)
        self.last_frame_at, self.last_stamp = time.monotonic(), stamp

    def _settle_when_idle(self) -> None:
        """After settle_after s without frames: settle once and publish what changed (rows, tracks)."""
        if self.last_frame_at is None or time.monotonic() - self.last_frame_at < self.params['settle_after']:
            return
        self.last_frame_at = None
        update = self.associator.settle()
        frame_id = self.params['world_frame']
        self._republish(update.republish, frame_id)
        self.count('merges', sum(1 for v in update.removed.values() if v >= 0))
        self.count('settled')
        self._publish_tracks(self.last_stamp, frame_id)

    def _table_msg(self, table: np.ndarray, stamp: int, frame_id: str) -> PointCloud2:
        msg = conv.table_to_cloud(table, stamp, frame_id)
        msg.is_dense = bool(np.all(table['object_id'] >= 0))    # unassociated rows carry NaN centres
        return msg

    def _republish(self, stamps: list[int], frame_id: str) -> None:
        for s in sorted(stamps):
            self.assoc_pub.publish(self._table_msg(self.associator.frame_table(s), s, frame_id))
        self.count('frames_republished', len(stamps))

    def _publish_tracks(self, stamp: int, frame_id: str) -> None:
        """The complete current object map (every published object with a box) plus a DELETE for each object
        sent before that is gone (merged away or withdrawn)."""
        markers = []
        current: dict[int, str] = {}
        for t in self.associator.confirmed_tracks():
            if t.box is not None:
                current[t.object_id] = category_by_id(t.coco_id).name
                markers.append(conv.box_to_marker(t.box.center, t.box.size, t.box.yaw, current[t.object_id],
                                                  t.object_id, stamp, frame_id))
        for oid, name in self.sent_tracks.items():
            if oid not in current:
                markers.append(conv.delete_marker(name, oid, stamp, frame_id))
        self.sent_tracks = current
        self.tracks_pub.publish(MarkerArray(markers=markers))
        self.count('tracks_published')

    def diagnostic_values(self) -> dict[str, Any]:
        lat = self.latency_ms
        fmt = lambda d, f: f'{f(d):.2f}' if d else 'n/a'       # noqa: E731
        return {'objects': len(self.associator.confirmed_tracks()), 'clusters': len(self.associator.tracks),
                'detections': len(self.associator.rows), 'frames_cached': len(self.cache),
                'frames_unmatched': self.cache.evicted_incomplete,
                'association_ms_mean': fmt(lat, np.mean), 'association_ms_max': fmt(lat, np.max),
                'refine_ms_mean': fmt(self.refine_ms, np.mean), 'refine_ms_max': fmt(self.refine_ms, np.max),
                'evidence_ms_mean': fmt(self.evidence_ms, np.mean)}


def main(args=None) -> int:
    """Entry point of `association_node`."""
    return run_node(AssociationNode, args)


if __name__ == '__main__':
    main()
