"""TopicRecorder: live messages recorded as they come off the wire, read back without ROS."""

import itertools
import time

from ctid_ros.files.bag_reader import BagReader
from ctid_ros.files.mcap_writer import RecordingWriter
from ctid_ros.ros.recorder import TopicRecorder
from geometry_msgs.msg import PointStamped
import pytest
import rclpy
from rclpy.context import Context
from std_msgs.msg import Float64

_COUNTER = itertools.count()


def wait_for(predicate, timeout, what):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f'timed out after {timeout} s: {what}'
        time.sleep(0.02)


@pytest.mark.ros
def test_recorded_messages_read_back(tmp_path):
    namespace = f'/rec{next(_COUNTER)}_{int(time.time() * 1000) % 100000}'
    topics = {f'{namespace}/y': 'geometry_msgs/msg/PointStamped',
              f'{namespace}/u': 'std_msgs/msg/Float64'}
    context = Context()
    rclpy.init(context=context)
    publisher_node = rclpy.create_node('publisher', namespace=namespace, context=context)
    points = publisher_node.create_publisher(PointStamped, 'y', 10)
    floats = publisher_node.create_publisher(Float64, 'u', 10)
    decoded = []
    path = tmp_path / 'run.mcap'
    try:
        with RecordingWriter(path) as writer, TopicRecorder(writer, topics) as recorder:
            recorder.subscribe(f'{namespace}/u', 'std_msgs/msg/Float64', decoded.append)
            recorder.start()
            wait_for(lambda: points.get_subscription_count() and
                     floats.get_subscription_count() == 2, 60.0, 'subscriptions')
            for k in range(5):
                message = PointStamped()
                message.header.stamp.sec, message.point.x = 100 + k, 0.5 * k
                points.publish(message)
                floats.publish(Float64(data=float(k)))
            wait_for(lambda: recorder.counts == dict.fromkeys(topics, 5) and len(decoded) == 5,
                     20.0, lambda: recorder.counts)
    finally:
        publisher_node.destroy_node()
        rclpy.shutdown(context=context)
    assert [message.data for message in decoded] == [0.0, 1.0, 2.0, 3.0, 4.0]
    with BagReader(path) as bag:
        assert bag.topics() == topics
        points_read = [message.msg for message in bag.messages(f'{namespace}/y')]
        times = [message.log_time_ns for message in bag.messages()]
    assert [(msg.header.stamp.sec, msg.point.x) for msg in points_read] == [
        (100 + k, 0.5 * k) for k in range(5)]
    assert times == sorted(times) and times[0] > 1_600_000_000 * 10**9   # reception times
