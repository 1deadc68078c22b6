"""Render a synthetic scene along a camera trajectory into a contract bag (CONTRACT.md inputs + ground truth).

Topics written (all stamps = frame stamp = log time; frames advance by 1/fps from `start_ns`):

| topic | type | content |
|---|---|---|
| `/camera/color/camera_info` | CameraInfo | before the first image and once per frame (plumb_bob, d = 0) |
| `/camera/color/image_raw` | Image `rgb8` | rendered colour (optionally with pixel noise) |
| `/camera/pose` | PoseStamped, frame `world` | T_world_camera (optionally noisy; rendering uses the true pose) |
| `/camera/instances` | Image `16UC1` | `coco_id * 256 + k`, k a random per-frame number (not the object id) |
| `/camera/depth/image_raw` | Image `16UC1` (mm), registered to colour (CONTRACT v1.1) | only with `depth=True` |
| `/slam/points` | PointCloud2 x,y,z float32 | noisy landmarks seen in >= `slam_min_views` frames so far; the whole map every `slam_every` frames and at the end |
| `/ground_truth/objects` | MarkerArray (transient local, depth 1) | one TRIANGLE_LIST per object at the first stamp: ns = class, id = ground-truth id, world vertices |

A JSON sidecar `<bag stem>.gt.json` describes the scene, camera and true poses.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
from visualization_msgs.msg import MarkerArray

from frodo_common import topics
from frodo_common.bag import BagWriter, qos_yaml
from frodo_common.conversions import (make_camera_info, make_pose_stamped, mesh_to_marker, numpy_to_image,
                                      xyz_to_cloud)
from frodo_common.geometry import invert_transform, project_points
from frodo_datasets.degrade import MaskNoise, PoseNoise, PoseNoiser, add_image_noise, degrade_instances
from frodo_datasets.realcapture import (CaptureEffects, blur_vector, distort, distortion_maps, kinect_depth,
                                        motion_blur, photometric, shaken_pose, texture_strength)
from frodo_datasets.render import Light, Realism, Renderer, intrinsics
from frodo_datasets.scene import (CONTINUOUS_PATHS, SCENE_LAYOUT, HandheldPath, Scene, compose_scene,
                                  continuous_path, trajectory)

CAMERA_FRAME = 'camera_color_optical_frame'
DEFAULT_START_NS = 1_700_000_000_000_000_000  # 2023-11-14T22:13:20Z
SIDECAR_SUFFIX = '.gt.json'


@dataclass
class SynthConfig:
    """What to synthesise.

    scene: trajectory and layout, 'walk' (room walk), 'orbit' (object-centric loop), 'handheld' (walk
      layout, close-range hand-held scan with the frames spread over a long path: `scene.HandheldPath`) or
      'insideout' (perimeter layout, a walk through the room's middle looking outwards: `scene.InsideOutPath`).
    min_mask_pixels: visible object parts smaller than this are not reported as instances.
    slam_density: landmarks per m² of object surface (room surfaces get a twentieth of it).
    slam_noise_m: std of the fixed per-landmark position error.
    slam_texture_min: keep only landmarks whose surface texture (`realcapture.texture_strength`) reaches
      this (0 = everywhere, as before; feature-based SLAM has no landmarks on plain surfaces).
    family_set, tuck_chairs, clutter: see `scene.compose_scene`.
    realism: ambient occlusion, soft shadows, specular highlights (`render.Realism`, off by default).
    capture: exposure, vignetting, sensor noise, motion blur, lens distortion, depth noise
      (`realcapture.CaptureEffects`, off by default).
    depth_topic: where `depth=True` writes depth (CONTRACT v1.1 names `/camera/depth/image_raw`).
    """

    scene: str = 'walk'
    objects: int = 3
    classes: tuple[str, ...] = ('chair', 'dining table')
    frames: int = 60
    width: int = 320
    height: int = 240
    seed: int = 0
    fps: float = 10.0
    hfov_deg: float = 60.0
    start_ns: int = DEFAULT_START_NS
    min_mask_pixels: int = 40
    mask_noise: MaskNoise = field(default_factory=MaskNoise)
    pose_noise: PoseNoise = field(default_factory=PoseNoise)
    image_noise: float = 0.0
    depth: bool = False
    slam: bool = True
    slam_every: int = 5
    slam_min_views: int = 3
    slam_density: float = 300.0
    slam_noise_m: float = 0.01
    shadows: bool = True
    world_frame: str = 'world'
    compression: str = 'zstd'
    family_set: str = 'train'
    tuck_chairs: float = 0.0
    clutter: int = 0
    realism: Realism = field(default_factory=Realism)
    capture: CaptureEffects = field(default_factory=CaptureEffects)
    slam_texture_min: float = 0.0
    depth_topic: str = topics.DEPTH


@dataclass
class SynthResult:
    """What was written: the scene, true and published poses (lists of (4, 4)), stamps (ns), message counts."""

    path: Path
    scene: Scene
    K: np.ndarray
    stamps: list[int]
    true_poses: list[np.ndarray]
    published_poses: list[np.ndarray]
    counts: dict[str, int]


class _Landmarks:
    """Simulated SLAM map: fixed noisy surface samples that join the map once seen in enough frames."""

    def __init__(self, scene: Scene, density: float, noise: float, rng: np.random.Generator,
                 texture_min: float = 0.0):
        pts = []
        for obj in scene.render_objects():
            rate = density if obj.label else density / 20
            n = max(1, int(rate * obj.mesh.area))
            samples = trimesh.sample.sample_surface(obj.mesh, n, seed=int(rng.integers(2**31)))[0]
            if texture_min > 0:
                samples = samples[texture_strength(obj.material, samples) >= texture_min]
            pts.append(samples)
        self.true = np.concatenate(pts)
        self.noisy = self.true + rng.normal(0, noise, self.true.shape)
        self.views = np.zeros(len(self.true), dtype=np.int32)

    def observe(self, K: np.ndarray, T_world_camera: np.ndarray, depth: np.ndarray) -> None:
        """Count a view for every landmark in the image and not occluded (depth test against `depth` (H, W))."""
        h, w = depth.shape
        uv, z = project_points(K, invert_transform(T_world_camera), self.true)
        ui, vi = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
        inside = (z > 0.1) & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
        idx = np.flatnonzero(inside)
        d = depth[vi[idx], ui[idx]]
        seen = idx[(d > 0) & (np.abs(d - z[idx]) < 0.01 + 0.02 * z[idx])]
        self.views[seen] += 1

    def map(self, min_views: int) -> np.ndarray:
        """Current map points (N, 3)."""
        return self.noisy[self.views >= min_views]


def instance_image(labels: np.ndarray, scene: Scene, rng: np.random.Generator, min_pixels: int) -> np.ndarray:
    """Contract instance image (H, W) uint16 from a render label image (object ids, 0 = background).

    Objects with fewer than `min_pixels` visible pixels are left out; each kept object gets a random
    per-frame k in 1..255, so k carries no information about the object's identity.
    """
    coco = {o.id: o.coco_id for o in scene.objects}
    ids, areas = np.unique(labels[labels > 0], return_counts=True)
    ids = [int(i) for i, a in zip(ids, areas) if a >= min_pixels]
    ks = rng.choice(np.arange(1, 256), size=len(ids), replace=False)
    lut = np.zeros(max(coco) + 1, dtype=np.uint16)
    for obj_id, k in zip(ids, ks):
        lut[obj_id] = (coco[obj_id] << 8) | int(k)
    return lut[labels]


def ground_truth_markers(scene: Scene, stamp_ns: int, frame_id: str) -> MarkerArray:
    """One TRIANGLE_LIST marker per object (ns = class name, id = ground-truth id, world vertices)."""
    markers = []
    for o in scene.objects:
        mesh = o.mesh_world
        markers.append(mesh_to_marker(mesh.vertices, mesh.faces, o.class_name, o.id, stamp_ns, frame_id,
                                      rgba=(*o.material.color, 1.0)))
    return MarkerArray(markers=markers)


def synthesize(config: SynthConfig, out_path: str | Path, progress: Callable[[int], None] | None = None,
               sidecar: bool = True, scene: Scene | None = None, poses: list[np.ndarray] | None = None,
               K: np.ndarray | None = None) -> SynthResult:
    """Compose the scene, render every frame and write the contract bag to `out_path`.

    `progress(1)` is called after each frame (e.g. `tqdm.update`). Returns a `SynthResult`.
    scene, poses (T_world_camera (4, 4) each, `config.frames` of them) and K (3, 3) replace the composed room,
    the generated trajectory and the `hfov_deg` intrinsics when given (e.g. public furniture models placed
    as in their world file, rendered along a recorded camera trajectory: `frodo_datasets.real_data`).
    """
    if config.frames < 1 or config.width < 8 or config.height < 8:
        raise ValueError('need at least 1 frame and an image of at least 8x8 pixels')
    if poses is not None and len(poses) != config.frames:
        raise ValueError(f'{len(poses)} poses given for {config.frames} frames')
    out_path = Path(out_path)
    rng = np.random.default_rng(config.seed)
    if scene is None:
        layout = SCENE_LAYOUT.get(config.scene, config.scene)
        scene = compose_scene(config.objects, config.classes, seed=config.seed, layout=layout,
                              family_set=config.family_set, tuck_chairs=config.tuck_chairs, clutter=config.clutter)
    path = None
    times = np.arange(config.frames) / config.fps
    if poses is None:
        if config.scene in CONTINUOUS_PATHS:
            path = continuous_path(scene, config.scene, seed=config.seed + 1)
            times = path.keyframe_times(config.frames, seed=config.seed + 1)
            poses = [path.pose(t) for t in times]
        else:
            poses = trajectory(scene, config.scene, config.frames, seed=config.seed + 1, hfov_deg=config.hfov_deg)
    if K is None:
        K = intrinsics(config.width, config.height, config.hfov_deg)
    # Real-capture effects draw from their own stream, so bags without them are unchanged.
    fx_rng = np.random.default_rng([config.seed, 3])
    capture = config.capture
    lens = (distortion_maps(K, capture.distortion, config.width, config.height)
            if any(capture.distortion) else None)
    renderer = Renderer(scene.render_objects())
    elevation, azimuth = rng.uniform(np.radians(45), np.radians(70)), rng.uniform(0, 2 * np.pi)
    light = Light(direction=(-np.cos(elevation) * np.cos(azimuth), -np.cos(elevation) * np.sin(azimuth),
                             -np.sin(elevation)), intensity=0.7)
    landmarks = (_Landmarks(scene, config.slam_density, config.slam_noise_m, rng, config.slam_texture_min)
                 if config.slam else None)
    noiser = PoseNoiser(config.pose_noise, rng)
    stamps = [config.start_ns + int(round(k * 1e9 / config.fps)) for k in range(config.frames)]
    published: list[np.ndarray] = []
    world, w, h = config.world_frame, config.width, config.height
    counts: dict[str, int] = {}
    with BagWriter(out_path, compression=config.compression) as bag:
        def put(topic: str, msg, stamp_ns: int) -> None:
            bag.write(topic, msg, stamp_ns)
            counts[topic] = counts.get(topic, 0) + 1

        bag.add_topic(topics.GROUND_TRUTH, 'visualization_msgs/msg/MarkerArray',
                      qos_yaml(transient_local=True, depth=1))
        put(topics.GROUND_TRUTH, ground_truth_markers(scene, stamps[0], world), stamps[0])
        for k, (stamp, T) in enumerate(zip(stamps, poses)):
            quality = (Realism(**{**asdict(config.realism), 'seed': config.realism.seed + k})
                       if config.realism.active else None)
            res = renderer.render(K, T, w, h, light=light, shadows=config.shadows, background=(0.82, 0.86, 0.9),
                                  quality=quality)
            rgb = add_image_noise(res.rgb, config.image_noise, rng)
            rgb = _camera_effects(rgb, res.depth, K, T, path, float(times[k]), capture, fx_rng)
            labels, depth = res.labels, res.depth
            if lens is not None:
                rgb, labels, depth = distort(rgb, lens), distort(labels, lens, True), distort(depth, lens, True)
            instances = instance_image(labels, scene, rng, config.min_mask_pixels)
            if config.mask_noise.active:
                instances = degrade_instances(instances, config.mask_noise, rng)
            dt = float(times[k] - times[k - 1]) if k else float(times[0])
            T_pub = noiser(T, dt) if config.pose_noise.active else T
            published.append(T_pub)
            info = make_camera_info(K, w, h, stamp, CAMERA_FRAME)
            if lens is not None:
                info.d = [float(capture.distortion[0]), float(capture.distortion[1]), 0.0, 0.0, 0.0]
            put(topics.CAMERA_INFO, info, stamp)
            put(topics.IMAGE, numpy_to_image(rgb, 'rgb8', stamp, CAMERA_FRAME), stamp)
            put(topics.POSE, make_pose_stamped(T_pub, stamp, world), stamp)
            put(topics.INSTANCES, numpy_to_image(instances, '16UC1', stamp, CAMERA_FRAME), stamp)
            if config.depth:
                sensed = kinect_depth(depth, fx_rng) if capture.depth_noise else depth
                depth_mm = np.clip(np.round(sensed * 1000), 0, 65535).astype(np.uint16)
                put(config.depth_topic, numpy_to_image(depth_mm, '16UC1', stamp, CAMERA_FRAME), stamp)
            if landmarks is not None:
                landmarks.observe(K, T, res.depth)
                if (k + 1) % config.slam_every == 0 or k == config.frames - 1:
                    points = landmarks.map(config.slam_min_views)
                    if len(points):
                        put(topics.SLAM_POINTS, xyz_to_cloud(points, stamp, world), stamp)
            if progress is not None:
                progress(1)
    if sidecar:
        write_sidecar(sidecar_path(out_path), config, scene, K, stamps, poses, published, times)
    return SynthResult(out_path, scene, K, stamps, poses, published, counts)


def _camera_effects(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, T: np.ndarray, path: HandheldPath | None,
                    t: float, capture: CaptureEffects, rng: np.random.Generator) -> np.ndarray:
    """Motion blur (needs the continuous `path`), then exposure, vignetting and sensor noise."""
    if capture.motion_blur_s > 0 and path is not None:
        T_end = path.pose(t + capture.motion_blur_s)
        if capture.hand_shake_dps:
            T_end = shaken_pose(T_end, capture.hand_shake_dps, capture.motion_blur_s, rng)
        rgb = motion_blur(rgb, blur_vector(K, depth, T, T_end))
    return photometric(rgb, capture, rng) if capture.photometric else rgb


def sidecar_path(bag_path: str | Path) -> Path:
    """`scene.mcap` -> `scene.gt.json`."""
    bag_path = Path(bag_path)
    return bag_path.with_name(bag_path.stem + SIDECAR_SUFFIX)


def write_sidecar(path: Path, config: SynthConfig, scene: Scene, K: np.ndarray, stamps: list[int],
                  true_poses: list[np.ndarray], published: list[np.ndarray], times: np.ndarray | None = None) -> None:
    """Ground-truth JSON: generation config, scene (objects, poses, shapes), intrinsics, per-frame poses
    (and, for continuous paths (`scene.CONTINUOUS_PATHS`), the capture time of each keyframe in seconds along
    the path)."""
    doc = {
        'config': asdict(config), 'scene': scene.to_dict(),
        'camera': {'K': K.tolist(), 'width': config.width, 'height': config.height, 'frame_id': CAMERA_FRAME},
        'frames': [{'stamp_ns': s, 'T_world_camera': T.tolist(), 'T_world_camera_published': P.tolist()}
                   for s, T, P in zip(stamps, true_poses, published)],
    }
    if config.scene in CONTINUOUS_PATHS and times is not None:
        for frame, t in zip(doc['frames'], times):
            frame['capture_time_s'] = float(t)
    path.write_text(json.dumps(doc, indent=1) + '\n')
