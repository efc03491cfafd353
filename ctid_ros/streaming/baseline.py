"""
The baseline of the change alarm: what the plant's parameters were, and how well known.

A :class:`Baseline` is a parameter vector with its covariance. It comes from one of three
places, in this order of precedence (:func:`configured_baseline`):

1. captured from the running estimates (``~/capture_baseline``,
   :meth:`ctid_ros.streaming.alarm.ChangeDetector.capture`): the average of the last
   ``baseline_windows`` windows, with the covariance of that average
   (:func:`average_windows`, which accounts for the overlap of the windows), written to
   ``baseline_file`` when one is configured;
2. ``baseline_file``, when it exists: a params file holding ``baseline`` and
   ``baseline_std`` mappings, as :func:`write_baseline_file` writes it, read at start-up so
   that a restart keeps the captured baseline;
3. the params file itself: ``baseline: {J: 0.05, b: 0.2}`` with an optional
   ``baseline_std: {J: 0.001}`` (ROS flattens them to ``baseline.J``; see
   :meth:`~ctid_ros.streaming.config.IdentificationConfig.per_parameter_values`). A value
   without a standard deviation is exact (a data-sheet value the user vouches for).

A partial baseline (some parameters only) is fine: only those parameters are watched.
"""

from dataclasses import dataclass
import math
import os
from pathlib import Path
from typing import Optional, Sequence, Tuple

from ctid_ros.core.limits import MAX_PARAMS_BYTES, read_limited
from ctid_ros.errors import ConfigError, DataError
from ctid_ros.streaming.config import IdentificationConfig, per_parameter_name
from ctid_ros.streaming.contract import DEFAULT_NODE_NAME, NANOSECONDS
from ctid_ros.streaming.params_file import node_parameters, parse_yaml
import numpy as np

__all__ = ['BASELINE_PREFIXES', 'Baseline', 'average_windows', 'configured_baseline',
           'overlap', 'read_baseline_file', 'write_baseline_file']

# The per-parameter names a baseline file may hold.
BASELINE_PREFIXES = ('baseline', 'baseline_std')


def overlap(separation_s: float, window_s: float) -> float:
    """
    Return the correlation of the estimates of two windows ``separation_s`` apart.

    Windows of ``window_s`` fitted seconds share ``window_s - separation_s`` of their data;
    with information spread evenly over the data the correlation of their estimation errors is
    that shared fraction, ``max(0, 1 - separation/window)`` (docs/algorithm.md, section 17).
    """
    if window_s <= 0.0:
        return 0.0
    return max(0.0, 1.0 - abs(separation_s) / window_s)


@dataclass(frozen=True)
class Baseline:
    """
    Reference values of some parameters with their covariance.

    Attributes
    ----------
    names : tuple of str
        Parameters the baseline covers, in publishing order.
    values : ndarray
        Their baseline values.
    covariance : ndarray
        Covariance of ``values`` (n x n); zero for exact values.
    source : str
        Where it came from, for people (``'params file'``, ``'baseline_file /x.yaml'``,
        ``'captured from 5 windows'``).

    """

    names: Tuple[str, ...]
    values: np.ndarray
    covariance: np.ndarray
    source: str

    def __post_init__(self) -> None:
        values = np.asarray(self.values, dtype=float).reshape(-1)
        covariance = np.asarray(self.covariance, dtype=float).reshape(values.size, values.size)
        if len(self.names) != values.size or len(set(self.names)) != values.size:
            raise DataError(f'a baseline needs one value per distinct name, got names '
                            f'{list(self.names)} and {values.size} values')
        if not (np.all(np.isfinite(values)) and np.all(np.isfinite(covariance))):
            raise DataError('baseline values and covariance must be finite')
        object.__setattr__(self, 'names', tuple(self.names))
        object.__setattr__(self, 'values', values)
        object.__setattr__(self, 'covariance', 0.5 * (covariance + covariance.T))

    @property
    def stds(self) -> np.ndarray:
        """Return the standard deviations of the baseline values."""
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    def value(self, name: str) -> float:
        """Return the baseline value of ``name``."""
        return float(self.values[self.names.index(name)])

    @classmethod
    def from_config(cls, config: IdentificationConfig, source: str = 'params file'
                    ) -> Optional['Baseline']:
        """Return the ``baseline.<name>`` values of ``config`` (None if there are none)."""
        values = config.per_parameter_values('baseline')
        if not values:
            return None
        stds = config.per_parameter_values('baseline_std')
        names = tuple(values)
        return cls(names, np.array([values[name] for name in names]),
                   np.diag([stds.get(name, 0.0) ** 2 for name in names]), source)

    def describe(self) -> str:
        """Return ``'J = 0.05 +- 0.0001, b = 0.2'`` (exact values without a std)."""
        return ', '.join(f'{name} = {value:.6g}' + (f' +- {std:.2g}' if std > 0 else '')
                         for name, value, std in zip(self.names, self.values, self.stds))


