"""
ROS 2 params files: the configuration of the live node and of ``ctid replay``.

The same YAML file (``ctid_node:`` then ``ros__parameters:``) is read by rcl for the live node
and by :func:`load_params_file` for the replay, with the same section matching (plain,
namespaced and wildcard keys) and the same errors as :class:`IdentificationConfig`. The example
configurations (``config/*.yaml``) are found by :func:`find_config` in a sourced workspace, in
a ``pip install``, or in the source checkout.
"""

import os
from pathlib import Path
import re
import sys
from typing import Any, Dict, List, Mapping, Type

from ctid_ros.core.limits import MAX_PARAMS_BYTES, MAX_YAML_DEPTH, MAX_YAML_NODES, read_limited
from ctid_ros.errors import ConfigError, CtidError
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import DEFAULT_NODE_NAME
import yaml

__all__ = ['BoundedLoader', 'PACKAGE', 'ROS_STANDARD_PARAMETERS', 'UNITS_PREFIX',
           'config_directories', 'find_config', 'load_params_file',
           'load_units', 'node_parameters', 'parse_yaml']

PACKAGE = 'ctid_ros'
# ``units: {J: kg m^2, u: N m, y: rad/s}`` in a params file, which ROS flattens to ``units.J``:
# the units of parameters and signals on the axes of figures (not a parameter of the node).
UNITS_PREFIX = 'units.'
# Every ROS 2 node has these; a params file may set them for ctid_node, so they are not errors.
ROS_STANDARD_PARAMETERS = ('use_sim_time', 'start_type_description_service')
_ROS_STANDARD_PREFIXES = ('qos_overrides.',)


# An error message quoting the configuration stays readable (a value may be long).
_MESSAGE_LIMIT = 500


class BoundedLoader(yaml.SafeLoader):
    """
    PyYAML's safe loader with limits on nesting and on alias expansion.

    YAML anchors and aliases share nodes, so a few hundred bytes can describe a structure of a
    billion nodes ("billion laughs") that is harmless until something walks it (a ``repr`` in an
    error message, flattening the parameters). This loader counts every node as if aliases were
    expanded and refuses the document beyond :data:`~ctid_ros.core.limits.MAX_YAML_NODES`, and
    refuses collections nested deeper than :data:`~ctid_ros.core.limits.MAX_YAML_DEPTH`
    (PyYAML's composer recurses: 5000 nested brackets would end in a ``RecursionError``).
    """

    # Nodes allowed with aliases expanded (a subclass may allow more).
    max_nodes = MAX_YAML_NODES

    def __init__(self, stream: Any) -> None:
        super().__init__(stream)
        self._depth = 0
        self._expanded: Dict[int, int] = {}

    def _refuse(self, problem: str) -> yaml.YAMLError:
        return yaml.composer.ComposerError(None, None, problem, self.peek_event().start_mark)

    def compose_node(self, parent: Any, index: Any) -> Any:
        """Compose one node as PyYAML does, counting depth and expanded size."""
        self._depth += 1
        if self._depth > MAX_YAML_DEPTH:
            raise self._refuse(f'collections nested more than {MAX_YAML_DEPTH} deep')
        try:
            node = super().compose_node(parent, index)
        finally:
            self._depth -= 1
        key = id(node)
        if key not in self._expanded:
            if isinstance(node, yaml.SequenceNode):
                size = 1 + sum(self._expanded[id(item)] for item in node.value)
            elif isinstance(node, yaml.MappingNode):
                size = 1 + sum(self._expanded[id(name)] + self._expanded[id(item)]
                               for name, item in node.value)
            else:
                size = 1
            self._expanded[key] = size
            if size > self.max_nodes or len(self._expanded) > self.max_nodes:
                raise self._refuse(f'more than {self.max_nodes} values with aliases expanded '
                                   '(an alias bomb, or not a params file)')
        return node


