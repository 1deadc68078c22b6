"""Rerun viewer node: a live 3D/2D view of the graph (camera frames, detections, tracks, object meshes,
SLAM points, optional ground truth), streamed to a Rerun viewer or saved to an .rrd file.

Open a saved recording with `rerun FILE.rrd`; check one headlessly with `rerun rrd verify FILE.rrd`.
"""
from __future__ import annotations

import numpy as np
import rerun as rr
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from geometry_msgs.msg import PoseStamped
from visualization_msgs.msg import Marker, MarkerArray

from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.frame_cache import FrameCache
from frodo_common.geometry import matrix_to_quat
from frodo_common.node import FrodoNode, run_node
from frodo_common.params import ParamSpec

PARAMS = (
    ParamSpec('mode', 'save', "Where to send the recording: 'save' (rrd_path), 'spawn' (start a viewer), "
                              "'connect' (to a running viewer at connect_url)."),
    ParamSpec('rrd_path', 'frodo.rrd', "Recording file for mode 'save'."),
    ParamSpec('connect_url', 'rerun+http://127.0.0.1:9876/proxy', "gRPC URL for mode 'connect'."),
    ParamSpec('image_stride', 1, 'Log every n-th camera frame (keeps recordings small on long bags).'),
    ParamSpec('show_ground_truth', True, 'Show /ground_truth/objects (when a player publishes it).'),
)


class ViewerNode(FrodoNode):
    """Logs every FroDO topic to Rerun on a `stamp` timeline (seconds) and a `frame` sequence."""

    def __init__(self, **kwargs):
        super().__init__('viewer_node', PARAMS, **kwargs)
        rr.init('frodo')
        mode = self.params['mode']
        if mode == 'save':
            rr.save(self.params['rrd_path'])
        elif mode == 'spawn':
            rr.spawn()
        elif mode == 'connect':
            rr.connect_grpc(self.params['connect_url'])
        else:
            raise ValueError(f"mode must be 'save', 'spawn' or 'connect', got {mode!r}")
        rr.log('world', rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.frames = FrameCache(['image', 'pose'], 50)
        self.frame_index = 0
        self.shown_objects: set[str] = set()
        q = topics.FRAME_QOS
        self.create_subscription(CameraInfo, topics.CAMERA_INFO, self.guarded(self._on_info), q)
        self.create_subscription(Image, topics.IMAGE, self.guarded(lambda m: self._add(m, 'image')), q)
        self.create_subscription(PoseStamped, topics.POSE, self.guarded(lambda m: self._add(m, 'pose')), q)
        self.create_subscription(Image, topics.DETECTIONS, self.guarded(self._on_detections), q)
        self.create_subscription(PointCloud2, topics.SLAM_POINTS, self.guarded(self._on_slam), q)
        self.create_subscription(MarkerArray, topics.TRACKS, self.guarded(self._on_tracks), topics.LATCHED_QOS)
        self.create_subscription(MarkerArray, topics.OBJECTS, self.guarded(self._on_objects), topics.LATCHED_QOS)
        if self.params['show_ground_truth']:
            self.create_subscription(MarkerArray, topics.GROUND_TRUTH, self.guarded(self._on_ground_truth),
                                     topics.LATCHED_QOS)

    @staticmethod
    def _time(stamp) -> None:
        rr.set_time('stamp', timestamp=conv.stamp_to_ns(stamp) * 1e-9)

    def _on_info(self, msg: CameraInfo) -> None:
        self.frames.camera_info = msg

    def _add(self, msg, part: str) -> None:
        frame = self.frames.add(conv.stamp_to_ns(msg.header.stamp), part, msg)
        if frame is None or self.frames.camera_info is None:
            return
        self.frame_index += 1
        if (self.frame_index - 1) % max(int(self.params['image_stride']), 1):
            return
        self._time(msg.header.stamp)
        rr.set_time('frame', sequence=self.frame_index)
        T = conv.pose_to_matrix(frame.parts['pose'].pose)
        info = self.frames.camera_info
        rr.log('world/camera', rr.Transform3D(translation=T[:3, 3], quaternion=rr.Quaternion(xyzw=matrix_to_quat(T[:3, :3]))))
        rr.log('world/camera/image', rr.Pinhole(image_from_camera=conv.camera_info_to_K(info),
                                                resolution=[info.width, info.height],
                                                camera_xyz=rr.ViewCoordinates.RDF))
        rr.log('world/camera/image/rgb', rr.Image(conv.image_to_rgb(frame.parts['image'])))
        self.count('frames_logged')

    def _on_detections(self, msg: Image) -> None:
        self._time(msg.header.stamp)
        labels = conv.image_to_numpy(msg)
        rr.log('world/camera/image/detections', rr.SegmentationImage((labels >> 8).astype(np.uint16)))

    def _on_slam(self, msg: PointCloud2) -> None:
        self._time(msg.header.stamp)
        rr.log('world/slam_points', rr.Points3D(conv.cloud_to_xyz(msg), radii=0.01, colors=[180, 180, 180]))

    def _on_tracks(self, msg: MarkerArray) -> None:
        cubes = [m for m in msg.markers if m.type == Marker.CUBE and m.action == Marker.ADD]
        if not cubes:
            return
        self._time(cubes[0].header.stamp)
        boxes = [conv.marker_to_box(m) for m in cubes]
        rr.log('world/tracks', rr.Boxes3D(
            centers=[b[0] for b in boxes], sizes=[b[1] for b in boxes],
            rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], radians=b[2]) for b in boxes],
            labels=[f'{m.ns} {m.id}' for m in cubes]))

    @staticmethod
    def _entity(root: str, m: Marker) -> str:
        return f'{root}/{m.ns.replace(" ", "_")}_{m.id}'

    def _log_meshes(self, msg: MarkerArray, root: str, alpha: float) -> set[str]:
        logged = set()
        for m in msg.markers:
            path = self._entity(root, m)
            if m.action == Marker.DELETE:
                rr.log(path, rr.Clear(recursive=True))
            elif m.type == Marker.TRIANGLE_LIST and m.points:
                verts, faces = conv.marker_to_mesh(m)
                colour = [m.color.r, m.color.g, m.color.b, alpha]
                rr.log(path, rr.Mesh3D(vertex_positions=verts, triangle_indices=faces, albedo_factor=colour))
                logged.add(path)
        return logged

    def _on_objects(self, msg: MarkerArray) -> None:
        if msg.markers:
            self._time(msg.markers[0].header.stamp)
        logged = self._log_meshes(msg, 'world/objects', 1.0)
        deleted = {self._entity('world/objects', m) for m in msg.markers if m.action == Marker.DELETE}
        for path in self.shown_objects - logged - deleted:   # each message is the complete map (CONTRACT.md)
            rr.log(path, rr.Clear(recursive=True))
        self.shown_objects = logged
        self.count('maps_logged')

    def diagnostic_values(self) -> dict:
        return {'objects_shown': len(self.shown_objects)}

    def _on_ground_truth(self, msg: MarkerArray) -> None:
        for m in msg.markers:
            m.color.r, m.color.g, m.color.b = 0.5, 0.9, 0.5
        self._log_meshes(msg, 'world/ground_truth', 0.35)

    def on_shutdown(self) -> None:
        """Flush the recording so a saved .rrd is complete."""
        rr.disconnect()


def main(args=None) -> int:
    """Entry point of `viewer_node`."""
    return run_node(ViewerNode, args, threads=1)


if __name__ == '__main__':
    main()
