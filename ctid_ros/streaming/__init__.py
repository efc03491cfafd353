"""
Identification on streams of stamped samples: configuration, buffer, sessions, replay.

Shared by the live node and the offline replay; imports no ROS code.
"""

__all__: list = []
