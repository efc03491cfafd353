"""Models' derivations stored on disk: same numbers, no sympy, nothing but checked data read."""

import json
import os
from pathlib import Path
import subprocess
import sys

from ctid_ros.core import model_cache
from ctid_ros.core.derivation import derive
from ctid_ros.core.model import Model
from ctid_ros.core.model_cache import CoefficientProgram
from ctid_ros.errors import ModelError
import numpy as np
import pytest
import sympy as sp

REPOSITORY = Path(__file__).resolve().parents[2]
# Texts whose generated functions use every form the program knows: products, sums, powers,
# rationals, pi, square roots, a closed loop, a model equation with a constant input.
TEXTS = [
    ('K*exp(-tau*s)/(T*s + 1)', None, None, 'y'),
    ('K*w**2/(s**2 + 2*z*w*s + w**2)', None, None, 'y'),
    ('(a + b)**0.5/(s + c*pi)', None, None, 'y'),
    ('K*exp(-0.5*s)/(T*s + 1)/tau', None, None, 'y'),
    ('1/(m*s**2 + d*s + k)', '(5*s**2 + 20*s + 10)/(s*(0.02*s + 1))', None, 'y'),
    ('M*s**2*y + Fv*s*y = 35.15*u - Fc*w - off', None, ('u', 'w'), 'y'),
]


@pytest.fixture
def store(tmp_path, monkeypatch):
    directory = tmp_path / 'models'
    monkeypatch.setenv(model_cache.CACHE_VARIABLE, str(directory))
    return directory


@pytest.mark.parametrize('key', TEXTS)
def test_program_gives_the_generated_functions_numbers_bit_for_bit(key):
    expression, controller, inputs, output = key
    captured = []
    original = CoefficientProgram.from_function.__func__

    def keep(cls, function):
        captured.append(function)
        return original(cls, function)

    CoefficientProgram.from_function = classmethod(keep)
    try:
        attributes = derive(expression, controller, inputs=inputs, output=output)
    finally:
        CoefficientProgram.from_function = classmethod(original)
    program = attributes['_evaluate']
    assert isinstance(program, CoefficientProgram)
    rng = np.random.default_rng(0)
    for _ in range(20):
        theta = rng.uniform(0.1, 5.0, len(attributes['parameters']))
        expected = np.asarray(captured[0](*theta), dtype=float)
        assert np.array_equal(np.asarray(program(*theta), dtype=float), expected)
        # The Python float path the estimator takes gives the same numbers.
        assert np.array_equal(np.asarray(program.floats(theta.tolist()), dtype=float), expected)


@pytest.mark.parametrize('theta, operations', [
    ([0.0], [['const', 1.0], ['/', 1, 0]]),                 # 1/p at p = 0: inf in numpy
    ([-2.0], [['const', 0.5], ['**', 0, 1]]),               # p**0.5 at p < 0: NaN in numpy
    ([-2.0], [['sqrt', 0]]),
    ([1e300], [['const', 3], ['**', 0, 1]]),                 # overflow: inf in numpy
])
def test_float_path_leaves_what_python_refuses_to_numpy(theta, operations):
    program = CoefficientProgram(1, operations, [len(operations)])
    assert program.floats(theta) is None
    with np.errstate(all='ignore'):
        assert not np.isfinite(program(*np.array(theta))[0])


@pytest.mark.parametrize('key', TEXTS)
def test_stored_model_reads_back_equal(store, key):
    expression, controller, inputs, output = key
    derived = derive(expression, controller, inputs=inputs, output=output)
    model_cache.store(key, derived)
    assert len(list(store.glob('*.json'))) == 1
    loaded = model_cache.load(key)
    assert loaded is not None
    program = loaded.pop('_evaluate')
    assert loaded == {name: value for name, value in derived.items() if name != '_evaluate'}
    theta = np.linspace(0.5, 2.0, len(derived['parameters']))
    assert program(*theta) == derived['_evaluate'](*theta)
    other = (expression + ' ', controller, inputs, output)
    assert model_cache.load(other) is None


def _next_slot(data) -> int:
    return data['program']['parameters'] + len(data['program']['operations'])


def _stored_file(store: Path) -> Path:
    key = TEXTS[1]
    model_cache.store(key, derive(key[0], key[1], inputs=key[2], output=key[3]))
    path, = store.glob('*.json')
    return path


@pytest.mark.parametrize('change', [
    lambda data: data['program']['operations'].append(['exec', 0]),
    lambda data: data['program']['operations'].append(['+', 0, 999]),
    lambda data: data['program']['operations'].extend(
        [['const', 10], ['const', 10 ** 6], ['**', _next_slot(data), _next_slot(data) + 1]]),
    lambda data: data['program']['outputs'].append(10 ** 6),
    lambda data: data['program']['operations'].append(['const', '__import__("os")']),
    lambda data: data['attributes'].update(parameters=['K', 'w']),
    lambda data: data['attributes'].update(is_affine='yes'),
    lambda data: data['key'].__setitem__(0, 'K/(T*s + 1)'),
])
def test_tampered_store_is_not_used(store, change):
    path = _stored_file(store)
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))
    assert model_cache.load(TEXTS[1]) is None


