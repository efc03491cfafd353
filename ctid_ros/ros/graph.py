"""
The ROS graph as the command-line tools see it: published topics, their types, matching QoS.

``ctid record`` and ``ctid echo`` stand in for ``ros2 bag record`` and ``ros2 topic echo``,
which the pip route lacks. Like them they learn a topic's type from the graph and subscribe
with a QoS that matches its publishers (:func:`matching_qos`): reliable where every publisher is
reliable, best effort otherwise; transient local where every publisher is (so the last estimate
the node latched arrives at once, however late the tool starts), volatile otherwise.
"""

import time
from typing import Dict, Iterable, List

from ctid_ros.errors import ConfigError
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

__all__ = ['matching_qos', 'published_types', 'wait_for_topics']

# Seconds between two looks at the graph while waiting for publishers.
_POLL = 0.05


def published_types(node: Node) -> Dict[str, List[str]]:
    """Return every topic that has a publisher, with its type(s)."""
    return {name: list(types) for name, types in node.get_topic_names_and_types()
            if node.count_publishers(name)}


def wait_for_topics(node: Node, topics: Iterable[str], timeout: float) -> Dict[str, str]:
    """
    Wait until every topic has a publisher; return each topic's message type.

    Parameters
    ----------
    node : Node
        Any node of the context (the graph is that of its DDS participant; nothing spins).
    topics : iterable of str
        Absolute topic names.
    timeout : float
        Seconds to wait for discovery.

    Raises
    ------
    ConfigError
        If a topic has no publisher after ``timeout`` (the message lists the published
        topics), or its publishers disagree on the type.

    """
    topics = list(dict.fromkeys(topics))
    deadline = time.monotonic() + timeout
    while True:
        published = published_types(node)
        if all(topic in published for topic in topics) or time.monotonic() > deadline:
            break
        time.sleep(_POLL)
    missing = [topic for topic in topics if topic not in published]
    if missing:
        listing = ', '.join(sorted(published)) or 'none'
        raise ConfigError(f'no publisher of {", ".join(missing)} after {timeout:g} s; published '
                          f'topics: {listing} (same ROS_DOMAIN_ID and discovery range as the '
                          'publishers?)')
    for topic in topics:
        if len(published[topic]) > 1:
            raise ConfigError(f'the publishers of {topic} disagree on its type: '
                              f'{", ".join(published[topic])}')
    return {topic: published[topic][0] for topic in topics}


def matching_qos(node: Node, topic: str, depth: int) -> QoSProfile:
    """
    Return a subscription QoS that matches every current publisher of ``topic``.

    Reliable if every publisher is reliable, else best effort (which matches both); transient
    local if every publisher is, else volatile. Without publishers: reliable and volatile, the
    ROS default.
    """
    publishers = node.get_publishers_info_by_topic(topic)
    reliable = all(info.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                   for info in publishers)
    latched = bool(publishers) and all(
        info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for info in publishers)
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE if reliable
                      else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                      else DurabilityPolicy.VOLATILE)
