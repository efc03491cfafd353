"""
numpy.linalg's solvers for the estimator's small matrices, by LAPACK directly.

numpy's wrappers (type checks, error state, the result's wrapping) cost tens of Python-level
calls each, more than the LAPACK routine itself on the few-by-few matrices of the estimator's
updates, checks and starts (several per update). These call the routine numpy calls, with
numpy's settings: the same results to the bit (checked on every call of 10 estimates per
reference system). Float64 arrays only.
"""

import math
from typing import Optional, Tuple

import numpy as np
from scipy.linalg import lapack

__all__ = ['bounded_least_squares', 'condition', 'least_squares', 'normal_solution', 'solve',
           'solve_or_none', 'symmetric_eigen', 'symmetric_eigenvalues', 'thin_svd']

# The spacing of floats at 1: numpy's least-squares cutoff is it times the longer side.
_EPSILON = np.finfo(float).eps


def least_squares(matrix: np.ndarray, rhs: np.ndarray,
                  rcond: Optional[float] = None) -> np.ndarray:
    """
    Return ``np.linalg.lstsq(matrix, rhs, rcond=rcond)[0]`` (float64 arrays).

    LAPACK's gelsd with numpy's cutoff (by default its default one). A wide matrix, which
    numpy pads the right-hand side for, goes through numpy.
    """
    rows, columns = matrix.shape
    if rows < columns:
        return np.linalg.lstsq(matrix, rhs, rcond=rcond)[0]
    cutoff = _EPSILON * rows if rcond is None else rcond
    work, integers, info = lapack.dgelsd_lwork(rows, columns, rhs.size // rows, cutoff)
    if info == 0:
        solution, _, _, info = lapack.dgelsd(matrix, rhs, work, integers, cutoff)
    if info != 0:
        raise np.linalg.LinAlgError(f'least-squares solution failed (LAPACK info {info})')
    return solution[:columns]


def bounded_least_squares(matrix: np.ndarray, rhs: np.ndarray, lower: np.ndarray,
                          upper: np.ndarray) -> np.ndarray:
    """
    Return ``scipy.optimize.lsq_linear(matrix, rhs, (lower, upper), method='bvls').x``.

    The least-squares solution within the bounds (finite or infinite, ``lower < upper``) of a
    tall, small problem: the unbounded solution where it lies within them, else the
    bounded-variable least-squares algorithm of Stark and Parker. The same steps and
    arithmetic as scipy's (its default tolerance 1e-10 and iteration limit), so the same
    result to the bit, without most of its checks of the arguments, its report and its
    import. Raises ValueError, as scipy does, unless every lower bound is below its upper one.
    """
    if np.logical_or.reduce(lower >= upper):
        raise ValueError('Each lower bound must be strictly less than each upper bound.')
    # lsq_linear's unbounded solution, its cutoff machine precision.
    solution = least_squares(matrix, rhs, -1)
    if np.logical_and.reduce((solution >= lower) & (solution <= upper)):
        return solution
    return _bounded_variables(matrix, rhs, solution, lower, upper, 1e-10)


def _bounded_variables(matrix: np.ndarray, rhs: np.ndarray, start: np.ndarray,
                       lower: np.ndarray, upper: np.ndarray, tolerance: float) -> np.ndarray:
    """Return scipy's ``bvls(matrix, rhs, start, lower, upper, tolerance, None, 0).x``."""
    size = matrix.shape[1]
    x = start.copy()
    on_bound = np.zeros(size)
    mask = x <= lower
    x[mask] = lower[mask]
    on_bound[mask] = -1
    mask = x >= upper
    x[mask] = upper[mask]
    on_bound[mask] = 1
    free = on_bound == 0
    active = ~free
    free_set = free.nonzero()[0]
    residual = matrix.dot(x) - rhs
    cost = 0.5 * np.dot(residual, residual)
    gradient = matrix.T.dot(residual)
    # The start: least squares on the free variables, those it puts beyond a bound fixed
    # there, until the free ones' solution is feasible.
    iteration = 0
    while free_set.size > 0:
        iteration += 1
        solution = least_squares(matrix[:, free_set], rhs - matrix.dot(x * active))
        below = solution < lower[free_set]
        above = solution > upper[free_set]
        beyond = below | above
        if below.any():
            index = free_set[below]
            x[index] = lower[index]
            active[index] = True
            on_bound[index] = -1
        if above.any():
            index = free_set[above]
            x[index] = upper[index]
            active[index] = True
            on_bound[index] = 1
        x[free_set[~beyond]] = solution[~beyond]
        residual = matrix.dot(x) - rhs
        cost = 0.5 * np.dot(residual, residual)
        gradient = matrix.T.dot(residual)
        if beyond.any():
            free_set = free_set[~beyond]
        else:
            break
    optimality = _violation(gradient, on_bound)
    for _ in range(iteration, size + iteration):
        if optimality < tolerance:
            break
        on_bound[np.argmax(gradient * on_bound)] = 0
        while True:
            free = on_bound == 0
            active = ~free
            free_set = free.nonzero()[0]
            x_free = x[free_set]
            lower_free, upper_free = lower[free_set], upper[free_set]
            solution = least_squares(matrix[:, free_set], rhs - matrix.dot(x * active))
            below = (solution < lower_free).nonzero()[0]
            above = (solution > upper_free).nonzero()[0]
            beyond = np.hstack((below, above))
            if beyond.size > 0:
                # The step towards the solution stops at the first bound it meets.
                alphas = np.hstack((lower_free[below] - x_free[below],
                                    upper_free[above] - x_free[above])) / \
                    (solution[beyond] - x_free[beyond])
                first = np.argmin(alphas)
                alpha = alphas[first]
                x_free *= 1 - alpha
                x_free += alpha * solution
                x[free_set] = x_free
                on_bound[free_set[beyond[first]]] = -1 if first < below.size else 1
            else:
                x[free_set] = solution
                break
        residual = matrix.dot(x) - rhs
        new_cost = 0.5 * np.dot(residual, residual)
        settled = cost - new_cost < tolerance * cost
        cost = new_cost
        gradient = matrix.T.dot(residual)
        optimality = _violation(gradient, on_bound)
        if settled:
            break
    return x


def _violation(gradient: np.ndarray, on_bound: np.ndarray) -> float:
    """Return the largest violation of the optimality conditions (scipy's KKT measure)."""
    violation = gradient * on_bound
    free = on_bound == 0
    violation[free] = np.abs(gradient[free])
    return np.max(violation)


def solve(matrix: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """
    Return ``x`` with ``matrix x = rhs`` as numpy's linalg does it (LAPACK's gesv).

    Raises LinAlgError for a singular matrix, as numpy does.
    """
    solution, info = lapack.dgesv(matrix, rhs)[2:]
    if info != 0:
        raise np.linalg.LinAlgError('Singular matrix')
    return solution


def solve_or_none(matrix: np.ndarray, rhs: np.ndarray) -> Optional[np.ndarray]:
    """Return :func:`solve`'s solution, or None for a singular matrix (a caller's no-step)."""
    try:
        return solve(matrix, rhs)
    except np.linalg.LinAlgError:
        return None


def normal_solution(gram: np.ndarray, rhs: np.ndarray, condition_limit: float
                    ) -> Optional[np.ndarray]:
    """
    Return the solution of the normal equations ``gram x = rhs``, or None if ill conditioned.

    None unless the columns behind ``gram`` (``gram = A^T A``), scaled to unit norm, are
    conditioned within ``condition_limit``: the normal equations' ``cond^2 eps`` relative error
    is then small, and a caller falls back to least squares on ``A`` otherwise. A zero or
    non-finite column is ill conditioned too.
    """
    scales = np.sqrt(gram.diagonal())
    if not np.logical_and.reduce((scales > 0.0) & (scales < np.inf)):
        return None
    # The scaled Gram matrix, by np.outer's product: its largest eigenvalue is at least 1.
    eigenvalues = symmetric_eigenvalues(gram / (scales[:, None] * scales))
    if not eigenvalues[0] >= eigenvalues[-1] / condition_limit ** 2:
        return None
    return solve(gram, rhs)


def symmetric_eigenvalues(matrix: np.ndarray) -> np.ndarray:
    """Return ``np.linalg.eigvalsh(matrix)`` of one matrix, ascending (LAPACK's syevd)."""
    eigenvalues, _, info = lapack.dsyevd(matrix, compute_v=0, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError('Eigenvalues did not converge')
    return eigenvalues


def symmetric_eigen(matrix: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Return ``np.linalg.eigh(matrix)`` of one symmetric matrix (syevd, the lower triangle)."""
    values, vectors, info = lapack.dsyevd(matrix, compute_v=1, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError('Eigenvalues did not converge')
    return values, vectors


def condition(matrix: np.ndarray) -> float:
    """Return ``np.linalg.cond(matrix)`` of a finite matrix: its singular values' ratio (gesdd)."""
    values, info = lapack.dgesdd(matrix, compute_uv=0)[1::2]
    if info != 0:
        raise np.linalg.LinAlgError('SVD did not converge')
    largest, smallest = values[0].item(), values[-1].item()
    # numpy's quotient for a smallest value of 0 is inf, also where 0/0 gives nan.
    return math.inf if smallest == 0.0 else largest / smallest


def thin_svd(matrix: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return ``np.linalg.svd(matrix, full_matrices=False)`` (gesdd, numpy's optimal workspace).

    ``u`` and ``vh`` in numpy's row order, as its products expect. An empty matrix (nothing
    free) takes numpy's own empty factors: LAPACK refuses it.
    """
    if not matrix.size:
        return np.linalg.svd(matrix, full_matrices=False)
    rows, columns = matrix.shape
    workspace = int(lapack.dgesdd_lwork(rows, columns, compute_uv=1, full_matrices=0)[0])
    u, singular, vh, info = lapack.dgesdd(matrix, compute_uv=1, full_matrices=0,
                                          lwork=workspace)
    if info != 0:
        raise np.linalg.LinAlgError('SVD did not converge')
    return np.ascontiguousarray(u), singular, np.ascontiguousarray(vh)
