"""
The command line of every ``ctid`` subcommand: its arguments, and nothing that computes.

``ctid --help`` and ``ctid <command> --help`` need only this module, so they start without
numpy, sympy, scipy, matplotlib, rclpy or the bag readers (about a tenth of a second instead
of two to three, see ``bench/cli_startup.py``). :mod:`ctid_ros.cli.main` imports the module
that runs the chosen command only once the command line has been parsed, and that module
imports the heavy libraries it needs. So the estimator's choices and the node's default name
come from the plain parameter table :mod:`ctid_ros.streaming.parameter_specs`, not from the
estimator or the contract (which import numpy); ``test/cli/test_arguments.py`` checks that
they are ``ctid_ros.estimation.options.METHODS``, ``INITIAL_STATES``,
``ctid_ros.core.simulation.INTERSAMPLE`` and ``ctid_ros.streaming.contract``'s name.
"""

import argparse
from pathlib import Path
from typing import Dict, Optional, Tuple

from ctid_ros.streaming.parameter_specs import (DEFAULT_NODE_NAME, ESTIMATION_METHODS,
                                                INITIAL_STATES, INTERSAMPLE)

__all__ = ['CONTROLLERS', 'DEFAULT_NODE_NAME', 'DEFAULT_PLOT', 'DESIGN_METHODS',
           'INITIAL_STATES', 'INTERSAMPLE', 'METHODS', 'configure_compare', 'configure_echo',
           'configure_fit', 'configure_fleet', 'configure_node', 'configure_record',
           'configure_replay', 'configure_tune', 'parse_bounds', 'parse_fixed', 'parse_initial',
           'parse_interval', 'parse_range', 'parse_target', 'parse_units']

# The estimator's choices from the plain parameter table, which imports nothing heavy.
METHODS = ESTIMATION_METHODS
# ctid_ros.design.tune.CONTROLLERS and METHODS (checked by test/cli/test_tune.py).
CONTROLLERS = ('PI', 'PID')
DESIGN_METHODS = ('auto', 'simc', 'ms')
# The value of ``--plot`` given without a file name (each command picks its default path).
DEFAULT_PLOT = object()


def _assignments(text: str, option: str) -> Dict[str, str]:
    pairs = {}
    for item in filter(None, (part.strip() for part in text.split(','))):
        name, separator, value = item.partition('=')
        if not separator or not name.strip():
            raise argparse.ArgumentTypeError(f'{option} expects NAME=VALUE[,NAME=VALUE...], '
                                             f'got {item!r}')
        pairs[name.strip()] = value.strip()
    return pairs


def _values(text: str, option: str) -> Dict[str, float]:
    try:
        return {name: float(value) for name, value in _assignments(text, option).items()}
    except ValueError as error:
        raise argparse.ArgumentTypeError(f'{option}: {error}') from None


def parse_initial(text: str) -> Dict[str, float]:
    """Parse ``K=1,T=2`` into ``{'K': 1.0, 'T': 2.0}``."""
    return _values(text, '--initial')


def parse_fixed(text: str) -> Dict[str, float]:
    """Parse ``--fix J=0.05,tau=0.03`` into ``{'J': 0.05, 'tau': 0.03}``."""
    return _values(text, '--fix')


def parse_units(text: str) -> Dict[str, str]:
    """Parse ``--units 'J=kg m^2,u=N m,y=rad/s'`` into ``{'J': 'kg m^2', ...}``."""
    return _assignments(text, '--units')


def parse_interval(text: str) -> Tuple[float, float]:
    """Parse ``MIN:MAX`` seconds, e.g. ``0:0.1`` for ``--delay-range``."""
    try:
        low, high = (float(part) for part in text.split(':'))
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected MIN:MAX in seconds, got {text!r}') from None
    if not 0 <= low < high < float('inf'):
        raise argparse.ArgumentTypeError(f'need 0 <= MIN < MAX, got {text!r}')
    return low, high


def parse_bounds(text: str) -> Dict[str, Tuple[Optional[float], Optional[float]]]:
    """Parse ``T=0:10,tau=0:`` into ``{'T': (0, 10), 'tau': (0, None)}``."""
    bounds = {}
    for name, value in _assignments(text, '--bounds').items():
        low, separator, high = value.partition(':')
        if not separator:
            raise argparse.ArgumentTypeError(f'--bounds expects NAME=LOW:HIGH, got {value!r}')
        try:
            bounds[name] = (float(low) if low else None, float(high) if high else None)
        except ValueError as error:
            raise argparse.ArgumentTypeError(f'--bounds: {error}') from None
    return bounds


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected seconds, got {text!r}') from None
    if not 0 < value < float('inf'):
        raise argparse.ArgumentTypeError(f'expected a positive number of seconds, got {text!r}')
    return value


