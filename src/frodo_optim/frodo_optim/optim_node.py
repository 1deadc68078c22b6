"""Optimiser node: turns tracks (3D boxes) and fused shape codes into placed object meshes, asynchronously
(paper Sec. 5.3). Stage 'fused': decode + box-fit placement (frodo_optim.core); stage 'sparse': yaw search
and joint code/pose optimisation against the object's masks and SLAM points (frodo_optim.sparse), published
after the fused result of the same pass; stage 'dense': code + 7-DoF pose on the SDF decoder against masks,
colours, landmarks and (optional) depth (frodo_optim.dense), published after the sparse result.

In:  /frodo/tracks (latched MarkerArray of boxes), /frodo/object_codes (latched table); for the sparse and
     dense stages /frodo/detections (16UC1), /frodo/associations (table), /camera/pose, /camera/color/image_raw
     (dense/photometric only), /camera/color/camera_info (stamp matched by FrameCache; each detection is
     reduced to a compact `sparse.View` and `photometric.DenseView` and the frame freed), /slam/points (latest
     map), /camera/depth/image_raw (optional, contract v1.1: cached by stamp, used when present).
Out: /frodo/objects (contract: TRIANGLE_LIST per object, world vertices), /frodo/boxes (contract: CUBE per
     object), /frodo/object_states (latched table for the command line's objects.json), /diagnostics with
     state idle|busy, pending_objects, waiting_fused/sparse/dense and the stage running.
Work is breadth first (`frodo_optim.scheduling`): every object with new input gets its fused mesh and box
before any object's sparse stage runs, every sparse stage before any dense stage, the object seen first first;
a dense run yields (best state kept, re-queued) as soon as an object waits for an earlier stage.
Stamps are data time, never the node clock: each object's markers carry its estimate's stamp (the newest
frame of the box, code and views it was made from, `ObjectEstimate.stamp_ns`); DELETEs and the state table
the newest stamp the node has received (`data_stamp`). So a recording of a bag keeps one time line, with or
without /clock and use_sim_time. Only /diagnostics is on the node clock.

Several workers (parameters worker_index k, worker_count N) split the objects by id (id % N == k): each takes
only its own objects' tracks, codes and views; workers 1..N-1 publish their share of the outputs on internal
topics (topics.object_share_topic) and worker 0 merges every share into the complete map of the contract
topics (frodo_optim.merge, which also says why worker 0). With one worker the outputs are published directly.
Worker 0 (node name optim_node; the others optim_node_<k>) also reports `state` and `pending_objects` for all
workers (merge.WorkerLoads, from their /diagnostics), so "done" can be read from the optimiser node alone.
Every message says what the map has (ADDs) and every (class, id) it has retracted (DELETEs, repeated), never
DELETEALL. With map_dir the
worker saves its objects after each published stage (frodo_optim.object_map; also on the ~/save_map
service); with resume it starts from a saved map and republishes it at once.
"""
from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.categories import CATEGORIES
from frodo_common.node import ERROR, OK, WARN, FrodoNode, run_node
from frodo_common.frame_cache import FrameCache
from frodo_common.params import ParamSpec
from frodo_common.torch_threads import call_in_passing_thread
from frodo_common.frames import depth_to_metres
from frodo_common.marker_wire import MeshMarker, matches_rmw, read_marker_array, serialize_marker_array
from frodo_optim.config import PARAMS as OPTIM_PARAMS, optim_config
from frodo_optim.core import ObjectEstimate
from frodo_optim.merge import TABLE_KIND, MapMerger, Retractions, WorkerLoads, item_marker
from frodo_optim.object_map import MapObject, MapWriter, load_maps, map_dirs, worker_map_dir
from frodo_optim.reconstructor import ObjectInput, ObjectReconstructor, Scene, StageOutcome
from frodo_optim.scheduling import Job, StageQueue
from frodo_optim.states import OBJECT_STATES, StageReason, estimates_table
from frodo_optim.views import ViewMemory
from frodo_shape.prior import ShapePrior

