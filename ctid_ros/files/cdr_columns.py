"""
Numeric fields of many CDR-encoded ROS 2 messages decoded at once, with numpy.

A bag stores every message of a topic in the same layout: the type's fields in order, each
primitive aligned to its size relative to the start of the payload (after the 4-byte
encapsulation header), strings and sequences prefixed by a ``uint32`` length. Fixed-layout
types (``std_msgs/Float64``, ``geometry_msgs/PointStamped``) put every field at the same
offset in every message; variable-length ones (``sensor_msgs/JointState``: a ``frame_id``, then
sequences of names, positions, velocities and efforts) need each message's offsets, which
:class:`CdrColumns` computes for all messages together: one array of positions, advanced field
by field (a sequence of strings or of messages one element index at a time).

It reads the fields of :class:`~ctid_ros.streaming.message_fields.FieldPath` paths and
``header.stamp`` of messages of any type built from primitives, strings, nested messages,
fixed arrays and sequences, from the type definitions the bag stores (a rosbags typestore).
An element of an array of numbers selected by joint name (``position[wheel_left]``) is found
through the name list of the same message (``name`` or ``joint_names``): messages whose name
lists have the same bytes share one lookup, so a bag that keeps one list (or a few orders)
costs one lookup per distinct list and block, and the order may change from message to
message.
Every message whose bytes do not follow the layout exactly (a length beyond its end, a string
without its terminator or with non-ASCII bytes, more than 3 trailing bytes, another
encapsulation than plain CDR) and every message whose path does not lead to a number (a field
that does not exist, an index beyond a sequence's length) is flagged for the per-message
decoder instead, which decodes it, or reports it, exactly as the streaming replay does; so
does every message whose name list lacks the joint, and every name selecting an element of
an array of messages.
"""

from dataclasses import dataclass
import struct
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from ctid_ros.files.mcap_source import byte_rows
from ctid_ros.streaming.contract import NANOSECONDS
from ctid_ros.streaming.message_fields import FieldPath, Key, NAME_FIELDS
import numpy as np

__all__ = ['CdrColumns', 'Decoded', 'PRIMITIVES']

# Primitive types of ROS 2 messages: numpy type code (without byte order) and size in bytes.
PRIMITIVES: Dict[str, Tuple[str, int]] = {
    'bool': ('u1', 1), 'byte': ('u1', 1), 'char': ('u1', 1), 'octet': ('u1', 1),
    'int8': ('i1', 1), 'uint8': ('u1', 1), 'int16': ('i2', 2), 'uint16': ('u2', 2),
    'int32': ('i4', 4), 'uint32': ('u4', 4), 'int64': ('i8', 8), 'uint64': ('u8', 8),
    'float32': ('f4', 4), 'float64': ('f8', 8),
}
# Node types of rosbags' field definitions (rosbags.interfaces.Nodetype).
_BASE, _NAME, _ARRAY, _SEQUENCE = 1, 2, 3, 4
_STAMP = ('header', 'stamp')
# Bytes a rosbags-deserialised message may carry after its last field (CDR padding).
_TRAILING = 3
# Smallest serialised element of a sequence of strings or messages (bounds its count).
_MIN_STRING = 5
# Characters of a string checked for ASCII at once; messages with longer ones are decoded one
# by one.
_ASCII_SPAN = 64


class _Unsupported(Exception):
    """A field type the columnar decoder does not handle (the topic is decoded per message)."""


@dataclass(frozen=True)
class Decoded:
    """
    The columns of a batch of messages.

    Attributes
    ----------
    values : ndarray
        ``(messages, paths)`` float values of the paths.
    stamp_ns : ndarray or None
        ``header.stamp`` in nanoseconds (0 where it is zero), None for a type without one.
    fallback : ndarray
        True for the messages to decode one by one (bytes off the layout, or a path that does
        not reach a number in them); their values and stamps here are meaningless.

    """

    values: np.ndarray
    stamp_ns: Optional[np.ndarray]
    fallback: np.ndarray


