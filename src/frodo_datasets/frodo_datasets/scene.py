"""Synthetic rooms: furniture from `frodo_datasets.shapes` on a textured floor, and camera trajectories.

World frame (CONTRACT.md): z up, the floor is the plane z = 0, the room is centred on the origin.
Objects stand on the floor with a random yaw and non-overlapping footprints (2D oriented rectangles,
separating-axis test with a clearance). Two camera trajectories, both optical-frame `T_world_camera`:
- `orbit_trajectory`: Redwood-like object-centric loop (~35 views) around one object or a small group,
  camera 1.2-1.6 m high, always looking at the group;
- `walk_trajectory`: ScanNet-like hand-held walk (~60 views) along a smooth open loop between the
  furniture and the walls, looking across the room at drifting targets, so objects occlude each other and
  leave the image at its borders.
Two continuous hand-held paths (`pose(t)`, keyframes spread over the whole path): `HandheldPath` (close-range
scan from object to object) and `InsideOutPath` (a slow walk through the middle of a 'perimeter' room,
panning round at the furniture along the walls: what a person filming a room does).
Everything is deterministic given the seed.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import trimesh

from frodo_common.categories import category_by_name
from frodo_common.geometry import look_at, make_transform, yaw_matrix
from frodo_datasets.render import Material, RenderObject

WALL_HEIGHT = 2.6
LAYOUTS = ('walk', 'orbit', 'perimeter')
TRAJECTORIES = ('walk', 'orbit', 'handheld', 'insideout')
CONTINUOUS_PATHS = ('handheld', 'insideout')   # trajectories with a continuous `pose(t)` (motion blur, drift/s)
SCENE_LAYOUT = {'walk': 'walk', 'orbit': 'orbit', 'handheld': 'walk', 'insideout': 'perimeter'}


@dataclass
class SceneObject:
    """One piece of furniture.

    id: ground-truth object id (1, 2, ...; also its render label).
    mesh: metric mesh in the canonical object frame (z up, front +x, origin at the bounding-box centre).
    T_world_object: (4, 4) rigid transform, yaw about z and translation; the mesh stands on z = 0.
    family, shape_seed: reproduce the shape with `frodo_datasets.shapes.generate(class_name, shape_seed, family)`.
    """

    id: int
    class_name: str
    coco_id: int
    mesh: trimesh.Trimesh
    T_world_object: np.ndarray
    material: Material
    family: str = ''
    shape_seed: int = -1

    @property
    def mesh_world(self) -> trimesh.Trimesh:
        """The mesh in the world frame (a new object each call)."""
        return self.mesh.copy().apply_transform(self.T_world_object)

    @property
    def yaw(self) -> float:
        """Heading of the object's front (+x) about world z, radians."""
        return float(np.arctan2(self.T_world_object[1, 0], self.T_world_object[0, 0]))

    @property
    def footprint(self) -> np.ndarray:
        """Corners (4, 2) of the object's floor rectangle (its bounding box projected on the floor)."""
        lo, hi = self.mesh.bounds[0, :2], self.mesh.bounds[1, :2]
        corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
        return corners @ self.T_world_object[:2, :2].T + self.T_world_object[:2, 3]


@dataclass
class Scene:
    """A room with furniture. room_size: (x extent, y extent) of the floor in metres; room: floor and wall
    geometry (label 0); layout: 'walk' (furniture spread over the room), 'orbit' (a small group at the centre) or
    'perimeter' (furniture along the walls, the middle free); inner_size: the furniture area ('walk', 'orbit')
    or the free middle ('perimeter')."""

    objects: list[SceneObject]
    room: list[RenderObject]
    room_size: tuple[float, float]
    layout: str
    seed: int
    inner_size: tuple[float, float] = field(default=(0.0, 0.0))

    def render_objects(self) -> list[RenderObject]:
        """Room geometry (label 0) followed by every object in the world frame (label = object id)."""
        return list(self.room) + [RenderObject(o.mesh_world, o.material, label=o.id) for o in self.objects]

    def to_dict(self) -> dict:
        """JSON-ready description (ground truth sidecar)."""
        return {
            'seed': self.seed, 'layout': self.layout, 'room_size': list(self.room_size),
            'objects': [{
                'id': o.id, 'class': o.class_name, 'coco_id': o.coco_id, 'family': o.family,
                'shape_seed': o.shape_seed, 'T_world_object': o.T_world_object.tolist(),
                'extents': o.mesh.extents.tolist(), 'material': vars(o.material),
            } for o in self.objects],
        }


# ---------------------------------------------------------------- placement
def footprints_overlap(a: np.ndarray, b: np.ndarray, clearance: float) -> bool:
    """Separating-axis test of two convex quads (4, 2), each grown by `clearance` along every axis."""
    for quad in (a, b):
        for i in range(4):
            edge = quad[(i + 1) % 4] - quad[i]
            axis = np.array([-edge[1], edge[0]]) / np.linalg.norm(edge)
            pa, pb = a @ axis, b @ axis
            if pa.max() + clearance <= pb.min() or pb.max() + clearance <= pa.min():
                return False
    return True


