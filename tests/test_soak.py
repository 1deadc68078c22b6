"""Long inputs from the demo bag (stamps shifted per copy) and the soak run's probe and summary; the soak's
figures themselves are measured by `frodo bench --only soak`, not asserted here."""
from __future__ import annotations

import numpy as np
import pytest

from frodo_bringup import bench, cli
from frodo_bringup.long_bag import RepeatedMessages, RepeatingPlayer, repeat_bag, shift_stamp
from frodo_bringup.session import RosSession
from frodo_bringup.soak import SoakProbe, growth_per_1000_frames, summarise
from frodo_bringup.testing import wait_until
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.bag import BagMessage, BagReader

FRAME_TOPICS = (topics.IMAGE, topics.CAMERA_INFO, topics.POSE, topics.INSTANCES)


def _base() -> list[BagMessage]:
    return [m for m in BagReader(bench.DEMO_BAG).messages() if m.topic != topics.GROUND_TRUTH]


def test_repeat_bag_shifts_every_stamp_so_frames_keep_the_bag_rate(tmp_path):
    messages = list(BagReader(repeat_bag(bench.DEMO_BAG, tmp_path / 'long.mcap', copies=3)).messages())
    for topic in FRAME_TOPICS:
        stamps = [conv.stamp_to_ns(m.decode().header.stamp) for m in messages if m.topic == topic]
        assert len(stamps) == 150 and set(np.diff(stamps)) == {100_000_000}, topic   # 10 Hz across the joins
        assert stamps == [m.log_time_ns for m in messages if m.topic == topic]
    assert {m.topic for m in messages} == set(FRAME_TOPICS) | {topics.SLAM_POINTS}   # no ground truth


def test_repeated_messages_end_at_the_requested_frame_and_are_made_on_access():
    repeated = RepeatedMessages(_base(), frames=120)
    listed = list(repeated)
    assert sum(m.topic == topics.IMAGE for m in listed) == 120 and len(listed) == len(repeated)
    assert repeated.copies == 3 and repeated[-1] == listed[-1] and repeated[60] == listed[60]
    last_image = [m for m in listed if m.topic == topics.IMAGE][-1]
    assert max(m.log_time_ns for m in listed) == last_image.log_time_ns
    assert conv.stamp_to_ns(last_image.decode().header.stamp) == last_image.log_time_ns


def test_shift_stamp_refuses_messages_without_a_leading_header():
    pose = next(m for m in _base() if m.topic == topics.POSE)
    with pytest.raises(ValueError, match='does not start with a std_msgs/Header'):
        shift_stamp(BagMessage('/x', 'std_msgs/msg/String', 0, pose.data), 1)
    with pytest.raises(ValueError, match='not plain CDR'):
        shift_stamp(BagMessage(pose.topic, pose.msgtype, 0, b'\x00\x07' + pose.data[2:]), 1)


def test_repeating_player_publishes_every_frame_once_and_the_probe_counts_them():
    with RosSession('frodo_test_soak') as session:
        probe = SoakProbe(session.node, ['detection_node'])
        player = RepeatingPlayer(session.node, bench.DEMO_BAG, frames=70, rate=0.0, progress=False)
        assert player.message_count == len(list(player._messages)) and player.duration > 6.0
        assert not player.wait_for_subscribers(10.0, wanted=[topics.POSE], settle=0.5)
        stats = player.play()
        assert stats.published[topics.IMAGE] == 70
        assert wait_until(lambda: len(probe.pose_arrival) == 70, 20), len(probe.pose_arrival)
        probe.sample()
    row = probe.samples[-1]
    assert row['frames'] == 70 and row['rss_mb']['runner'] > 50   # this process holds rclpy, numpy, torch
    assert probe.latencies()[2] == 70                              # no association node: no outputs


def test_summary_tells_growing_memory_from_bounded_and_splits_latency_by_tenths():
    frames = np.arange(0, 2001, 100)
    samples = [{'t_s': float(i), 'frames': int(f), 'backlog': {'a': 3, 'b': int(f // 100)},
                'rss_mb': {'a': 100.0 + 5 * np.sin(f), 'b': 100.0 + 0.04 * f},           # b leaks 40 MB / 1000
                'sizes': {'b': {'views_held': float(min(f, 500))}}} for i, f in enumerate(frames)]
    index = np.arange(2000)
    latency = np.where(index < 1000, 20.0, 40.0)
    doc = summarise(samples, index, latency, {'a': [0.0, 1.0, 2.0, 3.5]})
    assert abs(doc['memory']['a']['growth_mb_per_1000_frames']) < 10
    assert doc['memory']['b']['growth_mb_per_1000_frames'] == pytest.approx(40.0)
    assert doc['memory']['b']['peak_mb'] == pytest.approx(180.0) and doc['memory']['b']['end_mb'] == 180.0
    assert doc['sizes']['b']['views_held'] == {'max': 500.0, 'end': 500.0, 'growth_per_1000_frames': 0.0}
    tenths = doc['latency_by_tenth']
    assert len(tenths) == 10 and tenths[0]['median_ms'] == 20.0 and tenths[-1]['median_ms'] == 40.0
    assert doc['latency']['last_to_first_tenth_median'] == 2.0
    assert doc['backlog_frames']['b'] == {'max': 20, 'end': 20}
    assert doc['diagnostics_intervals']['a'] == {'reports': 4, 'mean_s': 1.25, 'p95_s': 1.475, 'max_s': 1.5,
                                                 'over_1_25_s': 1}
    assert growth_per_1000_frames(np.array([5.0, 5.0, 5.0]), np.array([1.0, 2.0, 3.0])) is None


def test_frodo_bench_soak_is_not_in_the_default_set_and_checks_its_options(tmp_path, capsys):
    assert 'soak' in bench.ALL_SECTIONS and 'soak' not in bench.SECTIONS
    assert cli.main(['bench', '--only', 'soak', '--soak-frames', '0', '--out', str(tmp_path)]) == 2
    assert '--soak-frames must be >= 1' in capsys.readouterr().err
    assert not (tmp_path / 'bench.json').exists()
