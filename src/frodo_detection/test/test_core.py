"""Instance filtering keeps clean detections of the wanted classes and drops tiny, foreign, truncated and
fragmented ones; the Mask R-CNN wrapper emits contract instance images and names missing weights."""
import numpy as np
import pytest
import torch
import torchvision

from frodo_detection.core import (MASKRCNN_URL, FilterConfig, MaskRCNNDetector, WeightsNotFoundError,
                                  filter_instances, instance_boxes, masks_to_instances, resolution_scale,
                                  resolve_weights)

CHAIR, TABLE, PERSON = 62, 67, 1


def _label(coco, k):
    return coco * 256 + k


def _scene() -> np.ndarray:
    img = np.zeros((120, 160), np.uint16)
    img[20:60, 30:70] = _label(CHAIR, 1)       # clean chair, 40x40
    img[70:110, 80:150] = _label(TABLE, 2)     # clean table
    img[10:50, 100:140] = _label(PERSON, 3)    # class not wanted
    img[100:104, 10:14] = _label(CHAIR, 4)     # tiny
    img[30:80, 0:30] = _label(CHAIR, 5)        # touches the left border
    return img


def test_instance_boxes_pixel_edges():
    img = np.zeros((10, 10), np.uint16)
    img[2:5, 3:8] = 7
    labels, boxes, areas = instance_boxes(img)
    assert labels.tolist() == [7] and areas.tolist() == [15]
    assert boxes[0].tolist() == [2.5, 1.5, 7.5, 4.5]


def test_filter_drops_tiny_foreign_and_truncated():
    img = _scene()     # 160x120: 1/16 of the 640x480 reference pixels, so min_area 1600 means 100 px here
    out, dets = filter_instances(img, FilterConfig(classes=(CHAIR, TABLE), min_area=1600))
    assert sorted(d.label for d in dets) == [_label(CHAIR, 1), _label(CHAIR, 5), _label(TABLE, 2)]
    assert set(np.unique(out)) == {0, _label(CHAIR, 1), _label(CHAIR, 5), _label(TABLE, 2)}
    chair = next(d for d in dets if d.label == _label(CHAIR, 1))
    assert chair.bbox == (29.5, 19.5, 69.5, 59.5) and chair.area == 1600 and not chair.truncated
    assert next(d for d in dets if d.label == _label(CHAIR, 5)).truncated
    out, dets = filter_instances(img, FilterConfig(classes=(CHAIR, TABLE), min_area=1600, drop_truncated=True))
    assert sorted(d.label for d in dets) == [_label(CHAIR, 1), _label(TABLE, 2)]
    assert not np.any(out == _label(CHAIR, 5))
    _, dets = filter_instances(img, FilterConfig(classes=None, min_area=1, min_box_side=1))
    assert len(dets) == 5


def test_size_thresholds_scale_with_the_resolution():
    assert resolution_scale(640, 480) == 1.0 and resolution_scale(320, 240) == 0.5
    assert resolution_scale(1280, 960) == 2.0
    # A thin stool at 320x240: 10 px wide, 30 px high, 250 mask pixels. The defaults (400 px area, 16 px side
    # at 640x480) mean 100 px and 8 px here, so it is kept; the same stool at 640x480 (20 x 60 px, 1000 px)
    # is kept too, and a 12 x 12 px blob at 640x480 (below 16 px) is dropped at either size.
    small = np.zeros((240, 320), np.uint16)
    small[100:130, 150:160] = _label(CHAIR, 1)
    small[100:125:5, 150:160] = 0             # slats: 250 of the 300 box pixels are set
    small[10:16, 10:16] = _label(CHAIR, 2)    # 6 x 6 px here = 12 x 12 px at 640x480
    _, dets = filter_instances(small, FilterConfig())
    assert [d.label for d in dets] == [_label(CHAIR, 1)] and dets[0].area == 250
    big = np.kron(small, np.ones((2, 2), np.uint16))
    _, dets = filter_instances(big, FilterConfig())
    assert [d.label for d in dets] == [_label(CHAIR, 1)] and dets[0].area == 1000
    # Absolute thresholds would have dropped the stool at 320x240 (area 250 < 400).
    _, dets = filter_instances(small, FilterConfig(min_area=4 * 400))
    assert dets == []


def test_fragments_specks_and_policies():
    img = np.zeros((100, 100), np.uint16)
    lab = _label(CHAIR, 1)
    img[10:50, 10:50] = lab        # main piece, 1600 px
    img[60:90, 60:90] = lab        # second real piece, 900 px
    img[95, 95] = lab              # speck
    out, dets = filter_instances(img, FilterConfig(min_area=1))
    assert dets[0].area == 2500 and out[95, 95] == 0 and dets[0].bbox == (9.5, 9.5, 89.5, 89.5)
    _, dets = filter_instances(img, FilterConfig(min_area=1, fragment_policy='largest'))
    assert dets[0].area == 1600 and dets[0].bbox == (9.5, 9.5, 49.5, 49.5)
    _, dets = filter_instances(img, FilterConfig(min_area=1, fragment_policy='drop'))
    assert dets == []
    with pytest.raises(ValueError, match='fragment_policy'):
        FilterConfig(fragment_policy='merge')


def test_masks_to_instances_higher_score_on_top():
    masks = np.zeros((2, 8, 8), bool)
    masks[0, :, :5] = True
    masks[1, :, 3:] = True
    out = masks_to_instances(masks, np.array([CHAIR, TABLE]), np.array([0.6, 0.9]), (8, 8))
    assert out[0, 4] == _label(TABLE, 1) and out[0, 0] == _label(CHAIR, 2) and out.dtype == np.uint16


def test_missing_weights_error_names_file_and_url(tmp_path):
    with pytest.raises(WeightsNotFoundError) as err:
        resolve_weights(tmp_path / 'nope.pth')
    assert MASKRCNN_URL in str(err.value) and 'nope.pth' in str(err.value) and 'hub/checkpoints' in str(err.value)


def test_maskrcnn_wiring_with_random_weights():
    torch.manual_seed(0)
    model = torchvision.models.detection.maskrcnn_resnet50_fpn_v2(
        weights=None, weights_backbone=None, min_size=64, max_size=96, rpn_pre_nms_top_n_test=50,
        rpn_post_nms_top_n_test=20, box_detections_per_img=5)                 # small and quick on the CPU
    det = MaskRCNNDetector(model=model, score_threshold=0.0, classes=None)
    rgb = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    out = det.detect(rgb)
    assert out.shape == (48, 64) and out.dtype == np.uint16 and out.any()
    ks = np.unique(out[out > 0]) & 0xFF
    assert np.all((ks >= 1) & (ks <= 255))
    with pytest.raises(ValueError, match='RGB uint8'):
        det.detect(rgb[..., 0])
