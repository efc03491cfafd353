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
  reorder horizon of it, otherwise it is dropped and counted as late, or as out of clock if
  more than ``CLOCK_HORIZON_NS`` (or ``max_gap``) older;
* a stamp newer than the stream's newest one by more than the reorder horizon and
  ``JUMP_STEPS`` of its recent intervals is held as a candidate (:attr:`Admission.PENDING`)
  and admitted only once ``CONFIRMATIONS`` consistent stamps follow it with no sample admitted
  in between (a stream resuming after a silence); otherwise it is refused as out of clock.
  One message stamped an hour ahead, random or zero stamps therefore never capture a stream;
* a stream whose every new stamp is refused as too old, consistently for ``max_gap`` and
  ``CONFIRMATIONS`` stamps, re-anchors on them (a publisher restarted with an earlier clock):
  its samples of the old clock are dropped;
* beyond ``capacity`` samples the oldest are pushed out; they count as evicted only if newer
  than the buffer's ``history`` before the newest stamp (a window would still have used them),
  not as the normal turnover of a buffer sized for its windows.

Each refusal is remembered with the stream's clock at the time, so a window reports how many
samples of each stream were refused while its data arrived (:attr:`Window.refused`).

Resampling (see :mod:`ctid_ros.streaming.timing`, which chooses the grid): the grid follows the
input's own hold instants when the input is periodic, its phase and period fitted to the
input's stamps in the window (jitter, dropped messages and a drifting publisher clock
included); otherwise it is the absolute grid ``t_k = k * sample_time``.

* input, zero-order hold: on the input's instants, the sample of the latest input instant at
  or before ``t_k`` (a stamp jittered past ``t_k`` still counts for ``t_k``); on the absolute
  grid, the last input sample at or before ``t_k``. An instant whose message was lost while
  the input changed gets the midpoint and its bounds (:attr:`Window.input_bounds`), which the
  session fits with the model;
