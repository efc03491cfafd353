"""
``ctid fleet``: estimate on every bag of a fleet, each bag a task on Dask distributed.

``ctid fleet PATH_OR_GLOB... --params-file P --results DIR`` finds the bags
(:func:`~ctid_ros.files.fleet.find_bags`), names each one's robot from ``--robot-from`` (a path
pattern relative to the bags' common root, e.g. ``'{robot}/{date}/*.mcap'``), and runs
:func:`~ctid_ros.files.fleet.analyse_bag` on each as a task of a Dask ``LocalCluster``
(``--workers N``, one single-threaded worker process each) or of an existing cluster
(``--scheduler tcp://HOST:8786``). Results land in DIR as Parquet:

* ``bags.parquet``: one row per bag (estimate over the whole bag; with ``--sliding`` the last
  window's), ``status`` ``'ok'`` or ``'error'`` with the reason: a bag that fails is a row;
  with ``--span SECONDS`` one row per span of each bag (column ``span``, from 0), each span a
  task of its own (:func:`~ctid_ros.files.fleet.span_bounds` says how a bag is cut);
* ``windows.parquet`` (``--sliding``): one row per window;
* ``robots.parquet`` and ``robots.csv``: one row per robot, flagged where it differs from the
  fleet (:mod:`ctid_ros.cli.fleet_report`), and one PNG per parameter.

Each finished bag or span is written at once (``DIR/parts/``), so a run that stops loses
nothing: the next run skips every bag or span whose result is there for the same path, size,
modification time, params file, mode and span boundaries (``--rerun`` recomputes them).
Results of runs without ``--span`` (of this version or an earlier one) are reused by runs
without it; a run with ``--span`` computes its spans, and a run with another ``--span`` computes
them again (the boundaries differ). A bag's first and last log time, which place its spans, are
kept in ``DIR/parts/`` too, so a resumed run does not open its bags.
"""

import argparse
import hashlib
import json
import math
import os
from pathlib import Path
import sys
from typing import Any, Dict, List, Optional, Sequence, Tuple

from ctid_ros.cli.fleet_report import flag_robots, write_figures, write_robot_tables
from ctid_ros.errors import ConfigError, CtidError
from ctid_ros.files.fleet import (analyse_bag, bag_row_columns, bag_time_range, BagResult,
                                  BagTask, distinct_bags, find_bags, IDENTITY, load_params_text,
                                  make_task, split_task)
from ctid_ros.streaming.contract import DEFAULT_NODE_NAME
import pyarrow as pa
import pyarrow.parquet as pq
from tqdm import tqdm

__all__ = ['run', 'run_fleet']

PARTS = 'parts'


def run(arguments: argparse.Namespace) -> int:
    """Run ``ctid fleet``; user errors raise :class:`~ctid_ros.errors.CtidError`."""
    if arguments.workers is not None and arguments.workers < 1:
        raise ConfigError(f'--workers must be at least 1, got {arguments.workers}')
    summary = run_fleet(arguments.paths, Path(arguments.params_file), arguments.results,
                        node_name=arguments.node_name, robot_from=arguments.robot_from,
                        sliding=arguments.sliding, workers=arguments.workers,
                        scheduler=arguments.scheduler, processes=not arguments.threads,
                        rerun=arguments.rerun, plots=not arguments.no_plots,
                        span=arguments.span)
    spans = f' in {summary["spans"]} spans' if 'spans' in summary else ''
    spans += f' ({summary["copies"]} copies counted once)' if 'copies' in summary else ''
    print(f'ctid fleet: {summary["bags"]} bags{spans}: {summary["computed"]} analysed, '
          f'{summary["skipped"]} already done, {summary["errors"]} with errors; '
          f'{summary["flagged"]} of {summary["robots"]} robots flagged; results in '
          f'{arguments.results}')
    return 0


