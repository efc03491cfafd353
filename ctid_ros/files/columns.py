"""
Samples of a bag read as columns: the fast path of ``ctid replay`` and ``ctid fleet``.

:func:`sample_columns` reads only the input and output topics of a bag, as blocks of
serialised messages (:meth:`~ctid_ros.files.bag_reader.BagReader.raw_blocks`: a chunk at a time
from MCAP, in the order the streaming reader yields them), decodes the configured fields and
``header.stamp`` of a whole block at once (:class:`~ctid_ros.files.cdr_columns.CdrColumns`),
applies the sampler's stamp rule to the arrays
(:func:`~ctid_ros.streaming.message_fields.sample_stamps`) and yields
:class:`~ctid_ros.streaming.replay.SampleColumns` for
:func:`~ctid_ros.streaming.replay.replay_columns`.

Messages the columnar decoder does not take (a type outside its layouts, damaged bytes, a
path that does not reach a number in them) go one by one through the streaming reader's own
decoder and :class:`~ctid_ros.streaming.sampler.MessageSampler`, in arrival order, so a wrong
field path raises the same :class:`~ctid_ros.errors.ConfigError` at the same message, a
message without the selected joint or index is skipped and counted as there
(:class:`~ctid_ros.streaming.sampler.FieldErrors`), and a damaged message ends the blocks
where the streaming reader stops, with the same :class:`~ctid_ros.errors.BagError`.
"""

from typing import Any, Dict, Iterator, List, Optional, Tuple

from ctid_ros.errors import BagError
from ctid_ros.files.bag_reader import BagReader
from ctid_ros.files.cdr_columns import CdrColumns
from ctid_ros.files.mcap_source import RawBlock, RawStream
from ctid_ros.streaming.buffer import INPUT, OUTPUT
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.message_fields import parse_field_path, sample_stamps
from ctid_ros.streaming.replay import SampleColumns
from ctid_ros.streaming.sampler import FieldErrors, MessageSampler
import numpy as np

__all__ = ['sample_columns']


class _Stream:
    """How the messages of one stream become samples."""

    def __init__(self, stream: RawStream, roles: Tuple[str, ...], inputs: int,
                 decoder: Optional[CdrColumns]):
        self.stream = stream
        self.roles = roles
        self.inputs = inputs
        self.decoder = decoder


def sample_columns(bag: BagReader, config: IdentificationConfig, topics: Tuple[str, str],
                   start_ns: Optional[int] = None, end_ns: Optional[int] = None
                   ) -> Iterator[SampleColumns]:
    """
    Yield the samples of the input and output topics of ``bag``, a block at a time.

    Parameters
    ----------
    bag : BagReader
        An open bag.
    config : IdentificationConfig
        Field paths and stamp source.
    topics : (str, str)
        The input and output topics as the bag spells them (the same topic for both is allowed).
    start_ns, end_ns : int, optional
        Log-time window ``start_ns <= t < end_ns``.

    Yields
    ------
    SampleColumns
        The samples of consecutive messages, in arrival order.

    Raises
    ------
    BagError
        For a topic that cannot be decoded (at once), or a damaged message or chunk (after the
        samples of every message before it were yielded).
    ConfigError
        At the first message whose field path does not lead to a number; after the last
        block if no message of a stream has the selected joint or index (messages without it
        are skipped and counted in :attr:`SampleColumns.field_errors`).

    """
    sampler = MessageSampler(config, topics)
    inputs = len(config.input_fields)
    paths = {INPUT: tuple(parse_field_path(path) for path in config.input_fields),
             OUTPUT: (parse_field_path(config.output_field),)}
    streams: Dict[int, _Stream] = {}
    raw_streams = bag.raw_streams(sorted(set(topics)))
    for key, stream in raw_streams.items():
        roles = sampler.roles(stream.topic)
        decoder = None
        if stream.fielddefs is not None:
            wanted = [path for role in roles for path in paths[role]]
            decoder = CdrColumns(stream.fielddefs, stream.msgtype, wanted,
                                 stamp=config.stamp_source == 'header')
            decoder = decoder if decoder.supported else None
        streams[key] = _Stream(stream, roles, inputs, decoder)
    errors = FieldErrors(sampler.names)
    for raw in bag.raw_blocks(raw_streams, start_ns=start_ns, end_ns=end_ns):
        for block in _samples(raw, streams, sampler, config.stamp_source):
            block.count_into(errors)
            yield block
    errors.check()


