"""Development data from public sources: openly licensed furniture models, placed as in their world file and
rendered along a recorded hand-held camera trajectory ("public scans rendered along real trajectories",
issue 9 item 2). Provenance, licences and the rebuild command: data/real/README.md.

What is real and what is rendered:
- camera motion: a TUM RGB-D ground-truth trajectory (hand-held Kinect, motion capture, `groundtruth.txt`:
  `timestamp tx ty tz qx qy qz qw`, T_world_camera of the optical frame, z-up world), moved rigidly into the
  furniture's world (one yaw and one horizontal shift, recorded heights kept: `place_trajectory`);
- furniture: artist-made models of real products (AWS RoboMaker small house world, COLLADA meshes) in the
  arrangement of the world file (`<model><include><uri>model://NAME</uri></include><pose>x y z r p y</pose>`);
  their visual meshes are the ground truth;
- rendered by `frodo_datasets.render` through `frodo_datasets.synth.synthesize`: images (each model's mean
  texture colour on a procedural texture), depth, instance masks (exact projections of the ground-truth meshes:
  the figures measure the pipeline given good masks) and SLAM points (simulated as in `frodo synth`).

The same sources give the held-out real-CAD split for shape priors (issue 9 item 5): `REAL_CAD_MODELS`, loaded
into the canonical object frame by `load_real_cad` and scored by `python -m frodo_shape.evaluate_prior --real-cad`.
"""
from __future__ import annotations

import argparse
import re
import sys
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from frodo_common.categories import category_by_name
from frodo_common.geometry import invert_transform, make_transform, project_points, yaw_matrix
from frodo_datasets.convert.tum import intrinsics_preset, read_trajectory
from frodo_datasets.render import Material, RenderObject
from frodo_datasets.scene import Scene, SceneObject
from frodo_datasets.synth import SynthConfig, synthesize

TUM_SIZE = (640, 480)


@dataclass(frozen=True)
class SceneSpec:
    """A group of world-file models rendered together.

    models: world-file model instance names (e.g. 'ChairA_01_001'); classes: model name prefix -> class name;
    distance: horizontal metres from the trajectory's mean camera centre to the group centre, along the mean
    viewing direction (chosen on a 0.2 m grid as the one with the largest mean `visible_fraction` over the
    trajectory; the recorded camera looks 43 degrees down at a desk about 1 m away, so a larger distance puts
    the furniture at the top edge of the images); yaw_deg: heading of the mean viewing direction in the
    furniture world;
    clutter: world-file models rendered as background (label 0, not ground truth).
    """

    models: tuple[str, ...]
    distance: float
    yaw_deg: float
    clutter: tuple[str, ...] = ()


MODEL_PREFIXES = ('aws_robomaker_residential_', 'aws_robomaker_retail_')  # small-house, bookstore models
CLASS_BY_PREFIX = {'Chair': 'chair', 'KitchenTable': 'dining table', 'BalconyTable': 'dining table',
                   'CoffeeTable': 'dining table', 'ReadingDesk': 'dining table'}

SCENES = {
    # Kitchen table with four chairs, two on each long side.
    'aws_dining': SceneSpec(('KitchenTable_01_001', 'ChairA_01_001', 'ChairA_01_002', 'ChairA_01_003',
                             'ChairA_01_004'), distance=1.8, yaw_deg=-60.0),
    # Small round balcony table between two armless chairs.
    'aws_balcony': SceneSpec(('BalconyTable_01_001', 'ChairD_01_001', 'ChairD_01_002'), distance=2.2,
                             yaw_deg=110.0),
}


