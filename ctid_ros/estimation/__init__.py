"""
Estimation of grey-box parameters: the projection iteration, its starts and the covariance.

Depends on :mod:`ctid_ros.core` only; imports no ROS code.
"""
