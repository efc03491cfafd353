"""
Fuzzing the arguments of ``estimate`` and ``Data`` with hostile values (seeded, about 3 s).

For every generated call the outcome must be one of: a :class:`~ctid_ros.errors.CtidError`
with a short, non-empty message, or a correct result (an ``Estimate`` near the truth, a
``Data`` of finite samples). Anything else (a bare ``TypeError``, ``ZeroDivisionError``, a
``RecursionError``...) fails the test with the call that caused it.
"""

from decimal import Decimal
from fractions import Fraction
import math
import random

from ctid_ros import CtidError, Data, Estimate, estimate, Model
from ctid_ros.core.excitation import prbs
from ctid_ros.errors import bounded_repr
import numpy as np
import pytest

MODEL = Model('K*exp(-tau*s)/(T*s + 1)')
TRUTH = {'K': 2.0, 'T': 0.5, 'tau': 0.12}
TS = 0.05


def nested(depth):
    value = [1.0]
    for _ in range(depth):
        value = [value]
    return value


def bomb():
    value = ['lol']
    for _ in range(40):
        value = [value] * 9
    return value


# Values of every kind a caller (or a params file, a command line) might pass.
HOSTILE = [
    None, True, False, 0, 1, -1, 3, 2.5, -2.5, 0.0, -0.0, 1e-300, 1e300, math.nan, math.inf,
    -math.inf, 10 ** 400, 1 + 1j, Decimal('1.5'), Fraction(1, 3), np.float32(0.5), np.int64(7),
    np.bool_(True), np.float64(math.nan), np.array([1.0, 2.0]), np.array(3.0), '', 'auto', 'x',
    'iv', 'gn', 'ls', 'foh', 'zoh', 'zero', 'estimate', 'yes', '1', b'iv', [], [1, 2],
    [1, 2, 3], (0.1, 1.0), (1.0, 0.1), (None, None), (None, 1.0), (-1.0, 1.0), {}, {'K': 1.0},
    {'K': 'x'}, {'K': math.nan}, {'nope': 1.0}, {1: 2}, {'K': (0.0, 10.0)},
    {'T': (1.0, 0.5)}, {'tau': (None, -1.0)}, {'T': 'x'}, {'T': (1, 2, 3)}, {'T': [0.01, None]},
    {'K': 1.0, 'T': 0.5, 'tau': 0.1}, {'K': -5.0, 'T': -1.0, 'tau': 0.0}, object(), range(3),
    nested(3000), bomb(), {'K': nested(50)}, slice(1), Ellipsis,
]
ARGUMENTS = ['initial', 'bounds', 'method', 'intersample', 'max_iterations', 'tolerance',
             'delay_range', 'transient', 'initial_state', 'output_offset', 'integrator_cutoff']


@pytest.fixture(scope='module')
def data():
    u = prbs(7, 4)[:400]
    y = MODEL.simulate(TRUTH, u, TS)
    return Data(u, y + 0.005 * np.random.default_rng(3).standard_normal(y.size), TS)


def check_outcome(call, what):
    """Run ``call``: a CtidError with a message, or a result; return the result or None."""
    try:
        return call()
    except CtidError as error:
        message = str(error)
        assert message and len(message) < 1000, (what, message)
        return None
    except Exception as error:       # anything else is a bug: report the call
        pytest.fail(f'{what} raised {type(error).__name__}: {str(error)[:300]}')


def test_one_hostile_argument_at_a_time(data):
    rng = random.Random(16)
    results = 0
    for argument in ARGUMENTS:
        for value in rng.sample(HOSTILE, 12):
            what = f'estimate(..., {argument}={type(value).__name__} {bounded_repr(value, 40)})'
            result = check_outcome(lambda: estimate(MODEL, data, **{argument: value}), what)
            if result is not None:
                results += 1
                assert isinstance(result, Estimate), what
                assert all(np.isfinite(list(result.params.values()))), what
    assert results >= 10          # the valid values among them did estimate


