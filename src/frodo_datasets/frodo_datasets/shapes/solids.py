"""Solid building blocks of the procedural furniture and their boolean union into one watertight mesh.

Every builder returns a `manifold3d.Manifold` (a closed, oriented 2-manifold solid) in metres, z up. The
furniture generators compose boxes, struts, rods, rounded slabs and lathed profiles that overlap where
they join; `union` merges them with manifold3d's exact boolean union, so the result is watertight and a
positive volume by construction. Round parts use a fixed segment count (never manifold3d's global
quality setting), so a shape only depends on its parameters.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import trimesh
from manifold3d import CrossSection, Error, Manifold, OpType

ROUND_SEGMENTS = 24  # circular segments of round parts (legs, columns, seats, rings)
BALL_SEGMENTS = 12  # segments of the spheres rounding corners and capping rods
CAP_THICKNESS = 1e-3  # thickness of the thin end caps whose convex hull forms a strut (m)
SLIVER_VOLUME = 1e-9  # union components below this volume (m^3) are numerical slivers


def box(size: Sequence[float], centre: Sequence[float]) -> Manifold:
    """Axis-aligned box of extents `size` (3,) centred at `centre` (3,)."""
    return Manifold.cube(tuple(float(s) for s in size), True).translate(tuple(float(c) for c in centre))


def box_between(lower: Sequence[float], upper: Sequence[float]) -> Manifold:
    """Axis-aligned box spanning the opposite corners `lower` (3,) and `upper` (3,) (in any order)."""
    first, second = np.asarray(lower, float), np.asarray(upper, float)
    return box(np.abs(second - first), (first + second) / 2)


def rounded_box(size: Sequence[float], centre: Sequence[float], radius: float) -> Manifold:
    """Box of extents `size` (3,) centred at `centre` (3,) with all edges rounded by `radius` (clipped to fit)."""
    half = np.asarray(size, float) / 2
    radius = float(min(radius, 0.49 * half.min()))
    inner = half - radius
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * inner
    ball = Manifold.sphere(radius, BALL_SEGMENTS)
    return Manifold.batch_hull([ball.translate(tuple(c)) for c in corners]).translate(tuple(float(c) for c in centre))


def rounded_slab(length_x: float, width_y: float, thickness: float, corner_radius: float,
                 centre: Sequence[float]) -> Manifold:
    """Horizontal slab (table top) of extents (`length_x`, `width_y`, `thickness`) with vertical corners
    rounded by `corner_radius` (clipped to fit), centred at `centre` (3,)."""
    radius = float(min(corner_radius, 0.49 * min(length_x, width_y)))
    if radius <= 1e-4:
        return box((length_x, width_y, thickness), centre)
    post = Manifold.cylinder(thickness, radius, radius, ROUND_SEGMENTS, True)
    corners = [(sx * (length_x / 2 - radius), sy * (width_y / 2 - radius), 0.0) for sx in (-1, 1) for sy in (-1, 1)]
    return Manifold.batch_hull([post.translate(c) for c in corners]).translate(tuple(float(c) for c in centre))


def strut(bottom: Sequence[float], top: Sequence[float], bottom_half_width: float, top_half_width: float,
          round_profile: bool) -> Manifold:
    """Leg or post from `bottom` (3,) to `top` (3,) with horizontal end faces: the convex hull of two thin
    horizontal discs (`round_profile`) or squares of the given half widths, so splayed legs stand flat."""
    def cap(centre: Sequence[float], half_width: float) -> Manifold:
        if round_profile:
            disc = Manifold.cylinder(CAP_THICKNESS, half_width, half_width, ROUND_SEGMENTS, True)
        else:
            disc = Manifold.cube((2 * half_width, 2 * half_width, CAP_THICKNESS), True)
        return disc.translate(tuple(float(c) for c in centre))

    bottom_centre = np.asarray(bottom, float) + [0.0, 0.0, CAP_THICKNESS / 2]
    top_centre = np.asarray(top, float) - [0.0, 0.0, CAP_THICKNESS / 2]
    return Manifold.batch_hull([cap(bottom_centre, bottom_half_width), cap(top_centre, top_half_width)])


def rod(start: Sequence[float], end: Sequence[float], start_radius: float, end_radius: float) -> Manifold:
    """Round-ended rod (capsule, optionally tapered) from `start` (3,) to `end` (3,): hull of two spheres."""
    return Manifold.batch_hull([Manifold.sphere(start_radius, BALL_SEGMENTS).translate(tuple(float(c) for c in start)),
                                Manifold.sphere(end_radius, BALL_SEGMENTS).translate(tuple(float(c) for c in end))])


def beam(start: Sequence[float], end: Sequence[float], width: float, height: float) -> Manifold:
    """Rectangular beam from `start` (3,) to `end` (3,) (end faces through the points): cross-section
    `width` along the horizontal perpendicular of the axis and `height` along the remaining direction."""
    start_point, end_point = np.asarray(start, float), np.asarray(end, float)
    axis = end_point - start_point
    length = float(np.linalg.norm(axis))
    along = axis / length
    side = np.cross([0.0, 0.0, 1.0], along)
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-9 else np.array([0.0, 1.0, 0.0])
    up = np.cross(along, side)
    rotation = np.stack([along, side, up], axis=1)  # columns: local x, y, z in the world frame
    affine = np.concatenate([rotation, ((start_point + end_point) / 2)[:, None]], axis=1)
    return Manifold.cube((length, float(width), float(height)), True).transform(affine)


def cylinder(radius: float, z_bottom: float, z_top: float, centre_xy: Sequence[float] = (0.0, 0.0)) -> Manifold:
    """Vertical cylinder of `radius` from `z_bottom` to `z_top` above the point `centre_xy` (2,)."""
    return Manifold.cylinder(z_top - z_bottom, radius, radius, ROUND_SEGMENTS, False).translate(
        (float(centre_xy[0]), float(centre_xy[1]), float(z_bottom)))


def radial_foot(angle: float, reach: float, hub_width: float, hub_height: float, tip_width: float,
                tip_height: float) -> Manifold:
    """Tapered foot on the floor (z = 0) from the z axis out to radius `reach` in the horizontal direction
    `angle` (radians from +x): the hull of a hub block (`hub_width` x `hub_height`) at the axis and a tip
    block (`tip_width` x `tip_height`) at the end of the foot."""
    hub = box((hub_width, hub_width, hub_height), (0.0, 0.0, hub_height / 2))
    tip = box((tip_width, tip_width, tip_height), (reach - tip_width / 2, 0.0, tip_height / 2))
    return Manifold.batch_hull([hub, tip]).rotate((0.0, 0.0, float(np.degrees(angle))))


def lathe(profile_rz: np.ndarray) -> Manifold:
    """Solid of revolution about the z axis of the closed profile `profile_rz` (N, 2) of (radius, z) points
    in counter-clockwise order (radius >= 0; points on the axis close the solid)."""
    return CrossSection([np.asarray(profile_rz, float)]).revolve(ROUND_SEGMENTS)


def torus(major_radius: float, tube_radius: float, z: float) -> Manifold:
    """Horizontal ring about the z axis at height `z` (a footrest ring)."""
    tube = CrossSection.circle(tube_radius, BALL_SEGMENTS).translate((major_radius, 0.0))
    return tube.revolve(ROUND_SEGMENTS).translate((0.0, 0.0, float(z)))


def tilt_back(part: Manifold, degrees: float, pivot: Sequence[float]) -> Manifold:
    """Rotate `part` about the y axis through `pivot` (3,) so that points above the pivot lean towards -x
    (a chair back reclining away from the +x front) by `degrees`."""
    pivot_point = tuple(float(c) for c in pivot)
    return part.translate(tuple(-c for c in pivot_point)).rotate((0.0, -float(degrees), 0.0)).translate(pivot_point)


def merge(parts: Sequence[Manifold]) -> Manifold:
    """Exact boolean union of solids as one Manifold (to transform an assembly as a whole)."""
    return Manifold.batch_boolean(list(parts), OpType.Add)


def union(parts: Sequence[Manifold]) -> trimesh.Trimesh:
    """Exact boolean union of overlapping solids as one watertight trimesh (vertices (V, 3) float64 metres).

    Zero-volume slivers that the boolean can leave where surfaces nearly coincide are dropped.
    """
    merged = merge(parts)
    if merged.status() != Error.NoError or merged.is_empty():
        raise RuntimeError(f'invalid furniture solid: {merged.status()}, {len(parts)} parts')
    pieces = [piece for piece in merged.decompose() if piece.volume() > SLIVER_VOLUME]
    mesh = Manifold.compose(pieces).to_mesh64()
    return trimesh.Trimesh(vertices=np.asarray(mesh.vert_properties, float)[:, :3],
                           faces=np.asarray(mesh.tri_verts, np.int64), process=False)
