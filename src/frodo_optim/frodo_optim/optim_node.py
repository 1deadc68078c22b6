"""Optimiser node: turns tracks (3D boxes) and fused shape codes into placed object meshes, asynchronously
(paper Sec. 4.3). Stage 'fused': decode + box-fit placement (frodo_optim.core); stage 'sparse': yaw search
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
     state idle|busy and pending_objects.

Several workers (parameters worker_index k, worker_count N) split the objects by id (id % N == k): each takes
only its own objects' tracks, codes and views; workers 1..N-1 publish their share of the outputs on internal
topics (topics.object_share_topic) and worker 0 merges every share into the complete map of the contract
topics (frodo_optim.merge, which also says why worker 0). With one worker the outputs are published directly.
Every message says what the map has (ADDs) and every (class, id) it has retracted (DELETEs, repeated), never
DELETEALL. With map_dir the
worker saves its objects after each published stage (frodo_optim.object_map; also on the ~/save_map
service); with resume it starts from a saved map and republishes it at once.
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict

import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.categories import category_by_id
from frodo_common.node import ERROR, OK, WARN, FrodoNode, run_node
from frodo_common.frame_cache import FrameCache
from frodo_common.params import ParamSpec
from frodo_optim.core import ObjectEstimate, fused_estimate, world_box
from frodo_optim.dense import DenseConfig, refine_dense_starts
from frodo_optim.merge import TABLE_KIND, MapMerger, Retractions
from frodo_optim.object_map import MapObject, MapWriter, load_maps, map_dirs, worker_map_dir
from frodo_optim.photometric import ViewBatch, dense_view_from_frame
from frodo_optim.sparse import SparseConfig, ViewStore, refine, select_views, view_from_mask
from frodo_optim import support
from frodo_optim.states import OBJECT_STATES, STAGE_REASONS, STAGES, STATES_DTYPE
from frodo_shape.prior import DEFAULT_PRIOR, ShapePrior

PARAMS = (
    ParamSpec('prior', DEFAULT_PRIOR, 'Shipped prior name (frodo_shape/priors/<name>) or path to a prior folder.'),
    ParamSpec('device', 'auto', "Torch device: 'auto' (cuda if available), 'cpu' or 'cuda'."),
    ParamSpec('mesh_resolution', 96, 'Marching-cubes grid resolution for decoded meshes.'),
    ParamSpec('min_views', 2, 'Views (kept, associated detections) an object needs before it is reconstructed.'),
    ParamSpec('fill_views', 16, 'An object with fewer kept views than this is optimised with its pruned associated '
              'views too (truncated or overlapping; evenly spread) up to this many; 0: kept views only.'),
    ParamSpec('code_change_tolerance', 0.02,
              'Re-decode the mesh only when the fused code moved by more than this (relative L2); '
              'box updates alone just re-place the cached mesh.'),
    ParamSpec('sparse_enabled', True, "Run the sparse stage (Sec. 4.3: yaw search + silhouette/SLAM-point "
              "optimisation) after the fused stage; false publishes the fused placement only."),
    ParamSpec('sparse_iterations', 40, 'Adam iterations of the sparse stage per object and pass.'),
    ParamSpec('sparse_views', 16, 'Views (spread evenly over the kept ones) used by the sparse stage.'),
    ParamSpec('sparse_views_stored', 64, 'Views remembered per object (thinned evenly beyond this; bounded memory).'),
    ParamSpec('sparse_mask_samples', 96, 'Pixels sampled on each mask for the mask-to-points chamfer half.'),
    ParamSpec('sparse_point_samples', 384, 'Decoded points (of 2048) matched against the mask samples.'),
    ParamSpec('sparse_yaw_candidates', 24, 'Yaw angles of the exhaustive initial search about gravity.'),
    ParamSpec('sparse_w_silhouette', 1.0, 'Weight of the silhouette energy Es (2D chamfer, box diagonals).'),
    ParamSpec('sparse_w_geometry', 0.5, 'Weight of the SLAM-point energy Eg (truncated 3D chamfer); 0 disables.'),
    ParamSpec('sparse_w_code', 0.01, 'Weight of the code regulariser Er (squared code z-score w.r.t. training codes).'),
    ParamSpec('sparse_optimise_code', True, 'Optimise the shape code too (false: pose only).'),
    ParamSpec('sparse_lr_code', 0.02, 'Adam step size of the shape code in the sparse stage.'),
    ParamSpec('sparse_w_photometric', 0.0, 'Weight of the sparse photometric energy Ep (Eq. 5, visibility-aware; '
              'needs dense_enabled for the colour crops); 0 disables.'),
    ParamSpec('sparse_placement_search', True, 'Also start the sparse stage from placement hypotheses (placement.py: '
              'ray-crossing centres, silhouette scales) for a badly wrong association box; a hypothesis replaces the box '
              'start only when clearly better on common landmarks and silhouettes (README "Placement").'),
    ParamSpec('sparse_code_restarts', 4, 'Also start the sparse stage from the best of this many lowest-energy '
              'training codes of the object\'s class (beyond the paper; 0: off; README "Code freedom").'),
    ParamSpec('sparse_landmark_filter', True, 'Only landmarks in the detections\' visual hull (on the masks in '
              '>= 75 % of the views that count; a view where one falls on another detection counts only if it lies in '
              'a neighbour\'s box) enter Eg, in the sparse and the dense stage; false: every landmark near the box '
              '(the paper\'s setting; README "Landmarks in the visual hull").'),
    ParamSpec('support_w_floor', 0.05, 'Weight of the floor prior E_floor in the sparse and dense stages (beyond the '
              'paper: the lowest points on the floor estimated from the boxes and landmarks; support.py); 0 disables.'),
    ParamSpec('support_w_height', 1.0, 'Weight of the class height prior E_size in the sparse and dense stages (beyond '
              'the paper: height inside Category.height_range; support.py); 0 disables.'),
    ParamSpec('dense_enabled', True, 'Run the dense stage (Sec. 4.3 Dense Optimization: SDF decoder, code + 7-DoF '
              'pose) after a successful sparse stage.'),
    ParamSpec('dense_iterations', 40, 'Adam iterations of the dense stage per object and pass.'),
    ParamSpec('dense_starts', 3, 'Dense stage from the sparse result and up to N - 1 end states of the sparse '
              'stage\'s other runs (box, placement hypothesis, code restart); the lowest dense energy wins (1: the '
              'sparse result only, a third of the dense cost).'),
    ParamSpec('dense_max_seconds', 30.0, 'Wall-clock bound of one dense run (per object and start; best state kept).'),
    ParamSpec('dense_views', 16, 'Views (spread evenly over the kept ones) used by the dense stage.'),
    ParamSpec('dense_grid_resolution', 32, 'Resolution of the adaptive SDF volume / proxy mesh per iteration.'),
    ParamSpec('dense_rays_per_view', 384, 'Pixels (rays) per view and pyramid level of the dense silhouette.'),
    ParamSpec('dense_surface_points', 1024, 'Proxy-mesh vertices used by the dense photometric term.'),
    ParamSpec('dense_sharpness', 100.0, 'zeta: SDF-to-logit scale of the ray-accumulated silhouette (per normalised unit).'),
    ParamSpec('dense_crop_size', 96, 'Side of the stored label/colour crop per detection (bounded memory).'),
    ParamSpec('dense_w_silhouette', 1.0, 'Weight of the dense silhouette energy (Eq. 8/9).'),
    ParamSpec('dense_w_photometric', 2.0, 'Weight of the dense photometric energy (Eq. 5 on the proxy surface).'),
    ParamSpec('dense_w_geometry', 0.5, 'Weight of the landmark term (|SDF| at SLAM points, truncated).'),
    ParamSpec('dense_w_depth', 0.5, 'Weight of the registered-depth term (|SDF| at masked depth pixels), when depth is present.'),
    ParamSpec('dense_w_code', 0.01, 'Weight of the code regulariser in the dense stage.'),
    ParamSpec('dense_lr_code', 0.02, 'Adam step size of the shape code in the dense stage.'),
    ParamSpec('dense_upright', False, 'Dense stage rotates objects about gravity (world z) only; false: any rotation '
              '(the paper\'s 7-DoF pose).'),
    ParamSpec('dense_rerun_growth', 1.25, 'While other objects wait, re-run an object\'s dense stage only when its '
              'views grew by this factor; the rest are caught up when the queue is empty.'),
    ParamSpec('image_topic', topics.IMAGE, 'Colour image topic (dense stage and photometric terms).'),
    ParamSpec('depth_topic', '/camera/depth/image_raw', "Optional registered depth (16UC1 mm or 32FC1 m); '' disables."),
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

CLASS_COLOURS = {'chair': (0.95, 0.55, 0.15, 1.0), 'dining table': (0.2, 0.6, 0.95, 1.0)}


class OptimNode(FrodoNode):
    """Keeps a pending set of objects whose inputs changed; a worker thread reconstructs them one by one."""

    def __init__(self, **kwargs):
        super().__init__('optim_node', PARAMS, **kwargs)
        self.worker_index, self.worker_count = int(self.params['worker_index']), int(self.params['worker_count'])
        if not 0 <= self.worker_index < self.worker_count:
            raise ValueError(f'worker_index {self.worker_index} must be in 0..worker_count-1 '
                             f'(worker_count {self.worker_count})')
        self.prior = ShapePrior.load(self.params['prior'], device=self.params['device'])
        self.tracks: dict[int, tuple[str, tuple]] = {}             # id -> (class, (centre, size, yaw))
        self.codes: dict[int, tuple[int, int, np.ndarray]] = {}     # id -> (category, views, code)
        self.estimates: dict[int, ObjectEstimate] = {}
        self.mesh_cache: dict[int, tuple[np.ndarray, object]] = {}  # id -> (code, normalised mesh)
        self.mesh_markers: dict[int, tuple[ObjectEstimate, Marker]] = {}   # id -> (estimate, its mesh marker)
        self.retractions = Retractions()                            # published once, now gone: DELETE every time
        self.resumed: dict[int, int] = {}                           # id -> views of its saved estimate (not re-run yet)
        self.pending: set[int] = set()
        self.busy: int | None = None                                # id of the object being reconstructed
        self.cond = threading.Condition()
        self.stopping = False
        self.view_store = ViewStore(int(self.params['sparse_views_stored']))
        self.dense_store = ViewStore(int(self.params['sparse_views_stored']), capacity=1000)  # same keys
        self.slam_points: np.ndarray | None = None
        self.sparse_info: dict[int, str] = {}                       # id -> last sparse outcome
        self.dense_info: dict[int, str] = {}                        # id -> last dense outcome
        self.dense_views_used: dict[int, int] = {}                  # id -> associated views at its last dense run
        self.dense_stale: set[int] = set()                          # dense deferred; run when the queue empties
        self.force_dense: set[int] = set()
        self.dense_on = bool(self.params['sparse_enabled'] and self.params['dense_enabled'])
        self.depth_cache: OrderedDict[int, np.ndarray] = OrderedDict()
        parts = ('detections', 'associations', 'pose') + (('image',) if self.dense_on else ())
        self.frames = FrameCache(parts, int(self.params['frame_cache_size']))
        self.rng = np.random.default_rng(0)
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
        self.merger = MapMerger(self.worker_count) if self.worker_count > 1 and not sharing else None
        self.merge_lock = threading.Lock()   # own share (worker thread) and the others' (executor) are merged
        if self.merger is not None:
            for k in range(1, self.worker_count):
                for msg_type, kind in ((MarkerArray, 'objects'), (MarkerArray, 'boxes'), (PointCloud2, TABLE_KIND)):
                    self.create_subscription(msg_type, topics.object_share_topic(kind, k),
                                             self.guarded(lambda m, kind=kind, k=k: self._on_share(kind, k, m),
                                                          f'worker_{k}_{kind}'), topics.LATCHED_QOS)
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
        if self.params['sparse_enabled']:
            for msg_type, topic, part in ((Image, topics.DETECTIONS, 'detections'),
                                          (PointCloud2, topics.ASSOCIATIONS, 'associations'),
                                          (PoseStamped, self.params['pose_topic'], 'pose')):
                self.create_subscription(msg_type, topic, self.guarded(lambda m, p=part: self._on_frame_part(m, p), part),
                                         topics.FRAME_QOS)
            if self.dense_on:
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

    # ------------------------------------------------------------ inputs
    def _on_tracks(self, msg: MarkerArray) -> None:
        self.count('tracks_received')
        with self.cond:
            for m in msg.markers:
                if m.action != Marker.DELETEALL and not self.owns(m.id):
                    continue
                if m.action == Marker.DELETEALL:
                    self.tracks.clear()
                elif m.action == Marker.DELETE:
                    self.tracks.pop(m.id, None)
                    self.resumed.pop(m.id, None)   # the association dropped it: a resumed object goes too
                    self.pending.add(m.id)
                elif m.type == Marker.CUBE:
                    try:  # one bad box must not drop the others of the array
                        box = conv.marker_to_box(m)
                    except conv.ConversionError as err:
                        self.report_error('tracks', f'object {m.id}: {err}')
                        continue
                    if np.all(np.isfinite(box[0])) and np.all(np.isfinite(box[1])) and np.all(box[1] > 0):
                        self.tracks[m.id] = (m.ns, box)
                        self.pending.add(m.id)
                    else:
                        self.report_error('tracks', f'object {m.id}: invalid box {box}')
            self.cond.notify()

    def _on_codes(self, msg: PointCloud2) -> None:
        self.count('object_codes_received')
        table = conv.cloud_to_table(msg)
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
                    self.pending.add(oid)
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
        depth = conv.image_to_numpy(msg).astype(np.float32)
        if msg.encoding == '16UC1':
            depth *= 0.001
        with self.cond:
            self.depth_cache[conv.stamp_to_ns(msg.header.stamp)] = depth
            while len(self.depth_cache) > 64:
                self.depth_cache.popitem(last=False)

    def _on_slam_points(self, msg: PointCloud2) -> None:
        points = conv.cloud_to_xyz(msg)
        with self.cond:
            self.slam_points = points[np.isfinite(points).all(1)] if len(points) else points

    def _on_frame_part(self, msg, part: str) -> None:
        self.count(f'{part}_received')
        stamp = conv.stamp_to_ns(msg.header.stamp)
        if part == 'associations' and stamp in self.frames.completed:
            rows = conv.cloud_to_table(msg)       # a re-send after merges: move the stored views
            owners = {int(r['label']): (int(r['object_id']), bool(r['kept'])) for r in rows}
            with self.cond:
                self.view_store.assign(stamp, owners)
                self.dense_store.assign(stamp, owners)
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
        detected = labels > 0
        rgb = depth = None
        if self.dense_on:
            rgb = conv.image_to_rgb(frame.parts['image'])
            if rgb.shape[:2] != (height, width):
                raise conv.ConversionError(f'image {rgb.shape[1]}x{rgb.shape[0]} does not match camera_info {width}x{height}')
            with self.cond:
                depth = self.depth_cache.pop(frame.stamp_ns, None)
            if depth is not None and depth.shape != (height, width):
                self.report_error('depth', f'depth {depth.shape[1]}x{depth.shape[0]} is not registered to the '
                                           f'{width}x{height} colour image; ignored', counter='warnings')
                depth = None
        for r in rows:   # all rows: ids of past frames are assigned or changed later by re-sends
            if r['object_id'] >= 0 and not self.owns(int(r['object_id'])):
                continue     # another worker's object (a later merge into one of ours loses this view)
            mask = labels == r['label']
            view = view_from_mask(K, T, mask, int(self.params['sparse_mask_samples']), detected & ~mask, self.rng)
            if view is None:
                self.count('views_rejected')
                continue
            key = (frame.stamp_ns, int(r['label']), int(r['object_id']), bool(r['kept']))
            dense_view = None
            if self.dense_on:
                dense_view = dense_view_from_frame(K, T, mask, detected & ~mask, rgb, depth,
                                                   size=int(self.params['dense_crop_size']), rng=self.rng)
            with self.cond:
                self.view_store.add(*key, view)
                if dense_view is not None:
                    self.dense_store.add(*key, dense_view)
            self.count('views_stored')

    def sparse_config(self) -> SparseConfig:
        p = self.params
        return SparseConfig(iterations=int(p['sparse_iterations']), max_views=int(p['sparse_views']),
                            mask_samples=int(p['sparse_mask_samples']), point_samples=int(p['sparse_point_samples']),
                            yaw_candidates=int(p['sparse_yaw_candidates']), w_silhouette=float(p['sparse_w_silhouette']),
                            w_geometry=float(p['sparse_w_geometry']), w_code=float(p['sparse_w_code']),
                            optimise_code=bool(p['sparse_optimise_code']), lr_code=float(p['sparse_lr_code']),
                            w_photometric=float(p['sparse_w_photometric']),
                            placement_search=bool(p['sparse_placement_search']),
                            code_restarts=int(p['sparse_code_restarts']), w_floor=float(p['support_w_floor']),
                            landmark_filter=bool(p['sparse_landmark_filter']),
                            w_height=float(p['support_w_height']))

    def dense_config(self) -> DenseConfig:
        p = self.params
        return DenseConfig(iterations=int(p['dense_iterations']), max_views=int(p['dense_views']),
                           max_seconds=float(p['dense_max_seconds']), grid_resolution=int(p['dense_grid_resolution']),
                           rays_per_view=int(p['dense_rays_per_view']), surface_points=int(p['dense_surface_points']),
                           sharpness=float(p['dense_sharpness']), w_silhouette=float(p['dense_w_silhouette']),
                           w_photometric=float(p['dense_w_photometric']), w_geometry=float(p['dense_w_geometry']),
                           w_depth=float(p['dense_w_depth']), w_code=float(p['dense_w_code']),
                           lr_code=float(p['dense_lr_code']), upright=bool(p['dense_upright']),
                           w_floor=float(p['support_w_floor']),
                           w_height=float(p['support_w_height']))

    # ------------------------------------------------------------ worker
    def _work(self) -> None:
        while True:
            with self.cond:
                while not self.pending and not self.stopping:
                    if self.dense_stale:   # queue empty: catch up the dense stages deferred during bursts
                        self.force_dense |= self.dense_stale
                        self.pending |= self.dense_stale
                        self.dense_stale.clear()
                        break
                    self.cond.wait(timeout=0.5)
                if self.stopping:
                    return
                oid = min(self.pending)
                self.pending.discard(oid)
                self.busy = oid
                track, codes = self.tracks.get(oid), self.codes.get(oid)
            try:
                self._reconstruct(oid, track, codes)
            except Exception as err:  # noqa: BLE001 - one bad object must not stop the others
                self.report_error(f'object {oid}', err)
            finally:
                with self.cond:
                    self.busy = None
                    self.force_dense.discard(oid)

    def _reconstruct(self, oid: int, track, codes) -> None:
        if track is None or codes is None or codes[1] < int(self.params['min_views']):
            # A resumed object stays until the association deletes its track: its fused code may come first.
            if track is None and oid in self.estimates and oid not in self.resumed:
                del self.estimates[oid]
                self._publish()
            return
        if oid in self.resumed and self.params['sparse_enabled']:
            # A restarted worker has none of the views its saved estimate came from: keep that estimate until
            # as many new ones as a sparse pass uses (or as it had) are in, so a re-run is not worse for want
            # of views.
            needed = max(int(self.params['min_views']), min(self.resumed[oid], int(self.params['sparse_views'])))
            with self.cond:
                stored = len(self.view_store.views_of(oid))
            if stored < needed:
                self.count('resumed_waiting_for_views')
                return
        self.resumed.pop(oid, None)
        class_name, box = track
        category, views, code = codes
        start = time.perf_counter()
        cached = self.mesh_cache.get(oid)
        tol = float(self.params['code_change_tolerance'])
        if cached is None or np.linalg.norm(code - cached[0]) > tol * max(np.linalg.norm(cached[0]), 1e-6):
            mesh = self.prior.mesh(code, resolution=int(self.params['mesh_resolution']))
            if mesh is None or len(mesh.faces) == 0:
                raise RuntimeError('decoded shape has no surface (code far from the prior?)')
            self.mesh_cache[oid] = (code, mesh)
            self.count('meshes_decoded')
        mesh = self.mesh_cache[oid][1]
        known = category_by_id(category)
        estimate = fused_estimate(oid, known.name if known else class_name, category, code, views, mesh, box)
        estimate.timings['fused_s'] = time.perf_counter() - start
        estimate.stage_reason = STAGE_REASONS.index('in progress' if self.params['sparse_enabled']
                                                    else 'sparse stage disabled')
        previous = self.estimates.get(oid)
        if previous is None or previous.stage == 'fused' or not self.params['sparse_enabled']:
            self.estimates[oid] = estimate        # a refined object keeps its last refinement until the next one
            self._publish()
        if not self.params['sparse_enabled']:
            return
        refined = self._sparse(estimate, code, box)
        if refined is None or not self.dense_on:
            return
        sparse, landmarks, alternatives = refined
        with self.cond:
            due = (oid in self.force_dense or oid not in self.dense_views_used or not self.pending
                   or views >= float(self.params['dense_rerun_growth']) * self.dense_views_used[oid])
            if not due:
                self.dense_stale.add(oid)
        if due:
            self._dense(sparse, box, views, landmarks, alternatives)
        else:
            self.count('dense_deferred')

    def _sparse(self, fused: ObjectEstimate, code: np.ndarray, box
                ) -> tuple[ObjectEstimate, np.ndarray | None, list[tuple[np.ndarray, np.ndarray, str]]] | None:
        """Sparse stage of one object after its fused stage; publishes and returns the refined estimate, the
        landmarks it chose for the object (None with `sparse_landmark_filter` off) and its other runs' end states
        (`SparseResult.alternatives`), or None when it fails: the fused result stays, with the reason."""
        config = self.sparse_config()
        with self.cond:
            fill = int(self.params['fill_views'])
            views = self.view_store.views_of(fused.object_id, fill)
            colour = select_views(self.dense_store.views_of(fused.object_id, fill), config.max_views)
            slam = self.slam_points
            floor = support.scene_floor(self.tracks, slam)
            neighbours = [b for oid, (_, b) in self.tracks.items() if oid != fused.object_id]
        t0 = time.perf_counter()
        photometric = ViewBatch(colour) if colour and config.w_photometric > 0 else None   # sparse runs on CPU
        result = refine(self.prior, code, box, views, slam, config, photometric=photometric, floor_height=floor,
                        height_range=support.class_height_range(fused.class_name), code_class=fused.class_name,
                        neighbour_boxes=neighbours)
        self.count('sparse_runs')
        if not result.ok:
            self.count('sparse_fallbacks')
            self.sparse_info[fused.object_id] = result.reason
            fused.stage_reason = STAGE_REASONS.index('sparse stage failed')
            if fused.object_id not in self.estimates or self.estimates[fused.object_id].stage != 'fused':
                self.estimates[fused.object_id] = fused
            elif self.estimates[fused.object_id].stage == 'fused':
                self.estimates[fused.object_id].stage_reason = fused.stage_reason
            self._publish()
            return None
        mesh = self.prior.mesh(result.code, resolution=int(self.params['mesh_resolution']))
        if mesh is None or len(mesh.faces) == 0:
            self.report_error(f'object {fused.object_id}', 'refined code decodes to no surface; fused result kept',
                              counter='warnings')
            return None
        mesh_world = mesh.copy()
        mesh_world.apply_transform(result.T_world_object)
        estimate = ObjectEstimate(fused.object_id, fused.class_name, fused.category, result.code,
                                  result.T_world_object, result.scale, world_box(mesh, result.T_world_object, result.yaw),
                                  fused.num_views, 'sparse', mesh_world,
                                  dict(fused.timings, sparse_s=time.perf_counter() - t0),
                                  STAGE_REASONS.index('in progress' if self.dense_on else 'dense stage disabled'))
        e0, e1 = result.initial_energies.get('total', np.nan), result.energies.get('total', np.nan)
        self.sparse_info[fused.object_id] = (f'{result.views} views, {result.iterations} it, E {e0:.3f}->{e1:.3f}, '
                                             f'{result.seconds:.2f}s')
        self.estimates[fused.object_id] = estimate
        self._publish()
        return estimate, result.landmarks, result.alternatives

    def _dense(self, sparse: ObjectEstimate, box, num_views: int, landmarks: np.ndarray | None,
               alternatives: list[tuple[np.ndarray, np.ndarray, str]] = ()) -> None:
        """Dense stage after a successful sparse stage: publishes the dense estimate, or keeps the sparse one
        (with the reason) when the dense result is not better or the stage cannot run. landmarks: the sparse
        stage's visual-hull landmarks of the object (None: those of the whole map near the box); alternatives:
        the sparse stage's other end states, further starts (`dense_starts`)."""
        oid = sparse.object_id
        with self.cond:
            views = self.dense_store.views_of(oid, int(self.params['fill_views']))
            slam = self.slam_points
            self.dense_views_used[oid] = num_views
            floor = support.scene_floor(self.tracks, slam)
        t0 = time.perf_counter()
        if landmarks is not None:
            slam, box = landmarks, None     # already the object's: no box selection
        result, _ = refine_dense_starts(self.prior, sparse.code, sparse.T_world_object, views, slam, box,
                                        self.dense_config(),
                                        should_stop=lambda: self.stopping,   # shutdown does not wait for a dense stage
                                        floor_height=floor, height_range=support.class_height_range(sparse.class_name),
                                        alternatives=alternatives, max_starts=int(self.params['dense_starts']))
        self.count('dense_runs')
        self.dense_info[oid] = (f'{result.views} views, {result.iterations} it, {result.seconds:.2f}s '
                                f'({result.seconds_per_iteration:.2f}s/it): {result.reason}')
        mesh = None
        if result.improved:
            mesh = self.prior.mesh(result.code, resolution=int(self.params['mesh_resolution']))
        if mesh is None or len(mesh.faces) == 0:
            if result.improved:
                self.report_error(f'object {oid}', 'dense code decodes to no surface; sparse result kept',
                                  counter='warnings')
            reason = ('dense stage failed' if 'no usable views' in result.reason or 'non-finite' in result.reason
                      or 'no surface' in result.reason else 'dense not better than sparse')
            self.count('dense_kept_sparse')
            if self.estimates.get(oid) is sparse:
                sparse.stage_reason = STAGE_REASONS.index(reason)
                sparse.timings['dense_s'] = time.perf_counter() - t0
                self._publish()
            return
        mesh_world = mesh.copy()
        mesh_world.apply_transform(result.T_world_object)
        reason = 'dense time limit' if 'time limit' in result.reason else 'all stages done'
        estimate = ObjectEstimate(oid, sparse.class_name, sparse.category, result.code, result.T_world_object,
                                  result.scale, world_box(mesh, result.T_world_object, result.yaw), sparse.num_views,
                                  'dense', mesh_world, dict(sparse.timings, dense_s=time.perf_counter() - t0),
                                  STAGE_REASONS.index(reason))
        self.estimates[oid] = estimate
        self._publish()

    # ------------------------------------------------------------ outputs
    def _mesh_marker(self, est: ObjectEstimate, stamp_ns: int, frame: str, rgba) -> Marker:
        """The TRIANGLE_LIST marker of an estimate, built once per estimate and re-stamped afterwards: a map of
        n objects is republished after every stage of every object, and building all n markers each time made
        ~40k Point messages per object; they set off full garbage collections that held the GIL for up to a
        second (optim_node's /diagnostics came 1.4-2.4 s apart under load)."""
        cached = self.mesh_markers.get(est.object_id)
        if cached is not None and cached[0] is est:   # same estimate: same mesh, class and colour
            cached[1].header.stamp = conv.ns_to_stamp(stamp_ns)
            return cached[1]
        marker = conv.mesh_to_marker(est.mesh_world.vertices, est.mesh_world.faces, est.class_name, est.object_id,
                                     stamp_ns, frame, rgba)
        self.mesh_markers[est.object_id] = (est, marker)
        return marker

    def _publish(self) -> None:
        now = self.get_clock().now().nanoseconds
        frame = self.params['world_frame']
        objects, boxes = MarkerArray(), MarkerArray()
        estimates = sorted(self.estimates.values(), key=lambda e: e.object_id)
        current = {(est.class_name, est.object_id) for est in estimates}
        # Every object this worker published and has since dropped gets a DELETE in every message, first (a
        # listener keyed by id then keeps an object whose class changed): a listener that missed a message still
        # drops it. Never DELETEALL (a share of several workers' map holds only this worker's objects).
        for ns, oid in self.retractions.update(current):
            objects.markers.append(conv.delete_marker(ns, oid, now, frame))
            boxes.markers.append(conv.delete_marker(ns, oid, now, frame))
        states = np.zeros(len(estimates), dtype=STATES_DTYPE)
        for i, est in enumerate(estimates):
            rgba = CLASS_COLOURS.get(est.class_name, (0.7, 0.7, 0.7, 1.0))
            objects.markers.append(self._mesh_marker(est, now, frame, rgba))
            center, size, yaw = est.box
            boxes.markers.append(conv.box_to_marker(center, size, yaw, est.class_name, est.object_id, now, frame,
                                                    rgba[:3] + (0.35,)))
            states[i] = (est.object_id, est.category, STAGES.index(est.stage), est.num_views, est.scale,
                         est.T_world_object.ravel(), np.r_[center, size, yaw], est.code,
                         sum(est.timings.values()), est.stage_reason)
        self.mesh_markers = {oid: entry for oid, entry in self.mesh_markers.items() if oid in self.estimates}
        if self.merger is None:       # alone: the map; worker k >= 1: its share
            self.objects_pub.publish(objects)
            self.boxes_pub.publish(boxes)
            self.states_pub.publish(conv.table_to_cloud(states, now, frame))
        else:
            with self.merge_lock:
                self.merger.put_markers('objects', 0, objects)
                self.merger.put_markers('boxes', 0, boxes)
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
        """Worker 0: another worker's share of `kind`; the merged map of that kind is published again."""
        self.count('shares_received')
        table = conv.cloud_to_table(msg) if kind == TABLE_KIND else None
        with self.merge_lock:
            if table is None:
                self.merger.put_markers(kind, worker, msg)
            else:
                self.merger.put_table(worker, table)
            self._publish_merged(kind)

    def _publish_merged(self, kind: str) -> None:
        """Worker 0 (under merge_lock): the complete map of `kind` from every share heard of (CONTRACT.md)."""
        now, frame = self.get_clock().now().nanoseconds, self.params['world_frame']
        if kind == TABLE_KIND:
            table = self.merger.merged_table()
            if table is not None:
                self.states_pub.publish(conv.table_to_cloud(table, now, frame))
        else:
            (self.objects_pub if kind == 'objects' else self.boxes_pub).publish(
                self.merger.merged_markers(kind, now, frame))
            if kind == 'objects':
                self.count('merged_maps_published')

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
    def diagnostic_values(self) -> dict:
        with self.cond:
            # distinct objects with work left: queued, deferred dense stages, and the one being reconstructed
            waiting = self.pending | self.dense_stale | ({self.busy} if self.busy is not None else set())
            state = 'busy' if waiting else 'idle'
            values = {'state': state, 'pending_objects': len(waiting),
                      'objects': len(self.estimates), 'tracks': len(self.tracks),
                      'worker': f'{self.worker_index}/{self.worker_count}',
                      **({'shares_merged': f'{len(self.merger.heard)}/{self.worker_count}'} if self.merger else {}),
                      'resumed_unrefined': len(self.resumed),
                      'sparse_objects': sum(e.stage == 'sparse' for e in self.estimates.values()),
                      'dense_objects': sum(e.stage == 'dense' for e in self.estimates.values()),
                      'views_held': len(self.view_store), 'dense_views_held': len(self.dense_store)}
            if self.sparse_info:
                oid = max(self.sparse_info)
                values['sparse_last'] = f'object {oid}: {self.sparse_info[oid]}'
            if self.dense_info:
                oid = max(self.dense_info)
                values['dense_last'] = f'object {oid}: {self.dense_info[oid]}'
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
