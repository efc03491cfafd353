"""
The package's layering, read from the imports of every module under ctid_ros (ast, no import).

Layers, lowest first: core -> estimation -> design -> streaming -> files -> {ros, cli, demo}.
A module imports only its own layer or lower ones; ``ctid_ros.errors`` is shared by all and imports
nothing of the package; the package root (the public API) imports core, estimation and errors.
Within the top layer the ROS adapters (ros) import neither the command (cli) nor the demo, and
the command does not import the demo. Every import counts, also one inside a function, and so
does a string naming a module of the package (``importlib`` dispatch, ``python -m``).

Also checked: no import cycle between modules; no name with a leading underscore taken from
another module; ROS (rclpy and the ``*_msgs``/``*_srvs``/``*_interfaces`` packages) imported
only under ``ctid_ros/ros``.
"""

import ast
from collections import defaultdict
from pathlib import Path
import re
from typing import Dict, Iterator, List, NamedTuple, Set, Tuple

PACKAGE = 'ctid_ros'
ROOT = Path(__file__).resolve().parents[1] / PACKAGE
RANKS = {'core': 0, 'estimation': 1, 'design': 2, 'streaming': 3, 'files': 4, 'ros': 5, 'cli': 5,
         'demo': 5}
# Imports within the top layer that are refused although the ranks are equal.
FORBIDDEN = {('ros', 'cli'), ('ros', 'demo'), ('cli', 'demo')}
SHARED = 'errors'
API_LAYERS = {'core', 'estimation', SHARED}
ROS_PACKAGE = re.compile(r'(rclpy|rcl_\w+|rosidl_\w+|rmw\w*|builtin_interfaces|'
                         r'\w+_msgs|\w+_srvs|\w+_interfaces|\w+_actions?)\Z')


class Import(NamedTuple):
    """One import statement's target as seen in a module."""

    module: str     # importing module
    line: int
    target: str     # imported module (absolute), or external top-level package
    names: Tuple[str, ...]  # names taken with ``from target import ...``


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix('').parts
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


MODULES: Dict[str, Path] = {module_name(path): path for path in sorted(ROOT.rglob('*.py'))}


def _absolute(module: str, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ''
    package = module.split('.')
    is_package = MODULES[module].name == '__init__.py'
    base = package[:len(package) - node.level + (1 if is_package else 0)]
    return '.'.join(base + ([node.module] if node.module else []))


def imports(module: str) -> Iterator[Import]:
    """Yield every import of ``module``: statements anywhere, and module names in strings."""
    tree = ast.parse(MODULES[module].read_text(encoding='utf-8'))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield Import(module, node.lineno, alias.name, ())
        elif isinstance(node, ast.ImportFrom):
            target = _absolute(module, node)
            names = tuple(alias.name for alias in node.names)
            # 'from package import module' imports the module itself.
            submodules = [name for name in names if f'{target}.{name}' in MODULES]
            for name in submodules:
                yield Import(module, node.lineno, f'{target}.{name}', ())
            rest = tuple(name for name in names if name not in submodules)
            if rest or not submodules:
                yield Import(module, node.lineno, target, rest)
        elif (isinstance(node, ast.Constant) and isinstance(node.value, str)
              and '.' in node.value and node.value in MODULES and node.value != module):
            yield Import(module, node.lineno, node.value, ())


ALL_IMPORTS: List[Import] = [item for module in MODULES for item in imports(module)]


def internal(target: str) -> bool:
    return target == PACKAGE or target.startswith(PACKAGE + '.')


def layer(module: str) -> str:
    parts = module.split('.')
    return parts[1] if len(parts) > 1 else PACKAGE


def where(item: Import) -> str:
    return f'{MODULES[item.module].relative_to(ROOT.parent)}:{item.line}'


def test_every_module_belongs_to_a_layer():
    unknown = sorted(module for module in MODULES
                     if layer(module) not in {*RANKS, SHARED, PACKAGE})
    assert not unknown, f'modules outside the layers {sorted(RANKS)}: {unknown}'
    assert len(MODULES) > 30 and ALL_IMPORTS


def test_modules_import_only_their_own_layer_or_lower_ones():
    violations = []
    for item in ALL_IMPORTS:
        if not internal(item.target) or item.target == item.module:
            continue
        source, target = layer(item.module), layer(item.target)
        if source == SHARED:
            allowed = False
        elif source == PACKAGE:
            allowed = target in API_LAYERS
        elif target == SHARED:
            allowed = True
        elif target == PACKAGE:
            allowed = False
        else:
            allowed = RANKS[target] <= RANKS[source] and (source, target) not in FORBIDDEN
        if not allowed:
            violations.append(f'{where(item)}: {item.module} ({source}) imports {item.target} '
                              f'({target})')
    assert not violations, 'layer rule broken:\n' + '\n'.join(violations)


def test_no_import_cycle_between_modules():
    graph: Dict[str, Set[str]] = defaultdict(set)
    for item in ALL_IMPORTS:
        if item.target in MODULES and item.target != item.module:
            graph[item.module].add(item.target)
    # Tarjan's strongly connected components, iteratively.
    index: Dict[str, int] = {}
    low: Dict[str, int] = {}
    stack: List[str] = []
    on_stack: Set[str] = set()
    cycles = []
    for start in MODULES:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    cycles.append(' <-> '.join(sorted(component)))
    assert not cycles, 'import cycles:\n' + '\n'.join(cycles)


def test_no_private_name_is_imported_from_another_module():
    violations = [f'{where(item)}: {item.module} takes {name} from {item.target}'
                  for item in ALL_IMPORTS if internal(item.target) and item.target != item.module
                  for name in item.names if name.startswith('_')]
    for module, path in MODULES.items():
        tree = ast.parse(path.read_text(encoding='utf-8'))
        aliases = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                aliases.update({alias.asname: alias.name for alias in node.names
                                if alias.asname and internal(alias.name)})
            elif isinstance(node, ast.ImportFrom):
                target = _absolute(module, node)
                aliases.update({alias.asname or alias.name: f'{target}.{alias.name}'
                                for alias in node.names if f'{target}.{alias.name}' in MODULES})
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                    and node.value.id in aliases and node.attr.startswith('_')):
                violations.append(f'{path.relative_to(ROOT.parent)}:{node.lineno}: {module} '
                                  f'uses {aliases[node.value.id]}.{node.attr}')
    assert not violations, 'private names used across modules:\n' + '\n'.join(violations)


def test_ros_is_imported_only_under_ctid_ros_ros():
    violations = [f'{where(item)}: {item.module} imports {item.target}'
                  for item in ALL_IMPORTS
                  if not internal(item.target) and layer(item.module) != 'ros'
                  and ROS_PACKAGE.match(item.target.split('.')[0])]
    assert not violations, 'ROS imported outside ctid_ros/ros:\n' + '\n'.join(violations)


def test_the_checks_see_what_they_check():
    """The rules above would notice: known imports of each kind are found."""
    found = {(item.module, item.target) for item in ALL_IMPORTS}
    assert ('ctid_ros.ros.runner', 'rclpy') in found
    assert ('ctid_ros.cli.main', 'ctid_ros.cli.replay') in found      # a string, for importlib
    assert ('ctid_ros.cli.node', 'ctid_ros.ros.node') in found        # inside a function
    assert ('ctid_ros.streaming.buffer', 'ctid_ros.streaming.contract') in found
    assert ROS_PACKAGE.match('diagnostic_msgs') and ROS_PACKAGE.match('std_srvs')
    assert not ROS_PACKAGE.match('rosbags') and not ROS_PACKAGE.match('mcap_ros2')
