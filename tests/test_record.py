"""`Recorder` / `frodo record`: log time = header stamp (receive time for header-less types), the publishers'
QoS kept as channel metadata, latched topics caught after the fact, a finalised rosbag2 MCAP."""
from __future__ import annotations

import time

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.qos import DurabilityPolicy
from rclpy.serialization import serialize_message
from visualization_msgs.msg import MarkerArray

from frodo_bringup import cli
from frodo_bringup.player import offered_qos_texts, qos_from_offered
from frodo_bringup.recorder import Recorder, has_header, header_stamp_ns
from frodo_bringup.session import RosSession
from frodo_bringup.testing import wait_until
from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.bag import BagReader


def test_header_stamp_is_read_from_cdr_bytes():
    pose = conv.make_pose_stamped(np.eye(4), 1_700_000_000_123_456_789, 'world')
    assert has_header(PoseStamped) and not has_header(MarkerArray)
    assert header_stamp_ns(serialize_message(pose)) == 1_700_000_000_123_456_789
    assert header_stamp_ns(serialize_message(PoseStamped())) is None  # unset stamp: use receive time


def test_recorder_keeps_stamps_and_qos(tmp_path):
    # Topics of this test's own: test domains cycle, so a participant another test left alive may share
    # the domain and publish (or listen) on the contract topics, changing counts and the negotiated QoS.
    pose_topic, objects_topic = '/frodo_test_record/pose', '/frodo_test_record/objects'
    stamps = [1_700_000_000_000_000_000 + i * 50_000_000 for i in range(5)]
    with RosSession('frodo_test_recorder') as session:
        node = session.node
        latched = node.create_publisher(MarkerArray, objects_topic, topics.LATCHED_QOS)
        latched.publish(MarkerArray())  # before the recorder exists: caught through transient local
        poses = node.create_publisher(PoseStamped, pose_topic, topics.FRAME_QOS)
        recorder = Recorder(node, tmp_path / 'rec.mcap', [pose_topic, objects_topic])
        assert wait_until(lambda: pose_topic in recorder.recorded_topics and poses.get_subscription_count() == 1
                          and recorder.subscription(pose_topic).get_publisher_count() == 1, 20)
        before = time.time_ns()
        for stamp in stamps:
            poses.publish(conv.make_pose_stamped(np.eye(4), stamp, 'world'))
        wait_until(lambda: recorder.counts[pose_topic] == 5 and recorder.counts[objects_topic] == 1, 20)
        assert dict(recorder.counts) == {pose_topic: 5, objects_topic: 1}
        recorder.close()
    reader = BagReader(tmp_path / 'rec.mcap')
    assert not reader.problems
    assert [m.log_time_ns for m in reader.messages([pose_topic])] == stamps
    (objects,) = reader.messages([objects_topic])
    assert objects.log_time_ns >= before - 5 * 10**9  # receive time (MarkerArray has no header)
    qos = offered_qos_texts(reader)
    assert qos_from_offered(qos[objects_topic], objects_topic).durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert qos_from_offered(qos[pose_topic], pose_topic).durability == DurabilityPolicy.VOLATILE


@pytest.mark.parametrize('args, message', [
    (['OUT'], 'name the topics to record or use --all'),
    (['not_a_bag.txt', '--all'], 'output must be an .mcap file'),
])
def test_bad_record_arguments_are_explained(tmp_path, capsys, args, message):
    args = [str(tmp_path / 'out.mcap') if a == 'OUT' else a for a in args]
    assert cli.main(['record', *args]) == 2
    assert message in capsys.readouterr().err
