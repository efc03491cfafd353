"""Test-run isolation for ROS 2: a private DDS domain and loopback-only discovery."""

import os

# Set before anything imports rclpy: one domain per test run so parallel runs never meet.
os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')

# The models derived by the tests (and their subprocesses) are stored in a directory of this run,
# removed at its end, not in the user's cache (ctid_ros/core/model_cache.py).
if 'CTID_CACHE_DIR' not in os.environ:
    import atexit
    import shutil
    import tempfile

    os.environ['CTID_CACHE_DIR'] = tempfile.mkdtemp(prefix='ctid-test-models-')
    atexit.register(shutil.rmtree, os.environ['CTID_CACHE_DIR'], True)
