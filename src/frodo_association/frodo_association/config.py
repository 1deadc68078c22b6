"""Association parameters (`AssociationConfig`, documented by `CONFIG_DOC`; the node's ROS parameters are
generated from both), `EvidenceConfig` and the row type of /frodo/associations (`ASSOCIATION_DTYPE`, defined in
frodo_common.schemas)."""
from __future__ import annotations

from dataclasses import dataclass, fields

from frodo_common.schemas import ASSOCIATION_DTYPE  # noqa: F401 - the row type, re-exported


@dataclass(frozen=True)
class AssociationConfig:
    """Association parameters; `CONFIG_DOC` describes each (the node's ROS parameters are generated from both)."""

    cluster_penalty: float = 0.4
    merge_distance: float = 0.25
    full_pass_every: int = 20
    full_pass_distance: float = 0.0
    max_em_iterations: int = 10
    reassign_ratio: float = 0.5
    depth_margin: float = 0.3
    min_depth: float = 0.3
    max_depth: float = 20.0
    center_prior_weight: float = 1e-3
    whole_view_centers: bool = True
    max_center_segments: int = 64
    max_detections_per_object: int = 400
    min_track_views: int = 3
    min_hit_ratio: float = 0.6
    confirm_window: int = 10
    drop_hit_ratio: float = 0.4
    truncated_opens_clusters: bool = False
    truncated_min_views: int = 3
    truncated_merge_distance: float = 0.4
    truncated_explained_iou: float = 0.5
    objects_on_floor: bool = True
    floor_height: float = 0.0
    size_prior_weight: float = 0.05
    center_anchor_weight: float = 0.1
    box_truncation_hinge: bool = True
    box_contact_edges: bool = True
    box_surface_weight: float = 1.0
    box_bottom_below_weight: float = 0.3
    box_points_weight: float = 1.0
    box_points_per_detection: int = 16
    box_max_points: int = 192
    box_refit_growth: float = 1.5
    box_max_views: int = 24
    max_box_fits_per_frame: int = 1
    prune: bool = True
    min_box_width: float = 24.0
    min_box_height: float = 24.0
    occlusion_iou: float = 0.6
    overlap_iou: float = 0.4
    border_margin: float = 2.0
    surface_slack: float = 0.1
    evidence_opens_clusters: bool = True
    complete_truncated: bool = True
    flat_segments: bool = True
    occluded_fraction: float = 0.5
    height_prior_weight: float = 0.2
    box_overlap_merge: float = 0.3
    consistent_merges: bool = True
    confirm_distance: float = 0.3
    explained_inside: float = 0.8
    frustum_merges: bool = True


