"""
The bare bag read a user writes with rosbags: every message of one topic read and deserialised.

The baseline of ``ctid replay`` in ``bench/replay_startup.py`` (issue #26), run as a fresh
process: ``rosbags.highlevel.AnyReader`` over the bag, ``deserialize`` of every message on the
topic, the two fields the identification needs kept in Python lists.

Run with ``python -m bench.bare_bag_read BAG [TOPIC]``.
"""

from pathlib import Path
import sys

from rosbags.highlevel import AnyReader

__all__ = ['main']


def main(argv=None) -> int:
    """Read and deserialise every message of the topic; print how many."""
    path, *rest = sys.argv[1:] if argv is None else argv
    topic = rest[0] if rest else '/joint_states'
    efforts, velocities = [], []
    with AnyReader([Path(path)]) as reader:
        connections = [c for c in reader.connections if c.topic == topic]
        for connection, _, raw in reader.messages(connections=connections):
            message = reader.deserialize(raw, connection.msgtype)
            efforts.append(message.effort[0])
            velocities.append(message.velocity[0])
    print(len(efforts))
    return 0


if __name__ == '__main__':
    sys.exit(main())
