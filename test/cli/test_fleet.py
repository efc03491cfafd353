"""
``ctid fleet`` on a small synthetic fleet, with Dask in this process (and once with processes).

Three robots, one with a 20 % heavier payload, two bags each, a corrupt bag and a bag missing
the topic (test/fleet_fixtures.py): the heavy robot is flagged, the bad bags are rows with
their errors, a second run skips every finished bag, and the bag rows equal a direct columnar
replay of each bag. With ``--span``, three 40 s bags (steady; the torque down to 80 % from
20 s; nothing recorded from 9.5 to 20.5 s) cut into 10 s spans: one row per span showing the
change, the empty span an error row, a resumed run skipping every span without opening a bag.
"""

from pathlib import Path
import re

from ctid_ros.cli.fleet import run_fleet
from ctid_ros.cli.fleet_report import combine, flag_robots
from ctid_ros.cli.main import main
from ctid_ros.errors import CtidError
from ctid_ros.files.fleet import analyse_bag, find_bags, make_task, robot_fields
from distributed import Client, LocalCluster
from fleet_fixtures import TRUTH, write_fleet, write_joint_state_bag, write_params
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest


@pytest.fixture(scope='module')
def fleet(tmp_path_factory):
    root = tmp_path_factory.mktemp('fleet')
    bags = write_fleet(root / 'bags', robots=3, days=1, runs=2, seconds=8.0, heavy='r1')
    return root, bags, write_params(root / 'params.yaml', window=4.0, update_period=2.0)


@pytest.fixture(scope='module')
def client():
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                      dashboard_address=':0') as cluster, Client(cluster) as dask_client:
        yield dask_client


def test_the_heavy_robot_is_flagged_and_bad_bags_are_rows(fleet, client, tmp_path):
    root, bags, params = fleet
    results = tmp_path / 'results'
    summary = run_fleet([str(root / 'bags')], params, results, robot_from='{robot}/{date}/*',
                        client=client)
    assert summary == {'bags': 8, 'computed': 8, 'skipped': 0, 'errors': 2, 'robots': 3,
                       'flagged': 1}
    table = pq.read_table(results / 'bags.parquet')
    assert table.column_names[:16] == ['robot', 'bag', 'start', 'end', 'J', 'J_std', 'b',
                                       'b_std', 'tau', 'tau_std', 'fit', 'residual', 'status',
                                       'error', 'date', 'warnings']
    assert str(table.schema.field('start').type) == 'timestamp[ns, tz=UTC]'
    rows = {row['bag']: row for row in table.to_pylist()}
    errors = {name: row['error'] for name, row in rows.items() if row['status'] == 'error'}
    assert set(errors) == {'r0/2025-10-01/run_corrupt', 'r1/2025-10-01/run_no_topic'}
    assert 'damaged' in errors['r0/2025-10-01/run_corrupt']
    assert 'topic(s) /joint_states not in' in errors['r1/2025-10-01/run_no_topic']
    assert rows['r2/2025-10-01/run_1']['date'] == '2025-10-01'
    robots = {row['robot']: row for row in pq.read_table(results / 'robots.parquet').to_pylist()}
    assert [name for name, row in robots.items() if row['flagged']] == ['r1']
    assert robots['r1']['flag_reason'].startswith('J ') and '+20.' in robots['r1']['flag_reason']
    assert robots['r1']['J'] == pytest.approx(0.06, rel=0.01)
    assert robots['r0']['errors'] == 1 and robots['r0']['bags'] == 2
    assert (results / 'robots.csv').read_text().startswith('"robot","bags","errors"')
    assert {path.name for path in results.glob('*.png')} == {
        'fleet_J.png', 'fleet_b.png', 'fleet_tau.png'}
    # The rows are those of the bag replayed on its own.
    one = bags[0]
    task = make_task(one, root / 'bags', '{robot}/{date}/*', params.read_text(), 'ctid_node',
                     False)
    direct = analyse_bag(task).bag
    assert rows[task.name]['J'] == direct['J'] and rows[task.name]['tau_std'] == direct['tau_std']

    again = run_fleet([str(root / 'bags')], params, results, robot_from='{robot}/{date}/*',
                      client=client)
    assert (again['computed'], again['skipped']) == (0, 8)
    assert pq.read_table(results / 'bags.parquet').to_pylist() == table.to_pylist()
    # A changed bag is analysed again, the others stay.
    (bags[1] / 'metadata.yaml').touch()
    assert run_fleet([str(root / 'bags')], params, results, robot_from='{robot}/{date}/*',
                     client=client)['computed'] == 1


