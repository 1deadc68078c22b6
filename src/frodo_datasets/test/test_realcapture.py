"""Real-capture regime: each condition has the effect it claims (deterministic seeds, small images)."""
import numpy as np
import pytest
import trimesh

from frodo_common import topics
from frodo_common.bag import BagReader
from frodo_common.conversions import image_to_numpy
from frodo_common.geometry import invert_transform, look_at, project_points
from frodo_datasets.degrade import (MaskNoise, PoseNoise, PoseNoiser, bleed, degrade_instances, punch_holes,
                                    wobble_boundary)
from frodo_datasets.realcapture import (CaptureEffects, blur_vector, distort, distortion_maps, kinect_depth,
                                        motion_blur, photometric, preset_kwargs, texture_strength, vignette_gain)
from frodo_datasets.render import Material, Realism, RenderObject, Renderer, intrinsics
from frodo_datasets.scene import HandheldPath, compose_scene, family_pool, footprints_overlap, walk_trajectory
from frodo_datasets.shapes import eval_families, extra_families, families
from frodo_datasets.synth import SynthConfig, synthesize

W, H = 96, 72


@pytest.fixture(scope='module')
def room():
    return compose_scene(4, ('dining table', 'chair', 'chair'), seed=3, family_set='all', tuck_chairs=1.0, clutter=3)


def _truncated_fraction(scene, poses, K, width, height):
    """Fraction of (frame, visible object) pairs whose projected mesh leaves the image."""
    truncated = visible = 0
    for T in poses:
        for o in scene.objects:
            uv, z = project_points(K, invert_transform(T), o.mesh_world.vertices)
            inside = (z > 0.05) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
            if inside.any():
                visible += 1
                truncated += not inside.all()
    return truncated / max(visible, 1)


def test_handheld_path_is_close_truncated_and_spread(room):
    K = intrinsics(W, H)
    path = HandheldPath(room, seed=1)
    poses = path.keyframes(35, seed=1)
    walk = walk_trajectory(room, 35, seed=1)
    assert _truncated_fraction(room, poses, K, W, H) > _truncated_fraction(room, walk, K, W, H)
    assert _truncated_fraction(room, poses, K, W, H) > 0.6
    # close range: distance from the camera to the nearest object surface point
    points = np.concatenate([trimesh.sample.sample_surface(o.mesh_world, 2000, seed=0)[0] for o in room.objects])
    near = [np.linalg.norm(points - T[:3, 3], axis=1).min() for T in poses]
    assert 0.3 < np.median(near) < 1.5 and max(near) < 2.5
    times = path.keyframe_times(35, seed=1)
    assert path.duration > 60 and times[0] < 0.05 * path.duration and times[-1] > 0.95 * path.duration
    assert np.allclose(path.pose(12.5), path.pose(12.5)) and not np.allclose(path.pose(12.5), path.pose(13.5))
    assert all(np.allclose(a, b) for a, b in zip(poses, HandheldPath(room, seed=1).keyframes(35, seed=1)))


def test_chairs_pushed_under_tables_and_clutter_on_tops(room):
    from frodo_datasets.scene import _intersection_volume
    tables = [o for o in room.objects if o.class_name == 'dining table']
    chairs = [o for o in room.objects if o.class_name == 'chair']
    tucked = [c for c in chairs if any(footprints_overlap(c.footprint, t.footprint, 0.0) for t in tables)]
    assert tucked, 'tuck_chairs=1 should push at least one chair under a table'
    for c in tucked:
        assert all(_intersection_volume(c.mesh_world, t.mesh_world) < 1e-6 for t in tables)
    plain = compose_scene(4, ('dining table', 'chair', 'chair'), seed=3, family_set='all')
    assert len(room.room) > len(plain.room)  # clutter items are unlabelled room geometry
    tops = [t.mesh_world.bounds[1, 2] for t in tables]
    for item in room.room[len(plain.room):]:
        assert item.label == 0 and any(abs(item.mesh.bounds[0, 2] - top) < 0.07 for top in tops)
    # the same objects, families and shape seeds with and without the options
    assert [(o.family, o.shape_seed) for o in plain.objects] == [(o.family, o.shape_seed) for o in room.objects]


def test_family_pools():
    for c in ('chair', 'dining table'):
        assert family_pool(c, 'train') == families(c)
        assert set(family_pool(c, 'heldout')) == set(eval_families(c)) and not set(eval_families(c)) & set(families(c))
        assert family_pool(c, 'all') == families(c) + eval_families(c)
        assert family_pool(c, 'extra') == families(c) + extra_families(c)
        assert not set(extra_families(c)) & (set(families(c)) | set(eval_families(c)))
    with pytest.raises(ValueError):
        family_pool('chair', 'test')


