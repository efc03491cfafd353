"""Grey-box Model: coefficients, Jacobians, affinity, delays, closed loop and rejected models."""

import time

from ctid_ros import DataError, Model, ModelError
import numpy as np
import pytest


MSD = '1/(m*s**2 + d*s + k)'


@pytest.mark.parametrize('text', [
    'K*s', 's**2/(s+1)', 'K*s**2/(T*s + 1)', '(s**3 + a)/(s**2 + b*s + 1)', 'K/s**-2',
    'K*(T*s + 1)', 's', 'K + s',
])
def test_improper_models_are_rejected(text):
    with pytest.raises(ModelError, match='improper'):
        Model(text)


@pytest.mark.parametrize('text,fragment', [
    ('1/(s+1) + exp(-tau*s)', 'factor'),
    ('K/(s+1) + K*exp(-tau*s)/(s+2)', 'factor'),
    ('exp(-tau*s**2)/(s+1)', 'not a dead time'),
    ('K*exp(-tau/s)/(s+1)', 'not a dead time'),
    ('K*exp(-tau*s + 1)/(s+1)', 'not a dead time'),
    ('1/(exp(-tau*s) + s)', 'factor'),
    ('K/(s+1)/exp(-tau*s)**-1 + 1/(s+2)', 'non-causal'),
    ('exp(2*s)/(s+1)', 'advance'),
    ('K*exp(0.5*s)/(T*s+1)', 'advance'),
    ('K*exp(-a*s)/(s+1) + exp(-b*s)/(s+2)', 'at most one'),
    ('K*exp(-a*s)/(s+1) - K*exp(-b*s)/(s+1)', 'at most one'),
    ('K*exp(exp(-tau*s))/(s+1)', 'at most one'),
])
def test_dead_times_that_are_not_a_factor_are_rejected(text, fragment):
    with pytest.raises(ModelError, match=fragment):
        Model(text)


@pytest.mark.parametrize('controller', [
    'kp*(1 + 1/(Ti*s))', 'kp', '4 + ki/s', 'kp*exp(-0.1*s)',
])
def test_controllers_with_parameters_are_rejected(controller):
    with pytest.raises(ModelError, match='numeric coefficients'):
        Model(MSD, controller=controller)


def test_delays_in_closed_loop_are_rejected():
    with pytest.raises(ModelError, match='dead time'):
        Model('K*exp(-tau*s)/(T*s + 1)', controller='4 + 2/s')
    with pytest.raises(ModelError, match='dead time'):
        Model('K*exp(-0.5*s)/(T*s + 1)', controller='1')
    with pytest.raises(ModelError, match='dead time'):
        Model(MSD, controller='2*exp(-0.1*s)')
    with pytest.raises(ModelError, match='zero'):
        Model(MSD, controller='0*s')


@pytest.mark.parametrize('name', ['lambda', 'import', 'class', 'def', 'None', 'True', 'if',
                                  'yield', 'await', 'not'])
def test_python_keywords_are_not_parameter_names(name):
    with pytest.raises(ModelError, match='reserved word') as info:
        Model(f'K/({name}*s + 1)')
    assert 'column 4' in str(info.value)


def test_models_without_parameters_are_rejected():
    with pytest.raises(ModelError, match='no parameters'):
        Model('1/(s+1)')
    with pytest.raises(ModelError, match='no parameters'):
        Model('2*pi/(s+pi)')


def test_mass_spring_damper_coefficients():
    model = Model(MSD)
    assert model.parameters == ('m', 'd', 'k')
    assert model.is_affine
    assert not model.has_delay
    assert (model.num_degree, model.den_degree) == (0, 2)
    coefficients = model.coefficients({'m': 0.5, 'd': 1.0, 'k': 50.0})
    np.testing.assert_array_equal(coefficients.num[0], [1.0])
    np.testing.assert_array_equal(coefficients.den, [0.5, 1.0, 50.0])
    assert coefficients.delay == 0.0
    np.testing.assert_array_equal(coefficients.num_jacobian[:, 0], np.zeros((3, 1)))
    np.testing.assert_array_equal(coefficients.den_jacobian, np.eye(3))
    np.testing.assert_array_equal(coefficients.delay_gradient, np.zeros(3))
    # The same coefficients with '^' as power and a vector of values.
    same = Model('1/(m*s^2 + d*s + k)').coefficients([0.5, 1.0, 50.0])
    np.testing.assert_array_equal(same.den, coefficients.den)


