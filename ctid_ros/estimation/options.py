"""
The arguments of :func:`~ctid_ros.estimation.estimate.estimate`, checked and normalised once.

:func:`check_options` refuses every argument that is not what the documentation of ``estimate``
says, before any computation, with a :class:`~ctid_ros.errors.ConfigError` (a ``ValueError``)
that names the argument and quotes the value given (:func:`~ctid_ros.errors.bounded_repr`).
Names that the model does not have raise a :class:`~ctid_ros.errors.ModelError`, a record longer
than :data:`~ctid_ros.core.limits.MAX_SAMPLES` a :class:`~ctid_ros.errors.DataError`. What it
returns is plain Python: floats, ints, bools, tuples and dicts.
"""

import math
from numbers import Integral, Real
from typing import Any, Dict, Mapping, NamedTuple, Optional, Tuple, Union

from ctid_ros.core.data import Data
from ctid_ros.core.limits import MAX_SAMPLES
from ctid_ros.core.model import Model
from ctid_ros.core.simulation import INTERSAMPLE
from ctid_ros.errors import bounded_repr, ConfigError, DataError, ModelError
from ctid_ros.estimation.problem import delay_parameter
import numpy as np

__all__ = ['EstimateOptions', 'INITIAL_STATES', 'METHODS', 'check_options']

# The choices of estimate(); ctid_ros.cli.arguments writes them out for a fast --help.
METHODS = ('iv', 'ls', 'gn')
INITIAL_STATES = ('zero', 'estimate')

Pair = Tuple[Optional[float], Optional[float]]


class EstimateOptions(NamedTuple):
    """The keyword arguments of ``estimate`` after :func:`check_options`, in its order."""

    initial: Union[str, Dict[str, float]]
    bounds: Optional[Dict[str, Pair]]
    method: str
    intersample: str
    max_iterations: int
    tolerance: float
    delay_range: Optional[Tuple[float, float]]
    transient: Union[float, str]
    initial_state: str
    output_offset: bool
    integrator_cutoff: Optional[float]


def _refuse(argument: str, requirement: str, value: Any) -> ConfigError:
    return ConfigError(f'{argument} must be {requirement}, got {bounded_repr(value)}')


def _is_real(value: Any) -> bool:
    return isinstance(value, Real) and not isinstance(value, (bool, np.bool_))


def _number(value: Any, argument: str, requirement: str = 'a number') -> float:
    """Return ``value`` as a float if it is a real number (not a bool, not text)."""
    if not _is_real(value):
        raise _refuse(argument, requirement, value)
    try:
        return float(value)
    except (OverflowError, ValueError, TypeError):
        raise _refuse(argument, requirement, value) from None


def _choice(value: Any, argument: str, choices: Tuple[str, ...]) -> str:
    if not isinstance(value, str) or value not in choices:
        listed = ', '.join(repr(choice) for choice in choices)
        raise _refuse(argument, f'one of {listed}', value)
    return str(value)


def _names(values: Mapping, argument: str, model: Model) -> None:
    """Check that a mapping is keyed by parameter names of the model."""
    for name in values:
        if not isinstance(name, str):
            raise _refuse(f'the keys of {argument}', 'parameter names (strings)', name)
    unknown = sorted(set(values) - set(model.parameters))
    if unknown:
        what = 'initial values' if argument == 'initial' else 'bounds'
        raise ModelError(f'{what} given for unknown parameter(s) '
                         f'{", ".join(bounded_repr(name, 40) for name in unknown[:5])}; the '
                         f'model has {", ".join(model.parameters)}')


def _initial(initial: Any, model: Model) -> Union[str, Dict[str, float]]:
    if initial is None or (isinstance(initial, str) and initial == 'auto'):
        return 'auto'
    if not isinstance(initial, Mapping):
        raise _refuse('initial', "a dict {name: value} or 'auto'", initial)
    _names(initial, 'initial', model)
    values = {}
    for name, value in initial.items():
        number = _number(value, f'initial[{name!r}]', 'a finite number')
        if not math.isfinite(number):
            raise _refuse(f'initial[{name!r}]', 'a finite number', value)
        values[name] = number
    return values


def _bound(value: Any, argument: str, side: str) -> Optional[float]:
    """Return one side of a bound pair as a float, None for None or an infinite open side."""
    if value is None:
        return None
    where = f'the {side} side of {argument}'
    number = _number(value, where, 'a number or None')
    if math.isnan(number):
        raise _refuse(where, 'a number or None', value)
    if math.isinf(number):
        if (number < 0) != (side == 'low'):
            raise ConfigError(f'{argument} is empty: its {side} side is {number}')
        return None
    return number