class _Cursor:
    """Positions of a subset of the messages of a batch, advanced field by field."""

    def __init__(self, data: np.ndarray, ids: np.ndarray, pos: np.ndarray, origin: np.ndarray,
                 limit: np.ndarray, order: str, bad: np.ndarray):
        self.data, self.ids, self.pos = data, ids, pos
        self.origin, self.limit, self.order, self.bad = origin, limit, order, bad

    def subset(self, mask: np.ndarray) -> '_Cursor':
        return _Cursor(self.data, self.ids[mask], self.pos[mask], self.origin[mask],
                       self.limit[mask], self.order, self.bad)

    def align(self, size: int, where: Optional[np.ndarray] = None) -> None:
        if size > 1:
            offset = self.pos - self.origin
            aligned = self.origin + ((offset + size - 1) & -size)
            self.pos = aligned if where is None else np.where(where, aligned, self.pos)

    def read(self, code: str, size: int, at: Optional[np.ndarray] = None,
             where: Optional[np.ndarray] = None) -> np.ndarray:
        """
        Read one primitive at every position, checking bounds.

        ``at`` are the positions (default the cursor's) of the messages selected by ``where``
        (default all).
        """
        at = self.pos if at is None else at
        limit, ids = (self.limit, self.ids) if where is None else \
            (self.limit[where], self.ids[where])
        outside = at + size > limit
        if np.any(outside):
            self.bad[ids[outside]] = True
        at = np.clip(at, 0, max(self.data.size - size, 0))
        if self.data.size < size:
            return np.zeros(at.size, dtype=self.order + code)
        return byte_rows(self.data, at, size).view(self.order + code).ravel()

    def count(self, minimum: int) -> np.ndarray:
        """Read a sequence's uint32 length, flagging lengths its remaining bytes cannot hold."""
        self.align(4)
        count = self.read('u4', 4).astype(np.int64)
        self.pos = self.pos + 4
        too_long = self.pos + count * minimum > self.limit
        if np.any(too_long):
            self.bad[self.ids[too_long]] = True
            count = np.where(too_long, 0, count)
        return count

    def skip_string(self) -> None:
        """
        Step over a string, flagging one whose bytes rosbags could refuse.

        A length of zero or beyond the message, a missing terminator and non-ASCII bytes
        (which may not be UTF-8) are left to the per-message decoder.
        """
        self.align(4)
        length = self.read('u4', 4).astype(np.int64)
        end = self.pos + 4 + length
        broken = (length < 1) | (end > self.limit)
        safe_length = np.where(broken, 1, length)
        last = np.clip(self.pos + 3 + safe_length, 0, max(self.data.size - 1, 0))
        flagged = broken | (self.data[last] != 0 if self.data.size else True)
        longest = int(safe_length.max(initial=1)) - 1
        if longest:
            short = safe_length - 1 <= _ASCII_SPAN
            span = min(longest, _ASCII_SPAN)
            inside = np.arange(span) < (safe_length - 1)[:, None]
            text = byte_rows(self.data, self.pos + 4, span)
            flagged |= np.any((text >= 0x80) & inside, axis=1) | ~short
        if np.any(flagged):
            self.bad[self.ids[flagged]] = True
        self.pos = np.where(broken, self.limit, end)


class _NameList:
    """
    The name list of one message level of a batch, and the elements of arrays selected by it.

    ``span`` holds where each message's list starts (4-byte aligned) and ends, and the count of
    a fixed array (None for a sequence); ``pending`` the reads of elements selected by name,
    done once the whole level is walked since the list may come after the array.
    """

    def __init__(self, field: str):
        self.field = field
        self.span: Optional[Tuple[np.ndarray, np.ndarray, Optional[int]]] = None
        self.pending: List[Tuple[np.ndarray, np.ndarray, str, int, Key, Sequence[Any]]] = []

    @classmethod
    def of(cls, fields: Sequence[Tuple[str, Tuple[int, Any]]], wanted: Mapping[Any, Any]
           ) -> Optional['_NameList']:
        """
        Return the name list of a level whose arrays are selected by name, else None.

        As in :func:`~ctid_ros.streaming.message_fields.extract`, the first of
        :data:`~ctid_ros.streaming.message_fields.NAME_FIELDS` the type declares is the list;
        one that is not an array of strings resolves nothing (the per-message decoder reports
        it).
        """
        if not any(isinstance(step, Key) for below in wanted.values()
                   if isinstance(below, dict) for step in below):
            return None
        declared = dict(fields)
        field = next((name for name in NAME_FIELDS if name in declared), None)
        if field is None:
            return None
        kind, detail = declared[field]
        strings = kind in (_ARRAY, _SEQUENCE) and int(detail[0][0]) == _BASE and \
            detail[0][1][0] == 'string'
        return cls(field) if strings else None

    def indices(self, cursor: _Cursor) -> Dict[Key, np.ndarray]:
        """
        Return, per key of :attr:`pending`, its index in each message's list (-1 if absent).

        Messages whose lists have the same bytes have the same names, so each distinct list is
        split and searched once; messages already flagged are left at -1.
        """
        keys = {entry[4] for entry in self.pending}
        found = {key: np.full(cursor.ids.size, -1, dtype=np.int64) for key in keys}
        if self.span is None:
            return found
        start, end, fixed = self.span
        size = end - start
        valid = ~cursor.bad[cursor.ids] & (size > 0) & (end <= cursor.limit)
        for length in np.unique(size[valid]).tolist():
            rows = np.flatnonzero(valid & (size == length))
            block = cursor.data[start[rows, None] + np.arange(length)]
            first, inverse = _distinct_rows(block)
            lists = [_split_names(block[row].tobytes(), cursor.order, fixed) for row in first]
            for key in keys:
                name = key.name.encode()
                index = np.array([names.index(name) if name in names else -1
                                  for names in lists])
                found[key][rows] = index[inverse]
        return found


