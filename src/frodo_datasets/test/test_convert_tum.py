"""`frodo convert tum`: a TUM RGB-D sequence written by the test in TUM's exact layout (text lists with
comments, PNG colour, depth x5000, ground truth at other stamps, a missing depth image, an unmatched colour
frame) and a mocap world that is not z up; the bag passes the rosbags check and the world comes out z up."""
import numpy as np
import pytest

from frodo_common.conversions import cloud_to_xyz, image_to_numpy
from frodo_common.geometry import make_transform, quat_to_matrix
from frodo_datasets import cli_convert
from frodo_datasets.convert import ConvertError, ConvertOptions, convert_tum
from frodo_datasets.convert.fixtures import read_with_rosbags, render_sequence, write_intrinsics_yaml, write_tum
from frodo_datasets.convert.tum import INTRINSICS, guess_preset, nearest, read_tum

# The mocap world: y up, offset.
T_MOCAP_WORLD = make_transform(np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]), (0.3, 1.0, -2.0))  # world z -> mocap y


@pytest.fixture(scope='module')
def sequence():
    return render_sequence(frames=8, width=128, height=96, seed=0)


@pytest.fixture(scope='module')
def tum_dir(sequence, tmp_path_factory):
    root = tmp_path_factory.mktemp('tum')
    write_tum(sequence, root / 'rgbd_dataset_freiburg3_fixture', T_MOCAP_WORLD, drop_depth=(3,))
    write_intrinsics_yaml(sequence, root / 'camera.yaml')
    return root


def _pose(msg):
    p = msg.pose
    return make_transform(quat_to_matrix([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]),
                          [p.position.x, p.position.y, p.position.z])


def test_reader_associates_by_nearest_stamp_and_counts_the_rest(tum_dir):
    src = read_tum(tum_dir / 'rgbd_dataset_freiburg3_fixture', intrinsics=str(tum_dir / 'camera.yaml'))
    assert len(src.frames) == 7
    assert src.skipped == {'no ground-truth pose within 0.02 s': 1, 'no depth image within 0.02 s': 1}
    assert guess_preset(tum_dir / 'rgbd_dataset_freiburg3_fixture') == 'fr3'
    assert nearest(np.array([1.0, 2.0, 3.0]), 2.4, 0.5) == 1 and nearest(np.array([1.0]), 2.0, 0.5) is None
    depth = src.frames[0].depth()
    assert depth.dtype == np.float32 and 0.5 < np.median(depth[depth > 0]) < 6


def test_converted_bag_is_z_up_with_floor_at_zero_and_passes_rosbags(sequence, tum_dir, tmp_path):
    out = tmp_path / 'tum.mcap'
    summary = convert_tum(tum_dir / 'rgbd_dataset_freiburg3_fixture', out, intrinsics=str(tum_dir / 'camera.yaml'))
    assert summary.frames_written == 7 and summary.frames_in == 9 and 'floor plane fit' in summary.gravity
    msgs = read_with_rosbags(out)
    assert {t: len(m) for t, m in msgs.items()} == {
        '/camera/color/camera_info': 7, '/camera/color/image_raw': 7, '/camera/pose': 7,
        '/camera/depth/image_raw': 7, '/slam/points': 2}
    # Frame k of the bag is rendered frame k (frame 3 lacks depth and is skipped).
    kept = [0, 1, 2, 4, 5, 6, 7]
    poses = [_pose(m) for _, m in msgs['/camera/pose']]
    for k, T in zip(kept, poses):
        true = sequence.poses[k]
        # up is recovered: camera axes' z components and heights above the floor match the z-up truth
        assert np.allclose(T[2, :3], true[2, :3], atol=0.02) and T[2, 3] == pytest.approx(true[2, 3], abs=0.02)
    # relative motion is kept exactly
    rel = np.linalg.inv(poses[0]) @ poses[-1]
    rel_true = np.linalg.inv(sequence.poses[0]) @ sequence.poses[7]
    assert np.allclose(rel, rel_true, atol=1e-4)
    depth = image_to_numpy(_as_image(msgs, 0))
    assert np.allclose(depth / 1000.0, sequence.depth[0], atol=2e-3)
    pts = cloud_to_xyz(_as_cloud(msgs))
    assert len(pts) > 20 and pts[:, 2].min() > -0.1  # landmarks stand on or above the floor
    text = summary.text()
    assert '1 no ground-truth pose within 0.02 s' in text and '1 no depth image within 0.02 s' in text


def _as_image(msgs, i):
    from sensor_msgs.msg import Image
    m = msgs['/camera/depth/image_raw'][i][1]
    return Image(height=m.height, width=m.width, encoding=m.encoding, is_bigendian=m.is_bigendian, step=m.step,
                 data=bytes(m.data))


def _as_cloud(msgs):
    from sensor_msgs.msg import PointCloud2, PointField
    m = msgs['/slam/points'][-1][1]
    fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in m.fields]
    return PointCloud2(height=m.height, width=m.width, fields=fields, is_bigendian=m.is_bigendian,
                       point_step=m.point_step, row_step=m.row_step, data=bytes(m.data), is_dense=m.is_dense)


def test_options_views_up_vector_and_no_landmarks(sequence, tum_dir, tmp_path):
    out = tmp_path / 'tum_up.mcap'
    summary = convert_tum(tum_dir / 'rgbd_dataset_freiburg3_fixture', out,
                          ConvertOptions(views=3, up=(0, 1, 0), gravity='up', landmarks='none', depth=False),
                          intrinsics=str(tum_dir / 'camera.yaml'))
    msgs = read_with_rosbags(out)
    assert summary.frames_written == 3 and set(msgs) == {'/camera/color/camera_info', '/camera/color/image_raw',
                                                         '/camera/pose'}
    T = _pose(msgs['/camera/pose'][0][1])
    # --up 0,1,0 is a pure rotation: the mocap offset stays, rotated
    assert np.allclose(T[:3, :3], sequence.poses[0][:3, :3], atol=1e-4)


def test_presets_and_clear_errors(tum_dir, tmp_path):
    assert INTRINSICS['ros'][:4] == (525.0, 525.0, 319.5, 239.5)
    folder = tum_dir / 'rgbd_dataset_freiburg3_fixture'
    with pytest.raises(ConvertError, match='are for 640x480'):  # the fr3 preset does not fit 128x96 images
        convert_tum(folder, tmp_path / 'x.mcap')
    with pytest.raises(ConvertError, match='unknown TUM intrinsics preset'):
        convert_tum(folder, tmp_path / 'x.mcap', intrinsics='fr9')
    with pytest.raises(ConvertError, match='missing rgb.txt'):
        convert_tum(tmp_path, tmp_path / 'x.mcap')
    assert not list(tmp_path.glob('x.mcap*'))  # nothing half-written


def test_cli_converts_and_reports(tum_dir, tmp_path, capsys):
    out = tmp_path / 'cli.mcap'
    code = cli_convert.main(['tum', str(tum_dir / 'rgbd_dataset_freiburg3_fixture'), str(out), '--intrinsics',
                             str(tum_dir / 'camera.yaml'), '--every', '2', '--quiet'])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    assert 'wrote' in printed.out and '4 of 9 frames' in printed.out and out.is_file()
    assert cli_convert.main(['tum', str(tum_dir), str(out), '--labels-tsv', 'x.tsv']) == 2
    assert '--labels-tsv does not apply to tum' in capsys.readouterr().err
    assert cli_convert.main(['tum', str(tmp_path / 'nowhere'), str(tmp_path / 'y.mcap')]) == 1
    assert 'TUM sequence folder not found' in capsys.readouterr().err
