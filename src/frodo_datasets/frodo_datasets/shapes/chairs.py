"""Procedural chairs: four-leg chairs, office chairs, stools and armchairs.

Each generator draws continuous proportions and discrete part styles from a numpy Generator and returns
the union of overlapping solids as one watertight trimesh in metres, with the floor at z = 0, the seat
centred over the origin in x-y, the back towards -x and the front (where a seated person looks) towards
+x. `library.generate` moves the result into the canonical frame (bounding box centred at the origin).
"""
from __future__ import annotations

import numpy as np
import trimesh
from manifold3d import Manifold

from .solids import (beam, box, box_between, cylinder, lathe, merge, rod, rounded_box, strut, tilt_back, torus,
                     union)

MAX_OFFICE_CHAIR_HEIGHT = 1.28  # m, head rests included


def four_leg_chair(rng: np.random.Generator) -> trimesh.Trimesh:
    """Dining/kitchen chair: four (possibly splayed, tapered, round or square) legs, a seat slab, a straight
    or slanted back (solid panel, vertical slats or horizontal rails between two posts), optional side
    stretchers and optional arm rests."""
    seat_depth, seat_width = rng.uniform(0.40, 0.50), rng.uniform(0.40, 0.52)
    seat_top, seat_thickness = rng.uniform(0.43, 0.48), rng.uniform(0.025, 0.06)
    back_height = rng.uniform(0.33, 0.50)  # above the seat top
    back_slant_deg = rng.uniform(3.0, 15.0) if rng.random() < 0.6 else 0.0
    back_style = rng.choice(['panel', 'slats', 'rails'])
    round_legs = bool(rng.random() < 0.5)
    leg_half_width = rng.uniform(0.014, 0.024)
    leg_taper = rng.uniform(0.6, 1.0)
    leg_splay = rng.uniform(0.0, 0.035) if rng.random() < 0.5 else 0.0
    leg_inset = rng.uniform(0.01, 0.03)
    seat_bottom = seat_top - seat_thickness

    parts: list[Manifold] = [rounded_box((seat_depth, seat_width, seat_thickness), (0.0, 0.0, seat_top - seat_thickness / 2),
                                         rng.uniform(0.002, 0.012))]
    leg_x = seat_depth / 2 - leg_inset - leg_half_width
    leg_y = seat_width / 2 - leg_inset - leg_half_width
    leg_top_z = seat_bottom + 0.5 * seat_thickness  # legs reach into the seat
    leg_tops, leg_bottoms = [], []
    for sx in (-1, 1):
        for sy in (-1, 1):
            top = np.array([sx * leg_x, sy * leg_y, leg_top_z])
            bottom = np.array([sx * (leg_x + leg_splay), sy * (leg_y + leg_splay), 0.0])
            leg_tops.append(top)
            leg_bottoms.append(bottom)
            parts.append(strut(bottom, top, leg_taper * leg_half_width, leg_half_width, round_legs))

    if rng.random() < 0.4:  # side stretchers (front-back on each side) and one cross stretcher
        height_fraction = rng.uniform(0.2, 0.4)
        stretcher_z = height_fraction * seat_bottom
        stretcher_points = [bottom + (top - bottom) * stretcher_z / leg_top_z for bottom, top in zip(leg_bottoms, leg_tops)]
        thickness = 0.9 * leg_taper * leg_half_width * 2
        rear_left, rear_right, front_left, front_right = stretcher_points  # order of the sx, sy loops
        parts += [beam(rear_left, front_left, thickness, thickness), beam(rear_right, front_right, thickness, thickness)]
        parts.append(beam((rear_left + front_left) / 2, (rear_right + front_right) / 2, thickness, thickness))

    # Back, built upright above the rear edge of the seat, then reclined about the rear seat edge.
    post_half_width = leg_half_width * rng.uniform(0.8, 1.0)
    post_x = -leg_x
    back_top = seat_top + back_height
    back_parts = [strut((post_x, sy * leg_y, seat_bottom + 0.005), (post_x, sy * leg_y, back_top), post_half_width,
                        post_half_width, round_legs) for sy in (-1, 1)]
    inner_half_y = leg_y - 0.5 * post_half_width
    board_thickness = rng.uniform(0.015, 0.03)
    if back_style == 'panel':
        panel_bottom = seat_top + rng.uniform(0.05, 0.45) * back_height
        back_parts.append(rounded_box((board_thickness, 2 * leg_y, back_top - panel_bottom),
                                      (post_x, 0.0, (back_top + panel_bottom) / 2), 0.006))
    else:
        top_rail_height = rng.uniform(0.05, 0.12)
        back_parts.append(box((board_thickness, 2 * leg_y, top_rail_height), (post_x, 0.0, back_top - top_rail_height / 2)))
        if back_style == 'slats':
            bottom_rail_z = seat_top + rng.uniform(0.04, 0.12)
            back_parts.append(box((board_thickness, 2 * leg_y, 0.03), (post_x, 0.0, bottom_rail_z)))
            slat_count = int(rng.integers(2, 6))
            slat_width = rng.uniform(0.015, 0.05)
            for slat_y in np.linspace(-inner_half_y, inner_half_y, slat_count + 2)[1:-1]:
                back_parts.append(box_between((post_x - board_thickness / 3, slat_y - slat_width / 2, bottom_rail_z),
                                              (post_x + board_thickness / 3, slat_y + slat_width / 2, back_top - 0.01)))
        else:
            rail_count = int(rng.integers(1, 4))
            for rail_z in np.linspace(seat_top + 0.1 * back_height, back_top - top_rail_height, rail_count + 1)[:-1]:
                back_parts.append(box((board_thickness * 0.8, 2 * leg_y, 0.03), (post_x, 0.0, rail_z + 0.015)))
    parts.append(tilt_back(merge(back_parts), back_slant_deg, (post_x, 0.0, seat_top)))

    if rng.random() < 0.25:  # arm rests: front posts and horizontal rests reaching back into the back posts
        arm_height = rng.uniform(0.18, 0.25)
        arm_z = seat_top + arm_height
        arm_thickness, arm_width = rng.uniform(0.02, 0.03), rng.uniform(0.04, 0.06)
        front_x = leg_x - rng.uniform(0.0, 0.06)
        back_post_x_at_arm = post_x - arm_height * np.sin(np.radians(back_slant_deg))
        for sy in (-1, 1):
            arm_y = sy * (leg_y - arm_width / 2 + post_half_width)
            parts.append(strut((front_x, arm_y, seat_bottom + 0.01), (front_x, arm_y, arm_z), 0.8 * post_half_width,
                               0.8 * post_half_width, round_legs))
            parts.append(rounded_box((front_x + 0.04 - back_post_x_at_arm, arm_width, arm_thickness),
                                     ((front_x + 0.04 + back_post_x_at_arm) / 2, arm_y, arm_z), 0.008))
    return union(parts)


