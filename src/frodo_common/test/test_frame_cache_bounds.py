"""FrameCache stays bounded on long runs: frames by `capacity`, and the completed stamps it remembers (nodes pop
processed frames but keep their stamps marked complete) by `completed_capacity`, older stamps by a watermark."""
from frodo_common.frame_cache import CompletedStamps, FrameCache


def test_completed_stamps_stay_bounded_and_old_ones_still_count_as_completed():
    cache = FrameCache(('a', 'b'), capacity=10, completed_capacity=50)
    for stamp in range(10_000):
        cache.add(stamp, 'a', 1)
        assert cache.add(stamp, 'b', 2) is not None       # completes exactly once
        cache.frames.pop(stamp)                            # processed: popped, as the nodes do
    assert len(cache.completed) <= 50 and len(cache.completed._order) <= 50 and len(cache) == 0
    assert 9_999 in cache.completed and 3 in cache.completed and 10_000 not in cache.completed
    assert cache.add(3, 'b', 2) is None                    # a late duplicate part does not complete it again
    assert cache.add(10_000, 'a', 1) is None and cache.add(10_000, 'b', 1) is not None


def test_completed_stamps_default_to_ten_times_the_frame_capacity_and_discard():
    assert FrameCache(('a',), capacity=40).completed.capacity == 400
    stamps = CompletedStamps(3)
    for s in (5, 6, 7):
        stamps.add(s)
    stamps.discard(6)
    assert 6 not in stamps and stamps.watermark is None
    stamps.add(8)                                          # 5 leaves: it is now covered by the watermark
    assert stamps.watermark == 5 and 5 in stamps and 4 in stamps and 6 not in stamps and len(stamps) == 2
