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
from typing import Any, Dict, List, Mapping

from ctid_ros.errors import ConfigError
from ctid_ros.streaming.config import IdentificationConfig
from ctid_ros.streaming.contract import DEFAULT_NODE_NAME
import yaml

__all__ = ['PACKAGE', 'ROS_STANDARD_PARAMETERS', 'config_directories', 'find_config',
           'load_params_file', 'node_parameters']

PACKAGE = 'ctid_ros'
# Every ROS 2 node has these; a params file may set them for ctid_node, so they are not errors.
ROS_STANDARD_PARAMETERS = ('use_sim_time', 'start_type_description_service')
_ROS_STANDARD_PREFIXES = ('qos_overrides.',)


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
        parameters (``use_sim_time``, ``qos_overrides.*``, ...) left out.

    Raises
    ------
    ConfigError
        If no section matches, several namespaces match a plain name, a section is malformed,
        or a value is an empty list (which rcl would not accept either).

    """
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
    for name, value in merged.items():
        if isinstance(value, list) and not value:
            raise ConfigError(f'{source}: {name} is an empty list, which ROS 2 cannot type (rcl '
                              f'reads [] as "not set"): leave {name} out to keep its default')
    return {name: value for name, value in merged.items()
            if name not in ROS_STANDARD_PARAMETERS and not name.startswith(_ROS_STANDARD_PREFIXES)}


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
        parameter (the message lists the valid ones), or has a wrong type or invalid value.

    """
    try:
        text = Path(path).read_text(encoding='utf-8')
    except OSError as error:
        raise ConfigError(f'cannot read params file {path}: {error.strerror or error}') from None
    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise ConfigError(f'params file {path} is not valid YAML: {error}') from None
    values = node_parameters(document, node_name, source=str(path))
    try:
        return IdentificationConfig.from_dict(values)
    except ConfigError as error:
        raise ConfigError(f'{path}: {error}') from None


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
