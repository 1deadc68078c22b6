"""Contract bag synthesis: contents read back with frodo_common.bag, instances, SLAM map, degradations, CLI."""
import json

import numpy as np
import pytest

from frodo_common import topics
from frodo_common.bag import BagReader
from frodo_common.categories import split_instance_label
from frodo_common.conversions import (camera_info_to_K, cloud_to_xyz, image_to_numpy, marker_to_mesh, pose_to_matrix,
                                      stamp_to_ns)
from frodo_datasets.degrade import MaskNoise, PoseNoise, PoseNoiser, add_image_noise, degrade_instances
from frodo_datasets.render import Renderer
from frodo_datasets.synth import SynthConfig, sidecar_path, synthesize

W, H, N = 128, 96, 10


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp('synth') / 'small.mcap'
    config = SynthConfig(scene='walk', objects=3, frames=N, width=W, height=H, seed=2, depth=True, slam_every=3,
                         min_mask_pixels=10)
    result = synthesize(config, path)
    by_topic: dict[str, list] = {}
    order = []
    for m in BagReader(path).messages():
        by_topic.setdefault(m.topic, []).append((m.log_time_ns, m.decode()))
        order.append(m.topic)
    return result, by_topic, order


def test_topics_counts_and_stamps(bag):
    result, msgs, order = bag
    assert {t: len(v) for t, v in msgs.items()} == {
        topics.GROUND_TRUTH: 1, topics.CAMERA_INFO: N, topics.IMAGE: N, topics.POSE: N, topics.INSTANCES: N,
        topics.DEPTH: N, topics.SLAM_POINTS: 4}  # SLAM map after frames 3, 6, 9 and at the end
    assert order.index(topics.CAMERA_INFO) < order.index(topics.IMAGE)
    stamps = [t for t, _ in msgs[topics.IMAGE]]
    assert stamps == result.stamps and np.allclose(np.diff(stamps), 1e8)  # 10 fps
    for topic, items in msgs.items():
        for log_ns, msg in items:
            header = msg.markers[0].header if topic == topics.GROUND_TRUTH else msg.header
            assert stamp_to_ns(header.stamp) == log_ns
            expected = 'world' if topic in (topics.POSE, topics.SLAM_POINTS, topics.GROUND_TRUTH) \
                else 'camera_color_optical_frame'
            assert header.frame_id == expected
    K = camera_info_to_K(msgs[topics.CAMERA_INFO][0][1])
    assert np.allclose(K, result.K)
    for (_, pose), T in zip(msgs[topics.POSE], result.true_poses):
        assert np.allclose(pose_to_matrix(pose.pose), T, atol=1e-9)


def test_instances_match_rendered_objects(bag):
    result, msgs, _ = bag
    scene = result.scene
    renderer = Renderer(scene.render_objects())
    coco = {o.id: o.coco_id for o in scene.objects}
    k_of_object: dict[int, set] = {}
    for (_, image), T in zip(msgs[topics.INSTANCES], result.true_poses):
        inst = image_to_numpy(image)
        assert image.encoding == '16UC1' and inst.shape == (H, W)
        labels = renderer.render(result.K, T, W, H, shadows=False).labels
        for value in np.unique(inst[inst > 0]):
            cat, k = split_instance_label(int(value))
            ids = np.unique(labels[inst == value])
            assert len(ids) == 1 and coco[int(ids[0])] == cat  # one object per instance, right class
            assert np.array_equal(inst == value, labels == ids[0])  # exact mask
            k_of_object.setdefault(int(ids[0]), set()).add(k)
    assert k_of_object  # objects were seen
    assert any(len(ks) > 1 for ks in k_of_object.values())  # k is per frame, not a track id


def test_ground_truth_slam_and_depth(bag):
    result, msgs, _ = bag
    import trimesh
    markers = msgs[topics.GROUND_TRUTH][0][1].markers
    assert [(m.ns, m.id) for m in markers] == [(o.class_name, o.id) for o in result.scene.objects]
    for marker, obj in zip(markers, result.scene.objects):
        vertices, _ = marker_to_mesh(marker)
        assert np.allclose(vertices.min(axis=0), obj.mesh_world.bounds[0], atol=1e-9)
    sizes = [len(cloud_to_xyz(c)) for _, c in msgs[topics.SLAM_POINTS]]
    assert sizes == sorted(sizes) and sizes[-1] > 200  # the map grows
    # Map points lie near a surface of the scene (1 cm noise).
    points = cloud_to_xyz(msgs[topics.SLAM_POINTS][-1][1])
    world = trimesh.util.concatenate([o.mesh for o in result.scene.render_objects()])
    _, dist, _ = trimesh.proximity.closest_point(world, points[:300])
    assert np.median(dist) < 0.02 and dist.max() < 0.06
    depth = image_to_numpy(msgs[topics.DEPTH][0][1])
    assert depth.dtype == np.uint16 and 300 < np.median(depth[depth > 0]) < 15000  # millimetres


