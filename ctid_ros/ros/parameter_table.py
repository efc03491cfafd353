"""
Every parameter ``ctid_node`` declares, as plain data, and its ``--help`` text.

This module imports no rclpy: a documentation generator or a test lists the parameters with
:func:`declared_parameters` without starting a node or a ROS context. The node declares
exactly these (``ctid_ros.ros.parameters``), so what it lists with ``list_parameters`` and
what this table says cannot drift apart:

* the configuration parameters of :data:`~ctid_ros.streaming.config.PARAMETERS` (one field of
  :class:`~ctid_ros.streaming.config.IdentificationConfig` each, its one place of truth);
* per model parameter ``<name>``, the change alarm's ``baseline.<name>``,
  ``baseline_std.<name>`` and ``min_relative_change.<name>``
  (:data:`~ctid_ros.streaming.config.PER_PARAMETER`), declared once the model is known;
* the two every rclpy node declares by itself, ``use_sim_time`` and
  ``start_type_description_service``.
"""

import textwrap
from typing import Any, NamedTuple, Optional, Sequence, Tuple

from ctid_ros.streaming.parameter_specs import (DEFAULT_NODE_NAME, PARAMETERS, PER_PARAMETER,
                                                per_parameter_name)

__all__ = ['DeclaredParameter', 'MODEL_NAME_PLACEHOLDER', 'declared_parameters', 'node_usage',
           'per_parameter_description', 'wrap_text']

# Stands for a model parameter's name in the per-parameter entries when no model is given.
MODEL_NAME_PLACEHOLDER = '<name>'


class DeclaredParameter(NamedTuple):
    """
    One ROS parameter of ``ctid_node``.

    Attributes
    ----------
    name : str
        Parameter name, as ``list_parameters`` gives it.
    kind : str
        ``string``, ``double``, ``integer``, ``bool``, ``string_array`` or ``double_array``
        (the ``rcl_interfaces/ParameterType`` name without ``PARAMETER_``, lower case).
    default : object
        Value when not set (arrays as tuples; None: unset).
    description : str
        What it does, as in its ``ParameterDescriptor``.
    constraints : str
        Allowed values in words ('' if any value of the type).
    read_only : bool
        True if it is only read at start-up.
    origin : str
        ``config`` (the identification's configuration), ``per_parameter`` (the change alarm,
        one per model parameter) or ``rclpy`` (declared by every rclpy node).
    configure_only : bool
        True if it is read at configure and set only while the node is unconfigured.

    """

    name: str
    kind: str
    default: Any
    description: str
    constraints: str
    read_only: bool
    origin: str
    configure_only: bool = False


# Declared by rclpy itself in every node (rclpy.node.Node.__init__).
_RCLPY_PARAMETERS = (
    DeclaredParameter('use_sim_time', 'bool', False,
                      'Take time from the /clock topic (simulation or bag playback) instead of '
                      'the system clock; declared by rclpy.', '', False, 'rclpy'),
    DeclaredParameter('start_type_description_service', 'bool', True,
                      'Offer the ~/get_type_description service; declared by rclpy.', '',
                      True, 'rclpy'),
)


def per_parameter_description(prefix: str, name: str) -> str:
    """Return the description of the per-parameter value ``<prefix>.<name>``."""
    return f'Change alarm: {PER_PARAMETER[prefix]} {name} (NaN: not set).'


def declared_parameters(model_names: Optional[Sequence[str]] = None
                        ) -> Tuple[DeclaredParameter, ...]:
    """
    Return every parameter the node declares, in declaration order.

    Parameters
    ----------
    model_names : sequence of str, optional
        Names of the model's parameters (``K``, ``T``): the per-parameter entries are given
        for them, as a configured node lists them. Without it, one entry per prefix with
        :data:`MODEL_NAME_PLACEHOLDER` (``baseline.<name>``), for documentation.

    Returns
    -------
    tuple of DeclaredParameter
        The configuration parameters, the per-parameter ones, then rclpy's own.

    """
    table = [DeclaredParameter(spec.name, spec.kind,
                               list(spec.default) if isinstance(spec.default, tuple)
                               else spec.default,
                               spec.description, spec.constraints, spec.read_only, 'config',
                               spec.configure_only)
             for spec in PARAMETERS]
    names = (MODEL_NAME_PLACEHOLDER,) if model_names is None else tuple(model_names)
    table += [DeclaredParameter(per_parameter_name(prefix, name), 'double', None,
                                per_parameter_description(prefix, name), '', False,
                                'per_parameter')
              for prefix in PER_PARAMETER for name in names]
    return tuple(table) + _RCLPY_PARAMETERS


def wrap_text(text: str, indent: str) -> str:
    """Wrap ``text`` for a --help page at 99 columns, every line indented by ``indent``."""
    return textwrap.fill(text, 99, initial_indent=indent, subsequent_indent=indent)


def node_usage() -> str:
    """Return the ``ctid_node --help`` text: how to run it and every parameter."""
    lines = [
        f'usage: {DEFAULT_NODE_NAME} [-h] [--ros-args [--params-file FILE] [-p NAME:=VALUE]... '
        '[-r __ns:=/NAMESPACE]]',
        '',
        wrap_text('Identify the physical parameters of a continuous-time transfer function '
                  'live from two ROS topics (input and output), and publish them with their '
                  'uncertainty on ~/estimate, ~/estimate_std, ~/estimate_covariance, '
                  '~/params/<name> and /diagnostics.', ''),
        '',
        'examples:',
        f'  {DEFAULT_NODE_NAME} --ros-args --params-file config/open_loop_delay.yaml',
        f"  {DEFAULT_NODE_NAME} --ros-args -p model:='K/(T*s + 1)' -p input_topic:=/u "
        '-p output_topic:=/y',
        f'  {DEFAULT_NODE_NAME} --ros-args --params-file p.yaml -p lifecycle:=true   '
        '# managed node',
        '',
        'parameters (-p NAME:=VALUE or a params file; integers are accepted for doubles):',
    ]
    table = declared_parameters()
    for entry in table:
        if entry.origin == 'config':
            flags = ', read-only' if entry.read_only else (
                ', set while unconfigured' if entry.configure_only else '')
            lines.append(f'  {entry.name} ({entry.kind}{flags}, default {entry.default!r})')
            lines.append(wrap_text(entry.description, '      '))
    lines.append('per model parameter <name> (a mapping in a params file, e.g. baseline: {J: '
                 '0.05, b: 0.2}):')
    for prefix, meaning in PER_PARAMETER.items():
        lines.append(f'  {per_parameter_name(prefix, MODEL_NAME_PLACEHOLDER)} (double, default '
                     'unset)')
        lines.append(wrap_text(f"The change alarm's {meaning}.", '      '))
    return '\n'.join(lines)
