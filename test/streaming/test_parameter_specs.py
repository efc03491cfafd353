"""The plain parameter specs: importable without the numerical stack, choices as the code's."""

import subprocess
import sys

from ctid_ros.core.simulation import INTERSAMPLE
from ctid_ros.design.tune import CONTROLLERS, METHODS as DESIGN_METHODS
from ctid_ros.estimation.options import INITIAL_STATES, METHODS
from ctid_ros.streaming import parameter_specs


def test_choices_are_those_of_the_estimator_and_the_design():
    assert parameter_specs.ESTIMATION_METHODS == METHODS
    assert parameter_specs.INTERSAMPLE == INTERSAMPLE
    assert parameter_specs.INITIAL_STATES == INITIAL_STATES
    assert parameter_specs.TUNE_CONTROLLERS == ('',) + tuple(CONTROLLERS)
    assert parameter_specs.TUNE_METHODS == tuple(DESIGN_METHODS)


def test_the_specs_import_no_numerical_library():
    code = ('import sys; import ctid_ros.streaming.parameter_specs; '
            "print(sorted({name.split('.')[0] for name in sys.modules} & "
            "{'numpy', 'scipy', 'sympy', 'rclpy', 'yaml'}))")
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            check=True)
    assert result.stdout.strip() == '[]'
