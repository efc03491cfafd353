"""
The work of ``ctid fleet``: many bags, each one task (or one per time span), results as rows.

:func:`find_bags` expands paths and globs into bags (rosbag2 directories, ``.mcap``, ``.db3``
and ROS 1 ``.bag`` files) and names each bag's robot from a path pattern (:func:`robot_fields`);
:func:`analyse_bag` replays one bag, or one span of its log time, through the columnar path
(:func:`~ctid_ros.files.columns.sample_columns`,
:func:`~ctid_ros.streaming.replay.replay_columns`) and returns its rows, an error row if
anything fails (a broken bag or span never ends a run). It is a plain function of picklable
arguments, so a Dask worker (``ctid fleet``) or any other executor can run it.

``ctid fleet --span SECONDS`` cuts each bag into consecutive spans of log time
(:func:`bag_time_range` reads the bag's first and last log time from its metadata or summary,
:func:`span_bounds` cuts, :func:`split_task` makes one task per span), so that the workers share
a long bag and its rows trace the parameters through it.

A task is identified by the bag's path, size and modification time, the params file's content,
the mode and the span's boundaries (:data:`IDENTITY`, :attr:`BagTask.key`): a result with the
same key is not computed again.
"""

from dataclasses import dataclass, field, replace
import glob
import hashlib
import os
from pathlib import Path
import re
from typing import Any, Dict, List, Optional, Sequence, Tuple

from ctid_ros.errors import CtidError
from ctid_ros.files.bag_reader import open_bag, readable_part
from ctid_ros.files.columns import sample_columns
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import NANOSECONDS, resolve_topic
from ctid_ros.streaming.params_file import node_parameters, parse_yaml
from ctid_ros.streaming.replay import replay_columns
from ctid_ros.streaming.session import Update

__all__ = ['IDENTITY', 'BagResult', 'BagTask', 'analyse_bag', 'bag_row_columns',
           'bag_time_range', 'distinct_bags', 'find_bags', 'load_params_text', 'make_task',
           'robot_fields', 'span_bounds', 'split_task']

_BAG_SUFFIXES = ('.mcap', '.db3', '.bag')
# Characters of an error message kept in a result row.
_ERROR_LIMIT = 500
# Bytes read at a time to hash a bag.
_HASH_PIECE = 1 << 20
# The columns of a result row that identify its task (see BagTask.key); the span columns are
# only written with --span, and a row without them (a run without spans, or of an earlier
# version) reads them as None, which is the key of a task without spans.
IDENTITY = ('path', 'size', 'mtime_ns', 'params_sha256', 'sliding', 'span', 'span_start_ns',
            'span_end_ns')


@dataclass(frozen=True)
class BagTask:
    """
    One bag to analyse, with what identifies its result.

    Attributes
    ----------
    path : str
        The bag (absolute).
    name : str
        The bag's path relative to the common root of the run.
    fields : dict
        What the robot pattern captured from ``name`` (``robot``, and e.g. ``date``).
    size, mtime_ns : int
        Size in bytes (of every file, for a directory) and newest modification time.
    params : str
        The params file's content (parsed on the worker).
    params_sha256 : str
        Its hash, part of the key.
    node_name : str
        Node section of the params file.
    sliding : bool
        One row per window as well (``windows.parquet``).
    span : int or None
        Index of the time span of the bag (from 0), None for the whole bag.
    span_start_ns, span_end_ns : int or None
        The span's log times, ``span_start_ns <= t < span_end_ns`` (None: that side open).

    """

    path: str
    name: str
    fields: Dict[str, str]
    size: int
    mtime_ns: int
    params: str
    params_sha256: str
    node_name: str = 'ctid_node'
    sliding: bool = False
    span: Optional[int] = None
    span_start_ns: Optional[int] = None
    span_end_ns: Optional[int] = None

    @property
    def key(self) -> Tuple[Any, ...]:
        """Return what makes a stored result this task's: the values of :data:`IDENTITY`."""
        return tuple(getattr(self, name) for name in IDENTITY)

    def identity(self) -> Dict[str, Any]:
        """Return the identifying columns of its rows (the span's only for a span)."""
        names = IDENTITY if self.span is not None else IDENTITY[:IDENTITY.index('span')]
        return {name: getattr(self, name) for name in names}


@dataclass
class BagResult:
    """The rows of one bag: one in ``bags.parquet``, one per window in ``windows.parquet``."""

    bag: Dict[str, Any]
    windows: List[Dict[str, Any]] = field(default_factory=list)