def parse_range(text: str) -> Tuple[int, int]:
    """Parse ``FIRST:LAST``, 1-based inclusive sample numbers (as MATLAB's ``z(1:500)``)."""
    try:
        first, last = (int(part) for part in text.split(':'))
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected FIRST:LAST sample numbers, got {text!r}'
                                         ) from None
    if not 1 <= first <= last:
        raise argparse.ArgumentTypeError(f'need 1 <= FIRST <= LAST, got {text!r}')
    return first, last


def configure_fit(fit: argparse.ArgumentParser) -> None:
    """Add the ``ctid fit`` arguments to ``fit``."""
    fit.description = ('Estimate grey-box parameters from a CSV file with columns t,u,y (or '
                       'u,y with --ts).')
    fit.add_argument('csv', help='CSV file with a header line')
    fit.add_argument('--model', required=True, help="plant transfer function, e.g. 'K/(T*s+1)'")
    fit.add_argument('--controller', default=None,
                     help='known controller for closed-loop data (u is then the reference r)')
    fit.add_argument('--initial', type=parse_initial, default=None,
                     help='initial values NAME=VALUE,...; missing ones are found automatically')
    fit.add_argument('--bounds', type=parse_bounds, default=None,
                     help='bounds NAME=LOW:HIGH,... (either side may be empty)')
    fit.add_argument('--fix', type=parse_fixed, default=None, metavar='NAME=VALUE,...',
                     help='hold parameters at known values (not estimated; shown as fixed)')
    fit.add_argument('--delay-range', type=parse_interval, default=None, metavar='MIN:MAX',
                     help='search range of the dead time in seconds (default: from its bounds, '
                     'else automatic)')
    fit.add_argument('--ts', type=float, default=None,
                     help='sample time if there is no time column')
    fit.add_argument('--time', default=None, metavar='COLUMN',
                     help='time column in seconds (default t, else __time as PlotJuggler '
                     'exports it)')
    fit.add_argument('--input', action='append', default=None, metavar='[SIGNAL=]COLUMN',
                     help='input column (default u), as named in the file, e.g. /cmd/data; '
                     'repeat (or separate by commas) for the inputs of a model equation, which '
                     'names its signals after the columns or SIGNAL=')
    fit.add_argument('--output', default='y', metavar='[SIGNAL=]COLUMN',
                     help="output column (default y), e.g. '/joint_states/position[0]'")
    fit.add_argument('--estimate-range', type=parse_range, default=None, metavar='FIRST:LAST',
                     help='estimate on these samples only (1-based, inclusive)')
    fit.add_argument('--validate', default=None, metavar='CSV',
                     help='report the fit on this validation file (same columns)')
    fit.add_argument('--validate-range', type=parse_range, default=None, metavar='FIRST:LAST',
                     help='validation samples (of --validate, else of the estimation file)')
    fit.add_argument('--detrend', choices=('none', 'mean', 'initial'), default='none',
                     help='remove the operating point of every range: its means, or its first '
                     'samples (default none: the columns are deviations already)')
    fit.add_argument('--initial-state', choices=INITIAL_STATES, default='zero',
                     help='zero: data start at rest (default); estimate: fit the initial state')
    fit.add_argument('--output-offset', action='store_true',
                     help='estimate a constant offset of the output')
    fit.add_argument('--method', choices=METHODS, default='iv')
    fit.add_argument('--intersample', choices=INTERSAMPLE, default='zoh')
    fit.add_argument('--max-iterations', type=int, default=100)
    fit.add_argument('--json', action='store_true', help='print a JSON object instead of a table')
    fit.add_argument('--plot', type=Path, nargs='?', const=DEFAULT_PLOT, default=None,
                     metavar='PNG',
                     help='PNG of measured vs simulated output and the residual; also writes '
                     '<stem>_bode.png (the model over the response seen in the data) and '
                     '<stem>_residual.png (its auto- and cross-correlations). Without '
                     'a value: <csv name>_fit.png in the current directory')
    fit.add_argument('--units', type=parse_units, default=None, metavar='NAME=UNIT,...',
                     help="units of parameters and signals on the figures' axes, e.g. "
                     "'J=kg m^2,b=N m s/rad,u=N m,y=rad/s'")


