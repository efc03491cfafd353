"""
Configuration shared by the live identification node and the offline replay.

Reading it from a ROS 2 params file is :mod:`ctid_ros.streaming.params_file`.

Every parameter is declared once, as a field of :class:`IdentificationConfig` with its default,
ROS type, help text and range; :data:`PARAMETERS` exposes them as :class:`ParameterSpec`
records so that the node can declare its ROS parameters in a loop::

    for spec in PARAMETERS:
        descriptor = ParameterDescriptor(
            type=getattr(ParameterType, spec.type_name), description=spec.description,
            additional_constraints=spec.constraints, read_only=spec.read_only)
        ...

(declare array parameters by type: rclpy types an empty default ``[]`` as a byte array).

Values are checked and converted in one place (construction), so a params file, a runtime
parameter change (:meth:`IdentificationConfig.updated`) and the replay's arguments all get the
same errors. Integers are accepted for doubles (YAML ``5`` for ``5.0``; the live node declares
its double parameters with dynamic typing so that rclpy accepts them too).

Resource limits are checked here, before anything is allocated, so a params file, the replay and
a runtime ``ros2 param set`` are refused alike with a :class:`ConfigError` that names the
parameter, the value and the limit: at most :data:`~ctid_ros.core.limits.MAX_SAMPLES` samples
per estimate (window plus settling transient), at most :data:`MAX_BUFFER_BYTES` of sample
buffer, a sample time of at least :data:`~ctid_ros.core.limits.MIN_SAMPLE_TIME`, an update
period of at least
:data:`MIN_UPDATE_PERIOD`, and the other ``MAX_*``/``MIN_*`` bounds below.
"""

from dataclasses import dataclass, field, fields, replace
import functools
import math
import re
from typing import Any, Dict, Mapping, Optional, Tuple

from ctid_ros.core.limits import MAX_SAMPLES, MIN_SAMPLE_TIME
from ctid_ros.core.model import Model
from ctid_ros.core.simulation import INTERSAMPLE
from ctid_ros.errors import bounded_repr, ConfigError, ModelError
from ctid_ros.estimation.options import INITIAL_STATES, METHODS
from ctid_ros.streaming.buffer import capacity_for
from ctid_ros.streaming.message_fields import parse_field_path
import numpy as np

__all__ = ['IdentificationConfig', 'MAX_BASELINE_WINDOWS', 'MAX_BUFFER_BYTES', 'MAX_DURATION',
           'MAX_FALSE_ALARM_PER_HOUR', 'MAX_ITERATIONS', 'MAX_MESSAGE_RATE', 'MAX_QOS_DEPTH',
           'MAX_RELATIVE_CHANGE', 'MIN_FALSE_ALARM_PER_HOUR',
           'MIN_MAX_GAP', 'MIN_UPDATE_PERIOD', 'MIN_WINDOW_SAMPLES',
           'PARAMETER_NAMES', 'PARAMETERS', 'PER_PARAMETER', 'ParameterSpec', 'RELIABILITIES',
           'STAMP_SOURCES', 'buffer_bytes', 'per_parameter_name', 'split_per_parameter']

STAMP_SOURCES = ('header', 'receive')
RELIABILITIES = ('best_effort', 'reliable')
MIN_WINDOW_SAMPLES = 10

# Resource limits (README, "Limits of the live node"). Stamps are integer nanoseconds, so a
# grid or a gap below a microsecond means nothing.
MIN_MAX_GAP = 1e-6
# Memory of the live node's sample buffer (both streams, stamps and values).
MAX_BUFFER_BYTES = 256 << 20
# Highest message rate the buffer may be sized for (per topic).
MAX_MESSAGE_RATE = 100_000.0
# Estimates are at least this far apart; the node also keeps half a core free (node.py).
MIN_UPDATE_PERIOD = 0.1
# Longest update_period: 11.6 days, far below the int64 nanosecond range of a timer. (Window,
# transient and max_gap are bounded by the samples and buffer limits.)
MAX_DURATION = 1e6
MAX_ITERATIONS = 10_000
MAX_QOS_DEPTH = 10_000
# Change alarms (streaming/alarm.py): a false-alarm rate between one in 114 years and one every
# 36 s; a practical threshold of at most 1000 % of the baseline; at most 1000 windows averaged
# into a captured baseline.
MIN_FALSE_ALARM_PER_HOUR = 1e-6
MAX_FALSE_ALARM_PER_HOUR = 100.0
MAX_RELATIVE_CHANGE = 10.0
MAX_BASELINE_WINDOWS = 1000
# Parameters that change the model's parameter names.
_MODEL_PARAMETERS = ('model', 'controller', 'input_names', 'output_name', 'parameter_names')
# Parameters set per model parameter, as ROS flattens a nested mapping of a params file
# (``baseline: {J: 0.05}`` arrives as ``baseline.J``): the prefix and what it means.
PER_PARAMETER = {
    'baseline': 'baseline value of the parameter, against which changes are alarmed',
    'baseline_std': 'standard deviation of that baseline value (0 or unset: exact)',
    'min_relative_change': 'smallest relative change of the parameter that is an alarm '
                           '(unset: min_relative_change)',
}
# The ring buffer keeps twice its capacity (see buffer._Stream) and capacity_for adds a
# safety factor of 2 against bursts.
_STORAGE_FACTOR = 2
_BURST_MARGIN = 2.0

