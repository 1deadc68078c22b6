"""Instance masks for real RGB-D sequences with poses but no annotations: one 3D box per object, drawn once.

    python -m frodo_datasets.annotate fuse SEQ OUT_DIR                       # scene cloud .ply + top-down picture
    python -m frodo_datasets.annotate build ANNOTATION.json SEQ OUT.mcap     # masks -> contract bag + .gt.json
    python -m frodo_datasets.annotate measure BAG... --out DIR [--readme data/real/README.md]

The sequence is read by the TUM converter (`convert.tum.read_tum`; lens distortion removed first, so every
step works on pinhole images). Steps:

1. `fuse`: every K-th depth image back-projected into the dataset world and averaged in voxels (position and
   colour): `scene.ply` to look at, `topdown.png` (height-coloured, metre grid) and a height histogram to read
   the floor and a table top from. The user writes the object's box (centre, size, yaw about z, in the
   dataset's world) into an annotation JSON.
2. `build`: per annotated object a truncated signed distance volume (TSDF, projective distance, running
   weighted mean) is fused over the box only, and its zero level set (marching cubes) is the object's surface
   mesh: everything inside the box, nothing outside (set the box bottom above the floor and its top below what
   stands on the object). In every written frame the mesh is ray cast (`render.Renderer`) and a pixel belongs to
   the object where the frame's own depth does not lie in front of the mesh surface by more than
   `depth_tolerance` (or has no measurement): occlusion by anything else in the room is taken from the real
   depth. A small morphological close fills speckle; masks under `min_pixels` are dropped. The bag is written
   by the converter's writer (`convert.writer.write_bag`, gravity alignment as chosen) with the meshes as
   `/ground_truth/objects`, and a `<stem>.gt.json` sidecar (camera, per-frame poses, the boxes in the bag's world).
3. `measure`: `frodo reconstruct` per bag and a table: objects found, centre error of the nearest prediction of
   the object's class to the annotated box centre, and the CONTRACT.md scores against the fused meshes.

Annotation JSON: `{"sequence": ..., "intrinsics": "fr1", "pair_by_order": false, "trajectory": "groundtruth.txt",
"gravity": "none", "objects": [{"id": 1, "class": "dining table", "name": "desk", "box": {"center": [x, y, z],
"size": [dx, dy, dz], "yaw_deg": a}, "how": "..."}]}` (boxes in the world of the sequence's trajectory; an
optional `truth_box` per object, the true box when the dataset has one, is what `measure` scores against).
Limits: a surface seen in no frame is not in the mesh, so its pixels are missed in frames that see it from
further away; depth holes (black, shiny, far surfaces) are filled only where the mesh has surface; the box
must separate the object from what touches it (a chair pushed under a desk is cut with it).
"""
from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import trimesh

from frodo_common.categories import category_by_name
from frodo_common.geometry import yaw_matrix
from frodo_common.host import git_commit
from frodo_datasets.convert.common import (ConvertOptions, GroundTruthObject, Source, SourceFrame, backproject,
                                           select_keyframes, undistort_maps)
from frodo_datasets.convert.tum import read_tum

ANNOTATION_VERSION = 1
RESULTS_BEGIN = '<!-- tum-results:begin (python -m frodo_datasets.annotate measure --readme) -->'
RESULTS_END = '<!-- tum-results:end -->'