def test_sliding_writes_one_row_per_window(fleet, client, tmp_path):
    root, bags, params = fleet
    results = tmp_path / 'results'
    run_fleet([str(bags[0]), str(bags[2])], params, results, sliding=True, client=client,
              plots=False)
    windows = pq.read_table(results / 'windows.parquet').to_pylist()
    per_bag = pq.read_table(results / 'bags.parquet').to_pylist()
    assert len(windows) == sum(row['windows'] for row in per_bag) >= 4
    assert all(row['status'] == 'ok' for row in windows)
    last = [row for row in windows if row['bag'] == per_bag[0]['bag']][-1]
    assert last['J'] == per_bag[0]['J']


def test_robot_patterns_and_bag_discovery(fleet):
    root, bags, _ = fleet
    assert robot_fields('r3/2025-10-02/run_1', '{robot}/{date}/*') == {
        'robot': 'r3', 'date': '2025-10-02'}
    assert robot_fields('site/r3/x.mcap', '**/{robot}/*.mcap') == {'robot': 'r3'}
    assert robot_fields('r3/run_1', None) == {'robot': 'r3'}
    assert robot_fields('run.mcap', None) == {'robot': 'run'}
    with pytest.raises(CtidError, match='does not match'):
        robot_fields('r3/run_1', '{robot}/{date}/*')
    with pytest.raises(CtidError, match='no {robot}'):
        robot_fields('r3/run_1', '{date}/*')
    found_root, found = find_bags([str(root / 'bags' / 'r*' / '*' / 'run_[01]')])
    assert found_root == (root / 'bags').resolve() and len(found) == 6
    with pytest.raises(CtidError, match='no such file'):
        find_bags([str(root / 'nothing*')])


def test_flags_follow_the_uncertainty():
    assert combine([1.0, 3.0], [1.0, 1.0]) == pytest.approx((2.0, np.sqrt(0.5) * np.sqrt(2)))
    rows = [{'robot': f'r{k}', 'status': 'ok', 'start': k, 'x': value, 'x_std': std}
            for k, (value, std) in enumerate([(1.0, 0.01), (1.02, 0.01), (0.99, 0.01),
                                              (1.01, 0.01), (1.5, 0.01), (1.5, 1.0)])]
    flagged = {row['robot']: row['flagged'] for row in flag_robots(rows, ['x'])}
    # 1.5 is far from the fleet for a std of 0.01, not for a std of 1.
    assert flagged == {'r0': False, 'r1': False, 'r2': False, 'r3': False, 'r4': True,
                       'r5': False}


def test_the_command_with_worker_processes(fleet, tmp_path, capsys):
    root, bags, params = fleet
    results = tmp_path / 'results'
    status = main(['fleet', str(bags[0]), str(bags[-1]), '--params-file', str(params),
                   '--results', str(results), '--workers', '2', '--no-plots'])
    assert status == 0
    assert 'ctid fleet: 2 bags: 2 analysed, 0 already done, 1 with errors' in \
        capsys.readouterr().out
    assert Path(results / 'bags.parquet').exists()


@pytest.fixture(scope='module')
def long_bags(tmp_path_factory):
    root = tmp_path_factory.mktemp('long')
    write_joint_state_bag(root / 'bags' / 'r0' / 'run_0', TRUTH, 40.0, 100.0, seed=11)
    write_joint_state_bag(root / 'bags' / 'r1' / 'run_0', TRUTH, 40.0, 100.0, seed=12,
                          gain_change=(20.0, 0.8))
    write_joint_state_bag(root / 'bags' / 'r2' / 'run_0', TRUTH, 40.0, 100.0, seed=13,
                          pause=(9.5, 20.5))
    return root / 'bags', write_params(root / 'params.yaml', window=5.0, update_period=2.5)


