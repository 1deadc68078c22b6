"""Procedural tables: four-leg tables, round pedestal tables, trestle tables and coffee tables.

Each generator draws continuous proportions and discrete part styles from a numpy Generator and returns
the union of overlapping solids as one watertight trimesh in metres, floor at z = 0, top centred over the
origin in x-y. Front convention: the long side runs along y, so +x is the normal of a long side (where a
diner sits facing -x); round tables are symmetric. `library.generate` moves the result into the canonical
frame (bounding box centred at the origin).
"""
from __future__ import annotations

import numpy as np
import trimesh
from manifold3d import Manifold

from .solids import beam, box, box_between, cylinder, lathe, radial_foot, rounded_slab, strut, union


def corner_legs(rng: np.random.Generator, depth: float, length: float, leg_top_z: float,
                  leg_half_width: float) -> tuple[list[Manifold], np.ndarray, np.ndarray]:
    """Four tapered round or square legs under a top of extents (`depth` x, `length` y), with a random inset.

    Returns (leg solids, leg centres at the floor (4, 3), leg centres at `leg_top_z` (4, 3)); legs are
    ordered (-x,-y), (-x,+y), (+x,-y), (+x,+y).
    """
    inset = rng.uniform(0.03, 0.10)
    round_legs = bool(rng.random() < 0.4)
    taper = rng.uniform(0.6, 1.0)
    splay = rng.uniform(0.0, 0.03) if rng.random() < 0.3 else 0.0
    leg_x, leg_y = depth / 2 - inset - leg_half_width, length / 2 - inset - leg_half_width
    signs = np.array([[sx, sy] for sx in (-1, 1) for sy in (-1, 1)], float)
    tops = np.column_stack([signs * [leg_x, leg_y], np.full(4, leg_top_z)])
    bottoms = np.column_stack([signs * [leg_x + splay, leg_y + splay], np.zeros(4)])
    legs = [strut(bottom, top, taper * leg_half_width, leg_half_width, round_legs) for bottom, top in zip(bottoms, tops)]
    return legs, bottoms, tops


def four_leg_table(rng: np.random.Generator) -> trimesh.Trimesh:
    """Rectangular dining table: top with square or rounded corners, four legs, optional apron and optional
    H or box stretchers."""
    length, depth, height = rng.uniform(1.2, 2.0), rng.uniform(0.75, 1.0), rng.uniform(0.72, 0.77)
    top_thickness = rng.uniform(0.025, 0.05)
    top_bottom = height - top_thickness
    corner_radius = rng.uniform(0.02, 0.12) if rng.random() < 0.5 else 0.0
    leg_half_width = rng.uniform(0.02, 0.04)
    parts: list[Manifold] = [rounded_slab(depth, length, top_thickness, corner_radius, (0.0, 0.0, height - top_thickness / 2))]
    legs, bottoms, tops = corner_legs(rng, depth, length, top_bottom + 0.5 * top_thickness, leg_half_width)
    parts += legs

    if rng.random() < 0.6:  # apron: boards under the top joining the legs
        apron_height, apron_thickness = rng.uniform(0.06, 0.11), 0.02
        leg_x, leg_y = tops[3, 0], tops[3, 1]
        apron_z = top_bottom - apron_height / 2 + 0.005
        for sx in (-1, 1):
            parts.append(box((apron_thickness, 2 * leg_y, apron_height), (sx * (leg_x - leg_half_width / 2), 0.0, apron_z)))
        for sy in (-1, 1):
            parts.append(box((2 * leg_x, apron_thickness, apron_height), (0.0, sy * (leg_y - leg_half_width / 2), apron_z)))

    stretcher_style = rng.choice(['none', 'H', 'box'], p=[0.6, 0.2, 0.2])
    if stretcher_style != 'none':
        stretcher_z = rng.uniform(0.1, 0.2)
        points = bottoms + (tops - bottoms) * stretcher_z / tops[0, 2]
        thickness = rng.uniform(0.025, 0.04)
        parts += [beam(points[0], points[2], thickness, thickness), beam(points[1], points[3], thickness, thickness)]
        if stretcher_style == 'H':
            parts.append(beam((points[0] + points[2]) / 2, (points[1] + points[3]) / 2, thickness, thickness))
        else:
            parts += [beam(points[0], points[1], thickness, thickness), beam(points[2], points[3], thickness, thickness)]
    return union(parts)


def pedestal_table(rng: np.random.Generator) -> trimesh.Trimesh:
    """Round pedestal table: round top on a support plate, a turned (straight, tapered or bulging) column and
    a foot: a bevelled disk or three/four radial feet."""
    top_radius, height = rng.uniform(0.35, 0.60), rng.uniform(0.72, 0.76)
    top_thickness = rng.uniform(0.025, 0.045)
    top_bottom = height - top_thickness
    top_profile = np.array([[0.0, top_bottom], [top_radius, top_bottom], [top_radius, height], [0.0, height]])
    plate_radius, plate_thickness = rng.uniform(0.12, 0.25), 0.02
    parts: list[Manifold] = [lathe(top_profile), cylinder(plate_radius, top_bottom - plate_thickness, top_bottom + 0.005)]

    foot_style = rng.choice(['disk', 'feet'])
    foot_height = rng.uniform(0.03, 0.06)
    column_radius = rng.uniform(0.035, 0.075)
    column_bottom, column_top = foot_height - 0.01, top_bottom - plate_thickness + 0.005
    column_z = np.linspace(column_bottom, column_top, 9)
    bulge, taper = rng.uniform(-0.3, 0.6), rng.uniform(-0.3, 0.3)
    along = np.linspace(0.0, 1.0, column_z.size)
    column_radii = column_radius * (1.0 + bulge * np.sin(np.pi * along) + taper * (along - 0.5))
    column_profile = np.vstack([[0.0, column_bottom], np.column_stack([column_radii, column_z]), [0.0, column_top]])
    parts.append(lathe(column_profile))

    if foot_style == 'disk':
        foot_radius = rng.uniform(0.22, 0.35)
        foot_profile = np.array([[0.0, 0.0], [foot_radius, 0.0], [foot_radius, 0.4 * foot_height],
                                 [column_radius * 1.2, foot_height], [0.0, foot_height]])
        parts.append(lathe(foot_profile))
    else:
        foot_count = int(rng.choice([3, 4]))
        reach = rng.uniform(0.25, 0.38)
        foot_width = rng.uniform(0.04, 0.07)
        parts.append(cylinder(max(column_radius * 1.3, foot_width), 0.0, foot_height + 0.04))
        for angle in np.pi / foot_count + 2 * np.pi * np.arange(foot_count) / foot_count:
            parts.append(radial_foot(angle, reach, foot_width, foot_height + 0.05, 0.8 * foot_width, 0.5 * foot_height + 0.01))
    return union(parts)


