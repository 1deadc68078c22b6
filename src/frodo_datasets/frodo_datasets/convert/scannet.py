"""ScanNet scenes (http://www.scan-net.org, ScanNet/ScanNet SensReader and annotation tools).

A scene folder as distributed, `scans/scene0000_00/`, with either or both of
- `scene0000_00.sens`: read directly. Binary, little endian: uint32 version (4), uint64 name length + sensor
  name, 4x4 float32 colour intrinsics, colour extrinsics, depth intrinsics, depth extrinsics, int32 colour
  compression (2 = JPEG), int32 depth compression (1 = zlib uint16), uint32 colour width, height, depth
  width, height, float32 depth shift (1000 = mm), uint64 frame count; per frame 4x4 float32 camera-to-world,
  uint64 colour and depth timestamps (microseconds), uint64 colour and depth byte sizes, then the bytes;
- the SensReader export: `color/N.jpg` (1296x968), `depth/N.png` (640x480, uint16 mm), `pose/N.txt` (4x4
  camera-to-world), `intrinsic/intrinsic_color.txt`, `intrinsic/intrinsic_depth.txt` (4x4; also accepted at
  the scene root) and optionally `intrinsic/extrinsic_{color,depth}.txt`.
Optional annotations: `instance-filt/N.png` (8-bit, objectId + 1) and `label-filt/N.png` (16-bit ScanNet
label ids) from the `_2d-instance-filt.zip` / `_2d-label-filt.zip` archives, and the label table
`scannetv2-labels.combined.tsv` (in the scene folder or up to two folders above, or `labels_tsv`). Each
instance's class is its `*.aggregation.json` label (raw category) when that file is there, else the most
frequent label-filt id under it, looked up in the table (`raw_category`, then `category`); `class_map` maps
those names to COCO ids (default: chair, office chair, armchair -> 62; table, dining table, coffee table,
desk -> 67; sofa, couch -> 63; bed -> 65); unmapped instances (walls, floor, ...) are left out, and the
kept ones get k = 1, 2, ... per frame in order of their ScanNet instance value.
Ground truth: per-instance meshes cut from `*_vh_clean_2.ply` (faces whose three vertices lie in the
instance's segments, `*_vh_clean_2.0.010000.segs.json` `segIndices` via the aggregation's `segGroups`).
Invalid poses (-inf/NaN, where ScanNet lost tracking) are skipped and counted by the writer. ScanNet's world
is z up (the meshes' convention), so the writer does not re-align it by default.
"""
from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

from frodo_common.categories import category_by_id
from frodo_datasets.convert.common import (ConvertError, GroundTruthObject, Source, SourceFrame, decode_color,
                                           image_size, list_images, read_color, read_depth, read_matrix)

DEFAULT_CLASS_MAP: dict[str, int] = {
    'chair': 62, 'office chair': 62, 'armchair': 62,
    'table': 67, 'dining table': 67, 'coffee table': 67, 'desk': 67,
    'sofa': 63, 'couch': 63, 'bed': 65,
}
LABELS_TSV = 'scannetv2-labels.combined.tsv'
SENS_COLOR_JPEG, SENS_DEPTH_ZLIB = 2, 1