def _distinct_rows(block: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return the first row of each distinct row of ``block`` and each row's distinct row.

    Rows equal to the first are found by one comparison, since a publisher mostly sends the
    same list; only the others are sorted.
    """
    inverse = np.zeros(block.shape[0], dtype=np.int64)
    first = np.zeros(1, dtype=np.int64)
    others = np.flatnonzero(np.any(block != block[0], axis=1))
    if others.size:
        _, other_first, other_inverse = np.unique(block[others], axis=0, return_index=True,
                                                  return_inverse=True)
        first = np.concatenate([first, others[other_first]])
        inverse[others] = other_inverse.reshape(-1) + 1
    return first, inverse


def _split_names(raw: bytes, order: str, fixed: Optional[int]) -> List[bytes]:
    """Split a name list's bytes (validated, from its aligned start) into the names' bytes."""
    count, pos = (fixed, 0) if fixed is not None else (struct.unpack_from(order + 'I', raw)[0], 4)
    names = []
    for _ in range(count):
        pos += -pos % 4
        length = struct.unpack_from(order + 'I', raw, pos)[0]
        # The string without its terminator, as rosbags and mcap_ros2 decode it.
        names.append(raw[pos + 4:pos + 3 + length])
        pos += 4 + length
    return names


class CdrColumns:
    """
    Decode numeric fields and ``header.stamp`` of many messages of one type at once.

    Parameters
    ----------
    fielddefs : mapping
        Field definitions of the type and of every type it uses, as a rosbags typestore's
        ``fielddefs`` (built from the definitions the bag stores).
    msgtype : str
        The message type, e.g. ``'sensor_msgs/msg/JointState'``.
    paths : sequence of FieldPath
        The fields to read, one column each.
    stamp : bool
        Also read ``header.stamp`` where the type has one (as
        :func:`~ctid_ros.streaming.message_fields.message_stamp` does).

    Attributes
    ----------
    supported : bool
        False when the type holds a field the decoder does not handle (a ``wstring``, bounded
        or unknown types): the caller then decodes every message one by one.

    """

    def __init__(self, fielddefs: Mapping[str, Any], msgtype: str, paths: Sequence[FieldPath],
                 stamp: bool = True):
        self._fielddefs = fielddefs
        self.msgtype = msgtype
        self.paths = tuple(paths)
        self._wanted: Dict[Any, Any] = {}
        for column, path in enumerate(self.paths):
            node = self._wanted
            for step in path.steps:
                node = node.setdefault(step, {})
            node.setdefault(None, []).append(column)
        self.supported = True
        try:
            self._has_stamp = stamp and self._stamp_fields()
            self._check(msgtype)
        except _Unsupported:
            self.supported = False
            self._has_stamp = False
        if self._has_stamp:
            stamp_node = self._wanted.setdefault('header', {}).setdefault('stamp', {})
            stamp_node.setdefault('sec', {}).setdefault(None, []).append('sec')
            stamp_node.setdefault('nanosec', {}).setdefault(None, []).append('nanosec')

    def _fields(self, msgtype: str) -> List[Tuple[str, Tuple[int, Any]]]:
        definition = self._fielddefs.get(msgtype)
        if definition is None:
            raise _Unsupported(msgtype)
        return [(name, (int(kind), detail)) for name, (kind, detail) in definition[1]]

    def _stamp_fields(self) -> bool:
        """Tell whether the type has ``header.stamp`` with integer ``sec`` and ``nanosec``."""
        msgtype = self.msgtype
        for name in _STAMP:
            fields = dict(self._fields(msgtype))
            if name not in fields or fields[name][0] != _NAME:
                return False
            msgtype = fields[name][1]
        fields = dict(self._fields(msgtype))
        if not {'sec', 'nanosec'} <= set(fields):
            return False
        if not all(fields[name][0] == _BASE and fields[name][1][0] in PRIMITIVES and
                   PRIMITIVES[fields[name][1][0]][0][0] in 'iu' for name in ('sec', 'nanosec')):
            raise _Unsupported('a stamp of other than integers')
        return True

    def _check(self, msgtype: str, seen: Tuple[str, ...] = ()) -> None:
        """Refuse types with fields the walk cannot follow (before any message is read)."""
        if msgtype in seen:
            raise _Unsupported(msgtype)
        fields = self._fields(msgtype)
        if not fields:
            raise _Unsupported(msgtype)     # an empty message holds a placeholder byte
        for _, (kind, detail) in fields:
            element = detail if kind in (_BASE, _NAME) else detail[0]
            element_kind = kind if kind in (_BASE, _NAME) else int(element[0])
            element = element if kind in (_BASE, _NAME) else element[1]
            if kind == _SEQUENCE and detail[1]:
                raise _Unsupported('bounded sequence')
            if element_kind == _NAME:
                self._check(element, seen + (msgtype,))
            elif element_kind != _BASE or (element[0] not in PRIMITIVES and
                                           element[0] != 'string') or \
                    (element[0] == 'string' and element[1]):
                raise _Unsupported(str(element))

    def decode(self, data: np.ndarray, starts: np.ndarray, lengths: np.ndarray) -> Decoded:
        """
        Decode the messages ``data[starts[i]:starts[i] + lengths[i]]``.

        Parameters
        ----------
        data : ndarray of uint8
            A buffer holding the messages (e.g. a decompressed MCAP chunk).
        starts, lengths : ndarray of int
            Where each serialised message (with its encapsulation header) starts, and its size.

        Returns
        -------
        Decoded
            The values, stamps and the messages left to the per-message decoder.

        """
        count = starts.size
        starts = starts.astype(np.int64)
        limit = starts + lengths.astype(np.int64)
        values = np.zeros((count, len(self.paths)))
        bad = np.zeros(count, dtype=bool)
        raw_sec = np.zeros(count, dtype=np.int64)
        raw_nanosec = np.zeros(count, dtype=np.int64)
        short = lengths < 4
        header = data[np.clip(starts[:, None] + np.arange(2), 0, max(data.size - 1, 0))] \
            if data.size else np.zeros((count, 2), dtype=np.uint8)
        little = (header[:, 0] == 0) & (header[:, 1] == 1) & ~short
        big = (header[:, 0] == 0) & (header[:, 1] == 0) & ~short
        bad |= ~(little | big)
        outputs = {'values': values, 'sec': raw_sec, 'nanosec': raw_nanosec}
        for mask, order in ((little, '<'), (big, '>')):
            if not np.any(mask):
                continue
            ids = np.flatnonzero(mask)
            cursor = _Cursor(data, ids, starts[ids] + 4, starts[ids] + 4, limit[ids], order,
                             bad)
            self._walk(self.msgtype, self._wanted, cursor, outputs)
            # A message that ends inside its last field is short even when the fields read lie
            # before its end (a sequence's count is checked without its alignment padding).
            left = limit[ids] - cursor.pos
            bad[ids[(left > _TRAILING) | (left < 0)]] = True
        stamp_ns = raw_sec * NANOSECONDS + raw_nanosec if self._has_stamp else None
        return Decoded(values, stamp_ns, bad | self._path_errors(count, outputs))

    def _path_errors(self, count: int, outputs: Dict[str, Any]) -> np.ndarray:
        """Flag the messages in which a path did not reach a number (all, if none could)."""
        reached = outputs.get('reached')
        if reached is None:
            reached = np.zeros((count, len(self.paths)), dtype=bool)
        return ~np.all(reached, axis=1) if self.paths else np.zeros(count, dtype=bool)

    def _walk(self, msgtype: str, wanted: Mapping[Any, Any], cursor: _Cursor,
              outputs: Dict[str, Any]) -> None:
        fields = self._fields(msgtype)
        names = _NameList.of(fields, wanted)
        for name, (kind, detail) in fields:
            below = wanted.get(name, {})
            if kind == _BASE:
                self._primitive(detail[0], below, cursor, outputs)
            elif kind == _NAME:
                self._walk(detail, below, cursor, outputs)
            elif names is not None and name == names.field:
                cursor.align(4)
                start = cursor.pos.copy()
                self._array(kind, detail, below, cursor, outputs, names)
                names.span = (start, cursor.pos.copy(), detail[1] if kind == _ARRAY else None)
            else:
                self._array(kind, detail, below, cursor, outputs, names)
        if names is not None and names.pending:
            found = names.indices(cursor)
            for pos, counts, code, size, key, columns in names.pending:
                self._element(cursor, (code, size), pos, counts, found[key], columns, outputs)

    def _primitive(self, typename: str, wanted: Mapping[Any, Any], cursor: _Cursor,
                   outputs: Dict[str, Any]) -> None:
        if typename == 'string':
            cursor.skip_string()
            return
        code, size = PRIMITIVES[typename]
        cursor.align(size)
        if None in wanted:
            value = cursor.read(code, size)
            if typename == 'bool':
                value = value != 0
            self._store(wanted[None], cursor.ids, value, outputs)
        cursor.pos = cursor.pos + size

    def _store(self, columns: Sequence[Any], ids: np.ndarray, value: np.ndarray,
               outputs: Dict[str, Any]) -> None:
        reached = outputs.setdefault(
            'reached', np.zeros((outputs['values'].shape[0], len(self.paths)), dtype=bool))
        for column in columns:
            if isinstance(column, str):
                outputs[column][ids] = value.astype(np.int64)
            else:
                outputs['values'][ids, column] = value.astype(float)
                reached[ids, column] = True

    def _array(self, kind: int, detail: Any, wanted: Mapping[Any, Any], cursor: _Cursor,
               outputs: Dict[str, Any], names: Optional['_NameList']) -> None:
        (element_kind, element), fixed = detail
        element_kind = int(element_kind)
        primitive = element_kind == _BASE and element[0] != 'string'
        if kind == _ARRAY:
            counts = np.full(cursor.pos.size, fixed, dtype=np.int64)
        else:
            minimum = (PRIMITIVES[element[0]][1] if primitive else
                       _MIN_STRING if element_kind == _BASE else 1)
            counts = cursor.count(minimum)
        if primitive:
            code, size = PRIMITIVES[element[0]]
            cursor.align(size, counts > 0)
            for index, below in wanted.items():
                if None not in below:
                    continue
                if isinstance(index, int):
                    self._element(cursor, (code, size), cursor.pos, counts,
                                  np.full(counts.size, index), below[None], outputs)
                elif isinstance(index, Key) and names is not None:
                    # Read when the whole message is walked: the names may come after.
                    names.pending.append((cursor.pos, counts, code, size, index, below[None]))
            cursor.pos = cursor.pos + counts * size
            return
        for index in range(int(counts.max(initial=0))):
            active = counts > index
            part = cursor.subset(active)
            if element_kind == _BASE:
                part.skip_string()
            else:
                self._walk(element, wanted.get(index, {}), part, outputs)
            cursor.pos = cursor.pos.copy()
            cursor.pos[active] = part.pos

    def _element(self, cursor: _Cursor, primitive: Tuple[str, int], pos: np.ndarray,
                 counts: np.ndarray, index: np.ndarray, columns: Sequence[Any],
                 outputs: Dict[str, Any]) -> None:
        """Read element ``index`` (per message, -1 for none) of arrays starting at ``pos``."""
        code, size = primitive
        inside = (index >= 0) & (index < counts)
        if np.any(inside):
            value = cursor.read(code, size, pos[inside] + index[inside] * size, inside)
            self._store(columns, cursor.ids[inside], value, outputs)
