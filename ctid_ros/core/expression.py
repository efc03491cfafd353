"""
Safe parsing of transfer-function text into sympy expressions.

Model strings arrive from ROS parameters that anyone on the graph can set, so they are never
handed to ``eval``, ``sympify`` or ``parse_expr``. This module tokenises the text itself and
builds the sympy expression with a small recursive-descent parser that knows exactly one
grammar::

    equation   := expression ('=' expression)?     (model equations only)
    expression := term (('+' | '-') term)*
    term       := unary (('*' | '/') unary)*
    unary      := ('+' | '-') unary | power
    power      := atom (('**' | '^') unary)?
    atom       := number | name | 'exp' '(' expression ')' | '(' expression ')'

Names are parameters (or the Laplace variable ``s``, or the constant ``pi``); ``exp`` is the only
function. Everything else (attribute access, other calls, strings, keywords, oversized numbers
or exponents, deep nesting) raises :class:`~ctid_ros.errors.ModelError` with the column of the
offending part.

Text that is short and shallow can still describe enormous objects (``(a+b+c+s)**16``,
``((9**16)**16)**16``, ``1e999999999``), and sympy would expand or compute them eagerly or when
the model takes the expression apart. The parser therefore carries an upper bound of the size
of every sub-expression written as ``numerator/denominator`` (number of terms once expanded,
degree in ``s``, digits of the numbers) and rejects the text before anything large is built.
"""

from dataclasses import dataclass
import keyword
import math
import re
from typing import List, Tuple

from ctid_ros.errors import ModelError
import sympy as sp

LAPLACE = sp.Symbol('s')
MAX_LENGTH = 2000
MAX_NAME_LENGTH = 64
MAX_DEPTH = 40
MAX_EXPONENT = 16
MAX_NUMBER_DIGITS = 32
# Bounds of the size of an expression, checked before sympy builds it (see the module notes).
MAX_DEGREE = 32          # degree in s of a numerator or denominator
MAX_TERMS = 1024         # terms of an expanded numerator or denominator
MAX_VALUE_DIGITS = 1000  # decimal digits of the exact numbers
MAX_WORK = 2048          # (numerator + denominator terms) * number of parameters

_ASCII_SPACE = ' \t\n\r\f\v'
# re.ASCII: only ASCII digits and white space (no other Unicode digits that mean something else).
_TOKEN = re.compile(
    r'\s*(?:'
    r'(?P<number>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)'
    r'|(?P<name>[A-Za-z_][A-Za-z0-9_]*)'
    r'|(?P<op>\*\*|[-+*/^()=])'
    r')', re.ASCII)


@dataclass(frozen=True)
class Token:
    """One lexical token with its column in the source text (0-based)."""

    kind: str
    text: str
    column: int


@dataclass(frozen=True)
class Size:
    """
    Upper bound of the size of ``numerator/denominator`` once put over a common denominator.

    ``*_terms`` count the terms of the expanded polynomials (in ``s`` and the parameters),
    ``*_degree`` their degree in ``s``; ``digits`` bounds the decimal digits of the exact
    rational numbers involved.
    """

    num_terms: int = 1
    den_terms: int = 1
    num_degree: int = 0
    den_degree: int = 0
    digits: int = 0

    def __add__(self, other: 'Size') -> 'Size':
        return Size(self.num_terms * other.den_terms + other.num_terms * self.den_terms,
                    self.den_terms * other.den_terms,
                    max(self.num_degree + other.den_degree, other.num_degree + self.den_degree),
                    self.den_degree + other.den_degree,
                    max(self.digits, other.digits) + 1)

    def __mul__(self, other: 'Size') -> 'Size':
        return Size(self.num_terms * other.num_terms, self.den_terms * other.den_terms,
                    self.num_degree + other.num_degree, self.den_degree + other.den_degree,
                    self.digits + other.digits)

    def inverse(self) -> 'Size':
        return Size(self.den_terms, self.num_terms, self.den_degree, self.num_degree,
                    self.digits)

    def power(self, exponent) -> 'Size':
        """Size of ``self ** exponent`` (integer exponents expand multinomially)."""
        base = self if exponent >= 0 else self.inverse()
        k = int(sp.ceiling(abs(exponent)))
        if exponent.is_Integer:
            return Size(math.comb(base.num_terms + k - 1, k),
                        math.comb(base.den_terms + k - 1, k),
                        k * base.num_degree, k * base.den_degree, k * base.digits)
        # A fractional power of an expression free of s (enforced by the parser) stays one
        # generator, except that sympy's expand splits off its integer part.
        return Size(math.comb(base.num_terms + k - 1, k) + 1,
                    math.comb(base.den_terms + k - 1, k) + 1,
                    0, 0, k * base.digits + 1)

    def problem(self):
        """Return what exceeds the limits, or None."""
        if max(self.num_degree, self.den_degree) > MAX_DEGREE:
            return f'its degree in s would exceed {MAX_DEGREE}'
        if max(self.num_terms, self.den_terms) > MAX_TERMS:
            return f'it would expand to more than {MAX_TERMS} terms'
        if self.digits > MAX_VALUE_DIGITS:
            return f'its numbers would have more than {MAX_VALUE_DIGITS} digits'
        return None


