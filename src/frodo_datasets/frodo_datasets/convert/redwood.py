"""Redwood sequences: Redwood-OS object scans (http://redwood-data.org/3dscan) and Redwood indoor scenes
(http://redwood-data.org/indoor), with a camera trajectory in the Redwood `.log` format.

Layout:

    SEQUENCE/
      rgb/     colour images, e.g. 0000001-000000000000.jpg (Redwood-OS: frame number - timestamp in us)
               or 00000.jpg (indoor); `image/` and `color/` are accepted too
      depth/   16-bit PNG depth in mm registered to colour, same frame numbers
      *.log    trajectory (or `trajectory=`): per frame a line of three ids "i j n" then 4 lines of the
               4x4 camera-to-world T (p_world = T p_camera, optical frame); n is the frame number,
               1-based (0-based when the file has a frame 0), matched to the image with that frame number
               (image numbers likewise 0- or 1-based: the Open3D/Redwood "i i i+1" log of images 00000.jpg ...
               and Redwood-OS 0000001-....jpg both match)

Colour and depth are paired by frame number (the first integer of the name); frames without depth, without
a trajectory entry or without an image are skipped and counted. Intrinsics: the PrimeSense default
(fx = fy = 525, principal point 319.5, 239.5, for 640x480) unless an intrinsics YAML is given. Optional
ground truth: `mesh` (a mesh file in the trajectory's world, e.g. a Redwood-OS reconstruction cropped to the
object) written as one object of class `mesh_class`. The world is not gravity aligned in general: the
writer's default floor fit makes it z up.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from frodo_common.categories import category_by_name
from frodo_datasets.convert.common import (ConvertError, GroundTruthObject, Source, SourceFrame, image_size,
                                           leading_int, list_images, read_color, read_depth)

PRIMESENSE = (525.0, 525.0, 319.5, 239.5)
PRIMESENSE_SIZE = (640, 480)
COLOR_DIRS = ('rgb', 'image', 'color')


def read_log(path: Path) -> list[tuple[tuple[int, int, int], np.ndarray]]:
    """Entries ((id, id, frame), T (4, 4)) of a Redwood `.log` trajectory."""
    if not path.is_file():
        raise ConvertError(f'trajectory not found: {path}')
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    if len(lines) % 5:
        raise ConvertError(f'{path}: {len(lines)} non-empty lines; a .log has 5 lines per frame (3 ids + 4x4)')
    out = []
    for i in range(0, len(lines), 5):
        try:
            ids = tuple(int(v) for v in lines[i])
            T = np.array([[float(v) for v in row] for row in lines[i + 1:i + 5]])
        except ValueError:
            raise ConvertError(f'{path}:{i + 1}: expected 3 integers then a 4x4 matrix') from None
        if len(ids) != 3 or T.shape != (4, 4):
            raise ConvertError(f'{path}:{i + 1}: expected 3 integers then a 4x4 matrix')
        out.append((ids, T))
    return out


def _stamp_us(path: Path) -> int | None:
    """Timestamp from a Redwood-OS name `0000001-000000033333.jpg` (microseconds), else None."""
    parts = path.stem.split('-')
    return int(parts[1]) if len(parts) == 2 and parts[1].isdigit() else None


def read_redwood(folder: str | Path, trajectory: str | Path | None = None, intrinsics: str | Path | None = None,
                 mesh: str | Path | None = None, mesh_class: str | None = None, depth_factor: float = 1000.0,
                 fps: float = 30.0, start_ns: int = 1_700_000_000_000_000_000) -> Source:
    """Read a Redwood sequence folder into a `Source` (see module docstring)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ConvertError(f'Redwood sequence folder not found: {folder}')
    color_dir = next((folder / d for d in COLOR_DIRS if (folder / d).is_dir()), None)
    if color_dir is None or not (folder / 'depth').is_dir():
        raise ConvertError(f'{folder} is not a Redwood sequence: expected rgb/ (or image/) and depth/ folders')
    if trajectory is None:
        logs = sorted(folder.glob('*.log'))
        if len(logs) != 1:
            raise ConvertError(f'{folder}: found {len(logs)} .log files; give the trajectory (--trajectory)')
        trajectory = logs[0]
    entries = read_log(Path(trajectory))
    colors = list_images(color_dir)
    depths = {leading_int(p): p for p in list_images(folder / 'depth')}
    if not colors:
        raise ConvertError(f'{color_dir} has no images')
    numbers = [leading_int(p) for p in colors]
    if None in numbers or len(set(numbers)) != len(numbers):
        raise ConvertError(f'{color_dir}: image names must carry distinct frame numbers')
    # Frame numbers count from 0 when any id is 0, else from 1, in the trajectory and in the image names alike;
    # trajectory frame n is the image numbered n - log_base + image_base (gaps in either stay gaps).
    log_base = 0 if min(ids[2] for ids, _ in entries) == 0 else 1
    image_base = 0 if min(numbers) == 0 else 1
    by_number = {leading_int(p): p for p in colors}
    first_number = min(numbers)
    if intrinsics is not None:
        from frodo_datasets.convert.folder import read_intrinsics
        K, dist, size = read_intrinsics(Path(intrinsics))
    else:
        fx, fy, cx, cy = PRIMESENSE
        K, dist, size = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), None, PRIMESENSE_SIZE
    actual = image_size(colors[0])
    if size is not None and actual != tuple(size):
        raise ConvertError(f'images are {actual[0]}x{actual[1]} but the intrinsics are for {size[0]}x{size[1]}'
                           f'{"" if intrinsics else " (PrimeSense default)"}; give an intrinsics YAML')
    source = Source('redwood', [], K, actual, dist=dist, depth_size=actual)
    stamps_us = {leading_int(p): _stamp_us(p) for p in colors}
    ordered = [stamps_us[n] for n in sorted(stamps_us)]
    timed = None not in ordered and all(b > a for a, b in zip(ordered, ordered[1:]))
    posed = set()
    for ids, T in entries:
        number = ids[2] - log_base + image_base
        img = by_number.get(number)
        if img is None:
            source.skip('trajectory entry without a colour image')
            continue
        posed.add(number)
        d = depths.get(number)
        if d is None:
            source.skip('missing depth image')
            continue
        stamp = start_ns + ((stamps_us[number] - ordered[0]) * 1000 if timed
                            else int(round((number - first_number) * 1e9 / fps)))
        source.frames.append(SourceFrame(number, stamp, T, lambda p=img: read_color(p),
                                         lambda p=d: read_depth(p, depth_factor)))
    source.skip('colour image without a trajectory entry', len(by_number) - len(posed))
    if not source.frames:
        raise ConvertError(f'mismatched counts: {len(colors)} colour images, {len(depths)} depth images and '
                           f'{len(entries)} trajectory entries share no frame')
    source.frames.sort(key=lambda f: f.stamp_ns)
    origin = f'from {intrinsics}' if intrinsics else 'PrimeSense default'
    source.notes.append(f'{len(entries)} trajectory entries for {len(colors)} colour images (frame numbers '
                        f'{log_base}-based, images {image_base}-based); intrinsics {origin}')
    if mesh is not None:
        import trimesh
        name = mesh_class or 'chair'
        try:
            category_by_name(name)
        except KeyError as err:
            raise ConvertError(str(err)) from None
        try:
            m = trimesh.load(mesh, force='mesh')
        except Exception as err:  # noqa: BLE001 - trimesh raises many types for bad files
            raise ConvertError(f'cannot read mesh {mesh}: {err}') from None
        source.ground_truth = [GroundTruthObject(name, 1, np.asarray(m.vertices, float), np.asarray(m.faces))]
    return source
