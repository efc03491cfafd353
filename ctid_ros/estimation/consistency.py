"""
Model adequacy across the record: does one parameter vector hold over the whole record.

An estimate's covariance (:mod:`~ctid_ros.estimation.noise`) says how far noise alone could
move it. Where the plant is time-varying or nonlinear, or the model misses a lag or has another
structure, the parameters that fit one part of the record differ from those that fit another by
far more than that, and the residual may still look like coloured noise independent of the
input. The check here (``docs/algorithm.md`` section 18) estimates the parameters on blocks of
the record (two halves and four quarters) and compares each block with the whole:

* each block's estimate is one Gauss-Newton step from the full estimate, with the full-record
  sensitivities ``Psi`` and residual ``e`` restricted to the block's rows:
  ``d_b = (Psi_b^T Psi_b)^-1 Psi_b^T e_b``. The simulation runs over the whole record, so every
  block starts from the state the model reaches there: no initial transient to handle;
* ``d_b = (A_b - A) v`` to first order, ``A_b = (Psi_b^T Psi_b)^-1 Psi_b^T S_b`` and
  ``A = (Psi^T Psi)^-1 Psi^T`` the maps from the noise ``v`` to the block's and the whole
  record's estimate; its covariance ``(A_b - A) Sigma (A_b - A)^T``, ``Sigma`` the estimate's
  own noise model, is exact for that model and positive semi-definite (the difference
  ``C_b - C`` of the two covariances is equal to it only for white noise);
* ``z = d_b,i / sqrt(cov(d_b)_ii)`` for every free parameter and block; the model is
  consistent if ``max |z|`` stays below a Bonferroni bound over the parameters and blocks
  tested at about 1 % false alarms.

Cost: the column-scaled sensitivities and the residual are the covariance's (handed on by the
estimate), filtered backwards once (the covariance's filter pass, reused:
:func:`block_deviations`); their products are summed once over the pieces between the blocks'
edges, and per block there is a p x p inverse and two free responses of the noise filter over
its memory, all stacked into single calls. For white noise the variances are
``c^2 (G_b^-1 - G^-1)`` from the p x p inverses alone. Where the noise model is shaped, a
block's sensitivities are ill conditioned or the filter's memory is as long as a block: an SVD
and one backward filter of the block's map per block. Only a flagged estimate is refined:
each quarter's estimate is iterated (Gauss-Newton on the block's rows of the full-record
simulation, at most :data:`REFINE_ITERATIONS` updates) and the reported standard deviations
become at least the scatter of the quarter estimates.
"""

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Dict, List, Optional, Tuple

from ctid_ros.core.simulation import all_pole
from ctid_ros.estimation.correlation import bonferroni_quantile
from ctid_ros.estimation.linear_algebra import gram_matrix
from ctid_ros.estimation.noise import (coloured_covariance, model_score, noise_memory,
                                       noise_root, NoiseModel, shaped_noise_model, unit_root)
from ctid_ros.estimation.problem import Problem, State
from ctid_ros.estimation.projected_noise import noise_freedom
import numpy as np
from scipy import special

__all__ = ['BLOCKS', 'Consistency', 'CovarianceParts', 'FAMILY', 'REFINE_ITERATIONS',
           'block_deviations', 'check_consistency', 'consistency_bound', 'loop_sensitivity',
           'small_sample_factors', 'with_consistency']

# Halves and quarters.
BLOCKS = (2, 4)
# Family-wise probability of no alarm on an adequate model (Bonferroni over the tests), set
# above the 0.99 the z statistics would need if they were exactly standard normal: with the
# noise fed back through a controller their spread is 1.1-1.3 (the AR noise model only
# approximates the sensitivity-shaped spectrum), and the false alarms stay below 2 %.
FAMILY = 0.998
# Gauss-Newton updates of each quarter's estimate when the model is flagged.
REFINE_ITERATIONS = 4
# A block whose scaled sensitivities are worse conditioned than this determines no parameter.
_BLOCK_CONDITION = 1e8
# Scaled sensitivities conditioned within this are inverted through their normal equations.
_NORMAL_CONDITION = 1e3
# Fewest fitted samples per parameter in a block.
_SAMPLES_PER_PARAMETER = 10
# The normal distribution's 97.5 % quantile, which the t quantiles are compared with.
_Z_975 = float(special.ndtri(0.975))