CONFIG_DOC: dict[str, str] = {
    'cluster_penalty': 'DP-means cluster penalty lambda (m): a segment farther than this from every centre of its '
                       'class opens a new cluster (paper: 0.4).',
    'merge_distance': 'Clusters of one class whose centres come closer than this (m) are merged; the older id survives.',
    'full_pass_every': 'Frames between full DP-means EM passes over all segments (0: never).',
    'full_pass_distance': 'A full pass also runs once the camera has travelled this far (m) since the last one '
                          '(0: off).',
    'max_em_iterations': 'Maximum EM iterations of a full pass.',
    'reassign_ratio': 'Full-pass hysteresis: a detection moves to another cluster only if that centre is closer '
                      'than this times the distance to its own (1: plain DP-means re-assignment).',
    'depth_margin': 'Relative widening of the depth interval [S_min/a, S_max/a] of a detection segment.',
    'min_depth': 'Segments start no closer than this (m, optical depth).',
    'max_depth': 'Segments end no farther than this (m, optical depth).',
    'center_prior_weight': 'Weight (per segment) pulling a cluster centre towards the mean segment midpoint; '
                           'regularises near-parallel segments.',
    'whole_view_centers': 'A cluster that merged one opened by truncated detections with an ordinary one estimates '
                          'its centre from its untruncated detections once it has min_track_views of them (box-centre '
                          'rays of truncated detections are biased towards the visible part).',
    'max_center_segments': 'Segments per cluster used to re-estimate its centre, evenly spread over its detections.',
    'max_detections_per_object': 'Bounded history for long runs (0: unbounded): a cluster holds at most this many '
                                 'detections, its newest half and an even subsample of the older ones (the rest are '
                                 'retired: they keep what was last published and are no longer clustered, pruned or '
                                 'republished; its box and published state stay); a detection unassigned for this '
                                 'many frames is retired too.',
    'min_track_views': 'Frames with mutually consistent detections (confirm_distance) a cluster needs before it is '
                       'published, one of them reliable (not truncated, at least min_box_width x min_box_height, '
                       'scaled); cut and occluded detections count.',
    'min_hit_ratio': 'A cluster is published once it was detected in at least this fraction of the frames whose '
                     'image contains its centre (since its first detection).',
    'confirm_window': 'A cluster whose centre is still in view waits until it has been in view this many frames '
                      '(since its first detection) before it is published (a live map does not publish an object '
                      'from its first partial views); once it left the view, or at the end of the input, its '
                      'consistent detections suffice.',
    'drop_hit_ratio': 'A published cluster whose hit ratio falls below this (checked at full passes) is withdrawn.',
    'truncated_opens_clusters': 'Let detections touching the image border open new clusters and count towards '
                                'publishing one (their box centre and size are biased).',
    'truncated_min_views': 'Deferred opening (own extension, not in the paper): at full passes, unassigned '
                           'truncated detections farther than lambda from every centre of their class are clustered '
                           'among themselves (DP-means, lambda); a group with detections from at least this many '
                           'frames opens a cluster (0: off), which its truncated detections may publish without a '
                           'reliable one (a table never seen whole).',
    'truncated_merge_distance': 'A cluster opened by the deferred rule merges with a cluster of its class closer than '
                                'this (m) (its centre is biased by the truncation); groups this close to an existing '
                                'cluster open none.',
    'truncated_explained_iou': 'A detection whose box has at least this IoU with the projected (clipped) 3D box of '
                               'another published object of its class is explained by it (own extension): explained '
                               'truncated detections are not pooled for deferred opening, and at full passes a cluster '
                               'whose detections are mostly explained by one object is merged into it (> 1: off).',
    'objects_on_floor': 'Boxes stand on the plane z = floor_height (gravity-aligned world).',
    'floor_height': 'Height of the support plane (m) when objects_on_floor.',
    'size_prior_weight': 'Weight of the class size prior (log-size residual) in the box fit.',
    'center_anchor_weight': 'Weight (per metre) pulling the box centre towards the cluster centre in the box fit '
                            '(resolves the depth ambiguity of few or similar views).',
    'box_truncation_hinge': 'Box fit: a detection edge on the image border says the object reaches at least that '
                            'far; the projected box edge is pulled out when it lies inside (one-sided residual).',
    'box_contact_edges': 'Box fit: detection edges where the mask meets another instance (possibly hidden by it) '
                         'count like edges on the image border.',
    'box_surface_weight': 'Box fit: weight (per metre) of the one-sided residual that keeps the box\'s nearest corner '
                          'no farther than surface_slack behind each detection\'s visible surface (depth image or '
                          'landmarks), distances taken horizontally along the view (0: surface depths play no part '
                          'in the box fit).',
    'box_bottom_below_weight': 'Box fit (objects on the floor): weight of a detection\'s bottom-edge residual where '
                               'the box reaches lower in the image than the detection (1: two-sided; above it: '
                               'full weight). A detection often ends above the floor contact (legs the mask '
                               'misses, something unlabelled in front), and matching it exactly stands the box on '
                               'the floor farther away.',
    'box_points_weight': 'Box fit: weight (per metre) of the residuals that keep the visible surface inside the box: '
                         'points back-projected from a depth image inside each detection\'s eroded mask '
                         '(evidence.mask_points), their term weighing about one residual per view in all (0: off; '
                         'no effect without a depth image).',
    'box_points_per_detection': 'Depth points kept per detection for the box fit (fixed when the association starts).',
    'box_max_points': 'Depth points used per box fit at most (evenly spread over its detections\' points).',
    'box_refit_growth': 'An object box is refitted when its detection count grew by this factor since the last fit.',
    'box_max_views': 'Detections used per box fit (evenly spread over the object\'s detections).',
    'max_box_fits_per_frame': 'Box fits per processed frame at most (bounds the per-frame latency).',
    'prune': 'Apply detection pruning (size, occlusion, overlap); off: every associated detection is kept.',
    'min_box_width': 'Pruning (1): detections narrower than this are rejected and open no clusters (pixels at '
                     '640x480, scaled by sqrt(W*H/(640*480)) at other resolutions).',
    'min_box_height': 'Pruning (1): detections lower than this are rejected and open no clusters (pixels at '
                      '640x480, scaled by sqrt(W*H/(640*480)) at other resolutions).',
    'occlusion_iou': 'Pruning (2): detections whose IoU with their object\'s projected 3D box is below this are '
                     'rejected (occluded or truncated).',
    'overlap_iou': 'Pruning (3): detections whose IoU with another object\'s projected 3D box is above this are '
                   'rejected.',
    'border_margin': 'A box edge within this many pixels of the image border is truncated (not used in box fits).',
    'surface_slack': 'With a visible-surface depth d_s for a detection (depth image or landmarks), its segment is '
                     'the ray between optical depths d_s - surface_slack and d_s + the class\'s half horizontal '
                     'diagonal (m) instead of the size-derived interval.',
    'evidence_opens_clusters': 'A truncated detection with a visible-surface depth is reliable: it opens clusters '
                               'and counts towards publishing (its segment is short and its ray completed).',
    'complete_truncated': 'With a visible-surface depth, a box cut by the image border on one side is extended on '
                          'that side to the class\'s typical projected size before its centre ray is taken.',
    'flat_segments': 'With a surface depth and objects_on_floor, the segment keeps the ray\'s x, y over its depth '
                     'interval but lies at the class\'s typical centre height (CLASS_SHAPES), not at the box centre\'s '
                     '(biased by occlusion below and truncation at the top).',
    'occluded_fraction': 'A detection with a surface depth, not cut by the top or bottom border, whose box is lower '
                         'than this fraction of the class\'s typical height projected at that depth is occluded: it '
                         'joins clusters but opens none and does not count towards publishing (0: off).',


    'height_prior_weight': 'Weight of the class shape prior in the box fit (0: the isotropic size prior alone): '
                           'log-height residual against the typical height of the class (CLASS_SHAPES) with this '
                           'weight, horizontal sizes against the class\'s typical sqrt(long x short) with '
                           'size_prior_weight. Seen from one side, with the bottom hidden, the depth of a box is '
                           'fixed by its size alone, and the isotropic prior (0.67 m a side for a chair) puts it too '
                           'far.',
    'box_overlap_merge': 'At full passes, two published objects of one class whose 3D box footprints overlap by at '
                         'least this fraction of the smaller footprint are merged (the older id survives; > 1: off).',
    'consistent_merges': 'At full passes, clusters of one class, not both published, with no frame in common and '
                         'each with a reliable detection, merge while the DP-means objective (squared '
                         'segment-to-centre distances plus cluster_penalty^2 per cluster) falls and one centre fits '
                         'all their segments within cluster_penalty: an object split along its near-parallel rays '
                         '(narrow baseline) becomes one.',
    'confirm_distance': 'Publishing: a detection is consistent with its cluster when its segment passes within this '
                        'distance (m) of the cluster centre; a cluster needs consistent detections in min_track_views '
                        'frames.',
    'explained_inside': 'A detection box lying at least this fraction inside the (clipped) projected 3D box of another '
                        'published object of its class is explained by it too (a partial view: the top of a chair '
                        'behind a table, whose biased centre ray opened a cluster of its own) (> 1: off).',
    'frustum_merges': 'At full passes, two published objects of one class with no frame in common and box centres '
                      'within the class\'s largest extent merge when one\'s '
                      'detections hold the other in at least min_track_views frames and half of those that see its '
                      'centre: its box centre between the depths of the detection\'s segment and, in the image, '
                      'inside the detection box (or its projected box explained_inside of it). A table too long for '
                      'the view, split as its visible part moves along it.',
}
assert set(CONFIG_DOC) == {f.name for f in fields(AssociationConfig)}