def trestle_table(rng: np.random.Generator) -> trimesh.Trimesh:
    """Trestle table: long top on two trestles near its ends (foot bar, upright as a slab, an A frame or an
    X frame, cleat under the top) joined by a long stretcher."""
    length, depth, height = rng.uniform(1.6, 2.4), rng.uniform(0.8, 1.0), rng.uniform(0.72, 0.77)
    top_thickness = rng.uniform(0.03, 0.06)
    top_bottom = height - top_thickness
    parts: list[Manifold] = [rounded_slab(depth, length, top_thickness, rng.uniform(0.0, 0.05), (0.0, 0.0, height - top_thickness / 2))]

    trestle_y = length / 2 - rng.uniform(0.15, 0.30)
    foot_length, foot_height, foot_width = depth * rng.uniform(0.65, 0.85), rng.uniform(0.04, 0.08), rng.uniform(0.05, 0.09)
    cleat_length, cleat_height = depth * rng.uniform(0.7, 0.9), rng.uniform(0.04, 0.06)
    upright_style = rng.choice(['slab', 'a_frame', 'x_frame'])
    upright_thickness = rng.uniform(0.04, 0.07)
    slab_width = rng.uniform(0.12, 0.30)
    strut_top_x = rng.uniform(0.03, 0.15)
    stretcher_height, stretcher_thickness = rng.uniform(0.06, 0.10), rng.uniform(0.03, 0.05)
    slab_stretcher_fraction = rng.uniform(0.25, 0.5)
    upright_bottom, upright_top = foot_height - 0.01, top_bottom - cleat_height + 0.01
    for sy in (-1, 1):
        y = sy * trestle_y
        parts.append(box_between((-foot_length / 2, y - foot_width / 2, 0.0), (foot_length / 2, y + foot_width / 2, foot_height)))
        parts.append(box_between((-cleat_length / 2, y - foot_width / 2, top_bottom - cleat_height),
                                 (cleat_length / 2, y + foot_width / 2, top_bottom + 0.005)))
        if upright_style == 'slab':
            parts.append(box_between((-slab_width / 2, y - upright_thickness / 2, upright_bottom),
                                     (slab_width / 2, y + upright_thickness / 2, upright_top)))
            continue
        strut_bottom_x = 0.8 * foot_length / 2 - upright_thickness
        for sx in (-1, 1):  # an A frame narrows towards the top, an X frame crosses at mid height
            top_x = sx * strut_top_x if upright_style == 'a_frame' else -sx * strut_bottom_x
            parts.append(beam((sx * strut_bottom_x, y, upright_bottom), (top_x, y, upright_top), upright_thickness, upright_thickness))
    stretcher_z = {'slab': slab_stretcher_fraction * height,
                   'a_frame': top_bottom - cleat_height - stretcher_height / 2 + 0.005,
                   'x_frame': (upright_bottom + upright_top) / 2}[upright_style]
    parts.append(box((stretcher_thickness, 2 * trestle_y, stretcher_height), (0.0, 0.0, stretcher_z)))
    return union(parts)


def coffee_table(rng: np.random.Generator) -> trimesh.Trimesh:
    """Low coffee table: thick top, four sturdy legs and an optional lower shelf."""
    length, depth, height = rng.uniform(0.9, 1.4), rng.uniform(0.5, 0.8), rng.uniform(0.35, 0.50)
    top_thickness = rng.uniform(0.03, 0.07)
    top_bottom = height - top_thickness
    parts: list[Manifold] = [rounded_slab(depth, length, top_thickness, rng.uniform(0.0, 0.06) if rng.random() < 0.5 else 0.0,
                                          (0.0, 0.0, height - top_thickness / 2))]
    leg_half_width = rng.uniform(0.02, 0.045)
    legs, bottoms, tops = corner_legs(rng, depth, length, top_bottom + 0.5 * top_thickness, leg_half_width)
    parts += legs
    if rng.random() < 0.5:  # lower shelf reaching into the legs
        shelf_z, shelf_thickness = rng.uniform(0.08, 0.15), 0.02
        shelf_points = bottoms + (tops - bottoms) * shelf_z / tops[0, 2]
        half_x, half_y = np.abs(shelf_points[3, :2]) + 0.5 * leg_half_width
        parts.append(box((2 * half_x, 2 * half_y, shelf_thickness), (0.0, 0.0, shelf_z)))
    return union(parts)
