"""Safe parsing of model text: hostile and malformed strings, valid grammar, size limits."""

import json
import subprocess
import sys
import textwrap

from ctid_ros import Model, ModelError
from ctid_ros.core.expression import (LAPLACE, MAX_DELAY_TERMS, MAX_DEPTH, MAX_FACTORS, MAX_LENGTH,
                                      MAX_PARAMETERS, parse_expression, parse_model_text,
                                      tokenize)
import pytest
import sympy as sp


# (text, column the message must point at, or None when the parser cannot know one)
HOSTILE = [
    ("__import__('os').system('x')", 12),          # the quote; the dunder name never parses
    ('().__class__', 3),
    ('s.__class__', 2),
    ('K.real/(s+1)', 2),
    ('__class__/(s+1)', 1),
    ('K/(s+__dict__)', 6),
    ('_K/(s+1)', 1),
    ('sin(s)', 1),
    ('eval(1)', 1),
    ('open(1)', 1),
    ('exec(K)/(s+1)', 1),
    ('K/(s+1)*getattr(K)', 9),
    ('K(s)', 1),                                   # a parameter used as a function
    ("'a'", 1),
    ('"K"/(s+1)', 1),
    ('K/(s+1) # comment', 9),
    ('lambda: 1', 7),
    ('lambda x: x', 9),
    ('K;import os', 2),
    ('1;2', 2),
    ('`s`', 1),
    ('[1]', 1),
    ('K[0]/(s+1)', 2),
    ('{K}', 1),
    ('1,2', 2),
    ('K/(s+1), 1', 8),
    ('K/(s+1) if K else 1', 9),
    ('K @ s', 3),
    ('K % s', 3),
    ('K // s', 4),                                 # '/' followed by '/'
    ('K/(s+1)\\', 8),
    ('K = 1', 3),
    ('K/(s+1)\x00', 8),
    ('K\u00a0/(s+1)', 2),                          # non-ASCII white space
    ('\u0661/(K*s+1)', 1),                         # ARABIC-INDIC DIGIT ONE
    ('K\u00b2/(s+1)', 2),
    ('s**100000', 4),
    ('K/(s+1)**33', 10),
    ('2**10**10', 4),
    ('K*s**(-33)', 6),
    ('K/(s+1)**K', 10),                            # symbolic exponent
    ('K/(s+1)**0.5', 10),                          # fractional power of s
    ('K*1e400/(s+1)', 3),
    ('K*1e-400/(s+1)', 3),
    ('K*' + '1' * 40 + '/(s+1)', 3),
    ('K/(s+1)*' + 'x' * 65, 9),                    # name too long
    ('(' * 100 + 'K' + ')' * 100 + '/(s+1)', MAX_DEPTH + 1),
    ('-' * 100 + 'K/(s+1)', MAX_DEPTH + 1),
    ('K/(s+1))', 8),
    ('(K/(s+1)', 9),
    ('K/(s+1) +', 10),
    ('K/(s+1) K', 9),
    ('K**', 4),
    ('*K', 1),
    ('K/()', 4),
    ('K/0', 2),
    ('K/(s-s)', 2),
    ('0**-1*K', 4),
    ('exp', 1),
    ('K*exp/(s+1)', 3),
    ('exp s', 1),
    ('lambda/(s+1)', 1),
    ('K*import/(s+1)', 3),
    ('None*K/(s+1)', 1),
    ('K/(True*s+1)', 4),
    ('K/(class*s+1)', 4),
    ('if/(s+1)', 1),
]


@pytest.mark.parametrize('text,column', HOSTILE)
def test_hostile_text_is_rejected_with_its_column(text, column):
    with pytest.raises(ModelError) as info:
        parse_expression(text)
    message = str(info.value)
    assert f'column {column}' in message
    # The caret line points at the same place under the echoed text.
    lines = message.splitlines()
    assert lines[-1] == '  ' + ' ' * (column - 1) + '^'
    with pytest.raises(ModelError):
        Model(text)


@pytest.mark.parametrize('text', [
    '', '   ', '\t\n',
    '(' * 10000 + 's' + ')' * 10000,
    'K+' * 1500 + 'K',
    ' ' * (MAX_LENGTH + 1) + 'K/(s+1)',
])
def test_empty_or_oversized_text_is_rejected(text):
    with pytest.raises(ModelError):
        parse_expression(text)
    with pytest.raises(ModelError):
        Model(text)


@pytest.mark.parametrize('value', [None, 1, 1.5, b'K/(s+1)', ['K/(s+1)'], {'K': 1},
                                   sp.Symbol('K')])