def run_fleet(paths: Sequence[str], params_file: Path, results: Path, *,
              node_name: str = DEFAULT_NODE_NAME, robot_from: Optional[str] = None,
              sliding: bool = False, workers: Optional[int] = None,
              scheduler: Optional[str] = None, processes: bool = True, rerun: bool = False,
              plots: bool = True, client: Any = None, span: Optional[float] = None
              ) -> Dict[str, int]:
    """
    Analyse every bag (or every ``span`` seconds of each) on Dask, write results and report.

    ``client`` (a ``distributed.Client``) is used as it is when given; otherwise a
    ``LocalCluster`` of ``workers`` processes (threads in this process unless ``processes``)
    is started, or ``scheduler`` is connected to, and closed at the end. Returns the counts
    ``bags``, ``computed`` and ``skipped`` (tasks: bags, or spans), ``errors`` (error rows),
    ``robots``, ``flagged``, with ``span`` the number of ``spans``, and where bags were
    byte-identical copies of others (counted once: :func:`~ctid_ros.files.fleet.distinct_bags`)
    the number of ``copies``.

    Raises
    ------
    ConfigError
        For an unreadable params file or results directory, or a ``span`` that is not a
        positive number of seconds at least as long as the params file's ``window``.

    """
    try:
        params = params_file.read_text(encoding='utf-8')
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(f'cannot read params file {params_file}: {error}') from None
    config = load_params_text(params, node_name, str(params_file))
    if span is not None:
        _check_span(span, config.window, params_file)
    root, found = find_bags(paths)
    bags, copies = distinct_bags(found)
    for copy, original in copies:
        print(f'ctid fleet: {copy} is a byte-identical copy of {original}: counted once',
              file=sys.stderr)
    tasks = [make_task(bag, root, robot_from, params, node_name, sliding) for bag in bags]
    try:
        results.mkdir(parents=True, exist_ok=True)
        (results / PARTS).mkdir(exist_ok=True)
    except OSError as error:
        raise ConfigError(f'--results {results}: {error.strerror or error}') from None
    if span is not None:
        tasks = [piece for task in tasks
                 for piece in split_task(task, _time_range(results, task), span, config.window)]
    todo = tasks if rerun else [task for task in tasks if not _done(results, task)]
    if todo:
        _compute(todo, results, client, workers, scheduler, processes)
    bag_rows, window_rows = _collect(results, tasks)
    names = list(config.names)
    _write(results / 'bags.parquet', bag_rows, names)
    if sliding:
        _write(results / 'windows.parquet', window_rows, names)
    robots = flag_robots(bag_rows, names)
    write_robot_tables(results, robots, names)
    if plots:
        write_figures(results, bag_rows, robots, names)
    summary = {'bags': len(bags), 'computed': len(todo), 'skipped': len(tasks) - len(todo),
               'errors': sum(row['status'] != 'ok' for row in bag_rows),
               'robots': len(robots), 'flagged': sum(bool(row['flagged']) for row in robots)}
    if span is not None:
        summary['spans'] = len(tasks)
    if copies:
        summary['copies'] = len(copies)
    return summary


def _check_span(span: float, window: float, params_file: Path) -> None:
    if not (math.isfinite(span) and span > 0):
        raise ConfigError(f'--span must be a positive number of seconds, got {span:g}')
    if span < window:
        raise ConfigError(f'--span {span:g} s is shorter than the window of {params_file} '
                          f'({window:g} s, the data one estimate uses): give --span {window:g} '
                          'or more, or a shorter window')


def _digest(task: BagTask) -> str:
    return hashlib.sha1(task.path.encode()).hexdigest()[:20]


def _part(results: Path, task: BagTask, kind: str) -> Path:
    span = '' if task.span is None else f'.span{task.span}'
    return results / PARTS / f'{_digest(task)}{span}.{kind}.parquet'


def _done(results: Path, task: BagTask) -> bool:
    """Tell whether the stored result of this bag or span is for the same task (its key)."""
    part = _part(results, task, 'bag')
    if not part.exists():
        return False
    try:
        row = pq.read_table(part).to_pylist()[0]
    except Exception:   # a part cut short by a crash: compute it again
        return False
    return tuple(row.get(name) for name in IDENTITY) == task.key


def _time_range(results: Path, task: BagTask) -> Optional[Tuple[int, int]]:
    """Return the bag's first and last log time, from ``parts/`` if known for this file."""
    path = results / PARTS / f'{_digest(task)}.range.json'
    signature = [task.path, task.size, task.mtime_ns]
    try:
        stored = json.loads(path.read_text(encoding='utf-8'))
        if stored['bag'] == signature:
            return stored['start_ns'], stored['end_ns']
    except (OSError, ValueError, KeyError, TypeError):
        pass    # not known yet (or a file cut short): the bag is opened
    found = bag_time_range(task.path)
    if found is not None:
        temporary = path.with_suffix('.tmp')
        temporary.write_text(json.dumps({'bag': signature, 'start_ns': found[0],
                                         'end_ns': found[1]}), encoding='utf-8')
        os.replace(temporary, path)
    return found