# ------------------------------------------------------------------------------------------ trajectory
def read_recorded_trajectory(path: str | Path) -> tuple[np.ndarray, list[np.ndarray]]:
    """Stamps (N,) in seconds and poses T_world_camera (4, 4) of a TUM `groundtruth.txt`.

    Some copies lost the `#` of the column header ("timestamp tx ty tz qx qy qz qw"); such a line is read as
    the comment it was. Parsing is the converter's (`frodo_datasets.convert.tum.read_trajectory`).
    """
    path = Path(path)
    text = path.read_text()
    if not re.search(r'^timestamp\s', text, flags=re.M):
        return read_trajectory(path)
    with tempfile.TemporaryDirectory() as tmp:
        fixed = Path(tmp) / path.name
        fixed.write_text(re.sub(r'^timestamp\s', '# timestamp ', text, flags=re.M))
        return read_trajectory(fixed)


def sample_evenly(stamps: np.ndarray, poses: list[np.ndarray], n: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """`n` poses evenly spread over the trajectory's duration (nearest recorded pose to each instant)."""
    targets = np.linspace(stamps[0], stamps[-1], n)
    idx = np.clip(np.searchsorted(stamps, targets), 0, len(stamps) - 1)
    return stamps[idx], [poses[i] for i in idx]


def place_trajectory(poses: list[np.ndarray], centre: np.ndarray, distance: float,
                     yaw_deg: float) -> list[np.ndarray]:
    """Move a recorded trajectory rigidly into the furniture world, keeping the recorded camera heights.

    The TUM motion-capture world is gravity-aligned with z up (checked: the cameras' mean up axis must point
    along +z), so only a yaw about z and a horizontal shift are applied: the mean horizontal viewing direction
    gets heading `yaw_deg`, and the mean camera centre lands `distance` metres before `centre` (3,) along it.
    Returns the moved poses T_world_camera (4, 4); the relative motion is unchanged.
    """
    P = np.asarray(poses)
    up = -P[:, :3, 1].mean(axis=0)
    if up[2] < 0.5 * np.linalg.norm(up):
        raise ValueError(f'trajectory world is not z-up (mean camera up {np.round(up, 2).tolist()})')
    view = P[:, :3, 2].mean(axis=0)
    R = trimesh.transformations.rotation_matrix(np.radians(yaw_deg) - np.arctan2(view[1], view[0]),
                                                [0, 0, 1])[:3, :3]
    heading = np.array([np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg)), 0.0])
    mean_centre = R @ P[:, :3, 3].mean(axis=0)
    target = np.asarray(centre, dtype=np.float64) - distance * heading
    shift = np.array([target[0] - mean_centre[0], target[1] - mean_centre[1], 0.0])
    T = make_transform(R, shift)
    return [T @ p for p in P]


def tum_intrinsics(width: int, height: int) -> np.ndarray:
    """TUM fr1 colour intrinsics (3, 3) resampled to width x height (pixel centres kept aligned); the rendered
    images are ideal pinhole images, so the preset's distortion is not used."""
    sx, sy = width / TUM_SIZE[0], height / TUM_SIZE[1]
    K = intrinsics_preset('fr1')[0]
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


# ------------------------------------------------------------------------------------------ furniture
def read_world_poses(world_file: str | Path) -> dict[str, tuple[str, np.ndarray]]:
    """Gazebo world file -> {model instance name: (included model name, T_world_model (4, 4))}."""
    root = ET.parse(world_file).getroot()
    out = {}
    for model in root.iter('model'):
        uri, pose = model.find('include/uri'), model.find('pose')
        if uri is None or pose is None or uri.text is None or pose.text is None:
            continue
        x, y, z, roll, pitch, yaw = (float(v) for v in pose.text.split())
        R = trimesh.transformations.euler_matrix(roll, pitch, yaw, 'sxyz')[:3, :3]
        out[model.get('name')] = (uri.text.strip().removeprefix('model://'), make_transform(R, [x, y, z]))
    return out