def _bounds(bounds: Any, model: Model) -> Optional[Dict[str, Pair]]:
    if bounds is None:
        return None
    if not isinstance(bounds, Mapping):
        raise _refuse('bounds', 'a dict {name: (low, high)} or None', bounds)
    _names(bounds, 'bounds', model)
    delay_index = delay_parameter(model)
    delay = None if delay_index is None else model.parameters[delay_index]
    checked = {}
    for name, pair in bounds.items():
        argument = f'bounds[{name!r}]'
        if isinstance(pair, (str, bytes, Mapping)) or not hasattr(pair, '__len__') or \
                len(pair) != 2:
            raise _refuse(argument, 'a pair (low, high), either side None', pair)
        low, high = _bound(pair[0], argument, 'low'), _bound(pair[1], argument, 'high')
        if low is not None and high is not None and not low < high:
            raise ConfigError(f'{argument} is empty: the low side {low:g} is not below the high '
                              f'side {high:g}')
        if name == delay and high is not None and high <= 0.0:
            raise ConfigError(f'{argument}: {name} is a dead time, kept >= 0, so its upper '
                              f'bound must be positive, got {high:g}')
        checked[name] = (low, high)
    return checked


def _delay_range(delay_range: Any) -> Optional[Tuple[float, float]]:
    if delay_range is None:
        return None
    requirement = 'None or a pair (min, max) of seconds with 0 <= min < max'
    if isinstance(delay_range, (str, bytes)) or not hasattr(delay_range, '__len__') or \
            len(delay_range) != 2:
        raise _refuse('delay_range', requirement, delay_range)
    low, high = (_number(value, 'delay_range', requirement) for value in delay_range)
    if not (math.isfinite(low) and math.isfinite(high) and 0.0 <= low < high):
        raise _refuse('delay_range', requirement, delay_range)
    return low, high


def _transient(transient: Any) -> Union[float, str]:
    requirement = "'auto' or a finite number of seconds >= 0"
    if isinstance(transient, str):
        if transient == 'auto':
            return 'auto'
        raise _refuse('transient', requirement, transient)
    seconds = _number(transient, 'transient', requirement)
    if not (math.isfinite(seconds) and seconds >= 0.0):
        raise _refuse('transient', requirement, transient)
    return seconds


def check_options(model: Any, data: Any, initial: Any = 'auto', *, bounds: Any = None,
                  method: Any = 'iv', intersample: Any = 'zoh', max_iterations: Any = 100,
                  tolerance: Any = 1e-8, delay_range: Any = None, transient: Any = 0.0,
                  initial_state: Any = 'zero', output_offset: Any = False,
                  integrator_cutoff: Any = None) -> EstimateOptions:
    """
    Check and normalise the arguments of ``estimate`` (same names, same defaults).

    Returns
    -------
    EstimateOptions
        The keyword arguments as plain Python values: ``initial`` is ``'auto'`` or a dict of
        floats, bounds a dict of ``(low, high)`` float pairs (None for an open or infinite
        side), ``transient`` a float or ``'auto'``.

    Raises
    ------
    ConfigError
        If an argument has the wrong type or value; the message names it and shows the value.
    ModelError
        If ``initial`` or ``bounds`` name a parameter the model does not have.
    DataError
        If the record is longer than :data:`~ctid_ros.core.limits.MAX_SAMPLES`.

    """
    if not isinstance(model, Model):
        raise _refuse('model', "a ctid_ros Model (Model('K/(T*s + 1)'))", model)
    if not isinstance(data, Data):
        raise _refuse('data', 'a ctid_ros Data (Data(u, y, ts))', data)
    if len(data) > MAX_SAMPLES:
        raise DataError(f'the record has {len(data)} samples, more than the limit of '
                        f'{MAX_SAMPLES} for one estimate; decimate it or estimate on a part '
                        '(Data.segment, --estimate-range)')
    if not isinstance(max_iterations, Integral) or isinstance(max_iterations, (bool, np.bool_)) \
            or max_iterations < 1:
        raise _refuse('max_iterations', 'an integer >= 1', max_iterations)
    tolerance_value = _number(tolerance, 'tolerance', 'a finite number >= 0')
    if not (math.isfinite(tolerance_value) and tolerance_value >= 0.0):
        raise _refuse('tolerance', 'a finite number >= 0', tolerance)
    if not isinstance(output_offset, (bool, np.bool_)):
        raise _refuse('output_offset', 'True or False', output_offset)
    cutoff = None
    if integrator_cutoff is not None:
        requirement = 'None or a positive, finite corner frequency in rad/s'
        cutoff = _number(integrator_cutoff, 'integrator_cutoff', requirement)
        if not (math.isfinite(cutoff) and cutoff > 0.0):
            raise _refuse('integrator_cutoff', requirement, integrator_cutoff)
    return EstimateOptions(
        initial=_initial(initial, model), bounds=_bounds(bounds, model),
        method=_choice(method, 'method', METHODS),
        intersample=_choice(intersample, 'intersample', INTERSAMPLE),
        max_iterations=int(max_iterations), tolerance=tolerance_value,
        delay_range=_delay_range(delay_range), transient=_transient(transient),
        initial_state=_choice(initial_state, 'initial_state', INITIAL_STATES),
        output_offset=bool(output_offset), integrator_cutoff=cutoff)
