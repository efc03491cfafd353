"""
The symbolic derivation of a :class:`~ctid_ros.core.model.Model` from its texts, with sympy.

From the safely parsed texts (:mod:`ctid_ros.core.expression`) :class:`Derivation` finds the
coefficients of ``N(s, theta)`` and ``D(s, theta)``, their Jacobians with respect to ``theta``,
the dead time ``tau(theta)`` and the structure's properties (affine, integrators), and compiles
the numbers into one function of ``theta``. It is the only part of a model that needs sympy, so
it lives apart from :mod:`ctid_ros.core.model`: a model whose derivation is stored
(:mod:`ctid_ros.core.model_cache`) is built without importing sympy (a third of a second).
"""

import keyword
from typing import Dict, List, Optional, Sequence, Tuple

from ctid_ros.core.expression import (LAPLACE, MAX_DEGREE, MAX_TERMS, MAX_WORK,
                                      parse_model_text, Parsed, work)
from ctid_ros.core.model_cache import CoefficientProgram
from ctid_ros.errors import ModelError
import sympy as sp

__all__ = ['Derivation', 'derive']


def _poly(expression: sp.Expr, *gens: sp.Expr) -> sp.Poly:
    """
    Return ``Poly(expression, *gens)`` with the coefficients in a polynomial ring.

    Built over every generator first, then the others moved into the coefficients: sympy's
    direct route sums each coefficient one Expr term at a time, quadratic in the terms.
    """
    try:
        others = [gen for gen in sp.Poly(expression).gens if gen not in gens]
    except sp.GeneratorsNeeded:
        others = []
    poly = sp.Poly(expression, *gens, *others)
    return poly.eject(*others) if others else poly


def _polynomials(rational: sp.Expr, text: str) -> Tuple[sp.Poly, sp.Poly]:
    if not rational.is_rational_function(LAPLACE):
        raise ModelError(f'{text!r} is not a rational function of s')
    num, den = sp.fraction(sp.together(rational))
    num_poly = _poly(num, LAPLACE)
    den_poly = _poly(den, LAPLACE)
    if den_poly.is_zero:
        raise ModelError(f'{text!r} has a zero denominator')
    return num_poly, den_poly


def _terms(poly: sp.Poly) -> int:
    """Count the terms of ``poly`` expanded in ``s`` and the parameters."""
    return sum(len(sp.Add.make_args(c)) for c in poly.all_coeffs())


def _weight(expression: sp.Expr) -> int:
    """Node count of ``expression`` times (its longest product + 1): see :func:`work`."""
    nodes, longest = 0, 0
    for node in sp.preorder_traversal(expression):
        nodes += 1
        if node.is_Mul:
            longest = max(longest, len(node.args))
    return nodes * (longest + 1)


def _check_work(nums: Sequence[sp.Poly], den: sp.Poly, tau: sp.Expr, parameters: int,
                what: str) -> None:
    """Reject a model whose Jacobian would take long to derive and compile, before it is."""
    coefficients = [c for poly in list(nums) + [den] for c in poly.all_coeffs()] + [tau]
    weight = sum(_weight(c) for c in coefficients)
    cost = work(parameters, len(coefficients), weight)
    if cost > MAX_WORK:
        raise ModelError(f'{what} is too large to differentiate: {len(coefficients)} '
                         f'coefficients of total weight {weight} in {parameters} parameters; '
                         f'P x (C x (P + 1) + 5 x weight) = {cost} exceeds the limit of '
                         f'{MAX_WORK} (see the limits of the model language in '
                         'docs/user-guide.md)')


def _check_proper(num: sp.Poly, den: sp.Poly, text: str) -> None:
    if not num.is_zero and num.degree() > den.degree():
        raise ModelError(f'{text!r} is improper: numerator degree {num.degree()} exceeds '
                         f'denominator degree {den.degree()} (a physical plant cannot '
                         'differentiate its input)')


def _numeric_controller(text: str) -> Tuple[sp.Poly, sp.Poly]:
    """Return ``(num, den)`` of a proper controller with numeric coefficients."""
    try:
        parsed = parse_model_text(text, equation=False, controller=True)
        num, den = _polynomials(parsed.sides[0], text)
    except ModelError as error:
        raise ModelError(f'controller: {error}') from None
    if num.is_zero:
        raise ModelError(f'controller {text!r} is identically zero')
    if num.degree() > den.degree():
        raise ModelError(f'controller {text!r} is improper: numerator degree {num.degree()} '
                         f'exceeds denominator degree {den.degree()}, so it would differentiate '
                         'the error; give its derivative part a filter, e.g. '
                         "'20 + 10/s + 2*s/(0.01*s + 1)'")
    return num, den