def office_chair(rng: np.random.Generator) -> trimesh.Trimesh:
    """Swivel office chair: five-spoke star base with casters, gas column, cushioned seat, reclined back on
    a spine, optional T arm rests and optional head rest."""
    base_radius = rng.uniform(0.27, 0.34)
    caster_radius = rng.uniform(0.022, 0.032)
    spoke_radius = rng.uniform(0.014, 0.022)
    hub_z = 2 * caster_radius + rng.uniform(0.03, 0.05)
    tip_z = 2 * caster_radius + 0.012
    seat_depth, seat_width = rng.uniform(0.44, 0.52), rng.uniform(0.46, 0.54)
    seat_top, seat_thickness = rng.uniform(0.46, 0.56), rng.uniform(0.06, 0.10)
    seat_bottom = seat_top - seat_thickness
    mechanism_height = rng.uniform(0.03, 0.06)

    parts: list[Manifold] = []
    spoke_angle_offset = rng.uniform(0.0, 2 * np.pi / 5)
    for angle in spoke_angle_offset + 2 * np.pi * np.arange(5) / 5:
        direction = np.array([np.cos(angle), np.sin(angle)])
        tip = np.array([*(base_radius * direction), tip_z])
        parts.append(rod((0.0, 0.0, hub_z), tip, 1.3 * spoke_radius, 0.8 * spoke_radius))
        wheel_centre = np.array([*((base_radius + 0.3 * caster_radius) * direction), caster_radius])
        parts.append(Manifold.sphere(caster_radius, 12).translate(tuple(wheel_centre)))
        parts.append(cylinder(0.35 * caster_radius, caster_radius, tip_z + 0.005, tip[:2]))
    column_radius = rng.uniform(0.018, 0.028)
    mechanism_bottom = seat_bottom - mechanism_height
    parts += [cylinder(rng.uniform(0.035, 0.05), hub_z - 0.03, hub_z + 0.03),
              cylinder(1.4 * column_radius, hub_z, hub_z + 0.45 * (mechanism_bottom - hub_z)),
              cylinder(column_radius, hub_z, mechanism_bottom + 0.01),
              box_between((-0.09, -0.08, mechanism_bottom), (0.09, 0.08, seat_bottom + 0.01))]
    parts.append(rounded_box((seat_depth, seat_width, seat_thickness), (0.0, 0.0, seat_top - seat_thickness / 2),
                             rng.uniform(0.015, 0.035)))

    back_width, back_height = rng.uniform(0.38, 0.50), rng.uniform(0.40, 0.60)
    back_thickness = rng.uniform(0.04, 0.08)
    back_bottom = seat_top + rng.uniform(0.03, 0.12)
    back_x = -seat_depth / 2 + back_thickness / 2 - 0.01
    spine_x = back_x - back_thickness / 2
    spine_width, spine_thickness = rng.uniform(0.05, 0.09), 0.02
    back_parts = [rounded_box((back_thickness, back_width, back_height), (back_x, 0.0, back_bottom + back_height / 2),
                              rng.uniform(0.015, 0.035)),
                  box_between((spine_x - spine_thickness, -spine_width / 2, mechanism_bottom),
                              (spine_x + 0.01, spine_width / 2, back_bottom + 0.4 * back_height))]
    if rng.random() < 0.25:  # head rest on a short stem, the chair kept below MAX_OFFICE_CHAIR_HEIGHT
        head_height = rng.uniform(0.10, 0.16)
        head_bottom = min(back_bottom + back_height + rng.uniform(0.03, 0.06), MAX_OFFICE_CHAIR_HEIGHT - head_height)
        back_parts.append(box_between((spine_x - 0.005, -0.02, back_bottom + back_height - 0.05),
                                      (spine_x + 0.015, 0.02, head_bottom + 0.03)))
        back_parts.append(rounded_box((back_thickness, 0.6 * back_width, head_height),
                                      (back_x, 0.0, head_bottom + head_height / 2), 0.02))
    parts.append(box_between((spine_x - spine_thickness, -spine_width / 2, mechanism_bottom),
                             (0.0, spine_width / 2, mechanism_bottom + spine_thickness)))
    parts.append(tilt_back(merge(back_parts), rng.uniform(3.0, 16.0), (spine_x, 0.0, mechanism_bottom)))

    if rng.random() < 0.6:  # T arm rests: bracket under the seat, post, pad
        arm_top = seat_top + rng.uniform(0.18, 0.26)
        pad_length, pad_width = rng.uniform(0.20, 0.28), rng.uniform(0.06, 0.085)
        arm_x = -rng.uniform(0.0, 0.06)
        for sy in (-1, 1):
            post_y = sy * (seat_width / 2 + 0.025)
            parts.append(box_between((arm_x - 0.025, min(0.0, post_y), mechanism_bottom),
                                     (arm_x + 0.025, max(0.0, post_y), mechanism_bottom + 0.015)))
            parts.append(box_between((arm_x - 0.02, post_y - 0.012, mechanism_bottom), (arm_x + 0.02, post_y + 0.012, arm_top)))
            parts.append(rounded_box((pad_length, pad_width, 0.03), (arm_x, post_y, arm_top), 0.012))
    return union(parts)