def _signature(path: Path) -> Tuple[int, int]:
    """Return the size and newest mtime (ns) of a bag file or of the files of a directory."""
    files = [path] if path.is_file() else [item for item in path.rglob('*') if item.is_file()]
    stats = [item.stat() for item in files]
    return sum(stat.st_size for stat in stats), max((stat.st_mtime_ns for stat in stats),
                                                    default=0)


def _is_bag_dir(path: Path) -> bool:
    return (path / 'metadata.yaml').is_file()


def _bags_in(path: Path) -> List[Path]:
    """Return the bags at ``path``: itself, or those found below a directory that is none."""
    if path.is_file() or _is_bag_dir(path):
        return [path]
    found: List[Path] = []
    for root, directories, files in os.walk(path):
        here = Path(root)
        if _is_bag_dir(here):
            found.append(here)
            directories.clear()
            continue
        directories.sort()
        found.extend(here / name for name in sorted(files) if name.endswith(_BAG_SUFFIXES))
    return found


def find_bags(patterns: Sequence[str]) -> Tuple[Path, List[Path]]:
    """
    Expand paths and globs into bags, and return their common root too.

    A directory with ``metadata.yaml`` is one bag; any other directory is searched for bags
    (rosbag2 directories, ``.mcap``, ``.db3`` and ROS 1 ``.bag`` files outside them). Globs
    may use ``**``.

    Raises
    ------
    CtidError
        If a pattern matches nothing, or no bag is found.

    """
    bags: List[Path] = []
    for pattern in patterns:
        matches = sorted(glob.glob(pattern, recursive=True)) if glob.has_magic(pattern) \
            else ([pattern] if os.path.exists(pattern) else [])
        if not matches:
            raise CtidError(f'{pattern}: no such file or directory')
        for match in matches:
            bags.extend(_bags_in(Path(match).resolve()))
    unique = sorted(dict.fromkeys(bags))
    if not unique:
        raise CtidError(f'no bag found in {", ".join(patterns)}')
    root = Path(os.path.commonpath([str(bag) for bag in unique]))
    if len(unique) == 1:
        root = unique[0].parent
    return root, unique


def _files_of(bag: Path) -> List[Path]:
    """Return the files of a bag: itself, or those of a directory in a stable order."""
    return [bag] if bag.is_file() else sorted(item for item in bag.rglob('*') if item.is_file())


def _layout(bag: Path) -> Tuple[Any, ...]:
    """Return what two byte-identical bags share without reading them: names and sizes."""
    files = _files_of(bag)
    if bag.is_file():
        return ('file', bag.suffix, bag.stat().st_size)
    return ('directory',) + tuple((item.relative_to(bag).as_posix(), item.stat().st_size)
                                  for item in files)


def _content_hash(bag: Path) -> str:
    """Return the SHA-256 of a bag's bytes (a directory's files with their relative names)."""
    digest = hashlib.sha256()
    for item in _files_of(bag):
        if bag.is_dir():
            digest.update(item.relative_to(bag).as_posix().encode() + b'\0')
        with open(item, 'rb') as stream:
            for piece in iter(lambda: stream.read(_HASH_PIECE), b''):
                digest.update(piece)
    return digest.hexdigest()


def distinct_bags(bags: Sequence[Path]) -> Tuple[List[Path], List[Tuple[Path, Path]]]:
    """
    Drop the byte-identical copies of a bag: a copied recording counts once in a fleet.

    Only bags with the same layout (a file's suffix and size; a directory's file names and
    sizes) are hashed (SHA-256), so a fleet without copies is not read here.

    Returns
    -------
    (list of Path, list of (Path, Path))
        The bags kept, in the given order (of copies the first), and ``(copy, original)`` for
        each dropped one.

    """
    groups: Dict[Tuple[Any, ...], List[Path]] = {}
    for bag in bags:
        try:
            groups.setdefault(_layout(bag), []).append(bag)
        except OSError:     # unreadable: analyse_bag reports it in the bag's row
            groups.setdefault(('unreadable', bag), []).append(bag)
    originals: Dict[Path, Path] = {}
    for group in groups.values():
        if len(group) < 2:
            continue
        first: Dict[str, Path] = {}
        for bag in group:
            try:
                digest = _content_hash(bag)
            except OSError:
                continue
            originals[bag] = first.setdefault(digest, bag)
    copies = [(bag, originals[bag]) for bag in bags if originals.get(bag, bag) != bag]
    dropped = {copy for copy, _ in copies}
    return [bag for bag in bags if bag not in dropped], copies


