"""frodo_datasets.rescale: a contract bag at another image size."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from frodo_common.bag import BagReader
from frodo_common.conversions import camera_info_to_K, image_to_numpy
from frodo_datasets.convert.common import resize_nearest, scale_intrinsics
from frodo_datasets.rescale import main, rescale_bag

REPO = Path(__file__).resolve().parents[3]
ORBIT = REPO / 'bags' / 'demo_orbit.mcap'


def test_labels_take_the_nearest_pixel_and_are_never_blended():
    labels = np.zeros((4, 6), np.uint16)
    labels[:, 3:] = 62 * 256 + 1
    half = resize_nearest(labels, (3, 2))
    assert half.dtype == np.uint16 and set(np.unique(half)) <= {0, 62 * 256 + 1}
    np.testing.assert_array_equal(half, labels[::2, ::2])
    np.testing.assert_array_equal(resize_nearest(half, (6, 4)), np.repeat(np.repeat(half, 2, 0), 2, 1))


def test_the_demo_orbit_at_half_size_keeps_every_message_and_its_ground_truth(tmp_path, capsys):
    out = tmp_path / 'orbit_half.mcap'
    assert main([str(ORBIT), str(out), '--scale', '0.5']) == 0
    assert 'camera/instances 35' in capsys.readouterr().out
    src, dst = BagReader(ORBIT), BagReader(out)
    assert {t: n for t, (_, n) in src.topics().items()} == {t: n for t, (_, n) in dst.topics().items()}
    info = [m.decode() for m in dst.messages(['/camera/color/camera_info'])]
    first = next(src.messages(['/camera/color/camera_info'])).decode()
    assert (info[0].width, info[0].height) == (first.width // 2, first.height // 2)
    np.testing.assert_allclose(camera_info_to_K(info[0]), scale_intrinsics(camera_info_to_K(first), (first.width, first.height), (info[0].width, info[0].height)))
    full = image_to_numpy(next(src.messages(['/camera/instances'])).decode())
    half = image_to_numpy(next(dst.messages(['/camera/instances'])).decode())
    assert half.shape == (full.shape[0] // 2, full.shape[1] // 2)
    assert set(np.unique(half)) <= set(np.unique(full)) and np.count_nonzero(half) > 0.2 * np.count_nonzero(full) / 4
    colour = image_to_numpy(next(dst.messages(['/camera/color/image_raw'])).decode())
    assert colour.shape[:2] == half.shape
    sidecar = json.loads(out.with_suffix('.gt.json').read_text())['camera']
    original = json.loads(ORBIT.with_suffix('.gt.json').read_text())['camera']
    assert sidecar['width'] == original['width'] // 2
    np.testing.assert_allclose(sidecar['K'], scale_intrinsics(np.array(original['K']), (original['width'],
                               original['height']), (sidecar['width'], sidecar['height'])))


def test_a_bad_scale_or_a_missing_bag_is_refused_with_a_message(tmp_path, capsys):
    assert main([str(ORBIT), str(tmp_path / 'x.mcap'), '--scale', '0']) == 1
    assert 'scale must be > 0' in capsys.readouterr().err
    assert main([str(tmp_path / 'missing.mcap'), str(tmp_path / 'y.mcap'), '--scale', '0.5']) == 1
    assert 'rescale: error' in capsys.readouterr().err


def test_the_half_size_orbit_is_reconstructed_like_the_original(tmp_path):
    from frodo_bringup.pipeline import reconstruct
    from frodo_common.evaluation import EvalObject, evaluate, load_ground_truth

    out = tmp_path / 'orbit_half.mcap'
    rescale_bag(ORBIT, out, 0.5)
    result = reconstruct(str(out))
    report = evaluate([EvalObject(o, e.class_name, e.mesh_world) for o, e in result.estimates.items()],
                      load_ground_truth(out))
    assert len(report.pairs) == 1 and not report.unmatched_pred and report.overall.f1 > 90
