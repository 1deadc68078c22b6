"""The Rerun recording of FroDO, live or offline, without ROS: entity layout, blueprint and logging calls.

`viewer_node` turns the graph's messages into calls of `FrodoRecording` (numpy in, Rerun out); `write_recording`
makes the same recording from a bag and an offline result (`frodo_bringup.pipeline.ObjectMap`). Open one with
`rerun FILE.rrd` (or drop it on https://rerun.io/viewer, the web viewer of the same version).

Time: everything sits on one `stamp` timeline of data time (the bag's or the sensor's stamps; the graph's nodes
stamp their outputs with the time of the frames they came from, never with the wall clock) plus a `frame`
sequence (the n-th camera frame; outputs stamped with a frame's stamp get its number). Rerun's own `log_time`
and `log_tick` timelines are off, so no wall-clock time line spreads the recording over today.

Entities (`ENTITIES`):

| entity | what |
|---|---|
| `world` | right-handed, z up (static) |
| `world/camera` | camera pose T_world_camera per frame; `world/camera/image` its pinhole, `.../rgb` the image |
| `world/camera/image/detections` | the frame's detections as a segmentation of classes (COCO ids; label 0 background, transparent) |
| `world/slam_points` | SLAM landmarks (grey) |
| `world/tracks` | the association's boxes, class-coloured, labelled `<class> <id>` |
| `world/associations` | per associated detection of a frame, a segment from the camera centre to the centre of the object it joined (class colour; pruned detections grey) |
| `world/objects/<class>_<id>` | the object's mesh, coloured by its stage (`STAGE_COLOURS`); `.../box` its box |
| `world/ground_truth/<class>_<id>` | ground-truth meshes (grey, translucent, static) |
| `plots/stage/<class>_<id>` | the object's stage over time: 0 fused, 1 sparse, 2 dense |
| `plots/views/<class>_<id>` | detections the object's estimate was made from |
| `plots/energy/<class>_<id>/<stage>` | the optimiser's total energy at the start and the end of the stage (offline: from the stage outcomes) |

Colours: meshes by stage, fused amber, sparse blue, dense green; detections and tracks by class
(`frodo_common.categories.Category.colour`: chair orange, dining table blue, ...); ground truth and SLAM
points grey.
"""
from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Mapping, Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from frodo_common.categories import CATEGORIES, category_by_id, category_by_name
from frodo_optim.states import STAGES   # ('fused', 'sparse', 'dense'); numpy only, no torch

if TYPE_CHECKING:   # the pipeline imports torch; write_recording imports it when called
    from frodo_bringup.pipeline import ObjectMap

STAMP = 'stamp'                 # timeline of data time (timestamps)
FRAME = 'frame'                 # sequence timeline: the n-th camera frame (1, 2, ...)

WORLD = 'world'
CAMERA = 'world/camera'
IMAGE = 'world/camera/image'
RGB = 'world/camera/image/rgb'
DETECTIONS = 'world/camera/image/detections'
SLAM_POINTS = 'world/slam_points'
TRACKS = 'world/tracks'
ASSOCIATIONS = 'world/associations'
OBJECTS = 'world/objects'
GROUND_TRUTH = 'world/ground_truth'
PLOTS = 'plots'
STAGE_PLOTS = 'plots/stage'
VIEW_PLOTS = 'plots/views'
ENERGY_PLOTS = 'plots/energy'
ENTITIES = (WORLD, CAMERA, IMAGE, RGB, DETECTIONS, SLAM_POINTS, TRACKS, ASSOCIATIONS, OBJECTS, GROUND_TRUTH,
            STAGE_PLOTS, VIEW_PLOTS, ENERGY_PLOTS)

STAGE_COLOURS = {'fused': (0.95, 0.75, 0.2), 'sparse': (0.25, 0.55, 0.95), 'dense': (0.2, 0.75, 0.35)}
GROUND_TRUTH_COLOUR = (0.6, 0.6, 0.6, 0.35)
SLAM_COLOUR = (0.7, 0.7, 0.7)
PRUNED_COLOUR = (0.6, 0.6, 0.6)
BACKGROUND = 0                               # the class of a pixel without detection (label 0)
UNKNOWN_COLOUR = (0.7, 0.7, 0.7)


@dataclass
class Track:
    """A box: the association's track or an object estimate's box. center (3,), size (3,), yaw about z."""

    object_id: int
    class_name: str
    center: np.ndarray
    size: np.ndarray
    yaw: float


