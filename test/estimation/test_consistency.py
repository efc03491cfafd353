"""Model adequacy across the record: block estimates against the whole (Estimate.consistency)."""

from bench.coverage import arma_noise, FOPDT, FOPDT_BOUNDS, INADEQUATE
from ctid_ros import Data, estimate
from ctid_ros.core import reference_systems as systems
from ctid_ros.estimation.consistency import block_deviations, consistency_bound
from ctid_ros.estimation.noise import NoiseModel
import numpy as np
import pytest
from scipy import linalg, signal


def noisy(clean, rng, snr_db=20.0):
    return clean + np.std(clean) / 10.0 ** (snr_db / 20.0) * arma_noise(rng, clean.size)


def test_an_adequate_model_with_arma_noise_is_consistent_and_reports_it():
    system = systems.first_order_dead_time()
    rng = np.random.default_rng(3)
    clean = system.noise_free()
    data = Data(system.u, noisy(clean, rng, system.snr_db), system.ts)
    result = estimate(system.model, data, 'auto', bounds=system.bounds)
    consistency = result.consistency
    assert consistency.consistent
    assert consistency.blocks == 6
    assert consistency.bound == pytest.approx(consistency_bound(18))
    assert consistency.bound == pytest.approx(3.86, abs=0.01)
    assert 0.0 < consistency.max_z < consistency.bound
    assert result.std == result.std_noise
    # The change test's standard deviations leave out the t factors and the restored noise:
    # a few per cent narrower on 2 550 samples of ARMA noise.
    for name in system.model.parameters:
        assert 0.9 * result.std[name] < result.std_change[name] < result.std[name]
    assert consistency.verdict.startswith('consistent over the record')
    summary = result.to_dict()['consistency']
    assert summary['consistent'] is True and summary['blocks'] == 6
    assert summary['max_z'] == pytest.approx(consistency.max_z)
    assert 'the model does not hold' not in ' '.join(result.warnings)


@pytest.mark.parametrize('case', list(INADEQUATE))
def test_a_model_that_does_not_hold_over_the_record_is_flagged(case):
    # A FOPDT fitted to a second order plus dead time, to a gain drifting by +-15 %, and to a
    # saturating plant, on a record whose input changes character halfway (as operating
    # records do), ARMA noise at 20 dB: the blocks' estimates move by 4-6 std (bench/coverage.py
    # counts how often each is flagged).
    data = INADEQUATE[case](np.random.default_rng(11))
    result = estimate(FOPDT, data, 'auto', bounds=FOPDT_BOUNDS)
    consistency = result.consistency
    assert not consistency.consistent
    assert consistency.max_z > consistency.bound
    assert 'the model does not hold over the record' in consistency.verdict
    assert consistency.verdict in result.warnings
    assert 'the standard deviations account for it' not in result.residuals.verdict
    assert len(consistency.quarter_params) == 4
    # The reported std covers the quarters' scatter; the noise-only one stays available.
    for name in FOPDT.parameters:
        quarters = [quarter[name] for quarter in consistency.quarter_params]
        assert result.std[name] >= np.std(quarters, ddof=1) - 1e-12
        assert result.std[name] >= result.std_noise[name]
    assert any(result.std[name] > 1.5 * result.std_noise[name] for name in FOPDT.parameters)
    std = np.sqrt(np.diag(result.covariance))
    assert std == pytest.approx([result.std[name] for name in FOPDT.parameters])
    summary = result.to_dict()
    assert summary['consistency']['consistent'] is False
    assert summary['std_noise'] == pytest.approx(result.std_noise)


def test_false_alarms_of_adequate_models_with_arma_noise_are_rare():
    # 40 records of the non-affine second order with ARMA noise at its 10 dB: at most one
    # flagged (the bound is set for 1 %; bench/coverage.py --consistency counts 200).
    system = systems.second_order_nonaffine()
    rng = np.random.default_rng(5)
    clean = system.noise_free()
    flagged = 0
    for _ in range(40):
        data = Data(system.u, noisy(clean, rng, system.snr_db), system.ts)
        flagged += not estimate(system.model, data, 'auto',
                                bounds=system.bounds).consistency.consistent
    assert flagged <= 1


@pytest.mark.parametrize('roots', [[], [0.5], [0.8, -0.4],
                                   [0.8 * np.exp(0.4j), 0.8 * np.exp(-0.4j)], [0.995]])
def test_block_deviations_equal_the_dense_covariance_of_each_block(roots):
    # d_b = (A_b - A) e and diag((A_b - A) Sigma (A_b - A)^T), Sigma = c s^2 H H^T with H the
    # impulse-response matrix of 1/A: the filtered-once path (short memories) and the block by
    # block one (the near-unit root) against dense matrices.
    count = 2400
    rng = np.random.default_rng(7)
    sensitivities = rng.standard_normal((count, 3))
    sensitivities[:, 1] += 0.6 * sensitivities[:, 0]
    sensitivities /= np.linalg.norm(sensitivities, axis=0)
    residual = rng.standard_normal(count)
    ar = np.real(np.poly(roots)) if roots else np.ones(1)
    noise = NoiseModel(ar, 0.3, 1.0)
    impulse = signal.lfilter([1.0], ar, np.eye(count)[0])
    response = linalg.toeplitz(impulse, np.zeros(count))
    sigma = 1.01 * 0.3 * response @ response.T
    whole = np.linalg.pinv(sensitivities)
    edges = {2: np.linspace(0, count, 3).round().astype(int),
             4: np.linspace(0, count, 5).round().astype(int)}
    expected = []
    for parts, names in ((2, ('first half', 'second half')),
                         (4, ('quarter 1', 'quarter 2', 'quarter 3', 'quarter 4'))):
        for name, first, last in zip(names, edges[parts][:-1], edges[parts][1:]):
            local = np.zeros_like(whole)
            local[:, first:last] = np.linalg.pinv(sensitivities[first:last])
            difference = local - whole
            expected.append((name, difference @ residual,
                             np.diag(difference @ sigma @ difference.T)))
    blocks = block_deviations(sensitivities, residual, noise, 1.01)
    assert [block[0] for block in blocks] == [block[0] for block in expected]
    for (_, deviation, variance), (_, want_deviation, want_variance) in zip(blocks, expected):
        np.testing.assert_allclose(deviation, want_deviation, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(variance, want_variance, rtol=1e-9)