_ATOM = Size()


def _pointer(text: str, column: int) -> str:
    return f'\n  {text}\n  {" " * column}^'


def tokenize(text: str) -> List[Token]:
    """Split ``text`` into tokens, rejecting any character outside the model grammar."""
    if not isinstance(text, str):
        raise ModelError(f'model expression must be a string, got {type(text).__name__}')
    if len(text) > MAX_LENGTH:
        raise ModelError(f'model expression is {len(text)} characters long; the limit is '
                         f'{MAX_LENGTH}')
    tokens = []
    position = 0
    stripped_end = len(text.rstrip(_ASCII_SPACE))
    while position < stripped_end:
        match = _TOKEN.match(text, position)
        if match is None or match.end() == position:
            bad = text[position:].lstrip(_ASCII_SPACE)
            column = len(text) - len(bad)
            raise ModelError(f'unexpected character {bad[0]!r} at column {column + 1}; only '
                             'numbers, names, + - * / ** ^ ( ), = and exp(...) are allowed'
                             + _pointer(text, column))
        kind = match.lastgroup
        column = match.start(kind)
        tokens.append(Token(kind, match.group(kind), column))
        position = match.end()
    tokens.append(Token('end', '', len(text)))
    return tokens


Node = Tuple[sp.Expr, Size]


