"""
Exact sampled-data simulation of continuous-time transfer functions.

A rational ``N(s)/D(s)`` (optionally with a dead time ``e^{-tau s}``) is applied to a signal
known only at the sample instants ``t_k = k*ts`` under an intersample assumption:

* ``'zoh'``: the signal is held constant between samples (exact for a zero-order-hold input);
* ``'foh'``: the signal is linear between samples (the usual assumption for a measured output);
  it is zero before ``t_0`` and jumps to ``u_0`` there, as in ``scipy.signal.lsim``, also when
  delayed.

The response is exact for that assumption, including dead times that are not a multiple of the
sample time: ``tau = d*ts + eps`` splits each sample interval into two sub-intervals whose
matrix exponentials are composed (the modified discretisation). Everything starts at rest.

Numerics (``docs/algorithm.md`` section 4): the denominator is time-scaled so its roots are O(1),
realised in controllable canonical form whose states are ``s^j/D(s)`` applied to the signal
(so any numerator of degree <= deg D is just an output map of one state simulation), diagonally
balanced, discretised with one matrix exponential per sub-interval, and propagated in modal
(eigenvector, else complex Schur) coordinates where every mode is a first-order recursion run by
:func:`recursions` (LAPACK's banded triangular solve, the forward substitution of
``scipy.signal.lfilter``, for all modes at once, or block products of pole powers on long
records). On long records the uncoupled modes are held in real form, a complex mode as its real
and imaginary parts (:func:`_form_recursions`), so that output maps are real products.
A repeated root (the state-variable filters ``1/(p + lam)^n``) runs as one real Jordan chain,
on long records all its states in blocks at once, and several such filters (or first-order
ones) over one signal run together (:func:`filter_responses`). No high-order difference
equation is ever formed, so precision holds up to high orders, and no Python loop runs per
sample.
"""

import cmath
from dataclasses import dataclass
from functools import cached_property, lru_cache, partial
import math
import threading
from typing import Callable, Dict, Iterable, List, Optional, Sequence, Tuple

from ctid_ros.errors import DataError, ModelError
import numpy as np
from scipy import linalg
from scipy.linalg import blas, lapack

__all__ = ['ContinuousFilter', 'DiscreteFilter', 'INTERSAMPLE', 'Sample', 'StateResponse',
           'all_finite', 'all_pole', 'companion_roots', 'filter_responses', 'polynomial_roots',
           'recursions', 'response', 'responses', 'shifted', 'skew_delay', 'skew_extended']

INTERSAMPLE = ('zoh', 'foh')
# Discretisations kept for every caller (:meth:`ContinuousFilter.discretize`), latest last.
_SHARED_DISCRETIZATIONS = 64
_DISCRETIZATIONS: Dict[Tuple, 'DiscreteFilter'] = {}
_DISCRETIZATIONS_LOCK = threading.Lock()
# Above this condition number of the eigenvector basis the propagation uses the Schur form.
_MODAL_CONDITION_LIMIT = 1e4
# Poles whose magnitudes are further apart than this factor are left to the matrix exponential,
# which reports them as beyond floating point.
_MODAL_RANGE_LIMIT = 1e30
# Above this amplification of rounding by the partial fractions of 1/D^2 (residues squared times
# the poles' spread, in the scaled variable) responses through 1/D^2 are simulated in their own
# (Schur) coordinates instead of as the double-pole chains of D's modes.
_SQUARED_AMPLIFICATION_LIMIT = 1e6
# Highest order of a single repeated root (the state-variable filters (p + lam)^n) propagated as
# one real Jordan chain (binomial basis; beyond this its coefficients grow): else Schur form.
_CHAIN_MAX_ORDER = 8
# The reductions behind the array methods ``sum``, ``all``, ``prod`` and ``any`` (axis None
# for the whole array; the same values), called directly: the methods and np.any reach them
# through Python functions of numpy's, several calls per small array. The extremes of a
# handful of values are Python's max and min of their floats, without a ufunc's set-up.
_SUM = np.add.reduce
_ALL = np.logical_and.reduce
_PROD = np.multiply.reduce
_ANY = np.logical_or.reduce
# Up to this many values Python's own tests and reductions cost less than one ufunc reduction,
# most of whose cost is its iterator's set-up.
_FEW_VALUES = 16


def _polynomial(coefficients, what: str) -> np.ndarray:
    """Return float coefficients (highest power first) without leading zeros."""
    array = np.asarray(coefficients, dtype=float)
    if array.ndim == 0:
        array = array.reshape(1)                    # np.atleast_1d's, without its wrapper
    if array.ndim != 1 or array.size == 0:
        raise ModelError(f'{what} must be a 1-D coefficient sequence')
    if not all_finite(array):
        raise ModelError(f'{what} has non-finite coefficients: {array}')
    if array[0] != 0.0:
        return array
    nonzero = np.flatnonzero(array)
    if nonzero.size == 0:
        return np.zeros(1)
    return array[nonzero[0]:]


def all_finite(values: np.ndarray) -> bool:
    """
    Return True if every value (real or complex) is finite.

    The ufuncs' own calls instead of ``np.isfinite(values).all()``, which reaches the
    reduction through a Python wrapper; a few values (the coefficients and small matrices
    tested for every candidate) by ``cmath.isfinite`` on their Python numbers, without a
    ufunc's set-up. Not a sum tested once: the sum of ``+inf`` and ``-inf``, or one
    that overflows, raises a RuntimeWarning, and silencing it costs more.
    """
    if values.size <= _FEW_VALUES:
        return all(map(cmath.isfinite, values.ravel().tolist()))
    return bool(_ALL(np.isfinite(values), None))


def _check_intersample(intersample: str) -> None:
    if intersample not in INTERSAMPLE:
        raise ModelError(f'intersample must be one of {INTERSAMPLE}, got {intersample!r}')


def polynomial_roots(coefficients: np.ndarray) -> np.ndarray:
    """
    Return ``np.roots(coefficients)`` (read-only) for float coefficients, highest power first.

    The few latest polynomials are remembered: the estimator asks for the roots of one
    denominator to check its stability, to scale its realisation and for its settling time.
    """
    return _roots(np.asarray(coefficients, dtype=float).tobytes())


@lru_cache(maxsize=16)
def _roots(key: bytes) -> np.ndarray:
    coefficients = np.frombuffer(key)
    roots = _low_order_roots(coefficients)
    if roots is None:
        roots = companion_roots(coefficients)
    roots.setflags(write=False)
    return roots


def _low_order_roots(coefficients: np.ndarray) -> Optional[np.ndarray]:
    """
    Return the roots of a first- or second-degree polynomial in closed form, else None.

    ``np.roots`` builds a companion matrix and calls LAPACK's eigenvalue routine, mostly call
    overhead at these degrees; the estimator asks for the roots of every candidate
    denominator. Real roots come as a float array, complex ones as a complex array, as
    ``np.roots`` gives them; the quadratic takes the larger root first and the other from
    their product, so neither cancels.
    """
    if coefficients.size not in (2, 3) or coefficients[0] == 0.0:
        return None
    # Python floats and math (IEEE divisions and square roots, as numpy's): no numpy scalars
    # per candidate.
    if coefficients.size == 2:
        lead, last = coefficients.tolist()
        if not (math.isfinite(lead) and math.isfinite(last)):
            return None
        return np.array([-last / lead])
    a, b, c = coefficients.tolist()
    discriminant = b * b - 4.0 * a * c
    # Not finite where a coefficient is not (an infinity meets a product, NaNs propagate) or
    # the squares overflow.
    if not math.isfinite(discriminant):
        return None
    if discriminant < 0.0:
        real, imaginary = -b / (2.0 * a), math.sqrt(-discriminant) / (2.0 * abs(a))
        return np.array([complex(real, imaginary), complex(real, -imaginary)])
    half = -0.5 * (b + math.copysign(math.sqrt(discriminant), b))
    if half == 0.0:
        return None
    return np.array([half / a, c / half])


def companion_roots(coefficients: np.ndarray) -> np.ndarray:
    """
    Return ``np.roots(coefficients)``: the eigenvalues of its own companion matrix.

    Formed here as ``np.roots`` forms it, without its stripping of zero coefficients and
    stacking of zero roots where there are none (every candidate denominator of a fit); else
    ``np.roots`` itself.
    """
    n = coefficients.size - 1
    if n < 2 or coefficients[0] == 0.0 or coefficients[-1] == 0.0:
        return np.roots(coefficients)
    companion = np.zeros((n, n))
    companion.flat[n::n + 1] = 1.0                  # the subdiagonal
    companion[0, :] = -coefficients[1:] / coefficients[0]
    return np.linalg.eigvals(companion)


def _time_scale(roots: np.ndarray) -> float:
    """Geometric mean of the nonzero root magnitudes: makes the scaled coefficients O(1)."""
    if roots.size == 0:
        return 1.0
    magnitudes = abs(roots)
    # The largest of a handful of magnitudes (none negative) by Python's max of their floats.
    magnitudes = magnitudes[magnitudes > 1e-12 * max(1.0, *magnitudes.tolist())]
    if magnitudes.size == 0:
        return 1.0
    logarithms = np.log(magnitudes)
    # np.mean's own arithmetic (the sum, then one division), without its dispatch.
    return float(np.exp(np.add.reduce(logarithms) / logarithms.size))


