"""The README's module paths, files and commands point at what exists."""

import importlib
from pathlib import Path
import re

import pytest

REPOSITORY = Path(__file__).resolve().parents[1]
README = (REPOSITORY / 'README.md').read_text(encoding='utf-8')


def resolves(dotted: str) -> bool:
    """Return True if ``dotted`` is a module or an attribute of one (``module.name``)."""
    parts = dotted.split('.')
    for split in range(len(parts), 0, -1):
        try:
            target = importlib.import_module('.'.join(parts[:split]))
        except ImportError:
            continue
        for name in parts[split:]:
            if not hasattr(target, name):
                return False
            target = getattr(target, name)
        return True
    return False


@pytest.mark.parametrize('dotted', sorted(set(re.findall(r'\bctid_ros(?:\.\w+)+', README))))
def test_dotted_paths_resolve(dotted):
    assert resolves(dotted), dotted


@pytest.mark.parametrize('path', sorted(set(re.findall(
    r'\b((?:ctid_ros|test|config|docs|bench)/[\w./]*\w/?)', README))))
def test_paths_exist(path):
    assert (REPOSITORY / path).exists(), path


def test_layout_names_every_module_outside_estimation():
    layout = README[README.index('## Layout'):README.index('## References')]
    missing = sorted(str(path.relative_to(REPOSITORY)) for path in
                     (REPOSITORY / 'ctid_ros').glob('*/*.py')
                     if path.parent.name != 'estimation' and path.stem not in (
                         '__init__', '__main__') and f'`{path.name}`' not in layout
                     and f'/{path.name}`' not in layout)
    assert not missing, f'modules missing in the README layout: {missing}'


def test_commands_name_existing_modules_and_scripts():
    for module in re.findall(r'python -m ([\w.]+)', README):
        assert importlib.util.find_spec(module) is not None, module
    setup = (REPOSITORY / 'setup.py').read_text(encoding='utf-8')
    for script in ('ctid', 'ctid_node', 'ctid_plant'):
        assert re.search(rf"'{script} = ctid_ros\.[\w.]+:main'", setup), script
        assert f'{script} ' in README