def test_store_writable_by_others_is_not_used(store):
    path = _stored_file(store)
    assert model_cache.load(TEXTS[1]) is not None
    path.chmod(0o666)
    assert model_cache.load(TEXTS[1]) is None


def test_errors_are_not_stored_and_empty_variable_stores_nothing(store, monkeypatch):
    for _ in range(2):
        with pytest.raises(ModelError, match='no parameters'):
            Model('1/(s + 2)', inputs=('v',))
    assert not store.exists() or not list(store.glob('*.json'))
    monkeypatch.setenv(model_cache.CACHE_VARIABLE, '')
    assert model_cache.cache_directory() is None
    model_cache.store(TEXTS[0], derive(*TEXTS[0][:2], inputs=None, output='y'))
    assert model_cache.load(TEXTS[0]) is None


def test_new_process_builds_a_stored_model_without_sympy(store):
    script = ('import sys\n'
              'from ctid_ros.core.model import Model\n'
              'model = Model("K*w**2/(s**2 + 2*z*w*s + w**2)")\n'
              'print(model.parameters, model.is_affine, "sympy" in sys.modules,\n'
              '      model.coefficient_array([2.0, 3.0, 0.5])[:4].tolist())\n')
    environment = dict(os.environ, PYTHONPATH=str(REPOSITORY),
                       **{model_cache.CACHE_VARIABLE: str(store)})
    first, second = (subprocess.run([sys.executable, '-c', script], env=environment, check=True,
                                    capture_output=True, text=True).stdout for _ in range(2))
    assert first.replace('True [', 'False [') == second
    assert "('K', 'w', 'z') False True [18.0, 1.0, 3.0, 9.0]" in first
    assert "('K', 'w', 'z') False False [18.0, 1.0, 3.0, 9.0]" in second


def test_program_rejects_unknown_forms():
    assert CoefficientProgram.from_function(sp.lambdify([sp.Symbol('x')], [sp.sin(1)])) is None
    assert CoefficientProgram.from_function(len) is None


def test_store_keeps_at_most_max_stored_models(store, monkeypatch):
    monkeypatch.setattr(model_cache, 'MAX_STORED', 3)
    derived = derive('K/(T*s + 1)', None, inputs=None, output='y')
    keys = [(f'K/(T*s + {index})', None, None, 'y') for index in range(1, 6)]
    seen = set()
    for index, key in enumerate(keys):
        model_cache.store(key, dict(derived, expression=key[0]))
        written, = set(store.glob('*.json')) - seen
        os.utime(written, (1000 + index, 1000 + index))    # written in this order
        seen = set(store.glob('*.json'))
    assert len(seen) == 3
    kept = [model_cache.load(key) is not None for key in keys]
    assert kept == [False, False, True, True, True]


def test_no_home_directory_means_no_store(monkeypatch):
    monkeypatch.delenv(model_cache.CACHE_VARIABLE)
    monkeypatch.delenv('XDG_CACHE_HOME', raising=False)
    monkeypatch.setattr(os.path, 'expanduser', lambda path: path)
    assert model_cache.cache_directory() is None
    monkeypatch.setenv('XDG_CACHE_HOME', 'relative/cache')
    assert model_cache.cache_directory() is None
    monkeypatch.setenv('XDG_CACHE_HOME', '/somewhere/cache')
    assert model_cache.cache_directory() == Path('/somewhere/cache/ctid_ros/models')


@pytest.mark.parametrize('operations', [
    [['const', 1], ['const', 0], ['/', 1, 2]],
    [['const', 10.0], ['const', 400], ['**', 1, 2]],
    [['const', 10 ** 1000], ['sqrt', 1]],
])
def test_program_refuses_arithmetic_that_fails_on_numbers(operations):
    with pytest.raises(ValueError, match='arithmetic on numbers fails'):
        CoefficientProgram(1, operations, [len(operations)])


def test_a_text_over_the_length_limit_is_refused_without_sympy(store):
    """A hostile parameter (a 200 000-character controller) costs no sympy import."""
    script = ('import sys\n'
              'from ctid_ros.core.model import Model\n'
              'from ctid_ros.errors import ModelError\n'
              'for model, controller in (("K/(T*s + 1)", "1+" * 100000 + "1"),\n'
              '                          ("K/(T*s + 1)" + " + 0" * 1000, None)):\n'
              '    try:\n'
              '        Model(model, controller)\n'
              '    except ModelError as error:\n'
              '        print(error)\n'
              'print("sympy" in sys.modules)\n')
    environment = dict(os.environ, PYTHONPATH=str(REPOSITORY),
                       **{model_cache.CACHE_VARIABLE: str(store)})
    lines = subprocess.run([sys.executable, '-c', script], env=environment, check=True,
                           capture_output=True, text=True).stdout.splitlines()
    assert lines == ['controller: model expression is 200001 characters long; the limit is 2000',
                     'model expression is 4011 characters long; the limit is 2000', 'False']