# ---------------------------------------------------------------- .sens
class SensFile:
    """Random access to the frames of a ScanNet `.sens` file (header parsed, frame offsets indexed)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        try:
            with open(self.path, 'rb') as f:
                self._read_header(f)
                self._index(f)
        except struct.error:
            raise ConvertError(f'{self.path}: truncated .sens file') from None

    def _read_header(self, f: BinaryIO) -> None:
        (version,) = struct.unpack('<I', f.read(4))
        if version != 4:
            raise ConvertError(f'{self.path}: .sens version {version}, expected 4')
        (n,) = struct.unpack('<Q', f.read(8))
        if n > 1024:
            raise ConvertError(f'{self.path}: not a .sens file (sensor name length {n})')
        self.sensor_name = f.read(n).decode('ascii', 'replace')
        mats = np.frombuffer(f.read(4 * 64), dtype='<f4').astype(np.float64).reshape(4, 4, 4)
        self.intrinsic_color, self.extrinsic_color, self.intrinsic_depth, self.extrinsic_depth = mats
        self.color_compression, self.depth_compression = struct.unpack('<ii', f.read(8))
        self.color_width, self.color_height, self.depth_width, self.depth_height = struct.unpack('<IIII', f.read(16))
        (self.depth_shift,) = struct.unpack('<f', f.read(4))
        (self.num_frames,) = struct.unpack('<Q', f.read(8))
        if self.color_compression not in (SENS_COLOR_JPEG, 1):
            raise ConvertError(f'{self.path}: colour compression {self.color_compression} not supported (JPEG/PNG)')
        if self.depth_compression not in (SENS_DEPTH_ZLIB, 0):
            raise ConvertError(f'{self.path}: depth compression {self.depth_compression} not supported '
                               f'(zlib or raw uint16)')

    def _index(self, f: BinaryIO) -> None:
        """Per frame: pose (4, 4), colour timestamp (us), (offset, size) of the colour and depth bytes."""
        self.poses, self.timestamps, self.color_at, self.depth_at = [], [], [], []
        size = self.path.stat().st_size
        for k in range(self.num_frames):
            head = f.read(64 + 32)
            if len(head) < 96:
                raise ConvertError(f'{self.path}: truncated at frame {k} of {self.num_frames}')
            self.poses.append(np.frombuffer(head[:64], dtype='<f4').astype(np.float64).reshape(4, 4))
            t_color, _, n_color, n_depth = struct.unpack('<QQQQ', head[64:])
            self.timestamps.append(t_color)
            start = f.tell()
            if start + n_color + n_depth > size:
                raise ConvertError(f'{self.path}: truncated at frame {k} of {self.num_frames}')
            self.color_at.append((start, n_color))
            self.depth_at.append((start + n_color, n_depth))
            f.seek(n_color + n_depth, 1)

    def _bytes(self, at: tuple[int, int]) -> bytes:
        with open(self.path, 'rb') as f:
            f.seek(at[0])
            return f.read(at[1])

    def color(self, k: int) -> np.ndarray:
        """RGB uint8 of frame k."""
        return decode_color(self._bytes(self.color_at[k]), f'{self.path.name} frame {k}')

    def depth(self, k: int) -> np.ndarray:
        """Depth in metres float32 (depth_height, depth_width) of frame k."""
        data = self._bytes(self.depth_at[k])
        try:
            raw = zlib.decompress(data) if self.depth_compression == SENS_DEPTH_ZLIB else data
        except zlib.error as err:
            raise OSError(f'{self.path.name} frame {k}: bad zlib depth ({err})') from None
        if len(raw) != 2 * self.depth_width * self.depth_height:
            raise OSError(f'{self.path.name} frame {k}: depth has {len(raw)} bytes, expected '
                          f'{2 * self.depth_width * self.depth_height}')
        return (np.frombuffer(raw, dtype='<u2').reshape(self.depth_height, self.depth_width)
                .astype(np.float32) / np.float32(self.depth_shift))


# ---------------------------------------------------------------- labels
def find_labels_tsv(folder: Path, given: Path | None) -> Path | None:
    """The label table: `given`, or LABELS_TSV in the scene folder or up to two folders above."""
    if given is not None:
        if not Path(given).is_file():
            raise ConvertError(f'label table not found: {given}')
        return Path(given)
    for d in (folder, folder.parent, folder.parent.parent):
        if (d / LABELS_TSV).is_file():
            return d / LABELS_TSV
    return None


def read_labels_tsv(path: Path) -> dict[int, tuple[str, str]]:
    """ScanNet label id -> (raw_category, category) from scannetv2-labels.combined.tsv."""
    lines = path.read_text().splitlines()
    if not lines:
        raise ConvertError(f'{path} is empty')
    header = lines[0].split('\t')
    try:
        i_id, i_raw, i_cat = header.index('id'), header.index('raw_category'), header.index('category')
    except ValueError:
        raise ConvertError(f'{path}: expected columns id, raw_category, category; found {header[:5]}') from None
    out = {}
    for line in lines[1:]:
        cols = line.split('\t')
        if len(cols) > max(i_id, i_raw, i_cat) and cols[i_id].strip().isdigit():
            out[int(cols[i_id])] = (cols[i_raw].strip().lower(), cols[i_cat].strip().lower())
    return out


def _find_one(folder: Path, pattern: str) -> Path | None:
    hits = sorted(folder.glob(pattern))
    return hits[0] if hits else None


def read_aggregation(folder: Path) -> list[dict] | None:
    """segGroups of `*.aggregation.json` (None when the file is not there)."""
    path = _find_one(folder, '*.aggregation.json')
    if path is None:
        return None
    try:
        return json.loads(path.read_text())['segGroups']
    except (OSError, ValueError, KeyError) as err:
        raise ConvertError(f'cannot read {path}: {err}') from None


class InstanceMapper:
    """ScanNet instance (objectId + 1) and label images -> contract instance image `coco_id * 256 + k`."""

    def __init__(self, class_map: dict[str, int], groups: list[dict] | None, labels: dict[int, tuple[str, str]] | None):
        self.class_map = {k.lower(): int(v) for k, v in class_map.items()}
        self.labels = labels or {}
        self.group_class: dict[int, int | None] | None = None
        if groups is not None:
            self.group_class = {int(g['objectId']) + 1: self.class_map.get(str(g['label']).lower())
                                for g in groups}

    def label_class(self, label_id: int) -> int | None:
        """COCO id of a ScanNet label id through the table (raw category first, then category)."""
        raw, cat = self.labels.get(int(label_id), ('', ''))
        return self.class_map.get(raw, self.class_map.get(cat))

    def __call__(self, instance: np.ndarray, label: np.ndarray | None) -> np.ndarray:
        out = np.zeros(instance.shape, dtype=np.uint16)
        k = 0
        for v in np.unique(instance[instance > 0]):
            mask = instance == v
            coco = self.group_class.get(int(v)) if self.group_class is not None else None
            if self.group_class is None and label is not None:
                ids, counts = np.unique(label[mask], return_counts=True)
                coco = self.label_class(int(ids[np.argmax(counts)]))
            if coco is None or k == 255:
                continue
            k += 1
            out[mask] = (coco << 8) | k
        return out


def _read_png(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2:
        raise OSError(f'cannot read annotation image {path}')
    return img


# ---------------------------------------------------------------- ground truth
def read_ground_truth(folder: Path, class_map: dict[str, int]) -> list[GroundTruthObject]:
    """Per-instance meshes of mapped classes cut from `*_vh_clean_2.ply` (empty when the files are missing)."""
    import trimesh
    ply = _find_one(folder, '*_vh_clean_2.ply')
    segs = _find_one(folder, '*_vh_clean_2.0.010000.segs.json')
    groups = read_aggregation(folder)
    if ply is None or segs is None or groups is None:
        return []
    mesh = trimesh.load(ply, process=False)  # keep ScanNet's vertex order: segIndices index it
    try:
        seg = np.asarray(json.loads(segs.read_text())['segIndices'])
    except (OSError, ValueError, KeyError) as err:
        raise ConvertError(f'cannot read {segs}: {err}') from None
    if len(seg) != len(mesh.vertices):
        raise ConvertError(f'{segs.name} has {len(seg)} segment indices but {ply.name} has '
                           f'{len(mesh.vertices)} vertices')
    cmap = {k.lower(): int(v) for k, v in class_map.items()}
    out = []
    for g in groups:
        coco = cmap.get(str(g['label']).lower())
        if coco is None:
            continue
        inside = np.isin(seg, np.asarray(g['segments']))
        faces = mesh.faces[inside[mesh.faces].all(axis=1)]
        if not len(faces):
            continue
        used, remap = np.unique(faces, return_inverse=True)
        category = category_by_id(coco)
        name = category.name if category else f'coco_{coco}'
        out.append(GroundTruthObject(name, int(g['objectId']) + 1, np.asarray(mesh.vertices[used], dtype=np.float64),
                                     remap.reshape(-1, 3)))
    return out


# ---------------------------------------------------------------- reader
def _intrinsics_file(folder: Path, name: str) -> Path | None:
    for p in (folder / 'intrinsic' / f'{name}.txt', folder / f'{name}.txt'):
        if p.is_file():
            return p
    return None


def read_scannet(folder: str | Path, labels_tsv: str | Path | None = None, class_map: dict[str, int] | None = None,
                 prefer: str = 'exported', fps: float = 30.0, start_ns: int = 1_700_000_000_000_000_000,
                 with_instances: bool = True, with_ground_truth: bool = True) -> Source:
    """Read a ScanNet scene folder into a `Source` (see module docstring)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ConvertError(f'ScanNet scene folder not found: {folder}')
    class_map = class_map or DEFAULT_CLASS_MAP
    sens_path = _find_one(folder, '*.sens')
    exported = (folder / 'color').is_dir()
    if sens_path is None and not exported:
        raise ConvertError(f'{folder} is not a ScanNet scene: no *.sens file and no color/ folder '
                           f'(expected scene0000_00.sens or the SensReader export color/, depth/, pose/, intrinsic/)')
    use_sens = sens_path is not None and (prefer == 'sens' or not exported)
    period_ns = int(round(1e9 / fps))
    if use_sens:
        sens = SensFile(sens_path)
        K_c, K_d = sens.intrinsic_color[:3, :3], sens.intrinsic_depth[:3, :3]
        color_size, depth_size = (sens.color_width, sens.color_height), (sens.depth_width, sens.depth_height)
        E_c, E_d = sens.extrinsic_color, sens.extrinsic_depth
        ts = np.array(sens.timestamps, dtype=np.int64)
        timed = len(ts) > 1 and np.all(np.diff(ts) > 0)
        indices = list(range(sens.num_frames))
        stamps = {k: start_ns + (int(ts[k] - ts[0]) * 1000 if timed else k * period_ns) for k in indices}
        poses = {k: sens.poses[k] for k in indices}
        color = {k: (lambda k=k: sens.color(k)) for k in indices}
        depth = {k: (lambda k=k: sens.depth(k)) for k in indices}
        note = (f'read {sens_path.name} ({sens.num_frames} frames, sensor {sens.sensor_name!r}, '
                f'{"timestamps" if timed else f"no usable timestamps: {fps:g} fps"})')
    else:
        kc, kd = _intrinsics_file(folder, 'intrinsic_color'), _intrinsics_file(folder, 'intrinsic_depth')
        if kc is None:
            raise ConvertError(f'{folder}: missing intrinsic/intrinsic_color.txt')
        K_c = read_matrix(kc)[:3, :3]
        K_d = read_matrix(kd)[:3, :3] if kd is not None else K_c
        ec, ed = _intrinsics_file(folder, 'extrinsic_color'), _intrinsics_file(folder, 'extrinsic_depth')
        E_c = read_matrix(ec) if ec is not None else np.eye(4)
        E_d = read_matrix(ed) if ed is not None else np.eye(4)
        color_files = {int(p.stem): p for p in list_images(folder / 'color') if p.stem.isdigit()}
        depth_files = {int(p.stem): p for p in list_images(folder / 'depth')
                       if p.stem.isdigit()} if (folder / 'depth').is_dir() else {}
        pose_files = {int(p.stem): p for p in (folder / 'pose').glob('*.txt')
                      if p.stem.isdigit()} if (folder / 'pose').is_dir() else {}
        if not color_files:
            raise ConvertError(f'{folder / "color"} has no N.jpg images')
        if not pose_files:
            raise ConvertError(f'{folder}: no pose/N.txt files (camera-to-world 4x4 per frame)')
        indices = sorted(set(color_files) | set(pose_files))
        color_size = image_size(color_files[min(color_files)])
        depth_size = image_size(depth_files[min(depth_files)]) if depth_files else None
        stamps = {k: start_ns + k * period_ns for k in indices}
        poses, color, depth = {}, {}, {}
        for k in indices:
            if k in pose_files:
                try:
                    poses[k] = read_matrix(pose_files[k])
                except ConvertError:
                    poses[k] = None
            color[k] = (lambda p=color_files[k]: read_color(p)) if k in color_files else None
            depth[k] = (lambda p=depth_files[k]: read_depth(p, 1000.0)) if k in depth_files else None
        note = f'read the exported layout ({len(color_files)} colour images, {len(pose_files)} poses)'

    # Depth -> colour camera, assuming each extrinsic maps its camera into a common rig frame [INFERRED:
    # ScanNet ships identity for both].
    T_cd = np.linalg.inv(E_c) @ E_d
    source = Source('scannet', [], K_c, color_size, K_depth=K_d, depth_size=depth_size, T_color_depth=T_cd,
                    world_up=np.array([0.0, 0.0, 1.0]))
    source.notes.append(note)

    mapper = None
    inst_dir, label_dir = folder / 'instance-filt', folder / 'label-filt'
    if with_instances and inst_dir.is_dir():
        groups = read_aggregation(folder)
        tsv = find_labels_tsv(folder, Path(labels_tsv) if labels_tsv else None)
        labels = read_labels_tsv(tsv) if tsv is not None else None
        if groups is None and (labels is None or not label_dir.is_dir()):
            raise ConvertError(f'{inst_dir} needs the classes of its instances: *.aggregation.json, or '
                               f'label-filt/ with {LABELS_TSV} (give --labels-tsv)')
        mapper = InstanceMapper(class_map, groups, labels)
        first = next(iter(sorted(inst_dir.glob('*.png'), key=lambda p: int(p.stem) if p.stem.isdigit() else -1)),
                     None)
        if first is None:
            raise ConvertError(f'{inst_dir} has no N.png images')
        source.label_size = image_size(first)
        source.notes.append(f'instances from {inst_dir.name}/ with classes from '
                            f'{"the aggregation" if groups is not None else "label-filt/ and " + LABELS_TSV}')

    for k in indices:
        if color.get(k) is None:
            source.skip('missing colour image')
            continue
        if poses.get(k) is None:
            source.skip('missing or unreadable pose file')
            continue
        if depth_size is not None and depth.get(k) is None:
            source.skip('missing depth image')
            continue
        instances = None
        if mapper is not None:
            ip, lp = inst_dir / f'{k}.png', label_dir / f'{k}.png'
            if not ip.is_file():
                source.skip('missing instance image')
                continue
            instances = (lambda ip=ip, lp=lp: mapper(_read_png(ip), _read_png(lp) if lp.is_file() else None))
        source.frames.append(SourceFrame(k, stamps[k], poses[k], color[k], depth.get(k), instances))
    if with_ground_truth:
        source.ground_truth = read_ground_truth(folder, class_map)
    return source