def configure_replay(parser: argparse.ArgumentParser) -> None:
    """Add the ``ctid replay`` arguments to ``parser``."""
    parser.description = ('Estimate from a rosbag2 directory (sqlite3 or mcap storage), a '
                          'standalone .mcap file or a ROS 1 .bag file with the params file of '
                          'the live node: one '
                          'estimate over the selected span, or --sliding as the node would.')
    parser.add_argument('path',
                        help='rosbag2 directory, .mcap or ROS 1 .bag file (never modified)')
    parser.add_argument('--params-file', required=True,
                        help='ROS 2 params YAML of the node (e.g. config/open_loop_delay.yaml)')
    parser.add_argument('--node-name', default=DEFAULT_NODE_NAME,
                        help='node section of the params file, optionally with namespace '
                        '(/plant1/ctid_node); also names the --output topics')
    parser.add_argument('--start', type=float, default=None,
                        help='start of the span, seconds from the first message of the bag')
    parser.add_argument('--end', type=float, default=None,
                        help='end of the span, seconds from the first message of the bag')
    parser.add_argument('--sliding', action='store_true',
                        help='estimate every update_period on the last window seconds, as the '
                        'live node does (default: once over the whole span)')
    parser.add_argument('--output', type=Path, default=None,
                        help='new .mcap file for the estimates, on the topics of the live node, '
                        'with the replayed input and output messages')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace an existing --output file (never the input bag)')
    parser.add_argument('--plot', type=Path, nargs='?', const=DEFAULT_PLOT, default=None,
                        metavar='PNG',
                        help='PNG of measured vs simulated output; also writes <stem>_bode.png, '
                        '<stem>_residual.png and, with --sliding, <stem>_params.png. Without '
                        'a value: '
                        '<bag name>_replay.png in the current directory (next to the bag if '
                        'that is inside the bag). Never inside the input bag.')
    parser.add_argument('--json', action='store_true',
                        help='print the ctid fit --json object (a list of them with --sliding)')


def configure_node(parser: argparse.ArgumentParser) -> None:
    """Add the ``ctid node`` arguments; ROS arguments (``--ros-args ...``) pass through."""
    parser.add_argument('config', nargs='?', default=None,
                        help='params file or name of an example configuration (e.g. '
                        'open_loop_delay); same as --ros-args --params-file FILE')


def configure_record(parser: argparse.ArgumentParser) -> None:
    """Add the ``ctid record`` arguments to ``parser``."""
    parser.description = ('Record live topics into a standalone MCAP file, as ros2 bag record '
                          'does: types from the graph, messages as they come off the wire, at '
                          'their reception time. Stops after --duration or at Ctrl-C; the file '
                          'is closed with its index either way, and is a readable MCAP file '
                          'after every --flush-interval even if the recorder is killed.')
    parser.add_argument('output', type=Path, help='the .mcap file to write')
    parser.add_argument('topics', nargs='+', metavar='TOPIC',
                        help='topics to record (relative names are in the root namespace)')
    parser.add_argument('--duration', type=_positive, default=None, metavar='SECONDS',
                        help='stop after this many seconds (default: at Ctrl-C)')
    parser.add_argument('--wait', type=_positive, default=10.0, metavar='SECONDS',
                        help='how long to wait for every topic to have a publisher (default 10)')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace the output file if it exists')
    parser.add_argument('--flush-interval', type=_positive, default=1.0, metavar='SECONDS',
                        help='write what was received to disk at least this often: a killed '
                        'recorder loses at most about that long (default 1)')


def configure_echo(parser: argparse.ArgumentParser) -> None:
    """Add the ``ctid echo`` arguments to ``parser``."""
    parser.description = ("Print a running identification node's estimates as a live table: "
                          'one row per estimate, value ± standard deviation of every parameter, '
                          'the fit and the status of the node (what ros2 topic echo of its '
                          'estimate, estimate_std and /diagnostics topics would show).')
    parser.add_argument('--node', default='/' + DEFAULT_NODE_NAME, metavar='NAME',
                        help='the node, with its namespace if any (default /ctid_node; e.g. '
                        '/plant1/ctid_node)')
    parser.add_argument('--once', action='store_true',
                        help='print the latest estimate (one row, no status rows) and exit; '
                        'the node keeps its last estimate for subscribers that start later')
    parser.add_argument('--json', action='store_true',
                        help='one JSON object per line instead of the table')
    parser.add_argument('--timeout', type=_positive, default=None, metavar='SECONDS',
                        help='give up (exit 2) if no estimate arrives within this time '
                        '(default: wait)')