def _room_geometry(size_x: float, size_y: float, rng: np.random.Generator) -> list[RenderObject]:
    """Floor slab (top at z = 0) and four walls, each with a random procedural material."""
    t = 0.05
    floor = trimesh.creation.box((size_x + 2 * t, size_y + 2 * t, t))
    floor.apply_translation((0, 0, -t / 2))
    floor_mat = Material.random(rng, kinds=('wood', 'checker', 'noise'))
    wall_mat = Material.random(rng, kinds=('plain', 'noise', 'stripes'))
    # Muted room colours, light walls: the furniture stays the most saturated thing in view.
    floor_mat.color = tuple(float(v) for v in 0.5 * np.asarray(floor_mat.color) + 0.25)
    floor_mat.color2 = tuple(float(v) for v in 0.5 * np.asarray(floor_mat.color2) + 0.15)
    wall_mat.color = tuple(float(v) for v in 0.6 + 0.35 * np.asarray(wall_mat.color))
    wall_mat.color2 = tuple(float(v) for v in 0.5 + 0.35 * np.asarray(wall_mat.color2))
    out = [RenderObject(floor, floor_mat, 0)]
    for sx, sy, cx, cy in ((size_x + 2 * t, t, 0, size_y / 2 + t / 2), (size_x + 2 * t, t, 0, -size_y / 2 - t / 2),
                           (t, size_y, size_x / 2 + t / 2, 0), (t, size_y, -size_x / 2 - t / 2, 0)):
        wall = trimesh.creation.box((sx, sy, WALL_HEIGHT))
        wall.apply_translation((cx, cy, WALL_HEIGHT / 2))
        out.append(RenderObject(wall, wall_mat, 0))
    return out


def _class_list(n_objects: int, classes: Sequence[str]) -> list[str]:
    """Object classes in order: `classes` cycled (2 chairs + 1 table for 3 objects of chair, dining table)."""
    if not classes:
        raise ValueError('at least one class is needed')
    return [classes[i % len(classes)] for i in range(n_objects)]


FAMILY_SETS = ('train', 'all', 'heldout', 'extra')


def family_pool(class_name: str, family_set: str = 'train') -> list[str]:
    """Families a scene draws from: 'train' (the prior's training families, the default), 'heldout' (the
    evaluation-only designs of `shapes.eval_families`), 'all' (both) or 'extra' (the training families and the
    broader prior's extra ones, `shapes.extra_families`: designs the first prior `furniture` has not seen that
    anyone may tune on)."""
    from frodo_datasets.shapes import eval_families, extra_families, families

    if family_set not in FAMILY_SETS:
        raise ValueError(f'family_set must be one of {FAMILY_SETS}, got {family_set!r}')
    pool = [] if family_set == 'heldout' else families(class_name)
    added = {'all': eval_families, 'heldout': eval_families, 'extra': extra_families}.get(family_set)
    return pool + (added(class_name) if added else [])


def _place(placed: dict, i: int, name: str, mesh, yaw: float, xy, rng: np.random.Generator, family: str,
           shape_seed: int, clearance: float) -> bool:
    """Put object i (its bbox-centred canonical mesh lifted so its lowest point touches z = 0) at xy with yaw unless
    its footprint comes within `clearance` of one already placed; True when placed."""
    T = make_transform(yaw_matrix(yaw), (xy[0], xy[1], -mesh.bounds[0, 2]))
    obj = SceneObject(i + 1, name, category_by_name(name).coco_id, mesh, T, Material.random(rng), family, shape_seed)
    if any(footprints_overlap(obj.footprint, o.footprint, clearance) for o in placed.values()):
        return False
    placed[i] = obj
    return True