@dataclass
class ObjectMesh:
    """One object of the map: world-frame mesh, its data time, and its stage when known (else the last stage
    `log_states` gave for it, or 'fused')."""

    object_id: int
    class_name: str
    vertices: np.ndarray
    faces: np.ndarray
    stamp_ns: int
    stage: str | None = None
    box: Track | None = None


@dataclass
class ObjectState:
    """An object's state: stage ('fused' | 'sparse' | 'dense'), views, and per stage the optimiser's total
    energies {'initial': e0, 'final': e1} where known."""

    object_id: int
    class_name: str
    stage: str
    num_views: int = 0
    energies: dict[str, dict[str, float]] = field(default_factory=dict)


def object_key(class_name: str, object_id: int) -> str:
    """Entity name of an object: `<class>_<id>` (spaces as underscores)."""
    return f'{class_name.replace(" ", "_")}_{int(object_id)}'


def _rgb255(colour, alpha: float = 1.0) -> list[int]:
    c = list(colour) + ([alpha] if len(colour) == 3 else [])
    return [int(round(255 * min(max(float(v), 0.0), 1.0))) for v in c]


def class_colour(class_name: str) -> tuple[float, float, float]:
    try:
        return category_by_name(class_name).colour
    except KeyError:
        return UNKNOWN_COLOUR


def annotation_context() -> rr.AnnotationContext:
    """Classes of the detections' segmentation: 0 background (transparent, no label), then every category by
    its COCO id with its name and colour."""
    infos = [rr.AnnotationInfo(id=BACKGROUND, label='background', color=[0, 0, 0, 0])]
    infos += [rr.AnnotationInfo(id=c.coco_id, label=c.name, color=_rgb255(c.colour)) for c in CATEGORIES]
    return rr.AnnotationContext([rr.ClassDescription(info=info) for info in infos])


