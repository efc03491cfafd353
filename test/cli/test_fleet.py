"""
``ctid fleet`` on a small synthetic fleet, with Dask in this process (and once with processes).

Three robots, one with a 20 % heavier payload, two bags each, a corrupt bag and a bag missing
the topic (test/fleet_fixtures.py): the heavy robot is flagged, the bad bags are rows with
their errors, a second run skips every finished bag, and the bag rows equal a direct columnar
replay of each bag.
"""

from pathlib import Path

from ctid_ros.cli.fleet import run_fleet
from ctid_ros.cli.fleet_report import combine, flag_robots
from ctid_ros.cli.main import main
from ctid_ros.errors import CtidError
from ctid_ros.files.fleet import analyse_bag, find_bags, make_task, robot_fields
from distributed import Client, LocalCluster
from fleet_fixtures import write_fleet, write_params
import numpy as np
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
