"""Box world: upright boxes on a floor seen by a walking camera, rendered as contract instance images
(numpy/OpenCV, no ROS, no mesh renderer); `make_furniture_scene` does the same walk with procedural furniture
meshes rendered by `frodo_datasets.render`. Used to test and evaluate the association stage (paper Sec. 5.1)
with exact ground truth: which object each instance is and how much of it is visible.

A box is convex, so its silhouette is the convex hull of its projected corners; instances are painted far to
near (by centre depth), which gives the occlusions. Noise models: mask noise (each instance mask dilated or
eroded by a random radius up to `mask_noise` pixels), pose noise (each camera pose perturbed by a random
rotation of `rot_noise_deg` and translation of `trans_noise` metres, standard deviations; the associator sees
the noisy pose, the image comes from the true one) and missed detections (`miss_rate`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from frodo_common.geometry import box_corners, invert_transform, look_at, project_points

CHAIR, TABLE = 62, 67
# (min, max) size per axis (dx, dy, dz) in metres, per class.
_SIZES = {CHAIR: ((0.42, 0.42, 0.8), (0.6, 0.6, 1.0)), TABLE: ((0.9, 0.6, 0.7), (1.6, 0.95, 0.78))}


@dataclass
class BoxObject:
    """A ground-truth object: class, centre (3,), size (dx, dy, dz) (3,), yaw about z."""

    coco_id: int
    center: np.ndarray
    size: np.ndarray
    yaw: float

    def corners(self) -> np.ndarray:
        """(8, 3) world corners."""
        return box_corners(self.center, self.size, self.yaw)


@dataclass
class SynthFrame:
    """One camera frame: true and observed (noisy) pose, intrinsics, instance image and its ground truth.

    gt: instance label -> object index; visibility: label -> visible pixels / projected box area;
    landmarks: the SLAM map (P, 3) (world) as it stood at this frame (a bag's latest /slam/points), if any.
    """

    stamp: int
    K: np.ndarray
    T_world_camera: np.ndarray
    T_world_camera_observed: np.ndarray
    size: tuple[int, int]
    instances: np.ndarray
    gt: dict[int, int] = field(default_factory=dict)
    visibility: dict[int, float] = field(default_factory=dict)
    depth: np.ndarray | None = None
    landmarks: np.ndarray | None = None


@dataclass
class SynthScene:
    """Objects and frames of one scene, optionally with sparse SLAM landmarks (P, 3) (world)."""

    objects: list[BoxObject]
    frames: list[SynthFrame]
    landmarks: np.ndarray | None = None


def random_objects(n: int, rng: np.random.Generator, extent: float = 1.6, max_tables: int = 1) -> list[BoxObject]:
    """`n` non-overlapping upright boxes standing on z = 0 in [-extent, extent]^2: chairs, up to `max_tables` tables."""
    objects: list[BoxObject] = []
    for i in range(n):
        coco = TABLE if i < max_tables and rng.random() < 0.6 else CHAIR
        lo, hi = (np.array(v) for v in _SIZES[coco])
        for _ in range(1000):
            size = rng.uniform(lo, hi)
            xy = rng.uniform(-extent, extent, 2)
            radius = 0.5 * np.hypot(size[0], size[1])
            if all(np.linalg.norm(xy - o.center[:2]) > radius + 0.5 * np.hypot(*o.size[:2]) + 0.15 for o in objects):
                break
        else:
            raise RuntimeError(f'could not place {n} objects in a {2 * extent} m square')
        objects.append(BoxObject(coco, np.array([xy[0], xy[1], size[2] / 2]), size, float(rng.uniform(-np.pi, np.pi))))
    return objects


def walk_poses(n_frames: int, rng: np.random.Generator, radius: float = 3.6, sweep_deg: float = 240.0) -> np.ndarray:
    """Camera poses T_world_camera (F, 4, 4) walking an arc around the origin, looking roughly at the scene."""
    start = rng.uniform(0, 2 * np.pi)
    angles = start + np.radians(sweep_deg) * np.linspace(0, 1, n_frames)
    r = radius + 0.4 * np.sin(np.linspace(0, 2 * np.pi, n_frames) + rng.uniform(0, 2 * np.pi))
    height = rng.uniform(1.3, 1.7)
    wander = rng.normal(0, 0.5, (2, 2))
    poses = []
    for k, (a, rk) in enumerate(zip(angles, r)):
        s = k / max(n_frames - 1, 1)
        target = np.array([*(wander[0] * np.sin(np.pi * s) + wander[1] * np.sin(2 * np.pi * s)), 0.3])
        eye = np.array([rk * np.cos(a), rk * np.sin(a), height + 0.1 * np.sin(3 * a)])
        poses.append(look_at(eye, target))
    return np.array(poses)


def _perturb(T: np.ndarray, rng: np.random.Generator, rot_deg: float, trans: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.normal(0, rot_deg)) if rot_deg > 0 else 0.0
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    out = T.copy()
    out[:3, :3] = R @ T[:3, :3]
    out[:3, 3] += rng.normal(0, trans, 3) if trans > 0 else 0.0
    return out


def render_instances(objects: list[BoxObject], K: np.ndarray, T_world_camera: np.ndarray, size: tuple[int, int],
                     near: float = 0.1) -> tuple[np.ndarray, dict[int, int], dict[int, float]]:
    """Instance image (H, W) uint16 of the boxes (far to near), with label -> object index and visibility."""
    w, h = size
    T_cw = invert_transform(T_world_camera)
    depth = np.array([(T_cw[:3, :3] @ o.center + T_cw[:3, 3])[2] for o in objects])
    out = np.zeros((h, w), np.uint16)
    areas: dict[int, float] = {}
    gt: dict[int, int] = {}
    k = 0
    for i in np.argsort(-depth):
        uv, z = project_points(K, T_cw, objects[i].corners())
        if np.any(z < near):
            continue
        hull = cv2.convexHull(np.round(uv * 16).astype(np.int32))       # 4 fractional bits
        poly = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(poly, hull, 1, lineType=cv2.LINE_8, shift=4)
        if not poly.any():
            continue
        k += 1
        label = objects[i].coco_id * 256 + k
        out[poly.astype(bool)] = label
        gt[label] = int(i)
        areas[label] = cv2.contourArea(hull.astype(np.float32) / 16)
    visibility = {lab: float(np.sum(out == lab)) / max(areas[lab], 1.0) for lab in gt}
    present = {lab for lab in gt if visibility[lab] > 0}
    return out, {lab: gt[lab] for lab in present}, {lab: visibility[lab] for lab in present}


def _noisy_masks(instances: np.ndarray, rng: np.random.Generator, radius: int, miss_rate: float) -> np.ndarray:
    """Dilate or erode each instance by a random radius in [-radius, radius]; drop instances at miss_rate."""
    out = np.zeros_like(instances)
    for lab in np.unique(instances[instances > 0]):
        if rng.random() < miss_rate:
            continue
        mask = (instances == lab).astype(np.uint8)
        r = int(rng.integers(-radius, radius + 1)) if radius > 0 else 0
        if r:
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * abs(r) + 1, 2 * abs(r) + 1))
            mask = cv2.dilate(mask, kernel) if r > 0 else cv2.erode(mask, kernel)
        out[(mask > 0) & (out == 0)] = lab
    return out


def add_noise(scene: SynthScene, seed: int, mask_noise: int = 0, rot_noise_deg: float = 0.0,
              trans_noise: float = 0.0, miss_rate: float = 0.0) -> SynthScene:
    """A copy of `scene` with the noise models of `make_scene` applied to its instance images and observed
    poses (perturbing the true ones), e.g. for a scene read from a bag (`evaluate.scene_from_bag`)."""
    if not (mask_noise or rot_noise_deg or trans_noise or miss_rate):
        return scene
    rng = np.random.default_rng(seed)
    frames = []
    for f in scene.frames:
        instances, gt, vis = f.instances, f.gt, f.visibility
        if mask_noise or miss_rate:
            instances = _noisy_masks(instances, rng, mask_noise, miss_rate)
            present = set(np.unique(instances).tolist())
            gt = {lab: i for lab, i in gt.items() if lab in present}
            vis = {lab: v for lab, v in vis.items() if lab in present}
        observed = _perturb(f.T_world_camera, rng, rot_noise_deg, trans_noise) \
            if (rot_noise_deg or trans_noise) else f.T_world_camera_observed
        frames.append(SynthFrame(f.stamp, f.K, f.T_world_camera, observed, f.size, instances, gt, vis, f.depth))
    return SynthScene(scene.objects, frames, scene.landmarks)


def make_scene(n_objects: int, seed: int, n_frames: int = 60, size: tuple[int, int] = (320, 240),
               mask_noise: int = 0, rot_noise_deg: float = 0.0, trans_noise: float = 0.0,
               miss_rate: float = 0.0, fps: float = 10.0, extent: float = 1.6, radius: float = 3.6,
               sweep_deg: float = 240.0) -> SynthScene:
    """A seeded box-world walk: `n_objects` boxes in [-extent, extent]^2, `n_frames` frames of `size`
    (width, height) from a camera walking an arc of `sweep_deg` at about `radius` from the origin."""
    rng = np.random.default_rng(seed)
    objects = random_objects(n_objects, rng, extent)
    w, h = size
    f = 0.9 * w
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    frames = []
    for k, T in enumerate(walk_poses(n_frames, rng, radius, sweep_deg)):
        instances, gt, vis = render_instances(objects, K, T, size)
        if mask_noise or miss_rate:
            instances = _noisy_masks(instances, rng, mask_noise, miss_rate)
            present = set(np.unique(instances).tolist())
            gt = {lab: i for lab, i in gt.items() if lab in present}
            vis = {lab: v for lab, v in vis.items() if lab in present}
        observed = _perturb(T, rng, rot_noise_deg, trans_noise) if (rot_noise_deg or trans_noise) else T.copy()
        frames.append(SynthFrame(int(1e9 + k * 1e9 / fps), K, T, observed, size, instances, gt, vis))
    return SynthScene(objects, frames)


def make_furniture_scene(n_objects: int, seed: int, n_frames: int = 60, size: tuple[int, int] = (640, 480),
                         mask_noise: int = 0, rot_noise_deg: float = 0.0, trans_noise: float = 0.0,
                         miss_rate: float = 0.0, fps: float = 10.0) -> SynthScene:
    """Like `make_scene`, with procedural chairs and tables (`frodo_datasets.shapes`) rendered by the
    `frodo_datasets.render` ray caster instead of boxes: real silhouettes (legs, backs, holes). Ground-truth
    boxes are the meshes' upright bounding boxes; visibility is not computed (empty)."""
    from frodo_datasets.render import Renderer, RenderObject
    from frodo_datasets.shapes import generate
    from frodo_common.geometry import make_transform, yaw_matrix

    names = {CHAIR: 'chair', TABLE: 'dining table'}
    rng = np.random.default_rng(seed)
    objects: list[BoxObject] = []
    meshes = []
    for i in range(n_objects):
        coco = TABLE if i == 0 and rng.random() < 0.6 else CHAIR
        mesh = generate(names[coco], int(rng.integers(0, 10_000)))
        ext = np.asarray(mesh.bounding_box.extents, dtype=np.float64)
        for _ in range(1000):
            xy = rng.uniform(-1.6, 1.6, 2)
            if all(np.linalg.norm(xy - o.center[:2]) > 0.5 * np.hypot(*ext[:2]) + 0.5 * np.hypot(*o.size[:2]) + 0.15
                   for o in objects):
                break
        else:
            raise RuntimeError(f'could not place {n_objects} objects')
        yaw = float(rng.uniform(-np.pi, np.pi))
        center = np.array([xy[0], xy[1], ext[2] / 2])
        mesh = mesh.copy()
        mesh.apply_transform(make_transform(yaw_matrix(yaw), center - yaw_matrix(yaw) @ mesh.bounding_box.centroid))
        objects.append(BoxObject(coco, center, ext, yaw))
        meshes.append(RenderObject(mesh, label=i + 1))
    renderer = Renderer(meshes)
    w, h = size
    K = np.array([[0.9 * w, 0, (w - 1) / 2], [0, 0.9 * w, (h - 1) / 2], [0, 0, 1.0]])
    codes = np.array([0] + [o.coco_id * 256 + i + 1 for i, o in enumerate(objects)], dtype=np.uint16)
    frames = []
    for k, T in enumerate(walk_poses(n_frames, rng)):
        instances = codes[renderer.render(K, T, w, h, shadows=False).labels]
        if mask_noise or miss_rate:
            instances = _noisy_masks(instances, rng, mask_noise, miss_rate)
        present = set(np.unique(instances).tolist())
        gt = {int(c): i for i, c in enumerate(codes[1:]) if int(c) in present}
        observed = _perturb(T, rng, rot_noise_deg, trans_noise) if (rot_noise_deg or trans_noise) else T.copy()
        frames.append(SynthFrame(int(1e9 + k * 1e9 / fps), K, T, observed, size, instances, gt, {}))
    return SynthScene(objects, frames)

