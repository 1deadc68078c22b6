"""Capture-condition randomisation of encoder training crops (`augment.py`): each condition does what a
handheld capture does to a detection crop."""
import numpy as np
import pytest

from frodo_shape.augment import CropAugmentation, augment_crop, mask_noise, occlude, truncate


def _object(size: int = 160):
    """A textured 'object' (a filled rectangle) in the middle of a context crop, and its box."""
    rng = np.random.default_rng(0)
    image = rng.integers(60, 200, (size, size, 3), dtype=np.uint8)
    mask = np.zeros((size, size), bool)
    mask[40:120, 50:110] = True
    image[mask] = (200, 40, 40)
    return image, mask, np.array([50.0, 40.0, 110.0, 120.0])


def test_truncation_zeroes_beyond_the_border_and_recentres_on_the_visible_part():
    image, mask, box = _object()
    for seed in range(20):
        cut_image, cut_mask, cut_box = truncate(image, mask, box, np.random.default_rng(seed), 0.55)
        assert cut_mask.sum() < mask.sum() and not (cut_mask & ~mask).any()
        assert (cut_box[:2] >= box[:2]).all() and (cut_box[2:] <= box[2:]).all()
        gone = mask & ~cut_mask
        assert (cut_image[gone] == 0).all()              # beyond the simulated border: the crop's zero padding
        assert cut_mask.sum() >= 0.25 * mask.sum()


def test_occluder_is_drawn_over_the_object_and_removed_from_its_mask():
    image, mask, box = _object()
    changed = 0
    for seed in range(20):
        occ_image, occ_mask, occ_box = occlude(image, mask, box, np.random.default_rng(seed), 0.45)
        assert not (occ_mask & ~mask).any() and occ_mask.sum() >= 0.4 * mask.sum()
        hidden = mask & ~occ_mask
        if hidden.any():
            changed += 1
            assert (occ_image[hidden] != image[hidden]).any(axis=-1).mean() > 0.9
            ys, xs = np.nonzero(occ_mask)
            assert tuple(occ_box) == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
    assert changed >= 10


@pytest.mark.parametrize('seed', range(6))
def test_mask_noise_stays_near_the_true_mask(seed):
    _, mask, _ = _object()
    noisy = mask_noise(mask, np.random.default_rng(seed), 3.0)
    iou = (noisy & mask).sum() / (noisy | mask).sum()
    assert 0.75 < iou < 1.0


def test_enabled_conditions_change_the_crop_and_keep_its_format():
    image, mask, box = _object()
    plain = augment_crop(image, mask, box, np.random.default_rng(3), 64)
    strong = CropAugmentation(p_truncate=1, p_occlude=1, p_mask_noise=1, p_blur=1, p_vignette=1, p_exposure=1)
    crop, cmask = augment_crop(image, mask, box, np.random.default_rng(3), 64, aug=strong)
    assert crop.shape == (64, 64, 3) and crop.dtype == np.uint8 and cmask.shape == (64, 64) and cmask.any()
    assert not (crop == plain[0]).all() and not (cmask == plain[1]).all()


def test_unknown_augment_keys_are_refused():
    with pytest.raises(ValueError, match='p_trunkate'):
        CropAugmentation.from_dict({'p_trunkate': 0.3})
    assert CropAugmentation.from_dict({'p_blur': '0.5'}).p_blur == 0.5


def test_handheld_evaluation_crops_are_seeded_and_differ_from_clean_ones():
    import trimesh
    from frodo_shape.evaluate_prior import heldout_views
    from frodo_shape.train import TrainingShape
    shape = TrainingShape('box', 'chair', 'primitive', 0.5, trimesh.creation.box((1.2, 0.8, 1.6)))
    cut = CropAugmentation(p_truncate=1.0)
    first = heldout_views([shape], 2, handheld=cut)
    again = heldout_views([shape], 2, handheld=cut)
    clean = heldout_views([shape], 2)
    for (i, crop, mask), (_, crop2, mask2), (_, clean_crop, clean_mask) in zip(first, again, clean):
        assert i == 0 and crop.shape == (128, 128, 3) and (crop == crop2).all() and (mask == mask2).all()
        assert mask.any() and clean_mask.any() and (mask != clean_mask).any()