def _pattern_regex(pattern: str) -> 're.Pattern[str]':
    parts = re.split(r'(\{[A-Za-z_][A-Za-z0-9_]*\}|\*\*/?|\*|\?)', pattern.strip('/'))
    regex = ''
    for part in parts:
        if part.startswith('{'):
            regex += f'(?P<{part[1:-1]}>[^/]+)'
        elif part.startswith('**'):
            regex += '(?:.*/)?' if part.endswith('/') else '.*'
        elif part == '*':
            regex += '[^/]*'
        elif part == '?':
            regex += '[^/]'
        else:
            regex += re.escape(part)
    return re.compile(regex + r'(?:/.*)?\Z')


def robot_fields(name: str, pattern: Optional[str]) -> Dict[str, str]:
    """
    Return what ``pattern`` captures from a bag's relative path, ``robot`` at least.

    ``pattern`` is a path pattern relative to the common root, e.g.
    ``'{robot}/{date}/*.mcap'``: ``{field}`` matches one path component, ``*`` and ``?`` as in
    globs, ``**`` any number of components. Without a pattern the robot is the first component
    of a path with several, else the bag's name without its suffix.

    Raises
    ------
    CtidError
        If the pattern does not match, or captures no ``robot``.

    """
    if pattern is None:
        parts = Path(name).parts
        return {'robot': parts[0] if len(parts) > 1 else Path(name).stem}
    if '{robot}' not in pattern:
        raise CtidError(f'--robot-from {pattern!r} has no {{robot}} field')
    match = _pattern_regex(pattern).match(Path(name).as_posix())
    if match is None:
        raise CtidError(f'{name} does not match --robot-from {pattern!r}')
    return dict(match.groupdict())


def make_task(path: Path, root: Path, pattern: Optional[str], params: str, node_name: str,
              sliding: bool) -> BagTask:
    """Return the task of one bag (see :class:`BagTask`)."""
    name = path.relative_to(root).as_posix() if path != root else path.name
    size, mtime_ns = _signature(path)
    return BagTask(str(path), name, robot_fields(name, pattern), size, mtime_ns, params,
                   hashlib.sha256(params.encode()).hexdigest(), node_name, sliding)


def bag_time_range(path: str) -> Optional[Tuple[int, int]]:
    """
    Return the log times of a bag's first and last message, without reading the messages.

    They come from ``metadata.yaml`` or the MCAP summary (checked against the storage, see
    :class:`~ctid_ros.files.bag_reader.BagReader`). None for a bag without messages or one
    that cannot be opened: its task then runs on the whole bag and its row says why.
    """
    try:
        with open_bag(path) as bag:
            if bag.start_time_ns is None:
                return None
            return bag.start_time_ns, bag.end_time_ns
    except Exception:   # a broken bag is reported by its task (analyse_bag), not here
        return None


def span_bounds(start_ns: int, end_ns: int, span: float, minimum: float
                ) -> List[Tuple[int, int]]:
    """
    Cut a bag's log times into consecutive spans of ``span`` seconds.

    The spans start at the bag's first message and follow one another without gaps or overlap,
    the last ending just after the last message, so every message is in exactly one span. The
    last piece is kept as a span of its own if it lasts at least ``minimum`` seconds (the
    params file's ``window``: as much data as one estimate of the live node uses), and is
    otherwise merged into the span before it, which then lasts less than ``span + minimum``.
    Merged rather than dropped, because dropping would silently leave out the end of every bag;
    merged rather than estimated alone, because an estimate on less data than the window is
    weak or fails, and its row would look like a fault of the plant.

    Parameters
    ----------
    start_ns, end_ns : int
        Log times of the bag's first and last message (ns).
    span, minimum : float
        Length of a span and the shortest last span kept, in seconds.

    Returns
    -------
    list of (int, int)
        ``(lo, hi)`` per span: the messages with ``lo <= t < hi``. One span for a bag shorter
        than ``span``.

    """
    step = max(1, round(span * NANOSECONDS))
    stop = end_ns + 1
    spans = [(lo, min(lo + step, stop)) for lo in range(start_ns, stop, step)]
    if len(spans) > 1 and spans[-1][1] - spans[-1][0] < minimum * NANOSECONDS:
        last = spans.pop()
        spans[-1] = (spans[-1][0], last[1])
    return spans


