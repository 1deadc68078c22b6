"""Breadth-first work order of the optimiser (frodo_optim.scheduling): every fused stage before any sparse one,
every sparse before any dense, the object seen first first; new input restarts an object; deferred dense stages
run, forced, only when nothing else waits."""
from frodo_optim.scheduling import Job, StageQueue


def drain(queue: StageQueue) -> list[tuple[int, str]]:
    """Run the queue to the end as the node does: each finished stage queues the next."""
    order = []
    while (job := queue.pop()) is not None:
        order.append((job.object_id, job.stage))
        queue.advance(job.object_id, job.stage)
    return order


def test_objects_are_refined_breadth_first_in_the_order_they_were_seen():
    queue = StageQueue()
    for oid in (7, 3, 5):
        queue.request(oid)
    assert queue.waiting() == {'fused': 3, 'sparse': 0, 'dense': 0} and len(queue) == 3
    assert drain(queue) == [(7, 'fused'), (3, 'fused'), (5, 'fused'), (7, 'sparse'), (3, 'sparse'), (5, 'sparse'),
                            (7, 'dense'), (3, 'dense'), (5, 'dense')]
    assert not queue and queue.pop() is None


def test_new_input_restarts_an_object_and_a_new_object_goes_before_the_others_later_stages():
    queue = StageQueue()
    queue.request(1)
    queue.request(2)
    assert queue.pop() == Job(1, 'fused')
    queue.advance(1, 'fused')                       # 1: sparse next
    queue.request(1)                                # its code changed meanwhile: from fused again, but 2's first
    assert queue.pop() == Job(2, 'fused')           # mesh goes before 1's re-run (1 was seen first)
    queue.advance(2, 'fused')
    assert queue.pop() == Job(1, 'fused')
    queue.advance(1, 'fused')
    queue.request(9)                                # seen last, but its first mesh comes before 1's sparse stage
    assert queue.waiting_before('sparse') and queue.waiting_before('dense')
    assert queue.pop() == Job(9, 'fused')
    assert not queue.waiting_before('sparse') and queue.pop() == Job(1, 'sparse')
    queue.request(1, 'sparse')
    queue.request(2, 'dense')                       # an earlier stage already queued (2's sparse) stays
    queue.request(9, 'dense')
    assert queue.waiting() == {'fused': 0, 'sparse': 2, 'dense': 1}
    queue.request(5)
    assert queue.queued('fused') == [5] and sorted(queue.queued('sparse')) == [1, 2] and queue.queued('dense') == [9]


def test_an_object_whose_code_changes_every_frame_does_not_keep_others_from_their_first_mesh():
    """While a bag plays, the first object's code changes with every frame: its fused stage is asked for again and
    again. Objects seen after it still get their first fused stage next; the re-run follows, then the sparse
    stages in the order the objects were seen."""
    queue = StageQueue()
    queue.request(0)
    assert queue.pop() == Job(0, 'fused')
    queue.advance(0, 'fused')
    for new in (1, 2, 3):
        queue.request(new)
        queue.request(0)                            # new code for 0 with every frame
        job = queue.pop()
        assert job == Job(new, 'fused'), job
        queue.advance(new, 'fused')
    assert queue.pop() == Job(0, 'fused')           # its re-run after every first mesh
    queue.advance(0, 'fused')
    assert [queue.pop() for _ in range(4)] == [Job(oid, 'sparse') for oid in (0, 1, 2, 3)]
    queue.advance(0, 'sparse')
    queue.request(0, 'sparse')                      # 0's sparse asked for again before 1's first one ran
    queue.request(1, 'sparse')
    assert queue.pop() == Job(1, 'sparse')


def test_a_deferred_dense_stage_waits_for_an_empty_queue_and_then_runs_forced():
    queue = StageQueue()
    queue.request(1)
    queue.request(2)
    queue.pop(), queue.pop()                        # both fused
    queue.defer(1)                                  # 1's dense stage: not due while others wait
    queue.advance(2, 'fused')
    assert queue.waiting() == {'fused': 0, 'sparse': 1, 'dense': 1} and queue.objects() == {1, 2}
    assert queue.pop() == Job(2, 'sparse')
    assert queue.pop() == Job(1, 'dense', forced=True)
    queue.defer(3)
    queue.request(3)                                # new input cancels the deferral: from fused
    assert queue.pop() == Job(3, 'fused')
    queue.advance(3, 'dense')                       # the last stage has no successor
    queue.request(4)
    queue.discard(4)
    assert queue.pop() is None
