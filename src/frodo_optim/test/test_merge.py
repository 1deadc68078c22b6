"""MapMerger / Retractions (frodo_optim.merge): the complete map from the optimiser workers' shares."""
import numpy as np
import pytest
from visualization_msgs.msg import Marker

from frodo_common import conversions as conv
from frodo_optim.merge import MapMerger, Retractions, WorkerLoads, item_marker
from frodo_optim.states import STATES_DTYPE


def _share(objects, deleted=()):
    """A worker's share as optim_node publishes it: DELETEs of its dropped (class, id), then its objects."""
    markers = [conv.delete_marker(ns, oid, 1, 'world') for ns, oid in deleted]
    markers += [conv.box_to_marker(np.array([oid, 0.0, 0.0]), np.ones(3), 0.0, ns, oid, 1, 'world')
                for ns, oid in objects]
    return markers


def _actions(items):
    return [(m.action, m.ns, m.id) for m in map(item_marker, items)]


def test_retractions_repeat_every_dropped_key_until_it_comes_back():
    r = Retractions()
    assert r.update({('chair', 1), ('chair', 2)}) == []
    assert r.update({('chair', 2)}) == [('chair', 1)]
    assert r.update({('chair', 2), ('dining table', 3)}) == [('chair', 1)]        # repeated
    assert r.update({('sofa', 2), ('chair', 1)}) == [('chair', 2), ('dining table', 3)]   # class change of 2
    assert r.update({('sofa', 2), ('chair', 1)}) == [('chair', 2), ('dining table', 3)]


def test_the_merged_map_holds_every_workers_share_and_replaces_a_share_as_a_whole():
    merger = MapMerger(3)
    merger.put_markers('objects', 1, _share([('chair', 1), ('chair', 4)]))
    assert _actions(merger.merged_markers('objects', 5, 'world')) == [(Marker.ADD, 'chair', 1), (Marker.ADD, 'chair', 4)]
    merger.put_markers('objects', 0, _share([('chair', 3), ('dining table', 0)]))
    merger.put_markers('objects', 2, _share([('chair', 2)]))
    assert [item_marker(m).id for m in merger.merged_markers('objects', 5, 'world')] == [0, 1, 2, 3, 4]
    assert merger.heard == {0, 1, 2}
    # Worker 1 drops 4 and 1 becomes a table; worker 2 restarted without its objects (an empty share).
    merger.put_markers('objects', 1, _share([('dining table', 1)], deleted=[('chair', 1), ('chair', 4)]))
    merger.put_markers('objects', 2, [])
    merged = merger.merged_markers('objects', 7, 'world')
    assert _actions(merged) == [(Marker.DELETE, 'chair', 1), (Marker.DELETE, 'chair', 2), (Marker.DELETE, 'chair', 4),
                                (Marker.ADD, 'dining table', 0), (Marker.ADD, 'dining table', 1),
                                (Marker.ADD, 'chair', 3)]
    assert all(conv.stamp_to_ns(m.header.stamp) == 7 for m in merged if m.action == Marker.DELETE)
    # The boxes are merged on their own.
    assert merger.merged_markers('boxes', 7, 'world') == []


def test_bad_shares_are_refused_with_a_clear_message():
    merger = MapMerger(2)
    with pytest.raises(ValueError, match='not in 0..1'):
        merger.put_markers('objects', 2, [])
    with pytest.raises(ValueError, match='DELETEALL'):
        merger.put_markers('objects', 1, [Marker(action=Marker.DELETEALL)])
    with pytest.raises(ValueError, match='kind'):
        merger.put_markers('tracks', 1, [])
    with pytest.raises(ValueError, match='at least 1'):
        MapMerger(0)


def test_state_tables_merge_by_object_id_and_a_share_replaces_the_workers_rows():
    merger = MapMerger(2)
    assert merger.merged_table() is None

    def table(ids):
        t = np.zeros(len(ids), dtype=STATES_DTYPE)
        t['object_id'] = ids
        return t

    merger.put_table(1, table([5, 1]))
    merger.put_table(0, table([2, 4]))
    assert merger.merged_table()['object_id'].tolist() == [1, 2, 4, 5]
    merger.put_table(1, conv.cloud_to_table(conv.table_to_cloud(table([3]), 1, 'world')))   # as received
    assert merger.merged_table()['object_id'].tolist() == [2, 3, 4]
    with pytest.raises(ValueError, match='different versions'):
        merger.put_table(1, np.zeros(1, dtype=[('object_id', '<i4')]))
    with pytest.raises(ValueError, match='without object_id'):
        merger.put_table(1, np.zeros(1, dtype=[('id', '<i4')]))


def test_a_mesh_shared_with_its_points_as_an_array_is_merged_as_it_came():
    merger = MapMerger(2)
    mesh = conv.mesh_marker_parts(np.eye(3), [[0, 1, 2]], 'chair', 5, 1, 'world')   # (marker, points (3, 3))
    merger.put_markers('objects', 1, [conv.delete_marker('chair', 2, 1, 'world'), mesh])
    (item,) = merger.merged_markers('objects', 2, 'world')
    assert item is mesh


def test_worker_0_reports_busy_until_every_worker_is_heard_idle_and_sums_their_pending_objects():
    loads = WorkerLoads(3)
    assert loads.combined(False, 0) == {'state': 'busy', 'pending_objects': 0, 'pending_by_worker': '0 ? ?'}
    loads.heard(1, 'idle', 0)
    assert loads.combined(False, 0)['state'] == 'busy'          # worker 2 not heard from yet
    loads.heard(2, 'busy', 3)
    assert loads.combined(False, 1) == {'state': 'busy', 'pending_objects': 4, 'pending_by_worker': '1 0 3'}
    loads.heard(2, 'idle', 0)
    assert loads.combined(False, 0) == {'state': 'idle', 'pending_objects': 0, 'pending_by_worker': '0 0 0'}
    assert loads.combined(True, 2)['state'] == 'busy'           # its own work counts too
    assert WorkerLoads(1).combined(False, 0)['state'] == 'idle'
    for worker in (0, 3):
        with pytest.raises(ValueError, match='not in 1..2'):
            loads.heard(worker, 'idle', 0)