def _samples(raw: RawBlock, streams: Dict[int, _Stream], sampler: MessageSampler,
             stamp_source: str) -> Iterator[SampleColumns]:
    """Turn one block of messages into samples; see :func:`sample_columns`."""
    count = len(raw)
    stamps = np.zeros(count, dtype=np.int64)
    width = max(stream.inputs for stream in streams.values()) + 1
    values = np.zeros((count, width))
    roles = np.zeros((count, 2), dtype=bool)
    one_by_one: List[np.ndarray] = []
    unstamped: List[Tuple[Tuple[str, ...], np.ndarray]] = []
    errors = FieldErrors(sampler.names)
    for key, stream in streams.items():
        rows = np.flatnonzero(raw.topic == key)
        if not rows.size:
            continue
        for column, role in enumerate((INPUT, OUTPUT)):
            roles[rows, column] = role in stream.roles
        if stream.decoder is None:
            one_by_one.append(rows)
            continue
        decoded = stream.decoder.decode(raw.data, raw.starts[rows], raw.lengths[rows])
        stamps[rows] = sample_stamps(decoded.stamp_ns, raw.log_time_ns[rows], stamp_source)
        _place(values, rows, decoded.values, stream)
        one_by_one.append(rows[decoded.fallback])
        if stamp_source == 'header' and decoded.stamp_ns is not None:
            # Those the streaming decoder takes count theirs through the sampler.
            unstamped.append((stream.roles, rows[(decoded.stamp_ns == 0) & ~decoded.fallback]))
    rows = np.sort(np.concatenate(one_by_one)) if one_by_one else np.zeros(0, dtype=np.int64)
    stop = count
    damage: Optional[BagError] = None
    for row in rows.tolist():
        stream = streams[int(raw.topic[row])]
        log_time_ns = int(raw.log_time_ns[row])
        try:
            msg = stream.stream.decode(log_time_ns, raw.message(row))
        except BagError as error:
            stop, damage = row, error
            break
        sample = sampler(stream.stream.topic, log_time_ns, msg)
        errors.add(sample, stream.roles, stream.stream.msgtype)
        stamps[row] = sample.stamp_ns
        # A field the message lacks gives no sample; the message's other field still does.
        roles[row] &= (sample.u is not None, sample.y is not None)
        if INPUT in stream.roles and sample.u is not None:
            values[row, :stream.inputs] = sample.u
        if OUTPUT in stream.roles and sample.y is not None:
            values[row, -1] = sample.y
    errors.read.update(zip((INPUT, OUTPUT), roles[:stop].sum(axis=0).tolist()))
    for carried, rows in unstamped:
        for role in carried:
            errors.unstamped[role] += int(np.count_nonzero(rows < stop))
    if stop:
        yield _block(raw.log_time_ns[:stop], stamps[:stop], values[:stop], roles[:stop],
                     width - 1, errors)
    if damage is not None:
        raise damage


def _place(values: np.ndarray, rows: np.ndarray, decoded: np.ndarray, stream: _Stream) -> None:
    """Put decoded columns (the input paths, then the output path) in the block's table."""
    column = 0
    if INPUT in stream.roles:
        values[rows, :stream.inputs] = decoded[:, :stream.inputs]
        column = stream.inputs
    if OUTPUT in stream.roles:
        values[rows, -1] = decoded[:, column]


def _block(times: np.ndarray, stamps: np.ndarray, values: np.ndarray, roles: np.ndarray,
           inputs: int, errors: FieldErrors) -> SampleColumns:
    input_rows = np.flatnonzero(roles[:, 0])
    output_rows = np.flatnonzero(roles[:, 1])
    input_values: Any = values[input_rows, :inputs]
    if inputs == 1:
        input_values = input_values[:, 0]
    return SampleColumns(times, input_rows, stamps[input_rows], np.ascontiguousarray(
        input_values), output_rows, stamps[output_rows], values[output_rows, -1].copy(),
        errors)
