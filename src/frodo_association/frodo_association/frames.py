"""One frame through the association (paper Sec. 5.1), without ROS: detections of an instance image, their
visible-surface depths from registered depth or landmarks (`evidence`), then `Associator.add_frame` and one box
refinement step. The association node and the offline pipeline both call `FrameAssociator.add`."""
from __future__ import annotations

import time
from dataclasses import dataclass, fields

import numpy as np

from frodo_association.config import AssociationConfig, EvidenceConfig
from frodo_association.evidence import contact_edges, depth_points, surface_depths
from frodo_association.tracker import AssociationUpdate, Associator, detections_from_instances
from frodo_common.geometry import invert_transform


@dataclass
class FrameResult:
    """What one frame changed: `update` (its rows, merges, tracks_changed), `refined` (the box step), the
    stamps of earlier frames whose rows changed (to re-send), and timings (ms)."""

    update: AssociationUpdate
    refined: AssociationUpdate
    republish: list[int]
    association_ms: float
    refine_ms: float
    evidence_ms: float | None     # None: no depth and no landmarks for this frame

    @property
    def tracks_changed(self) -> bool:
        return bool(self.update.tracks_changed or self.refined.tracks_changed)


class FrameAssociator:
    """An `Associator` fed with whole frames (instance image, camera, optional depth and landmarks)."""

    def __init__(self, config: AssociationConfig | None = None, evidence: EvidenceConfig | None = None):
        self.associator = Associator(config or AssociationConfig())
        self.evidence = evidence or EvidenceConfig()

    def add(self, stamp: int, K: np.ndarray, T_world_camera: np.ndarray, size: tuple[int, int],
            instances: np.ndarray, depth_m: np.ndarray | None = None,
            landmarks: np.ndarray | None = None) -> FrameResult:
        """Associate one frame. instances (H, W) uint16 (contract encoding); size (W, H); depth_m (H, W) metres
        (NaN = none) registered to it, or None; landmarks (N, 3) world, or None. Raises ValueError for a depth
        image of another size than the instances (the caller reports it and may retry without)."""
        if depth_m is not None and depth_m.shape != instances.shape:
            raise ValueError(f'depth {depth_m.shape[1]}x{depth_m.shape[0]} is not registered to the detections '
                             f'{instances.shape[1]}x{instances.shape[0]}')
        labels, boxes = detections_from_instances(instances)
        surface, points, evidence_ms = None, None, None
        if landmarks is not None and not len(landmarks):
            landmarks = None
        if (depth_m is not None or landmarks is not None) and len(labels):
            e = self.evidence
            t0 = time.perf_counter()
            surface = surface_depths(instances, labels, K, invert_transform(T_world_camera), depth_m, landmarks,
                                     **e.surface_arguments())
            if depth_m is not None:
                points = depth_points(instances, labels, depth_m, K, T_world_camera, self.associator.cfg, e)
            evidence_ms = 1e3 * (time.perf_counter() - t0)
        contact = (contact_edges(instances, labels, boxes, surface) if self.associator.cfg.box_contact_edges
                   else None)
        t0 = time.perf_counter()
        update = self.associator.add_frame(stamp, K, T_world_camera, size, labels, boxes, surface, contact, points)
        t1 = time.perf_counter()
        refined = self.associator.refine_boxes()
        t2 = time.perf_counter()
        republish = update.republish + [s for s in refined.republish if s not in update.republish]
        return FrameResult(update, refined, republish, 1e3 * (t1 - t0), 1e3 * (t2 - t1), evidence_ms)


def config_from_values(values: dict) -> tuple[AssociationConfig, EvidenceConfig]:
    """(AssociationConfig, EvidenceConfig) from {parameter name: value} (node parameters or a params YAML
    section); names of neither are ignored, values are cast to the field's type."""
    def build(cls):
        defaults = cls()
        return cls(**{f.name: type(getattr(defaults, f.name))(values[f.name]) for f in fields(cls) if f.name in values})
    return build(AssociationConfig), build(EvidenceConfig)
