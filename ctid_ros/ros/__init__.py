"""
The ROS 2 adapters: the identification node and the simulated plant node.

The only subpackage that imports rclpy.
"""

__all__: list = []