def compose_scene(n_objects: int = 3, classes: Sequence[str] = ('chair', 'dining table'), seed: int = 0,
                  layout: str = 'walk', clearance: float = 0.12, max_tries: int = 2000,
                  family_set: str = 'train', tuck_chairs: float = 0.0, clutter: int = 0) -> Scene:
    """Place `n_objects` procedural objects (classes cycled from `classes`) in a room.

    layout 'walk': objects spread over an inner area of the room that grows with the object count, with a
    camera corridor between it and the walls; 'orbit': objects packed around the room centre (the first
    object at the centre) so an orbit sees the group; 'perimeter': objects along the walls of a 5-6 x 4.5-5.5 m
    room, the middle free for an inside-out walk (`_place_along_walls`). Raises RuntimeError when the objects
    cannot be placed. family_set: see `family_pool`. Real-capture options (off by default; they draw from
    their own random streams, so a scene without them is unchanged): `tuck_chairs` is the probability that a
    chair is moved to a table side and pushed under its top (`tuck_chair`; in a 'perimeter' room never on the
    side facing the room's middle, so the camera sees it behind the table); `clutter` is the number of
    unlabelled small items (boxes, books, bottles, bowls) put on each table top (`add_clutter`).
    """
    from frodo_datasets.shapes import generate

    if layout not in LAYOUTS:
        raise ValueError(f'layout must be one of {LAYOUTS}, got {layout!r}')
    if n_objects < 1:
        raise ValueError('n_objects must be >= 1')
    rng = np.random.default_rng(seed)
    names = _class_list(n_objects, classes)
    shapes = []
    for name in names:
        fams = family_pool(name, family_set)
        family = fams[int(rng.integers(len(fams)))]
        shape_seed = int(rng.integers(0, 1_000_000))
        shapes.append((name, family, shape_seed, generate(name, shape_seed, family)))
    # Place the biggest footprints first so they find room.
    order = sorted(range(n_objects), key=lambda i: -np.prod(shapes[i][3].extents[:2]))
    if layout == 'perimeter':
        return _perimeter_scene(shapes, order, rng, int(seed), clearance, max_tries, tuck_chairs, clutter)
    area = sum(float(np.prod(s[3].extents[:2])) for s in shapes)
    if layout == 'walk':
        side = max(2.2, 1.25 * np.sqrt(3.5 * area))
        inner = (side * 1.15, side)
    else:
        inner = (max(1.0, 1.1 * np.sqrt(3.0 * area)),) * 2
    placed: dict[int, SceneObject] = {}
    for rank, i in enumerate(order):
        name, family, shape_seed, mesh = shapes[i]
        half = mesh.extents[:2] / 2
        for _ in range(max_tries):
            yaw = float(rng.uniform(-np.pi, np.pi))
            if layout == 'orbit' and rank == 0:
                xy = np.zeros(2)
            else:
                xy = rng.uniform(-np.asarray(inner) / 2 + half.min(), np.asarray(inner) / 2 - half.min())
            if _place(placed, i, name, mesh, yaw, xy, rng, family, shape_seed, clearance):
                break
        else:
            raise RuntimeError(f'could not place {n_objects} objects ({", ".join(names)}) without overlap; '
                               f'try fewer objects or another seed')
    objects = [placed[i] for i in range(n_objects)]
    if tuck_chairs > 0:
        tuck_rng = np.random.default_rng([seed, 11])
        tables = [o for o in objects if o.class_name == 'dining table']
        for chair in [o for o in objects if o.class_name == 'chair']:
            if tables and tuck_rng.random() < tuck_chairs:
                table = tables[int(tuck_rng.integers(len(tables)))]
                tucked = tuck_chair(chair, table, [o for o in objects if o is not chair], tuck_rng)
                if tucked is not None:
                    chair.T_world_object = tucked
    reach = max(np.abs(o.footprint).max(axis=0).max() for o in objects)
    corridor = 1.6 if layout == 'walk' else 2.6
    size = (2 * max(reach, inner[0] / 2) + 2 * corridor, 2 * max(reach, inner[1] / 2) + 2 * corridor)
    room = _room_geometry(size[0], size[1], rng)
    if clutter > 0:
        room += add_clutter(objects, clutter, np.random.default_rng([seed, 12]))
    return Scene(objects, room, (float(size[0]), float(size[1])), layout, int(seed),
                 (float(inner[0]), float(inner[1])))


