"""
Configuration shared by the live identification node and the offline replay.

Reading it from a ROS 2 params file is :mod:`ctid_ros.streaming.params_file`.

Every parameter is declared once, in :mod:`ctid_ros.streaming.parameter_specs` (plain data,
importable without the numerical stack) with its default, ROS type, help text and range;
:class:`IdentificationConfig` has one field per :data:`PARAMETERS` entry (``tune.controller``
is the field ``tune_controller``) and the node declares its ROS parameters in a loop::

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
from ctid_ros.errors import bounded_repr, ConfigError, ModelError
from ctid_ros.streaming.buffer import capacity_for
from ctid_ros.streaming.message_fields import parse_field_path
from ctid_ros.streaming.parameter_specs import (
    field_name, MAX_BASELINE_WINDOWS, MAX_BUFFER_BYTES, MAX_COMPARE_EVERY, MAX_DURATION,
    MAX_FALSE_ALARM_PER_HOUR, MAX_ITERATIONS, MAX_MESSAGE_RATE, MAX_QOS_DEPTH,
    MAX_RELATIVE_CHANGE, MAX_TUNE_DRAWS, MIN_FALSE_ALARM_PER_HOUR, MIN_MAX_GAP,
    MIN_UPDATE_PERIOD, MIN_WINDOW_SAMPLES, PARAMETER_NAMES, PARAMETERS, ParameterSpec,
    PER_PARAMETER, per_parameter_name, RELIABILITIES, STAMP_SOURCES)
import numpy as np

__all__ = ['IdentificationConfig', 'MAX_BASELINE_WINDOWS', 'MAX_BUFFER_BYTES', 'MAX_DURATION',
           'MAX_FALSE_ALARM_PER_HOUR', 'MAX_ITERATIONS', 'MAX_MESSAGE_RATE', 'MAX_QOS_DEPTH',
           'MAX_RELATIVE_CHANGE', 'MIN_FALSE_ALARM_PER_HOUR',
           'MIN_MAX_GAP', 'MIN_UPDATE_PERIOD', 'MIN_WINDOW_SAMPLES',
           'PARAMETER_NAMES', 'PARAMETERS', 'PER_PARAMETER', 'ParameterSpec', 'RELIABILITIES',
           'STAMP_SOURCES', 'buffer_bytes', 'per_parameter_name', 'split_per_parameter']

# Parameters that change the model's parameter names.
_MODEL_PARAMETERS = ('model', 'controller', 'input_names', 'output_name', 'parameter_names')
# The ring buffer keeps twice its capacity (see buffer._Stream) and capacity_for adds a
# safety factor of 2 against bursts.
_STORAGE_FACTOR = 2
_BURST_MARGIN = 2.0

_TOPIC = re.compile(r'(~/|/)?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*')


_SPECS = {spec.name: spec for spec in PARAMETERS}


def _param(name: str):
    """Return the field of the parameter ``name`` (:data:`PARAMETERS`), its spec the metadata."""
    spec = _SPECS[name]
    return field(default=spec.default, metadata={'spec': spec})


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

    input_topic: str = _param('input_topic')
    input_field: str = _param('input_field')
    output_topic: str = _param('output_topic')
    output_field: str = _param('output_field')
    extra_input_fields: Tuple[str, ...] = _param('extra_input_fields')
    model: str = _param('model')
    input_names: Tuple[str, ...] = _param('input_names')
    output_name: str = _param('output_name')
    controller: str = _param('controller')
    parameter_names: Tuple[str, ...] = _param('parameter_names')
    initial: Tuple[float, ...] = _param('initial')
    lower: Tuple[float, ...] = _param('lower')
    upper: Tuple[float, ...] = _param('upper')
    sample_time: float = _param('sample_time')
    window: float = _param('window')
    update_period: float = _param('update_period')
    method: str = _param('method')
    intersample: str = _param('intersample')
    stamp_source: str = _param('stamp_source')
    qos_reliability: str = _param('qos_reliability')
    qos_depth: int = _param('qos_depth')
    max_message_rate: float = _param('max_message_rate')
    max_gap: float = _param('max_gap')
    reorder_horizon: float = _param('reorder_horizon')
    delay_min: float = _param('delay_min')
    delay_max: float = _param('delay_max')
    max_iterations: int = _param('max_iterations')
    tolerance: float = _param('tolerance')
    transient: float = _param('transient')
    initial_state: str = _param('initial_state')
    output_offset: bool = _param('output_offset')
    warm_start: bool = _param('warm_start')
    publish_prediction: bool = _param('publish_prediction')
    hardware_id: str = _param('hardware_id')
    lifecycle: bool = _param('lifecycle')
    baseline_file: str = _param('baseline_file')
    baseline_windows: int = _param('baseline_windows')
    false_alarm_per_hour: float = _param('false_alarm_per_hour')
    min_relative_change: float = _param('min_relative_change')
    candidate_models: Tuple[str, ...] = _param('candidate_models')
    compare_every: int = _param('compare_every')
    tune_controller: str = _param('tune.controller')
    tune_method: str = _param('tune.method')
    tune_tc: float = _param('tune.tc')
    tune_ms: float = _param('tune.ms')
    tune_sample_time: float = _param('tune.sample_time')
    tune_draws: int = _param('tune.draws')
    tune_joint: str = _param('tune.joint')
    # Values per model parameter (PER_PARAMETER: baseline.J, baseline_std.J,
    # min_relative_change.J), in name order; not a ROS parameter of its own (the node declares
    # one per name once the model is known).
    per_parameter: Tuple[Tuple[str, float], ...] = ()

    def __post_init__(self):
        for item in _spec_fields():
            spec = item.metadata['spec']
            object.__setattr__(self, item.name,
                               _coerce(spec.name, spec.kind, getattr(self, item.name)))
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
        return cls(**_fields_of(plain), per_parameter=tuple(per_parameter.items()))

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
            names = replace(self, **_fields_of(plain), per_parameter=()).names
            merged = {key: value for key, value in merged.items()
                      if key in per_parameter or split_per_parameter(key)[1] in names}
        return replace(self, **_fields_of(plain), per_parameter=tuple(merged.items()))

    def to_dict(self) -> Dict[str, Any]:
        """Return ``{name: value}`` with arrays as lists, as in a params file (flattened)."""
        values = {item.metadata['spec'].name: list(value) if isinstance(value, tuple) else value
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
        self._check_tune()
        self._check_candidates()
        return model

    def _check_candidates(self) -> None:
        if not 1 <= self.compare_every <= MAX_COMPARE_EVERY:
            raise ConfigError(f'compare_every must be between 1 and {MAX_COMPARE_EVERY}, got '
                              f'{self.compare_every}')
        if not self.candidate_models:
            return
        if len(self.candidate_models) < 2:
            raise ConfigError('candidate_models needs at least two structures to compare, got '
                              f'{len(self.candidate_models)}')
        if self.controller:
            raise ConfigError('candidate_models compares plant structures on open-loop data: '
                              'not with a controller (closed loop)')
        for text in self.candidate_models:
            try:
                _compile_model(text, '', self.input_names, self.output_name)
            except ConfigError as error:
                raise ConfigError(f'candidate_models: {error}') from None

    def compare_options(self) -> Dict[str, Any]:
        """Return the options of :func:`ctid_ros.estimation.compare.compare` for the window."""
        return {'intersample': self.intersample,
                'transient': 'auto' if self.transient < 0 else self.transient,
                'initial_state': self.initial_state, 'output_offset': self.output_offset,
                'max_iterations': self.max_iterations, 'tolerance': self.tolerance}

    def _check_tune(self) -> None:
        for name, value in (('tune.tc', self.tune_tc), ('tune.ms', self.tune_ms),
                            ('tune.sample_time', self.tune_sample_time)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ConfigError(f'{name} must be non-negative and finite (0 = default), got '
                                  f'{value}')
        if self.tune_tc and self.tune_ms:
            raise ConfigError('tune.tc (SIMC) and tune.ms (loop shaping) are both set: give one')
        if 0.0 < self.tune_ms <= 1.0:
            raise ConfigError(f'tune.ms must be above 1 (a sensitivity peak), got '
                              f'{self.tune_ms:g}')
        for name, value, method in (('tune.tc', self.tune_tc, 'simc'),
                                    ('tune.ms', self.tune_ms, 'ms')):
            if value and self.tune_method not in ('auto', method):
                raise ConfigError(f"{name} belongs to tune.method '{method}', not "
                                  f"'{self.tune_method}'")
        if not 0 <= self.tune_draws <= MAX_TUNE_DRAWS:
            raise ConfigError(f'tune.draws must be between 0 and {MAX_TUNE_DRAWS}, got '
                              f'{self.tune_draws}')

    def tune_settings(self) -> Optional[Dict[str, Any]]:
        """
        Return the settings of :func:`ctid_ros.design.tune.tune_from_settings`, None untuned.

        ``controller``, ``method``, ``tc`` or ``ms`` (when set), ``sample_time`` (when set),
        ``draws`` and ``seed`` 0 (the same draws for every window, so two windows' bands
        differ by the data alone).
        """
        if not self.tune_controller:
            return None
        settings: Dict[str, Any] = {'controller': self.tune_controller,
                                    'method': self.tune_method, 'draws': self.tune_draws,
                                    'seed': 0}
        for key, value in (('tc', self.tune_tc), ('ms', self.tune_ms),
                           ('sample_time', self.tune_sample_time)):
            if value:
                settings[key] = value
        return settings

    def value(self, name: str) -> Any:
        """Return the value of the parameter ``name`` of :data:`PARAMETER_NAMES`."""
        return getattr(self, field_name(name))

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
            spec, value = item.metadata['spec'], getattr(self, item.name)
            if spec.choices and value not in spec.choices:
                allowed = ', '.join(choice or "''" for choice in spec.choices)
                raise ConfigError(f'{spec.name} must be one of {allowed}; got '
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


def _fields_of(values: Mapping[str, Any]) -> Dict[str, Any]:
    """Return ``{field name: value}`` of ``{parameter name: value}`` (``tune.tc``: tune_tc)."""
    return {field_name(name): value for name, value in values.items()}


def _spec_fields():
    """Return the fields of :class:`IdentificationConfig` that are ROS parameters."""
    return [item for item in fields(IdentificationConfig) if 'spec' in item.metadata]


_PER_PARAMETER_NAME = re.compile(r'(%s)\.([A-Za-z_][A-Za-z0-9_]*)\Z' % '|'.join(PER_PARAMETER))


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