class ContinuousFilter:
    """
    Realisation of ``1/D(s)`` whose states give every ``N(s)/D(s)`` by an output map.

    Parameters
    ----------
    den : array_like
        Denominator coefficients, highest power first; the leading one must be nonzero.

    """

    def __init__(self, den):
        den = _polynomial(den, 'denominator')
        if den[0] == 0.0:
            raise ModelError('denominator is identically zero')
        self.den = den
        self.order = den.size - 1
        # The roots scale the realisation and give its modes: found once (den is a float
        # array already: polynomial_roots' conversion is skipped).
        self._roots = _roots(den.tobytes()) if den.size > 1 else np.zeros(0)
        self.scale = _time_scale(self._roots)
        n = self.order
        # D(scale * z) / (den[0] * scale**n) is monic in the scaled Laplace variable z.
        with np.errstate(over='ignore', invalid='ignore', divide='ignore'):
            powers = self.scale ** np.arange(n, -1, -1, dtype=float)
            monic = den * powers / (den[0] * powers[0])
            self._gain = 1.0 / (den[0] * powers[0])
            self._powers = powers[::-1].copy()
        # Roots hundreds of decades apart (numbers like 1.5**490 in the model text) overflow
        # the scaled coefficients: say so instead of failing inside scipy with NaNs.
        if not (all_finite(monic) and math.isfinite(self._gain) and self._gain != 0.0):
            raise ModelError(f'the denominator {den} has roots too many decades apart to '
                             'simulate in floating point')
        self._monic_ascending = monic[::-1]            # a_0 .. a_n with a_n = 1
        a = np.zeros((n, n))
        if n > 1:
            a.flat[1::n + 1] = 1.0                      # the superdiagonal
            a[-1, :] = -self._monic_ascending[:-1]
            # Diagonal balancing keeps the companion matrix well conditioned: LAPACK's gebal
            # as linalg.matrix_balance(a, permute=False, separate=True) calls it, without its
            # per-call validation (a is finite).
            sc = lapack.dgebal(a, permute=0, scale=1)[3]
        else:
            # A 1 x 1 matrix has nothing to balance (gebal leaves it at scale 1). Ones from a
            # list: np.ones is a Python function (empty, then copyto) for a single value.
            a[:] = -self._monic_ascending[:-1]
            sc = np.array([1.0] * n)
        self._balance = sc
        self._companion = a
        self._modal: Optional[_ContinuousModes] = None
        self._modal_checked = False
        self._repeated: Optional[Tuple[Optional[float]]] = None
        # Set by :attr:`modal`: (nearly) repeated roots have no eigenvector basis to try.
        self.repeated_roots = False

    @cached_property
    def a(self) -> np.ndarray:
        """
        Return the balanced companion matrix (in the scaled time), formed when first asked for.

        Only the state-space form (repeated or ill-conditioned poles, free and impulse
        responses) uses it: the modes are read off the roots.
        """
        a, scales = self._companion, self._balance
        return a / scales[:, None] * scales[None, :] if self.order else a

    @cached_property
    def b(self) -> np.ndarray:
        """Return the balanced input vector of :attr:`a`'s realisation (the last state's)."""
        unit = np.zeros(self.order)
        if self.order:
            unit[-1] = 1.0
        return unit / self._balance

    @property
    def modal(self) -> Optional['_ContinuousModes']:
        """Return the uncoupled modes of the realisation, None if they are ill-conditioned."""
        if not self._modal_checked:
            self._modal = _continuous_modes(self)
            self._modal_checked = True
        return self._modal

    @property
    def repeated_root(self) -> Optional[float]:
        """
        Return ``z0`` (scaled) if ``D`` is ``den[0] (s - scale z0)^n`` to rounding, else None.

        To rounding: the scaled monic coefficients within 1e-14 (plus as much relative) of the
        binomial ones of the roots' mean.

        A single real root of multiplicity ``n`` (2 to :data:`_CHAIN_MAX_ORDER`), as the
        state-variable filters ``(p + lam)^n`` of the equation-error starts have: their states
        are propagated as one real Jordan chain (:class:`_Chain`) instead of in the complex Schur
        coordinates that the root, split by rounding into a cluster, would otherwise need.
        """
        # Asked for by every discretisation (each dead time and hold): found once.
        if self._repeated is None:
            self._repeated = (self._repeated_root(),)
        return self._repeated[0]

    def _repeated_root(self) -> Optional[float]:
        n = self.order
        if not 2 <= n <= _CHAIN_MAX_ORDER:
            return None
        root = -float(self._monic_ascending[n - 1]) / n               # mean of the scaled roots
        # np.poly's own rounding of (p + lam)^n stays within 3e-15 here (n <= 8, lam from 1e-4
        # to 1e4); roots 2e-7 apart already differ by 1e-14. Each binomial coefficient is
        # formed only if the ones before matched (distinct roots differ at once).
        for j, value in enumerate(self._monic_ascending.tolist()):
            target = math.comb(n, j) * (-root) ** (n - j)
            if abs(value - target) > 1e-14 * (1.0 + abs(target)):
                return None
        return root

    def output_map(self, num) -> Tuple[np.ndarray, float]:
        """
        Row ``c`` and feedthrough ``d`` such that ``N(s)/D(s) u = c x + d u``.

        Raises
        ------
        ModelError
            If ``deg N > deg D`` (improper).

        """
        num = _polynomial(num, 'numerator')
        n = self.order
        if num.size - 1 > n and np.any(num[:num.size - 1 - n] != 0.0):
            raise ModelError(f'improper transfer function: numerator degree {num.size - 1} '
                             f'exceeds denominator degree {n}')
        num = num[-(n + 1):] if num.size > n + 1 else num
        ascending = np.zeros(n + 1)
        # N(scale * z) scaled the same way as the monic denominator.
        coefficients = num[::-1] * self.scale ** np.arange(num.size)
        ascending[:num.size] = coefficients * self._gain
        feedthrough = ascending[n]
        row = ascending[:n] - feedthrough * self._monic_ascending[:n]
        return row * self._balance, float(feedthrough)

    def output_maps(self, numerators: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """
        Rows ``c_q`` and feedthroughs ``d_q`` of :meth:`output_map` for the rows of an array.

        ``numerators`` is ``(q, L)``, highest power first, every row padded to the same length
        ``L``; one pass over all of them, with the arithmetic of :meth:`output_map` per row.

        Raises
        ------
        ModelError
            If a coefficient is not finite or a numerator exceeds the degree of ``D``.

        """
        numerators = np.asarray(numerators, dtype=float)
        if not all_finite(numerators):
            raise ModelError(f'numerator has non-finite coefficients: {numerators}')
        n = self.order
        if numerators.shape[1] > n + 1:             # else there is nothing to cut
            numerators = _without_leading_zeros(numerators, n, f'denominator degree {n}')
        size = numerators.shape[1]
        # N(scale * z) scaled the same way as the monic denominator; numerators of every
        # power (the most common rows) need no zeros for the powers they lack.
        scaled = numerators[:, ::-1] * self._powers[:size] * self._gain
        if size == n + 1:
            ascending = scaled
        else:
            ascending = np.zeros((numerators.shape[0], n + 1))
            ascending[:, :size] = scaled
        feedthroughs = ascending[:, n]
        rows = ascending[:, :n] - feedthroughs[:, None] * self._monic_ascending[:n]
        return rows * self._balance, feedthroughs

    def discretize(self, ts: float, delay: float = 0.0,
                   intersample: str = 'zoh') -> 'DiscreteFilter':
        """Exact discretisation for the intersample assumption, including a fractional delay."""
        _check_intersample(intersample)
        # Shared by every caller: the starts' state-variable filters and the estimator's
        # denominators come back within a fit and from fit to fit on one record.
        key = (self.den.tobytes(), float(ts), float(delay), intersample)
        with _DISCRETIZATIONS_LOCK:
            # A hit moves to the end (the latest used) under the one lock.
            discrete = _DISCRETIZATIONS.pop(key, None)
            if discrete is not None:
                _DISCRETIZATIONS[key] = discrete
                return discrete
        # Checked before a discretisation is kept: every key kept is valid, and an invalid
        # one (a NaN never equals a key) always arrives here.
        if not (math.isfinite(ts) and ts > 0):
            raise DataError(f'sample time must be positive and finite, got {ts}')
        if not (math.isfinite(delay) and delay >= 0):
            raise ModelError(f'dead time must be non-negative and finite, got {delay}')
        discrete = self._discretization(ts, delay, intersample)
        with _DISCRETIZATIONS_LOCK:
            _DISCRETIZATIONS[key] = discrete
            while len(_DISCRETIZATIONS) > _SHARED_DISCRETIZATIONS:
                del _DISCRETIZATIONS[next(iter(_DISCRETIZATIONS))]
        return discrete

    def _discretization(self, ts: float, delay: float, intersample: str) -> 'DiscreteFilter':
        scaled_ts = ts * self.scale
        whole = math.floor(delay / ts + 1e-12)
        fraction = delay / ts - whole
        if fraction < 1e-12 or fraction > 1.0 - 1e-12:
            whole = int(round(delay / ts))
            fraction = 0.0
        segments, feed = _delayed_segments(whole, fraction, intersample)
        # On the sample lattice a held input jumps at the sample instants themselves: the
        # delayed input just before t_k is the previous sample (zoh), or reads as zero before
        # the first one (foh). Elsewhere both limits are the feedthrough value.
        feed_left = feed
        if fraction == 0.0:
            feed_left = {(-whole - 1, False): 1.0} if intersample == 'zoh' else \
                {(-whole, True): 1.0}
        scaled_segments = [(length * scaled_ts, start, end) for length, start, end in segments]
        root = self.repeated_root
        if root is not None:
            # Checked first: the modes of a root repeated n times are not tried at all.
            chain = _Chain.discretize(self, root, scaled_segments)
            if chain is not None:
                return DiscreteFilter(self, ts, scaled_segments, feed, feed_left, chain=chain)
        modal = self.modal
        if modal is not None:
            discrete_modes = modal.discretize(scaled_segments)
            if discrete_modes is None:
                self._too_far_apart(ts)
            return DiscreteFilter(self, ts, scaled_segments, feed, feed_left, discrete_modes)
        discrete = DiscreteFilter(self, ts, scaled_segments, feed, feed_left)
        discrete.transition     # discretised now: an overflow is an error here
        return discrete

    def _too_far_apart(self, ts: float) -> None:
        # A time scale ratio far beyond any physical model (1e36 and more) overflows the matrix
        # exponential: an error, rather than NaNs that fail later inside numpy.
        raise ModelError(f'the denominator {self.den} has roots too many decades apart to '
                         f'discretise with sample time {ts}')

    def state_discretization(self, segments) -> Tuple[np.ndarray, Dict['Sample', np.ndarray]]:
        """
        Return ``Ad`` and the drive vectors ``B_o`` of the sub-intervals ``segments``.

        ``segments`` are ``(scaled length, values at start, values at end)`` as
        :func:`_delayed_segments` gives them with lengths times ``ts * scale``: one matrix
        exponential per sub-interval.
        """
        return _state_discretization(self.a, self.b, segments)


def _state_discretization(a: np.ndarray, b: np.ndarray, segments
                          ) -> Tuple[np.ndarray, Dict['Sample', np.ndarray]]:
    """
    Return ``Ad`` and the drive vectors ``B_o`` of ``x' = a x + b u`` over ``segments``.

    ``segments`` as :meth:`ContinuousFilter.state_discretization` takes them: one matrix
    exponential with its hold integrals per sub-interval (:func:`_hold_integrals`).
    """
    transition = np.eye(a.shape[0])
    drive: Dict[Sample, np.ndarray] = {}
    for length, start, end in segments:
        e, integral, ramp = _hold_integrals(a, b, length)
        transition = e @ transition
        drive = {sample: e @ vector for sample, vector in drive.items()}
        _accumulate(drive, (start, integral - ramp), (end, ramp))
    return transition, drive


def _accumulate(terms: Dict['Sample', np.ndarray],
                *parts: Tuple[Dict['Sample', float], np.ndarray]) -> None:
    # ``parts``: (combination of samples, vector) in turn, a sub-interval's two ends in one call.
    for combination, vector in parts:
        for sample, weight in combination.items():
            # A weight of 1 (every held input's) and a first term need no arithmetic: the same
            # values. Terms are never written in place, so one array may serve several samples.
            term = vector if weight == 1.0 else weight * vector
            terms[sample] = terms[sample] + term if sample in terms else term


# A sample of the signal relative to the current step k: (offset, masked). ``masked`` marks the
# sample at the END of a delayed FOH interval; it reads as zero when it is the first sample u_0,
# because the signal is zero before t_0 (it jumps to u_0 at t_0 instead of ramping up from an
# imaginary u_{-1} = 0 over the preceding interval). Delaying by whole samples then shifts the
# response exactly, and the undelayed FOH response is unchanged.
Sample = Tuple[int, bool]


def _delayed_segments(whole: int, fraction: float, intersample: str):
    """
    Sub-intervals of one sample period and the input values at their ends.

    Each segment is ``(length as a fraction of ts, value at start, value at end)`` where a value
    is a linear combination ``{sample: weight}`` of input samples relative to ``k`` (see
    :data:`Sample`). The feedthrough combination gives the delayed input at the sample instant
    itself (its right limit).
    """
    d = whole
    if fraction == 0.0:
        if intersample == 'zoh':
            return [(1.0, {(-d, False): 1.0}, {(-d, False): 1.0})], {(-d, False): 1.0}
        return [(1.0, {(-d, False): 1.0}, {(-d + 1, True): 1.0})], {(-d, False): 1.0}
    beta = 1.0 - fraction
    if intersample == 'zoh':
        first, second = {(-d - 1, False): 1.0}, {(-d, False): 1.0}
        return [(fraction, first, first), (beta, second, second)], first
    # First segment: inside delayed interval k-d-1, second: inside delayed interval k-d.
    start = {(-d - 1, False): 1.0 - beta, (-d, True): beta}
    left = {(-d, True): 1.0}
    right = {(-d, False): 1.0}
    end = {(-d, False): 1.0 - beta, (-d + 1, True): beta}
    return [(fraction, start, left), (beta, right, end)], start


def _hold_integrals(a: np.ndarray, b: np.ndarray, h: float):
    """``e^{Ah}``, ``int_0^h e^{As} ds B`` and ``(1/h) int_0^h e^{A(h-s)} B s ds``."""
    n = a.shape[0]
    block = np.zeros((n + 2, n + 2))
    block[:n, :n] = a * h
    block[:n, n] = b * h
    block[n, n + 1] = 1.0
    exponential = linalg.expm(block)
    return exponential[:n, :n], exponential[:n, n], exponential[:n, n + 1]


def shifted(values: np.ndarray, offset: int) -> np.ndarray:
    """``values[k + offset]`` for every k, zero outside the record (signals start at rest)."""
    count = values.shape[0]
    # np.zeros_like's values, without its Python wrappers (empty_like, copyto).
    out = np.zeros(values.shape, dtype=values.dtype)
    if offset >= 0:
        if offset < count:
            out[:count - offset] = values[offset:]
    elif -offset < count:
        out[-offset:] = values[:count + offset]
    return out


def _sampled(values: np.ndarray, sample: Sample) -> np.ndarray:
    """Signal of one :data:`Sample` for every k."""
    offset, masked = sample
    if masked and values.shape[0]:
        values = values.copy()
        values[0] = 0.0
    return shifted(values, offset)


def _sampled_rows(values: np.ndarray, samples: Iterable[Sample],
                  length: Optional[int] = None) -> np.ndarray:
    """
    Return :func:`_sampled` of every sample as the rows of one array.

    Written into the array directly, without a temporary per sample and the stacking copy.
    ``length``: rows of that many samples instead of the signal's, cut or padded with zeros.
    """
    samples = list(samples)
    count = values.shape[0]
    length = count if length is None else length
    rows = np.zeros((len(samples), length), dtype=values.dtype)
    for row, (offset, masked) in zip(rows, samples):
        # row[k] = values[k + offset] where both exist.
        end = min(length, count - offset)
        if offset >= 0:
            if end > 0:
                row[:end] = values[offset:offset + end]
        elif -offset < end:
            row[-offset:end] = values[:end + offset]
        # The masked first sample, wherever the shift put it.
        if masked and 0 <= -offset < length:
            row[-offset] = 0.0
    return rows


class DiscreteFilter:
    """
    ``x[k+1] = Ad x[k] + sum_o B_o u[k+o]`` realising a :class:`ContinuousFilter` exactly.

    Where the realisation has well-conditioned uncoupled modes the filter is discretised mode
    by mode in closed form (:attr:`modes`) and simulations use only that; ``transition`` and
    ``drive`` (the state-space form, for stepping a plant or free responses) are then formed
    with matrix exponentials when first asked for.
    """

    def __init__(self, continuous: ContinuousFilter, ts: float, segments,
                 feed: Dict[Sample, float],
                 feed_left: Optional[Dict[Sample, float]] = None,
                 modes: Optional['_DiscreteModes'] = None, chain: Optional['_Chain'] = None):
        self.continuous = continuous
        self.ts = ts
        self.feed = feed
        self.feed_left = feed_left
        self.modes = modes
        self.chain = chain
        self._segments = segments
        self._state_space: Optional[Tuple[np.ndarray, Dict[Sample, np.ndarray]]] = None

    def _discretized(self) -> Tuple[np.ndarray, Dict[Sample, np.ndarray]]:
        if self._state_space is None:
            transition, drive = self.continuous.state_discretization(self._segments)
            if not all(np.all(np.isfinite(matrix)) for matrix in [transition, *drive.values()]):
                self.continuous._too_far_apart(self.ts)
            self._state_space = transition, drive
        return self._state_space

    @property
    def transition(self) -> np.ndarray:
        """``Ad``, the state transition over one sample time."""
        return self._discretized()[0]

    @property
    def drive(self) -> Dict[Sample, np.ndarray]:
        """``B_o`` by input sample relative to ``k`` (see :data:`Sample`)."""
        return self._discretized()[1]

    def states(self, values: np.ndarray) -> np.ndarray:
        """State trajectory (N x n) for the sampled signal, starting at rest."""
        return self._mapped(values, np.eye(self.continuous.order)).T

    def _mapped(self, values: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """``rows @ x[k]`` for every k, shape (q, N)."""
        return self.response(values).mapped(rows)

    def response(self, values: np.ndarray) -> 'StateResponse':
        """
        Return the state trajectory of ``values``, from which any output map is read.

        One simulation serves every numerator asked for later (:meth:`StateResponse.outputs`):
        a caller that wants the output now and its sensitivities at the same parameters later
        keeps the response instead of simulating twice.
        """
        return StateResponse(self, values)

    def free_responses(self, count: int) -> np.ndarray:
        """
        Basis of the free (initial-state) responses of ``1/D`` at ``k = 0..count-1``.

        Returns ``(count, n)``: column ``i`` is the output ``1/D`` would show from the initial
        state ``e_i`` (the realisation is observable, so the columns span every response of a
        nonzero initial state).
        """
        n = self.continuous.order
        if n == 0:
            return np.zeros((count, 0))
        row, _ = self.continuous.output_map(np.ones(1))
        impulse = np.zeros((1, count + 1))
        impulse[0, 0] = 1.0
        # x[k+1] = A^T x[k] + row^T impulse[k] gives x[k+1] = (row A^k)^T: all n columns at once.
        return _propagate(self.transition.T, impulse, row[None, :], np.eye(n))[:, 1:].T

    def impulse_responses(self, numerators: Iterable, count: int) -> np.ndarray:
        """
        Impulse responses of the strictly proper ``N_q(s)/D(s)`` at ``t = k ts``, shape (q, count).

        The response to a unit impulse at ``t = 0`` (the free response from the state it leaves),
        exact at the samples. The free responses of :meth:`free_responses` are those of the
        numerators ``s^j``, ``j < deg D``, in another basis.
        """
        continuous = self.continuous
        rows = []
        for num in numerators:
            row, feed = continuous.output_map(num)
            if feed != 0.0:
                raise ModelError('an impulse response needs a strictly proper N/D')
            rows.append(row)
        n = continuous.order
        if n == 0:
            return np.zeros((len(rows), count))
        impulse = np.zeros((1, count + 1))
        impulse[0, 0] = 1.0
        # A unit impulse in seconds is `scale` units of impulse in the scaled time.
        return _propagate(self.transition, impulse, continuous.scale * continuous.b[None, :],
                          np.asarray(rows))[:, 1:]

    def delayed_input(self, values: np.ndarray, left: bool = False) -> np.ndarray:
        """
        Return the delayed, held input at the sample instants (the feedthrough signal).

        Its right limit (the value from ``t_k`` on), or with ``left`` its left limit (just
        before ``t_k``); they differ only where the delayed input jumps at the sample instants,
        i.e. for a held input whose dead time is a whole number of samples.
        """
        feed = self.feed_left if left and self.feed_left is not None else self.feed
        result = None
        # Each sample's signal is a new array, scaled in place; the first is the sum so far
        # (0 + x is x): no zero-filled sum and product per term.
        for sample, weight in feed.items():
            term = _sampled(values, sample).astype(float, copy=False)
            term *= weight
            if result is None:
                result = term
            else:
                result += term
        return np.zeros(values.shape[0]) if result is None else result

    def outputs(self, values: np.ndarray, numerators: Iterable) -> np.ndarray:
        """``N_q(s)/D(s)`` applied to the signal for every numerator, shape (q, N)."""
        return self.response(values).outputs(numerators)


class StateResponse:
    """
    The state trajectory of one signal through a :class:`DiscreteFilter`, in modal form.

    :meth:`outputs` gives ``N_q(s)/D(s)`` of the signal for any numerators without simulating
    again; the values are those :meth:`DiscreteFilter.outputs` returns.
    """

    def __init__(self, discrete: DiscreteFilter, values: np.ndarray):
        self._start(discrete, values)
        if self._continuous.order:
            if discrete.modes is not None:
                # Padded to whole blocks: the recursions read them without another copy.
                signals = _sampled_rows(values, discrete.modes.samples,
                                        -(-self._count // _BLOCK) * _BLOCK)
                self._hold_modes(discrete.modes, signals,
                                 discrete.modes.run(signals, self._count))
            elif discrete.chain is not None:
                signals = _sampled_rows(values, discrete.chain.samples,
                                        -(-self._count // _BLOCK) * _BLOCK)
                self._modes = discrete.chain.run(signals, self._count)
            else:
                drive = discrete.drive
                signals = _sampled_rows(values, drive)
                self._modes = _Modes(discrete.transition, signals, np.array(list(drive.values())),
                                     self._continuous.repeated_roots)

    def _start(self, discrete: DiscreteFilter, values: np.ndarray) -> None:
        self._continuous = discrete.continuous
        self._count = values.shape[0]
        self._discrete = discrete
        self._values = values
        self._held_values: Optional[np.ndarray] = None
        # A response of the same delayed input whose held values this one reads.
        self._held_by: Optional[StateResponse] = None
        self._modes = None
        self._discrete_modes: Optional[_DiscreteModes] = None
        self._signals: Optional[np.ndarray] = None
        self._chains: Optional[np.ndarray] = None
        self._padded: Optional[np.ndarray] = None

    def _hold_modes(self, discrete_modes: '_DiscreteModes', signals: np.ndarray,
                    padded: np.ndarray) -> None:
        """
        Hold the uncoupled modes' trajectories ``padded`` over the sampled ``signals``.

        ``padded`` as :meth:`_DiscreteModes.run` returns them (real form, or complex rows),
        which :meth:`squared_outputs` reads again with ``signals``.
        """
        modes = discrete_modes.continuous
        self._padded = padded
        self._modes = _Modes.uncoupled(modes.basis, modes.keep, modes.weights,
                                       padded[:, :self._count],
                                       None if padded.dtype.kind == 'c' else modes.real)
        self._discrete_modes, self._signals = discrete_modes, signals

    @classmethod
    def _of_modes(cls, discrete: DiscreteFilter, values: np.ndarray,
                  modes: Optional['_Modes'], held_by: Optional['StateResponse'],
                  signals: Optional[np.ndarray] = None,
                  padded: Optional[np.ndarray] = None) -> 'StateResponse':
        """
        Return the response whose modes were run already (:func:`filter_responses`).

        ``modes``: a chain's modes; or, for uncoupled modes (:attr:`DiscreteFilter.modes`),
        ``signals`` and ``padded``: the sampled signal rows and the trajectories
        :meth:`_DiscreteModes.run` would have given (:meth:`_hold_modes`).
        """
        response = cls.__new__(cls)
        response._start(discrete, values)
        response._held_by = held_by
        if padded is not None:
            response._hold_modes(discrete.modes, signals, padded)
        else:
            response._modes = modes
        return response

    def squared_outputs(self, numerators: np.ndarray) -> Optional[np.ndarray]:
        """
        ``N_q(s)/D(s)^2`` applied to the signal for the rows of ``numerators``, shape (q, N).

        The same values as a simulation through ``1/D^2`` (``numerators`` of degree up to
        ``2 deg D``, highest power first, padded to one length), read off this response's modes
        instead: with the (scaled) poles ``z_i`` and residues ``r_i`` of ``D``,
        ``N/D^2 = c + sum_i A_i/(z - z_i)^2 + B_i/(z - z_i)`` and ``r_i/(z - z_i)^2`` of the
        signal is the derivative of mode ``i`` with respect to its pole, a first-order
        recursion driven by the mode itself (the exact discretisation of the double pole's
        chain, :meth:`_DiscreteModes.chains`). So the sensitivities of an output need no
        discretisation, eigen- or Schur decomposition of ``D^2`` and no coupled recursions.
        None where ``D`` has no uncoupled modes or their partial fractions would amplify
        rounding (poles close together): then simulate through ``1/D^2``.
        """
        modes = self._discrete_modes
        if modes is None or not modes.continuous.squared:
            return None
        numerators = np.asarray(numerators, dtype=float)
        order = self._continuous.order
        if numerators.shape[1] > 2 * order + 1:     # else there is nothing to cut
            numerators = _without_leading_zeros(numerators, 2 * order,
                                                f'twice the denominator degree {order}')
        size = numerators.shape[1]
        with np.errstate(over='ignore', invalid='ignore'):
            # N(scale * z) over D(scale * z)^2, D scaled to the monic polynomial of the z_i.
            ascending = (numerators[:, ::-1] * self._continuous.scale ** np.arange(size)
                         * self._continuous._gain ** 2)
        if not all_finite(ascending):
            return None
        modal = self._modes.trajectories
        continuous = modes.continuous
        poles = continuous.poles
        # Complex modes: the modes copied under the chains, so that one product reads both off
        # (real ones, cheaper, are read off as two).
        stacked = continuous.real < poles.size
        if self._chains is None:
            length = self._signals.shape[1]
            self._chains = modes.chains(self._padded[:, :length], self._signals, self._count,
                                        self._padded if stacked else None)[:, :self._count]
        powers = poles[:, None] ** np.arange(size)
        values = ascending @ powers.T                                   # N(z_i)
        slopes = (ascending[:, 1:] * np.arange(1, size)) @ powers[:, :size - 1].T   # N'(z_i)
        weighted = continuous.residues * continuous.weights
        on_chains = values * weighted
        on_modes = (slopes - 2.0 * values * continuous.spread) * weighted
        if self._padded.dtype.kind == 'c':
            out = (np.concatenate([on_chains, on_modes], axis=1) @ self._chains).real
        elif stacked:
            out = np.concatenate([_form_map(on_chains, continuous.real),
                                  _form_map(on_modes, continuous.real)], axis=1) @ self._chains
        else:
            out = _product(on_chains, self._chains)
            out += _product(on_modes, modal)            # the same sum, into the first product
        if size == 2 * order + 1 and any(ascending[:, -1].tolist()):
            out += ascending[:, -1, None] * self._held                # np.outer's product
        return out

    @property
    def _held(self) -> np.ndarray:
        # The delayed input itself, for feedthroughs only: a strictly proper model never asks.
        if self._held_values is None:
            self._held_values = self._discrete.delayed_input(self._values) \
                if self._held_by is None else self._held_by._held
        return self._held_values

    def mapped(self, rows: np.ndarray) -> np.ndarray:
        """``rows @ x[k]`` for every k, shape (q, N)."""
        if self._modes is None:
            return np.zeros((rows.shape[0], self._count))
        return self._modes.mapped(rows)

    def outputs(self, numerators: Iterable) -> np.ndarray:
        """
        ``N_q(s)/D(s)`` applied to the signal for every numerator, shape (q, N).

        ``numerators``: 1-D coefficient arrays, or the rows of a 2-D array; numerators of one
        length are mapped in one pass (:meth:`ContinuousFilter.output_maps`).
        """
        if isinstance(numerators, np.ndarray) and numerators.ndim == 2:
            rows, feeds = self._continuous.output_maps(numerators)
        else:
            numerators = list(numerators)
            if numerators and all(isinstance(num, np.ndarray) and num.ndim == 1 and
                                  num.size == numerators[0].size for num in numerators):
                rows, feeds = self._continuous.output_maps(np.array(numerators))
            else:
                rows, feeds = zip(*(self._continuous.output_map(num) for num in numerators))
                rows, feeds = np.asarray(rows), np.asarray(feeds)
        # The real part of complex modes copied out; any other map is a new array already.
        out = np.ascontiguousarray(self.mapped(rows))
        # The feedthrough only on the rows that have one (often one row of many, the highest
        # power of a state-variable filter): the others would add zeros. ``feeds`` is 1-D:
        # its own nonzero() is np.flatnonzero's, without numpy's Python wrappers.
        for index in feeds.nonzero()[0].tolist():
            out[index] += feeds[index] * self._held
        return out


def _product(left: np.ndarray, right: np.ndarray, out: Optional[np.ndarray] = None
             ) -> np.ndarray:
    """
    Return ``left @ right``; for one real row of ``right``, as the broadcast product.

    A sum of one term is that product, which numpy's matmul forms several times slower (one
    mode of a first-order model, one input sample driving the modes, on every simulation and
    sensitivity). A complex ``left`` times the real row is the same product too: the zero
    imaginary part adds nothing. ``out``, if given, receives the product and is returned.
    """
    if right.shape[0] == 1 and right.dtype.kind == 'f':
        return np.multiply(left, right, out=out)
    return np.matmul(left, right, out=out)


def _propagate(transition: np.ndarray, signals: np.ndarray, drives: np.ndarray,
               rows: np.ndarray) -> np.ndarray:
    """Return ``rows @ x[k]``, ``x[k+1] = A x[k] + drives.T @ signals[:, k]``, ``x[0] = 0``."""
    return _Modes(transition, signals, drives).mapped(rows)


class _Modes:
    """
    The modal trajectories of ``x[k+1] = A x[k] + drives.T @ signals[:, k]``, ``x[0] = 0``.

    Each mode is a first-order recursion run by :func:`recursions`. When the
    eigenvectors of ``A`` form a well-conditioned basis the modes are uncoupled and, the signals
    being real, only one mode of each conjugate pair is run; otherwise (repeated poles, as in
    ``D^2``) the modes are the coupled ones of the complex Schur form. :meth:`mapped` reads
    ``rows @ x[k]`` off them.

    """

    def __init__(self, transition: np.ndarray, signals: np.ndarray, drives: np.ndarray,
                 repeated: bool = False):
        self._real: Optional[int] = None
        self._basis, self._keep, self._weights, self._modal = _modes(transition, signals,
                                                                     drives, repeated)

    @classmethod
    def uncoupled(cls, basis: np.ndarray, keep: Optional[np.ndarray], weights: np.ndarray,
                  modal: np.ndarray, real: Optional[int]) -> '_Modes':
        """
        Return the modes already run (:meth:`_DiscreteModes.run`).

        ``modal``: their trajectories in the real form of :func:`_form_recursions`, whose
        first ``real`` modes are real; or one row per mode (``real`` None).
        """
        modes = cls.__new__(cls)
        modes._basis, modes._keep, modes._weights, modes._modal = basis, keep, weights, modal
        modes._real = real
        return modes

    @property
    def trajectories(self) -> np.ndarray:
        """
        Return the modal trajectories, one row per mode run (kept modes if uncoupled).

        Uncoupled modes (:meth:`uncoupled`) of a long record in real form (``real`` given),
        the others one row each, complex where their poles are.
        """
        return self._modal

    def mapped(self, rows: np.ndarray) -> np.ndarray:
        """Return ``rows @ x[k]`` for every k, shape (q, N)."""
        out_map = rows @ self._basis
        if self._keep is not None:
            out_map = out_map[:, self._keep] * self._weights
        if self._real is not None:
            return _product(_form_map(out_map, self._real), self._modal)
        return _product(out_map, self._modal).real


def _modes(transition: np.ndarray, signals: np.ndarray, drives: np.ndarray,
           repeated: bool = False):
    """
    Return the basis, the modes kept and their weights, and the modal trajectories.

    ``repeated``: the poles are known to repeat (as those of ``D^2``), so the eigenvectors
    are not tried.
    """
    eigenvalues, vectors = (None, None) if repeated else np.linalg.eig(transition)
    if not repeated and np.linalg.cond(vectors) <= _MODAL_CONDITION_LIMIT:
        keep = eigenvalues.imag >= 0.0
        poles = eigenvalues[keep]
        coupling = None
        modal_drives = np.linalg.solve(vectors, drives.T)[keep]
        # A conjugate partner contributes the conjugate: twice the real part in total.
        basis, weights = vectors, np.where(poles.imag > 0.0, 2.0, 1.0)
    else:
        upper, unitary = linalg.schur(transition, output='real')
        if np.any(np.diag(upper, -1)):
            # Complex poles: 2x2 blocks in the real form, so use the complex triangular one.
            upper, unitary = linalg.schur(transition.astype(complex), output='complex')
        poles = np.diag(upper)
        coupling = upper
        modal_drives = unitary.conj().T @ drives.T
        basis, keep, weights = unitary, None, None
    return basis, keep, weights, _run(poles, coupling, modal_drives @ signals)


def _run(poles: np.ndarray, coupling: Optional[np.ndarray], driving: np.ndarray) -> np.ndarray:
    """Modal trajectories: ``modal[i, k+1] = pole_i modal[i, k] + driving[i, k]`` (+ coupling)."""
    count = driving.shape[1]
    modal = np.zeros(driving.shape, dtype=driving.dtype)
    if count < 2:
        return modal
    if coupling is None:
        # Uncoupled: the real modes in one solve, the complex ones in another; a real mode of
        # real signals has only rounding in any imaginary part of its driving. Modes all of
        # one kind (the usual case) run without selecting rows.
        if poles.dtype.kind != 'c':
            modal[:, 1:] = recursions(poles, driving[:, :count - 1].real)
            return modal
        real = poles.imag == 0.0
        if not real.any():
            modal[:, 1:] = recursions(poles, driving[:, :count - 1])
            return modal
        modal[real, 1:] = recursions(poles[real].real, driving[real, :count - 1].real)
        if not real.all():
            modal[~real, 1:] = recursions(poles[~real], driving[~real, :count - 1])
        return modal
    for i in range(poles.size - 1, -1, -1):
        if i + 1 < poles.size:
            driving[i] += coupling[i, i + 1:] @ modal[i + 1:]
        modal[i, 1:] = recursions(poles[i:i + 1], driving[i:i + 1, :count - 1])[0]
    return modal


# The coefficients of no complex modes (:func:`_form_recursions`).
_NO_PAIRS = np.zeros((0, 0), dtype=complex)


def _form_drives(drives: np.ndarray, real: int) -> np.ndarray:
    """
    Return the real-form rows (:func:`_form_recursions`' ``out``) of the kept modes' drives.

    ``drives``: one row per kept mode, one column per signal row, the first ``real`` modes
    real. A real signal drives a complex mode's real part by the drive's real part and its
    imaginary part by the imaginary one (the interleaved parts of the complex numbers
    themselves); a real mode's drive has only rounding in any imaginary part, dropped.
    """
    if drives.dtype.kind != 'c':
        return drives
    count, signals = drives.shape
    parts = np.ascontiguousarray(drives[real:]).view(float).reshape(count - real, signals, 2)
    parts = parts.transpose(0, 2, 1).reshape(-1, signals)
    return np.concatenate([drives[:real].real, parts]) if real else parts


def _form_scaling(factors: np.ndarray, real: int) -> np.ndarray:
    """
    Return the real matrix that multiplies each kept mode by its factor, in real form.

    A complex factor ``a + ib`` acts on a complex mode's parts as ``[[a, -b], [b, a]]``; a
    real mode's factor has only rounding in any imaginary part, dropped.
    """
    if factors.dtype.kind != 'c':
        return np.diag(factors)
    rows = 2 * factors.size - real
    out = np.zeros((rows, rows))
    # Python scalars: a handful of modes, no fancy indexing per call.
    for index, factor in enumerate(factors.tolist()):
        if index < real:
            out[index, index] = factor.real
        else:
            first = 2 * index - real
            out[first, first] = out[first + 1, first + 1] = factor.real
            out[first, first + 1] = -factor.imag
            out[first + 1, first] = factor.imag
    return out


def _form_map(coefficients: np.ndarray, real: int) -> np.ndarray:
    """
    Return the real map that reads ``(coefficients @ modes).real`` off the modes' real form.

    ``coefficients``: one column per kept mode, the first ``real`` modes real;
    ``Re(c m) = Re(c) Re(m) - Im(c) Im(m)``: the interleaved parts of ``conj(c)``.
    """
    if coefficients.dtype.kind != 'c':
        return coefficients
    parts = np.conjugate(coefficients[:, real:], order='C').view(float)
    return np.concatenate([coefficients[:, :real].real, parts], axis=1) if real else parts


def _trajectories(rows: int, length: int) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """
    Return rows of ``length + 1`` samples starting at rest, and the blocks of the rest.

    Recursions write sample ``k + 1`` from the drive of sample ``k``: into ``[:, 1:]``, whose
    blocks of :data:`_BLOCK` samples (if ``length`` is whole blocks) are given as one view,
    rows apart by one sample more than their length (a strided view of the same memory).
    """
    trajectories = np.empty((rows, length + 1))
    trajectories[:, 0] = 0.0
    if not rows or not length or length % _BLOCK:
        return trajectories, None
    return trajectories, np.ndarray((rows, length // _BLOCK, _BLOCK), float, trajectories,
                                    trajectories.itemsize,
                                    (trajectories.strides[0], _BLOCK * trajectories.itemsize,
                                     trajectories.itemsize))


def _form_recursions(poles: np.ndarray, real: int, driving: np.ndarray, inputs: np.ndarray,
                     coefficients: Optional[np.ndarray], out: np.ndarray,
                     blocks: Optional[np.ndarray] = None) -> None:
    """
    Write uncoupled modes ``m_i[k] = p_i m_i[k-1] + d_i[k]`` into ``out``, from rest.

    In real form: ``poles`` the kept poles, the first ``real`` of them real; ``driving`` the
    drives ``d_i`` of the real modes (one row each); a complex mode ``i`` is driven by
    ``sum_j c_ij x_j`` of the real ``inputs`` rows ``x_j`` and the rows of ``coefficients``
    ``c_ij`` (one per complex mode), or (``coefficients`` None) by ``x_2i + 1j x_2i+1``, its
    driving's real and imaginary parts; ``out``: one row per real mode, then two per complex
    mode (its real and imaginary parts), and ``blocks`` its blocks as one view if known
    (:func:`_trajectories`). Every row is contiguous, all of one length; ``inputs`` are read
    before ``out`` is written (they may be its rows). A complex mode driven by one real row
    runs without complex arrays where it runs in blocks (:func:`_blocked_pairs`): its block
    products are real ones, and every output map is a real product.
    """
    rows, length = out.shape
    if length == 0:
        return
    if real:
        _recursions(poles[:real].real, driving, out[:real], None if blocks is None else
                    blocks[:real])
    if rows == real:
        return
    pairs = poles[real:]
    # One real input: its products with the real and imaginary parts of c T, half a complex
    # product's. Several: one complex driving per mode and the complex recursions, whose
    # product has as many terms as the inputs' real ones and fewer calls.
    if coefficients is None:
        # Each mode's driving from its own two rows: the values the product with the rows
        # [1, 1j] gives (every other term is a product with zero), without casting the real
        # rows to a complex copy first.
        runs = np.empty((pairs.size, length), dtype=complex)
        runs.real = inputs[0::2]
        runs.imag = inputs[1::2]
    elif inputs.shape[0] == 1 and length % _BLOCK == 0 and \
            length >= _BLOCKED_MIN_PAIR_LENGTH and \
            all(map((1.0).__ge__, abs(pairs).tolist())) and \
            all_finite(coefficients) and all_finite(inputs):
        # Rows of whole blocks: their blocks are given (_trajectories).
        _blocked_pairs(pairs, inputs, coefficients, out[real:], blocks[real:])
        return
    else:
        runs = _product(coefficients, inputs)
    # The complex drivings run in place: no second complex array of the record's length.
    recursions(pairs, runs, runs)
    out[real::2] = runs.real
    out[real + 1::2] = runs.imag


@lru_cache(maxsize=16)
def _pole_blocks(key: bytes, kind: str) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return the pole powers ``p^0 .. p^B`` and the transposed block matrices of the poles.

    The poles are of type ``kind`` (``dtype.char``), their bytes ``key``.
    ``matrices[i, j, k] = p_i^(k - j)`` for ``k >= j``, else 0: ``block @ matrices[i]`` runs a
    block of :data:`_BLOCK` samples from rest. Both are read-only and remembered by the poles'
    bytes: a denominator's poles come back for its cost, its linearisation and its
    sensitivities' chains.
    """
    poles = np.frombuffer(key, dtype=kind)
    powers = np.zeros((poles.size, _BLOCK + 2), dtype=poles.dtype)
    powers[:, :_BLOCK + 1] = poles[:, None] ** _BLOCK_EXPONENTS       # p^0 .. p^B, then 0
    matrices = powers[:, _BLOCK_INDEX]
    powers.flags.writeable = False      # shared by every later call with these poles
    matrices.flags.writeable = False
    return powers[:, :_BLOCK + 1], matrices


def _blocks(rows: np.ndarray) -> Optional[np.ndarray]:
    """
    Return one view of every row's blocks of :data:`_BLOCK` samples, (rows, blocks, B).

    None unless the rows are of whole blocks and each contiguous (the rows themselves may be
    apart): no copy is ever made. Splitting the contiguous last axis keeps the rows' own
    stride, so numpy's reshape gives a view of rows that are apart too.
    """
    count, length = rows.shape
    if length % _BLOCK or rows.strides[1] != rows.itemsize:
        return None
    return rows.reshape(count, length // _BLOCK, _BLOCK)


def _blocked_pairs(poles: np.ndarray, inputs: np.ndarray, coefficients: np.ndarray,
                   out: np.ndarray, out_blocks: np.ndarray) -> None:
    """
    Run the complex modes of :func:`_form_recursions`, driven by one real row, in blocks.

    As :func:`_blocked_recursions` with blocks of :data:`_BLOCK`: a complex mode's blocks are
    the input's blocks times ``c T``, its block matrix scaled by the input's coefficient ``c``,
    formed as the real products with the real and imaginary parts of ``c T`` (none of a
    complex product's terms spent on the input's zero imaginary part). The products and the
    carried states' corrections are written into ``out`` (the modes' real and imaginary
    parts, a row each) in place, through ``out_blocks``, its blocks as one view.
    """
    blocks = out.shape[1] // _BLOCK
    powers, matrices = _pole_blocks(poles.tobytes(), poles.dtype.char)
    source = _blocks(inputs)[0]
    # c T for every complex mode, its real and imaginary parts contiguous.
    scaled = coefficients[:, 0, None, None] * matrices
    parts = np.ascontiguousarray(scaled.real), np.ascontiguousarray(scaled.imag)
    for index, weight in enumerate(coefficients[:, 0].tolist()):
        targets = out_blocks[2 * index:2 * index + 2]
        if weight == 0:
            targets[:] = 0.0
            continue
        for target, part in zip(targets, parts):
            np.matmul(source, part[index], out=target)
    # The state at each block's end, carried over blocks: block b + 1 gains p^(k+1) times
    # the state carried out of block b at its sample k, [Re p^(k+1), -Im p^(k+1)] times its
    # parts in the real part, [Im p^(k+1), Re p^(k+1)] in the imaginary one.
    ends = np.empty((poles.size, blocks), dtype=complex)
    ends.real = out[0::2, _BLOCK - 1::_BLOCK]
    ends.imag = out[1::2, _BLOCK - 1::_BLOCK]
    carried = np.zeros((poles.size, blocks), dtype=complex)
    carried[:, 1:] = recursions(powers[:, _BLOCK], ends)[:, :-1]
    following = powers[:, 1:]
    updates = np.stack([following.real, -following.imag, following.imag, following.real],
                       axis=2).reshape(poles.size, _BLOCK, 2, 2)
    for index, state in enumerate(carried):
        parts_of_state = state.view(float).reshape(blocks, 2).T
        for part in range(2):
            blas.dgemm(1.0, updates[index, :, part], parts_of_state, 1.0,
                       out_blocks[2 * index + part].T, overwrite_c=True)


def _without_leading_zeros(numerators: np.ndarray, degree: int, limit: str) -> np.ndarray:
    """
    Return the numerator rows (highest power first) cut to ``degree + 1`` coefficients.

    Raises ModelError naming ``limit`` if a coefficient cut off is not zero.
    """
    extra = numerators.shape[1] - (degree + 1)
    if extra > 0:
        if _ANY(numerators[:, :extra] != 0.0, None):
            raise ModelError(f'improper transfer function: numerator degree exceeds {limit}')
        numerators = numerators[:, extra:]
    return numerators


def recursions(poles: np.ndarray, values: np.ndarray,
               out: Optional[np.ndarray] = None) -> np.ndarray:
    """
    Run ``out[i, k] = poles[i] * out[i, k-1] + values[i, k]`` from rest, for every row ``i``.

    Each row is ``scipy.signal.lfilter([1], [1, -pole], row)``, without importing
    :mod:`scipy.signal` (and with it :mod:`scipy.stats`) for the simulation. Many real rows
    or long complex ones of stable poles run in blocks (:func:`_blocked_recursions`); other
    rows as lower bidiagonal triangular solves (LAPACK ``?tbtrs``, the same forward
    substitution), several rows per solve up to :data:`_BAND_SIZE` real samples or half as
    many complex ones (a longer band leaves the cache and runs several times slower per
    sample).

    ``out``, if given, receives the result (of the values' shape and the result's type) and
    is returned; blocks of whole rows are written in place (:func:`_blocked_recursions`).
    """
    return _recursions(np.asarray(poles), values, out, None)


def _recursions(poles: np.ndarray, values: np.ndarray, out: Optional[np.ndarray],
                blocks: Optional[np.ndarray], alone: bool = False) -> np.ndarray:
    """
    :func:`recursions` of the ``poles`` array (not a sequence).

    ``blocks``: ``out``'s blocks as one view, where known.

    ``alone``: each row runs in blocks or as a substitution as it would if it were the only
    row (its own size, pole and values decide), so that its values do not depend on the rows
    run with it: rows of several filters run together give each filter's values alone.
    """
    rows, length = values.shape
    complex_valued = values.dtype.kind == 'c' or poles.dtype.kind == 'c'
    dtype = complex if complex_valued else float
    if rows == 0 or length == 0:
        result = np.zeros((rows, length), dtype=dtype)
    else:
        if values.dtype != dtype:               # else astype(copy=False) returns them as they are
            values = values.astype(dtype)
        # Finite values only: a block's product would spread a NaN or inf to the samples
        # before it. The checks are the ufuncs' reductions, without numpy's Python wrappers.
        # Blocks where they are worth it: a complex row of _BLOCKED_MIN_COMPLEX_LENGTH
        # samples, real rows of _BLOCKED_MIN_LENGTH and _BLOCKED_MIN_SIZE in all.
        if length >= _BLOCKED_MIN_COMPLEX_LENGTH if complex_valued else \
                length >= _BLOCKED_MIN_LENGTH and \
                (1 if alone else rows) * length >= _BLOCKED_MIN_SIZE:
            # Every pole at most 1 in magnitude (a NaN is not, as its maximum is not).
            if all(map((1.0).__ge__, abs(poles).tolist())) and all_finite(values):
                return _blocked_recursions(poles if poles.dtype == dtype else
                                           poles.astype(dtype), values, out, blocks, alone)
            if alone and rows > 1:
                # Some row would not run in blocks alone: every row decides for itself.
                parts = [_recursions(poles[index:index + 1], values[index:index + 1],
                                     None if out is None else out[index:index + 1], None)
                         for index in range(rows)]
                return out if out is not None else np.concatenate(parts)
        result = _banded_recursions(poles, values, complex_valued)
    if out is None:
        return result
    out[...] = result
    return out


def _banded_recursions(poles: np.ndarray, values: np.ndarray, complex_valued: bool
                       ) -> np.ndarray:
    """:func:`recursions` as banded triangular solves, for values of the solve's type."""
    rows, length = values.shape
    solve = lapack.ztbtrs if complex_valued else lapack.dtbtrs
    # A complex sample takes twice the memory of a real one: half as many per solve (at
    # least one row).
    step = (_BAND_SIZE // 2 if complex_valued else _BAND_SIZE) // length or 1
    parts = []
    for first in range(0, rows, step):
        chunk = values[first:first + step]          # the last one may be shorter
        count = chunk.shape[0]
        # Column-major, as LAPACK reads it (all_pole): no copy per solve.
        band = np.empty((2, count * length), dtype=values.dtype, order='F')
        band[0] = 1.0
        below = band[1].reshape(count, length)          # a view of the strided row
        below[:] = -poles[first:first + step, None]
        below[:, -1] = 0.0                  # a row's last sample does not feed the next row
        # Unit diagonal: the solve skips its division by 1 per sample (exact, so the same
        # values), a third of its time.
        out, _ = solve(band, chunk.reshape(-1, 1), uplo='L', diag='U')
        if rows <= step:
            return out.reshape(count, length)           # one solve (the usual case)
        parts.append(out.reshape(count, length))
    return np.concatenate(parts)


# The largest temporary (bytes) the blocked recursions form in one piece: glibc's default
# threshold for mapping a block from the system (and faulting its pages in on each use).
_TEMPORARY_SIZE = 128 * 1024
# Real samples per banded solve of recursions (complex ones: half as many).
_BAND_SIZE = 16384
# Block length of the blocked recursions, the shortest row and the fewest samples they run.
_BLOCK = 16
_BLOCKED_MIN_LENGTH = 8 * _BLOCK
_BLOCKED_MIN_SIZE = 1536
# The powers k and factorials k! of a chain's transition entries (t h)^k/k!, and where each
# entry of an n x n lower triangular Toeplitz matrix (the top left of these) reads a row of
# them: i - j on and below the diagonal, else the last entry, a zero (_Chain.block_maps).
_CHAIN_POWERS = np.arange(_CHAIN_MAX_ORDER, dtype=float)
_CHAIN_FACTORIALS = np.array([float(math.factorial(k)) for k in range(_CHAIN_MAX_ORDER)])
_CHAIN_LAGS = np.subtract.outer(np.arange(_CHAIN_MAX_ORDER), np.arange(_CHAIN_MAX_ORDER))
_CHAIN_LAGS[_CHAIN_LAGS < 0] = -1
# Bands of the carried states kept per chain (:meth:`_ChainBlocks.band`): one per record
# length in use.
_KEPT_BANDS = 4
# The shortest complex row run in blocks: its block products cost four real ones, and break
# even with the complex substitution at about this length.
_BLOCKED_MIN_COMPLEX_LENGTH = 2560
# The shortest rows of complex modes driven by real rows (in real form) run in blocks.
_BLOCKED_MIN_PAIR_LENGTH = 4096
# The exponents of a block's pole powers p^0 .. p^B, and where each entry of the transposed
# block matrix reads them: p^(k - j) at row j, column k for k >= j, else the zero appended
# after p^B (index B + 1). Constant: built once, not per run.
_BLOCK_EXPONENTS = np.arange(_BLOCK + 1)
_BLOCK_LAG = np.subtract.outer(np.arange(_BLOCK), np.arange(_BLOCK))    # j - k
_BLOCK_INDEX = np.where(_BLOCK_LAG <= 0, -_BLOCK_LAG, _BLOCK + 1)


def _blocked_recursions(poles: np.ndarray, values: np.ndarray,
                        out: Optional[np.ndarray] = None,
                        out_blocks: Optional[np.ndarray] = None,
                        alone: bool = False) -> np.ndarray:
    """
    :func:`recursions` for poles of magnitude at most 1, in blocks of :data:`_BLOCK`.

    A substitution carries one sample at a time, a chain of dependent multiply-adds. Instead
    each block's response from rest is a matrix product with the block's lower triangular
    Toeplitz matrix of pole powers (all blocks of a row in one product), then the state carried
    into block ``b`` is a recursion over blocks with pole ``p^B`` and adds
    ``p^(k+1) carry[b-1]`` to sample ``k``. Every power is at most 1 in magnitude, so the sums
    round no worse than the substitution's. Real or complex: ``poles`` and ``values`` of one
    type (a complex mode's substitution is a chain of complex multiply-adds, longer still).
    Rows of whole blocks are read and written (``out``, or its blocks as one view
    ``out_blocks``) in place, others through zero-padded copies. ``alone``: the carried
    recursion of each row is run as if that row were the only one (:func:`_recursions`).
    """
    rows, length = values.shape
    blocks = -(-length // _BLOCK)
    padded = _blocks(values)
    if padded is None:
        padded = np.zeros((rows, blocks, _BLOCK), dtype=values.dtype)
        padded.reshape(rows, -1)[:, :length] = values
    powers, transposed = _pole_blocks(poles.tobytes(), poles.dtype.char)
    # In place where the rows are of whole blocks and one array (a caller's other rows are
    # written from the whole response below).
    response = out_blocks if out_blocks is not None else \
        _blocks(out) if out is not None and out.dtype == values.dtype and \
        out.flags.c_contiguous else None
    in_place = response is not None
    if in_place:
        ends = out[:, _BLOCK - 1::_BLOCK]
    else:
        whole = np.empty((rows, blocks, _BLOCK), dtype=values.dtype)
        response, ends = whole, whole[:, :, -1]
    # One 2-D product per row (numpy's stacked matmul can miss BLAS for these shapes), each
    # written in place.
    for row, matrix, into in zip(padded, transposed, response):
        np.matmul(row, matrix, out=into)
    # The state at each block's end, carried over blocks (blocked again if they are many).
    carried = _recursions(powers[:, _BLOCK], ends, None, None, alone)
    # The carried states' products, a temporary of the response's size, are formed a few
    # rows at a time: a larger one is memory glibc maps from the system afresh on every run.
    step = _TEMPORARY_SIZE // (blocks * _BLOCK * values.itemsize) or 1
    for first in range(0, rows, step):
        last = first + step
        response[first:last, 1:, :] += \
            carried[first:last, :-1, None] * powers[first:last, None, 1:]
    if in_place:
        return out
    result = whole.reshape(rows, -1)[:, :length]
    if out is None:
        return result
    out[...] = result
    return out


def all_pole(den: np.ndarray, values: np.ndarray) -> np.ndarray:
    """
    Return ``scipy.signal.lfilter([1], den, values, axis=0)`` from rest, by column.

    ``den[0] out[k] = values[k] - den[1] out[k-1] - ... - den[p] out[k-p]``: one banded lower
    triangular solve (LAPACK ``?tbtrs``) for all columns, without importing
    :mod:`scipy.signal`.
    """
    den = np.asarray(den, dtype=float)
    values = np.asarray(values, dtype=float)
    columns = values.reshape(values.shape[0], -1)
    count, order = columns.shape[0], den.size - 1
    if count == 0 or columns.shape[1] == 0:
        return np.zeros(values.shape)
    # In LAPACK's column-major order: a row-major band would be copied into it on every call
    # (as large again, a record's length per lag, and its pages faulted in afresh).
    band = np.empty((order + 1, count), order='F')
    band[:] = den[:, None]
    for lag in range(1, order + 1):
        band[lag, max(count - lag, 0):] = 0.0       # outside the matrix
    # A monic denominator divides by 1 per sample: the unit-diagonal solve skips it (exact).
    out, _ = lapack.dtbtrs(band, columns, uplo='L', diag='U' if den[0] == 1.0 else 'N')
    return out.reshape(values.shape)


# Below this magnitude of ``pole * length`` the hold integrals are summed as power series
# (their closed forms cancel); 19 terms reach rounding at 0.5.
_SERIES_LIMIT = 0.5
_SERIES_TERMS = 19
_SERIES_POWERS = np.arange(_SERIES_TERMS)
_FACTORIALS = np.cumprod(np.arange(1, 22, dtype=float))       # 1!, 2!, ..., 21!
# The coefficients of x^k in the hold factors and their slopes, one column each:
# 1/(k+1)!, 1/(k+2)!, (k+1)/(k+2)!, (k+1)/(k+3)!. One product sums all four series.
_SERIES = np.stack([1.0 / _FACTORIALS[:19], 1.0 / _FACTORIALS[1:20],
                    (_SERIES_POWERS + 1.0) / _FACTORIALS[1:20],
                    (_SERIES_POWERS + 1.0) / _FACTORIALS[2:21]], axis=1)


def _powers(x: np.ndarray) -> np.ndarray:
    """
    Return ``x^0 .. x^18`` for every element of ``x``, one row each.

    Running products: ``x ** k`` calls ``pow`` per real element, several times slower.
    """
    powers = np.empty((x.size, _SERIES_TERMS), dtype=x.dtype)
    powers[:, 0] = 1.0
    powers[:, 1:] = x[:, None]
    return np.multiply.accumulate(powers, axis=1, out=powers)


def _series_factors(x: np.ndarray) -> Optional[np.ndarray]:
    """
    Return the hold factors of ``x`` and their slopes as series, if every ``|x|`` is small.

    Rows: :func:`_hold_factors` and :func:`_hold_factor_slopes` summed as power series, from
    one product of the powers of ``x``; None if some ``|x|`` reaches :data:`_SERIES_LIMIT`.
    """
    if all(map(_SERIES_LIMIT.__gt__, abs(x).tolist())):          # a handful: Python floats
        return (_powers(x) @ _SERIES).T
    return None


def _hold_factors(x: np.ndarray, series: Optional[np.ndarray]) -> Tuple[np.ndarray, np.ndarray]:
    """
    ``(e^x - 1)/x`` and ``(e^x - 1 - x)/x^2`` elementwise (1 and 1/2 at 0).

    ``series``: :func:`_series_factors` of ``x``.
    """
    if series is not None:
        # Fast sampling makes every |x| small: the series alone, the same values.
        return series[0], series[1]
    small = np.abs(x) < _SERIES_LIMIT
    with np.errstate(all='ignore'):
        expm1 = np.expm1(x)
        first, second = expm1 / x, (expm1 - x) / (x * x)
        if _ANY(small, None):
            factors = (_powers(x) @ _SERIES[:, :2]).T
            first = np.where(small, factors[0], first)
            second = np.where(small, factors[1], second)
    return first, second


def _hold_factor_slopes(x: np.ndarray, first: np.ndarray, second: np.ndarray,
                        series: Optional[np.ndarray]) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return the derivatives in x of :func:`_hold_factors`: ``(e^x - f)/x``, ``(f - 2g)/x``.

    ``series``: :func:`_series_factors` of ``x``.
    """
    if series is not None:
        return series[2], series[3]
    small = np.abs(x) < _SERIES_LIMIT
    with np.errstate(all='ignore'):
        first_slope = (np.exp(x) - first) / x
        second_slope = (first - 2.0 * second) / x
        if _ANY(small, None):
            slopes = (_powers(x) @ _SERIES[:, 2:]).T
            first_slope = np.where(small, slopes[0], first_slope)
            second_slope = np.where(small, slopes[1], second_slope)
    return first_slope, second_slope


@dataclass
class _ContinuousModes:
    """
    The uncoupled modes of a :class:`ContinuousFilter` with distinct, well-separated poles.

    With the (scaled) roots ``z_i`` of ``D`` the companion states ``s^j/D`` are
    ``sum_i z_i^j r_i/(s - z_i)``, ``r_i = 1/D'(z_i)``: the eigenvectors are the Vandermonde
    columns and every mode is discretised in closed form, without matrix exponentials,
    eigen-decompositions or solves. Only one mode of each conjugate pair is kept (``keep``),
    the other being its conjugate (``weights`` 2); the real modes come first.
    """

    poles: np.ndarray          # kept scaled continuous poles z_i
    basis: np.ndarray          # balanced states of each mode (all modes, columns)
    keep: Optional[np.ndarray]  # indices of the modes kept, None for all (real poles)
    weights: np.ndarray
    residues: np.ndarray       # r_i of the kept modes
    spread: np.ndarray         # sum over j != i of 1/(z_i - z_j), i.e. D''(z_i) / (2 D'(z_i))
    squared: bool              # 1/D^2 is read off these modes (StateResponse.squared_outputs)
    real: int                  # how many of the kept modes (the first ones) are real

    def discretize(self, segments) -> Optional['_DiscreteModes']:
        """Closed-form hold integrals per mode over the sub-intervals; None on overflow."""
        transition = None
        drive: Dict[Sample, np.ndarray] = {}
        factors = []
        span = 0.0
        for length, start, end in segments:
            x = self.poles * length
            e = np.exp(x)
            series = _series_factors(x)
            first, second = _hold_factors(x, series)
            # The drives before the sub-interval too: their slopes (drive_slopes) carry them.
            factors.append((length, start, end, x, e, first, second, series, drive))
            span += length
            # The first sub-interval's transition is its exponential itself (times 1, exact).
            transition = e if transition is None else e * transition
            drive = self._advanced(drive, length, start, end, e, first, second)
        drives = np.array(list(drive.values()))
        if not (all_finite(transition) and all_finite(drives)):
            return None
        return _DiscreteModes(self, transition, list(drive), drives, factors, span)

    def _advanced(self, drive: Dict['Sample', np.ndarray], length: float, start, end,
                  e: np.ndarray, first: np.ndarray, second: np.ndarray
                  ) -> Dict['Sample', np.ndarray]:
        """
        Return the modes' drives carried over one sub-interval and its hold integrals added.

        ``drive``: the drives up to the sub-interval's start; ``e``, ``first``, ``second``: its
        ``e^x`` and hold factors (:func:`_hold_factors`) for ``x`` = pole times ``length``;
        ``start``, ``end``: the input values at its ends.
        """
        q = length * second * self.residues
        # Nothing to carry into the first sub-interval: no comprehension over an empty dict.
        drive = {sample: e * vector for sample, vector in drive.items()} if drive else {}
        _accumulate(drive, (start, length * first * self.residues - q), (end, q))
        return drive

    def drive_slopes(self, factors, samples: List[Sample]) -> np.ndarray:
        """
        Return the derivatives of the drives of :meth:`discretize` in the poles, residues fixed.

        ``factors`` are :meth:`discretize`'s per sub-interval (length, values at start and
        end, ``x``, ``e^x``, the hold factors, :func:`_series_factors` and the drives up to
        the sub-interval's start, which are not written to). Returns
        ``(samples, kept modes)`` in the order of ``samples``: the drives of the chain
        ``r_i/(z - z_i)^2`` (:meth:`_DiscreteModes.chains`).
        """
        slope: Dict[Sample, np.ndarray] = {}
        for length, start, end, x, e, first, second, series, drive in factors:
            first_slope, second_slope = _hold_factor_slopes(x, first, second, series)
            q_slope = length * length * second_slope * self.residues
            slope = {sample: e * slope.get(sample, 0.0) + length * e * vector
                     for sample, vector in drive.items()}
            _accumulate(slope, (start, length * length * first_slope * self.residues - q_slope),
                        (end, q_slope))
        zero = np.zeros(self.poles.size, dtype=self.poles.dtype)
        return np.array([slope.get(sample, zero) for sample in samples])


@dataclass
class _DiscreteModes:
    """One sample period of :class:`_ContinuousModes`: ``m_i[k+1] = p_i m_i[k] + drive``."""

    continuous: _ContinuousModes
    poles: np.ndarray
    samples: List[Sample]
    drives: np.ndarray         # (samples, kept modes)
    factors: List              # per scaled sub-interval: ContinuousModes.discretize's values
    span: float                # the sub-intervals' scaled lengths summed: one sample period

    def chains(self, modal: np.ndarray, signals: np.ndarray, count: int,
               below: Optional[np.ndarray] = None) -> np.ndarray:
        """
        Run ``r_i/(z - z_i)^2`` over the signals, given the modes ``modal`` (:meth:`run`'s).

        The derivative of ``m[k+1] = p m[k] + g . u`` with respect to the pole ``z_i``
        (``p = e^{z_i h}``, ``dp/dz_i = h p``) is
        ``n[k+1] = p n[k] + h p m[k] + (dg/dz_i) . u``: the exact discretisation of the double
        pole, one recursion per kept mode. ``signals`` and ``count`` as :meth:`run` takes them,
        ``modal`` its trajectories over the signals' length; returns the same rows as
        :meth:`run` (real form or complex as ``modal``), and ``below`` (rows of the result's
        length) under them if given.
        """
        continuous = self.continuous
        real = continuous.real
        length = self.span
        slopes = continuous.drive_slopes(self.factors, self.samples)
        # One driving row per real mode and two per complex one (its real and imaginary
        # parts), each complex mode then driven by its own two rows.
        pairs = self.poles.size - real
        factors = length * self.poles
        if modal.dtype.kind == 'c':
            return self._run_complex(factors[:, None] * modal + _product(slopes.T, signals),
                                     count, below)

        def form(rows: np.ndarray) -> None:
            # Every row's driving, sample k at k, in the trajectories' own rows.
            if pairs:
                np.matmul(_form_scaling(factors, real), modal, out=rows)
                rows += _product(_form_drives(slopes.T, real), signals)
            else:
                np.multiply(factors[:, None], modal, out=rows)
                rows += _product(slopes.T, signals)

        return self._run_form(form, signals.shape[1], None, None, below)

    def run(self, signals: np.ndarray, count: int) -> np.ndarray:
        """
        Run every kept mode over the signals of :attr:`samples` (one row each).

        ``signals``: rows of ``count`` samples padded with zeros to whole blocks of
        :data:`_BLOCK` samples, whose responses come after the record (:func:`_sampled_rows`).
        Returns the modes' trajectories, one sample longer than the signals (``m[k+1]``
        takes the drive of ``u[k]``): in the real form of :func:`_form_recursions`, or as
        complex rows (:meth:`_run_complex`) for complex modes of records too short for their
        block products.
        """
        real = self.continuous.real
        drives = self.drives.T
        length = signals.shape[1]
        if real == drives.shape[0]:
            return self._run_form(partial(_product, drives.real, signals), length, signals,
                                  _NO_PAIRS)
        if length < _BLOCKED_MIN_PAIR_LENGTH:
            return self._run_complex(_product(drives, signals), count)
        return self._run_form(partial(_product, drives[:real].real, signals), length, signals,
                              drives[real:])

    def _run_complex(self, driving: np.ndarray, count: int,
                     below: Optional[np.ndarray] = None) -> np.ndarray:
        """
        Return the kept modes as complex rows driven by ``driving`` (one row each), from rest.

        The first ``count`` samples, zero after them: on a short record one complex
        substitution per mode and complex output maps take fewer calls than the real form;
        a real mode has only rounding in any imaginary part of its driving, dropped.
        ``below``: rows of the result's length copied under the modes' rows.
        """
        real, kept = self.continuous.real, self.poles.size
        trajectories = np.zeros((kept + (0 if below is None else below.shape[0]),
                                 driving.shape[1] + 1), dtype=complex)
        if count > 1:
            if real:
                trajectories[:real, 1:count] = recursions(self.poles[:real].real,
                                                          driving[:real, :count - 1].real)
            trajectories[real:kept, 1:count] = recursions(self.poles[real:],
                                                          driving[real:, :count - 1])
        if below is not None:
            trajectories[kept:] = below
        return trajectories

    def _run_form(self, form: Callable[[np.ndarray], object], length: int,
                  inputs: Optional[np.ndarray], coefficients: Optional[np.ndarray],
                  below: Optional[np.ndarray] = None) -> np.ndarray:
        """
        Return the kept modes in real form (:func:`_form_recursions`' arguments), from rest.

        ``m[k+1] = p m[k] + d[k]`` over ``length`` samples: the recursions write one sample on
        into rows that start at rest, in the blocks of ``d`` (as the sums of a recursion of
        ``d`` itself round). ``form`` writes the drives ``d`` into the rows it is given, sample
        k at k, which then run in place (the recursions read a row before they write it),
        without an array of the drives' size: the real modes' rows, the complex modes being
        driven by ``coefficients`` times the real ``inputs``; or (``inputs`` None) every row,
        a complex mode's two rows the real and imaginary parts of its driving. ``below``: rows
        of the result's length copied under the modes' rows.
        """
        real = self.continuous.real
        rows = 2 * self.poles.size - real
        trajectories, blocks = _trajectories(rows + (0 if below is None else below.shape[0]),
                                             length)
        formed = real if inputs is not None else rows
        form(trajectories[:formed, :length])
        if inputs is None:
            inputs = trajectories[real:rows, :length]
        _form_recursions(self.poles, real, trajectories[:real, :length], inputs, coefficients,
                         trajectories[:rows, 1:], None if blocks is None else blocks[:rows])
        trajectories[:formed, 0] = 0.0                                  # from rest
        if below is not None:
            trajectories[rows:] = below
        return trajectories


@dataclass
class _Chain:
    """
    The states of ``1/(z - z0)^n`` as one real Jordan chain, discretised exactly.

    ``c_m = 1/(z - z0)^m`` of the signal, ``m = 1..n``: ``c_1' = z0 c_1 + u``,
    ``c_m' = z0 c_m + c_(m-1)``. Over a sample period ``c[k+1] = T c[k] + sum_o B_o u[k+o]``
    with ``T`` lower triangular and every diagonal entry ``e^{z0 h}`` (matrix exponentials of
    the chain per sub-interval, as :meth:`ContinuousFilter.state_discretization` forms them for
    the companion states), so the states run one after the other, each a real first-order
    recursion driven by the ones before (:func:`recursions`). The companion states
    ``z^j/(z - z0)^n = sum_l C(j, l) z0^(j-l) c_(n-l)`` are read off through :attr:`basis`.
    """

    basis: np.ndarray          # balanced companion states from the chain states (n x n)
    transition: np.ndarray     # T, lower triangular
    samples: List[Sample]
    drives: np.ndarray         # (samples, n)

    @classmethod
    def discretize(cls, continuous: 'ContinuousFilter', root: float,
                   segments) -> Optional['_Chain']:
        """Return the chain of ``continuous`` over ``segments``; None on overflow."""
        n = continuous.order
        chain = root * np.eye(n) + np.eye(n, k=-1)
        transition, drive = _state_discretization(chain, np.eye(n)[0], segments)
        drives = np.array(list(drive.values()))
        if not (all_finite(transition) and all_finite(drives)):
            return None
        basis = np.zeros((n, n))
        for j in range(n):
            for power in range(j + 1):             # C(j, l) z0^(j - l) on c_(n - l), l = power
                basis[j, n - power - 1] = math.comb(j, power) * root ** (j - power)
        return cls(basis / continuous._balance[:, None], transition, list(drive), drives)

    def run(self, signals: np.ndarray, count: int) -> '_Modes':
        """
        Run the chain over the signals of :attr:`samples` (one row each).

        ``signals``: rows of ``count`` samples padded with zeros to whole blocks, as
        :meth:`_DiscreteModes.run` takes them: each state's recursion writes one sample on
        into its row of the trajectories in place.
        """
        return self.modes(_run_chains([self], signals), count)

    def modes(self, trajectories: np.ndarray, count: int) -> '_Modes':
        """Return the modes of the chain states ``trajectories`` (rows of :func:`_run_chains`)."""
        return _Modes.uncoupled(self.basis, None, None, trajectories[:, :count],
                                trajectories.shape[0])

    @cached_property
    def block_maps(self) -> Optional['_ChainBlocks']:
        """
        Return the maps that run the chain in blocks of :data:`_BLOCK` samples, None if unfit.

        None unless ``T``'s diagonal is at most 1 in magnitude (then every power of ``T`` is:
        each entry is ``(j h)^k/k! e^{z0 j h}`` of a stable root) and the maps are finite.
        """
        order = self.transition.shape[0]
        pole = float(self.transition[0, 0])
        if not abs(pole) <= 1.0:
            return None
        # T = e^{(z0 + N) h} = p sum_k (h N)^k/k! (N the chain's subdiagonal shift) is lower
        # triangular Toeplitz, and T^t = p^t sum_k (t h N)^k/k!: every power in closed form
        # from T's first two entries, a column of (t h)^k/k! p^t per power, then zeros.
        step = float(self.transition[1, 0]) / pole if pole else 0.0
        exponents = np.arange(_BLOCK + 1.0)[:, None]
        columns = np.zeros((_BLOCK + 1, order + 1))
        columns[:, :order] = (pole ** exponents * (exponents * step) ** _CHAIN_POWERS[:order]
                              / _CHAIN_FACTORIALS[:order])
        powers = columns[:, _CHAIN_LAGS[:order, :order]]
        count = len(self.samples)
        # T^t B_q for t = 0 .. B, then zeros (where _BLOCK_INDEX reads above the diagonal):
        # responses[q, i, j] is what the signal row q's sample i of a block adds to the states
        # at its sample j.
        impulses = np.zeros((count, _BLOCK + 2, order))
        impulses[:, :_BLOCK + 1] = np.einsum('tij,qj->qti', powers, self.drives)
        responses = impulses[:, _BLOCK_INDEX]
        offsets = [offset for offset, _ in self.samples]
        # Rows that are the signal shifted by one sample after another (a masked sample
        # only where the first sample never enters): one window of B + s - 1 samples.
        windowed = offsets == list(range(offsets[0], offsets[0] + count)) and \
            all(offset >= 1 for offset, masked in self.samples if masked)
        if windowed:
            inputs = np.zeros((_BLOCK + count - 1, _BLOCK, order))
            for row in range(count):
                inputs[row:row + _BLOCK] += responses[row]
        else:
            inputs = responses.reshape(count * _BLOCK, _BLOCK, order)
        size = inputs.shape[0]
        # The states entering a block (last state first, as the carried solve orders them)
        # add T^(j+1) times them to its sample j.
        maps = np.concatenate([inputs.transpose(2, 0, 1),
                               powers[1:, :, ::-1].transpose(1, 2, 0)], axis=1)
        # The carried chain C_b = T^B C_(b-1) + E_b as one lower triangular banded system, its
        # unknowns by block and, within a block, last state first: state m of block b reads
        # state l <= m of block b - 1 from n - m + l unknowns back (1 to n), the band's
        # column of the unknown (b - 1, l) (LAPACK's lower band storage, a column each).
        carry = powers[_BLOCK]
        band = np.zeros((order, order + 1))
        for state in range(order):
            for before in range(state + 1):
                band[order - 1 - before, order - state + before] = -carry[state, before]
        if not (all_finite(maps) and all_finite(band)):
            return None
        return _ChainBlocks(windowed, size,
                            np.ascontiguousarray(inputs[:, _BLOCK - 1, ::-1]),
                            np.ascontiguousarray(maps), band, {})


@dataclass
class _ChainBlocks:
    """
    A :class:`_Chain` in blocks of :data:`_BLOCK` samples (:func:`_blocked_chains`).

    A block's inputs are one row of ``size`` values: with ``windowed`` the ``B + s - 1``
    samples of the first signal row from the block's first sample on (the ``s`` rows are
    that row shifted by one sample after another), else the ``B`` samples of each row side
    by side; then the ``n`` states entering the block.
    """

    windowed: bool
    size: int                  # the inputs of a block before the entering states
    ends: np.ndarray           # (size, n): the states at a block's end from rest, last first
    maps: np.ndarray           # (n, size + n, B): state r's samples of the block
    columns: np.ndarray        # (n, n + 1): the carried chain's band, a column per unknown
    bands: Dict[int, np.ndarray]   # the band of every count of blocks asked for

    def band(self, blocks: int) -> np.ndarray:
        """Return the band of the carried chain over ``blocks`` (LAPACK's, column-major)."""
        band = self.bands.get(blocks)
        if band is None:
            columns = np.empty((blocks, *self.columns.shape))
            columns[:] = self.columns
            columns[:, :, 0] = 1.0                      # the unit diagonal
            columns[-1, :, 1:] = 0.0                    # nothing after the last block
            band = columns.reshape(-1, columns.shape[2]).T
            band.flags.writeable = False
            if len(self.bands) >= _KEPT_BANDS:
                self.bands.clear()
            self.bands[blocks] = band
        return band


def _run_chains(chains: Sequence[_Chain], signals: np.ndarray) -> np.ndarray:
    """
    Run chains of one order over the same signals of their (common) :attr:`_Chain.samples`.

    Returns each chain's state trajectories, one sample longer than the signals, in rows
    ``i n .. i n + n - 1`` for chain ``i``: the values of one chain at a time. Rows of whole
    blocks that a single recursion would run in blocks (:func:`_recursions`) run each chain
    in blocks as a whole (:func:`_blocked_chains`); others state by state
    (:func:`_chain_states`).
    """
    length = signals.shape[1]
    if length >= max(_BLOCKED_MIN_LENGTH, _BLOCKED_MIN_SIZE) and length % _BLOCK == 0 and \
            all_finite(signals):
        fit = [chain.block_maps is not None for chain in chains]
        if all(fit):
            trajectories = _blocked_chains(chains, signals)
            if trajectories is not None:
                return trajectories
        if any(fit) and len(chains) > 1:
            # Each chain as it would run alone.
            return np.concatenate([_run_chains([chain], signals) for chain in chains])
    return _chain_states(chains, signals)


def _blocked_chains(chains: Sequence[_Chain], signals: np.ndarray) -> Optional[np.ndarray]:
    """
    :func:`_run_chains` in blocks of :data:`_BLOCK` samples, None if the states overflow.

    As :func:`_blocked_recursions` runs one recursion, for a chain's ``n`` states at once
    (:class:`_ChainBlocks`): the states at each block's end from rest are one product of the
    blocks' inputs; the states carried over blocks by ``T^B`` (``C_b = T^B C_(b-1) + E_b``)
    are one banded triangular solve per chain (LAPACK ``dtbtrs``, band width ``n``); then
    each state's samples are one product of the blocks' inputs and the states entering
    them, written in place. No driving is formed per state and no coupling per sample: the
    drives and the coupling are in the block matrices, every power of ``T`` at most 1 in
    magnitude, so the sums round as the state-by-state recursions' do (to 1e-14 of a
    state's largest value on 10 000 samples). Each chain's values are its own alone.
    """
    order = chains[0].transition.shape[0]
    count, length = signals.shape
    blocks = length // _BLOCK
    rows = len(chains) * order
    maps = [chain.block_maps for chain in chains]
    size = maps[0].size
    trajectories, out_blocks = _trajectories(rows, length)
    inputs = np.empty((blocks, size + order))
    if maps[0].windowed:
        # The first row and the last row's samples beyond it: row q at k is this at k + q.
        window = np.concatenate([signals[0], signals[-1][length - count + 1:]]) \
            if count > 1 else signals[0]
        inputs[:, :size] = np.lib.stride_tricks.as_strided(
            window, (blocks, size), (_BLOCK * window.itemsize, window.itemsize),
            writeable=False)
    else:
        for row in range(count):
            inputs[:, row * _BLOCK:(row + 1) * _BLOCK] = signals[row].reshape(blocks, _BLOCK)
    carried = []
    for blocked in maps:
        ends = np.matmul(inputs[:, :size], blocked.ends)
        states, info = lapack.dtbtrs(blocked.band(blocks), ends.reshape(-1, 1), uplo='L',
                                     diag='U')
        if info != 0 or not all_finite(states):
            return None
        carried.append(states.reshape(blocks, order))
    inputs[0, size:] = 0.0                  # at rest before the first block
    for first, blocked, states in zip(range(0, rows, order), maps, carried):
        inputs[1:, size:] = states[:-1]
        for state in range(order):
            np.matmul(inputs, blocked.maps[state], out=out_blocks[first + state])
    return trajectories


def _chain_states(chains: Sequence[_Chain], signals: np.ndarray) -> np.ndarray:
    """
    :func:`_run_chains` state by state.

    State ``m`` of every chain runs in one call of the recursions (rows ``m``, ``n + m``,
    ...), each row chosen as if run alone (:func:`_recursions`).
    """
    order = chains[0].transition.shape[0]
    length = signals.shape[1]
    rows = len(chains) * order
    trajectories, blocks = _trajectories(rows, length)
    # Each state's driving is formed in its own row, sample k at k, and run one sample on in
    # place (the recursions read it before they write): no second array of the trajectories'
    # size (on a long record a fresh mapping of memory and its page faults).
    driving = trajectories[:, :length]
    for first, chain in zip(range(0, rows, order), chains):
        _product(chain.drives.T, signals, driving[first:first + order])
    poles = np.array([chain.transition[0, 0] for chain in chains])
    for m in range(order):
        if m:
            # The states before m add into its driving in place (BLAS gemv, y += A x): no
            # temporary product and second pass per state. Whole rows, contiguous: the last
            # sample of the sum is written by the recursion below, which never reads it.
            for first, chain in zip(range(0, rows, order), chains):
                blas.dgemv(1.0, trajectories[first:first + m].T, chain.transition[m, :m],
                           1.0, trajectories[first + m], overwrite_y=True)
        _recursions(poles, driving[m::order], trajectories[m::order, 1:],
                    None if blocks is None else blocks[m::order], True)
        trajectories[m::order, 0] = 0.0                                 # from rest
    return trajectories


def _condition(matrix: np.ndarray) -> float:
    """
    Return the 2-norm condition number of a square matrix (inf if singular).

    A 2 x 2 one from its Frobenius norm and determinant (``s1^2 + s2^2 = |M|_F^2``,
    ``s1 s2 = |det M|``), without the SVD's call overhead; larger ones as ``np.linalg.cond``
    forms it (the ratio of the extreme singular values), without its checks.
    """
    if matrix.shape != (2, 2):
        singular = np.linalg.svd(matrix, compute_uv=False)
        if not singular[-1] > 0.0:
            return math.inf
        return float(singular[0] / singular[-1])
    frobenius = float(_SUM(abs(matrix) ** 2, None))
    determinant = abs(matrix[0, 0] * matrix[1, 1] - matrix[0, 1] * matrix[1, 0])
    if not determinant > 0.0:
        return math.inf
    root = math.sqrt(max(frobenius * frobenius - 4.0 * determinant * determinant, 0.0))
    # s1^2 = (F + root)/2, and s1/s2 = s1^2/(s1 s2) takes the smaller one without cancellation.
    largest = 0.5 * (frobenius + root)
    return largest / determinant


def _continuous_modes(realisation: ContinuousFilter) -> Optional[_ContinuousModes]:
    """Return the uncoupled modes of ``realisation``, None if they are ill-conditioned."""
    n = realisation.order
    if n == 0:
        return None
    if n == 1:
        # One real pole: the general construction below reduces to this (residue 1, nothing
        # to compare it with), without its arrays of pole differences.
        pole = -realisation.den[1] / realisation.den[0] / realisation.scale
        if not math.isfinite(pole):
            return None
        return _ContinuousModes(np.array([pole]), np.array([[1.0 / realisation._balance[0]]]),
                                None, np.array([1.0]), np.array([1.0]), np.zeros(1), True, 1)
    # Asked for every new denominator: array methods and operators, not numpy's dispatch.
    poles = realisation._roots.astype(complex) / realisation.scale
    if poles.size != n:
        return None
    # The extremes of a handful of values by Python's own max and min of their floats, without
    # a ufunc's set-up (the same values: no NaN gets past the first test).
    magnitudes = abs(poles).tolist()
    if not all(map(math.isfinite, magnitudes)):
        return None
    largest = max(magnitudes)
    nonzero = [magnitude for magnitude in magnitudes if magnitude > 0.0]
    if nonzero and largest > _MODAL_RANGE_LIMIT * min(nonzero):
        return None                     # beyond any physical model: the state-space path says so
    differences = poles[:, None] - poles[None, :]
    differences.flat[::n + 1] = 1.0                 # the diagonal, as np.fill_diagonal sets it
    if min(abs(differences).ravel().tolist()) <= 1e-8 * max(largest, 1.0):
        realisation.repeated_roots = True
        return None                     # (nearly) repeated poles: no eigenvector basis
    vandermonde = poles[None, :] ** np.arange(n)[:, None]
    basis = vandermonde / realisation._balance[:, None]
    with np.errstate(all='ignore'):
        # The column norms as np.linalg.norm(basis, axis=0) forms them.
        norms = np.sqrt(np.add.reduce((basis.conj() * basis).real, axis=0))
        condition = _condition(basis / norms)
    if not condition <= _MODAL_CONDITION_LIMIT:
        return None
    inverse = 1.0 / differences
    inverse.flat[::n + 1] = 0.0
    imaginary = poles.imag.tolist()
    if any(imaginary):
        # The real modes first, then one of each conjugate pair: their trajectories run in the
        # real form of :func:`_form_recursions` without selecting rows. Python lists: a
        # handful of poles, for every new denominator.
        real = [index for index, value in enumerate(imaginary) if value == 0.0]
        keep = np.array(real + [index for index, value in enumerate(imaginary) if value > 0.0])
        kept = poles[keep]
        residues = 1.0 / _PROD(differences, 1)[keep]
        spread = _SUM(inverse, 1)[keep]
        weights = np.where(kept.imag > 0.0, 2.0, 1.0)
    else:
        # Real poles: every mode kept, real arithmetic throughout, as the eigen-decomposition
        # path has it.
        keep, kept, basis, weights = None, poles.real, basis.real, np.array([1.0] * n)
        residues = (1.0 / _PROD(differences, 1)).real
        spread = _SUM(inverse, 1).real
    # Every amplification within the limit: the largest is, and a NaN is not (as its maximum).
    amplifications = (abs(residues) ** 2 * (1.0 + 2.0 * abs(spread))).tolist()
    return _ContinuousModes(kept, basis, keep, weights, residues, spread,
                            all(map(_SQUARED_AMPLIFICATION_LIMIT.__ge__, amplifications)),
                            n if keep is None else len(real))


def skew_delay(ts: float, output_skew: float) -> float:
    """
    Extra input delay that brings outputs measured ``output_skew`` late onto the input grid.

    The response with dead time ``tau`` at ``t_k + output_skew`` equals the response with dead
    time ``tau + ts - output_skew`` at ``t_{k+1}``: simulate the input extended by one sample
    (:func:`skew_extended`) with this much more delay and drop the first output sample. Zero
    when there is no skew, so unskewed data take the unchanged path.
    """
    return ts - output_skew if output_skew else 0.0


def skew_extended(values: np.ndarray, output_skew: float) -> np.ndarray:
    """
    Return the input with its last sample repeated once if ``output_skew`` is nonzero.

    The extra sample is the input after the record: a held input never reaches the outputs with
    it (the extra delay :func:`skew_delay` is positive); a linearly interpolated one is taken
    as constant over the last interval.
    """
    if not output_skew:
        return values
    return np.concatenate([values, values[-1:]], axis=0)


def response(num, den, values, ts: float, *, delay: float = 0.0,
             intersample: str = 'zoh') -> np.ndarray:
    """
    Exact sampled response of ``num(s)/den(s) * exp(-delay*s)`` to a sampled signal.

    Parameters
    ----------
    num, den : array_like
        Polynomial coefficients in ``s``, highest power first (scipy.signal convention).
    values : array_like
        Signal samples at ``t_k = k*ts``; the system is at rest before ``t_0``.
    ts : float
        Sample time in seconds.
    delay : float, optional
        Dead time in seconds; need not be a multiple of ``ts``.
    intersample : {'zoh', 'foh'}, optional
        Behaviour of the signal between samples.

    Returns
    -------
    ndarray
        Output samples at ``t_k``.

    """
    return responses([num], den, values, ts, delay=delay, intersample=intersample)[0]


def responses(nums: List, den, values, ts: float, *, delay: float = 0.0,
              intersample: str = 'zoh') -> np.ndarray:
    """
    Responses of several numerators over one shared denominator, shape (q, N).

    One state simulation of ``1/den`` serves all numerators (each of degree <= deg den).
    """
    values = np.asarray(values, dtype=float)
    if values.ndim != 1:
        raise DataError(f'signal must be 1-D, got shape {values.shape}')
    discrete = ContinuousFilter(den).discretize(ts, delay, intersample)
    return discrete.outputs(values, nums)


def filter_responses(filters: Sequence[DiscreteFilter], values: np.ndarray
                     ) -> List[StateResponse]:
    """
    Return ``filter.response(values)`` of every filter, the chains among them run together.

    Filters that are repeated-root chains of one order over the same input samples and
    feedthrough (one dead time and hold), such as the state-variable filters ``1/(p + lam)^n``
    of several ``lam``, run each chain state of all of them through one call of the recursions
    (:func:`_run_chains`), on the signal sampled once, and share its delayed, held input: the
    work around each recursion is paid once per state, not once per filter and state. The
    values are those of one filter at a time (each row's recursion is chosen as alone).
    First-order filters (one real mode each) over the same input samples and feedthrough run
    in one recursion the same way. Other filters are run one at a time.

    Parameters
    ----------
    filters : sequence of DiscreteFilter
        The filters, in the order of the responses returned.
    values : numpy.ndarray
        The sampled signal (N,).

    Returns
    -------
    list of StateResponse
        One response per filter.

    """
    filters = list(filters)
    first = filters[0] if filters else None
    key = None if first is None else _run_together_key(first)
    if len(filters) < 2 or key is None or not all(
            _run_together_key(discrete) == key and discrete.feed == first.feed
            for discrete in filters[1:]):
        return [discrete.response(values) for discrete in filters]
    count = values.shape[0]
    length = -(-count // _BLOCK) * _BLOCK
    if first.chain is None:
        return _first_order_responses(filters, values, length)
    chains = [discrete.chain for discrete in filters]
    signals = _sampled_rows(values, first.chain.samples, length)
    trajectories = _run_chains(chains, signals)
    order = first.chain.transition.shape[0]
    responses: List[StateResponse] = []
    for index, (discrete, chain) in enumerate(zip(filters, chains)):
        modes = chain.modes(trajectories[index * order:(index + 1) * order], count)
        responses.append(StateResponse._of_modes(discrete, values, modes,
                                                 responses[0] if responses else None))
    return responses


def _run_together_key(discrete: DiscreteFilter) -> Optional[Tuple]:
    """
    Return what filters run together in :func:`filter_responses` share, None if it runs alone.

    A repeated-root chain: its order and input samples; one real mode (a first-order
    filter): its input samples.
    """
    if discrete.chain is not None:
        return 'chain', discrete.chain.transition.shape[0], tuple(discrete.chain.samples)
    modes = discrete.modes
    if modes is not None and modes.poles.size == 1 and modes.continuous.real == 1:
        return 'mode', tuple(modes.samples)
    return None


def _first_order_responses(filters: Sequence[DiscreteFilter], values: np.ndarray,
                           length: int) -> List[StateResponse]:
    """
    Return the responses of first-order filters (one real mode each) run in one recursion.

    As :meth:`_DiscreteModes.run` runs each alone (rows of ``length`` samples, whole blocks),
    each row's recursion chosen as if alone (:func:`_recursions`): the same values. The
    filters share the input samples and feedthrough (:func:`_run_together_key`).
    """
    modes = [discrete.modes for discrete in filters]
    signals = _sampled_rows(values, modes[0].samples, length)
    trajectories, blocks = _trajectories(len(filters), length)
    driving = trajectories[:, :length]
    for index, mode in enumerate(modes):
        _product(mode.drives.T.real, signals, driving[index:index + 1])
    poles = np.array([mode.poles[0].real for mode in modes])
    _recursions(poles, driving, trajectories[:, 1:], blocks, True)
    trajectories[:, 0] = 0.0                                            # from rest
    responses: List[StateResponse] = []
    for index, discrete in enumerate(filters):
        responses.append(StateResponse._of_modes(discrete, values, None,
                                                 responses[0] if responses else None,
                                                 signals, trajectories[index:index + 1]))
    return responses