def load_model(models_dir: str | Path, model: str) -> tuple[trimesh.Trimesh, tuple[float, float, float]]:
    """Visual mesh of a RoboMaker model in metres (the DAE's `<unit meter=...>`) and its mean texture colour."""
    mesh_dir = Path(models_dir) / model / 'meshes'
    files = sorted(mesh_dir.glob('*_visual.DAE')) or sorted(mesh_dir.glob('*.DAE'))
    if not files:
        raise FileNotFoundError(f'no COLLADA mesh in {mesh_dir}')
    unit = re.search(r'<unit[^>]*meter="([0-9.eE+-]+)"', files[0].read_text(errors='replace'))
    scene = trimesh.load(files[0], force='scene')  # needs pycollada
    mesh = scene.to_geometry()
    colours = []
    for geom in scene.geometry.values():
        material = getattr(geom.visual, 'material', None)
        image = getattr(material, 'image', None)
        if image is not None:
            colours.append(np.asarray(image.convert('RGB'), dtype=np.float64).reshape(-1, 3).mean(axis=0) / 255)
        elif material is not None and getattr(material, 'main_color', None) is not None:
            colours.append(np.asarray(material.main_color[:3], dtype=np.float64) / 255)
    mesh = trimesh.Trimesh(mesh.vertices * (float(unit.group(1)) if unit else 1.0), mesh.faces, process=True)
    colour = np.mean(colours, axis=0) if colours else np.array([0.6, 0.6, 0.6])
    return mesh, tuple(float(c) for c in colour)


def class_of(model: str) -> str:
    """Contract class name of a RoboMaker model name ('aws_robomaker_residential_ChairA_01' -> 'chair')."""
    short = model
    for model_prefix in MODEL_PREFIXES:
        short = short.removeprefix(model_prefix)
    for prefix, name in CLASS_BY_PREFIX.items():
        if short.startswith(prefix):
            return name
    raise KeyError(f'no class for model {model}')


def build_scene(aws_root: str | Path, spec: SceneSpec, seed: int = 0) -> Scene:
    """Furniture of `spec` posed as in the small-house world file, on a floor slab, as a `Scene`."""
    aws_root = Path(aws_root)
    world = read_world_poses(aws_root / 'worlds' / 'small_house.world')
    rng = np.random.default_rng(seed)
    objects, clutter = [], []
    for i, name in enumerate(spec.models + spec.clutter):
        if name not in world:
            raise KeyError(f'model instance {name} not in the world file')
        model, T_world_model = world[name]
        mesh, colour = load_model(aws_root / 'models', model)
        centre = mesh.bounds.mean(axis=0)
        mesh.apply_translation(-centre)  # canonical frame: origin at the bounding-box centre
        dark = tuple(0.6 * c for c in colour)
        material = Material(color=colour, kind='noise', color2=dark, scale=6.0, seed=int(rng.integers(2**31)))
        T = T_world_model @ make_transform(None, centre)
        if name in spec.clutter:
            clutter.append(RenderObject(mesh.copy().apply_transform(T), material, 0))
            continue
        class_name = class_of(model)
        objects.append(SceneObject(i + 1, class_name, category_by_name(class_name).coco_id, mesh, T, material,
                                   family=model))
    corners = np.concatenate([o.footprint for o in objects])
    lo, hi = corners.min(axis=0) - 3.0, corners.max(axis=0) + 3.0
    floor = trimesh.creation.box((*(hi - lo), 0.05))
    floor.apply_translation((*((lo + hi) / 2), -0.025))
    floor_mat = Material(color=(0.62, 0.55, 0.45), kind='wood', color2=(0.45, 0.38, 0.3), scale=3.0, seed=seed)
    room = [RenderObject(floor, floor_mat, 0)] + clutter
    return Scene(objects, room, tuple(float(v) for v in hi - lo), 'walk', seed)


def group_centre(scene: Scene) -> np.ndarray:
    """Centre (3,) of the objects' footprint box at 0.45 of the tallest object's height."""
    corners = np.concatenate([o.footprint for o in scene.objects])
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    return np.array([*(lo + hi) / 2, 0.45 * max(o.mesh.extents[2] for o in scene.objects)])