def test_parameter_order_is_order_of_first_appearance():
    assert Model('K*exp(-tau*s)/(T*s + 1)').parameters == ('K', 'tau', 'T')
    assert Model('(b1*s + b0)/(s**4 + a3*s**3 + a2*s**2 + a1*s + a0)').parameters == (
        'b1', 'b0', 'a3', 'a2', 'a1', 'a0')
    assert Model('z/(w*s + z*w + Kp)').parameters == ('z', 'w', 'Kp')
    assert Model('K/(s + 2*pi*f)').parameters == ('K', 'f')


def test_rao_garnier_black_box_coefficients():
    model = Model('(b1*s + b0)/(s**4 + a3*s**3 + a2*s**2 + a1*s + a0)')
    theta = {'b1': -6400.0, 'b0': 1600.0, 'a3': 5.0, 'a2': 408.0, 'a1': 416.0, 'a0': 1600.0}
    coefficients = model.coefficients(theta)
    np.testing.assert_array_equal(coefficients.num[0], [-6400.0, 1600.0])
    np.testing.assert_array_equal(coefficients.den, [1.0, 5.0, 408.0, 416.0, 1600.0])
    np.testing.assert_allclose(np.polymul([1, 1, 4], [1, 4, 400]), coefficients.den)
    assert model.is_affine


def test_non_affine_structures():
    model = Model('K/((T1*s + 1)*(T2*s + 1))')
    assert not model.is_affine
    coefficients = model.coefficients({'K': 2.0, 'T1': 3.0, 'T2': 5.0})
    np.testing.assert_allclose(coefficients.num[0], [2.0])
    np.testing.assert_allclose(coefficients.den, [15.0, 8.0, 1.0])
    model = Model('K*w**2/(s**2 + 2*z*w*s + w**2)')
    assert not model.is_affine
    assert model.parameters == ('K', 'w', 'z')
    coefficients = model.coefficients({'K': 1.5, 'w': 3.0, 'z': 0.2})
    np.testing.assert_allclose(coefficients.num[0], [13.5])
    np.testing.assert_allclose(coefficients.den, [1.0, 1.2, 9.0])
    # Section 8, test 5: dN/dK = w^2, dN/dw = 2 K w, dD/dw = 2 z s + 2 w, dD/dz = 2 w s.
    np.testing.assert_allclose(coefficients.num_jacobian[:, 0], [[9.0], [9.0], [0.0]])
    np.testing.assert_allclose(coefficients.den_jacobian,
                               [[0.0, 0.0, 0.0], [0.0, 0.4, 6.0], [0.0, 6.0, 0.0]])


def test_first_order_plus_dead_time():
    model = Model('K*exp(-tau*s)/(T*s + 1)')
    assert model.has_delay and model.delay_is_estimated and model.is_affine
    coefficients = model.coefficients({'K': 2.0, 'T': 5.0, 'tau': 1.234})
    np.testing.assert_array_equal(coefficients.num[0], [2.0])
    np.testing.assert_array_equal(coefficients.den, [5.0, 1.0])
    assert coefficients.delay == 1.234
    np.testing.assert_array_equal(coefficients.delay_gradient, [0.0, 1.0, 0.0])
    known = Model('K*exp(-0.5*s)/(T*s + 1)')
    assert known.has_delay and not known.delay_is_estimated
    assert known.coefficients([2.0, 5.0]).delay == 0.5
    with pytest.raises(ModelError, match='at most one'):
        Model('K*exp(-tau*s)*exp(-tau*s)/(T*s + 1)')
    summed = Model('K*exp(-(tau1 + tau2)*s)/(T*s + 1)')
    assert summed.coefficients([1.0, 0.3, 0.2, 1.0]).delay == pytest.approx(0.5, rel=1e-15)
    np.testing.assert_array_equal(summed.coefficients([1.0, 0.3, 0.2, 1.0]).delay_gradient,
                                  [0.0, 1.0, 1.0, 0.0])