# ---------------------------------------------------------------- boxes and annotation files
@dataclass
class AnnotatedBox:
    """An upright box in the dataset world: centre (3,), size (3,) metres, yaw about z (radians)."""

    center: np.ndarray
    size: np.ndarray
    yaw: float

    @classmethod
    def from_dict(cls, d: dict) -> 'AnnotatedBox':
        yaw = np.radians(d['yaw_deg']) if 'yaw_deg' in d else float(d.get('yaw', 0.0))
        return cls(np.asarray(d['center'], float), np.asarray(d['size'], float), float(yaw))

    def T_world_box(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = yaw_matrix(self.yaw)
        T[:3, 3] = self.center
        return T

    def contains(self, points: np.ndarray) -> np.ndarray:
        local = (np.asarray(points) - self.center) @ yaw_matrix(self.yaw)
        return np.all(np.abs(local) <= self.size / 2, axis=1)


@dataclass
class AnnotatedObject:
    object_id: int
    class_name: str
    box: AnnotatedBox
    name: str = ''
    truth: AnnotatedBox | None = None  # the object's true box when known (scored against); else `box`

    @property
    def reference(self) -> AnnotatedBox:
        return self.truth if self.truth is not None else self.box


def load_annotation(path: str | Path) -> dict:
    """The annotation JSON with `objects` parsed into AnnotatedObject (classes checked against the contract)."""
    doc = json.loads(Path(path).read_text())
    objects = []
    for o in doc['objects']:
        category_by_name(o['class'])  # KeyError naming the known classes
        truth = AnnotatedBox.from_dict(o['truth_box']) if 'truth_box' in o else None
        objects.append(AnnotatedObject(int(o['id']), o['class'], AnnotatedBox.from_dict(o['box']), o.get('name', ''),
                                       truth))
    doc['parsed_objects'] = objects
    return doc


def read_sequence(folder: str | Path, doc: dict | None = None) -> Source:
    """The TUM-layout sequence with the reader options of the annotation (intrinsics, trajectory, pairing),
    lens distortion removed (`undistorted`)."""
    doc = doc or {}
    kwargs = {k: doc[k] for k in ('intrinsics', 'trajectory', 'pair_by_order', 'max_dt') if k in doc}
    return undistorted(read_tum(folder, **kwargs))


def undistorted(source: Source) -> Source:
    """The source with colour and depth remapped to the undistorted pinhole K (as the writer would), dist None."""
    maps = undistort_maps(source.K_color, source.dist, source.color_size)
    if maps is None:
        return source

    def wrap(frame: SourceFrame) -> SourceFrame:
        color, depth = frame.color, frame.depth
        return SourceFrame(frame.index, frame.stamp_ns, frame.pose,
                           lambda: cv2.remap(color(), *maps, interpolation=cv2.INTER_LINEAR),
                           None if depth is None else lambda: cv2.remap(depth(), *maps, interpolation=cv2.INTER_NEAREST),
                           frame.instances)
    source.frames = [wrap(f) for f in source.frames]
    source.dist = None
    return source


# ---------------------------------------------------------------- scene point fusion (for picking a box)
def fuse_points(source: Source, every: int = 10, stride: int = 4, voxel: float = 0.02,
                max_depth: float = 4.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every `every`-th frame's depth (every `stride`-th pixel) in the world, averaged per voxel:
    (points (N, 3), colours (N, 3) uint8, counts (N,)), sorted by voxel key (deterministic)."""
    pts_all, rgb_all = [], []
    for i in select_keyframes(len(source.frames), every=every):
        f = source.frames[i]
        depth, rgb = f.depth(), f.color()
        sub = depth[::stride, ::stride]
        ok = (sub > 0) & (sub < max_depth)
        pts_all.append(backproject(depth, source.K_color, f.pose, stride=stride, max_depth=max_depth))
        rgb_all.append(rgb[::stride, ::stride][ok])
    pts = np.concatenate(pts_all)
    rgb = np.concatenate(rgb_all).astype(np.float64)
    keys = np.floor(pts / voxel).astype(np.int64)
    uniq, inverse, count = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    mean = np.zeros((len(uniq), 3))
    colour = np.zeros((len(uniq), 3))
    for k in range(3):
        mean[:, k] = np.bincount(inverse, pts[:, k], len(uniq)) / count
        colour[:, k] = np.bincount(inverse, rgb[:, k], len(uniq)) / count
    return mean, np.clip(np.round(colour), 0, 255).astype(np.uint8), count


def topdown_image(points: np.ndarray, colours: np.ndarray, path: Path, pixel: float = 0.01,
                  boxes: list[AnnotatedBox] = ()) -> None:
    """Orthographic top view (x right, y up) of the highest point per pixel, coloured by height, a 0.5 m grid
    (labelled each metre) and the given boxes' outlines."""
    lo, hi = points[:, :2].min(axis=0) - 0.1, points[:, :2].max(axis=0) + 0.1
    w, h = (np.ceil((hi - lo) / pixel).astype(int) + 1)
    ij = np.floor((points[:, :2] - lo) / pixel).astype(int)
    order = np.argsort(points[:, 2], kind='stable')
    z = np.full((h, w), np.nan)
    z[h - 1 - ij[order, 1], ij[order, 0]] = points[order, 2]
    zlo, zhi = np.nanpercentile(z, 2), np.nanpercentile(z, 98)
    norm = np.clip((np.nan_to_num(z, nan=zlo) - zlo) / max(zhi - zlo, 1e-6) * 255, 0, 255).astype(np.uint8)
    img = cv2.applyColorMap(norm, cv2.COLORMAP_VIRIDIS)
    img[np.isnan(z)] = 255
    for g in np.arange(np.ceil(lo[0] * 2) / 2, hi[0], 0.5):
        u = int((g - lo[0]) / pixel)
        cv2.line(img, (u, 0), (u, h - 1), (160, 160, 160), 1)
        if abs(g - round(g)) < 1e-6:
            cv2.putText(img, f'x={g:.0f}', (u + 2, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
    for g in np.arange(np.ceil(lo[1] * 2) / 2, hi[1], 0.5):
        v = h - 1 - int((g - lo[1]) / pixel)
        cv2.line(img, (0, v), (w - 1, v), (160, 160, 160), 1)
        if abs(g - round(g)) < 1e-6:
            cv2.putText(img, f'y={g:.0f}', (2, v - 2), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
    for b in boxes:
        c = np.array([[sx, sy] for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]) * b.size[:2] / 2
        c = c @ yaw_matrix(b.yaw)[:2, :2].T + b.center[:2]
        uv = np.stack([(c[:, 0] - lo[0]) / pixel, h - 1 - (c[:, 1] - lo[1]) / pixel], axis=1).astype(np.int32)
        cv2.polylines(img, [uv], True, (0, 0, 255), 2)
    cv2.putText(img, f'height {zlo:.2f} (dark) .. {zhi:.2f} m (yellow)', (2, h - 4), cv2.FONT_HERSHEY_SIMPLEX,
                0.35, (0, 0, 0), 1)
    cv2.imwrite(str(path), img)


def height_peaks(z: np.ndarray, bin_m: float = 0.02, count: int = 6) -> list[tuple[float, int]]:
    """The `count` most populated heights (bin centre, points), highest count first: floor and table tops."""
    edges = np.arange(np.floor(z.min() / bin_m) * bin_m, z.max() + bin_m, bin_m)
    hist, edges = np.histogram(z, edges)
    peaks = [i for i in range(len(hist)) if hist[i] > 0 and hist[i] >= hist[max(i - 1, 0)]
             and hist[i] >= hist[min(i + 1, len(hist) - 1)]]
    peaks.sort(key=lambda i: -hist[i])
    return [(float((edges[i] + edges[i + 1]) / 2), int(hist[i])) for i in peaks[:count]]


# ---------------------------------------------------------------- object TSDF
class BoxTSDF:
    """A truncated signed distance volume over one box (own small implementation: projective distance along
    the optical axis, truncated to +-`trunc`, running weighted mean with weight 1 per observation)."""

    def __init__(self, box: AnnotatedBox, voxel: float = 0.01, trunc: float | None = None):
        self.box, self.voxel = box, float(voxel)
        self.trunc = float(trunc) if trunc is not None else 4 * self.voxel
        self.shape = tuple(int(n) for n in np.maximum(np.ceil(box.size / voxel).astype(int), 2))
        axes = [(np.arange(n) + 0.5) * voxel - s / 2 for n, s in zip(self.shape, np.array(self.shape) * voxel)]
        grid = np.stack(np.meshgrid(*axes, indexing='ij'), axis=-1).reshape(-1, 3)
        self.local_origin = np.array([a[0] for a in axes])
        self.centres = grid @ yaw_matrix(box.yaw).T + box.center  # world
        self.tsdf = np.ones(len(grid), np.float32)
        self.weight = np.zeros(len(grid), np.float32)

    def integrate(self, depth: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray, max_depth: float = 4.0) -> None:
        R, t = T_world_camera[:3, :3], T_world_camera[:3, 3]
        pc = (self.centres - t) @ R
        z = pc[:, 2]
        front = z > 0.05
        u = np.full(len(z), -1, np.int64)
        v = np.full(len(z), -1, np.int64)
        u[front] = np.round(K[0, 0] * pc[front, 0] / z[front] + K[0, 2]).astype(np.int64)
        v[front] = np.round(K[1, 1] * pc[front, 1] / z[front] + K[1, 2]).astype(np.int64)
        h, w = depth.shape
        ok = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        idx = np.nonzero(ok)[0]
        d = depth[v[idx], u[idx]]
        good = (d > 0) & (d < max_depth) & np.isfinite(d)
        idx, d = idx[good], d[good]
        sdf = d - z[idx]
        near = sdf > -self.trunc
        idx, sdf = idx[near], np.minimum(sdf[near], self.trunc) / self.trunc
        wgt = self.weight[idx]
        self.tsdf[idx] = (self.tsdf[idx] * wgt + sdf) / (wgt + 1)
        self.weight[idx] = wgt + 1

    def mesh(self, min_weight: float = 2.0) -> trimesh.Trimesh:
        """Zero level set (marching cubes over voxels observed at least `min_weight` times), world frame."""
        from skimage.measure import marching_cubes
        vol = self.tsdf.reshape(self.shape)
        mask = (self.weight >= min_weight).reshape(self.shape)
        if not mask.any() or vol[mask].min() > 0 or vol[mask].max() < 0:
            return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)
        verts, faces, _, _ = marching_cubes(vol, 0.0, spacing=(self.voxel,) * 3, mask=mask)
        local = verts + self.local_origin
        world = local @ yaw_matrix(self.box.yaw).T + self.box.center
        mesh = trimesh.Trimesh(world, faces, process=False)
        mesh.merge_vertices()
        # keep the parts that carry the surface: drop specks (< 2 % of the largest connected part's faces)
        parts = mesh.split(only_watertight=False)
        if len(parts) > 1:
            big = max(len(p.faces) for p in parts)
            mesh = trimesh.util.concatenate([p for p in parts if len(p.faces) >= 0.02 * big])
        return mesh


def fuse_object(source: Source, box: AnnotatedBox, every: int = 2, voxel: float = 0.01,
                max_depth: float = 4.0) -> trimesh.Trimesh:
    """The object's surface mesh: TSDF over `box` from every `every`-th frame."""
    vol = BoxTSDF(box, voxel)
    for i in select_keyframes(len(source.frames), every=every):
        f = source.frames[i]
        vol.integrate(f.depth(), source.K_color, f.pose, max_depth)
    return vol.mesh()


# ---------------------------------------------------------------- masks
def object_masks(meshes: list[trimesh.Trimesh], depth: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray,
                 depth_tolerance: float = 0.05, close_px: int = 5, renderer=None) -> np.ndarray:
    """Label image (H, W) uint16: i+1 where object i's mesh is the nearest surface and the frame's own depth
    is not in front of it by more than `depth_tolerance` (plus 2 % of the range), 0 elsewhere."""
    from frodo_datasets.render import RenderObject, Renderer
    h, w = depth.shape
    renderer = renderer or Renderer([RenderObject(m, label=i + 1) for i, m in enumerate(meshes) if len(m.faces)])
    res = renderer.render(K, T_world_camera, w, h, shadows=False)
    z = res.depth
    visible = (res.labels > 0) & ((depth <= 0) | ~np.isfinite(depth) | (depth >= z - depth_tolerance - 0.02 * z))
    out = np.zeros((h, w), np.uint16)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (close_px, close_px)) if close_px > 1 else None
    for label in np.unique(res.labels[visible]):
        m = (visible & (res.labels == label)).astype(np.uint8)
        if kernel is not None:
            m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, kernel)
        out[(m > 0) & (out == 0)] = label
    return out


def encode_instances(labels: np.ndarray, objects: list[AnnotatedObject], min_pixels: int) -> np.ndarray:
    """Object labels (1-based index into `objects`) -> contract `coco_id * 256 + k`, k = 1, 2, ... per frame in
    object order; masks under `min_pixels` are dropped."""
    out = np.zeros(labels.shape, np.uint16)
    k = 0
    for i, obj in enumerate(objects):
        m = labels == i + 1
        if np.count_nonzero(m) < min_pixels:
            continue
        k += 1
        out[m] = category_by_name(obj.class_name).coco_id * 256 + k
    return out


# ---------------------------------------------------------------- build a bag
def build_bag(annotation: str | Path, sequence: str | Path, output: str | Path, views: int | None = None,
              resize: float | None = None, every_fuse: int = 2, voxel: float = 0.01, depth_tolerance: float = 0.05,
              min_pixels: int = 200, mesh_dir: Path | None = None, log=print) -> dict:
    """Masks from the annotation's boxes -> contract bag `output` + `<stem>.gt.json`; returns the sidecar."""
    from frodo_datasets.convert.writer import write_bag
    from frodo_datasets.render import RenderObject, Renderer
    from frodo_datasets.synth import sidecar_path
    doc = load_annotation(annotation)
    objects: list[AnnotatedObject] = doc['parsed_objects']
    source = read_sequence(sequence, doc)
    meshes = []
    for obj in objects:
        mesh = fuse_object(source, obj.box, every=every_fuse, voxel=voxel)
        log(f'object {obj.object_id} ({obj.class_name}, {obj.name}): fused mesh {len(mesh.vertices)} vertices, '
            f'extents {np.round(mesh.extents, 3).tolist() if len(mesh.vertices) else None}')
        if not len(mesh.faces):
            raise RuntimeError(f'object {obj.object_id}: no surface inside its box; check the box and the frame')
        meshes.append(mesh)
        if mesh_dir is not None:
            mesh_dir.mkdir(parents=True, exist_ok=True)
            mesh.export(mesh_dir / f'{obj.object_id}_{obj.class_name.replace(" ", "_")}.ply')
    renderer = Renderer([RenderObject(m, label=i + 1) for i, m in enumerate(meshes)])
    K = source.K_color
    pixels = {o.object_id: 0 for o in objects}
    masked_frames = {o.object_id: 0 for o in objects}

    def instances_of(frame: SourceFrame):
        def load():
            labels = object_masks(meshes, frame.depth(), K, frame.pose, depth_tolerance, renderer=renderer)
            inst = encode_instances(labels, objects, min_pixels)
            for i, o in enumerate(objects):
                n = int(np.count_nonzero((labels == i + 1) & (inst > 0)))
                pixels[o.object_id] += n
                masked_frames[o.object_id] += int(n > 0)
            return inst
        return load
    for f in source.frames:
        f.instances = instances_of(f)
    source.ground_truth = [GroundTruthObject(o.class_name, o.object_id, np.asarray(m.vertices), np.asarray(m.faces))
                           for o, m in zip(objects, meshes)]
    options = ConvertOptions(views=views, resize=resize, gravity=doc.get('gravity', 'auto'),
                             up=tuple(doc['up']) if 'up' in doc else None)
    summary = write_bag(source, output, options)
    log(summary.text())
    T = summary.T_aligned_dataset
    # the written frames: the writer's keyframe choice over the frames with valid poses
    picks = [source.frames[i] for i in select_keyframes(len(source.frames), views)]
    from frodo_datasets.convert.common import scale_intrinsics
    K_out = scale_intrinsics(K, source.color_size, summary.size)
    side = {
        'source': {'annotation': str(annotation), 'sequence': str(sequence), 'gravity': summary.gravity,
                   'T_world_dataset': T.tolist()},
        'config': {'min_mask_pixels': min_pixels, 'depth_tolerance': depth_tolerance, 'voxel': voxel},
        'camera': {'K': K_out.tolist(), 'width': summary.size[0], 'height': summary.size[1],
                   'frame_id': 'camera_color_optical_frame'},
        'frames': [{'stamp_ns': f.stamp_ns, 'T_world_camera': (T @ f.pose).tolist()} for f in picks],
        'scene': {'objects': []},
    }
    for o, m in zip(objects, meshes):
        Tb = T @ o.reference.T_world_box()
        side['scene']['objects'].append({
            'id': o.object_id, 'class': o.class_name, 'coco_id': category_by_name(o.class_name).coco_id,
            'name': o.name, 'T_world_object': Tb.tolist(), 'extents': o.reference.size.tolist(),
            'cut_box': {'center': (T[:3, :3] @ o.box.center + T[:3, 3]).tolist(), 'size': o.box.size.tolist()},
            'box_center': Tb[:3, 3].tolist(), 'box_yaw': float(np.arctan2(Tb[1, 0], Tb[0, 0])),
            'mesh_extents': np.asarray(m.extents).tolist(),
            'masked_frames': masked_frames[o.object_id], 'mask_pixels': pixels[o.object_id]})
    path = sidecar_path(Path(output))
    path.write_text(json.dumps(side, indent=1) + '\n')
    for o in side['scene']['objects']:
        log(f'object {o["id"]}: masks in {o["masked_frames"]} of {summary.frames_written} frames')
    return side


# ---------------------------------------------------------------- measure
def measure_row(bag: Path, run_dir: Path) -> dict:
    """Objects found, centre error of the nearest same-class prediction to each annotated box, eval scores."""
    from frodo_datasets.synth import sidecar_path
    side = json.loads(sidecar_path(bag).read_text())
    pred = json.loads((run_dir / 'objects.json').read_text())
    pred = pred['objects'] if isinstance(pred, dict) else pred
    ev = json.loads((run_dir / 'eval.json').read_text()) if (run_dir / 'eval.json').is_file() else {}
    rows = []
    for o in side['scene']['objects']:
        same = [p for p in pred if p.get('class') == o['class'] and p.get('box')]
        c = np.asarray(o['box_center'])
        errs = [float(np.linalg.norm(np.asarray(p['box']['center']) - c)) for p in same]
        best = int(np.argmin(errs)) if errs else None
        rows.append({'id': o['id'], 'class': o['class'], 'name': o.get('name', ''),
                     'centre_error_cm': 100 * errs[best] if errs else None,
                     'size_pred': same[best]['box']['size'] if errs else None, 'size_true': o['extents']})
    return {'bag': bag.name, 'frames': len(side['frames']), 'size_mb': bag.stat().st_size / 1e6,
            'found': len(pred), 'found_by_class': {c: sum(p.get('class') == c for p in pred)
                                                   for c in sorted({p.get('class') for p in pred})},
            'objects': rows, 'eval': ev.get('overall', {})}


RUN_COMMIT = 'commit.txt'     # in a measure run's folder: the commit that reconstructed it


def has_results_of(run_dir: Path, commit: str) -> bool:
    """Whether run_dir holds a reconstruction made at `commit` (results of another commit are not this one's)."""
    stamp = run_dir / RUN_COMMIT
    return (run_dir / 'objects.json').is_file() and stamp.is_file() and stamp.read_text().strip() == commit


def measure_table(results: list[dict], commit: str) -> str:
    lines = [f'`python -m frodo_datasets.annotate measure` on {platform.node()} ({platform.machine()}, '
             f'{platform.python_implementation()} {platform.python_version()}), commit {commit}:', '',
             '| bag | frames | size (MB) | objects found | annotated object | centre error (cm) | box size found / annotated (m) | F1@5cm (%) | CD (cm) |',
             '|---|---|---|---|---|---|---|---|---|']
    for r in results:
        found = ', '.join(f'{n} {c}' for c, n in r['found_by_class'].items()) or '0'
        ev = r['eval']
        f1, cd = ev.get('f1'), ev.get('cd_cm')
        for o in r['objects']:
            err = f'{o["centre_error_cm"]:.1f}' if o['centre_error_cm'] is not None else 'not found'
            size = ('x'.join(f'{v:.2f}' for v in o['size_pred']) if o['size_pred'] else '-') + ' / ' + \
                'x'.join(f'{v:.2f}' for v in o['size_true'])
            lines.append(f'| `{r["bag"]}` | {r["frames"]} | {r["size_mb"]:.1f} | {found} | {o["name"]} ({o["class"]}) | '
                         f'{err} | {size} | {_fmt(f1)} | {_fmt(cd)} |')
    return '\n'.join(lines)


def _fmt(v) -> str:
    return f'{v:.1f}' if isinstance(v, (int, float)) else '-'


def replace_section(readme: Path, text: str) -> None:
    """Put `text` between the RESULTS_BEGIN/RESULTS_END markers of `readme` (appended when absent)."""
    body = readme.read_text()
    block = f'{RESULTS_BEGIN}\n{text}\n{RESULTS_END}'
    if RESULTS_BEGIN in body and RESULTS_END in body:
        head, rest = body.split(RESULTS_BEGIN, 1)
        body = head + block + rest.split(RESULTS_END, 1)[1]
    else:
        body = body.rstrip('\n') + '\n\n' + block + '\n'
    readme.write_text(body)


# ---------------------------------------------------------------- CLI
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m frodo_datasets.annotate', description=__doc__.split('\n')[0])
    sub = parser.add_subparsers(dest='command', required=True)
    p = sub.add_parser('fuse', help='scene point cloud (.ply), top-down picture and height peaks, to pick boxes')
    p.add_argument('sequence', type=Path)
    p.add_argument('out', type=Path)
    p.add_argument('--annotation', type=Path, help='reader options and boxes to draw (optional)')
    p.add_argument('--every', type=int, default=10)
    p.add_argument('--voxel', type=float, default=0.02)
    p.add_argument('--max-depth', type=float, default=4.0)
    p = sub.add_parser('build', help='masks from the annotation boxes -> contract bag + .gt.json sidecar')
    p.add_argument('annotation', type=Path)
    p.add_argument('sequence', type=Path)
    p.add_argument('output', type=Path)
    p.add_argument('--views', type=int, help='keyframes spread evenly (default: all frames)')
    p.add_argument('--resize', type=float, help='output scale, e.g. 0.5')
    p.add_argument('--every-fuse', type=int, default=2, help='fuse every K-th frame into the object TSDF')
    p.add_argument('--voxel', type=float, default=0.01, help='TSDF voxel (m)')
    p.add_argument('--depth-tolerance', type=float, default=0.05, help='m (plus 2 %% of the range)')
    p.add_argument('--min-pixels', type=int, default=200, help='smaller masks are dropped (source resolution)')
    p.add_argument('--mesh-dir', type=Path, help='also write the fused object meshes here')
    p = sub.add_parser('measure', help='frodo reconstruct each bag, table of objects found and centre errors')
    p.add_argument('bags', nargs='+', type=Path)
    p.add_argument('--out', required=True, type=Path, help='run folders go to OUT/<bag stem>')
    p.add_argument('--rerun', action='store_true',
                   help='reconstruct again even when OUT/<stem> has results of this commit')
    p.add_argument('--readme', type=Path, help='replace the results block of this markdown file')
    args = parser.parse_args(argv)
    if args.command == 'fuse':
        doc = load_annotation(args.annotation) if args.annotation else {}
        source = read_sequence(args.sequence, doc)
        pts, rgb, count = fuse_points(source, every=args.every, voxel=args.voxel, max_depth=args.max_depth)
        args.out.mkdir(parents=True, exist_ok=True)
        trimesh.PointCloud(pts, colors=rgb).export(args.out / 'scene.ply')
        topdown_image(pts, rgb, args.out / 'topdown.png', boxes=[o.box for o in doc.get('parsed_objects', [])])
        print(f'{len(pts)} voxels of {args.voxel} m from {len(range(0, len(source.frames), args.every))} frames; '
              f'extent min {np.round(pts.min(0), 2).tolist()} max {np.round(pts.max(0), 2).tolist()}')
        print('most populated heights (z m, voxels): ' + ', '.join(f'{z:.2f} ({n})' for z, n in height_peaks(pts[:, 2])))
        print(f'wrote {args.out / "scene.ply"}, {args.out / "topdown.png"}')
        return 0
    if args.command == 'build':
        build_bag(args.annotation, args.sequence, args.output, args.views, args.resize, args.every_fuse, args.voxel,
                  args.depth_tolerance, args.min_pixels, args.mesh_dir)
        return 0
    results = []
    commit = git_commit(Path(__file__).parent) or 'unknown'
    for bag in args.bags:
        run_dir = args.out / bag.stem
        if args.rerun or not has_results_of(run_dir, commit):
            cmd = [sys.executable, '-m', 'frodo_bringup.cli', 'reconstruct', str(bag), '--out', str(run_dir),
                   '--quiet', '--no-recording']
            print('$ ' + ' '.join(cmd[2:]), flush=True)
            rc = subprocess.run(cmd).returncode
            if rc != 0:
                print(f'frodo reconstruct failed on {bag} (exit {rc})', file=sys.stderr)
                return 1
            (run_dir / RUN_COMMIT).write_text(commit + '\n')
        results.append(measure_row(bag, run_dir))
    text = measure_table(results, commit)
    print(text)
    if args.readme:
        replace_section(args.readme, text)
        print(f'updated {args.readme}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