def _compute(tasks: List[BagTask], results: Path, client: Any, workers: Optional[int],
             scheduler: Optional[str], processes: bool) -> None:
    from distributed import as_completed, Client, LocalCluster

    own: List[Any] = []
    if client is None:
        if scheduler is not None:
            try:
                client = Client(scheduler, timeout='20s')
            except (OSError, TimeoutError) as error:
                raise CtidError(f'--scheduler {scheduler}: cannot connect: {error}') from None
        else:
            count = workers or os.cpu_count() or 1
            cluster = LocalCluster(n_workers=count, threads_per_worker=1, processes=processes,
                                   dashboard_address=':0')
            client = Client(cluster)
            own.append(cluster)
        own.insert(0, client)
    try:
        # Largest bags first, so the last tasks are short and the workers finish together.
        ordered = sorted(tasks, key=lambda task: -task.size)
        futures = client.map(analyse_bag, ordered, pure=False)
        by_key = {future.key: task for future, task in zip(futures, ordered)}
        unit = 'bag' if ordered[0].span is None else 'span'
        with tqdm(total=len(futures), desc=f'{unit}s', unit=unit, file=sys.stderr,
                  disable=None) as bar:
            for future in as_completed(futures):
                _store(results, by_key[future.key], future.result())
                future.release()
                bar.update(1)
    finally:
        for item in own:
            item.close()


def _store(results: Path, task: BagTask, result: BagResult) -> None:
    """Write one task's rows at once (windows first: the bag part marks it done)."""
    windows = _part(results, task, 'windows')
    if result.windows:
        _write_table(windows, result.windows)
    elif windows.exists():
        windows.unlink()
    _write_table(_part(results, task, 'bag'), [result.bag])


def _write_table(path: Path, rows: List[Dict[str, Any]]) -> None:
    temporary = path.with_suffix('.tmp')
    pq.write_table(_table(rows, None), temporary)
    os.replace(temporary, path)


def _collect(results: Path, tasks: List[BagTask]) -> Tuple[List[Dict[str, Any]],
                                                           List[Dict[str, Any]]]:
    """Read the stored rows of this run's bags and spans, in the order of the tasks."""
    bags, windows = [], []
    for task in tasks:
        part = _part(results, task, 'bag')
        if not part.exists():
            continue
        bags.extend(_rows(pq.read_table(part)))
        part = _part(results, task, 'windows')
        if part.exists():
            windows.extend(_rows(pq.read_table(part)))
    return bags, windows


def _rows(table: pa.Table) -> List[Dict[str, Any]]:
    """Return a table's rows with its times as integer nanoseconds."""
    for name in ('start', 'end'):
        if name in table.column_names:
            index = table.column_names.index(name)
            table = table.set_column(index, name, table.column(name).cast(pa.int64()))
    return table.to_pylist()


def _table(rows: List[Dict[str, Any]], names: Optional[Sequence[str]]) -> pa.Table:
    """Build a table with the documented columns first; ``start``/``end`` as UTC times."""
    spans = any('span' in row for row in rows)
    columns: List[str] = bag_row_columns(names, spans) if names is not None else []
    for row in rows:
        columns.extend(key for key in row if key not in columns)
    data: Dict[str, Any] = {}
    for column in columns:
        values = [row.get(column) for row in rows]
        if column in ('start', 'end'):
            data[column] = pa.array(values, type=pa.int64()).cast(pa.timestamp('ns', tz='UTC'))
        elif column in ('status', 'error', 'robot', 'bag') or any(
                isinstance(value, str) for value in values):
            data[column] = pa.array([None if value is None else str(value) for value in values],
                                    type=pa.string())
        elif all(value is None or isinstance(value, bool) for value in values) and any(
                isinstance(value, bool) for value in values):
            data[column] = pa.array(values, type=pa.bool_())
        elif column in ('size', 'mtime_ns', 'windows', 'span', 'span_start_ns',
                        'span_end_ns'):
            data[column] = pa.array(values, type=pa.int64())
        else:
            data[column] = pa.array([None if value is None else float(value)
                                     for value in values], type=pa.float64())
    return pa.table(data)


def _write(path: Path, rows: List[Dict[str, Any]], names: Sequence[str]) -> None:
    temporary = path.with_suffix('.tmp')
    pq.write_table(_table(rows, names), temporary)
    os.replace(temporary, path)
