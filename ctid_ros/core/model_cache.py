"""
Models' derivations kept on disk as plain data, so that a model is built without sympy.

Deriving a :class:`~ctid_ros.core.model.Model` takes sympy (a third of a second to import, tens
of milliseconds to derive); what it produces is small: a few names, degrees and flags, and the
arithmetic that turns a parameter vector into the coefficients and their Jacobian. That
arithmetic is kept as a :class:`CoefficientProgram`: a list of operations (``+ - * / **``,
negation, ``sqrt``) on numbered slots and numbers, read from the function sympy generates and
evaluated by a small interpreter that performs the same Python operations in the same order, so
its numbers are those of the generated function, bit for bit.

The store holds data only, never code: a file is JSON of strings, numbers and operation names,
checked entry by entry when it is read (types, slot numbers, operations from the fixed list, no
arithmetic on two integers that could grow without bound) and then interpreted; nothing in it
is executed. A file is used only if the current user owns it and no one else can write it, and
only for the very texts it names, derived by the same versions of ctid_ros's model code and of
sympy (both in the key). Anything unexpected (missing, unreadable, malformed, stale) means the
model is derived again and the file rewritten; a store that cannot be written is skipped.

The directory is ``$CTID_CACHE_DIR`` if set (set it empty to keep nothing on disk), else
``$XDG_CACHE_HOME/ctid_ros/models`` or ``~/.cache/ctid_ros/models``; it holds at most
:data:`MAX_STORED` models.
"""

import ast
import functools
import hashlib
import importlib.util
import inspect
import json
import math
import operator
import os
from pathlib import Path
import stat
import tempfile
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

__all__ = ['CACHE_VARIABLE', 'CoefficientProgram', 'MAX_STORED', 'cache_directory', 'load',
           'store']

CACHE_VARIABLE = 'CTID_CACHE_DIR'
# Models kept on disk at most (a few kilobytes each): model texts can come from anyone on the
# ROS graph, so the store is bounded; beyond it the least recently written models go.
MAX_STORED = 256
# Bumped whenever the stored layout or the meaning of an attribute changes.
_FORMAT = 1
# A stored model is a few kilobytes; anything far larger is not one of ours.
_MAX_FILE_BYTES = 1 << 20
# Integers as large as the model language's numbers (1000 digits), not larger.
_MAX_INTEGER = 10 ** 1100
_BINARY: Dict[str, Callable[[Any, Any], Any]] = {
    '+': operator.add, '-': operator.sub, '*': operator.mul, '/': operator.truediv,
    '**': operator.pow,
}
# The operations of a program, each of two values (a unary one ignores its second, the same
# operand): on numpy scalars (CoefficientProgram.__call__) and on Python floats (.floats).
_OPERATIONS: Dict[str, Callable[[Any, Any], Any]] = {
    **_BINARY, 'neg': lambda value, _: -value, 'sqrt': lambda value, _: np.sqrt(value),
}
_FLOAT_OPERATIONS: Dict[str, Callable[[Any, Any], Any]] = {
    **_OPERATIONS, 'sqrt': lambda value, _: math.sqrt(value),
}
_AST_BINARY = {ast.Add: '+', ast.Sub: '-', ast.Mult: '*', ast.Div: '/', ast.Pow: '**'}
# Names of the generated function's namespace (sympy's numpy printer) and what they are.
_FUNCTIONS = {'sqrt': np.sqrt}
_CONSTANTS = {'pi': np.pi}
# The model's attributes kept on disk, with their types.
_ATTRIBUTES = {
    'expression': str, 'controller': (str, type(None)), 'inputs': tuple, 'output': str,
    'constant_input': bool, 'parameters': tuple, 'num_degree': int, 'den_degree': int,
    '_channels': int, 'is_affine': bool, 'has_delay': bool, 'delay_is_estimated': bool,
    'integrators': int,
}


