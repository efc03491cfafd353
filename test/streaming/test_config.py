"""Configuration: parameter specs, types, validation, runtime changes."""

import dataclasses
import math

from ctid_ros.errors import ConfigError
from ctid_ros.streaming.config import IdentificationConfig, PARAMETER_NAMES, PARAMETERS
import pytest

CONTRACT = (
    'input_topic', 'input_field', 'output_topic', 'output_field', 'extra_input_fields', 'model',
    'input_names', 'output_name', 'controller', 'parameter_names', 'initial', 'lower', 'upper',
    'sample_time', 'window', 'update_period',
    'method', 'intersample', 'stamp_source', 'qos_reliability', 'qos_depth', 'max_message_rate',
    'max_gap', 'reorder_horizon', 'delay_min', 'delay_max', 'max_iterations', 'tolerance',
    'transient', 'initial_state', 'output_offset', 'warm_start', 'publish_prediction',
    'hardware_id', 'lifecycle', 'baseline_file', 'baseline_windows', 'false_alarm_per_hour',
    'min_relative_change', 'candidate_models', 'compare_every', 'tune.controller', 'tune.method',
    'tune.tc', 'tune.ms', 'tune.sample_time', 'tune.draws', 'tune.joint')
FOPDT = 'K*exp(-tau*s)/(T*s + 1)'


@pytest.fixture(scope='module')
def base():
    return IdentificationConfig(model=FOPDT, input_topic='/plant/u', output_topic='/plant/y')


def test_parameter_specs_follow_the_contract():
    assert PARAMETER_NAMES == CONTRACT
    kinds = {spec.name: spec.kind for spec in PARAMETERS}
    assert {name for name, kind in kinds.items() if kind == 'integer'} == {
        'qos_depth', 'max_iterations', 'baseline_windows', 'compare_every',
        'tune.draws'}
    assert {name for name, kind in kinds.items() if kind == 'bool'} == {
        'output_offset', 'warm_start', 'publish_prediction', 'lifecycle'}
    assert {name for name, kind in kinds.items() if kind == 'double_array'} == {
        'initial', 'lower', 'upper'}
    assert kinds['parameter_names'] == 'string_array'
    assert all(kinds[name] == 'double' for name in (
        'sample_time', 'window', 'update_period', 'max_gap', 'reorder_horizon', 'delay_min',
        'delay_max', 'tolerance', 'transient', 'max_message_rate', 'false_alarm_per_hour',
        'min_relative_change'))
    defaults = IdentificationConfig(model='1/(T*s + 1)')
    for spec in PARAMETERS:
        assert len(spec.description) > 20, spec.name
        if spec.name != 'model':
            assert defaults.value(spec.name) == spec.default
    by_name = {spec.name: spec for spec in PARAMETERS}
    assert by_name['input_field'].default == 'data' and by_name['qos_depth'].default == 500
    assert by_name['stamp_source'].default == 'header'
    assert by_name['controller'].default == ''
    assert by_name['window'].type_name == 'PARAMETER_DOUBLE'
    assert by_name['initial'].type_name == 'PARAMETER_DOUBLE_ARRAY'
    assert by_name['method'].constraints == 'one of: iv, ls, gn'
    assert by_name['input_topic'].configure_only and not by_name['input_topic'].read_only
    assert by_name['qos_depth'].constraints == 'value >= 1; changes only while unconfigured ' \
        '(a managed node: cleanup, set, configure)'
    assert not by_name['model'].read_only and not by_name['model'].configure_only
    assert by_name['lifecycle'].read_only and by_name['hardware_id'].default == ''


def test_parameter_order_and_estimator_options(base):
    config = base.updated({'parameter_names': ['tau', 'K', 'T'],
                           'initial': [0.2, math.nan, 1.5],
                           'lower': [0.0, -math.inf, 0.1], 'upper': [1.0, math.inf, 10.0],
                           'delay_min': 0.05, 'delay_max': 0.5, 'method': 'ls'})
    assert config.compiled_model.parameters == ('K', 'tau', 'T')
    assert config.names == ('tau', 'K', 'T')
    assert config.model_index == (1, 0, 2)
    assert config.estimator_options() == {
        'initial': {'tau': 0.2, 'T': 1.5}, 'bounds': {'tau': (0.0, 1.0), 'T': (0.1, 10.0)},
        'method': 'ls', 'intersample': 'zoh', 'max_iterations': 100, 'tolerance': 1e-8,
        'delay_range': (0.05, 0.5), 'transient': 'auto', 'initial_state': 'zero',
        'output_offset': False}
    assert base.updated({'transient': 2.0}).estimator_options()['transient'] == 2.0
    assert base.names == ('K', 'tau', 'T')
    assert base.estimator_options()['initial'] == 'auto'
    assert base.estimator_options()['bounds'] is None
    assert base.delay_range is None