def _wall_frame(wall: int, half: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Wall 0..3 (+x, -x, +y, -y) of a room with half extents `half` (2,): the middle of the wall (2,), its
    inward unit normal (2,) and its half length."""
    normal = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]][wall])
    point = -normal * half
    return point, normal, float(half[1] if wall < 2 else half[0])


def _place_along_walls(shapes: list, order: list[int], rng: np.random.Generator, clearance: float,
                       max_tries: int) -> tuple[dict[int, SceneObject], np.ndarray]:
    """'perimeter' placement: a room of 5.2-6.4 x 4.4-5.4 m; each object against a random wall (biggest
    first): tables with their long side along the wall, 0.55-0.9 m from it (room for a chair behind), chairs
    0.05-0.35 m from it facing the room's middle +-35 degrees. Returns ({index: object}, room size (2,))."""
    size = np.array([rng.uniform(6.0, 7.2), rng.uniform(5.0, 6.0)])
    half = size / 2
    placed: dict[int, SceneObject] = {}
    for i in order:
        name, family, shape_seed, mesh = shapes[i]
        ext = mesh.extents[:2]
        for _ in range(max_tries):
            wall = int(rng.choice(4, p=np.r_[size[1], size[1], size[0], size[0]] / (2 * size.sum())))
            point, inward, wall_half = _wall_frame(wall, half)
            along = np.array([-inward[1], inward[0]])
            if name == 'dining table':
                long_axis = 0 if ext[0] >= ext[1] else 1   # the table's long side runs along the wall
                yaw = np.arctan2(along[1], along[0]) - long_axis * np.pi / 2 + np.radians(rng.uniform(-6, 6))
                gap = rng.uniform(0.55, 0.9)
            else:
                yaw = np.arctan2(inward[1], inward[0]) + np.radians(rng.uniform(-35, 35))
                gap = rng.uniform(0.05, 0.35)
            c, s_ = abs(np.cos(yaw)), abs(np.sin(yaw))
            footprint_half = np.array([c * ext[0] + s_ * ext[1], s_ * ext[0] + c * ext[1]]) / 2   # world x, y
            depth = footprint_half @ np.abs(inward)
            width = footprint_half @ np.abs(along)
            slack = wall_half - 0.25 - width
            if slack <= 0:
                continue
            xy = point + inward * (gap + depth) + along * rng.uniform(-slack, slack)
            if _place(placed, i, name, mesh, yaw, xy, rng, family, shape_seed, clearance):
                break
        else:
            raise RuntimeError(f'could not place {len(shapes)} objects along the walls without overlap; '
                               f'try fewer objects or another seed')
    return placed, size


def _perimeter_scene(shapes: list, order: list[int], rng: np.random.Generator, seed: int, clearance: float,
                     max_tries: int, tuck_chairs: float, clutter: int) -> Scene:
    """compose_scene's 'perimeter' layout: `_place_along_walls`, chairs tucked under tables on a side away
    from the room's middle (the far or a lateral side, the far one twice as often), clutter on the tops."""
    placed, size = _place_along_walls(shapes, order, rng, clearance, max_tries)
    objects = [placed[i] for i in range(len(shapes))]
    if tuck_chairs > 0:
        tuck_rng = np.random.default_rng([seed, 11])
        tables = [o for o in objects if o.class_name == 'dining table']
        for chair in [o for o in objects if o.class_name == 'chair']:
            if tables and tuck_rng.random() < tuck_chairs:
                table = tables[int(tuck_rng.integers(len(tables)))]
                to_middle = -table.T_world_object[:2, 3] @ table.T_world_object[:2, :2]   # in the table frame
                facing = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]], float) @ to_middle
                near, far = int(np.argmax(facing)), int(np.argmin(facing))
                sides = [far] + [s for s in range(4) if s != near]
                tucked = tuck_chair(chair, table, [o for o in objects if o is not chair], tuck_rng, sides=sides,
                                    bounds=size / 2 - 0.05)
                if tucked is not None:
                    chair.T_world_object = tucked
    room = _room_geometry(size[0], size[1], rng)
    if clutter > 0:
        room += add_clutter(objects, clutter, np.random.default_rng([seed, 12]))
    # the free middle: the room less, on every side, the deepest reach of furniture from its nearest wall
    band = 0.0
    for o in objects:
        corners = np.abs(o.footprint)
        axis = int(np.argmin(size / 2 - np.abs(o.T_world_object[:2, 3])))
        band = max(band, float(size[axis] / 2 - corners[:, axis].min()))
    free = np.clip(size - 2 * band, 0.0, None)
    return Scene(objects, room, (float(size[0]), float(size[1])), 'perimeter', seed,
                 (float(free[0]), float(free[1])))


# ---------------------------------------------------------------- real-capture arrangements
def _manifold(mesh: trimesh.Trimesh):
    from manifold3d import Manifold, Mesh
    return Manifold(Mesh(vert_properties=np.asarray(mesh.vertices, np.float32),
                         tri_verts=np.asarray(mesh.faces, np.uint32)))


def _intersection_volume(a: trimesh.Trimesh, b: trimesh.Trimesh) -> float:
    """Volume (m^3) shared by two watertight meshes (manifold3d exact boolean)."""
    return float((_manifold(a) ^ _manifold(b)).volume())


def tuck_chair(chair: SceneObject, table: SceneObject, others: Sequence[SceneObject], rng: np.random.Generator,
               clearance: float = 0.05, sides: Sequence[int] | None = None,
               bounds: np.ndarray | None = None) -> np.ndarray | None:
    """A pose (4, 4) that puts `chair` at a random side of `table`, facing it (+-10 degrees), pushed as far
    under the top as it goes without touching the table (exact mesh intersection, bisection on the push
    depth) times a random 40-100 %, clear of `others`' footprints. None if no side works (8 tries).
    sides: the table sides to draw from (0..3: +x, -x, +y, -y of the table frame; default all, uniformly);
    bounds: (2,) half extents the chair's footprint must stay within (the room's walls; default none).

    This is the arrangement real rooms have and the plain layouts lack: the seat and legs hidden under
    the table top, the chair back against its edge.
    """
    table_world = table.mesh_world
    t_half = table.mesh.extents[:2] / 2
    c_half = chair.mesh.extents[:2] / 2
    for _ in range(8):
        # +x, -x, +y, -y side of the table, in the table frame
        side = int(rng.integers(4)) if sides is None else int(sides[int(rng.integers(len(sides)))])
        axis = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]][side], float)
        along = np.array([-axis[1], axis[0]])
        span = max(0.0, t_half @ np.abs(along) - c_half[1])
        offset = rng.uniform(-span, span) * 0.8
        yaw_local = np.arctan2(-axis[1], -axis[0]) + np.radians(rng.uniform(-10, 10))  # chair front faces the table
        table_yaw = table.yaw

        def pose(depth: float) -> np.ndarray:
            centre_local = axis * (t_half @ np.abs(axis) + c_half[0] - depth) + along * offset
            c, s_ = np.cos(table_yaw), np.sin(table_yaw)
            xy = table.T_world_object[:2, 3] + np.array([[c, -s_], [s_, c]]) @ centre_local
            return make_transform(yaw_matrix(table_yaw + yaw_local), (xy[0], xy[1], -chair.mesh.bounds[0, 2]))

        def free(depth: float) -> bool:
            mesh = chair.mesh.copy().apply_transform(pose(depth))
            return _intersection_volume(mesh, table_world) < 1e-7

        if not free(0.0):
            continue
        lo, hi = 0.0, 2 * c_half[0]
        for _ in range(10):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if free(mid) else (lo, mid)
        T = pose(lo * rng.uniform(0.4, 1.0))
        candidate = SceneObject(chair.id, chair.class_name, chair.coco_id, chair.mesh, T, chair.material)
        if bounds is not None and np.any(np.abs(candidate.footprint) > bounds):
            continue
        if not any(footprints_overlap(candidate.footprint, o.footprint, clearance) for o in others if o is not table):
            return T
    return None


