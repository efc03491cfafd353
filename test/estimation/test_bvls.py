"""bounded_least_squares: scipy's lsq_linear(method='bvls') to the bit, without its overhead."""

from ctid_ros.estimation.bvls import bounded_least_squares
import numpy as np
import pytest
from scipy.optimize import lsq_linear


def test_bounded_least_squares_gives_scipys_bvls_bits():
    rng = np.random.default_rng(11)
    through_bvls = 0
    for _ in range(300):
        rows = int(rng.integers(2, 9))
        columns = int(rng.integers(1, rows + 1))
        matrix = rng.standard_normal((rows, columns)) * 10.0 ** rng.uniform(-3, 3, columns)
        rhs = rng.standard_normal(rows)
        lower = np.where(rng.random(columns) < 0.8, rng.uniform(-1.0, 0.5, columns), -np.inf)
        upper = np.where(rng.random(columns) < 0.5, rng.uniform(0.6, 2.0, columns), np.inf)
        expected = lsq_linear(matrix, rhs, bounds=(lower, upper), method='bvls')
        through_bvls += expected.status != 3
        np.testing.assert_array_equal(bounded_least_squares(matrix, rhs, lower, upper),
                                      expected.x)
    assert through_bvls > 100           # the bounded algorithm itself, not only the unbounded
    with pytest.raises(ValueError):
        bounded_least_squares(np.eye(2), np.ones(2), np.zeros(2), np.array([1.0, 0.0]))
