"""
The output contract of the identification node, written down once.

The live node (:mod:`ctid_ros.ros.node`) and ``ctid replay --output``
(:class:`ctid_ros.files.mcap_writer.EstimateWriter`) publish the same topics, types and layouts
because both take them from here. With the node ``/ctid_node`` (``~`` below), one message of
each per update:

* ``~/estimate``, ``~/estimate_std``: ``std_msgs/msg/Float64MultiArray``, the estimates and their
  standard deviations in ``parameter_names`` order, the comma-separated names in
  ``layout.dim[0].label``;
* ``~/estimate_covariance``: ``std_msgs/msg/Float64MultiArray``, the parameter covariance, row
  major, two dimensions (rows, columns) each labelled with the names;
* ``~/params/<name>``: ``std_msgs/msg/Float64``, one topic per parameter;
* ``~/prediction``: ``std_msgs/msg/Float64MultiArray``, the model output at every grid instant
  of the window, label ``prediction``; its first and last instants are ``window_start`` and
  ``window_end`` of the diagnostics sent with it (plus their ``output_skew``: the output is
  predicted where it was measured);
* ``/diagnostics``: ``diagnostic_msgs/msg/DiagnosticArray`` with one status named
  ``ctid_node: estimate`` (also after an update that gave no estimate);
* ``~/alarm``: ``diagnostic_msgs/msg/DiagnosticStatus`` named ``ctid_node: alarm``, the change
  alarm after each update (:mod:`ctid_ros.streaming.alarm`): OK, WARN (the model no longer
  explains the data) or ERROR (a parameter changed), which parameters, how much and since
  when in its values (:func:`alarm_message`).

Publisher QoS (:class:`PublisherQos`, in :attr:`OutputMessage.qos`): the estimates, standard
deviations, covariance, per-parameter topics and the alarm are :data:`LATCHED` (reliable,
transient local, keep last 1), so a tool that starts later still gets the last estimate and the
current alarm; the prediction and the diagnostics are :data:`STREAM` (reliable, volatile, keep
last 10).

The status level follows :func:`update_status` (OK, or WARN with the reason, raised to the
alarm's level when the diagnostics carry one) after an estimate and :func:`failure_status`
(WARN for missing or unusable data, ERROR for a failed estimate) otherwise. Messages are plain
data here: nested dicts of field values, as the message definitions nest them, which the node
turns into rclpy messages and the MCAP writer serialises. Times are integer nanoseconds since
the epoch (:data:`NANOSECONDS` per second) in messages; text meant for people (status
messages, log lines) counts seconds since the first sample (:func:`estimate_line`,
:func:`warm_up_text`), and the diagnostics carry both.
"""

from dataclasses import dataclass
import json
import re
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from ctid_ros.errors import ConfigError, CtidError, DataError
from ctid_ros.streaming.parameter_specs import DEFAULT_NODE_NAME
import numpy as np

__all__ = [
    'ALARM', 'DEFAULT_NODE_NAME', 'DIAGNOSTIC_ARRAY', 'DIAGNOSTIC_STATUS', 'DIAGNOSTICS_TOPIC',
    'ERROR', 'ESTIMATE', 'LEVELS', 'alarm_message',
    'ESTIMATE_COVARIANCE', 'ESTIMATE_STD', 'FLOAT64', 'FLOAT64_MULTI_ARRAY', 'LATCHED',
    'NANOSECONDS', 'NodeTopics', 'count_change', 'OK', 'OutputMessage', 'PARAMS', 'PREDICTION',
    'PREDICTION_LABEL', 'PublisherQos', 'STREAM', 'WARN', 'diagnostics_message',
    'estimate_line', 'estimate_messages', 'estimate_summary', 'failure_status',
    'format_diagnostic', 'matrix_multiarray', 'multiarray', 'resolve_topic', 'time_fields',
    'update_status', 'warm_up_text', 'MODEL_RECOMMENDATION', 'STRING', 'TUNING',
    'comparison_message', 'tuning_message',
]

NANOSECONDS = 1_000_000_000

# Topic suffixes below the node's name, and the one absolute topic.
ESTIMATE = 'estimate'
ESTIMATE_STD = 'estimate_std'
ESTIMATE_COVARIANCE = 'estimate_covariance'
PARAMS = 'params'
PREDICTION = 'prediction'
ALARM = 'alarm'
TUNING = 'tuning'
MODEL_RECOMMENDATION = 'model_recommendation'
DIAGNOSTICS_TOPIC = '/diagnostics'
PREDICTION_LABEL = 'prediction'