def _clutter_item(rng: np.random.Generator) -> trimesh.Trimesh:
    """One small table-top item standing on z = 0: a box, a book stack, a bottle, a mug or a bowl."""
    kind = rng.choice(['box', 'books', 'bottle', 'mug', 'bowl'])
    if kind == 'box':
        mesh = trimesh.creation.box(rng.uniform([0.08, 0.08, 0.05], [0.30, 0.25, 0.25]))
    elif kind == 'books':
        mesh = trimesh.creation.box((rng.uniform(0.15, 0.3), rng.uniform(0.12, 0.22), rng.uniform(0.02, 0.12)))
    elif kind == 'bottle':
        radius, tall = rng.uniform(0.03, 0.045), rng.uniform(0.18, 0.32)
        body = trimesh.creation.cylinder(radius, tall * 0.7, sections=16)
        body.apply_translation((0, 0, tall * 0.35))
        neck = trimesh.creation.cylinder(radius * 0.35, tall * 0.35, sections=12)
        neck.apply_translation((0, 0, tall * 0.8))
        mesh = trimesh.util.concatenate([body, neck])
    elif kind == 'mug':
        mesh = trimesh.creation.cylinder(rng.uniform(0.035, 0.05), rng.uniform(0.08, 0.11), sections=16)
    else:
        mesh = trimesh.creation.cone(rng.uniform(0.07, 0.13), rng.uniform(0.05, 0.08), sections=20)
        mesh.apply_transform(make_transform(np.diag([1.0, -1.0, -1.0])))  # opening up
    mesh.apply_translation((0, 0, -mesh.bounds[0, 2]))
    return mesh


def add_clutter(objects: Sequence[SceneObject], per_table: int, rng: np.random.Generator) -> list[RenderObject]:
    """Up to `per_table` small unlabelled items (label 0: not objects to reconstruct, they only occlude) on
    the top of every table, each resting where a downward ray from above hits the table's upper surface."""
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    items = []
    for table in [o for o in objects if o.class_name == 'dining table']:
        mesh = table.mesh_world
        caster = RayMeshIntersector(mesh)
        top = mesh.bounds[1, 2]
        half = table.mesh.extents[:2] / 2
        for _ in range(per_table):
            local = rng.uniform(-0.8 * half, 0.8 * half)
            xy = table.T_world_object[:2, :2] @ local + table.T_world_object[:2, 3]
            locations, _, _ = caster.intersects_location([[xy[0], xy[1], top + 1.0]], [[0.0, 0.0, -1.0]],
                                                         multiple_hits=False)
            if not len(locations) or locations[0, 2] < top - 0.06:  # missed the top (round or narrow tops)
                continue
            item = _clutter_item(rng)
            item.apply_transform(make_transform(yaw_matrix(rng.uniform(-np.pi, np.pi)),
                                                (xy[0], xy[1], locations[0, 2] + 1e-3)))
            items.append(RenderObject(item, Material.random(rng), 0))
    return items


# ---------------------------------------------------------------- trajectories
def _smooth_noise(rng: np.random.Generator, t: np.ndarray, amplitude: float, harmonics: int = 3) -> np.ndarray:
    """Smooth periodic noise (len(t),) on t in [0, 1): a few random low-frequency sinusoids."""
    out = np.zeros_like(t)
    for h in range(1, harmonics + 1):
        out += rng.normal(0, amplitude / h) * np.sin(2 * np.pi * h * t + rng.uniform(0, 2 * np.pi))
    return out


def _group_centre(objects: Sequence[SceneObject]) -> np.ndarray:
    corners = np.concatenate([o.footprint for o in objects])
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    height = max(o.mesh.extents[2] for o in objects)
    return np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.45 * height])


