"""Procedural extra tables of the broader shape prior: panel-end (waterfall) tables, X-base tables and small
side tables.

These are extra training designs (real-world part variety) registered in `library.EXTRA_FAMILIES`, so
`families()` and the synthetic scenes are unchanged; they avoid the held-out designs of `heldout` (no drawer
pedestals or modesty panels, no round or oval tops on four legs). Same conventions as `tables`: each
generator draws continuous proportions and discrete part styles from a numpy Generator and returns the union
of overlapping solids as one watertight trimesh in metres, floor at z = 0, top centred over the origin in x-y,
the long side along y (+x is the normal of a long side). `library.generate` moves the result into the
canonical frame (bounding box centred at the origin).
"""
from __future__ import annotations

import numpy as np
import trimesh
from manifold3d import Manifold

from .solids import beam, box, box_between, cylinder, merge, rounded_slab, strut, union
from .tables import corner_legs


def panel_end_table(rng: np.random.Generator) -> trimesh.Trimesh:
    """Panel-end (waterfall / Parsons) dining table: rectangular top with square or slightly rounded corners
    on two full-depth vertical panels at its short ends, flush with the top's ends or inset; the panels are
    solid slabs or rectangular frames (two posts and two bars round a cut-out), with an optional long
    stretcher between them near the floor or under the top."""
    length, depth, height = rng.uniform(1.2, 2.2), rng.uniform(0.7, 1.0), rng.uniform(0.72, 0.77)
    top_thickness = rng.uniform(0.02, 0.05)
    top_bottom = height - top_thickness
    panel_thickness = rng.uniform(0.02, 0.08)
    flush = bool(rng.random() < 0.5)
    inset = 0.0 if flush else rng.uniform(0.05, 0.25)
    corner_radius = rng.uniform(0.01, 0.05) if not flush and rng.random() < 0.5 else 0.0  # within the inset
    top_centre = (0.0, 0.0, height - top_thickness / 2)
    parts: list[Manifold] = [rounded_slab(depth, length, top_thickness, corner_radius, top_centre)]

    framed = bool(rng.random() < 0.35)
    post_width, bar_height = rng.uniform(0.05, 0.12), rng.uniform(0.05, 0.12)
    panel_top = top_bottom + 0.5 * top_thickness
    panel_y = length / 2 - inset - panel_thickness / 2
    for sy in (-1, 1):
        y = sy * panel_y
        if not framed:
            parts.append(box((depth, panel_thickness, panel_top), (0.0, y, panel_top / 2)))
            continue
        for sx in (-1, 1):  # posts along the long edges; floor and top bars across the full depth
            parts.append(box_between((sx * depth / 2, y - panel_thickness / 2, 0.0),
                                     (sx * (depth / 2 - post_width), y + panel_thickness / 2, panel_top)))
        parts.append(box_between((-depth / 2, y - panel_thickness / 2, 0.0),
                                 (depth / 2, y + panel_thickness / 2, bar_height)))
        parts.append(box_between((-depth / 2, y - panel_thickness / 2, top_bottom - bar_height),
                                 (depth / 2, y + panel_thickness / 2, panel_top)))

    stretcher_style = rng.choice(['none', 'floor', 'under_top'], p=[0.4, 0.3, 0.3])
    if stretcher_style != 'none':
        stretcher_width, stretcher_height = rng.uniform(0.03, 0.06), rng.uniform(0.05, 0.12)
        if stretcher_style == 'floor':  # low enough to meet a frame's floor bar
            stretcher_bottom = rng.uniform(0.0, 0.5 * bar_height) if framed else rng.uniform(0.0, 0.12)
        else:
            stretcher_bottom = top_bottom - stretcher_height + 0.005
        parts.append(box_between((-stretcher_width / 2, -panel_y, stretcher_bottom),
                                 (stretcher_width / 2, panel_y, stretcher_bottom + stretcher_height)))
    return union(parts)


