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
               background: np.ndarray | Sequence[float] | None = None) -> RenderResult:
        """Render one view.

        K (3, 3) pinhole intrinsics; T_world_camera (4, 4) optical camera pose; light defaults to `Light()`;
        ambient and light intensity are multiplied by the albedo (clipped to 1). background: RGB colour in
        [0, 1] (3,) or an image (H, W, 3) uint8 shown where rays hit nothing; None = black.
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
            shade = ambient + light.intensity * self._direct(loc, normals, light, shadows)
            rgb[ray] = np.clip(albedo * shade[:, None], 0.0, 1.0)
        return RenderResult(rgb=(rgb.reshape(height, width, 3) * 255 + 0.5).astype(np.uint8),
                            labels=labels.reshape(height, width), depth=depth.reshape(height, width))

    def _direct(self, points: np.ndarray, normals: np.ndarray, light: Light, shadows: bool) -> np.ndarray:
        """Cosine term (N,) of the light at surface points, zero where occluded (when `shadows`)."""
        if light.position is not None:
            to_light = np.asarray(light.position, dtype=np.float64) - points
            dist = np.linalg.norm(to_light, axis=1)
            to_light /= np.maximum(dist, 1e-9)[:, None]
        else:
            to_light = np.broadcast_to(-np.asarray(light.direction, dtype=np.float64)
                                       / np.linalg.norm(light.direction), points.shape).copy()
            dist = np.full(len(points), np.inf)
        cos = np.clip(np.sum(normals * to_light, axis=1), 0.0, None)
        if shadows:
            lit = np.flatnonzero(cos > 0)
            if len(lit):
                start = points[lit] + normals[lit] * self._eps
                s_tri, s_ray, s_loc = self._ray.intersects_id(start, to_light[lit], multiple_hits=False,
                                                              return_locations=True)
                blocked = np.linalg.norm(s_loc - start[s_ray], axis=1) < dist[lit][s_ray]
                cos[lit[s_ray[blocked]]] = 0.0
        return cos

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
