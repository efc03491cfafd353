"""
The node's ROS parameters: declared from one table, read at configure, changed at runtime.

What is declared is :func:`~ctid_ros.ros.parameter_table.declared_parameters` (plain data,
importable without rclpy); :func:`declare_parameters` gives each its ``ParameterDescriptor``
(type, description, range, read-only). Doubles are dynamically typed, so an integer (YAML
``5``) is accepted and converted by the configuration, as in ``ctid replay``.

A parameter update is validated by :class:`~ctid_ros.streaming.config.IdentificationConfig`,
whose resource limits are checked before anything is allocated, in a helper thread with a time
bound (:data:`VALIDATION_TIMEOUT`, :func:`bounded`), so a model text that takes long to analyse
cannot block the executor; the parameter callback never waits for an estimate. Unconfigured,
an update is accepted as it is and validated on configure, as nav2 does; the parameters read
at configure (topics, stamp source, QoS: ``configure_only``) change only then.

:class:`ParameterHandling` is the part of the identification node that does this; it reads
and replaces the node's configuration, sampler and buffer (``_config``, ``_sampler``,
``_buffer`` under ``_lock``) and asks the node to follow a new configuration through the
methods :meth:`_follow_topics` and :meth:`_follow_outputs`; new field paths are checked
against the types published on the topics (:meth:`_unreadable_fields`).
"""

import math
import threading
from typing import Any, Callable, Dict, List, Mapping, Optional, Tuple

from ctid_ros.errors import ConfigError
from ctid_ros.ros.parameter_table import per_parameter_description
from ctid_ros.streaming.baseline import Baseline, configured_baseline
from ctid_ros.streaming.config import (IdentificationConfig, PARAMETER_NAMES, PARAMETERS,
                                       ParameterSpec, PER_PARAMETER, per_parameter_name,
                                       split_per_parameter)
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter

__all__ = ['BUFFER_PARAMETERS', 'ParameterHandling', 'VALIDATION_TIMEOUT', 'bounded',
           'changed_parameters', 'declare_parameters', 'declare_per_parameter',
           'parameter_value', 'per_parameter_names']

# Longest time a parameter update may take to validate (a model text is parsed and
# differentiated); beyond it the update is refused and the executor goes on.
VALIDATION_TIMEOUT = 5.0
# Changing one of these rebuilds the sample buffer (its gap rules or size depend on them).
BUFFER_PARAMETERS = ('window', 'sample_time', 'max_gap', 'reorder_horizon', 'transient',
                     'max_message_rate')
_INT64_MAX = 2 ** 63 - 1
# Parameters read at configure, fixed while the node is configured.
_CONFIGURE_ONLY = frozenset(spec.name for spec in PARAMETERS if spec.configure_only)
# The parameters given per model parameter, in parameter_names' order: a new model with other
# parameters needs them changed in the same update.
_PER_MODEL_PARAMETER = ('parameter_names', 'initial', 'lower', 'upper')
_ARRAY_TYPES = {'string_array': Parameter.Type.STRING_ARRAY}


def _descriptor(spec: ParameterSpec) -> ParameterDescriptor:
    dynamic = spec.kind in ('double', 'double_array')
    descriptor = ParameterDescriptor(
        name=spec.name, type=getattr(ParameterType, spec.type_name),
        description=spec.description, additional_constraints=spec.constraints,
        read_only=spec.read_only, dynamic_typing=dynamic)
    if spec.minimum is not None and spec.kind == 'double':
        descriptor.floating_point_range = [FloatingPointRange(
            from_value=float(spec.minimum), to_value=math.inf, step=0.0)]
    elif spec.minimum is not None and spec.kind == 'integer':
        descriptor.integer_range = [IntegerRange(
            from_value=int(spec.minimum), to_value=_INT64_MAX, step=0)]
    return descriptor


def _initial_value(spec: ParameterSpec) -> Any:
    """Return the declaration default; string arrays are declared by type (rclpy types [])."""
    if spec.kind in _ARRAY_TYPES:
        return _ARRAY_TYPES[spec.kind]
    return list(spec.default) if isinstance(spec.default, tuple) else spec.default


def declare_parameters(node: Node) -> None:
    """Declare every configuration parameter on ``node``, with its descriptor."""
    for spec in PARAMETERS:
        node.declare_parameter(spec.name, _initial_value(spec), _descriptor(spec))


def per_parameter_names(names: Tuple[str, ...]) -> List[str]:
    """Return ``baseline.<name>`` and the like for every model parameter in ``names``."""
    return [per_parameter_name(prefix, name) for prefix in PER_PARAMETER for name in names]