def _x_frame(half_span: float, bar_width: float, beam_thickness: float, foot_height: float, cleat_height: float,
             top_bottom: float) -> Manifold:
    """X leg frame in the x-z plane at y = 0: a floor foot bar and an under-top bar (cleat) of half length
    `half_span` joined by two beams crossing at mid height, the beams clipped to the frame's outline."""
    beam_bottom, beam_top = foot_height / 2, top_bottom - cleat_height / 2
    crossed = merge([beam((-half_span, 0.0, beam_bottom), (half_span, 0.0, beam_top), 0.9 * bar_width, beam_thickness),
                     beam((half_span, 0.0, beam_bottom), (-half_span, 0.0, beam_top), 0.9 * bar_width, beam_thickness)])
    crossed = crossed ^ box_between((-half_span, -bar_width, 0.0), (half_span, bar_width, top_bottom))
    foot = box_between((-half_span, -bar_width / 2, 0.0), (half_span, bar_width / 2, foot_height))
    cleat = box_between((-half_span, -bar_width / 2, top_bottom - cleat_height),
                        (half_span, bar_width / 2, top_bottom + 0.005))
    return merge([crossed, foot, cleat])


def x_base_table(rng: np.random.Generator) -> trimesh.Trimesh:
    """X-base table: rectangular top (square or rounded corners) on two X-shaped leg frames near its ends
    (two beams crossing in the x-z plane between a floor foot bar and a bar under the top) joined by a long
    stretcher at the crossings or under the top; or a square top on a single central base of two such X
    frames crossing at right angles, along the top's axes or its diagonals."""
    central = bool(rng.random() < 0.3)
    if central:
        length = depth = rng.uniform(0.8, 1.2)
    else:
        length, depth = rng.uniform(1.0, 2.2), rng.uniform(0.75, 1.0)
    height = rng.uniform(0.72, 0.77)
    top_thickness = rng.uniform(0.025, 0.05)
    top_bottom = height - top_thickness
    corner_radius = rng.uniform(0.02, 0.10) if rng.random() < 0.5 else 0.0
    top_centre = (0.0, 0.0, height - top_thickness / 2)
    parts: list[Manifold] = [rounded_slab(depth, length, top_thickness, corner_radius, top_centre)]
    bar_width, beam_thickness = rng.uniform(0.04, 0.08), rng.uniform(0.03, 0.08)
    foot_height, cleat_height = rng.uniform(0.03, 0.07), rng.uniform(0.03, 0.06)

    if central:
        diagonal = bool(rng.random() < 0.5)
        margin = rng.uniform(0.08, 0.20) + corner_radius
        half_span = (depth / 2 - margin) * (np.sqrt(2.0) if diagonal else 1.0) - bar_width
        frame = _x_frame(half_span, bar_width, beam_thickness, foot_height, cleat_height, top_bottom)
        first_angle = 45.0 if diagonal else 0.0
        parts += [frame.rotate((0.0, 0.0, first_angle)), frame.rotate((0.0, 0.0, first_angle + 90.0))]
        return union(parts)

    frame_y = length / 2 - rng.uniform(0.10, 0.30)
    half_span = depth / 2 - rng.uniform(0.03, 0.10)
    frame = _x_frame(half_span, bar_width, beam_thickness, foot_height, cleat_height, top_bottom)
    parts += [frame.translate((0.0, -frame_y, 0.0)), frame.translate((0.0, frame_y, 0.0))]
    stretcher_width, stretcher_height = rng.uniform(0.03, 0.06), rng.uniform(0.04, 0.09)
    if rng.random() < 0.6:  # through the crossings
        stretcher_z = (foot_height / 2 + top_bottom - cleat_height / 2) / 2
    else:  # under the top, between the cleats
        stretcher_z = top_bottom - stretcher_height / 2 + 0.005
    parts.append(box((stretcher_width, 2 * frame_y, stretcher_height), (0.0, 0.0, stretcher_z)))
    return union(parts)


