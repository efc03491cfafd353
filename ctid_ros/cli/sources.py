"""
The record of ``ctid compare`` and ``ctid tune``: a CSV file, or a bag read with a params file.

A CSV file is read as ``ctid fit`` reads it (columns, ``--ts``, ``--time``, ranges, detrend).
A rosbag2 directory or ``.mcap`` file needs ``--params-file``: its input and output topics,
fields, stamps and sample time say what the samples are, as for ``ctid replay`` (the model of
the params file is not used: the command names its own). The samples of the span are resampled
on the grid exactly as the live node would (:func:`~ctid_ros.streaming.buffer.resample`).
"""

import argparse
from pathlib import Path
import sys
from typing import List, Optional, Sequence

from ctid_ros.cli.fit import select_samples, signals
from ctid_ros.core.data import Data
from ctid_ros.core.model import Model
from ctid_ros.errors import ConfigError, DataError
from ctid_ros.files.csv_file import load_csv, TIME_COLUMNS
import numpy as np

__all__ = ['is_bag', 'load_record', 'model_signals', 'models', 'plot_path']

_BAG_SUFFIXES = ('.mcap', '.db3')


def is_bag(path: str) -> bool:
    """Return True for a rosbag2 directory or a ``.mcap``/``.db3`` file."""
    item = Path(path)
    return item.is_dir() or item.suffix.lower() in _BAG_SUFFIXES


def plot_path(record: str, command: str, directory: Optional[Path] = None) -> Path:
    """Return where ``--plot`` without a value writes: ``<record name>_<command>.png``."""
    name = Path(record).resolve().name
    for suffix in ('.gz', '.csv', '.mcap'):
        name = name[:-len(suffix)] if name.endswith(suffix) else name
    return (directory or Path.cwd()) / f'{name or "record"}_{command}.png'


def _bag_data(arguments: argparse.Namespace) -> Data:
    """Return the samples of the bag's configured topics over ``--start``/``--end``."""
    from ctid_ros.files.bag_reader import open_bag
    from ctid_ros.files.columns import sample_columns
    from ctid_ros.streaming.buffer import resample
    from ctid_ros.streaming.contract import resolve_topic
    from ctid_ros.streaming.params_file import load_params_file
    from ctid_ros.streaming.sampler import FieldErrors, stream_names

    if arguments.params_file is None:
        raise ConfigError(f'{arguments.path} is a bag: give --params-file (its input and output '
                          'topics, fields and sample time say what the samples are)')
    config = load_params_file(arguments.params_file, arguments.node_name)
    topics = (resolve_topic(config.input_topic, arguments.node_name),
              resolve_topic(config.output_topic, arguments.node_name))
    with open_bag(arguments.path) as bag:
        for warning in bag.warnings:
            print(f'ctid: warning: {warning}', file=sys.stderr)
        topics = tuple(bag.topic_name(topic) or topic for topic in topics)
        start_ns, end_ns = bag.time_range_ns(arguments.start, arguments.end)
        blocks = list(sample_columns(bag, config, topics, start_ns, end_ns))
    # Messages skipped (no such joint), ignored (a type without the field) or unstamped, as the
    # live node and ctid replay report them.
    skipped = FieldErrors(stream_names(config, topics))
    for block in blocks:
        block.count_into(skipped)
    for warning in skipped.warnings():
        print(f'ctid: warning: {warning}', file=sys.stderr)
    inputs = len(config.input_fields)
    pieces = {name: [getattr(block, name) for block in blocks] for name in
              ('input_stamps', 'input_values', 'output_stamps', 'output_values')}
    if not sum(item.size for item in pieces['input_stamps']) or \
            not sum(item.size for item in pieces['output_stamps']):
        raise DataError(f'no samples of {topics[0]} and {topics[1]} in the selected span of '
                        f'{arguments.path}')
    window, _ = resample(np.concatenate(pieces['input_stamps']),
                         np.concatenate(pieces['input_values']).reshape(
                             (-1, inputs) if inputs > 1 else (-1,)),
                         np.concatenate(pieces['output_stamps']),
                         np.concatenate(pieces['output_values']), config.sample_time,
                         max_gap=config.max_gap, reorder_horizon=config.reorder_horizon,
                         names=stream_names(config, topics))
    for warning in window.warnings:
        print(f'ctid: warning: {warning}', file=sys.stderr)
    return window.data


def load_record(arguments: argparse.Namespace, equation: bool = False) -> Data:
    """
    Return the estimation data of the command line: a CSV file's columns or a bag's topics.

    ``arguments``: ``path``, ``input``, ``output``, ``time``, ``ts``, ``estimate_range``,
    ``detrend`` (CSV) and ``params_file``, ``node_name``, ``start``, ``end`` (bag).
    ``equation``: a model equation names its signals after the columns.
    """
    if is_bag(arguments.path):
        data = _bag_data(arguments)
    else:
        columns = signals(arguments.input, arguments.output, equation)
        times = TIME_COLUMNS if arguments.time is None else arguments.time
        data = load_csv(arguments.path, input_column=columns.input_columns,
                        output_column=columns.output_column, time_column=times,
                        ts=arguments.ts)
    return select_samples(data, arguments.estimate_range, arguments.detrend, 'estimation')


def model_signals(models: Sequence[str]) -> bool:
    """Return True if any model is an equation (names its signals after the columns)."""
    return any('=' in text for text in models)


def models(arguments: argparse.Namespace, texts: Sequence[str]) -> List[Model]:
    """
    Return the models of ``texts`` with the signal names of the record.

    A CSV record names its signals after ``--input``/``--output`` (as ``ctid fit``); a bag's
    are ``u`` (``u1``, ``u2``, ... for several input fields) and ``y``.
    """
    equation = model_signals(texts)
    if is_bag(arguments.path):
        return [Model(text) for text in texts]
    columns = signals(arguments.input, arguments.output, equation)
    return [Model(text, inputs=columns.input_names, output=columns.output_name)
            for text in texts]