def test_non_string_input_is_rejected(value):
    with pytest.raises(ModelError, match='must be a string'):
        parse_expression(value)
    with pytest.raises(ModelError, match='must be a string'):
        Model(value)


@pytest.mark.parametrize('controller', ["__import__('os')", 'sin(s)', 'eval(1)', '1;2', ''.join(
    ['('] * 60 + ['1'] + [')'] * 60)])
def test_hostile_controller_is_rejected(controller):
    with pytest.raises(ModelError):
        Model('1/(m*s**2 + d*s + k)', controller=controller)


# Short texts that describe enormous objects. They are run in a child process so that a
# regression shows up as a failed test instead of a test run that never ends.
EXPANSIVE = [
    '1e999999999/(s+1)',
    'K*1e-999999999/(s+1)',
    '((((((9**16)**16)**16)**16)**16)**16)*K/(s+1)',
    'K*((((((2*pi)**16)**16)**16)**16)**16)/(s+1)',
    'K/(((s**16)**16)**16)',
    'K/(((((s+1)**16)**16)**16)**16)',
    'K/(s+1)**16/(s+2)**16/(s+3)',
    'K/(a+b+c+d+e+f+g+h+i+j+l+m+n+o+p+s)**16',
    'K/(' + '*'.join(['(a+b+c+d+s)'] * 60) + ')',
    'K/(' + '+'.join(['(a+b+c+d+s)**16'] * 30) + ')',
    'K/(' + '*'.join(f'(x{i}*s+1)' for i in range(24)) + ')',
    '+'.join(f'k{i}/(x{i}*s+1)' for i in range(10)),
    'K*exp(-(' + '*'.join(['(a+b+c+d+s)'] * 60) + '))/(s+1)',
]


