"""Params files as ROS 2 reads them: sections, types in YAML, example configurations."""

import textwrap

from ctid_ros.errors import ConfigError
from ctid_ros.streaming.config import PARAMETER_NAMES, PARAMETERS, PER_PARAMETER
from ctid_ros.streaming.params_file import (config_directories, find_config, load_params_file,
                                            load_units, node_parameters)
import pytest
import yaml


def write(tmp_path, text, name='params.yaml'):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


@pytest.mark.parametrize('name, checks', [
    ('open_loop_delay', {'input_topic': '/plant/u', 'output_topic': '/plant/y',
                         'input_field': 'point.x', 'model': 'K*exp(-tau*s)/(T*s + 1)',
                         'controller': '', 'parameter_names': ('K', 'T', 'tau'),
                         'delay_max': 1.0}),
    ('closed_loop_pi', {'input_topic': '/plant/r', 'output_topic': '/plant/y',
                        'model': '1/(m*s**2 + d*s + k)', 'controller': '20 + 10/s',
                        'parameter_names': ('m', 'd', 'k'), 'initial': (1.0, 1.0, 1.0)}),
    ('joint_states', {'input_topic': '/joint_states', 'output_topic': '/joint_states',
                      'input_field': 'effort[0]', 'output_field': 'position[0]',
                      'model': '1/(J*s**2 + b*s + k)', 'parameter_names': ('J', 'b', 'k')}),
    ('wheel_demo', {'input_topic': '/wheel/u', 'output_topic': '/wheel/y',
                    'input_field': 'point.x', 'model': 'exp(-tau*s)/(J*s + b)',
                    'controller': '', 'parameter_names': ('J', 'b', 'tau'), 'delay_max': 0.2,
                    'per_parameter': (('baseline.J', 0.05), ('baseline.b', 0.2),
                                      ('baseline.tau', 0.0373))}),
])
def test_example_files_load(name, checks):
    path = find_config(name)
    assert path.name == f'{name}.yaml'
    config = load_params_file(path)
    for key, value in checks.items():
        assert getattr(config, key) == value, key
    assert set(config.compiled_model.parameters) == set(config.names)
    # Every parameter is set and commented, with doubles written as doubles.
    section = yaml.safe_load(path.read_text())['ctid_node']['ros__parameters']
    text = path.read_text()
    # An empty list cannot be typed by ROS 2: such a parameter is shown commented out.
    # Comparing and tuning (candidate_models, compare_every, tune.*) are left out: no example
    # compares or tunes.
    names = tuple(name for name in PARAMETER_NAMES if not name.startswith('tune.')
                  and name not in ('candidate_models', 'compare_every'))
    empty = [name for name in names if name not in section]
    assert empty == ['extra_input_fields'] and '    # extra_input_fields: [' in text
    # The figures' units (wheel_demo) come last: no parameter of the node.
    units = section.pop('units', None)
    assert units is None or (tuple(yaml.safe_load(text)['ctid_node']['ros__parameters'])[-1]
                             == 'units' and load_units(path) == units)
    # Per-parameter mappings (baseline: {J: 0.05}) follow the parameters.
    plain = tuple(name for name, value in section.items()
                  if not (name in PER_PARAMETER and isinstance(value, dict)))
    assert plain == tuple(name for name in names if name in section)
    assert list(section)[:len(plain)] == list(plain)
    for parameter in names:
        line = text.index(f'    {parameter}:') if parameter in section else \
            text.index(f'    # {parameter}:')
        assert text[:line].rstrip().splitlines()[-1].strip().startswith('#'), parameter
    for spec in PARAMETERS:
        if spec.name not in names:
            continue
        if spec.kind == 'double':
            assert isinstance(section[spec.name], float), spec.name
        if spec.kind == 'double_array':
            assert all(isinstance(value, float) for value in section[spec.name]), spec.name


def test_example_closed_loop_is_a_closed_loop():
    config = load_params_file(find_config('closed_loop_pi.yaml'))
    assert config.compiled_model.controller == '20 + 10/s'
    assert config.estimator_options()['initial'] == {'m': 1.0, 'd': 1.0, 'k': 1.0}


def test_find_config_prefers_a_workspace_prefix(tmp_path, monkeypatch):
    installed = tmp_path / 'install' / 'share' / 'ctid_ros' / 'config'
    installed.mkdir(parents=True)
    (installed / 'joint_states.yaml').write_text('ctid_node: {}\n')
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path / 'install'))
    assert config_directories()[0] == installed
    assert find_config('joint_states') == installed / 'joint_states.yaml'
    # Not in the workspace: found in the source checkout.
    assert find_config('closed_loop_pi').parent.name == 'config'
    assert find_config(str(installed / 'joint_states.yaml')) == installed / 'joint_states.yaml'
    with pytest.raises(ConfigError, match='available: closed_loop_pi, joint_states, '
                                          'open_loop_delay'):
        find_config('nonexistent')
    with pytest.raises(ConfigError, match='neither an existing file nor a bare name'):
        find_config('some/dir/x.yaml')