def test_closed_loop_coefficients_match_hand_computation():
    model = Model(MSD, controller='4 + 2/s')
    assert model.parameters == ('m', 'd', 'k')
    m, d, k = 0.5, 1.0, 50.0
    coefficients = model.coefficients({'m': m, 'd': d, 'k': k})
    np_, dp = np.array([1.0]), np.array([m, d, k])                 # plant
    kn, kd = np.array([4.0, 2.0]), np.array([1.0, 0.0])            # 4 + 2/s = (4s + 2)/s
    num = np.polymul(np_, kn)
    den = np.polyadd(np.polymul(dp, kd), np.polymul(np_, kn))
    np.testing.assert_allclose(coefficients.num[0], num, rtol=1e-15)
    np.testing.assert_allclose(coefficients.den, den, rtol=1e-15)
    np.testing.assert_allclose(coefficients.den, [m, d, k + 4.0, 2.0], rtol=1e-15)
    assert model.is_affine


def test_closed_loop_pid_matches_hand_expansion():
    controller = '(5*s**2 + 20*s + 10)/(s*(0.02*s + 1))'
    model = Model(MSD, controller=controller)
    coefficients = model.coefficients({'m': 1.0, 'd': 0.5, 'k': -2.0})
    den = np.array([0.02, 1.01, 5.46, 18.0, 10.0])
    num = np.array([5.0, 20.0, 10.0])
    scale = coefficients.den[0] / den[0]          # N and D are defined up to a common factor
    np.testing.assert_allclose(coefficients.den, scale * den, rtol=1e-13)
    np.testing.assert_allclose(coefficients.num[0], scale * num, rtol=1e-13)
    poles = np.sort_complex(np.roots(coefficients.den))
    np.testing.assert_allclose(poles.real, [-44.86, -2.48, -2.48, -0.678], atol=0.006)
    # D_m = Tf s^4 + s^3, D_d = Tf s^3 + s^2, D_k = Tf s^2 + s (times the same factor).
    np.testing.assert_allclose(coefficients.den_jacobian / scale, [
        [0.02, 1.0, 0.0, 0.0, 0.0], [0.0, 0.02, 1.0, 0.0, 0.0], [0.0, 0.0, 0.02, 1.0, 0.0]],
        atol=1e-15)
    np.testing.assert_array_equal(coefficients.num_jacobian[:, 0], np.zeros((3, 3)))


JACOBIAN_CASES = [
    ('K*w**2/(s**2 + 2*z*w*s + w**2)', [1.5, 3.0, 0.2]),
    ('K/((T1*s + 1)*(T2*s + 1))', [2.0, 3.0, 0.7]),
    ('K*exp(-tau*s)*(a*s + 1)/(T**2*s**2 + T*s + 1)', [2.0, 0.3, 0.5, 1.7]),
    ('k*exp(-(a + b**2)*s)/(a*b*s + (a + 1)**0.5)', [1.2, 0.4, 0.8]),
    ('(K/T)/(s + 1/T)', [2.0, 0.25]),
]


@pytest.mark.parametrize('text,theta', JACOBIAN_CASES)
def test_jacobians_match_central_differences(text, theta):
    model = Model(text)
    theta = np.array(theta)
    coefficients = model.coefficients(theta)
    for index in range(theta.size):
        step = 1e-6 * max(1.0, abs(theta[index]))
        up, down = theta.copy(), theta.copy()
        up[index] += step
        down[index] -= step
        plus, minus = model.coefficients(up), model.coefficients(down)
        for field in ('num', 'den', 'delay'):
            difference = (np.asarray(getattr(plus, field))
                          - np.asarray(getattr(minus, field))) / (2 * step)
            exact = {'num': coefficients.num_jacobian, 'den': coefficients.den_jacobian,
                     'delay': coefficients.delay_gradient}[field][index]
            np.testing.assert_allclose(exact, difference, rtol=1e-7, atol=1e-7,
                                       err_msg=f'{text}: d{field}/d{model.parameters[index]}')