class CoefficientProgram:
    """
    Straight-line arithmetic from a parameter vector to a list of numbers, held as data.

    ``operations`` are tuples, each filling the next slot after the ``parameters`` arguments:
    ``('const', number)``, ``('neg', slot)``, ``('sqrt', slot)`` or ``(op, slot, slot)`` with
    ``op`` one of ``+ - * / **``; ``outputs`` are the slots returned, in order. Calling the
    program with the parameter values returns the list of the output slots' values.
    """

    def __init__(self, parameters: int, operations: Sequence[Tuple], outputs: Sequence[int]):
        self.parameters = parameters
        self.operations = [tuple(operation) for operation in operations]
        self.outputs = list(outputs)
        self._template, self._steps = self._float_steps(self._check())
        # The output slots read by one C call: a tuple of several, a single value of one (an
        # empty list, through an empty slice, of none); :meth:`floats` makes each 1-D.
        self._pick = operator.itemgetter(*(self.outputs or [slice(0, 0)]))

    def _check(self) -> List[Any]:
        """
        Raise ValueError unless every operation is well formed (see the module notes).

        Returns the value of every slot that depends on no parameter (None for the others).
        """
        if type(self.parameters) is not int or self.parameters < 0:
            raise ValueError('bad parameter count')
        integer = [False] * self.parameters     # which slots hold Python integers
        # The value of each slot that depends on no parameter, computed here once: arithmetic
        # that fails on numbers alone (1/0, 10.0**400) is refused now, not met at run time.
        constant: List[Any] = [None] * self.parameters
        for operation in self.operations:
            code, *operands = operation
            if code == 'const':
                value, = operands
                if type(value) is int:
                    if abs(value) > _MAX_INTEGER:
                        raise ValueError('integer too large')
                elif type(value) is not float or not math.isfinite(value):
                    raise ValueError('bad constant')
                integer.append(type(value) is int)
                constant.append(value)
                continue
            if any(type(slot) is not int or not 0 <= slot < len(integer) for slot in operands):
                raise ValueError('bad slot')
            if code in ('neg', 'sqrt') and len(operands) == 1:
                integer.append(code == 'neg' and integer[operands[0]])
            elif code in _BINARY and len(operands) == 2:
                # Two integers only ever meet in a division (a rational such as 1/2): sums,
                # products and powers of integers could grow without bound.
                if integer[operands[0]] and integer[operands[1]] and code != '/':
                    raise ValueError('arithmetic on two integers')
                integer.append(False)
            else:
                raise ValueError(f'bad operation {code!r}')
            values = [constant[slot] for slot in operands]
            constant.append(None if None in values else _folded(code, values))
        if any(type(slot) is not int or not 0 <= slot < len(integer) for slot in self.outputs):
            raise ValueError('bad output slot')
        return constant

    def _float_steps(self, constant: List[Any]) -> Tuple[List[Any], List[Tuple]]:
        """
        Return the slots :meth:`floats` starts from and the operations it performs.

        The slots that depend on no parameter hold their values (as Python numbers: the same
        values); each step is ``(slot, function of two values, operand, operand)``, a unary
        operation reading its one operand twice.
        """
        template = [value if type(value) is int else None if value is None else float(value)
                    for value in constant]
        steps = []
        for slot, (code, *operands) in enumerate(self.operations, start=self.parameters):
            if template[slot] is None:
                steps.append((slot, _FLOAT_OPERATIONS[code], operands[0], operands[-1]))
        return template, steps

    def __call__(self, *theta) -> List[Any]:
        if len(theta) != self.parameters:
            raise TypeError(f'expected {self.parameters} parameter values, got {len(theta)}')
        slots = list(theta)
        for code, *operands in self.operations:
            slots.append(operands[0] if code == 'const' else
                         _OPERATIONS[code](slots[operands[0]], slots[operands[-1]]))
        return [slots[slot] for slot in self.outputs]

    def floats(self, theta: Sequence[float]) -> Optional[np.ndarray]:
        """
        Return the program's outputs as a float array for Python float parameters, or None.

        Python's float arithmetic and ``math.sqrt`` round as numpy's float scalars do (IEEE
        operations, the C library's ``pow``), so the values are those of calling the program
        with numpy scalars, bit for bit, without numpy's dispatch per operation and with the
        slots that depend on no parameter filled once (the estimator evaluates thousands of
        parameter vectors per fit). None where Python refuses what numpy completes with an
        infinity or NaN (a division by zero, a power that overflows, a negative number to a
        fractional power, the square root of a negative number): call the program with numpy
        scalars then.
        """
        if len(theta) != self.parameters:
            raise TypeError(f'expected {self.parameters} parameter values, got {len(theta)}')
        slots = self._template.copy()
        slots[:self.parameters] = theta
        try:
            for slot, function, first, second in self._steps:
                slots[slot] = function(slots[first], slots[second])
            # A negative number to a fractional power is complex in Python (NaN in numpy):
            # the conversion to floats refuses it.
            return np.array(self._pick(slots), dtype=float, ndmin=1)
        except (ArithmeticError, ValueError, TypeError):
            return None

    def to_data(self) -> Dict[str, Any]:
        """Return the program as JSON-ready data."""
        return {'parameters': self.parameters, 'operations': [list(o) for o in self.operations],
                'outputs': self.outputs}

    @classmethod
    def from_data(cls, data: Any) -> 'CoefficientProgram':
        """Rebuild a program from :meth:`to_data`; ValueError if it is not one."""
        if not isinstance(data, dict) or set(data) != {'parameters', 'operations', 'outputs'}:
            raise ValueError('not a program')
        if not isinstance(data['operations'], list) or not isinstance(data['outputs'], list) or \
                not all(isinstance(o, list) and o and type(o[0]) is str
                        for o in data['operations']):
            raise ValueError('not a program')
        return cls(data['parameters'], data['operations'], data['outputs'])

    @classmethod
    def from_function(cls, function: Callable) -> Optional['CoefficientProgram']:
        """
        Return the program of a function generated by ``sympy.lambdify``, or None.

        The function's source is read back (sympy keeps it for :func:`inspect.getsource`) and
        only the forms its numpy printer writes for the model's arithmetic are accepted:
        assignments of expressions to names, then ``return [...]``. Anything else, None.
        """
        try:
            tree = ast.parse(inspect.getsource(function))
            definition, = tree.body
            return _Translation(definition).program()
        except (OSError, TypeError, ValueError):
            return None