def test_mask_boundary_holes_and_bleeding():
    rng = np.random.default_rng(0)
    mask = np.zeros((H, W), np.uint8)
    mask[20:60, 20:70] = 1
    wobbly = wobble_boundary(mask, 2.0, rng)
    changed = np.sum(wobbly != mask)
    assert 0.3 * 2 * 90 < changed < 4 * 2 * 90  # about amplitude x perimeter pixels flip
    assert np.sum(wobbly & mask) > 0.8 * mask.sum()
    holed = punch_holes(mask, 3.0, np.random.default_rng(1))
    assert holed.sum() < mask.sum() and not np.any(holed & ~mask.astype(bool))
    spill = bleed(mask, 4, np.random.default_rng(2))
    assert spill.any() and not np.any(spill & mask)
    ys, xs = np.nonzero(spill)
    assert max(np.ptp(ys), np.ptp(xs)) < 60 + 2 * 4  # one side only, within the radius
    # in the instance image: a second instance next to the first loses pixels to bleeding
    inst = np.zeros((H, W), np.uint16)
    inst[20:60, 10:48] = (62 << 8) | 1
    inst[20:60, 48:86] = (67 << 8) | 2
    out = [degrade_instances(inst, MaskNoise(boundary_px=1.5, hole_rate=0.5, bleed_px=5), np.random.default_rng(s))
           for s in range(10)]
    iou = [np.sum((o == inst) & (inst > 0)) / np.sum((o > 0) | (inst > 0)) for o in out]
    assert 0.7 < np.mean(iou) < 0.99


def test_drift_grows_along_the_path_and_not_with_the_keyframe_count():
    T = np.eye(4)

    def end_errors(n_frames, duration=100.0, runs=40):
        errors = []
        for s in range(runs):
            noiser = PoseNoiser(PoseNoise(drift_trans_m=0.003, drift_per_second=True), np.random.default_rng(s))
            traj = [noiser(T, duration / n_frames) for _ in range(n_frames)]
            errors.append([np.linalg.norm(P[:3, 3]) for P in traj])
        return np.array(errors)

    e35, e100 = end_errors(35), end_errors(100)
    assert e35[:, -1].mean() > 2 * e35[:, 2].mean()  # grows along the path
    assert 0.7 < e35[:, -1].mean() / e100[:, -1].mean() < 1.4  # per-second walk: same end drift
    expected = 0.003 * np.sqrt(100) * np.sqrt(8 / np.pi)  # mean norm of a 3D Gaussian of that std
    assert 0.7 * expected < e100[:, -1].mean() < 1.3 * expected


