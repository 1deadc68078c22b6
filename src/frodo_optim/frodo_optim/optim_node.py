"""Optimiser node: turns tracks (3D boxes) and fused shape codes into placed object meshes, asynchronously
(paper Sec. 4.3; this version runs the fused stage: decode + box-fit placement, see frodo_optim.core).

In:  /frodo/tracks (latched MarkerArray of boxes), /frodo/object_codes (latched table).
Out: /frodo/objects (contract: TRIANGLE_LIST per object, world vertices), /frodo/boxes (contract: CUBE per
     object), /frodo/object_states (latched table for the command line's objects.json), /diagnostics with
     state idle|busy and pending_objects.
"""
from __future__ import annotations

import threading
import time

import numpy as np
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import Marker, MarkerArray

from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.categories import category_by_id
from frodo_common.node import ERROR, OK, WARN, FrodoNode, run_node
from frodo_common.params import ParamSpec
from frodo_optim.core import ObjectEstimate, fused_estimate
from frodo_optim.states import OBJECT_STATES, STAGES, STATES_DTYPE
from frodo_shape.prior import ShapePrior

PARAMS = (
    ParamSpec('prior', 'furniture', 'Shipped prior name (frodo_shape/priors/<name>) or path to a prior folder.'),
    ParamSpec('device', 'auto', "Torch device: 'auto' (cuda if available), 'cpu' or 'cuda'."),
    ParamSpec('mesh_resolution', 64, 'Marching-cubes grid resolution for decoded meshes.'),
    ParamSpec('min_views', 2, 'Views (kept, associated detections) an object needs before it is reconstructed.'),
    ParamSpec('code_change_tolerance', 0.02,
              'Re-decode the mesh only when the fused code moved by more than this (relative L2); '
              'box updates alone just re-place the cached mesh.'),
)

CLASS_COLOURS = {'chair': (0.95, 0.55, 0.15, 1.0), 'dining table': (0.2, 0.6, 0.95, 1.0)}


class OptimNode(FrodoNode):
    """Keeps a pending set of objects whose inputs changed; a worker thread reconstructs them one by one."""

    def __init__(self, **kwargs):
        super().__init__('optim_node', PARAMS, **kwargs)
        self.prior = ShapePrior.load(self.params['prior'], device=self.params['device'])
        self.tracks: dict[int, tuple[str, tuple]] = {}             # id -> (class, (centre, size, yaw))
        self.codes: dict[int, tuple[int, int, np.ndarray]] = {}     # id -> (category, views, code)
        self.estimates: dict[int, ObjectEstimate] = {}
        self.mesh_cache: dict[int, tuple[np.ndarray, object]] = {}  # id -> (code, normalised mesh)
        self.published_ids: set[tuple[str, int]] = set()
        self.pending: set[int] = set()
        self.busy = False
        self.cond = threading.Condition()
        self.stopping = False
        self.objects_pub = self.create_publisher(MarkerArray, topics.OBJECTS, topics.LATCHED_QOS)
        self.boxes_pub = self.create_publisher(MarkerArray, topics.BOXES, topics.LATCHED_QOS)
        self.states_pub = self.create_publisher(PointCloud2, OBJECT_STATES, topics.LATCHED_QOS)
        self.create_subscription(MarkerArray, topics.TRACKS, self.guarded(self._on_tracks, 'tracks'),
                                 topics.LATCHED_QOS)
        self.create_subscription(PointCloud2, topics.OBJECT_CODES, self.guarded(self._on_codes, 'object_codes'),
                                 topics.LATCHED_QOS)
        self.worker = threading.Thread(target=self._work, name='optim_worker', daemon=True)
        self.worker.start()

    # ------------------------------------------------------------ inputs
    def _on_tracks(self, msg: MarkerArray) -> None:
        self.count('tracks_received')
        with self.cond:
            for m in msg.markers:
                if m.action == Marker.DELETEALL:
                    self.tracks.clear()
                elif m.action == Marker.DELETE:
                    self.tracks.pop(m.id, None)
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
                code = np.asarray(row['code'], dtype=np.float32)
                if not np.all(np.isfinite(code)):
                    self.report_error('object_codes', f'object {oid}: non-finite code ignored')
                    continue
                old = self.codes.get(oid)
                if old is None or old[1] != int(row['num_views']) or not np.array_equal(old[2], code):
                    self.codes[oid] = (int(row['category']), int(row['num_views']), code)
                    self.pending.add(oid)
            self.cond.notify()

    # ------------------------------------------------------------ worker
    def _work(self) -> None:
        while True:
            with self.cond:
                while not self.pending and not self.stopping:
                    self.cond.wait(timeout=0.5)
                if self.stopping:
                    return
                oid = min(self.pending)
                self.pending.discard(oid)
                self.busy = True
                track, codes = self.tracks.get(oid), self.codes.get(oid)
            try:
                self._reconstruct(oid, track, codes)
            except Exception as err:  # noqa: BLE001 - one bad object must not stop the others
                self.report_error(f'object {oid}', err)
            finally:
                with self.cond:
                    self.busy = False

    def _reconstruct(self, oid: int, track, codes) -> None:
        if track is None or codes is None or codes[1] < int(self.params['min_views']):
            if track is None and oid in self.estimates:
                del self.estimates[oid]
                self._publish()
            return
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
        self.estimates[oid] = estimate
        self._publish()

    # ------------------------------------------------------------ outputs
    def _publish(self) -> None:
        now = self.get_clock().now().nanoseconds
        frame = self.params['world_frame']
        objects, boxes = MarkerArray(), MarkerArray()
        current = set()
        states = np.zeros(len(self.estimates), dtype=STATES_DTYPE)
        for i, est in enumerate(sorted(self.estimates.values(), key=lambda e: e.object_id)):
            rgba = CLASS_COLOURS.get(est.class_name, (0.7, 0.7, 0.7, 1.0))
            objects.markers.append(conv.mesh_to_marker(est.mesh_world.vertices, est.mesh_world.faces,
                                                       est.class_name, est.object_id, now, frame, rgba))
            center, size, yaw = est.box
            boxes.markers.append(conv.box_to_marker(center, size, yaw, est.class_name, est.object_id, now, frame,
                                                    rgba[:3] + (0.35,)))
            current.add((est.class_name, est.object_id))
            states[i] = (est.object_id, est.category, STAGES.index(est.stage), est.num_views, est.scale,
                         est.T_world_object.ravel(), np.r_[center, size, yaw], est.code,
                         sum(est.timings.values()))
        for ns, oid in self.published_ids - current:
            objects.markers.append(conv.delete_marker(ns, oid, now, frame))
            boxes.markers.append(conv.delete_marker(ns, oid, now, frame))
        self.published_ids = current
        self.objects_pub.publish(objects)
        self.boxes_pub.publish(boxes)
        self.states_pub.publish(conv.table_to_cloud(states, now, frame))
        self.count('maps_published')

    # ------------------------------------------------------------ diagnostics and shutdown
    def diagnostic_values(self) -> dict:
        with self.cond:
            state = 'busy' if (self.busy or self.pending) else 'idle'
            return {'state': state, 'pending_objects': len(self.pending) + int(self.busy),
                    'objects': len(self.estimates), 'tracks': len(self.tracks)}

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