def test_valid_options_give_a_correct_result(data):
    result = estimate(MODEL, data, {'K': 1.0, 'T': 1.0, 'tau': 0.0}, bounds={'T': (0.01, None)},
                      method='iv', intersample='zoh', max_iterations=np.int64(50),
                      tolerance=1e-10, delay_range=(0.0, 0.5), transient=0.0,
                      initial_state='zero', output_offset=False, integrator_cutoff=None)
    assert result.params == pytest.approx(TRUTH, rel=0.05)


def test_hostile_positional_arguments(data):
    rng = random.Random(17)
    for value in rng.sample(HOSTILE, 30):
        what = f'{type(value).__name__} {bounded_repr(value, 40)}'
        check_outcome(lambda: estimate(value, data), f'estimate(model={what})')
        check_outcome(lambda: estimate(MODEL, value), f'estimate(data={what})')
        check_outcome(lambda: estimate(MODEL, data, value), f'estimate(initial={what})')


def random_signal(rng, length):
    """Return a hostile signal: wrong shapes, types, non-finite values, or a valid one."""
    choice = rng.randrange(12)
    if choice == 0:
        return rng.choice(HOSTILE)
    if choice == 1:
        return np.full(length, rng.choice([math.nan, math.inf, 1e308, -1e308]))
    if choice == 2:
        return np.zeros((length, rng.randrange(0, 3)))
    if choice == 3:
        return np.zeros((length, 1, 2))
    if choice == 4:
        return [rng.choice([1.0, 'a', None, [1.0], 10 ** 400]) for _ in range(length)]
    if choice == 5:
        return np.ma.masked_array(np.ones(length), np.arange(length) % 7 == 0)
    if choice == 6:
        return np.arange(length).astype(rng.choice(['int8', 'uint64', 'float16', 'bool', 'U3',
                                                    'complex128', 'datetime64[s]', 'object']))
    if choice == 7:
        return np.ones(rng.randrange(0, 3))
    return np.random.default_rng(rng.randrange(100)).standard_normal(length)


def test_data_from_hostile_arrays_and_times():
    rng = random.Random(18)
    accepted = 0
    for _ in range(400):
        length = rng.randrange(1, 50)
        u, y = random_signal(rng, length), random_signal(rng, length)
        ts = rng.choice(HOSTILE + [0.01, 1e-12, 1e12, 1e308] * 20)
        t0 = rng.choice([0.0, -5.0, 1e308, math.nan, 'x', np.float32(2), 0.0, 0.0])
        what = (f'Data(u={type(u).__name__}, y={type(y).__name__}, ts={bounded_repr(ts, 30)}, '
                f't0={t0})')
        result = check_outcome(lambda: Data(u, y, ts, t0), what)
        if result is not None:
            accepted += 1
            assert np.all(np.isfinite(result.u)) and np.all(np.isfinite(result.y)), what
            assert result.ts > 0 and math.isfinite(result.ts) and math.isfinite(result.t0)
            assert np.all(np.isfinite(result.time)), what
            for call in (lambda: result.detrend(rng.choice(['mean', 'initial', 'linear', 3])),
                         lambda: result.segment(rng.choice([0, 1, -1, 2.5, None, 'a']),
                                                rng.choice([None, 3, -2, 1e9]))):
                check_outcome(call, f'{what}: detrend/segment')
    assert accepted >= 10


def test_estimate_on_hostile_data():
    rng = random.Random(19)
    for _ in range(40):
        length = rng.choice([5, 12, 60])
        u = rng.choice([np.zeros(length), np.ones(length), np.arange(length, dtype=float),
                        np.random.default_rng(rng.randrange(9)).standard_normal(length),
                        np.column_stack([np.ones(length), np.arange(length)])])
        y = rng.choice([np.zeros(length), np.full(length, 1e300),
                        np.random.default_rng(rng.randrange(9)).standard_normal(length) * 1e-300,
                        np.random.default_rng(rng.randrange(9)).standard_normal(length)])
        ts = rng.choice([1e-9, 0.05, 1e6])
        check_outcome(lambda: estimate(MODEL, Data(u, y, ts)),
                      f'estimate on u={u[:3]}..., y={y[:3]}..., ts={ts}')
