"""tune(): the rules' numbers, the design checked on the true plant, and the refusals."""

from types import SimpleNamespace

from ctid_ros.core.model import Model
from ctid_ros.core.reference_systems import two_lags_dead_time
from ctid_ros.design.margins import (closed_loop_step, Gains, integral_absolute_error,
                                     loop_margins, Plant)
from ctid_ros.design.tune import (DEFAULT_MS, loop_shaping, reduce, simc, tune,
                                  tune_from_settings)
from ctid_ros.errors import ConfigError, DesignError
from ctid_ros.estimation.estimate import estimate
import numpy as np
import pytest
import yaml


def known(expression, params, std=None):
    """Return an identified model given by hand: what tune() reads of an Estimate."""
    model = Model(expression)
    spread = np.array([(std or {}).get(name, 0.0) for name in model.parameters])
    return SimpleNamespace(model=model, params=params, covariance=np.diag(spread ** 2))


def test_simc_first_order_plus_dead_time_numbers():
    reduced = reduce(Plant.of([2.0], [5.0, 1.0], 1.0))
    assert reduced.lags == (5.0,) and reduced.delay == 1.0 and reduced.note == 'exact'
    gains = simc(reduced, 'PI')
    # Kc = tau1 / (k (tc + theta)) = 5 / 4, tau_I = min(5, 8) = 5.
    assert gains.kp == pytest.approx(1.25) and gains.ki == pytest.approx(0.25)
    assert simc(reduced, 'PI', tc=3.0).kp == pytest.approx(5.0 / 8.0)


def test_half_rule_and_series_to_parallel_pid():
    # Three lags 4, 1, 0.4 and dead time 0.2: PI keeps 4 + 0.5, theta 0.2 + 0.5 + 0.4.
    den = np.polymul(np.polymul([4.0, 1.0], [1.0, 1.0]), [0.4, 1.0])
    plant = Plant.of([3.0], den, 0.2)
    pi = reduce(plant, 'PI')
    assert pi.lags == pytest.approx((4.5,)) and pi.delay == pytest.approx(1.1)
    pid = reduce(plant, 'PID')
    assert pid.lags == pytest.approx((4.0, 1.2)) and pid.delay == pytest.approx(0.4)
    gains = simc(pid, 'PID')
    # Series Kc = 4 / (3 (tc + theta)), tau_I = min(4, 4 (tc + theta)), tau_D = 1.2; the
    # derivative filter (a tenth of the parallel Td of the first pass, 1.2 / (1 + 1.2 / 3.2))
    # joins the dead time and the default tc; then the parallel form.
    lag = 1.2 / (1 + 1.2 / 3.2) / 10.0
    total = 2 * (0.4 + lag)
    kc, ti, td = 4.0 / (3.0 * total), min(4.0, 4.0 * total), 1.2
    assert gains.tf == pytest.approx(lag)
    assert gains.kp == pytest.approx(kc * (1 + td / ti))
    assert gains.ki == pytest.approx(kc / ti)
    assert gains.kd == pytest.approx(kc * td)


def test_integrating_plant_rule():
    reduced = reduce(Plant.of([0.5], [2.0, 1.0, 0.0], 0.3), 'PI')
    # k/(s (2 s + 1)): the lag goes half into the dead time for a PI.
    assert reduced.integrators == 1 and reduced.delay == pytest.approx(1.3)
    gains = simc(reduced, 'PI')
    assert gains.kp == pytest.approx(1.0 / (0.5 * 2.6))
    assert gains.ki == pytest.approx(gains.kp / (4 * 2.6))


def test_pi_from_noisy_sopdt_data_on_the_true_plant():
    """Acceptance: identified from its own noisy data, applied to the true plant."""
    system = two_lags_dead_time()
    true_plant = Plant.from_model(system.model, system.truth)
    reference = simc(reduce(true_plant, 'PI'), 'PI')
    _, best = closed_loop_step(true_plant, reference, 40.0)[:2]
    times = closed_loop_step(true_plant, reference, 40.0)[0]
    best_iae = integral_absolute_error(times, best)
    for seed in (3, 4):
        result = estimate(system.model, system.data(seed))
        tuning = tune(result, 'PI', seed=seed)
        assert tuning.method.startswith('SIMC PI') and tuning.unstable_draws == 0
        on_truth = loop_margins(true_plant, tuning.gains)
        assert on_truth.stable and on_truth.ms <= 2.0
        times, output, _ = closed_loop_step(true_plant, tuning.gains, 40.0)
        assert integral_absolute_error(times, output) <= 1.5 * best_iae
        for name in ('gain_db', 'phase_deg', 'ms'):
            low, high = tuning.band[name]
            assert low <= getattr(on_truth, name) <= high, (seed, name, low, high)


def test_the_band_is_seeded_and_covers_the_spread():
    result = known('K*exp(-tau*s)/(T*s + 1)', {'K': 2.0, 'T': 5.0, 'tau': 1.0},
                   {'K': 0.1, 'T': 0.3, 'tau': 0.05})
    first, second = tune(result, seed=7), tune(result, seed=7)
    assert first.band == second.band
    low, high = first.band['phase_deg']
    assert low < first.margins.phase_deg < high and high - low > 1.0


