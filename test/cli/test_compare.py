"""``ctid compare``: the JSON list, the table, the figure, a bag, validation files."""

import json

from ctid_ros.cli.main import main
from ctid_ros.core.reference_systems import first_order_dead_time, two_lags_dead_time
from record_fixtures import write_csv
from replay_fixtures import DELAY, float_records, params_file, simulate, write_bag

FOPDT = 'K*exp(-tau*s)/(T*s+1)'
SOPDT = 'K*exp(-tau*s)/((T1*s+1)*(T2*s+1))'


def test_json_is_a_ranked_list_with_one_recommendation(tmp_path, capsys):
    csv = write_csv(tmp_path / 'sopdt.csv', two_lags_dead_time().data(1))
    plot = tmp_path / 'compare.png'
    assert main(['compare', str(csv), '--model', FOPDT, '--model', SOPDT, '--json',
                 '--plot', str(plot)]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [item['model'] for item in listed] == [SOPDT, FOPDT]
    assert [item['recommended'] for item in listed] == [True, False]
    for item in listed:
        assert {'model', 'params', 'std', 'fit', 'consistent', 'recommended', 'why'} <= set(item)
        assert item['why']
    assert abs(listed[0]['params']['tau'] - 0.7) < 0.1
    assert plot.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_table_and_validation_file(tmp_path, capsys):
    system = first_order_dead_time()
    estimation = write_csv(tmp_path / 'est.csv', system.data(1))
    validation = write_csv(tmp_path / 'val.csv', system.data(2))
    assert main(['compare', str(estimation), '--model', SOPDT, '--model', FOPDT,
                 '--validate', str(validation)]) == 0
    out = capsys.readouterr().out
    assert f'validation data ({len(system.u)} samples)' in out
    starred = [line for line in out.splitlines() if line.startswith('*')]
    assert FOPDT in starred[0] and 'simplest adequate' in starred[1]


def test_compare_from_a_bag(tmp_path, capsys):
    u, y = simulate(DELAY, 30.0)
    bag = write_bag(tmp_path, float_records(u, y), 'sqlite3')
    params = params_file(tmp_path, DELAY)
    assert main(['compare', str(bag), '--params-file', str(params), '--model', 'K/(T*s+1)',
                 '--model', DELAY['model'], '--json']) == 0
    listed = json.loads(capsys.readouterr().out)
    assert listed[0]['model'] == DELAY['model'] and listed[0]['recommended']
    assert abs(listed[0]['params']['tau'] - DELAY['truth']['tau']) < 0.01


def test_one_model_is_a_user_error(tmp_path, capsys):
    csv = write_csv(tmp_path / 'fopdt.csv', first_order_dead_time().data(1))
    assert main(['compare', str(csv), '--model', FOPDT]) == 2
    assert 'at least two' in capsys.readouterr().err
