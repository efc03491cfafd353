"""Noise model, coloured-residual covariance and the measured rate (docs/algorithm.md 15)."""

from ctid_ros.core.model import Model
from ctid_ros.estimation.noise import (coloured_covariance, inverse_filtered,
                                       measured_every, noise_memory, noise_model, noise_root,
                                       NoiseModel, rational_form)
import numpy as np
import pytest
from scipy import linalg, signal


def ar1(pole, count, rng):
    """Return stationary AR(1) noise of unit variance."""
    white = rng.standard_normal(count + 500)
    return signal.lfilter([np.sqrt(1.0 - pole ** 2)], [1.0, -pole], white)[500:]


def test_white_residual_gives_order_zero_and_the_white_formula_exactly():
    rng = np.random.default_rng(1)
    residual = rng.standard_normal(3000)
    psi = np.column_stack([np.sin(0.01 * np.arange(3000)), np.ones(3000)])
    covariance, model = coloured_covariance(psi, residual, 2)
    assert model.order == 0
    variance = residual @ residual / (3000 - 2)
    np.testing.assert_allclose(covariance, variance * np.linalg.inv(psi.T @ psi), rtol=1e-10)


def test_ar1_pole_is_recovered():
    model = noise_model(ar1(0.9, 5000, np.random.default_rng(2)))
    assert model.order >= 1
    assert -model.ar[1] == pytest.approx(0.9, abs=0.02)
    # Low-frequency power over white noise of equal variance: (1 + p) / (1 - p) = 19.
    assert model.variance_ratio == pytest.approx(19.0, rel=0.15)


def test_sandwich_matches_the_exact_covariance_of_a_regression_with_ar1_noise():
    # Regression y = Psi theta + e with AR(1) noise: the exact covariance of the least-squares
    # estimate is (Psi^T Psi)^-1 Psi^T Sigma Psi (Psi^T Psi)^-1 with the true Sigma.
    count, pole = 2000, 0.8
    time = np.arange(count)
    psi = np.column_stack([np.sin(2 * np.pi * time / 400), np.cos(2 * np.pi * time / 150),
                           np.ones(count)])
    sigma = linalg.toeplitz(pole ** np.arange(count))
    gram = np.linalg.inv(psi.T @ psi)
    exact = gram @ psi.T @ sigma @ psi @ gram
    rng = np.random.default_rng(3)
    estimates = [coloured_covariance(psi, ar1(pole, count, rng), 3)[0] for _ in range(20)]
    ratio = np.diag(np.mean(estimates, axis=0)) / np.diag(exact)
    np.testing.assert_allclose(ratio, 1.0, atol=0.15)
    white_formula = np.diag(gram)               # sigma^2 = 1
    assert np.all(np.diag(exact) > 3.0 * white_formula)


@pytest.mark.parametrize('factor', [2, 4, 10])
def test_interpolated_and_held_outputs_are_recognised(factor):
    rng = np.random.default_rng(factor)
    measured = np.cumsum(rng.standard_normal(400))
    fine = np.arange((measured.size - 1) * factor + 1) / factor
    assert measured_every(np.interp(fine, np.arange(measured.size), measured)) == factor
    assert measured_every(np.repeat(measured, factor)) == factor


def test_measured_outputs_are_not_mistaken_for_interpolated_ones():
    rng = np.random.default_rng(5)
    assert measured_every(rng.standard_normal(2000)) == 1
    # A quantised, slowly moving signal repeats values and bends irregularly.
    quantised = np.round(np.cumsum(0.3 * rng.standard_normal(2000)))
    assert measured_every(quantised) == 1
    assert measured_every(np.sin(0.01 * np.arange(2000))) == 1


def loop_sensitivity_response(count):
    """Return the pulse response of ``1 - T`` of a PI loop around a lag and an integrator."""
    model = Model('1/(J*s**2 + b*s)', controller='40 + 20/s')
    pulse = np.zeros(count)
    pulse[0] = 1.0
    shaping = -model.simulate({'J': 1.0, 'b': 2.0}, pulse, 0.01)
    shaping[0] += 1.0
    return shaping


