"""
rclpy message classes by name, and messages built from plain data.

The node's output contract (:mod:`ctid_ros.streaming.contract`) describes its messages as
nested dicts; :func:`to_message` turns one into the rclpy message, reading the field types from
the message class itself, so no layout is repeated here. :func:`field_problem` checks a field
path against a message class before any message arrives, so that the node can choose, among
the types published on a topic, the one that holds the configured fields.
"""

import importlib
import re
from typing import Any, Mapping, Optional, Union

from ctid_ros.errors import ConfigError
from ctid_ros.streaming.message_fields import FieldPath, Key, NAME_FIELDS, parse_field_path
from ctid_ros.streaming.sampler import normalized_type

__all__ = ['field_problem', 'import_message', 'to_message']

# rosidl field types as get_fields_and_field_types() spells them.
_SEQUENCE = re.compile(r'sequence<([^,>]+)(?:, \d+)?>\Z')
_ARRAY = re.compile(r'(.+)\[\d+\]\Z')
_BYTES = ('octet', 'byte')
# Field types that extract() reads as a number.
_NUMBERS = frozenset(('float', 'double', 'long double', 'boolean', 'int8', 'uint8', 'int16',
                      'uint16', 'int32', 'uint32', 'int64', 'uint64', 'char'))
_STRINGS = re.compile(r'w?string(<=\d+)?\Z')


def import_message(type_name: str) -> type:
    """
    Import a message class from its graph name, e.g. ``'sensor_msgs/msg/JointState'``.

    ``'sensor_msgs/JointState'`` (the form of nested field types) is accepted as well.

    Raises
    ------
    ConfigError
        If the name is malformed or the package is not installed.

    """
    package, _, name = normalized_type(type_name).rpartition('/')
    try:
        return getattr(importlib.import_module(package.replace('/', '.')), name)
    except (ImportError, AttributeError, ValueError):
        raise ConfigError(f'message type {type_name} is not installed: install the package '
                          f'{package.split("/")[0]} in this environment') from None


def _value(field_type: str, value: Any) -> Any:
    """Convert plain data to what rclpy accepts for a field of ``field_type``."""
    match = _SEQUENCE.match(field_type) or _ARRAY.match(field_type)
    if match is not None:
        return [_value(match.group(1), item) for item in value]
    if '/' in field_type:
        return to_message(import_message(field_type), value)
    if field_type in _BYTES and isinstance(value, int):
        return bytes([value])
    return value


def to_message(message_class: type, fields: Mapping[str, Any]) -> Any:
    """
    Build an rclpy message from nested plain data.

    Parameters
    ----------
    message_class : type
        The rclpy message class, e.g. from :func:`import_message`.
    fields : mapping
        Field values; a nested message as a mapping, sequences as lists, ``byte`` fields as
        integers. Fields left out keep their defaults.

    Raises
    ------
    ConfigError
        If a field does not exist in the message.

    """
    types = message_class.get_fields_and_field_types()
    unknown = sorted(set(fields) - set(types))
    if unknown:
        raise ConfigError(f'{message_class.__name__} has no field(s) {", ".join(unknown)}; '
                          f'its fields: {", ".join(types)}')
    return message_class(**{name: _value(types[name], value) for name, value in fields.items()})


def _element_type(field_type: str) -> Optional[str]:
    """Return the element type of a sequence or array type, None for anything else."""
    match = _SEQUENCE.match(field_type) or _ARRAY.match(field_type)
    return match.group(1) if match else None


def field_problem(message_class: type, path: Union[FieldPath, str]) -> Optional[str]:
    """
    Say why messages of ``message_class`` cannot hold the number at ``path``, or None if they can.

    Checked from the field types alone: a missing field, an index on a non-array, a name
    selector without a ``name`` (or ``joint_names``) list of strings next to the array, or a
    value that is not a number. Array lengths and joint names can only be checked on messages.
    """
    if not isinstance(path, FieldPath):
        path = parse_field_path(path)
    current: Optional[type] = message_class
    field_type = ''
    siblings: Mapping[str, str] = {}
    for step in path.steps:
        if isinstance(step, str):
            if current is None:
                return f'{field_type} has no field {step!r}'
            types = current.get_fields_and_field_types()
            if step not in types:
                return (f'{current.__name__} has no field {step!r}; its fields: '
                        f'{", ".join(types)}')
            siblings, field_type = types, types[step]
        else:
            element = _element_type(field_type)
            if element is None:
                return f'{field_type or current.__name__} is not an array, cannot take [{step}]'
            if isinstance(step, Key) and not any(
                    _element_type(siblings.get(name, '')) and
                    _STRINGS.match(_element_type(siblings[name])) for name in NAME_FIELDS):
                return (f'selecting [{step}] by name needs a list of names '
                        f'({" or ".join(NAME_FIELDS)}) next to the array')
            field_type, siblings = element, {}
        current = import_message(field_type) if '/' in field_type else None
    if field_type not in _NUMBERS:
        return f'{path} is a {field_type or message_class.__name__}, not a number'
    return None