def declare_per_parameter(node: Node, names: Tuple[str, ...]) -> None:
    """Declare the change alarm's per-parameter values of ``names`` not declared yet."""
    for name in per_parameter_names(names):
        if not node.has_parameter(name):
            prefix, parameter = split_per_parameter(name)
            node.declare_parameter(name, math.nan, ParameterDescriptor(
                name=name, type=ParameterType.PARAMETER_DOUBLE, dynamic_typing=True,
                description=per_parameter_description(prefix, parameter)))


def parameter_value(node: Node, name: str, default: Any = None) -> Any:
    """Return a declared parameter's value, or ``default`` if it was declared by type only."""
    try:
        value = node.get_parameter(name).value
    except ParameterUninitializedException:
        return default
    return default if value is None else value


def bounded(function: Callable[[], Any], timeout: float, busy: List[threading.Thread]) -> Any:
    """
    Run ``function`` in a helper thread and wait at most ``timeout`` seconds for it.

    ``busy`` holds a helper still running from an earlier call: while it runs, further calls
    are refused at once, so at most one runaway validation exists.

    Raises
    ------
    ConfigError
        If the helper does not finish in time, or an earlier one is still running.

    """
    if busy and busy[0].is_alive():
        raise ConfigError('the previous parameter update is still being checked (its model '
                          'took longer than {:g} s to analyse); try again later'.format(timeout))
    busy.clear()
    outcome: Dict[str, Any] = {}

    def run() -> None:
        try:
            outcome['value'] = function()
        except BaseException as error:  # noqa: B902 - re-raised in the caller's thread
            outcome['error'] = error

    helper = threading.Thread(target=run, name='ctid_validate', daemon=True)
    helper.start()
    helper.join(timeout)
    if helper.is_alive():
        busy.append(helper)
        raise ConfigError(f'checking the new parameters took longer than {timeout:g} s: '
                          'refused, the node keeps its configuration')
    if 'error' in outcome:
        raise outcome['error']
    return outcome['value']


def changed_parameters(old: IdentificationConfig, new: IdentificationConfig) -> List[str]:
    """Return the names of the parameters whose values differ between two configurations."""
    plain = [name for name in PARAMETER_NAMES if old.value(name) != new.value(name)]
    before, after = dict(old.per_parameter), dict(new.per_parameter)
    return plain + sorted(name for name in set(before) | set(after)
                          if before.get(name) != after.get(name))


def _refuse_configure_only(config: IdentificationConfig, changes: Mapping[str, Any]) -> None:
    """
    Refuse a change of a parameter read at configure while the node is configured.

    The topics, the stamp source and the QoS make the subscriptions and the streams' labels; a
    managed node takes new values between cleanup and configure (as nav2 nodes read theirs at
    configure), a plain node at start-up. The same value again is no change.
    """
    fixed = sorted(name for name, value in changes.items()
                   if name in _CONFIGURE_ONLY and value != config.value(name))
    if fixed:
        raise ConfigError(f'{", ".join(fixed)}: read-only while the node is configured; a '
                          'managed node (lifecycle: true) takes a new value between cleanup '
                          'and configure, a plain node at start-up')


def _together_hint(changes: Mapping[str, Any], error: str) -> str:
    """
    Return how to change a model with the values given per parameter, where that was refused.

    ``ros2 param set`` and the SetParameters service change one parameter at a time: a model
    with other parameters then fails against the old parameter_names or vectors, and those
    fail against the old model. Only an atomic update changes them together.
    """
    missing = [name for name in _PER_MODEL_PARAMETER if name not in changes]
    if 'model' not in changes or not missing or \
            not any(error.startswith(name) for name in _PER_MODEL_PARAMETER):
        return ''
    return (f'; set model with {", ".join(missing)} in one atomic update (the '
            'set_parameters_atomically service of the node, as AsyncParameterClient.'
            'set_parameters_atomically of rclpy calls it), or clear them first')