def test_photometric_effects():
    img = np.full((H, W, 3), 120, np.uint8)
    gain = vignette_gain(W, H, 0.4)
    assert gain[H // 2, W // 2] > 0.99 and abs(gain[0, 0] - 0.6) < 1e-6
    dark = photometric(img, CaptureEffects(vignetting=0.4), np.random.default_rng(0))
    assert dark[0, 0, 0] < dark[H // 2, W // 2, 0]
    means = [photometric(img, CaptureEffects(exposure_std=0.3), np.random.default_rng(s)).mean() for s in range(8)]
    assert np.std(means) > 10
    bright, dim = np.full((H, W, 3), 200, np.uint8), np.full((H, W, 3), 20, np.uint8)
    fx = CaptureEffects(shot_noise=1.0, read_noise=1.0)
    s_bright = photometric(bright, fx, np.random.default_rng(0)).astype(float).std()
    s_dim = photometric(dim, fx, np.random.default_rng(0)).astype(float).std()
    assert abs(s_bright - np.sqrt(201)) < 1.5 and abs(s_dim - np.sqrt(21)) < 0.7  # Poisson-Gaussian


def test_motion_blur_follows_the_camera_motion():
    K = intrinsics(W, H)
    depth = np.full((H, W), 2.0, np.float32)
    T0 = np.eye(4)
    T1 = np.eye(4)
    T1[0, 3] = 0.05  # camera moves 5 cm right: the scene moves left by f * 0.05 / 2 pixels
    v = blur_vector(K, depth, T0, T1)
    assert np.allclose(v, [-K[0, 0] * 0.05 / 2.0, 0.0], atol=0.05)
    stripes = np.zeros((H, W, 3), np.uint8)
    stripes[:, ::4] = 255
    blurred = motion_blur(stripes, v)
    assert np.abs(np.diff(blurred[..., 0].astype(float), axis=1)).mean() < 0.5 * np.abs(
        np.diff(stripes[..., 0].astype(float), axis=1)).mean()
    assert motion_blur(stripes, np.array([0.3, 0.0])) is stripes


def test_lens_distortion_moves_points_like_opencv():
    import cv2
    K = intrinsics(W, H)
    d = (-0.3, 0.08)
    maps = distortion_maps(K, d, W, H)
    img = np.zeros((H, W), np.uint16)
    point = np.array([[0.5, -0.35, 1.0]])  # a camera-frame point near the corner
    uv, _ = project_points(K, np.eye(4), point)
    u, v = np.round(uv[0]).astype(int)
    img[v - 1:v + 2, u - 1:u + 2] = 7
    out = distort(img, maps, nearest=True)
    expected, _ = cv2.projectPoints(point, np.zeros(3), np.zeros(3), K, np.array([d[0], d[1], 0, 0, 0.0]))
    ys, xs = np.nonzero(out == 7)
    assert np.hypot(xs.mean() - expected[0, 0, 0], ys.mean() - expected[0, 0, 1]) < 1.0
    assert np.hypot(xs.mean() - u, ys.mean() - v) > 2.0  # it did move


def test_kinect_depth_noise_and_holes():
    depth = np.full((H, W), 2.0, np.float32)
    depth[:, W // 2:] = 3.0  # a depth edge
    depth[:5] = 0.2  # too close to measure
    out = kinect_depth(depth, np.random.default_rng(0), dropout=0.02)
    assert not out[:5].any()
    edge = out[10:, W // 2 - 1:W // 2 + 1]
    assert (edge == 0).mean() > 0.4
    flat = out[10:, 5:W // 2 - 5]
    valid = flat[flat > 0]
    assert 0.0035 < valid.std() < 0.0065  # 1.2 mm + 1.9 mm * (2 - 0.4)^2 = 6.1 mm, quantised to mm
    assert 0.01 < (out[10:] == 0).mean() < 0.15  # dropouts and edge holes
    assert np.allclose(np.round(valid * 1000), valid * 1000, atol=1e-3)


def test_texture_strength_and_textured_landmarks():
    pts = np.random.default_rng(0).uniform(-1, 1, (200, 3))
    assert np.all(texture_strength(Material(kind='plain'), pts) == 0)
    assert np.mean(texture_strength(Material(kind='checker', scale=8.0), pts) > 0) > 0.05
    assert np.mean(texture_strength(Material(kind='noise', scale=8.0, color2=(0.1, 0.1, 0.1)), pts)) > 0.01


def test_realism_darkens_creases_and_adds_highlights():
    floor = trimesh.creation.box((4, 4, 0.1))
    floor.apply_translation((0, 0, -0.05))
    block = trimesh.creation.box((0.6, 0.6, 0.6))
    block.apply_translation((0, 0, 0.3))
    r = Renderer([RenderObject(floor, Material(color=(0.8, 0.8, 0.8)), 0),
                  RenderObject(block, Material(color=(0.8, 0.8, 0.8)), 1)])
    K = intrinsics(W, H)
    T = look_at(np.array([1.6, 1.2, 1.4]), np.array([0.0, 0.0, 0.2]))
    plain = r.render(K, T, W, H)
    assert np.array_equal(plain.rgb, r.render(K, T, W, H, quality=Realism()).rgb)  # inactive = unchanged
    ao = r.render(K, T, W, H, quality=Realism(ao_samples=8, ao_radius=0.5))
    floor_px = plain.labels == 0
    assert ao.rgb[floor_px].mean() < plain.rgb[floor_px].mean()  # the floor next to the block is occluded
    shiny = r.render(K, T, W, H, quality=Realism(specular=0.8, shininess=4))
    assert shiny.rgb.astype(float).mean() > plain.rgb.astype(float).mean()
    assert np.array_equal(plain.labels, ao.labels) and np.array_equal(plain.depth, ao.depth)


def test_preset_bag(tmp_path):
    """The handheld preset end to end: close-range keyframes, noisy masks and poses, depth on the v1.1 topic."""
    path = tmp_path / 'hh.mcap'
    config = SynthConfig(**{**preset_kwargs('handheld'), 'frames': 4}, objects=3, classes=('dining table', 'chair'),
                         width=W, height=H, seed=1, depth=True, depth_topic='/camera/depth/image_raw',
                         min_mask_pixels=5, family_set='all')
    result = synthesize(config, path)
    reader = BagReader(path)
    assert reader.topics()['/camera/depth/image_raw'] == ('sensor_msgs/msg/Image', 4)
    depths = [image_to_numpy(m.decode()) for m in reader.messages() if m.topic == '/camera/depth/image_raw']
    assert all(d.dtype == np.uint16 for d in depths) and 0.0 < np.mean([(d == 0).mean() for d in depths]) < 0.6
    errors = [np.linalg.norm(P[:3, 3] - T[:3, 3]) for P, T in zip(result.published_poses, result.true_poses)]
    assert 0 < max(errors) < 0.2
    import json
    from frodo_datasets.synth import sidecar_path
    frames = json.loads(sidecar_path(path).read_text())['frames']
    assert np.all(np.diff([f['capture_time_s'] for f in frames]) > 5.0)  # keyframes seconds apart
    from frodo_datasets.cli_synth import main
    assert main([str(tmp_path / 'cli.mcap'), '--preset', 'handheld', '--frames', '2', '--width', '48', '--height',
                 '36', '--objects', '2', '--mask-bleed', '0', '--no-sidecar', '--quiet']) == 0
    assert BagReader(tmp_path / 'cli.mcap').topics()[topics.IMAGE] == ('sensor_msgs/msg/Image', 2)
    assert main([str(tmp_path / 'x.mcap'), '--motion-blur', '0.03', '--quiet']) == 2  # needs a hand-held path
