"""
No function of ``ctid_ros/estimation`` is more complex than a reader can follow.

The McCabe (cyclomatic) complexity of every function and method, as flake8's own ``mccabe``
counts it (a nested function counts within the function that defines it), stays at or below
:data:`LIMIT`. The estimator's driver used to hold the record: ``iterate()`` at 30 with six
mode flags, now a frozen policy and a named step schedule (issue 27).
"""

import ast
from pathlib import Path
from typing import Iterator, Tuple

import mccabe

LIMIT = 25
ESTIMATION = Path(__file__).resolve().parents[1] / 'ctid_ros' / 'estimation'


def complexities(path: Path) -> Iterator[Tuple[str, int, int]]:
    """Yield ``(name, line, complexity)`` for every function and method in ``path``."""
    tree = compile(path.read_text(encoding='utf-8'), str(path), 'exec', ast.PyCF_ONLY_AST)
    visitor = mccabe.PathGraphingAstVisitor()
    visitor.preorder(tree, visitor)
    for graph in visitor.graphs.values():
        yield graph.entity, graph.lineno, graph.complexity()


def test_the_count_sees_a_complex_function(tmp_path):
    branches = '\n'.join(f'    if x == {value}:\n        return {value}' for value in range(30))
    source = tmp_path / 'branchy.py'
    source.write_text(f'def branchy(x):\n{branches}\n    return None\n', encoding='utf-8')
    assert list(complexities(source)) == [('branchy', 1, 31)]


def test_no_function_in_estimation_above_the_limit():
    paths = sorted(ESTIMATION.glob('*.py'))
    assert len(paths) > 10
    measured = [(f'{path.name}:{line} {name}', value)
                for path in paths for name, line, value in complexities(path)]
    assert len(measured) > 100
    above = [f'{where} ({value})' for where, value in measured if value > LIMIT]
    assert not above, f'McCabe complexity above {LIMIT}: {", ".join(above)}'