def test_runtime_change_leaves_the_current_configuration_intact(base):
    changed = base.updated({'window': 5, 'model': 'K/(T*s + 1)', 'publish_prediction': True})
    assert (changed.window, changed.model, changed.publish_prediction) == (
        5.0, 'K/(T*s + 1)', True)
    assert changed.compiled_model.parameters == ('K', 'T')
    assert (base.window, base.model, base.publish_prediction) == (10.0, FOPDT, False)
    with pytest.raises(ConfigError, match='window .* must hold at least 10 samples'):
        base.updated({'window': 0.05})
    with pytest.raises(ConfigError, match='unknown parameter.s. modle'):
        base.updated({'modle': 'K/s'})
    assert base.window == 10.0 and base.compiled_model.parameters == ('K', 'tau', 'T')
    assert dataclasses.replace(base) == base


@pytest.mark.parametrize('changes, message', [
    ({'model': ''}, 'model is required'),
    ({'model': 'K/(T*s + 1'}, "model 'K/\\(T\\*s \\+ 1' is invalid"),
    ({'model': 's/(T + 1)'}, 'is invalid: .*improper'),
    ({'model': '1/(m*s**2 + k)', 'controller': '20 + x/s'},
     "controller '20 \\+ x/s' is invalid: .*numeric coefficients"),
    ({'parameter_names': ['K', 'T']}, r'permutation of the model parameters \(K, tau, T\): '
                                      'missing tau'),
    ({'parameter_names': ['K', 'T', 'tau', 'x']}, 'not in the model x'),
    ({'parameter_names': ['K', 'K', 'T', 'tau']}, 'repeated K'),
    ({'initial': [1.0, 2.0]}, r'initial has 2 values but the model has 3 parameters '
                              r'\(K, tau, T\)'),
    ({'upper': [1.0]}, 'upper has 1 values'),
    ({'lower': [0.0, 1.0, 0.0], 'upper': [1.0, 1.0, 1.0]},
     'lower must be < upper: for tau lower = 1.0 >= upper = 1.0'),
    ({'initial': [5.0, 0.1, 1.0], 'upper': [2.0, 1.0, 1.0]},
     r'initial value of K = 5.0 is outside its bounds \[-inf, 2.0\]'),
    ({'initial': [math.inf, 0.1, 1.0]}, 'initial values must be finite or NaN'),
    ({'lower': [math.nan, 0.0, 0.0]}, 'lower may not contain NaN'),
    ({'sample_time': 0.0}, 'sample_time must be positive and finite'),
    ({'sample_time': -0.01}, 'sample_time must be positive'),
    ({'window': math.inf}, 'window must be positive and finite'),
    ({'window': 0.05}, r'window \(0.05 s\) must hold at least 10 samples .* at least 0.1 s'),
    ({'update_period': 0.0}, 'update_period must be positive'),
    ({'max_gap': 0.0}, 'max_gap must be positive'),
    ({'tolerance': 0.0}, 'tolerance must be positive'),
    ({'reorder_horizon': -0.1}, 'reorder_horizon must be non-negative'),
    ({'reorder_horizon': 10.0}, r'reorder_horizon \(10.0 s\) must be shorter than the window'),
    ({'qos_depth': 0}, 'qos_depth must be at least 1'),
    ({'transient': math.inf}, 'transient must be finite'),
    ({'max_iterations': 0}, 'max_iterations must be at least 1'),
    ({'method': 'gradient'}, "method must be one of iv, ls, gn; got 'gradient'"),
    ({'intersample': 'spline'}, 'intersample must be one of zoh, foh'),
    ({'stamp_source': 'now'}, 'stamp_source must be one of header, receive'),
    ({'qos_reliability': 'sometimes'}, 'qos_reliability must be one of best_effort, reliable'),
    ({'delay_min': -1.0}, 'delay_min must be non-negative'),
    ({'delay_min': 0.5, 'delay_max': 0.2}, r'delay_min \(0.5 s\) must be < delay_max'),
    ({'delay_max': 20.0}, r'delay_max \(20.0 s\) must be shorter than the window'),
    ({'model': 'K/(T*s + 1)', 'delay_max': 1.0}, 'model .* has no estimated dead time'),
    ({'input_topic': 'plant u'}, "input_topic 'plant u' is not a valid topic name"),
    ({'output_topic': '/plant//y'}, 'output_topic .* is not a valid topic name'),
    ({'output_topic': ''}, 'output_topic .* is not a valid topic name'),
    ({'input_field': 'data.__class__'}, 'input_field: invalid field path'),
    ({'output_field': 'position[-1]'}, 'output_field: invalid field path'),
    ({'output_topic': '/plant/u'}, 'input and output are the same field of the same topic'),
])
def test_each_validation_error(base, changes, message):
    with pytest.raises(ConfigError, match=message):
        base.updated(changes)


