"""PlantSimulator: the exact sample-by-sample plant of ctid_plant and the demo, without ROS."""

import math

from ctid_ros import Model
from ctid_ros.core.excitation import prbs
from ctid_ros.core.plant import excitation, PlantSimulator
from ctid_ros.errors import ConfigError
import numpy as np
import pytest

TS = 0.01
WHEEL = 'exp(-tau*s)/(J*s + b)'
TRUTH = {'J': 0.05, 'b': 0.2, 'tau': 0.0373}


@pytest.mark.parametrize('expression, params, controller', [
    ('K*exp(-tau*s)/(T*s + 1)', {'K': 2.0, 'T': 0.5, 'tau': 0.137}, ''),   # 13.7 samples
    ('(b1*s + b0)/(s**2 + a1*s + a0)', {'b1': 1.0, 'b0': 2.0, 'a1': 0.8, 'a0': 4.0}, ''),
    ('1/(m*s**2 + d*s + k)', {'m': 1.0, 'd': 2.0, 'k': 3.0}, '20 + 10/s'),
])
def test_stepping_matches_model_simulate(expression, params, controller):
    # The batch simulation is the reference: exact ZOH, fractional dead time, closed loop.
    reference = prbs(8, 5)[:600]
    simulator = PlantSimulator(expression, params, TS, controller=controller)
    stepped = np.array([simulator.step(value) for value in reference])
    expected = Model(expression, controller or None).simulate(params, reference, TS)
    np.testing.assert_allclose(stepped[:, 1], expected, rtol=0, atol=1e-12)
    if not controller:
        np.testing.assert_array_equal(stepped[:, 0], reference)   # open loop: u is the input
    assert simulator.closed_loop == bool(controller)
    assert simulator.parameters == Model(expression).parameters


def test_digital_pi_loop_matches_a_hand_written_recursion():
    # tau = 3.73 samples: over [k, k+1) the plant sees u[k-4] for 0.73 and u[k-3] for 0.27
    # of the sample, so y[k+1] = a y[k] + (early u[k-d-1] + late u[k-d]) / b.
    kp, ki = 1.0, 4.0
    simulator = PlantSimulator(WHEEL, TRUTH, TS, pi_gains=(kp, ki))
    reference = 2.0 + np.sign(np.sin(0.05 * np.arange(300)))
    simulated = np.array([simulator.step(r) for r in reference])
    whole = math.floor(TRUTH['tau'] / TS)
    fraction = TRUTH['tau'] / TS - whole
    pole = TRUTH['b'] / TRUTH['J']
    late = 1.0 - math.exp(-pole * (1.0 - fraction) * TS)
    early = math.exp(-pole * (1.0 - fraction) * TS) * (1.0 - math.exp(-pole * fraction * TS))
    y, integral, commands, expected = 0.0, 0.0, [], []
    for k, r in enumerate(reference):
        integral += ki * TS * (r - y)
        commands.append(kp * (r - y) + integral)
        expected.append((commands[-1], y))
        held = [commands[k - lag] if k >= lag else 0.0 for lag in (whole, whole + 1)]
        y = math.exp(-pole * TS) * y + (late * held[0] + early * held[1]) / TRUTH['b']
    np.testing.assert_allclose(simulated, expected, rtol=0, atol=1e-12)
    assert simulated[-1, 1] == pytest.approx(reference[-1], abs=0.05)  # the PI tracks
    # The measured command drives the plant: the open-loop model reproduces y from u.
    np.testing.assert_allclose(Model(WHEEL).simulate(TRUTH, simulated[:, 0], TS),
                               simulated[:, 1], rtol=0, atol=1e-12)


def test_digital_pi_needs_a_strictly_proper_plant_and_no_second_controller():
    with pytest.raises(ConfigError, match='strictly proper'):
        PlantSimulator('(T*s + 2)/(T*s + 1)', {'T': 1.0}, TS, pi_gains=(1.0, 1.0))
    with pytest.raises(ConfigError, match='exclude a continuous'):
        PlantSimulator('1/(T*s + 1)', {'T': 1.0}, TS, controller='2 + 1/s',
                       pi_gains=(1.0, 1.0))
    with pytest.raises(ConfigError, match='two gains'):
        PlantSimulator('1/(T*s + 1)', {'T': 1.0}, TS, pi_gains=(1.0,))


def test_noise_is_seeded_and_retuning_to_the_same_values_changes_nothing():
    levels = excitation(6, 4, amplitude=0.5, offset=1.0)
    reference = [next(levels) for _ in range(400)]
    assert set(reference) == {0.5, 1.5}
    runs = []
    for seed in (3, 3, 4):
        simulator = PlantSimulator(WHEEL, TRUTH, TS, pi_gains=(1.0, 4.0), noise_std=0.05,
                                   seed=seed)
        rows = []
        for k, r in enumerate(reference):
            if k == 200:
                simulator.retune(TRUTH)
            rows.append(simulator.step(r))
        runs.append(np.array(rows))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])
    noiseless = PlantSimulator(WHEEL, TRUTH, TS, pi_gains=(1.0, 4.0))
    clean = np.array([noiseless.step(r) for r in reference])
    # Without feedback of the noise the outputs would differ by the noise alone; through the
    # loop the difference stays of its order.
    assert 0.02 < np.std(runs[0][:, 1] - clean[:, 1]) < 0.2
