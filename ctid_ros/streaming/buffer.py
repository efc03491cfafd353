"""
Timestamped samples of asynchronous input/output streams, resampled onto a uniform grid.

A live node appends every received message to a :class:`SampleBuffer` (per message, from
subscription callbacks) and periodically takes a :meth:`SampleBuffer.window`; an offline replay
either does exactly the same while reading a bag, or calls :func:`resample` on complete arrays,
which fills a buffer through the same :meth:`SampleBuffer.add_input`/``add_output`` code and
takes the same window. Identical samples therefore give identical :class:`ctid_ros.Data`.

Admission rules, per stream (stamps are integer nanoseconds):

* a non-finite value is rejected and counted;
* a stamp equal to one already held is a duplicate: the first sample is kept;
* a stamp older than the stream's newest one is inserted in order if it is within the
  reorder horizon of it, otherwise it is dropped and counted as late;
* beyond ``capacity`` samples the oldest are evicted (counted).

Resampling onto the grid ``t_k = k * sample_time`` (absolute time, so successive windows share
instants):

* input, zero-order hold: the value of the last input sample at or before ``t_k``;
* output, linear interpolation between the samples that bracket ``t_k``.

A stream is missing where two consecutive samples are more than ``max_gap`` apart (the whole
interval between them) and after its newest sample: the output beyond it, the input beyond it
plus ``max_gap`` (a held command stays valid that long). Nothing is ever interpolated or held
across a missing interval: the window is split into contiguous segments and the *latest*
segment of at least ``min_length`` seconds is returned, since a live estimator wants the most
recent behaviour; :class:`Window` reports all segments and the gaps that split them.
"""

from dataclasses import dataclass
import enum
import math
import operator
import threading
from typing import Optional, Tuple

from ctid_ros.core.data import Data
from ctid_ros.errors import DataError
from ctid_ros.streaming.contract import NANOSECONDS
import numpy as np

__all__ = ['Admission', 'BufferStats', 'Gap', 'INPUT', 'OUTPUT', 'SampleBuffer', 'StreamStats',
           'Window', 'capacity_for', 'resample']

INPUT = 'input'
OUTPUT = 'output'


def _to_ns(seconds: float, name: str) -> int:
    value = float(seconds)
    if not math.isfinite(value) or value < 0:
        raise DataError(f'{name} must be a finite, non-negative number of seconds, '
                        f'got {seconds!r}')
    return round(value * NANOSECONDS)


def capacity_for(span: float, rate: float, margin: float = 2.0) -> int:
    """
    Size a stream's ring buffer to hold ``span`` seconds of messages arriving at ``rate`` Hz.

    Parameters
    ----------
    span : float
        Seconds of history needed: the window plus ``max_gap`` and the reorder horizon.
    rate : float
        Highest expected message rate in Hz.
    margin : float
        Safety factor against bursts and rate changes.

    Returns
    -------
    int
        Number of samples, at least 16.

    """
    if not (span > 0 and rate > 0 and margin >= 1):
        raise DataError(f'capacity_for needs span > 0, rate > 0 and margin >= 1, got '
                        f'{span}, {rate}, {margin}')
    return max(16, math.ceil(span * rate * margin))


class Admission(enum.Enum):
    """What happened to one appended sample."""

    ACCEPTED = 'accepted'
    DUPLICATE = 'duplicate'
    LATE = 'late'
    NON_FINITE = 'non_finite'


@dataclass(frozen=True)
class StreamStats:
    """
    Diagnostics of one stream.

    Attributes
    ----------
    received : int
        Samples offered, whatever became of them.
    accepted : int
        Samples admitted (some may since have been evicted).
    duplicates, late, non_finite, evicted : int
        Samples refused or removed for each reason.
    size : int
        Samples currently held.
    first, last : float or None
        Oldest and newest stamp held, in seconds.
    span : float
        ``last - first`` in seconds (0 when fewer than two samples).
    gaps : int
        Intervals longer than ``max_gap`` between consecutive held samples.

    """

    received: int
    accepted: int
    duplicates: int
    late: int
    non_finite: int
    evicted: int
    size: int
    first: Optional[float]
    last: Optional[float]
    span: float
    gaps: int


