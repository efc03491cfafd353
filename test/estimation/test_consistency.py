"""Model adequacy across the record: block estimates against the whole (Estimate.consistency)."""

from ctid_ros import Data, estimate, Model
from ctid_ros.core import reference_systems as systems
from ctid_ros.core.excitation import prbs
from ctid_ros.estimation.consistency import consistency_bound
import numpy as np
import pytest
from scipy import signal

FOPDT = Model('K*exp(-tau*s)/(T*s + 1)')
FOPDT_BOUNDS = {'T': (1e-3, None), 'tau': (0.0, 10.0)}
TRUTH = {'K': 2.0, 'T': 5.0, 'tau': 1.234}


def arma_noise(rng, count):
    """Return ARMA noise (1 + 0.5 q^-1) / (1 - 0.9 q^-1) of unit variance."""
    values = signal.lfilter([1.0, 0.5], [1.0, -0.9], rng.standard_normal(count + 500))[500:]
    return values / np.std(values)


def operating_input():
    """Return an input that is not stationary: slow moves, then faster ones (Ts 0.1 s)."""
    return np.concatenate([prbs(7, 30), prbs(8, 6)])


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
    assert 0.0 < consistency.max_z < consistency.bound
    assert result.std == result.std_noise
    assert consistency.verdict.startswith('consistent over the record')
    summary = result.to_dict()['consistency']
    assert summary['consistent'] is True and summary['blocks'] == 6
    assert summary['max_z'] == pytest.approx(consistency.max_z)
    assert 'the model does not hold' not in ' '.join(result.warnings)


@pytest.mark.parametrize('case', ['missing lag', 'time-varying gain', 'saturation'])
def test_a_model_that_does_not_hold_over_the_record_is_flagged(case):
    # A FOPDT fitted to a second order plus dead time, to a gain drifting by +-15 %, and to a
    # saturating plant, on a record whose input changes character halfway (as operating
    # records do), ARMA noise at 20 dB: the quarters' estimates move by 4-6 std.
    rng = np.random.default_rng(11)
    u = operating_input()
    if case == 'missing lag':
        clean = Model('K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))').simulate(
            {'K': 2.0, 'T1': 1.5, 'T2': 0.6, 'tau': 0.7}, u, 0.1)
    elif case == 'time-varying gain':
        clean = FOPDT.simulate(TRUTH, u, 0.1) * np.linspace(0.85, 1.15, u.size)
    else:
        u = np.concatenate([0.4 * prbs(7, 30), 1.5 * prbs(8, 6)])
        clean = 1.5 * np.tanh(FOPDT.simulate(TRUTH, u, 0.1) / 1.5)
    result = estimate(FOPDT, Data(u, noisy(clean, rng), 0.1), 'auto', bounds=FOPDT_BOUNDS)
    consistency = result.consistency
    assert not consistency.consistent
    assert consistency.max_z > consistency.bound
    assert 'the model does not hold over the record' in consistency.verdict
    assert consistency.verdict in result.warnings
    assert 'account for it' not in result.residuals.verdict
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
