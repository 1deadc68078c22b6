"""Canonical object frame and the normalised frame the shape decoders see.

Object (canonical, metric) frame: z up (gravity), the object's front faces +x (a chair: the direction a
seated person looks; a table: +x is the normal of a long side, so the long side runs along y), origin at
the centre of the axis-aligned bounding box, units metres. The floor contact is at z = -height / 2.

Normalised frame: the canonical frame scaled uniformly so that the bounding-box half-diagonal is
`CANONICAL_RADIUS` (the shape lies inside the unit sphere, with room to sample [-1, 1]^3 around it).
`scale` is metres per normalised unit, the 7th DoF of `T_world_object`:
`x_metric = scale * x_normalised` and `x_world = scale * R * x_normalised + t`.
"""
from __future__ import annotations

import numpy as np
import trimesh

CANONICAL_RADIUS = 0.9  # bounding-box half-diagonal of a shape in the normalised frame

AXIS_VECTORS: dict[str, np.ndarray] = {
    sign + name: (1.0 if sign == '' else -1.0) * np.eye(3)[index]
    for index, name in enumerate('xyz') for sign in ('', '+', '-')
}


def bbox_centre(mesh: trimesh.Trimesh) -> np.ndarray:
    """Centre (3,) of the axis-aligned bounding box of `mesh`."""
    return mesh.bounds.mean(axis=0)


def centre_on_bbox(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Copy of `mesh` translated so that its axis-aligned bounding box is centred at the origin."""
    centred = mesh.copy()
    centred.apply_translation(-bbox_centre(mesh))
    return centred


def normalisation_scale(mesh: trimesh.Trimesh) -> float:
    """Metres per normalised unit: bounding-box half-diagonal of the metric `mesh` / CANONICAL_RADIUS."""
    half_diagonal = 0.5 * float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]))
    return half_diagonal / CANONICAL_RADIUS


def normalise(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, float]:
    """Map a canonical metric mesh to the normalised frame.

    The mesh is centred on its bounding box (a no-op for canonical meshes) and divided by
    `scale = half_diagonal / CANONICAL_RADIUS`. Returns (normalised mesh, scale in metres per unit);
    `denormalise(normalised, scale)` gives the bbox-centred metric mesh back.
    """
    scale = normalisation_scale(mesh)
    normalised = centre_on_bbox(mesh)
    normalised.apply_scale(1.0 / scale)
    return normalised, scale


def denormalise(mesh_normalised: trimesh.Trimesh, scale: float) -> trimesh.Trimesh:
    """Inverse of `normalise`: the metric canonical mesh (normalised vertices times `scale`)."""
    metric = mesh_normalised.copy()
    metric.apply_scale(float(scale))
    return metric


def axes_to_canonical(up_axis: str, front_axis: str) -> np.ndarray:
    """Rotation (3, 3) taking a source frame whose up and front directions are the named axes
    ('x', 'y', 'z', optionally signed: '+y', '-z') to the canonical frame (up +z, front +x)."""
    try:
        up, front = AXIS_VECTORS[up_axis.strip().lower()], AXIS_VECTORS[front_axis.strip().lower()]
    except KeyError as error:
        raise ValueError(f'axis names must be one of {sorted(AXIS_VECTORS)}, got up={up_axis!r}, '
                         f'front={front_axis!r}') from error
    if abs(float(up @ front)) > 0.5:
        raise ValueError(f'up axis {up_axis!r} and front axis {front_axis!r} must be perpendicular')
    # Rows are the source directions that become canonical x (front), y (up x front, the left) and z (up).
    return np.stack([front, np.cross(up, front), up])