def orbit_trajectory(scene: Scene, n_frames: int = 35, seed: int = 0, object_ids: Sequence[int] | None = None,
                     height: tuple[float, float] = (1.2, 1.6), arc_deg: float = 340.0,
                     hfov_deg: float = 60.0) -> list[np.ndarray]:
    """Object-centric loop around `object_ids` (default: all objects of an orbit scene, else the first).

    The radius makes the group fill about half of the horizontal field of view; the camera height wanders
    smoothly within `height`; the view direction jitters by a few degrees around the group centre.
    Returns `n_frames` poses T_world_camera (4, 4).
    """
    rng = np.random.default_rng(seed)
    if object_ids is None:
        object_ids = [o.id for o in scene.objects] if scene.layout == 'orbit' else [scene.objects[0].id]
    group = [o for o in scene.objects if o.id in set(object_ids)]
    if not group:
        raise ValueError(f'no objects with ids {list(object_ids)} in the scene')
    centre = _group_centre(group)
    corners = np.concatenate([o.footprint for o in group])
    extent = np.linalg.norm(corners - centre[:2], axis=1).max()
    size = max(extent, max(o.mesh.extents[2] for o in group) / 2)
    radius = max(1.2, size / np.tan(np.radians(hfov_deg) / 4))
    limit = min(scene.room_size) / 2 - 0.3
    radius = min(radius, limit)
    t = np.arange(n_frames) / n_frames
    start = rng.uniform(0, 2 * np.pi)
    direction = rng.choice([-1.0, 1.0])
    az = start + direction * np.radians(arc_deg) * np.arange(n_frames) / max(n_frames - 1, 1)
    r = radius * (1 + _smooth_noise(rng, t, 0.05))
    z = np.clip(np.mean(height) + _smooth_noise(rng, t, (height[1] - height[0]) / 3), *height)
    poses = []
    for k in range(n_frames):
        eye = np.array([centre[0] + r[k] * np.cos(az[k]), centre[1] + r[k] * np.sin(az[k]), z[k]])
        target = centre + rng.normal(0, 0.04 * size, 3)
        poses.append(look_at(eye, target))
    return poses


