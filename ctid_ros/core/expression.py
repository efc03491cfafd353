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

Names are parameters (or the Laplace variable ``s``, or the constant ``pi``). ``exp`` is the
only function and it only spells a dead time: ``exp(-tau*s)`` whose argument is ``-tau*s`` with
``tau`` free of ``s`` and positive whenever the parameters are (``exp(-tau*s)``,
``exp(-(tau1 + tau2)*s)``, ``exp(-0.1*s)``), written once, as a factor of the whole transfer
function: not in a sum, a denominator, a power, an exponent or the argument of another
``exp``, and neither in a model equation nor in a controller. A time advance (``exp(tau*s)``,
``1/exp(-tau*s)``, ``exp(-tau*s)**-1``) is non-causal and rejected as such. Everything else
(attribute access, other calls, strings, keywords, oversized numbers or exponents, deep
nesting) raises :class:`~ctid_ros.errors.ModelError` with the column of the offending part.

Text that is short and shallow can still describe enormous objects (``(a+b+c+s)**16``,
``((9**16)**16)**16``, ``1e999999999``, ``K/(a0*a1*...*a99)``), and sympy would expand,
compute or differentiate them eagerly or when the model takes the expression apart. The parser
therefore carries an upper bound of the size of every sub-expression written as
``numerator/denominator`` (:class:`Size`: terms once expanded, factors per term, degree in
``s``, digits of the numbers) and rejects the text before anything large is built. The limits
are the module constants below. The expanded coefficients, whose size these bounds limit, are
then measured exactly: :func:`work` turns their sizes into the cost of the symbolic Jacobian
that :class:`~ctid_ros.core.model.Model` derives and compiles, checked before it does.
"""

from dataclasses import dataclass
import keyword
import math
import re
from typing import List, Optional, Tuple

from ctid_ros.core.limits import check_model_text_length, MAX_MODEL_TEXT
from ctid_ros.errors import ModelError
import sympy as sp

__all__ = [
    'DeadTime', 'LAPLACE', 'MAX_DEGREE', 'MAX_DELAY_TERMS', 'MAX_DEPTH', 'MAX_EXPONENT',
    'MAX_FACTORS', 'MAX_LENGTH', 'MAX_NAME_LENGTH', 'MAX_NUMBER_DIGITS', 'MAX_PARAMETERS',
    'MAX_TERMS', 'MAX_VALUE_DIGITS', 'MAX_WORK', 'Parsed', 'Size', 'Token', 'parse_equation',
    'parse_expression', 'parse_model_text', 'tokenize', 'work',
]

LAPLACE = sp.Symbol('s')
# Limits of the model language, stated in the README (section "The model language", Limits).
# Each is far above what a grey-box model needs (tens of parameters, degree 10-20) and low
# enough that no text within all of them stalls the caller (bench/model_text.py measures it).
MAX_LENGTH = MAX_MODEL_TEXT  # characters of one text
MAX_NAME_LENGTH = 64     # characters of one name
MAX_DEPTH = 40           # nesting of parentheses, signs and powers
MAX_NUMBER_DIGITS = 32   # characters of one number as written
MAX_PARAMETERS = 64      # distinct names (parameters and, in an equation, signals)
MAX_EXPONENT = 32        # magnitude of an exponent, as MAX_DEGREE so that s**32 can be written
# Bounds of the size of an expression, checked before sympy builds it (see the module notes).
MAX_DEGREE = 32          # degree in s of a numerator or denominator
MAX_TERMS = 512          # terms of an expanded numerator or denominator
MAX_FACTORS = 24         # factors of one expanded term (K/(a0*...*a59) has 60)
MAX_VALUE_DIGITS = 1000  # decimal digits of the exact numbers
MAX_DELAY_TERMS = 16     # terms of the argument of exp(...)
# Bound of work(...) of the Jacobian, checked on the expanded coefficients before sympy
# differentiates them; calibrated with bench/model_text.py on the largest texts within limits.
MAX_WORK = 100_000

_ASCII_SPACE = ' \t\n\r\f\v'
# re.ASCII: only ASCII digits and white space (no other Unicode digits that mean something else).
_TOKEN = re.compile(
    r'\s*(?:'
    r'(?P<number>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)'
    r'|(?P<name>[A-Za-z_][A-Za-z0-9_]*)'
    r'|(?P<op>\*\*|[-+*/^()=])'
    r')', re.ASCII)


def work(parameters: int, coefficients: int, weight: int) -> int:
    """
    Upper bound of the cost of differentiating and compiling a model, in units of sympy steps.

    Parameters
    ----------
    parameters : int
        Number of parameters P (every one is a column of the Jacobian).
    coefficients : int
        Number of coefficient expressions C (of the numerator(s), denominator and dead time).
    weight : int
        Sum over the coefficients of their node count times (their longest product + 1).

    Returns
    -------
    int
        ``P * (C * (P + 1) + 5 * weight)``, compared with :data:`MAX_WORK`: compiling visits
        every entry of the C x (P + 1) values and Jacobian once per parameter, and sympy
        differentiates a product of f factors in about f**2 steps, a few times slower each.

    """
    return parameters * (coefficients * (parameters + 1) + 5 * weight)


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
    rational numbers involved. A term is a product of powers of the parameters (and ``pi``,
    ``s``, numbers): ``*_factors`` bound how many such powers other than ``s`` and numbers one
    term has, counted with multiplicity, ``bases`` lists the names that can occur (so no term
    has more than that many distinct factors), and ``atom_weight`` adds the fractional powers
    ``(...)**0.5``, each weighing as much as the expanded base that sympy keeps inside it.
    """

    num_terms: int = 1
    den_terms: int = 1
    num_degree: int = 0
    den_degree: int = 0
    digits: int = 0
    num_factors: int = 0
    den_factors: int = 0
    bases: frozenset = frozenset()
    atom_weight: int = 0

    @property
    def factors(self) -> int:
        """Bound of the sympy Mul arguments of one term of the numerator or denominator."""
        return min(max(self.num_factors, self.den_factors), len(self.bases) + self.atom_weight)

    def __post_init__(self):
        # Without fractional powers a term is s**i times a monomial of degree <= factors in
        # the bases: a numeric polynomial such as (s + 1)**10 has 11 terms, not 2**10.
        if self.atom_weight == 0:
            for side in ('num', 'den'):
                degree, factors = getattr(self, f'{side}_degree'), getattr(self, f'{side}_factors')
                if factors <= MAX_FACTORS:
                    cap = (degree + 1) * math.comb(len(self.bases) + factors, factors)
                    if cap < getattr(self, f'{side}_terms'):
                        object.__setattr__(self, f'{side}_terms', cap)

    def __add__(self, other: 'Size') -> 'Size':
        return Size(self.num_terms * other.den_terms + other.num_terms * self.den_terms,
                    self.den_terms * other.den_terms,
                    max(self.num_degree + other.den_degree, other.num_degree + self.den_degree),
                    self.den_degree + other.den_degree,
                    max(self.digits, other.digits) + 1,
                    max(self.num_factors + other.den_factors,
                        other.num_factors + self.den_factors),
                    self.den_factors + other.den_factors,
                    self.bases | other.bases, self.atom_weight + other.atom_weight)

    def __mul__(self, other: 'Size') -> 'Size':
        return Size(self.num_terms * other.num_terms, self.den_terms * other.den_terms,
                    self.num_degree + other.num_degree, self.den_degree + other.den_degree,
                    self.digits + other.digits, self.num_factors + other.num_factors,
                    self.den_factors + other.den_factors,
                    self.bases | other.bases, self.atom_weight + other.atom_weight)

    def inverse(self) -> 'Size':
        return Size(self.den_terms, self.num_terms, self.den_degree, self.num_degree,
                    self.digits, self.den_factors, self.num_factors, self.bases,
                    self.atom_weight)

    def power(self, exponent, generator: str = '#') -> 'Size':
        """
        Size of ``self ** exponent`` (integer exponents expand multinomially).

        ``generator`` names a fractional power of a number in ``bases`` (a name that no
        parameter can have, distinct for each such power in the text).
        """
        base = self if exponent >= 0 else self.inverse()
        k = int(sp.ceiling(abs(exponent)))
        if exponent.is_Integer:
            return Size(math.comb(base.num_terms + k - 1, k),
                        math.comb(base.den_terms + k - 1, k),
                        k * base.num_degree, k * base.den_degree, k * base.digits,
                        k * base.num_factors, k * base.den_factors, base.bases,
                        base.atom_weight)
        if all(name == 'pi' or name.startswith('#') for name in base.bases):
            # A number such as 2**0.5 or (1 + 3**0.5)**1.5: nothing to differentiate, only one
            # more generator of the coefficients besides its integer part.
            return Size(math.comb(base.num_terms + k - 1, k) + 1,
                        math.comb(base.den_terms + k - 1, k) + 1,
                        0, 0, k * base.digits + 1,
                        k * base.num_factors + 1, k * base.den_factors + 1,
                        base.bases | {generator}, 0)
        # A fractional power of an expression free of s (enforced by the parser) stays one
        # generator, except that sympy's expand splits off its integer part. That generator
        # keeps the expanded base inside it, so it weighs as much as the base's terms.
        inner = (base.num_terms + base.den_terms) * (base.factors + 1) + 1
        return Size(math.comb(base.num_terms + k - 1, k) + 1,
                    math.comb(base.den_terms + k - 1, k) + 1,
                    0, 0, k * base.digits + 1,
                    k * base.num_factors + inner, k * base.den_factors + inner, base.bases,
                    base.atom_weight + inner)

    def problem(self) -> Optional[str]:
        """Return what exceeds the limits, or None."""
        if max(self.num_degree, self.den_degree) > MAX_DEGREE:
            return f'its degree in s would exceed {MAX_DEGREE}'
        if max(self.num_terms, self.den_terms) > MAX_TERMS:
            return f'it would expand to more than {MAX_TERMS} terms'
        if self.factors > MAX_FACTORS:
            return (f'a term would be a product of up to {self.factors} factors; the limit is '
                    f'{MAX_FACTORS}')
        if self.digits > MAX_VALUE_DIGITS:
            return f'its numbers would have more than {MAX_VALUE_DIGITS} digits'
        return None


