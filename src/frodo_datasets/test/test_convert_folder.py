"""`frodo convert folder`: users' own images + poses (TUM lines, 4x4 per line, or one 4x4 file per frame) +
intrinsics YAML, with depth and contract instance masks; and without depth (landmarks from ORB features)."""
import shutil

import numpy as np
import pytest

from frodo_common.geometry import make_transform, quat_to_matrix
from frodo_datasets.convert import ConvertError, ConvertOptions, convert_folder
from frodo_datasets.convert.fixtures import read_with_rosbags, render_sequence, write_folder
from frodo_datasets.convert.folder import read_intrinsics


@pytest.fixture(scope='module')
def sequence():
    return render_sequence(frames=10, width=128, height=96, seed=1, layout='orbit', objects=2)


def _poses(msgs):
    out = []
    for _, m in msgs['/camera/pose']:
        p = m.pose
        out.append(make_transform(quat_to_matrix([p.orientation.x, p.orientation.y, p.orientation.z,
                                                  p.orientation.w]), [p.position.x, p.position.y, p.position.z]))
    return out


@pytest.mark.parametrize('pose_format', ['tum', '4x4', 'dir'])
def test_every_pose_format_gives_the_true_poses_and_instances(sequence, tmp_path, pose_format):
    folder = write_folder(sequence, tmp_path / 'run', pose_format)
    summary = convert_folder(folder, tmp_path / 'run.mcap', ConvertOptions(gravity='none'))
    assert summary.frames_written == 10 and not summary.skipped
    msgs = read_with_rosbags(tmp_path / 'run.mcap')
    for T, true in zip(_poses(msgs), sequence.poses):
        assert np.allclose(T, true, atol=1e-6)
    inst = msgs['/camera/instances'][4][1]
    pixels = np.frombuffer(bytes(inst.data), '<u2').reshape(inst.height, inst.width)
    # the mask of each object sits where the renderer saw it
    for obj in sequence.scene.objects:
        seen = sequence.labels[4] == obj.id
        if seen.sum() > 20:
            values, counts = np.unique(pixels[seen], return_counts=True)
            assert (values[np.argmax(counts)] >> 8) == obj.coco_id
    assert len(msgs['/slam/points']) == 2 and 'depth' in summary.landmarks


def test_without_depth_landmarks_are_opt_in_features(sequence, tmp_path):
    folder = write_folder(sequence, tmp_path / 'run', 'tum')
    shutil.rmtree(folder / 'depth')
    summary = convert_folder(folder, tmp_path / 'rgb_only.mcap')
    msgs = read_with_rosbags(tmp_path / 'rgb_only.mcap')
    assert '/camera/depth/image_raw' not in msgs and '/slam/points' not in msgs and summary.landmarks == 'none'
    assert 'camera mean up' in summary.gravity  # no depth: gravity from the cameras
    summary = convert_folder(folder, tmp_path / 'orb.mcap', ConvertOptions(landmarks='features'))
    assert summary.landmarks.startswith('features') and read_with_rosbags(tmp_path / 'orb.mcap')['/slam/points']


def test_clear_errors_and_nothing_half_written(sequence, tmp_path):
    folder = write_folder(sequence, tmp_path / 'run', '4x4')
    lines = (folder / 'poses.txt').read_text().splitlines()
    (folder / 'poses.txt').write_text('\n'.join(lines[:-2]) + '\n')
    with pytest.raises(ConvertError, match='mismatched counts: 10 images but 8 poses'):
        convert_folder(folder, tmp_path / 'x.mcap')
    (folder / 'poses.txt').write_text('\n'.join(lines) + '\n')
    for img in (folder / 'rgb').iterdir():  # every colour image unreadable
        img.write_bytes(b'not an image')
    with pytest.raises(ConvertError):
        convert_folder(folder, tmp_path / 'x.mcap')
    assert not list(tmp_path.glob('x.mcap*'))
    (folder / 'intrinsics.yaml').write_text('fx: 100\n')
    with pytest.raises(ConvertError, match='incomplete intrinsics'):
        convert_folder(folder, tmp_path / 'x.mcap')
    with pytest.raises(ConvertError, match='no colour image folder'):
        convert_folder(tmp_path, tmp_path / 'x.mcap')


def test_ros_camera_info_yaml(tmp_path):
    path = tmp_path / 'cam.yaml'
    path.write_text('image_width: 640\nimage_height: 480\ncamera_matrix:\n  rows: 3\n  cols: 3\n'
                    '  data: [500, 0, 320, 0, 501, 240, 0, 0, 1]\ndistortion_model: plumb_bob\n'
                    'distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0.1, 0, 0, 0, 0]\n')
    K, dist, size = read_intrinsics(path)
    assert K[1, 1] == 501 and dist[0] == 0.1 and size == (640, 480)