_TOPIC = re.compile(r'(~/|/)?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*')


@dataclass(frozen=True)
class ParameterSpec:
    """
    One configuration parameter, as the node declares it.

    Attributes
    ----------
    name : str
        Parameter name (a field of :class:`IdentificationConfig`).
    kind : str
        One of ``string``, ``double``, ``integer``, ``bool``, ``string_array``,
        ``double_array``.
    default : object
        Default value (arrays as tuples).
    description : str
        Help text.
    minimum : float or None
        Inclusive lower limit (for a descriptor range); stricter rules such as > 0 are in the
        description and enforced by validation.
    choices : tuple of str
        Allowed values of a string parameter (empty: any).
    read_only : bool
        True for parameters that only take effect at start-up (topics, QoS).

    """

    name: str
    kind: str
    default: Any
    description: str
    minimum: Optional[float] = None
    choices: Tuple[str, ...] = ()
    read_only: bool = False

    @property
    def type_name(self) -> str:
        """Return the ``rcl_interfaces/ParameterType`` constant name, e.g. PARAMETER_DOUBLE."""
        return 'PARAMETER_' + self.kind.upper()

    @property
    def constraints(self) -> str:
        """Return the constraints in words, for ``ParameterDescriptor.additional_constraints``."""
        if self.choices:
            return 'one of: ' + ', '.join(self.choices)
        if self.minimum is not None:
            return f'value >= {self.minimum}'
        return ''


def _param(default: Any, kind: str, description: str, *, minimum: Optional[float] = None,
           choices: Tuple[str, ...] = (), read_only: bool = False):
    spec = {'kind': kind, 'description': description, 'minimum': minimum, 'choices': choices,
            'read_only': read_only}
    return field(default=default, metadata={'spec': spec})


@functools.lru_cache(maxsize=16)
def _compile_model(expression: str, controller: str, inputs: Tuple[str, ...],
                   output: str) -> Model:
    """Parse the plant, then the closed loop, so that an error names the text at fault."""
    try:
        plant = Model(expression, inputs=inputs, output=output)
    except ModelError as error:
        raise ConfigError(f'model {bounded_repr(expression)} is invalid: {error}') from None
    if not controller:
        return plant
    try:
        return Model(expression, controller, inputs=inputs, output=output)
    except ModelError as error:
        raise ConfigError(f'controller {bounded_repr(controller)} is invalid: {error}') from None


