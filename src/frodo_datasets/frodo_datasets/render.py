"""Embree ray-cast renderer for synthetic scenes: RGB, instance labels and depth (numpy, no ROS).

Objects are triangle meshes in the world frame, each with a procedural *solid* texture evaluated at the
3D hit position (no UVs), so a surface point has the same albedo in every view and photometric consistency
across views carries signal. Shading is Lambertian with ambient light and one directional or point light,
optionally with shadow rays. All per-pixel work is vectorised; one embree scene is built per `Renderer` and
reused for every camera of a trajectory.

Camera conventions (CONTRACT.md): optical frame x right, y down, z forward; `T_world_camera` maps camera to
world points; pixel (u, v) is the centre of column u and row v, so a world point lands at
`frodo_common.geometry.project_points(K, inv(T_world_camera), p)`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

TEXTURE_KINDS: tuple[str, ...] = ('plain', 'wood', 'checker', 'noise', 'stripes')


# ---------------------------------------------------------------- procedural solid textures
def _hash01(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer lattice point (arrays of equal shape)."""
    with np.errstate(over='ignore'):
        h = (ix.astype(np.uint64) * np.uint64(73856093)) ^ (iy.astype(np.uint64) * np.uint64(19349663)) \
            ^ (iz.astype(np.uint64) * np.uint64(83492791)) ^ np.uint64((seed * 2654435761) & 0xFFFFFFFF)
        h ^= h >> np.uint64(13)
        h *= np.uint64(0x5BD1E995)
        h ^= h >> np.uint64(15)
    return (h & np.uint64(0xFFFFFF)).astype(np.float64) / float(0x1000000)


def value_noise(points: np.ndarray, seed: int, octaves: int = 3) -> np.ndarray:
    """Smooth 3D value noise in [0, 1] at points (N, 3) (lattice spacing 1, octaves halve the spacing)."""
    out = np.zeros(len(points))
    amp_sum = 0.0
    for o in range(octaves):
        p = points * (2.0 ** o)
        i0 = np.floor(p).astype(np.int64)
        f = p - i0
        f = f * f * (3 - 2 * f)
        acc = np.zeros(len(points))
        for dx in (0, 1):
            wx = f[:, 0] if dx else 1 - f[:, 0]
            for dy in (0, 1):
                wy = f[:, 1] if dy else 1 - f[:, 1]
                for dz in (0, 1):
                    wz = f[:, 2] if dz else 1 - f[:, 2]
                    acc += wx * wy * wz * _hash01(i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz, seed + 7919 * o)
        amp = 0.5 ** o
        out += amp * acc
        amp_sum += amp
    return out / amp_sum


def _random_rotation(seed: int) -> np.ndarray:
    """Rotation (3, 3) drawn from `seed` (orients grain, stripes and checkers per material)."""
    q = np.random.default_rng(seed).normal(size=4)
    q /= np.linalg.norm(q)
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _hsv_to_rgb(h: float, s: float, v: float) -> np.ndarray:
    i = int(h * 6) % 6
    f = h * 6 - int(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i])