def test_floor_fit_on_orb_landmarks_without_depth(tmp_path):
    seq = render_sequence(frames=24, width=160, height=120, seed=3, layout='orbit')  # 15 degrees between views
    folder = write_folder(seq, tmp_path / 'run', 'tum')
    shutil.rmtree(folder / 'depth')
    summary = convert_folder(folder, tmp_path / 'orb.mcap', ConvertOptions(gravity='floor'))
    assert summary.gravity.startswith('floor plane fit on ORB landmarks'), summary.gravity
    poses = _poses(read_with_rosbags(tmp_path / 'orb.mcap'))
    A = poses[0] @ np.linalg.inv(seq.poses[0])  # true world -> converted world, the same for every frame
    for T, true in zip(poses, seq.poses):
        assert np.allclose(T, A @ true, atol=1e-5)
    tilt = np.degrees(np.arccos(np.clip(A[2, 2], -1, 1)))
    assert tilt < 4.0 and abs(A[2, 3]) < 0.05  # up within 4 degrees, the floor at z = 0 near the origin


def test_distorted_images_are_undistorted_to_the_same_pinhole(sequence, tmp_path):
    """A plumb_bob camera (as TUM fr1/fr2): images distorted by the test come out as the pinhole renders."""
    import cv2
    folder = write_folder(sequence, tmp_path / 'run', 'tum')
    K = sequence.K
    dist = np.array([0.6, 0.3, 0.002, -0.003, 0.0])  # up to 12 px at the corners of 128x96
    (folder / 'intrinsics.yaml').write_text(
        f'fx: {K[0, 0]}\nfy: {K[1, 1]}\ncx: {K[0, 2]}\ncy: {K[1, 2]}\nwidth: 128\nheight: 96\n'
        f'dist: {dist.tolist()}\ndepth_scale: 1000\n')
    # distorted pixel -> the undistorted pixel it shows
    u, v = np.meshgrid(np.arange(128, dtype=np.float64), np.arange(96, dtype=np.float64))
    und = cv2.undistortPoints(np.stack([u.ravel(), v.ravel()], 1)[:, None], K, dist, P=K)[:, 0]
    mx, my = und[:, 0].reshape(96, 128).astype(np.float32), und[:, 1].reshape(96, 128).astype(np.float32)
    for k, rgb in enumerate(sequence.rgb):
        distorted = cv2.remap(rgb, mx, my, cv2.INTER_LINEAR)
        cv2.imwrite(str(folder / 'rgb' / f'{k:06d}.png'), cv2.cvtColor(distorted, cv2.COLOR_RGB2BGR))
        for sub in ('depth', 'instances'):
            img = cv2.imread(str(folder / sub / f'{k:06d}.png'), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(folder / sub / f'{k:06d}.png'), cv2.remap(img, mx, my, cv2.INTER_NEAREST))
    convert_folder(folder, tmp_path / 'd.mcap', ConvertOptions(gravity='none'))
    msgs = read_with_rosbags(tmp_path / 'd.mcap')
    info = msgs['/camera/color/camera_info'][0][1]
    assert list(info.d) == [0.0] * 5 and np.allclose(np.reshape(info.k, (3, 3)), K)
    img = msgs['/camera/color/image_raw'][2][1]
    out = np.frombuffer(bytes(img.data), np.uint8).reshape(96, 128, 3).astype(float)
    inner = (slice(12, 84), slice(16, 112))  # the border holds pixels the distorted image did not see
    distorted_err = np.abs(cv2.remap(sequence.rgb[2], mx, my, cv2.INTER_LINEAR).astype(float) - sequence.rgb[2])
    err = np.abs(out - sequence.rgb[2])
    # what is left is the blur of two bilinear resamplings of a textured render
    assert err[inner].mean() < 0.6 * distorted_err[inner].mean()
    inst = msgs['/camera/instances'][2][1]
    pixels = np.frombuffer(bytes(inst.data), '<u2').reshape(96, 128)
    truth = sequence.labels[2] > 0
    distorted_masks = cv2.remap(truth.astype(np.uint8), mx, my, cv2.INTER_NEAREST) > 0
    assert np.mean((pixels[inner] > 0) == truth[inner]) > 0.99 > np.mean(distorted_masks[inner] == truth[inner])