_ATOM = Size()


@dataclass(frozen=True)
class DeadTime:
    """The dead-time factor ``exp(argument)`` of a transfer function, ``argument = -tau*s``."""

    tau: sp.Expr
    argument: sp.Expr
    column: int


@dataclass(frozen=True)
class Parsed:
    """
    A parsed model or controller text.

    ``sides`` are ``[expression]`` or, for a model equation, ``[left, right]``, without the
    dead-time factor (given apart as ``dead_time``). ``symbols`` are the names other than ``s``
    and ``pi`` in order of first appearance; ``size`` bounds ``left - right``.
    """

    sides: List[sp.Expr]
    symbols: Tuple[sp.Symbol, ...]
    dead_time: Optional[DeadTime]
    size: Size

    def full_sides(self) -> List[sp.Expr]:
        """Return the sides with the dead-time factor multiplied back in."""
        if self.dead_time is None:
            return list(self.sides)
        return [self.sides[0] * sp.exp(self.dead_time.argument)]


@dataclass(frozen=True)
class _Node:
    """A parsed sub-expression: sympy object, size bound, and the exp(...) token it carries."""

    expr: sp.Expr
    size: Size
    dead_time: Optional[Token] = None


def _pointer(text: str, column: int) -> str:
    return f'\n  {text}\n  {" " * column}^'


