"""
The parameters of the live node and of ``ctid replay``, as plain data: importable at once.

This module imports neither numpy nor sympy nor rclpy, so ``ctid_node --help``, a
documentation generator and the node's parameter table read it without the numerical stack
(issue #26). It is the one place of every parameter's name, type, default, help text and range;
:class:`~ctid_ros.streaming.config.IdentificationConfig` has one field per entry of
:data:`PARAMETERS` and validates the values, the node declares them
(:mod:`ctid_ros.ros.parameters`).

A name with a dot is a nested mapping of a params file as ROS flattens it: ``tune:
{controller: PI}`` is the parameter ``tune.controller`` (the field ``tune_controller``).

The choices of ``method``, ``intersample`` and ``initial_state`` repeat the estimator's
(:data:`ctid_ros.estimation.options.METHODS`, :data:`ctid_ros.core.simulation.INTERSAMPLE`,
:data:`ctid_ros.estimation.options.INITIAL_STATES`) and those of ``tune.*`` the design's
(:data:`ctid_ros.design.tune.CONTROLLERS`, :data:`ctid_ros.design.tune.METHODS`), because
those modules import the numerical stack; test/streaming/test_parameter_specs.py checks that
they agree.
"""

from dataclasses import dataclass
from typing import Any, Optional, Tuple

from ctid_ros.core.limits import MAX_SAMPLES

__all__ = ['CONFIGURE_ONLY_CONSTRAINT', 'DEFAULT_NODE_NAME', 'ESTIMATION_METHODS',
           'INITIAL_STATES', 'INTERSAMPLE', 'MAX_BASELINE_WINDOWS', 'MAX_BUFFER_BYTES',
           'MAX_DURATION',
           'MAX_FALSE_ALARM_PER_HOUR', 'MAX_ITERATIONS', 'MAX_MESSAGE_RATE', 'MAX_QOS_DEPTH',
           'MAX_COMPARE_EVERY', 'MAX_RELATIVE_CHANGE', 'MAX_TUNE_DRAWS',
           'MIN_FALSE_ALARM_PER_HOUR', 'MIN_MAX_GAP',
           'MIN_UPDATE_PERIOD', 'MIN_WINDOW_SAMPLES', 'PARAMETER_NAMES', 'PARAMETERS',
           'PER_PARAMETER', 'ParameterSpec', 'RELIABILITIES', 'STAMP_SOURCES',
           'TUNE_CONTROLLERS', 'TUNE_METHODS', 'field_name', 'per_parameter_name']

DEFAULT_NODE_NAME = 'ctid_node'
# The constraint of a parameter read at configure, as ros2 param describe shows it.
CONFIGURE_ONLY_CONSTRAINT = ('changes only while unconfigured (a managed node: cleanup, set, '
                             'configure)')
STAMP_SOURCES = ('header', 'receive')
RELIABILITIES = ('best_effort', 'reliable')
ESTIMATION_METHODS = ('iv', 'ls', 'gn')
INTERSAMPLE = ('zoh', 'foh')
INITIAL_STATES = ('zero', 'estimate')
# '' = no tuning; else ctid_ros.design.tune.CONTROLLERS.
TUNE_CONTROLLERS = ('', 'PI', 'PID')
TUNE_METHODS = ('auto', 'simc', 'ms')
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
# Covariance draws of a tuning's verification: each is a margin computation, and the node
# tunes after every estimate.
MAX_TUNE_DRAWS = 1000
MAX_COMPARE_EVERY = 1_000_000
# Parameters set per model parameter, as ROS flattens a nested mapping of a params file
# (``baseline: {J: 0.05}`` arrives as ``baseline.J``): the prefix and what it means.
PER_PARAMETER = {
    'baseline': 'baseline value of the parameter, against which changes are alarmed',
    'baseline_std': 'standard deviation of that baseline value (0 or unset: exact)',
    'min_relative_change': 'smallest relative change of the parameter that is an alarm '
                           '(unset: min_relative_change)',
}


