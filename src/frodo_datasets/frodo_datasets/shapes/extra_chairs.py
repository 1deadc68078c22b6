"""Procedural extra chairs of the broader shape prior: moulded shell chairs, upholstered dining chairs and
Windsor (spindle-back) chairs.

These are extra training designs (real-world part variety) registered in `library.EXTRA_FAMILIES`, so
`families()` and the synthetic scenes are unchanged; they avoid the held-out designs of `heldout` (no tubular
floor runners or S-frames, no round barrel wall wrapping the seat). Same conventions as `chairs`: each
generator draws continuous proportions and discrete part styles from a numpy Generator and returns the union
of overlapping solids as one watertight trimesh in metres, with the floor at z = 0, the seat centred over the
origin in x-y, the back towards -x and the front (where a seated person looks) towards +x.
`library.generate` moves the result into the canonical frame (bounding box centred at the origin).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import trimesh
from manifold3d import CrossSection, JoinType, Manifold

from .solids import beam, box, cylinder, lathe, merge, radial_foot, rod, rounded_box, strut, tilt_back, union

ARC_STEP_DEG = 8.0  # bend of one segment of a shell's centre line
ARC_CORNER_SEGMENTS = 6  # segments of a quarter circle in a rounded outline


def shell_chair(rng: np.random.Generator) -> trimesh.Trimesh:
    """Moulded shell chair (plastic or plywood, Eames-DSW-like stacking chair): one thin shell, its side
    profile a waterfall front edge, a seat pan sloping slightly down towards the back, a rounded bend and a
    reclined back (straight or curving further back, optionally rolled back at the top); the sides of the
    shell optionally rise towards the sitter, the front and top corners are rounded, and optional arm wings
    rise from the seat edges into the back. Base: four thin splayed legs (round or square, optionally with
    wire bracing), a wire 'eiffel' base (four legs, side rails and X bracing on every face) or a four-star
    swivel foot without casters on a column."""
    seat_top, back_top = rng.uniform(0.42, 0.49), rng.uniform(0.76, 0.88)
    depth = rng.uniform(0.48, 0.58)
    thickness = rng.uniform(0.010, 0.018)
    arms = bool(rng.random() < 0.3)
    width = rng.uniform(0.53, 0.60) if arms else rng.uniform(0.45, 0.53)
    seat_tilt = rng.uniform(2.0, 7.0)  # degrees, the seat pan sloping down towards the back
    recline = rng.uniform(8.0, 18.0)  # degrees of the back from the vertical
    front_heading, front_radius = rng.uniform(105.0, 140.0), rng.uniform(0.03, 0.07)  # waterfall front edge
    bend_radius = rng.uniform(0.06, 0.12)
    back_curve = rng.uniform(0.0, 10.0)  # degrees the back keeps turning back over its length
    top_roll = rng.uniform(10.0, 30.0) if rng.random() < 0.4 else 0.0
    lip_width = rng.uniform(0.05, 0.10)
    lip_rise = min(rng.uniform(0.02, 0.05), 0.5 * bend_radius) if rng.random() < 0.8 else 0.0

    # Side profile of the shell as a centre line in the x-z plane, traced from the bottom of the front edge
    # to the top of the back; the seat and back lengths are solved for the drawn depth and back height.
    front_turn = 180.0 + seat_tilt - front_heading
    bend_turn = (90.0 + recline) - (180.0 + seat_tilt)

    def centre_line(seat_length: float, back_length: float) -> np.ndarray:
        moves = [(front_radius * np.radians(front_turn), front_turn), (seat_length, 0.0),
                 (bend_radius * np.radians(-bend_turn), bend_turn), (back_length, back_curve),
                 (0.05 * np.radians(top_roll), top_roll)]
        return _turtle_line(front_heading, moves)

    front_steps = _arc_steps(front_turn)  # centre-line index of the start of the seat pan
    seat_length, back_length = 0.30, 0.35
    for _ in range(6):
        line = centre_line(seat_length, back_length)
        rise = line[:, 1].max() - line[front_steps, 1]
        back_length += (back_top - seat_top - rise) / np.cos(np.radians(recline + back_curve / 2))
        extent = np.ptp(line[:, 0]) + thickness
        seat_length = max(0.22, seat_length + (depth - extent) / np.cos(np.radians(seat_tilt)))
    line = centre_line(seat_length, back_length)
    seat_start, bend_start = line[front_steps], line[front_steps + 1]
    line = line + [-(seat_start[0] + bend_start[0]) / 2, seat_top - thickness / 2 - seat_start[1]]
    seat_start, bend_start = line[front_steps], line[front_steps + 1]

    # Thicken the centre line into a profile (upper = sitter side), extrude it across the width and bend
    # the sides towards the sitter (fading in over the front edge); then round the front and top corners.
    tangents = np.gradient(line, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    normals = np.column_stack([tangents[:, 1], -tangents[:, 0]])  # towards the sitter
    arc_length = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    fade = np.clip(arc_length / (arc_length[front_steps] + 0.1), 0.0, 1.0)
    profile = np.vstack([line + normals * thickness / 2, (line - normals * thickness / 2)[::-1]])
    profile_normals = np.vstack([normals * fade[:, None], (normals * fade[:, None])[::-1]])
    lip_start = width / 2 - lip_width

    def bend_sides(points: np.ndarray) -> np.ndarray:
        nearest = ((points[:, None, [0, 2]] - profile[None]) ** 2).sum(axis=2).argmin(axis=1)
        lift = lip_rise * np.clip((np.abs(points[:, 1]) - lip_start) / lip_width, 0.0, 1.0) ** 2
        bent = points.copy()
        bent[:, [0, 2]] += lift[:, None] * profile_normals[nearest]
        return bent

    margin = 0.02
    shell = _prism(profile, 'y', -width / 2 - margin, width / 2 + margin,
                   divisions=int(np.ceil((width + 2 * margin) / 0.012))).warp_batch(bend_sides)
    top_radius, front_corner_radius = rng.uniform(0.04, 0.2), rng.uniform(0.03, 0.12)
    low, high = line[:, 1].min() - 0.1, line[:, 1].max() + 0.1
    shell = shell ^ _prism(_rounded_rectangle(-width / 2, width / 2, low, high, (0.0, 0.0, top_radius, top_radius)),
                           'x', -1.0, 1.0)
    front = line[:, 0].max() + thickness
    shell = shell ^ _prism(_rounded_rectangle(-1.0, front, -width / 2 - 0.1, width / 2 + 0.1,
                                              (0.0, front_corner_radius, front_corner_radius, 0.0)), 'z', low, high)
    parts: list[Manifold] = [shell]

    if arms:  # arm wings: plates on the mid-surface of the shell edges, from the seat up into the back
        arm_back_z = seat_top + rng.uniform(0.17, 0.23)
        arm_front_z = arm_back_z - rng.uniform(0.0, 0.05)
        arm_front_x = seat_start[0] - rng.uniform(0.05, 0.12)
        under = line[(line[:, 0] <= arm_front_x) & (line[:, 1] < arm_back_z) & (np.arange(len(line)) > front_steps)]
        above = np.nonzero(line[:, 1] >= arm_back_z)[0][0]
        wing = np.vstack([[[arm_front_x, np.interp(arm_front_x, [bend_start[0], seat_start[0]],
                                                   [bend_start[1], seat_start[1]]) - thickness / 2]],
                          under, [_point_at_height(line[above - 1], line[above], arm_back_z)],
                          [[arm_front_x, arm_front_z]]])
        wing = _rounded_polygon(wing, rng.uniform(0.015, 0.04))
        for sy in (-1, 1):
            parts.append(_prism(wing, 'y', *sorted((sy * width / 2, sy * (width / 2 - thickness)))))

    # Base, fixed to the seat pan inside its flat middle (clear of the rising sides).
    def seat_mid_z(x: float) -> float:
        return float(np.interp(x, [bend_start[0], seat_start[0]], [bend_start[1], seat_start[1]]))

    pan_length = seat_start[0] - bend_start[0]
    front_x = seat_start[0] - rng.uniform(0.15, 0.3) * pan_length
    back_x = bend_start[0] + rng.uniform(0.0, 0.15) * pan_length
    leg_y = lip_start - rng.uniform(0.015, 0.04)
    base = rng.choice(['legs', 'eiffel', 'star'], p=[0.4, 0.35, 0.25])
    if base == 'star':
        reach, hub_width, hub_height = rng.uniform(0.23, 0.28), rng.uniform(0.07, 0.09), rng.uniform(0.04, 0.06)
        tip_width, tip_height = rng.uniform(0.03, 0.04), rng.uniform(0.012, 0.02)
        parts += [radial_foot(angle, reach, hub_width, hub_height, tip_width, tip_height)
                  for angle in np.radians([45.0, 135.0, 225.0, 315.0])]
        plate_x = min(rng.uniform(0.08, 0.11), 0.4 * pan_length)
        plate_y = rng.uniform(0.08, 0.12)
        plate_bottom = seat_mid_z(-plate_x) - rng.uniform(0.03, 0.05)
        plate_ends = [box((0.01, 2 * plate_y, seat_mid_z(x) - plate_bottom),
                          (x, 0.0, (seat_mid_z(x) + plate_bottom) / 2)) for x in (-plate_x, plate_x)]
        parts.append(Manifold.batch_hull(plate_ends))  # a wedge under the sloping seat pan
        column = rng.uniform(0.02, 0.03)
        parts += [cylinder(1.6 * column, 0.0, hub_height + 0.03), cylinder(column, hub_height, plate_bottom + 0.01)]
        return union(parts)

    splay = rng.uniform(0.03, 0.07)
    splay_y = min(splay, width / 2 - leg_y - 0.015)
    tops = [np.array([x, sy * leg_y, seat_mid_z(x)]) for x in (front_x, back_x) for sy in (-1, 1)]
    bottoms = [np.array([x + np.sign(x - (front_x + back_x) / 2) * splay, sy * (leg_y + splay_y), 0.0])
               for x in (front_x, back_x) for sy in (-1, 1)]  # order: front left, front right, back left, back right
    if base == 'legs':
        leg_radius, leg_taper, round_legs = rng.uniform(0.010, 0.016), rng.uniform(0.6, 0.9), bool(rng.random() < 0.6)
        parts += [strut(bottom, top, leg_taper * leg_radius, leg_radius, round_legs)
                  for bottom, top in zip(bottoms, tops)]
        if rng.random() < 0.5:  # wire bracing: side rods and a cross rod between their middles
            wire = rng.uniform(0.004, 0.006)
            fraction = rng.uniform(0.3, 0.5)
            points = [bottom + fraction * (top - bottom) for bottom, top in zip(bottoms, tops)]
            parts += [rod(points[0], points[2], wire, wire), rod(points[1], points[3], wire, wire),
                      rod((points[0] + points[2]) / 2, (points[1] + points[3]) / 2, wire, wire)]
        return union(parts)

    # Eiffel: wire legs from the floor to two side rails under the seat, four mounts into the shell, X bracing.
    wire = rng.uniform(0.006, 0.009)
    drop = rng.uniform(0.02, 0.04)
    rail_points = [top - [0.0, 0.0, drop] for top in tops]
    bottoms = [bottom + [0.0, 0.0, wire] for bottom in bottoms]
    for top, rail_point in zip(tops, rail_points):
        parts.append(strut(rail_point - [0.0, 0.0, 0.005], top, 0.012, 0.018, True))
    parts += [rod(rail_points[0], rail_points[2], wire, wire), rod(rail_points[1], rail_points[3], wire, wire)]
    parts += [rod(bottom, rail_point, wire, wire) for bottom, rail_point in zip(bottoms, rail_points)]
    fraction = rng.uniform(0.15, 0.3)
    low_points = [bottom + fraction * (rail_point - bottom) for bottom, rail_point in zip(bottoms, rail_points)]
    for first, second in ((0, 2), (1, 3), (0, 1), (2, 3)):  # left, right, front and back faces
        parts += [rod(low_points[first], rail_points[second], wire, wire),
                  rod(low_points[second], rail_points[first], wire, wire)]
    return union(parts)


def upholstered_chair(rng: np.random.Generator) -> trimesh.Trimesh:
    """Upholstered (Parsons-style) dining chair: a thick padded seat block; a tall padded back block with a
    square, rounded or arched top (its top face bevelled slightly down towards the front, its edges
    softened), optionally a wing back with side wings, upright or slightly reclined; four short tapered legs
    (square or round, the back legs optionally raked back), optional side stretchers and optional padded arms
    (closed arm panels, or arm pads on front posts)."""
    width, seat_depth = rng.uniform(0.45, 0.58), rng.uniform(0.49, 0.58)
    seat_bottom, seat_thickness = rng.uniform(0.32, 0.41), rng.uniform(0.06, 0.12)
    seat_top = seat_bottom + seat_thickness
    back_top, back_thickness = rng.uniform(0.86, 1.08), rng.uniform(0.06, 0.12)
    softness = rng.uniform(0.008, 0.025)  # edge rounding / bevel of the upholstery
    recline = rng.uniform(2.0, 7.0) if rng.random() < 0.6 else 0.0
    top_style = rng.choice(['square', 'rounded', 'arched'])
    parts: list[Manifold] = [rounded_box((seat_depth, width, seat_thickness),
                                         (0.0, 0.0, seat_bottom + seat_thickness / 2), softness)]

    # Back: its y-z outline through the back thickness, on the rear edge of the seat and down to the seat's
    # underside; the top face slopes down towards the front by more than the recline, so that its rear edge
    # stays the top of the chair. Reclined (with the wings) about the rear bottom edge of the seat.
    half = width / 2 * rng.uniform(0.92, 1.0)
    rear_x = -seat_depth / 2
    if top_style == 'arched':
        rise = rng.uniform(0.03, 0.08)
        arc_radius = (half ** 2 + rise ** 2) / (2 * rise)
        arc_y = np.linspace(half, -half, 13)
        outline = np.vstack([[[-half, seat_bottom], [half, seat_bottom]],
                             np.column_stack([arc_y, back_top - arc_radius + np.sqrt(arc_radius ** 2 - arc_y ** 2)])])
    else:
        radius = rng.uniform(0.01, 0.03) if top_style == 'square' else rng.uniform(0.06, 0.18)
        outline = _rounded_rectangle(-half, half, seat_bottom, back_top, (0.0, 0.0, radius, radius))
    slope = np.tan(np.radians(recline + rng.uniform(4.0, 10.0)))
    front_x = rear_x + back_thickness
    side_profile = np.array([[rear_x - 0.01, seat_bottom - 0.01], [front_x + 0.01, seat_bottom - 0.01],
                             [front_x + 0.01, back_top - slope * (back_thickness + 0.01)],
                             [rear_x - 0.01, back_top + slope * 0.01]])
    back_parts = [_prism(outline, 'x', rear_x, front_x, bevel=softness)
                  ^ _prism(side_profile, 'y', -half - 0.01, half + 0.01)]
    if rng.random() < 0.25:  # wing back: side wings reaching forward from the upper back
        wing_depth, wing_thickness = rng.uniform(0.10, 0.20), rng.uniform(0.05, 0.08)
        wing_bottom = seat_top + rng.uniform(0.0, 0.10)
        wing_top = min(_outline_top(outline, half - wing_thickness / 2), back_top - slope * back_thickness)
        wing_top = max(wing_top - rng.uniform(0.01, 0.04), wing_bottom + 0.15)
        wing = _rounded_rectangle(rear_x, front_x + wing_depth, wing_bottom, wing_top,
                                  (0.0, rng.uniform(0.03, 0.9 * wing_depth), rng.uniform(0.03, 0.1), 0.0))
        for sy in (-1, 1):
            back_parts.append(_prism(wing, 'y', *sorted((sy * half, sy * (half - wing_thickness))), bevel=softness))
    parts.append(tilt_back(merge(back_parts), recline, (rear_x, 0.0, seat_bottom)))

    if rng.random() < 0.3:  # padded arms from the back to near the front of the seat
        arm_top = seat_top + rng.uniform(0.17, 0.24)
        arm_width = rng.uniform(0.05, 0.09)
        arm_front = seat_depth / 2 - rng.uniform(0.0, 0.08)
        arm_back = rear_x - (arm_top - seat_bottom) * np.tan(np.radians(recline)) + back_thickness / 2
        closed = bool(rng.random() < 0.5)
        pad_height, post_depth = rng.uniform(0.035, 0.06), rng.uniform(0.04, 0.06)
        for sy in (-1, 1):
            y = sy * (width / 2 - arm_width / 2)
            if closed:
                parts.append(rounded_box((arm_front - arm_back, arm_width, arm_top - seat_top + 0.03),
                                         ((arm_front + arm_back) / 2, y, (arm_top + seat_top - 0.03) / 2), softness))
                continue
            parts.append(rounded_box((arm_front - arm_back, arm_width, pad_height),
                                     ((arm_front + arm_back) / 2, y, arm_top - pad_height / 2), softness))
            parts.append(rounded_box((post_depth, 0.8 * arm_width, arm_top - seat_top + 0.03),
                                     (arm_front - post_depth / 2 - 0.01, y, (arm_top + seat_top - 0.03) / 2), softness))

    leg_half_width, leg_taper = rng.uniform(0.016, 0.026), rng.uniform(0.5, 0.85)
    round_legs = bool(rng.random() < 0.4)
    inset = rng.uniform(0.0, 0.02)
    rake = rng.uniform(0.02, 0.06) if rng.random() < 0.5 else 0.0  # back legs splayed back
    leg_x, leg_y = seat_depth / 2 - inset - leg_half_width, width / 2 - inset - leg_half_width
    leg_top_z = seat_bottom + 0.5 * seat_thickness
    tops = [np.array([sx * leg_x, sy * leg_y, leg_top_z]) for sx in (-1, 1) for sy in (-1, 1)]
    bottoms = [np.array([top[0] - (rake if top[0] < 0 else 0.0), top[1], 0.0]) for top in tops]
    parts += [strut(bottom, top, leg_taper * leg_half_width, leg_half_width, round_legs)
              for bottom, top in zip(bottoms, tops)]
    if rng.random() < 0.25:  # side stretchers and a cross stretcher between their middles
        height_fraction = rng.uniform(0.2, 0.4)
        points = [bottom + height_fraction * (top - bottom) for bottom, top in zip(bottoms, tops)]
        thickness = 1.6 * leg_taper * leg_half_width
        rear_left, rear_right, front_left, front_right = points  # order of the sx, sy loops
        parts += [beam(rear_left, front_left, thickness, thickness),
                  beam(rear_right, front_right, thickness, thickness),
                  beam((rear_left + front_left) / 2, (rear_right + front_right) / 2, thickness, thickness)]
    return union(parts)


def spindle_chair(rng: np.random.Generator) -> trimesh.Trimesh:
    """Windsor (spindle-back) chair: a thick saddle seat (rounded rectangle, round or D-shaped, bevelled edge,
    optionally dished), four strongly splayed round legs with an optional H stretcher, and a back of 4-9 thin
    spindles rising from an arc along the seat's rear edge, leaning back and fanning out, under a bow (a curved
    top rail whose ends enter the seat) or a comb (a straight crest rail); optionally a horizontal arm rail at
    about 0.2 m above the seat, threaded by the back spindles and carried by arm posts and short spindles."""
    seat_top, seat_thickness = rng.uniform(0.43, 0.47), rng.uniform(0.03, 0.05)
    seat_bottom = seat_top - seat_thickness
    seat_style = rng.choice(['rounded', 'round', 'D'])
    if seat_style == 'round':
        seat_width = seat_depth = rng.uniform(0.42, 0.48)
        radii = (seat_width / 2,) * 4
    else:
        seat_width, seat_depth = rng.uniform(0.42, 0.52), rng.uniform(0.40, 0.47)
        corner, front_corner = rng.uniform(0.03, 0.10), rng.uniform(0.01, 0.04)
        radii = (seat_width / 2, front_corner, front_corner, seat_width / 2) if seat_style == 'D' else (corner,) * 4
    a, b = seat_depth / 2, seat_width / 2
    bevel = rng.uniform(0.004, 0.01)
    inner_radii = [max(r - bevel, 0.0) for r in radii]
    seat = Manifold.batch_hull([
        _prism(_rounded_rectangle(-a, a, -b, b, radii), 'z', seat_bottom + bevel, seat_top - bevel),
        _prism(_rounded_rectangle(-a + bevel, a - bevel, -b + bevel, b - bevel, inner_radii), 'z', seat_bottom,
               seat_top)])
    if rng.random() < 0.7:  # saddle: a shallow spherical hollow in the seat top, wider than long
        dip, stretch, shift = rng.uniform(0.004, 0.012), rng.uniform(1.0, 1.3), rng.uniform(0.0, 0.04)
        dish_radius = min(rng.uniform(0.10, 0.15), a - 0.03 - shift, (b - 0.03) / stretch)
        sphere_radius = (dish_radius ** 2 + dip ** 2) / (2 * dip)
        ring = np.linspace(0.0, dish_radius, 7)
        hollow = seat_top - dip + sphere_radius - np.sqrt(sphere_radius ** 2 - ring ** 2)
        profile = np.vstack([np.column_stack([ring, hollow]), [[dish_radius, seat_top + 0.02], [0.0, seat_top + 0.02]]])
        seat = seat - lathe(profile).scale((1.0, stretch, 1.0)).translate((shift, 0.0, 0.0))
    parts: list[Manifold] = [seat]

    leg_inset, leg_angle = rng.uniform(0.04, 0.07), np.radians(rng.uniform(38.0, 50.0))
    splay = rng.uniform(0.05, 0.09)
    leg_radius, leg_taper = rng.uniform(0.015, 0.021), rng.uniform(0.65, 0.85)
    leg_top_z = seat_bottom + 0.5 * seat_thickness
    tops, bottoms = [], []
    for sx, sy in ((1, -1), (1, 1), (-1, -1), (-1, 1)):  # front right, front left, back right, back left
        top = np.array([sx * (a - leg_inset) * np.cos(leg_angle), sy * (b - leg_inset) * np.sin(leg_angle), leg_top_z])
        tops.append(top)
        bottoms.append(np.array([top[0] + sx * splay, top[1] + sy * splay, 0.0]))
        parts.append(strut(bottoms[-1], top, leg_taper * leg_radius, leg_radius, True))
    if rng.random() < 0.65:  # H stretcher: front-back rods on both sides and a cross rod between their middles
        stretcher_z, stretcher_radius = rng.uniform(0.12, 0.2), rng.uniform(0.009, 0.013)
        points = [bottom + (top - bottom) * stretcher_z / leg_top_z for bottom, top in zip(bottoms, tops)]
        parts += [rod(points[0], points[2], stretcher_radius, stretcher_radius),
                  rod(points[1], points[3], stretcher_radius, stretcher_radius),
                  rod((points[0] + points[2]) / 2, (points[1] + points[3]) / 2, stretcher_radius, stretcher_radius)]

    # Back: lines rising from the rear half of an ellipse inset in the seat, leaning back by the recline and
    # spreading sideways by `flare` per metre of height; members end 0.4 seat thicknesses into the seat.
    recline, back_inset = rng.uniform(5.0, 12.0), rng.uniform(0.03, 0.05)
    arc_a, arc_b = a - back_inset, b - back_inset
    half_span = arc_b * rng.uniform(0.6, 0.85)  # half the lateral span of the back at the seat
    style = rng.choice(['bow', 'comb'])
    flare = rng.uniform(0.0, 0.3) if style == 'bow' else rng.uniform(0.1, 0.6)
    lean = np.tan(np.radians(recline))
    sink = 0.4 * seat_thickness

    def back_point(y: float, h: float) -> np.ndarray:
        arc_x = -arc_a * np.sqrt(max(0.0, 1.0 - (y / arc_b) ** 2))
        return np.array([arc_x - h * lean, y * (1.0 + flare * h), seat_top + h])

    spindle_count = int(rng.integers(4, 10))
    spindle_radius, spindle_taper = rng.uniform(0.008, 0.012), rng.uniform(0.7, 0.9)
    spindles: list[np.ndarray] = []  # (2, 3) end points
    members: list[np.ndarray] = []  # polylines of the back (spindles included), threaded by the arm rail
    if style == 'bow':
        height = rng.uniform(0.36, 0.55)
        bow_radius = min(rng.uniform(0.011, 0.016), 0.6 * seat_thickness - 0.002)
        bow = np.array([back_point(-half_span, -sink)]
                       + [back_point(half_span * np.cos(t), height * np.sin(t)) for t in np.linspace(np.pi, 0.0, 15)]
                       + [back_point(half_span, -sink)])
        parts += [rod(p, q, bow_radius, bow_radius) for p, q in zip(bow[:-1], bow[1:])]
        members.append(bow)
        for y in np.linspace(-half_span, half_span, spindle_count + 2)[1:-1]:
            spindles.append(np.array([back_point(y, -sink),
                                      back_point(y, height * np.sqrt(1.0 - (y / half_span) ** 2))]))
    else:
        height = rng.uniform(0.34, 0.50)  # of the crest rail's lower part, where the spindles end
        rail_height, rail_thickness = rng.uniform(0.05, 0.09), rng.uniform(0.02, 0.035)
        rail_x = -arc_a - height * lean
        spread = 1.0 + flare * height
        for y in np.linspace(-half_span, half_span, spindle_count):
            spindles.append(np.array([back_point(y, -sink), [rail_x, y * spread, seat_top + height]]))
        rail_centre = (rail_x, 0.0, seat_top + height + 0.25 * rail_height)
        rail_length = 2 * half_span * spread + rng.uniform(0.04, 0.12)
        rail = rounded_box((rail_thickness, rail_length, rail_height), rail_centre, 0.008)
        parts.append(tilt_back(rail, recline, rail_centre))
    parts += [rod(bottom, top, spindle_radius, spindle_taper * spindle_radius) for bottom, top in spindles]
    members += spindles

    if rng.random() < 0.35:  # arm rail through the back members, curving forward to the arm ends on posts
        arm_z = seat_top + rng.uniform(0.18, 0.24)
        rail_radius, post_radius = rng.uniform(0.012, 0.016), rng.uniform(0.012, 0.016)
        arm_x, arm_y = a * rng.uniform(0.35, 0.6), b + rng.uniform(-0.01, 0.02)
        short_count = int(rng.integers(0, 3))
        crossings = sorted((point for member in members for point in _crossings(member, arm_z)), key=lambda p: p[1])
        rail_points = list(crossings)
        for sy, end in ((-1, crossings[0]), (1, crossings[-1])):
            tip = np.array([arm_x, sy * arm_y, arm_z])
            control = np.array([end[0] + 0.25 * (arm_x - end[0]), sy * arm_y, arm_z])
            curve = [(1 - u) ** 2 * end + 2 * u * (1 - u) * control + u ** 2 * tip for u in np.linspace(0.0, 1.0, 6)]
            parts += [rod(p, q, rail_radius, rail_radius) for p, q in zip(curve[:-1], curve[1:])]
            post_x = arm_x - 0.02
            post_foot = (post_x, sy * 0.95 * arc_b * np.sqrt(1.0 - (post_x / arc_a) ** 2), seat_top - sink)
            parts.append(rod(post_foot, tip, post_radius, 0.8 * post_radius))
            for u in np.linspace(0.0, 1.0, short_count + 2)[1:-1]:  # short spindles under the arm
                top = (1 - u) ** 2 * end + 2 * u * (1 - u) * control + u ** 2 * tip
                inside = min(1.0, 0.97 / np.hypot(top[0] / arc_a, top[1] / arc_b))
                parts.append(rod((top[0] * inside, top[1] * inside, seat_top - sink), top, spindle_radius,
                                 spindle_taper * spindle_radius))
        parts += [rod(p, q, rail_radius, rail_radius) for p, q in zip(rail_points[:-1], rail_points[1:])]
    return union(parts)


def _arc_steps(turn_deg: float) -> int:
    """Segments of a centre-line bend turning by `turn_deg` degrees (one for a straight run)."""
    return max(1, int(np.ceil(abs(turn_deg) / ARC_STEP_DEG)))


def _turtle_line(start_heading_deg: float, moves: Sequence[tuple[float, float]]) -> np.ndarray:
    """Polyline (N, 2) in a plane from the origin, starting in the direction `start_heading_deg` (degrees
    from the first axis towards the second): each move (length, turn_deg) is an arc of that length turning
    the heading by turn_deg (a straight run when 0), in `_arc_steps` chords; zero-length moves are skipped."""
    heading = np.radians(start_heading_deg)
    points = [np.zeros(2)]
    for length, turn_deg in moves:
        if length <= 0.0:
            continue
        steps = _arc_steps(turn_deg)
        turn = np.radians(turn_deg) / steps
        for _ in range(steps):
            middle = heading + turn / 2
            points.append(points[-1] + length / steps * np.array([np.cos(middle), np.sin(middle)]))
            heading += turn
    return np.array(points)


def _prism(outline: np.ndarray | CrossSection, axis: str, low: float, high: float, divisions: int = 0,
           bevel: float = 0.0) -> Manifold:
    """Prism of a closed outline (N, 2) (either orientation) or CrossSection from `low` to `high` along `axis`:
    the outline's coordinates are (y, z) for 'x', (x, z) for 'y' and (x, y) for 'z'. `divisions` extra copies
    of the outline along the prism (for warping); `bevel` > 0 chamfers the prism's edges (convex outlines only)."""
    section = outline if isinstance(outline, CrossSection) else CrossSection([_counter_clockwise(outline)])
    if bevel > 0.0:
        return Manifold.batch_hull([_prism(section.offset(-bevel, JoinType.Miter), axis, low, high),
                                    _prism(section, axis, low + bevel, high - bevel)])
    prism = section.extrude(high - low, divisions)  # local (u, v, w), w along the prism
    if axis == 'z':
        return prism.translate((0.0, 0.0, low))
    if axis == 'y':  # (u, v, w) -> (u, -w, v)
        return prism.rotate((90.0, 0.0, 0.0)).translate((0.0, high, 0.0))
    return prism.rotate((90.0, 0.0, 90.0)).translate((low, 0.0, 0.0))  # 'x': (u, v, w) -> (w, u, v)