def parse_yaml(content: bytes, source: str, error: Type[CtidError] = ConfigError,
               max_nodes: int = MAX_YAML_NODES) -> Any:
    """
    Parse one YAML document from UTF-8 bytes with :class:`BoundedLoader`.

    Parameters
    ----------
    content : bytes
        The document.
    source : str
        What it is, for the messages (``'params file run.yaml'``).
    error : type
        The :class:`~ctid_ros.errors.CtidError` to raise (a bag's metadata: ``BagError``).
    max_nodes : int
        Nodes allowed with aliases expanded.

    Raises
    ------
    ConfigError
        (or ``error``) If the content is binary (NUL bytes), not UTF-8, not valid YAML, or
        beyond the limits of :class:`BoundedLoader`; the message names ``source`` and the line.

    """
    if b'\0' in content:
        offset = content.index(b'\0')
        raise error(f'{source} is binary, not YAML text (a NUL byte at offset {offset})')
    try:
        text = content.decode('utf-8')
    except UnicodeDecodeError as problem:
        line = content[:problem.start].count(b'\n') + 1
        raise error(f'{source} is not UTF-8 text: byte 0x{content[problem.start]:02x} on '
                    f'line {line} (offset {problem.start}); save it as UTF-8') from None
    loader = BoundedLoader if max_nodes == MAX_YAML_NODES else type(
        'Loader', (BoundedLoader,), {'max_nodes': max_nodes})
    try:
        return yaml.load(text, Loader=loader)
    except yaml.MarkedYAMLError as problem:
        mark = problem.problem_mark or problem.context_mark
        where = f' (line {mark.line + 1}, column {mark.column + 1})' if mark else ''
        what = ' '.join(str(part) for part in (problem.context, problem.problem) if part)
        raise error(f'{source} is not valid YAML: {what}{where}') from None
    except yaml.YAMLError as problem:
        raise error(f'{source} is not valid YAML: {_clipped(str(problem))}') from None


def _clipped(text: str) -> str:
    """Return a message on one line, cut to a readable length."""
    text = ' '.join(text.split())
    return text if len(text) <= _MESSAGE_LIMIT else text[:_MESSAGE_LIMIT - 3] + '...'


def _flatten(values: Mapping[str, Any], prefix: str = '') -> Dict[str, Any]:
    """Turn nested YAML mappings into dotted names, as ROS does for parameters."""
    flat: Dict[str, Any] = {}
    for key, value in values.items():
        name = f'{prefix}{key}'
        if isinstance(value, Mapping):
            flat.update(_flatten(value, name + '.'))
        else:
            flat[name] = value
    return flat


def _key_pattern(key: str) -> 're.Pattern[str]':
    """Compile a node key (``/**``, ``/ns/*``, ``/**/name``) to a regex on qualified names."""
    escaped = re.escape(key).replace(r'/\*\*', '(/[^/]+)*').replace(r'\*', '[^/]+')
    return re.compile(escaped)


def _merged(document: Any, node_name: str, source: str) -> Dict[str, Any]:
    """Merge the sections of ``document`` that match the node (see :func:`node_parameters`)."""
    if not isinstance(document, Mapping):
        raise ConfigError(f'{source}: expected a mapping of node names to sections, got '
                          f'{type(document).__name__}')
    qualified = node_name.startswith('/')
    base = node_name.rsplit('/', 1)[-1]
    wildcard, exact = [], []
    for key, section in document.items():
        key = str(key)
        full = key if key.startswith('/') else '/' + key
        if qualified:
            matches = bool(_key_pattern(full).fullmatch(node_name))
        else:
            matches = full.rstrip('/').rsplit('/', 1)[-1] in (base, '*', '**')
        if matches:
            (wildcard if '*' in full else exact).append((full, section))
    namespaces = sorted({full for full, _ in exact})
    if len(namespaces) > 1:
        raise ConfigError(f'{source} has sections for several nodes named {base!r} '
                          f'({", ".join(namespaces)}): pass the fully qualified node name')
    if not wildcard and not exact:
        keys = ', '.join(str(key) for key in document) or 'none'
        raise ConfigError(f'{source} has no section for node {node_name!r} (top-level keys: '
                          f'{keys}); write "{base}:" or "/**:" with "ros__parameters:" under it')
    merged: Dict[str, Any] = {}
    for key, section in wildcard + exact:
        if not isinstance(section, Mapping) or set(section) != {'ros__parameters'}:
            found = list(section) if isinstance(section, Mapping) else type(section).__name__
            raise ConfigError(f'{source}: section {key!r} must contain exactly '
                              f'"ros__parameters:", found {found}')
        parameters = section['ros__parameters'] or {}
        if not isinstance(parameters, Mapping):
            raise ConfigError(f'{source}: {key}.ros__parameters must be a mapping of names to '
                              f'values')
        merged.update(_flatten(parameters))
    return merged


def node_parameters(document: Any, node_name: str = DEFAULT_NODE_NAME,
                    source: str = 'params file') -> Dict[str, Any]:
    """
    Select the parameters of one node from a parsed ROS 2 params file.

    Sections whose key matches the node are merged: wildcard keys (``/**``, ``/**/ctid_node``,
    ``/ns/*``) first, in file order, then exact keys, which therefore take precedence. A plain
    ``node_name`` matches the node in any namespace; pass a fully qualified one
    (``/plant1/ctid_node``) when the file configures several namespaces.

    Returns
    -------
    dict
        ``{name: value}`` with nested mappings flattened to dotted names and the standard ROS
        parameters (``use_sim_time``, ``qos_overrides.*``, ...) and the ``units`` of the
        figures (:func:`load_units`) left out.

    Raises
    ------
    ConfigError
        If no section matches, several namespaces match a plain name, a section is malformed,
        or a value is an empty list (which rcl would not accept either).

    """
    merged = _merged(document, node_name, source)
    for name, value in merged.items():
        if isinstance(value, list) and not value:
            raise ConfigError(f'{source}: {name} is an empty list, which ROS 2 cannot type (rcl '
                              f'reads [] as "not set"): leave {name} out to keep its default')
    return {name: value for name, value in merged.items()
            if name not in ROS_STANDARD_PARAMETERS and not name.startswith(_ROS_STANDARD_PREFIXES)
            and not name.startswith(UNITS_PREFIX)}