def test_spans_are_rows_pooled_per_robot_and_resumed(long_bags, client, tmp_path, monkeypatch):
    bags, params = long_bags
    results = tmp_path / 'results'
    summary = run_fleet([str(bags)], params, results, span=10.0, client=client)
    assert summary == {'bags': 3, 'spans': 12, 'computed': 12, 'skipped': 0, 'errors': 1,
                       'robots': 3, 'flagged': 0}
    table = pq.read_table(results / 'bags.parquet')
    assert table.column_names[:5] == ['robot', 'bag', 'span', 'start', 'end']
    rows = table.to_pylist()
    assert [(row['robot'], row['span']) for row in rows] == [
        (f'r{robot}', span) for robot in range(3) for span in range(4)]
    # r1's torque is 80 % of the command from 20 s: J = 0.05 / 0.8 in spans 2 and 3.
    j = [row['J'] for row in rows if row['robot'] == 'r1']
    assert j == pytest.approx([0.05, 0.05, 0.0625, 0.0625], rel=0.005)
    errors = [(row['robot'], row['span'], row['error']) for row in rows
              if row['status'] == 'error']
    assert errors == [('r2', 1, 'no messages of the input /joint_states (effort[0]) and the '
                       'output /joint_states (velocity[0]) in the selected span')]
    robots = {row['robot']: row for row in pq.read_table(results / 'robots.parquet').to_pylist()}
    assert [(row['bags'], row['estimates'], row['errors']) for row in robots.values()] == [
        (1, 4, 0), (1, 4, 0), (1, 3, 1)]
    # Pooled inverse-variance over the spans; r1's spans disagree, which the Birge ratio shows
    # as a std of about half the change instead of the spans' own 3e-5.
    assert robots['r0']['J'] == pytest.approx(0.05, rel=0.001) and robots['r0']['J_std'] < 1e-4
    assert 0.05 < robots['r1']['J'] < 0.0625 and robots['r1']['J_std'] > 0.002
    assert (results / 'fleet_J.png').exists()

    def opened(path):
        raise AssertionError(f'{path} opened on resume')

    monkeypatch.setattr('ctid_ros.cli.fleet.bag_time_range', opened)
    again = run_fleet([str(bags)], params, results, span=10.0, client=client, plots=False)
    assert (again['computed'], again['skipped']) == (0, 12)
    assert pq.read_table(results / 'bags.parquet').to_pylist() == rows
    monkeypatch.undo()
    # Whole bags and spans are kept apart: each kind is computed once and then reused.
    whole = run_fleet([str(bags)], params, results, client=client, plots=False)
    assert (whole['computed'], 'spans' in whole) == (3, False)
    assert 'span' not in pq.read_table(results / 'bags.parquet').column_names
    assert run_fleet([str(bags)], params, results, span=10.0, client=client,
                     plots=False)['computed'] == 0
    assert run_fleet([str(bags)], params, results, client=client, plots=False)['computed'] == 0
    # Other boundaries are other spans.
    assert run_fleet([str(bags)], params, results, span=20.0, client=client,
                     plots=False)['computed'] == 6


def test_spans_with_sliding_windows(long_bags, client, tmp_path):
    bags, params = long_bags
    results = tmp_path / 'results'
    run_fleet([str(bags / 'r1')], params, results, span=20.0, sliding=True, client=client,
              plots=False)
    spans = pq.read_table(results / 'bags.parquet').to_pylist()
    windows = pq.read_table(results / 'windows.parquet')
    ends = windows.column('end').cast(pa.int64()).to_pylist()
    assert [row['span'] for row in spans] == [0, 1]
    for row in spans:
        own = [(window, end) for window, end in zip(windows.to_pylist(), ends)
               if window['span'] == row['span']]
        assert len(own) == row['windows'] >= 4
        assert own[-1][0]['J'] == row['J']
        assert all(row['span_start_ns'] <= end < row['span_end_ns'] for _, end in own)
    # The last window of each span is on one side of the change at 20 s.
    assert [row['J'] for row in spans] == pytest.approx([0.05, 0.0625], rel=0.005)


@pytest.mark.parametrize('span, message', [
    ('0', '--span must be a positive number of seconds, got 0'),
    ('-5', '--span must be a positive number of seconds, got -5'),
    ('nan', '--span must be a positive number of seconds, got nan'),
    ('2', '--span 2 s is shorter than the window of '),
])
def test_a_bad_span_is_a_user_error(long_bags, tmp_path, capsys, span, message):
    bags, params = long_bags
    results = tmp_path / 'results'
    status = main(['fleet', str(bags), '--params-file', str(params), '--results', str(results),
                   '--span', span])
    assert status == 2
    assert f'ctid fleet: error: {message}' in capsys.readouterr().err
    assert not results.exists()


def test_the_command_with_spans(long_bags, tmp_path, capsys):
    bags, params = long_bags
    results = tmp_path / 'results'
    status = main(['fleet', str(bags / 'r0'), '--params-file', str(params), '--results',
                   str(results), '--span', '18', '--threads', '--workers', '2', '--no-plots'])
    assert status == 0
    assert 'ctid fleet: 1 bags in 2 spans: 2 analysed, 0 already done, 0 with errors' in \
        capsys.readouterr().out
    rows = pq.read_table(results / 'bags.parquet').to_pylist()
    # The bag's messages span 39.99 s: after two spans of 18 s, 3.99 s are left, less than the
    # 5 s window, so they are part of the second span.
    lengths = [(row['span_end_ns'] - row['span_start_ns']) / 1e9 for row in rows]
    assert lengths[0] == 18.0 and lengths[1] == pytest.approx(21.99, abs=0.001)
    assert rows[1]['J'] == pytest.approx(TRUTH['J'], rel=0.005)