@dataclass(frozen=True)
class IdentificationConfig:
    """
    Validated configuration of an identification run (live node or replay).

    Construct it with keyword arguments, :meth:`from_dict` or
    :func:`~ctid_ros.streaming.params_file.load_params_file`; change
    it with :meth:`updated`. Invalid values raise :class:`ConfigError` naming the parameter.
    The field metadata (see :data:`PARAMETERS`) documents each parameter.
    """

    input_topic: str = _param(
        'u', 'string', 'Topic of the input u (the reference r in closed loop); relative names '
        'follow the node namespace.', read_only=True)
    input_field: str = _param(
        'data', 'string', "Field of the input message holding the value, e.g. 'data', "
        "'effort[0]', 'twist.linear.x'.")
    output_topic: str = _param(
        'y', 'string', 'Topic of the measured output y; may equal input_topic when one '
        'message carries both (e.g. /joint_states).', read_only=True)
    output_field: str = _param(
        'data', 'string', "Field of the output message holding the value, e.g. 'position[0]'.")
    extra_input_fields: Tuple[str, ...] = _param(
        (), 'string_array', 'Fields of the input message holding the further inputs of a '
        "model equation, in input_names order after the first, e.g. ['effort[1]'].")
    model: str = _param(
        '', 'string', 'Plant transfer function in s; every other name is a parameter, e.g. '
        "'K*exp(-tau*s)/(T*s + 1)'; or a model equation such as "
        "'M*s**2*y + Fv*s*y = 35.2*u - Fc*w - off' with its signals named by input_names and "
        'output_name. Required.')
    input_names: Tuple[str, ...] = _param(
        ('u',), 'string_array', 'Names of the inputs in a model equation: the first is read '
        'from input_field, the others from extra_input_fields.')
    output_name: str = _param(
        'y', 'string', 'Name of the output in a model equation.')
    controller: str = _param(
        '', 'string', "Known controller K(s) with numeric coefficients, e.g. '20 + 10/s': the "
        "data are then the closed loop from the reference (input_topic) to y. '' = open loop.")
    parameter_names: Tuple[str, ...] = _param(
        (), 'string_array', 'Order of the parameters in initial/lower/upper and in all published '
        'arrays; a permutation of the model parameters. Empty = order of first appearance in '
        'the model.')
    initial: Tuple[float, ...] = _param(
        (), 'double_array', 'Initial values in parameter_names order; NaN entries (and an empty '
        'array) are initialised automatically.')
    lower: Tuple[float, ...] = _param(
        (), 'double_array', 'Lower bounds in parameter_names order (-.inf = none); empty = '
        'no bounds.')
    upper: Tuple[float, ...] = _param(
        (), 'double_array', 'Upper bounds in parameter_names order (.inf = none); empty = '
        'no bounds.')
    sample_time: float = _param(
        0.01, 'double', 'Sample time (s, at least 1e-6) of the grid the messages are resampled '
        "onto, normally the actuator update period; the grid follows the input's own instants "
        "when it is a whole multiple or fraction of the input's period (finer than the data's "
        "own rate: the data's period, with a warning), else the multiples of sample_time.",
        minimum=0.0)
    window: float = _param(
        10.0, 'double', f'Length (s) of the data window used by each estimate; at least '
        f'{MIN_WINDOW_SAMPLES} sample times, and with its settling transient at most '
        f'{MAX_SAMPLES} samples.', minimum=0.0)
    update_period: float = _param(
        1.0, 'double', f'Seconds ({MIN_UPDATE_PERIOD:g} to {MAX_DURATION:g}) between successive '
        'estimates.', minimum=0.0)
    method: str = _param(
        'iv', 'string', "'iv': least squares then instrumental-variable iterations "
        "(consistent under noise); 'ls': least-squares iterations only; 'gn': Gauss-Newton on "
        'the output error.', choices=METHODS)
    intersample: str = _param(
        'zoh', 'string', "Input behaviour between samples: 'zoh' (held, e.g. a digital "
        "actuator command) or 'foh' (linear).", choices=INTERSAMPLE)
    stamp_source: str = _param(
        'header', 'string', "'header': use header.stamp when the message has a non-zero one, "
        "else the receive time; 'receive': always the receive time.", choices=STAMP_SOURCES,
        read_only=True)
    qos_reliability: str = _param(
        'best_effort', 'string', 'Subscription reliability; best_effort also matches reliable '
        'publishers.', choices=RELIABILITIES, read_only=True)
    qos_depth: int = _param(
        500, 'integer', f'Subscription queue depth (keep last, at most {MAX_QOS_DEPTH}); deep, so '
        'bursts are not lost.', minimum=1, read_only=True)
    max_message_rate: float = _param(
        1000.0, 'double', 'Highest message rate (Hz) per topic the live sample buffer is sized '
        'for (1/sample_time if that is higher); faster messages shorten the history it holds. '
        'With window, transient and max_gap it sets the buffer memory, which is limited.',
        minimum=0.0)
    max_gap: float = _param(
        0.5, 'double', 'Seconds (at least 1e-6) without a sample after which a stream counts as '
        'missing: data are never interpolated or held across such a gap.', minimum=0.0)
    reorder_horizon: float = _param(
        0.05, 'double', 'Seconds a sample may arrive out of order and still be used; older '
        'late samples are dropped and counted.', minimum=0.0)
    delay_min: float = _param(
        0.0, 'double', 'Lower end (s) of the dead-time search range; delay_min = delay_max = 0 '
        'means automatic.', minimum=0.0)
    delay_max: float = _param(
        0.0, 'double', 'Upper end (s) of the dead-time search range (see delay_min).',
        minimum=0.0)
    max_iterations: int = _param(
        100, 'integer', f'Largest number of iterations of one estimate (at most '
        f'{MAX_ITERATIONS}).', minimum=1)
    tolerance: float = _param(
        1e-8, 'double', 'Stop when the largest relative parameter change falls below it (> 0).',
        minimum=0.0)
    transient: float = _param(
        -1.0, 'double', 'Seconds at the start of each window that are simulated but not fitted, '
        'because a window cut from a running plant does not start at rest. Negative = '
        'automatic (five slowest time constants plus the dead time, at most half the window).')
    initial_state: str = _param(
        'zero', 'string', "'zero': each window is treated as starting at rest (with the "
        "transient excluded); 'estimate': the initial state is estimated as well.",
        choices=INITIAL_STATES)
    output_offset: bool = _param(
        False, 'bool', 'Estimate a constant offset of the output (an unknown operating point).')
    warm_start: bool = _param(
        True, 'bool', 'Start each estimate from the previous one instead of initial.')
    publish_prediction: bool = _param(
        False, 'bool', 'Publish the model output predicted over the window.')
    hardware_id: str = _param(
        '', 'string', "hardware_id of the node's status on /diagnostics, e.g. the drive being "
        "identified; '' = the node's name.")
    lifecycle: bool = _param(
        False, 'bool', 'Live node only: true = a managed (lifecycle) node that starts '
        'unconfigured and follows configure/activate/deactivate/cleanup/shutdown transitions, '
        'as nav2 nodes do; false = configure and activate at start-up.', read_only=True)
    baseline_file: str = _param(
        '', 'string', 'YAML file of the baseline the change alarm compares with: written by '
        'the ~/capture_baseline service, read at configure (so a restart keeps it) and when '
        'this parameter changes; when it exists it takes precedence over baseline.<name> '
        "parameters. '' = none.")
    baseline_windows: int = _param(
        5, 'integer', f'Windows averaged by ~/capture_baseline into a baseline (1 to '
        f'{MAX_BASELINE_WINDOWS}).', minimum=1)
    false_alarm_per_hour: float = _param(
        0.1, 'double', f'Change alarms a stationary plant raises per hour, on average '
        f'({MIN_FALSE_ALARM_PER_HOUR:g} to {MAX_FALSE_ALARM_PER_HOUR:g}); sets the threshold of '
        'the sequential test on the windows (with update_period and the overlap of the '
        'windows).', minimum=0.0)
    min_relative_change: float = _param(
        0.02, 'double', f'Smallest change of a parameter, relative to its baseline, that is an '
        f'alarm (0 to {MAX_RELATIVE_CHANGE:g}): a real but smaller change is not; per parameter '
        'as min_relative_change.<name> (a mapping in a params file).', minimum=0.0)
    # Values per model parameter (PER_PARAMETER: baseline.J, baseline_std.J,
    # min_relative_change.J), in name order; not a ROS parameter of its own (the node declares
    # one per name once the model is known).
    per_parameter: Tuple[Tuple[str, float], ...] = ()

    def __post_init__(self):
        for item in _spec_fields():
            object.__setattr__(self, item.name,
                               _coerce(item.name, item.metadata['spec']['kind'],
                                       getattr(self, item.name)))
        object.__setattr__(self, 'per_parameter', _per_parameter_values(self.per_parameter))
        object.__setattr__(self, '_model', self._validate())

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> 'IdentificationConfig':
        """
        Build a configuration from ``{parameter name: value}`` (unset names take defaults).

        Names of :data:`PER_PARAMETER` form (``baseline.J``, as ROS flattens ``baseline: {J:
        0.05}``) go into :attr:`per_parameter`; NaN leaves one unset.

        Raises
        ------
        ConfigError
            On an unknown name (the message lists the valid ones), a wrong type or an invalid
            value.

        """
        plain, per_parameter = _split(values)
        return cls(**plain, per_parameter=tuple(per_parameter.items()))

    def updated(self, changes: Mapping[str, Any]) -> 'IdentificationConfig':
        """
        Return a new configuration with ``changes`` applied; ``self`` is left unchanged.

        For a runtime parameter change: on :class:`ConfigError` reject the change and keep the
        current configuration. A change of the model drops the per-parameter values
        (``baseline.<name>``...) of parameters the new model does not have.
        """
        plain, per_parameter = _split(changes)
        merged = {**dict(self.per_parameter), **per_parameter}
        if set(plain) & set(_MODEL_PARAMETERS) and self.per_parameter:
            # Another model: the values of parameters it does not have are dropped.
            names = replace(self, **plain, per_parameter=()).names
            merged = {key: value for key, value in merged.items()
                      if key in per_parameter or split_per_parameter(key)[1] in names}
        return replace(self, **plain, per_parameter=tuple(merged.items()))

    def to_dict(self) -> Dict[str, Any]:
        """Return ``{name: value}`` with arrays as lists, as in a params file (flattened)."""
        values = {item.name: list(value) if isinstance(value, tuple) else value
                  for item in _spec_fields() for value in [getattr(self, item.name)]}
        values.update(self.per_parameter)
        return values

    def per_parameter_values(self, prefix: str) -> Dict[str, float]:
        """
        Return the values set for ``prefix`` (a key of :data:`PER_PARAMETER`) by name.

        E.g. ``config.per_parameter_values('baseline')`` is ``{'J': 0.05, 'b': 0.2}`` for a
        params file with ``baseline: {J: 0.05, b: 0.2}``; in :attr:`names` order.
        """
        values = dict(self.per_parameter)
        return {name: values[per_parameter_name(prefix, name)] for name in self.names
                if per_parameter_name(prefix, name) in values}

    def relative_changes(self) -> Dict[str, float]:
        """Return the practical threshold of every parameter: its own, else the common one."""
        own = self.per_parameter_values('min_relative_change')
        return {name: own.get(name, self.min_relative_change) for name in self.names}

    @property
    def compiled_model(self) -> Model:
        """Return the parsed :class:`ctid_ros.Model` (closed loop if a controller is set)."""
        return self._model

    @property
    def names(self) -> Tuple[str, ...]:
        """Return the parameter order of all arrays (``parameter_names`` or the model's)."""
        return self.parameter_names or self._model.parameters

    @property
    def model_index(self) -> Tuple[int, ...]:
        """
        Return, for each name in :attr:`names`, its index in ``compiled_model.parameters``.

        ``theta[list(config.model_index)]`` reorders a model-ordered vector for publishing.
        """
        return tuple(self._model.parameters.index(name) for name in self.names)

    @property
    def delay_range(self) -> Optional[Tuple[float, float]]:
        """Return the dead-time search range, or None for automatic."""
        if self.delay_min == 0.0 and self.delay_max == 0.0:
            return None
        return self.delay_min, self.delay_max

    def initial_values(self) -> Dict[str, float]:
        """Return the configured initial values by name (NaN/automatic entries left out)."""
        return {name: value for name, value in zip(self.names, self.initial)
                if not math.isnan(value)}

    def bounds(self) -> Dict[str, Tuple[Optional[float], Optional[float]]]:
        """Return ``{name: (lower, upper)}`` for bounded parameters (None = unbounded side)."""
        lower = self.lower or (-math.inf,) * len(self.names)
        upper = self.upper or (math.inf,) * len(self.names)
        return {name: (low if math.isfinite(low) else None,
                       high if math.isfinite(high) else None)
                for name, low, high in zip(self.names, lower, upper)
                if math.isfinite(low) or math.isfinite(high)}

    @property
    def history_span(self) -> float:
        """
        Return the longest span (s) of data one estimate asks for.

        It is the fitted window plus the transient before it that only settles the model's
        state (a window cut from a running plant does not start at rest); an automatic
        transient is at most one window long.
        """
        return self.window + (self.transient if self.transient >= 0 else self.window)

    @property
    def window_samples(self) -> float:
        """Return the samples of one estimate at most: :attr:`history_span` / sample_time."""
        return self.history_span / self.sample_time

    @property
    def message_rate(self) -> float:
        """Return the message rate (Hz) the live buffer is sized for."""
        return max(1.0 / self.sample_time, self.max_message_rate)

    def buffer_capacity(self, rate_hz: Optional[float] = None) -> int:
        """
        Return the samples per stream of a buffer for this configuration.

        It holds :attr:`history_span` plus ``max_gap`` and the reorder horizon of messages at
        ``rate_hz`` (default :attr:`message_rate`), with a margin of 2 against bursts.
        """
        span = self.history_span + self.max_gap + self.reorder_horizon
        return capacity_for(span, self.message_rate if rate_hz is None else rate_hz,
                            _BURST_MARGIN)

    def buffer_bytes(self, rate_hz: Optional[float] = None) -> int:
        """Return the memory (bytes) of the buffer of :meth:`buffer_capacity`."""
        return buffer_bytes(self.buffer_capacity(rate_hz), len(self.input_fields))

    @property
    def input_fields(self) -> Tuple[str, ...]:
        """Return the field paths of all inputs in the input message, in input_names order."""
        return (self.input_field,) + self.extra_input_fields

    def estimator_options(self) -> Dict[str, Any]:
        """Return keyword arguments for :func:`ctid_ros.estimate` (without model and data)."""
        return {'initial': self.initial_values() or 'auto', 'bounds': self.bounds() or None,
                'method': self.method, 'intersample': self.intersample,
                'max_iterations': self.max_iterations, 'tolerance': self.tolerance,
                'delay_range': self.delay_range,
                'transient': 'auto' if self.transient < 0 else self.transient,
                'initial_state': self.initial_state, 'output_offset': self.output_offset}

    def _validate(self) -> Model:
        for name in ('input_topic', 'output_topic'):
            topic = getattr(self, name)
            if not _TOPIC.fullmatch(topic):
                raise ConfigError(
                    f'{name} {bounded_repr(topic)} is not a valid topic name: tokens of letters, '
                    "digits and underscores (not starting with a digit) separated by '/', "
                    "optionally starting with '/' or '~/'")
        for name, path in [('input_field', self.input_field),
                           ('output_field', self.output_field)] + [
                ('extra_input_fields', path) for path in self.extra_input_fields]:
            try:
                parse_field_path(path)
            except ConfigError as error:
                raise ConfigError(f'{name}: {error}') from None
        if len(self.extra_input_fields) != len(self.input_names) - 1:
            raise ConfigError(f'input_names has {len(self.input_names)} name(s), so '
                              f'extra_input_fields needs {len(self.input_names) - 1} field(s), '
                              f'got {len(self.extra_input_fields)}')
        if (self.input_topic, self.input_field) == (self.output_topic, self.output_field):
            raise ConfigError('input and output are the same field of the same topic: '
                              'set output_topic or output_field')
        if not self.model.strip():
            raise ConfigError('model is required: a transfer function in s such as '
                              "'K/(T*s + 1)'")
        model = _compile_model(self.model, self.controller, self.input_names, self.output_name)
        self._check_names(model)
        self._check_vectors(self.parameter_names or model.parameters)
        self._check_choices()
        self._check_times(model)
        self._check_resources()
        self._check_alarm(self.parameter_names or model.parameters)
        return model

    def _check_alarm(self, names: Tuple[str, ...]) -> None:
        far = self.false_alarm_per_hour
        if not (math.isfinite(far)
                and MIN_FALSE_ALARM_PER_HOUR <= far <= MAX_FALSE_ALARM_PER_HOUR):
            raise ConfigError(f'false_alarm_per_hour must be between {MIN_FALSE_ALARM_PER_HOUR:g} '
                              f'and {MAX_FALSE_ALARM_PER_HOUR:g}, got {far:g}')
        if not 1 <= self.baseline_windows <= MAX_BASELINE_WINDOWS:
            raise ConfigError(f'baseline_windows must be between 1 and {MAX_BASELINE_WINDOWS}, '
                              f'got {self.baseline_windows}')
        for key, value in (('min_relative_change', self.min_relative_change),
                           *self.per_parameter):
            prefix, _, name = key.partition('.')
            if name and name not in names:
                raise ConfigError(f'{key}: the model has no parameter {bounded_repr(name)} '
                                  f'(its parameters: {", ".join(names)})')
            if not math.isfinite(value):
                raise ConfigError(f'{key} must be finite, got {value}')
            if prefix == 'min_relative_change' and not 0.0 <= value <= MAX_RELATIVE_CHANGE:
                raise ConfigError(f'{key} must be between 0 and {MAX_RELATIVE_CHANGE:g} (a '
                                  f'fraction of the baseline: 0.02 is 2 %), got {value:g}')
            if prefix == 'baseline_std' and value < 0.0:
                raise ConfigError(f'{key} must be >= 0, got {value:g}')
        given = dict(self.per_parameter)
        for key in given:
            prefix, _, name = key.partition('.')
            if prefix == 'baseline_std' and per_parameter_name('baseline', name) not in given:
                raise ConfigError(f'{key} is set but baseline.{name} is not: a standard deviation '
                                  'needs its baseline value')

    def _check_names(self, model: Model) -> None:
        if not self.parameter_names:
            return
        given, expected = self.parameter_names, model.parameters
        repeated = sorted({name for name in given if given.count(name) > 1})
        unknown = [name for name in given if name not in expected]
        missing = [name for name in expected if name not in given]
        if repeated or unknown or missing:
            problems = [f'{label} {", ".join(names)}' for label, names in
                        (('repeated', repeated), ('not in the model', unknown),
                         ('missing', missing)) if names]
            raise ConfigError(f'parameter_names must be a permutation of the model parameters '
                              f'({", ".join(expected)}): {"; ".join(problems)}')

    def _check_vectors(self, order: Tuple[str, ...]) -> None:
        count = len(order)
        for name in ('initial', 'lower', 'upper'):
            values = getattr(self, name)
            if values and len(values) != count:
                raise ConfigError(f'{name} has {len(values)} values but the model has {count} '
                                  f'parameters ({", ".join(order)}); give one per parameter, '
                                  'or none')
        if any(math.isinf(value) for value in self.initial):
            raise ConfigError(f'initial values must be finite or NaN (automatic), got '
                              f'{list(self.initial)}')
        for name in ('lower', 'upper'):
            if any(math.isnan(value) for value in getattr(self, name)):
                raise ConfigError(f'{name} may not contain NaN; use -.inf / .inf for no bound')
        lower = np.asarray(self.lower or [-math.inf] * count)
        upper = np.asarray(self.upper or [math.inf] * count)
        empty = np.flatnonzero(~(lower < upper))
        if empty.size:
            index = empty[0]
            raise ConfigError(f'lower must be < upper: for {order[index]} lower = '
                              f'{lower[index]} >= upper = {upper[index]}')
        initial = np.asarray(self.initial or [math.nan] * count)
        outside = np.flatnonzero((initial < lower) | (initial > upper))
        if outside.size:
            index = outside[0]
            raise ConfigError(f'initial value of {order[index]} = {initial[index]} is outside '
                              f'its bounds [{lower[index]}, {upper[index]}]')

    def _check_choices(self) -> None:
        for item in _spec_fields():
            choices = item.metadata['spec']['choices']
            value = getattr(self, item.name)
            if choices and value not in choices:
                raise ConfigError(f'{item.name} must be one of {", ".join(choices)}; got '
                                  f'{bounded_repr(value)}')

    def _check_times(self, model: Model) -> None:
        for name in ('sample_time', 'window', 'update_period', 'max_gap', 'tolerance',
                     'max_message_rate'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f'{name} must be positive and finite, got {value}')
        for name in ('reorder_horizon', 'delay_min', 'delay_max'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f'{name} must be non-negative and finite, got {value}')
        if not math.isfinite(self.transient):
            raise ConfigError(f'transient must be finite (negative = automatic), got '
                              f'{self.transient}')
        for name, limit in (('qos_depth', MAX_QOS_DEPTH), ('max_iterations', MAX_ITERATIONS)):
            value = getattr(self, name)
            if value < 1:
                raise ConfigError(f'{name} must be at least 1, got {value}')
            if value > limit:
                raise ConfigError(f'{name} {value} is more than the limit of {limit}')
        for name, low, reason in (
                ('sample_time', MIN_SAMPLE_TIME, 'time stamps are integer nanoseconds'),
                ('max_gap', MIN_MAX_GAP, 'time stamps are integer nanoseconds'),
                ('update_period', MIN_UPDATE_PERIOD, 'estimates more often only load the CPU '
                 'and flood /diagnostics')):
            if getattr(self, name) < low:
                raise ConfigError(f'{name} {getattr(self, name):g} s is below the limit of '
                                  f'{low:g} s ({reason})')
        if self.update_period > MAX_DURATION:
            raise ConfigError(f'update_period {self.update_period:g} s is more than the limit of '
                              f'{MAX_DURATION:g} s')
        if self.max_message_rate > MAX_MESSAGE_RATE:
            raise ConfigError(f'max_message_rate {self.max_message_rate:g} Hz is more than the '
                              f'limit of {MAX_MESSAGE_RATE:g} Hz')
        if self.window < MIN_WINDOW_SAMPLES * self.sample_time:
            raise ConfigError(f'window ({self.window} s) must hold at least '
                              f'{MIN_WINDOW_SAMPLES} samples of sample_time '
                              f'({self.sample_time} s): at least '
                              f'{MIN_WINDOW_SAMPLES * self.sample_time:g} s')
        if self.reorder_horizon >= self.window:
            raise ConfigError(f'reorder_horizon ({self.reorder_horizon} s) must be shorter than '
                              f'the window ({self.window} s)')
        if self.delay_range is not None:
            if not model.delay_is_estimated:
                raise ConfigError('delay_min/delay_max set a dead-time search range but the '
                                  f'model {bounded_repr(self.model)} has no estimated dead time '
                                  'exp(-tau*s); set both to 0.0')
            if not self.delay_min < self.delay_max:
                raise ConfigError(f'delay_min ({self.delay_min} s) must be < delay_max '
                                  f'({self.delay_max} s), or both 0.0 for automatic')
            if self.delay_max >= self.window:
                raise ConfigError(f'delay_max ({self.delay_max} s) must be shorter than the '
                                  f'window ({self.window} s)')

    def _check_resources(self) -> None:
        """Refuse what one estimate or the live buffer could not afford, before allocating."""
        samples = self.window_samples
        if samples > MAX_SAMPLES:
            transient = 'automatic, one window' if self.transient < 0 else f'{self.transient:g} s'
            raise ConfigError(
                f'window ({self.window:g} s) plus its settling transient ({transient}) at '
                f'sample_time {self.sample_time:g} s is {samples:.3g} samples per estimate, '
                f'more than the limit of {MAX_SAMPLES}; use a shorter window or '
                'transient, or a longer sample_time')
        size = self.buffer_bytes()
        if size > MAX_BUFFER_BYTES:
            span = self.history_span + self.max_gap + self.reorder_horizon
            raise ConfigError(
                f'the sample buffer would take {_size_text(size)}: {span:.6g} s (window, '
                f'transient, max_gap and reorder_horizon) of messages at up to '
                f'{self.message_rate:g} Hz (max_message_rate, or 1/sample_time), more than the '
                f'limit of {_size_text(MAX_BUFFER_BYTES)}; use a shorter window or max_gap, or '
                'a lower max_message_rate')


