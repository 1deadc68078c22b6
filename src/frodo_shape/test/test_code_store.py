"""The shape node's code memory stays bounded on long runs (CodeStore) while fusion still sees every part of
an object's trajectory and the view count keeps counting."""
import numpy as np
import pytest

from frodo_shape.code_store import CodeStore


def _feed(store: CodeStore, frames: int, objects: int = 2) -> None:
    rng = np.random.default_rng(0)
    for stamp in range(frames):
        for oid in range(objects):
            store.add((stamp, oid + 1), rng.normal(size=64))
        store.assign_frame(stamp, {oid + 1: 10 + oid for oid in range(objects)})


def test_codes_per_object_stay_within_the_bound_and_spread_over_the_run():
    store = CodeStore(per_object=32)
    _feed(store, 5000)
    members = store.members()
    assert set(members) == {10, 11} and len(store) <= 2 * 32 and len(store.assignment) == len(store)
    for oid, keys in members.items():
        stamps = [s for s, _ in keys]
        assert len(keys) <= 32 and store.num_views(oid, len(keys)) == 5000
        assert stamps[0] < 500 and stamps[-1] == 4999      # old and new parts of the run are both represented


def test_short_runs_are_not_thinned_and_reassignment_moves_codes():
    store = CodeStore(per_object=32)
    _feed(store, 16)
    assert len(store) == 32 and sum(store.thinned.values()) == 0
    store.assign_frame(3, {1: 11})                      # a re-send: label 2 left its object, label 1 moved
    members = store.members()
    assert (3, 1) in members[11] and (3, 2) not in store.assignment and (3, 2) in store
    assert store.forget_unassigned(lambda stamp: stamp >= 3) == 0    # its frame may still be re-sent
    assert store.forget_unassigned(lambda stamp: False) == 1 and (3, 2) not in store
    with pytest.raises(KeyError, match='no code stored'):
        store.assign_frame(99, {1: 10})
    with pytest.raises(ValueError):
        CodeStore(per_object=1)