FLOAT64 = 'std_msgs/msg/Float64'
STRING = 'std_msgs/msg/String'
FLOAT64_MULTI_ARRAY = 'std_msgs/msg/Float64MultiArray'
DIAGNOSTIC_ARRAY = 'diagnostic_msgs/msg/DiagnosticArray'
DIAGNOSTIC_STATUS = 'diagnostic_msgs/msg/DiagnosticStatus'

# diagnostic_msgs/DiagnosticStatus levels, and their names (the alarm's level in --json).
OK, WARN, ERROR = 0, 1, 2
LEVELS = {'OK': OK, 'WARN': WARN, 'ERROR': ERROR}

_NAME = re.compile(r'[A-Za-z_][A-Za-z0-9_]*\Z')


@dataclass(frozen=True)
class PublisherQos:
    """
    The QoS of a published topic, as plain data (the node builds the rclpy profile from it).

    Attributes
    ----------
    reliability : str
        ``'reliable'`` or ``'best_effort'``.
    durability : str
        ``'transient_local'`` (late subscribers get the last ``depth`` messages) or
        ``'volatile'``.
    depth : int
        History depth (keep last).

    """

    reliability: str
    durability: str
    depth: int


# The last estimate stays available to subscribers that start later.
LATCHED = PublisherQos('reliable', 'transient_local', 1)
STREAM = PublisherQos('reliable', 'volatile', 10)


def _check_name(token: str, what: str) -> None:
    if not _NAME.match(token):
        raise ConfigError(f'invalid ROS name {token!r} in {what}: use letters, digits and '
                          'underscores, not starting with a digit')


@dataclass(frozen=True)
class NodeTopics:
    """
    The names under which one node publishes.

    Attributes
    ----------
    node : str
        Fully qualified node name, e.g. ``'/ctid_node'`` or ``'/plant1/ctid_node'``.

    Raises
    ------
    ConfigError
        If the name is not a valid fully qualified ROS node name.

    """

    node: str

    def __post_init__(self) -> None:
        tokens = self.node.split('/')
        if not self.node.startswith('/') or len(tokens) < 2:
            raise ConfigError(f'{self.node!r} is not a fully qualified node name such as '
                              f'/{DEFAULT_NODE_NAME}')
        for token in tokens[1:]:
            _check_name(token, f'node {self.node!r}')

    @classmethod
    def of(cls, node_name: str = DEFAULT_NODE_NAME, namespace: str = '') -> 'NodeTopics':
        """
        Return the topics of node ``node_name`` in ``namespace``.

        ``node_name`` may carry the namespace itself (``'/plant1/ctid_node'``, as ``ctid replay
        --node-name`` takes it); a relative one is placed in ``namespace`` (default the root).
        """
        space, _, base = node_name.rpartition('/')
        tokens = [token for token in f'{namespace}/{space}'.split('/') if token]
        for token in (*tokens, base):
            _check_name(token, f'namespace {namespace!r} / node {node_name!r}')
        return cls('/' + '/'.join((*tokens, base)))

    @property
    def name(self) -> str:
        """Return the node's base name, which is also the ``hardware_id`` of its status."""
        return self.node.rpartition('/')[2]

    @property
    def estimate(self) -> str:
        """Return the topic of the estimates."""
        return f'{self.node}/{ESTIMATE}'

    @property
    def estimate_std(self) -> str:
        """Return the topic of the standard deviations."""
        return f'{self.node}/{ESTIMATE_STD}'

    @property
    def estimate_covariance(self) -> str:
        """Return the topic of the parameter covariance."""
        return f'{self.node}/{ESTIMATE_COVARIANCE}'

    @property
    def prediction(self) -> str:
        """Return the topic of the predicted output."""
        return f'{self.node}/{PREDICTION}'

    @property
    def alarm(self) -> str:
        """Return the topic of the change alarm."""
        return f'{self.node}/{ALARM}'

    @property
    def tuning(self) -> str:
        """Return the topic of the controller recommendation (``tune.controller``)."""
        return f'{self.node}/{TUNING}'

    @property
    def model_recommendation(self) -> str:
        """Return the topic of the comparison of ``candidate_models``."""
        return f'{self.node}/{MODEL_RECOMMENDATION}'

    @property
    def diagnostics(self) -> str:
        """Return the diagnostics topic (absolute: shared by all nodes)."""
        return DIAGNOSTICS_TOPIC

    @property
    def alarm_name(self) -> str:
        """Return the name of the alarm status, e.g. ``'ctid_node: alarm'``."""
        return f'{self.node[1:]}: {ALARM}'

    @property
    def status_name(self) -> str:
        """Return the name of the node's diagnostic status, e.g. ``'ctid_node: estimate'``."""
        return f'{self.node[1:]}: {ESTIMATE}'

    def param(self, name: str) -> str:
        """Return the topic of parameter ``name``."""
        return f'{self.node}/{PARAMS}/{name}'


