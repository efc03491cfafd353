"""
numpy.linalg's solvers for the estimator's small matrices, by LAPACK directly.

numpy's wrappers (type checks, error state, the result's wrapping) cost tens of Python-level
calls each, more than the LAPACK routine itself on the few-by-few matrices of the estimator's
updates, checks and starts (several per update). These call the routine numpy calls, with
numpy's settings: the same results to the bit (checked on every call of 10 estimates per
reference system). Float64 arrays only. Beside them, :func:`gram_matrix`: the normal matrix
of a few columns over a record, in the form OpenBLAS forms fastest.
"""

import math
from typing import Optional, Tuple

import numpy as np
from scipy.linalg import lapack

__all__ = ['condition', 'gram_matrix', 'least_squares', 'normal_solution', 'solve',
           'solve_or_none', 'symmetric_eigen', 'symmetric_eigenvalues', 'thin_svd']

# The spacing of floats at 1: numpy's least-squares cutoff is it times the longer side.
_EPSILON = np.finfo(float).eps
# Three record-length columns from this many rows on have their Gram padded (gram_matrix).
_PADDED_ROWS = 1024


def gram_matrix(columns: np.ndarray) -> np.ndarray:
    """
    Return ``columns^T columns`` of an ``N x p`` matrix of columns over a record.

    OpenBLAS forms the products of three columns over a record more slowly than those of
    four, so three columns from :data:`_PADDED_ROWS` rows on get a zero fourth column: its
    products are zeros and the others are the same sums, to the bit (checked on every call
    of 10 estimates per reference system). Other counts and shorter records gain nothing
    (one or five columns padded take longer, and one column's products change in the last
    bits).
    """
    rows, count = columns.shape
    if count != 3 or rows < _PADDED_ROWS:
        return columns.T @ columns
    padded = np.zeros((4, rows))
    padded[:3] = columns.T
    return (padded @ padded.T)[:3, :3]


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
