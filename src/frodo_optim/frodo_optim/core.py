"""Optimiser core (paper Sec. 5.3, "Initialization"): per-object state and the fused-stage placement.

The fused stage places the mesh decoded from the object's fused code (Sec. 5.2) into the world from
its 3D box (Sec. 5.1): translation = box centre, scale = box height over the decoded shape's height
(the paper scales by the box height), rotation = yaw about gravity. The box yaw is known up to the box
symmetry; of the four candidates yaw + k*pi/2 we keep the one whose rotated shape footprint best fits
the box footprint. Front/back (k vs k+2) cannot be told from a box: that is left to the exhaustive
yaw search of the sparse stage, so the fused stage is named "box-fit placement", not the full init.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from frodo_common.geometry import Box3D, make_transform, transform_points, yaw_matrix


@dataclass
class ObjectEstimate:
    """Everything known about one object.

    T_world_object: (4, 4) similarity, x_world = scale * R @ x_normalised + t.
    box: the mesh's upright world box (`Box3D`).
    stage: 'fused' | 'sparse' | 'dense' (states.STAGES); stage_reason: index into states.STAGE_REASONS.
    stamp_ns: data time of the estimate, the stamp (ns, the bag's or the sensor's clock) of the newest frame it
    was made from (0: unknown); the optimiser stamps the object's markers with it, never with the wall clock.
    """

    object_id: int
    class_name: str
    category: int
    code: np.ndarray
    T_world_object: np.ndarray
    scale: float
    box: Box3D
    num_views: int
    stage: str
    mesh_world: trimesh.Trimesh
    timings: dict[str, float] = field(default_factory=dict)
    stage_reason: int = 0           # index into states.STAGE_REASONS: why the object ends at `stage`
    stamp_ns: int = 0               # stamp of the newest frame the estimate used (data time, not wall time)


def place_from_box(mesh_normalised: trimesh.Trimesh, center, size, yaw: float):
    """Similarity placing a normalised-frame mesh into an upright world box.

    mesh_normalised: decoded shape in the normalised object frame (z up).
    center (3,), size (3,) = (along box x, along box y, height), yaw: the world box.
    Returns (T_world_object (4, 4), scale, chosen yaw).
    """
    lo, hi = mesh_normalised.bounds
    extent = np.maximum(hi - lo, 1e-6)
    size = np.maximum(np.asarray(size, dtype=np.float64), 1e-6)
    scale = size[2] / extent[2]
    # k = 0 keeps the shape's x along the box x; k = 1 swaps the footprint axes.
    errors = [np.sum(np.log(scale * extent[[0, 1]] / size[[0, 1]]) ** 2),
              np.sum(np.log(scale * extent[[1, 0]] / size[[0, 1]]) ** 2)]
    chosen = float(yaw + (np.pi / 2 if errors[1] < errors[0] else 0.0))
    R = yaw_matrix(chosen)
    mid = (lo + hi) / 2
    t = np.asarray(center, dtype=np.float64) - scale * R @ mid
    return make_transform(R, t, scale), float(scale), chosen


def world_box(mesh_normalised: trimesh.Trimesh, T_world_object: np.ndarray, yaw: float) -> Box3D:
    """Upright world box of a placed mesh: its normalised-frame box mapped by T."""
    lo, hi = mesh_normalised.bounds
    scale = float(np.linalg.norm(T_world_object[:3, 0]))
    center = transform_points(T_world_object, ((lo + hi) / 2)[None])[0]
    return Box3D(center, (hi - lo) * scale, float(yaw))


def fused_estimate(object_id: int, class_name: str, category: int, code: np.ndarray, num_views: int,
                   mesh_normalised: trimesh.Trimesh, track_box, stamp_ns: int = 0) -> ObjectEstimate:
    """ObjectEstimate of the fused stage from a decoded mesh and the association's box (stamp_ns: its data time)."""
    center, size, yaw = track_box
    T, scale, chosen = place_from_box(mesh_normalised, center, size, yaw)
    mesh_world = mesh_normalised.copy()
    mesh_world.apply_transform(T)
    return ObjectEstimate(object_id, class_name, int(category), np.asarray(code, dtype=np.float32), T, scale,
                          world_box(mesh_normalised, T, chosen), int(num_views), 'fused', mesh_world,
                          stamp_ns=int(stamp_ns))
