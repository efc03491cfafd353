"""The direct LAPACK solvers give numpy.linalg's results to the bit."""

from ctid_ros.estimation import linear_algebra
import numpy as np
import pytest

SIZES = [1, 2, 3, 4, 6]


def _symmetric(rng: np.random.Generator, size: int) -> np.ndarray:
    half = rng.standard_normal((size + 3, size))
    return half.T @ half


@pytest.mark.parametrize('size', SIZES)
def test_solvers_give_numpys_bits(size):
    rng = np.random.default_rng(size)
    for _ in range(20):
        matrix = rng.standard_normal((size, size))
        rhs = rng.standard_normal(size)
        np.testing.assert_array_equal(linear_algebra.solve(matrix, rhs),
                                      np.linalg.solve(matrix, rhs))
        tall = rng.standard_normal((3 * size + 2, size))
        long_rhs = rng.standard_normal(3 * size + 2)
        np.testing.assert_array_equal(linear_algebra.least_squares(tall, long_rhs),
                                      np.linalg.lstsq(tall, long_rhs, rcond=None)[0])
        symmetric = _symmetric(rng, size)
        np.testing.assert_array_equal(linear_algebra.symmetric_eigenvalues(symmetric),
                                      np.linalg.eigvalsh(symmetric))
        values, vectors = linear_algebra.symmetric_eigen(symmetric)
        expected_values, expected_vectors = np.linalg.eigh(symmetric)
        np.testing.assert_array_equal(values, expected_values)
        np.testing.assert_array_equal(vectors, expected_vectors)
        assert linear_algebra.condition(matrix) == np.linalg.cond(matrix)
        for got, expected in zip(linear_algebra.thin_svd(tall),
                                 np.linalg.svd(tall, full_matrices=False)):
            np.testing.assert_array_equal(got, expected)


def test_singular_and_empty_matrices_behave_as_in_numpy():
    singular = np.array([[1.0, 2.0], [2.0, 4.0]])
    with pytest.raises(np.linalg.LinAlgError):
        linear_algebra.solve(singular, np.ones(2))
    assert linear_algebra.condition(np.zeros((2, 2))) == np.inf
    u, values, vh = linear_algebra.thin_svd(np.zeros((5, 0)))
    assert u.shape == (5, 0) and values.shape == (0,) and vh.shape == (0, 0)
    wide = np.random.default_rng(0).standard_normal((2, 4))
    np.testing.assert_array_equal(linear_algebra.least_squares(wide, np.ones(2)),
                                  np.linalg.lstsq(wide, np.ones(2), rcond=None)[0])


def test_normal_solution_only_where_the_scaled_columns_are_well_conditioned():
    rng = np.random.default_rng(7)
    columns = rng.standard_normal((40, 3)) * [1.0, 1e4, 1e-3]     # scales alone: conditioned
    rhs = rng.standard_normal(3)
    gram = columns.T @ columns
    np.testing.assert_array_equal(linear_algebra.normal_solution(gram, rhs, 1e3),
                                  np.linalg.solve(gram, rhs))
    nearly_dependent = columns.copy()
    nearly_dependent[:, 2] = nearly_dependent[:, 0] + 1e-6 * rng.standard_normal(40)
    assert linear_algebra.normal_solution(nearly_dependent.T @ nearly_dependent, rhs,
                                          1e3) is None
    zero_column = columns.copy()
    zero_column[:, 1] = 0.0
    assert linear_algebra.normal_solution(zero_column.T @ zero_column, rhs, 1e3) is None


def test_solve_or_none_gives_none_for_a_singular_matrix():
    matrix = np.array([[2.0, 1.0], [1.0, 3.0]])
    np.testing.assert_array_equal(linear_algebra.solve_or_none(matrix, np.ones(2)),
                                  np.linalg.solve(matrix, np.ones(2)))
    assert linear_algebra.solve_or_none(np.array([[1.0, 2.0], [2.0, 4.0]]), np.ones(2)) is None


@pytest.mark.parametrize('rows', [10, 1023, 1024, 2550, 10220])
@pytest.mark.parametrize('count', [1, 2, 3, 4])
def test_gram_matrix_is_the_product_of_the_columns(rows, count):
    # The padded product (three columns from 1024 rows on) sums the same terms in the same
    # order as the plain one in OpenBLAS; another BLAS may order them otherwise, so within a
    # few units of the last place of the largest entry.
    columns = np.random.default_rng(rows + count).standard_normal((rows, count))
    got = linear_algebra.gram_matrix(columns)
    expected = columns.T @ columns
    assert got.shape == (count, count)
    np.testing.assert_allclose(got, expected, rtol=0, atol=8 * np.spacing(np.abs(expected).max()))
    np.testing.assert_array_equal(got, got.T)
