"""TUM RGB-D sequences (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats).

Layout (as downloaded and extracted, e.g. `rgbd_dataset_freiburg1_xyz/`):

    rgb.txt            # "timestamp filename" per line, e.g. "1305031102.175304 rgb/1305031102.175304.png"
    depth.txt          # same for depth/
    groundtruth.txt    # "timestamp tx ty tz qx qy qz qw": the colour camera's optical centre in the mocap world
    rgb/*.png          # 640x480 colour
    depth/*.png        # 16-bit, 5000 units per metre, registered to colour; 0 = no measurement

Lines starting with `#` are comments. Every colour image is paired with the nearest depth image and the
nearest ground-truth pose, each within `max_dt` seconds (0.02 s like TUM's associate.py); colour frames
without a partner are skipped and counted. Intrinsics presets from the TUM page: `fr1`, `fr2`, `fr3`
(fr1/fr2 with their plumb_bob distortion; the writer undistorts colour and depth to the same K) and `ros`
(the default 525, 525, 319.5, 239.5 the TUM ROS bags use), or a YAML file (see `folder.read_intrinsics`).
The preset is guessed from the folder name (`freiburg1` -> fr1, ...) unless given. The mocap world is not
gravity aligned in general: the writer's default floor fit makes it z up.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from frodo_common.geometry import make_transform, quat_to_matrix
from frodo_datasets.convert.common import ConvertError, Source, SourceFrame, read_color, read_depth

DEPTH_FACTOR = 5000.0
# (fx, fy, cx, cy, (k1, k2, p1, p2, k3)) of the colour cameras, from the TUM "File Formats" page.
INTRINSICS = {
    'fr1': (517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    'fr2': (520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    'fr3': (535.4, 539.2, 320.1, 247.6, (0.0, 0.0, 0.0, 0.0, 0.0)),
    'ros': (525.0, 525.0, 319.5, 239.5, (0.0, 0.0, 0.0, 0.0, 0.0)),
}
IMAGE_SIZE = (640, 480)


def read_list(path: Path, columns: int) -> list[list[str]]:
    """Non-comment, non-empty lines of a TUM text file split on whitespace; checks the column count."""
    if not path.is_file():
        raise ConvertError(f'missing {path.name} in {path.parent} (a TUM RGB-D sequence has rgb.txt, depth.txt '
                           f'and groundtruth.txt)')
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith('#'):
            continue
        parts = line.split()
        if len(parts) < columns:
            raise ConvertError(f'{path}:{n}: expected {columns} columns, got {line!r}')
        rows.append(parts)
    return rows


def read_trajectory(path: Path) -> tuple[np.ndarray, list[np.ndarray]]:
    """TUM trajectory lines -> (stamps (N,) seconds sorted, T_world_camera (4, 4) each)."""
    rows = read_list(path, 8)
    try:
        values = np.array([[float(v) for v in r[:8]] for r in rows])
    except ValueError as err:
        raise ConvertError(f'{path}: {err}') from None
    values = values[np.argsort(values[:, 0], kind='stable')]
    poses = []
    for v in values:
        q = v[4:8]
        norm = np.linalg.norm(q)
        poses.append(make_transform(quat_to_matrix(q / norm), v[1:4]) if np.isfinite(norm) and norm > 1e-9
                     else np.full((4, 4), np.nan))
    return values[:, 0], poses


def nearest(stamps: np.ndarray, t: float, max_dt: float) -> int | None:
    """Index of the sorted `stamps` entry nearest to t, or None when farther than max_dt."""
    if not len(stamps):
        return None
    i = int(np.searchsorted(stamps, t))
    best = min((j for j in (i - 1, i) if 0 <= j < len(stamps)), key=lambda j: abs(stamps[j] - t))
    return best if abs(stamps[best] - t) <= max_dt else None


def intrinsics_preset(name: str) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), distortion (5,)) of a preset name."""
    if name not in INTRINSICS:
        raise ConvertError(f'unknown TUM intrinsics preset {name!r}; use one of {sorted(INTRINSICS)} or a YAML file')
    fx, fy, cx, cy, dist = INTRINSICS[name]
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), np.array(dist)


