"""
ctid_ros: continuous-time grey-box identification for ROS 2.

Only :mod:`ctid_ros.ros` imports ROS (rclpy); the numerical core needs nothing of it::

    from ctid_ros import Data, Model, estimate

    model = Model('K*exp(-tau*s)/(T*s + 1)')
    y = model.simulate({'K': 2.0, 'T': 1.5, 'tau': 0.237}, u, ts=0.01)

``Data``, ``Model``, ``Estimate`` and ``estimate`` are imported on first use (PEP 562), so
importing a subpackage that needs none of them (the ``ctid`` command line, the errors) does not
load sympy and scipy.
"""

import importlib
from typing import Any, List

from ctid_ros.errors import (BagError, ConfigError, CtidError, DataError, EstimationError,
                             ModelError)

__all__ = [
    'BagError', 'ConfigError', 'CtidError', 'Data', 'DataError', 'Estimate', 'EstimationError',
    'Model', 'ModelError', 'estimate',
]

# The public names defined elsewhere, by the module that defines each.
_LAZY = {'Data': 'ctid_ros.core.data', 'Model': 'ctid_ros.core.model',
         'Estimate': 'ctid_ros.estimation.estimate', 'estimate': 'ctid_ros.estimation.estimate'}


def __getattr__(name: str) -> Any:
    """Import ``Data``, ``Model``, ``Estimate`` and ``estimate`` when first asked for."""
    if name not in _LAZY:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    value = getattr(importlib.import_module(_LAZY[name]), name)
    globals()[name] = value
    return value


def __dir__() -> List[str]:
    """List the module's names, the ones not imported yet included."""
    return sorted(set(globals()) | set(_LAZY))