def _counter_clockwise(outline: np.ndarray) -> np.ndarray:
    """The closed outline (N, 2) in counter-clockwise order (positive shoelace area)."""
    points = np.asarray(outline, float)
    area = np.sum(points[:, 0] * np.roll(points[:, 1], -1) - np.roll(points[:, 0], -1) * points[:, 1])
    return points if area > 0 else points[::-1]


def _rounded_rectangle(u_min: float, u_max: float, v_min: float, v_max: float, radii: Sequence[float]) -> np.ndarray:
    """Counter-clockwise outline (N, 2) of the rectangle [u_min, u_max] x [v_min, v_max] with its corners
    (low-low, high-low, high-high, low-high in (u, v)) rounded by `radii` (4,) (each clipped to half the
    shorter side; 0 keeps a sharp corner)."""
    limit = 0.5 * min(u_max - u_min, v_max - v_min)
    corners = [(u_min, v_min, -1, -1, 180.0), (u_max, v_min, 1, -1, 270.0), (u_max, v_max, 1, 1, 0.0),
               (u_min, v_max, -1, 1, 90.0)]  # corner, its outward signs, start angle of its arc
    points: list[tuple[float, float]] = []
    for (u, v, su, sv, start), radius in zip(corners, radii):
        radius = min(float(radius), limit)
        if radius <= 1e-6:
            points.append((u, v))
            continue
        for angle in np.radians(np.linspace(start, start + 90.0, ARC_CORNER_SEGMENTS + 1)):
            points.append((u - su * radius + radius * np.cos(angle), v - sv * radius + radius * np.sin(angle)))
    outline = np.array(points)
    keep = np.linalg.norm(outline - np.roll(outline, 1, axis=0), axis=1) > 1e-9  # arcs meeting at a point
    return outline[keep]


