"""
ctid_ros: continuous-time grey-box identification for ROS 2.

Only :mod:`ctid_ros.ros` imports ROS (rclpy); the numerical core needs nothing of it::

    from ctid_ros import Data, Model, estimate

    model = Model('K*exp(-tau*s)/(T*s + 1)')
    y = model.simulate({'K': 2.0, 'T': 1.5, 'tau': 0.237}, u, ts=0.01)
"""

from ctid_ros.core.data import Data
from ctid_ros.core.model import Model
from ctid_ros.errors import (BagError, ConfigError, CtidError, DataError, EstimationError,
                             ModelError)
from ctid_ros.estimation.estimate import Estimate, estimate

__all__ = [
    'BagError', 'ConfigError', 'CtidError', 'Data', 'DataError', 'Estimate', 'EstimationError',
    'Model', 'ModelError', 'estimate',
]