def load_params_file(path, node_name: str = DEFAULT_NODE_NAME) -> IdentificationConfig:
    """
    Read the configuration from a ROS 2 params YAML file.

    Parameters
    ----------
    path : str or Path
        The file, as passed to ``--ros-args --params-file``.
    node_name : str
        Node whose section to read: ``ctid_node`` (any namespace) or ``/ns/ctid_node``.

    Returns
    -------
    IdentificationConfig
        The validated configuration; parameters not in the file keep their defaults.

    Raises
    ------
    ConfigError
        If the file cannot be read or parsed, has no section for the node, names an unknown
        parameter (the message lists the valid ones), or has a wrong type or invalid value; if
        it is larger than :data:`~ctid_ros.core.limits.MAX_PARAMS_BYTES`, not a regular file,
        binary, or beyond the limits of :class:`BoundedLoader` or of one estimate.

    """
    content = read_limited(Path(path), MAX_PARAMS_BYTES, 'params file', ConfigError)
    document = parse_yaml(content, f'params file {path}')
    values = node_parameters(document, node_name, source=str(path))
    try:
        config = IdentificationConfig.from_dict(values)
    except ConfigError as error:
        raise ConfigError(f'{path}: {_clipped(str(error))}') from None
    return config


def load_units(path, node_name: str = DEFAULT_NODE_NAME) -> Dict[str, str]:
    """
    Read the ``units`` mapping of a params file: the units of parameters and signals.

    ``units: {J: kg m^2, b: N m s/rad, tau: s, u: N m, y: rad/s}`` under ``ros__parameters``
    (ROS reads it as the parameters ``units.J``, ... which the node ignores) labels the axes of
    the figures; names without a unit are shown without one. No mapping: ``{}``.

    Raises
    ------
    ConfigError
        If the file cannot be read (as :func:`load_params_file`), or a unit is not a string.

    """
    content = read_limited(Path(path), MAX_PARAMS_BYTES, 'params file', ConfigError)
    document = parse_yaml(content, f'params file {path}')
    units: Dict[str, str] = {}
    for name, unit in _merged(document, node_name, str(path)).items():
        if name.startswith(UNITS_PREFIX):
            if not isinstance(unit, str):
                raise ConfigError(f'{path}: {name} must be a unit as text (e.g. "N m"), got '
                                  f'{unit!r}')
            units[name[len(UNITS_PREFIX):]] = unit
    return units


def config_directories() -> List[Path]:
    """
    List where example configurations are looked for, in order.

    ``<prefix>/share/ctid_ros/config`` for each ``AMENT_PREFIX_PATH`` entry (a sourced ROS
    workspace), then for ``sys.prefix`` (``pip install .`` into a venv), then the ``config/``
    directory of the source checkout (editable installs do not install data files).
    """
    prefixes = [entry for entry in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)
                if entry]
    prefixes.append(sys.prefix)
    directories = [Path(prefix) / 'share' / PACKAGE / 'config' for prefix in prefixes]
    directories.append(Path(__file__).resolve().parents[2] / 'config')
    return list(dict.fromkeys(directories))


def find_config(name: str) -> Path:
    """
    Locate an example configuration by name (``'closed_loop_pi'`` or ``'closed_loop_pi.yaml'``).

    An existing file path is returned as it is, so command lines can take either.

    Raises
    ------
    ConfigError
        If no directory of :func:`config_directories` has it; the message lists those searched
        and the names available.

    """
    candidate = Path(name)
    if candidate.is_file():
        return candidate
    filename = name if name.endswith(('.yaml', '.yml')) else name + '.yaml'
    if Path(filename).name != filename:
        raise ConfigError(f'configuration {name!r} is neither an existing file nor a bare name')
    directories = config_directories()
    for directory in directories:
        if (directory / filename).is_file():
            return directory / filename
    available = sorted({path.stem for directory in directories if directory.is_dir()
                        for path in directory.glob('*.yaml')})
    raise ConfigError(f'configuration {filename!r} not found in '
                      f'{", ".join(str(directory) for directory in directories)}; available: '
                      f'{", ".join(available) or "none"}')
