"""`frodo convert scannet`: scene folders written by the test in ScanNet's layouts (a real `.sens` binary with
JPEG colour and zlib depth, and the SensReader export), colour at twice the depth/label resolution, 2D
instance/label annotations with the label table, the scene mesh with segments and aggregation, a -inf pose
and a missing colour frame."""
import json
import shutil

import numpy as np
import pytest

from frodo_common.geometry import make_transform, quat_to_matrix
from frodo_datasets.convert import ConvertError, ConvertOptions, convert_scannet
from frodo_datasets.convert.fixtures import read_with_rosbags, render_sequence, write_scannet
from frodo_datasets.convert.scannet import SensFile, read_scannet

N = 8


@pytest.fixture(scope='module')
def sequence():
    return render_sequence(frames=N, width=128, height=96, seed=2, layout='orbit', objects=3)


@pytest.fixture(scope='module')
def scenes(sequence, tmp_path_factory):
    root = tmp_path_factory.mktemp('scannet')
    write_scannet(sequence, root / 'exported' / 'scene0000_00', 'exported', invalid_pose=(2,), missing_color=(5,),
                  color_scale=2)
    write_scannet(sequence, root / 'sens' / 'scene0000_00', 'sens', invalid_pose=(2,), color_scale=2)
    return root


def _pose(m):
    p = m.pose
    return make_transform(quat_to_matrix([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]),
                          [p.position.x, p.position.y, p.position.z])


def _pixels(m):
    return np.frombuffer(bytes(m.data), '<u2').reshape(m.height, m.width)


def test_sens_binary_is_parsed(sequence, scenes):
    sens = SensFile(scenes / 'sens' / 'scene0000_00' / 'scene0000_00.sens')
    assert (sens.num_frames, sens.color_width, sens.color_height, sens.depth_width, sens.depth_height) == \
        (N, 256, 192, 64, 48)
    assert sens.depth_shift == 1000.0 and sens.sensor_name == 'StructureSensor'
    assert np.all(np.isinf(sens.poses[2])) and np.allclose(sens.poses[1], sequence.poses[1], atol=1e-6)
    assert sens.timestamps[3] == 3 * 33333
    assert sens.color(0).shape == (192, 256, 3)
    depth = sens.depth(1)
    expected = np.round(sequence.depth[1][::2, ::2] * 1000) / 1000
    assert depth.shape == (48, 64) and np.allclose(depth, expected, atol=1e-6)


def test_sens_and_exported_layouts_give_the_same_bag_content(sequence, scenes, tmp_path):
    summaries, bags = {}, {}
    for layout in ('sens', 'exported'):
        out = tmp_path / f'{layout}.mcap'
        summaries[layout] = convert_scannet(scenes / layout / 'scene0000_00', out)
        bags[layout] = read_with_rosbags(out)
    assert summaries['sens'].skipped == {'invalid pose (inf/NaN or not rigid)': 1}
    assert summaries['exported'].skipped == {'missing colour image': 1, 'invalid pose (inf/NaN or not rigid)': 1}
    assert summaries['sens'].frames_written == N - 1 and summaries['exported'].frames_written == N - 2
    assert summaries['sens'].gravity.startswith('none') and summaries['sens'].size == (128, 96)
    sens, exported = bags['sens'], bags['exported']
    kept = [k for k in range(N) if k != 2]
    for k, (_, m) in zip(kept, sens['/camera/pose']):
        assert np.allclose(_pose(m), sequence.poses[k], atol=1e-5)
    # the same frames (sens minus frame 5) carry identical instances and poses in both layouts
    sens_by_k = dict(zip(kept, sens['/camera/instances']))
    exp_kept = [k for k in kept if k != 5]
    for k, (_, m) in zip(exp_kept, exported['/camera/instances']):
        assert np.array_equal(_pixels(m), _pixels(sens_by_k[k][1]))
    # colour resized down to the label resolution, intrinsics scaled back to the rendered camera
    info = sens['/camera/color/camera_info'][0][1]
    assert (info.width, info.height) == (128, 96) and np.allclose(np.reshape(info.k, (3, 3)), sequence.K, atol=1e-9)
    # depth registered from the 64x48 depth camera to the 128x96 output (nearest neighbour)
    depth = _pixels(sens['/camera/depth/image_raw'][0][1]) / 1000.0
    valid = sequence.depth[0] > 0
    true = sequence.depth[0][valid]
    assert np.mean(np.abs(depth[valid] - true) < 0.03 * true) > 0.9  # a pixel's neighbour on slanted surfaces