@dataclass
class Material:
    """Diffuse material with a procedural solid texture.

    color, color2: RGB albedos in [0, 1] (color2 is the second tone of checker / stripes / wood / noise).
    kind: one of TEXTURE_KINDS.
    scale: texture frequency in cycles per metre.
    seed: makes noise and the texture orientation deterministic.
    """

    color: tuple[float, float, float] = (0.7, 0.7, 0.7)
    kind: str = 'plain'
    color2: tuple[float, float, float] = (0.4, 0.4, 0.4)
    scale: float = 4.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.kind not in TEXTURE_KINDS:
            raise ValueError(f'unknown texture kind {self.kind!r}; known: {TEXTURE_KINDS}')

    @classmethod
    def random(cls, rng: np.random.Generator, kinds: Sequence[str] = TEXTURE_KINDS) -> 'Material':
        """A random saturated-ish colour pair with a random texture kind from `kinds`."""
        h = float(rng.uniform())
        c1 = _hsv_to_rgb(h, float(rng.uniform(0.25, 0.8)), float(rng.uniform(0.45, 0.95)))
        c2 = _hsv_to_rgb((h + rng.uniform(-0.08, 0.08)) % 1.0, float(rng.uniform(0.2, 0.9)),
                         float(rng.uniform(0.2, 0.6)))
        return cls(color=tuple(float(v) for v in c1), kind=str(rng.choice(list(kinds))),
                   color2=tuple(float(v) for v in c2), scale=float(rng.uniform(2.0, 12.0)),
                   seed=int(rng.integers(0, 2**31 - 1)))

    def albedo(self, points: np.ndarray) -> np.ndarray:
        """Albedo RGB (N, 3) in [0, 1] at world points (N, 3)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        c1, c2 = np.asarray(self.color, dtype=np.float64), np.asarray(self.color2, dtype=np.float64)
        if self.kind == 'plain':
            return np.broadcast_to(c1, points.shape).copy()
        p = points @ _random_rotation(self.seed).T * self.scale
        if self.kind == 'checker':
            t = (np.floor(p).astype(np.int64).sum(axis=1) % 2).astype(np.float64)
        elif self.kind == 'stripes':
            t = 0.5 + 0.5 * np.sin(2 * np.pi * p[:, 0])
        elif self.kind == 'noise':
            t = value_noise(p, self.seed, octaves=3)
            t = np.clip((t - 0.5) * 2.2 + 0.5, 0.0, 1.0)
        else:  # wood: rings around the rotated z axis, perturbed by noise
            r = np.hypot(p[:, 0], p[:, 1]) + 0.6 * value_noise(p * np.array([1.0, 1.0, 0.15]), self.seed, 2)
            t = (r % 1.0) ** 2
        return c1 + t[:, None] * (c2 - c1)


# ---------------------------------------------------------------- scene description
@dataclass
class RenderObject:
    """A mesh in the world frame with its material; `label` is written to the label image (0 = room/background)."""

    mesh: trimesh.Trimesh
    material: Material = field(default_factory=Material)
    label: int = 0


@dataclass
class Light:
    """One light source: directional (`direction` = direction the light travels) or point (`position` set)."""

    direction: tuple[float, float, float] = (-0.35, -0.25, -1.0)
    position: tuple[float, float, float] | None = None
    intensity: float = 0.75


@dataclass
class RenderResult:
    """rgb (H, W, 3) uint8; labels (H, W) uint16 (RenderObject.label per pixel, 0 = no object / background);
    depth (H, W) float32 z-depth along the optical axis in metres, 0 where no surface was hit."""

    rgb: np.ndarray
    labels: np.ndarray
    depth: np.ndarray


@dataclass
class Realism:
    """Optional rendering effects (all off by default; the real-capture preset turns them on).

    ao_samples: ambient-occlusion rays per pixel (0 = none); ao_radius: their length, m; ao_strength: how
    much of the ambient term a fully occluded point loses. soft_shadow_deg: angular radius of the light
    (one jittered shadow ray per pixel; 0 = hard shadows). specular, shininess: Blinn-Phong highlight
    (white, added on top of the diffuse colour). seed: the random rays (fixed per frame for repeatability).
    Cost at 320x240 (2-core CPU VM, shared/loaded; median of 6 hand-held views of a furnished room): plain
    0.89 s, with 4 AO rays + soft shadows + specular 2.0 s per frame (x2.3); the AO rays are most of it.
    """

    ao_samples: int = 0
    ao_radius: float = 0.35
    ao_strength: float = 0.8
    soft_shadow_deg: float = 0.0
    specular: float = 0.0
    shininess: float = 40.0
    seed: int = 0

    @property
    def active(self) -> bool:
        return bool(self.ao_samples or self.soft_shadow_deg or self.specular)


def _jitter_directions(directions: np.ndarray, max_angle: float, rng: np.random.Generator) -> np.ndarray:
    """Unit directions (N, 3) each tilted towards a uniform random point of a cone of half-angle `max_angle`."""
    helper = np.where(np.abs(directions[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    tangent = np.cross(directions, helper)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    bitangent = np.cross(directions, tangent)
    radius, phi = np.tan(max_angle) * np.sqrt(rng.uniform(size=len(directions))), rng.uniform(0, 2 * np.pi, len(directions))
    out = directions + (radius * np.cos(phi))[:, None] * tangent + (radius * np.sin(phi))[:, None] * bitangent
    return out / np.linalg.norm(out, axis=1, keepdims=True)


class Renderer:
    """Ray caster over a fixed set of objects; build once, render many cameras.

    >>> r = Renderer([RenderObject(mesh, Material.random(rng), label=1)])
    >>> out = r.render(K, look_at(eye, target), 320, 240)
    """

    def __init__(self, objects: Sequence[RenderObject]):
        objects = [o for o in objects if len(o.mesh.faces) > 0]
        if not objects:
            raise ValueError('Renderer needs at least one object with faces')
        self.objects = list(objects)
        self._mesh = trimesh.util.concatenate([o.mesh for o in objects])
        self._owner = np.repeat(np.arange(len(objects)), [len(o.mesh.faces) for o in objects])
        self._labels = np.array([o.label for o in objects], dtype=np.uint16)
        self._normals = np.asarray(self._mesh.face_normals, dtype=np.float64)
        self._ray = RayMeshIntersector(self._mesh)
        self._eps = 1e-4 * max(1.0, float(self._mesh.scale))

    def render(self, K: np.ndarray, T_world_camera: np.ndarray, width: int, height: int,
               light: Light | None = None, ambient: float = 0.35, shadows: bool = True,
               background: np.ndarray | Sequence[float] | None = None,
               quality: Realism | None = None) -> RenderResult:
        """Render one view.

        K (3, 3) pinhole intrinsics; T_world_camera (4, 4) optical camera pose; light defaults to `Light()`;
        ambient and light intensity are multiplied by the albedo (clipped to 1). background: RGB colour in
        [0, 1] (3,) or an image (H, W, 3) uint8 shown where rays hit nothing; None = black. quality: ambient
        occlusion, soft shadows and specular highlights (`Realism`); None = plain Lambertian (the default).
        """
        light = light if light is not None else Light()
        K = np.asarray(K, dtype=np.float64)
        T = np.asarray(T_world_camera, dtype=np.float64)
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        d_cam = np.stack([(u.ravel() - K[0, 2]) / K[0, 0], (v.ravel() - K[1, 2]) / K[1, 1],
                          np.ones(width * height)], axis=1)
        dirs = d_cam @ T[:3, :3].T
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        origins = np.broadcast_to(T[:3, 3], dirs.shape)
        tri, ray, loc = self._ray.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)

        rgb = self._background(background, height, width)
        labels = np.zeros(width * height, dtype=np.uint16)
        depth = np.zeros(width * height, dtype=np.float32)
        if len(ray):
            owner = self._owner[tri]
            labels[ray] = self._labels[owner]
            depth[ray] = ((loc - T[:3, 3]) @ T[:3, 2]).astype(np.float32)
            normals = self._normals[tri]
            facing = np.sum(normals * dirs[ray], axis=1) > 0
            normals[facing] *= -1.0  # two-sided surfaces: normals face the camera
            albedo = np.empty((len(ray), 3))
            for i in np.unique(owner):
                sel = owner == i
                albedo[sel] = self.objects[i].material.albedo(loc[sel])
            if quality is None or not quality.active:
                shade = ambient + light.intensity * self._direct(loc, normals, light, shadows)
                rgb[ray] = np.clip(albedo * shade[:, None], 0.0, 1.0)
            else:
                rng = np.random.default_rng(quality.seed)
                direct = self._direct(loc, normals, light, shadows, quality.soft_shadow_deg, rng)
                occlusion = self._ambient_occlusion(loc, normals, quality, rng)
                colour = albedo * (ambient * (1.0 - quality.ao_strength * occlusion) + light.intensity * direct)[:, None]
                if quality.specular > 0:
                    to_light = self._to_light(loc, light)[0]
                    half = to_light - dirs[ray]
                    half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-9)
                    glint = np.clip(np.sum(normals * half, axis=1), 0.0, None) ** quality.shininess
                    colour += (quality.specular * light.intensity * glint * (direct > 0))[:, None]
                rgb[ray] = np.clip(colour, 0.0, 1.0)
        return RenderResult(rgb=(rgb.reshape(height, width, 3) * 255 + 0.5).astype(np.uint8),
                            labels=labels.reshape(height, width), depth=depth.reshape(height, width))

    @staticmethod
    def _to_light(points: np.ndarray, light: Light) -> tuple[np.ndarray, np.ndarray]:
        """Unit directions (N, 3) from surface points to the light and distances (N,) (inf if directional)."""
        if light.position is not None:
            to_light = np.asarray(light.position, dtype=np.float64) - points
            dist = np.linalg.norm(to_light, axis=1)
            to_light /= np.maximum(dist, 1e-9)[:, None]
        else:
            to_light = np.broadcast_to(-np.asarray(light.direction, dtype=np.float64)
                                       / np.linalg.norm(light.direction), points.shape).copy()
            dist = np.full(len(points), np.inf)
        return to_light, dist

    def _direct(self, points: np.ndarray, normals: np.ndarray, light: Light, shadows: bool,
                soft_deg: float = 0.0, rng: np.random.Generator | None = None) -> np.ndarray:
        """Cosine term (N,) of the light at surface points, zero where occluded (when `shadows`).

        soft_deg > 0: the shadow ray of each point goes to a random point of a light disc of that angular
        radius (one jittered ray per pixel: penumbrae are soft but grainy, like a noisy sensor sees them).
        """
        to_light, dist = self._to_light(points, light)
        cos = np.clip(np.sum(normals * to_light, axis=1), 0.0, None)
        if shadows:
            lit = np.flatnonzero(cos > 0)
            if len(lit):
                start = points[lit] + normals[lit] * self._eps
                towards = to_light[lit]
                if soft_deg > 0 and rng is not None:
                    towards = _jitter_directions(towards, np.radians(soft_deg), rng)
                s_tri, s_ray, s_loc = self._ray.intersects_id(start, towards, multiple_hits=False,
                                                              return_locations=True)
                blocked = np.linalg.norm(s_loc - start[s_ray], axis=1) < dist[lit][s_ray]
                cos[lit[s_ray[blocked]]] = 0.0
        return cos

    def _ambient_occlusion(self, points: np.ndarray, normals: np.ndarray, quality: Realism,
                           rng: np.random.Generator) -> np.ndarray:
        """Fraction (N,) of `quality.ao_samples` cosine-weighted hemisphere rays per point that hit a surface
        within `quality.ao_radius` metres (0 = open sky, 1 = fully enclosed): darkens creases, the floor
        under tables and chairs, and the seat under a table top."""
        n = quality.ao_samples
        if n <= 0 or not len(points):
            return np.zeros(len(points))
        normal = np.repeat(normals, n, axis=0)
        start = np.repeat(points, n, axis=0) + normal * self._eps
        # Cosine-weighted hemisphere: uniform disc sample lifted onto the hemisphere about the normal.
        r, phi = np.sqrt(rng.uniform(size=len(start))), rng.uniform(0, 2 * np.pi, len(start))
        helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        tangent = np.cross(normal, helper)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        bitangent = np.cross(normal, tangent)
        dirs = ((r * np.cos(phi))[:, None] * tangent + (r * np.sin(phi))[:, None] * bitangent
                + np.sqrt(np.clip(1 - r * r, 0, None))[:, None] * normal)
        _, hit_ray, hit_loc = self._ray.intersects_id(start, dirs, multiple_hits=False, return_locations=True)
        near = np.linalg.norm(hit_loc - start[hit_ray], axis=1) < quality.ao_radius
        hits = np.zeros(len(start))
        hits[hit_ray[near]] = 1.0
        return hits.reshape(-1, n).mean(axis=1)

    @staticmethod
    def _background(background, height: int, width: int) -> np.ndarray:
        if background is None:
            return np.zeros((height * width, 3))
        bg = np.asarray(background)
        if bg.ndim == 3:
            if bg.shape != (height, width, 3):
                raise ValueError(f'background image has shape {bg.shape}, expected {(height, width, 3)}')
            return bg.reshape(-1, 3).astype(np.float64) / 255.0
        if bg.shape != (3,):
            raise ValueError(f'background must be an RGB colour (3,) or an image (H, W, 3), got shape {bg.shape}')
        return np.broadcast_to(bg.astype(np.float64), (height * width, 3)).copy()


def render(objects: Sequence[RenderObject], K: np.ndarray, T_world_camera: np.ndarray, width: int, height: int,
           light: Light | None = None, ambient: float = 0.35, shadows: bool = True,
           background: np.ndarray | Sequence[float] | None = None) -> RenderResult:
    """Render one view of `objects` (builds a throwaway `Renderer`; use the class for many views)."""
    return Renderer(objects).render(K, T_world_camera, width, height, light=light, ambient=ambient,
                                    shadows=shadows, background=background)


def intrinsics(width: int, height: int, hfov_deg: float = 60.0) -> np.ndarray:
    """Pinhole K (3, 3) with square pixels, principal point at the image centre, horizontal FOV `hfov_deg`."""
    f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