def _rounded_polygon(outline: np.ndarray, radius: float) -> CrossSection:
    """The closed outline (N, 2) with its convex corners rounded by `radius` (a morphological opening)."""
    section = CrossSection([_counter_clockwise(outline)])
    segments = 4 * ARC_CORNER_SEGMENTS
    return section.offset(-radius, JoinType.Round, 2.0, segments).offset(radius, JoinType.Round, 2.0, segments)


def _outline_top(outline: np.ndarray, u: float) -> float:
    """Highest second coordinate of the closed outline (N, 2) at the first coordinate `u`."""
    start, end = np.asarray(outline, float), np.roll(np.asarray(outline, float), -1, axis=0)
    spans = ((np.minimum(start[:, 0], end[:, 0]) <= u) & (u <= np.maximum(start[:, 0], end[:, 0]))
             & (start[:, 0] != end[:, 0]))
    fraction = (u - start[spans, 0]) / (end[spans, 0] - start[spans, 0])
    return float((start[spans, 1] + fraction * (end[spans, 1] - start[spans, 1])).max())


def _point_at_height(first: np.ndarray, second: np.ndarray, z: float) -> np.ndarray:
    """Point (2,) at height `z` on the x-z segment from `first` (2,) to `second` (2,)."""
    fraction = (z - first[1]) / (second[1] - first[1])
    return first + fraction * (second - first)


def _crossings(polyline: np.ndarray, z: float) -> list[np.ndarray]:
    """Points (3,) where the 3-d `polyline` (N, 3) crosses the height `z`."""
    points = []
    for first, second in zip(polyline[:-1], polyline[1:]):
        if (first[2] - z) * (second[2] - z) < 0.0:
            points.append(first + (z - first[2]) / (second[2] - first[2]) * (second - first))
    return points