def test_fully_qualified_and_wildcard_keys(tmp_path):
    path = write(tmp_path, """
        /**:
          ros__parameters:
            model: K/(T*s + 1)
            window: 30
            use_sim_time: true
        /plant1/ctid_node:
          ros__parameters:
            input_topic: u1
            window: 20.0
        /plant2/ctid_node:
          ros__parameters:
            input_topic: u2
        other_node:
          ros__parameters:
            input_topic: never
        """)
    first = load_params_file(path, '/plant1/ctid_node')
    # The node's own section overrides the wildcard one.
    assert (first.model, first.input_topic, first.window) == ('K/(T*s + 1)', 'u1', 20.0)
    second = load_params_file(path, '/plant2/ctid_node')
    assert (second.input_topic, second.window) == ('u2', 30.0)
    assert load_params_file(path, '/elsewhere/ctid_node').input_topic == 'u'
    with pytest.raises(ConfigError, match='several nodes named .ctid_node. '
                                          r'\(/plant1/ctid_node, /plant2/ctid_node\)'):
        load_params_file(path)


def test_plain_and_namespaced_keys_match_a_plain_node_name(tmp_path):
    for key in ('ctid_node', '/ctid_node', '/robot/ctid_node', '/**/ctid_node', '/robot/*'):
        path = write(tmp_path, f"""
            {key}:
              ros__parameters:
                model: 1/(J*s**2 + b*s + k)
            """)
        assert load_params_file(path).model == '1/(J*s**2 + b*s + k)', key
    assert load_params_file(path, '/robot/ctid_node').compiled_model.parameters == (
        'J', 'b', 'k')
    with pytest.raises(ConfigError, match="no section for node '/arm/ctid_node' .*/robot/\\*"):
        load_params_file(path, '/arm/ctid_node')


def test_integers_are_accepted_for_doubles(tmp_path):
    path = write(tmp_path, """
        ctid_node:
          ros__parameters:
            model: K/(T*s + 1)
            sample_time: 1
            window: 20
            max_gap: 2
            lower: [0, 1]
            upper: [10, 5]
            initial: [1, 2]
        """)
    config = load_params_file(path)
    assert (config.sample_time, config.window, config.max_gap) == (1.0, 20.0, 2.0)
    assert all(isinstance(value, float) for value in
               (config.sample_time, config.window, *config.lower, *config.upper))
    assert config.bounds() == {'K': (0.0, 10.0), 'T': (1.0, 5.0)}
    assert config.to_dict()['initial'] == [1.0, 2.0]


@pytest.mark.parametrize('yaml_text, message', [
    ('window: true', 'window must be a number, got True'),
    ('window: "10"', "window must be a number, got '10'"),
    ('qos_depth: 500.0', r'qos_depth must be an integer \(write 500, not 500.0\)'),
    ('qos_depth: true', 'qos_depth must be an integer'),
    ('warm_start: 1', 'warm_start must be true or false'),
    ('model: 3', 'model must be a string'),
    ('initial: 1.0', 'initial must be a list of numbers'),
    ('initial: [1.0, "a"]', 'initial must be a list of numbers'),
    ('parameter_names: [K, 1]', 'parameter_names must be a list of strings'),
    ('parameter_names: K', 'parameter_names must be a list of strings'),
    ('lower: []', 'lower is an empty list, which ROS 2 cannot type'),
    ('windw: 5.0', 'unknown parameter.s. windw; valid names: input_topic, input_field'),
    ('qos: {depth: 5}', r'unknown parameter\(s\) qos.depth'),
])
def test_wrong_types_and_names_in_a_file(tmp_path, yaml_text, message):
    path = write(tmp_path, f"""
        ctid_node:
          ros__parameters:
            model: K/(T*s + 1)
            {yaml_text}
        """)
    with pytest.raises(ConfigError, match=message):
        load_params_file(path)


def test_ros_standard_parameters_are_not_errors(tmp_path):
    path = write(tmp_path, """
        ctid_node:
          ros__parameters:
            model: K/(T*s + 1)
            use_sim_time: true
            qos_overrides:
              /plant/y:
                subscription:
                  reliability: reliable
        """)
    assert load_params_file(path).model == 'K/(T*s + 1)'


