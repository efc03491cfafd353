"""
Resource limits of ctid_ros, and the bounded reading of user files.

Every limit here is stated in the README (section Limits) with the error a user gets beyond
it. They bound what one estimate, one params file, one CSV file or one MCAP chunk may cost, so
that a hostile or broken input is refused quickly with a clear error instead of exhausting
memory or time. Files are never modified: they are opened read-only, and only regular files
and pipes are read (a device such as ``/dev/zero`` never ends).
"""

import os
from pathlib import Path
import stat
from typing import Optional, Type

from ctid_ros.errors import CtidError, ModelError

__all__ = [
    'MAX_BLANK_LINES', 'MAX_CHUNK_BYTES', 'MAX_COMPRESSION_RATIO', 'MAX_CSV_BYTES',
    'MAX_LINE_BYTES', 'MAX_METADATA_BYTES', 'MAX_MODEL_TEXT', 'MAX_PARAMS_BYTES', 'MAX_SAMPLES',
    'MAX_YAML_DEPTH', 'MAX_YAML_NODES', 'MIB', 'MIN_SAMPLE_TIME', 'check_model_text_length',
    'check_readable', 'read_limited', 'size_text',
]

MIB = 1 << 20
# Samples in one estimate (the record, or a window plus its transient). An estimate of a
# first-order model with a dead time on 1e6 samples takes about 3 s and 0.6 GB.
MAX_SAMPLES = 1_000_000
# Shortest sample time (s): stamps are integer nanoseconds, a grid finer than 1 us is no grid.
MIN_SAMPLE_TIME = 1e-6
# A CSV file, or what a .gz file decompresses to.
MAX_CSV_BYTES = 256 * MIB
# One line of a CSV file.
MAX_LINE_BYTES = MIB
# Blank lines in a CSV file (a file of newlines is not a record).
MAX_BLANK_LINES = 10_000
# A ROS 2 params file (the examples are 2-3 KB; YAML is parsed at about 0.25 MiB/s).
MAX_PARAMS_BYTES = 256 << 10
# Nesting of YAML collections in a params file.
MAX_YAML_DEPTH = 32
# YAML nodes of a params file counted with every alias expanded (a "billion laughs" has 1e9).
MAX_YAML_NODES = 20_000
# A rosbag2 metadata.yaml (about 1 KB per topic and 0.2 KB per file).
MAX_METADATA_BYTES = 4 * MIB
# Uncompressed size of one MCAP chunk (writers use 1-4 MB; a chunk holds whole messages).
MAX_CHUNK_BYTES = 256 * MIB
# Uncompressed over compressed size of a chunk above 1 MiB (real data: 2-50).
MAX_COMPRESSION_RATIO = 1000
# Characters of one model or controller text (the model language's first limit, checked here
# without sympy: a text refused for its length costs no import).
MAX_MODEL_TEXT = 2000


def check_model_text_length(text: object) -> None:
    """Raise :class:`~ctid_ros.errors.ModelError` for a text over :data:`MAX_MODEL_TEXT`."""
    if isinstance(text, str) and len(text) > MAX_MODEL_TEXT:
        raise ModelError(f'model expression is {len(text)} characters long; the limit is '
                         f'{MAX_MODEL_TEXT}')


def size_text(count: int) -> str:
    """Return a byte count for a message: ``'1.5 MiB'``, ``'310 bytes'``."""
    for unit, scale in (('GiB', 1 << 30), ('MiB', MIB), ('KiB', 1 << 10)):
        if count >= scale:
            return f'{count / scale:.3g} {unit}'
    return f'{count} bytes'


def check_readable(path: Path, limit: int, what: str, error: Type[CtidError]) -> Optional[int]:
    """
    Check that ``path`` is a regular file of at most ``limit`` bytes, or a pipe.

    Returns
    -------
    int or None
        The size of a regular file; None for a pipe (``<(zcat run.csv.gz)``), whose reader must
        stop at ``limit`` bytes itself.

    Raises
    ------
    error
        If the path does not exist, is a directory, a device (``/dev/zero`` never ends) or a
        socket, cannot be inspected, or is larger than ``limit``.

    """
    try:
        info = os.stat(path)
    except (OSError, ValueError) as problem:
        reason = getattr(problem, 'strerror', None) or problem
        raise error(f'cannot read {what} {path}: {reason}') from None
    if stat.S_ISDIR(info.st_mode):
        raise error(f'{what} {path} is a directory, not a file')
    if stat.S_ISFIFO(info.st_mode):
        return None
    if not stat.S_ISREG(info.st_mode):
        raise error(f'{what} {path} is not a regular file (a device or socket); give a file')
    if info.st_size > limit:
        raise error(f'{what} {path} is {size_text(info.st_size)}, more than the limit of '
                    f'{size_text(limit)}')
    return info.st_size


def read_limited(path: Path, limit: int, what: str, error: Type[CtidError]) -> bytes:
    """
    Return the bytes of a file checked by :func:`check_readable`, at most ``limit`` of them.

    Raises
    ------
    error
        As :func:`check_readable`, or if the file cannot be read or grows beyond ``limit``
        while it is read (a pipe, a file being written).

    """
    check_readable(path, limit, what, error)
    try:
        with open(path, 'rb') as stream:
            content = stream.read(limit + 1)
    except OSError as problem:
        raise error(f'cannot read {what} {path}: {problem.strerror or problem}') from None
    if len(content) > limit:
        raise error(f'{what} {path} is more than the limit of {size_text(limit)}')
    return content