def resolve_topic(name: str, node_name: str = DEFAULT_NODE_NAME) -> str:
    """
    Return the absolute topic a node named ``node_name`` subscribes to for ``name``.

    A relative name follows the node's namespace (``u`` -> ``/u``, or ``/plant1/u`` for the
    node ``/plant1/ctid_node``); ``~/x`` is private to the node (``/ctid_node/x``).
    """
    namespace, _, base = node_name.rpartition('/')
    namespace = namespace.rstrip('/')
    if name.startswith('/'):
        return name
    if name.startswith('~/'):
        return f'{namespace}/{base}/{name[2:]}'
    return f'{namespace}/{name}'


@dataclass(frozen=True)
class OutputMessage:
    """
    One message of the contract as plain data.

    Attributes
    ----------
    topic : str
        Absolute topic.
    msgtype : str
        Message type, e.g. ``'std_msgs/msg/Float64MultiArray'``.
    fields : dict
        Field values, nested as the message definition nests them; arrays as lists.
    qos : PublisherQos
        How the live node publishes it.

    """

    topic: str
    msgtype: str
    fields: Dict[str, Any]
    qos: PublisherQos = STREAM


def time_fields(time_ns: int) -> Dict[str, int]:
    """Return a ``builtin_interfaces/Time`` as ``{'sec': ..., 'nanosec': ...}``."""
    sec, nanosec = divmod(int(time_ns), NANOSECONDS)
    return {'sec': sec, 'nanosec': nanosec}


def multiarray(label: str, values: Sequence[float]) -> Dict[str, Any]:
    """Return a one-dimensional ``std_msgs/Float64MultiArray`` whose dimension is ``label``."""
    data = [float(value) for value in np.asarray(values, dtype=float).ravel()]
    return {'layout': {'dim': [{'label': label, 'size': len(data), 'stride': len(data)}],
                       'data_offset': 0},
            'data': data}


def matrix_multiarray(label: str, matrix: Any) -> Dict[str, Any]:
    """
    Return a square matrix as a two-dimensional ``std_msgs/Float64MultiArray``, row major.

    Both dimensions are labelled ``label`` (the parameter names), as ROS lays out a matrix:
    ``dim[0]`` the rows (stride n*n), ``dim[1]`` the columns (stride n).
    """
    matrix = np.asarray(matrix, dtype=float)
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1]:
        raise DataError(f'a covariance must be a square matrix, got shape {matrix.shape}')
    size = matrix.shape[0]
    return {'layout': {'dim': [{'label': label, 'size': size, 'stride': size * size},
                               {'label': label, 'size': size, 'stride': size}],
                       'data_offset': 0},
            'data': [float(value) for value in matrix.ravel()]}


def _check_parameters(names: Sequence[str], arrays: Mapping[str, Sequence[float]]) -> None:
    for name in names:
        if not isinstance(name, str) or not _NAME.match(name):
            raise DataError(f'parameter name {name!r} cannot be used in a topic name')
    if len(set(names)) != len(names):
        raise DataError(f'parameter names must be unique, got {list(names)}')
    for label, array in arrays.items():
        if len(array) != len(names):
            raise DataError(f'{len(array)} {label} for {len(names)} parameter names')


def estimate_messages(topics: NodeTopics, names: Sequence[str], values: Sequence[float],
                      stds: Optional[Sequence[float]] = None,
                      prediction: Optional[Sequence[float]] = None, *,
                      covariance: Optional[Any] = None) -> List[OutputMessage]:
    """
    Return the messages of one update in publishing order, diagnostics excepted.

    Parameters
    ----------
    topics : NodeTopics
        The publishing node.
    names : sequence of str
        Parameter names in publishing order.
    values, stds : sequence of float
        Estimates and standard deviations in ``names`` order; without ``stds`` nothing goes
        to ``estimate_std``.
    prediction : sequence of float, optional
        Model output over the window; without it nothing goes to ``prediction``.
    covariance : array_like, optional
        Parameter covariance in ``names`` order (n x n); without it nothing goes to
        ``estimate_covariance``.

    Raises
    ------
    DataError
        If a name cannot be part of a topic name, names repeat, or lengths differ.

    """
    names = list(names)
    arrays = {'values': values} if stds is None else {'values': values, 'stds': stds}
    if covariance is not None:
        arrays['covariance rows'] = np.asarray(covariance)
    _check_parameters(names, arrays)
    label = ','.join(names)
    messages = [OutputMessage(topics.estimate, FLOAT64_MULTI_ARRAY, multiarray(label, values),
                              LATCHED)]
    if stds is not None:
        messages.append(OutputMessage(topics.estimate_std, FLOAT64_MULTI_ARRAY,
                                      multiarray(label, stds), LATCHED))
    if covariance is not None:
        messages.append(OutputMessage(topics.estimate_covariance, FLOAT64_MULTI_ARRAY,
                                      matrix_multiarray(label, covariance), LATCHED))
    messages.extend(OutputMessage(topics.param(name), FLOAT64, {'data': float(value)}, LATCHED)
                    for name, value in zip(names, values))
    if prediction is not None:
        messages.append(OutputMessage(topics.prediction, FLOAT64_MULTI_ARRAY,
                                      multiarray(PREDICTION_LABEL, prediction)))
    return messages


