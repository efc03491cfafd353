"""
rclpy message classes by name, and messages built from plain data.

The node's output contract (:mod:`ctid_ros.streaming.contract`) describes its messages as
nested dicts; :func:`to_message` turns one into the rclpy message, reading the field types from
the message class itself, so no layout is repeated here.
"""

import importlib
import re
from typing import Any, Mapping

from ctid_ros.errors import ConfigError

__all__ = ['import_message', 'to_message']

# rosidl field types as get_fields_and_field_types() spells them.
_SEQUENCE = re.compile(r'sequence<([^,>]+)(?:, \d+)?>\Z')
_ARRAY = re.compile(r'(.+)\[\d+\]\Z')
_BYTES = ('octet', 'byte')


def import_message(type_name: str) -> type:
    """
    Import a message class from its graph name, e.g. ``'sensor_msgs/msg/JointState'``.

    ``'sensor_msgs/JointState'`` (the form of nested field types) is accepted as well.

    Raises
    ------
    ConfigError
        If the name is malformed or the package is not installed.

    """
    package, _, name = type_name.rpartition('/')
    if '/' not in package:
        package += '/msg'
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