class _Parser:
    """Recursive-descent parser over the token list; builds sympy objects directly."""

    def __init__(self, text: str):
        self.text = text
        self.tokens = tokenize(text)
        self.index = 0
        self.depth = 0
        self.symbols = {}

    def error(self, message: str, token: Token) -> ModelError:
        return ModelError(f'{message} at column {token.column + 1}'
                          + _pointer(self.text, token.column))

    def checked(self, size: Size, token: Token) -> Size:
        problem = size.problem()
        if problem is not None:
            raise self.error(f'expression too large: {problem}', token)
        return size

    @property
    def current(self) -> Token:
        return self.tokens[self.index]

    def advance(self) -> Token:
        token = self.tokens[self.index]
        self.index += 1
        return token

    def expect(self, text: str) -> Token:
        token = self.current
        if token.text != text:
            found = repr(token.text) if token.kind != 'end' else 'end of expression'
            raise self.error(f'expected {text!r} but found {found}', token)
        return self.advance()

    def parse(self, equation: bool = False) -> List[sp.Expr]:
        if self.current.kind == 'end':
            raise ModelError('model expression is empty')
        result, size = self.expression()
        sides = [result]
        if equation and self.current.text == '=':
            sign = self.advance()
            if self.current.kind == 'end':
                raise self.error("nothing after '='", self.current)
            right, right_size = self.expression()
            sides.append(right)
            size = self.checked(size + right_size, sign)
        if self.current.text == '=':
            raise self.error("'=' is only allowed once, in a model equation", self.current)
        if self.current.kind != 'end':
            raise self.error(f'unexpected {self.current.text!r}', self.current)
        work = (size.num_terms + size.den_terms) * max(1, len(self.symbols))
        if work > MAX_WORK:
            raise ModelError(f'model expression too large: up to {size.num_terms} + '
                             f'{size.den_terms} terms in {len(self.symbols)} parameters '
                             f'exceed the limit of {MAX_WORK} (terms times parameters)')
        return sides

    def nested(self, token: Token):
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise self.error(f'expression nested deeper than {MAX_DEPTH} levels', token)

    def expression(self) -> Node:
        result, size = self.term()
        while self.current.text in ('+', '-'):
            operator = self.advance()
            right, right_size = self.term()
            size = self.checked(size + right_size, operator)
            result = result + right if operator.text == '+' else result - right
        return result, size

    def term(self) -> Node:
        result, size = self.unary()
        while self.current.text in ('*', '/'):
            operator = self.advance()
            right, right_size = self.unary()
            if operator.text == '*':
                size = self.checked(size * right_size, operator)
                result = result * right
            elif right == 0:
                raise self.error('division by zero', operator)
            else:
                size = self.checked(size * right_size.inverse(), operator)
                result = result / right
        return result, size

    def unary(self) -> Node:
        token = self.current
        if token.text in ('+', '-'):
            self.advance()
            self.nested(token)
            operand, size = self.unary()
            self.depth -= 1
            return (-operand if token.text == '-' else operand), size
        return self.power()

    def power(self) -> Node:
        base = self.atom()
        if self.current.text not in ('**', '^'):
            return base
        operator = self.advance()
        self.nested(operator)
        exponent_token = self.current
        exponent, _ = self.unary()
        self.depth -= 1
        return self.checked_power(base, exponent, exponent_token)

    def checked_power(self, base: Node, exponent: sp.Expr, token: Token) -> Node:
        base, size = base
        if not exponent.is_Number:
            raise self.error('exponents must be numbers', token)
        if abs(exponent) > MAX_EXPONENT:
            raise self.error(f'exponent {exponent} is larger than {MAX_EXPONENT} in magnitude',
                             token)
        if base.has(LAPLACE) and not exponent.is_Integer:
            raise self.error('powers of expressions in s must have integer exponents', token)
        if base == 0 and exponent < 0:
            raise self.error('division by zero', token)
        # Checked before sympy evaluates the power (it computes numeric powers eagerly).
        size = self.checked(size.power(exponent), token)
        return base ** exponent, size

    def atom(self) -> Node:
        token = self.current
        if token.kind == 'number':
            self.advance()
            return self.number(token)
        if token.kind == 'name':
            self.advance()
            return self.name(token)
        if token.text == '(':
            self.advance()
            self.nested(token)
            inner = self.expression()
            self.expect(')')
            self.depth -= 1
            return inner
        found = repr(token.text) if token.kind != 'end' else 'end of expression'
        raise self.error(f'expected a number, a name or "(" but found {found}', token)

    def number(self, token: Token) -> Node:
        if len(token.text) > MAX_NUMBER_DIGITS:
            raise self.error(f'number longer than {MAX_NUMBER_DIGITS} characters', token)
        # Range check on the float first: sp.Rational('1e999999999') would compute 10**999999999.
        if not re.split('[eE]', token.text)[0].strip('0.'):
            return sp.Integer(0), _ATOM
        if not 1e-300 < float(token.text) < 1e300:
            raise self.error(f'number {token.text} is out of range', token)
        value = sp.Rational(token.text)
        digits = len(str(abs(value.p))) + len(str(value.q))
        return value, Size(digits=digits)

    def name(self, token: Token) -> Node:
        name = token.text
        if self.current.text == '(':
            if name != 'exp':
                raise self.error(f'function {name}(...) is not allowed; the only function is '
                                 'exp(-tau*s), a dead time', token)
            open_paren = self.advance()
            self.nested(open_paren)
            argument, _ = self.expression()
            self.expect(')')
            self.depth -= 1
            return sp.exp(argument), Size(digits=1)
        if name == 'exp':
            raise self.error('exp must be called as exp(...)', token)
        if name.startswith('_'):
            raise self.error(f'names may not start with "_" ({name!r})', token)
        if len(name) > MAX_NAME_LENGTH:
            raise self.error(f'name longer than {MAX_NAME_LENGTH} characters', token)
        if keyword.iskeyword(name):
            raise self.error(f'{name!r} is a reserved word and cannot name a parameter', token)
        if name == 's':
            return LAPLACE, Size(num_degree=1)
        if name == 'pi':
            return sp.pi, Size(digits=1)
        if name not in self.symbols:
            self.symbols[name] = sp.Symbol(name, real=True)
        return self.symbols[name], _ATOM


def parse_expression(text: str) -> tuple:
    """
    Parse transfer-function text safely.

    Parameters
    ----------
    text : str
        Expression in the Laplace variable ``s``, e.g. ``"K*exp(-tau*s)/(T*s + 1)"``.

    Returns
    -------
    expression : sympy.Expr
        The parsed expression.
    parameters : tuple of sympy.Symbol
        The parameters (every name other than ``s`` and ``pi``) in order of first appearance.

    Raises
    ------
    ModelError
        If the text is not in the grammar, with the column of the offending part.

    """
    parser = _Parser(text)
    expression, = parser.parse()
    return expression, tuple(parser.symbols.values())


def parse_equation(text: str) -> tuple:
    """
    Parse a model equation ``left = right`` (or a single expression) safely.

    Parameters
    ----------
    text : str
        For example ``"M*s**2*y + Fv*s*y = 35.15*u - Fc*w - off"``; ``s`` acts on the signal
        it multiplies.

    Returns
    -------
    sides : list of sympy.Expr
        ``[left, right]``, or ``[expression]`` when the text has no ``=``.
    names : tuple of sympy.Symbol
        Every name other than ``s`` and ``pi`` (signals and parameters) in order of first
        appearance.

    Raises
    ------
    ModelError
        As :func:`parse_expression`; also for more than one ``=``.

    """
    parser = _Parser(text)
    sides = parser.parse(equation=True)
    return sides, tuple(parser.symbols.values())
