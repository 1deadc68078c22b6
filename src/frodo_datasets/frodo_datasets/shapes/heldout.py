"""Held-out furniture families: designs the shape priors never see, for the real-capture evaluation set.

These are registered in `library.EVAL_FAMILIES`, not in `library.FAMILIES`, so `families()` and
`library()` (what the prior's training cycles over) are unchanged; `eval_families()` lists them and
`generate()` builds them like any other family. Same conventions as `chairs` / `tables`: one watertight
union of overlapping solids, metres, floor at z = 0, centred over the origin in x-y, chair front +x,
table long side along y.

- chair `cantilever`: tubular S-frame (no rear legs): floor runners, front uprights, seat and back shells;
- chair `tub`: round barrel chair, a curved back wrapping the seat, on a short column and disk or 4 stubby feet;
- dining table `desk`: rectangular top on a drawer pedestal at one end and a panel leg at the other,
  optional modesty panel at the back;
- dining table `round_four_leg`: round or oval top, apron ring, four legs.
"""
from __future__ import annotations

import numpy as np
import trimesh
from manifold3d import CrossSection, Manifold

from .solids import box, cylinder, lathe, merge, rod, rounded_box, rounded_slab, strut, tilt_back, union


def cantilever_chair(rng: np.random.Generator) -> trimesh.Trimesh:
    """Cantilever chair: two tube runners on the floor, bent up at the front to carry the seat, the tubes
    running back under the seat and up as the back posts; seat and back are thin shells."""
    seat_depth, seat_width = rng.uniform(0.40, 0.48), rng.uniform(0.42, 0.50)
    seat_top, seat_thickness = rng.uniform(0.44, 0.48), rng.uniform(0.02, 0.05)
    back_height = rng.uniform(0.30, 0.45)
    tube = rng.uniform(0.011, 0.016)
    runner_front = seat_depth / 2 + rng.uniform(0.00, 0.06)  # the bend in front of the seat
    runner_back = -seat_depth / 2 - rng.uniform(0.00, 0.04)
    seat_bottom = seat_top - seat_thickness
    parts: list[Manifold] = [rounded_box((seat_depth, seat_width, seat_thickness), (0.0, 0.0, seat_top - seat_thickness / 2), 0.01)]
    y = seat_width / 2 - tube
    back_x = -seat_depth / 2 + tube
    for sy in (-1, 1):
        floor_back, floor_front = (runner_back, sy * y, tube), (runner_front, sy * y, tube)
        seat_front = (seat_depth / 2 - 0.03, sy * y, seat_bottom - tube)
        seat_rear = (back_x, sy * y, seat_bottom - tube)
        parts += [rod(floor_back, floor_front, tube, tube), rod(floor_front, seat_front, tube, tube),
                  rod(seat_front, seat_rear, tube, tube)]
    if rng.random() < 0.5:  # cross tube joining the runners at the back
        parts.append(rod((runner_back, -y, tube), (runner_back, y, tube), tube, tube))
    back: list[Manifold] = [rod((back_x, sy * y, seat_bottom - tube), (back_x, sy * y, seat_top + back_height), tube, tube)
                            for sy in (-1, 1)]
    shell_height = back_height * rng.uniform(0.45, 0.8)
    back.append(rounded_box((0.02, seat_width, shell_height),
                            (back_x, 0.0, seat_top + back_height - shell_height / 2), 0.008))
    parts.append(tilt_back(merge(back), rng.uniform(4.0, 14.0),
                           (back_x, 0.0, seat_top)))
    return union(parts)


def tub_chair(rng: np.random.Generator) -> trimesh.Trimesh:
    """Tub (barrel) chair: round seat cushion, a back that wraps 180-270 degrees round the seat as a thick
    curved wall, on a central column with a disk foot or on four stubby feet."""
    radius = rng.uniform(0.30, 0.40)
    seat_top = rng.uniform(0.42, 0.48)
    back_top = seat_top + rng.uniform(0.25, 0.40)
    wall = rng.uniform(0.05, 0.09)
    shell_bottom = seat_top - rng.uniform(0.10, 0.18)
    wrap_deg = rng.uniform(180.0, 270.0)
    parts: list[Manifold] = [cylinder(radius, shell_bottom, seat_top)]
    # Curved back: a ring wall clipped to the arc behind the seat (centred on -x, the back of a chair).
    ring = lathe(np.array([[radius - wall, shell_bottom], [radius, shell_bottom], [radius, back_top],
                           [radius - wall, back_top]]))
    keep = _arc_sector(radius + 0.05, shell_bottom - 0.01, back_top + 0.01, wrap_deg)
    parts.append(ring ^ keep)
    if rng.random() < 0.5:
        column = rng.uniform(0.03, 0.05)
        parts += [cylinder(column, 0.0, shell_bottom + 0.01),
                  cylinder(rng.uniform(0.22, 0.3), 0.0, rng.uniform(0.015, 0.03))]
    else:
        foot = rng.uniform(0.018, 0.03)
        for angle in np.radians([45.0, 135.0, 225.0, 315.0]):
            x, y = 0.7 * radius * np.cos(angle), 0.7 * radius * np.sin(angle)
            parts.append(strut((1.15 * x, 1.15 * y, 0.0), (x, y, shell_bottom + 0.01), 0.7 * foot, foot, True))
    return union(parts)