def walk_trajectory(scene: Scene, n_frames: int = 60, seed: int = 0, height: tuple[float, float] = (1.3, 1.65),
                    arc_deg: float = 300.0) -> list[np.ndarray]:
    """Hand-held walk along a wobbly ellipse between the furniture area and the walls (an open loop over
    `arc_deg`), looking at targets that drift smoothly between the objects and the room centre, at eye
    height within `height`. Returns `n_frames` poses T_world_camera (4, 4).
    """
    rng = np.random.default_rng(seed)
    half_room = np.asarray(scene.room_size) / 2
    half_inner = np.asarray(scene.inner_size) / 2
    corners = np.concatenate([o.footprint for o in scene.objects])
    reach = np.maximum(np.abs(corners).max(axis=0), half_inner)
    axes = np.minimum((reach + half_room) / 2 + 0.2, half_room - 0.45)
    t = np.arange(n_frames) / max(n_frames - 1, 1)
    start = rng.uniform(0, 2 * np.pi)
    direction = rng.choice([-1.0, 1.0])
    az = start + direction * np.radians(arc_deg) * t
    wobble = 1 + _smooth_noise(rng, t, 0.05, harmonics=4)
    xy = np.stack([axes[0] * wobble * np.cos(az), axes[1] * wobble * np.sin(az)], axis=1)
    xy = np.clip(xy, -half_room + 0.35, half_room - 0.35)
    z = np.clip(np.mean(height) + _smooth_noise(rng, t, (height[1] - height[0]) / 3), *height)
    # Targets: a smooth blend of object centres and the room centre, so objects cross the image borders.
    anchors = np.array([o.T_world_object[:3, 3] * [1, 1, 0.8] for o in scene.objects] + [[0.0, 0.0, 0.5]])
    n_keys = max(3, n_frames // 12)
    keys = anchors[rng.integers(len(anchors), size=n_keys)] + rng.normal(0, [0.35, 0.35, 0.1], (n_keys, 3))
    key_t = np.linspace(0, 1, n_keys)
    weights = np.exp(-0.5 * ((t[:, None] - key_t[None, :]) / (0.7 / n_keys)) ** 2)
    targets = weights @ keys / weights.sum(axis=1, keepdims=True)
    poses = []
    for k in range(n_frames):
        eye = np.array([xy[k, 0], xy[k, 1], z[k]])
        target = targets[k]
        if np.linalg.norm((target - eye)[:2]) < 0.8:  # too close to look at: look across the room instead
            target = np.array([-eye[0], -eye[1], 0.5])
        poses.append(look_at(eye, target))
    return poses


class HandheldPath:
    """Real-capture-like hand-held scan: the camera goes from object to object, stops at close range (0.5-2 m
    from a point on the object's surface, so big objects are cut by the image border), looks at different
    parts of each, and visits every object twice in a random order. Continuous in time (`pose(t)`, for
    motion blur); `keyframes(n)` spreads n views over the whole path, as a SLAM system's keyframes are
    (far apart, not consecutive frames).

    The path: per visit 2-3 waypoints (eye, target) on an arc around the object at horizontal distance
    `distance` and eye height `height`, eyes kept out of the furniture and 0.3 m from the walls; eye and
    target interpolated by monotone cubics (PCHIP, no overshoot) at walking speed `speed` with a dwell at
    each waypoint; a few degrees of smooth hand roll.
    """

    def __init__(self, scene: Scene, seed: int = 0, distance: tuple[float, float] = (0.4, 1.7),
                 height: tuple[float, float] = (1.0, 1.6), speed: float = 0.35, dwell_s: float = 1.0,
                 visits_per_object: int = 2):
        from scipy.interpolate import PchipInterpolator

        rng = np.random.default_rng(seed)
        self.scene = scene
        order = [o for _ in range(visits_per_object) for o in rng.permutation(scene.objects)]
        eyes, targets = [], []
        for obj in order:
            mesh = obj.mesh_world
            azimuth = rng.uniform(0, 2 * np.pi)
            for _ in range(int(rng.integers(2, 4))):
                azimuth += rng.uniform(0.3, 1.1) * rng.choice([-1, 1])
                target = trimesh.sample.sample_surface(mesh, 1, seed=int(rng.integers(2**31)))[0][0]
                eye = self._place_eye(target, azimuth, distance, height, rng)
                eyes.append(eye)
                targets.append(target)
        eyes, targets = np.array(eyes), np.array(targets)
        legs = np.linalg.norm(np.diff(eyes, axis=0), axis=1) + 0.3 * np.linalg.norm(np.diff(targets, axis=0), axis=1)
        times = np.concatenate([[0.0], np.cumsum(legs / speed + dwell_s)])
        self.duration = float(times[-1])
        self._eye = PchipInterpolator(times, eyes)
        self._target = PchipInterpolator(times, targets)
        self._roll = (rng.normal(0, 2.0, 4), rng.uniform(0, 2 * np.pi, 4))

    def _inside_furniture(self, eye: np.ndarray, margin: float = 0.2) -> bool:
        for o in self.scene.objects:
            if eye[2] < o.mesh_world.bounds[1, 2] + margin:
                local = (eye[:2] - o.T_world_object[:2, 3]) @ o.T_world_object[:2, :2]
                if np.all(np.abs(local) < o.mesh.extents[:2] / 2 + margin):
                    return True
        return False

    def _in_room(self, eye: np.ndarray) -> bool:
        return bool(np.all(np.abs(eye[:2]) < np.asarray(self.scene.room_size) / 2 - 0.3))

    def _place_eye(self, target: np.ndarray, azimuth: float, distance: tuple[float, float],
                   height: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
        eye = None
        for attempt in range(40):
            az = azimuth + (0 if attempt == 0 else rng.uniform(-np.pi, np.pi))
            d = rng.uniform(*distance)
            eye = np.array([target[0] + d * np.cos(az), target[1] + d * np.sin(az), rng.uniform(*height)])
            if self._in_room(eye) and not self._inside_furniture(eye):
                return eye
        half = np.asarray(self.scene.room_size) / 2 - 0.3
        eye[:2] = np.clip(eye[:2], -half, half)
        return eye

    def pose(self, t: float) -> np.ndarray:
        """T_world_camera (4, 4) at time t in [0, duration] seconds."""
        t = float(np.clip(t, 0.0, self.duration))
        eye, target = self._eye(t), self._target(t)
        if self._inside_furniture(eye, margin=0.05):  # between waypoints: step over the furniture
            top = max(o.mesh_world.bounds[1, 2] for o in self.scene.objects)
            eye = np.array([eye[0], eye[1], max(eye[2], top + 0.1)])
        T = look_at(eye, target)
        amplitude, phase = self._roll
        roll = np.radians(np.sum(amplitude * np.sin(2 * np.pi * t / np.array([7.0, 3.1, 1.7, 0.9]) + phase)))
        c, s_ = np.cos(roll), np.sin(roll)
        return T @ make_transform(np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]]))

    def keyframe_times(self, n_frames: int, seed: int = 0) -> np.ndarray:
        """n_frames times spread evenly over the whole path, each jittered by up to 30 % of the spacing."""
        spacing = self.duration / max(n_frames, 1)
        jitter = np.random.default_rng(seed).uniform(-0.3, 0.3, n_frames) * spacing
        return np.clip((np.arange(n_frames) + 0.5) * spacing + jitter, 0.0, self.duration)

    def keyframes(self, n_frames: int, seed: int = 0) -> list[np.ndarray]:
        """Poses of `keyframe_times(n_frames)`."""
        return [self.pose(t) for t in self.keyframe_times(n_frames, seed)]


