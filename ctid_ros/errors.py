"""
Exceptions raised by ctid_ros.

Every failure a user can cause (a malformed model, unusable data, a bag that cannot be read, an
estimation problem that the data cannot answer) raises a subclass of :class:`CtidError` whose
message says what is wrong and what to do about it. A value quoted in a message goes through
:func:`bounded_repr`, so a hostile value (a YAML alias bomb, a huge array) cannot blow up the
message itself.
"""

import reprlib

__all__ = ['BagError', 'ConfigError', 'CtidError', 'DataError', 'DesignError', 'EstimationError',
           'ModelError', 'bounded_repr']

_REPR = reprlib.Repr()
_REPR.maxlevel = 3
_REPR.maxstring = 60
_REPR.maxother = 60
_REPR.maxlong = 40
for _name in ('maxlist', 'maxtuple', 'maxdict', 'maxset', 'maxfrozenset', 'maxarray', 'maxdeque'):
    setattr(_REPR, _name, 6)


def bounded_repr(value: object, limit: int = 80) -> str:
    """
    Return ``repr(value)`` cut to at most ``limit`` characters, in bounded time and memory.

    Containers are shown to a depth of three and six items each (:mod:`reprlib`), so a nested
    structure that would expand to gigabytes (a YAML alias bomb) costs nothing to quote, and a
    long string or number is elided in the middle.
    """
    try:
        text = _REPR.repr(value)
    except Exception:  # a broken __repr__ must not hide the error being reported
        text = f'<{type(value).__name__} object>'
    return text if len(text) <= limit else text[:limit - 3] + '...'


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


class DesignError(CtidError, ValueError):
    """No controller of the kind asked for can be designed from the model by the rule asked for."""
