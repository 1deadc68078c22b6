"""Users' own sequences: a folder of images, poses and an intrinsics YAML (e.g. the output of your SLAM system).

Layout:

    FOLDER/
      intrinsics.yaml     # fx, fy, cx, cy, width, height; optional dist: [k1, k2, p1, p2, k3], depth_scale
                          # (depth units per metre, default 1000); or a ROS camera_info YAML (camera_matrix,
                          # distortion_coefficients, image_width, image_height)
      rgb/ | color/ | images/   colour images (.png/.jpg), natural order ("2.png" before "10.png")
      depth/              optional 16-bit PNGs registered to colour, same file stems as the colour images
      instances/          optional 16-bit PNGs already in the contract encoding (coco_id * 256 + k), same stems
      poses.txt           T_world_camera of the colour optical frame (x right, y down, z forward) per frame:
                          TUM lines "timestamp tx ty tz qx qy qz qw" (matched to images whose stems are
                          timestamps with a decimal point, `1305031102.175304.png`, by nearest time within
                          max_dt; otherwise by order), or 12 (3x4, KITTI
                          style) or 16 (4x4) numbers per line, one line per image in order
      poses/              alternatively one 4x4 text file per image, same stem (`poses/000012.txt`)

`#` starts a comment line in poses.txt. Stamps come from timestamp stems, or frame index / fps.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from frodo_datasets.convert.common import (ConvertError, Source, SourceFrame, image_size, list_images, read_color,
                                           read_depth, read_matrix)
from frodo_datasets.convert.tum import nearest, read_trajectory

COLOR_DIRS = ('rgb', 'color', 'images')


def read_intrinsics(path: Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int] | None]:
    """(K (3, 3), distortion (5,), (width, height) or None) from an intrinsics YAML (see module docstring)."""
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ConvertError(f'cannot read intrinsics {path}: {err}') from None
    if not isinstance(doc, dict):
        raise ConvertError(f'{path}: expected a mapping with fx, fy, cx, cy (or a ROS camera_info YAML)')
    try:
        if 'camera_matrix' in doc:
            K = np.array(doc['camera_matrix']['data'], dtype=np.float64).reshape(3, 3)
            dist = np.array((doc.get('distortion_coefficients') or {}).get('data', [0] * 5), dtype=np.float64)
            size = (int(doc['image_width']), int(doc['image_height'])) if 'image_width' in doc else None
        else:
            K = np.array([[doc['fx'], 0, doc['cx']], [0, doc['fy'], doc['cy']], [0, 0, 1]], dtype=np.float64)
            dist = np.array(doc.get('dist', [0] * 5), dtype=np.float64)
            size = (int(doc['width']), int(doc['height'])) if 'width' in doc else None
    except (KeyError, TypeError, ValueError) as err:
        raise ConvertError(f'{path}: incomplete intrinsics ({type(err).__name__}: {err}); '
                           f'need fx, fy, cx, cy (and width, height)') from None
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ConvertError(f'{path}: fx and fy must be > 0')
    dist = np.concatenate([dist, np.zeros(5)])[:5] if dist.size <= 5 else dist
    return K, dist, size


def _stem_time(path: Path) -> float | None:
    """Seconds from a timestamp file name (`1305031102.175304.png`); frame numbers (`000012`) are not times."""
    if '.' not in path.stem:
        return None
    try:
        return float(path.stem)
    except ValueError:
        return None


def _pose_rows(path: Path) -> list[list[float]]:
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if line and not line.startswith('#'):
            try:
                rows.append([float(v) for v in line.split()])
            except ValueError:
                raise ConvertError(f'{path}:{n}: not numbers: {line!r}') from None
    return rows


def read_folder(folder: str | Path, intrinsics: str | Path | None = None, max_dt: float = 0.02,
                fps: float = 30.0, start_ns: int = 1_700_000_000_000_000_000) -> Source:
    """Read a user folder into a `Source` (see module docstring)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ConvertError(f'folder not found: {folder}')
    color_dir = next((folder / d for d in COLOR_DIRS if (folder / d).is_dir()), None)
    if color_dir is None:
        raise ConvertError(f'{folder}: no colour image folder ({", ".join(d + "/" for d in COLOR_DIRS)})')
    images = list_images(color_dir)
    if not images:
        raise ConvertError(f'{color_dir} has no .png/.jpg images')
    intr = Path(intrinsics) if intrinsics else folder / 'intrinsics.yaml'
    if not intr.is_file():
        raise ConvertError(f'missing intrinsics YAML {intr} (fx, fy, cx, cy, width, height)')
    K, dist, size = read_intrinsics(intr)
    depth_scale = float((yaml.safe_load(intr.read_text()) or {}).get('depth_scale', 1000.0))
    actual = image_size(images[0])
    if size is not None and size != actual:
        raise ConvertError(f'{intr} says {size[0]}x{size[1]} but {images[0].name} is {actual[0]}x{actual[1]}')
    times = [_stem_time(p) for p in images]
    timed = all(t is not None for t in times)
    stamps = [int(round(t * 1e9)) for t in times] if timed else \
        [start_ns + int(round(i * 1e9 / fps)) for i in range(len(images))]

    source = Source('folder', [], K, actual, dist=dist)
    poses: list[np.ndarray | None]
    if (folder / 'poses').is_dir():
        poses = []
        for p in images:
            f = folder / 'poses' / (p.stem + '.txt')
            poses.append(read_matrix(f) if f.is_file() else None)
        source.skip('no pose file', sum(p is None for p in poses))
    elif (folder / 'poses.txt').is_file():
        rows = _pose_rows(folder / 'poses.txt')
        widths = {len(r) for r in rows}
        if widths == {8}:
            p_stamps, p_list = read_trajectory(folder / 'poses.txt')
            if timed:
                poses = []
                for t in times:
                    i = nearest(p_stamps, t, max_dt)
                    poses.append(None if i is None else p_list[i])
                source.skip(f'no pose within {max_dt} s', sum(p is None for p in poses))
            elif len(p_list) == len(images):
                poses = list(p_list)
            else:
                raise ConvertError(f'mismatched counts: {len(images)} images in {color_dir.name}/ but '
                                   f'{len(p_list)} poses in poses.txt (image names are not timestamps, so they '
                                   f'are paired by order)')
        elif widths in ({12}, {16}):
            if len(rows) != len(images):
                raise ConvertError(f'mismatched counts: {len(images)} images but {len(rows)} poses in poses.txt')
            poses = [np.vstack([np.reshape(r, (-1, 4)), [0, 0, 0, 1]])[:4] for r in rows]
        else:
            raise ConvertError(f'{folder / "poses.txt"}: lines must have 8 (TUM), 12 (3x4) or 16 (4x4) numbers, '
                               f'found {sorted(widths)}')
    else:
        raise ConvertError(f'{folder}: no poses.txt and no poses/ folder')

    depth_dir, inst_dir = folder / 'depth', folder / 'instances'
    for i, (img, stamp, pose) in enumerate(zip(images, stamps, poses)):
        if pose is None:
            continue
        depth = inst = None
        if depth_dir.is_dir():
            d = depth_dir / (img.stem + '.png')
            if not d.is_file():
                source.skip('missing depth image')
                continue
            depth = (lambda p=d: read_depth(p, depth_scale))
        if inst_dir.is_dir():
            m = inst_dir / (img.stem + '.png')
            if not m.is_file():
                source.skip('missing instance image')
                continue
            inst = (lambda p=m: _read_instances(p))
        source.frames.append(SourceFrame(i, stamp, pose, lambda p=img: read_color(p), depth, inst))
    if depth_dir.is_dir():
        source.depth_size = actual
    if inst_dir.is_dir():
        source.label_size = actual
    return source


def _read_instances(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2:
        raise OSError(f'cannot read instance image {path} (expected a 16-bit single channel PNG)')
    return img.astype(np.uint16)