@dataclass(frozen=True)
class ParameterSpec:
    """
    One configuration parameter, as the node declares it.

    Attributes
    ----------
    name : str
        Parameter name as ROS declares it (``tune.controller``).
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
        True for a parameter that never changes once the node runs (``lifecycle``).
    configure_only : bool
        True for a parameter read when the node is configured and fixed while it is (topics,
        stamp source, QoS): a managed node takes a new value between cleanup and configure,
        a plain node only at start-up.

    """

    name: str
    kind: str
    default: Any
    description: str
    minimum: Optional[float] = None
    choices: Tuple[str, ...] = ()
    read_only: bool = False
    configure_only: bool = False

    @property
    def type_name(self) -> str:
        """Return the ``rcl_interfaces/ParameterType`` constant name, e.g. PARAMETER_DOUBLE."""
        return 'PARAMETER_' + self.kind.upper()

    @property
    def constraints(self) -> str:
        """Return the constraints in words, for ``ParameterDescriptor.additional_constraints``."""
        if self.choices:
            text = 'one of: ' + ', '.join(choice or "''" for choice in self.choices)
        elif self.minimum is not None:
            text = f'value >= {self.minimum}'
        else:
            text = ''
        if self.configure_only:
            text += ('; ' if text else '') + CONFIGURE_ONLY_CONSTRAINT
        return text


def _spec(name: str, default: Any, kind: str, description: str, *,
          minimum: Optional[float] = None, choices: Tuple[str, ...] = (),
          read_only: bool = False, configure_only: bool = False) -> ParameterSpec:
    return ParameterSpec(name, kind, default, description, minimum, choices, read_only,
                         configure_only)


