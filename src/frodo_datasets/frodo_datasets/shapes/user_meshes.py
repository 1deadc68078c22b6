"""Load user meshes (ShapeNetCore v2 or a plain folder of mesh files) into the canonical object frame.

Accepted layouts under `root`:
  (a) ShapeNetCore v2: `root/<synset>/<model>/models/model_normalized.obj` (or `root` itself a synset
      folder `<synset>/<model>/models/model_normalized.obj`); the synset gives the COCO class
      (03001627 chair, 04379243 dining table, 04256520 couch, 02818832 bed; other synsets are skipped).
      ShapeNet is y up with the front facing -z, the defaults of `up_axis` / `front_axis`.
  (b) a plain folder of mesh files (.obj .ply .stl .off .glb .gltf): files directly in `root` take the
      class `class_name`; a subfolder per class (searched recursively) takes its folder name as the class
      ('chair', 'dining_table'; 'table' means 'dining table').

Each mesh is rotated so that `up_axis` becomes +z and `front_axis` becomes +x, optionally rescaled so its
height is `target_height` metres (for unit-normalised sources such as ShapeNet), centred on its bounding
box, and repaired (merge duplicate vertices, drop degenerate and duplicate faces, fill small holes, fix
winding and orientation). A mesh that is still not a closed volume is kept with `watertight=False` and a
warning, unless `remesh_resolution` is given: then it is rebuilt as the marching-cubes surface of its
filled voxelisation (always watertight), which is what SDF sampling needs.
"""
from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np
import trimesh

from .canonical import axes_to_canonical, centre_on_bbox
from .library import ShapeRecord

MESH_SUFFIXES = ('.obj', '.ply', '.stl', '.off', '.glb', '.gltf')
SHAPENET_MODEL_FILE = Path('models') / 'model_normalized.obj'
SHAPENET_SYNSETS = {'03001627': 'chair', '04379243': 'dining table', '04256520': 'couch', '02818832': 'bed'}
CLASS_ALIASES = {'table': 'dining table', 'tables': 'dining table', 'chairs': 'chair', 'sofa': 'couch'}
EXPECTED_LAYOUTS = ('a ShapeNetCore v2 folder (root/<synset>/<model>/models/model_normalized.obj) or a folder of '
                    f'mesh files ({" ".join(MESH_SUFFIXES)}), directly or in one subfolder per class')
SYNSET_PATTERN = re.compile(r'^\d{8}$')
TAUBIN_ITERATIONS = 10  # smoothing of the voxel staircase after remeshing


@dataclass(frozen=True)
class MeshSource:
    """A mesh file to load: record name, COCO class, family ('shapenet' or 'user') and path."""
    name: str
    class_name: str
    family: str
    path: Path


def canonical_class_name(name: str) -> str:
    """COCO class name from a folder name, a class name or a ShapeNet synset id ('dining_table',
    'Table', '04379243' -> 'dining table')."""
    if name in SHAPENET_SYNSETS:
        return SHAPENET_SYNSETS[name]
    spaced = re.sub(r'[_\-]+', ' ', name.strip().lower())
    return CLASS_ALIASES.get(spaced, spaced)


def shapenet_sources(root: Path) -> list[MeshSource]:
    """ShapeNetCore v2 models under `root` (a ShapeNetCore root or one synset folder), sorted by path;
    synsets without a COCO class are skipped with a warning."""
    if SYNSET_PATTERN.match(root.name) and any(root.glob(f'*/{SHAPENET_MODEL_FILE.as_posix()}')):
        model_files = sorted(root.glob(f'*/{SHAPENET_MODEL_FILE.as_posix()}'))
    else:
        model_files = sorted(root.glob(f'*/*/{SHAPENET_MODEL_FILE.as_posix()}'))
    sources, unknown_synsets = [], set()
    for path in model_files:
        model_folder = path.parent.parent
        synset = model_folder.parent.name
        if synset not in SHAPENET_SYNSETS:
            unknown_synsets.add(synset)
            continue
        sources.append(MeshSource(f'shapenet-{synset}-{model_folder.name}', SHAPENET_SYNSETS[synset], 'shapenet', path))
    if unknown_synsets:
        warnings.warn(f'skipping ShapeNet synsets without a COCO class: {sorted(unknown_synsets)} '
                      f'(known: {SHAPENET_SYNSETS})', RuntimeWarning, stacklevel=3)
    return sources


def plain_folder_sources(root: Path, class_name: str | None) -> list[MeshSource]:
    """Mesh files directly in `root` (class `class_name`) and in class subfolders (class from the folder
    name, files found recursively), sorted by path."""
    def is_mesh(path: Path) -> bool:
        return path.is_file() and path.suffix.lower() in MESH_SUFFIXES

    top_level = sorted(p for p in root.iterdir() if is_mesh(p))
    if top_level and class_name is None:
        raise ValueError(f'{root} holds mesh files directly; pass class_name for them, or put them in one '
                         'subfolder per class (e.g. chair/, dining_table/)')
    sources = [MeshSource(p.stem, class_name, 'user', p) for p in top_level]
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        folder_class = canonical_class_name(folder.name)
        sources += [MeshSource(p.relative_to(root).with_suffix('').as_posix(), folder_class, 'user', p)
                    for p in sorted(folder.rglob('*')) if is_mesh(p)]
    return sources