* output: a periodic output at the grid step (or a whole fraction of it) is taken at its own
  samples, ``Data.output_skew`` after the grid instants (each on its own lattice, so a clock
  drifting against the input's moves none); any other output is interpolated linearly at
  ``t_k``.

A stream is missing where two consecutive samples are more than ``max_gap`` apart (the whole
interval between them) and after its newest sample: the output beyond it, the input beyond it
plus ``max_gap`` (a held command stays valid that long). Nothing is ever interpolated or held
across a missing interval: the window is split into contiguous segments and the *latest*
segment of at least ``min_length`` seconds is returned, since a live estimator wants the most
recent behaviour; :class:`Window` reports all segments and the gaps that split them.
"""

from dataclasses import dataclass, field
import enum
import math
import operator
import threading
from typing import Any, List, Optional, Tuple

from ctid_ros.core.data import Data
from ctid_ros.errors import DataError
from ctid_ros.streaming.contract import NANOSECONDS
from ctid_ros.streaming.timing import (assign_instants, GridPlan, LATTICE_SLACK,
                                       MIN_EARLY, plan_grid)
import numpy as np

__all__ = ['Admission', 'BufferStats', 'CLOCK_HORIZON_NS', 'CONFIRMATIONS', 'Gap', 'INPUT',
           'JUMP_STEPS', 'OUTPUT', 'Refusals', 'SampleBuffer', 'StreamStats', 'Window',
           'capacity_for', 'resample']

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
    OUT_OF_CLOCK = 'out_of_clock'
    PENDING = 'pending'


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
    duplicates, late, non_finite : int
        Samples refused for each reason.
    evicted : int
        Samples pushed out by the capacity while a window could still have used them (within
        the buffer's ``history`` of the newest stamp; every one pushed out without a
        ``history``): a buffer too small, not its normal turnover.
    out_of_clock : int
        Samples refused because their stamps were far from the stream's clock.
    pending : int
        Samples held as candidates of a new clock (see the module notes).
    reanchors : int
        Times the stream restarted on an earlier clock (its older samples were dropped).
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
    out_of_clock: int = 0
    pending: int = 0
    reanchors: int = 0


@dataclass(frozen=True)
class Refusals:
    """Samples of one stream refused while the data of a window arrived, by reason."""

    stream: str
    non_finite: int = 0
    late: int = 0
    duplicates: int = 0
    out_of_clock: int = 0

    @property
    def total(self) -> int:
        """Return the number of refused samples."""
        return self.non_finite + self.late + self.duplicates + self.out_of_clock

    def describe(self) -> str:
        """Return e.g. ``input /u (data): 12 samples refused (non-finite 10, late 2)``."""
        reasons = ', '.join(f'{label} {count}' for label, count in (
            ('non-finite', self.non_finite), ('late', self.late),
            ('duplicate', self.duplicates), ('out of clock', self.out_of_clock)) if count)
        return f'{self.stream}: {self.total} samples refused in this window ({reasons})'


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
    start_ns : int
        First instant of :attr:`data` in integer nanoseconds.
    plan : GridPlan or None
        How the grid was chosen (its step is ``data.ts``, its skew ``data.output_skew``).
    refused : tuple of Refusals
        Samples of the input and of the output refused while the data of :attr:`data`
        arrived.
    missing : (int, int)
        Instants of :attr:`data` without a sample of their own (dropped messages): input
        instants held from the sample before, output instants interpolated. Counted only for
        a stream on its own lattice.
    unreceived : int
        Requested instants before both streams' data begin (after a start, a clear or a
        longer window): not in :attr:`data`, but no data were lost there, so no warning.
    notes : tuple of str
        Further warnings, e.g. a buffer too small for the requested span.
    input_bounds : (ndarray, ndarray) or None
        Where input instants lost their samples while the input changed (a dropped message at
        a step), the lowest and highest value it may have had there, like ``data.u`` (equal
        to it elsewhere); None if there is no such instant.

    """

    data: Data
    requested: int
    segments: Tuple[Tuple[float, float], ...]
    gaps: Tuple[Gap, ...]
    start_ns: int = 0
    plan: Optional[GridPlan] = None
    refused: Tuple[Refusals, ...] = ()
    missing: Tuple[int, int] = (0, 0)
    unreceived: int = 0
    notes: Tuple[str, ...] = ()
    input_bounds: Optional[Tuple[np.ndarray, np.ndarray]] = field(default=None, compare=False)

    @property
    def uncertain_inputs(self) -> np.ndarray:
        """Return the indices into ``data`` of the instants listed in :attr:`input_bounds`."""
        if self.input_bounds is None:
            return np.zeros(0, dtype=int)
        low, high = self.input_bounds
        differ = low != high
        return np.flatnonzero(differ if differ.ndim == 1 else np.any(differ, axis=1))

    @property
    def dropped(self) -> int:
        """Return how many requested grid instants are not in :attr:`data`."""
        return self.requested - len(self.data)

    @property
    def complete(self) -> bool:
        """Return True if the whole requested range was returned."""
        return self.dropped == 0

    @property
    def end_ns(self) -> int:
        """Return the last instant of :attr:`data` in integer nanoseconds."""
        return self.start_ns + round((len(self.data) - 1) * self.data.ts * NANOSECONDS)

    @property
    def warnings(self) -> Tuple[str, ...]:
        """Return what a user should know about the data: the grid, refused samples, gaps."""
        notes = list(self.plan.warnings) if self.plan is not None else []
        notes.extend(refusals.describe() for refusals in self.refused if refusals.total)
        names = [refusals.stream for refusals in self.refused] or [INPUT, OUTPUT]
        for name, count, treatment in zip(names, self.missing, (
                'held or, where the input changed, estimated with the model', 'interpolated')):
            if count:
                notes.append(f'{name}: {count} of {len(self.data)} instants without a sample '
                             f'of their own (messages dropped or bunched): {treatment}')
        left_out = self.dropped - self.unreceived
        if left_out > 0:
            cause = (f'by {len(self.gaps)} gap(s) in the data' if self.gaps else
                     'where the input or the output has no sample')
            notes.append(f'{left_out} of {self.requested} samples left out {cause}')
        notes.extend(self.notes)
        return tuple(notes)


# Codes of the refusal events a stream remembers (for the counts of a window).
_NON_FINITE, _LATE, _DUPLICATE, _OUT_OF_CLOCK = range(4)
# A stamp further ahead of its stream's newest one than this many of its recent intervals (and
# than the reorder horizon) starts a new clock only once this many consistent stamps follow.
JUMP_STEPS = 3
CONFIRMATIONS = 3
# A stamp older than its stream's newest one by more than this (or max_gap if longer) is out of
# clock rather than late.
CLOCK_HORIZON_NS = NANOSECONDS
# Before every stamp: a window from here takes all the data.
_EARLIEST = -2 ** 62
# Stamps whose intervals give a stream's clock (see _Stream._jump_ns).
_RECENT = 33
# Samples examined at once by _Stream.extend: few after a refusal, doubling while all pass.
_LOOKAHEAD = 16
_MAX_LOOKAHEAD = 1 << 16


class _Stream:
    """
    Stamp-ordered samples of one signal in a bounded buffer (not thread-safe).

    The samples occupy ``[start, stop)`` of arrays twice the capacity long, so every view is
    contiguous; when the end is reached the live part is copied to the front, once per at
    least ``capacity`` appends, which keeps appending O(1) amortised.

    Stamps far from the stream's own clock (its newest sample) wait in a *run* of candidates
    until they are confirmed or refused (see :class:`SampleBuffer`); refusals are remembered,
    with the stream's newest stamp when they happened, in a ring of ``capacity`` events.
    """

    def __init__(self, name: str, capacity: int, horizon_ns: int, max_gap_ns: int,
                 width: int = 1, history_ns: Optional[int] = None):
        self.name = name
        self.capacity = capacity
        self.horizon_ns = horizon_ns
        self.max_gap_ns = max_gap_ns
        self.width = width
        self.history_ns = history_ns
        self._stamps = np.empty(2 * capacity, dtype=np.int64)
        # One value per stamp, or a row of ``width`` values (several inputs in one message).
        self._values = np.empty(2 * capacity if width == 1 else (2 * capacity, width))
        self._event_stamps = np.zeros(capacity, dtype=np.int64)
        self._event_kinds = np.zeros(capacity, dtype=np.int8)
        self.clear()

    def clear(self) -> None:
        self._start = self._stop = 0
        self.received = self.accepted = self.duplicates = 0
        self.late = self.non_finite = self.evicted = 0
        self.out_of_clock = self.reanchors = 0
        # The newest stamp pushed out by the capacity (a window reaching back to it is short).
        self.evicted_until = _EARLIEST
        self._events = 0
        # Candidates (stamp, value) ahead of the clock, or (stamp, value, late) behind it.
        self._run: List[Tuple[Any, ...]] = []
        self._run_forward = True

    def __len__(self) -> int:
        return self._stop - self._start

    @property
    def pending(self) -> int:
        return len(self._run) if self._run_forward else 0

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

    def _newest(self, default: int) -> int:
        return int(self._stamps[self._stop - 1]) if self._stop > self._start else default

    def _refuse(self, kind: int, stamp: int) -> None:
        """Remember a refusal at the stream's current clock (its newest stamp)."""
        slot = self._events % self.capacity
        self._event_stamps[slot] = self._newest(stamp)
        self._event_kinds[slot] = kind
        self._events += 1

    def _store(self, stamp: int, value) -> None:
        """Insert a sample whose stamp is not held yet, in order."""
        self._make_room()
        if self._stop == self._start or stamp > self._stamps[self._stop - 1]:
            position = self._stop
        else:
            position = self._start + int(np.searchsorted(self.stamps, stamp))
            # Late arrivals lie within the horizon, so only a few newer samples move.
            self._stamps[position + 1:self._stop + 1] = self._stamps[position:self._stop]
            self._values[position + 1:self._stop + 1] = self._values[position:self._stop]
        self._stamps[position] = stamp
        self._values[position] = value
        self._stop += 1
        self.accepted += 1
        if len(self) > self.capacity:
            self._evict(self._stamps[self._start:self._start + 1])
            self._start += 1

    def _evict(self, stamps: np.ndarray) -> None:
        """
        Count the samples at ``stamps`` (the oldest held, increasing) as pushed out.

        Only those within ``history_ns`` of the newest stamp count as :attr:`evicted`: older
        ones are the normal turnover of a buffer that holds what the windows need.
        """
        if not stamps.size:
            return
        newest = int(self._stamps[self._stop - 1])
        self.evicted_until = max(self.evicted_until, int(stamps[-1]))
        if self.history_ns is None:
            self.evicted += int(stamps.size)
        else:
            kept = int(np.searchsorted(stamps, newest - self.history_ns, side='right'))
            self.evicted += int(stamps.size) - kept

    def _jump_ns(self) -> int:
        """Return how far ahead of the newest stamp a new one is still in the stream's clock."""
        recent = self._stamps[max(self._start, self._stop - _RECENT):self._stop]
        if recent.size < 3:
            return max(self.horizon_ns, self.max_gap_ns)
        return max(self.horizon_ns, JUMP_STEPS * int(np.median(np.diff(recent))))

    def append(self, stamp: int, value) -> Admission:
        self.received += 1
        if not (math.isfinite(value) if self.width == 1 else np.all(np.isfinite(value))):
            self.non_finite += 1
            self._refuse(_NON_FINITE, stamp)
            return Admission.NON_FINITE
        if self._stop == self._start:
            self._drop_run()
            self._store(stamp, value)
            return Admission.ACCEPTED
        newest = int(self._stamps[self._stop - 1])
        if stamp > newest:
            if stamp - newest > self.horizon_ns and stamp - newest > self._jump_ns():
                return self._candidate(stamp, value)
        elif stamp < newest - self.horizon_ns:
            return self._behind(stamp, value, newest)
        elif self._stamps[self._start + int(np.searchsorted(self.stamps, stamp))] == stamp:
            self.duplicates += 1
            self._refuse(_DUPLICATE, stamp)
            return Admission.DUPLICATE
        self._drop_run()
        self._store(stamp, value)
        return Admission.ACCEPTED

    def _candidate(self, stamp: int, value) -> Admission:
        """
        Hold a stamp far ahead of the stream's clock until it is confirmed or refused.

        Candidates form a run: increasing stamps, each within ``max_gap`` (or the jump
        horizon) of the one before, received while no sample was admitted. CONFIRMATIONS of
        them make the stream's new clock (a stream resuming after a silence, a publisher
        restarted with a later clock); an admitted sample or a stamp that does not continue the
        run refuses them as out of clock.
        """
        run = self._run
        if not (run and self._run_forward and
                run[-1][0] < stamp <= run[-1][0] + max(self._jump_ns(), self.max_gap_ns)):
            self._drop_run()
            self._run_forward = True
        run.append((stamp, value))
        if len(run) < CONFIRMATIONS:
            return Admission.PENDING
        for held_stamp, held_value in run:
            self._store(held_stamp, held_value)
        run.clear()
        return Admission.ACCEPTED

    def _behind(self, stamp: int, value, newest: int) -> Admission:
        """
        Refuse a stamp older than the reorder horizon, unless the stream's clock went back.

        It is late if within the clock horizon of the newest stamp, else out of clock. A run
        of such stamps (as for :meth:`_candidate`) that holds CONFIRMATIONS of them and spans
        ``max_gap`` with no sample admitted in between is a publisher restarted with an earlier
        clock: the samples of the old clock are dropped and the run is admitted.
        """
        late = stamp >= newest - max(self.max_gap_ns, CLOCK_HORIZON_NS)
        if late:
            self.late += 1
        else:
            self.out_of_clock += 1
        self._refuse(_LATE if late else _OUT_OF_CLOCK, stamp)
        run = self._run
        if not (run and not self._run_forward and
                run[-1][0] < stamp <= run[-1][0] + self._jump_ns()):
            self._drop_run()
            self._run_forward = False
        run.append((stamp, value, late))
        if len(run) < CONFIRMATIONS or run[-1][0] - run[0][0] < self.max_gap_ns:
            return Admission.LATE if late else Admission.OUT_OF_CLOCK
        self._start = self._stop = 0
        self.reanchors += 1
        for held_stamp, held_value, was_late in run:
            if was_late:
                self.late -= 1
            else:
                self.out_of_clock -= 1
            self._store(held_stamp, held_value)
        run.clear()
        return Admission.ACCEPTED

    def _drop_run(self) -> None:
        """End the run of candidates; those ahead of the clock are refused as out of clock."""
        if self._run_forward:
            for stamp, _ in self._run:
                self.out_of_clock += 1
                self._refuse(_OUT_OF_CLOCK, stamp)
        self._run.clear()

    def extend(self, stamps: np.ndarray, values: np.ndarray) -> None:
        """
        Append many samples in arrival order, exactly as :meth:`append` one by one would.

        The samples that :meth:`append` would simply store after the newest one (finite, newer
        than it and within its clock, with no candidate run pending) are found with array
        operations and stored as one block; every other sample goes through :meth:`append`
        itself, so duplicates, late and far stamps, runs and re-anchoring keep their one rule.
        """
        count = stamps.size
        if count == 0:
            return
        finite = np.isfinite(values) if values.ndim == 1 else np.all(np.isfinite(values), axis=1)
        position = 0
        lookahead = _LOOKAHEAD
        while position < count:
            simple = self._simple_prefix(stamps[position:position + lookahead],
                                         finite[position:position + lookahead])
            if simple:
                self._store_block(stamps[position:position + simple],
                                  values[position:position + simple])
                position += simple
                if simple == min(lookahead, count - position + simple):
                    lookahead = min(2 * lookahead, _MAX_LOOKAHEAD)
                    continue
            if position < count:
                value = values[position]
                self.append(int(stamps[position]),
                            float(value) if self.width == 1 else value.copy())
                position += 1
            lookahead = _LOOKAHEAD

    def _simple_prefix(self, stamps: np.ndarray, finite: np.ndarray) -> int:
        """
        Count the leading samples :meth:`append` would store at the end without question.

        A sample qualifies if it is finite, newer than the newest held stamp and, if further
        ahead of it than the reorder horizon, within :meth:`_jump_ns` of the stream as it will
        be once the samples before it are stored. Needs no candidate run and at least as many
        held samples as :meth:`_jump_ns` looks at, else 0 (the caller appends one by one).
        """
        recent = min(_RECENT, self.capacity)
        if self._run or len(self) < recent:
            return 0
        held = self._stamps[self._stop - recent:self._stop]
        sequence = np.concatenate((held, stamps))
        steps = np.diff(sequence)[recent - 1:]
        ahead = steps > self.horizon_ns
        ok = finite & (steps > 0)
        if np.any(ahead & ok):
            if recent < 3:
                jump = np.full(steps.size, max(self.horizon_ns, self.max_gap_ns))
            else:
                intervals = np.lib.stride_tricks.sliding_window_view(
                    np.diff(sequence)[:-1], recent - 1)
                which = np.flatnonzero(ahead & ok)
                jump = np.full(steps.size, self.horizon_ns, dtype=np.int64)
                medians = np.median(intervals[which], axis=1)
                jump[which] = np.maximum(self.horizon_ns,
                                         JUMP_STEPS * np.trunc(medians).astype(np.int64))
            ok &= ~ahead | (steps <= jump)
        bad = np.flatnonzero(~ok)
        return int(bad[0]) if bad.size else stamps.size

    def _store_block(self, stamps: np.ndarray, values: np.ndarray) -> None:
        """Store samples newer than the newest held one, in order, as :meth:`_store` would."""
        count = stamps.size
        self.received += count
        self.accepted += count
        total = len(self) + count
        keep = min(self.capacity, total)
        if total > keep:
            self._count_block_evictions(stamps, total - keep)
        if self._stop + count <= self._stamps.size:
            self._stamps[self._stop:self._stop + count] = stamps
            self._values[self._stop:self._stop + count] = values
            self._stop += count
            self._start = self._stop - keep
            return
        old = keep - min(count, keep)
        self._stamps[:old] = self._stamps[self._stop - old:self._stop]
        self._values[:old] = self._values[self._stop - old:self._stop]
        self._stamps[old:keep] = stamps[count - (keep - old):]
        self._values[old:keep] = values[count - (keep - old):]
        self._start, self._stop = 0, keep

    def _count_block_evictions(self, stamps: np.ndarray, count: int) -> None:
        """Count the ``count`` oldest of the held samples followed by ``stamps`` as evicted."""
        held = self.stamps
        pushed = held[:count] if count <= held.size else np.concatenate(
            (held, stamps[:count - held.size]))
        newest = int(stamps[-1])
        self.evicted_until = max(self.evicted_until, int(pushed[-1]))
        if self.history_ns is None:
            self.evicted += count
        else:
            self.evicted += count - int(np.searchsorted(pushed, newest - self.history_ns,
                                                        side='right'))

    def adopt(self, other: '_Stream') -> None:
        """
        Take the newest samples, counters and refusals of ``other`` (same signal, new sizes).

        The samples that do not fit the capacity are pushed out oldest first, counted as
        :meth:`_evict` counts them; a candidate run in progress is kept.
        """
        count = min(len(other), self.capacity)
        self._start, self._stop = 0, count
        self._stamps[:count] = other.stamps[len(other) - count:]
        self._values[:count] = other.values[len(other) - count:]
        for name in ('received', 'accepted', 'duplicates', 'late', 'non_finite', 'evicted',
                     'out_of_clock', 'reanchors', 'evicted_until'):
            setattr(self, name, getattr(other, name))
        if count < len(other):
            newest = int(other.stamps[-1])
            pushed = other.stamps[:len(other) - count]
            self.evicted_until = max(self.evicted_until, int(pushed[-1]))
            self.evicted += int(pushed.size) if self.history_ns is None else int(
                pushed.size - np.searchsorted(pushed, newest - self.history_ns, side='right'))
        self._run = list(other._run)
        self._run_forward = other._run_forward
        stamps, kinds = other.events()
        kept = min(stamps.size, self.capacity)
        self._event_stamps[:kept] = stamps[stamps.size - kept:]
        self._event_kinds[:kept] = kinds[kinds.size - kept:]
        self._events = kept

    def events(self) -> Tuple[np.ndarray, np.ndarray]:
        """Copy the remembered refusals: the stream's clock at each (ns) and its reason code."""
        count = min(self._events, self.capacity)
        return self._event_stamps[:count].copy(), self._event_kinds[:count].copy()

    def stats(self, max_gap_ns: int) -> StreamStats:
        stamps = self.stamps
        first = float(stamps[0]) / NANOSECONDS if stamps.size else None
        last = float(stamps[-1]) / NANOSECONDS if stamps.size else None
        return StreamStats(
            received=self.received, accepted=self.accepted, duplicates=self.duplicates,
            late=self.late, non_finite=self.non_finite, evicted=self.evicted, size=stamps.size,
            first=first, last=last,
            span=float(stamps[-1] - stamps[0]) / NANOSECONDS if stamps.size else 0.0,
            gaps=int(np.count_nonzero(np.diff(stamps) > max_gap_ns)),
            out_of_clock=self.out_of_clock, pending=self.pending, reanchors=self.reanchors)

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


def _counts(length: float, sample_time: float, min_length: Optional[float],
            count: Optional[int] = None) -> Tuple[int, int]:
    """Return the instants of a window and the contiguous ones needed, or raise."""
    if count is None:
        count = round(float(length) / float(sample_time))
    needed = max(2, math.ceil(count / 2) if min_length is None
                 else round(float(min_length) / float(sample_time)))
    if count < needed:
        raise DataError(f'a window of {length:.6g} s holds {count} samples of '
                        f'{sample_time:.6g} s, fewer than the {needed} required')
    return count, needed


def _recent(stamps: np.ndarray, values: np.ndarray, begin: int, end: int, max_gap_ns: int
            ) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return the samples a stream's lattice is fitted to: those in ``[begin, end]``.

    Only those after the last silence longer than ``max_gap`` count, if they are at least half
    of them: a publisher restarted inside the window may have a new phase.
    """
    inside = (stamps >= begin) & (stamps <= end)
    if not np.any(inside):
        # Nothing in the range yet (a buffer just cleared): the grid still needs a reference.
        return stamps, values
    stamps, values = stamps[inside], values[inside]
    silences = np.flatnonzero(np.diff(stamps) > max_gap_ns)
    if silences.size and stamps.size - silences[-1] - 1 >= stamps.size // 2:
        stamps, values = stamps[silences[-1] + 1:], values[silences[-1] + 1:]
    return stamps, values


def _grid(plan: GridPlan, length: float, min_length: Optional[float], begin: int, end_ns: int,
          start_ns: Optional[int]) -> Tuple[np.ndarray, int]:
    """
    Return the grid instants (ns) of a window and the contiguous instants it needs.

    The last instant is the latest whose output is measured by ``end_ns`` (up to the jitter
    tolerance); there are ``length / step`` instants, or all from ``start_ns`` on.
    """
    seconds = plan.step / NANOSECONDS
    last = plan.index_at_or_before(end_ns - round(plan.skew) + round(plan.tolerance))
    if start_ns is None:
        count = round(float(length) / seconds)
    else:
        count = last - plan.index_at_or_before(begin - round(plan.tolerance) - 1)
    count, needed = _counts(count * seconds, seconds, min_length, count)
    return plan.instants(last - count + 1, count), needed


def _refusals(name: str, stamps: np.ndarray, kinds: np.ndarray, begin: int, end: int
              ) -> Refusals:
    """Count the refusal events of a stream whose clock was in ``[begin, end]``."""
    counts = np.bincount(kinds[(stamps >= begin) & (stamps <= end)], minlength=4)
    return Refusals(name, *(int(value) for value in counts))


def _early(plan: GridPlan, period: float) -> float:
    """Return how early (in periods) a stamp may be for its instant: the plan's tolerance."""
    return min(LATTICE_SLACK, max(plan.tolerance / period, MIN_EARLY))


def _held(stamps: np.ndarray, values: np.ndarray, grid: np.ndarray, plan: GridPlan,
          max_gap_ns: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Hold the input on its own instants: the sample of the latest instant at or before each.

    Every input sample belongs to an instant of the input's lattice
    (:func:`~ctid_ros.streaming.timing.assign_instants`: the nearest, or a free one before it
    for a burst of late messages); grid instant ``t_k`` takes the sample of the latest lattice
    instant at or before it, so jitter cannot move a sample to the next grid instant. Valid at
    the sample's own instant, where that sample and the next one are at most ``max_gap``
    apart, or, after the newest sample, up to ``max_gap`` after it.

    Where instants lost their samples (dropped messages) between two samples of different
    values, the command changed at one of them, unknown which: each takes the expected value
    under a change equally likely at every one of them, the line from the sample before to the
    sample after (holding the one before would move every such change late, biasing the dead
    time), and its bounds are the two values: the session estimates it within them with the
    model (:class:`~ctid_ros.streaming.session.IdentificationSession`), so that the guess
    costs one sample's information instead of biasing the estimate.

    Returns
    -------
    (u, valid, missing, bounds) : (ndarray, ndarray, ndarray, (ndarray, ndarray))
        The input at each grid instant, its validity, whether the instant is one of the
        input's whose own sample is missing, and the lowest and highest value the input may
        have had there (both equal to ``u`` where it is known).

    """
    period = plan.input_period
    relative = (stamps - plan.reference).astype(float) - plan.origin
    lattice, assigned = assign_instants(relative / period, _early(plan, period))
    chosen = np.flatnonzero(assigned)
    if chosen.size == 0:
        nothing = np.zeros(grid.size, dtype=bool)
        return values[np.zeros(grid.size, dtype=int)], nothing, nothing
    instants = lattice[chosen]
    position_float = ((grid - plan.reference).astype(float) - plan.origin) / period
    wanted = np.floor(position_float + 1e-6)
    position = np.searchsorted(instants, wanted, side='right') - 1
    known = position >= 0
    position = np.maximum(position, 0)
    held = stamps[chosen]
    following = np.minimum(position + 1, chosen.size - 1)
    has_next = position + 1 < chosen.size
    own = instants[position] == wanted
    bridged = has_next & (held[following] - held[position] <= max_gap_ns)
    valid = known & (own | bridged | (~has_next & (grid - held[position] <= max_gap_ns)))
    u = values[chosen[position]]
    low, high = u.copy(), u.copy()
    lost = known & ~own & bridged
    if np.any(lost):
        before, after = chosen[position[lost]], chosen[following[lost]]
        fraction = (wanted[lost] - instants[position[lost]]) / (
            instants[following[lost]] - instants[position[lost]])
        if u.ndim == 2:
            fraction = fraction[:, None]
        u[lost] = values[before] + fraction * (values[after] - values[before])
        low[lost] = np.minimum(values[before], values[after])
        high[lost] = np.maximum(values[before], values[after])
    # Instants of the input's lattice whose own sample is missing (a finer grid has others).
    instant = np.abs(position_float - wanted) < 1e-3
    return u, valid, known & instant & ~own, (low, high)


def _own_samples(stamps: np.ndarray, grid: np.ndarray, plan: GridPlan) -> np.ndarray:
    """
    Return, per grid instant, the index of the output sample measured at it (or -1).

    The output's samples are given the instants of its own lattice, ``skew`` after the grid
    instants and every output period (:func:`~ctid_ros.streaming.timing.assign_instants`);
    the grid instants take those on them.
    """
    own = np.full(grid.size, -1)
    if stamps.size == 0:
        return own
    every = max(1, round(plan.step / plan.output_period))
    # The grid's subdivision rather than the output's own period: the two clocks may drift.
    period = plan.step / every
    lattice = plan.output_lattice
    if lattice is None:
        relative = (stamps - grid[0]).astype(float) - plan.skew
        index, assigned = assign_instants(relative / period, _early(plan, period))
    else:
        # Each sample on its own lattice first (its jitter), then that instant to the nearest
        # subdivision of the grid: the output's clock may drift against the input's.
        own_index, assigned = assign_instants(
            ((stamps - lattice.reference).astype(float) - lattice.origin) / lattice.period,
            lattice.early)
        instant = float(lattice.reference - grid[0]) + lattice.origin + \
            own_index * lattice.period - plan.skew
        position = instant / period
        index = np.round(position).astype(np.int64)
        assigned &= np.abs(position - index) < LATTICE_SLACK
    on_grid = assigned & (np.mod(index, every) == 0) & (index >= 0) & (index < every * grid.size)
    own[index[on_grid] // every] = np.flatnonzero(on_grid)
    return own


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
    history : float, optional
        Seconds of data the windows take (window, transient, ``max_gap``, reorder horizon): a
        sample pushed out by the capacity counts as evicted only if it is newer than that
        before its stream's newest stamp (older ones are normal turnover). Default: every
        sample pushed out counts.
    origin_ns : int, optional
        Time origin of the times in messages (``t=...`` counts seconds from it); default 0,
        absolute stamps (see :attr:`origin_ns`).

    Notes
    -----
    Stamps are integer nanoseconds (``header.stamp`` or a receive time). All methods may be
    called concurrently: appends from subscription callbacks, windows from a timer or worker.

    """

    def __init__(self, capacity: int, *, max_gap: float = 0.5, reorder_horizon: float = 0.05,
                 names: Tuple[str, str] = (INPUT, OUTPUT), inputs: int = 1,
                 history: Optional[float] = None, origin_ns: Optional[int] = None):
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
        history_ns = None if history is None else _to_ns(history, 'history')
        self._input = _Stream(self.names[0], capacity, self._horizon_ns, self._max_gap_ns,
                              operator.index(inputs), history_ns)
        self._output = _Stream(self.names[1], capacity, self._horizon_ns, self._max_gap_ns,
                               history_ns=history_ns)
        self._origin_ns = None if origin_ns is None else operator.index(origin_ns)
        self._lock = threading.Lock()

    @property
    def origin_ns(self) -> Optional[int]:
        """
        Return the time origin of messages, None for absolute stamps.

        Times in error messages are ``t=`` seconds from it: a node or a replay sets it to its
        own origin (e.g. its first sample or the bag's start), so that all its messages count
        from one instant. It survives :meth:`clear` and :meth:`carry_over`.
        """
        return self._origin_ns

    @origin_ns.setter
    def origin_ns(self, value: Optional[int]) -> None:
        self._origin_ns = None if value is None else operator.index(value)

    def carry_over(self, previous: 'SampleBuffer') -> None:
        """
        Take the samples of ``previous`` that still fit (a window or capacity changed).

        Each stream whose label and width are unchanged (same topic, field and number of
        inputs) keeps its newest samples up to this buffer's capacity, its counters and its
        refusals; a stream that changed starts empty. The time origin is kept either way. The
        gap rules of this buffer apply to the windows taken from now on.
        """
        if previous is self:
            return
        with previous._lock:
            origin = previous.origin_ns
            with self._lock:
                for mine, theirs in ((self._input, previous._input),
                                     (self._output, previous._output)):
                    if (mine.name, mine.width) == (theirs.name, theirs.width):
                        mine.adopt(theirs)
                if self._origin_ns is None:
                    self._origin_ns = origin

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

    def add_inputs(self, stamps_ns, values) -> None:
        """
        Append many input samples in arrival order, as :meth:`add_input` one by one would.

        Parameters
        ----------
        stamps_ns : array_like of int
            Stamps in integer nanoseconds (a float array is refused).
        values : array_like of float
            One value per stamp, or one row of ``inputs`` values per stamp.

        Notes
        -----
        The admission rules are those of :meth:`add_input`: the samples it would simply store
        after the newest one are stored as blocks, every other sample goes through it
        (duplicates, late, far and non-finite stamps alike), so both give the same buffer.

        """
        stamps, values = _batch(stamps_ns, values, self._input.width, self.names[0])
        with self._lock:
            self._input.extend(stamps, values)

    def add_outputs(self, stamps_ns, values) -> None:
        """Append many output samples in arrival order; see :meth:`add_inputs`."""
        stamps, values = _batch(stamps_ns, values, 1, self.names[1])
        with self._lock:
            self._output.extend(stamps, values)

    def clear(self) -> None:
        """Forget all samples and reset the counters; the time origin is kept."""
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
               min_length: Optional[float] = None, start_ns: Optional[int] = None,
               transient: float = 0.0) -> Window:
        """
        Resample the latest ``length`` seconds onto the grid of the input's instants.

        Parameters
        ----------
        length : float
            Window length in seconds; the grid has ``round(length / step)`` instants, the last
            one the latest grid instant at or before ``end_ns`` (minus the output skew).
        sample_time : float
            Configured grid step in seconds; the grid itself follows the input's instants
            (:func:`~ctid_ros.streaming.timing.plan_grid`), else its multiples.
        end_ns : int, optional
            End of the window in nanoseconds; default the settled end of :meth:`coverage`.
        min_length : float, optional
            Shortest acceptable contiguous segment in seconds (default half the window).
        start_ns : int, optional
            Take every grid instant from ``start_ns`` on (whose input and output samples are
            held, up to the jitter of their stamps) instead of ``length`` seconds.
        transient : float
            Seconds of ``length`` that only settle the model's state before the fitted
            window: messages then name the window as configured, ``length - transient``.

        Returns
        -------
        Window
            The latest contiguous segment of at least ``min_length`` seconds as ``Data`` (input
            held, output at its own samples or interpolated), with the segments and gaps found,
            the grid plan and the refused samples.

        Raises
        ------
        DataError
            If a stream is empty, or no contiguous segment is long enough; the message says how
            many seconds are available and needed and which stream is missing where.

        """
        step = _to_ns(sample_time, 'sample_time')
        if step == 0:
            raise DataError(f'sample_time must be positive, got {sample_time!r}')
        _counts(length, sample_time, min_length)
        with self._lock:
            self._require_samples()
            if end_ns is None:
                end_ns = self._coverage(settled=True)[1]
            end_ns = operator.index(end_ns)
            begin = end_ns - _to_ns(length, 'length') if start_ns is None else start_ns
            # Stamps around the window: the grid's phase is fitted to them, a held input and
            # the interpolation may reach back up to max_gap before its first instant.
            margin = self._max_gap_ns + step
            su, vu = self._input.snapshot(begin - margin, end_ns + margin)
            sy, vy = self._output.snapshot(begin - margin, end_ns + margin)
            oldest = (int(self._input.stamps[0]), int(self._output.stamps[0]))
            evicted = (self._input.evicted_until, self._output.evicted_until)
            events = (self._input.events(), self._output.events())
            origin = self.origin_ns
        plan = plan_grid(*_recent(su, vu, begin, end_ns, self._max_gap_ns),
                         _recent(sy, vy, begin, end_ns, self._max_gap_ns)[0], step, self.names)
        if start_ns is not None:
            # The first instant whose input and output are both measured at or after start_ns.
            begin = max(begin, oldest[0], oldest[1] - round(plan.skew))
        grid, needed = _grid(plan, length, min_length, begin, end_ns, start_ns)
        window = self._resample(su, vu, sy, vy, grid, needed, plan, oldest, evicted,
                                (origin or 0, transient))
        refused = tuple(_refusals(name, *stream_events, window.start_ns, window.end_ns)
                        for name, stream_events in zip(self.names, events))
        return Window(window.data, window.requested, window.segments, window.gaps,
                      window.start_ns, plan, refused, window.missing, window.unreceived,
                      window.notes, window.input_bounds)

    def _silence(self) -> str:
        silent = [stream for stream in (self._input, self._output) if not len(stream)]
        parts = []
        for stream in silent:
            refused = stream.received - stream.accepted
            detail = (f'{stream.received} received, all refused (non-finite {stream.non_finite}'
                      f', late {stream.late}, duplicates {stream.duplicates}, out of clock '
                      f'{stream.out_of_clock}, pending {stream.pending})'
                      if refused else 'none received')
            parts.append(f'{stream.name}: {detail}')
        return ('no samples yet from ' + '; '.join(parts) +
                ': check that the topic is published, the field exists and the QoS matches')

    def _resample(self, su: np.ndarray, vu: np.ndarray, sy: np.ndarray, vy: np.ndarray,
                  grid: np.ndarray, needed: int, plan: GridPlan, oldest: Tuple[int, int],
                  evicted: Tuple[int, int], frame: Tuple[int, float]) -> Window:
        gap = self._max_gap_ns
        sample_time = plan.step / NANOSECONDS
        held = bounds = None
        if plan.input_period is None:
            index_u, inside_u, after_u = _bracket(su, grid, gap)
            valid_u = inside_u | (after_u & (grid - su[index_u] <= gap))
            u = vu[index_u]
        else:
            u, valid_u, held, bounds = _held(su, vu, grid, plan, gap)
        skew = round(plan.skew)
        index_y, inside_y, _ = _bracket(sy, grid + skew, gap)
        valid_y = inside_y
        own = None
        if plan.output_period is not None:
            own = _own_samples(sy, grid, plan)
            valid_y = valid_y | (own >= 0)
        valid = valid_u & valid_y
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
                                           evicted, frame))
        first, stop = int(starts[long_enough[-1]]), int(stops[long_enough[-1]])
        instants = grid[first:stop] + skew
        origin = instants[0]
        y = np.interp((instants - origin).astype(float), (sy - origin).astype(float), vy)
        missing = [0, 0]
        if own is not None:
            taken = own[first:stop]
            y[taken >= 0] = vy[taken[taken >= 0]]
            missing[1] = int(np.count_nonzero(taken < 0))
        if held is not None:
            missing[0] = int(np.count_nonzero(held[first:stop]))
        data = Data(u[first:stop], y, sample_time, float(seconds[first]),
                    plan.skew / NANOSECONDS)
        # Instants before both streams began are not lost data (yet to come, or never kept).
        begun = max(oldest[0], oldest[1] - skew) + round(plan.tolerance)
        unreceived = int(np.searchsorted(grid[:int(starts[0])], begun, side='right'))
        notes = tuple(
            f'{unreceived} of {grid.size} samples left out: the buffer of {self.capacity} '
            f'samples holds {name} only since t={(since - frame[0]) / NANOSECONDS:.3f} s, '
            f'{(since - int(grid[0])) / NANOSECONDS:.3g} s short: raise its capacity'
            for name, since, pushed in zip(self.names, oldest, evicted)
            if unreceived and pushed >= int(grid[0]))
        uncertain = None
        if bounds is not None and np.any(bounds[0][first:stop] != bounds[1][first:stop]):
            uncertain = (bounds[0][first:stop], bounds[1][first:stop])
        return Window(data, grid.size, segments, gaps, int(grid[first]), missing=tuple(missing),
                      unreceived=unreceived, notes=notes, input_bounds=uncertain)

    def _shortage(self, longest: int, needed: int, grid: np.ndarray, sample_time: float,
                  gaps: Tuple[Gap, ...], oldest: Tuple[int, int], evicted: Tuple[int, int],
                  frame: Tuple[int, float]) -> str:
        origin, transient = frame
        zero = origin / NANOSECONDS
        end = (int(grid[-1]) - origin) / NANOSECONDS
        span = grid.size * sample_time
        fitted = span - transient if 0 < transient < span else span
        extra = f' (plus {span - fitted:.6g} s settling transient)' if fitted < span else ''
        text = (f'not enough contiguous data: {longest * sample_time:.6g} s of {self.names[0]} '
                f'and {self.names[1]} available together in the {fitted:.6g} s window{extra} '
                f'ending at t={end:.3f} s, need at least {needed * sample_time:.6g} s')
        reasons = []
        for gap in gaps:
            if gap.end is None:
                reasons.append(f'{gap.stream} silent since t={gap.start - zero:.3f} s '
                               f'({end + zero - gap.start:.3g} s before the window end)')
            else:
                reasons.append(f'{gap.stream} missing for {gap.duration:.3g} s from '
                               f't={gap.start - zero:.3f} s (max_gap {self.max_gap:g} s)')
        for name, first, pushed in zip(self.names, oldest, evicted):
            since = (first - origin) / NANOSECONDS
            if pushed >= grid[0] and first > grid[0]:
                reasons.append(f'the buffer of {self.capacity} samples holds {name} only since '
                               f't={since:.3f} s: raise its capacity')
            elif first > grid[0]:
                reasons.append(f'{name} starts at t={since:.3f} s: wait for more data or '
                               'shorten the window')
        return text + ('; ' + '; '.join(reasons) if reasons else '')