def _signal_names(inputs: Sequence[str], output: str) -> Tuple[str, ...]:
    if isinstance(inputs, str):
        inputs = (inputs,)
    names = tuple(inputs)
    if not names:
        raise ModelError('a model needs at least one input')
    for name in names + (output,):
        if not (isinstance(name, str) and name.isidentifier() and name.isascii()) or \
                keyword.iskeyword(name) or name in ('s', 'pi', 'exp'):
            raise ModelError(f'{name!r} cannot name a signal: use a plain identifier other than '
                             's, pi and exp')
    if len(set(names + (output,))) != len(names) + 1:
        raise ModelError(f'signal names must be distinct, got inputs {names} and output '
                         f'{output!r}')
    return names


def _padded_coefficients(poly: sp.Poly, degree: int) -> list:
    coefficients = poly.all_coeffs() if not poly.is_zero else [sp.Integer(0)]
    return [sp.Integer(0)] * (degree + 1 - len(coefficients)) + coefficients


class Derivation:
    """
    The attributes of the model of these texts, derived with sympy (see :class:`Model`).

    Raises
    ------
    ModelError
        As :class:`~ctid_ros.core.model.Model`.

    """

    def __init__(self, expression: str, controller: Optional[str], *,
                 inputs: Optional[Sequence[str]], output: str):
        if controller is not None and not isinstance(controller, str):
            raise ModelError(f'controller must be a string, got {type(controller).__name__}')
        self.expression = expression
        self.controller = controller if controller and controller.strip() else None
        self.inputs: Tuple[str, ...] = _signal_names(('u',) if inputs is None else inputs,
                                                     output)
        self.output = output
        parsed = parse_model_text(expression)
        sides, names = parsed.sides, parsed.symbols
        # The controller text first: what is wrong with it is said before how it fits the plant.
        loop = _numeric_controller(self.controller) if self.controller is not None else None
        for symbol in names:
            if keyword.iskeyword(symbol.name):
                raise ModelError(f'parameter name {symbol.name!r} is a reserved word')
        if len(sides) == 2:
            if self.controller is not None:
                raise ModelError('a controller needs the transfer-function form of the plant; '
                                 'write it without "=" and with one input')
            nums, den, tau, self.constant_input = self._equation(sides, names)
            signals = set(self.inputs) | {output}
            symbols = tuple(symbol for symbol in names if symbol.name not in signals)
        else:
            if len(self.inputs) != 1:
                raise ModelError(f'a transfer function has one input, {len(self.inputs)} were '
                                 'declared; write a model equation (with "=") for several '
                                 'inputs')
            num, den, tau = self._transfer_function(parsed, loop)
            nums, symbols, self.constant_input = [num], names, False
        self._symbols = symbols
        self.parameters: Tuple[str, ...] = tuple(symbol.name for symbol in symbols)
        if not self.parameters:
            raise ModelError(f'{expression!r} has no parameters to estimate')
        _check_work(nums, den, tau, len(symbols), repr(expression) if self.controller is None
                    else f'the closed loop of {expression!r} with {self.controller!r}')
        self._build(nums, den, tau)

    def _transfer_function(self, parsed: Parsed, loop: Optional[Tuple[sp.Poly, sp.Poly]]
                           ) -> Tuple[sp.Poly, sp.Poly, sp.Expr]:
        expression = self.expression
        num, den = _polynomials(parsed.sides[0], expression)
        _check_proper(num, den, expression)
        tau = sp.Integer(0) if parsed.dead_time is None else parsed.dead_time.tau
        if tau.free_symbols and den.degree() == 0:
            # Rejected rather than given a meaning: y(t) = K u(t - tau) under a held input jumps
            # when tau crosses a sample instant and is flat in between, so no data determine an
            # estimated tau (a known one, K*exp(-0.5*s), simulates exactly and is accepted).
            raise ModelError(f'{expression!r} is a dead time without dynamics (no pole): its '
                             'sampled output only jumps as the dead time changes, so the dead '
                             'time cannot be estimated; give the model at least one pole, e.g. '
                             'K*exp(-tau*s)/(T*s + 1), or a known dead time, e.g. '
                             'K*exp(-0.5*s)')
        if loop is None:
            return num, den, tau
        if tau != 0:
            raise ModelError(
                'a dead time inside a closed loop makes P K/(1 + P K) irrational; identify '
                'the plant open loop from its measured input u instead')
        k_num, k_den = loop
        degree = max(num.degree() + k_num.degree(), den.degree() + k_den.degree())
        if degree > MAX_DEGREE:
            raise ModelError(f'the closed loop of {expression!r} with {self.controller!r} '
                             f'has degree {degree} in s; the limit is {MAX_DEGREE}')
        # Bounded before multiplying: N Kn/(D Kd + N Kn) has more terms than N/D.
        terms = (2 * _terms(num) * (k_num.degree() + 1) + _terms(den) * (k_den.degree() + 1))
        if terms > MAX_TERMS:
            raise ModelError(f'the closed loop of {expression!r} with {self.controller!r} is '
                             f'too large: it would expand to up to {terms} terms; the limit is '
                             f'{MAX_TERMS}')
        num, den = num * k_num, den * k_den + num * k_num
        _check_proper(num, den, f'closed loop of {expression!r} with {self.controller!r}')
        return num, den, tau

    def _equation(self, sides: Sequence[sp.Expr], names: Sequence[sp.Symbol]
                  ) -> Tuple[List[sp.Poly], sp.Poly, sp.Expr, bool]:
        """Return ``(numerators per input [+ constant], D, 0, has constant)`` of an equation."""
        text = self.expression
        by_name = {symbol.name: symbol for symbol in names}
        missing = [name for name in (self.output,) + self.inputs if name not in by_name]
        if missing:
            raise ModelError(f'signal(s) {", ".join(missing)} do not appear in the equation '
                             f'{text!r} (declared output {self.output!r}, inputs '
                             f'{", ".join(self.inputs)})')
        output = by_name[self.output]
        inputs = [by_name[name] for name in self.inputs]
        signals = [output] + inputs
        difference = sides[0] - sides[1]
        numerator, denominator = sp.fraction(sp.together(difference))
        if denominator.has(*signals):
            raise ModelError(f'{text!r} divides by a signal: the equation must be linear in '
                             f'{", ".join(symbol.name for symbol in signals)}')
        if not numerator.is_polynomial(LAPLACE, *signals):
            raise ModelError(f'{text!r} is not polynomial in s and the signals')
        poly = _poly(numerator, *signals)
        if poly.total_degree() > 1:
            raise ModelError(f'{text!r} is not linear in the signals '
                             f'{", ".join(symbol.name for symbol in signals)} (a product or '
                             'power of signals)')
        unit = [0] * len(signals)

        def coefficient(index: Optional[int]) -> sp.Expr:
            monomial = list(unit)
            if index is not None:
                monomial[index] = 1
            return poly.coeff_monomial(tuple(monomial))

        den = _poly(coefficient(0), LAPLACE)
        if den.is_zero:
            raise ModelError(f'the output {self.output} cancels out of {text!r}')
        nums = [_poly(-coefficient(1 + index), LAPLACE) for index in range(len(inputs))]
        constant = -coefficient(None)
        if constant.has(LAPLACE):
            raise ModelError(f'the constant term of {text!r} may not be multiplied by s (the '
                             'derivative of a constant input is zero)')
        for name, num in zip(self.inputs, nums):
            if num.is_zero:
                raise ModelError(f'input {name} cancels out of {text!r}')
            _check_proper(num, den, f'{text!r} from input {name}')
        has_constant = constant != 0
        if has_constant:
            nums.append(_poly(constant, LAPLACE))
        return nums, den, sp.Integer(0), has_constant

    def _build(self, nums: Sequence[sp.Poly], den: sp.Poly, tau: sp.Expr) -> None:
        self.num_degree = max(0 if num.is_zero else num.degree() for num in nums)
        self.den_degree = den.degree()
        num_coefficients = [_padded_coefficients(num, self.num_degree) for num in nums]
        den_coefficients = _padded_coefficients(den, self.den_degree)
        self._channels = len(nums)
        symbols = self._symbols
        flat_nums = [c for row in num_coefficients for c in row]
        jacobian = [[sp.diff(c, p) for p in symbols]
                    for c in flat_nums + den_coefficients + [tau]]
        absent = [p.name for i, p in enumerate(symbols) if all(row[i] == 0 for row in jacobian)]
        if absent:
            raise ModelError(f'parameter(s) {", ".join(absent)} cancel out of the transfer '
                             'function, so no data can determine them; remove them')
        self.is_affine = all(not entry.has(*symbols) for row in jacobian for entry in row)
        self.has_delay = tau != 0
        self.delay_is_estimated = bool(tau.free_symbols)
        trailing = 0
        while trailing < self.den_degree and den_coefficients[-1 - trailing] == 0:
            trailing += 1
        # Roots at s = 0 for every theta (integrators): D is never Hurwitz, see integrators.py.
        self.integrators = trailing
        flat = flat_nums + den_coefficients + [tau] + [e for row in jacobian for e in row]
        function = sp.lambdify(symbols, flat, modules='numpy', dummify=True, cse=True)
        # The same arithmetic as plain data where it can be (a model stored on disk, see
        # model_cache.py), else the generated function itself.
        self._evaluate = CoefficientProgram.from_function(function) or function


def derive(expression: str, controller: Optional[str], *, inputs: Optional[Sequence[str]],
           output: str) -> Dict[str, object]:
    """
    Return the attributes of the :class:`~ctid_ros.core.model.Model` of these texts.

    Raises
    ------
    ModelError
        If the texts do not describe a model (see :class:`~ctid_ros.core.model.Model`).

    """
    attributes = dict(vars(Derivation(expression, controller, inputs=inputs, output=output)))
    del attributes['_symbols']      # sympy objects, needed only while deriving
    return attributes
