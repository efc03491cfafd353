"""docs/parameters.md documents every parameter a running ctid_node lists, as it lists it."""

import importlib.util
from pathlib import Path
import re

from ctid_ros.streaming.config import PARAMETERS, PER_PARAMETER
import pytest

GENERATOR = Path(__file__).resolve().parents[1] / 'docs' / 'generate_parameters.py'


def generator():
    """Import docs/generate_parameters.py (a script, not part of the package)."""
    spec = importlib.util.spec_from_file_location('generate_parameters', GENERATOR)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def documented(text):
    """Return the parameter names of the reference's table rows."""
    return set(re.findall(r'^\| `([^`]+)` \|', text, flags=re.MULTILINE))


def test_every_declaration_of_the_configuration_has_a_row():
    names = documented(generator().REFERENCE.read_text(encoding='utf-8'))
    missing = {spec.name for spec in PARAMETERS} - names
    missing |= {f'{prefix}.<name>' for prefix in PER_PARAMETER} - names
    assert not missing, f'parameters missing in docs/parameters.md: {sorted(missing)}'


@pytest.mark.ros
def test_the_table_is_what_the_running_node_lists():
    module = generator()
    declarations = module.live_declarations()
    text = module.REFERENCE.read_text(encoding='utf-8')
    listed = {row.name for row in declarations}
    assert len(listed) >= len(PARAMETERS) + len(PER_PARAMETER)
    missing = listed - documented(text)
    assert not missing, f'listed by the node, missing in docs/parameters.md: {sorted(missing)}'
    assert module.table_of(text) == module.render(declarations), \
        'docs/parameters.md is out of date: run python docs/generate_parameters.py'
