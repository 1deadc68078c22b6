"""Write a rendered synthetic scene in each dataset's on-disk layout: the test fixtures of the converters, and
a way to try `frodo convert` without downloading a dataset.

`render_sequence` renders a room (`frodo_datasets.scene`, `frodo_datasets.render`) along a trajectory; the
`write_*` functions lay the frames out exactly as the datasets ship them (file names, encodings, units,
pose conventions, the ScanNet `.sens` binary, label tables and scene annotation files), optionally in a
world frame that is not z up (`T_dataset_world`) as TUM's mocap world or a Redwood trajectory are.
"""
from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import trimesh

from frodo_common.geometry import matrix_to_quat
from frodo_datasets.render import Light, Renderer, intrinsics
from frodo_datasets.scene import Scene, compose_scene, trajectory
from frodo_datasets.convert.common import scale_intrinsics

# Raw ScanNet categories written for the scene's classes (exercising the default class map).
SCANNET_RAW = {'chair': ('office chair', 'chair', 'armchair'), 'dining table': ('table', 'desk', 'coffee table')}
# A few rows of ScanNet's label table: id, raw_category, category, nyu40id, nyu40class.
SCANNET_LABELS = [(1, 'wall', 'wall', 1, 'wall'), (2, 'chair', 'chair', 5, 'chair'), (3, 'floor', 'floor', 2, 'floor'),
                  (4, 'table', 'table', 7, 'table'), (9, 'desk', 'desk', 14, 'desk'),
                  (10, 'office chair', 'office chair', 5, 'chair'), (13, 'couch', 'sofa', 6, 'sofa'),
                  (23, 'coffee table', 'coffee table', 7, 'table'), (45, 'armchair', 'armchair', 5, 'chair')]
TSV_HEADER = ('id\traw_category\tcategory\tcount\tnyu40id\teigen13id\tnyuClass\tnyu40class\teigen13class\t'
              'ModelNet40\tModelNet10\tShapeNetCore55\tsynsetoffset\twnsynsetid\twnsynsetkey\tmpcat40\tmpcat40index')


@dataclass
class RenderedSequence:
    """Frames of a synthetic scene: K (3, 3), size (w, h), poses T_world_camera (z-up world), rgb (H, W, 3)
    uint8, depth (H, W) metres, labels (H, W) object ids (0 = room)."""

    scene: Scene
    K: np.ndarray
    size: tuple[int, int]
    poses: list[np.ndarray]
    rgb: list[np.ndarray]
    depth: list[np.ndarray]
    labels: list[np.ndarray]


def render_sequence(frames: int = 8, width: int = 128, height: int = 96, seed: int = 0, layout: str = 'orbit',
                    objects: int = 1, classes: Sequence[str] = ('chair', 'dining table'),
                    hfov_deg: float = 60.0) -> RenderedSequence:
    """Render `frames` views of a composed scene (deterministic in `seed`): the scene, trajectory and light
    of `frodo synth --scene LAYOUT --seed SEED` (same draws), without its noise options."""
    scene = compose_scene(objects, classes, seed=seed, layout=layout)
    poses = trajectory(scene, layout, frames, seed=seed + 1, hfov_deg=hfov_deg)
    K = intrinsics(width, height, hfov_deg)
    renderer = Renderer(scene.render_objects())
    rng = np.random.default_rng(seed)
    elevation, azimuth = rng.uniform(np.radians(45), np.radians(70)), rng.uniform(0, 2 * np.pi)
    light = Light(direction=(-np.cos(elevation) * np.cos(azimuth), -np.cos(elevation) * np.sin(azimuth),
                             -np.sin(elevation)), intensity=0.7)
    seq = RenderedSequence(scene, K, (width, height), poses, [], [], [])
    for T in poses:
        res = renderer.render(K, T, width, height, light=light, background=(0.82, 0.86, 0.9))
        seq.rgb.append(res.rgb)
        seq.depth.append(res.depth)
        seq.labels.append(res.labels)
    return seq


def _write_png16(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.asarray(img, dtype=np.uint16))


