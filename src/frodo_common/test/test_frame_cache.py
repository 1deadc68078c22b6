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


def test_missed_frames_name_their_missing_parts_and_duplicates_are_counted():
    cache = FrameCache(['image', 'detections'], capacity=3, stale_after_ns=10, stale_after_s=0)
    cache.add(0, 'detections', 'd')          # never gets its image: a late joiner's first frames
    cache.add(1, 'detections', 'd')
    assert cache.missed() == (0, {})         # not stale yet: the image may still come
    cache.add(20, 'image', 'i')
    cache.add(20, 'detections', 'd')
    cache.add(20, 'detections', 'again')
    assert cache.duplicates == 1
    count, parts = cache.missed()
    assert count == 2 and parts == {'image': 2}
    for stamp in (21, 22, 23):
        cache.add(stamp, 'image', 'i')       # evicts 0, 1 (incomplete) and 20 (complete)
    count, parts = cache.missed()
    assert cache.evicted_incomplete == 2 and count == 2 and parts == {'image': 2}


def test_a_part_merely_queued_is_not_missed_until_it_waited_in_wall_clock_time():
    """At rate 0 the stamps run ahead of the wall clock: a frame whose pose is still queued is not missed."""
    cache = FrameCache(['image', 'pose'], stale_after_ns=10, stale_after_s=60)
    cache.add(0, 'image', 'i')
    cache.add(100, 'image', 'i')
    assert cache.missed() == (0, {})
    cache.frames[0].received -= 61
    assert cache.missed() == (1, {'pose': 1})