def test_closed_loop_jacobian_matches_central_differences():
    model = Model('K*w**2/(s**2 + 2*z*w*s + w**2)', controller='(3*s + 2)/(s*(0.1*s + 1))')
    theta = np.array([1.5, 3.0, 0.2])
    coefficients = model.coefficients(theta)
    for index in range(3):
        step = 1e-6 * theta[index]
        up, down = theta.copy(), theta.copy()
        up[index] += step
        down[index] -= step
        difference = (model.coefficients(up).den - model.coefficients(down).den) / (2 * step)
        np.testing.assert_allclose(coefficients.den_jacobian[index], difference, rtol=1e-7,
                                   atol=1e-7)


def test_parameter_values_are_validated():
    model = Model('K*exp(-tau*s)/(T*s + 1)')
    with pytest.raises(ModelError, match='missing'):
        model.coefficients({'K': 1.0, 'T': 1.0})
    with pytest.raises(ModelError, match='unknown'):
        model.coefficients({'K': 1.0, 'T': 1.0, 'tau': 0.1, 'L': 2.0})
    with pytest.raises(ModelError, match='expected 3'):
        model.coefficients([1.0, 2.0])
    with pytest.raises(ModelError, match='finite'):
        model.coefficients([1.0, np.nan, 2.0])
    with pytest.raises(ModelError, match='undefined'):
        Model('K/(s + (1/T)**0.5)').coefficients({'K': 1.0, 'T': 0.0})
    assert model.as_dict(model.vector({'tau': 0.1, 'T': 2.0, 'K': 3.0})) == {
        'K': 3.0, 'tau': 0.1, 'T': 2.0}


def test_frequency_response_matches_formula():
    model = Model('K*exp(-tau*s)/(T*s + 1)')
    omega = np.logspace(-2, 2, 50)
    response = model.frequency_response({'K': 2.0, 'T': 1.5, 'tau': 0.237}, omega)
    expected = 2.0 * np.exp(-0.237j * omega) / (1.5j * omega + 1.0)
    np.testing.assert_allclose(response, expected, rtol=1e-14)


def test_simulate_rejects_bad_arguments():
    model = Model('K/(T*s + 1)')
    with pytest.raises(ModelError, match='intersample'):
        model.simulate({'K': 1.0, 'T': 1.0}, np.ones(10), 0.1, intersample='linear')
    with pytest.raises(DataError):
        model.simulate({'K': 1.0, 'T': 1.0}, [1.0, np.nan], 0.1)
    with pytest.raises(DataError):
        model.simulate({'K': 1.0, 'T': 1.0}, np.ones(10), 0.0)
    with pytest.raises(ModelError, match='order drops'):
        model.simulate({'K': 1.0, 'T': 0.0}, np.ones(10), 0.1)


def test_simulate_rejects_a_negative_dead_time():
    model = Model('K*exp(-tau*s)/(T*s + 1)')
    with pytest.raises(ModelError, match='dead time'):
        model.simulate({'K': 1.0, 'T': 1.0, 'tau': -0.5}, np.ones(20), 0.1)


def test_model_rejects_parameters_that_cancel_and_non_string_controllers():
    with pytest.raises(ModelError, match='cancel out'):
        Model('K/K/(s + 1)')
    with pytest.raises(ModelError, match='controller must be a string'):
        Model('1/(T*s + 1)', controller=0)
    assert Model('1/(T*s + 1)', controller='  ').controller is None


def test_closed_loop_degree_is_limited_before_expansion():
    with pytest.raises(ModelError, match='degree'):
        Model('K/(a*s + 1)**16/(b*s + 1)**4', controller='(s + 1)**16/(s + 2)**16')


# Issue #16: each example with the answer it must get, well within a second.
PRODUCT_60 = 'K/(' + '*'.join(f'a{i}' for i in range(60)) + ')'
PRODUCT_100 = 'K/(' + '*'.join(f'a{i}' for i in range(100)) + ')'
EXP_OF_POWER = 'exp((a+b+c+d+e)**10)/(s+1)'