def count_change(value: Any) -> int:
    """
    Return a middleware counter's increment as a non-negative Python int.

    rmw reports counts such as ``total_count_change`` of a lost-message event as ``size_t``;
    a negative change read through it (seen after a message of 1e7 elements) arrives as a
    number near ``2**64`` and made ``input_lost`` read 18446744071562067969. Values from
    ``2**63`` on are such wrapped negatives and count as 0, as does anything negative or not an
    integer; the sum of the returned increments can then only grow, by what really happened.
    """
    try:
        change = int(value)
    except (TypeError, ValueError, OverflowError):
        return 0
    return change if 0 <= change < 2 ** 63 else 0


def format_diagnostic(value: Any) -> str:
    """
    Format a diagnostic value as a ``diagnostic_msgs/KeyValue`` string.

    Floats keep every digit (the shortest text that reads back exactly): ``window_start`` and
    ``window_end`` are seconds since the epoch, which six significant digits would round to
    hours.
    """
    if isinstance(value, (bool, np.bool_)):
        return 'true' if value else 'false'
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, (list, tuple)):
        return '; '.join(format_diagnostic(item) for item in value)
    return str(value)


def estimate_summary(names: Sequence[str], values: Sequence[float],
                     stds: Optional[Sequence[float]] = None) -> str:
    """Return the one-line summary of an estimate, e.g. ``'K=2.01 (std 0.003), T=...'``."""
    if stds is None:
        return ', '.join(f'{name}={value:.6g}' for name, value in zip(names, values))
    return ', '.join(f'{name}={value:.6g} (std {std:.3g})'
                     for name, value, std in zip(names, values, stds))


def _number(value: float, std: Optional[float] = None) -> str:
    return f'{value:.6g}' if std is None else f'{value:.6g} +- {std:.2g}'


def estimate_line(names: Sequence[str], values: Sequence[float], stds: Sequence[float],
                  time_s: float, fit: Optional[float] = None,
                  residuals: Optional[str] = None) -> str:
    """
    Return the one-line log of an estimate, for people reading the node's console.

    ``time_s`` is the end of the window in seconds since the first sample. Example::

        t=12.50 s: K = 2.0013 +- 0.0031, T = 0.4998 +- 0.0012; fit 95.3 %; residuals white

    """
    text = ', '.join(f'{name} = {_number(value, std)}'
                     for name, value, std in zip(names, values, stds))
    parts = [f't={time_s:.2f} s: {text}']
    if fit is not None:
        parts.append(f'fit {fit:.1f} %')
    if residuals:
        parts.append(f'residuals {residuals}')
    return '; '.join(parts)


def warm_up_text(available_s: float, window_s: float,
                 first_estimate_s: Optional[float] = None) -> str:
    """
    Return the status text while the node collects its first window of data.

    E.g. ``'warming up: 6.4 of 10 s of data (first estimate after 5 s)'``: the configured
    window, not the longer span (with the settling transient) the node asks for. Without
    ``first_estimate_s`` (estimates already come) the parenthesis is left out.
    """
    text = f'warming up: {max(available_s, 0.0):.1f} of {window_s:g} s of data'
    if first_estimate_s is None:
        return text
    return f'{text} (first estimate after {first_estimate_s:g} s)'