def test_per_parameter_values_as_ros_flattens_a_mapping(base):
    # baseline: {K: 2.0, T: 0.5} in a params file arrives as baseline.K and baseline.T.
    config = IdentificationConfig.from_dict({
        'model': FOPDT, 'parameter_names': ['T', 'K', 'tau'], 'baseline.K': 2, 'baseline.T': 0.5,
        'baseline_std.K': 0.01, 'min_relative_change': 0.05, 'min_relative_change.tau': 0.2})
    assert config.per_parameter_values('baseline') == {'T': 0.5, 'K': 2.0}
    assert list(config.per_parameter_values('baseline')) == ['T', 'K']   # parameter order
    assert config.per_parameter_values('baseline_std') == {'K': 0.01}
    assert config.relative_changes() == {'T': 0.05, 'K': 0.05, 'tau': 0.2}
    assert config.to_dict()['baseline.K'] == 2.0
    # A runtime change merges; NaN unsets (the node declares them with NaN: not set).
    changed = config.updated({'baseline.tau': 0.1, 'baseline.T': math.nan})
    assert changed.per_parameter_values('baseline') == {'K': 2.0, 'tau': 0.1}
    assert config.per_parameter_values('baseline') == {'T': 0.5, 'K': 2.0}
    assert base.per_parameter == () and base.relative_changes() == dict.fromkeys(base.names, 0.02)
    # Another model keeps the values of the parameters it shares, drops the others.
    other = config.updated({'model': 'K/(T*s + 1)', 'parameter_names': ['K', 'T']})
    assert other.per_parameter_values('baseline') == {'K': 2.0, 'T': 0.5}
    assert config.updated({'model': 'K/(T2*s + 1)', 'parameter_names': []}).per_parameter == (
        ('baseline.K', 2.0), ('baseline_std.K', 0.01))
    assert IdentificationConfig.from_dict({'model': FOPDT, 'baseline.K': math.nan}).per_parameter \
        == ()


@pytest.mark.parametrize('changes, message', [
    ({'baseline.J': 1.0}, r"baseline.J: the model has no parameter 'J' \(its parameters: K, tau, "
                          r'T\)'),
    ({'baseline_std.K': 0.1}, 'baseline_std.K is set but baseline.K is not'),
    ({'baseline.K': 1.0, 'baseline_std.K': -0.1}, 'baseline_std.K must be >= 0'),
    ({'baseline.K': math.inf}, 'baseline.K must be finite'),
    ({'baseline.K': 'two'}, "baseline.K must be a number, got 'two'"),
    ({'min_relative_change.T': -0.1}, 'min_relative_change.T must be between 0 and 10'),
    ({'min_relative_change': 20.0}, 'min_relative_change must be between 0 and 10'),
    ({'false_alarm_per_hour': 0.0}, 'false_alarm_per_hour must be between 1e-06 and 100'),
    ({'false_alarm_per_hour': 1e3}, 'false_alarm_per_hour must be between 1e-06 and 100'),
    ({'baseline_windows': 0}, 'baseline_windows must be between 1 and 1000'),
    ({'baseline_windows': 5.0}, 'baseline_windows must be an integer'),
    ({'baselines.K': 1.0}, r'unknown parameter\(s\) baselines.K; .*per model parameter '
                           r'baseline.<name>'),
])
def test_alarm_parameter_errors(base, changes, message):
    with pytest.raises(ConfigError, match=message):
        base.updated(changes)


def test_valid_edge_cases(base):
    assert base.updated({'reorder_horizon': 0.0, 'window': 0.1}).window == 0.1
    assert base.updated({'input_topic': '~/u', 'output_topic': 'y_1'}).input_topic == '~/u'
    same_topic = base.updated({'output_topic': '/plant/u', 'output_field': 'position[0]'})
    assert same_topic.output_field == 'position[0]'
    assert IdentificationConfig.from_dict({'model': FOPDT}).model == FOPDT


def test_model_equation_with_extra_inputs():
    config = IdentificationConfig(
        model='M*s**2*q + F*s*q = v - c*w', input_names=('v', 'w'), output_name='q',
        extra_input_fields=('effort[1]',), input_field='effort[0]', output_field='position[0]',
        input_topic='/joint_states', output_topic='/joint_states')
    assert config.compiled_model.inputs == ('v', 'w')
    assert config.compiled_model.parameters == ('M', 'F', 'c')
    with pytest.raises(ConfigError, match='extra_input_fields needs 1 field'):
        config.updated({'extra_input_fields': []})
    with pytest.raises(ConfigError, match='extra_input_fields'):
        config.updated({'extra_input_fields': ['effort[']})
    with pytest.raises(ConfigError, match='do not appear'):
        config.updated({'input_names': ['v', 'z']})


