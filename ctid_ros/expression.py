"""
Safe parsing of transfer-function text into sympy expressions.

Model strings arrive from ROS parameters that anyone on the graph can set, so they are never
handed to ``eval``, ``sympify`` or ``parse_expr``. This module tokenises the text itself and
builds the sympy expression with a small recursive-descent parser that knows exactly one
grammar::

    expression := term (('+' | '-') term)*
    term       := unary (('*' | '/') unary)*
    unary      := ('+' | '-') unary | power
    power      := atom (('**' | '^') unary)?
    atom       := number | name | 'exp' '(' expression ')' | '(' expression ')'

Names are parameters (or the Laplace variable ``s``, or the constant ``pi``); ``exp`` is the only
function. Everything else (attribute access, other calls, strings, keywords, oversized numbers
or exponents, deep nesting) raises :class:`~ctid_ros.errors.ModelError` with the column of the
offending part.
"""

from dataclasses import dataclass
import re
from typing import List

from ctid_ros.errors import ModelError
import sympy as sp

LAPLACE = sp.Symbol('s')
MAX_LENGTH = 2000
MAX_NAME_LENGTH = 64
MAX_DEPTH = 40
MAX_EXPONENT = 16
MAX_NUMBER_DIGITS = 32

_TOKEN = re.compile(
    r'\s*(?:'
    r'(?P<number>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)'
    r'|(?P<name>[A-Za-z_][A-Za-z0-9_]*)'
    r'|(?P<op>\*\*|[-+*/^()])'
    r')')


@dataclass(frozen=True)
class Token:
    """One lexical token with its column in the source text (0-based)."""

    kind: str
    text: str
    column: int


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
    stripped_end = len(text.rstrip())
    while position < stripped_end:
        match = _TOKEN.match(text, position)
        if match is None or match.end() == position:
            bad = text[position:].lstrip()
            column = len(text) - len(bad)
            raise ModelError(f'unexpected character {bad[0]!r} at column {column + 1}; only '
                             'numbers, names, + - * / ** ^ ( ) and exp(...) are allowed'
                             + _pointer(text, column))
        kind = match.lastgroup
        column = match.start(kind)
        tokens.append(Token(kind, match.group(kind), column))
        position = match.end()
    tokens.append(Token('end', '', len(text)))
    return tokens


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

    def parse(self) -> sp.Expr:
        if self.current.kind == 'end':
            raise ModelError('model expression is empty')
        result = self.expression()
        if self.current.kind != 'end':
            raise self.error(f'unexpected {self.current.text!r}', self.current)
        return result

    def nested(self, token: Token):
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise self.error(f'expression nested deeper than {MAX_DEPTH} levels', token)

    def expression(self) -> sp.Expr:
        result = self.term()
        while self.current.text in ('+', '-'):
            operator = self.advance().text
            right = self.term()
            result = result + right if operator == '+' else result - right
        return result

    def term(self) -> sp.Expr:
        result = self.unary()
        while self.current.text in ('*', '/'):
            operator = self.advance()
            right = self.unary()
            if operator.text == '*':
                result = result * right
            elif right == 0:
                raise self.error('division by zero', operator)
            else:
                result = result / right
        return result

    def unary(self) -> sp.Expr:
        token = self.current
        if token.text in ('+', '-'):
            self.advance()
            self.nested(token)
            operand = self.unary()
            self.depth -= 1
            return -operand if token.text == '-' else operand
        return self.power()

    def power(self) -> sp.Expr:
        base = self.atom()
        if self.current.text not in ('**', '^'):
            return base
        operator = self.advance()
        self.nested(operator)
        exponent_token = self.current
        exponent = self.unary()
        self.depth -= 1
        return self.checked_power(base, exponent, exponent_token)

    def checked_power(self, base: sp.Expr, exponent: sp.Expr, token: Token) -> sp.Expr:
        if not exponent.is_Number:
            raise self.error('exponents must be numbers', token)
        if abs(exponent) > MAX_EXPONENT:
            raise self.error(f'exponent {exponent} is larger than {MAX_EXPONENT} in magnitude',
                             token)
        if base.has(LAPLACE) and not exponent.is_Integer:
            raise self.error('powers of expressions in s must have integer exponents', token)
        if base == 0 and exponent < 0:
            raise self.error('division by zero', token)
        return base ** exponent

    def atom(self) -> sp.Expr:
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

    def number(self, token: Token) -> sp.Expr:
        if len(token.text) > MAX_NUMBER_DIGITS:
            raise self.error(f'number longer than {MAX_NUMBER_DIGITS} characters', token)
        value = sp.Rational(token.text)
        if value != 0 and not (1e-300 < abs(value) < 1e300):
            raise self.error(f'number {token.text} is out of range', token)
        return value

    def name(self, token: Token) -> sp.Expr:
        name = token.text
        if self.current.text == '(':
            if name != 'exp':
                raise self.error(f'function {name}(...) is not allowed; the only function is '
                                 'exp(-tau*s), a dead time', token)
            open_paren = self.advance()
            self.nested(open_paren)
            argument = self.expression()
            self.expect(')')
            self.depth -= 1
            return sp.exp(argument)
        if name == 'exp':
            raise self.error('exp must be called as exp(...)', token)
        if name.startswith('_'):
            raise self.error(f'names may not start with "_" ({name!r})', token)
        if len(name) > MAX_NAME_LENGTH:
            raise self.error(f'name longer than {MAX_NAME_LENGTH} characters', token)
        if name == 's':
            return LAPLACE
        if name == 'pi':
            return sp.pi
        if name not in self.symbols:
            self.symbols[name] = sp.Symbol(name, real=True)
        return self.symbols[name]


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
    expression = parser.parse()
    return expression, tuple(parser.symbols.values())
