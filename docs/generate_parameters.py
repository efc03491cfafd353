"""
Write the parameter table of ``docs/parameters.md`` from a running ``ctid_node``.

The node is started in this process, with nothing configured but an example model (without a
model it does not start), in a namespace of its own with discovery on localhost. A second node
then asks it over DDS what ``ros2 param list`` and ``ros2 param describe`` would:
``list_parameters``, ``describe_parameters`` and ``get_parameters`` through rclpy's
``AsyncParameterClient``. So the table holds exactly the parameters the running node lists,
with its own descriptions, constraints and read-only flags. Types and defaults are those of
the declarations the node makes from :data:`ctid_ros.streaming.config.PARAMETERS` (it
declares the array parameters by type, without a value, so ``ros2 param describe`` shows an
empty double array as a byte array, and ``model`` is set here); for the others (rclpy's own,
the per-parameter ones) they are what the node reports. The parameters the node declares once per
model parameter (``baseline.K``, ``baseline.tau``, ...) are one row each, as
``baseline.<name>``.

Run from the repository root::

    python docs/generate_parameters.py           # rewrite the table in docs/parameters.md
    python docs/generate_parameters.py --check   # exit 1 if the table is out of date

``test/test_parameter_reference.py`` runs the check.
"""

import argparse
from dataclasses import dataclass
import math
import os
from pathlib import Path
import sys
import time
from typing import Any, Dict, List, Optional, Sequence, Tuple

__all__ = ['BEGIN', 'Declaration', 'END', 'EXAMPLE_MODEL', 'REFERENCE', 'live_declarations',
           'main', 'RCLPY', 'render', 'table_of', 'updated']

REFERENCE = Path(__file__).resolve().parent / 'parameters.md'
BEGIN = '<!-- BEGIN table written by `python docs/generate_parameters.py`; do not edit -->'
END = '<!-- END table -->'
# Any valid model will do; its parameter names become <name> in the table.
EXAMPLE_MODEL = 'K*exp(-tau*s)/(T*s + 1)'
EXAMPLE_PARAMETERS = ('K', 'tau', 'T')
# rclpy declares use_sim_time without a description.
RCLPY = {'use_sim_time': 'rclpy: take the time from the /clock topic (bag playback with '
                         '--clock) instead of the system clock.'}
_TYPES = {1: 'bool', 2: 'integer', 3: 'double', 4: 'string', 5: 'byte_array',
          6: 'bool_array', 7: 'integer_array', 8: 'double_array', 9: 'string_array'}


@dataclass(frozen=True)
class Declaration:
    """
    One parameter as the running node describes it.

    Attributes
    ----------
    name : str
        Parameter name; per model parameter with ``<name>`` in place of the parameter.
    kind : str
        Declared type (``double``, ``string_array``, ...).
    default : object
        Value without any configuration (None: unset).
    description : str
        The descriptor's description.
    constraints : str
        The descriptor's additional constraints ('' if none).
    read_only : bool
        Whether the parameter can only be set at start-up.

    """

    name: str
    kind: str
    default: Any
    description: str
    constraints: str
    read_only: bool