def test_auto_uses_loop_shaping_for_complex_poles_and_meets_ms():
    result = known('K*exp(-tau*s)/(s**2 + 2*z*w*s + w**2)',
                   {'K': 4.0, 'z': 0.3, 'w': 2.0, 'tau': 0.2})
    tuning = tune(result, 'PI', draws=0)
    assert tuning.method.startswith('loop shaping') and tuning.target == {'ms': DEFAULT_MS}
    assert tuning.margins.stable and tuning.margins.ms <= DEFAULT_MS * 1.01
    assert tuning.margins.ms >= DEFAULT_MS * 0.95
    pid = tune(result, 'PID', target={'ms': 1.4}, draws=0)
    assert pid.gains.kd > 0 and pid.margins.ms <= 1.4 * 1.01 and pid.margins.stable


def test_loop_shaping_gives_a_negative_gain_plant_negative_gains():
    gains = loop_shaping(Plant.of([-2.0], [5.0, 1.0], 1.0), 'PI')
    assert gains.kp < 0 and gains.ki < 0
    assert loop_margins(Plant.of([-2.0], [5.0, 1.0], 1.0), gains).stable


@pytest.mark.parametrize('expression, params, controller, method, match', [
    ('K*exp(-tau*s)/(T*s - 1)', {'K': 1.0, 'T': 2.0, 'tau': 0.1}, 'PI', 'auto', 'unstable'),
    ('K*exp(-tau*s)*(1 - b*s)/((T1*s + 1)*(T2*s + 1))',
     {'K': 1.0, 'b': 0.5, 'T1': 2.0, 'T2': 0.5, 'tau': 0.1}, 'PI', 'simc', 'non-minimum'),
    ('K*exp(-tau*s)/(T*s + 1)', {'K': 1.0, 'T': 2.0, 'tau': 0.1}, 'PID', 'simc', 'second lag'),
    ('K*exp(-tau*s)/s**2', {'K': 1.0, 'tau': 0.1}, 'PI', 'auto', 'double integrator'),
    ('K/(T*s + 1)', {'K': 1.0, 'T': 2.0}, 'PI', 'simc', 'no dead time'),
])
def test_requests_a_rule_cannot_serve_are_refused(expression, params, controller, method,
                                                  match):
    with pytest.raises(DesignError, match=match):
        tune(known(expression, params), controller, method)


def test_double_integrator_gets_a_pid():
    tuning = tune(known('K*exp(-tau*s)/s**2', {'K': 1.0, 'tau': 0.1}), 'PID', draws=0)
    # SIMC's double-integrating rule: Ms 1.96 with or without the (compensated) filter.
    assert tuning.margins.stable and tuning.margins.ms == pytest.approx(1.96, abs=0.02)


def test_bad_arguments_are_config_errors():
    result = known('K*exp(-tau*s)/(T*s + 1)', {'K': 1.0, 'T': 2.0, 'tau': 0.1})
    with pytest.raises(ConfigError, match='controller'):
        tune(result, 'PD')
    with pytest.raises(ConfigError, match="belongs to method 'ms'"):
        tune(result, method='simc', target={'ms': 1.5})
    with pytest.raises(ConfigError, match='above 1'):
        tune(result, target={'ms': 0.9})
    with pytest.raises(ConfigError, match='unknown keys'):
        tune_from_settings(result, {'controler': 'PI'})


def test_json_and_ros2_control_params():
    result = known('K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))',
                   {'K': 2.0, 'T1': 1.5, 'T2': 0.4, 'tau': 0.7},
                   {'K': 0.02, 'T1': 0.04, 'T2': 0.03, 'tau': 0.02})
    tuning = tune_from_settings(result, {'controller': 'PID', 'tc': 1.0, 'draws': 50})
    summary = tuning.to_dict('wheel_left')
    assert set(summary['gains']) == {'kp', 'ki', 'kd', 'tf'}
    assert {'gain_db', 'phase_deg', 'ms'} <= set(summary['margins'])
    assert summary['target'] == {'tc': 1.0} and 'SIMC PID' in summary['method']
    params = yaml.safe_load(summary['ros2_control'])['pid_controller']['ros__parameters']
    assert params['dof_names'] == ['wheel_left']
    assert params['gains']['wheel_left'] == {'p': pytest.approx(tuning.gains.kp),
                                             'i': pytest.approx(tuning.gains.ki),
                                             'd': pytest.approx(tuning.gains.kd)}
    assert isinstance(tuning.gains, Gains)


def test_real_dryer_pi_at_its_sample_time():
    from pathlib import Path

    from ctid_ros.files.csv_file import load_csv

    data = load_csv(Path(__file__).resolve().parents[1] / 'data' / 'dryer_daisy.csv')
    result = estimate(Model('K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))'), data.detrend('mean'))
    tuning = tune(result, 'PI', sample_time=data.ts)
    assert 'half the 0.08 s sample time' in tuning.method and tuning.hold == pytest.approx(0.04)
    assert tuning.unstable_draws == 0 and 1.5 < tuning.margins.ms < 1.8
    for name in ('gain_db', 'phase_deg', 'ms', 'bandwidth'):
        low, high = tuning.band[name]
        assert low <= getattr(tuning.margins, name) <= high, name
    # The hold's delay is in the verification: without it the same gains look safer.
    continuous = loop_margins(Plant.from_model(result.model, result.params), tuning.gains)
    assert continuous.ms < tuning.margins.ms and continuous.phase_deg > tuning.margins.phase_deg
