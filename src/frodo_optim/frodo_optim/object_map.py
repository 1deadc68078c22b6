"""The optimiser's object map on disk: save it at any time, load it at start (issue 12, "Faults": a restarted
optimiser does not start from nothing). No rclpy here; `optim_node` calls it.

A map directory holds `objects.json` and `meshes/<id>_<class>.ply` (world frame) in the layout `frodo run
--out` writes, so `frodo eval --pred MAP_DIR` reads it too. Each record carries what the run's
objects.json has (id, class, 4x4 object-to-world pose, scale, box, shape code, views, stage, stage reason,
timings, mesh) plus what the optimiser needs to continue: the COCO category, the shape node's fused code
and view count the estimate was made from (`fused_code`, `fused_views`), the association's box
(`track`) and the estimate's data time (`stamp_ns`: the newest frame stamp it used; optional, 0 when absent). The objects.json of a `frodo run --out` folder loads as well (category from the class name, no
fused code or track), so a run can go on from another run's output. With several optimiser workers each
writes its own map in `DIR/worker_<k>/`; loading reads
`DIR` and every `DIR/worker_*/`, keeping the objects the loading worker owns, so a map can be resumed with
another number of workers.

Writes are atomic against a killed process (temporary file + rename; meshes first, then the JSON that
names them), not against power loss (no fsync). A truncated or corrupt map raises `ObjectMapError` with
the path and the reason; a bad record or mesh skips that object with a message (`load_map` problems).
"""
from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
import trimesh

from frodo_common.categories import category_by_id, category_by_name
from frodo_common.geometry import Box3D
from frodo_optim.core import ObjectEstimate
from frodo_optim.states import STAGE_REASONS, STAGES

MAP_FILE = 'objects.json'
MESH_DIR = 'meshes'
FORMAT = 'frodo_object_map'
VERSION = 1
WORKER_DIR = re.compile(r'worker_(\d+)')


class ObjectMapError(RuntimeError):
    """A map file that cannot be read (missing, truncated, not JSON, another format)."""


@dataclass
class MapObject:
    """One saved object: the optimiser's estimate and the inputs it was made from.

    fused_code (D,) / fused_views / category: the shape node's fused code table row (None when unknown).
    track: (class name, `Box3D`) of the association's box (None when unknown).
    """

    estimate: ObjectEstimate
    fused_code: np.ndarray | None = None
    fused_views: int = 0
    track: tuple[str, Box3D] | None = None


def worker_map_dir(root: str | os.PathLike, index: int, count: int) -> Path:
    """Where worker `index` of `count` writes its map: `root` itself for one worker, else `root/worker_<index>`."""
    return Path(root) if count <= 1 else Path(root) / f'worker_{index}'


def _file_stem(object_id: int, class_name: str) -> str:
    return f'{object_id}_{re.sub(r"[^A-Za-z0-9]+", "_", class_name).strip("_") or "object"}'


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f'.{path.name}.tmp')
    with open(tmp, 'wb') as f:
        f.write(data)
    os.replace(tmp, path)


def _floats(values) -> list[float]:
    return [float(v) for v in np.asarray(values, dtype=np.float64).ravel()]


def _record(obj: MapObject, mesh_file: str) -> dict[str, Any]:
    est = obj.estimate
    center, size, yaw = est.box
    known = category_by_id(int(est.category))
    record = {
        'id': int(est.object_id), 'class': est.class_name or (known.name if known else ''),
        'category': int(est.category),
        'pose': np.asarray(est.T_world_object, dtype=float).reshape(4, 4).tolist(), 'scale': float(est.scale),
        'box': {'center': _floats(center), 'size': _floats(size), 'yaw': float(yaw)},
        'code': _floats(est.code), 'num_views': int(est.num_views), 'stage': est.stage,
        'stage_reason': STAGE_REASONS[est.stage_reason] if 0 <= est.stage_reason < len(STAGE_REASONS) else None,
        'timings': {k: float(v) for k, v in est.timings.items()},
        'stamp_ns': int(est.stamp_ns),
        'mesh': mesh_file, 'mesh_faces': int(len(est.mesh_world.faces)),
        'fused_code': _floats(obj.fused_code) if obj.fused_code is not None else None,
        'fused_views': int(obj.fused_views),
        'track': None,
    }
    if obj.track is not None:
        ns, (t_center, t_size, t_yaw) = obj.track
        record['track'] = {'class': ns, 'center': _floats(t_center), 'size': _floats(t_size), 'yaw': float(t_yaw)}
    return record


