"""The change alarm's baseline: params file, baseline file, capture."""

import math

from ctid_ros.errors import ConfigError, DataError
from ctid_ros.streaming.baseline import (average_windows, Baseline, configured_baseline,
                                         overlap, read_baseline_file, write_baseline_file)
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import NANOSECONDS
from ctid_ros.streaming.params_file import load_params_file
import numpy as np
import pytest
import yaml

MODEL = 'exp(-tau*s)/(J*s + b)'


def config(**values):
    return IdentificationConfig.from_dict({'model': MODEL, 'parameter_names': ['J', 'b', 'tau'],
                                           **values})


def test_baseline_from_the_params_file_mapping(tmp_path):
    path = tmp_path / 'node.yaml'
    path.write_text(f"""
ctid_node:
  ros__parameters:
    model: '{MODEL}'
    parameter_names: [J, b, tau]
    baseline: {{J: 0.05, b: 0.2}}
    baseline_std: {{J: 0.0002}}
    min_relative_change: {{J: 0.05}}
""")
    loaded = load_params_file(path)
    baseline = Baseline.from_config(loaded)
    assert baseline.names == ('J', 'b') and baseline.values.tolist() == [0.05, 0.2]
    assert baseline.stds.tolist() == pytest.approx([0.0002, 0.0])
    assert baseline.source == 'params file'
    assert baseline.describe() == 'J = 0.05 +- 0.0002, b = 0.2'
    assert loaded.relative_changes() == {'J': 0.05, 'b': 0.02, 'tau': 0.02}
    assert Baseline.from_config(config()) is None
    with pytest.raises(DataError, match='one value per distinct name'):
        Baseline(('J', 'J'), [1.0, 2.0], np.zeros((2, 2)), 'x')


def test_a_written_baseline_file_reads_back_and_takes_precedence(tmp_path):
    baseline = Baseline(('J', 'b', 'tau'), [0.0501234567891234, 0.2, 0.0373],
                        np.diag([1e-8, 4e-8, 0.0]), 'captured from 5 windows')
    path = tmp_path / 'wheel_baseline.yaml'
    write_baseline_file(str(path), baseline, '/robot1/ctid_node',
                        'captured by /robot1/ctid_node from 5 windows')
    text = path.read_text()
    assert text.startswith('# captured by /robot1/ctid_node from 5 windows\n')
    document = yaml.safe_load(text)
    section = document['/robot1/ctid_node']['ros__parameters']
    assert section['baseline'] == {'J': 0.0501234567891234, 'b': 0.2, 'tau': 0.0373}
    assert section['baseline_std'] == pytest.approx({'J': 1e-4, 'b': 2e-4, 'tau': 0.0})
    read = read_baseline_file(str(path), ('J', 'b', 'tau'))
    assert read.values.tolist() == baseline.values.tolist()      # every digit
    assert read.stds == pytest.approx(baseline.stds)
    assert read.source == f'baseline_file {path}'
    # The file wins over the params file's values; without it those are used.
    both = config(**{'baseline_file': str(path), 'baseline.J': 0.06})
    assert configured_baseline(both)[0].values[0] == pytest.approx(0.0501234567891234)
    assert configured_baseline(both)[1] == f'read from {path}'
    missing = config(**{'baseline_file': str(tmp_path / 'none.yaml'), 'baseline.J': 0.06})
    found, note = configured_baseline(missing)
    assert found.values.tolist() == [0.06] and note == 'from the params file'
    assert configured_baseline(config(baseline_file=str(tmp_path / 'none.yaml'))) == (
        None, f'no baseline yet ({tmp_path / "none.yaml"} does not exist)')
    assert configured_baseline(config()) == (None, 'no baseline configured')
    # Its two mappings pasted into the node's params file give the same baseline.
    pasted = tmp_path / 'node.yaml'
    pasted.write_text(f"/robot1/ctid_node:\n  ros__parameters:\n    model: '{MODEL}'\n"
                      + text.split('ros__parameters:\n')[1])
    from_params = Baseline.from_config(load_params_file(pasted, '/robot1/ctid_node'))
    assert {name: from_params.value(name) for name in from_params.names} == dict(
        zip(baseline.names, baseline.values.tolist()))
    assert sorted(from_params.stds) == pytest.approx(sorted(baseline.stds))


@pytest.mark.parametrize('body, message', [
    ('ctid_node:\n  ros__parameters:\n    baseline: {J: 0.05}\n    model: x\n',
     'only baseline and baseline_std .* found model'),
    ('ctid_node:\n  ros__parameters:\n    baseline: {K: 1.0}\n', 'found baseline.K'),
    ('ctid_node:\n  ros__parameters:\n    baseline: {J: .inf}\n', 'baseline.J must be a finite'),
    ('ctid_node:\n  ros__parameters:\n    baseline: {J: yes}\n', 'baseline.J must be a finite'),
    ('ctid_node:\n  ros__parameters:\n    baseline_std: {J: 0.1}\n', 'needs its baseline'),
    ('ctid_node:\n  ros__parameters:\n    baseline: {J: 1.0}\n    baseline_std: {J: -1.0}\n',
     'must be >= 0'),
    ('other_node:\n  ros__parameters:\n    baseline: {J: 1.0}\n', 'no section for node'),
    ('ctid_node: [1, 2\n', 'not valid YAML'),
])
def test_bad_baseline_files(tmp_path, body, message):
    path = tmp_path / 'baseline.yaml'
    path.write_text(body)
    with pytest.raises(ConfigError, match=message):
        read_baseline_file(str(path), ('J', 'b', 'tau'))
    with pytest.raises(ConfigError, match=message):
        configured_baseline(config(baseline_file=str(path)))


def test_writing_into_a_missing_directory_is_a_config_error(tmp_path):
    baseline = Baseline(('J',), [0.05], np.zeros((1, 1)), 'x')
    with pytest.raises(ConfigError, match='directory .* does not exist'):
        write_baseline_file(str(tmp_path / 'no' / 'b.yaml'), baseline, '/ctid_node', 'note')


def test_average_of_overlapping_windows():
    assert overlap(0.0, 4.0) == 1.0 and overlap(2.0, 4.0) == 0.5 and overlap(-3.0, 4.0) == 0.25
    assert overlap(5.0, 4.0) == 0.0
    covariance = np.diag([4.0, 1.0])
    ends = [round(i * 2.0 * NANOSECONDS) for i in range(4)]
    values = np.array([[1.0, 2.0], [3.0, 2.0], [1.0, 4.0], [3.0, 4.0]])
    baseline = average_windows(('a', 'b'), ends, values, np.array([covariance] * 4), 4.0, 'test')
    assert baseline.values.tolist() == [2.0, 3.0]
    # Four windows each half overlapping its neighbours: (4 + 2 * 3 * 0.5)/16 of one window.
    assert np.diag(baseline.covariance) == pytest.approx(np.diag(covariance) * 7 / 16)
    # Independent windows (4 s apart for 2 s windows): the usual 1/n.
    independent = average_windows(('a', 'b'), ends, values, np.array([covariance] * 4), 2.0, 't')
    assert np.diag(independent.covariance) == pytest.approx(np.diag(covariance) / 4)
    assert math.isclose(independent.stds[0], 1.0)