PARAMS = OPTIM_PARAMS + (
    ParamSpec('image_topic', topics.IMAGE, 'Colour image topic (dense stage and photometric terms).'),
    ParamSpec('depth_topic', topics.DEPTH, "Optional registered depth (16UC1 mm or 32FC1 m); '' disables."),
    ParamSpec('camera_info_topic', topics.CAMERA_INFO, 'Camera intrinsics topic.'),
    ParamSpec('pose_topic', topics.POSE, 'Camera pose topic (T_world_camera, optical frame).'),
    ParamSpec('slam_points_topic', topics.SLAM_POINTS, 'SLAM landmarks topic (whole map per message).'),
    ParamSpec('worker_index', 0, 'This worker takes the objects with id % worker_count == worker_index.'),
    ParamSpec('worker_count', 1, 'Optimiser workers sharing the objects (frodo launch --optim-workers N).'),
    ParamSpec('map_dir', '', "Save the object map here after each published stage (DIR/worker_<k> with several "
              "workers; also on the ~/save_map service); '' disables."),
    ParamSpec('resume', '', "Start from the object map saved in this folder (and its worker_* folders), "
              "republished at once; '' starts empty."),
)

CLASS_COLOURS = {c.name: (*c.colour, 1.0) for c in CATEGORIES}   # chair orange, dining table blue, ...


