"""
A bag cut into time spans (``ctid fleet --span``): the cut, and each span estimated on its own.

Wheel-drive bags of test/fleet_fixtures.py (J = 0.05, b = 0.2, tau = 0.0373; 100 Hz, 60 s):
the spans follow one another over the whole bag, each span's estimate is that of the plant
which generated it, a drive whose torque drops to 80 % halfway through shows it in the spans
after the change, and a span in which nothing was recorded is an error row of its own.
"""

from pathlib import Path

from ctid_ros.files.fleet import (analyse_bag, bag_time_range, BagTask, IDENTITY, make_task,
                                  span_bounds, split_task)
from fleet_fixtures import TRUTH, write_joint_state_bag, write_params
import pytest
from replay_fixtures import (damage_chunk, DELAY, float_records, params_file, simulate,
                             T0_NS, write_mcap)

S = 10 ** 9
# Every span's J and b within this fraction of the truth, tau within TAU_TOLERANCE seconds:
# five to ten of the standard deviations a 15 s span's estimate reports at this noise (J about
# 3e-5, b 1e-4, tau 3e-5 s).
RELATIVE = 0.005
TAU_TOLERANCE = 0.0002


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp('spans')
    params = write_params(root / 'params.yaml', window=5.0, update_period=2.5)
    steady = write_joint_state_bag(root / 'steady', TRUTH, 60.0, 100.0, seed=3)
    weaker = write_joint_state_bag(root / 'weaker', TRUTH, 60.0, 100.0, seed=3,
                                   gain_change=(30.0, 0.8))
    paused = write_joint_state_bag(root / 'paused', TRUTH, 40.0, 100.0, seed=4,
                                   pause=(9.5, 20.5))
    return root, params.read_text(), steady, weaker, paused


def spans_of(root, params, bag, span):
    task = make_task(bag, root, None, params, 'ctid_node', False)
    time_range = bag_time_range(task.path)
    return time_range, [analyse_bag(piece).bag
                        for piece in split_task(task, time_range, span, 5.0)]


def assert_near(row, truth):
    assert row['status'] == 'ok', row['error']
    assert row['J'] == pytest.approx(truth['J'], rel=RELATIVE)
    assert row['b'] == pytest.approx(truth['b'], rel=RELATIVE)
    assert row['tau'] == pytest.approx(truth['tau'], abs=TAU_TOLERANCE)


def test_spans_follow_one_another_and_a_short_last_piece_is_merged():
    assert span_bounds(0, 60 * S - 1, 15.0, 5.0) == [
        (0, 15 * S), (15 * S, 30 * S), (30 * S, 45 * S), (45 * S, 60 * S)]
    # 2 s left after four spans: shorter than the 5 s window, so part of the fourth span.
    assert span_bounds(0, 62 * S - 1, 15.0, 5.0)[-1] == (45 * S, 62 * S)
    # 7 s left: long enough for an estimate, a span of its own.
    assert span_bounds(0, 67 * S - 1, 15.0, 5.0)[-2:] == [(45 * S, 60 * S), (60 * S, 67 * S)]
    # A bag shorter than one span is one span, whatever its length.
    assert span_bounds(7, 3 * S, 15.0, 5.0) == [(7, 3 * S + 1)]


def test_a_bag_without_time_range_is_one_task_that_reports_why(tmp_path):
    task = BagTask('/nowhere', 'nowhere', {'robot': 'r0'}, 0, 0, '', '')
    (whole,) = split_task(task, None, 15.0, 5.0)
    assert (whole.span, whole.span_start_ns, whole.span_end_ns) == (0, None, None)
    assert bag_time_range(str(tmp_path / 'missing')) is None
    row = analyse_bag(whole).bag
    assert row['span'] == 0 and row['status'] == 'error'