def visible_fraction(scene: Scene, poses: list[np.ndarray], K: np.ndarray, width: int, height: int,
                     samples: int = 300) -> np.ndarray:
    """Per pose (N,): the fraction of `samples` surface points per object (all objects together) that project
    inside the width x height image in front of the camera (occlusion ignored): how well a placement frames
    the furniture."""
    points = np.concatenate([trimesh.sample.sample_surface(o.mesh_world, samples, seed=o.id)[0]
                             for o in scene.objects])
    out = []
    for T in poses:
        uv, z = project_points(K, invert_transform(T), points)
        u, v = uv[:, 0] + 0.5, uv[:, 1] + 0.5  # pixel edges at integers
        inside = (z > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        out.append(inside.mean())
    return np.array(out)


# ------------------------------------------------------------------------------------------ real-CAD split
AWS_HOUSE_REPO = 'aws-robomaker-small-house-world'  # checkout folder names (scripts/fetch_real_cad.sh)
AWS_BOOKSTORE_REPO = 'aws-robomaker-bookstore-world'


@dataclass(frozen=True)
class RealCadModel:
    """A model of the held-out real-CAD split.

    repo: checkout folder under the sources folder; model: RoboMaker model name (`models/<model>/meshes/`);
    class_name: contract class; yaw_deg: rotation about z (the DAEs are z up, in metres after `load_model`) that
    brings the model into the canonical frame (chairs: front, where a seated person looks, to +x; tables: long
    side along y), checked on renders and on where the backrest lies; note: what the model is.
    """

    repo: str
    model: str
    class_name: str
    yaw_deg: float
    note: str


REAL_CAD_MODELS = (
    RealCadModel(AWS_HOUSE_REPO, 'aws_robomaker_residential_ChairA_01', 'chair', 180.0,
                 'upholstered dining chair; its backrest is at +x in the DAE'),
    RealCadModel(AWS_HOUSE_REPO, 'aws_robomaker_residential_ChairD_01', 'chair', 0.0,
                 'cantilevered one-piece (Z-shaped) chair; backrest at -x'),
    RealCadModel(AWS_BOOKSTORE_REPO, 'aws_robomaker_retail_ChairB_01', 'chair', 0.0,
                 'backless three-legged bar stool (COCO has no stool class); no front, yaw arbitrary'),
    RealCadModel(AWS_HOUSE_REPO, 'aws_robomaker_residential_KitchenTable_01', 'dining table', 0.0,
                 'rectangular dining table on two trestle leg frames; long side along y'),
    RealCadModel(AWS_HOUSE_REPO, 'aws_robomaker_residential_BalconyTable_01', 'dining table', 0.0,
                 'square pedestal side table (0.4 m high)'),
    RealCadModel(AWS_HOUSE_REPO, 'aws_robomaker_residential_CoffeeTable_01', 'dining table', 90.0,
                 'low box coffee table (top, bottom and two long side panels); long side along x in the DAE'),
    RealCadModel(AWS_HOUSE_REPO, 'aws_robomaker_residential_ReadingDesk_01', 'dining table', 0.0,
                 'writing desk on four legs with two drawer boxes; long side along y'),
)
# Looked at and left out: not a chair or table in COCO's sense.
REAL_CAD_DROPPED = {
    'aws_robomaker_retail_DeskA_01': 'shop counter: a closed 3.6 x 1.0 x 1.0 m cabinet of book cubbies under a top',
    'aws_robomaker_retail_DeskB_01': 'bar counter: a 6.0 x 0.75 m top at 1.1 m on one row of three legs',
}


def real_cad_canonical(mesh: trimesh.Trimesh, spec: RealCadModel) -> trimesh.Trimesh:
    """Copy of a loaded (z up, metric) model mesh in the canonical frame: turned by `spec.yaw_deg` about z and
    centred on its bounding box."""
    out = mesh.copy()
    out.apply_transform(make_transform(yaw_matrix(np.radians(spec.yaw_deg)), None))
    out.apply_translation(-out.bounds.mean(axis=0))
    return out


def real_cad_models(classes: list[str] | tuple[str, ...] | None = None) -> list[RealCadModel]:
    """The split's models, those of `classes` only when given (in table order)."""
    return [m for m in REAL_CAD_MODELS if classes is None or m.class_name in classes]


def load_real_cad(src: str | Path, classes: list[str] | tuple[str, ...] | None = None) -> list:
    """The real-CAD split as canonical metric `ShapeRecord`s (family 'aws_robomaker', seed -1, `source` the DAE).

    src: the folder holding the repository checkouts (`scripts/fetch_real_cad.sh`'s SRC); reading the COLLADA
    files needs pycollada (SRC/pydeps on PYTHONPATH). Meshes are repaired like user meshes
    (`shapes.user_meshes.repair`); `watertight` says whether the result is a closed volume (several are open
    shells: their inside test falls back to the winding number, `frodo_shape.sdf_data.inside`).
    """
    from frodo_datasets.shapes.library import ShapeRecord
    from frodo_datasets.shapes.user_meshes import repair
    src = Path(src)
    records = []
    for spec in real_cad_models(classes):
        models_dir = src / spec.repo / 'models'
        if not (models_dir / spec.model).is_dir():
            raise FileNotFoundError(f'{models_dir / spec.model} not found; run scripts/fetch_real_cad.sh {src}')
        mesh, _ = load_model(models_dir, spec.model)
        mesh = repair(real_cad_canonical(mesh, spec))
        mesh.apply_translation(-mesh.bounds.mean(axis=0))
        source = min((models_dir / spec.model / 'meshes').glob('*_visual.DAE'), default=None)
        records.append(ShapeRecord(name=spec.model.split('_', 3)[-1], class_name=spec.class_name,
                                   family='aws_robomaker', seed=-1, mesh=mesh, watertight=bool(mesh.is_volume),
                                   source=source))
    return records


# ------------------------------------------------------------------------------------------ bags
def build_bag(aws_root: str | Path, tum_groundtruth: str | Path, scene_name: str, frames: int,
              out_path: str | Path, width: int = 320, height: int = 240, seed: int = 0) -> Path:
    """Render `scene_name` along `frames` evenly spread poses of the TUM trajectory into a contract bag
    (with registered depth, instances, simulated SLAM points and ground-truth markers) at `out_path`."""
    spec = SCENES[scene_name]
    scene = build_scene(aws_root, spec, seed)
    stamps, poses = read_recorded_trajectory(tum_groundtruth)
    stamps, poses = sample_evenly(stamps, poses, frames)
    poses = place_trajectory(poses, group_centre(scene), spec.distance, spec.yaw_deg)
    fps = (frames - 1) / max(stamps[-1] - stamps[0], 1e-6) if frames > 1 else 1.0
    config = SynthConfig(scene='walk', objects=len(scene.objects), frames=frames, width=width, height=height,
                         seed=seed, fps=float(fps), start_ns=int(round(stamps[0] * 1e9)), depth=True)
    synthesize(config, out_path, scene=scene, poses=poses, K=tum_intrinsics(width, height))
    return Path(out_path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m frodo_datasets.real_data', description=__doc__.split('\n')[0])
    parser.add_argument('--aws', required=True, help='checkout of aws-robotics/aws-robomaker-small-house-world')
    parser.add_argument('--tum', required=True, help='TUM RGB-D groundtruth.txt (fr1/xyz)')
    parser.add_argument('--out', required=True, help='output folder for the bags')
    parser.add_argument('--scenes', default=','.join(SCENES), help=f'comma-separated, of {list(SCENES)}')
    parser.add_argument('--frames', default='35,120', help='comma-separated frame counts, one bag each')
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name in args.scenes.split(','):
        if name not in SCENES:
            print(f'unknown scene {name!r}; known: {list(SCENES)}', file=sys.stderr)
            return 2
        for n in (int(v) for v in args.frames.split(',')):
            path = build_bag(args.aws, args.tum, name, n, out / f'{name}_fr1xyz_{n}.mcap')
            print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
