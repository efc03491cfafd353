"""
When a stream was sampled, and the grid a window is resampled onto.

A periodic publisher stamps its messages on a lattice ``a + n * P``: jitter moves single stamps
a little, dropped messages leave indices out, a publisher clock whose rate differs from
nominal makes ``P`` differ from its nominal value, a publisher whose timer fires late sends
the samples that came due in a burst, stamped late (DDS source times). :func:`fit_lattice`
fits such a lattice to the stamps of a window: instants by rounding, a burst taking the free
instants before it (:func:`assign_instants`), extended from the newest samples backwards four
times at a time (so neither drift nor drops can slip an index), then a least-squares line
through the stamps within a quarter period of it. A stream is *periodic* when at least
``PERIODIC_INLIERS`` of its stamps lie that close (or, among ``BURSTY_STAMPS`` stamps or more,
are late in a burst while ``PERIODIC_ON_TIME`` lie that close) and the robust spread of those
(the jitter) is below ``PERIODIC_JITTER`` of the period (half that for fewer than
``MANY_STAMPS`` stamps).

:func:`plan_grid` puts the grid of a window on the instants the input was held at:

* the grid follows the input's lattice: its step is the input's period times ``m`` when
  ``sample_time`` is ``m`` (whole) input periods, with the phase of the input's changes among the
  ``m`` candidates; or the period divided by ``q`` when ``sample_time`` is ``1/q`` of it;
* if the output is sampled more slowly than that grid (a ``sample_time`` finer than the data's
  own rate) and the input is held over whole output periods, the grid is the output's own
  period instead: every instant then carries a measurement, as the estimator's standard
  deviations assume;
* an output sampled periodically at the grid step (or a whole fraction of it) is taken as
  measured: its own samples, each ``skew`` after its grid instant (``Data.output_skew``);
  any other output is interpolated linearly at the grid instants;
* without a periodic input, or with a ``sample_time`` that is no whole multiple or fraction of
  the input's period, the grid is today's absolute one, the multiples of ``sample_time``, and
  the plan says so.

All times are integer nanoseconds or, relative to an integer reference stamp, float
nanoseconds (a float cannot hold an absolute stamp to the nanosecond).
"""

from dataclasses import dataclass
import math
from typing import Optional, Sequence, Tuple

import numpy as np

__all__ = ['GridPlan', 'Lattice', 'assign_instants', 'fit_lattice', 'plan_grid',
           'stream_lattice']

# A stamp within this fraction of a period from the lattice belongs to it.
LATTICE_SLACK = 0.25
# Fraction of the stamps on the lattice, and largest jitter (fraction of the period), for a
# periodic stream; below MANY_STAMPS stamps the jitter must be half as large (with a free
# period and phase, a few dozen scattered stamps fit a lattice with a jitter of 7-12 % now
# and then; from 64 on, never in 4800 trials).
PERIODIC_INLIERS = 0.8
PERIODIC_JITTER = 0.1
MANY_STAMPS = 64
# From BURSTY_STAMPS stamps on, stamps late in bursts (published after a late timer) count
# as on the lattice too, but at least PERIODIC_ON_TIME of them must lie within a quarter
# period of their instants (no false lattice in 4500 scattered sets of 150 to 3000 stamps).
BURSTY_STAMPS = 256
PERIODIC_ON_TIME = 0.5
# An output whose jitter is below this fraction of its period is taken at its own samples
# (its stamps jitter, its sampling does not); a more irregular one is interpolated.
OWN_SAMPLES_JITTER = 0.05
# A stamp may be this early for its instant (fraction of the period) even without jitter.
MIN_EARLY = 0.02
# Relative tolerance of "a whole multiple" between periods and sample_time (clock drift and
# the estimation error of the periods are far below it).
RATIO_TOLERANCE = 0.02
# An output skew closer than this fraction of the grid step to 0 (or to a whole period) is 0.
SKEW_SNAP = 1e-3
# Fewest stamps a lattice is fitted to (with a free period and phase 16 scattered stamps fit
# one with a jitter of 4 % now and then), and fewest stamps per period of a periodic stream.
MIN_STAMPS = 24
MAX_SPARSITY = 4
# Robust standard deviation from the median absolute deviation (normal distribution).
_MAD_TO_STD = 1.4826


