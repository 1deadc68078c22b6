"""Incremental association (paper Sec. 5.1): `Associator` turns per-frame detections into objects with stable
ids, confirmation ("publishing"), 3D boxes and pruning flags (numpy/scipy, no ROS).

DP-means over ray segments (`frodo_association.segments`) runs incrementally: each frame's segments are
matched to the centres of their class by a Hungarian assignment gated by lambda, because a frame sees an object at most
once, and the centres of the touched clusters are re-estimated; every `full_pass_every` frames a full EM
pass re-assigns every segment (with hysteresis, `reassign_ratio`, against drift between neighbouring
clusters along long segments) until the assignment is stable.
Ids are never reused and never renumbered: a cluster keeps its id until it is merged away (two centres of
one class closer than `merge_distance`; the older id survives) or emptied by a full pass.
Same-frame duplicates and splits: when a merge or a full pass puts two detections of one frame on one
object, the one nearer the centre keeps it and the other is ignored (object id -1); a segment within
lambda of a centre that a closer detection of its frame already holds is ignored rather than opening a
cluster (a split mask or a duplicate detection). Detections touching the image border or smaller than
the pruning size are "unreliable": they join clusters but open none (they count as consistent evidence).
Always-truncated objects (the project's own extension; the paper does not address them): truncated
detections that stay unassigned and lie farther than lambda from every centre of their class are pooled;
at each full pass the pool of a class is clustered among itself with the same segment DP-means (leader
opening at lambda, then least-squares centres and nearest-centre re-assignment, then merges of groups while
the DP-means objective falls, `segments.merge_segment_groups`: near-parallel rays of a narrow baseline are
split by the leader sweep, and a group's centre on its own segments never lets it dissolve), and a group with
detections from at least `truncated_min_views` distinct frames, whose centre is at least
`truncated_merge_distance` from every cluster of its class, opens a cluster (one detection per frame, the
nearest). Pooled detections explained by a published object's 3D box (IoU of the detection box with the
object's projected box, clipped to the image, at least `truncated_explained_iou`) are left out: the visible
end of a long table is far from the table's centre. Such a cluster counts its truncated detections towards
publishing (until it has min_track_views reliable ones) and merges with a cluster of its class within
`truncated_merge_distance` (rather than merge_distance). At every full pass, a cluster most of whose
detections are explained by another published object's box is merged into it (`merge_explained`), so an
object first seen truncated and later whole is not duplicated by the biased centres of its truncated views
(this also merges the two halves of a long table seen from its ends, whose centres stay apart), and two
published objects never in one frame merge when one lies in the frustums of the other's detections
(`_frustum_duplicates`: a table too long for the view, split as the view turns along it).
Publishing ("confirmed") from geometry, not from frame counts: a cluster is published once its detections in
`min_track_views` frames are mutually consistent (their segments pass within `confirm_distance` of its centre;
detections cut by the border or by a nearer instance count), one of them reliable, and it was detected in at least
`min_hit_ratio` of the frames with its centre in view; while its centre is still in view it waits until it has
been in view for `confirm_window` frames (at the end of the input, `settle`, it does not). A spurious detection
in one frame never meets this; a piece of furniture seen from one side in 3 keyframes far apart does. A
published cluster whose hit ratio drops below `drop_hit_ratio` (checked at full passes) is withdrawn.
Unpublished clusters' detections carry object id -1.

Pixel sizes (min_box_width, min_box_height) are given for a 640x480 image and scaled by
s = sqrt(W * H / (640 * 480)) for a W x H image (`frodo_detection.core.resolution_scale`); border_margin
is in plain pixels.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from frodo_association.boxes import (CLASS_SHAPES, Box3D, box_area, box_inside_fraction, box_iou, clip_boxes,
                                     fit_box, footprint_overlap, project_boxes)
from frodo_association.config import ASSOCIATION_DTYPE, AssociationConfig
from frodo_association.pruning import prune_detections
from frodo_association.segments import (box_segments, clip_segments_to_heights, complete_truncated_boxes,
                                        depth_intervals, gated_assignment, lsq_center, lsq_centers,
                                        merge_segment_groups, point_segment_distance, ray_segments,
                                        surface_intervals)
from frodo_common.categories import category_by_id
from frodo_common.geometry import invert_transform
from frodo_detection.core import instance_boxes, resolution_scale


def class_shape(coco_id: int, size_range: tuple[float, float]) -> tuple[float, float, float]:
    """Typical (long, short, height) of a class (`CLASS_SHAPES`); a cube of the geometric-mean size for others."""
    if int(coco_id) in CLASS_SHAPES:
        return CLASS_SHAPES[int(coco_id)]
    s = float(np.sqrt(size_range[0] * size_range[1]))
    return (s, s, s)


@dataclass
class ObjectTrack:
    """One cluster: id, class, centre (3,), published ("confirmed") or not, 3D box (None until fitted), its
    detection count at the last box fit, whether the deferred truncated rule opened it (until it merges
    with another cluster or gains min_track_views reliable detections), whether it merged a cluster opened
    that way with an ordinary one (its centre then comes from its untruncated detections), and the frame from
    which its detections are all held (max_detections_per_object thins older ones; its hit ratio counts from there)."""

    object_id: int
    coco_id: int
    center: np.ndarray
    confirmed: bool = False
    box: Box3D | None = None
    fitted_views: int = 0
    from_truncated: bool = False
    whole_view_center: bool = False
    recent_from: int = 0        # frame index from which its detections are all held (older ones thinned)


@dataclass
class AssociationUpdate:
    """What one `add_frame` or `refine_boxes` call changed.

    stamp / table: the new frame and its rows (ASSOCIATION_DTYPE) (`add_frame` only; None otherwise);
    republish: stamps of earlier frames whose rows (object ids or kept flags) changed, oldest first;
    removed: {object id no longer published: id it was merged into, or -1};
    tracks_changed: an object's box or existence changed (re-send the tracks); fitted: ids whose box was fitted.
    """

    stamp: int | None = None
    table: np.ndarray | None = None
    republish: list[int] = field(default_factory=list)
    removed: dict[int, int] = field(default_factory=dict)
    tracks_changed: bool = False
    fitted: list[int] = field(default_factory=list)


class _Table:
    """Named columns (numpy arrays sharing the first axis) with amortised O(1) append."""

    def __init__(self, **columns: tuple[tuple[int, ...], type, object]):
        self.n = 0
        self._fill = {name: fill for name, (_, _, fill) in columns.items()}
        self._cols = {name: np.full((16,) + shape, fill, dtype) for name, (shape, dtype, fill) in columns.items()}

    def append(self, **values) -> slice:
        """Append k rows (every column given, first axis k); returns their slice."""
        k = len(next(iter(values.values())))
        cap = len(next(iter(self._cols.values())))
        if self.n + k > cap:
            for name, arr in self._cols.items():
                grown = np.full((max(2 * cap, self.n + k),) + arr.shape[1:], self._fill[name], arr.dtype)
                grown[:self.n] = arr[:self.n]
                self._cols[name] = grown
        for name, arr in values.items():
            self._cols[name][self.n:self.n + k] = arr
        self.n += k
        return slice(self.n - k, self.n)

    def keep(self, mask: np.ndarray) -> None:
        """Keep only the rows where mask (n,) is True, in order, in newly allocated columns (the old ones are freed)."""
        n = int(np.count_nonzero(mask))
        for name, arr in self._cols.items():
            kept = np.full((max(16, 2 * n),) + arr.shape[1:], self._fill[name], arr.dtype)
            kept[:n] = arr[:self.n][mask]
            self._cols[name] = kept
        self.n = n

    def __getattr__(self, name: str) -> np.ndarray:
        cols = self.__dict__.get('_cols')
        if cols is None or name not in cols:
            raise AttributeError(name)
        return cols[name][:self.n]

    def __len__(self) -> int:
        return self.n


class Associator:
    """Incremental DP-means association of per-frame detections into objects with 3D boxes and pruning.

    `add_frame` per frame (fast: clustering, merges, pruning with the current boxes); `refine_boxes`
    after it (box fits, bounded per call). Detections are rows of `self.rows` (segment, box, label, class,
    frame, cluster `assign`, `kept`), frames rows of `self.frames` (stamp, K, poses, size, row range).
    """

    def __init__(self, cfg: AssociationConfig | None = None):
        self.cfg = cfg or AssociationConfig()
        self.rows = _Table(segment=((2, 3), np.float64, 0.0), box=((4,), np.float64, 0.0),
                           edge_valid=((4,), bool, False), fit_edges=((4,), bool, False),
                           label=((), np.int64, 0), coco=((), np.int64, 0),
                           frame=((), np.int64, 0), assign=((), np.int64, -1), kept=((), bool, False),
                           valid=((), bool, False), reliable=((), bool, False), truncated=((), bool, False),
                           evidence=((), bool, False), surface=((), np.float64, np.nan),
                           points=((self.cfg.box_points_per_detection, 3), np.float32, np.nan),
                           sent_id=((), np.int64, -1), sent_kept=((), bool, False),   # as last published
                           slot=((), np.int64, 0))                                    # position in its frame
        self.frames = _Table(stamp=((), np.int64, 0), K=((3, 3), np.float64, 0.0),
                             T_world_camera=((4, 4), np.float64, 0.0), T_camera_world=((4, 4), np.float64, 0.0),
                             size=((2,), np.float64, 0.0), start=((), np.int64, 0), stop=((), np.int64, 0))
        self.frame_index: dict[int, int] = {}
        self.tracks: dict[int, ObjectTrack] = {}
        self.next_id = 0
        self.merges = 0
        self._frames_since_pass = 0                 # full-pass cadence: frames and camera travel since the last
        self._travel = 0.0
        self._last_eye: np.ndarray | None = None
        self._corners: dict[int, tuple[Box3D, np.ndarray]] = {}   # object id -> (its box, that box's corners)
        # Retired detections (max_detections_per_object) of frames that still hold live rows: frame index ->
        # (positions in the frame (k,), their last published rows (k,) ASSOCIATION_DTYPE), for republishing.
        self._retired: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.retired = 0                            # detections retired so far

    # ------------------------------------------------------------ public API
    def add_frame(self, stamp: int, K: np.ndarray, T_world_camera: np.ndarray, size: tuple[int, int],
                  labels: np.ndarray, boxes: np.ndarray, surface_depth: np.ndarray | None = None,
                  contact: np.ndarray | None = None, surface_points: np.ndarray | None = None) -> AssociationUpdate:
        """Associate one frame's detections (clustering, merges, confirmation, pruning with the current boxes).

        stamp: frame stamp (ns); K: (3, 3); T_world_camera: (4, 4); size: image (width, height);
        labels: (N,) contract instance labels; boxes: (N, 4) detection boxes; surface_depth: optional (N,)
        optical depth (m) of each detection's visible surface (`evidence.surface_depths`; NaN: unknown). A
        stamp seen before is ignored (its current rows are returned). Box fits are left to `refine_boxes`.
        With a surface depth a detection's segment is [d_s - surface_slack, d_s + half the class's horizontal
        diagonal] on its ray, the ray of a truncated box is completed (`complete_truncated`), a truncated
        detection may open clusters (`evidence_opens_clusters`), the segment lies at the class's typical centre
        height (`flat_segments`, objects on the floor), and one lower than occluded_fraction of the
        class's typical projected height (not cut vertically) is occluded: it joins clusters but opens none.
        contact: optional (N, 4) bool, box edges where the mask meets another instance (`evidence.contact_edges`):
        with `box_contact_edges` the box fit treats them like edges on the image border.
        surface_points: optional (N, k, 3) world points of each detection's visible surface from a depth image
        (`evidence.mask_points`, NaN: none; the first box_points_per_detection are kept): the box fit keeps them
        inside the box (`box_points_weight`).
        """
        if stamp in self.frame_index:
            return AssociationUpdate(stamp, self.frame_table(stamp))
        cfg = self.cfg
        labels = np.asarray(labels, dtype=np.int64).reshape(-1)
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        K = np.asarray(K, dtype=np.float64)
        T_world_camera = np.asarray(T_world_camera, dtype=np.float64)
        coco = labels >> 8
        cats = [category_by_id(c) for c in coco]
        valid = np.array([c is not None for c in cats], dtype=bool) & np.all(np.isfinite(boxes), axis=1) \
            & (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
        size_ranges = np.array([c.size_range if c is not None else (1.0, 1.0) for c in cats]).reshape(-1, 2)
        w, h = size
        m = cfg.border_margin
        scale = resolution_scale(w, h)
        edge_valid = np.stack([boxes[:, 0] > m - 0.5, boxes[:, 1] > m - 0.5,
                               boxes[:, 2] < w - 0.5 - m, boxes[:, 3] < h - 0.5 - m], axis=1)
        big_enough = (boxes[:, 2] - boxes[:, 0] >= cfg.min_box_width * scale) \
            & (boxes[:, 3] - boxes[:, 1] >= cfg.min_box_height * scale)
        truncated = ~edge_valid.all(axis=1)
        fit_edges = edge_valid.copy()
        if contact is not None and cfg.box_contact_edges:
            fit_edges &= ~np.asarray(contact, dtype=bool).reshape(-1, 4)
        segments = box_segments(boxes, K, T_world_camera, size_ranges, cfg.depth_margin, cfg.min_depth,
                                cfg.max_depth)
        surface = np.full(len(labels), np.nan) if surface_depth is None \
            else np.asarray(surface_depth, dtype=np.float64).reshape(-1)
        if len(surface) != len(labels):
            raise ValueError(f'surface_depth has {len(surface)} entries for {len(labels)} detections')
        # Implausible surface depths are dropped: the map's points inside a mask are on the object or behind it,
        # and an untextured chair has none, so its "surface" is the table or wall behind (0.5-2 m too far). A box
        # that wide cannot come from an object of the class that far: beyond the size interval's far end, or
        # wider than the class's typical horizontal diagonal (widened by depth_margin) spans there.
        diag = np.array([np.hypot(*class_shape(c, r)[:2]) for c, r in zip(coco, size_ranges)]).reshape(-1)
        far = np.minimum(depth_intervals(boxes, K, size_ranges, cfg.depth_margin, cfg.min_depth, cfg.max_depth)[:, 1],
                         K[0, 0] * diag * (1 + cfg.depth_margin) / np.maximum(boxes[:, 2] - boxes[:, 0], 1e-6))
        has_depth = valid & np.isfinite(surface) & (surface > 0) & (surface <= far)
        occluded = np.zeros(len(labels), dtype=bool)
        if has_depth.any():
            shapes = np.array([class_shape(c, r) for c, r in zip(coco[has_depth], size_ranges[has_depth])])
            extent = 0.5 * np.hypot(shapes[:, 0], shapes[:, 1])
            ray_boxes = boxes[has_depth]
            if cfg.complete_truncated:
                ray_boxes = complete_truncated_boxes(ray_boxes, edge_valid[has_depth], K,
                                                     surface[has_depth] + 0.5 * shapes[:, 1], shapes)
            segments[has_depth] = ray_segments(ray_boxes, K, T_world_camera, surface_intervals(
                surface[has_depth], extent, cfg.surface_slack, cfg.min_depth, cfg.max_depth))
            if cfg.objects_on_floor and cfg.flat_segments:
                # Centre height from the class, not from the box: the box centre of a chair seen over a table
                # (lower half hidden) or cut at the top is 0.3 m too high; x, y and depth stay the ray's.
                segments[has_depth, :, 2] = (cfg.floor_height + 0.5 * shapes[:, 2])[:, None]
            # Occluded: whole vertically, yet much lower than the class's typical height at that depth (a chair
            # back above a table): its box-centre ray misses the object centre, so it must not open clusters.
            expected_h = K[1, 1] * shapes[:, 2] / (surface[has_depth] + 0.5 * shapes[:, 1])
            low = (boxes[has_depth, 3] - boxes[has_depth, 1]) < cfg.occluded_fraction * expected_h
            occluded[has_depth] = low & edge_valid[has_depth][:, 1] & edge_valid[has_depth][:, 3]
        if cfg.objects_on_floor:     # the centre of an object standing on the floor is at half its height
            segments = clip_segments_to_heights(segments, cfg.floor_height + 0.25 * size_ranges[:, 0],
                                                cfg.floor_height + 0.5 * size_ranges[:, 1] * (1 + cfg.depth_margin))
        evidence_opens = has_depth & cfg.evidence_opens_clusters & ~occluded
        opens = (cfg.truncated_opens_clusters | ~truncated | evidence_opens) & ~occluded
        points = np.full((len(labels), cfg.box_points_per_detection, 3), np.nan, np.float32)
        if surface_points is not None:
            given = np.asarray(surface_points, dtype=np.float32)[:, :cfg.box_points_per_detection]
            if given.shape[0] != len(labels):
                raise ValueError(f'surface_points has {given.shape[0]} entries for {len(labels)} detections')
            points[:, :given.shape[1]] = np.where(valid[:, None, None], given, np.nan)
        fi = len(self.frames)
        rows = self.rows.append(points=points, segment=segments, box=boxes, edge_valid=edge_valid, fit_edges=fit_edges,
                                label=labels, coco=coco,
                                frame=np.full(len(labels), fi), assign=np.full(len(labels), -1),
                                kept=np.zeros(len(labels), bool), valid=valid, slot=np.arange(len(labels)),
                                surface=np.where(has_depth, surface, np.nan), reliable=valid & big_enough & opens,
                                truncated=valid & big_enough & truncated & ~evidence_opens,
                                evidence=valid & big_enough)
        self.frames.append(stamp=[stamp], K=K[None], T_world_camera=T_world_camera[None],
                           T_camera_world=invert_transform(T_world_camera)[None], size=[(w, h)],
                           start=[rows.start], stop=[rows.stop])
        self.frame_index[stamp] = fi
        self._update_centers(self._assign_frame(rows))
        dirty: set[int] = set()
        removed: dict[int, int] = {}
        eye = T_world_camera[:3, 3]
        self._travel += float(np.linalg.norm(eye - self._last_eye)) if self._last_eye is not None else 0.0
        self._last_eye = eye.copy()
        self._frames_since_pass += 1
        full = (cfg.full_pass_every > 0 and self._frames_since_pass >= cfg.full_pass_every) \
            or (cfg.full_pass_distance > 0 and self._travel >= cfg.full_pass_distance)
        if full:
            self._frames_since_pass, self._travel = 0, 0.0
        if full:
            changed, gone = self.full_pass()
            dirty |= changed
            removed.update(gone)
            for merge in (self.merge_explained, self.merge_consistent):
                gone, merge_frames = merge()
                removed.update(gone)
                dirty |= merge_frames
        merged, merge_frames = self.merge_close()
        removed.update(merged)
        confirm_frames, dropped = self._update_confirmation(recheck=full)
        removed.update(dropped)
        dirty |= merge_frames | confirm_frames
        dirty.discard(fi)
        self._prune_frames(sorted(dirty | {fi}))
        dirty |= self._keep_best_views(dirty | {fi}) - {fi}
        table = self.frame_table(stamp)
        sl = self._frame_rows(fi)
        self.rows.sent_id[sl], self.rows.sent_kept[sl] = table['object_id'], table['kept']
        removed = {k: v for k, v in removed.items() if not (k in self.tracks and self.tracks[k].confirmed)}
        update = AssociationUpdate(stamp, table, self._changed_stamps(dirty), removed, bool(removed))
        self._retire_history()
        return update

    def settle(self) -> AssociationUpdate:
        """End of the input (or a pause): a full pass, the merges, and confirmation as if every cluster had left
        the view (an object still in view in the last frames is published on its consistent detections), then
        pruning of every frame with the final boxes (the merges again after each round of box fits). Returns what
        changed (republish stamps, removed ids)."""
        dirty, removed = self.full_pass()
        for merge in (self.merge_explained, self.merge_consistent):
            gone, merge_frames = merge()
            removed.update(gone)
            dirty |= merge_frames
        merged, merge_frames = self.merge_close()
        removed.update(merged)
        dirty |= merge_frames
        confirm_frames, dropped = self._update_confirmation(recheck=True, final=True)
        removed.update(dropped)
        dirty |= confirm_frames
        republish: set[int] = set()
        while (refined := self.refine_boxes(max_fits=100)).fitted:
            republish.update(refined.republish)
            # Objects confirmed just now get their first boxes here: a duplicate of a published object (the
            # far end of a table seen in the last frames) shows only now, by its box's footprint.
            gone, merge_frames = self.merge_explained()
            removed.update(gone)
            dirty |= merge_frames
        every = list(range(len(self.frames)))
        self._prune_frames(every)
        self._keep_best_views(set(every))
        republish.update(self._changed_stamps(set(every)))
        removed = {k: v for k, v in removed.items() if not (k in self.tracks and self.tracks[k].confirmed)}
        return AssociationUpdate(republish=sorted(republish), removed=removed, tracks_changed=True)

    def refine_boxes(self, max_fits: int | None = None) -> AssociationUpdate:
        """Fit the boxes of the objects that grew most since their last fit (at most `max_fits`, default
        max_box_fits_per_frame; objects without a box first) and re-prune their frames."""
        cfg = self.cfg
        limit = cfg.max_box_fits_per_frame if max_fits is None else max_fits
        counts = np.bincount(self.rows.assign[self.rows.assign >= 0], minlength=self.next_id)
        due = []
        for t in self.confirmed_tracks():
            n = int(counts[t.object_id])
            if t.box is None or n >= max(t.fitted_views + 1, np.ceil(t.fitted_views * cfg.box_refit_growth)):
                due.append((t.box is not None, -n / max(t.fitted_views, 1), t.object_id, n))
        fitted = []
        for _, _, oid, n in sorted(due)[:limit]:
            self.fit_object_box(oid)
            self.tracks[oid].fitted_views = n
            fitted.append(oid)
        if not fitted:
            return AssociationUpdate()
        dirty = set(np.unique(self.rows.frame[np.isin(self.rows.assign, fitted)]).tolist())
        self._prune_frames(sorted(dirty))
        dirty |= self._keep_best_views(dirty)
        return AssociationUpdate(republish=self._changed_stamps(dirty), tracks_changed=True, fitted=fitted)

    def frame_table(self, stamp: int) -> np.ndarray:
        """Current rows (ASSOCIATION_DTYPE) of a processed frame."""
        fi = self.frame_index[stamp]
        sl = self._frame_rows(fi)
        ids, kept = self._row_ids(sl)
        out = np.zeros(len(ids), dtype=ASSOCIATION_DTYPE)
        out['label'] = self.rows.label[sl]
        out['bbox'] = self.rows.box[sl]
        centers = np.array([self.tracks[a].center if a >= 0 else (np.nan,) * 3 for a in ids]).reshape(-1, 3)
        out['x'], out['y'], out['z'] = centers.T
        out['object_id'] = ids
        out['kept'] = kept
        if fi not in self._retired:
            return out
        positions, retired = self._retired[fi]              # retired rows as last published, in frame order
        full = np.zeros(len(out) + len(retired), dtype=ASSOCIATION_DTYPE)
        full[self.rows.slot[sl]] = out
        full[positions] = retired
        return full

    def confirmed_tracks(self) -> list[ObjectTrack]:
        """Published objects (confirmed clusters), by id."""
        return [t for _, t in sorted(self.tracks.items()) if t.confirmed]

    def members(self, object_id: int) -> np.ndarray:
        """Row indices of a cluster's detections."""
        return np.nonzero(self.rows.assign == object_id)[0]

    # ------------------------------------------------------------ bookkeeping
    def _retire_history(self) -> None:
        """Bounded history (max_detections_per_object = B > 0; long runs, issue 12). A cluster holding more than B
        detections keeps its newest B - B // 2 and, of the older ones, at most B // 2 from frames at multiples of a
        power-of-two stride (an even subsample that only ever drops rows: viewpoints spread over its history for
        the centre and the box; its hit ratio counts from the recent, complete part, `ObjectTrack.recent_from`);
        detections unassigned for B frames are retired too. Retired rows leave `self.rows` (no longer clustered,
        pruned, counted or republished; the columns are reallocated, so their memory is freed); a retired detection
        keeps what was last published for it, which `frame_table` returns while its frame still has live rows
        (with its object's current centre)."""
        cap = self.cfg.max_detections_per_object
        if cap <= 0:
            return
        assign, frame = self.rows.assign, self.rows.frame
        retire = (assign < 0) & (frame < len(self.frames) - cap)
        counts = np.bincount(assign[assign >= 0], minlength=self.next_id)
        for oid in np.nonzero(counts > cap)[0].tolist():
            rows = np.nonzero(assign == oid)[0]                              # oldest first
            older = rows[:len(rows) - (cap - cap // 2)]
            stride = 1                  # frames at multiples of a doubling stride: an even subsample, nested in time
            while np.count_nonzero(frame[older] % stride == 0) > cap // 2 and cap // 2 > 0:
                stride *= 2
            retire[older[(frame[older] % stride != 0) | (cap // 2 == 0)]] = True
            self.tracks[oid].recent_from = int(frame[older[-1]]) + 1
        if not retire.any():
            return
        gone = np.nonzero(retire)[0]
        table = np.zeros(len(gone), dtype=ASSOCIATION_DTYPE)
        table['label'], table['bbox'] = self.rows.label[gone], self.rows.box[gone]
        ids = self.rows.sent_id[gone]
        table['object_id'], table['kept'] = ids, self.rows.sent_kept[gone]
        table['x'], table['y'], table['z'] = np.array(
            [self.tracks[a].center if a in self.tracks else (np.nan,) * 3 for a in ids.tolist()]).reshape(-1, 3).T
        fis, starts = np.unique(frame[gone], return_index=True)
        for fi, part in zip(fis.tolist(), np.split(np.arange(len(gone)), starts[1:])):
            positions, rows_out = self.rows.slot[gone[part]], table[part]
            if fi in self._retired:
                positions = np.concatenate([self._retired[fi][0], positions])
                rows_out = np.concatenate([self._retired[fi][1], rows_out])
            self._retired[fi] = (positions, rows_out)
        live = np.concatenate([[0], np.cumsum(~retire)])                  # new row index of each old one
        self.frames.start[:], self.frames.stop[:] = live[self.frames.start], live[self.frames.stop]
        self.rows.keep(~retire)
        self.retired += len(gone)
        for fi in fis.tolist():                  # a frame without live rows is never republished
            if self.frames.start[fi] == self.frames.stop[fi]:
                del self._retired[fi]

    def _frame_rows(self, fi: int) -> slice:
        return slice(int(self.frames.start[fi]), int(self.frames.stop[fi]))

    def _row_ids(self, rows: slice | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(published object ids (-1 unless assigned to a confirmed cluster), kept flags) of detection rows."""
        assign = self.rows.assign[rows]
        confirmed = np.zeros(self.next_id + 1, dtype=bool)
        confirmed[[t.object_id for t in self.tracks.values() if t.confirmed]] = True
        ids = np.where(confirmed[assign], assign, -1)
        return ids, self.rows.kept[rows] & (ids >= 0)

    def _changed_stamps(self, frame_indices: set[int]) -> list[int]:
        """Stamps of the given (already published) frames whose rows differ from what was last published (and
        mark them sent), in frame order."""
        rows = self._rows_of_frames(np.array(sorted(frame_indices), dtype=np.int64))
        ids, kept = self._row_ids(rows)
        changed = (ids != self.rows.sent_id[rows]) | (kept != self.rows.sent_kept[rows])
        self.rows.sent_id[rows], self.rows.sent_kept[rows] = ids, kept
        return self.frames.stamp[np.unique(self.rows.frame[rows[changed]])].tolist()

    def _rows_of_frames(self, fis: np.ndarray) -> np.ndarray:
        """Detection rows of the frames fis (F,), frame after frame."""
        starts, counts = self.frames.start[fis], self.frames.stop[fis] - self.frames.start[fis]
        return np.arange(counts.sum()) + np.repeat(starts - (np.cumsum(counts) - counts), counts)

    def _frames_of(self, object_ids) -> set[int]:
        """Frame indices with a detection of any of the given clusters."""
        return set(np.unique(self.rows.frame[np.isin(self.rows.assign, list(object_ids))]).tolist())

    # ------------------------------------------------------------ clustering
    def _new_track(self, row: int) -> int:
        """Open a cluster at the midpoint of detection `row`'s segment."""
        oid = self.next_id
        self.next_id += 1
        seg = self.rows.segment[row]
        self.tracks[oid] = ObjectTrack(oid, int(self.rows.coco[row]), (seg[0] + seg[1]) / 2)
        self.rows.assign[row] = oid
        return oid

    def _class_centers(self, coco: int) -> tuple[np.ndarray, np.ndarray]:
        ids = np.array([t.object_id for t in self.tracks.values() if t.coco_id == coco], dtype=np.int64)
        centers = np.array([self.tracks[i].center for i in ids]).reshape(-1, 3)
        return ids, centers

    def _assign_frame(self, rows: slice) -> set[int]:
        """Assign one frame's detections (DP-means step with same-frame exclusivity); returns touched ids."""
        touched: set[int] = set()
        idx = np.arange(rows.start, rows.stop)[self.rows.valid[rows]]
        for coco in np.unique(self.rows.coco[idx]):
            sel = idx[self.rows.coco[idx] == coco]
            ids, centers = self._class_centers(coco)
            dist = point_segment_distance(centers, self.rows.segment[sel])
            match = gated_assignment(dist, self.cfg.cluster_penalty)
            self.rows.assign[sel[match >= 0]] = ids[match[match >= 0]]
            touched.update(ids[match[match >= 0]].tolist())
            far = (dist.min(axis=1) if dist.shape[1] else np.full(len(sel), np.inf)) >= self.cfg.cluster_penalty
            for i in sel[(match < 0) & far & self.rows.reliable[sel]]:
                self._new_track(int(i))
        return touched

    def _update_centers(self, ids) -> None:
        """Re-estimate the centres of the given clusters from their member segments (one batched solve). A cluster
        merged with one opened by the deferred truncated rule (`ObjectTrack.whole_view_center`, with
        whole_view_centers) uses only its untruncated detections once it has min_track_views of them: the
        box-centre rays of the truncated ones are biased towards the visible part and drag the merged centre."""
        ids = np.asarray(sorted(ids), dtype=np.int64)
        if len(ids) == 0:
            return
        slot = np.full(self.next_id + 1, -1, np.int64)
        slot[ids] = np.arange(len(ids))
        rows = np.nonzero(slot[self.rows.assign] >= 0)[0]
        group = slot[self.rows.assign[rows]]
        if self.cfg.whole_view_centers:
            whole = self.rows.edge_valid[rows].all(axis=1)
            flagged = np.array([self.tracks[int(i)].whole_view_center for i in ids], dtype=bool)
            only_whole = flagged & (np.bincount(group[whole], minlength=len(ids)) >= self.cfg.min_track_views)
            sel = whole | ~only_whole[group]
            rows, group = rows[sel], group[sel]
        # At most max_center_segments per cluster, evenly spread over its detections (bounded cost).
        order = np.argsort(group, kind='stable')
        rows, group = rows[order], group[order]
        counts = np.bincount(group, minlength=len(ids))
        rank = np.arange(len(rows)) - (np.cumsum(counts) - counts)[group]
        cap, n = self.cfg.max_center_segments, counts[group]
        keep = (n <= cap) | ((rank * cap) // np.maximum(n, 1) != ((rank - 1) * cap) // np.maximum(n, 1))
        centers = lsq_centers(self.rows.segment[rows[keep]], group[keep], len(ids), self.cfg.center_prior_weight)
        for oid, c in zip(ids, centers):
            if np.all(np.isfinite(c)):
                self.tracks[int(oid)].center = c

    def _box_corners(self, boxed: list[ObjectTrack]) -> np.ndarray:
        """World corners (O, 8, 3) of the boxes of the given tracks, cached per box (pruning projects them every
        frame; a box is replaced, never changed in place, when it is refitted or merged)."""
        out = np.empty((len(boxed), 8, 3))
        for k, t in enumerate(boxed):
            cached = self._corners.get(t.object_id)
            if cached is None or cached[0] is not t.box:
                cached = self._corners[t.object_id] = (t.box, t.box.corners())
            out[k] = cached[1]
        return out

    def _explaining_objects(self, rows: np.ndarray) -> np.ndarray:
        """Per detection row, the published object of its class (with a box, not the row's own cluster) whose
        projected 3D box, clipped to the image, has the highest IoU with the detection box if that is at least
        truncated_explained_iou, or that holds at least explained_inside of the detection box (a partial view of
        it); else -1. (R,) ids."""
        out = np.full(len(rows), -1, np.int64)
        boxed = [t for t in self.confirmed_tracks() if t.box is not None]
        if not boxed or len(rows) == 0:
            return out
        fis, at = np.unique(self.rows.frame[rows], return_inverse=True)      # project once per frame
        proj, valid = project_boxes(self.frames.K[fis], self.frames.T_camera_world[fis], self._box_corners(boxed))
        proj, valid = clip_boxes(proj, self.frames.size[fis])[at], valid[at]
        iou = box_iou(self.rows.box[rows][:, None, :], proj)
        if self.cfg.explained_inside <= 1.0:     # a partial view lies inside the object's projection
            inside = box_inside_fraction(self.rows.box[rows][:, None, :], proj) >= self.cfg.explained_inside
            iou = np.where(inside, np.maximum(iou, self.cfg.truncated_explained_iou), iou)
        ids = np.array([t.object_id for t in boxed])
        classes = np.array([t.coco_id for t in boxed])
        ok = valid & (classes[None, :] == self.rows.coco[rows][:, None]) & (ids[None, :] != self.rows.assign[rows][:, None])
        iou = np.where(ok, iou, 0.0)
        best = iou.argmax(axis=1)
        hit = iou[np.arange(len(rows)), best] >= self.cfg.truncated_explained_iou
        out[hit] = ids[best[hit]]
        return out

    def _open_truncated_clusters(self) -> list[int]:
        """Deferred opening for always-truncated objects (the project's own extension; the paper does not
        address truncation here): DP-means over the pooled truncated detections (unassigned, beyond lambda
        of every centre of their class), per class. Groups are opened leader-style (the first pooled segment
        farther than lambda from every group centre opens a group at its midpoint and takes the pooled
        segments within lambda), then refined by least-squares centres and nearest-centre re-assignment within
        lambda, and merged while the DP-means objective falls (`merge_segment_groups`). A group with
        detections of at least truncated_min_views frames, whose centre is at least truncated_merge_distance
        from every cluster of its class, opens a cluster flagged `from_truncated` with its nearest detection
        of each frame. Returns the opened ids."""
        cfg = self.cfg
        if cfg.truncated_min_views <= 0:
            return []
        pool = np.nonzero(self.rows.truncated & (self.rows.assign < 0))[0]
        pool = pool[self._explaining_objects(pool) < 0]
        opened: list[int] = []
        for coco in np.unique(self.rows.coco[pool]):
            sel = pool[self.rows.coco[pool] == coco]
            ids, centers = self._class_centers(coco)
            if len(ids):
                sel = sel[point_segment_distance(centers, self.rows.segment[sel]).min(axis=1) >= cfg.cluster_penalty]
            if len(np.unique(self.rows.frame[sel])) < cfg.truncated_min_views:
                continue
            segs = self.rows.segment[sel]
            group = np.full(len(sel), -1, np.int64)
            leaders: list[np.ndarray] = []
            while np.any(group < 0):                          # leader opening (DP-means' first sweep)
                i = int(np.argmax(group < 0))
                leaders.append((segs[i, 0] + segs[i, 1]) / 2)
                near = (group < 0) & (point_segment_distance(leaders[-1][None], segs)[:, 0] < cfg.cluster_penalty)
                near[i] = True
                group[near] = len(leaders) - 1
            g_centers = np.array(leaders)
            for _ in range(cfg.max_em_iterations):           # EM among the pooled segments
                ok = group >= 0
                g_centers = lsq_centers(segs[ok], group[ok], len(g_centers), cfg.center_prior_weight)
                dist = point_segment_distance(np.nan_to_num(g_centers, nan=1e9), segs)
                new = np.where(dist.min(axis=1) < cfg.cluster_penalty, dist.argmin(axis=1), -1)
                if np.array_equal(new, group):
                    break
                group = new
            group, g_centers = merge_segment_groups(segs, group, self.rows.frame[sel], cfg.cluster_penalty,
                                                     cfg.center_prior_weight)
            for g in range(len(g_centers)):
                members = np.nonzero(group == g)[0]
                frames = self.rows.frame[sel[members]]
                if len(np.unique(frames)) < cfg.truncated_min_views:
                    continue
                # One detection per frame: the nearest to the group centre.
                d = point_segment_distance(g_centers[g][None], segs[members])[:, 0]
                order = np.lexsort((d, frames))
                first = np.ones(len(order), bool)
                first[1:] = frames[order][1:] != frames[order][:-1]
                members = members[order[first]]
                center = lsq_center(segs[members], cfg.center_prior_weight)
                ids, centers = self._class_centers(coco)
                if len(ids) and np.linalg.norm(centers - center, axis=1).min() < cfg.truncated_merge_distance:
                    continue
                oid = self._new_track(int(sel[members[0]]))
                self.rows.assign[sel[members]] = oid
                self.tracks[oid].center = center
                self.tracks[oid].from_truncated = True
                opened.append(oid)
        return opened

    def full_pass(self) -> tuple[set[int], dict[int, int]]:
        """EM over all detections until the assignment is stable (at most max_em_iterations): nearest centre
        within lambda with same-frame exclusivity, new clusters for segments beyond lambda of every centre,
        centres re-estimated; once stable, the deferred rule for truncated detections
        (`_open_truncated_clusters`) may open clusters and EM goes on.
        Returns (frames whose assignment changed, {emptied cluster id: -1})."""
        cfg = self.cfg
        valid = np.nonzero(self.rows.valid)[0]
        before = self.rows.assign.copy()
        removed: dict[int, int] = {}
        pooled = False
        for _ in range(cfg.max_em_iterations):
            ids = np.array(sorted(self.tracks), dtype=np.int64)
            if len(ids) == 0:
                break
            centers = np.array([self.tracks[i].center for i in ids])
            classes = np.array([self.tracks[i].coco_id for i in ids])
            dist = point_segment_distance(centers, self.rows.segment[valid])
            dist[self.rows.coco[valid][:, None] != classes[None, :]] = np.inf
            # Hysteresis: a detection leaves its cluster only for a centre reassign_ratio times closer.
            cost = np.where(dist < cfg.cluster_penalty, dist, np.inf)
            slot = np.full(self.next_id + 1, -1, np.int64)
            slot[ids] = np.arange(len(ids))
            cur = slot[self.rows.assign[valid]]
            has = np.nonzero(cur >= 0)[0]
            cost[has, cur[has]] *= cfg.reassign_ratio
            best = np.argmin(cost, axis=1)
            ok = np.isfinite(cost[np.arange(len(valid)), best])
            assign = np.where(ok, best, -1)
            frames = self.rows.frame[valid]
            key = frames * (len(ids) + 1) + np.where(ok, best, len(ids))
            _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
            for f in np.unique(frames[ok & (counts[inv] > 1)]):       # same-frame clashes: Hungarian
                rows_f = np.nonzero(frames == f)[0]
                assign[rows_f] = gated_assignment(cost[rows_f], cfg.cluster_penalty)
            new_assign = np.where(assign >= 0, ids[np.maximum(assign, 0)], -1)
            changed = not np.array_equal(new_assign, self.rows.assign[valid])
            self.rows.assign[valid] = new_assign
            opened: list[int] = []
            orphans = valid[(dist.min(axis=1) >= cfg.cluster_penalty) & self.rows.reliable[valid]]
            for i in orphans:       # DP-means: open a cluster; orphans near it join on the next iteration
                near = [o for o in opened if self.tracks[o].coco_id == self.rows.coco[i]]
                if not near or point_segment_distance(np.array([self.tracks[o].center for o in near]),
                                                      self.rows.segment[i][None]).min() >= cfg.cluster_penalty:
                    opened.append(self._new_track(int(i)))
                    changed = True
            counts = np.bincount(self.rows.assign[self.rows.assign >= 0], minlength=self.next_id)
            for oid in [o for o in self.tracks if counts[o] == 0]:
                del self.tracks[oid]
                removed[oid] = -1
            self._update_centers(list(self.tracks))
            if not changed:
                if pooled or not self._open_truncated_clusters():
                    pooled = True
                    break
                pooled = True
        if not pooled:
            self._open_truncated_clusters()
        diff = np.nonzero(before != self.rows.assign)[0]
        return set(np.unique(self.rows.frame[diff]).tolist()), removed

    def merge_close(self) -> tuple[dict[int, int], set[int]]:
        """Merge same-class clusters closer than merge_distance (truncated_merge_distance when one was opened by
        the deferred truncated rule; the older id survives); of two detections of
        one frame on the merged cluster the one nearer its centre stays, the other is ignored (-1)."""
        removed: dict[int, int] = {}
        dirty: set[int] = set()
        while len(self.tracks) > 1:
            ids = np.array(sorted(self.tracks), dtype=np.int64)
            centers = np.array([self.tracks[i].center for i in ids])
            classes = np.array([self.tracks[i].coco_id for i in ids])
            trunc = np.array([self.tracks[i].from_truncated for i in ids])
            d = np.linalg.norm(centers[:, None] - centers[None], axis=2)
            d[classes[:, None] != classes[None, :]] = np.inf
            d[np.tril_indices(len(ids))] = np.inf
            # Relative to the pair's merge distance (larger when a cluster was opened by truncated detections).
            limit = np.where(trunc[:, None] | trunc[None, :], self.cfg.truncated_merge_distance,
                             self.cfg.merge_distance)
            i, j = np.unravel_index(np.argmin(d / limit), d.shape)
            if d[i, j] >= limit[i, j]:
                break
            removed, dirty = self._merge_pair(int(ids[i]), int(ids[j]), removed, dirty)   # ids[i] is the older
        return removed, dirty

    def _merge_pair(self, a: int, b: int, removed: dict[int, int], dirty: set[int]) -> tuple[dict[int, int], set[int]]:
        """Merge clusters a and b (the older id survives): of two detections of one frame the one nearer the
        merged centre stays, the other is ignored (-1). Returns the updated (removed, dirty frames)."""
        keep, gone = min(a, b), max(a, b)
        members = np.nonzero((self.rows.assign == keep) | (self.rows.assign == gone))[0]
        center = lsq_center(self.rows.segment[members], self.cfg.center_prior_weight)
        frames = self.rows.frame[members]
        dist = point_segment_distance(center[None], self.rows.segment[members])[:, 0]
        order = np.lexsort((dist, frames))
        first = np.ones(len(order), bool)
        first[1:] = frames[order][1:] != frames[order][:-1]
        self.rows.assign[members] = keep
        self.rows.assign[members[order[~first]]] = -1
        survivor = self.tracks[keep]
        survivor.confirmed = survivor.confirmed or self.tracks[gone].confirmed
        survivor.whole_view_center |= self.tracks[gone].whole_view_center \
            or (survivor.from_truncated != self.tracks[gone].from_truncated)
        survivor.from_truncated = survivor.from_truncated and self.tracks[gone].from_truncated
        survivor.fitted_views = 0                      # refit with the merged detections
        survivor.recent_from = max(survivor.recent_from, self.tracks[gone].recent_from)
        if survivor.box is None:
            survivor.box = self.tracks[gone].box
        del self.tracks[gone]
        removed = {k: (keep if v == gone else v) for k, v in removed.items()}
        removed[gone] = keep
        self.merges += 1
        self._update_centers([keep])
        return removed, dirty | set(np.unique(frames).tolist())

    def merge_explained(self) -> tuple[dict[int, int], set[int]]:
        """Merge a cluster (with at least min_track_views detections) into a published object of its class when
        more than half of its detections are explained by that object's 3D box (`_explaining_objects`: IoU with
        the clipped projection at least truncated_explained_iou). Run at full passes; catches duplicates whose
        centres are farther apart than the merge distances because the box-centre rays of partial views (the
        visible end of a long table) are biased. Also merges two published objects of one class whose 3D boxes'
        floor footprints overlap by at least box_overlap_merge of the smaller one (two objects cannot stand in one
        place; partial views at close range give such duplicates). Returns ({gone id: surviving id}, frames whose
        rows changed)."""
        removed: dict[int, int] = {}
        dirty: set[int] = set()
        touched: set[int] = set()
        if len(self.tracks) < 2:
            return removed, dirty
        if self.cfg.truncated_explained_iou <= 1.0:
            rows = np.nonzero(self.rows.assign >= 0)[0]
            expl = self._explaining_objects(rows)                 # one batched projection for all clusters
            n = np.bincount(self.rows.assign[rows], minlength=self.next_id)
            pairs, counts = np.unique(np.stack([self.rows.assign[rows], expl])[:, expl >= 0], axis=1,
                                      return_counts=True)
            for (oid, by), c in zip(pairs.T.tolist(), counts.tolist()):
                if c * 2 > n[oid] and n[oid] >= self.cfg.min_track_views and not {oid, by} & touched:
                    removed, dirty = self._merge_pair(oid, by, removed, dirty)
                    touched |= {oid, by}                           # the rest waits for the next full pass
        if self.cfg.frustum_merges:
            boxed = [t for t in self.confirmed_tracks() if t.box is not None and t.object_id not in touched]
            for a, b in self._frustum_duplicates(boxed):
                if not {a, b} & touched:
                    removed, dirty = self._merge_pair(a, b, removed, dirty)
                    touched |= {a, b}
        if self.cfg.box_overlap_merge <= 1.0:
            boxed = [t for t in self.confirmed_tracks() if t.box is not None and t.object_id not in touched]
            for i, a in enumerate(boxed):
                for b in boxed[i + 1:]:
                    if a.coco_id == b.coco_id and not {a.object_id, b.object_id} & touched \
                            and footprint_overlap(a.box, b.box) >= self.cfg.box_overlap_merge:
                        removed, dirty = self._merge_pair(a.object_id, b.object_id, removed, dirty)
                        touched |= {a.object_id, b.object_id}
        return removed, dirty

    def _frustum_duplicates(self, boxed: list[ObjectTrack]) -> list[tuple[int, int]]:
        """Pairs (a, b) of published objects of one class that are one object seen in parts: their box centres
        lie within the class's largest extent, no frame holds a detection of both, and a's detections hold b in at least min_track_views frames and in at least half of
        a's frames that see b's box centre. A detection holds b when b's centre lies between the optical depths
        of the detection's segment and, in the image, b's centre lies inside the detection box or b's projected
        box (clipped to the image) lies explained_inside of it. A table too long for the view is detected as its
        visible part, and as the view turns the short segments of those detections move along it, beyond
        lambda: two clusters, each published, with boxes that barely overlap. Another object behind or beside
        a's detections fails the depth or the image test; one in view in a's frames has detections of its own
        there."""
        if len(boxed) < 2:
            return []
        # Two parts of one object have box centres closer than the class's largest extent (cheap, first).
        centres = np.array([b.box.center for b in boxed])
        classes = np.array([b.coco_id for b in boxed])
        reach = np.array([category_by_id(c).size_range[1] for c in classes])
        candidate = (classes[:, None] == classes[None, :]) \
            & (np.linalg.norm(centres[:, None] - centres[None], axis=2) <= reach[:, None])
        np.fill_diagonal(candidate, False)
        if not candidate.any():
            return []
        ids = np.array([t.object_id for t in boxed])
        slot = np.full(self.next_id + 1, -1, np.int64)
        slot[ids] = np.arange(len(ids))
        members = np.nonzero(np.isin(self.rows.assign, ids))[0]
        seen = np.zeros((len(ids), len(self.frames)), bool)
        seen[slot[self.rows.assign[members]], self.rows.frame[members]] = True
        candidate &= (seen.astype(np.int64) @ seen.T.astype(np.int64)) == 0            # never in one frame
        if not candidate.any():
            return []
        rows = members[candidate.any(axis=1)[slot[self.rows.assign[members]]]]    # detections of candidates only
        owner, fi = slot[self.rows.assign[rows]], self.rows.frame[rows]
        R, t = self.frames.T_camera_world[fi, :3, :3], self.frames.T_camera_world[fi, :3, 3]
        K = self.frames.K[fi]
        pc = np.einsum('rij,oj->roi', R, centres) + t[:, None]                       # (R, O, 3)
        z = pc[..., 2]
        zs = np.maximum(z, 1e-6)
        u = K[:, None, 0, 0] * pc[..., 0] / zs + K[:, None, 0, 2]
        v = K[:, None, 1, 1] * pc[..., 1] / zs + K[:, None, 1, 2]
        size = self.frames.size[fi]
        in_view = (z > self.cfg.min_depth) & (u >= 0) & (v >= 0) & (u < size[:, None, 0]) & (v < size[:, None, 1])
        box = self.rows.box[rows]
        centre_inside = in_view & (u >= box[:, None, 0]) & (u <= box[:, None, 2]) & (v >= box[:, None, 1]) \
            & (v <= box[:, None, 3])
        proj, valid = project_boxes(K, self.frames.T_camera_world[fi], self._box_corners(boxed))
        proj = clip_boxes(proj, size)                                                   # (R, O, 4)
        box_inside = valid & (box_area(proj) > 0) \
            & (box_inside_fraction(proj, box[:, None, :]) >= self.cfg.explained_inside)
        seg_depth = np.einsum('ri,rki->rk', R[:, 2], self.rows.segment[rows]) + t[:, 2:3]   # (R, 2)
        inside = (centre_inside | box_inside) & (z >= seg_depth.min(1)[:, None]) & (z <= seg_depth.max(1)[:, None])
        held = np.zeros((len(ids), len(ids)), np.int64)
        viewed = np.zeros_like(held)
        np.add.at(held, owner, inside.astype(np.int64))
        np.add.at(viewed, owner, in_view.astype(np.int64))
        ok = candidate & (held >= self.cfg.min_track_views) & (2 * held >= viewed)
        return [(int(ids[i]), int(ids[j])) for i, j in zip(*np.nonzero(ok))]

    def merge_consistent(self) -> tuple[dict[int, int], set[int]]:
        """DP-means merges of a split object (the project's own extension). Near-parallel rays of a narrow
        baseline split an object along its rays: a detection beyond lambda of the centre opens a second cluster,
        and each centre then stays on its own segments, decimetres from the other and beyond merge_distance.
        Clusters of one class, not both published, with no frame in common and each with a reliable detection,
        merge while the DP-means objective (squared segment-to-centre distances plus lambda^2 per cluster) falls
        and one centre fits all their segments within lambda (`segments.merge_segment_groups`). A cluster of cut
        views alone is left to the truncated rules: the box-centre rays of cut boxes are biased, so a centre that
        fits them says little. Run at full passes (with consistent_merges). Returns ({gone id: surviving id},
        frames whose rows changed)."""
        removed: dict[int, int] = {}
        dirty: set[int] = set()
        if not self.cfg.consistent_merges:
            return removed, dirty
        for coco in {t.coco_id for t in self.tracks.values() if not t.confirmed}:
            ids = np.array(sorted(i for i, t in self.tracks.items() if t.coco_id == coco), dtype=np.int64)
            if len(ids) < 2:
                continue
            rows = np.nonzero(np.isin(self.rows.assign, ids))[0]
            old = np.searchsorted(ids, self.rows.assign[rows])
            locked = np.array([self.tracks[int(i)].confirmed for i in ids])
            whole = np.bincount(old[self.rows.reliable[rows]], minlength=len(ids)) > 0
            old = np.where(whole[old], old, -1)
            new, _ = merge_segment_groups(self.rows.segment[rows], old, self.rows.frame[rows],
                                          self.cfg.cluster_penalty, self.cfg.center_prior_weight, locked)
            for g in np.unique(new[new >= 0]):
                together = ids[np.unique(old[new == g])]
                for other in together[1:]:                   # into the oldest id
                    removed, dirty = self._merge_pair(int(together[0]), int(other), removed, dirty)
        return removed, dirty

    def hit_ratio(self, object_id: int) -> tuple[float, int]:
        """(frames with a detection / frames whose image contains the cluster centre, frames in view),
        counted from the cluster's first detection."""
        ratio, n_view, _ = self._view_stats(object_id)
        return ratio, n_view

    def _view_stats(self, object_id: int) -> tuple[float, int, bool]:
        """`hit_ratio` and whether the cluster centre is in view in the latest frame."""
        t = self.tracks[object_id]
        hit_frames = self.rows.frame[self.members(object_id)]
        if t.recent_from > 0 and hit_frames.max() >= t.recent_from:   # older ones thinned (max_detections_per_object)
            hit_frames = hit_frames[hit_frames >= t.recent_from]
        first = int(hit_frames.min())
        fr = slice(first, len(self.frames))
        pc = np.einsum('fij,j->fi', self.frames.T_camera_world[fr][:, :3, :3], t.center) \
            + self.frames.T_camera_world[fr][:, :3, 3]
        z = pc[:, 2]
        K = self.frames.K[fr]
        zs = np.maximum(z, 1e-6)
        u = K[:, 0, 0] * pc[:, 0] / zs + K[:, 0, 2]
        v = K[:, 1, 1] * pc[:, 1] / zs + K[:, 1, 2]
        size = self.frames.size[fr]
        in_view = (z > self.cfg.min_depth) & (u >= 0) & (v >= 0) & (u < size[:, 0]) & (v < size[:, 1])
        hit = np.zeros(len(in_view), dtype=bool)
        hit[hit_frames - first] = True
        n_view = int(np.count_nonzero(in_view | hit))
        return float(np.count_nonzero(hit)) / max(n_view, 1), n_view, bool(in_view[-1] | hit[-1])

    def consistent_frames(self, object_id: int) -> int:
        """Frames with a detection of the cluster (valid and at least the pruning size; cut by the border or a
        nearer instance or not) whose segment passes within confirm_distance of the cluster centre: detections
        whose rays meet in one place (with surface depths from depth or landmarks, their short segments meet in
        3D; without, the rays at least agree)."""
        rows = self.members(object_id)
        rows = rows[self.rows.evidence[rows]]
        if not len(rows):
            return 0
        d = point_segment_distance(self.tracks[object_id].center[None], self.rows.segment[rows])[:, 0]
        return len(np.unique(self.rows.frame[rows[d <= self.cfg.confirm_distance]]))

    def publish_blocker(self, object_id: int, reliable: int | None = None, final: bool = False) -> str | None:
        """Why an unpublished cluster is not published (the first publishing condition it fails, in words), or
        None when it meets the rule (`_update_confirmation` publishes it then). reliable: its reliable detections
        (counted when None); final: the input has ended (`settle`), so a cluster still in view does not wait.

        Confirmation from geometry: the cluster needs detections in min_track_views frames whose segments pass
        within confirm_distance of its centre (`consistent_frames`; cut and occluded detections count), one of
        them reliable (or opened by the deferred truncated rule), and a hit ratio of at least min_hit_ratio over
        the frames with its centre in view; however narrow the range of viewpoints and however far apart the
        frames. A cluster whose centre is still in view waits until it has been in view for confirm_window frames
        (a live map does not publish an object from its first partial views), unless `final`."""
        cfg = self.cfg
        t = self.tracks[object_id]
        if reliable is None:
            rows = self.members(object_id)
            reliable = int(np.count_nonzero(self.rows.reliable[rows]))
        if reliable < 1 and not t.from_truncated:
            return 'no reliable detection (all cut, occluded or too small)'
        frames = self.consistent_frames(object_id)
        if frames < cfg.min_track_views:
            return (f'consistent detections in {frames} frames < min_track_views {cfg.min_track_views} '
                    f'(confirm_distance {cfg.confirm_distance} m)')
        ratio, n_view, in_view = self._view_stats(object_id)
        if ratio < cfg.min_hit_ratio:
            return f'hit ratio {ratio:.2f} < min_hit_ratio {cfg.min_hit_ratio} ({n_view} frames in view)'
        if in_view and n_view < cfg.confirm_window and not final:
            return f'still in view, {n_view} frames in view < confirm_window {cfg.confirm_window}'
        return None

    def _update_confirmation(self, recheck: bool, final: bool = False) -> tuple[set[int], dict[int, int]]:
        """Publish clusters that meet the rule (`publish_blocker` says None; `final`: the input has ended); with
        `recheck`, withdraw published clusters whose hit ratio fell below drop_hit_ratio (over at least
        2 * min_track_views frames in view). A cluster opened by the deferred truncated rule becomes an ordinary
        one once it has min_track_views reliable detections. Returns (frames whose rows change, withdrawn ids)."""
        cfg = self.cfg
        counts = np.bincount(self.rows.assign[(self.rows.assign >= 0) & self.rows.reliable], minlength=self.next_id)
        changed: list[int] = []
        withdrawn: dict[int, int] = {}
        for t in self.tracks.values():
            if t.from_truncated and counts[t.object_id] >= cfg.min_track_views:
                t.from_truncated = False          # now seen whole often enough: an ordinary cluster
            if not t.confirmed:
                if self.publish_blocker(t.object_id, int(counts[t.object_id]), final) is None:
                    t.confirmed = True
                    changed.append(t.object_id)
            elif recheck:
                ratio, n_view = self.hit_ratio(t.object_id)
                if ratio < cfg.drop_hit_ratio and n_view >= 2 * cfg.min_track_views:
                    t.confirmed = False
                    changed.append(t.object_id)
                    withdrawn[t.object_id] = -1
        return (self._frames_of(changed) if changed else set()), withdrawn

    # ------------------------------------------------------------ boxes and pruning
    def fit_object_box(self, object_id: int) -> Box3D:
        """Fit (or refit) an object's 3D box from its detections: the kept ones when pruning and they are at
        least half of them (and min_track_views), else all of them."""
        cfg = self.cfg
        track = self.tracks[object_id]
        members = self.members(object_id)
        if cfg.prune and track.box is not None:
            kept = members[self.rows.kept[members]]
            if len(kept) >= max(cfg.min_track_views, len(members) / 2):
                members = kept
        if len(members) > cfg.box_max_views:
            members = members[np.linspace(0, len(members) - 1, cfg.box_max_views).round().astype(int)]
        frames = self.rows.frame[members]
        fit_edges = self.rows.fit_edges[members]   # uncut edges: not on the border, not against a nearer mask
        if not fit_edges.any():
            fit_edges = np.ones_like(fit_edges)
        category = category_by_id(track.coco_id)
        points = self.rows.points[members].reshape(-1, 3)
        points = points[np.isfinite(points[:, 0])]
        if len(points) > cfg.box_max_points:
            points = points[np.linspace(0, len(points) - 1, cfg.box_max_points).round().astype(int)]
        track.box = fit_box(self.frames.K[frames], self.frames.T_camera_world[frames], self.rows.box[members],
                            fit_edges, category.size_range, track.center,
                            cfg.floor_height if cfg.objects_on_floor else None, cfg.size_prior_weight,
                            cfg.center_anchor_weight, track.box, class_shape(track.coco_id, category.size_range),
                            cfg.height_prior_weight, cfg.box_truncation_hinge, self.rows.surface[members],
                            cfg.box_surface_weight, cfg.surface_slack, cfg.box_bottom_below_weight, points,
                            cfg.box_points_weight)
        return track.box

    def _prune_frames(self, frame_indices: list[int]) -> None:
        """Recompute the kept flags of the detections of the given frames with the current boxes."""
        if not frame_indices:
            return
        fis = np.asarray(frame_indices, dtype=np.int64)
        rows = self._rows_of_frames(fis)
        assign = self.rows.assign[rows]
        if not self.cfg.prune:
            self.rows.kept[rows] = assign >= 0
            return
        boxed = [t for t in self.confirmed_tracks() if t.box is not None]
        proj, valid = project_boxes(self.frames.K[fis], self.frames.T_camera_world[fis], self._box_corners(boxed))
        position = np.repeat(np.arange(len(fis)), self.frames.stop[fis] - self.frames.start[fis])
        slot = np.full(self.next_id + 1, -1, np.int64)
        slot[[t.object_id for t in boxed]] = np.arange(len(boxed))
        index = np.where(assign >= 0, slot[assign], -1)
        kept = prune_detections(self.rows.box[rows], index, proj[position], valid[position],
                                self.frames.size[fis][position], self.cfg)
        self.rows.kept[rows] = kept & (assign >= 0)

    def _keep_best_views(self, frame_indices: set[int]) -> set[int]:
        """Pruning never starves a published object (own extension): one with a box and detections in the given
        frames but fewer than min_track_views kept ones keeps its min_track_views detections whose boxes best
        match its projected 3D box clipped to the image, among those passing the size and overlap tests; where
        fewer than that overlap the box at all (a box placed far off along the view), the largest passing ones
        fill up; where none passes those tests, the best of all are kept. The occlusion test fails every view of
        an object cut by the border in all of them (a table never seen whole) and every view of one whose box is
        off (a stool under a chair-sized box prior); the overlap test every view of a table with chairs in front
        of it (realwalk-tune 8401); without kept views the shape stage never encodes it and it is never
        reconstructed. Returns the frames whose flags changed."""
        cfg = self.cfg
        if not cfg.prune or not frame_indices:
            return set()
        assigned = self.rows.assign >= 0
        kept_counts = np.bincount(self.rows.assign[assigned & self.rows.kept], minlength=self.next_id)
        touched = np.unique(self.rows.assign[self._rows_of_frames(np.array(sorted(frame_indices)))])
        starved = [self.tracks[o] for o in touched.tolist() if o >= 0 and self.tracks[o].confirmed
                   and self.tracks[o].box is not None and kept_counts[o] < cfg.min_track_views]
        if not starved:
            return set()
        boxed = [t for t in self.confirmed_tracks() if t.box is not None]
        slot = {t.object_id: k for k, t in enumerate(boxed)}
        corners = np.array([t.box.corners() for t in boxed])
        changed: set[int] = set()
        for t in starved:
            rows = self.members(t.object_id)
            fis = self.rows.frame[rows]
            proj, valid = project_boxes(self.frames.K[fis], self.frames.T_camera_world[fis], corners)
            sizes = self.frames.size[fis]
            own = slot[t.object_id]
            # Size and overlap tests as in pruning; the occlusion test is replaced by the ranking below, so the own
            # box need not project validly (a camera inside a misplaced table's box).
            own_valid = valid.copy()
            own_valid[:, own] = True
            passing = prune_detections(self.rows.box[rows], np.full(len(rows), own), proj, own_valid, sizes,
                                       replace(cfg, occlusion_iou=-1.0))
            iou = np.where(valid[:, own],
                           box_iou(self.rows.box[rows], clip_boxes(proj[:, own][:, None], sizes)[:, 0]), 0.0)
            order = np.lexsort((-box_area(self.rows.box[rows]), -iou, ~passing))[:cfg.min_track_views]
            eligible = passing[order] if passing.any() else np.ones(len(order), bool)
            best = rows[order][eligible & ~self.rows.kept[rows[order]]]
            self.rows.kept[best] = True
            changed |= set(self.rows.frame[best].tolist())
        return changed


def detections_from_instances(instances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(labels (N,), boxes (N, 4)) of the instances in a contract instance image (H, W) uint16."""
    labels, boxes, _ = instance_boxes(instances)
    return labels, boxes