def blueprint() -> rrb.Blueprint:
    """The layout: the 3D world on the left; the camera (image + detections) over the per-object plots (stage,
    views, energy) on the right; the time panel on the `stamp` timeline."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin=WORLD, name='world'),
            rrb.Vertical(
                rrb.Spatial2DView(origin=IMAGE, name='camera + detections'),
                rrb.Tabs(
                    rrb.TimeSeriesView(origin=STAGE_PLOTS, name='stage (0 fused, 1 sparse, 2 dense)',
                                       axis_y=rrb.ScalarAxis(range=(-0.2, 2.2))),
                    rrb.TimeSeriesView(origin=ENERGY_PLOTS, name='optimiser energy'),
                    rrb.TimeSeriesView(origin=VIEW_PLOTS, name='views'),
                ),
                row_shares=[3, 2]),
            column_shares=[3, 2]),
        rrb.TimePanel(timeline=STAMP),
        collapse_panels=False)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (unit length; zero for vertices of no face), so meshes render shaded."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    normals = np.zeros_like(v)
    if len(f):
        face_n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        for k in range(3):
            np.add.at(normals, f[:, k], face_n)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return (normals / np.where(length > 0, length, 1.0)).astype(np.float32)


class FrodoRecording:
    """A FroDO recording on one Rerun stream: `log_*` calls with plain data, each at a data stamp (ns).

    image_stride: log the image of every n-th frame only (the camera pose of every frame). Objects are given as
    the complete map each time (`log_objects`): objects missing from it are cleared."""

    def __init__(self, stream: rr.RecordingStream, image_stride: int = 1, frame_memory: int = 100_000):
        self.stream = stream
        self.image_stride = max(int(image_stride), 1)
        self.frame_memory = int(frame_memory)
        self.frames: OrderedDict[int, tuple[int, np.ndarray]] = OrderedDict()   # stamp -> (frame, camera centre)
        self.frame_count = 0
        self.stages: dict[str, str] = {}           # object key -> its last stage
        self.shown: dict[str, str] = {}            # object key -> entity of its shown mesh
        self.styled: set[str] = set()              # plot entities whose series style is logged
        stream.set_log_time_enabled(False)         # data time only: no wall-clock timeline
        stream.set_log_tick_enabled(False)
        self._static()

    # ------------------------------------------------------------ opening
    @classmethod
    def open(cls, mode: str = 'save', path: str | os.PathLike = 'frodo.rrd',
             url: str = 'rerun+http://127.0.0.1:9876/proxy', image_stride: int = 1,
             application_id: str = 'frodo') -> 'FrodoRecording':
        """A recording saved to `path` ('save'), shown in a new viewer ('spawn') or sent to a running one at
        `url` ('connect'), with the FroDO blueprint."""
        stream = rr.RecordingStream(application_id)
        if mode == 'save':
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            stream.save(str(path), default_blueprint=blueprint())
        elif mode == 'spawn':
            stream.spawn(default_blueprint=blueprint())
        elif mode == 'connect':
            stream.connect_grpc(url, default_blueprint=blueprint())
        else:
            raise ValueError(f"mode must be 'save', 'spawn' or 'connect', got {mode!r}")
        return cls(stream, image_stride)

    def close(self) -> None:
        """Flush and close the sink (a saved .rrd is complete afterwards)."""
        self.stream.flush()
        self.stream.disconnect()

    def _static(self) -> None:
        log = self.stream.log
        log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        log(DETECTIONS, annotation_context(), static=True)
        log(SLAM_POINTS, rr.Points3D.from_fields(colors=[_rgb255(SLAM_COLOUR)], radii=[0.01]), static=True)

    # ------------------------------------------------------------ time
    def frame_of(self, stamp_ns: int) -> int | None:
        """The frame number of a logged frame's stamp (None: no frame with that stamp)."""
        entry = self.frames.get(int(stamp_ns))
        return entry[0] if entry else None

    def at(self, stamp_ns: int) -> None:
        """Set the time of the next calls: `stamp` = stamp_ns, `frame` = its frame's number when it is one."""
        self.stream.reset_time()
        self.stream.set_time(STAMP, timestamp=np.datetime64(int(stamp_ns), 'ns'))
        frame = self.frame_of(stamp_ns)
        if frame is not None:
            self.stream.set_time(FRAME, sequence=frame)

    # ------------------------------------------------------------ per frame
    def log_frame(self, stamp_ns: int, K: np.ndarray, size: tuple[int, int], T_world_camera: np.ndarray,
                  rgb: np.ndarray | None) -> int:
        """A camera frame: pose, pinhole and (every image_stride-th frame) the image. Returns its number."""
        stamp_ns = int(stamp_ns)
        if stamp_ns not in self.frames:
            self.frame_count += 1
            self.frames[stamp_ns] = (self.frame_count, np.asarray(T_world_camera, float)[:3, 3].copy())
            while len(self.frames) > self.frame_memory:
                self.frames.popitem(last=False)
        number = self.frames[stamp_ns][0]
        self.at(stamp_ns)
        T = np.asarray(T_world_camera, float)
        self.stream.log(CAMERA, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        self.stream.log(IMAGE, rr.Pinhole(image_from_camera=np.asarray(K, float), resolution=[int(size[0]), int(size[1])],
                                          camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.4))
        if rgb is not None and (number - 1) % self.image_stride == 0:
            self.stream.log(RGB, rr.Image(np.ascontiguousarray(rgb)))
        return number

    def log_detections(self, stamp_ns: int, labels: np.ndarray) -> None:
        """A frame's instance image (contract encoding category * 256 + k) as a segmentation of classes."""
        number = self.frame_of(stamp_ns)
        if number is not None and (number - 1) % self.image_stride:
            return
        self.at(stamp_ns)
        classes = (np.asarray(labels).astype(np.uint16) >> 8).astype(np.uint16)
        self.stream.log(DETECTIONS, rr.SegmentationImage(classes, opacity=0.5, draw_order=1.0))

    def log_slam_points(self, stamp_ns: int, points: np.ndarray) -> None:
        """The SLAM map (N, 3) as of stamp_ns (each message the whole map)."""
        points = np.asarray(points, np.float32).reshape(-1, 3)
        self.at(stamp_ns)
        self.stream.log(SLAM_POINTS, rr.Points3D.from_fields(positions=points[np.isfinite(points).all(1)]))

    def log_associations(self, stamp_ns: int, rows: np.ndarray, camera_centre: np.ndarray | None = None) -> None:
        """A frame's association table (schemas.ASSOCIATION_DTYPE: x, y, z of the object each detection joined,
        label, object_id, kept): one segment per associated detection from the camera centre (the frame's, or
        `camera_centre`) to its object's centre. Nothing when the frame's camera is unknown."""
        if camera_centre is None:
            entry = self.frames.get(int(stamp_ns))
            if entry is None:
                return
            camera_centre = entry[1]
        strips, colours, labels = [], [], []
        for r in rows:
            centre = np.array([r['x'], r['y'], r['z']], np.float64)
            if int(r['object_id']) < 0 or not np.isfinite(centre).all():
                continue
            category = category_by_id(int(r['label']) >> 8)
            strips.append([np.asarray(camera_centre, float), centre])
            colours.append(_rgb255(category.colour if category and r['kept'] else PRUNED_COLOUR))
            labels.append(f'{int(r["object_id"])}')
        self.at(stamp_ns)
        self.stream.log(ASSOCIATIONS, rr.LineStrips3D(strips, colors=colours or None, radii=0.004, labels=labels or None,
                                                      show_labels=False))

    # ------------------------------------------------------------ map
    def log_tracks(self, stamp_ns: int, tracks: Sequence[Track]) -> None:
        """The association's current boxes (the complete set)."""
        self.at(stamp_ns)
        self.stream.log(TRACKS, self._boxes(tracks, radius=0.006))

    @staticmethod
    def _boxes(tracks: Sequence[Track], radius: float, colour=None) -> rr.Boxes3D:
        return rr.Boxes3D(
            centers=[np.asarray(t.center, float) for t in tracks], sizes=[np.asarray(t.size, float) for t in tracks],
            rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], radians=float(t.yaw)) for t in tracks],
            colors=[_rgb255(colour or class_colour(t.class_name)) for t in tracks],
            labels=[f'{t.class_name} {t.object_id}' for t in tracks], radii=radius)

    def log_objects(self, objects: Sequence[ObjectMesh], stamp_ns: int | None = None) -> set[str]:
        """The complete object map: each mesh at its own stamp, coloured by stage; objects shown before and not
        in it are cleared at stamp_ns (default: the newest object stamp). Returns the shown entities."""
        shown: dict[str, str] = {}
        for obj in objects:
            key = object_key(obj.class_name, obj.object_id)
            path = f'{OBJECTS}/{key}'
            if obj.stage is not None:
                self.stages[key] = obj.stage
            stage = self.stages.get(key, 'fused')
            vertices = np.asarray(obj.vertices, np.float32)
            faces = np.asarray(obj.faces, np.uint32)
            self.at(obj.stamp_ns)
            self.stream.log(path, rr.Mesh3D(vertex_positions=vertices, triangle_indices=faces,
                                            vertex_normals=vertex_normals(vertices, faces),
                                            albedo_factor=_rgb255(STAGE_COLOURS.get(stage, UNKNOWN_COLOUR))))
            if obj.box is not None:
                self.stream.log(f'{path}/box', self._boxes([obj.box], radius=0.004, colour=STAGE_COLOURS.get(stage)))
            shown[key] = path
        gone = [path for key, path in self.shown.items() if key not in shown]
        if gone:
            when = stamp_ns if stamp_ns is not None else max((o.stamp_ns for o in objects), default=0)
            self.at(when)
            for path in gone:
                self.stream.log(path, rr.Clear(recursive=True))
        self.shown = shown
        return set(shown.values())

    def log_boxes(self, stamp_ns: int, boxes: Iterable[Track]) -> None:
        """Boxes of the objects' estimates (/frodo/boxes), under each shown object."""
        for box in boxes:
            key = object_key(box.class_name, box.object_id)
            if key in self.shown:
                self.at(stamp_ns)
                colour = STAGE_COLOURS.get(self.stages.get(key, 'fused'))
                self.stream.log(f'{self.shown[key]}/box', self._boxes([box], radius=0.004, colour=colour))

    def log_states(self, stamp_ns: int, states: Iterable[ObjectState]) -> None:
        """Per object its stage, views and (where given) energies on the plots; a shown mesh whose stage changed
        takes the new stage's colour at stamp_ns."""
        self.at(stamp_ns)
        for state in states:
            key = object_key(state.class_name, state.object_id)
            stage_index = STAGES.index(state.stage) if state.stage in STAGES else -1
            self._style(f'{STAGE_PLOTS}/{key}', rr.SeriesLines(names=[key], colors=[_rgb255(class_colour(state.class_name))],
                                                                interpolation_mode='StepAfter'))
            self.stream.log(f'{STAGE_PLOTS}/{key}', rr.Scalars([float(stage_index)]))
            self._style(f'{VIEW_PLOTS}/{key}', rr.SeriesLines(names=[key], colors=[_rgb255(class_colour(state.class_name))]))
            self.stream.log(f'{VIEW_PLOTS}/{key}', rr.Scalars([float(state.num_views)]))
            for stage, energies in state.energies.items():
                values = [energies.get('initial', np.nan), energies.get('final', np.nan)]
                path = f'{ENERGY_PLOTS}/{key}/{stage}'
                self._style(path, rr.SeriesPoints(names=[f'{key} {stage} initial', f'{key} {stage} final'],
                                                  colors=[_rgb255(STAGE_COLOURS.get(stage, UNKNOWN_COLOUR), 0.5),
                                                          _rgb255(STAGE_COLOURS.get(stage, UNKNOWN_COLOUR))],
                                                  markers=['Circle', 'Diamond'], marker_sizes=[4.0, 6.0]))
                self.stream.log(path, rr.Scalars([float(v) for v in values]))
            if self.stages.get(key) != state.stage:
                self.stages[key] = state.stage
                if key in self.shown:
                    colour = _rgb255(STAGE_COLOURS.get(state.stage, UNKNOWN_COLOUR))
                    self.stream.log(self.shown[key], rr.Mesh3D.from_fields(albedo_factor=colour))

    def _style(self, path: str, series) -> None:
        if path not in self.styled:
            self.stream.log(path, series, static=True)
            self.styled.add(path)

    def log_ground_truth(self, objects: Iterable[tuple[int, str, np.ndarray, np.ndarray]]) -> None:
        """Ground-truth meshes (id, class, world vertices, faces), static, grey and translucent."""
        for oid, class_name, vertices, faces in objects:
            vertices = np.asarray(vertices, np.float32)
            faces = np.asarray(faces, np.uint32)
            self.stream.log(f'{GROUND_TRUTH}/{object_key(class_name, oid)}',
                            rr.Mesh3D(vertex_positions=vertices, triangle_indices=faces,
                                      vertex_normals=vertex_normals(vertices, faces),
                                      albedo_factor=_rgb255(GROUND_TRUTH_COLOUR)), static=True)