def _folded(code: str, values: List[Any]) -> Any:
    """Return the value of an operation on numbers, as the program computes it, or ValueError."""
    try:
        with np.errstate(all='ignore'):     # numpy's nan and inf are the run time's too
            return _OPERATIONS[code](values[0], values[-1])
    except (ArithmeticError, ValueError, TypeError, AttributeError) as error:
        raise ValueError(f'arithmetic on numbers fails: {error}') from None


class _Translation:
    """The operations of a generated function's body, one slot per value (see from_function)."""

    def __init__(self, definition: ast.FunctionDef):
        if not isinstance(definition, ast.FunctionDef) or definition.decorator_list or \
                definition.args.vararg or definition.args.kwarg or \
                definition.args.kwonlyargs or definition.args.defaults:
            raise ValueError('not a generated function')
        self.names = {argument.arg: index for index, argument in enumerate(definition.args.args)}
        self.parameters = len(self.names)
        self.operations: List[Tuple] = []
        self.body = definition.body

    def program(self) -> CoefficientProgram:
        *assignments, result = self.body
        for statement in assignments:
            if not isinstance(statement, ast.Assign) or len(statement.targets) != 1 or \
                    not isinstance(statement.targets[0], ast.Name) or \
                    statement.targets[0].id in self.names:
                raise ValueError('unexpected statement')
            self.names[statement.targets[0].id] = self.slot(statement.value)
        if not isinstance(result, ast.Return) or not isinstance(result.value, ast.List):
            raise ValueError('unexpected result')
        outputs = [self.slot(element) for element in result.value.elts]
        return CoefficientProgram(self.parameters, self.operations, outputs)

    def emit(self, operation: Tuple) -> int:
        self.operations.append(operation)
        return self.parameters + len(self.operations) - 1

    def slot(self, node: ast.AST) -> int:
        """Emit the operations of one expression; return the slot of its value."""
        if isinstance(node, ast.Constant) and type(node.value) in (int, float):
            return self.emit(('const', node.value))
        if isinstance(node, ast.Name):
            if node.id in self.names:
                return self.names[node.id]
            if node.id in _CONSTANTS:
                return self.emit(('const', _CONSTANTS[node.id]))
        elif isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
            return self.emit(('neg', self.slot(node.operand)))
        elif isinstance(node, ast.BinOp) and type(node.op) in _AST_BINARY:
            left = self.slot(node.left)
            return self.emit((_AST_BINARY[type(node.op)], left, self.slot(node.right)))
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and \
                node.func.id in _FUNCTIONS and len(node.args) == 1 and not node.keywords:
            return self.emit((node.func.id, self.slot(node.args[0])))
        raise ValueError(f'unexpected expression {ast.dump(node)[:80]}')


def cache_directory() -> Optional[Path]:
    """Return the directory of the stored models, None if storing is switched off."""
    configured = os.environ.get(CACHE_VARIABLE)
    if configured is not None:
        return Path(configured) if configured.strip() else None
    base = os.environ.get('XDG_CACHE_HOME', '')
    if not os.path.isabs(base):     # unset, or relative (which the XDG rules ignore)
        base = os.path.join(os.path.expanduser('~'), '.cache')
    # No home directory (expanduser left '~'): nowhere to keep models, rather than the cwd.
    return Path(base) / 'ctid_ros' / 'models' if os.path.isabs(base) else None


