"""`frodo convert redwood`: a Redwood-OS-style sequence written by the test (rgb/NNNNNNN-TTTTTTTTTTTT.jpg,
depth/ in mm, a `.log` trajectory with "i i i+1" headers in a world that is not z up, a missing colour image)
and an optional ground-truth mesh."""
import numpy as np
import pytest

from frodo_common.geometry import make_transform, quat_to_matrix
from frodo_datasets.convert import ConvertError, ConvertOptions, convert_redwood
from frodo_datasets.convert.fixtures import read_with_rosbags, render_sequence, write_intrinsics_yaml, write_redwood
from frodo_datasets.convert.redwood import PRIMESENSE, read_log, read_redwood

# The trajectory's world: z -> y (y up), x -> z.
A = make_transform(np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]]), (0.0, 0.0, 0.0))


@pytest.fixture(scope='module')
def sequence():
    return render_sequence(frames=8, width=128, height=96, seed=4, layout='orbit', objects=1, classes=('chair',))


@pytest.fixture(scope='module')
def redwood(sequence, tmp_path_factory):
    root = tmp_path_factory.mktemp('redwood')
    write_redwood(sequence, root / '00033', A, missing_image=4)
    write_intrinsics_yaml(sequence, root / 'cam.yaml')
    sequence.scene.objects[0].mesh_world.apply_transform(A).export(root / 'chair.ply')
    return root


def _poses(msgs):
    out = []
    for _, m in msgs['/camera/pose']:
        p = m.pose
        out.append(make_transform(quat_to_matrix([p.orientation.x, p.orientation.y, p.orientation.z,
                                                  p.orientation.w]), [p.position.x, p.position.y, p.position.z]))
    return out


def test_log_and_frame_pairing_with_a_gap(sequence, redwood):
    entries = read_log(redwood / '00033' / 'trajectory.log')
    assert len(entries) == 8 and entries[0][0] == (0, 0, 1)
    src = read_redwood(redwood / '00033', intrinsics=redwood / 'cam.yaml')
    assert [f.index for f in src.frames] == [1, 2, 3, 4, 6, 7, 8]  # frame 5's colour image is missing
    assert src.skipped == {'trajectory entry without a colour image': 1}
    for f in src.frames:
        assert np.allclose(f.pose, A @ sequence.poses[f.index - 1], atol=1e-6)
    # stamps from the names' microsecond part
    assert src.frames[1].stamp_ns - src.frames[0].stamp_ns == 33333 * 1000
    assert PRIMESENSE == (525.0, 525.0, 319.5, 239.5)


def test_bag_is_z_up_with_the_ground_truth_mesh(sequence, redwood, tmp_path):
    out = tmp_path / 'rw.mcap'
    summary = convert_redwood(redwood / '00033', out, intrinsics=redwood / 'cam.yaml', mesh=redwood / 'chair.ply',
                              mesh_class='chair')
    msgs = read_with_rosbags(out)
    assert summary.frames_written == 7 and 'floor plane fit' in summary.gravity
    kept = [0, 1, 2, 3, 5, 6, 7]
    for k, T in zip(kept, _poses(msgs)):
        assert np.allclose(T[2, :3], sequence.poses[k][2, :3], atol=0.02)
        assert T[2, 3] == pytest.approx(sequence.poses[k][2, 3], abs=0.02)
    (marker,) = msgs['/ground_truth/objects'][0][1].markers
    v = np.array([[p.x, p.y, p.z] for p in marker.points])
    assert marker.ns == 'chair' and v[:, 2].min() == pytest.approx(0.0, abs=0.02)  # stands on the fitted floor
    height = np.ptp(sequence.scene.objects[0].mesh_world.vertices[:, 2])
    assert np.ptp(v[:, 2]) == pytest.approx(height, abs=0.02)


def test_errors(redwood, tmp_path):
    with pytest.raises(ConvertError, match='not a Redwood sequence'):
        convert_redwood(tmp_path, tmp_path / 'x.mcap')
    with pytest.raises(ConvertError, match='PrimeSense default'):  # 128x96 images, 640x480 intrinsics
        convert_redwood(redwood / '00033', tmp_path / 'x.mcap')
    bad = tmp_path / 'bad.log'
    bad.write_text('0 0 1\n1 0 0 0\n0 1 0 0\n')
    with pytest.raises(ConvertError, match='5 lines per frame'):
        convert_redwood(redwood / '00033', tmp_path / 'x.mcap', ConvertOptions(), trajectory=bad,
                        intrinsics=redwood / 'cam.yaml')
    assert not list(tmp_path.glob('x.mcap*'))
