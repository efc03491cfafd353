"""What the output is blind to, as a status code apart from its message (docs section 14)."""

from ctid_ros import Data, Model
from ctid_ros.core.excitation import prbs
from ctid_ros.estimation.identifiability import (blind_combination, Blindness,
                                                 structurally_blind)
from ctid_ros.estimation.problem import bound_vectors, Problem
import numpy as np


def problem_at(model, data, values):
    """Return the problem of ``model`` on ``data`` and its state at ``values``."""
    problem = Problem(model, data, *bound_vectors(model, None), 'zoh')
    theta = model.vector(values)
    return problem, problem.state(theta, problem.admissible(theta))


def test_a_combination_only_ratios_reveal_is_a_weak_combination_the_model_cannot_see():
    model = Model('g/(J*s**2 + b*s + k)')
    u = prbs(8, 5)
    truth = {'g': 2.0, 'J': 1.0, 'b': 1.0, 'k': 4.0}
    problem, state = problem_at(model, Data(u, model.simulate(truth, u, 0.05), 0.05), truth)
    blind = blind_combination(problem, state)
    assert blind.status is Blindness.WEAK_COMBINATION and not blind.status.always_fatal
    assert blind.message.startswith('the parameters are not identifiable from these data')
    assert structurally_blind(model, state.theta, np.random.default_rng(0))


def test_a_parameter_the_input_does_not_reach_is_unexcited():
    # The second input is zero throughout: its gain has no effect on the output.
    model = Model('T*s*y + y = K1*u1 + K2*u2', inputs=('u1', 'u2'))
    u = np.column_stack([prbs(7, 4), np.zeros(prbs(7, 4).size)])
    truth = {'K1': 1.5, 'K2': 0.5, 'T': 0.4}
    problem, state = problem_at(model, Data(u, model.simulate(truth, u, 0.05), 0.05), truth)
    blind = blind_combination(problem, state)
    assert blind.status is Blindness.UNEXCITED and blind.status.always_fatal
    assert blind.message == ('the output does not depend on K2 on these data: the input does '
                             'not excite it')


def test_a_well_determined_model_is_blind_to_nothing():
    model = Model('K/(T*s + 1)')
    u = prbs(7, 4)
    truth = {'K': 1.5, 'T': 0.4}
    y = model.simulate(truth, u, 0.05) + 0.01 * np.random.default_rng(0).standard_normal(u.size)
    problem, state = problem_at(model, Data(u, y, 0.05), truth)
    assert blind_combination(problem, state) is None
    assert not structurally_blind(model, state.theta, np.random.default_rng(0))