def stool(rng: np.random.Generator) -> trimesh.Trimesh:
    """Stool, from low kitchen stools to bar stools: round or square seat on three or four splayed legs,
    with an optional footrest ring or footrest bars."""
    seat_top = rng.uniform(0.45, 0.80)
    seat_thickness = rng.uniform(0.03, 0.06)
    seat_bottom = seat_top - seat_thickness
    round_seat = bool(rng.random() < 0.6)
    seat_radius = rng.uniform(0.15, 0.21)  # half side length of a square seat
    leg_count = int(rng.choice([3, 4]))
    round_legs = bool(rng.random() < 0.6)
    leg_half_width = rng.uniform(0.012, 0.022)
    leg_taper = rng.uniform(0.7, 1.0)
    leg_top_radius = seat_radius * rng.uniform(0.55, 0.78)
    leg_bottom_radius = leg_top_radius + rng.uniform(0.03, 0.12) * seat_top

    parts: list[Manifold] = []
    if round_seat:
        bevel = min(rng.uniform(0.004, 0.02), 0.4 * seat_thickness)
        profile = np.array([[0.0, seat_bottom], [seat_radius - bevel, seat_bottom], [seat_radius, seat_bottom + bevel],
                            [seat_radius, seat_top - bevel], [seat_radius - bevel, seat_top], [0.0, seat_top]])
        parts.append(lathe(profile))
    else:
        parts.append(rounded_box((2 * seat_radius, 2 * seat_radius, seat_thickness), (0.0, 0.0, seat_top - seat_thickness / 2),
                                 rng.uniform(0.004, 0.015)))
    angle_offset = np.pi / leg_count  # legs symmetric about the x-z plane
    leg_directions = [np.array([np.cos(a), np.sin(a), 0.0]) for a in angle_offset + 2 * np.pi * np.arange(leg_count) / leg_count]
    leg_top_z = seat_bottom + 0.5 * seat_thickness
    for direction in leg_directions:
        parts.append(strut(leg_bottom_radius * direction, leg_top_radius * direction + [0.0, 0.0, leg_top_z],
                           leg_taper * leg_half_width, leg_half_width, round_legs))

    footrest = rng.choice(['none', 'ring', 'bars'], p=[0.3, 0.4, 0.3])
    footrest_z = seat_bottom * rng.uniform(0.3, 0.45)
    radius_at_footrest = leg_bottom_radius + (leg_top_radius - leg_bottom_radius) * footrest_z / leg_top_z
    tube_radius = rng.uniform(0.008, 0.013)
    if footrest == 'ring':
        parts.append(torus(radius_at_footrest, tube_radius, footrest_z))
    elif footrest == 'bars':
        points = [radius_at_footrest * d + [0.0, 0.0, footrest_z] for d in leg_directions]
        parts += [rod(points[i], points[(i + 1) % leg_count], tube_radius, tube_radius) for i in range(leg_count)]
    return union(parts)


