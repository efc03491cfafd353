"""Loop analysis against closed-form results: margins, Nyquist count, step response."""

import math

from ctid_ros.design.margins import (closed_loop_step, Gains, integral_absolute_error,
                                     loop_margins, Plant)
from ctid_ros.errors import ModelError
import numpy as np
import pytest


def test_simc_pi_on_a_first_order_plus_dead_time_has_its_textbook_margins():
    # tau_I = tau_1 cancels the lag: L = exp(-theta s) / (2 theta s) with tc = theta.
    theta = 0.8
    plant = Plant.of([2.0], [5.0, 1.0], theta)
    kc = 5.0 / (2.0 * 2.0 * theta)
    margins = loop_margins(plant, Gains(kc, kc / 5.0))
    assert margins.stable and margins.unstable_poles == 0
    assert margins.crossover == pytest.approx(1.0 / (2.0 * theta), rel=1e-3)
    assert margins.phase_deg == pytest.approx(90.0 - math.degrees(0.5), abs=0.05)
    # Phase -180 at omega theta = pi/2, where |L| = 1/pi.
    assert margins.gain_db == pytest.approx(20.0 * math.log10(math.pi), abs=0.02)
    omega = np.logspace(-3, 3, 200001)
    loop = np.exp(-1j * omega * theta) / (2.0 * theta * 1j * omega)
    assert margins.ms == pytest.approx(np.max(np.abs(1.0 / (1.0 + loop))), rel=1e-4)


@pytest.mark.parametrize('gain, stable', [(1.5, True), (1.6, False)])
def test_nyquist_count_finds_the_integrator_with_dead_time_limit(gain, stable):
    # k exp(-theta s)/s is stable for k theta < pi/2 (= 1.571).
    margins = loop_margins(Plant.of([1.0], [1.0, 0.0], 1.0), Gains(gain, 0.0))
    assert margins.stable is stable
    assert margins.unstable_poles == (0 if stable else 2)


def test_nyquist_count_with_an_unstable_plant():
    plant = Plant.of([1.0], [1.0, -1.0])
    # (s - 1) s + 3 s + 1 = (s + 1)^2: stable; with kp = 0.5: s^2 - 0.5 s + 1, two in the RHP.
    assert loop_margins(plant, Gains(3.0, 1.0)).stable
    assert loop_margins(plant, Gains(0.5, 1.0)).unstable_poles == 2


def test_a_pi_cannot_stabilise_a_double_integrator():
    # s^3 + kp s + ki lacks its s^2 term: never stable.
    assert not loop_margins(Plant.of([1.0], [1.0, 0.0, 0.0]), Gains(1.0, 0.1)).stable
    # A PID can: s^3 (tf s + 1) + ... with SIMC's settings is stable.
    assert loop_margins(Plant.of([1.0], [1.0, 0.0, 0.0]),
                        Gains(0.1875, 0.0234375, 0.375, 0.1)).stable


def test_step_response_matches_the_closed_form():
    # 1/(s + 1) under kp = ki = 1: L = 1/s, y = 1 - exp(-t).
    times, output, command = closed_loop_step(Plant.of([1.0], [1.0, 1.0]), Gains(1.0, 1.0), 8.0)
    assert np.max(np.abs(output - (1.0 - np.exp(-times)))) < 2e-3
    assert command[-1] == pytest.approx(1.0, abs=1e-3)
    assert integral_absolute_error(times, output) == pytest.approx(1.0 - math.exp(-8.0),
                                                                   abs=2e-3)


def test_step_response_holds_the_dead_time():
    times, output, _ = closed_loop_step(Plant.of([2.0], [5.0, 1.0], 1.3), Gains(1.0, 0.2), 20.0)
    assert np.all(output[times < 1.3 - 1e-9] == 0.0)
    assert output[times > 1.4][0] > 0.0


def test_improper_and_empty_plants_are_refused():
    with pytest.raises(ModelError, match='improper'):
        Plant.of([1.0, 0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ModelError, match='zero'):
        Plant.of([0.0], [1.0, 1.0])


def test_margins_serialise_infinite_values_as_null():
    margins = loop_margins(Plant.of([1.0], [1.0, 1.0]), Gains(1.0, 1.0))
    summary = margins.to_dict()
    assert summary['gain_db'] is None and summary['phase_deg'] == pytest.approx(90.0, abs=0.01)