class OptimNode(FrodoNode):
    """Queues the stages of objects whose inputs changed; a worker thread runs them breadth first."""

    def __init__(self, **kwargs):
        super().__init__('optim_node', PARAMS, **kwargs)
        self.worker_index, self.worker_count = int(self.params['worker_index']), int(self.params['worker_count'])
        if not 0 <= self.worker_index < self.worker_count:
            raise ValueError(f'worker_index {self.worker_index} must be in 0..worker_count-1 '
                             f'(worker_count {self.worker_count})')
        self.config = optim_config({spec.name: self.params[spec.name] for spec in OPTIM_PARAMS})
        # loaded in a passing thread: its OpenMP team must not outlive it beside the worker's (torch_threads)
        prior = call_in_passing_thread(lambda: ShapePrior.load(self.config.prior, device=self.config.device))
        self.reconstructor = ObjectReconstructor(prior, self.config)
        self.tracks: dict[int, tuple[str, tuple]] = {}             # id -> (class, (centre, size, yaw))
        self.codes: dict[int, tuple[int, int, np.ndarray]] = {}     # id -> (category, views, code)
        self.mesh_markers: dict[int, MeshMarker] = {}                # id -> its estimate's mesh marker
        self.retractions = Retractions()                            # published once, now gone: DELETE every time
        self.resumed: dict[int, int] = {}                           # id -> views of its saved estimate (not re-run yet)
        self.queue = StageQueue()                                   # breadth first: every fused, then sparse, then dense
        self.busy: Job | None = None                                # the stage being run
        self.cond = threading.Condition()
        self.stopping = False
        self.views = ViewMemory(self.config)
        self.slam_points: np.ndarray | None = None
        self.stage_info: dict[str, dict[int, str]] = {'sparse': {}, 'dense': {}}   # stage -> id -> last outcome
        self.depth_cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self.stamp_lock = threading.Lock()
        self.data_stamp = 0                                         # newest stamp (ns) of any input received
        self.input_stamps: dict[int, int] = {}                      # id -> newest stamp of its track and code
        parts = ('detections', 'associations', 'pose') + (('image',) if self.config.dense_on else ())
        self.frames = FrameCache(parts, int(self.params['frame_cache_size']))
        # Alone or worker 0: the contract topics; worker k >= 1: its share topics, merged by worker 0.
        sharing = self.worker_index > 0
        self.objects_pub = self.create_publisher(
            MarkerArray, topics.object_share_topic('objects', self.worker_index) if sharing else topics.OBJECTS,
            topics.LATCHED_QOS)
        self.boxes_pub = self.create_publisher(
            MarkerArray, topics.object_share_topic('boxes', self.worker_index) if sharing else topics.BOXES,
            topics.LATCHED_QOS)
        self.states_pub = self.create_publisher(
            PointCloud2, topics.object_share_topic(TABLE_KIND, self.worker_index) if sharing else OBJECT_STATES,
            topics.LATCHED_QOS)
        # The map is published serialised from arrays (marker_wire) where this RMW reads those bytes back right.
        self.map_wire = matches_rmw()
        if not self.map_wire:
            self.get_logger().warning('this RMW writes visualization_msgs/MarkerArray differently from '
                                      'frodo_common.marker_wire: the map is published as messages (slower)')
        self.merger = MapMerger(self.worker_count) if self.worker_count > 1 and not sharing else None
        self.merge_lock = threading.Lock()   # own share (worker thread) and the others' (executor) are merged
        if self.merger is not None:
            for k in range(1, self.worker_count):
                for msg_type, kind in ((MarkerArray, 'objects'), (MarkerArray, 'boxes'), (PointCloud2, TABLE_KIND)):
                    # meshes read raw, their points as arrays (marker_wire), where this RMW's bytes allow
                    self.create_subscription(msg_type, topics.object_share_topic(kind, k),
                                             self.guarded(lambda m, kind=kind, k=k: self._on_share(kind, k, m),
                                                          f'worker_{k}_{kind}'), topics.LATCHED_QOS,
                                             raw=kind == 'objects' and self.map_wire)
        # Worker 0 is the optimiser node a listener watches for "done": its state covers every worker's.
        self.worker_loads = WorkerLoads(self.worker_count) if self.merger is not None else None
        if self.worker_loads is not None:
            self.create_subscription(DiagnosticArray, topics.DIAGNOSTICS,
                                     self.guarded(self._on_diagnostics, 'diagnostics'), 50)
        self.map_lock = threading.Lock()
        self.map_writer = (MapWriter(worker_map_dir(self.params['map_dir'], self.worker_index, self.worker_count),
                                     (self.worker_index, self.worker_count)) if self.params['map_dir'] else None)
        self.create_service(Trigger, '~/save_map', self._on_save_map)
        if self.params['resume']:
            self._resume(self.params['resume'])
        self.create_subscription(MarkerArray, topics.TRACKS, self.guarded(self._on_tracks, 'tracks'),
                                 topics.LATCHED_QOS)
        self.create_subscription(PointCloud2, topics.OBJECT_CODES, self.guarded(self._on_codes, 'object_codes'),
                                 topics.LATCHED_QOS)
        if self.config.sparse_enabled:
            for msg_type, topic, part in ((Image, topics.DETECTIONS, 'detections'),
                                          (PointCloud2, topics.ASSOCIATIONS, 'associations'),
                                          (PoseStamped, self.params['pose_topic'], 'pose')):
                self.create_subscription(msg_type, topic, self.guarded(lambda m, p=part: self._on_frame_part(m, p), part),
                                         topics.FRAME_QOS)
            if self.config.dense_on:
                self.create_subscription(Image, self.params['image_topic'],
                                         self.guarded(lambda m: self._on_frame_part(m, 'image'), 'image'),
                                         topics.FRAME_QOS)
                if self.params['depth_topic']:
                    self.create_subscription(Image, self.params['depth_topic'], self.guarded(self._on_depth, 'depth'),
                                             topics.FRAME_QOS)
            self.create_subscription(CameraInfo, self.params['camera_info_topic'],
                                     self.guarded(self._on_camera_info, 'camera_info'), topics.FRAME_QOS)
            self.create_subscription(PointCloud2, self.params['slam_points_topic'],
                                     self.guarded(self._on_slam_points, 'slam_points'), topics.FRAME_QOS)
        self.worker = threading.Thread(target=self._work, name='optim_worker', daemon=True)
        self.worker.start()

    def owns(self, object_id: int) -> bool:
        """True for the objects this worker reconstructs (all of them with one worker)."""
        return object_id % self.worker_count == self.worker_index

    @property
    def estimates(self) -> dict[int, ObjectEstimate]:
        """The current estimate of each of this worker's objects (the reconstructor's map)."""
        return self.reconstructor.estimates

    @estimates.setter
    def estimates(self, value: dict[int, ObjectEstimate]) -> None:
        self.reconstructor.estimates = value

    # ------------------------------------------------------------ inputs
    def _saw(self, stamp_ns: int) -> None:
        """Note the data time of an input (the outputs' stamps come from these, not from the clock)."""
        with self.stamp_lock:
            self.data_stamp = max(self.data_stamp, int(stamp_ns))

    def _on_tracks(self, msg: MarkerArray) -> None:
        self.count('tracks_received')
        with self.cond:
            for m in msg.markers:
                stamp = conv.stamp_to_ns(m.header.stamp)
                self._saw(stamp)
                if m.action != Marker.DELETEALL and not self.owns(m.id):
                    continue
                if m.action == Marker.DELETEALL:
                    self.tracks.clear()
                elif m.action == Marker.DELETE:
                    self.tracks.pop(m.id, None)
                    self.resumed.pop(m.id, None)   # the association dropped it: a resumed object goes too
                    self.queue.request(m.id)
                elif m.type == Marker.CUBE:
                    try:  # one bad box must not drop the others of the array
                        box = conv.marker_to_box(m)
                    except conv.ConversionError as err:
                        self.report_error('tracks', f'object {m.id}: {err}')
                        continue
                    if np.all(np.isfinite(box.center)) and np.all(np.isfinite(box.size)) and np.all(box.size > 0):
                        previous = self.tracks.get(m.id)
                        self.tracks[m.id] = (m.ns, box)
                        self.input_stamps[m.id] = max(self.input_stamps.get(m.id, 0), stamp)
                        # the association re-sends every track when one changes: only a changed one is new work
                        if previous is None or previous[0] != m.ns or not previous[1].same_as(box):
                            self.queue.request(m.id)
                    else:
                        self.report_error('tracks', f'object {m.id}: invalid box {box}')
            self.cond.notify()

    def _on_codes(self, msg: PointCloud2) -> None:
        self.count('object_codes_received')
        table = conv.cloud_to_table(msg)
        stamp = conv.stamp_to_ns(msg.header.stamp)
        self._saw(stamp)
        with self.cond:
            for row in table:
                oid = int(row['object_id'])
                if not self.owns(oid):
                    continue
                code = np.asarray(row['code'], dtype=np.float32)
                if not np.all(np.isfinite(code)):
                    self.report_error('object_codes', f'object {oid}: non-finite code ignored')
                    continue
                old = self.codes.get(oid)
                if old is None or old[1] != int(row['num_views']) or not np.array_equal(old[2], code):
                    self.codes[oid] = (int(row['category']), int(row['num_views']), code)
                    self.input_stamps[oid] = max(self.input_stamps.get(oid, 0), stamp)
                    self.queue.request(oid)
            self.cond.notify()

    def _on_camera_info(self, msg: CameraInfo) -> None:
        first = self.frames.camera_info is None
        self.frames.camera_info = (conv.camera_info_to_K(msg), (int(msg.width), int(msg.height)))
        if first:   # frames completed before the first camera info were held in the cache
            for frame in self.frames.complete_frames():
                self._views_of_frame(frame)

    def _on_depth(self, msg: Image) -> None:
        """Registered depth, kept by stamp (bounded) until its frame's views are extracted."""
        self.count('depth_received')
        if msg.encoding not in ('16UC1', '32FC1'):
            raise conv.ConversionError(f'depth encoding must be 16UC1 (mm) or 32FC1 (m), got {msg.encoding!r}')
        depth = depth_to_metres(conv.image_to_numpy(msg))
        with self.cond:
            self.depth_cache[conv.stamp_to_ns(msg.header.stamp)] = depth
            while len(self.depth_cache) > 64:
                self.depth_cache.popitem(last=False)

    def _on_slam_points(self, msg: PointCloud2) -> None:
        self._saw(conv.stamp_to_ns(msg.header.stamp))
        points = conv.cloud_to_xyz(msg)
        with self.cond:
            self.slam_points = points[np.isfinite(points).all(1)] if len(points) else points

    def _on_frame_part(self, msg, part: str) -> None:
        self.count(f'{part}_received')
        stamp = conv.stamp_to_ns(msg.header.stamp)
        self._saw(stamp)
        if part == 'associations' and stamp in self.frames.completed:
            rows = conv.cloud_to_table(msg)       # a re-send after merges: move the stored views
            with self.cond:
                self.views.assign(stamp, rows)
            return
        frame = self.frames.add(stamp, part, msg)
        if frame is not None:
            if self.frames.camera_info is None:
                self.count('frames_waiting_for_camera_info')   # held (bounded by the cache) until it arrives
                return
            self._views_of_frame(frame)

    def _views_of_frame(self, frame) -> None:
        try:
            self._extract_views(frame)
        finally:
            self.frames.frames.pop(frame.stamp_ns, None)   # free the image (the stamp stays marked complete)

    def _extract_views(self, frame) -> None:
        """Compact sparse-stage views (mask samples + distance transform) of a frame's kept associated masks."""
        K, (width, height) = self.frames.camera_info
        det = frame.parts['detections']
        if det.encoding != '16UC1':
            raise conv.ConversionError(f'detections encoding must be 16UC1, got {det.encoding!r}')
        labels = conv.image_to_numpy(det)
        if labels.shape != (height, width):
            raise conv.ConversionError(f'detections {labels.shape[1]}x{labels.shape[0]} do not match '
                                       f'camera_info {width}x{height}')
        T = conv.pose_to_matrix(frame.parts['pose'].pose)
        if not np.isfinite(T).all():
            raise conv.ConversionError('non-finite camera pose')
        rows = conv.cloud_to_table(frame.parts['associations'])
        rgb = depth = None
        if self.config.dense_on:
            rgb = conv.image_to_rgb(frame.parts['image'])
            if rgb.shape[:2] != (height, width):
                raise conv.ConversionError(f'image {rgb.shape[1]}x{rgb.shape[0]} does not match camera_info {width}x{height}')
            with self.cond:
                depth = self.depth_cache.pop(frame.stamp_ns, None)
            if depth is not None and depth.shape != (height, width):
                self.report_error('depth', f'depth {depth.shape[1]}x{depth.shape[0]} is not registered to the '
                                           f'{width}x{height} colour image; ignored', counter='warnings')
                depth = None
        with self.cond:
            stored, rejected = self.views.add_frame(frame.stamp_ns, K, T, labels, rows, rgb, depth, self.owns)
        self.count('views_stored', stored)
        self.count('views_rejected', rejected)

    # ------------------------------------------------------------ worker
    def _work(self) -> None:
        """Run the queued stages one at a time, breadth first (`scheduling.StageQueue`)."""
        while True:
            with self.cond:
                while not self.queue and not self.stopping:
                    self.cond.wait(timeout=0.5)
                if self.stopping:
                    return
                job = self.queue.pop()
                self.busy = job
                track, codes = self.tracks.get(job.object_id), self.codes.get(job.object_id)
                stamp = self.input_stamps.get(job.object_id, 0)
            try:
                self._run(job, track, codes, stamp)
            except Exception as err:  # noqa: BLE001 - one bad object must not stop the others
                self.report_error(f'object {job.object_id}', err)
            finally:
                with self.cond:
                    self.busy = None

    def _yield_dense(self) -> bool:
        """A dense run stops (its best state kept, the rest re-queued) when the node stops or an object waits for
        its fused or sparse stage: a new object's first mesh does not wait for another's dense stage."""
        with self.cond:
            return self.stopping or self.queue.waiting_before('dense')

    def _yield_sparse(self) -> bool:
        """A sparse run stops at its next iteration (nothing kept, run again next) when the node stops or an object
        without any estimate waits for its fused stage: its first mesh does not wait for another's sparse stage.
        Objects that already have one do not interrupt it: boxes move with every frame while a bag plays, so
        sparse stages would never end."""
        with self.cond:
            return self.stopping or any(oid not in self.reconstructor.estimates for oid in self.queue.queued('fused'))

    def _run(self, job: Job, track, codes, stamp_ns: int = 0) -> None:
        oid = job.object_id
        if track is None or codes is None or codes[1] < self.config.min_views:
            # A resumed object stays until the association deletes its track: its fused code may come first.
            if track is None and oid in self.estimates and oid not in self.resumed:
                self.reconstructor.forget(oid)
                self._publish()
            return
        if oid in self.resumed and self.config.sparse_enabled:
            # A restarted worker has none of the views its saved estimate came from: keep that estimate until
            # as many new ones as a sparse pass uses (or as it had) are in, so a re-run is not worse for want
            # of views.
            needed = max(self.config.min_views, min(self.resumed[oid], self.config.sparse.max_views))
            with self.cond:
                stored = self.views.count(oid)
            if stored < needed:
                self.count('resumed_waiting_for_views')
                return
        self.resumed.pop(oid, None)
        class_name, box = track
        category, views, code = codes
        with self.cond:
            scene = Scene(self.slam_points, dict(self.tracks))
            others_waiting = bool(self.queue) and not job.forced
        step = self.reconstructor.run_stage(
            ObjectInput(oid, class_name, category, box, code, views, stamp_ns), job.stage, self.views, scene,
            others_waiting=others_waiting, should_stop=self._yield_dense if job.stage == 'dense' else self._yield_sparse,
            on_stage=self._on_stage)
        if step.error:
            raise RuntimeError(step.error)
        with self.cond:
            interrupted = step.outcome is not None and step.outcome.reason is StageReason.DENSE_INTERRUPTED
            if step.yielded and not self.stopping:
                self.queue.request(oid, 'sparse')
                self.count('sparse_yielded')
            elif step.deferred or (interrupted and not self.stopping):
                self.queue.defer(oid)
                self.count('dense_deferred' if step.deferred else 'dense_yielded')
            elif step.next is not None:
                self.queue.advance(oid, job.stage)

    def _on_stage(self, outcome: StageOutcome) -> None:
        """After each stage of an object: count, remember its words for /diagnostics, publish the map."""
        if outcome.stage == 'fused':
            self.count('meshes_placed')
        else:
            self.count(f'{outcome.stage}_runs')
            self.stage_info[outcome.stage][outcome.object_id] = f'{outcome.reason.text}: {outcome.detail}'
        if outcome.published:
            self._publish()

    # ------------------------------------------------------------ outputs
    def _mesh_marker(self, est: ObjectEstimate, stamp_ns: int, frame: str, rgba) -> MeshMarker:
        """The TRIANGLE_LIST marker of an estimate (stamped `stamp_ns`, its data time), built once per estimate (a
        map of n objects is republished after every stage of every object), its points kept as an array until the
        map is serialised: as ~40k Point messages per object they cost ~0.3 s to build and convert, and their
        garbage set off full collections that held the GIL for up to a second."""
        cached = self.mesh_markers.get(est.object_id)
        if cached is not None and cached.source is est:   # same estimate: same mesh, class and colour
            cached.restamp(stamp_ns)
            return cached
        marker, points = conv.mesh_marker_parts(est.mesh_world.vertices, est.mesh_world.faces, est.class_name,
                                                 est.object_id, stamp_ns, frame, rgba)
        self.mesh_markers[est.object_id] = MeshMarker(est, marker, points)
        return self.mesh_markers[est.object_id]

    def _map_message(self, markers: list) -> MarkerArray | bytes:
        """The MarkerArray of `markers` (Markers, MeshMarkers and (marker, points) items), serialised from the
        arrays where the RMW allows."""
        items = [m.parts() if isinstance(m, MeshMarker) else m for m in markers]
        if self.map_wire:
            return serialize_marker_array(items)
        return MarkerArray(markers=[conv.with_points(*m) if isinstance(m, tuple) else m for m in items])

    def _map_stamp(self, estimates) -> int:
        """Data time of a map message (its DELETEs, the state table): the newest stamp received or estimated."""
        with self.stamp_lock:
            return max([self.data_stamp] + [int(e.stamp_ns) for e in estimates])

    def _publish(self) -> None:
        frame = self.params['world_frame']
        objects, boxes = [], MarkerArray()      # objects: Markers (deletes) and MeshMarkers
        estimates = sorted(self.estimates.values(), key=lambda e: e.object_id)
        now = self._map_stamp(estimates)
        current = {(est.class_name, est.object_id) for est in estimates}
        # Every object this worker published and has since dropped gets a DELETE in every message, first (a
        # listener keyed by id then keeps an object whose class changed): a listener that missed a message still
        # drops it. Never DELETEALL (a share of several workers' map holds only this worker's objects).
        for ns, oid in self.retractions.update(current):
            objects.append(conv.delete_marker(ns, oid, now, frame))
            boxes.markers.append(conv.delete_marker(ns, oid, now, frame))
        for est in estimates:
            rgba = CLASS_COLOURS.get(est.class_name, (0.7, 0.7, 0.7, 1.0))
            stamp = int(est.stamp_ns) or now       # 0: a map resumed from a file without stamps
            objects.append(self._mesh_marker(est, stamp, frame, rgba))
            center, size, yaw = est.box
            boxes.markers.append(conv.box_to_marker(center, size, yaw, est.class_name, est.object_id, stamp, frame,
                                                    rgba[:3] + (0.35,)))
        states = estimates_table(estimates)
        self.mesh_markers = {oid: entry for oid, entry in self.mesh_markers.items() if oid in self.estimates}
        if self.merger is None:       # alone: the map; worker k >= 1: its share
            self.objects_pub.publish(self._map_message(objects))
            self.boxes_pub.publish(boxes)
            self.states_pub.publish(conv.table_to_cloud(states, now, frame))
        else:
            with self.merge_lock:
                self.merger.put_markers('objects', 0, [m.parts() if isinstance(m, MeshMarker) else m for m in objects])
                self.merger.put_markers('boxes', 0, boxes.markers)
                self.merger.put_table(0, states)
                for kind in ('objects', 'boxes', TABLE_KIND):
                    self._publish_merged(kind)
        self.count('maps_published')
        if self.map_writer is not None:
            try:
                self.save_map()
            except OSError as err:   # a full disk must not stop the optimiser
                self.report_error('map_dir', err)

    def _on_share(self, kind: str, worker: int, msg) -> None:
        """Worker 0: another worker's share of `kind` (a message, or the serialised objects share); the merged map
        of that kind is published again."""
        self.count('shares_received')
        table = conv.cloud_to_table(msg) if kind == TABLE_KIND else None
        items = [] if table is not None else read_marker_array(msg) if isinstance(msg, bytes) else msg.markers
        stamps = [msg.header.stamp] if table is not None else [item_marker(m).header.stamp for m in items]
        self._saw(max((conv.stamp_to_ns(s) for s in stamps), default=0))
        with self.merge_lock:
            if table is None:
                self.merger.put_markers(kind, worker, items)
            else:
                self.merger.put_table(worker, table)
            self._publish_merged(kind)

    def _publish_merged(self, kind: str) -> None:
        """Worker 0 (under merge_lock): the complete map of `kind` from every share heard of (CONTRACT.md)."""
        now, frame = self._map_stamp(()), self.params['world_frame']    # data time, as each share's
        if kind == TABLE_KIND:
            table = self.merger.merged_table()
            if table is not None:
                self.states_pub.publish(conv.table_to_cloud(table, now, frame))
        else:
            items = self.merger.merged_markers(kind, now, frame)
            if kind == 'objects':
                self.objects_pub.publish(self._map_message(items))
                self.count('merged_maps_published')
            else:
                self.boxes_pub.publish(MarkerArray(markers=items))

    # ------------------------------------------------------------ object map on disk
    def save_map(self) -> str:
        """Write this worker's objects (and the fused code and track each has now) to map_dir; returns the
        objects.json path. Raises ValueError without map_dir, OSError when the files cannot be written."""
        if self.map_writer is None:
            raise ValueError('map_dir is not set')
        estimates = dict(self.estimates)      # one atomic copy: the worker thread replaces entries meanwhile
        with self.cond:
            inputs = {oid: (self.codes.get(oid), self.tracks.get(oid)) for oid in estimates}
        objects = [MapObject(est, codes[2] if codes else None, codes[1] if codes else 0, track)
                   for oid, est in estimates.items() for codes, track in [inputs[oid]]]
        with self.map_lock:
            path = self.map_writer.save(objects, self.params['world_frame'])
        self.count('maps_saved')
        return str(path)

    def _on_save_map(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """~/save_map (std_srvs/Trigger): save now; the response says where, or why not."""
        try:
            path = self.save_map()
            response.success, response.message = True, f'{len(self.estimates)} object(s) saved to {path}'
        except ValueError as err:
            response.success, response.message = False, str(err)
        except OSError as err:
            self.report_error('save_map', err)
            response.success, response.message = False, f'saving failed: {err}'
        return response

    def _resume(self, root: str) -> None:
        """Take this worker's objects of the map saved under `root` and publish them at once; a map that cannot
        be read is reported and the worker starts without it."""
        if not map_dirs(root):
            self.get_logger().info(f'resume: no saved object map in {root} yet; starting empty')
            return
        objects, problems = load_maps(root, self.owns)
        for problem in problems:
            self.report_error('resume', problem, counter='warnings')
        for oid, obj in objects.items():
            self.estimates[oid] = obj.estimate
            self.resumed[oid] = obj.estimate.num_views
        self.count('objects_resumed', len(objects))
        self.get_logger().info(f'resume: {len(objects)} object(s) from {root}')
        if objects:
            self._publish()

    # ------------------------------------------------------------ diagnostics and shutdown
    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        """Worker 0: note the state and pending objects each other worker of this graph reports."""
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            index, _, count = values.get('worker', '').partition('/')
            if (status.name == f'{self.get_name()}_{index}' and count == str(self.worker_count)
                    and index.isdigit() and 1 <= int(index) < self.worker_count):
                with self.cond:
                    self.worker_loads.heard(int(index), values.get('state', 'busy'),
                                            int(values.get('pending_objects', '0') or 0))

    def diagnostic_values(self) -> dict:
        with self.cond:
            # distinct objects with work left: queued, deferred dense stages, and the one being reconstructed
            waiting = self.queue.objects() | ({self.busy.object_id} if self.busy is not None else set())
            state = 'busy' if waiting else 'idle'
            values = {'state': state, 'pending_objects': len(waiting),
                      **{f'waiting_{stage}': n for stage, n in self.queue.waiting().items()},
                      'running': f'object {self.busy.object_id} {self.busy.stage}' if self.busy is not None else '-',
                      'objects': len(self.estimates), 'tracks': len(self.tracks),
                      'worker': f'{self.worker_index}/{self.worker_count}',
                      **({'shares_merged': f'{len(self.merger.heard)}/{self.worker_count}'} if self.merger else {}),
                      'resumed_unrefined': len(self.resumed),
                      'sparse_objects': sum(e.stage == 'sparse' for e in self.estimates.values()),
                      'dense_objects': sum(e.stage == 'dense' for e in self.estimates.values()),
                      'views_held': len(self.views.sparse), 'dense_views_held': len(self.views.dense)}
            if self.worker_loads is not None:      # worker 0 reports for the whole optimiser
                values.update(self.worker_loads.combined(bool(waiting), len(waiting)))
            for stage, info in self.stage_info.items():
                if info:
                    oid = max(info)
                    values[f'{stage}_last'] = f'object {oid}: {info[oid]}'
            return values

    def diagnostic_summary(self) -> tuple[int, str]:
        if not self.worker.is_alive() and not self.stopping:
            return ERROR, 'optimiser worker thread died'
        return (OK, f'{len(self.estimates)} objects') if not self.last_error else \
            (WARN, f'{len(self.estimates)} objects; last error: {self.last_error}')

    def on_shutdown(self) -> None:
        """Stop the worker thread (called by run_node)."""
        with self.cond:
            self.stopping = True
            self.cond.notify()
        self.worker.join(timeout=5)


def main(args=None) -> int:
    """Entry point of `optim_node`."""
    return run_node(OptimNode, args)


if __name__ == '__main__':
    main()
