"""
Bounded-variable least squares (Stark and Parker), step for step as SciPy's.

``scipy.optimize.lsq_linear(method='bvls')`` spends more on checking its arguments, building
its result and its norms than on the few-by-few problems of the equation-error starts
(issue #26): this is the algorithm alone, with the same steps and arithmetic, so the same
result to the bit (``test/estimation/test_bvls.py`` compares them).
:func:`bounded_least_squares` runs it where the unbounded solution leaves the box.

Adapted from SciPy's ``scipy/optimize/_lsq/bvls.py``, which carries this notice:

Copyright (c) 2001-2002 Enthought, Inc. 2003, SciPy Developers.
All rights reserved.

Redistribution and use in source and binary forms, with or without
modification, are permitted provided that the following conditions
are met:

1. Redistributions of source code must retain the above copyright
   notice, this list of conditions and the following disclaimer.

2. Redistributions in binary form must reproduce the above
   copyright notice, this list of conditions and the following
   disclaimer in the documentation and/or other materials provided
   with the distribution.

3. Neither the name of the copyright holder nor the names of its
   contributors may be used to endorse or promote products derived
   from this software without specific prior written permission.

THIS SOFTWARE IS PROVIDED BY THE COPYRIGHT HOLDERS AND CONTRIBUTORS
"AS IS" AND ANY EXPRESS OR IMPLIED WARRANTIES, INCLUDING, BUT NOT
LIMITED TO, THE IMPLIED WARRANTIES OF MERCHANTABILITY AND FITNESS FOR
A PARTICULAR PURPOSE ARE DISCLAIMED. IN NO EVENT SHALL THE COPYRIGHT
OWNER OR CONTRIBUTORS BE LIABLE FOR ANY DIRECT, INDIRECT, INCIDENTAL,
SPECIAL, EXEMPLARY, OR CONSEQUENTIAL DAMAGES (INCLUDING, BUT NOT
LIMITED TO, PROCUREMENT OF SUBSTITUTE GOODS OR SERVICES; LOSS OF USE,
DATA, OR PROFITS; OR BUSINESS INTERRUPTION) HOWEVER CAUSED AND ON ANY
THEORY OF LIABILITY, WHETHER IN CONTRACT, STRICT LIABILITY, OR TORT
(INCLUDING NEGLIGENCE OR OTHERWISE) ARISING IN ANY WAY OUT OF THE USE
OF THIS SOFTWARE, EVEN IF ADVISED OF THE POSSIBILITY OF SUCH DAMAGE.
"""

from ctid_ros.estimation.linear_algebra import least_squares
import numpy as np

__all__ = ['bounded_least_squares', 'bounded_variables']


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
    return bounded_variables(matrix, rhs, solution, lower, upper, 1e-10)


def bounded_variables(matrix: np.ndarray, rhs: np.ndarray, start: np.ndarray,
                      lower: np.ndarray, upper: np.ndarray, tolerance: float) -> np.ndarray:
    """
    Return scipy's ``bvls(matrix, rhs, start, lower, upper, tolerance, None, 0).x``.

    Parameters
    ----------
    matrix, rhs : numpy.ndarray
        The tall least-squares problem ``min |matrix x - rhs|``.
    start : numpy.ndarray
        Its unbounded solution.
    lower, upper : numpy.ndarray
        The bounds, ``lower < upper`` (infinite ones allowed).
    tolerance : float
        The largest violation of the optimality conditions accepted (scipy's ``tol``).

    """
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