def update_status(names: Sequence[str], values: Sequence[float],
                  stds: Optional[Sequence[float]], diagnostics: Mapping[str, Any]
                  ) -> Tuple[int, str]:
    """
    Return the level and message of the status of an update.

    WARN with the warnings when the estimate has any (gaps, active bounds, ...), WARN ``not
    converged`` when it did not converge, else OK with :func:`estimate_summary`. When the
    diagnostics carry the change alarm (``alarm``: ``'OK'``, ``'WARN'`` or ``'ERROR'``, and
    ``alarm_message``; :meth:`ctid_ros.streaming.alarm.AlarmStatus.diagnostics`), a WARN or
    ERROR alarm raises the level to its own and its message comes first.
    """
    warnings = list(diagnostics.get('warnings') or [])
    if warnings:
        level, text = WARN, '; '.join(str(warning) for warning in warnings)
    elif diagnostics.get('converged') is False:
        level, text = WARN, 'not converged'
    else:
        level, text = OK, estimate_summary(names, values, stds)
    alarm = LEVELS.get(str(diagnostics.get('alarm', 'OK')), OK)
    if alarm > OK:
        level = max(level, alarm)
        text = f'alarm: {diagnostics.get("alarm_message", "")}; {text}'
    return level, text


def failure_status(error: CtidError) -> Tuple[int, str]:
    """
    Return the level and message of the status when an update gave no estimate.

    WARN when the data are missing or unusable (a :class:`~ctid_ros.errors.DataError`: the
    node waits for better data), ERROR when the estimation itself failed.
    """
    return (WARN if isinstance(error, DataError) else ERROR), str(error)


def _status(name: str, level: int, message: str, values: Mapping[str, Any],
            hardware_id: str) -> Dict[str, Any]:
    return {'level': int(level), 'name': name, 'message': message, 'hardware_id': hardware_id,
            'values': [{'key': str(key), 'value': format_diagnostic(value)}
                       for key, value in values.items()]}


def alarm_message(topics: NodeTopics, level: int, message: str, values: Mapping[str, Any],
                  hardware_id: str = '') -> OutputMessage:
    """
    Return the ``~/alarm`` message: a ``diagnostic_msgs/DiagnosticStatus``, latched.

    Named :attr:`NodeTopics.alarm_name`; ``level`` OK/WARN/ERROR, ``message`` what changed and
    since when, ``values`` the details (:meth:`ctid_ros.streaming.alarm.AlarmStatus.values`:
    ``parameters``, ``since``, per parameter its change, 95 % interval and evidence).
    """
    return OutputMessage(topics.alarm, DIAGNOSTIC_STATUS,
                         _status(topics.alarm_name, level, message, values,
                                 hardware_id or topics.name), LATCHED)


def tuning_message(topics: NodeTopics, recommendation: Mapping[str, Any]) -> OutputMessage:
    """
    Return the ``~/tuning`` message: a ``std_msgs/String`` of JSON, latched (depth 1).

    ``recommendation`` is :meth:`ctid_ros.design.tune.Tuning.to_dict` (``gains``, ``margins``
    with their ``band``, ``method``, ``target``, ``warnings``, ``ros2_control``: the params
    YAML of a ros2_control ``pid_controller``) with what it was tuned on (``time``, the
    window's end in seconds, and ``model``); a late subscriber gets the latest.
    """
    return OutputMessage(topics.tuning, STRING,
                         {'data': json.dumps(recommendation, allow_nan=False)}, LATCHED)


def comparison_message(topics: NodeTopics, comparison: Mapping[str, Any]) -> OutputMessage:
    """
    Return the ``~/model_recommendation`` message: a ``std_msgs/String`` of JSON, latched.

    ``comparison``: ``time`` (the window's end, s), ``recommended`` (the model text) and
    ``candidates``, the ``ctid compare --json`` list (best first, exactly one recommended).
    """
    return OutputMessage(topics.model_recommendation, STRING,
                         {'data': json.dumps(comparison, allow_nan=False)}, LATCHED)


def diagnostics_message(topics: NodeTopics, stamp_ns: int, level: int, message: str,
                        values: Mapping[str, Any], hardware_id: str = '') -> OutputMessage:
    """
    Return the ``/diagnostics`` message of one update (or failed update) of the node.

    Parameters
    ----------
    topics : NodeTopics
        The node; names the status, and is its ``hardware_id`` unless one is given.
    stamp_ns : int
        Header stamp.
    level : int
        :data:`OK`, :data:`WARN` or :data:`ERROR`.
    message : str
        Status message.
    values : mapping
        Key/value pairs in order, formatted by :func:`format_diagnostic`.
    hardware_id : str
        The ``hardware_id`` of the status (the ``hardware_id`` parameter); '' = the node name.

    """
    status = _status(topics.status_name, level, message, values, hardware_id or topics.name)
    return OutputMessage(DIAGNOSTICS_TOPIC, DIAGNOSTIC_ARRAY,
                         {'header': {'stamp': time_fields(stamp_ns), 'frame_id': ''},
                          'status': [status]})