PARAMETERS: Tuple[ParameterSpec, ...] = (
    _spec(
        'input_topic',
        'u', 'string', 'Topic of the input u (the reference r in closed loop); relative names '
        'follow the node namespace.', configure_only=True),
    _spec(
        'input_field',
        'data', 'string', "Field of the input message holding the value, e.g. 'data', "
        "'effort[0]', 'twist.linear.x'."),
    _spec(
        'output_topic',
        'y', 'string', 'Topic of the measured output y; may equal input_topic when one '
        'message carries both (e.g. /joint_states).', configure_only=True),
    _spec(
        'output_field',
        'data', 'string', "Field of the output message holding the value, e.g. 'position[0]'."),
    _spec(
        'extra_input_fields',
        (), 'string_array', 'Fields of the input message holding the further inputs of a '
        "model equation, in input_names order after the first, e.g. ['effort[1]']."),
    _spec(
        'model',
        '', 'string', 'Plant transfer function in s; every other name is a parameter, e.g. '
        "'K*exp(-tau*s)/(T*s + 1)'; or a model equation such as "
        "'M*s**2*y + Fv*s*y = 35.2*u - Fc*w - off' with its signals named by input_names and "
        'output_name. Required.'),
    _spec(
        'input_names',
        ('u',), 'string_array', 'Names of the inputs in a model equation: the first is read '
        'from input_field, the others from extra_input_fields.'),
    _spec(
        'output_name',
        'y', 'string', 'Name of the output in a model equation.'),
    _spec(
        'controller',
        '', 'string', "Known controller K(s) with numeric coefficients, e.g. '20 + 10/s': the "
        "data are then the closed loop from the reference (input_topic) to y. '' = open loop."),
    _spec(
        'parameter_names',
        (), 'string_array', 'Order of the parameters in initial/lower/upper and in all published '
        'arrays; a permutation of the model parameters. Empty = order of first appearance in '
        'the model.'),
    _spec(
        'initial',
        (), 'double_array', 'Initial values in parameter_names order; NaN entries (and an empty '
        'array) are initialised automatically.'),
    _spec(
        'lower',
        (), 'double_array', 'Lower bounds in parameter_names order (-.inf = none); empty = '
        'no bounds.'),
    _spec(
        'upper',
        (), 'double_array', 'Upper bounds in parameter_names order (.inf = none); empty = '
        'no bounds.'),
    _spec(
        'sample_time',
        0.01, 'double', 'Sample time (s, at least 1e-6) of the grid the messages are resampled '
        "onto, normally the actuator update period; the grid follows the input's own instants "
        "when it is a whole multiple or fraction of the input's period (finer than the data's "
        "own rate: the data's period, with a warning), else the multiples of sample_time.",
        minimum=0.0),
    _spec(
        'window',
        10.0, 'double', f'Length (s) of the data window used by each estimate; at least '
        f'{MIN_WINDOW_SAMPLES} sample times, and with its settling transient at most '
        f'{MAX_SAMPLES} samples.', minimum=0.0),
    _spec(
        'update_period',
        1.0, 'double', f'Seconds ({MIN_UPDATE_PERIOD:g} to {MAX_DURATION:g}) between successive '
        'estimates.', minimum=0.0),
    _spec(
        'method',
        'iv', 'string', "'iv': least squares then instrumental-variable iterations "
        "(consistent under noise); 'ls': least-squares iterations only; 'gn': Gauss-Newton on "
        'the output error.', choices=ESTIMATION_METHODS),
    _spec(
        'intersample',
        'zoh', 'string', "Input behaviour between samples: 'zoh' (held, e.g. a digital "
        "actuator command) or 'foh' (linear).", choices=INTERSAMPLE),
    _spec(
        'stamp_source',
        'header', 'string', "'header': use header.stamp when the message has a non-zero one, "
        "else the receive time; 'receive': always the receive time.", choices=STAMP_SOURCES,
        configure_only=True),
    _spec(
        'qos_reliability',
        'best_effort', 'string', 'Subscription reliability; best_effort also matches reliable '
        'publishers.', choices=RELIABILITIES, configure_only=True),
    _spec(
        'qos_depth',
        500, 'integer', f'Subscription queue depth (keep last, at most {MAX_QOS_DEPTH}); deep, so '
        'bursts are not lost.', minimum=1, configure_only=True),
    _spec(
        'max_message_rate',
        1000.0, 'double', 'Highest message rate (Hz) per topic the live sample buffer is sized '
        'for (1/sample_time if that is higher); faster messages shorten the history it holds. '
        'With window, transient and max_gap it sets the buffer memory, which is limited.',
        minimum=0.0),
    _spec(
        'max_gap',
        0.5, 'double', 'Seconds (at least 1e-6) without a sample after which a stream counts as '
        'missing: data are never interpolated or held across such a gap.', minimum=0.0),
    _spec(
        'reorder_horizon',
        0.05, 'double', 'Seconds a sample may arrive out of order and still be used; older '
        'late samples are dropped and counted.', minimum=0.0),
    _spec(
        'delay_min',
        0.0, 'double', 'Lower end (s) of the dead-time search range; delay_min = delay_max = 0 '
        'means automatic.', minimum=0.0),
    _spec(
        'delay_max',
        0.0, 'double', 'Upper end (s) of the dead-time search range (see delay_min).',
        minimum=0.0),
    _spec(
        'max_iterations',
        100, 'integer', f'Largest number of iterations of one estimate (at most '
        f'{MAX_ITERATIONS}).', minimum=1),
    _spec(
        'tolerance',
        1e-8, 'double', 'Stop when the largest relative parameter change falls below it (> 0).',
        minimum=0.0),
    _spec(
        'transient',
        -1.0, 'double', 'Seconds at the start of each window that are simulated but not fitted, '
        'because a window cut from a running plant does not start at rest. Negative = '
        'automatic (five slowest time constants plus the dead time, at most half the window).'),
    _spec(
        'initial_state',
        'zero', 'string', "'zero': each window is treated as starting at rest (with the "
        "transient excluded); 'estimate': the initial state is estimated as well.",
        choices=INITIAL_STATES),
    _spec(
        'output_offset',
        False, 'bool', 'Estimate a constant offset of the output (an unknown operating point).'),
    _spec(
        'warm_start',
        True, 'bool', 'Start each estimate from the previous one instead of initial.'),
    _spec(
        'publish_prediction',
        False, 'bool', 'Publish the model output predicted over the window.'),
    _spec(
        'hardware_id',
        '', 'string', "hardware_id of the node's status on /diagnostics, e.g. the drive being "
        "identified; '' = the node's name."),
    _spec(
        'lifecycle',
        False, 'bool', 'Live node only: true = a managed (lifecycle) node that starts '
        'unconfigured and follows configure/activate/deactivate/cleanup/shutdown transitions, '
        'as nav2 nodes do; false = configure and activate at start-up.', read_only=True),
    _spec(
        'baseline_file',
        '', 'string', 'YAML file of the baseline the change alarm compares with: written by '
        'the ~/capture_baseline service, read at configure (so a restart keeps it) and when '
        'this parameter changes; when it exists it takes precedence over baseline.<name> '
        "parameters. '' = none."),
    _spec(
        'baseline_windows',
        5, 'integer', f'Windows averaged by ~/capture_baseline into a baseline (1 to '
        f'{MAX_BASELINE_WINDOWS}).', minimum=1),
    _spec(
        'false_alarm_per_hour',
        0.1, 'double', f'Change alarms a stationary plant raises per hour, on average '
        f'({MIN_FALSE_ALARM_PER_HOUR:g} to {MAX_FALSE_ALARM_PER_HOUR:g}); sets the threshold of '
        'the sequential test on the windows (with update_period and the overlap of the '
        'windows).', minimum=0.0),
    _spec(
        'min_relative_change',
        0.02, 'double', f'Smallest change of a parameter, relative to its baseline, that is an '
        f'alarm (0 to {MAX_RELATIVE_CHANGE:g}): a real but smaller change is not; per parameter '
        'as min_relative_change.<name> (a mapping in a params file).', minimum=0.0),
    _spec(
        'candidate_models',
        (), 'string_array', 'Model structures to compare on the window every compare_every '
        "estimates, as 'ctid compare' does (e.g. ['K*exp(-tau*s)/(T*s + 1)', "
        "'K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))']): the ranking and the simplest adequate "
        'structure are published on the latched ~/model_recommendation. Open loop only; '
        'empty (default) = no comparison; else at least two.'),
    _spec(
        'compare_every',
        10, 'integer', f'Estimates between two comparisons of candidate_models (1 to '
        f'{MAX_COMPARE_EVERY}); a comparison fits every candidate, so it costs their estimates.',
        minimum=1),
    _spec(
        'tune.controller',
        '', 'string', 'Controller to tune after every estimate, from the identified model '
        "(ctid_ros.design.tune, as 'ctid tune'): 'PI' or 'PID'; the gains, their margins on "
        'the model and across its uncertainty and a ros2_control snippet are published on the '
        "latched ~/tuning. '' = no tuning.", choices=TUNE_CONTROLLERS),
    _spec(
        'tune.method',
        'auto', 'string', "Design method: 'simc' (SIMC rules on the model reduced to first or "
        "second order plus dead time), 'ms' (loop shaping on the exact model with its dead "
        "time, Ms-constrained), 'auto' (SIMC for lags and dead time, else loop shaping).",
        choices=TUNE_METHODS),
    _spec(
        'tune.tc',
        0.0, 'double', "SIMC's closed-loop time constant (s); 0 = the effective dead time. "
        'Give tune.tc or tune.ms, not both.', minimum=0.0),
    _spec(
        'tune.ms',
        0.0, 'double', 'Largest sensitivity peak Ms (> 1) of the loop-shaping design; 0 = 1.6.',
        minimum=0.0),
    _spec(
        'tune.sample_time',
        0.0, 'double', "Period (s) of the digital controller: half of it (the hold's delay) is "
        'added to the dead time for the design and its verification; 0 = continuous.',
        minimum=0.0),
    _spec(
        'tune.draws',
        50, 'integer', f'Covariance draws the margins are verified on (0 to {MAX_TUNE_DRAWS}); '
        'each costs a margin computation after every estimate.', minimum=0),
    _spec(
        'tune.joint',
        'joint1', 'string', 'Joint name of the ros2_control pid_controller snippet '
        '(gains.<joint>.p/i/d).'),
)
PARAMETER_NAMES: Tuple[str, ...] = tuple(spec.name for spec in PARAMETERS)


def field_name(name: str) -> str:
    """Return the :class:`~ctid_ros.streaming.config.IdentificationConfig` field of a name."""
    return name.replace('.', '_')


def per_parameter_name(prefix: str, name: str) -> str:
    """Return the ROS name of a per-parameter value, e.g. ``baseline.J``."""
    return f'{prefix}.{name}'