def buffer_bytes(capacity: int, inputs: int = 1) -> int:
    """
    Return the memory of a :class:`~ctid_ros.streaming.buffer.SampleBuffer` in bytes.

    Per stream: ``capacity`` samples, stored twice over (the ring is kept contiguous), each an
    int64 stamp and float64 values (``inputs`` of them for the input stream, one output).
    """
    per_sample = (8 + 8 * inputs) + (8 + 8)
    return _STORAGE_FACTOR * int(capacity) * per_sample


def _size_text(count: float) -> str:
    for unit, scale in (('TiB', 1 << 40), ('GiB', 1 << 30), ('MiB', 1 << 20), ('KiB', 1 << 10)):
        if count >= scale:
            return f'{count / scale:.3g} {unit}'
    return f'{int(count)} bytes'


def _coerce(name: str, kind: str, value: Any) -> Any:
    """Convert a value to the parameter's kind, refusing anything ROS would not mean by it."""
    def wrong(expected: str) -> ConfigError:
        return ConfigError(f'{name} must be {expected}, got {bounded_repr(value)} '
                           f'({type(value).__name__})')

    if kind == 'string':
        if not isinstance(value, str):
            raise wrong('a string')
        return value
    if kind == 'bool':
        if not isinstance(value, (bool, np.bool_)):
            raise wrong('true or false')
        return bool(value)
    if kind == 'integer':
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise wrong('an integer (write 500, not 500.0)')
        return int(value)
    if kind == 'double':
        if not _is_number(value):
            raise wrong('a number')
        return float(value)
    expected = 'a list of strings' if kind == 'string_array' else 'a list of numbers'
    if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, '__iter__'):
        raise wrong(expected)
    items = list(value)
    check = (lambda item: isinstance(item, str)) if kind == 'string_array' else _is_number
    if not all(check(item) for item in items):
        raise wrong(expected)
    return tuple(items) if kind == 'string_array' else tuple(float(item) for item in items)