def test_instances_carry_coco_classes_and_drop_unmapped_ones(sequence, scenes, tmp_path):
    out = tmp_path / 'inst.mcap'
    convert_scannet(scenes / 'sens' / 'scene0000_00', out)
    inst = _pixels(read_with_rosbags(out)['/camera/instances'][0][1])
    labels = sequence.labels[0]
    for obj in sequence.scene.objects:
        mask = labels == obj.id
        if mask.sum() > 10:
            assert np.all((inst[mask] >> 8) == obj.coco_id)  # office chair / chair -> 62, table -> 67
    assert np.all(inst[labels == 0] == 0)  # the floor is annotated in ScanNet but not mapped
    ks = np.unique(inst[inst > 0] & 0xFF)
    assert set(ks) <= {1, 2, 3}


def test_classes_from_label_images_and_tsv_without_aggregation(scenes, tmp_path):
    src = scenes / 'sens' / 'scene0000_00'
    copy = tmp_path / 'scene0000_00'
    shutil.copytree(src, copy)
    (copy / 'scene0000_00.aggregation.json').unlink()
    a, b = tmp_path / 'agg.mcap', tmp_path / 'tsv.mcap'
    convert_scannet(src, a, ConvertOptions(ground_truth=False))
    convert_scannet(copy, b)
    for (_, ma), (_, mb) in zip(read_with_rosbags(a)['/camera/instances'], read_with_rosbags(b)['/camera/instances']):
        assert np.array_equal(_pixels(ma), _pixels(mb))
    (copy / 'scannetv2-labels.combined.tsv').unlink()
    with pytest.raises(ConvertError, match='needs the classes'):
        convert_scannet(copy, tmp_path / 'x.mcap')


def test_class_map_and_instances_at_colour_resolution(sequence, scenes, tmp_path):
    out = tmp_path / 'chairs.mcap'
    summary = convert_scannet(scenes / 'sens' / 'scene0000_00', out, ConvertOptions(instances_at='color', views=3),
                              class_map={'office chair': 62, 'chair': 62})
    msgs = read_with_rosbags(out)
    assert summary.size == (256, 192) and summary.frames_written == 3
    inst = _pixels(msgs['/camera/instances'][0][1])
    assert inst.shape == (192, 256) and set(np.unique(inst >> 8)) <= {0, 62}
    assert [m.ns for m in msgs['/ground_truth/objects'][0][1].markers] == ['chair', 'chair']


def test_ground_truth_meshes_are_cut_from_the_scene_mesh(sequence, scenes, tmp_path):
    out = tmp_path / 'gt.mcap'
    convert_scannet(scenes / 'exported' / 'scene0000_00', out)
    markers = read_with_rosbags(out)['/ground_truth/objects'][0][1].markers
    assert [(m.ns, m.id) for m in markers] == [(o.class_name, o.id) for o in sequence.scene.objects]
    for m, obj in zip(markers, sequence.scene.objects):
        v = np.array([[p.x, p.y, p.z] for p in m.points])
        assert np.allclose([v.min(axis=0), v.max(axis=0)], obj.mesh_world.bounds, atol=1e-5)
        assert len(v) == 3 * len(obj.mesh.faces)


def test_clear_errors(scenes, tmp_path):
    with pytest.raises(ConvertError, match='is not a ScanNet scene'):
        convert_scannet(tmp_path, tmp_path / 'x.mcap')
    bad = tmp_path / 'bad'
    bad.mkdir()
    data = (scenes / 'sens' / 'scene0000_00' / 'scene0000_00.sens').read_bytes()
    (bad / 'bad.sens').write_bytes(data[:len(data) // 2])
    with pytest.raises(ConvertError, match='truncated'):
        read_scannet(bad)
    seg = json.loads((scenes / 'sens' / 'scene0000_00' / 'scene0000_00_vh_clean_2.0.010000.segs.json').read_text())
    assert len(seg['segIndices']) > 0
    assert not list(tmp_path.glob('x.mcap*'))