def tokenize(text: str) -> List[Token]:
    """Split ``text`` into tokens, rejecting any character outside the model grammar."""
    if not isinstance(text, str):
        raise ModelError(f'model expression must be a string, got {type(text).__name__}')
    check_model_text_length(text)
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


class _Parser:
    """Recursive-descent parser over the token list; builds sympy objects directly."""

    def __init__(self, text: str, *, equation: bool, controller: bool):
        self.text = text
        self.tokens = tokenize(text)
        # Known before parsing, so that a dead time in an equation gets the equation's message.
        self.equation = equation and any(token.text == '=' for token in self.tokens)
        self.controller = controller
        self.index = 0
        self.depth = 0
        self.symbols = {}
        self.dead_time: Optional[DeadTime] = None

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

    def parse(self) -> Parsed:
        if self.current.kind == 'end':
            raise ModelError('model expression is empty')
        node = self.expression()
        sides, size = [node.expr], node.size
        if self.equation and self.current.text == '=':
            sign = self.advance()
            if self.current.kind == 'end':
                raise self.error("nothing after '='", self.current)
            right = self.expression()
            sides.append(right.expr)
            size = self.checked(size + right.size, sign)
        if self.current.text == '=':
            raise self.error("'=' is only allowed once, in a model equation", self.current)
        if self.current.kind != 'end':
            raise self.error(f'unexpected {self.current.text!r}', self.current)
        return Parsed(sides, tuple(self.symbols.values()), self.dead_time, size)

    def nested(self, token: Token):
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise self.error(f'expression nested deeper than {MAX_DEPTH} levels', token)

    def expression(self) -> _Node:
        node = self.term()
        while self.current.text in ('+', '-'):
            operator = self.advance()
            right = self.term()
            for side in (node, right):
                if side.dead_time is not None:
                    raise self.error('the dead time exp(...) must be a factor of the whole '
                                     'transfer function, not a term of a sum',
                                     side.dead_time)
            size = self.checked(node.size + right.size, operator)
            result = node.expr + right.expr if operator.text == '+' else node.expr - right.expr
            node = _Node(result, size)
        return node

    def term(self) -> _Node:
        node = self.unary()
        while self.current.text in ('*', '/'):
            operator = self.advance()
            right = self.unary()
            if operator.text == '*':
                size = self.checked(node.size * right.size, operator)
                node = _Node(node.expr * right.expr, size, node.dead_time or right.dead_time)
                continue
            if right.dead_time is not None:
                raise self.error('a dead time exp(-tau*s) in a denominator is the time advance '
                                 'exp(tau*s), which is non-causal (the output would react '
                                 'before the input); write exp(-tau*s) as a factor of the '
                                 'numerator', right.dead_time)
            if right.expr == 0:
                raise self.error('division by zero', operator)
            size = self.checked(node.size * right.size.inverse(), operator)
            node = _Node(node.expr / right.expr, size, node.dead_time)
        return node

    def unary(self) -> _Node:
        token = self.current
        if token.text in ('+', '-'):
            self.advance()
            self.nested(token)
            operand = self.unary()
            self.depth -= 1
            if token.text == '+':
                return operand
            return _Node(-operand.expr, operand.size, operand.dead_time)
        return self.power()

    def power(self) -> _Node:
        base = self.atom()
        if self.current.text not in ('**', '^'):
            return base
        operator = self.advance()
        self.nested(operator)
        exponent_token = self.current
        exponent = self.unary()
        self.depth -= 1
        if exponent.dead_time is not None:
            raise self.error('exponents must be numbers, not a dead time', exponent.dead_time)
        if base.dead_time is not None:
            if exponent.expr.is_Number and exponent.expr < 0:
                raise self.error(f'a dead time raised to the power {exponent.expr} is a time '
                                 'advance, which is non-causal (the output would react before '
                                 'the input)', base.dead_time)
            raise self.error('a dead time exp(-tau*s) may not be raised to a power; write one '
                             'factor exp(-tau*s) with the whole dead time in tau (e.g. '
                             'exp(-2*tau*s))', base.dead_time)
        return self.checked_power(base, exponent.expr, exponent_token)

    def checked_power(self, base: _Node, exponent: sp.Expr, token: Token) -> _Node:
        if not exponent.is_Number:
            raise self.error('exponents must be numbers', token)
        if abs(exponent) > MAX_EXPONENT:
            raise self.error(f'exponent {exponent} is larger than {MAX_EXPONENT} in magnitude',
                             token)
        if base.expr.has(LAPLACE) and not exponent.is_Integer:
            raise self.error('powers of expressions in s must have integer exponents', token)
        if base.expr == 0 and exponent < 0:
            raise self.error('division by zero', token)
        if not exponent.is_Integer and base.expr.is_number and base.expr.is_negative:
            raise self.error(f'a fractional power of the negative number {base.expr} is not '
                             'real', token)
        # Checked before sympy evaluates the power (it computes numeric powers eagerly).
        size = self.checked(base.size.power(exponent, f'#{token.column}'), token)
        return _Node(base.expr ** exponent, size)

    def atom(self) -> _Node:
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

    def number(self, token: Token) -> _Node:
        if len(token.text) > MAX_NUMBER_DIGITS:
            raise self.error(f'number longer than {MAX_NUMBER_DIGITS} characters', token)
        # Range check on the float first: sp.Rational('1e999999999') would compute 10**999999999.
        if not re.split('[eE]', token.text)[0].strip('0.'):
            return _Node(sp.Integer(0), _ATOM)
        if not 1e-300 < float(token.text) < 1e300:
            raise self.error(f'number {token.text} is out of range', token)
        value = sp.Rational(token.text)
        digits = len(str(abs(value.p))) + len(str(value.q))
        return _Node(value, Size(digits=digits))

    def name(self, token: Token) -> _Node:
        name = token.text
        if self.current.text == '(':
            if name != 'exp':
                raise self.error(f'function {name}(...) is not allowed; the only function is '
                                 'exp(-tau*s), a dead time', token)
            return self.exponential(token)
        if name == 'exp':
            raise self.error('exp must be called as exp(...)', token)
        if name.startswith('_'):
            raise self.error(f'names may not start with "_" ({name!r})', token)
        if len(name) > MAX_NAME_LENGTH:
            raise self.error(f'name longer than {MAX_NAME_LENGTH} characters', token)
        if keyword.iskeyword(name):
            raise self.error(f'{name!r} is a reserved word and cannot name a parameter', token)
        if name == 's':
            return _Node(LAPLACE, Size(num_degree=1))
        if name == 'pi':
            return _Node(sp.pi, Size(digits=1, num_factors=1, bases=frozenset(['pi'])))
        if self.controller:
            raise self.error(f'a controller must have numeric coefficients; {name!r} is a '
                             'parameter name', token)
        if name not in self.symbols:
            if len(self.symbols) >= MAX_PARAMETERS:
                what = 'names (parameters and signals)' if self.equation else 'parameters'
                raise self.error(f'more than {MAX_PARAMETERS} {what}: {name!r} would be '
                                 f'number {len(self.symbols) + 1}', token)
            self.symbols[name] = sp.Symbol(name, real=True)
        return _Node(self.symbols[name], Size(num_factors=1, bases=frozenset([name])))

    def exponential(self, token: Token) -> _Node:
        """Parse ``exp(...)`` after its name: the dead time, returned as the factor 1."""
        if self.controller:
            raise self.error('a controller may not contain a dead time exp(...): inside the '
                             'loop it would make P K/(1 + P K) irrational', token)
        if self.equation:
            raise self.error('a dead time exp(-tau*s) is not supported in a model equation; '
                             'use the transfer-function form', token)
        open_paren = self.advance()
        self.nested(open_paren)
        argument = self.expression()
        close = self.expect(')')
        self.depth -= 1
        if argument.dead_time is not None:
            raise self.error('exp(...) inside exp(...): at most one dead-time factor '
                             'exp(-tau*s) is allowed', argument.dead_time)
        if self.dead_time is not None:
            raise self.error('at most one dead-time factor exp(-tau*s) is allowed (the first is '
                             f'at column {self.dead_time.column + 1}); write the whole dead '
                             'time in one factor, e.g. exp(-(tau1 + tau2)*s)', token)
        written = self.text[token.column:close.column + 1]
        if len(written) > 60:
            written = written[:56] + '...)'
        # A walk over the unexpanded argument, as long as the text at most.
        if not argument.expr.has(LAPLACE):
            raise self.error(f'{written} is not allowed: exp(...) is only the dead time '
                             'exp(-tau*s), and its argument has no s', token)
        size = argument.size
        if max(size.num_terms, size.den_terms) > MAX_DELAY_TERMS:
            raise self.error(f'the argument of exp(...) may have at most {MAX_DELAY_TERMS} '
                             f'terms (up to {max(size.num_terms, size.den_terms)} here)', token)
        tau = self.delay(argument.expr, token, written)
        self.dead_time = DeadTime(tau, argument.expr, token.column)
        return _Node(sp.Integer(1), _ATOM, token)

    def delay(self, argument: sp.Expr, token: Token, written: str) -> sp.Expr:
        """Return ``tau`` of ``exp(argument)``, ``argument = -tau*s``, or raise why not."""
        # Both small: the argument is bounded by MAX_DELAY_TERMS and MAX_FACTORS.
        tau = sp.cancel(-argument / LAPLACE)
        if tau.has(LAPLACE):
            raise self.error(f'{written} is not a dead time: its argument must be -tau*s with '
                             'tau independent of s', token)
        if tau.is_number:
            positive = tau.is_positive
        else:
            positive = tau.xreplace({symbol: sp.Dummy(symbol.name, positive=True)
                                     for symbol in tau.free_symbols}).is_positive
        if positive is False:
            raise self.error(f'{written} is a time advance, which is non-causal (the output '
                             'would react before the input): a dead time is exp(-tau*s) with '
                             'tau > 0', token)
        if positive is None:
            raise self.error(f'{written}: cannot tell that the dead time {tau} is positive; '
                             'write exp(-tau*s) with tau a sum of products of parameters and '
                             'positive numbers', token)
        return tau


def parse_model_text(text: str, *, equation: bool = True, controller: bool = False) -> Parsed:
    """
    Parse model or controller text safely, with the dead time apart.

    Parameters
    ----------
    text : str
        A transfer function in ``s``, e.g. ``"K*exp(-tau*s)/(T*s + 1)"``, or (if ``equation``)
        a model equation ``"M*s**2*y + Fv*s*y = 35.15*u - off"``.
    equation : bool
        Whether one ``=`` is allowed.
    controller : bool
        Parse a controller: numeric coefficients only, no dead time.

    Returns
    -------
    Parsed
        The sides without the dead-time factor, the names, the dead time and the size bound.

    Raises
    ------
    ModelError
        If the text is not in the grammar or exceeds a limit, with the column of the
        offending part where there is one.

    """
    return _Parser(text, equation=equation, controller=controller).parse()


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
    parsed = parse_model_text(text, equation=False)
    expression, = parsed.full_sides()
    return expression, parsed.symbols


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
    parsed = parse_model_text(text)
    return parsed.full_sides(), parsed.symbols
