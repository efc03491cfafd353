"""
What the data and the model can determine at an estimate (``docs/algorithm.md`` section 14).

:func:`blind_combination` looks at the column-scaled sensitivities of the free parameters and
returns, apart from its message, a :class:`Blindness` status code: the output does not depend
on a parameter at all (the input does not excite it, or the dead time left the record), or a
combination of parameters has almost no effect on it. :func:`structurally_blind` asks whether
the transfer function itself ignores a combination, which no data can separate.
:class:`Sensitivities` keeps the decomposition the check and the covariance share.
"""

from dataclasses import dataclass
import enum
from typing import Optional, Tuple

from ctid_ros.errors import ModelError
from ctid_ros.estimation.iteration import free_parameters
from ctid_ros.estimation.linear_algebra import thin_svd
from ctid_ros.estimation.problem import delay_parameter, Problem, State
import numpy as np

__all__ = ['BlindCombination', 'Blindness', 'IDENTIFIABILITY_LIMIT', 'Sensitivities',
           'blind_combination', 'structurally_blind']

# Above this condition number of the scaled sensitivities a combination counts as unseen.
IDENTIFIABILITY_LIMIT = 1e10


class Blindness(enum.Enum):
    """
    Status code of :func:`blind_combination`: what the output is blind to.

    Attributes
    ----------
    UNEXCITED
        The output does not depend on a parameter: the input does not excite it.
    DEAD_TIME_PAST_RECORD
        The output does not depend on any parameter: the dead time went beyond half the
        record, where the model output is zero.
    WEAK_COMBINATION
        A combination of parameters has (almost) no effect on the output (condition number
        above :data:`IDENTIFIABILITY_LIMIT`): the model or only these data may be blind to it.

    """

    UNEXCITED = 'unexcited'
    DEAD_TIME_PAST_RECORD = 'dead time past the record'
    WEAK_COMBINATION = 'weak combination'

    @property
    def always_fatal(self) -> bool:
        """Return True if no estimate can be returned whatever the model's structure."""
        return self is not Blindness.WEAK_COMBINATION


@dataclass(frozen=True)
class BlindCombination:
    """Outcome of :func:`blind_combination`: a status code and the message a user reads."""

    status: Blindness
    message: str


class Sensitivities:
    """
    The sensitivities of the free parameters at the latest state asked for, and their SVD.

    The identifiability check and the covariance of one estimate use the same column-scaled
    sensitivities: one decomposition serves both, and the scaled columns it decomposed serve
    the covariance and the checks after it (:meth:`scaled`).
    """

    def __init__(self, problem: Problem):
        self._problem = problem
        self._latest: Optional[Tuple[State, tuple, Optional[np.ndarray]]] = None

    def at(self, state: State) -> Tuple[np.ndarray, np.ndarray, np.ndarray, Optional[tuple]]:
        """
        Return ``free``, ``psi[:, free]``, its column norms and the SVD of ``psi / norms``.

        ``free`` are the parameters not held at a bound (:func:`free_parameters`); the SVD is
        None if a column is zero.
        """
        if self._latest is None or self._latest[0] is not state:
            problem = self._problem
            free = free_parameters(problem, state, np.zeros(state.theta.size, dtype=bool))
            lin = problem.linearize(state.coefficients, regressors=False)
            # At a kink of the cost in the dead time (on the sample lattice) the two one-sided
            # sensitivities differ; their mean stands for both (one side alone can be zero
            # where a lag far below the sample time leaves the output a shifted input).
            psi = lin.psi if lin.delay_jump is None else lin.psi + 0.5 * lin.delay_jump
            psi = psi[:, free]
            norms = np.linalg.norm(psi, axis=0)
            scaled = None if any((norms == 0.0).tolist()) else psi / norms
            svd = None
            if scaled is not None:
                scaled.flags.writeable = False
                svd = thin_svd(scaled)
            self._latest = (state, (free, psi, norms, svd), scaled)
        return self._latest[1]

    def scaled(self, state: State) -> Optional[np.ndarray]:
        """
        Return ``psi[:, free] / norms`` at ``state``, the matrix :meth:`at` decomposed.

        None if a column is zero (no decomposition then). Read-only: the covariance and the
        checks after it share it.
        """
        self.at(state)
        return self._latest[2]