def _is_number(value: Any) -> bool:
    return (isinstance(value, (int, float, np.integer, np.floating))
            and not isinstance(value, (bool, np.bool_)))


def _spec_fields():
    """Return the fields of :class:`IdentificationConfig` that are ROS parameters."""
    return [item for item in fields(IdentificationConfig) if 'spec' in item.metadata]


PARAMETERS: Tuple[ParameterSpec, ...] = tuple(
    ParameterSpec(name=item.name, default=item.default, **item.metadata['spec'])
    for item in _spec_fields())
PARAMETER_NAMES: Tuple[str, ...] = tuple(spec.name for spec in PARAMETERS)
_PER_PARAMETER_NAME = re.compile(r'(%s)\.([A-Za-z_][A-Za-z0-9_]*)\Z' % '|'.join(PER_PARAMETER))


def per_parameter_name(prefix: str, name: str) -> str:
    """Return the ROS name of a per-parameter value, e.g. ``baseline.J``."""
    return f'{prefix}.{name}'


def split_per_parameter(name: str) -> Optional[Tuple[str, str]]:
    """Return ``(prefix, parameter)`` of a per-parameter name (``baseline.J``), else None."""
    match = _PER_PARAMETER_NAME.match(name) if isinstance(name, str) else None
    return (match.group(1), match.group(2)) if match else None