# The attacks of issue #16 and the limits that stop them before anything is allocated.
@pytest.mark.parametrize('changes, message', [
    ({'window': 5e8}, r'window \(5e\+08 s\) plus its settling transient \(automatic, one '
                      r'window\) at sample_time 0.01 s is 1e\+11 samples per estimate, more than '
                      r'the limit of 1000000'),
    ({'sample_time': 3e-10}, r'sample_time 3e-10 s is below the limit of 1e-06 s'),
    ({'max_gap': 1e-10}, r'max_gap 1e-10 s is below the limit of 1e-06 s'),
    ({'update_period': 1e-6}, r'update_period 1e-06 s is below the limit of 0.1 s'),
    ({'update_period': 1e7}, r'update_period 1e\+07 s is more than the limit of 1e\+06 s'),
    ({'transient': 2e4}, r'transient \(20000 s\) at sample_time 0.01 s is 2e\+06 samples'),
    ({'window': 4000.0, 'sample_time': 0.1},
     r'the sample buffer would take 977 MiB: 8000.55 s \(window, transient, max_gap and '
     r'reorder_horizon\) of messages at up to 1000 Hz .* more than the limit of 256 MiB'),
    ({'max_gap': 5e5}, r'the sample buffer would take .* GiB'),
    ({'max_message_rate': 1e6}, r'max_message_rate 1e\+06 Hz is more than the limit of 100000 Hz'),
    ({'max_message_rate': 0.0}, 'max_message_rate must be positive'),
    ({'max_iterations': 10 ** 9}, 'max_iterations 1000000000 is more than the limit of 10000'),
    ({'qos_depth': 10 ** 6}, 'qos_depth 1000000 is more than the limit of 10000'),
])
def test_resource_limits(base, changes, message):
    with pytest.raises(ConfigError, match=message):
        base.updated(changes)


def test_buffer_size_follows_the_message_rate(base):
    # A slow plant over an hour: refused at the default 1 kHz, fine at its real 10 Hz.
    slow = {'window': 3600.0, 'sample_time': 0.1}
    with pytest.raises(ConfigError, match='max_message_rate'):
        base.updated(slow)
    config = base.updated({**slow, 'max_message_rate': 10.0})
    assert config.buffer_capacity() == math.ceil((7200 + 0.55) * 10 * 2)
    assert config.buffer_bytes() == 2 * config.buffer_capacity() * 32
    assert config.window_samples == pytest.approx(72000)
    # At the limits themselves: accepted.
    edge = base.updated({'window': 5000.0, 'sample_time': 0.01, 'max_message_rate': 100.0})
    assert edge.window_samples == pytest.approx(1_000_000)
    assert base.updated({'update_period': 0.1}).update_period == 0.1


def test_tune_settings_come_from_the_nested_tune_mapping(base):
    assert base.tune_settings() is None
    config = IdentificationConfig.from_dict({**base.to_dict(), 'tune.controller': 'PI',
                                            'tune.tc': 2.5})
    assert config.tune_settings() == {'controller': 'PI', 'method': 'auto', 'draws': 50,
                                      'seed': 0, 'tc': 2.5}
    assert config.to_dict()['tune.tc'] == 2.5 and config.value('tune.tc') == 2.5
    assert config.updated({'tune.controller': ''}).tune_settings() is None
    for changes, message in (({'tune.tc': 1.0, 'tune.ms': 1.5}, 'both set'),
                             ({'tune.tc': 0.0, 'tune.ms': 0.5}, 'above 1'),
                             ({'tune.controller': 'P'}, "one of '', PI, PID"),
                             ({'tune.method': 'ms', 'tune.tc': 1.0}, 'belongs to tune.method'),
                             ({'tune.draws': 5000}, 'tune.draws must be between')):
        with pytest.raises(ConfigError, match=message):
            config.updated(changes)


def test_candidate_models_are_checked(base):
    candidates = ['K*exp(-tau*s)/(T*s + 1)', 'K*exp(-tau*s)/((T1*s + 1)*(T2*s + 1))']
    assert base.updated({'candidate_models': candidates}).candidate_models == tuple(candidates)
    for changes, message in (({'candidate_models': candidates[:1]}, 'at least two'),
                             ({'candidate_models': [candidates[0], 'K/(T*s +']},
                              'candidate_models: model'),
                             ({'candidate_models': candidates, 'controller': '2 + 1/s',
                               'model': 'K/(T*s + 1)'}, 'open-loop'),
                             ({'compare_every': 0}, 'compare_every must be between')):
        with pytest.raises(ConfigError, match=message):
            base.updated(changes)