@functools.lru_cache(maxsize=1)
def _versions() -> str:
    """Return a digest of what the stored derivations depend on: the model code and sympy."""
    here = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for name in ('model_cache.py', 'derivation.py', 'expression.py', 'model.py'):
        digest.update((here / name).read_bytes())
    spec = importlib.util.find_spec('sympy')
    if spec is None or spec.origin is None:
        raise OSError('sympy is not installed')
    digest.update(Path(spec.origin).with_name('release.py').read_bytes())
    return digest.hexdigest()


def _path(key: Tuple) -> Optional[Path]:
    directory = cache_directory()
    if directory is None:
        return None
    name = hashlib.sha256(json.dumps([_FORMAT, _versions(), list(key)]).encode()).hexdigest()
    return directory / f'{name}.json'


def _owned(path: Path) -> bool:
    """Whether the current user owns the file and its directory and no one else can write."""
    for item in (path.parent, path):
        status = item.stat()
        if status.st_uid != os.getuid() or status.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
            return False
    return True


def load(key: Tuple) -> Optional[Dict[str, object]]:
    """
    Return the stored attributes of the model of ``key``, or None (see the module notes).

    ``key`` is ``(expression, controller, inputs, output)`` as plain strings (``inputs`` a
    tuple of strings or None, ``controller`` a string or None).
    """
    try:
        path = _path(key)
        if path is None or not _owned(path) or path.stat().st_size > _MAX_FILE_BYTES:
            return None
        data = json.loads(path.read_text(encoding='utf-8'))
        return _attributes(data, key)
    except (OSError, ValueError, TypeError, KeyError, RecursionError):
        return None


def _attributes(data: Any, key: Tuple) -> Dict[str, object]:
    """Check the stored data against ``key`` and return the model's attributes."""
    if not isinstance(data, dict) or data.get('key') != _json_key(key) or \
            set(data) != {'key', 'attributes', 'program'}:
        raise ValueError('not this model')
    stored = data['attributes']
    if not isinstance(stored, dict) or set(stored) != set(_ATTRIBUTES):
        raise ValueError('not a model')
    attributes: Dict[str, object] = {}
    for name, kind in _ATTRIBUTES.items():
        value = tuple(stored[name]) if kind is tuple and isinstance(stored[name], list) \
            else stored[name]
        if not isinstance(value, kind) or (kind is int and type(value) is bool) or \
                (kind is tuple and not all(type(item) is str for item in value)):
            raise ValueError(f'bad attribute {name}')
        attributes[name] = value
    program = CoefficientProgram.from_data(data['program'])
    rows = (attributes['_channels'] * (attributes['num_degree'] + 1)
            + attributes['den_degree'] + 2)
    if program.parameters != len(attributes['parameters']) or \
            len(program.outputs) != rows * (1 + program.parameters):
        raise ValueError('program does not fit the model')
    attributes['_evaluate'] = program
    return attributes


def _json_key(key: Tuple) -> List:
    expression, controller, inputs, output = key
    return [expression, controller, None if inputs is None else list(inputs), output]


def store(key: Tuple, attributes: Dict[str, object]) -> None:
    """Keep the derived attributes of the model of ``key`` on disk, if they are data."""
    program = attributes.get('_evaluate')
    if not isinstance(program, CoefficientProgram):
        return      # arithmetic outside the program's forms: derived again each time
    stored = {name: list(value) if isinstance(value, tuple) else value
              for name, value in attributes.items() if name in _ATTRIBUTES}
    data = {'key': _json_key(key), 'attributes': stored, 'program': program.to_data()}
    try:
        path = _path(key)
        if path is None:
            return
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=path.parent, suffix='.tmp')
        try:
            with os.fdopen(handle, 'w', encoding='utf-8') as file:
                json.dump(data, file)
            os.replace(temporary, path)
        except BaseException:
            os.unlink(temporary)
            raise
        _trim(path.parent)
    except (OSError, ValueError):
        pass


def _trim(directory: Path) -> None:
    """Remove the least recently written models beyond :data:`MAX_STORED` (see its note)."""
    files = list(directory.glob('*.json'))
    if len(files) <= MAX_STORED:
        return
    dated = []
    for file in files:
        try:
            dated.append((file.stat().st_mtime, file))
        except OSError:
            continue        # removed meanwhile by another process
    dated.sort()
    for _, file in dated[:len(dated) - MAX_STORED]:
        try:
            file.unlink()
        except OSError:
            pass