def load_mesh_file(path: Path) -> trimesh.Trimesh:
    """One triangle mesh from a mesh file (scenes are flattened with their node transforms; materials
    and textures are not loaded)."""
    mesh = trimesh.load(path, force='mesh', skip_materials=True)
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError('no triangles')
    return trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, process=True)


def repair(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Cleaned copy of `mesh`: merged duplicate vertices, no degenerate or duplicate faces, small holes
    filled, consistent outward winding where the surface allows it."""
    repaired = mesh.copy()
    repaired.merge_vertices(merge_tex=True, merge_norm=True)
    repaired.update_faces(repaired.nondegenerate_faces())
    repaired.update_faces(repaired.unique_faces())
    repaired.remove_unreferenced_vertices()
    trimesh.repair.fill_holes(repaired)
    trimesh.repair.fix_normals(repaired)
    return repaired


def voxel_remesh(mesh: trimesh.Trimesh, resolution: int) -> trimesh.Trimesh:
    """Watertight surface of the filled voxelisation of `mesh` with `resolution` voxels along its
    largest extent (marching cubes, Taubin smoothing, which keeps the topology, then an axis-wise affine
    fit onto the source bounding box, undoing the half-voxel growth). Open surfaces whose holes are
    larger than a voxel cannot be filled and come back as thin closed shells."""
    pitch = float(mesh.extents.max()) / resolution
    grid = mesh.voxelized(pitch).fill()
    surface = grid.marching_cubes
    surface.apply_transform(grid.transform)
    trimesh.smoothing.filter_taubin(surface, iterations=TAUBIN_ITERATIONS)
    fit = np.eye(4)
    fit[:3, :3] = np.diag(mesh.extents / surface.extents)
    fit[:3, 3] = mesh.bounds[0] - surface.bounds[0] * np.diag(fit)[:3]
    surface.apply_transform(fit)
    trimesh.repair.fix_normals(surface)
    return surface


def height_for(class_name: str, target_height: float | Mapping[str, float] | None) -> float | None:
    """Target height of a class: a single value for all classes, a per-class mapping, or None."""
    if isinstance(target_height, Mapping):
        return target_height.get(class_name)
    return target_height


def load_user_meshes(root: str | Path, class_name: str | None = None, up_axis: str = 'y', front_axis: str = '-z',
                     target_height: float | Mapping[str, float] | None = None,
                     remesh_resolution: int | None = None) -> list[ShapeRecord]:
    """Load meshes under `root` (ShapeNetCore v2 layout, or a plain folder) as canonical ShapeRecords.

    Args:
        root: ShapeNetCore v2 root (or one synset folder), or a folder of mesh files (see module docs).
        class_name: keep only this class ('chair', 'dining table', aliases, or a synset id); required
            for mesh files directly in a plain `root`, which all get this class.
        up_axis, front_axis: the source's up and front directions ('x', 'y', 'z', optionally signed);
            the defaults are ShapeNet's (y up, front -z).
        target_height: rescale each mesh uniformly so that its height (z extent) is this many metres;
            one value, or a mapping class name -> height (classes missing from it keep their scale).
        remesh_resolution: voxels along the largest extent for rebuilding meshes that repair leaves
            open; None keeps them as they are, flagged `watertight=False`.

    Returns:
        One ShapeRecord per loaded mesh (family 'shapenet' or 'user', seed -1, `source` the file).

    Raises:
        FileNotFoundError: `root` is not a folder, or holds no mesh of the expected layouts and class.
        ValueError: bad axis names, or mesh files directly in a plain `root` without `class_name`.
    """
    root = Path(root).expanduser()
    if not root.is_dir():
        raise FileNotFoundError(f'{root} is not a folder; expected {EXPECTED_LAYOUTS}')
    rotation = np.eye(4)
    rotation[:3, :3] = axes_to_canonical(up_axis, front_axis)
    wanted_class = canonical_class_name(class_name) if class_name is not None else None
    sources = shapenet_sources(root) or plain_folder_sources(root, wanted_class)
    if wanted_class is not None:
        sources = [source for source in sources if source.class_name == wanted_class]
    if not sources:
        class_note = f' of class {wanted_class!r}' if wanted_class is not None else ''
        raise FileNotFoundError(f'no meshes{class_note} found under {root}; expected {EXPECTED_LAYOUTS}')

    records = []
    for source in sources:
        try:
            mesh = load_mesh_file(source.path)
        except Exception as error:  # any unreadable file is skipped, the rest still load
            warnings.warn(f'skipping {source.path}: cannot load a triangle mesh ({error})', RuntimeWarning, stacklevel=2)
            continue
        mesh.apply_transform(rotation)
        height = height_for(source.class_name, target_height)
        if height is not None:
            mesh.apply_scale(height / float(mesh.extents[2]))
        mesh = repair(mesh)
        if not mesh.is_volume and remesh_resolution is not None:
            mesh = voxel_remesh(mesh, remesh_resolution)
        if not mesh.is_volume:
            warnings.warn(f'{source.path} is not watertight after repair; kept with watertight=False',
                          RuntimeWarning, stacklevel=2)
        records.append(ShapeRecord(name=source.name, class_name=source.class_name, family=source.family, seed=-1,
                                   mesh=centre_on_bbox(mesh), watertight=bool(mesh.is_volume), source=source.path))
    return records
