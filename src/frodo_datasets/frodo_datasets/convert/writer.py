"""Write a `Source` as a contract bag (CONTRACT.md v1.1 inputs + ground truth) through `frodo_common.bag.BagWriter`,
the same writing path as `frodo synth`.

Per written frame, all with the frame's stamp (= log time): camera info, `rgb8` image, pose (frame `world`),
registered depth (`16UC1` mm, when the dataset has depth), instances (`16UC1`, when it has them);
`/slam/points` (the whole landmark map) every `slam_every` frames and after the last one; ground truth
once at the first stamp (transient local). The file is written as `OUTPUT.partial` and renamed at the end,
so a failed conversion leaves nothing behind.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
from visualization_msgs.msg import MarkerArray

from frodo_common import topics
from frodo_common.bag import BagWriter, qos_yaml
from frodo_common.conversions import make_camera_info, make_pose_stamped, mesh_to_marker, numpy_to_image, xyz_to_cloud
from frodo_datasets.convert.common import (ConvertError, ConvertOptions, ConvertSummary, Source, SourceFrame,
                                           backproject, register_depth, resize_color, resize_nearest,
                                           scale_intrinsics, select_keyframes, undistort_maps, valid_pose)
from frodo_datasets.convert.gravity import align_floor, align_up, camera_up, fit_floor
from frodo_datasets.convert.landmarks import DepthLandmarks, FeatureLandmarks

# CONTRACT.md v1.1: depth registered to the colour image.
GRAVITY_MODES = ('auto', 'none', 'up', 'camera', 'floor')
LANDMARK_MODES = ('auto', 'depth', 'features', 'none')
# Keyframes sampled for the floor fit.
FLOOR_FIT_FRAMES = 15


def output_camera(source: Source, options: ConvertOptions, with_instances: bool) -> tuple[np.ndarray, tuple[int, int]]:
    """(K_out (3, 3), (width, height)) of the written images (see ConvertOptions.resize / instances_at)."""
    K = np.asarray(source.K_color, dtype=np.float64)
    size = source.color_size
    if isinstance(options.resize, (int, float)) and not isinstance(options.resize, bool):
        if options.resize <= 0:
            raise ConvertError(f'resize scale must be > 0, got {options.resize}')
        out = (max(8, round(size[0] * options.resize)), max(8, round(size[1] * options.resize)))
    elif options.resize is not None:
        out = (int(options.resize[0]), int(options.resize[1]))
    elif with_instances and source.label_size is not None and options.instances_at == 'labels':
        out = tuple(source.label_size)
    else:
        out = tuple(size)
    if out[0] < 8 or out[1] < 8:
        raise ConvertError(f'output size {out} is too small')
    return scale_intrinsics(K, size, out), out


def _depth_points(source: Source, frames: list[SourceFrame], max_depth: float) -> np.ndarray:
    """World points (dataset frame) from the depth of up to FLOOR_FIT_FRAMES frames spread over `frames`."""
    K_d = source.K_depth if source.K_depth is not None else source.K_color
    T_cd = source.T_color_depth if source.T_color_depth is not None else np.eye(4)
    pts = []
    for i in select_keyframes(len(frames), views=FLOOR_FIT_FRAMES):
        f = frames[i]
        try:
            depth = f.depth()
        except OSError:
            continue
        pts.append(backproject(depth, K_d, f.pose @ T_cd, stride=8, max_depth=max_depth))
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def _feature_points(source: Source, frames: list[SourceFrame]) -> np.ndarray:
    """World points (dataset frame) triangulated from ORB matches of consecutive frames (no depth)."""
    landmarks = FeatureLandmarks(voxel=0.05)  # coarser than the published map: one vote per 5 cm for the plane fit
    undistort = undistort_maps(source.K_color, source.dist, source.color_size)
    for f in frames:
        try:
            rgb = f.color()
        except OSError:
            continue
        if undistort is not None:
            rgb = cv2.remap(rgb, *undistort, interpolation=cv2.INTER_LINEAR)
        landmarks.add(rgb, source.K_color, f.pose)
    return landmarks.points()


def gravity_alignment(source: Source, frames: list[SourceFrame], options: ConvertOptions) -> tuple[np.ndarray, str]:
    """(T_aligned_dataset (4, 4), description) per `options.gravity` (see frodo_datasets.convert.gravity)."""
    mode = options.gravity
    if mode not in GRAVITY_MODES:
        raise ConvertError(f'unknown gravity mode {mode!r}; use one of {GRAVITY_MODES}')
    poses = [f.pose for f in frames]
    has_depth = all(f.depth is not None for f in frames)
    if mode == 'auto':
        if source.world_up is not None:
            if np.allclose(source.world_up / np.linalg.norm(source.world_up), [0, 0, 1]):
                return np.eye(4), f'none: the {source.format} world is z up already'
            return align_up(source.world_up), f'the {source.format} world up {list(source.world_up)} -> +z'
        mode = 'floor' if has_depth else 'camera'
    if mode == 'none':
        return np.eye(4), 'none (world kept as in the dataset)'
    if mode == 'up':
        if options.up is None:
            raise ConvertError('gravity mode "up" needs the up vector (--up x,y,z)')
        return align_up(np.asarray(options.up, float)), f'given up {list(options.up)} -> +z'
    up = camera_up(poses)
    if mode == 'floor':
        points = _depth_points(source, frames, options.max_depth) if has_depth else _feature_points(source, frames)
        what = 'depth' if has_depth else 'ORB landmarks'
        try:
            plane = fit_floor(points, up, np.array([T[:3, 3] for T in poses]))
        except ValueError as err:
            T = align_up(up)
            return T, f'camera mean up (floor fit failed: {err})'
        tilt = np.degrees(np.arccos(np.clip(plane.normal @ up, -1, 1)))
        return align_floor(plane), (f'floor plane fit on {what} (RANSAC, {plane.inliers} inliers; normal '
                                    f'{tilt:.1f} deg from the cameras\' mean up), floor moved to z = 0')
    return align_up(up), 'camera mean up (-y of the optical frames) -> +z'


def write_bag(source: Source, output: str | os.PathLike, options: ConvertOptions | None = None,
              progress: Callable[[int], None] | None = None) -> ConvertSummary:
    """Convert `source` into the contract bag `output`; returns what was written. Raises ConvertError."""
    options = options or ConvertOptions()
    output = Path(output)
    if options.landmarks not in LANDMARK_MODES:
        raise ConvertError(f'unknown landmarks mode {options.landmarks!r}; use one of {LANDMARK_MODES}')
    frames_in = len(source.frames) + sum(source.skipped.values())
    usable = []
    for f in source.frames:
        if valid_pose(f.pose):
            usable.append(f)
        else:
            source.skip('invalid pose (inf/NaN or not rigid)')
    if not usable:
        raise ConvertError(f'no frame of the {source.format} sequence has a valid pose (skipped: {source.skipped})')
    picks = [usable[i] for i in select_keyframes(len(usable), options.views, options.every, options.max_frames)]
    with_depth = all(f.depth is not None for f in picks)
    with_instances = options.instances and all(f.instances is not None for f in picks)
    K_out, size = output_camera(source, options, with_instances)
    T_align, gravity = gravity_alignment(source, picks, options)
    landmark_mode = options.landmarks
    if landmark_mode == 'auto':  # ORB landmarks cost accuracy on the measured scenes: opt-in only
        landmark_mode = 'depth' if with_depth else 'none'
    if landmark_mode == 'depth' and not with_depth:
        raise ConvertError('landmarks from depth need depth images; use --landmarks features')
    landmarks = (DepthLandmarks(options.landmark_stride, options.landmark_voxel, options.landmark_min_views,
                                options.max_depth) if landmark_mode == 'depth'
                 else FeatureLandmarks(options.landmark_voxel) if landmark_mode == 'features' else None)
    K_src = np.asarray(source.K_color, dtype=np.float64)
    undistort = undistort_maps(K_src, source.dist, source.color_size)
    # Depth camera in the output camera: the colour camera's undistorted K scaled to the output size.
    K_depth = source.K_depth if source.K_depth is not None else K_src
    T_out_depth = source.T_color_depth
    if source.K_depth is None and source.depth_size is not None and tuple(source.depth_size) != source.color_size:
        K_depth = scale_intrinsics(K_src, source.color_size, source.depth_size)

    partial = output.with_name(output.name + '.partial')
    counts: dict[str, int] = {}
    world, cam = options.world_frame, options.camera_frame
    written, last_stamp = 0, -1
    try:
        with BagWriter(partial, compression=options.compression) as bag:
            def put(topic: str, msg, stamp_ns: int) -> None:
                bag.write(topic, msg, stamp_ns)
                counts[topic] = counts.get(topic, 0) + 1

            gt_written = False
            for f in picks:
                if progress is not None:
                    progress(1)
                if f.stamp_ns <= last_stamp:
                    source.skip('duplicate or decreasing timestamp')
                    continue
                try:
                    rgb = f.color()
                    if (rgb.shape[1], rgb.shape[0]) != tuple(source.color_size):
                        raise OSError(f'frame {f.index}: colour is {rgb.shape[1]}x{rgb.shape[0]}, '
                                      f'expected {source.color_size[0]}x{source.color_size[1]}')
                    depth = f.depth() if with_depth else None
                    inst = f.instances() if with_instances else None
                except OSError as err:
                    source.skip('unreadable frame')
                    if source.skipped['unreadable frame'] <= 3:  # name the first few, count the rest
                        source.notes.append(str(err))
                    continue
                if undistort is not None:
                    rgb = cv2.remap(rgb, *undistort, interpolation=cv2.INTER_LINEAR)
                    if depth is not None and source.K_depth is None:
                        depth = cv2.remap(depth, *undistort, interpolation=cv2.INTER_NEAREST)
                    if inst is not None:
                        inst = cv2.remap(inst, *undistort, interpolation=cv2.INTER_NEAREST)
                rgb = resize_color(rgb, size)
                T = T_align @ f.pose
                stamp = f.stamp_ns
                if not gt_written:
                    if options.ground_truth and source.ground_truth:
                        bag.add_topic(topics.GROUND_TRUTH, 'visualization_msgs/msg/MarkerArray',
                                      qos_yaml(transient_local=True, depth=1))
                        markers = [mesh_to_marker(g.vertices @ T_align[:3, :3].T + T_align[:3, 3], g.faces,
                                                  g.class_name, g.object_id, stamp, world)
                                   for g in source.ground_truth]
                        put(topics.GROUND_TRUTH, MarkerArray(markers=markers), stamp)
                    gt_written = True
                put(topics.CAMERA_INFO, make_camera_info(K_out, size[0], size[1], stamp, cam), stamp)
                put(topics.IMAGE, numpy_to_image(rgb, 'rgb8', stamp, cam), stamp)
                put(topics.POSE, make_pose_stamped(T, stamp, world), stamp)
                if depth is not None:
                    depth = np.where(np.isfinite(depth), depth, 0).astype(np.float32)
                    depth_out = register_depth(depth, K_depth, K_out, size, T_out_depth)
                    if options.depth:
                        mm = np.clip(np.round(depth_out * 1000), 0, 65535).astype(np.uint16)
                        put(topics.DEPTH, numpy_to_image(mm, '16UC1', stamp, cam), stamp)
                    if isinstance(landmarks, DepthLandmarks):
                        landmarks.add(depth_out, K_out, T)
                if inst is not None:
                    put(topics.INSTANCES, numpy_to_image(resize_nearest(inst, size), '16UC1', stamp, cam), stamp)
                if isinstance(landmarks, FeatureLandmarks):
                    landmarks.add(rgb, K_out, T)
                written += 1
                last_stamp = stamp
                if landmarks is not None and written % options.slam_every == 0:
                    points = landmarks.points()
                    if len(points):
                        put(topics.SLAM_POINTS, xyz_to_cloud(points, stamp, world), stamp)
            if written == 0:
                raise ConvertError(f'no frame could be written (skipped: {source.skipped}; '
                                   f'{"; ".join(source.notes[-3:])})')
            if landmarks is not None and written % options.slam_every != 0:
                points = landmarks.points()
                if len(points):
                    put(topics.SLAM_POINTS, xyz_to_cloud(points, last_stamp, world), last_stamp)
        os.replace(partial, output)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    n_points = counts.get(topics.SLAM_POINTS, 0)
    if landmarks is None:
        landmark_text = 'none'
    else:
        final = len(landmarks.points())
        landmark_text = (f'{landmark_mode}: {final} points in the final map, {n_points} map messages'
                         if final else f'{landmark_mode}: none found')
    return ConvertSummary(output, source.format, frames_in, written, size, K_out, counts, dict(source.skipped),
                          gravity, landmark_text, len(source.ground_truth) if options.ground_truth else 0,
                          list(source.notes), T_align)
