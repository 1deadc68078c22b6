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
    queue.request(1)                                # its code changed meanwhile: from fused again
    assert queue.pop() == Job(1, 'fused')
    queue.advance(1, 'fused')
    queue.request(9)                                # seen last, but its first mesh comes before 1's sparse stage
    assert queue.waiting_before('sparse') and queue.waiting_before('dense')
    assert [queue.pop() for _ in range(2)] == [Job(2, 'fused'), Job(9, 'fused')]
    assert not queue.waiting_before('sparse') and queue.pop() == Job(1, 'sparse')
    queue.request(1, 'sparse')                      # an earlier stage already queued stays
    queue.request(2, 'dense')
    assert queue.waiting() == {'fused': 0, 'sparse': 1, 'dense': 1}


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