class ParameterHandling:
    """
    Reading the parameters at configure and following their runtime changes.

    A part of :class:`~ctid_ros.ros.node.IdentificationNode`, not usable alone.
    """

    def _read_config(self) -> IdentificationConfig:
        """Validate the declared parameters into a configuration (raise ConfigError)."""
        values = {spec.name: parameter_value(self, spec.name, spec.default)
                  for spec in PARAMETERS}
        config = bounded(lambda: IdentificationConfig.from_dict(values), VALIDATION_TIMEOUT,
                         self._validating)
        # The model's parameters are known now: baseline.J and the like can be declared (a
        # params file's values for them become theirs) and read.
        declare_per_parameter(self, config.names)
        values.update({name: parameter_value(self, name, math.nan)
                       for name in per_parameter_names(config.names)})
        return IdentificationConfig.from_dict(values)

    def _on_set_parameters(self, parameters: List[Parameter]) -> SetParametersResult:
        try:
            changes = {parameter.name: parameter.value for parameter in parameters
                       if parameter.name in PARAMETER_NAMES
                       or split_per_parameter(parameter.name)}
            if not changes or self._config is None:
                # Unconfigured: the parameters are validated on configure, as nav2 does.
                return SetParametersResult(successful=True)
            defaults = {spec.name: spec.default for spec in PARAMETERS}
            changes = {name: defaults.get(name, math.nan) if value is None else value
                       for name, value in changes.items()}
            current = self._config
            _refuse_configure_only(current, changes)
            config = bounded(lambda: current.updated(changes), VALIDATION_TIMEOUT,
                             self._validating)
            self._check_fields(current, config)
            baseline = self._changed_baseline(current, config, changes)
            if changed_parameters(current, config):
                # The same values again (the declaration of baseline.<name> for a new model, a
                # repeated set) leave the configuration alone and are not logged.
                self._apply(config)
            if baseline is not None:
                with self._lock:
                    self._pending_baseline = baseline
        except ConfigError as error:
            reason = str(error) + _together_hint(changes, str(error))
            self._rejected_parameters += 1
            self._last_rejected_parameter = reason[:500]
            self.get_logger().warning(f'parameter update refused: {reason}')
            return SetParametersResult(successful=False, reason=reason)
        except Exception as error:  # noqa: B902 - MemoryError, bugs: refuse, keep running
            self._internal_error('parameter update', error)
            return SetParametersResult(successful=False, reason=f'internal error: {error!r}')
        return SetParametersResult(successful=True)

    def _check_fields(self, old: IdentificationConfig, new: IdentificationConfig) -> None:
        """
        Refuse new field paths that no published type has, where the old ones are read.

        Such a change would stop the estimates while the publishers go on; where the old
        paths fit no published type either (or a topic has no publisher yet), it is accepted
        and followed as the types come.
        """
        if (new.input_fields, new.output_field) == (old.input_fields, old.output_field):
            return
        unreadable = self._unreadable_fields(new)
        if unreadable is not None and self._unreadable_fields(old) is None:
            raise ConfigError(f'{unreadable}; the node keeps reading '
                              f'{", ".join(old.input_fields)} and {old.output_field}')

    def _changed_baseline(self, old: IdentificationConfig, new: IdentificationConfig,
                          changes: Mapping[str, Any]) -> Optional[Tuple[Optional[Baseline], str]]:
        """
        Return the baseline a runtime change sets, or None if it leaves the baseline alone.

        Setting any ``baseline.<name>``/``baseline_std.<name>`` uses the parameters' baseline
        (even over a captured one); a changed ``baseline_file`` (or model) gives
        :func:`configured_baseline`.

        Raises
        ------
        ConfigError
            If the new ``baseline_file`` exists and cannot be used.

        """
        if new.baseline_file != old.baseline_file or new.names != old.names:
            return configured_baseline(new, self.get_fully_qualified_name())
        if any((split_per_parameter(name) or ('',))[0] in ('baseline', 'baseline_std')
               for name in changes):
            return Baseline.from_config(new), 'from the parameters'
        return None

    def _apply(self, config: IdentificationConfig) -> None:
        """Switch to a validated configuration; the session follows at the next estimate."""
        old, old_buffer = self._config, self._buffer
        sampler = self._new_sampler(config)
        rebuild = any(getattr(config, name) != getattr(old, name) for name in BUFFER_PARAMETERS)
        same_width = len(config.input_fields) == len(old.input_fields)
        buffer = self._buffer
        if rebuild or not same_width:
            # Each stream whose topic and fields are unchanged keeps the samples that fit.
            buffer = self._new_buffer(config, sampler, previous=old_buffer)
        fields_changed = (config.input_fields != old.input_fields
                          or config.output_field != old.output_field)
        with self._lock:
            self._sampler, self._buffer, self._config = sampler, buffer, config
            if buffer is not old_buffer:
                self._estimated_since_start = False
        if fields_changed:
            # Another field may fit another of the published types.
            self._follow_topics()
        if config.update_period != old.update_period and self._active:
            self._restart_update_timer()
        if self._active:
            self._connect()
        if config.names != old.names:
            # A new model: its parameters get their baseline.<name> and the like.
            declare_per_parameter(self, config.names)
        # The topics of the old model's parameters (or of the prediction) go.
        self._follow_outputs(config)
        changed = ', '.join(changed_parameters(old, config))
        self.get_logger().info(f'configuration updated: {changed}')
