"""Synthetic rooms: furniture from `frodo_datasets.shapes` on a textured floor, and camera trajectories.

World frame (CONTRACT.md): z up, the floor is the plane z = 0, the room is centred on the origin.
Objects stand on the floor with a random yaw and non-overlapping footprints (2D oriented rectangles,
separating-axis test with a clearance). Two camera trajectories, both optical-frame `T_world_camera`:
- `orbit_trajectory`: Redwood-like object-centric loop (~35 views) around one object or a small group,
  camera 1.2-1.6 m high, always looking at the group;
- `walk_trajectory`: ScanNet-like hand-held walk (~60 views) along a smooth open loop between the
  furniture and the walls, looking across the room at drifting targets, so objects occlude each other and
  leave the image at its borders.
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
LAYOUTS = ('walk', 'orbit')


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
    geometry (label 0); layout: 'walk' (furniture spread over the room) or 'orbit' (a small group at the centre)."""

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


def compose_scene(n_objects: int = 3, classes: Sequence[str] = ('chair', 'dining table'), seed: int = 0,
                  layout: str = 'walk', clearance: float = 0.12, max_tries: int = 2000) -> Scene:
    """Place `n_objects` procedural objects (classes cycled from `classes`) in a room.

    layout 'walk': objects spread over an inner area of the room that grows with the object count, with a
    camera corridor between it and the walls; 'orbit': objects packed around the room centre (the first
    object at the centre) so an orbit sees the group. Raises RuntimeError when the objects cannot be placed.
    """
    from frodo_datasets.shapes import families, generate

    if layout not in LAYOUTS:
        raise ValueError(f'layout must be one of {LAYOUTS}, got {layout!r}')
    if n_objects < 1:
        raise ValueError('n_objects must be >= 1')
    rng = np.random.default_rng(seed)
    names = _class_list(n_objects, classes)
    shapes = []
    for name in names:
        fams = families(name)
        family = fams[int(rng.integers(len(fams)))]
        shape_seed = int(rng.integers(0, 1_000_000))
        shapes.append((name, family, shape_seed, generate(name, shape_seed, family)))
    # Place the biggest footprints first so they find room.
    order = sorted(range(n_objects), key=lambda i: -np.prod(shapes[i][3].extents[:2]))
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
            # bbox-centred canonical mesh: lift it so its lowest point touches z = 0
            T = make_transform(yaw_matrix(yaw), (xy[0], xy[1], -mesh.bounds[0, 2]))
            obj = SceneObject(i + 1, name, category_by_name(name).coco_id, mesh, T,
                              Material.random(rng), family, shape_seed)
            if not any(footprints_overlap(obj.footprint, o.footprint, clearance) for o in placed.values()):
                placed[i] = obj
                break
        else:
            raise RuntimeError(f'could not place {n_objects} objects ({", ".join(names)}) without overlap; '
                               f'try fewer objects or another seed')
    objects = [placed[i] for i in range(n_objects)]
    reach = max(np.abs(o.footprint).max(axis=0).max() for o in objects)
    corridor = 1.6 if layout == 'walk' else 2.6
    size = (2 * max(reach, inner[0] / 2) + 2 * corridor, 2 * max(reach, inner[1] / 2) + 2 * corridor)
    room = _room_geometry(size[0], size[1], rng)
    return Scene(objects, room, (float(size[0]), float(size[1])), layout, int(seed),
                 (float(inner[0]), float(inner[1])))


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


def trajectory(scene: Scene, kind: str, n_frames: int, seed: int = 0, hfov_deg: float = 60.0) -> list[np.ndarray]:
    """`orbit_trajectory` or `walk_trajectory` by name."""
    if kind == 'orbit':
        return orbit_trajectory(scene, n_frames, seed, hfov_deg=hfov_deg)
    if kind == 'walk':
        return walk_trajectory(scene, n_frames, seed)
    raise ValueError(f'trajectory kind must be one of {LAYOUTS}, got {kind!r}')
