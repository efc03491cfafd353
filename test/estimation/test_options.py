"""Tests of ctid_ros.estimation.options: every argument of estimate() checked once, up front."""

from ctid_ros import ConfigError, Data, DataError, estimate, Model, ModelError
from ctid_ros.core.limits import MAX_SAMPLES
from ctid_ros.estimation.options import check_options
import numpy as np
import pytest

MODEL = Model('K*exp(-tau*s)/(T*s + 1)')
DATA = Data(np.sin(np.arange(50.0)), np.cos(np.arange(50.0)), 0.1)


@pytest.mark.parametrize('keywords,argument', [
    ({'bounds': {'K': 'x'}}, "bounds['K']"),
    ({'bounds': {'K': (1, 2, 3)}}, "bounds['K']"),
    ({'bounds': {'K': {'low': 1}}}, "bounds['K']"),
    ({'bounds': {'K': ('a', 2)}}, "low side of bounds['K']"),
    ({'bounds': {'K': (1, float('nan'))}}, "high side of bounds['K']"),
    ({'bounds': {'K': (2, 1)}}, "bounds['K'] is empty"),
    ({'bounds': {'K': (float('inf'), None)}}, "bounds['K'] is empty"),
    ({'bounds': {'tau': (None, -1.0)}}, 'dead time'),
    ({'bounds': [('K', 1, 2)]}, 'bounds must be a dict'),
    ({'initial': [1, 2]}, 'initial must be a dict'),
    ({'initial': 'guess'}, 'initial must be a dict'),
    ({'initial': {'K': 'one'}}, "initial['K']"),
    ({'initial': {'K': float('inf')}}, "initial['K']"),
    ({'initial': {1: 1.0}}, 'keys of initial'),
    ({'transient': -1}, 'transient'),
    ({'transient': float('nan')}, 'transient'),
    ({'transient': 'yes'}, 'transient'),
    ({'transient': True}, 'transient'),
    ({'method': 'magic'}, "method must be one of 'iv', 'ls', 'gn'"),
    ({'method': ['iv']}, 'method'),
    ({'intersample': 'cubic'}, 'intersample'),
    ({'initial_state': 'random'}, 'initial_state'),
    ({'max_iterations': 0}, 'max_iterations must be an integer >= 1, got 0'),
    ({'max_iterations': 2.5}, 'max_iterations'),
    ({'max_iterations': True}, 'max_iterations'),
    ({'max_iterations': '10'}, 'max_iterations'),
    ({'tolerance': -1e-3}, 'tolerance'),
    ({'tolerance': None}, 'tolerance'),
    ({'delay_range': (1.0, 0.5)}, 'delay_range'),
    ({'delay_range': 0.5}, 'delay_range'),
    ({'delay_range': (-1.0, 1.0)}, 'delay_range'),
    ({'output_offset': 'yes'}, 'output_offset'),
    ({'output_offset': 1}, 'output_offset'),
    ({'integrator_cutoff': 0}, 'integrator_cutoff'),
    ({'integrator_cutoff': -5}, 'integrator_cutoff'),
    ({'integrator_cutoff': float('nan')}, 'integrator_cutoff'),
    ({'integrator_cutoff': '1'}, 'integrator_cutoff'),
])
def test_bad_arguments_raise_a_config_error_naming_them(keywords, argument):
    with pytest.raises(ConfigError) as error:
        estimate(MODEL, DATA, **keywords)
    assert argument in str(error.value)
    assert isinstance(error.value, ValueError)


def test_names_unknown_to_the_model_are_model_errors():
    with pytest.raises(ModelError, match="bounds given for unknown parameter.*'mass'"):
        estimate(MODEL, DATA, bounds={'mass': (0, 1)})
    with pytest.raises(ModelError, match="initial values given for unknown.*'mass'.*K, tau, T"):
        estimate(MODEL, DATA, {'mass': 1.0})


def test_model_and_data_must_be_ctid_objects():
    with pytest.raises(ConfigError, match='model must be a ctid_ros Model'):
        estimate('K/(T*s + 1)', DATA)
    with pytest.raises(ConfigError, match='data must be a ctid_ros Data'):
        estimate(MODEL, (DATA.u, DATA.y))


def test_record_longer_than_the_limit_is_refused_before_any_work():
    long = Data(np.zeros(MAX_SAMPLES + 1), np.zeros(MAX_SAMPLES + 1), 0.001)
    with pytest.raises(DataError, match=f'more than the limit of {MAX_SAMPLES}'):
        estimate(MODEL, long)


def test_the_value_quoted_in_a_message_is_bounded():
    nested = ['lol']
    for _ in range(40):
        nested = [nested] * 9          # 9**40 leaves if expanded
    with pytest.raises(ConfigError) as error:
        estimate(MODEL, DATA, initial=nested)
    assert len(str(error.value)) < 200


def test_options_are_normalised_to_plain_python():
    options = check_options(MODEL, DATA, {'K': np.int64(2)},
                            bounds={'K': (np.float32(1), np.inf), 'T': [None, 5]},
                            transient=np.float64(0.5), max_iterations=np.int32(7),
                            output_offset=np.bool_(True), delay_range=[0, 1],
                            integrator_cutoff=3)
    assert options.initial == {'K': 2.0} and type(options.initial['K']) is float
    assert options.bounds == {'K': (1.0, None), 'T': (None, 5.0)}
    assert options.transient == 0.5 and type(options.transient) is float
    assert options.max_iterations == 7 and type(options.max_iterations) is int
    assert options.output_offset is True
    assert options.delay_range == (0.0, 1.0) and options.integrator_cutoff == 3.0
    assert check_options(MODEL, DATA, None).initial == 'auto'
    assert check_options(MODEL, DATA, transient='auto').transient == 'auto'
    assert check_options(MODEL, DATA).bounds is None