class InsideOutPath(HandheldPath):
    """Inside-out walk through the middle of a room looking outwards (issue 27), what a person filming a room
    does and what the real captures the project failed on look like: the body walks slowly (`walk_m` in all)
    along the room's long axis through its middle, swaying a little sideways, while the camera, held `lever`
    m in front of the body at eye height `height`, pans round at the furniture along the walls, tilted down
    by `pitch_deg`. The pan is one sweep in one direction (`sweep_deg` in all: with a 60-degree field of view
    every wall comes into view once; the headings it leaves out face the widest stretch of wall without
    furniture) at an angular speed that changes every `segment_s` seconds (log-normal, spread `turn_sigma`: a
    pause here, a quick turn there), with an occasional slower turn back (`back_rate` of the segments).
    Keyframes spread evenly over `duration_s` (the base class's `keyframe_times`) are then rotation-dominated
    and narrow-baseline: at 35 keyframes a median turn of ~8 degrees (90th percentile ~18) and a median
    baseline of ~8 cm between consecutive ones, and each object is in view in a handful of them, from one
    side (`capture_stats`). Continuous in time like `HandheldPath` (`pose(t)`: motion blur; the hand roll and
    stepping over furniture are the base class's).
    """

    def __init__(self, scene: Scene, seed: int = 0, duration_s: float = 35.0,
                 sweep_deg: tuple[float, float] = (270.0, 310.0), turn_sigma: float = 0.8, back_rate: float = 0.08,
                 segment_s: float = 1.0, walk_m: tuple[float, float] = (2.0, 3.4), sway_m: float = 0.15,
                 lever: float = 0.35, height: tuple[float, float] = (1.3, 1.6),
                 pitch_deg: tuple[float, float] = (-28.0, -12.0)):
        from scipy.interpolate import PchipInterpolator

        rng = np.random.default_rng(seed)
        self.scene = scene
        self.duration = float(duration_s)
        n = max(2, int(round(duration_s / segment_s)))
        times = np.linspace(0.0, self.duration, n + 1)
        u = times / self.duration
        speed = np.exp(rng.normal(0.0, turn_sigma, n)) * np.where(rng.random(n) < back_rate, -0.5, 1.0)
        sweep = np.radians(rng.uniform(*sweep_deg)) * rng.choice([-1.0, 1.0])
        # start so that the headings the sweep leaves out face the widest stretch of wall without furniture
        bearing = np.sort([np.arctan2(o.T_world_object[1, 3], o.T_world_object[0, 3]) for o in scene.objects])
        gaps = np.diff(np.concatenate([bearing, [bearing[0] + 2 * np.pi]]))
        bare = bearing[int(np.argmax(gaps))] + gaps.max() / 2 + np.radians(rng.uniform(-10, 10))
        start = bare - np.sign(sweep) * (np.pi + abs(sweep) / 2)
        heading = start + sweep * np.concatenate([[0.0], np.cumsum(speed)]) / speed.sum()
        pitch = np.radians(np.clip(np.mean(pitch_deg) + _smooth_noise(rng, u, (pitch_deg[1] - pitch_deg[0]) / 3),
                                   *pitch_deg))
        z = np.clip(np.mean(height) + _smooth_noise(rng, u, (height[1] - height[0]) / 4), *height)
        long_axis = int(np.argmax(scene.room_size))
        walk = min(rng.uniform(*walk_m), max(0.4, scene.inner_size[long_axis] - lever))
        body = np.tile(rng.uniform(-0.2, 0.2, 2), (n + 1, 1))
        body[:, long_axis] += rng.choice([-1.0, 1.0]) * walk * (u - 0.5)
        body[:, 1 - long_axis] += _smooth_noise(rng, u, sway_m, harmonics=2)
        look = np.stack([np.cos(pitch) * np.cos(heading), np.cos(pitch) * np.sin(heading), np.sin(pitch)], axis=1)
        eyes = np.concatenate([body + lever * look[:, :2] / np.linalg.norm(look[:, :2], axis=1, keepdims=True),
                               z[:, None]], axis=1)
        half = np.asarray(scene.room_size) / 2 - 0.3
        eyes[:, :2] = np.clip(eyes[:, :2], -half, half)
        self._eye = PchipInterpolator(times, eyes)
        self._target = PchipInterpolator(times, eyes + 2.0 * look)
        self._roll = (rng.normal(0, 2.0, 4), rng.uniform(0, 2 * np.pi, 4))


def continuous_path(scene: Scene, kind: str, seed: int = 0) -> HandheldPath:
    """The continuous path of a `CONTINUOUS_PATHS` trajectory: `HandheldPath` or `InsideOutPath`."""
    if kind == 'handheld':
        return HandheldPath(scene, seed)
    if kind == 'insideout':
        return InsideOutPath(scene, seed)
    raise ValueError(f'no continuous path for trajectory {kind!r}; continuous ones: {CONTINUOUS_PATHS}')


def trajectory(scene: Scene, kind: str, n_frames: int, seed: int = 0, hfov_deg: float = 60.0) -> list[np.ndarray]:
    """`orbit_trajectory`, `walk_trajectory` or the keyframes of a `HandheldPath` / `InsideOutPath` by name."""
    if kind == 'orbit':
        return orbit_trajectory(scene, n_frames, seed, hfov_deg=hfov_deg)
    if kind == 'walk':
        return walk_trajectory(scene, n_frames, seed)
    if kind in CONTINUOUS_PATHS:
        return continuous_path(scene, kind, seed).keyframes(n_frames, seed)
    raise ValueError(f'trajectory kind must be one of {TRAJECTORIES}, got {kind!r}')