@dataclass(frozen=True)
class BufferStats:
    """Diagnostics of the input ``u`` and the output ``y``, as :class:`StreamStats`."""

    u: StreamStats
    y: StreamStats


@dataclass(frozen=True)
class Gap:
    """
    An interval in which a stream is missing, in seconds.

    ``end`` is None when the stream has been silent since ``start`` (its newest sample).
    """

    stream: str
    start: float
    end: Optional[float]

    @property
    def duration(self) -> Optional[float]:
        """Return the length of the gap in seconds (None if it is still open)."""
        return None if self.end is None else self.end - self.start


@dataclass(frozen=True)
class Window:
    """
    A resampled window and what was left out of it.

    Attributes
    ----------
    data : Data
        The returned contiguous segment (``data.t0`` is its first instant, in seconds).
    requested : int
        Number of grid instants asked for.
    segments : tuple of (float, float)
        First and last instant (seconds) of every contiguous segment in the requested range,
        oldest first; ``data`` is one of them.
    gaps : tuple of Gap
        Missing intervals of either stream that overlap the requested range.

    """

    data: Data
    requested: int
    segments: Tuple[Tuple[float, float], ...]
    gaps: Tuple[Gap, ...]

    @property
    def dropped(self) -> int:
        """Return how many requested grid instants are not in :attr:`data`."""
        return self.requested - len(self.data)

    @property
    def complete(self) -> bool:
        """Return True if the whole requested range was returned."""
        return self.dropped == 0


class _Stream:
    """
    Stamp-ordered samples of one signal in a bounded buffer (not thread-safe).

    The samples occupy ``[start, stop)`` of arrays twice the capacity long, so every view is
    contiguous; when the end is reached the live part is copied to the front, once per at
    least ``capacity`` appends, which keeps appending O(1) amortised.
    """

    def __init__(self, name: str, capacity: int, horizon_ns: int, width: int = 1):
        self.name = name
        self.capacity = capacity
        self.horizon_ns = horizon_ns
        self.width = width
        self._stamps = np.empty(2 * capacity, dtype=np.int64)
        # One value per stamp, or a row of ``width`` values (several inputs in one message).
        self._values = np.empty(2 * capacity if width == 1 else (2 * capacity, width))
        self.clear()

    def clear(self) -> None:
        self._start = self._stop = 0
        self.received = self.accepted = self.duplicates = 0
        self.late = self.non_finite = self.evicted = 0

    def __len__(self) -> int:
        return self._stop - self._start

    @property
    def stamps(self) -> np.ndarray:
        return self._stamps[self._start:self._stop]

    @property
    def values(self) -> np.ndarray:
        return self._values[self._start:self._stop]

    def _make_room(self) -> None:
        if self._stop == self._stamps.size:
            count = len(self)
            self._stamps[:count] = self._stamps[self._start:self._stop]
            self._values[:count] = self._values[self._start:self._stop]
            self._start, self._stop = 0, count

    def append(self, stamp: int, value) -> Admission:
        self.received += 1
        if not (math.isfinite(value) if self.width == 1 else np.all(np.isfinite(value))):
            self.non_finite += 1
            return Admission.NON_FINITE
        if self._stop == self._start or stamp > self._stamps[self._stop - 1]:
            self._make_room()
            position = self._stop
        else:
            if stamp < self._stamps[self._stop - 1] - self.horizon_ns:
                self.late += 1
                return Admission.LATE
            offset = int(np.searchsorted(self.stamps, stamp))
            if self._stamps[self._start + offset] == stamp:
                self.duplicates += 1
                return Admission.DUPLICATE
            self._make_room()
            position = self._start + offset
            # Late arrivals lie within the horizon, so only a few newer samples move.
            self._stamps[position + 1:self._stop + 1] = self._stamps[position:self._stop]
            self._values[position + 1:self._stop + 1] = self._values[position:self._stop]
        self._stamps[position] = stamp
        self._values[position] = value
        self._stop += 1
        self.accepted += 1
        if len(self) > self.capacity:
            self._start += 1
            self.evicted += 1
        return Admission.ACCEPTED

    def stats(self, max_gap_ns: int) -> StreamStats:
        stamps = self.stamps
        first = float(stamps[0]) / NANOSECONDS if stamps.size else None
        last = float(stamps[-1]) / NANOSECONDS if stamps.size else None
        return StreamStats(
            received=self.received, accepted=self.accepted, duplicates=self.duplicates,
            late=self.late, non_finite=self.non_finite, evicted=self.evicted, size=stamps.size,
            first=first, last=last,
            span=float(stamps[-1] - stamps[0]) / NANOSECONDS if stamps.size else 0.0,
            gaps=int(np.count_nonzero(np.diff(stamps) > max_gap_ns)))

    def snapshot(self, begin: int, end: int) -> Tuple[np.ndarray, np.ndarray]:
        """Copy the samples that bear on instants in ``[begin, end]``: one before, one after."""
        stamps = self.stamps
        low = max(int(np.searchsorted(stamps, begin, side='right')) - 1, 0)
        high = int(np.searchsorted(stamps, end, side='right')) + 1
        return stamps[low:high].copy(), self.values[low:high].copy()