def test_loop_sensitivity_has_its_low_order_rational_form_found():
    shaping = loop_sensitivity_response(4000)
    num, den = rational_form(shaping)
    # The closed loop has degree 3 in s: its sampled sensitivity has order 3.
    assert den.size == 4 and num.size == 4
    response = signal.lfilter(num, den, np.eye(1, 4000)[0])
    np.testing.assert_allclose(response, shaping, rtol=0.0, atol=1e-10 * np.abs(shaping).max())


def test_order_hint_finds_the_same_form_with_any_hint():
    shaping = loop_sensitivity_response(4000)
    num, den = rational_form(shaping)
    # A right hint (the loop's degree) and wrong ones, below and above, give the same result.
    for hint in (1, 2, 3, 4, 7):
        hinted = rational_form(shaping, order_hint=hint)
        np.testing.assert_array_equal(hinted[0], num)
        np.testing.assert_array_equal(hinted[1], den)
    # A response with a pole and a zero 1e-12 apart has an order-1 form: a hint of its
    # nominal order 2 must not skip it.
    pulse = np.eye(1, 500)[0]
    near = signal.lfilter([1.0, -0.5 - 1e-12], np.poly([0.5, 0.8]), pulse)
    assert rational_form(near)[1].size == 2
    assert rational_form(near, order_hint=2)[1].size == 2


def test_inverse_filter_equals_the_long_forward_substitution():
    shaping = loop_sensitivity_response(4000)
    residual = ar1(0.5, 4000, np.random.default_rng(7))
    residual -= residual.mean()
    long_form = signal.lfilter([1.0], shaping, residual)
    inverse = inverse_filtered(shaping, residual)
    # H w = e holds for the result (to rounding, up to the tail beyond the response's length).
    np.testing.assert_allclose(np.convolve(shaping, inverse)[:4000], residual, rtol=0.0,
                               atol=1e-9 * np.abs(residual).max())
    # S has a zero at z = 1 (the integrators): both inverses accumulate, and the long form's
    # response, cut after 4000 samples, has that zero moved by its tail, so they drift apart
    # by that much and no more.
    np.testing.assert_allclose(inverse, long_form, rtol=0.0, atol=1e-6 * np.abs(long_form).max())


def test_response_without_a_low_order_form_takes_the_long_substitution():
    rng = np.random.default_rng(8)
    shaping = np.concatenate([[1.0], 0.3 * rng.standard_normal(200) / np.arange(2, 202) ** 2])
    assert rational_form(shaping) is None
    values = rng.standard_normal(1000)
    np.testing.assert_allclose(inverse_filtered(shaping, values),
                               signal.lfilter([1.0], shaping, values), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('roots', [[0.9], [0.99, 0.99, 0.99],
                                   [0.95 * np.exp(0.3j), 0.95 * np.exp(-0.3j), -0.5]])
def test_noise_root_past_the_memory_depends_on_its_last_samples_only(roots):
    # A map supported on a late block, filtered backwards over the block and the memory only,
    # equals the whole backward filter there; before it the whole filter is zero to rounding.
    model = NoiseModel(np.real(np.poly(roots)), 1.0, 1.0)
    count = 40000
    memory = noise_memory(model, count)
    assert memory < 20000
    columns = np.zeros((count, 2))
    columns[30000:] = np.random.default_rng(5).standard_normal((count - 30000, 2))
    whole = noise_root(columns, model)
    part = noise_root(columns[30000 - memory:], model)
    scale = np.max(np.abs(whole))
    np.testing.assert_allclose(part, whole[30000 - memory:], rtol=0, atol=1e-13 * scale)
    assert np.max(np.abs(whole[:30000 - memory])) <= 1e-18 * scale


def test_noise_memory_is_the_whole_record_for_a_root_on_the_unit_circle():
    assert noise_memory(NoiseModel(np.array([1.0, -1.0]), 1.0, 1.0), 5000) == 5000