class MapWriter:
    """Writes one map directory, re-writing only the meshes that changed since the last save.

    A mesh counts as changed when the estimate holds another mesh object than at the last save (the
    optimiser makes a new estimate, with a new mesh, for every stage it publishes).
    """

    def __init__(self, directory: str | os.PathLike, worker: tuple[int, int] = (0, 1)):
        self.directory = Path(directory)
        self.worker = worker
        self._written: dict[int, tuple[trimesh.Trimesh, str]] = {}   # id -> (mesh saved, its relative path)

    def save(self, objects: Iterable[MapObject], frame_id: str = 'world') -> Path:
        """Write every object (meshes first, then objects.json naming them); returns the objects.json path."""
        (self.directory / MESH_DIR).mkdir(parents=True, exist_ok=True)
        records = []
        current: dict[int, tuple[trimesh.Trimesh, str]] = {}
        for obj in sorted(objects, key=lambda o: o.estimate.object_id):
            est = obj.estimate
            relative = f'{MESH_DIR}/{_file_stem(est.object_id, est.class_name)}.ply'
            previous = self._written.get(est.object_id)
            if previous is None or previous[0] is not est.mesh_world or previous[1] != relative:
                _write_atomic(self.directory / relative, trimesh.exchange.ply.export_ply(est.mesh_world))
            current[est.object_id] = (est.mesh_world, relative)
            records.append(_record(obj, relative))
        document = {'format': FORMAT, 'version': VERSION, 'frame_id': frame_id,
                    'worker': {'index': int(self.worker[0]), 'count': int(self.worker[1])}, 'objects': records}
        path = self.directory / MAP_FILE
        _write_atomic(path, (json.dumps(document, indent=1) + '\n').encode())
        for oid, (_, relative) in self._written.items():   # meshes of objects that are gone
            if oid not in current or current[oid][1] != relative:
                (self.directory / relative).unlink(missing_ok=True)
        self._written = current
        return path


def _vector(record: dict, key: str, length: int | None = None) -> np.ndarray:
    value = np.asarray(record[key], dtype=np.float64)
    if value.ndim != 1 or (length is not None and len(value) != length) or not np.isfinite(value).all():
        raise ValueError(f'{key} must be {length or "a list of"} finite numbers')
    return value


def _box(value: Any) -> Box3D:
    center, size = _vector(value, 'center', 3), _vector(value, 'size', 3)
    yaw = float(value['yaw'])
    if not math.isfinite(yaw) or not (size > 0).all():
        raise ValueError('box needs a finite yaw and a positive size')
    return Box3D(center, size, yaw)


def _map_object(record: dict, directory: Path) -> MapObject:
    """MapObject of one record; raises ValueError / KeyError / TypeError / OSError naming what is wrong."""
    oid = int(record['id'])
    pose = np.asarray(record['pose'], dtype=np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise ValueError('pose must be a finite 4x4 matrix')
    scale = float(record['scale'])
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f'scale {scale} is not positive')
    stage = record['stage']
    if stage not in STAGES:
        raise ValueError(f'stage {stage!r} is not one of {", ".join(STAGES)}')
    reason = record.get('stage_reason')
    reason_index = STAGE_REASONS.index(reason) if reason in STAGE_REASONS else 0
    mesh_path = directory / str(record['mesh'])
    try:
        mesh = trimesh.load(mesh_path, file_type='ply', process=False, force='mesh')
    except Exception as err:  # noqa: BLE001 - trimesh raises many kinds on a damaged file
        raise ValueError(f'mesh {mesh_path} unreadable ({type(err).__name__}: {err})') from err
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0 or not np.isfinite(mesh.vertices).all():
        raise ValueError(f'mesh {mesh_path} has no finite surface')
    category = record.get('category')   # absent in a `frodo run` objects.json: from the class name
    estimate = ObjectEstimate(oid, str(record['class']),
                              int(category) if category is not None else category_by_name(record['class']).coco_id,
                              _vector(record, 'code').astype(np.float32), pose, scale, _box(record['box']),
                              int(record['num_views']), stage, mesh,
                              {str(k): float(v) for k, v in (record.get('timings') or {}).items()}, reason_index,
                              int(record.get('stamp_ns') or 0))
    fused = record.get('fused_code')
    track = record.get('track')
    return MapObject(estimate, _vector(record, 'fused_code').astype(np.float32) if fused is not None else None,
                     int(record.get('fused_views') or 0),
                     (str(track['class']), _box(track)) if track is not None else None)