@pytest.mark.parametrize('text,controller,fragment', [
    (PRODUCT_60, None, 'product of up to 25 factors; the limit is 24'),
    (PRODUCT_100, None, 'product of up to 25 factors; the limit is 24'),
    ('K/((' + '*'.join(f'a{i}' for i in range(60)) + ')*s + 1)', None, 'the limit is 24'),
    (EXP_OF_POWER, None, 'expression too large: it would expand to more than 512 terms at '
                         'column 18'),
    ('*'.join(['exp((a+b+c+d+e)**10)'] * 3) + '/(s+1)', None, 'more than 512 terms at column 18'),
    ('exp((a+b+c+d+e)**3)/(s+1)', None,
     r'exp\(\(a\+b\+c\+d\+e\)\*\*3\) is not allowed: exp\(\.\.\.\) is only the dead time'),
    ('K*exp(-(a+b+c+d+e)**3*s)/(s+1)', None, 'at most 16 terms'),
    ('K*exp(tau*s)/(T*s + 1)', None, r'exp\(tau\*s\) is a time advance, which is non-causal'),
    ('K*exp(-tau*s)**-1/(s+1)', None, 'power -1 is a time advance, which is non-causal'),
    ('K*exp(-tau*s)**2/(s+1)', None, 'may not be raised to a power'),
    ('exp(-tau*s)', None, 'dead time without dynamics'),
    ('K*exp(-tau*s)', None, 'dead time without dynamics'),
    (MSD, 's**3', r"controller 's\*\*3' is improper: numerator degree 3 exceeds denominator "
                  'degree 0'),
    (MSD, 's', "controller 's' is improper"),
    (MSD, '20 + 10/s + 5*s', 'improper'),
])
def test_issue_16_examples_get_their_error_quickly(text, controller, fragment):
    start = time.perf_counter()
    with pytest.raises(ModelError, match=fragment):
        Model(text, controller=controller)
    assert time.perf_counter() - start < 1.0


@pytest.mark.parametrize('plant', ['K*exp(-tau*s)/(T*s + 1)', MSD])
def test_unsafe_controller_text_is_named_not_the_dead_time(plant):
    with pytest.raises(ModelError) as info:
        Model(plant, controller="__import__('os')")
    message = str(info.value)
    assert message.startswith('controller: unexpected character "\'" at column 12')
    assert 'dead time' not in message
    with pytest.raises(ModelError, match='controller: function sin'):
        Model(plant, controller='sin(s)')
    with pytest.raises(ModelError, match='controller: a controller must have numeric'):
        Model(plant, controller='kp + ki/s')


@pytest.mark.parametrize('text,fragment', [
    ('K/(exp(-tau*s)*(s + 1))', 'in a denominator is the time advance'),
    ('K/(s + 1)/exp(-tau*s)', 'in a denominator is the time advance'),
    ('K*exp(-(a - b)*s)/(s + 1)', 'cannot tell that the dead time a - b is positive'),
    ('K*exp(0.5*s)/(s + 1)', 'non-causal'),
    ('K*exp(-(1 - 2)*s)/(s + 1)', 'non-causal'),
    ('K*exp(-0*s)/(s + 1)', 'its argument has no s'),
    ('K*exp(a)/(s + 1)', 'its argument has no s'),
    ('K*exp(-tau*s)**1/(s + 1)', 'may not be raised to a power'),
    ('K*2**exp(-tau*s)/(s + 1)', 'exponents must be numbers'),
    ('K*exp(-tau*s)*exp(-L*s)/(s + 1)', 'at most one'),
])
def test_dead_time_grammar_is_precise(text, fragment):
    with pytest.raises(ModelError, match=fragment):
        Model(text)


@pytest.mark.parametrize('text,delay', [
    ('K*exp(-tau*s)/(T*s + 1)', 0.3), ('K*exp(-(tau + L)*s)/(T*s + 1)', 0.5),
    ('K*exp(-0.1*s)/(T*s + 1)', 0.1), ('-K*exp(-tau*s)/(T*s + 1)', 0.3),
    ('(K*exp(-tau*s))/(T*s + 1)', 0.3), ('K/(T*s + 1)*exp(-tau*s)', 0.3),
    ('K*exp(-tau**2*s)/(T*s + 1)', 0.09), ('K*exp(-s*tau/2)/(T*s + 1)', 0.15),
    ('K*exp(-pi*s)/(T*s + 1)', np.pi),
])
def test_dead_times_written_as_one_causal_factor_are_accepted(text, delay):
    model = Model(text)
    values = {'K': 2.0, 'tau': 0.3, 'L': 0.2, 'T': 1.5}
    structure = model.coefficients({name: values[name] for name in model.parameters})
    assert structure.delay == pytest.approx(delay, rel=1e-14)
    assert abs(structure.num[0][-1]) == 2.0