def _arc_sector(reach: float, z_bottom: float, z_top: float, wrap_deg: float) -> Manifold:
    """Prism over the horizontal sector of `wrap_deg` degrees centred on the -x direction (a chair's back)."""
    angles = np.radians(np.linspace(180.0 - wrap_deg / 2, 180.0 + wrap_deg / 2, 24))
    outline = np.vstack([[0.0, 0.0], 1.5 * reach * np.column_stack([np.cos(angles), np.sin(angles)])])
    return CrossSection([outline]).extrude(z_top - z_bottom).translate((0.0, 0.0, z_bottom))


def desk(rng: np.random.Generator) -> trimesh.Trimesh:
    """Desk: rectangular top, a drawer pedestal (block with drawer-front grooves as shallow boxes) under one
    end and a panel leg under the other, optional modesty panel along the back (-x) edge."""
    length, depth, height = rng.uniform(1.1, 1.8), rng.uniform(0.6, 0.8), rng.uniform(0.72, 0.76)
    top_thickness = rng.uniform(0.02, 0.04)
    top_bottom = height - top_thickness
    parts: list[Manifold] = [rounded_slab(depth, length, top_thickness, rng.uniform(0.0, 0.03), (0.0, 0.0, height - top_thickness / 2))]
    side = float(rng.choice([-1.0, 1.0]))
    pedestal_width = rng.uniform(0.35, 0.45)
    pedestal_y = side * (length / 2 - pedestal_width / 2 - 0.01)
    pedestal_depth = depth - rng.uniform(0.02, 0.08)
    parts.append(box((pedestal_depth, pedestal_width, top_bottom + 0.01), (0.0, pedestal_y, (top_bottom + 0.01) / 2)))
    drawers = int(rng.integers(2, 5))
    drawer_height = (top_bottom - 0.06) / drawers
    for i in range(drawers):  # drawer fronts stand 1 cm proud of the pedestal, with a bar handle
        z = 0.04 + (i + 0.5) * drawer_height
        parts.append(box((0.012, pedestal_width - 0.04, drawer_height - 0.015), (pedestal_depth / 2 + 0.005, pedestal_y, z)))
        parts.append(box((0.03, 0.12, 0.015), (pedestal_depth / 2 + 0.015, pedestal_y, z + 0.25 * drawer_height)))
    panel = rng.uniform(0.025, 0.04)
    parts.append(box((depth - 0.04, panel, top_bottom + 0.01), (0.0, -side * (length / 2 - panel / 2 - 0.01), (top_bottom + 0.01) / 2)))
    if rng.random() < 0.6:
        modesty_height = rng.uniform(0.25, 0.45)
        parts.append(box((0.02, length - pedestal_width - 0.04, modesty_height),
                         (-depth / 2 + 0.05, -side * pedestal_width / 2, top_bottom - modesty_height / 2 + 0.005)))
    return union(parts)


def round_four_leg_table(rng: np.random.Generator) -> trimesh.Trimesh:
    """Round (or slightly oval) table: disk top, an apron ring under it and four legs just inside the ring."""
    radius = rng.uniform(0.45, 0.65)
    oval = rng.uniform(1.0, 1.3) if rng.random() < 0.4 else 1.0
    height, top_thickness = rng.uniform(0.72, 0.77), rng.uniform(0.025, 0.045)
    top_bottom = height - top_thickness
    top = cylinder(radius, top_bottom, height).scale((1.0, oval, 1.0))
    apron_height = rng.uniform(0.06, 0.10)
    apron_radius = radius * rng.uniform(0.75, 0.88)
    apron = lathe(np.array([[apron_radius - 0.02, top_bottom - apron_height], [apron_radius, top_bottom - apron_height],
                            [apron_radius, top_bottom + 0.005], [apron_radius - 0.02, top_bottom + 0.005]])).scale((1.0, oval, 1.0))
    parts: list[Manifold] = [top, apron]
    leg = rng.uniform(0.02, 0.035)
    round_legs = bool(rng.random() < 0.5)
    splay = rng.uniform(0.0, 0.06)
    for angle in np.radians([45.0, 135.0, 225.0, 315.0]):
        direction = np.array([np.cos(angle), oval * np.sin(angle)])
        at_top = (apron_radius - 0.02 - leg) * direction
        at_floor = at_top * (1 + splay / max(apron_radius, 1e-3))
        parts.append(strut((*at_floor, 0.0), (*at_top, top_bottom + 0.005), 0.75 * leg, leg, round_legs))
    return union(parts)