@dataclass(frozen=True)
class Lattice:
    """
    The instants ``reference + origin + n * period`` (ns) fitted to a stream's stamps.

    Attributes
    ----------
    reference : int
        The newest fitted stamp; ``origin`` and the stamps' offsets are relative to it.
    origin : float
        Offset (ns) of the lattice instant ``n = 0`` from ``reference`` (near zero).
    period : float
        Period in nanoseconds, as measured by the stamps.
    jitter : float
        Robust standard deviation (ns) of the stamps about their instants.
    inliers : float
        Fraction of the stamps within a quarter period of their instants.
    count : int
        Number of stamps fitted.
    centre : float
        Mean offset (ns) of the fitted stamps from ``reference``: where the fitted line is
        most precise.
    late : float
        Fraction of the stamps more than a quarter period after their instants, in bursts of
        messages published late (:func:`assign_instants`).

    """

    reference: int
    origin: float
    period: float
    jitter: float
    inliers: float
    count: int
    centre: float = 0.0
    late: float = 0.0

    @property
    def periodic(self) -> bool:
        """Return True if the stamps follow the lattice (see the module notes)."""
        jitter = PERIODIC_JITTER if self.count >= MANY_STAMPS else PERIODIC_JITTER / 2
        # Late bursts count only among many stamps: a few dozen scattered stamps fit a lattice
        # with some "late" ones all too easily.
        late = self.late if self.count >= BURSTY_STAMPS else 0.0
        return (self.inliers + late >= PERIODIC_INLIERS and
                self.inliers >= PERIODIC_ON_TIME and self.jitter <= jitter * self.period)

    @property
    def early(self) -> float:
        """Return how many periods early a stamp may be for its instant: four jitters."""
        return min(LATTICE_SLACK, max(4.0 * self.jitter / self.period, MIN_EARLY))

    def offsets(self, stamps: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Return the instant of every stamp (:func:`assign_instants`) and its offset (ns)."""
        relative = (np.asarray(stamps, dtype=np.int64) - self.reference).astype(float)
        index, _ = assign_instants((relative - self.origin) / self.period, self.early)
        return index, relative - self.origin - index * self.period


def assign_instants(positions: np.ndarray, early: float = LATTICE_SLACK
                    ) -> Tuple[np.ndarray, np.ndarray]:
    """
    Give increasing stamps their lattice instants, one stamp per instant.

    Parameters
    ----------
    positions : ndarray
        Non-decreasing positions of the stamps on the lattice, in periods
        (``(stamp - origin) / period``).
    early : float
        How early (in periods) a stamp may be for its instant: a few jitters once they are
        known (a stamp earlier than that is late for the instant before).

    Returns
    -------
    (index, assigned) : (ndarray of int, ndarray of bool)
        The instant of each stamp, and whether it got one.

    Notes
    -----
    Each stamp goes to the latest instant at most ``early`` after it (jitter may stamp a
    sample a little early, a publisher cannot send it much before its instant, but late by
    any amount). Several stamps on one instant are a burst of messages published late (a
    publisher's timer that fired late sends the samples that came due together, their stamps
    the publishing time): the latest keeps the instant, the ones before it take the free
    instants just before it, in order, as many as are free; a stamp left without one is not
    assigned (two messages for one instant).

    """
    index = np.floor(positions + early).astype(np.int64)
    count = index.size
    if count == 0:
        return index, np.zeros(0, dtype=bool)
    steps = np.diff(index)
    if np.all(steps > 0):
        # One stamp per instant, the usual case: each keeps its own (what the rule below
        # gives, without its per-stamp bookkeeping).
        return index, np.ones(count, dtype=bool)
    starts = np.flatnonzero(np.concatenate(([True], steps != 0)))
    ends = np.append(starts[1:], count)
    values = index[starts]
    free = np.concatenate(([count], np.diff(values)))
    group = np.repeat(np.arange(starts.size), ends - starts)
    from_end = ends[group] - 1 - np.arange(count)
    return values[group] - from_end, from_end < free[group]


def _line(index: np.ndarray, relative: np.ndarray) -> Tuple[float, float]:
    """Least-squares ``relative = origin + period * index``; return (origin, period)."""
    mean_index, mean_value = index.mean(), relative.mean()
    centred = index - mean_index
    # Sums, not BLAS dot products: threaded BLAS spends milliseconds waking its threads.
    period = float(np.sum(centred * (relative - mean_value)) / np.sum(centred * centred))
    return float(mean_value - period * mean_index), period


def _phase(relative: np.ndarray, period: float) -> float:
    """Return the circular mean of ``relative`` modulo ``period``, in ``(-period/2, period/2]``."""
    return float(np.angle(np.mean(np.exp(2j * np.pi * relative / period)))) * period / (
        2 * np.pi)


def fit_lattice(stamps: np.ndarray, base: float) -> Optional[Lattice]:
    """
    Fit a lattice to increasing stamps, starting from the period ``base`` (ns).

    The newest 32 stamps are fitted first (the phase their circular mean), then four times as
    many at a time; at every stage the stamps get their instants from :func:`assign_instants`
    and the line is fitted to those within a quarter period of it. Returns None if no lattice
    could be fitted (too few stamps, a degenerate fit).
    """
    stamps = np.asarray(stamps, dtype=np.int64)
    count = stamps.size
    if count < MIN_STAMPS or not base > 0:
        return None
    reference = int(stamps[-1])
    relative = (stamps - reference).astype(float)
    period = float(base)
    size = min(count, 32)
    origin = _phase(relative[count - size:], period)
    while True:
        part = relative[count - size:]
        # Three passes while cheap, two on many stamps (the start is good by then).
        for _ in range(3 if size <= 512 else 2):
            index, assigned = assign_instants((part - origin) / period)
            keep = assigned & (np.abs(part - origin - index * period) <
                               LATTICE_SLACK * period)
            if np.count_nonzero(keep) < 2 or np.ptp(index[keep]) == 0:
                return None
            origin, period = _line(index[keep], part[keep])
            if not period > 0:
                return None
        if size == count:
            break
        size = min(count, 4 * size)
    index, assigned = assign_instants((relative - origin) / period)
    residual = relative - origin - index * period
    on_time = assigned & (np.abs(residual) < LATTICE_SLACK * period)
    late = assigned & (residual >= LATTICE_SLACK * period)
    middle = float(np.median(residual[on_time])) if np.any(on_time) else 0.0
    jitter = _MAD_TO_STD * float(np.median(np.abs(residual[on_time] - middle))) \
        if np.any(on_time) else float(period)
    # Refit on the stamps within five jitters (at least 0.1 % of a period): outliers out.
    close = on_time & (np.abs(residual - middle) <= max(5.0 * jitter, 1e-3 * period))
    if np.count_nonzero(close) >= 2 and np.ptp(index[close]) > 0:
        origin, period = _line(index[close], relative[close])
    return Lattice(reference, origin, period, jitter,
                   float(np.count_nonzero(on_time)) / count, count,
                   float(relative[close].mean()) if np.any(close) else 0.0,
                   float(np.count_nonzero(late)) / count)


def stream_lattice(stamps: np.ndarray) -> Optional[Lattice]:
    """
    Return the lattice of a stream's stamps if it is periodic, else None.

    The period is tried as the median interval, then as the median of the shortest intervals
    (more than half of the messages dropped); the first periodic fit wins. A stream with fewer
    than one stamp per ``MAX_SPARSITY`` periods is not periodic: with a free period, a few
    scattered stamps would fit some lattice by chance.
    """
    stamps = np.asarray(stamps, dtype=np.int64)
    if stamps.size < MIN_STAMPS:
        return None
    steps = np.diff(stamps).astype(float)
    steps = steps[steps > 0]
    if steps.size < MIN_STAMPS - 1:
        return None
    median = float(np.median(steps))
    for attempt in range(2):
        if attempt == 0:
            base = median
        else:
            base = float(np.median(steps[steps <= 1.5 * float(np.quantile(steps, 0.1))]))
            if abs(base - median) <= RATIO_TOLERANCE * median:
                break
        lattice = fit_lattice(stamps, base) if base > 0 else None
        if lattice is not None and lattice.periodic and \
                float(stamps[-1] - stamps[0]) <= MAX_SPARSITY * lattice.count * lattice.period:
            return lattice
    return None


@dataclass(frozen=True)
class GridPlan:
    """
    The grid of one window: instants ``reference + origin + k * step`` (ns).

    Attributes
    ----------
    reference : int
        Integer stamp the instants are counted from.
    origin : float
        Offset (ns) of instant 0 from ``reference``.
    step : float
        Grid step in nanoseconds (``Data.ts`` times 1e9).
    follows_input : bool
        True if the instants are the input's hold instants; False for the absolute grid.
    input_period : float or None
        The input's period (ns) if it is periodic: its samples are then assigned to the
        nearest lattice instant, not to the grid instant after them.
    skew : float
        Output skew (ns): the output sample of grid instant ``k`` is taken ``skew`` after it.
    output_period : float or None
        The output's period (ns) when its own samples are taken; None: interpolated.
    tolerance : float
        Slack (ns) at the ends of a requested range: a few jitters of the stamps; also how
        early a stamp may be for its instant.
    warnings : tuple of str
        What a user should know (the dead time or the standard deviations may suffer).
    description : str
        How the grid was chosen, for the diagnostics.
    output_lattice : Lattice or None
        The output's own lattice when its own samples are taken: each sample belongs to the
        grid instant nearest its lattice instant minus ``skew``, so that a clock drifting
        against the input's (a command stamped by a free-running timer) moves no sample to
        another instant.

    """

    reference: int
    origin: float
    step: float
    follows_input: bool
    input_period: Optional[float]
    skew: float
    output_period: Optional[float]
    tolerance: float
    warnings: Tuple[str, ...]
    description: str
    output_lattice: Optional[Lattice] = None

    def instants(self, first: int, count: int) -> np.ndarray:
        """Return ``count`` successive grid instants, integer ns, from index ``first`` on."""
        index = np.arange(first, first + count, dtype=float)
        return self.reference + np.round(self.origin + index * self.step).astype(np.int64)

    def index_at_or_before(self, stamp: int) -> int:
        """Return the index of the last grid instant at or before ``stamp``."""
        position = (float(stamp - self.reference) - self.origin) / self.step
        index = math.floor(position)
        # Round-off: an instant equal to the stamp counts as at or before it.
        if self.instants(index + 1, 1)[0] <= stamp:
            index += 1
        elif self.instants(index, 1)[0] > stamp:
            index -= 1
        return index


def _seconds(nanoseconds: float) -> str:
    return f'{nanoseconds / 1e9:.6g} s'


def _whole(ratio: float) -> Optional[int]:
    """Return the whole number ``ratio`` is within RATIO_TOLERANCE of, else None."""
    whole = round(ratio)
    return whole if whole >= 1 and abs(ratio - whole) <= RATIO_TOLERANCE * whole else None


def _changes(lattice: Lattice, stamps: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Return the lattice indices at which the input's value differs from the one before."""
    index, _ = lattice.offsets(stamps)
    values = np.asarray(values, dtype=float)
    changed = np.any(np.diff(values.reshape(values.shape[0], -1), axis=0) != 0, axis=1)
    return index[1:][changed]


def _absolute(sample_time_ns: int, stamps: np.ndarray, why: str) -> GridPlan:
    reference = int(stamps[-1]) // sample_time_ns * sample_time_ns
    return GridPlan(reference, 0.0, float(sample_time_ns), False, None, 0.0, None, 0.0, (why,),
                    'multiples of sample_time (absolute)')


def plan_grid(input_stamps: np.ndarray, input_values: np.ndarray, output_stamps: np.ndarray,
              sample_time_ns: int, names: Sequence[str] = ('input', 'output')) -> GridPlan:
    """
    Choose the grid of a window from the stamps of its input and output.

    Parameters
    ----------
    input_stamps, output_stamps : ndarray of int
        Increasing stamps (ns) of the samples in and around the window.
    input_values : ndarray
        The input values at ``input_stamps`` (a row per stamp for several inputs): the phase
        of its changes picks the grid instants when ``sample_time`` spans several periods.
    sample_time_ns : int
        The configured grid step.
    names : (str, str)
        Stream labels for the messages.

    Returns
    -------
    GridPlan

    """
    input_name, output_name = names
    h0 = float(sample_time_ns)
    source = stream_lattice(input_stamps)
    output = stream_lattice(output_stamps)
    if source is None:
        plan = _absolute(sample_time_ns, input_stamps, (
            f'{input_name} is not periodic (its stamps lie on no lattice): grid at multiples '
            'of sample_time, so the dead time is resolved to one sample only'))
        return _with_output(plan, output, output_stamps, output_name, None)
    warnings = []
    period = source.period
    origin, step = source.origin, period
    multiple, fraction = _whole(h0 / period), _whole(period / h0)
    if h0 > period * (1 - RATIO_TOLERANCE) and multiple is not None:
        step = multiple * period
        if multiple > 1:
            origin, note = _held_phase(source, input_stamps, input_values, multiple,
                                       sample_time_ns, input_name)
            warnings.extend(note)
    elif fraction is not None:
        step = period / fraction
    else:
        plan = _absolute(sample_time_ns, input_stamps, (
            f'sample_time {_seconds(h0)} is no whole multiple or fraction of the period of '
            f'{input_name} ({_seconds(period)}): grid at multiples of sample_time, so the dead '
            'time is resolved to one sample only'))
        return _with_output(plan, output, output_stamps, output_name, source)
    description = f'{input_name} instants (period {_seconds(period)}'
    if output is not None and output.period > 1.5 * step:
        # A grid finer than the output's own rate: the measurements are what counts.
        held = _whole(period / output.period)
        if held is not None:
            step = period / held
            warnings.append(
                f"sample_time {_seconds(h0)} is finer than the data's own rate ({output_name} "
                f'every {_seconds(output.period)}): estimated on the {_seconds(step)} grid of '
                'the measurements, since interpolated samples carry no information')
        else:
            warnings.append(
                f'sample_time {_seconds(h0)} is finer than the rate of {output_name} (every '
                f'{_seconds(output.period)}) and {input_name} changes between its samples: the '
                'output is interpolated, so the standard deviations are too small')
    plan = GridPlan(source.reference, origin, step, True, period, 0.0, None,
                    4.0 * source.jitter + 1.0, tuple(warnings),
                    description + f', jitter {_seconds(source.jitter)})')
    return _with_output(plan, output, output_stamps, output_name, source)


def _held_phase(source: Lattice, stamps: np.ndarray, values: np.ndarray, multiple: int,
                sample_time_ns: int, name: str) -> Tuple[float, Tuple[str, ...]]:
    """
    Pick which of ``multiple`` consecutive input instants the grid goes through.

    The one at which the input changes (a command updated every ``sample_time`` but published
    more often); if the changes spread over several, the one nearest the absolute grid (so
    successive windows agree) and a warning.
    """
    changes = _changes(source, stamps, values)
    counts = np.bincount(np.mod(changes, multiple).astype(int), minlength=multiple)
    # Instant n of the lattice, relative to the absolute grid of multiples of sample_time.
    phases = [math.remainder(float(source.reference % sample_time_ns) + source.origin +
                             residue * source.period, sample_time_ns)
              for residue in range(multiple)]
    nearest = int(np.argmin(np.abs(phases)))
    if counts.sum() == 0:
        return source.origin + nearest * source.period, ()
    best = int(np.argmax(counts))
    if counts[best] >= 0.9 * counts.sum():
        return source.origin + best * source.period, ()
    return source.origin + nearest * source.period, (
        f'{name} changes between the grid instants (sample_time is {multiple} of its periods '
        f'of {_seconds(source.period)}): those changes are held to the next instant, which '
        'biases the dead time; set sample_time to the period',)


def _with_output(plan: GridPlan, output: Optional[Lattice], stamps: np.ndarray, name: str,
                 source: Optional[Lattice]) -> GridPlan:
    """Add the output's treatment to ``plan``: its own samples and skew, or interpolation."""
    warnings = list(plan.warnings)
    description = plan.description
    own = None
    if output is not None and output.jitter <= OWN_SAMPLES_JITTER * output.period:
        own = _whole(plan.step / output.period)
    if own is None:
        if output is not None and output.period > 1.5 * plan.step and not plan.follows_input:
            warnings.append(
                f'sample_time {_seconds(plan.step)} is finer than the rate of {name} (every '
                f'{_seconds(output.period)}): the output is interpolated, so the standard '
                'deviations are too small')
        why = 'not periodic' if output is None else f'period {_seconds(output.period)}'
        return GridPlan(plan.reference, plan.origin, plan.step, plan.follows_input,
                        plan.input_period, 0.0, None, plan.tolerance, tuple(warnings),
                        description + f'; {name} interpolated ({why})')
    # The output's instant at the centre of its stamps (where its fitted line is most
    # precise), and its offset from the grid instant before it, modulo its period.
    shift = float(output.reference - plan.reference)
    centre = output.origin + round((output.centre - output.origin) / output.period) * \
        output.period
    before = plan.origin + math.floor((shift + centre - plan.origin) / plan.step) * plan.step
    offset = shift + centre - before
    skew = offset - math.floor(offset / output.period) * output.period
    if min(skew, output.period - skew) < SKEW_SNAP * plan.step:
        skew = 0.0
    tolerance = max(plan.tolerance, 4.0 * output.jitter + 1.0)
    return GridPlan(plan.reference, plan.origin, plan.step, plan.follows_input,
                    plan.input_period, skew, output.period, tolerance, tuple(warnings),
                    description + f'; {name} at its own samples, {_seconds(skew)} after the '
                    'grid instants', output)