def blind_combination(problem: Problem, state: State,
                      sensitivities: Optional[Sensitivities] = None
                      ) -> Optional[BlindCombination]:
    """
    Explain why the output is (almost) blind to a parameter combination, or None.

    Parameters held at a bound are left out.
    """
    free, psi, norms, svd = (sensitivities or Sensitivities(problem)).at(state)
    if not any(free.tolist()):
        return None
    names = [name for name, keep in zip(problem.model.parameters, free) if keep]
    if svd is None:
        dead = ', '.join(names[i] for i in np.flatnonzero(norms == 0.0))
        delay_index = delay_parameter(problem.model)
        record = problem.data.ts * len(problem.data)
        if np.all(norms == 0.0) and delay_index is not None and \
                state.theta[delay_index] >= 0.5 * record:
            return BlindCombination(
                Blindness.DEAD_TIME_PAST_RECORD,
                f'the output does not depend on {dead} on these data: the dead time went '
                f'to {state.theta[delay_index]:.4g} s, where the model output is zero over '
                f'the {record:.4g} s record (the fit never found the input in the output). '
                'A dead time beyond half the record is not searched: record longer, check '
                'that input and output are the right signals, or bound the dead time')
        return BlindCombination(
            Blindness.UNEXCITED,
            f'the output does not depend on {dead} on these data: the input does not excite it')
    singular, vectors = svd[1:]
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else np.inf
    if condition <= IDENTIFIABILITY_LIMIT:
        return None
    names = [f'{weight:+.2f}*{name}' for weight, name in zip(vectors[-1], names)
             if abs(weight) > 0.1]
    return BlindCombination(
        Blindness.WEAK_COMBINATION,
        'the parameters are not identifiable from these data: the combination '
        f'{" ".join(names)} has (almost) no effect on the output (condition number '
        f'{condition:.1e}); fix one of them, reparameterise the model or use a richer input')


def structurally_blind(model, theta: np.ndarray, rng: np.random.Generator) -> bool:
    """
    Return True if the transfer function itself ignores a combination of the parameters.

    The map from ``theta`` to the normalised coefficients (``N/d_0``, ``D/d_0`` without its
    leading 1, the dead time) is rank deficient at ``theta`` and at two random points near it:
    no data can separate such parameters (``g/(J s^2 + b s + k)``: only ratios count), so the
    model must change. Where the data alone cannot (time constants that coincide, lags far
    below the sample time acting as dead time, a poorly exciting input) the estimate is
    returned with the weakly determined combination in its warnings instead.

    The rank is judged on the Jacobian with its rows (parameters) and columns (coefficients)
    scaled to unit norm (:func:`_equilibrated`): neither units nor the size of a value may
    make a parameter look blind. Scaled by the parameters' values instead, a dead time at 0
    or a lag far below the sample time (coefficients 1e-8 beside 1) read as blind, and a
    merely symmetric start (``T1 = T2`` at 1e-4 s) was refused as structurally blind.
    """
    points = [theta] + [theta * (1.0 + 0.1 * rng.standard_normal(theta.size))
                        for _ in range(2)]
    for point in points:
        try:
            coefficients = model.coefficients(point)
        except ModelError:
            continue
        lead = coefficients.den[0]
        if lead == 0.0:
            continue
        values = np.concatenate([coefficients.num.ravel(), coefficients.den[1:]]) / lead
        lead_gradient = coefficients.den_jacobian[:, 0]
        jacobian = np.hstack([
            coefficients.num_jacobian.reshape(point.size, -1) / lead,
            coefficients.den_jacobian[:, 1:] / lead,
            coefficients.delay_gradient[:, None]])
        jacobian[:, :values.size] -= np.outer(lead_gradient, values) / lead
        singular = np.linalg.svd(_equilibrated(jacobian), compute_uv=False)
        if singular.size and singular[-1] > 1e-9 * singular[0] and \
                singular.size >= point.size:
            return False
    return True


def _equilibrated(matrix: np.ndarray) -> np.ndarray:
    """Return ``matrix`` with its nonzero rows, then its nonzero columns, scaled to unit norm."""
    rows = np.linalg.norm(matrix, axis=1)
    matrix = matrix / np.where(rows > 0.0, rows, 1.0)[:, None]
    columns = np.linalg.norm(matrix, axis=0)
    return matrix[:, columns > 0.0] / columns[columns > 0.0]
