"""Rerun viewer node: a live 3D/2D view of the graph (camera frames, detections, association tracks and segments,
object meshes by stage, SLAM points, optional ground truth, per-object stage plots), streamed to a Rerun viewer
or saved to an .rrd file. Messages in, `frodo_bringup.recording.FrodoRecording` calls out: the entity layout,
colours and blueprint live there (and `write_recording` makes the same recording offline).

Everything is logged at its message's stamp (data time: the nodes stamp outputs with their frames' stamps), so
the `stamp` timeline spans the bag's time only. Open a saved recording with `rerun FILE.rrd`; check one
headlessly with `rerun rrd verify FILE.rrd`.
"""
from __future__ import annotations

from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from visualization_msgs.msg import Marker, MarkerArray

from frodo_bringup.recording import FrodoRecording, ObjectMesh, ObjectState, Track
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.categories import category_by_id
from frodo_common.frame_cache import FrameCache
from frodo_common.marker_wire import read_marker_array
from frodo_common.node import FrodoNode, run_node
from frodo_common.params import ParamSpec
from frodo_optim.states import OBJECT_STATES, STAGES

PARAMS = (
    ParamSpec('mode', 'save', "Where to send the recording: 'save' (rrd_path), 'spawn' (start a viewer), "
                              "'connect' (to a running viewer at connect_url)."),
    ParamSpec('rrd_path', 'frodo.rrd', "Recording file for mode 'save'."),
    ParamSpec('connect_url', 'rerun+http://127.0.0.1:9876/proxy', "gRPC URL for mode 'connect'."),
    ParamSpec('image_stride', 1, 'Log every n-th camera frame (keeps recordings small on long bags).'),
    ParamSpec('show_ground_truth', True, 'Show /ground_truth/objects (when a player publishes it).'),
)


def _stamp(markers) -> int | None:
    stamps = [conv.stamp_to_ns(m.header.stamp) for m in markers]
    return max(stamps) if stamps else None


def _boxes(msg: MarkerArray) -> list[Track]:
    return [Track(m.id, m.ns, *conv.marker_to_box(m)) for m in msg.markers
            if m.type == Marker.CUBE and m.action == Marker.ADD]