def test_a_known_dead_time_without_dynamics_is_a_delayed_gain():
    model = Model('K*exp(-0.15*s)')
    assert (model.num_degree, model.den_degree, model.delay_is_estimated) == (0, 0, False)
    y = model.simulate({'K': 1.5}, np.arange(6.0), 0.1)
    np.testing.assert_allclose(y, [0.0, 0.0, 0.0, 1.5, 3.0, 4.5], atol=1e-15)


def test_proper_controllers_are_accepted():
    for controller in ['20 + 10/s', '(5*s**2 + 20*s + 10)/(s*(0.02*s + 1))', '3',
                       '20 + 10/s + 2*s/(0.01*s + 1)', '(s + 1)**10/(s + 2)**10']:
        assert Model(MSD, controller=controller).parameters == ('m', 'd', 'k')


def test_size_limits_name_the_limit_and_the_value():
    with pytest.raises(ModelError, match=r'more than 64 parameters: .a63. would be number 65'):
        Model('K/(' + '+'.join(f'a{i}*s' for i in range(70)) + ' + 1)')
    with pytest.raises(ModelError, match='too large to differentiate: .* exceeds the limit of '
                                         '100000'):
        Model('K/(' + '*'.join(f'(T{i}*s + 1)' for i in range(8)) + ')')
    with pytest.raises(ModelError, match='closed loop .* is too large to differentiate'):
        Model('K/(' + '*'.join(f'(T{i}*s + 1)' for i in range(5)) + ')',
              controller='(s + 1)**10/(s + 2)**11')
    with pytest.raises(ModelError, match='closed loop .* would expand to up to 790 terms; the '
                                         'limit is 512'):
        Model('K/(' + '*'.join(f'(T{i}*s + 1)' for i in range(6)) + ')',
              controller='(s + 1)**10/(s + 2)**11')
    # Within the limits: a degree-20 black box and a product of six first-order lags.
    black_box = Model('(' + ' + '.join(f'b{i}*s**{i}' for i in range(20)) + ')/(s**20 + '
                      + ' + '.join(f'a{i}*s**{i}' for i in range(20)) + ')')
    assert (black_box.den_degree, len(black_box.parameters)) == (20, 40)
    lags = Model('K/(' + '*'.join(f'(T{i}*s + 1)' for i in range(6)) + ')')
    assert lags.den_degree == 6


def test_fixed_parameters_become_numbers_in_the_same_structure():
    model = Model('exp(-tau*s)/(J*s + b)')
    held = model.with_fixed({'J': 0.05})
    assert held.parameters == ('tau', 'b') and held.expression == 'exp(-tau*s)/((0.05)*s + b)'
    params = {'tau': 0.0373, 'b': 0.2}
    u = np.sin(np.arange(200) * 0.1)
    np.testing.assert_allclose(held.simulate(params, u, 0.01),
                               model.simulate({**params, 'J': 0.05}, u, 0.01), rtol=1e-12)
    known_delay = model.with_fixed({'tau': 0.0373})
    assert known_delay.has_delay and not known_delay.delay_is_estimated
    loop = Model(MSD, controller='20 + 10/s').with_fixed({'k': 2.0})
    assert (loop.parameters, loop.controller) == (('m', 'd'), '20 + 10/s')
    equation = Model('M*s**2*q + Fv*s*q = 35.15065*u - Fc*w - off', inputs=('u', 'w'),
                     output='q').with_fixed({'off': -3.1})
    assert equation.parameters == ('M', 'Fv', 'Fc') and equation.inputs == ('u', 'w')
    for values, message in (({'q': 1.0}, "'q' is not a parameter"),
                            ({'J': float('nan')}, 'must be a finite number'),
                            ({'J': 1.0, 'b': 2.0, 'tau': 0.1}, 'leaves no parameter')):
        with pytest.raises(ModelError, match=message):
            model.with_fixed(values)
