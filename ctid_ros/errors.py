"""
Exceptions raised by ctid_ros.

Every failure a user can cause (a malformed model, unusable data, a bag that cannot be read, an
estimation problem that the data cannot answer) raises a subclass of :class:`CtidError` whose
message says what is wrong and what to do about it.
"""

__all__ = ['BagError', 'ConfigError', 'CtidError', 'DataError', 'EstimationError', 'ModelError']


class CtidError(Exception):
    """Base class of all errors raised by ctid_ros."""


class ModelError(CtidError, ValueError):
    """A model or controller expression is malformed, unsafe or not a proper transfer function."""


class DataError(CtidError, ValueError):
    """Input/output data are unusable (lengths, non-finite values, sample time, ...)."""


class EstimationError(CtidError, RuntimeError):
    """The data cannot identify the parameters (no excitation, rank deficiency, instability)."""


class ConfigError(CtidError, ValueError):
    """A configuration (params file, parameter update) is invalid."""


class BagError(CtidError, OSError):
    """A rosbag2 directory or MCAP file cannot be read, or lacks what the configuration needs."""