@dataclass(frozen=True)
class EvidenceConfig:
    """How a detection's visible-surface depth is taken from registered depth or SLAM landmarks
    (`evidence.surface_depths`); `EVIDENCE_DOC` describes each field (node parameters of the same names)."""

    evidence_erode_px: int = 3
    evidence_min_pixels: int = 20
    evidence_min_landmarks: int = 3
    landmark_quantile: float = 0.25

    def surface_arguments(self) -> dict:
        """These settings as keyword arguments of `evidence.surface_depths` (the node and the evaluation alike)."""
        return {'erode_px': self.evidence_erode_px, 'min_pixels': self.evidence_min_pixels,
                'min_landmarks': self.evidence_min_landmarks, 'landmark_quantile': self.landmark_quantile}


EVIDENCE_DOC: dict[str, str] = {
    'evidence_erode_px': 'Masks are eroded by this many pixels before depth pixels or landmarks inside them are used '
                         '(boundary errors, bleeding).',
    'evidence_min_pixels': 'Depth measurements inside the eroded mask needed for a surface depth (their median).',
    'evidence_min_landmarks': 'Landmarks projecting inside the eroded mask needed for a surface depth.',
    'landmark_quantile': 'Surface depth from landmarks: this quantile of their depths (the map also holds points on '
                         'the far side and behind the object).',
}