def guess_preset(folder: Path) -> str:
    """fr1/fr2/fr3 from a TUM folder name (`rgbd_dataset_freiburg2_desk` -> fr2), else 'ros'."""
    name = folder.resolve().name.lower()
    for k in ('1', '2', '3'):
        if f'freiburg{k}' in name or f'fr{k}' in name:
            return f'fr{k}'
    return 'ros'


def read_tum(folder: str | Path, intrinsics: str | None = None, max_dt: float = 0.02,
             depth_factor: float = DEPTH_FACTOR, trajectory: str = 'groundtruth.txt',
             pair_by_order: bool = False) -> Source:
    """Read a TUM RGB-D sequence folder into a `Source` (see module docstring).

    intrinsics: preset name, a YAML file path, or None (guessed from the folder name);
    trajectory: the pose file inside the folder (or a path), e.g. your SLAM output in TUM format;
    pair_by_order: line i of rgb.txt goes with line i of depth.txt and of the trajectory, whose stamps are used
    (keyframe extracts whose lists are numbered 0, 1, ... instead of stamped, e.g. a fr3/cabinet keyframe set).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ConvertError(f'TUM sequence folder not found: {folder}')
    rgb = read_list(folder / 'rgb.txt', 2)
    depth_path = folder / 'depth.txt'
    depth = read_list(depth_path, 2) if depth_path.exists() else []
    traj_path = Path(trajectory) if Path(trajectory).is_absolute() else folder / trajectory
    pose_stamps, poses = read_trajectory(traj_path)
    if intrinsics is not None and Path(intrinsics).suffix.lower() in ('.yaml', '.yml'):
        from frodo_datasets.convert.folder import read_intrinsics
        K, dist, size = read_intrinsics(Path(intrinsics))
        preset = str(intrinsics)
    else:
        preset = intrinsics or guess_preset(folder)
        K, dist = intrinsics_preset(preset)
        size = IMAGE_SIZE
    try:
        d_stamps = np.array([float(r[0]) for r in depth])
        c_stamps = [float(r[0]) for r in rgb]
    except ValueError as err:
        raise ConvertError(f'bad timestamp in rgb.txt/depth.txt of {folder}: {err}') from None
    if pair_by_order:
        if len(pose_stamps) != len(rgb) or (depth and len(depth) != len(rgb)):
            raise ConvertError(f'{folder}: pairing by order needs as many poses ({len(pose_stamps)}) and depth '
                               f'images ({len(depth)}) as colour images ({len(rgb)})')
        c_stamps = list(pose_stamps)
        d_stamps = np.array(c_stamps) if depth else d_stamps
    d_order = np.argsort(d_stamps, kind='stable')
    d_sorted = d_stamps[d_order]
    source = Source('tum', [], K, size or IMAGE_SIZE, dist=dist)
    source.notes.append(f'intrinsics {preset}: fx {K[0, 0]} fy {K[1, 1]} cx {K[0, 2]} cy {K[1, 2]}')
    for n, (t, row) in enumerate(sorted(zip(c_stamps, rgb), key=lambda x: x[0])):
        ip = nearest(pose_stamps, t, max_dt)
        if ip is None:
            source.skip(f'no ground-truth pose within {max_dt} s')
            continue
        depth_loader = None
        if depth:
            idd = nearest(d_sorted, t, max_dt)
            if idd is None:
                source.skip(f'no depth image within {max_dt} s')
                continue
            d_file = folder / depth[d_order[idd]][1]
            depth_loader = (lambda p=d_file: read_depth(p, depth_factor))
        c_file = folder / row[1]
        source.frames.append(SourceFrame(n, int(round(t * 1e9)), poses[ip], lambda p=c_file: read_color(p),
                                         depth_loader))
    if not source.frames:
        raise ConvertError(f'no colour image of {folder} has a pose (and depth) within {max_dt} s; '
                           f'skipped: {source.skipped}')
    first = source.frames[0].color()
    actual = (first.shape[1], first.shape[0])
    size = size or actual
    if actual != size:
        raise ConvertError(f'the images are {actual[0]}x{actual[1]} but the intrinsics {preset} are for '
                           f'{size[0]}x{size[1]}; give an intrinsics YAML')
    source.color_size = size
    source.depth_size = size if depth else None
    return source
