"""package.xml and setup.py declare every third-party package that ctid_ros imports."""

import ast
from pathlib import Path
import re
import sys
import xml.etree.ElementTree as ElementTree

from ctid_ros.streaming.contract import DIAGNOSTIC_ARRAY, FLOAT64, FLOAT64_MULTI_ARRAY

REPOSITORY = Path(__file__).resolve().parents[1]
# rosdep key and pip distribution of every Python package ctid_ros imports (None: no such key).
PYTHON = {
    'numpy': ('python3-numpy', 'numpy'), 'scipy': ('python3-scipy', 'scipy'),
    'sympy': ('python3-sympy', 'sympy'), 'yaml': ('python3-yaml', 'PyYAML'),
    'matplotlib': ('python3-matplotlib', 'matplotlib'), 'tqdm': ('python3-tqdm', 'tqdm'),
    'rosbags': ('python3-rosbags-pip', 'rosbags'), 'mcap': ('mcap-ros2-support', 'mcap'),
    'mcap_ros2': ('mcap-ros2-support', 'mcap-ros2-support'),
    'threadpoolctl': (None, 'threadpoolctl'),
    # No rosdep keys (ros/rosdistro rosdep/python.yaml and base.yaml): pip only.
    'zstandard': (None, 'zstandard'), 'lz4': (None, 'lz4'),
    # ctid fleet (pip only: no rosdep keys).
    'distributed': (None, 'distributed'), 'pyarrow': (None, 'pyarrow'),
}
# Imported by name at run time, not by an import statement: the node's output messages and
# the header stamp nested in them.
DYNAMIC = {msgtype.split('/')[0] for msgtype in (DIAGNOSTIC_ARRAY, FLOAT64, FLOAT64_MULTI_ARRAY)
           } | {'builtin_interfaces'}
# rclpy.lifecycle (the managed node) needs both; the rclpy wheel does not bring them.
DYNAMIC |= {'rcl_lifecycle', 'lifecycle_msgs'}
ROS = re.compile(r'(rclpy|rcl_\w+|builtin_interfaces|\w+_msgs|\w+_srvs|\w+_interfaces)\Z')


def third_party_imports():
    found = set()
    for path in (REPOSITORY / 'ctid_ros').rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
            if isinstance(node, ast.Import):
                found.update(alias.name.split('.')[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and not node.level:
                found.add(node.module.split('.')[0])
    return {name for name in found
            if name != 'ctid_ros' and name not in sys.stdlib_module_names}


def exec_depends():
    root = ElementTree.parse(REPOSITORY / 'package.xml').getroot()
    return {element.text for element in root.iter('exec_depend')}


def setup_requirements():
    """Return the distributions of install_requires and all extras, read from setup.py."""
    tree = ast.parse((REPOSITORY / 'setup.py').read_text(encoding='utf-8'))
    lists = {node.targets[0].id: ast.literal_eval(node.value) for node in tree.body
             if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name)
             and isinstance(node.value, ast.List)}
    call = next(node for node in ast.walk(tree) if isinstance(node, ast.Call)
                and getattr(node.func, 'id', '') == 'setup')
    keywords = {keyword.arg: keyword.value for keyword in call.keywords}
    requirements = list(ast.literal_eval(keywords['install_requires']))
    for value in keywords['extras_require'].values:
        if isinstance(value, ast.Name):
            requirements += lists[value.id]
        else:
            left = value.left if isinstance(value, ast.BinOp) else value
            requirements += ast.literal_eval(left)
    return {re.split(r'[<>=!\[]', requirement)[0] for requirement in requirements}


def test_every_import_is_a_declared_dependency():
    imported = third_party_imports()
    unknown = sorted(name for name in imported if name not in PYTHON and not ROS.match(name))
    assert not unknown, f'add these to package.xml, setup.py and PYTHON here: {unknown}'
    declared = exec_depends()
    keys = {PYTHON[name][0] for name in imported if name in PYTHON} - {None}
    ros = {name for name in imported if ROS.match(name)} | DYNAMIC
    assert keys | ros <= declared, f'missing in package.xml: {sorted(keys | ros - declared)}'
    assert declared <= keys | ros, f'not imported: {sorted(declared - keys - ros)}'
    distributions = {PYTHON[name][1] for name in imported if name in PYTHON}
    assert distributions <= setup_requirements(), sorted(distributions - setup_requirements())
    assert {'geometry_msgs', 'sensor_msgs', 'rcl_interfaces'} <= ros


def test_ament_python_layout_that_colcon_needs():
    """What colcon's ament_python build reads (``make colcon-check`` builds and tests for real)."""
    root = ElementTree.parse(REPOSITORY / 'package.xml').getroot()
    assert root.get('format') == '3' and root.findtext('name') == 'ctid_ros'
    assert root.find('export').findtext('build_type') == 'ament_python'
    marker = REPOSITORY / 'resource' / 'ctid_ros'
    assert marker.is_file() and marker.read_bytes().strip() == b''
    config = (REPOSITORY / 'setup.cfg').read_text(encoding='utf-8')
    assert 'script_dir=$base/lib/ctid_ros' in config
    assert 'install_scripts=$base/lib/ctid_ros' in config
    setup = (REPOSITORY / 'setup.py').read_text(encoding='utf-8')
    for entry in ("('share/ament_index/resource_index/packages', ['resource/' + PACKAGE])",
                  "('share/' + PACKAGE, ['package.xml'])",
                  "('share/' + PACKAGE + '/config', glob('config/*.yaml'))"):
        assert entry in setup, entry
    assert 'tests_require' not in setup     # setuptools warns about it on every install