def test_sidecar(bag):
    result, _, _ = bag
    doc = json.loads(sidecar_path(result.path).read_text())
    assert doc['config']['seed'] == 2 and len(doc['frames']) == N
    assert [o['class'] for o in doc['scene']['objects']] == [o.class_name for o in result.scene.objects]
    assert np.allclose(doc['frames'][3]['T_world_camera'], result.true_poses[3])


def test_pose_noise_affects_published_poses_only(tmp_path):
    config = SynthConfig(scene='orbit', objects=1, classes=('chair',), frames=4, width=64, height=48, seed=1,
                         slam=False, pose_noise=PoseNoise(rot_deg=1.0, trans_m=0.02))
    noisy = synthesize(config, tmp_path / 'noisy.mcap', sidecar=False)
    clean = synthesize(SynthConfig(**{**vars(config), 'pose_noise': PoseNoise()}), tmp_path / 'clean.mcap',
                       sidecar=False)
    assert all(np.array_equal(a, b) for a, b in zip(noisy.true_poses, clean.true_poses))
    offsets = [np.linalg.norm(P[:3, 3] - T[:3, 3]) for P, T in zip(noisy.published_poses, noisy.true_poses)]
    assert 0.001 < np.mean(offsets) < 0.1
    images = [[image_to_numpy(m.decode()) for m in BagReader(p).messages([topics.IMAGE])]
              for p in (noisy.path, clean.path)]
    assert all(np.array_equal(a, b) for a, b in zip(*images))  # rendered from the true poses
    assert not sidecar_path(noisy.path).exists()


def test_degrade_instances():
    rng = np.random.default_rng(0)
    inst = np.zeros((60, 80), np.uint16)
    inst[10:30, 10:30] = 62 * 256 + 5
    inst[35:55, 40:70] = 67 * 256 + 9
    assert not degrade_instances(inst, MaskNoise(drop_rate=1.0), rng).any()
    flipped = degrade_instances(inst, MaskNoise(wrong_class_rate=1.0, spurious_classes=(62, 67)), rng)
    assert set(np.unique(flipped).tolist()) == {0, 67 * 256 + 5, 62 * 256 + 9}
    spurious = degrade_instances(inst, MaskNoise(spurious_rate=3.0), np.random.default_rng(3))
    new = set(np.unique(spurious).tolist()) - set(np.unique(inst).tolist())
    assert new and len({v & 0xFF for v in np.unique(spurious) if v}) == len(np.unique(spurious)) - 1
    assert np.array_equal(spurious[inst > 0], inst[inst > 0])  # blobs only on background
    areas = [(degrade_instances(inst, MaskNoise(morph_px=3), np.random.default_rng(s)) == 62 * 256 + 5).sum()
             for s in range(12)]
    assert min(areas) < 400 < max(areas)  # eroded and dilated


def test_pose_noiser_and_image_noise():
    rng = np.random.default_rng(0)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 1.5]
    drift = PoseNoiser(PoseNoise(drift_trans_m=0.01), rng)
    errors = [np.linalg.norm(drift(T)[:3, 3] - T[:3, 3]) for _ in range(100)]
    assert np.mean(errors[-20:]) > np.mean(errors[:20])  # random walk grows
    rot = PoseNoiser(PoseNoise(rot_deg=2.0), rng)(T)
    assert np.allclose(rot[:3, 3], T[:3, 3]) and not np.allclose(rot[:3, :3], np.eye(3))  # about the camera centre
    img = np.full((10, 10, 3), 128, np.uint8)
    noisy = add_image_noise(img, 5.0, rng)
    assert noisy.dtype == np.uint8 and 3 < np.std(noisy.astype(float)) < 7
    assert add_image_noise(img, 0.0, rng) is img


def test_cli(tmp_path, capsys):
    from frodo_datasets.cli_synth import main
    out = tmp_path / 'cli.mcap'
    assert main([str(out), '--scene', 'orbit', '--objects', '1', '--classes', 'dining table', '--frames', '3',
                 '--width', '64', '--height', '48', '--mask-noise', '2', '--pose-noise', '0.5,0.01', '--quiet']) == 0
    assert 'wrote' in capsys.readouterr().out
    assert BagReader(out).topics()[topics.IMAGE] == ('sensor_msgs/msg/Image', 3)
    assert sidecar_path(out).is_file()
    with pytest.raises(SystemExit):
        main([str(out), '--classes', 'sofa'])
    with pytest.raises(SystemExit):
        main([str(out), '--pose-noise', '1,2,3'])
    assert main([str(out), '--frames', '0', '--quiet']) == 2