def test_expansive_text_is_rejected_without_hanging():
    script = textwrap.dedent("""
        import json, sys
        from ctid_ros import Model
        outcomes = []
        for text in json.loads(sys.stdin.read()):
            try:
                Model(text)
                outcomes.append('accepted')
            except Exception as error:
                outcomes.append(type(error).__name__ + ': ' + str(error).splitlines()[0])
        print(json.dumps(outcomes))
    """)
    done = subprocess.run([sys.executable, '-c', script], input=json.dumps(EXPANSIVE),
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    outcomes = json.loads(done.stdout)
    for text, outcome in zip(EXPANSIVE, outcomes):
        assert outcome.startswith('ModelError: '), (text[:60], outcome)
    sizes = [outcome for outcome in outcomes if 'too large' in outcome]
    assert len(sizes) >= 9
    assert all('column' in outcome for outcome in sizes)


def test_large_but_reasonable_expressions_still_parse():
    model = Model('K/(s+1)**16/(s+2)**16')                    # degree 32, the limit
    assert model.den_degree == 32
    model = Model('K/(' + '*'.join(f'(T{i}*s+1)' for i in range(5)) + ')')
    assert model.parameters == ('K', 'T0', 'T1', 'T2', 'T3', 'T4')
    assert model.den_degree == 5
    expression, _ = parse_expression('1e299*K/(1e-299*s+1)')
    assert expression.has(sp.Rational(10) ** 299)


def test_tokens_and_columns():
    tokens = tokenize('  K*exp(-tau*s) / (T1*s^2 + 1.5e-3)')
    assert [(token.kind, token.text, token.column) for token in tokens] == [
        ('name', 'K', 2), ('op', '*', 3), ('name', 'exp', 4), ('op', '(', 7), ('op', '-', 8),
        ('name', 'tau', 9), ('op', '*', 12), ('name', 's', 13), ('op', ')', 14),
        ('op', '/', 16), ('op', '(', 18), ('name', 'T1', 19), ('op', '*', 21),
        ('name', 's', 22), ('op', '^', 23), ('number', '2', 24), ('op', '+', 26),
        ('number', '1.5e-3', 28), ('op', ')', 34), ('end', '', 35)]


def test_valid_expression_parameters_and_values():
    expression, parameters = parse_expression('K*exp(-tau*s)/(T*s + 1)')
    assert [p.name for p in parameters] == ['K', 'tau', 'T']
    K, tau, T = parameters
    assert sp.simplify(expression - K * sp.exp(-tau * LAPLACE) / (T * LAPLACE + 1)) == 0
    # Numbers are exact rationals, '^' is a power, unary minus binds looser than '**'.
    expression, parameters = parse_expression('-b^2 + 0.25*b**-1 - 2**-1 + .5 + 1.')
    b, = parameters
    assert sp.simplify(expression - (-b ** 2 + sp.Rational(1, 4) / b + 1)) == 0
    expression, parameters = parse_expression('2*pi*f')
    assert [p.name for p in parameters] == ['f']
    assert expression == 2 * sp.pi * parameters[0]
    # The same name is the same symbol; s is not a parameter.
    expression, parameters = parse_expression('a*s + a*b + b')
    assert [p.name for p in parameters] == ['a', 'b']
    a, b = parameters
    assert sp.expand(expression - (a * LAPLACE + a * b + b)) == 0
    # Right-associative powers: 2**3**2 = 2**9.
    assert parse_expression('2**3**2')[0] == 512
    assert parse_expression('(-2)**2')[0] == 4
    assert parse_expression('-2**2')[0] == -4
    assert parse_expression('0e999999999999 + 1')[0] == 1


def test_dead_time_is_parsed_apart_from_the_rational_part():
    parsed = parse_model_text('K*exp(-(tau1 + tau2)*s)/(T*s + 1)')
    K, tau1, tau2, T = parsed.symbols
    assert parsed.sides == [K / (T * LAPLACE + 1)]
    assert parsed.dead_time.tau == tau1 + tau2
    assert parsed.dead_time.column == 2
    assert parse_model_text('K/(T*s + 1)').dead_time is None
    # parse_expression keeps the whole text, dead time included.
    expression, _ = parse_expression('K*exp(-(tau1 + tau2)*s)/(T*s + 1)')
    assert expression == K * sp.exp(-(tau1 + tau2) * LAPLACE) / (T * LAPLACE + 1)


@pytest.mark.parametrize('text,fragment,column', [
    ('y = exp(-t*s)*u', 'not supported in a model equation', 5),
    ('exp(-t*s)*y = u', 'not supported in a model equation', 1),
    ('K*exp(-t*s)/(s+1) = 1', 'not supported in a model equation', 3),
])
def test_a_dead_time_in_an_equation_gets_the_equation_message(text, fragment, column):
    with pytest.raises(ModelError, match=fragment) as info:
        parse_model_text(text)
    assert f'column {column}' in str(info.value)


@pytest.mark.parametrize('text,fragment,column', [
    ('kp + ki/s', 'numeric coefficients', 1),
    ('4 + 2/s*exp(-0.1*s)', 'may not contain a dead time', 9),
    ('s = 1', "'=' is only allowed once, in a model equation", 3),
])
def test_controller_text_has_numbers_only(text, fragment, column):
    with pytest.raises(ModelError, match=fragment) as info:
        parse_model_text(text, equation=False, controller=True)
    assert f'column {column}' in str(info.value)
    assert parse_model_text('20 + 10/s + 2*pi', controller=True).symbols == ()


@pytest.mark.parametrize('text,fragment,column', [
    ('K*(-1)**0.5/(s+1)', 'fractional power of the negative number -1 is not real', 9),
    ('K/(s + (-8)**(1/3))', 'not real', 14),
    ('K/(s + (2 - pi)**1.5)', 'not real', 18),
    ('K/(' + '*'.join(f'a{i}' for i in range(30)) + ')', 'product of up to 25 factors', 89),
    ('K*' + '*'.join(['(a+b+c+d+e+f+g+h+i+j+l+m)'] * 4) + '/(s+1)', 'more than 512 terms',
     54),
])
def test_parser_limits_and_non_real_numbers(text, fragment, column):
    with pytest.raises(ModelError, match=fragment) as info:
        parse_model_text(text)
    assert f'column {column}' in str(info.value)


def test_size_bounds_count_distinct_factors_and_numeric_terms():
    # Terms of a polynomial with numeric coefficients are bounded by its degree + 1.
    assert parse_model_text('(s + 1)**10*(s + 2)**10').size.num_terms == 21
    # (a*s + 1)**16 has 17 terms, each a power of a: with K two factors at most, not 16.
    size = parse_model_text('K/(a*s + 1)**16').size
    assert (size.den_terms, size.den_degree, size.den_factors, size.factors) == (17, 16, 16, 2)
    size = parse_model_text('K/(a*b*c*s + d)').size
    assert (size.num_factors, size.den_factors, size.factors) == (1, 3, 3)
    assert sorted(size.bases) == ['K', 'a', 'b', 'c', 'd']
    assert MAX_PARAMETERS == 64 and MAX_FACTORS == 24 and MAX_DELAY_TERMS == 16


def test_fractional_powers_of_numbers_are_one_generator_each():
    # No parameter inside: nothing to differentiate, so they do not weigh as their base.
    size = parse_model_text('K*(1 + 2**0.5)**2.5/(s + (3 + 5**0.5)**(1/3))**3').size
    assert size.atom_weight == 0 and size.factors <= 8
    size = parse_model_text('K/(s + (a + b)**0.5)').size
    assert size.atom_weight > 0