class ViewerNode(FrodoNode):
    """Logs every FroDO topic to Rerun on a `stamp` timeline (data time) and a `frame` sequence."""

    def __init__(self, **kwargs):
        super().__init__('viewer_node', PARAMS, **kwargs)
        self.recording = FrodoRecording.open(self.params['mode'], self.params['rrd_path'], self.params['connect_url'],
                                             int(self.params['image_stride']))
        self.frames = FrameCache(['image', 'pose'], 50)
        self.shown_objects: set[str] = set()
        q = topics.FRAME_QOS
        self.create_subscription(CameraInfo, topics.CAMERA_INFO, self.guarded(self._on_info), q)
        self.create_subscription(Image, topics.IMAGE, self.guarded(lambda m: self._add(m, 'image')), q)
        self.create_subscription(PoseStamped, topics.POSE, self.guarded(lambda m: self._add(m, 'pose')), q)
        self.create_subscription(Image, topics.DETECTIONS, self.guarded(self._on_detections), q)
        self.create_subscription(PointCloud2, topics.SLAM_POINTS, self.guarded(self._on_slam), q)
        self.create_subscription(PointCloud2, topics.ASSOCIATIONS, self.guarded(self._on_associations), q)
        latched = topics.LATCHED_QOS
        self.create_subscription(MarkerArray, topics.TRACKS, self.guarded(self._on_tracks), latched)
        self.create_subscription(MarkerArray, topics.OBJECTS, self.guarded(self._on_objects), latched, raw=True)
        self.create_subscription(MarkerArray, topics.BOXES, self.guarded(self._on_boxes), latched)
        self.create_subscription(PointCloud2, OBJECT_STATES, self.guarded(self._on_states), latched)
        if self.params['show_ground_truth']:
            self.create_subscription(MarkerArray, topics.GROUND_TRUTH, self.guarded(self._on_ground_truth), latched)

    def _on_info(self, msg: CameraInfo) -> None:
        first = self.frames.camera_info is None
        self.frames.camera_info = msg
        if first:   # frames completed before the first camera info (another topic, delivered later) were held
            for frame in self.frames.complete_frames():
                self._log_frame(frame)

    def _add(self, msg, part: str) -> None:
        frame = self.frames.add(conv.stamp_to_ns(msg.header.stamp), part, msg)
        if frame is not None and self.frames.camera_info is not None:
            self._log_frame(frame)

    def _log_frame(self, frame) -> None:
        info = self.frames.camera_info
        due = self.recording.frame_count % self.recording.image_stride == 0   # decode only logged images
        self.recording.log_frame(frame.stamp_ns, conv.camera_info_to_K(info), (info.width, info.height),
                                 conv.pose_to_matrix(frame.parts['pose'].pose),
                                 conv.image_to_rgb(frame.parts['image']) if due else None)
        self.frames.frames.pop(frame.stamp_ns, None)
        self.count('frames_logged')

    def _on_detections(self, msg: Image) -> None:
        self.recording.log_detections(conv.stamp_to_ns(msg.header.stamp), conv.image_to_numpy(msg))

    def _on_slam(self, msg: PointCloud2) -> None:
        self.recording.log_slam_points(conv.stamp_to_ns(msg.header.stamp), conv.cloud_to_xyz(msg))

    def _on_associations(self, msg: PointCloud2) -> None:
        self.recording.log_associations(conv.stamp_to_ns(msg.header.stamp), conv.cloud_to_table(msg))

    def _on_tracks(self, msg: MarkerArray) -> None:
        stamp = _stamp(msg.markers)
        if stamp is not None:          # each message is the complete set of tracks
            self.recording.log_tracks(stamp, _boxes(msg))

    def _on_objects(self, raw: bytes) -> None:
        """Each message is the complete map (CONTRACT.md): objects missing from it are cleared. Read from its
        serialised form with the points as arrays (`marker_wire`): as Point messages every map cost ~0.5 s of
        CPU, taken from the optimiser on a small machine."""
        markers = read_marker_array(raw)
        meshes = []
        for m, points in markers:
            if m.action == Marker.ADD and m.type == Marker.TRIANGLE_LIST and len(points):
                vertices, faces = conv.marker_to_mesh(m, points)
                meshes.append(ObjectMesh(m.id, m.ns, vertices, faces, conv.stamp_to_ns(m.header.stamp)))
        self.shown_objects = self.recording.log_objects(meshes, _stamp([m for m, _ in markers]))
        self.count('maps_logged')

    def _on_boxes(self, msg: MarkerArray) -> None:
        stamp = _stamp(msg.markers)
        if stamp is not None:
            self.recording.log_boxes(stamp, _boxes(msg))

    def _on_states(self, msg: PointCloud2) -> None:
        states = []
        for row in conv.cloud_to_table(msg):
            category = category_by_id(int(row['category']))
            stage = int(row['stage'])
            states.append(ObjectState(int(row['object_id']), category.name if category else str(int(row['category'])),
                                      STAGES[stage] if stage < len(STAGES) else str(stage), int(row['num_views'])))
        self.recording.log_states(conv.stamp_to_ns(msg.header.stamp), states)

    def _on_ground_truth(self, msg: MarkerArray) -> None:
        self.recording.log_ground_truth((m.id, m.ns, *conv.marker_to_mesh(m)) for m in msg.markers
                                        if m.action == Marker.ADD and m.type == Marker.TRIANGLE_LIST and m.points)

    def diagnostic_values(self) -> dict:
        return {'objects_shown': len(self.shown_objects)}

    def on_shutdown(self) -> None:
        """Flush the recording so a saved .rrd is complete."""
        self.recording.close()


def main(args=None) -> int:
    """Entry point of `viewer_node`."""
    return run_node(ViewerNode, args, threads=1)


if __name__ == '__main__':
    main()
