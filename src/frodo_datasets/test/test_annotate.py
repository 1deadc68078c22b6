"""`frodo_datasets.annotate`: a rendered TUM-layout sequence of one table (mocap world not z up) annotated with
its bounding box; the fused mesh fills the box, the masks match the renderer's instance labels, the bag has
instances, ground truth and a sidecar with the box in the bag's world, and the results block is replaced."""
import json

import numpy as np
import pytest

from frodo_common.conversions import image_to_numpy
from frodo_common.geometry import make_transform
from frodo_datasets import annotate
from frodo_datasets.convert.fixtures import read_with_rosbags, render_sequence, write_intrinsics_yaml, write_tum

T_MOCAP_WORLD = make_transform(np.eye(3), (0.5, -0.2, 0.0))  # a shifted z-up mocap world


@pytest.fixture(scope='module')
def sequence():
    return render_sequence(frames=8, width=128, height=96, seed=2, objects=1, classes=('dining table',))


@pytest.fixture(scope='module')
def tum(sequence, tmp_path_factory):
    root = tmp_path_factory.mktemp('annot')
    folder = write_tum(sequence, root / 'rgbd_dataset_freiburg3_fixture', T_MOCAP_WORLD, extra_rgb=False)
    obj = sequence.scene.objects[0]
    lo, hi = obj.mesh_world.bounds
    lo, hi = lo + T_MOCAP_WORLD[:3, 3], hi + T_MOCAP_WORLD[:3, 3]
    lo = lo - 0.03
    hi = hi + 0.03
    lo[2] = 0.02  # leave the floor out
    doc = {'intrinsics': str(write_intrinsics_yaml(sequence, root / 'camera.yaml')), 'gravity': 'none',
           'objects': [{'id': 1, 'class': 'dining table', 'name': 'table',
                        'box': {'center': ((lo + hi) / 2).tolist(), 'size': (hi - lo).tolist(), 'yaw_deg': 0}}]}
    (root / 'a.json').write_text(json.dumps(doc))
    return root, folder, obj


def _iou(a, b):
    return np.count_nonzero(a & b) / max(np.count_nonzero(a | b), 1)


def test_fused_mesh_fills_the_box_and_masks_match_the_rendered_labels(sequence, tum):
    root, folder, obj = tum
    doc = annotate.load_annotation(root / 'a.json')
    source = annotate.read_sequence(folder, doc)
    box = doc['parsed_objects'][0].box
    mesh = annotate.fuse_object(source, box, every=1, voxel=0.01)
    true_lo, true_hi = obj.mesh_world.bounds + T_MOCAP_WORLD[:3, 3]
    assert np.allclose(mesh.bounds[1], true_hi, atol=0.03)  # top and sides where seen
    assert np.allclose(mesh.bounds[0][:2], true_lo[:2], atol=0.03)
    ious = []
    for f, labels in zip(source.frames, sequence.labels):
        truth = labels == obj.id
        if np.count_nonzero(truth) < 50:
            continue
        mask = annotate.object_masks([mesh], f.depth(), source.K_color, f.pose) == 1
        ious.append(_iou(mask, truth))
    assert len(ious) >= 4 and min(ious) > 0.9, ious


def test_build_writes_instances_ground_truth_and_sidecar(tum, tmp_path):
    root, folder, obj = tum
    out = tmp_path / 'a.mcap'
    side = annotate.build_bag(root / 'a.json', folder, out, voxel=0.02, every_fuse=2, min_pixels=20, log=lambda s: None)
    msgs = read_with_rosbags(out)
    assert len(msgs['/camera/instances']) == 8 and len(msgs['/ground_truth/objects']) == 1
    m = msgs['/camera/instances'][0][1]
    from sensor_msgs.msg import Image
    inst = image_to_numpy(Image(height=m.height, width=m.width, encoding=m.encoding, step=m.step, data=bytes(m.data)))
    assert set(np.unique(inst)) <= {0, 67 * 256 + 1} and np.count_nonzero(inst) > 100
    o = side['scene']['objects'][0]
    assert o['masked_frames'] >= 6 and o['coco_id'] == 67
    assert np.allclose(o['box_center'], annotate.load_annotation(root / 'a.json')['parsed_objects'][0].box.center)
    assert json.loads((tmp_path / 'a.gt.json').read_text())['camera']['width'] == 128


def test_results_block_is_replaced(tmp_path):
    readme = tmp_path / 'R.md'
    readme.write_text('# x\n')
    annotate.replace_section(readme, 'one')
    annotate.replace_section(readme, 'two')
    text = readme.read_text()
    assert text.count(annotate.RESULTS_BEGIN) == 1 and 'two' in text and 'one' not in text
    assert annotate.height_peaks(np.r_[np.zeros(50), np.full(30, 0.75), np.linspace(0, 1, 10)])[0][1] >= 50


def test_measure_reuses_only_runs_of_the_same_commit(tmp_path):
    """`annotate measure` reconstructs again when a run folder's results came from another commit, so the figures
    it writes under a commit are that commit's."""
    from frodo_datasets.annotate import RUN_COMMIT, has_results_of
    assert not has_results_of(tmp_path, 'abc')
    (tmp_path / 'objects.json').write_text('[]')
    assert not has_results_of(tmp_path, 'abc')               # a run from before the commit was recorded
    (tmp_path / RUN_COMMIT).write_text('abc\n')
    assert has_results_of(tmp_path, 'abc') and not has_results_of(tmp_path, 'def')
