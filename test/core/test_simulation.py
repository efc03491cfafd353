"""Exact sampled simulation against independent references (solve_ivp, lsim)."""

import warnings

from ctid_ros import DataError, Model, ModelError
from ctid_ros.core import simulation
from ctid_ros.core.simulation import all_finite, ContinuousFilter, recursions, response, responses
import numpy as np
import pytest
from scipy import signal
from scipy.integrate import solve_ivp

ZOH_TOLERANCE = 1e-9

RAO_GARNIER = ([-6400.0, 1600.0], np.polymul([1.0, 1.0, 4.0], [1.0, 4.0, 400.0]))
# Poles from 0.1 to 100 rad/s, sampled far faster than the fastest time constant.
STIFF = ([1.0, 2.0, 0.5], np.poly([-0.1, -0.5, -2.0, -10.0, -30.0, -100.0]))

# name: (num, den, ts); orders 1 to 6, biproper, lightly damped, well-separated, unstable.
SYSTEMS = {
    'first order': ([2.0], [1.5, 1.0], 0.1),
    'msd (Test 2)': ([1.0], [0.5, 1.0, 50.0], 0.01),
    'lightly damped': ([1.0], [1.0, 0.004, 4.0], 0.1),
    'third order, integrator': ([3.0, 1.0], [1.0, 3.0, 2.0, 0.0], 0.05),
    'Rao-Garnier': (*RAO_GARNIER, 0.01),
    'fifth order, separated': ([0.5, 1.0, 4.0],
                               np.poly([-0.2, -1.0 + 5.0j, -1.0 - 5.0j, -8.0, -40.0]), 0.02),
    'sixth order, stiff': (*STIFF, 1e-3),
    'biproper first order (all-pass)': ([-1.0, 1.0], [1.0, 1.0], 0.1),
    'biproper second order': ([2.0, 1.0, 3.0], [1.0, 0.4, 5.0], 0.05),
    'biproper fourth order': (np.poly([-1.0, -3.0, 2.0 + 1.0j, 2.0 - 1.0j]),
                              np.polymul([1.0, 1.0, 4.0], [1.0, 4.0, 400.0]), 0.01),
    'unstable (Test 3 plant)': ([1.0], [1.0, 0.5, -2.0], 0.01),
    # Repeated poles (the sensitivity filters 1/D^2) have no eigenvector basis: Schur form.
    'repeated complex pair': ([1.0, 0.0], np.polymul([0.5, 1.0, 50.0], [0.5, 1.0, 50.0]), 0.01),
    'triple real pole': ([1.0], [1.0, 3.0, 3.0, 1.0], 0.1),
}


def relative_error(value, reference):
    return np.max(np.abs(value - reference)) / np.max(np.abs(reference))