def load_map(directory: str | os.PathLike) -> tuple[list[MapObject], list[str]]:
    """(objects, problems) of one map directory; a record or mesh that cannot be used is left out and named
    in problems. Raises ObjectMapError when objects.json is missing, truncated, not JSON or not a map."""
    directory = Path(directory)
    path = directory / MAP_FILE
    try:
        document = json.loads(path.read_text())
    except FileNotFoundError:
        raise ObjectMapError(f'{path}: no object map there') from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ObjectMapError(f'{path}: not a readable object map, truncated or corrupt ({err})') from None
    if not isinstance(document, dict) or not isinstance(document.get('objects'), list):
        raise ObjectMapError(f'{path}: not an object map (no "objects" list)')
    if document.get('format', FORMAT) != FORMAT:   # no format: a `frodo run` objects.json
        raise ObjectMapError(f'{path}: format {document.get("format")!r}, not an object map ({FORMAT!r})')
    if 'format' in document and document.get('version') != VERSION:
        raise ObjectMapError(f'{path}: object map version {document.get("version")!r}, this code reads {VERSION}')
    records = document['objects']
    objects, problems = [], []
    for i, record in enumerate(records):
        try:
            objects.append(_map_object(record, directory))
        except (KeyError, ValueError, TypeError, OSError) as err:
            what = f'object {record.get("id")}' if isinstance(record, dict) else f'record {i}'
            problems.append(f'{path}: {what} skipped: {type(err).__name__}: {err}')
    return objects, problems


def map_dirs(root: str | os.PathLike) -> list[Path]:
    """`root` and its `worker_<k>` folders, those holding an objects.json (root first, workers by index)."""
    root = Path(root)
    workers = sorted((p for p in root.iterdir() if p.is_dir() and WORKER_DIR.fullmatch(p.name)),
                     key=lambda p: int(WORKER_DIR.fullmatch(p.name).group(1))) if root.is_dir() else []
    return [d for d in [root, *workers] if (d / MAP_FILE).is_file()]


def load_maps(root: str | os.PathLike, owns: Callable[[int], bool] = lambda oid: True
              ) -> tuple[dict[int, MapObject], list[str]]:
    """({id: object} of every map under `root` whose id `owns` accepts, problems). A map that cannot be read
    is a problem, not an exception (the others still load); no map at all is one too. An id saved twice
    (maps of different worker counts) keeps the later stage, then the record with more views. No map under
    `root` at all gives nothing and no problem (a first start with `--resume` of the folder it saves to)."""
    dirs = map_dirs(root)
    found: dict[int, MapObject] = {}
    problems: list[str] = []
    for directory in dirs:
        try:
            objects, bad = load_map(directory)
        except ObjectMapError as err:
            problems.append(f'{err}; its objects are not resumed')
            continue
        problems += bad
        for obj in objects:
            est, old = obj.estimate, found.get(obj.estimate.object_id)
            if owns(est.object_id) and (old is None or (STAGES.index(est.stage), est.num_views)
                                        > (STAGES.index(old.estimate.stage), old.estimate.num_views)):
                found[est.object_id] = obj
    return found, problems
