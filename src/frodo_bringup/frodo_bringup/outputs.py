"""Files written by `frodo run --out DIR` (CONTRACT.md): `objects.json` and `meshes/<id>_<class>.ply`.

Built from the final `/frodo/objects` (meshes) and `/frodo/boxes` (boxes) MarkerArrays. What markers
cannot carry (shape code, views, stage, timings, the optimiser's own pose and scale) comes from an
optional per-object `info` dict, {object id: {field: value}} (the optimiser's `/frodo/object_states`
through `frodo_optim.states.states_to_records`), whose fields override the derived ones. Without it,
the pose is the box's (centre, yaw) and the scale follows the canonical frame of docs/ARCHITECTURE.md
(box half-diagonal = `CANONICAL_RADIUS` normalised units).
"""
from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
from visualization_msgs.msg import Marker, MarkerArray

from frodo_common.conversions import ConversionError, marker_to_box, marker_to_mesh
from frodo_common.geometry import make_transform, yaw_matrix

# Half-diagonal of an object's box in normalised units (docs/ARCHITECTURE.md, canonical object frame).
CANONICAL_RADIUS = 0.9
OBJECTS_FILE = 'objects.json'
MESH_DIR = 'meshes'


def current_markers(array: MarkerArray | None) -> dict[int, Marker]:
    """{id: marker} after applying the array's ADD / DELETE / DELETEALL actions in order."""
    markers: dict[int, Marker] = {}
    for marker in array.markers if array is not None else ():
        if marker.action == Marker.DELETEALL:
            markers.clear()
        elif marker.action == Marker.DELETE:
            markers.pop(marker.id, None)
        else:
            markers[marker.id] = marker
    return markers


def weld_vertices(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge identical vertices of a triangle soup: (V, 3), (F, 3) -> (V', 3), (F, 3)."""
    unique, inverse = np.unique(np.asarray(vertices, dtype=np.float32), axis=0, return_inverse=True)
    return unique, inverse.reshape(-1)[np.asarray(faces)].reshape(-1, 3)


def write_ply(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Binary little-endian PLY: vertices (V, 3) float32, faces (F, 3) as uchar-counted int32 lists."""
    vertices = np.asarray(vertices, dtype='<f4').reshape(-1, 3)
    faces = np.asarray(faces, dtype='<i4').reshape(-1, 3)
    header = ('ply\nformat binary_little_endian 1.0\ncomment FroDO object mesh, world frame\n'
              f'element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n'
              f'element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n')
    face_records = np.empty(len(faces), dtype=[('n', 'u1'), ('v', '<i4', (3,))])
    face_records['n'] = 3
    face_records['v'] = faces
    with open(path, 'wb') as f:
        f.write(header.encode('ascii'))
        f.write(vertices.tobytes())
        f.write(face_records.tobytes())


def _file_stem(object_id: int, class_name: str) -> str:
    return f'{object_id}_{re.sub(r"[^A-Za-z0-9]+", "_", class_name).strip("_") or "object"}'


def _box_fields(marker: Marker) -> dict[str, Any]:
    centre, size, yaw = marker_to_box(marker)
    scale = float(np.linalg.norm(size) / 2 / CANONICAL_RADIUS)
    return {
        'box': {'center': centre.tolist(), 'size': size.tolist(), 'yaw': yaw},
        'pose': make_transform(yaw_matrix(yaw), centre, scale).tolist(),
        'scale': scale,
    }


def object_records(objects: MarkerArray | None, boxes: MarkerArray | None,
                   info: dict[int, dict[str, Any]] | None = None) -> list[dict[str, Any]]:
    """One JSON-ready record per object (ids from meshes, boxes or info), sorted by id; no files written."""
    meshes, box_markers, info = current_markers(objects), current_markers(boxes), info or {}
    records = []
    for object_id in sorted(set(meshes) | set(box_markers) | set(info)):
        mesh, box = meshes.get(object_id), box_markers.get(object_id)
        record: dict[str, Any] = {
            'id': int(object_id), 'class': (mesh or box).ns if (mesh or box) else '',
            'pose': None, 'scale': None, 'box': None, 'code': None, 'num_views': None, 'stage': None,
            'timings': {}, 'mesh': None,
        }
        if box is not None:
            record.update(_box_fields(box))
        record.update(info.get(object_id, {}))
        records.append(record)
    return records


def write_outputs(out_dir: str | os.PathLike, objects: MarkerArray | None, boxes: MarkerArray | None,
                  info: dict[int, dict[str, Any]] | None = None) -> list[dict[str, Any]]:
    """Write `objects.json` and one PLY per object mesh under `out_dir`; returns the object records."""
    out = Path(out_dir)
    (out / MESH_DIR).mkdir(parents=True, exist_ok=True)
    records = object_records(objects, boxes, info)
    meshes = current_markers(objects)
    for record in records:
        marker = meshes.get(record['id'])
        if marker is None or not marker.points:
            continue
        try:
            vertices, faces = weld_vertices(*marker_to_mesh(marker))
        except ConversionError as err:
            record['mesh_error'] = str(err)
            continue
        relative = f'{MESH_DIR}/{_file_stem(record["id"], record["class"])}.ply'
        write_ply(out / relative, vertices, faces)
        record['mesh'] = relative
        record['mesh_faces'] = int(len(faces))
    frame_id = next((m.header.frame_id for m in meshes.values()), None)
    document = {'frame_id': frame_id, 'objects': records}
    (out / OBJECTS_FILE).write_text(json.dumps(document, indent=2) + '\n')
    return records


def summary_table(records: list[dict[str, Any]]) -> str:
    """Plain-text table of the objects: id, class, stage, views, box centre and size, mesh faces."""
    header = f'{"id":>4}  {"class":<14} {"stage":<7} {"views":>5}  {"centre (m)":<22} {"size (m)":<20} {"faces":>6}'
    lines = [header, '-' * len(header)]
    for r in records:
        box = r.get('box') or {}
        centre = ' '.join(f'{v:6.2f}' for v in box.get('center', ())) or '-'
        size = ' '.join(f'{v:5.2f}' for v in box.get('size', ())) or '-'
        views = r.get('num_views')
        lines.append(f'{r["id"]:>4}  {r["class"][:14]:<14} {r.get("stage") or "-":<7} '
                     f'{"-" if views is None else views:>5}  {centre:<22} {size:<20} {r.get("mesh_faces", "-"):>6}')
    if not records:
        lines.append('(no objects)')
    return '\n'.join(lines)