def test_a_fleet_mixes_ros1_bags_with_rosbag2_and_mcap(client, tmp_path):
    from replay_fixtures import convert_to_rosbag2, DELAY, params_file, simulate, write_rosbag1

    u, y = simulate(DELAY, 20.0)
    bags = tmp_path / 'bags'
    bags.mkdir()
    ros1 = write_rosbag1(bags / 'old.bag', u, y)
    converted = convert_to_rosbag2(ros1, bags / 'converted')
    # The storage file of the conversion on its own: a standalone MCAP file.
    (bags / 'single.mcap').write_bytes((converted / 'converted.mcap').read_bytes())
    params = params_file(tmp_path, DELAY, input_topic='/plant/cmd', input_field='effort')
    summary = run_fleet([str(bags)], params, tmp_path / 'results', client=client, plots=False)
    assert summary['bags'] == 3 and summary['errors'] == 0
    rows = {row['bag']: row for row in pq.read_table(tmp_path / 'results' / 'bags.parquet')
            .to_pylist()}
    assert set(rows) == {'old.bag', 'converted', 'single.mcap'}
    for name in DELAY['truth']:
        assert rows['old.bag'][name] == pytest.approx(rows['converted'][name], rel=1e-9)
        assert rows['single.mcap'][name] == pytest.approx(rows['converted'][name], rel=1e-9)
        assert rows['old.bag'][name] == pytest.approx(DELAY['truth'][name], rel=0.03)


def test_a_byte_identical_copy_counts_once_and_a_cut_bag_says_so(tmp_path, capsys):
    import shutil

    from replay_fixtures import DELAY, params_file, simulate, write_rosbag1

    u, y = simulate(DELAY, 12.0)
    bags = tmp_path / 'bags'
    (bags / 'r0').mkdir(parents=True)
    (bags / 'r1').mkdir()
    original = write_rosbag1(bags / 'r0' / 'run.bag', u, y)
    shutil.copy(original, bags / 'r1' / 'run.bag')                 # the same recording
    content = original.read_bytes()
    # Same size, other bytes: a different recording, kept.
    (bags / 'r1' / 'other.bag').write_bytes(content.replace(b'prbs', b'PRBS'))
    directory = bags / 'r2' / 'run'
    shutil.copytree(_converted(original, tmp_path), directory)
    shutil.copytree(directory, bags / 'r2' / 'run_copy')
    cut = bags / 'r3' / 'cut.mcap'
    cut.parent.mkdir()
    cut.write_bytes((directory / 'run.mcap').read_bytes()[:2000])  # inside its first chunk
    nothing = bags / 'r3' / 'nothing.mcap'
    nothing.write_bytes((directory / 'run.mcap').read_bytes()[:60])  # inside its header
    params = params_file(tmp_path, DELAY, input_topic='/plant/cmd', input_field='effort')
    code = main(['fleet', str(bags), '--params-file', str(params), '--results',
                 str(tmp_path / 'results'), '--threads', '--workers', '1', '--no-plots'])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert f'{bags}/r1/run.bag is a byte-identical copy of {bags}/r0/run.bag' in captured.err
    assert f'{bags}/r2/run_copy is a byte-identical copy of {bags}/r2/run' in captured.err
    assert 'ctid fleet: 5 bags (2 copies counted once): 5 analysed' in captured.out
    rows = {row['bag']: row for row in pq.read_table(tmp_path / 'results' / 'bags.parquet')
            .to_pylist()}
    assert set(rows) == {'r0/run.bag', 'r1/other.bag', 'r2/run', 'r3/cut.mcap',
                         'r3/nothing.mcap'}
    # The messages before the cut are read, too few for an estimate: the row says both.
    assert rows['r3/cut.mcap']['status'] == 'error'
    assert re.search(r'is truncated or corrupted: the file ends in the middle of a chunk, of '
                     r'which \d+ messages are read up to the cut', rows['r3/cut.mcap']['error'])
    assert rows['r3/nothing.mcap']['status'] == 'error'
    assert 'is truncated or damaged, and nothing is readable' in \
        rows['r3/nothing.mcap']['error']


def _converted(bag, tmp_path):
    from replay_fixtures import convert_to_rosbag2

    return convert_to_rosbag2(bag, tmp_path / 'run')
