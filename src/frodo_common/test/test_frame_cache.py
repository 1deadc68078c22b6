"""The frame cache completes frames in any arrival order and bounds memory."""
from frodo_common.frame_cache import FrameCache


def test_completes_once_in_any_order():
    cache = FrameCache(['image', 'pose'], capacity=10)
    assert cache.add(1, 'pose', 'p') is None
    frame = cache.add(1, 'image', 'i')
    assert frame is not None and frame.parts == {'pose': 'p', 'image': 'i'}
    assert cache.add(1, 'image', 'again') is None  # already delivered


def test_eviction_counts_incomplete():
    cache = FrameCache(['image', 'pose'], capacity=3)
    for stamp in range(5):
        cache.add(stamp, 'image', stamp)
    assert len(cache) == 3 and cache.evicted_incomplete == 2
    assert cache.get(0) is None and cache.get(4) is not None