def _per_parameter_values(items: Any) -> Tuple[Tuple[str, float], ...]:
    """Check and sort ``(dotted name, number)`` pairs; NaN values are left out (unset)."""
    if isinstance(items, Mapping):
        items = items.items()
    try:
        pairs = [(key, value) for key, value in items]
    except (TypeError, ValueError):
        raise ConfigError('per_parameter must be (name, value) pairs, got '
                          f'{bounded_repr(items)}') from None
    values = {}
    for key, value in pairs:
        if not isinstance(key, str) or not _PER_PARAMETER_NAME.match(key):
            raise ConfigError(f'{bounded_repr(key)} is not a per-parameter name such as '
                              f'baseline.J; prefixes: {", ".join(PER_PARAMETER)}')
        value = _coerce(key, 'double', value)
        if not math.isnan(value):
            values[key] = value
    return tuple(sorted(values.items()))


def _split(values: Mapping[str, Any]) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """Separate plain parameters from per-parameter ones (``baseline.J``); refuse the rest."""
    plain = {name: value for name, value in values.items()
             if not (isinstance(name, str) and _PER_PARAMETER_NAME.match(name))}
    unknown = sorted(str(name) for name in set(plain) - set(PARAMETER_NAMES))
    if unknown:
        raise ConfigError(f'unknown parameter(s) {", ".join(unknown)}; valid names: '
                          f'{", ".join(PARAMETER_NAMES)}, and per model parameter '
                          f'{", ".join(prefix + ".<name>" for prefix in PER_PARAMETER)}')
    return plain, {name: value for name, value in values.items() if name not in plain}