def test_input(rng, count, hold=5):
    """Random input: held +-1 levels plus Gaussian noise."""
    levels = np.repeat(rng.choice([-1.0, 1.0], count // hold + 1), hold)[:count]
    return levels + 0.5 * rng.standard_normal(count)


test_input.__test__ = False


def lsim_reference(num, den, u, ts, interp):
    _, y, _ = signal.lsim((num, den), u, ts * np.arange(u.size), interp=interp)
    return y


def ivp_reference(num, den, u, ts, delay=0.0):
    """
    Integrate the ODE of an independent realisation (tf2ss) with solve_ivp.

    The input is the delayed piecewise-constant signal u(t - delay), zero before t = delay;
    every interval on which it is constant is integrated separately.
    """
    a, b, c, d = signal.tf2ss(num, den)
    b, c, d = b[:, 0], c[0], float(np.atleast_2d(d)[0, 0])
    end = ts * (u.size - 1)
    grid = {round(k * ts, 12) for k in range(u.size)}
    grid |= {round(j * ts + delay, 12) for j in range(u.size) if j * ts + delay < end}
    grid = sorted(grid)

    def held(t):
        j = int(np.floor((t - delay) / ts + 1e-9))
        return u[j] if 0 <= j < u.size else 0.0

    x = np.zeros(a.shape[0])
    y = np.zeros(u.size)
    y[0] = d * held(0.0)
    for start, stop in zip(grid[:-1], grid[1:]):
        value = held(start)
        x = solve_ivp(lambda t, x: a @ x + b * value, (start, stop), x, method='DOP853',
                      rtol=1e-12, atol=1e-15).y[:, -1]
        k = int(round(stop / ts))
        if abs(stop - k * ts) < 1e-9 * ts:
            y[k] = c @ x + d * held(stop)
    return y


def fine_reference(num, den, u, ts, delay, factor, interp):
    """
    Exact response by lsim on a grid ``factor`` times finer, shifted by the delay.

    The delay must be a multiple of the fine step: the fine grid then contains every switching
    (ZOH) or break (FOH) instant of the delayed signal, so lsim on it is exact as well.
    """
    step = ts / factor
    shift = int(round(delay / step))
    assert abs(shift * step - delay) < 1e-9 * step
    count = (u.size - 1) * factor + 1
    fine_time = step * np.arange(count)
    if interp:
        fine_u = np.interp(fine_time, ts * np.arange(u.size), u)
    else:
        fine_u = np.repeat(u, factor)[:count]
    _, fine_y, _ = signal.lsim((num, den), fine_u, fine_time, interp=interp)
    index = factor * np.arange(u.size) - shift
    return np.where(index >= 0, fine_y[np.maximum(index, 0)], 0.0)


@pytest.mark.parametrize('name', list(SYSTEMS))
def test_zoh_matches_lsim(name):
    num, den, ts = SYSTEMS[name]
    u = test_input(np.random.default_rng(1), 2000)
    reference = lsim_reference(num, den, u, ts, interp=False)
    assert relative_error(response(num, den, u, ts), reference) < ZOH_TOLERANCE


@pytest.mark.parametrize('name', list(SYSTEMS))
def test_zoh_matches_solve_ivp(name):
    num, den, ts = SYSTEMS[name]
    u = test_input(np.random.default_rng(2), 150)
    reference = ivp_reference(num, den, u, ts)
    assert relative_error(response(num, den, u, ts), reference) < ZOH_TOLERANCE


@pytest.mark.parametrize('name', list(SYSTEMS))
def test_foh_matches_lsim_interp(name):
    num, den, ts = SYSTEMS[name]
    u = test_input(np.random.default_rng(3), 2000)
    reference = lsim_reference(num, den, u, ts, interp=True)
    value = response(num, den, u, ts, intersample='foh')
    assert relative_error(value, reference) < ZOH_TOLERANCE


def test_stiff_sixth_order_over_a_long_record():
    """Ts = 1 ms against poles from 0.1 to 100 rad/s, over 30 s (the slow mode settles)."""
    num, den = STIFF
    ts = 1e-3
    u = np.repeat(np.random.default_rng(4).choice([-1.0, 1.0], 60), 500)
    for interp, intersample in ((False, 'zoh'), (True, 'foh')):
        reference = lsim_reference(num, den, u, ts, interp=interp)
        value = response(num, den, u, ts, intersample=intersample)
        assert relative_error(value, reference) < ZOH_TOLERANCE


@pytest.mark.parametrize('num,den,ts,delay,factor', [
    ([2.0], [1.5, 1.0], 0.1, 0.237, 100),                  # tau = 2.37 samples
    ([2.0], [5.0, 1.0], 0.1, 1.234, 100),                  # Test 4: tau = 12.34 samples
    ([1.0, 0.4, 3.0], [1.0, 0.4, 4.0], 0.1, 0.037, 100),   # biproper, tau < one sample
    (*RAO_GARNIER, 0.01, 0.0037, 100),                     # tau = 0.37 samples
    ([1.0], [1.0, 0.2, 1.0], 0.1, 0.3, 1),                 # a whole number of samples
])
def test_fractional_delay_matches_fine_lsim(num, den, ts, delay, factor):
    u = test_input(np.random.default_rng(5), 120, hold=3)
    for interp, intersample in ((False, 'zoh'), (True, 'foh')):
        reference = fine_reference(num, den, u, ts, delay, factor, interp)
        value = response(num, den, u, ts, delay=delay, intersample=intersample)
        assert relative_error(value, reference) < ZOH_TOLERANCE, intersample


@pytest.mark.parametrize('num,den,ts,delay', [
    ([2.0], [1.5, 1.0], 0.1, 0.237),
    ([2.0], [5.0, 1.0], 0.1, 1.234),
    ([1.0, 0.4, 3.0], [1.0, 0.4, 4.0], 0.1, 0.037),
    (*RAO_GARNIER, 0.01, 0.0037),
])
def test_fractional_delay_matches_solve_ivp(num, den, ts, delay):
    u = test_input(np.random.default_rng(6), 100, hold=3)
    reference = ivp_reference(num, den, u, ts, delay)
    assert relative_error(response(num, den, u, ts, delay=delay), reference) < ZOH_TOLERANCE


@pytest.mark.parametrize('intersample', ['zoh', 'foh'])
@pytest.mark.parametrize('num,den', [([1.0], [1.0, 0.3, 2.0]), ([1.0, 2.0], [1.0, 1.0]),
                                     ([3.0], [2.0])])
def test_whole_sample_delay_shifts_the_response(num, den, intersample):
    u = test_input(np.random.default_rng(7), 300)
    ts = 0.05
    undelayed = response(num, den, u, ts, intersample=intersample)
    for samples in (1, 3, 17):
        delayed = response(num, den, u, ts, delay=samples * ts, intersample=intersample)
        np.testing.assert_array_equal(delayed[:samples], 0.0)
        np.testing.assert_allclose(delayed[samples:], undelayed[:-samples], rtol=0,
                                   atol=1e-12 * np.max(np.abs(undelayed)))
        if len(num) == len(den):
            continue        # the sampled output of a biproper system jumps with the delay
        # Strictly proper: continuous in the delay on both sides of a whole number of samples.
        for nearby in (samples * ts * (1 - 1e-9), samples * ts * (1 + 1e-9)):
            close = response(num, den, u, ts, delay=nearby, intersample=intersample)
            assert relative_error(close, delayed) < 1e-6


def test_delay_longer_than_the_record_gives_zeros():
    u = np.ones(50)
    for intersample in ('zoh', 'foh'):
        y = response([1.0], [1.0, 1.0], u, 0.1, delay=7.33, intersample=intersample)
        np.testing.assert_array_equal(y, np.zeros(50))


def test_static_gain_with_fractional_delay():
    u = np.arange(6.0)
    zoh = response([3.0], [2.0], u, 0.1, delay=0.15)
    foh = response([3.0], [2.0], u, 0.1, delay=0.15, intersample='foh')
    # y_k = 1.5 u(t_k - 0.15): held previous sample (ZOH) or the interpolated value (FOH).
    np.testing.assert_allclose(zoh, [0.0, 0.0, 0.0, 1.5, 3.0, 4.5], atol=1e-15)
    np.testing.assert_allclose(foh, [0.0, 0.0, 0.75, 2.25, 3.75, 5.25], atol=1e-15)


def test_foh_delay_below_one_sample_starts_with_a_jump():
    """The FOH signal is zero before t0: y(t) = 1 - exp(-(t - tau)) for a unit input."""
    ts, delay = 0.1, 0.04
    y = response([1.0], [1.0, 1.0], np.ones(5), ts, delay=delay, intersample='foh')
    t = ts * np.arange(5)
    np.testing.assert_allclose(y, np.where(t >= delay, 1.0 - np.exp(-(t - delay)), 0.0),
                               rtol=1e-13, atol=1e-15)


def test_model_simulate_first_order_plus_dead_time():
    model = Model('K*exp(-tau*s)/(T*s + 1)')
    params = {'K': 2.0, 'T': 1.5, 'tau': 0.237}
    ts = 0.1
    u = test_input(np.random.default_rng(8), 120, hold=4)
    y = model.simulate(params, u, ts)
    assert relative_error(y, ivp_reference([2.0], [1.5, 1.0], u, ts, 0.237)) < ZOH_TOLERANCE
    assert relative_error(y, fine_reference([2.0], [1.5, 1.0], u, ts, 0.237, 100, False)) \
        < ZOH_TOLERANCE
    foh = model.simulate([2.0, 0.237, 1.5], u, ts, intersample='foh')
    assert relative_error(foh, fine_reference([2.0], [1.5, 1.0], u, ts, 0.237, 100, True)) \
        < ZOH_TOLERANCE


def test_model_simulate_closed_loop_against_hand_built_loop():
    m, d, k = 0.5, 1.0, 50.0
    model = Model('1/(m*s**2 + d*s + k)', controller='4 + 2/s')
    plant_num, plant_den = np.array([1.0]), np.array([m, d, k])
    controller_num, controller_den = np.array([4.0, 2.0]), np.array([1.0, 0.0])
    open_num = np.polymul(plant_num, controller_num)
    loop_den = np.polyadd(np.polymul(plant_den, controller_den), open_num)
    ts = 0.01
    r = test_input(np.random.default_rng(9), 3000, hold=50)
    y = model.simulate({'m': m, 'd': d, 'k': k}, r, ts)
    assert relative_error(y, lsim_reference(open_num, loop_den, r, ts, False)) < ZOH_TOLERANCE


def test_model_simulate_unstable_plant_under_pid():
    model = Model('1/(m*s**2 + d*s + k)', controller='(5*s**2 + 20*s + 10)/(s*(0.02*s + 1))')
    num = [5.0, 20.0, 10.0]
    den = [0.02, 1.01, 5.46, 18.0, 10.0]
    ts = 0.01
    r = np.repeat(np.random.default_rng(10).choice([-1.0, 1.0], 40), 20)
    y = model.simulate([1.0, 0.5, -2.0], r, ts)
    assert relative_error(y, lsim_reference(num, den, r, ts, False)) < ZOH_TOLERANCE
    assert relative_error(y[:150], ivp_reference(num, den, r[:150], ts)) < ZOH_TOLERANCE


def test_shared_denominator_bank_matches_single_responses():
    num_list = [[1.0], [1.0, 0.0], [1.0, 0.0, 0.0], [2.0, -1.0, 0.5, 3.0]]
    den = np.poly([-0.5, -1.0 + 3.0j, -1.0 - 3.0j])
    u = test_input(np.random.default_rng(11), 500)
    for intersample in ('zoh', 'foh'):
        bank = responses(num_list, den, u, 0.05, delay=0.125, intersample=intersample)
        assert bank.shape == (4, 500)
        for row, num in zip(bank, num_list):
            single = response(num, den, u, 0.05, delay=0.125, intersample=intersample)
            np.testing.assert_allclose(row, single, rtol=0, atol=1e-14 * np.max(np.abs(single)))
            reference = fine_reference(num, den, u, 0.05, 0.125, 10, intersample == 'foh')
            assert relative_error(row, reference) < ZOH_TOLERANCE


def test_linearity_and_causality():
    num, den, ts = SYSTEMS['Rao-Garnier']
    rng = np.random.default_rng(12)
    u1, u2 = rng.standard_normal(800), rng.standard_normal(800)
    for intersample in ('zoh', 'foh'):
        y1 = response(num, den, u1, ts, delay=0.0123, intersample=intersample)
        y2 = response(num, den, u2, ts, delay=0.0123, intersample=intersample)
        y12 = response(num, den, 2.0 * u1 - 3.0 * u2, ts, delay=0.0123,
                       intersample=intersample)
        np.testing.assert_allclose(y12, 2.0 * y1 - 3.0 * y2, rtol=0,
                                   atol=1e-11 * np.max(np.abs(y12)))
        head = response(num, den, u1[:300], ts, delay=0.0123, intersample=intersample)
        np.testing.assert_allclose(head, y1[:300], rtol=0, atol=1e-12 * np.max(np.abs(y1)))


def test_long_record_through_fourth_order():
    num, den, ts = SYSTEMS['Rao-Garnier']
    u = test_input(np.random.default_rng(13), 100_000, hold=7)
    y = response(num, den, u, ts, delay=0.0042)
    assert y.shape == (100_000,)
    assert np.all(np.isfinite(y))
    assert np.std(y) > 0.1


def test_coefficient_scaling_and_leading_zeros_do_not_matter():
    u = test_input(np.random.default_rng(14), 400)
    base = response([1.0, 3.0], [1.0, 2.0, 5.0], u, 0.05)
    np.testing.assert_allclose(response([0.0, 1e-6, 3e-6], [0.0, 0.0, 1e-6, 2e-6, 5e-6], u, 0.05),
                               base, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(response([0.0], [1.0, 1.0], u, 0.05), np.zeros(400))


@pytest.mark.parametrize('kwargs,error', [
    ({'num': [1.0, 0.0, 0.0], 'den': [1.0, 1.0]}, ModelError),       # improper
    ({'den': [0.0, 0.0]}, ModelError),
    ({'den': [1.0, np.nan]}, ModelError),
    ({'num': []}, ModelError),
    ({'ts': 0.0}, DataError),
    ({'ts': -0.1}, DataError),
    ({'ts': np.nan}, DataError),
    ({'ts': np.inf}, DataError),
    ({'delay': -0.01}, ModelError),
    ({'delay': np.nan}, ModelError),
    ({'intersample': 'linear'}, ModelError),
    ({'values': np.ones((10, 2))}, DataError),
])
def test_invalid_arguments(kwargs, error):
    arguments = {'num': [1.0], 'den': [1.0, 1.0], 'values': np.ones(10), 'ts': 0.1}
    arguments.update(kwargs)
    extra = {key: arguments.pop(key) for key in ('delay', 'intersample') if key in arguments}
    with pytest.raises(error):
        response(arguments['num'], arguments['den'], arguments['values'], arguments['ts'],
                 **extra)


@pytest.mark.filterwarnings('ignore::RuntimeWarning')
@pytest.mark.parametrize('den', [
    [1.0, 1e40, 1e39],                     # roots -1e40 and -0.1: the exponential overflows
    [1.0, 1e200, 1e-200],                  # the scaled coefficients overflow
])
def test_roots_too_many_decades_apart_are_a_model_error(den):
    with pytest.raises(ModelError, match='decades apart'):
        response([1.0], den, np.ones(10), 0.05)


def test_tiny_records():
    assert response([1.0], [1.0, 1.0], np.zeros(0), 0.1).shape == (0,)
    np.testing.assert_array_equal(response([1.0], [1.0, 1.0], [5.0], 0.1), [0.0])
    np.testing.assert_array_equal(response([2.0, 1.0], [1.0, 1.0], [5.0], 0.1), [10.0])


@pytest.mark.parametrize('text,params', [
    ('K*exp(-tau*s)/(T*s + 1)', {'K': 2.0, 'T': 0.7, 'tau': 0.234}),
    ('K*exp(-tau*s)/(T*s + 1)', {'K': 2.0, 'T': 0.7, 'tau': 0.0}),
    ('(b1*s + b0)/(s**2 + a1*s + a0)', {'b1': 1.0, 'b0': 4.0, 'a1': 0.8, 'a0': 9.0}),
])
@pytest.mark.parametrize('skew', [0.03, 0.05, 0.099])
def test_output_skew_gives_the_response_at_the_output_instants(text, params, skew):
    # The reference: the same held input on a grid 1000 times finer, read at t_k + skew.
    model, ts, fine = Model(text), 0.1, 1000
    u = test_input(np.random.default_rng(3), 300)
    reference = model.simulate(params, np.repeat(u, fine), ts / fine)[
        int(round(skew * fine / ts))::fine]
    skewed = model.simulate(params, u, ts, output_skew=skew)
    assert skewed.shape == u.shape
    np.testing.assert_allclose(skewed, reference, rtol=0.0, atol=1e-10 * np.max(abs(reference)))
    # No skew is the unchanged path, bit for bit.
    np.testing.assert_array_equal(model.simulate(params, u, ts, output_skew=0.0),
                                  model.simulate(params, u, ts))
    with pytest.raises(ModelError, match='skew'):
        model.simulate(params, u, ts, output_skew=ts)


@pytest.mark.parametrize('den, delay', [
    ([1.0, 3.0, 2.0], 0.0), ([1.0, 3.0, 2.0], 0.37), ([1.0, 0.4, 9.0], 0.05),
    ([0.6, 1.9, 1.0], 0.7), ([1.0, 5.0, 408.0, 416.0, 1600.0], 0.0), ([2.0, 1.0], 1.234)])
@pytest.mark.parametrize('intersample', ['zoh', 'foh'])
def test_responses_through_the_squared_denominator_read_off_its_modes(den, delay,
                                                                      intersample):
    # N/D^2 of a signal from the modes of D (double-pole chains) equals the simulation through
    # 1/D^2 (complex Schur coordinates) to rounding, biproper numerators included.
    rng = np.random.default_rng(11)
    values = rng.standard_normal(1500)
    den = np.array(den)
    order = den.size - 1
    ts = 0.01 if order > 2 else 0.1
    numerators = rng.standard_normal((3, 2 * order + 1))
    numerators[1, :2] = 0.0
    state = ContinuousFilter(den).discretize(ts, delay, intersample).response(values)
    squared = state.squared_outputs(numerators)
    simulated = ContinuousFilter(np.convolve(den, den)).discretize(ts, delay, intersample).outputs(
        values, numerators)
    np.testing.assert_allclose(squared, simulated, rtol=0.0, atol=1e-11 * np.abs(simulated).max())


def test_close_poles_leave_the_squared_denominator_to_its_own_simulation():
    # Poles 1e-4 apart: partial fractions of 1/D^2 would amplify rounding by ~1e12.
    den = np.convolve([1.0, 1.0], [1.0, 1.0001])
    state = ContinuousFilter(den).discretize(0.1, 0.0, 'zoh').response(np.ones(100))
    assert state.squared_outputs(np.ones((1, 5))) is None


@pytest.mark.parametrize('rows, length', [(1, 50), (3, 5000), (2, 20000), (40, 1000)])
@pytest.mark.parametrize('kind', ['stable', 'complex', 'unstable'])
def test_recursions_equal_first_order_lfilter_per_row(rows, length, kind):
    # Blocked products (many real samples or long complex rows of stable poles), banded solves
    # (the rest, several rows per solve): each row as scipy.signal.lfilter runs it, to rounding.
    rng = np.random.default_rng(12)
    values = rng.standard_normal((rows, length))
    poles = rng.uniform(-0.999, 1.0, rows)
    poles[0] = 1.0                                  # an integrator
    if kind == 'complex':
        poles = poles * np.exp(1j * rng.uniform(0.0, 0.5, rows))
        values = values + 1j * rng.standard_normal((rows, length))
    elif kind == 'unstable':
        poles[-1] = 1.0005
    out = recursions(poles, values)
    expected = np.array([signal.lfilter([1.0], [1.0, -pole], row)
                         for pole, row in zip(poles, values)])
    np.testing.assert_allclose(out, expected, rtol=1e-11, atol=1e-11 * np.abs(expected).max())


@pytest.mark.parametrize('order, lam', [(2, 1.0), (3, 30.0), (4, 0.5), (6, 2.0)])
@pytest.mark.parametrize('delay, intersample', [(0.0, 'zoh'), (0.0137, 'zoh'), (0.0137, 'foh')])
def test_repeated_root_runs_as_a_jordan_chain_equal_to_the_schur_form(monkeypatch, order, lam,
                                                                      delay, intersample):
    # (p + lam)^n, the state-variable filters: one real chain of recursions instead of the
    # complex Schur coordinates of the root's rounding cluster; the same responses.
    den = np.poly(np.full(order, -lam))
    values = np.random.default_rng(13).standard_normal(2000)
    numerators = [np.eye(order + 1)[order - j] for j in range(order + 1)]
    discrete = ContinuousFilter(den).discretize(0.01, delay, intersample)
    assert discrete.chain is not None
    chained = discrete.outputs(values, numerators)
    monkeypatch.setattr(simulation, '_CHAIN_MAX_ORDER', 0)
    monkeypatch.setattr(simulation, '_DISCRETIZATIONS', {})     # not the chain just kept
    schur = ContinuousFilter(den).discretize(0.01, delay, intersample).outputs(values, numerators)
    np.testing.assert_allclose(chained, schur, rtol=0.0, atol=1e-11 * np.abs(schur).max())


@pytest.mark.parametrize('count', [50, 600, 2000, 10220])
@pytest.mark.parametrize('order', [2, 4])
@pytest.mark.parametrize('delay, intersample', [(0.0, 'foh'), (0.0137, 'zoh')])
def test_chains_run_together_give_each_filters_own_values(count, order, delay, intersample):
    # Several state-variable filters over one signal in one pass: the values of each filter
    # run alone, to the bit. The lengths put rows where several would run in blocks and one
    # would not (600), and carried block states of one row below the blocked size (10220).
    lams = np.geomspace(0.5, 300.0, 3)
    filters = [ContinuousFilter(np.poly(np.full(order, -lam))).discretize(0.001, delay,
                                                                          intersample)
               for lam in lams]
    values = np.random.default_rng(17).standard_normal(count)
    numerators = [np.eye(order + 1)[order - j] for j in range(order + 1)]
    together = simulation.filter_responses(filters, values)
    assert len(together) == len(filters)
    for discrete, joint in zip(filters, together):
        np.testing.assert_array_equal(joint.outputs(numerators),
                                      discrete.outputs(values, numerators))


@pytest.mark.parametrize('count', [1600, 2550, 10220])
@pytest.mark.parametrize('order', [2, 4])
@pytest.mark.parametrize('delay, intersample', [(0.0, 'foh'), (0.0, 'zoh'), (0.0137, 'zoh'),
                                                (0.0137, 'foh'), (0.02, 'foh')])
def test_chains_in_blocks_are_the_state_by_state_recursions(count, order, delay, intersample):
    # A chain's states in blocks at once (a window of shifted signal rows, or the rows side
    # by side where a masked sample breaks the shift) against its states one recursion after
    # the other, which the chains of short records keep: within 1e-13 of each state's
    # largest value (both round; the slow filter integrates a random walk over the record).
    lams = np.geomspace(10.0 / (count * 0.01), 0.3 * np.pi / 0.01, 3)
    chains = [ContinuousFilter(np.poly(np.full(order, -lam))).discretize(0.01, delay,
                                                                         intersample).chain
              for lam in lams]
    values = np.cumsum(np.random.default_rng(29).standard_normal(count))
    signals = simulation._sampled_rows(values, chains[0].samples, -(-count // 16) * 16)
    blocked = simulation._run_chains(chains, signals)
    assert all(chain.block_maps is not None for chain in chains)
    by_state = simulation._chain_states(chains, signals)
    largest = np.abs(by_state).max(axis=1, keepdims=True)
    assert np.all(np.abs(blocked - by_state) <= 1e-13 * largest)


def test_chains_run_together_where_only_some_run_in_blocks_give_their_own_values():
    # An unstable repeated root (its powers grow: no blocks) among stable ones: each chain
    # still gives the values of its own run, to the bit.
    chains = [ContinuousFilter(np.poly(np.full(2, root))).discretize(0.01).chain
              for root in (-3.0, 0.5, -40.0)]
    assert [chain.block_maps is None for chain in chains] == [False, True, False]
    values = np.random.default_rng(37).standard_normal(2000)
    signals = simulation._sampled_rows(values, chains[0].samples, 2000)
    together = simulation._run_chains(chains, signals)
    for index, chain in enumerate(chains):
        np.testing.assert_array_equal(together[2 * index:2 * index + 2],
                                      simulation._run_chains([chain], signals))


def test_chains_of_short_or_non_finite_signals_run_state_by_state():
    chains = [ContinuousFilter(np.poly(np.full(3, -lam))).discretize(0.01).chain
              for lam in (1.0, 20.0)]
    values = np.random.default_rng(31).standard_normal(2000)
    values[700] = np.nan
    for length in (1024, 2000):
        signals = simulation._sampled_rows(values[:length], chains[0].samples,
                                           -(-length // 16) * 16)
        np.testing.assert_array_equal(simulation._run_chains(chains, signals),
                                      simulation._chain_states(chains, signals))


@pytest.mark.parametrize('count', [50, 600, 2550, 10220])
@pytest.mark.parametrize('delay, intersample', [(0.0, 'foh'), (0.0137, 'zoh'), (0.0137, 'foh')])
def test_first_order_filters_run_together_give_each_filters_own_values(count, delay,
                                                                       intersample):
    # First-order filters 1/(p + lam) over one signal in one recursion: each filter's values
    # alone, to the bit, their outputs and the squared outputs read off their modes.
    filters = [ContinuousFilter([1.0, lam]).discretize(0.001, delay, intersample)
               for lam in np.geomspace(0.5, 300.0, 3)]
    values = np.random.default_rng(23).standard_normal(count)
    numerators = [np.ones(2), np.ones(1)]
    squared = np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 1.0]])
    together = simulation.filter_responses(filters, values)
    assert len(together) == len(filters)
    for discrete, joint in zip(filters, together):
        alone = discrete.response(values)
        np.testing.assert_array_equal(joint.outputs(numerators), alone.outputs(numerators))
        np.testing.assert_array_equal(joint.squared_outputs(squared),
                                      alone.squared_outputs(squared))


def test_filters_that_are_not_one_chain_kind_run_one_at_a_time():
    values = np.random.default_rng(19).standard_normal(300)
    filters = [ContinuousFilter(np.poly([-2.0, -2.0])).discretize(0.01),
               ContinuousFilter(np.poly([-2.0, -2.0, -2.0])).discretize(0.01),
               ContinuousFilter([1.0, 3.0]).discretize(0.01),
               ContinuousFilter(np.poly([-2.0, -2.0])).discretize(0.01, 0.005)]
    together = simulation.filter_responses(filters, values)
    for discrete, joint in zip(filters, together):
        np.testing.assert_array_equal(joint.outputs([np.ones(1)]),
                                      discrete.outputs(values, [np.ones(1)]))
    assert simulation.filter_responses([], values) == []


@pytest.mark.parametrize('coefficients', [[2.0, -1.0], [1.0, 3.0, 2.0], [1.0, -0.5, 0.3, 0.1],
                                          [1.0, 0.0, 2.0, 0.0], [0.0, 1.0, 2.0]])
def test_companion_roots_are_numpys_roots_bit_for_bit(coefficients):
    coefficients = np.array(coefficients)
    np.testing.assert_array_equal(simulation.companion_roots(coefficients),
                                  np.roots(coefficients))


def test_distinct_roots_are_not_taken_for_a_repeated_one():
    assert ContinuousFilter(np.poly([-1.0, -1.0 - 1e-6])).repeated_root is None
    assert ContinuousFilter(np.poly([-2.0, -2.0, -2.0])).repeated_root is not None


def test_recursions_keep_a_non_finite_value_to_the_samples_after_it():
    # As the substitution does: a block's product must not carry a NaN back in time.
    values = np.ones((2, 5000))
    values[1, 3000] = np.nan
    out = recursions(np.array([0.5, 0.9]), values)
    assert np.isfinite(out[0]).all() and np.isfinite(out[1, :3000]).all()
    assert np.isnan(out[1, 3000:]).all()


def test_discretisations_are_shared_by_equal_denominators_only():
    # A realisation built again (the starts' filters, each fit) finds its discretisation kept.
    den = np.polymul([2.0, 1.0], [0.5, 1.0])
    first = ContinuousFilter(den).discretize(0.01, 0.0137, 'zoh')
    assert ContinuousFilter(list(den)).discretize(0.01, 0.0137, 'zoh') is first
    others = [ContinuousFilter(den).discretize(0.01, 0.0137, 'foh'),
              ContinuousFilter(den).discretize(0.01, 0.02, 'zoh'),
              ContinuousFilter(den).discretize(0.02, 0.0137, 'zoh'),
              ContinuousFilter(den * (1.0 + 1e-15)).discretize(0.01, 0.0137, 'zoh')]
    assert all(other is not first for other in others)
    values = np.random.default_rng(3).standard_normal(500)
    np.testing.assert_array_equal(first.outputs(values, [[1.0]])[0],
                                  response([1.0], den, values, 0.01, delay=0.0137))


@pytest.mark.parametrize('den', [np.poly([-44.9, -0.68, -2.45 + 3.2j, -2.45 - 3.2j]).real,
                                 RAO_GARNIER[1]])
@pytest.mark.parametrize('delay, intersample', [(0.0, 'zoh'), (0.0137, 'zoh'), (0.0137, 'foh')])
def test_complex_modes_of_long_records_run_in_blocks_as_substitutions(
        monkeypatch, den, delay, intersample):
    # Records long enough for the complex modes' block products (a real mode and a pair, two
    # pairs; one sampled input row, real products; several, complex ones): outputs, squared
    # outputs and state trajectories equal those of the forward substitutions, to rounding;
    # the undelayed held response equals lsim's.
    rng = np.random.default_rng(14)
    values = test_input(rng, 6007, hold=9)
    order = den.size - 1
    numerators = rng.standard_normal((3, order))
    squared_numerators = rng.standard_normal((2, 2 * order))

    def simulated():
        state = ContinuousFilter(den).discretize(0.01, delay, intersample).response(values)
        simulation._DISCRETIZATIONS.clear()
        return (state.outputs(numerators), state.squared_outputs(squared_numerators),
                state.mapped(np.eye(order)))

    blocked = simulated()
    monkeypatch.setattr(simulation, '_BLOCKED_MIN_PAIR_LENGTH', 10 ** 9)
    monkeypatch.setattr(simulation, '_BLOCKED_MIN_LENGTH', 10 ** 9)
    monkeypatch.setattr(simulation, '_BLOCKED_MIN_COMPLEX_LENGTH', 10 ** 9)
    for value, reference in zip(blocked, simulated()):
        np.testing.assert_allclose(value, reference, rtol=0.0,
                                   atol=1e-11 * np.abs(reference).max())
    if delay == 0.0 and intersample == 'zoh':
        reference = lsim_reference(numerators[0], den, values, 0.01, interp=False)
        assert relative_error(blocked[0][0], reference) < ZOH_TOLERANCE


def test_recursions_write_into_out():
    rng = np.random.default_rng(15)
    values = rng.standard_normal((2, 4096))
    poles = np.array([0.99, -0.5])
    buffer = np.zeros((2, 4100))
    out = recursions(poles, values, out=buffer[:, 3:4099])
    assert out is not None and np.shares_memory(out, buffer)
    np.testing.assert_array_equal(buffer[:, 3:4099], recursions(poles, values))
    assert not buffer[:, :3].any() and not buffer[:, 4099:].any()


def test_blocked_recursions_of_remembered_poles_give_the_same_values():
    # The block matrices of a pole set are remembered and shared: a second run with the same
    # poles (a fresh array of them) gives the first run's values bit for bit, the values of a
    # run with the remembered matrices cleared, and nobody can write into the shared ones.
    rng = np.random.default_rng(16)
    values = rng.standard_normal((2, 2560))
    poles = np.array([0.993, -0.41])
    first = recursions(poles, values)
    again = recursions(poles.copy(), values)
    simulation._pole_blocks.cache_clear()
    fresh = recursions(poles, values)
    np.testing.assert_array_equal(again, first)
    np.testing.assert_array_equal(fresh, first)
    np.testing.assert_allclose(first, np.stack([signal.lfilter([1.0], [1.0, -pole], row)
                                                for pole, row in zip(poles, values)]),
                               rtol=0.0, atol=1e-12 * np.abs(first).max())
    powers, matrices = simulation._pole_blocks(poles.tobytes(), poles.dtype.char)
    assert not powers.flags.writeable and not matrices.flags.writeable


@pytest.mark.parametrize('values, finite', [([np.inf, -np.inf], False), ([1e308, 1e308], True),
                                            ([1.0, np.nan], False), ([1e308j, 1e308j], True)])
def test_all_finite_answers_without_a_warning(values, finite):
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        assert all_finite(np.array(values)) is finite