def test_units_label_figures_and_are_no_parameter(tmp_path):
    path = write(tmp_path, """
        /**:
          ros__parameters:
            units: {u: N m}
        ctid_node:
          ros__parameters:
            model: exp(-tau*s)/(J*s + b)
            units:
              J: kg m^2
              tau: s
              y: rad/s
        """)
    assert load_params_file(path).model == 'exp(-tau*s)/(J*s + b)'
    assert load_units(path) == {'u': 'N m', 'J': 'kg m^2', 'tau': 's', 'y': 'rad/s'}
    # As ROS flattens it (a params file written by a tool), and no mapping at all.
    path = write(tmp_path, """
        ctid_node:
          ros__parameters:
            model: K/(T*s + 1)
            units.K: V/V
        """)
    assert load_units(path) == {'K': 'V/V'}
    assert load_units(write(tmp_path, 'ctid_node: {ros__parameters: {model: K/s}}')) == {}
    with pytest.raises(ConfigError, match='units.T must be a unit as text'):
        load_units(write(tmp_path, 'ctid_node: {ros__parameters: {model: K/s, units: {T: 1}}}'))


@pytest.mark.parametrize('document, message', [
    ('[1, 2]', 'expected a mapping of node names'),
    ('ctid_node: {parameters: {}}', 'must contain exactly "ros__parameters:"'),
    ('ctid_node: {ros__parameters: [1]}', 'ros__parameters must be a mapping'),
    ('other: {ros__parameters: {}}', r'no section for node .ctid_node. \(top-level keys: '
                                     'other\\); write "ctid_node:" or "/\\*\\*:"'),
    ('ctid_node: {ros__parameters: {model: "K/(T*s+1)"', 'is not valid YAML'),
])
def test_malformed_files(tmp_path, document, message):
    with pytest.raises(ConfigError, match=message):
        load_params_file(write(tmp_path, document))


def test_unreadable_file(tmp_path):
    with pytest.raises(ConfigError, match='cannot read params file .*missing.yaml'):
        load_params_file(tmp_path / 'missing.yaml')


def test_node_parameters_flattens_nested_names():
    document = {'/**': {'ros__parameters': {'a': {'b': 1, 'c': {'d': 2}}}}}
    assert node_parameters(document) == {'a.b': 1, 'a.c.d': 2}


def billion_laughs(levels=10):
    """Return a params file of a few hundred bytes whose value expands to 9**levels strings."""
    names = 'abcdefghijklmnop'
    lines = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for previous, name in zip(names, names[1:levels]):
        lines.append(f'{name}: &{name} [' + ','.join([f'*{previous}'] * 9) + ']')
    lines.append(f'ctid_node:\n  ros__parameters:\n    initial: *{names[levels - 1]}')
    return '\n'.join(lines) + '\n'


@pytest.mark.parametrize('content, message', [
    (billion_laughs().encode(), 'more than 20000 values with aliases expanded'),
    (('ctid_node:\n  ros__parameters:\n    model: ' + '[' * 5000 + ']' * 5000).encode(),
     'nested more than 32 deep'),
    (b'ctid_node:\n  ros__parameters:\n    model: "K/(T*s+1)"\x00\x01\x02', 'binary.*offset'),
    (b'ctid_node:\n  ros__parameters:\n    model: "\xff\xfe"\n',
     'not UTF-8 text: byte 0xff on line 3'),
    (b'ctid_node:\n  ros__parameters:\n    model: "K/(T*s+1)"\n    sample_time: 1.0e-12\n',
     'sample_time 1e-12 s is below the limit'),
    (b'ctid_node:\n  ros__parameters:\n    model: "K/(T*s+1)"\n    sample_time: 1.0e-6\n'
     b'    window: 10.0\n', r'2e\+07 samples per estimate, more than the limit of 1000000'),
    (b'ctid_node:\n  ros__parameters:\n    model: "K/(T*s+1)"\n    initial: ['
     + b', '.join([b'abc'] * 15000) + b']\n',
     r"initial must be a list of numbers, got \['abc', .*, \.\.\.\] \(list\)$"),
])
def test_hostile_files_are_refused_with_a_config_error(tmp_path, content, message):
    path = tmp_path / 'params.yaml'
    path.write_bytes(content)
    with pytest.raises(ConfigError, match=message) as error:
        load_params_file(path)
    assert len(str(error.value)) < 600 and '\n' not in str(error.value)
    assert path.read_bytes() == content


def test_too_large_and_non_regular_files_are_refused_before_reading(tmp_path):
    large = tmp_path / 'large.yaml'
    with open(large, 'wb') as stream:
        stream.truncate(300 << 10)                  # sparse: nothing is written
    with pytest.raises(ConfigError, match='large.yaml is 300 KiB, more than the limit of 256'):
        load_params_file(large)
    with pytest.raises(ConfigError, match='is a directory'):
        load_params_file(tmp_path)
    with pytest.raises(ConfigError, match='/dev/zero is not a regular file'):
        load_params_file('/dev/zero')


def test_small_anchors_and_a_byte_order_mark_are_fine(tmp_path):
    path = tmp_path / 'params.yaml'
    path.write_bytes('\ufeffdefaults: &d {model: "K/(T*s + 1)", window: 5.0}\n'
                     'ctid_node:\n  ros__parameters: *d\n'.encode())
    config = load_params_file(path)
    assert config.model == 'K/(T*s + 1)' and config.window == 5.0
