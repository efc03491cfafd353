"""Model adequacy across the record: block estimates against the whole (Estimate.consistency)."""

from bench.coverage import arma_noise, FOPDT, FOPDT_BOUNDS, INADEQUATE
from ctid_ros import Data, estimate
from ctid_ros.core import reference_systems as systems
from ctid_ros.estimation.consistency import consistency_bound
import numpy as np
import pytest


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
