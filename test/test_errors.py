"""Tests of ctid_ros.errors: the exception hierarchy and the bounded quoting of values."""

from ctid_ros.errors import (BagError, bounded_repr, ConfigError, CtidError, DataError,
                             EstimationError, ModelError)
import numpy as np


def test_every_error_is_a_ctid_error_and_a_standard_exception():
    for error, base in ((ModelError, ValueError), (DataError, ValueError),
                        (ConfigError, ValueError), (EstimationError, RuntimeError),
                        (BagError, OSError)):
        assert issubclass(error, CtidError) and issubclass(error, base)


def test_bounded_repr_is_short_for_any_value():
    bomb = ['lol']
    for _ in range(60):
        bomb = [bomb] * 9               # a YAML "billion laughs" after construction
    long_text = 'x' * 10 ** 6
    huge_number = 10 ** 5000             # repr() itself refuses it
    for value in (bomb, long_text, huge_number, np.zeros(10 ** 6), {i: i for i in range(10 ** 5)},
                  b'\x00' * 10 ** 6):
        text = bounded_repr(value)
        assert 0 < len(text) <= 80, text
    assert bounded_repr({'a': (1, 2)}) == "{'a': (1, 2)}"
    assert bounded_repr('abc', limit=10) == "'abc'"
    assert bounded_repr(long_text, limit=20).endswith('...') and len(
        bounded_repr(long_text, limit=20)) == 20


def test_bounded_repr_survives_a_broken_repr():
    class Broken:
        def __repr__(self):
            raise RuntimeError('no')

    assert bounded_repr(Broken()).startswith('<Broken')