def split_task(task: BagTask, time_range: Optional[Tuple[int, int]], span: float,
               minimum: float) -> List[BagTask]:
    """
    Return the tasks of a bag's spans (:func:`span_bounds`), numbered from 0.

    Without a time range (see :func:`bag_time_range`) the bag is one task, span 0 with open
    boundaries, whose row gives the reason.
    """
    if time_range is None:
        return [replace(task, span=0)]
    return [replace(task, span=index, span_start_ns=lo, span_end_ns=hi)
            for index, (lo, hi) in enumerate(span_bounds(*time_range, span, minimum))]


def bag_row_columns(names: Sequence[str], spans: bool = False) -> List[str]:
    """Return the columns of a result row for parameters ``names`` in order (``span`` too)."""
    columns = ['robot', 'bag'] + (['span'] if spans else []) + ['start', 'end']
    for name in names:
        columns += [name, f'{name}_std']
    return columns + ['fit', 'residual', 'status', 'error']


def _update_row(task: BagTask, update: Update) -> Dict[str, Any]:
    row: Dict[str, Any] = {**task.fields, 'bag': task.name,
                           'start': update.start_ns, 'end': update.end_ns}
    for name, value, std in zip(update.names, update.values, update.stds):
        row[name] = float(value)
        row[f'{name}_std'] = float(std)
    row.update(fit=float(update.result.fit),
               residual=float(update.result.noise_variance) ** 0.5, status='ok', error='',
               warnings=' | '.join(update.warnings))
    return row


def analyse_bag(task: BagTask) -> BagResult:
    """
    Replay one bag (or one span) through the columnar path and return its rows, never raising.

    The bag row holds the estimate over the whole bag or span (or, with ``sliding``, the last
    window's, every window in :attr:`BagResult.windows`); ``start``/``end`` are the first and
    last grid instants estimated on (ns since the epoch). A span is replayed on its own: its
    messages only, a fresh buffer and session, the transient at its start not fitted as for a
    window of the live node. A chunk or message that cannot be read ends the data there: the
    estimate is made on the messages before it, with the damage in ``warnings``, as ``ctid
    replay`` does. A bag or span that cannot be read, misses a topic or cannot be estimated
    gives a row with ``status`` ``'error'`` and the one-line reason.
    """
    identity = task.identity()
    damage: List[str] = []
    try:
        config = load_params_text(task.params, task.node_name)
        topics = (resolve_topic(config.input_topic, task.node_name),
                  resolve_topic(config.output_topic, task.node_name))
        with open_bag(task.path) as bag:
            if bag.truncated:     # said with an error too: it explains one from a short part
                damage.extend(bag.warnings)
            topics = tuple(bag.topic_name(topic) or topic for topic in topics)
            # A missing topic or a type that cannot be decoded is no damage: said at once.
            bag.raw_streams(sorted(set(topics)))
            # A damaged chunk ends the bag there: estimated on what came before, as replayed.
            samples = readable_part(sample_columns(bag, config, topics, task.span_start_ns,
                                                   task.span_end_ns), damage.append)
            replay = replay_columns(samples, config, sliding=task.sliding, topics=topics)
            warnings = list(dict.fromkeys(bag.warnings + damage)) + replay.warnings
    except CtidError as error:
        return BagResult(_error_row(task, identity, '; '.join([str(error), *damage])))
    except Exception as error:   # a bug or a library failing on odd bytes: still one row
        return BagResult(_error_row(task, identity, f'{type(error).__name__}: {error}'))
    windows = [{**_update_row(task, update), **identity} for update in replay.updates]
    row = dict(windows[-1])
    if warnings:
        row['warnings'] = ' | '.join(warnings + ([row['warnings']] if row['warnings'] else []))
    row['windows'] = len(windows)
    row['duration'] = (replay.updates[-1].end_ns - replay.updates[0].start_ns) / NANOSECONDS
    return BagResult(row, windows if task.sliding else [])


def load_params_text(text: str, node_name: str, source: str = 'params file'
                     ) -> IdentificationConfig:
    """Parse and check params-file content as :func:`load_params_file` does a file."""
    document = parse_yaml(text.encode(), source)
    return IdentificationConfig.from_dict(node_parameters(document, node_name, source=source))


def _error_row(task: BagTask, identity: Dict[str, Any], error: str) -> Dict[str, Any]:
    text = ' '.join(error.split())
    if len(text) > _ERROR_LIMIT:
        text = text[:_ERROR_LIMIT - 3] + '...'
    return {**task.fields, 'bag': task.name, 'start': None, 'end': None, 'fit': None,
            'residual': None, 'status': 'error', 'error': text, 'warnings': '', 'windows': 0,
            'duration': None, **identity}