def average_windows(names: Sequence[str], end_ns: Sequence[int], values: np.ndarray,
                    covariances: np.ndarray, window_s: float, source: str) -> Baseline:
    """
    Average the estimates of successive windows into a :class:`Baseline`.

    The covariance of the mean of ``n`` estimates is ``(1/n^2) sum_ij C_ij`` with
    ``C_ij = overlap(t_i - t_j) (P_i + P_j)/2``: estimates of overlapping windows share data,
    so their average is less precise than ``n`` independent ones would make it
    (:func:`overlap`; windows ending further apart than ``window_s`` are independent).

    Parameters
    ----------
    names : sequence of str
        Parameter names (columns).
    end_ns : sequence of int
        End of each window (ns).
    values : ndarray, shape (n, p)
        Estimates.
    covariances : ndarray, shape (n, p, p)
        Their covariances.
    window_s : float
        Fitted seconds per window.
    source : str
        Description for :attr:`Baseline.source`.

    """
    values = np.asarray(values, dtype=float)
    covariances = np.asarray(covariances, dtype=float)
    count = values.shape[0]
    times = np.asarray(end_ns, dtype=np.int64)
    covariance = np.zeros(covariances.shape[1:])
    for i in range(count):
        for j in range(count):
            weight = overlap((times[i] - times[j]) / NANOSECONDS, window_s)
            if weight:
                covariance += weight * 0.5 * (covariances[i] + covariances[j])
    return Baseline(tuple(names), values.mean(axis=0), covariance / count ** 2, source)


def read_baseline_file(path: str, names: Sequence[str],
                       node_name: str = DEFAULT_NODE_NAME) -> Optional[Baseline]:
    """
    Read a baseline file written by :func:`write_baseline_file` (or by hand).

    Parameters
    ----------
    path : str
        The file (``~`` is expanded). A missing file is no error: it returns None (nothing has
        been captured yet).
    names : sequence of str
        The model's parameters; the file may cover some of them.
    node_name : str
        Section of the file to read (as in a params file); a fully qualified name falls back
        to its base name (a file keyed ``ctid_node:``).

    Raises
    ------
    ConfigError
        If the file cannot be read or parsed, or holds anything but ``baseline`` and
        ``baseline_std`` values of the model's parameters (the message names the file).

    """
    file = Path(path).expanduser()
    if not file.exists():
        return None
    source = f'baseline_file {path}'
    content = read_limited(file, MAX_PARAMS_BYTES, 'baseline_file', ConfigError)
    document = parse_yaml(content, source)
    try:
        values = node_parameters(document, node_name, source=source)
    except ConfigError:
        # A hand-written file keyed by the plain node name serves the node in any namespace.
        base = node_name.rpartition('/')[2]
        if base == node_name:
            raise
        values = node_parameters(document, base, source=source)
    allowed = {per_parameter_name(prefix, name) for prefix in BASELINE_PREFIXES for name in names}
    other = sorted(set(values) - allowed)
    if other:
        raise ConfigError(f'{source}: only baseline and baseline_std of the parameters '
                          f'{", ".join(names)} belong in a baseline file; found '
                          f'{", ".join(other)}')
    numbers = {}
    for key, value in values.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                not math.isfinite(value):
            raise ConfigError(f'{source}: {key} must be a finite number, got {value!r}')
        numbers[key] = float(value)
    missing = [key for key in numbers if key.startswith('baseline_std.')
               and 'baseline.' + key.partition('.')[2] not in numbers]
    if missing or any(value < 0 for key, value in numbers.items()
                      if key.startswith('baseline_std.')):
        raise ConfigError(f'{source}: every baseline_std needs its baseline and must be >= 0')
    chosen = [name for name in names if f'baseline.{name}' in numbers]
    if not chosen:
        raise ConfigError(f'{source} holds no baseline value')
    return Baseline(tuple(chosen), np.array([numbers[f'baseline.{name}'] for name in chosen]),
                    np.diag([numbers.get(f'baseline_std.{name}', 0.0) ** 2 for name in chosen]),
                    source)


def write_baseline_file(path: str, baseline: Baseline, node_name: str, note: str) -> Path:
    """
    Write ``baseline`` as a params file a user can keep as ``baseline_file`` or paste from.

    The file holds the node's section with ``baseline`` and ``baseline_std`` mappings (every
    digit of each value) under a comment saying where the values come from (``note``). It is
    written next to its final name and renamed over it, so a crash never leaves half a file.

    Raises
    ------
    ConfigError
        If the directory does not exist or the file cannot be written.

    """
    file = Path(path).expanduser()
    if not file.parent.is_dir():
        raise ConfigError(f'baseline_file {path}: directory {file.parent} does not exist')
    comment = '\n'.join('# ' + line for line in note.splitlines())
    lines = [comment, '# Keep it as the baseline_file of the node, or paste the two mappings into '
             'its params file.', f'{node_name}:', '  ros__parameters:', '    baseline:']
    lines += [f'      {name}: {value!r}' for name, value in
              zip(baseline.names, baseline.values.tolist())]
    lines.append('    baseline_std:')
    lines += [f'      {name}: {std!r}'
              for name, std in zip(baseline.names, baseline.stds.tolist())]
    temporary = file.with_name(f'.{file.name}.{os.getpid()}.tmp')
    try:
        temporary.write_text('\n'.join(lines) + '\n', encoding='utf-8')
        os.replace(temporary, file)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        raise ConfigError(f'baseline_file {path}: cannot write it: '
                          f'{error.strerror or error}') from None
    return file


def configured_baseline(config: IdentificationConfig, node_name: str = DEFAULT_NODE_NAME
                        ) -> Tuple[Optional[Baseline], str]:
    """
    Return the baseline a node starting with ``config`` uses, and a note on where it is from.

    ``baseline_file`` when it exists, else the ``baseline.<name>`` parameters, else None.

    Raises
    ------
    ConfigError
        If ``baseline_file`` exists but cannot be used.

    """
    if config.baseline_file:
        found = read_baseline_file(config.baseline_file, config.names, node_name)
        if found is not None:
            return found, f'read from {config.baseline_file}'
    baseline = Baseline.from_config(config)
    if baseline is not None:
        return baseline, 'from the params file'
    if config.baseline_file:
        return None, f'no baseline yet ({config.baseline_file} does not exist)'
    return None, 'no baseline configured'