def configure_fleet(parser: argparse.ArgumentParser) -> None:
    """Add the ``ctid fleet`` arguments to ``parser``."""
    parser.description = ('Estimate on every bag of a fleet (rosbag2 directories, .mcap, '
                          '.db3 and ROS 1 .bag files), each bag (or each --span of a bag) a '
                          'task on Dask distributed; results and a fleet report as Parquet, '
                          'CSV and PNG in --results.')
    parser.add_argument('paths', nargs='+', metavar='PATH_OR_GLOB',
                        help="bags, directories holding bags, or globs ('fleet/**/*.mcap')")
    parser.add_argument('--params-file', required=True, help='ROS 2 params YAML of the node')
    parser.add_argument('--results', required=True, type=Path, metavar='DIR',
                        help='directory for bags.parquet, windows.parquet, robots.parquet, '
                        'robots.csv and the figures (created; finished bags or spans are '
                        'skipped)')
    parser.add_argument('--node-name', default=DEFAULT_NODE_NAME,
                        help='node section of the params file')
    parser.add_argument('--robot-from', default=None, metavar='PATTERN',
                        help="robot id (and other fields) from each bag's path relative to the "
                        "common root, e.g. '{robot}/{date}/*.mcap'; default the first "
                        'directory')
    parser.add_argument('--sliding', action='store_true',
                        help='estimate every update_period as the live node does; one row per '
                        'window in windows.parquet')
    parser.add_argument('--span', type=float, default=None, metavar='SECONDS',
                        help='cut each bag into consecutive spans of SECONDS of log time from '
                        'its first message, each span a task and a row of bags.parquet (column '
                        'span): the workers share a long bag and the rows trace the parameters '
                        'through it. At least the window of the params file; a last piece '
                        'shorter than the window is merged into the span before it')
    parser.add_argument('--workers', type=int, default=None, metavar='N',
                        help='worker processes of the local Dask cluster (default: the cores)')
    parser.add_argument('--scheduler', default=None, metavar='ADDRESS',
                        help='use an existing Dask cluster, e.g. tcp://host:8786')
    parser.add_argument('--threads', action='store_true',
                        help='run the local cluster in this process (threads, no worker '
                        'processes)')
    parser.add_argument('--rerun', action='store_true',
                        help='recompute bags (spans) whose results are already in --results')
    parser.add_argument('--no-plots', action='store_true', help='write no figures')


def parse_target(text: str) -> Dict[str, float]:
    """Parse ``tc=0.5`` (SIMC's closed-loop time constant) or ``ms=1.4`` (loop shaping)."""
    values = _values(text, '--target')
    if len(values) != 1 or not set(values) <= {'tc', 'ms'}:
        raise argparse.ArgumentTypeError(f'--target expects tc=SECONDS or ms=PEAK, got {text!r}')
    return values