def armchair(rng: np.random.Generator) -> trimesh.Trimesh:
    """Upholstered armchair / sofa-like chair: block body on optional short feet, seat cushion, two arms
    (square or rounded) and a thick, slightly reclined back."""
    width, depth, height = rng.uniform(0.70, 1.00), rng.uniform(0.75, 0.95), rng.uniform(0.75, 1.00)
    seat_top = rng.uniform(0.40, 0.47)
    foot_height = rng.uniform(0.03, 0.12) if rng.random() < 0.6 else 0.0
    cushion_thickness = rng.uniform(0.08, 0.15)
    arm_width = rng.uniform(0.08, 0.20)
    arm_top = rng.uniform(0.55, 0.68)
    back_thickness = rng.uniform(0.15, 0.25)
    softness = rng.uniform(0.01, 0.04)  # edge rounding radius of the upholstery
    body_top = seat_top - cushion_thickness

    parts: list[Manifold] = [rounded_box((depth, width, body_top - foot_height), (0.0, 0.0, (body_top + foot_height) / 2), softness)]
    inner_half_width = width / 2 - arm_width
    cushion_back_x = -depth / 2 + back_thickness - 0.02
    parts.append(rounded_box((depth / 2 - cushion_back_x, 2 * inner_half_width + 0.01, cushion_thickness + 0.01),
                             ((depth / 2 + cushion_back_x) / 2, 0.0, body_top + cushion_thickness / 2 - 0.005), 1.5 * softness))
    arm_front_x = depth / 2 - rng.uniform(0.0, 0.05)
    rounded_arm_top = bool(rng.random() < 0.5)
    for sy in (-1, 1):
        arm_y = sy * (width / 2 - arm_width / 2)
        arm_length = arm_front_x + depth / 2
        arm_centre_x = (arm_front_x - depth / 2) / 2
        parts.append(rounded_box((arm_length, arm_width, arm_top - foot_height), (arm_centre_x, arm_y, (arm_top + foot_height) / 2),
                                 softness))
        if rounded_arm_top:  # a roll along the top of the arm
            roll_radius = 0.6 * arm_width
            parts.append(rod((-depth / 2 + roll_radius, arm_y, arm_top - roll_radius),
                             (arm_front_x - roll_radius, arm_y, arm_top - roll_radius), roll_radius, roll_radius))
    back_width = width - rng.uniform(0.0, 2 * arm_width)
    back = rounded_box((back_thickness, back_width, height - body_top + 0.02),
                       (-depth / 2 + back_thickness / 2, 0.0, (height + body_top - 0.02) / 2), 1.5 * softness)
    parts.append(tilt_back(back, rng.uniform(0.0, 10.0), (-depth / 2 + back_thickness / 2, 0.0, body_top)))
    if foot_height > 0:
        foot_half_width = rng.uniform(0.015, 0.03)
        round_feet = bool(rng.random() < 0.5)
        for sx in (-1, 1):
            for sy in (-1, 1):
                x, y = sx * (depth / 2 - 0.06), sy * (width / 2 - 0.06)
                parts.append(strut((x, y, 0.0), (x, y, foot_height + 0.02), 0.7 * foot_half_width, foot_half_width, round_feet))
    return union(parts)
