"""Model equations: several inputs sharing D, constant inputs, integrators, and their errors."""

from ctid_ros import Model, ModelError
import numpy as np
import pytest

STAGE = 'M*s**2*y + Fv*s*y = 35*u - Fc*w - off'


def test_equation_with_two_inputs_and_a_constant():
    model = Model(STAGE, inputs=('u', 'w'))
    assert model.parameters == ('M', 'Fv', 'Fc', 'off')
    assert model.inputs == ('u', 'w') and model.constant_input
    assert model.integrators == 1 and model.is_affine
    coefficients = model.coefficients({'M': 2.0, 'Fv': 3.0, 'Fc': 4.0, 'off': 5.0})
    np.testing.assert_array_equal(coefficients.den, [2.0, 3.0, 0.0])
    np.testing.assert_array_equal(coefficients.num, [[35.0], [-4.0], [-5.0]])
    np.testing.assert_array_equal(coefficients.num_jacobian[2], [[0.0], [-1.0], [0.0]])
    num, den, delay = model.transfer_function([2.0, 3.0, 4.0, 5.0], 'w')
    np.testing.assert_array_equal(num, [-4.0])
    assert delay == 0.0


def test_equation_equals_the_transfer_function_form():
    equation = Model('T*s*y + y = K*u', inputs='u')
    function = Model('K/(T*s + 1)')
    theta = {'T': 0.5, 'K': 2.0}
    u = np.sin(np.arange(200) * 0.1)
    np.testing.assert_allclose(equation.simulate(theta, u, 0.05),
                               function.simulate(theta, u, 0.05), rtol=1e-12, atol=1e-14)


def test_rational_terms_and_output_on_both_sides():
    model = Model('a*s*y = b*u/(s + 1) - y', inputs=['u'])
    coefficients = model.coefficients({'a': 2.0, 'b': 3.0})
    np.testing.assert_allclose(coefficients.den, [2.0, 3.0, 1.0])
    np.testing.assert_allclose(coefficients.num, [[3.0]])


def test_simulation_sums_the_inputs():
    model = Model('s*y + 2*y = u + 3*w - c', inputs=('u', 'w'))
    u = np.random.default_rng(1).standard_normal((300, 2))
    theta = {'c': 0.5}
    both = model.simulate(theta, u, 0.01)
    first = Model('K/(s + 2)').simulate({'K': 1.0}, u[:, 0], 0.01)
    second = Model('K/(s + 2)').simulate({'K': 3.0}, u[:, 1], 0.01)
    constant = Model('K/(s + 2)').simulate({'K': -0.5}, np.ones(300), 0.01)
    np.testing.assert_allclose(both, first + second + constant, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('text, inputs, fragment', [
    ('a*y*u = u', ('u',), 'not linear'),
    ('a*y**2 = u', ('u',), 'not linear'),
    ('a*y = u/y', ('u',), 'divides by a signal'),
    ('a*s*y + y = b*u', ('u', 'w'), 'do not appear'),
    ('a*s*y + y = b', ('u',), 'do not appear'),
    ('a*s*y + y = b*exp(-t*s)*u', ('u',), 'dead time'),
    ('a*s*y + y = b*u + c*s', ('u',), 'constant term'),
    ('a*s*y + y = b*s**2*u', ('u',), 'improper'),
    ('y = 2*u', ('u',), 'no parameters'),
    ('a*s*y + y = b*u = c', ('u',), 'only allowed once'),
    ('a*s*y + y = ', ('u',), "nothing after '='"),
    ('K/(T*s + 1)', ('u', 'w'), 'one input'),
    ('a*s*y + y = b*u', ('s',), 'cannot name a signal'),
    ('a*s*y + y = b*u', ('u', 'u'), 'distinct'),
    ('a*s*y + y = b*u', ('lambda',), 'cannot name a signal'),
    ('a*s*y + y = b*u', (), 'at least one input'),
    ('(' + '+'.join(f'a{i}' for i in range(70)) + ')*s*y + y = u', ('u',),
     "more than 64 names \\(parameters and signals\\): 'a64'"),
    ('(a + b + c + d + e + s)**4*y = u', ('u',), 'too large to differentiate'),
])
def test_bad_equations_are_rejected(text, inputs, fragment):
    with pytest.raises(ModelError, match=fragment):
        Model(text, inputs=inputs)


def test_equation_rejects_a_controller():
    with pytest.raises(ModelError, match='transfer-function form'):
        Model('a*s*y + y = b*u', controller='2 + 1/s')


def test_integrators_are_counted_for_transfer_functions_too():
    assert Model('K/(s*(T*s + 1))').integrators == 1
    assert Model('1/(J*s**2)').integrators == 2
    assert Model('K/(T*s + 1)').integrators == 0
    # With a controller the closed loop has no integrator left.
    assert Model('1/(J*s**2 + b*s)', controller='40 + 20/s').integrators == 0