@dataclass
class Consistency:
    """
    Outcome of :func:`check_consistency`.

    Attributes
    ----------
    consistent : bool
        No block's estimate differs from the whole record's by more than the bound.
    max_z : float
        Largest ``|d_b,i| / std(d_b,i)`` over blocks and parameters (0 if none was tested).
    blocks : int
        Blocks tested (up to six: two halves and four quarters).
    verdict : str
        One line in words.
    bound : float
        The threshold ``max_z`` was compared with.
    worst : (str, str) or None
        Parameter and block (e.g. ``'quarter 3'``) of ``max_z``.
    z : dict
        ``{block name: {parameter: z}}`` for the blocks tested.
    quarter_params : list of dict
        The quarter estimates (refined if the model was flagged), in time order.
    spread : dict
        Sample standard deviation of the quarter estimates, by parameter.
    std_noise : dict
        The standard deviations the noise alone implies (the covariance of section 15).

    """

    consistent: bool
    max_z: float
    blocks: int
    verdict: str
    bound: float = float('inf')
    worst: Optional[Tuple[str, str]] = None
    z: Dict[str, Dict[str, float]] = field(default_factory=dict)
    quarter_params: List[Dict[str, float]] = field(default_factory=list)
    spread: Dict[str, float] = field(default_factory=dict)
    std_noise: Dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """Return the ``--json`` ``consistency`` object."""
        return {
            'consistent': bool(self.consistent),
            'max_z': float(self.max_z),
            'blocks': int(self.blocks),
            'verdict': self.verdict,
            'bound': float(self.bound),
            'spread': {name: _finite(value) for name, value in self.spread.items()},
        }


def _finite(value: float) -> Optional[float]:
    return float(value) if np.isfinite(value) else None


@dataclass
class CovarianceParts:
    """
    What an estimate's covariance computed that the checks after it use again.

    Built once by :func:`~ctid_ros.estimation.estimate.covariance` and handed on whole, so no
    check linearises, decomposes or fits the residual's noise model a second time.

    Attributes
    ----------
    scaled : ndarray, shape (N, p)
        The sensitivities of the free parameters (mean one-sided at a kink of the cost in the
        dead time) over their column norms.
    scales : ndarray, shape (p,)
        Those column norms (1 for a zero column).
    residual : ndarray, shape (N,)
        The residual at the estimate, on the fitted samples.
    svd : tuple of ndarray or None
        The thin SVD ``U S V^T`` of ``scaled`` (None if no parameter is free).
    residual_noise : NoiseModel
        The autoregressive model of the residual itself, before any restoring.
    root : ndarray or None
        ``U`` filtered through the covariance's noise model's ``1/A`` backwards for unit
        innovations (:func:`~ctid_ros.estimation.noise.unit_root`); None where not computed.
    again : ndarray or None
        ``root`` filtered so once more, for the small-sample factors
        (:func:`~ctid_ros.estimation.projected_noise.filtered_twice`); None where not computed.

    """

    scaled: np.ndarray
    scales: np.ndarray
    residual: np.ndarray
    svd: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]]
    residual_noise: NoiseModel
    root: Optional[np.ndarray] = None
    again: Optional[np.ndarray] = None


def consistency_bound(tests: int) -> float:
    """Return the normal quantile for :data:`FAMILY` over ``tests`` two-sided tests."""
    return bonferroni_quantile(FAMILY, tests)


# One record length per estimate, and the same lengths again and again in a stream of windows:
# remembered.
@lru_cache(maxsize=64)
def _block_rows(count: int) -> Tuple[Tuple[str, slice], ...]:
    names = {2: ('first half', 'second half'),
             4: ('quarter 1', 'quarter 2', 'quarter 3', 'quarter 4')}
    rows: List[Tuple[str, slice]] = []
    for parts in BLOCKS:
        edges = np.linspace(0, count, parts + 1).round().astype(int)
        rows += [(names[parts][i], slice(int(edges[i]), int(edges[i + 1])))
                 for i in range(parts)]
    return tuple(rows)