def test_each_span_estimates_the_plant_on_its_own_stretch(bags):
    root, params, steady, _, _ = bags
    (first, last), rows = spans_of(root, params, steady, 15.0)
    assert [row['span'] for row in rows] == [0, 1, 2, 3]
    assert rows[0]['span_start_ns'] == first and rows[-1]['span_end_ns'] == last + 1
    # The grid instants estimated on cover the bag: the sample stamps are k * 10 ms from T0,
    # logged 0.05 to 0.4 ms later; each span starts one sample after the one before ends.
    stamps = [(row['start'] - rows[0]['start'], row['end'] - rows[0]['start']) for row in rows]
    assert stamps == [(15 * k * S, (15 * k + 15) * S - S // 100) for k in range(4)]
    assert first - rows[0]['start'] < S // 2500 and last - rows[-1]['end'] < S // 2500
    for row in rows:
        assert_near(row, TRUTH)


def test_a_change_of_the_drive_shows_in_the_spans_after_it(bags):
    root, params, _, weaker, _ = bags
    _, rows = spans_of(root, params, weaker, 15.0)
    # From 30 s the torque is 0.8 times the command: J / 0.8 and b / 0.8 from the command.
    after = dict(TRUTH, J=TRUTH['J'] / 0.8, b=TRUTH['b'] / 0.8)
    for row, truth in zip(rows, [TRUTH, TRUTH, after, after]):
        assert_near(row, truth)


def test_a_span_without_messages_is_an_error_row_of_its_own(bags):
    root, params, _, _, paused = bags
    _, rows = spans_of(root, params, paused, 10.0)
    assert [row['status'] for row in rows] == ['ok', 'error', 'ok', 'ok']
    assert rows[1]['error'] == ('no messages of the input /joint_states (effort[0]) and the '
                                'output /joint_states (velocity[0]) in the selected span')
    assert rows[1]['span'] == 1 and rows[1]['start'] is None
    for row in rows[2:]:
        assert_near(row, TRUTH)


def test_the_key_holds_the_span_and_rows_of_whole_bags_read_as_before(bags):
    root, params, steady, _, _ = bags
    task = make_task(steady, root, None, params, 'ctid_node', False)
    pieces = split_task(task, bag_time_range(task.path), 15.0, 5.0)
    assert len({piece.key for piece in pieces}) == 4
    assert pieces[1].key == task.key[:5] + (1, pieces[1].span_start_ns, pieces[1].span_end_ns)
    # A row of a run without spans has no span columns: missing, they are the whole bag's key.
    row = analyse_bag(task).bag
    assert 'span' not in row and tuple(row.get(name) for name in IDENTITY) == task.key


def test_a_bag_with_a_damaged_chunk_is_estimated_on_the_messages_before_it(tmp_path):
    """
    As ``ctid replay`` does: the damage is a warning of the row, not an error row.

    The fleet lost such a bag ("chunk CRC mismatch: damaged") that the replay estimates.
    """
    u, y = simulate(DELAY, 40.0)
    path = write_mcap(tmp_path / 'run.mcap', float_records(u, y))
    index = damage_chunk(path, 0.8)
    params = params_file(tmp_path, DELAY).read_text()
    row = analyse_bag(make_task(path, tmp_path, None, params, 'ctid_node', False)).bag
    assert row['status'] == 'ok', row['error']
    assert f'{path} is corrupted at byte {index.chunk_start_offset} and cannot be read ' \
        'further' in row['warnings']
    assert 'estimating from the messages before it' in row['warnings']
    # The data end before the damaged chunk, which starts at about 80 % of the 40 s.
    assert 25 * S < row['end'] - T0_NS <= index.message_start_time - T0_NS
    for name in ('K', 'T', 'tau'):
        assert row[name] == pytest.approx(DELAY['truth'][name], rel=0.01)


@pytest.mark.parametrize('name', ['service_events_sqlite3', 'service_events_mcap'])
def test_a_topic_that_cannot_be_read_is_said_as_such_not_as_damage(tmp_path, name):
    # rosbag2's own bags: a service-event topic as the output. Read like a damaged chunk, the
    # row said "no messages of the input ... in the selected span" first.
    bag = Path(__file__).parents[1] / 'data' / 'bags' / name
    params = params_file(tmp_path, DELAY, input_topic='/test_topic1',
                         input_field='int32_value', output_topic='/test_service1/_service_event',
                         output_field='info.event_type').read_text()
    row = analyse_bag(make_task(bag, bag.parent, None, params, 'ctid_node', False)).bag
    assert row['status'] == 'error'
    where, _, reason = row['error'].partition(': ')
    assert where.startswith(str(bag)), row['error']
    assert reason.startswith('/test_service1/_service_event carries service events'), \
        row['error']