def side_table(rng: np.random.Generator) -> trimesh.Trimesh:
    """Small side / end / bedside table: a square (or nearly square) top on four thin, optionally splayed
    legs with a lower shelf; a round top on three splayed tripod legs with an optional round lower shelf; or
    a C-table (top, one side panel and a floor plate), optionally closed at both ends into an open cube."""
    style = rng.choice(['four_leg', 'tripod', 'c_table'], p=[0.4, 0.3, 0.3])
    height = rng.uniform(0.45, 0.70)
    top_thickness = rng.uniform(0.015, 0.04)
    top_bottom = height - top_thickness

    if style == 'four_leg':
        length = rng.uniform(0.35, 0.65)
        depth = rng.uniform(max(0.35, 0.75 * length), length)
        corner_radius = rng.uniform(0.01, 0.04) if rng.random() < 0.4 else 0.0
        top_centre = (0.0, 0.0, height - top_thickness / 2)
        parts: list[Manifold] = [rounded_slab(depth, length, top_thickness, corner_radius, top_centre)]
        leg_half_width = rng.uniform(0.012, 0.025)
        legs, bottoms, tops = corner_legs(rng, depth, length, top_bottom + 0.5 * top_thickness, leg_half_width)
        parts += legs
        if rng.random() < 0.85:  # lower shelf reaching into the legs
            shelf_z, shelf_thickness = rng.uniform(0.10, 0.25), rng.uniform(0.015, 0.025)
            shelf_points = bottoms + (tops - bottoms) * shelf_z / tops[0, 2]
            half_x, half_y = np.abs(shelf_points[3, :2]) + 0.5 * leg_half_width
            parts.append(box((2 * half_x, 2 * half_y, shelf_thickness), (0.0, 0.0, shelf_z)))
        return union(parts)

    if style == 'tripod':
        radius = rng.uniform(0.175, 0.325)
        parts = [cylinder(radius, top_bottom, height)]
        leg_half_width = rng.uniform(0.012, 0.025)
        round_legs = bool(rng.random() < 0.6)
        top_reach = radius * rng.uniform(0.35, 0.7)
        foot_reach = top_reach + rng.uniform(0.0, 0.9) * (radius - leg_half_width - top_reach)
        angles = np.radians([90.0, 210.0, 330.0])
        directions = np.column_stack([np.cos(angles), np.sin(angles)])
        leg_top = top_bottom + 0.5 * top_thickness
        for direction in directions:
            parts.append(strut((*(foot_reach * direction), 0.0), (*(top_reach * direction), leg_top),
                               0.75 * leg_half_width, leg_half_width, round_legs))
        if rng.random() < 0.5:  # round lower shelf reaching into the legs
            shelf_z, shelf_thickness = rng.uniform(0.10, 0.25), rng.uniform(0.015, 0.025)
            shelf_reach = foot_reach + (top_reach - foot_reach) * shelf_z / top_bottom
            parts.append(cylinder(shelf_reach + 0.5 * leg_half_width, shelf_z - shelf_thickness / 2,
                                  shelf_z + shelf_thickness / 2))
        return union(parts)

    length = rng.uniform(0.40, 0.65)
    depth = rng.uniform(0.35, min(0.55, length))
    panel_thickness = rng.uniform(0.015, 0.04)
    plate_thickness = rng.uniform(0.015, 0.04)
    plate_length = length * rng.uniform(0.7, 1.0)
    plate_depth = depth * rng.uniform(0.85, 1.0)
    closed = bool(rng.random() < 0.3)
    side = float(rng.choice([-1.0, 1.0]))
    panel_y = side * (length / 2 - panel_thickness / 2)
    panel_top = top_bottom + 0.5 * top_thickness
    parts = [box((depth, length, top_thickness), (0.0, 0.0, height - top_thickness / 2)),
             box((plate_depth, panel_thickness, panel_top), (0.0, panel_y, panel_top / 2))]
    if closed:  # second panel: an open cube, the floor plate spanning between the panels
        parts.append(box((plate_depth, panel_thickness, panel_top), (0.0, -panel_y, panel_top / 2)))
        plate_length = length
    parts.append(box((plate_depth, plate_length, plate_thickness),
                     (0.0, side * (length - plate_length) / 2, plate_thickness / 2)))
    return union(parts)