def _write_rgb(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def _depth_units(depth: np.ndarray, factor: float) -> np.ndarray:
    return np.clip(np.round(depth * factor), 0, 65535).astype(np.uint16)


def _matrix_text(T: np.ndarray) -> str:
    return '\n'.join(' '.join(f'{v:.9g}' for v in row) for row in T) + '\n'


# ---------------------------------------------------------------- TUM
def write_intrinsics_yaml(seq: RenderedSequence, path: Path) -> Path:
    """fx, fy, cx, cy, width, height of the rendered camera (for TUM/Redwood fixtures not at 640x480)."""
    K, (w, h) = seq.K, seq.size
    path.write_text(f'fx: {float(K[0, 0])!r}\nfy: {float(K[1, 1])!r}\ncx: {float(K[0, 2])!r}\ncy: {float(K[1, 2])!r}\n'
                    f'width: {w}\nheight: {h}\n')
    return path


def write_tum(seq: RenderedSequence, folder: Path, T_dataset_world: np.ndarray | None = None,
              start: float = 1305031102.175304, drop_depth: Sequence[int] = (), extra_rgb: bool = True) -> Path:
    """TUM RGB-D layout: rgb.txt/depth.txt/groundtruth.txt with comments, PNG colour, depth x5000.

    Ground truth is written at 100 Hz-like offsets (+3 ms) from the colour stamps, depth at +7 ms; the depth
    of frames in `drop_depth` is left out, and with `extra_rgb` one more colour image far from any pose is
    listed (both must be skipped by the converter). Poses are T_dataset_camera = T_dataset_world T_world_camera.
    """
    folder.mkdir(parents=True, exist_ok=True)
    A = np.eye(4) if T_dataset_world is None else T_dataset_world
    rgb_lines = ['# color images', '# file: fixture', '# timestamp filename']
    depth_lines = ['# depth maps', '# file: fixture', '# timestamp filename']
    gt_lines = ['# ground truth trajectory', '# file: fixture', '# timestamp tx ty tz qx qy qz qw']
    for k, (rgb, depth, T) in enumerate(zip(seq.rgb, seq.depth, seq.poses)):
        t = start + k / 30.0
        name = f'{t:.6f}'
        _write_rgb(folder / 'rgb' / f'{name}.png', rgb)
        rgb_lines.append(f'{name} rgb/{name}.png')
        if k not in drop_depth:
            dname = f'{t + 0.007:.6f}'
            _write_png16(folder / 'depth' / f'{dname}.png', _depth_units(depth, 5000.0))
            depth_lines.append(f'{dname} depth/{dname}.png')
        P = A @ T
        q = matrix_to_quat(P[:3, :3])
        gt_lines.append(f'{t + 0.003:.4f} ' + ' '.join(f'{v:.6f}' for v in (*P[:3, 3], *q)))
    if extra_rgb:
        t = start + len(seq.rgb) / 30.0 + 5.0
        _write_rgb(folder / 'rgb' / f'{t:.6f}.png', seq.rgb[-1])
        rgb_lines.append(f'{t:.6f} rgb/{t:.6f}.png')
    for name, lines in (('rgb.txt', rgb_lines), ('depth.txt', depth_lines), ('groundtruth.txt', gt_lines)):
        (folder / name).write_text('\n'.join(lines) + '\n')
    return folder


# ---------------------------------------------------------------- Redwood
def write_redwood(seq: RenderedSequence, folder: Path, T_dataset_world: np.ndarray | None = None,
                  missing_image: int | None = None) -> Path:
    """Redwood layout: rgb/NNNNNNN-TTTTTTTTTTTT.jpg, depth/….png (mm), trajectory.log (per frame "i i i+1"
    then the 4x4 camera-to-world). The colour of frame `missing_image` is left out."""
    folder.mkdir(parents=True, exist_ok=True)
    A = np.eye(4) if T_dataset_world is None else T_dataset_world
    log = []
    for k, (rgb, depth, T) in enumerate(zip(seq.rgb, seq.depth, seq.poses)):
        name = f'{k + 1:07d}-{int(k * 1e6 / 30):012d}'
        if k != missing_image:
            _write_rgb(folder / 'rgb' / f'{name}.jpg', rgb)
        _write_png16(folder / 'depth' / f'{name}.png', _depth_units(depth, 1000.0))
        log.append(f'{k} {k} {k + 1}\n' + _matrix_text(A @ T))
    (folder / 'trajectory.log').write_text(''.join(log))
    return folder


# ---------------------------------------------------------------- folder
def write_folder(seq: RenderedSequence, folder: Path, pose_format: str = 'tum') -> Path:
    """User folder layout: rgb/NNNNNN.png, depth/NNNNNN.png (mm), instances/ (contract encoding), intrinsics.yaml,
    poses.txt (TUM lines by order when pose_format='tum', 4x4 per line when '4x4') or poses/NNNNNN.txt ('dir')."""
    from frodo_datasets.synth import instance_image
    folder.mkdir(parents=True, exist_ok=True)
    K, (w, h) = seq.K, seq.size
    (folder / 'intrinsics.yaml').write_text(
        f'fx: {float(K[0, 0])!r}\nfy: {float(K[1, 1])!r}\ncx: {float(K[0, 2])!r}\ncy: {float(K[1, 2])!r}\n'
        f'width: {w}\nheight: {h}\ndepth_scale: 1000\n')
    rng = np.random.default_rng(0)
    lines = ['# timestamp tx ty tz qx qy qz qw']
    for k, (rgb, depth, labels, T) in enumerate(zip(seq.rgb, seq.depth, seq.labels, seq.poses)):
        stem = f'{k:06d}'
        _write_rgb(folder / 'rgb' / f'{stem}.png', rgb)
        _write_png16(folder / 'depth' / f'{stem}.png', _depth_units(depth, 1000.0))
        _write_png16(folder / 'instances' / f'{stem}.png', instance_image(labels, seq.scene, rng, 5))
        if pose_format == 'tum':
            q = matrix_to_quat(T[:3, :3])
            lines.append(f'{k / 30:.6f} ' + ' '.join(f'{v:.9f}' for v in (*T[:3, 3], *q)))
        elif pose_format == '4x4':
            lines.append(' '.join(f'{v:.9g}' for v in T.ravel()))
        else:
            (folder / 'poses').mkdir(exist_ok=True)
            (folder / 'poses' / f'{stem}.txt').write_text(_matrix_text(T))
    if pose_format in ('tum', '4x4'):
        (folder / 'poses.txt').write_text('\n'.join(lines) + '\n')
    return folder


# ---------------------------------------------------------------- ScanNet
def _scannet_labels(seq: RenderedSequence) -> dict[int, tuple[str, int]]:
    """Object id -> (raw ScanNet category, ScanNet label id), cycling the raw names of each class."""
    ids = {raw: i for i, raw, *_ in SCANNET_LABELS}
    seen: dict[str, int] = {}
    out = {}
    for o in seq.scene.objects:
        names = SCANNET_RAW[o.class_name]
        raw = names[seen.get(o.class_name, 0) % len(names)]
        seen[o.class_name] = seen.get(o.class_name, 0) + 1
        out[o.id] = (raw, ids[raw])
    return out


def write_scannet_labels_tsv(path: Path) -> Path:
    """A label table with ScanNet's columns and a few of its rows."""
    rows = [TSV_HEADER] + [f'{i}\t{raw}\t{cat}\t100\t{nyu}\t0\t{nyu_c}\t{nyu_c}\t\t\t\t\t\t\t\t\t'
                           for i, raw, cat, nyu, nyu_c in SCANNET_LABELS]
    path.write_text('\n'.join(rows) + '\n')
    return path


def _scannet_frame_annotations(seq: RenderedSequence, k: int, floor_object: int) -> tuple[np.ndarray, np.ndarray]:
    """(instance-filt uint8 = objectId + 1, label-filt uint16 = ScanNet label id) of frame k."""
    labels = seq.labels[k]
    table = _scannet_labels(seq)
    inst = labels.astype(np.uint8)  # object id o.id = objectId + 1
    lab = np.zeros(labels.shape, dtype=np.uint16)
    for obj_id, (_, label_id) in table.items():
        lab[labels == obj_id] = label_id
    # the floor is an annotated (but unmapped) instance too, as in ScanNet
    floor = (labels == 0) & (seq.depth[k] > 0) & (_world_z(seq, k) < 0.01)
    inst[floor] = floor_object + 1
    lab[floor] = 3
    return inst, lab


def _world_z(seq: RenderedSequence, k: int) -> np.ndarray:
    h, w = seq.depth[k].shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    z = seq.depth[k]
    K, T = seq.K, seq.poses[k]
    ray_z = T[2, 0] * (u - K[0, 2]) / K[0, 0] + T[2, 1] * (v - K[1, 2]) / K[1, 1] + T[2, 2]
    return T[2, 3] + z * ray_z


def write_scannet_scene_files(seq: RenderedSequence, folder: Path, scene_name: str) -> None:
    """`<scene>_vh_clean_2.ply` (binary PLY, room + objects), `<scene>_vh_clean_2.0.010000.segs.json`
    (segIndices per vertex; each object split into two segments) and `<scene>.aggregation.json` (segGroups
    with objectId, segments, raw label; plus the floor as an unmapped object)."""
    meshes, seg_indices, groups = [], [], []
    table = _scannet_labels(seq)
    floor_segments = []
    for i, obj in enumerate(seq.scene.render_objects()):
        mesh = obj.mesh
        if obj.label == 0:
            seg = 1000 + i
            if np.ptp(mesh.vertices[:, 2]) < 1e-6:
                floor_segments.append(seg)
            seg_indices.append(np.full(len(mesh.vertices), seg))
        else:
            high = mesh.vertices[:, 2] > mesh.vertices[:, 2].mean()
            seg_indices.append(np.where(high, 200 + obj.label, 100 + obj.label))
            groups.append({'id': obj.label - 1, 'objectId': obj.label - 1,
                           'segments': [100 + obj.label, 200 + obj.label],
                           'label': table[obj.label][0]})
        meshes.append(mesh)
    floor_object = len(seq.scene.objects)
    groups.append({'id': floor_object, 'objectId': floor_object, 'segments': floor_segments, 'label': 'floor'})
    mesh = trimesh.util.concatenate(meshes)
    mesh.export(folder / f'{scene_name}_vh_clean_2.ply', file_type='ply', encoding='binary')
    (folder / f'{scene_name}_vh_clean_2.0.010000.segs.json').write_text(json.dumps(
        {'params': {'kThresh': '0.0001'}, 'sceneId': scene_name, 'segIndices': np.concatenate(seg_indices).tolist()}))
    (folder / f'{scene_name}.aggregation.json').write_text(json.dumps(
        {'sceneId': f'scannet.{scene_name}', 'appId': 'fixture', 'segGroups': groups,
         'segmentsFile': f'scannet.{scene_name}_vh_clean_2.0.010000.segs.json'}))


def write_scannet(seq: RenderedSequence, folder: Path, layout: str = 'exported', scene_name: str = 'scene0000_00',
                  invalid_pose: Sequence[int] = (), missing_color: Sequence[int] = (), annotations: bool = True,
                  scene_files: bool = True, depth_scale: int = 2, color_scale: int = 1) -> Path:
    """A ScanNet scene folder.

    layout 'exported': SensReader's output (color/N.jpg, depth/N.png mm, pose/N.txt, intrinsic/*.txt);
    'sens': `<scene>.sens` (version 4: header with 4x4 colour/depth intrinsics and extrinsics, JPEG colour,
    zlib depth in mm, per frame camera-to-world and microsecond timestamps). Depth is written at 1/depth_scale
    of the render resolution and colour at `color_scale` times it (ScanNet: 1296x968 colour, 640x480 depth
    and annotations; annotations stay at the render resolution). Frames in `invalid_pose`
    get a -inf pose; colour of `missing_color` is left out (exported layout). With `annotations`,
    instance-filt/N.png (8-bit objectId + 1) and label-filt/N.png (16-bit label ids) and the label table;
    with `scene_files` the mesh, segments and aggregation files.
    """
    folder.mkdir(parents=True, exist_ok=True)
    w, h = seq.size
    dw, dh = w // depth_scale, h // depth_scale
    K_d = scale_intrinsics(seq.K, (w, h), (dw, dh))
    K4, K4d = np.eye(4), np.eye(4)
    K4[:3, :3], K4d[:3, :3] = scale_intrinsics(seq.K, (w, h), (w * color_scale, h * color_scale)), K_d
    colors = [cv2.resize(c, (w * color_scale, h * color_scale), interpolation=cv2.INTER_LINEAR) for c in seq.rgb]
    poses = []
    for k, T in enumerate(seq.poses):
        P = np.array(T, dtype=np.float64)
        if k in invalid_pose:
            P = np.full((4, 4), -np.inf)
        poses.append(P)
    depths = [cv2.resize(_depth_units(d, 1000.0), (dw, dh), interpolation=cv2.INTER_NEAREST) for d in seq.depth]
    if layout == 'exported':
        for k, (rgb, P) in enumerate(zip(colors, poses)):
            if k not in missing_color:
                _write_rgb(folder / 'color' / f'{k}.jpg', rgb)
            _write_png16(folder / 'depth' / f'{k}.png', depths[k])
            (folder / 'pose').mkdir(exist_ok=True)
            (folder / 'pose' / f'{k}.txt').write_text(_matrix_text(P))
        (folder / 'intrinsic').mkdir(exist_ok=True)
        for name, M in (('intrinsic_color', K4), ('intrinsic_depth', K4d), ('extrinsic_color', np.eye(4)),
                        ('extrinsic_depth', np.eye(4))):
            (folder / 'intrinsic' / f'{name}.txt').write_text(_matrix_text(M))
    elif layout == 'sens':
        write_sens(folder / f'{scene_name}.sens', colors, depths, poses, K4, K4d)
    else:
        raise ValueError(f'unknown ScanNet layout {layout!r}')
    if annotations:
        floor_object = len(seq.scene.objects)
        for k in range(len(seq.rgb)):
            inst, lab = _scannet_frame_annotations(seq, k, floor_object)
            (folder / 'instance-filt').mkdir(exist_ok=True)
            cv2.imwrite(str(folder / 'instance-filt' / f'{k}.png'), inst)
            _write_png16(folder / 'label-filt' / f'{k}.png', lab)
        write_scannet_labels_tsv(folder / 'scannetv2-labels.combined.tsv')
    if scene_files:
        write_scannet_scene_files(seq, folder, scene_name)
    return folder


def write_sens(path: Path, colors: Sequence[np.ndarray], depths_mm: Sequence[np.ndarray], poses: Sequence[np.ndarray],
               K_color4: np.ndarray, K_depth4: np.ndarray, depth_shift: float = 1000.0) -> Path:
    """A ScanNet `.sens` file (SensReader's layout, version 4, little endian): header then per frame
    camera_to_world (16 float32), timestamp_color, timestamp_depth, color_size_bytes, depth_size_bytes (uint64),
    JPEG bytes, zlib-compressed uint16 depth bytes; then an empty IMU frame count."""
    h_c, w_c = colors[0].shape[:2]
    h_d, w_d = depths_mm[0].shape
    out = bytearray()
    name = b'StructureSensor'
    out += struct.pack('<I', 4) + struct.pack('<Q', len(name)) + name
    for M in (K_color4, np.eye(4), K_depth4, np.eye(4)):
        out += np.asarray(M, dtype='<f4').tobytes()
    out += struct.pack('<ii', 2, 1)  # colour jpeg, depth zlib_ushort
    out += struct.pack('<IIII', w_c, h_c, w_d, h_d) + struct.pack('<f', depth_shift)
    out += struct.pack('<Q', len(colors))
    for k, (rgb, depth, P) in enumerate(zip(colors, depths_mm, poses)):
        ok, jpg = cv2.imencode('.jpg', cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
        z = zlib.compress(np.asarray(depth, dtype='<u2').tobytes())
        out += np.asarray(P, dtype='<f4').tobytes()
        out += struct.pack('<QQQQ', k * 33333, k * 33333, len(jpg), len(z))
        out += jpg.tobytes() + z
    out += struct.pack('<Q', 0)
    path.write_bytes(bytes(out))
    return path


# ---------------------------------------------------------------- checking a converted bag
CONTRACT_TYPES = {
    '/camera/color/image_raw': 'sensor_msgs/msg/Image',
    '/camera/color/camera_info': 'sensor_msgs/msg/CameraInfo',
    '/camera/pose': 'geometry_msgs/msg/PoseStamped',
    '/camera/instances': 'sensor_msgs/msg/Image',
    '/camera/depth/image_raw': 'sensor_msgs/msg/Image',
    '/slam/points': 'sensor_msgs/msg/PointCloud2',
    '/ground_truth/objects': 'visualization_msgs/msg/MarkerArray',
}


def read_with_rosbags(path: Path) -> dict[str, list[tuple[int, object]]]:
    """Read a bag with the independent `rosbags` reader and check what CONTRACT.md "Bags" requires.

    Checks: profile ros2, ros2msg schemas, cdr channels, the rosbag2 metadata record (version 9, message
    count), contract topic types, offered QoS on every
    channel (ground truth transient local, depth 1), header stamp = log time, frame ids, image encodings and
    sizes matching the camera info, camera info before the first image. Returns {topic: [(log ns, message)]};
    raises AssertionError naming the first violation.
    """
    import yaml
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import QosDurability
    from rosbags.typesys import Stores, get_typestore

    with open(path, 'rb') as f:
        reader = make_reader(f)
        assert reader.get_header().profile == 'ros2', 'MCAP profile is not ros2'
        summary = reader.get_summary()
        assert {s.encoding for s in summary.schemas.values()} == {'ros2msg'}
        assert {c.message_encoding for c in summary.channels.values()} == {'cdr'}
        records = {m.name: m.metadata for m in reader.iter_metadata()}
        info = yaml.safe_load(records['rosbag2']['serialized_metadata'])['rosbag2_bagfile_information']
        assert info['version'] == 9 and info['message_count'] == summary.statistics.message_count
    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = {c.topic: c for c in reader.connections}
        msgs = [(c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]
    for topic, c in conns.items():
        assert CONTRACT_TYPES.get(topic) == c.msgtype, f'{topic}: type {c.msgtype} is not the contract type'
        assert c.ext.offered_qos_profiles, f'{topic}: no offered_qos_profiles'
    if '/ground_truth/objects' in conns:
        qos = conns['/ground_truth/objects'].ext.offered_qos_profiles[0]
        assert qos.durability == QosDurability.TRANSIENT_LOCAL and qos.depth == 1, 'ground truth not latched'
    out: dict[str, list[tuple[int, object]]] = {}
    info = None
    for topic, t, msg in msgs:
        header = msg.markers[0].header if topic == '/ground_truth/objects' else msg.header
        assert header.stamp.sec * 10**9 + header.stamp.nanosec == t, f'{topic}: header stamp != log time'
        world = topic in ('/camera/pose', '/slam/points', '/ground_truth/objects')
        assert header.frame_id == ('world' if world else 'camera_color_optical_frame'), f'{topic}: frame id'
        if topic == '/camera/color/camera_info':
            info = msg
            assert msg.distortion_model == 'plumb_bob' and msg.k[0] > 0 and msg.k[4] > 0
        elif topic.startswith('/camera/') and topic.endswith(('image_raw', 'instances')):
            assert info is not None, f'{topic} before the first camera info'
            assert (msg.width, msg.height) == (info.width, info.height), f'{topic}: size differs from camera info'
            expected = 'rgb8' if topic == '/camera/color/image_raw' else '16UC1'
            assert msg.encoding == expected and msg.is_bigendian == 0, f'{topic}: encoding {msg.encoding}'
        elif topic == '/slam/points':
            assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [('x', 0, 7), ('y', 4, 7), ('z', 8, 7)]
        out.setdefault(topic, []).append((t, msg))
    stamps = [t for t, _ in out.get('/camera/color/image_raw', [])]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps), 'image stamps not strictly increasing'
    return out