def _add_record_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the arguments that select the record: a CSV file's columns or a bag's topics."""
    parser.add_argument('path', metavar='CSV|BAG',
                        help='CSV file with a header line, or a rosbag2 directory / .mcap file '
                        '(with --params-file); never modified')
    parser.add_argument('--input', action='append', default=None, metavar='[SIGNAL=]COLUMN',
                        help='CSV input column (default u)')
    parser.add_argument('--output', default='y', metavar='[SIGNAL=]COLUMN',
                        help='CSV output column (default y)')
    parser.add_argument('--ts', type=float, default=None,
                        help='CSV sample time if there is no time column')
    parser.add_argument('--time', default=None, metavar='COLUMN',
                        help='CSV time column in seconds (default t, else __time)')
    parser.add_argument('--params-file', default=None,
                        help='bag: the params YAML of the node (topics, fields, sample time; '
                        'its model is not used)')
    parser.add_argument('--node-name', default=DEFAULT_NODE_NAME,
                        help='bag: node section of the params file')
    parser.add_argument('--start', type=float, default=None,
                        help='bag: start of the span, seconds from its first message')
    parser.add_argument('--end', type=float, default=None,
                        help='bag: end of the span, seconds from its first message')
    parser.add_argument('--estimate-range', type=parse_range, default=None,
                        metavar='FIRST:LAST', help='use these samples only (1-based, inclusive)')
    parser.add_argument('--detrend', choices=('none', 'mean', 'initial'), default='none',
                        help='remove the operating point: means or first samples (default none)')
    parser.add_argument('--initial-state', choices=INITIAL_STATES, default='zero',
                        help='zero: data start at rest (default); estimate: fit the initial state')
    parser.add_argument('--output-offset', action='store_true',
                        help='estimate a constant offset of the output')
    parser.add_argument('--json', action='store_true', help='print JSON instead of a table')


def configure_compare(parser: argparse.ArgumentParser) -> None:
    """Add the ``ctid compare`` arguments to ``parser``."""
    parser.description = ('Fit every candidate model on the same record and rank them on what a '
                          'control engineer weighs: the fit on validation data, an information '
                          'criterion, consistency across the record, the residual, '
                          'identifiability; recommend the simplest adequate one and say why.')
    _add_record_arguments(parser)
    parser.add_argument('--model', action='append', required=True, metavar='MODEL',
                        help='a candidate transfer function; repeat, e.g. --model '
                        "'K*exp(-tau*s)/(T*s+1)' --model 'K*exp(-tau*s)/((T1*s+1)*(T2*s+1))'")
    parser.add_argument('--validate', default=None, metavar='CSV',
                        help='validation file (same columns); default: the last '
                        '--holdout of the record is held out')
    parser.add_argument('--holdout', type=float, default=0.3, metavar='FRACTION',
                        help='share of the record held out for validation without --validate '
                        '(default 0.3)')
    parser.add_argument('--plot', type=Path, nargs='?', const=DEFAULT_PLOT, default=None,
                        metavar='PNG',
                        help='side-by-side figure: validation outputs and Bode plots with '
                        'bands. Without a value: <record name>_compare.png')


def configure_tune(parser: argparse.ArgumentParser) -> None:
    """Add the ``ctid tune`` arguments to ``parser``."""
    parser.description = ('Identify the model on the record, design a PI or PID from it by a '
                          'stated method (SIMC, or loop shaping on the exact model with its '
                          'dead time), verify it on the model and across its uncertainty '
                          '(margins, Ms, bandwidth with 95 % bands) and give ros2_control '
                          'params.')
    _add_record_arguments(parser)
    parser.add_argument('--model', required=True, help='plant transfer function, e.g. '
                        "'K*exp(-tau*s)/((T1*s+1)*(T2*s+1))'")
    parser.add_argument('--controller', choices=CONTROLLERS, default='PI')
    parser.add_argument('--method', choices=DESIGN_METHODS, default='auto',
                        help='simc: Skogestad rules (lags + dead time); ms: largest integral '
                        'gain with Ms below the target; auto: simc where it applies')
    parser.add_argument('--target', type=parse_target, default=None, metavar='tc=S|ms=PEAK',
                        help="SIMC's closed-loop time constant (default: the effective dead "
                        'time) or the loop-shaping sensitivity peak (default 1.6)')
    parser.add_argument('--sample-time', type=_positive, default=None, metavar='SECONDS',
                        help='period of the digital controller: half of it is added to the dead '
                        'time (default: a continuous controller)')
    parser.add_argument('--initial', type=parse_initial, default=None,
                        help='initial values NAME=VALUE,... of the identification')
    parser.add_argument('--bounds', type=parse_bounds, default=None,
                        help='bounds NAME=LOW:HIGH,... of the identification')
    parser.add_argument('--delay-range', type=parse_interval, default=None, metavar='MIN:MAX',
                        help='search range of the dead time in seconds')
    parser.add_argument('--draws', type=int, default=200,
                        help='covariance draws for the bands (default 200, seeded)')
    parser.add_argument('--joint', default='joint1',
                        help='joint (dof) name of the ros2_control params (default joint1)')
    parser.add_argument('--params-out', type=Path, default=None, metavar='YAML',
                        help='write the ros2_control pid_controller params here (only when '
                        'everything succeeded)')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace an existing --params-out file')
    parser.add_argument('--plot', type=Path, nargs='?', const=DEFAULT_PLOT, default=None,
                        metavar='PNG',
                        help='step response on the model with its band over covariance draws, '
                        'and the loop Bode plot. Without a value: <record name>_tune.png')
