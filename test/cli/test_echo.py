"""``ctid echo``: rows put together from the node's messages, as a table or JSON lines."""

import json
import math

from ctid_ros.cli.echo import format_row, header, Row, row_json, RowAssembler, STATUS_WAIT
from ctid_ros.ros.echo import Estimates, Status
from ctid_ros.streaming.contract import OK, WARN

NAMES = ('K', 'T')
FIT = {'fit_percent': '95.5', 'window_end': '1700000012.5', 'iterations': '3'}


def estimate(values=(2.0, 0.5)):
    return Estimates('estimate', NAMES, values)


def std(values=(0.01, 0.002)):
    return Estimates('std', NAMES, values)


def test_an_update_is_one_row_with_its_fit_and_window_end():
    rows = RowAssembler()
    assert rows.add(estimate(), 0.0) == [] and rows.add(std(), 0.0) == []
    (row,) = rows.add(Status(OK, 'K=2 (std 0.01), T=0.5 (std 0.002)', FIT, 1700000012.6), 0.01)
    assert row == Row(1700000012.5, NAMES, (2.0, 0.5), (0.01, 0.002), 95.5, OK,
                      'K=2 (std 0.01), T=0.5 (std 0.002)')
    assert rows.expired(10.0) == []


def test_a_latched_estimate_without_its_status_is_released_after_the_wait():
    rows = RowAssembler()
    rows.add(estimate(), 0.0)
    rows.add(std(), 0.0)
    assert rows.expired(STATUS_WAIT / 2) == []
    (row,) = rows.expired(STATUS_WAIT)
    assert (row.time, row.values, row.stds, row.fit, row.level) == (
        None, (2.0, 0.5), (0.01, 0.002), None, None)
    # The status of an update whose estimate was missed adds no row.
    assert rows.add(Status(OK, 'x', FIT, 1.0), 1.0) == []


def test_a_status_alone_is_a_row_and_a_new_estimate_releases_the_held_one():
    rows = RowAssembler()
    (row,) = rows.add(Status(WARN, 'warming up: 6.4 of 10 s of data', {}, 1700000001.0), 0.0)
    assert (row.names, row.time, row.level) == ((), 1700000001.0, WARN)
    rows.add(estimate(), 0.0)
    (held,) = rows.add(estimate((2.1, 0.6)), 0.1)
    assert held.values == (2.0, 0.5) and all(math.isnan(value) for value in held.stds)


def test_table_and_json_lines():
    row = Row(1700000012.5, NAMES, (2.0, 0.5), (0.01, float('nan')), 95.5, WARN,
              'x' * 100)
    titles = header(NAMES).split()
    assert titles == ['window', 'end', 'K', 'T', 'fit', '%', 'status']
    line = format_row(row, NAMES)
    assert '2 ± 0.01' in line and '95.50' in line and line.endswith('WARN: ' + 'x' * 77 + '...')
    alone = format_row(Row(None, (), (), (), None, OK, 'fine'), NAMES)
    assert alone.split() == ['-', '(no', 'estimate)', '-', 'OK']
    record = json.loads(row_json(row, '/ctid_node'))
    assert record == {'node': '/ctid_node', 'time': 1700000012.5,
                      'params': {'K': 2.0, 'T': 0.5}, 'std': {'K': 0.01, 'T': None},
                      'fit': 95.5, 'level': 'WARN', 'status': 'x' * 100}
