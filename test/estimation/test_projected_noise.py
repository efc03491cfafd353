"""The noise a fit projected off, restored before the covariance; its degrees of freedom."""

from ctid_ros.estimation.noise import noise_model, NoiseModel
from ctid_ros.estimation.projected_noise import (filtered_twice, noise_freedom,
                                                 restored_noise_model)
import numpy as np
import pytest
from scipy import signal


def low_frequency_level(model):
    """Return the model's spectrum at frequency 0."""
    return model.innovation_variance / np.sum(model.ar) ** 2


def test_the_restored_noise_model_recovers_the_low_frequency_level_of_short_records():
    # 300 samples of AR(1) noise, pole 0.9 (level 100 for unit innovations), with two slow
    # columns fitted and removed: the residual's own model misses a fifth or more of the level.
    rng = np.random.default_rng(3)
    count = 300
    time = np.arange(count)
    columns = np.column_stack([1.0 - np.exp(-time / 40.0), np.sin(2 * np.pi * time / 150.0)])
    left, _, _ = np.linalg.svd(columns, full_matrices=False)
    raw, restored = [], []
    for _ in range(200):
        noise = signal.lfilter([1.0], [1.0, -0.9], rng.standard_normal(count + 300))[300:]
        residual = noise - left @ (left.T @ noise)
        raw.append(low_frequency_level(noise_model(residual)))
        restored.append(low_frequency_level(restored_noise_model(left, residual)))
    assert np.mean(raw) < 0.8 * 100.0
    # The mean of a skewed estimate: 114 here (the residual's own model 75).
    assert np.mean(restored) == pytest.approx(100.0, rel=0.2)


def test_white_noise_keeps_its_degrees_of_freedom():
    rng = np.random.default_rng(0)
    residual = rng.standard_normal(500)
    left, _, _ = np.linalg.svd(rng.standard_normal((500, 3)), full_matrices=False)
    model = noise_model(residual)
    assert model.order == 0
    assert restored_noise_model(left, residual, start=model) is model
    assert noise_freedom(left, np.eye(3), model, 500, 3) == pytest.approx(497.0)


def test_a_slow_parameter_under_coloured_noise_has_few_degrees_of_freedom():
    # AR(1) of pole 0.9 on 300 samples: about N / (2 r) = 300 / 38 for a slow column.
    rng = np.random.default_rng(1)
    count = 300
    noise = signal.lfilter([1.0], [1.0, -0.9], rng.standard_normal(count))
    slow = np.ones((count, 1)) / np.sqrt(count)
    model = noise_model(noise)
    freedom = noise_freedom(slow, np.eye(1), model, count, 1)
    assert 3.0 < freedom[0] < 20.0
    # A residual that lacks a quarter of the low-frequency level determines its model less.
    depleted = noise_freedom(slow, np.eye(1), model, count, 1, removed_share=0.25)
    assert depleted[0] == pytest.approx(0.75 * freedom[0], rel=0.1)


@pytest.mark.parametrize('roots', [[0.5], [0.6, -0.25], [0.3 * np.exp(0.8j), 0.3 * np.exp(-0.8j)],
                                   [0.999], [0.2] * 9])
def test_columns_filtered_twice_equal_two_backward_filters(roots):
    # Z = H^T X and Y = H^T Z, H the impulse-response matrix of 1/A, against lfilter on the
    # reversed columns: the squared recursion with A's FIR where A is short and far from the
    # unit circle, two recursions where not (a root at 0.999, order 9).
    ar = np.real(np.poly(roots))
    columns = np.random.default_rng(5).standard_normal((1500, 3))
    once = signal.lfilter([1.0], ar, columns[::-1], axis=0)
    twice = signal.lfilter([1.0], ar, once, axis=0)[::-1]
    root, again = filtered_twice(columns, NoiseModel(ar, 0.3, 1.0))
    np.testing.assert_allclose(root, once[::-1], rtol=0, atol=1e-12 * np.abs(once).max())
    np.testing.assert_allclose(again, twice, rtol=0, atol=1e-12 * np.abs(twice).max())
