"""Test-run isolation for ROS 2: a private DDS domain and loopback-only discovery."""

import os

# Set before anything imports rclpy: one domain per test run so parallel runs never meet.
os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