def _batch(stamps, values, width: int, name: str) -> Tuple[np.ndarray, np.ndarray]:
    """Check and convert the stamps and values of many samples of one stream."""
    stamps = np.asarray(stamps)
    values = np.asarray(values, dtype=float)
    if stamps.ndim != 1 or stamps.shape != values.shape[:1] or \
            values.ndim != (1 if width == 1 else 2) and values.size:
        raise DataError(f'{name} stamps and values must be 1-D of equal length, got shapes '
                        f'{stamps.shape} and {values.shape}')
    if stamps.size and not np.issubdtype(stamps.dtype, np.integer):
        raise DataError(f'{name} stamps must be integer nanoseconds, got {stamps.dtype}')
    if width > 1 and values.size and values.shape[1] != width:
        raise DataError(f'an input sample needs {width} values, got shape {values.shape[1:]}')
    values = values.reshape(-1) if width == 1 else values.reshape(-1, width)
    return stamps.astype(np.int64, copy=False), values


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
    inputs = np.shape(input_values)[1] if np.ndim(input_values) == 2 else 1
    streams = (_batch(input_stamps, input_values, inputs, names[0]),
               _batch(output_stamps, output_values, 1, names[1]))
    capacity = max(2, streams[0][0].size, streams[1][0].size)
    buffer = SampleBuffer(capacity, max_gap=max_gap, reorder_horizon=reorder_horizon,
                          names=names, inputs=inputs)
    buffer.add_inputs(*streams[0])
    buffer.add_outputs(*streams[1])
    first, last = buffer.coverage(settled=False)
    if end_ns is None:
        end_ns = last
    if length is None:
        # Every grid instant whose input and output are both measured.
        length = max(end_ns - first, 0) / NANOSECONDS
        return buffer.window(length, sample_time, end_ns, min_length=min_length,
                             start_ns=_EARLIEST), buffer.stats()
    return buffer.window(length, sample_time, end_ns, min_length=min_length), buffer.stats()
