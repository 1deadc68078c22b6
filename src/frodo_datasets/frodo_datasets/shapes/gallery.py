"""Gallery figure of the procedural shape families (headless matplotlib, Agg canvas, no pyplot state).

Each panel is a flat-shaded orthographic ray-cast view (embree) of one canonical mesh from the
front-right and above, so the front (+x) of every shape faces the viewer.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from trimesh.ray.ray_pyembree import RayMeshIntersector

from .library import eval_families, extra_families, families, generate

VIEW_AZIMUTH_DEG = -35.0  # camera azimuth about z, measured from +x (negative: on the -y side, the right)
VIEW_ELEVATION_DEG = 20.0
LIGHT_DIRECTION = np.array([0.6, -0.3, 0.75]) / np.linalg.norm([0.6, -0.3, 0.75])  # towards the light
CLASS_COLOURS = {'chair': np.array([0.80, 0.55, 0.30]), 'dining table': np.array([0.45, 0.60, 0.80])}
SHAPES_PER_FAMILY = 3
COLUMNS = 6
PANEL_PIXELS = 256


def view_axes(azimuth_deg: float = VIEW_AZIMUTH_DEG, elevation_deg: float = VIEW_ELEVATION_DEG) -> np.ndarray:
    """Rows (3, 3): screen right, screen up, and the direction towards the camera, in the object frame."""
    azimuth, elevation = np.radians(azimuth_deg), np.radians(elevation_deg)
    towards_camera = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    right = np.cross([0.0, 0.0, 1.0], towards_camera)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(towards_camera, right), towards_camera])


def render_mesh(mesh: trimesh.Trimesh, colour: np.ndarray, pixels: int = PANEL_PIXELS) -> np.ndarray:
    """Orthographic ray-cast image (pixels, pixels, 3) float RGB in [0, 1] of `mesh` seen along
    `view_axes()`, Lambert-shaded `colour` (3,) on a white background; the mesh fills the frame."""
    view = view_axes()
    screen = mesh.vertices @ view.T  # (V, 3): right, up, depth towards the camera
    low, high = screen[:, :2].min(axis=0), screen[:, :2].max(axis=0)
    half_size = 0.55 * float((high - low).max())
    offsets = np.linspace(-half_size, half_size, pixels)
    right, up = np.meshgrid(offsets, offsets[::-1])  # image row 0 at the top
    centre = (low + high) / 2
    camera_distance = float(np.abs(screen[:, 2]).max()) + 1.0
    origins = ((centre[0] + right.ravel())[:, None] * view[0] + (centre[1] + up.ravel())[:, None] * view[1]
               + camera_distance * view[2])
    directions = np.broadcast_to(-view[2], origins.shape)
    hit_faces = RayMeshIntersector(mesh).intersects_first(origins, directions)  # (pixels^2,), -1 for a miss
    hit = hit_faces >= 0
    image = np.ones((pixels * pixels, 3))
    normals = mesh.face_normals[hit_faces[hit]]
    brightness = 0.35 + 0.65 * np.clip(normals @ LIGHT_DIRECTION, 0.0, 1.0)
    image[hit] = np.clip(brightness[:, None] * colour[None, :], 0.0, 1.0)
    return image.reshape(pixels, pixels, 3)


def save_gallery(path: str | Path, seed: int = 0, shapes_per_family: int = SHAPES_PER_FAMILY,
                 heldout: bool = False, extra: bool = False) -> Path:
    """Render `shapes_per_family` shapes (seeds `seed`, `seed + 1`, ...) of every family of both classes
    into a grid figure at `path` (PNG); panel titles give family, seed and bounding-box extents
    (x depth, y width, z height) in metres. heldout: the evaluation-only families (`eval_families`)
    instead of the training families; extra: the extra training families of the broader prior
    (`extra_families`). Returns the path written."""
    listed = eval_families if heldout else extra_families if extra else families
    entries = [(class_name, family, seed + index) for class_name in CLASS_COLOURS for family in listed(class_name)
               for index in range(shapes_per_family)]
    rows = -(-len(entries) // COLUMNS)
    figure = Figure(figsize=(2.6 * COLUMNS, 2.7 * rows), dpi=110)
    FigureCanvasAgg(figure)
    for panel, (class_name, family, shape_seed) in enumerate(entries):
        mesh = generate(class_name, shape_seed, family)
        axes = figure.add_subplot(rows, COLUMNS, panel + 1)
        axes.imshow(render_mesh(mesh, CLASS_COLOURS[class_name]))
        axes.axis('off')
        depth, width, height = mesh.extents
        axes.set_title(f'{class_name}: {family} #{shape_seed}\n{depth:.2f} x {width:.2f} x {height:.2f} m', fontsize=8)
    figure.tight_layout()
    output = Path(path)
    output.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(output)
    return output