@lru_cache(maxsize=64)
def _long_blocks(count: int, params: int
                 ) -> Tuple[Tuple[str, ...], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """
    Return the blocks long enough for ``params`` parameters, and the pieces between them.

    The blocks' names, first and end rows; the edges of the pieces between the blocks (0,
    every block's first and end row, ``count``, sorted); and the first and end edge of the
    whole record and then of each block, as indices into those edges. Remembered, read-only.
    """
    kept = [(block, rows) for block, rows in _block_rows(count)
            if rows.stop - rows.start >= _SAMPLES_PER_PARAMETER * params]
    starts = np.array([rows.start for _, rows in kept], dtype=int)
    stops = np.array([rows.stop for _, rows in kept], dtype=int)
    edges = np.array(sorted({0, count, *starts.tolist(), *stops.tolist()}))
    spans = np.stack([edges.searchsorted(np.concatenate([[0], starts])),
                      edges.searchsorted(np.concatenate([[count], stops]))])
    for array in (starts, stops, edges, spans):
        array.flags.writeable = False
    return tuple(block for block, _ in kept), starts, stops, edges, spans


def _sensitivities(problem: Problem, state: State, free: np.ndarray
                   ) -> Tuple[np.ndarray, np.ndarray]:
    """Return the free columns of ``Psi`` (mean one-sided at a kink) and the residual."""
    lin = problem.linearize(state.coefficients, regressors=False)
    psi = lin.psi if lin.delay_jump is None else lin.psi + 0.5 * lin.delay_jump
    return psi[:, free], problem.measured - lin.output


def _pseudo_inverse(psi: np.ndarray) -> Optional[np.ndarray]:
    """
    Return ``(Psi^T Psi)^-1 Psi^T``, or None if ``Psi`` is (nearly) singular.

    Through the inverse of ``Psi^T Psi`` where ``Psi`` (columns of unit norm) is conditioned
    within :data:`_NORMAL_CONDITION`: squaring it then costs at most ``cond^2 eps`` relative.
    Otherwise through the SVD, which keeps the precision the normal equations would square
    away.
    """
    gram = gram_matrix(psi)
    eigenvalues = np.linalg.eigvalsh(gram)
    if eigenvalues[0] > 0.0 and eigenvalues[0] >= eigenvalues[-1] / _NORMAL_CONDITION ** 2:
        # (N x p) @ (p x p) by einsum: matmul runs these shapes far from BLAS speed.
        return np.einsum('ij,jk->ik', psi, np.linalg.inv(gram)).T
    left, singular, right_t = np.linalg.svd(psi, full_matrices=False)
    if singular.size == 0 or singular[-1] <= singular[0] / _BLOCK_CONDITION:
        return None
    return (right_t.T / singular) @ left.T


def block_deviations(sensitivities: np.ndarray, residual: np.ndarray, noise: NoiseModel,
                     scale: float = 1.0, filtered: Optional[np.ndarray] = None
                     ) -> Optional[List[Tuple[str, np.ndarray, np.ndarray]]]:
    """
    Return each block's deviation from the whole and its variance under the noise model.

    Parameters
    ----------
    sensitivities : ndarray, shape (N, p)
        The sensitivities ``S`` of the free parameters (columns of unit norm).
    residual : ndarray, shape (N,)
        The residual ``e`` of the estimate.
    noise : NoiseModel
        The noise model ``Sigma = scale sigma_w^2 H H^T`` (:func:`noise_root`).
    scale : float
        The covariance's ``N / (N - p)``.
    filtered : ndarray, shape (N, p), optional
        ``noise_root(sensitivities, noise, scale)``, if the caller has it.

    Returns
    -------
    list of (str, ndarray, ndarray) or None
        For each block long enough (:data:`BLOCKS`, at least ten samples per parameter) and
        not singular: its name, ``d_b = (A_b - A) e`` and the diagonal of
        ``(A_b - A) Sigma (A_b - A)^T``. None if the whole record does not determine the
        parameters.

    """
    blocks = _deviations(sensitivities, residual, noise, scale, filtered)
    return None if blocks is None else list(zip(*blocks))


# A block's name, and its d_b and var(d_b) by row.
_Blocks = Tuple[Tuple[str, ...], np.ndarray, np.ndarray]


def _deviations(scaled: np.ndarray, error: np.ndarray, noise: NoiseModel, scale: float,
                filtered: Optional[np.ndarray] = None, factor: Optional[np.ndarray] = None
                ) -> Optional[_Blocks]:
    """
    Return :func:`block_deviations` as the blocks' names, ``d_b`` and ``var(d_b)`` by row.

    ``filtered``: the filtered sensitivities, or with ``factor`` (p x p) the matrix whose
    product with ``factor`` they are (:func:`_filtered_once`).
    """
    blocks = _filtered_once(scaled, error, noise, scale, filtered, factor)
    return _filtered_by_block(scaled, error, noise, scale) if blocks is None else blocks


def _filtered_by_block(scaled: np.ndarray, error: np.ndarray, noise: NoiseModel, scale: float
                       ) -> Optional[_Blocks]:
    """
    Return the blocks' names, ``d_b`` and ``var(d_b)``, each block's map filtered on its own.

    None if the whole record does not determine the parameters. The noise root is linear and
    runs backwards in time: the whole record's map is filtered once, and a block's own map from
    the block's end over the block and the filter's memory before it (zero before that to
    rounding).
    """
    count, params = scaled.shape
    whole = _pseudo_inverse(scaled)
    if whole is None:
        return None
    whole_root = noise_root(whole.T, noise, scale)
    memory = noise_memory(noise, count)
    # Products of the samples with a map's N x p transpose (C-ordered): matmul runs a p x N
    # Fortran-ordered map far from BLAS speed.
    whole_deviation = error @ whole.T
    blocks = []
    for block, rows in _block_rows(count):
        if rows.stop - rows.start < _SAMPLES_PER_PARAMETER * params:
            continue
        local = _pseudo_inverse(scaled[rows])
        if local is None:
            continue
        # A_b - A as a p x N map of the noise, A_b acting on the block's rows only.
        deviation = error[rows] @ local.T - whole_deviation
        first = max(rows.start - memory, 0)
        extended = np.zeros((rows.stop - first, params))
        extended[rows.start - first:] = local.T
        root = noise_root(extended, noise, scale) - whole_root[first:rows.stop]
        variance = np.einsum('ij,ij->j', root, root)
        for outside in (whole_root[:first], whole_root[rows.stop:]):
            variance += np.einsum('ij,ij->j', outside, outside)
        blocks.append((block, deviation, variance))
    names, deviations, variances = zip(*blocks) if blocks else ((), (), ())
    return names, np.reshape(deviations, (-1, params)), np.reshape(variances, (-1, params))


def _filtered_once(scaled: np.ndarray, error: np.ndarray, noise: NoiseModel, scale: float,
                   filtered: Optional[np.ndarray] = None, factor: Optional[np.ndarray] = None
                   ) -> Optional[_Blocks]:
    """
    :func:`_filtered_by_block` from one backward filter of the sensitivities, or None.

    ``A_b - A = (G_b^-1 P_b - G^-1) S^T`` (``S`` the scaled sensitivities, ``G = S^T S``,
    ``P_b`` keeping the block's rows), so its noise root is ``E_b G_b^-1 - F G^-1`` with
    ``F = H^T S`` filtered once and ``E_b = H^T P_b S``. ``E_b`` equals ``F`` inside the block
    except for the filter's memory before the block's end, where the response to the samples
    after the block (``F``'s state there) is taken off, and before the block it is the response
    to the block's own state at its start: both free responses of the all-pole filter over its
    memory. Inside the block the squares sum through ``F``'s Gram matrix. None (the block by
    block filtering then) for a shaped noise model, an all-pole filter whose memory is not
    shorter than every block, or sensitivities worse conditioned than
    :data:`_NORMAL_CONDITION`. ``filtered``: ``F``, if the caller has it, or with ``factor``
    (p x p) a ``Z`` with ``F = Z factor``: ``F``'s products are then ``Z``'s times ``factor``,
    and ``F`` itself (N x p) is never formed.
    """
    count, params = scaled.shape
    if noise.shaping is not None:
        return None
    memory = noise_memory(noise, count)
    names, starts, stops, edges, (opening, closing) = _long_blocks(count, params)
    if names and int((stops - starts).min()) <= 2 * memory:
        return None
    firsts, inners = np.maximum(starts - memory, 0), stops - memory
    # Every block's sums of products are sums over the pieces between the blocks' edges
    # (``edges``): each row enters one product (halves and quarters share their rows). The
    # residual's products with the sensitivities ride along as a last row of each Gram
    # matrix. Entry 0 is the whole record's.
    sums = _running_grams(scaled, edges, error)
    sums = sums[closing] - sums[opening]
    # The whole record's and every block's inverse Gram matrix, decomposed together: the
    # matrices are p x p, and one stacked call costs what one alone does.
    inverses = _normal_inverses(sums[:, :params, :params])
    if inverses is None:
        return None
    inverse, locals_ = inverses[0], inverses[1:]
    estimates = (sums[:, params:, :params] @ inverses)[:, 0]
    deviations = estimates[1:] - estimates[0]
    if not noise.order:
        # White noise, Sigma = c^2 I: A_b A^T = G_b^-1 S_b^T S G^-1 = G^-1, so
        # (A_b - A) Sigma (A_b - A)^T = c^2 (G_b^-1 - G^-1), from the p x p inverses alone.
        variances = scale * noise.innovation_variance * np.diagonal(
            locals_ - inverse, axis1=1, axis2=2)
        return names, deviations, variances
    if filtered is None:
        filtered, factor = noise_root(scaled, noise, scale), None
    # Inside each block, away from its end: (F G_b^-1 - F G^-1) row by row; outside the
    # block and the memory before it: F G^-1. Through F's products over the pieces.
    filtered_edges = np.array(sorted({*edges.tolist(), *firsts.tolist(), *inners.tolist()}))
    filtered_grams = _running_grams(filtered, filtered_edges)
    # Rows of F taken below are rows of Z: factor rides on the p x p maps they meet.
    local_maps, whole_map = locals_, inverse
    if factor is not None:
        filtered_grams = factor.T @ filtered_grams @ factor
        local_maps, whole_map = factor @ locals_, factor @ inverse
    difference = locals_ - inverse
    outside = filtered_grams[-1] - _between(filtered_grams, filtered_edges, firsts, stops)
    inside = _between(filtered_grams, filtered_edges, starts, inners)
    # The diagonals of D^T X D by column sums of D * (X D): matmul, where einsum's three
    # operands cost several calls more.
    variances = np.add.reduce(difference * (inside @ difference) +
                              inverse * (outside @ inverse), axis=1)
    if memory:
        # Each block's end: F less the response to the samples after the block; before each
        # block: the response to the block's state at its start. Row by row.
        responses = _free_responses(
            filtered, noise.ar, np.concatenate([stops, starts]),
            np.concatenate([stops - inners, starts - firsts]), memory)
        ends, befores = responses[:stops.size], responses[stops.size:]
        span = np.arange(memory)
        at_end = filtered[inners[:, None] + span]
        rows_before = starts[:, None] - memory + span
        before = np.where((rows_before >= 0)[:, :, None],
                          filtered[np.maximum(rows_before, 0)], 0.0)
        root = np.concatenate([at_end - ends, befores], axis=1) @ local_maps - \
            np.concatenate([at_end, before], axis=1) @ whole_map
        variances += np.add.reduce(root * root, axis=1)
    return names, deviations, variances


def _running_grams(columns: np.ndarray, edges: np.ndarray,
                   residual: Optional[np.ndarray] = None) -> np.ndarray:
    """
    Return the running sums of ``X_k^T X_k`` over the pieces between ``edges`` of ``columns``.

    Entry ``k`` sums the pieces before edge ``k`` (rows ``0 .. edges[k] - 1``): entry 0 is 0.
    With ``residual``, each sum has the residual's products with the columns as a last row.
    """
    pieces = list(zip(edges[:-1], edges[1:]))
    width = columns.shape[1]
    # np.array stacks the pieces as np.stack does, without its checks.
    grams = [np.zeros((width, width))] + [columns[start:stop].T @ columns[start:stop]
                                          for start, stop in pieces]
    if residual is not None:
        # Apart, not as a column of an augmented copy: copying N x (p + 1) costs more than
        # the products.
        grams = np.concatenate([grams, np.array(
            [np.zeros(width)] + [residual[start:stop] @ columns[start:stop]
                                 for start, stop in pieces])[:, None]], axis=1)
    return np.array(grams).cumsum(axis=0)


def _between(sums: np.ndarray, edges: np.ndarray, starts: np.ndarray, stops: np.ndarray
             ) -> np.ndarray:
    """Return the sums over rows ``starts .. stops - 1`` (all among ``edges``) by block."""
    return sums[edges.searchsorted(stops)] - sums[edges.searchsorted(starts)]


def _normal_inverses(grams: np.ndarray) -> Optional[np.ndarray]:
    """
    Return the inverses of ``S^T S`` (stacked) if all ``S`` are conditioned within bounds.

    From the eigen decompositions that test the conditioning, ``V diag(1/lambda) V^T``: an
    inverse within ``cond eps`` of LU's (``cond`` at most :data:`_NORMAL_CONDITION` squared),
    without a second stacked LAPACK call.
    """
    eigenvalues, vectors = np.linalg.eigh(grams)
    smallest = eigenvalues[:, 0]
    if ((smallest > 0.0) & (smallest >= eigenvalues[:, -1] / _NORMAL_CONDITION ** 2)).all():
        return (vectors / eigenvalues[:, None, :]) @ vectors.transpose(0, 2, 1)
    return None


def _free_responses(filtered: np.ndarray, ar: np.ndarray, ends: np.ndarray,
                    lengths: np.ndarray, span: int) -> np.ndarray:
    """
    Return the backward all-pole filter's free responses before ``ends``, ``span`` rows each.

    The filter (``1/A`` backwards in time, as in ``noise_root``) holds the values of
    ``filtered`` at ``end .. end + order - 1`` (zero past the record) and gets no input before
    ``end``: the input that gives those values from rest is ``A`` applied to them, then zeros.
    Response ``i`` covers rows ``end - span .. end - 1``, of which only the last ``lengths[i]``
    are kept (the rest zero). Shape ``(len(ends), span, columns)``.

    The free response is linear in the held values: the filter's free responses to each unit
    state (one small filter pass, ``span x order``) map every end's values at once, where a
    filter pass of every end's driving would run ``len(ends) x columns`` recursions.
    """
    order = ar.size - 1
    count, columns = filtered.shape
    if order == 0 or span == 0:
        return np.zeros((ends.size, span, columns))
    rows = ends[:, None] + np.arange(order)
    states = np.where((rows < count)[:, :, None], filtered[np.minimum(rows, count - 1)], 0.0)
    # In reversed time, the input that leaves unit state m (the value at end + m) from rest:
    # A applied to it, on the state's first order rows.
    driving = np.zeros((order + span, order))
    for state in range(order):
        driving[order - 1 - state:order, state] = ar[:state + 1]
    # Row r of the basis: the responses at row end - span + r in forward time.
    basis = all_pole(ar, driving)[:order - 1:-1]
    keep = np.arange(span) >= span - lengths[:, None]
    return np.where(keep[:, :, None], basis @ states, 0.0)


def check_consistency(problem: Problem, state: State, noise: NoiseModel, free: np.ndarray,
                      std: np.ndarray, *, parts: CovarianceParts,
                      root: Optional[np.ndarray] = None) -> Consistency:
    """
    Test whether one parameter vector holds over the record (module docstring).

    Parameters
    ----------
    problem : Problem
        The estimation problem (its fitted samples, sensitivities and bounds).
    state : State
        The final estimate.
    noise : NoiseModel
        The residual's noise model behind the estimate's covariance.
    free : ndarray of bool
        Parameters not held at a bound (only these are tested).
    std : ndarray
        The noise-only standard deviations, ``model.parameters`` order.
    parts : CovarianceParts
        The covariance's sensitivities, residual and decomposition at ``state``, for ``free``.
    root : ndarray, optional
        ``U`` of ``parts.svd`` filtered through ``noise``'s ``1/A`` backwards in time for unit
        innovations, if the caller has it: the sensitivities' filtered form is then
        ``root S V^T`` scaled, without another filter pass.

    """
    names = problem.model.parameters
    std_noise = {name: float(value) for name, value in zip(names, std)}
    given = np.asarray(free, dtype=bool)
    free = given & np.isfinite(std)
    params = int(free.sum())
    if params == 0:
        return Consistency(True, 0.0, 0, 'no free parameter to compare across the record',
                           std_noise=std_noise)
    error = parts.residual
    # Each column scaled on its own: a parameter left out (a std that is not finite) leaves
    # the others' columns as they are.
    scaled = parts.scaled if params == parts.scaled.shape[1] else \
        parts.scaled[:, free[given]]
    count = error.size
    scale = count / max(count - params, 1)
    factor = None
    if root is not None and root.shape[1] == params:
        # The filtered sensitivities are root factor, the scale folded into the p x p factor:
        # their products are root's times it, and they are never formed.
        _, singular, right_t = parts.svd
        factor = np.sqrt(scale * noise.innovation_variance) * singular[:, None] * right_t
    else:
        root = None
    blocks = _deviations(scaled, error, noise, scale, root, factor)
    if blocks is None:
        return Consistency(True, 0.0, 0, 'the record does not determine the parameters',
                           std_noise=std_noise)
    free_names = [name for name, keep in zip(names, free) if keep]
    z_table, max_z, worst = _z_table(blocks, free_names)
    bound = consistency_bound(len(z_table) * params)
    consistent = max_z <= bound
    result = Consistency(consistent, max_z, len(z_table), '', bound, worst, z_table,
                         std_noise=std_noise)
    if not consistent:
        result.quarter_params = _quarter_estimates(problem, state, free)
        for index, name in enumerate(names):
            values = [quarter[name] for quarter in result.quarter_params]
            result.spread[name] = float(np.std(values, ddof=1)) if free[index] and \
                len(values) > 1 else float('nan')
    result.verdict = _verdict(result)
    return result


def _z_table(blocks: _Blocks, names: List[str]
             ) -> Tuple[Dict[str, Dict[str, float]], float, Optional[Tuple[str, str]]]:
    """
    Return ``{block: {parameter: z}}``, the largest ``|z|`` and its parameter and block.

    ``z = d_b / std(d_b)`` (0 where the variance is not positive); the first largest in block
    then parameter order is the worst, None if every ``z`` is 0.
    """
    blocks_named, deviations, variances = blocks
    if not blocks_named:
        return {}, 0.0, None
    z = np.where(variances > 0.0, deviations / np.sqrt(np.maximum(variances, 1e-300)), 0.0)
    table = {block: dict(zip(names, row)) for block, row in zip(blocks_named, z.tolist())}
    magnitudes = np.abs(z)
    if not np.isfinite(magnitudes.sum()):
        # A NaN ends its own block's search for the largest, as it always has.
        max_z, worst = 0.0, None
        for block, row in zip(blocks_named, magnitudes):
            top = int(np.argmax(row))
            if row[top] > max_z:
                max_z, worst = float(row[top]), (names[top], block)
        return table, max_z, worst
    block, top = divmod(int(np.argmax(magnitudes)), len(names))
    max_z = float(magnitudes[block, top])
    return table, max_z, ((names[top], blocks_named[block]) if max_z > 0.0 else None)


def _quarter_estimates(problem: Problem, state: State, free: np.ndarray
                       ) -> List[Dict[str, float]]:
    """
    Return each quarter's estimate: Gauss-Newton on its rows of the full-record simulation.

    From the full estimate, at most :data:`REFINE_ITERATIONS` updates, each halved (up to five
    times) until the quarter's cost falls and the model is admissible; parameters held at a
    bound stay there.
    """
    names = problem.model.parameters
    count = problem.measured.size
    edges = np.linspace(0, count, 5).round().astype(int)
    quarters = []
    for first, last in zip(edges[:-1], edges[1:]):
        rows = slice(first, last)
        theta, coefficients = state.theta.copy(), state.coefficients
        psi, error = _sensitivities(problem, _point(theta, coefficients), free)
        cost = float(error[rows] @ error[rows])
        for _ in range(REFINE_ITERATIONS):
            step = np.linalg.lstsq(psi[rows], error[rows], rcond=None)[0]
            accepted = False
            for _ in range(6):
                trial = theta.copy()
                trial[free] = np.clip(theta[free] + step, problem.lower[free],
                                      problem.upper[free])
                trial_coefficients = problem.admissible(trial)
                if trial_coefficients is not None:
                    trial_psi, trial_error = _sensitivities(
                        problem, _point(trial, trial_coefficients), free)
                    trial_cost = float(trial_error[rows] @ trial_error[rows])
                    if trial_cost < cost:
                        theta, coefficients, cost = trial, trial_coefficients, trial_cost
                        psi, error = trial_psi, trial_error
                        accepted = True
                        break
                step = 0.5 * step
            if not accepted:
                break
        quarters.append(dict(zip(names, map(float, theta))))
    return quarters


def _point(theta: np.ndarray, coefficients: Any) -> State:
    # A quarter's point: its cost is not the record's (NaN), and it is not a point seen.
    return State(theta, coefficients, float('nan'))


def _verdict(result: Consistency) -> str:
    """Return the verdict line."""
    if result.blocks == 0:
        return 'no block of the record determines the parameters: adequacy not tested'
    if result.consistent:
        return (f'consistent over the record: the estimates of its halves and quarters agree '
                f'with the whole within the noise (largest {result.max_z:.1f} std, bound '
                f'{result.bound:.1f})')
    name, block = result.worst
    return (f'the model does not hold over the record: {name} of the {block} differs from the '
            f"whole record's by {result.max_z:.1f} of its std (bound {result.bound:.1f}); the "
            'plant is time-varying or nonlinear, or the model misses a lag or has a different '
            'structure; the reported std covers the scatter of the quarter estimates')


def loop_sensitivity(problem: Problem, state: State) -> Optional[np.ndarray]:
    """
    Return the impulse response of the loop's sensitivity ``1 - T`` for a closed-loop model.

    With a known controller the model is the closed loop ``T`` from the reference, and noise on
    the measured output that the controller feeds back reaches the output through ``1 - T``
    (``docs/algorithm.md`` section 15). ``T``'s pulse response is simulated over the fitted
    samples and cut where it has decayed below 1e-12 of its peak. None for an open-loop model.

    The simulation is causal: the first half of the samples give the same response to the
    last bit, and where its last quarter has decayed (a loop that settles within a third of
    the record) the rest is not simulated.
    """
    if getattr(problem.model, 'controller', None) is None:
        return None
    count = problem.measured.size
    coefficients = state.coefficients
    for length in sorted({max(count // 2, 1), count}):
        # The model's response to the pulse (Model.simulate's values); a constant input's
        # channel, which it would add, is left to Model.simulate.
        if coefficients.num.shape[0] == 1:
            response = problem.bank.pulse_response(coefficients, length)
        else:
            pulse = np.zeros(length)
            pulse[0] = 1.0
            response = problem.model.simulate(state.theta, pulse, problem.data.ts)
        shaping = -np.asarray(response, dtype=float)
        shaping[0] += 1.0
        significant = np.flatnonzero(np.abs(shaping) > 1e-12 * np.abs(shaping).max())
        if significant[-1] < length - length // 4 or length == count:
            break
    return shaping[:significant[-1] + 1]


def _fed_back_noise(problem: Problem, state: State, free: np.ndarray, parts: CovarianceParts
                    ) -> Optional[Tuple[np.ndarray, NoiseModel]]:
    """
    Return the covariance and noise model with the noise shaped by the loop, if that fits better.

    For a closed-loop model the residual's noise model may be the plain autoregressive one or
    one passed through the loop's sensitivity (:func:`loop_sensitivity`), whichever scores
    better (:func:`~ctid_ros.estimation.noise.model_score`). None if the model is open loop or
    the plain one wins (the estimate's covariance stands). ``parts``: the covariance's.
    """
    shaping = loop_sensitivity(problem, state)
    if shaping is None or not free.any():
        return None
    error = parts.residual
    # The loop's degree in s is its sampled sensitivity's order where there is no dead time.
    shaped = shaped_noise_model(error, shaping, order_hint=problem.model.den_degree)
    count = error.size
    if not model_score(shaped, count) < model_score(parts.residual_noise, count):
        return None
    scaled, _ = coloured_covariance(parts.scaled, error, int(free.sum()), parts.svd,
                                    model=shaped)
    covariance = np.full((free.size, free.size), np.nan)
    # np.ix_'s indexing and np.outer's product.
    rows = free.nonzero()[0]
    covariance[rows[:, None], rows] = scaled / (parts.scales[:, None] * parts.scales)
    return covariance, shaped


def small_sample_factors(free: np.ndarray, noise: NoiseModel,
                         svd: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]],
                         removed_share: float = 0.0,
                         root: Optional[np.ndarray] = None,
                         again: Optional[np.ndarray] = None) -> np.ndarray:
    """
    Return ``t_0.975(nu_i) / z_0.975`` per parameter: the 95 % t quantile over the normal one.

    ``nu_i`` is the effective degrees of freedom of parameter ``i``'s variance: how much the
    noise model's own estimation error moves it
    (:func:`~ctid_ros.estimation.projected_noise.noise_freedom`). The standard deviations
    scaled by it make ``estimate +- 1.96 std`` the t interval; on long records or white
    noise it is 1 to within a per cent (``docs/algorithm.md`` section 15). 1 for parameters
    held at a bound. ``svd``: the thin SVD of the column-scaled sensitivities of the free
    parameters (None if none is free); ``removed_share``: the share of the noise's
    low-frequency level the fit took out of the residual, which the noise model then had to
    restore; ``root``: ``U`` filtered through the noise model's ``1/A`` backwards for unit
    innovations, and ``again``: ``root`` filtered so once more, if the caller has them.
    """
    factors = np.ones(free.size)
    if svd is None or not free.any():
        return factors
    left, singular, right_t = svd
    if singular[-1] <= 0.0:
        return factors
    freedom = noise_freedom(left, right_t.T / singular, noise, left.shape[0],
                            int(free.sum()), removed_share, root, again)
    # scipy.special's inverse t distribution: scipy.stats would cost a second of import.
    factors[free] = special.stdtrit(freedom, 0.975) / _Z_975
    return factors


def with_consistency(result: Any, problem: Problem, state: State, noise: NoiseModel,
                     free: np.ndarray, *, parts: CovarianceParts, removed_share: float = 0.0,
                     restored_factors: Optional[np.ndarray] = None) -> Any:
    """
    Return the estimate ``result`` with its consistency checked and reported.

    First, for a closed-loop model, the noise may be described better as passed through the
    loop's sensitivity (noise on the measured output fed back by the controller): then the
    covariance, standard deviations and the residual's noise order are recomputed with that
    description (:func:`loop_sensitivity`, ``docs/algorithm.md`` section 15). Then the
    standard deviations are scaled for a small effective sample
    (:func:`small_sample_factors`; ``removed_share``: the share of the noise's low-frequency
    level the fit took out of the residual, from
    :func:`~ctid_ros.estimation.estimate.covariance`; ``restored_factors``: its standard
    deviations with the restored noise over those without, None if not restored). ``parts``:
    what the covariance computed at ``state`` (:class:`CovarianceParts`), so it is not
    computed again.

    Sets ``result.consistency``, ``result.std_noise`` (the noise-only standard deviations) and
    ``result.std_change`` (those before the t factors and the restored noise: a change test's,
    ``docs/algorithm.md`` section 17).
    If the model does not hold over the record, each standard deviation becomes the larger of
    the noise-only one and the scatter of the quarter estimates (the covariance is scaled to
    match, correlations kept), a warning says so, and the residual verdict no longer claims
    that the standard deviations account for what is left.
    """
    names = problem.model.parameters
    free = np.asarray(free, dtype=bool)
    fed_back = _fed_back_noise(problem, state, free, parts)
    restored = np.ones(len(names)) if restored_factors is None else \
        np.asarray(restored_factors, dtype=float)
    if fed_back is not None:
        restored = np.ones(len(names))
        result.covariance, noise = fed_back
        result.std = dict(zip(names, map(float, np.sqrt(np.abs(result.covariance.diagonal())))))
        if result.residuals is not None:
            result.residuals.noise_order = noise.order
            result.residuals.noise_power_ratio = noise.variance_ratio
            result.residuals.noise_shaped = True
    # The sensitivities' basis filtered once through the noise model, for the small-sample
    # factors and the consistency check alike.
    svd, root, again = parts.svd, parts.root, parts.again
    if fed_back is not None or svd is None or noise.shaping is not None or not noise.order:
        root = again = None
    elif root is None:
        root, again = unit_root(svd[0], noise), None
    factors = small_sample_factors(free, noise, svd,
                                   0.0 if fed_back is not None else removed_share, root, again)
    # np.outer's product.
    result.covariance = result.covariance * (factors[:, None] * factors)
    result.std_change = {name: value / factor for (name, value), factor in
                         zip(result.std.items(), restored)}
    result.std = {name: value * factor for (name, value), factor in
                  zip(result.std.items(), factors)}
    std = np.array([result.std[name] for name in names], dtype=float)
    consistency = check_consistency(problem, state, noise, free, std, parts=parts, root=root)
    result.consistency = consistency
    result.std_noise = dict(consistency.std_noise)
    if consistency.consistent:
        return result
    spread = np.array([consistency.spread.get(name, np.nan) for name in names])
    widened = np.where(np.isfinite(spread) & (spread > std), spread, std)
    ratio = np.where(std > 0.0, widened / np.where(std > 0.0, std, 1.0), 1.0)
    ratio = np.where(np.isfinite(ratio), ratio, 1.0)
    result.covariance = result.covariance * (ratio[:, None] * ratio)
    result.std = dict(zip(names, map(float, widened)))
    result.warnings = list(result.warnings) + [consistency.verdict]
    if result.residuals is not None:
        result.residuals.mark_inconsistent()
    return result