def _bracket(stamps: np.ndarray, grid: np.ndarray, max_gap_ns: int
             ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Locate each grid instant between the samples of a stream.

    Returns
    -------
    index : ndarray
        Index of the last sample at or before each instant (clipped to 0).
    inside : ndarray
        True where the instant is a sample instant, or lies between two samples at most
        ``max_gap_ns`` apart.
    after_last : ndarray
        True where the instant is later than the newest sample.

    """
    index = np.searchsorted(stamps, grid, side='right') - 1
    known = index >= 0
    index = np.maximum(index, 0)
    after_last = known & (index == stamps.size - 1) & (grid > stamps[-1])
    following = np.minimum(index + 1, stamps.size - 1)
    short = (index + 1 < stamps.size) & (stamps[following] - stamps[index] <= max_gap_ns)
    inside = known & ((grid == stamps[index]) | short)
    return index, inside, after_last


def _gaps(name: str, stamps: np.ndarray, begin: int, end: int, max_gap_ns: int,
          hold_ns: int) -> Tuple[Gap, ...]:
    """List the missing intervals of one stream that overlap ``[begin, end]``."""
    long = np.flatnonzero(np.diff(stamps) > max_gap_ns)
    found = [Gap(name, float(stamps[i]) / NANOSECONDS, float(stamps[i + 1]) / NANOSECONDS)
             for i in long if stamps[i] < end and stamps[i + 1] > begin]
    if stamps[-1] + hold_ns < end:
        found.append(Gap(name, float(stamps[-1]) / NANOSECONDS, None))
    return tuple(found)


def _runs(valid: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Return start and stop indices of the runs of True in a boolean array."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], valid.astype(np.int8), [0]))))
    return edges[0::2], edges[1::2]


class SampleBuffer:
    """
    Thread-safe buffer of timestamped input and output samples, resampled on demand.

    Parameters
    ----------
    capacity : int
        Samples kept per stream (see :func:`capacity_for`); the oldest are evicted.
    max_gap : float
        Seconds between consecutive samples of one stream beyond which the stream counts as
        missing in between (and after its newest sample: output at once, input after holding
        its last value for ``max_gap``).
    reorder_horizon : float
        Seconds by which a sample may be older than its stream's newest one and still be
        inserted in order; older ones are dropped and counted as late.
    names : (str, str)
        How the input and output are called in error messages (e.g. ``'/plant/u data'``).
    inputs : int
        Values per input sample: more than one for a model with several inputs taken from one
        message (:meth:`add_input` then takes a sequence and windows have 2-D ``u``).

    Notes
    -----
    Stamps are integer nanoseconds (``header.stamp`` or a receive time). All methods may be
    called concurrently: appends from subscription callbacks, windows from a timer or worker.

    """

    def __init__(self, capacity: int, *, max_gap: float = 0.5, reorder_horizon: float = 0.05,
                 names: Tuple[str, str] = (INPUT, OUTPUT), inputs: int = 1):
        capacity = operator.index(capacity)
        if capacity < 2:
            raise DataError(f'capacity must be at least 2 samples, got {capacity}')
        self.max_gap = float(max_gap)
        self.reorder_horizon = float(reorder_horizon)
        self._max_gap_ns = _to_ns(max_gap, 'max_gap')
        if self._max_gap_ns == 0:
            raise DataError('max_gap must be positive')
        self._horizon_ns = _to_ns(reorder_horizon, 'reorder_horizon')
        self.names = tuple(names)
        self._input = _Stream(self.names[0], capacity, self._horizon_ns, operator.index(inputs))
        self._output = _Stream(self.names[1], capacity, self._horizon_ns)
        self._lock = threading.Lock()

    @property
    def capacity(self) -> int:
        """Return the number of samples kept per stream."""
        return self._input.capacity

    def _input_value(self, value):
        if self._input.width == 1:
            return float(value)
        row = np.asarray(value, dtype=float)
        if row.shape != (self._input.width,):
            raise DataError(f'an input sample needs {self._input.width} values, got shape '
                            f'{row.shape}')
        return row

    def add_input(self, stamp_ns: int, value) -> Admission:
        """
        Append one input sample.

        Parameters
        ----------
        stamp_ns : int
            Time stamp in integer nanoseconds (a float is refused: seconds would be misread).
        value : float or sequence of float
            The sample (one value per input).

        Returns
        -------
        Admission
            Whether it was accepted, or why not.

        """
        stamp, value = operator.index(stamp_ns), self._input_value(value)
        with self._lock:
            return self._input.append(stamp, value)

    def add_output(self, stamp_ns: int, value: float) -> Admission:
        """Append one output sample; see :meth:`add_input`."""
        stamp, value = operator.index(stamp_ns), float(value)
        with self._lock:
            return self._output.append(stamp, value)

    def add_pair(self, stamp_ns: int, u, y: float) -> Tuple[Admission, Admission]:
        """Append an input and an output carried by one message (e.g. a JointState)."""
        stamp, u, y = operator.index(stamp_ns), self._input_value(u), float(y)
        with self._lock:
            return self._input.append(stamp, u), self._output.append(stamp, y)

    def clear(self) -> None:
        """Forget all samples and reset the counters (e.g. after the configuration changed)."""
        with self._lock:
            self._input.clear()
            self._output.clear()

    def stats(self) -> BufferStats:
        """Return counters and coverage of both streams."""
        with self._lock:
            return BufferStats(self._input.stats(self._max_gap_ns),
                               self._output.stats(self._max_gap_ns))

    def _require_samples(self) -> None:
        if not (len(self._input) and len(self._output)):
            raise DataError(self._silence())

    def _coverage(self, settled: bool) -> Tuple[int, int]:
        first = max(int(self._input.stamps[0]), int(self._output.stamps[0]))
        last = min(int(self._output.stamps[-1]),
                   int(self._input.stamps[-1]) + self._max_gap_ns)
        return first, last - self._horizon_ns if settled else last

    def coverage(self, *, settled: bool = True) -> Tuple[int, int]:
        """
        Return the first and last instants (ns) at which both streams have data.

        The last one is the newest output stamp, or the newest input stamp plus ``max_gap`` if
        earlier. With ``settled`` the reorder horizon is subtracted from it, so that samples
        still allowed to arrive late cannot change a window that was already taken; a replay of
        complete data passes ``settled=False``. Gaps inside are not considered.

        Raises
        ------
        DataError
            If a stream has no samples (the message names it).

        """
        with self._lock:
            self._require_samples()
            return self._coverage(settled)

    def window(self, length: float, sample_time: float, end_ns: Optional[int] = None, *,
               min_length: Optional[float] = None) -> Window:
        """
        Resample the latest ``length`` seconds onto the grid of multiples of ``sample_time``.

        Parameters
        ----------
        length : float
            Window length in seconds; the grid has ``round(length / sample_time)`` instants,
            the last one the latest multiple of ``sample_time`` at or before ``end_ns``.
        sample_time : float
            Grid spacing in seconds (used rounded to whole nanoseconds).
        end_ns : int, optional
            End of the window in nanoseconds; default the settled end of :meth:`coverage`.
        min_length : float, optional
            Shortest acceptable contiguous segment in seconds (default half the window).

        Returns
        -------
        Window
            The latest contiguous segment of at least ``min_length`` seconds as ``Data`` (input
            held, output interpolated), with the segments and gaps found.

        Raises
        ------
        DataError
            If a stream is empty, or no contiguous segment is long enough; the message says how
            many seconds are available and needed and which stream is missing where.

        """
        step = _to_ns(sample_time, 'sample_time')
        if step == 0:
            raise DataError(f'sample_time must be positive, got {sample_time!r}')
        count = round(float(length) / float(sample_time))
        needed = max(2, math.ceil(count / 2) if min_length is None
                     else round(float(min_length) / float(sample_time)))
        if count < needed:
            raise DataError(f'a window of {length} s holds {count} samples of {sample_time} s, '
                            f'fewer than the {needed} required')
        with self._lock:
            self._require_samples()
            if end_ns is None:
                end_ns = self._coverage(settled=True)[1]
            last = operator.index(end_ns) // step
            grid = np.arange(last - count + 1, last + 1, dtype=np.int64) * step
            su, vu = self._input.snapshot(int(grid[0]), int(grid[-1]))
            sy, vy = self._output.snapshot(int(grid[0]), int(grid[-1]))
            oldest = (int(self._input.stamps[0]), int(self._output.stamps[0]))
            evicted = (self._input.evicted, self._output.evicted)
        return self._resample(su, vu, sy, vy, grid, needed, step / NANOSECONDS, oldest,
                              evicted)

    def _silence(self) -> str:
        silent = [stream for stream in (self._input, self._output) if not len(stream)]
        parts = []
        for stream in silent:
            refused = stream.received - stream.accepted
            detail = (f'{stream.received} received, all refused (non-finite {stream.non_finite}'
                      f', late {stream.late}, duplicates {stream.duplicates})'
                      if refused else 'none received')
            parts.append(f'{stream.name}: {detail}')
        return ('no samples yet from ' + '; '.join(parts) +
                ': check that the topic is published, the field exists and the QoS matches')

    def _resample(self, su: np.ndarray, vu: np.ndarray, sy: np.ndarray, vy: np.ndarray,
                  grid: np.ndarray, needed: int, sample_time: float, oldest: Tuple[int, int],
                  evicted: Tuple[int, int]) -> Window:
        gap = self._max_gap_ns
        index_u, inside_u, after_u = _bracket(su, grid, gap)
        index_y, inside_y, _ = _bracket(sy, grid, gap)
        held = after_u & (grid - su[index_u] <= gap)
        valid = (inside_u | held) & inside_y
        gaps = (_gaps(self.names[0], su, int(grid[0]), int(grid[-1]), gap, gap) +
                _gaps(self.names[1], sy, int(grid[0]), int(grid[-1]), gap, 0))
        starts, stops = _runs(valid)
        seconds = grid.astype(float) / NANOSECONDS
        segments = tuple((float(seconds[start]), float(seconds[stop - 1]))
                         for start, stop in zip(starts, stops))
        long_enough = np.flatnonzero(stops - starts >= needed)
        if long_enough.size == 0:
            longest = int(np.max(stops - starts, initial=0))
            raise DataError(self._shortage(longest, needed, grid, sample_time, gaps, oldest,
                                           evicted))
        first, stop = int(starts[long_enough[-1]]), int(stops[long_enough[-1]])
        instants = grid[first:stop]
        origin = instants[0]
        y = np.interp((instants - origin).astype(float), (sy - origin).astype(float), vy)
        data = Data(vu[index_u[first:stop]], y, sample_time, float(seconds[first]))
        return Window(data, grid.size, segments, gaps)

    def _shortage(self, longest: int, needed: int, grid: np.ndarray, sample_time: float,
                  gaps: Tuple[Gap, ...], oldest: Tuple[int, int], evicted: Tuple[int, int]
                  ) -> str:
        end = float(grid[-1]) / NANOSECONDS
        text = (f'not enough contiguous data: {longest * sample_time:.6g} s of {self.names[0]} '
                f'and {self.names[1]} available together in the {grid.size * sample_time:.6g} s '
                f'window ending at t={end:.3f} s, need at least {needed * sample_time:.6g} s')
        reasons = []
        for gap in gaps:
            if gap.end is None:
                reasons.append(f'{gap.stream} silent since t={gap.start:.3f} s '
                               f'({end - gap.start:.3g} s before the window end)')
            else:
                reasons.append(f'{gap.stream} missing for {gap.duration:.3g} s from '
                               f't={gap.start:.3f} s (max_gap {self.max_gap:g} s)')
        for name, first, dropped in zip(self.names, oldest, evicted):
            if dropped and first > grid[0]:
                reasons.append(f'the buffer of {self.capacity} samples holds {name} only since '
                               f't={first / NANOSECONDS:.3f} s: raise its capacity')
            elif first > grid[0]:
                reasons.append(f'{name} starts at t={first / NANOSECONDS:.3f} s: wait for more '
                               'data or shorten the window')
        return text + ('; ' + '; '.join(reasons) if reasons else '')


def resample(input_stamps, input_values, output_stamps, output_values, sample_time: float, *,
             length: Optional[float] = None, end_ns: Optional[int] = None, max_gap: float = 0.5,
             reorder_horizon: float = 0.05, min_length: Optional[float] = None,
             names: Tuple[str, str] = (INPUT, OUTPUT)) -> Tuple[Window, BufferStats]:
    """
    Resample complete recorded streams, exactly as a live :class:`SampleBuffer` would.

    The samples are appended in the given (arrival) order to a buffer large enough to hold all
    of them, then one window is taken, so duplicates, late samples and non-finite values are
    treated as in the live node.

    Parameters
    ----------
    input_stamps, output_stamps : array_like of int
        Stamps in integer nanoseconds, in arrival order.
    input_values, output_values : array_like of float
        Values, one per stamp (input: one row per stamp for several inputs).
    sample_time : float
        Grid spacing in seconds.
    length : float, optional
        Window length in seconds; default from the first instant covered by both streams.
    end_ns : int, optional
        End of the window; default the latest instant covered by both streams (not reduced by
        the reorder horizon: the data are complete).
    max_gap, reorder_horizon, min_length : float
        As for :class:`SampleBuffer` and :meth:`SampleBuffer.window`.
    names : (str, str)
        How the input and output are called in error messages.

    Returns
    -------
    (Window, BufferStats)
        The window and the admission counters.

    """
    streams = []
    for name, stamps, values in ((names[0], input_stamps, input_values),
                                 (names[1], output_stamps, output_values)):
        stamps = np.asarray(stamps)
        values = np.asarray(values, dtype=float)
        if stamps.ndim != 1 or stamps.shape != values.shape[:1] or \
                values.ndim > (2 if name == names[0] else 1):
            raise DataError(f'{name} stamps and values must be 1-D of equal length, got shapes '
                            f'{stamps.shape} and {values.shape}')
        if stamps.size and not np.issubdtype(stamps.dtype, np.integer):
            raise DataError(f'{name} stamps must be integer nanoseconds, got {stamps.dtype}')
        streams.append((stamps.tolist(), values.tolist()))
    capacity = max(2, len(streams[0][0]), len(streams[1][0]))
    inputs = np.shape(input_values)[1] if np.ndim(input_values) == 2 else 1
    buffer = SampleBuffer(capacity, max_gap=max_gap, reorder_horizon=reorder_horizon,
                          names=names, inputs=inputs)
    for add, (stamps, values) in zip((buffer.add_input, buffer.add_output), streams):
        for stamp, value in zip(stamps, values):
            add(stamp, value)
    first, last = buffer.coverage(settled=False)
    if end_ns is None:
        end_ns = last
    if length is None:
        step = _to_ns(sample_time, 'sample_time')
        count = end_ns // step - -(-first // step) + 1
        length = max(count, 2) * step / NANOSECONDS
    return buffer.window(length, sample_time, end_ns, min_length=min_length), buffer.stats()