def _wait(future, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while not future.done():
        if time.monotonic() > deadline:
            raise TimeoutError(f'no answer to {what} within {timeout:g} s')
        time.sleep(0.02)
    return future.result()


def _generic(name: str, description: str) -> Tuple[str, str]:
    """Return ``name`` and ``description`` with an example model parameter as ``<name>``."""
    prefix, _, last = name.rpartition('.')
    if prefix and last in EXAMPLE_PARAMETERS:
        return f'{prefix}.<name>', description.replace(f' {last} ', ' <name> ')
    return name, description


def live_declarations(timeout: float = 30.0) -> List[Declaration]:
    """
    Start ``ctid_node`` in this process and return every parameter it lists.

    Parameters
    ----------
    timeout : float
        Seconds to wait for the node's parameter services and for each answer.

    Returns
    -------
    list of Declaration
        In the order the node lists them, one row per ``<prefix>.<name>`` pattern.

    """
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    from ctid_ros.ros.node import IdentificationNode
    from ctid_ros.ros.spinner import Spinner
    from ctid_ros.streaming.config import PARAMETERS
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter, parameter_value_to_python
    from rclpy.parameter_client import AsyncParameterClient

    declared = {spec.name: spec for spec in PARAMETERS}
    namespace = f'/ctid_parameter_reference_{os.getpid()}'
    context = Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    nodes = []
    spinner = Spinner(executor, 'parameter reference')
    try:
        node = IdentificationNode(context=context, namespace=namespace, parameter_overrides=[
            Parameter('model', value=EXAMPLE_MODEL)])
        asking = rclpy.create_node('parameter_reference', namespace=namespace,
                                   context=context)
        nodes += [node, asking]
        for each in nodes:
            executor.add_node(each)
        spinner.start()
        client = AsyncParameterClient(asking, node.get_fully_qualified_name())
        if not client.wait_for_services(timeout_sec=timeout):
            raise TimeoutError(f'the parameter services of {node.get_fully_qualified_name()} '
                               f'did not appear within {timeout:g} s')
        listed = _wait(client.list_parameters(), timeout, 'list_parameters')
        names = list(listed.result.names)
        descriptors = _wait(client.describe_parameters(names), timeout,
                            'describe_parameters').descriptors
        # The node's own value for what it does not take from PARAMETERS (rclpy's parameters,
        # the per-parameter ones); the array parameters are declared by type, without a value.
        others = [name for name in names if name not in declared]
        values = _wait(client.get_parameters(others), timeout, 'get_parameters').values
    finally:
        spinner.stop()
        executor.shutdown()
        for each in nodes:
            each.destroy_node()
        rclpy.shutdown(context=context)
    if len(descriptors) != len(names) or len(values) != len(others):
        raise RuntimeError(f'{len(names)} parameters listed, {len(descriptors)} described and '
                           f'{len(values)} of {len(others)} values answered')
    live = {name: parameter_value_to_python(value) for name, value in zip(others, values)}
    rows: Dict[str, Declaration] = {}
    for name, descriptor in zip(names, descriptors):
        if name in declared:
            kind, default = declared[name].kind, declared[name].default
        else:
            kind, default = _TYPES.get(descriptor.type, f'type {descriptor.type}'), live[name]
        if isinstance(default, float) and math.isnan(default):
            default = None
        generic, description = _generic(name, descriptor.description or RCLPY.get(name, ''))
        rows.setdefault(generic, Declaration(generic, kind, default, description,
                                             descriptor.additional_constraints,
                                             descriptor.read_only))
    return list(rows.values())


def _default(value: Any) -> str:
    if value is None:
        return 'unset'
    if isinstance(value, bool):
        return '`true`' if value else '`false`'
    if isinstance(value, str):
        return f'`{value}`' if value else "`''`"
    if isinstance(value, (list, tuple)):
        return '`[' + ', '.join(str(item) for item in value) + ']`'
    return f'`{value!r}`'


def _cell(text: str) -> str:
    return text.replace('|', '\\|').replace('\n', ' ')


def render(declarations: Sequence[Declaration]) -> str:
    """Return the markdown table of ``declarations``, between the markers."""
    lines = [BEGIN, '', '| parameter | type | default | read-only | meaning |',
             '|---|---|---|---|---|']
    for row in declarations:
        meaning = row.description
        if row.constraints:
            meaning += f' Constraint: {row.constraints}.'
        lines.append(f'| `{row.name}` | {row.kind} | {_default(row.default)} | '
                     f'{"yes" if row.read_only else ""} | {_cell(meaning)} |')
    return '\n'.join(lines + ['', END])


def table_of(text: str) -> Optional[str]:
    """Return the generated table in the text of docs/parameters.md, markers included."""
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        return None
    return text[start:end + len(END)]


def updated(text: str, table: str) -> str:
    """Return ``text`` with its table (or, without one, an appended table) replaced."""
    current = table_of(text)
    return text.replace(current, table) if current else text.rstrip('\n') + '\n\n' + table + '\n'


def main(argv: Optional[List[str]] = None) -> int:
    """Rewrite or check the table of docs/parameters.md; return the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--check', action='store_true',
                        help='only compare; exit 1 if docs/parameters.md is out of date')
    parser.add_argument('--output', type=Path, default=REFERENCE)
    arguments = parser.parse_args(argv)
    table = render(live_declarations())
    text = arguments.output.read_text(encoding='utf-8') if arguments.output.exists() else ''
    if arguments.check:
        if table_of(text) != table:
            print(f'{arguments.output} is out of date: run python docs/generate_parameters.py',
                  file=sys.stderr)
            return 1
        return 0
    arguments.output.write_text(updated(text, table), encoding='utf-8')
    print(f'wrote the table of {arguments.output}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