# ------------------------------------------------------------------ offline
def write_recording(bag_path: str | os.PathLike, object_map: 'ObjectMap', rrd_path: str | os.PathLike, *,
                    tracks: Mapping[int, tuple[str, tuple]] | None = None,
                    associations: Mapping[int, np.ndarray] | None = None,
                    image_stride: int = 1) -> Path:
    """Write the recording of an offline reconstruction to `rrd_path` (returned): the bag's frames (camera,
    image, its `/camera/instances` as detections, SLAM points), ground truth when the bag has it, and the
    object map's final estimates (mesh by stage, box) at their data time (`ObjectEstimate.stamp_ns`, the
    newest frame each used; the last frame's stamp when unknown), with each object's stage outcomes on the
    plots (stage, views, sparse/dense energies).

    Optional: `tracks` {id: (class, (centre, size, yaw))}, the association's final boxes (as `Scene.tracks`),
    logged at the last frame; `associations` {stamp: ASSOCIATION_DTYPE rows}, the association of each frame.
    """
    from frodo_bringup.pipeline import bag_frames
    from frodo_common import topics
    from frodo_common.bag import BagReader

    reader = BagReader(bag_path)
    recording = FrodoRecording.open('save', rrd_path, image_stride=image_stride)
    try:
        if topics.GROUND_TRUTH in reader.topics():
            from frodo_common.evaluation import EvaluationError, load_ground_truth_bag
            try:
                gt = load_ground_truth_bag(bag_path)
            except EvaluationError:
                gt = []
            recording.log_ground_truth((o.id, o.class_name, o.mesh.vertices, o.mesh.faces) for o in gt)
        landmarks, first, last = None, None, None
        for frame in bag_frames(reader, need_instances=False):
            recording.log_frame(frame.stamp, frame.K, frame.size, frame.T_world_camera, frame.rgb)
            first = frame.stamp if first is None else first
            last = frame.stamp
            if frame.instances is not None:
                recording.log_detections(frame.stamp, frame.instances)
            if frame.landmarks is not None and frame.landmarks is not landmarks:
                recording.log_slam_points(frame.stamp, frame.landmarks)
                landmarks = frame.landmarks
            if associations is not None and frame.stamp in associations:
                recording.log_associations(frame.stamp, associations[frame.stamp])
        if last is None:
            raise ValueError(f'{bag_path}: no complete frame (image, pose, camera info) to record')
        if tracks:
            recording.log_tracks(last, [Track(oid, name, *box) for oid, (name, box) in sorted(tracks.items())])
        meshes, states = [], {}
        for oid in sorted(object_map.estimates):
            est = object_map.estimates[oid]
            stamp = int(est.stamp_ns) or last
            center, size, yaw = est.box
            meshes.append(ObjectMesh(oid, est.class_name, est.mesh_world.vertices, est.mesh_world.faces, stamp,
                                     est.stage, Track(oid, est.class_name, center, size, yaw)))
            outcome = object_map.outcomes.get(oid)
            energies = {s.stage: dict(getattr(s, 'energies', {}) or {}) for s in (outcome.stages if outcome else ())
                        if getattr(s, 'energies', None)}
            states.setdefault(stamp, []).append(ObjectState(oid, est.class_name, est.stage, int(est.num_views),
                                                            energies))
        recording.log_objects(meshes, last)
        for stamp in sorted(states):
            recording.log_states(stamp, states[stamp])
    finally:
        recording.close()
    return Path(rrd_path)
