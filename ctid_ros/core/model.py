"""
Grey-box continuous-time transfer-function models.

A :class:`Model` is built from safe text (see :mod:`ctid_ros.core.expression`)::

    Model('1/(m*s**2 + d*s + k)')                 # mass-spring-damper, parameters m, d, k
    Model('K*exp(-tau*s)/(T*s + 1)')              # first order plus dead time
    Model('K/((T1*s + 1)*(T2*s + 1))')            # not affine in (K, T1, T2)
    Model('1/(J*s**2 + b*s)', controller='40 + 20/s')   # closed loop r -> y of P K/(1 + P K)

Every name other than ``s`` (and the constant ``pi``) is a parameter. ``model.parameters`` lists
them in order of first appearance in the plant expression. From the text the model derives the
coefficients of ``N(s, theta)`` and ``D(s, theta)``, their Jacobians with respect to ``theta``
(symbolically, then compiled to numpy), the dead time ``tau(theta)`` of an optional factor
``exp(-tau*s)``, and whether the structure is affine in ``theta`` (``docs/algorithm.md``
section 2).
"""

from dataclasses import dataclass
import functools
import keyword
from typing import Dict, List, Mapping, Optional, Sequence, Tuple, Union

from ctid_ros.core.data import as_inputs
from ctid_ros.core.expression import (LAPLACE, MAX_DEGREE, MAX_TERMS, MAX_WORK,
                                      parse_model_text, Parsed, tokenize, work)
from ctid_ros.core.simulation import (ContinuousFilter, INTERSAMPLE, skew_delay,
                                      skew_extended)
from ctid_ros.errors import ModelError
import numpy as np
import sympy as sp

__all__ = ['Coefficients', 'Model', 'ParameterValues']

ParameterValues = Union[Mapping[str, float], Sequence[float], np.ndarray]
# Models whose derivation is kept, by their texts (a node, a replay's windows, a fleet's tasks
# and the command line build the same few models again and again).
_REMEMBERED_MODELS = 64


@dataclass(frozen=True)
class Coefficients:
    """
    Numeric ``N``, ``D``, dead time and their Jacobians at one parameter vector.

    :meth:`Model.coefficients` evaluates them; the model structure (the parameterised family)
    is the :class:`Model` itself. Coefficient arrays are highest power of ``s`` first. ``num``
    has one row per numerator channel (the measured inputs in order, then the constant input if
    the model has one); Jacobians have the parameters on their first axis.
    """

    num: np.ndarray
    den: np.ndarray
    delay: float
    num_jacobian: np.ndarray
    den_jacobian: np.ndarray
    delay_gradient: np.ndarray


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


def _model_key(expression, controller, inputs, output) -> Optional[Tuple]:
    """Return the hashable key of a model's texts, None if they are not all plain strings."""
    if inputs is not None:
        if isinstance(inputs, str) or not all(type(name) is str for name in inputs):
            return None
        inputs = tuple(inputs)
    if type(expression) is not str or type(output) is not str or \
            (controller is not None and type(controller) is not str):
        return None
    return expression, controller, inputs, output


@functools.lru_cache(maxsize=_REMEMBERED_MODELS)
def _derived(expression: str, controller: Optional[str], inputs: Optional[Tuple[str, ...]],
             output: str) -> Dict[str, object]:
    """Return the attributes of the model of these texts (an error is raised each time)."""
    model = Model.__new__(Model)
    model._derive(expression, controller, inputs=inputs, output=output)
    return dict(vars(model))


class Model:
    """
    Continuous-time grey-box model: a transfer function ``G(s, theta)`` or a model equation.

    Parameters
    ----------
    expression : str
        Either a plant transfer function in ``s`` (one input; every other name is a parameter;
        at most one dead-time factor ``exp(-tau*s)``), or a model equation
        ``D(s) y = N_1(s) u_1 + ... + c`` with an ``=`` whose terms multiply the output and the
        declared inputs (``s`` acts on the signal it multiplies) and an optional constant term
        ``c`` (a constant input, e.g. a force offset). All inputs share ``D``.
    controller : str, optional
        Known controller ``K(s)`` with numeric coefficients, e.g. ``'4 + 2/s'``. The model then
        describes the closed loop from reference ``r`` to output ``y``,
        ``P K / (1 + P K)``, while the parameters stay those of the plant ``P``.
    inputs : sequence of str, optional
        Names of the measured inputs, in the order of the columns of ``Data.u``; default
        ``('u',)``. In an equation these names are signals, not parameters.
    output : str
        Name of the output signal in an equation (default ``'y'``).

    Raises
    ------
    ModelError
        If either text is unsafe, malformed, improper, non-causal, beyond a size limit (see
        :mod:`ctid_ros.core.expression`), not linear in the signals, or has a dead time that is
        not a single factor ``exp(-tau*s)`` (an estimated one needs at least one pole).

    """

    def __init__(self, expression: str, controller: Optional[str] = None, *,
                 inputs: Optional[Sequence[str]] = None, output: str = 'y'):
        key = _model_key(expression, controller, inputs, output)
        if key is None:
            self._derive(expression, controller, inputs=inputs, output=output)
        else:
            # A model is never changed once built: one built from the same texts shares the
            # derivation (sympy and its compiled Jacobian), a few milliseconds per model.
            self.__dict__.update(_derived(*key))

    def _derive(self, expression: str, controller: Optional[str], *,
                inputs: Optional[Sequence[str]], output: str) -> None:
        """Parse the texts, derive the coefficients and their Jacobian and compile them."""
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
        self._evaluate = sp.lambdify(symbols, flat, modules='numpy', dummify=True, cse=True)

    def __repr__(self) -> str:
        controller = f', controller={self.controller!r}' if self.controller else ''
        signals = '' if self.inputs == ('u',) and self.output == 'y' else \
            f', inputs={self.inputs!r}, output={self.output!r}'
        return f'Model({self.expression!r}{controller}{signals})'

    def with_fixed(self, values: Mapping[str, float]) -> 'Model':
        """
        Return this model with some parameters held at known values (not estimated).

        Each named parameter is replaced in the text by its value, in parentheses, and the
        model is built again: the same structure, controller and signals, with the other
        parameters in their order. ``Model('exp(-tau*s)/(J*s + b)').with_fixed({'J': 0.05})``
        is ``Model('exp(-tau*s)/((0.05)*s + b)')``; a fixed dead time is a known one.

        Raises
        ------
        ModelError
            If a name is not a parameter of the model, a value is not a finite number, or no
            parameter would be left to estimate.

        """
        unknown = [name for name in values if name not in self.parameters]
        if unknown:
            raise ModelError(f'{", ".join(map(repr, unknown))} is not a parameter of '
                             f'{self.expression!r} (parameters: {", ".join(self.parameters)})')
        numbers = {}
        for name, value in values.items():
            if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) \
                    or not np.isfinite(value):
                raise ModelError(f'the value of {name} must be a finite number, got {value!r}')
            numbers[name] = f'({float(value)!r})'
        if set(numbers) >= set(self.parameters):
            raise ModelError(f'fixing {", ".join(numbers)} leaves no parameter of '
                             f'{self.expression!r} to estimate')
        text = self.expression
        for token in reversed(tokenize(text)):
            if token.kind == 'name' and token.text in numbers:
                text = text[:token.column] + numbers[token.text] + \
                    text[token.column + len(token.text):]
        return Model(text, self.controller, inputs=self.inputs, output=self.output)

    def vector(self, params: ParameterValues) -> np.ndarray:
        """Parameter values as a float vector in :attr:`parameters` order."""
        if isinstance(params, Mapping):
            missing = [name for name in self.parameters if name not in params]
            if missing:
                raise ModelError(f'missing value(s) for parameter(s) {", ".join(missing)}')
            unknown = sorted(set(params) - set(self.parameters))
            if unknown:
                raise ModelError(f'unknown parameter(s) {", ".join(unknown)}; the model has '
                                 f'{", ".join(self.parameters)}')
            values = [params[name] for name in self.parameters]
        elif isinstance(params, np.ndarray) and params.ndim == 1 and params.dtype == float:
            # The estimator's own vectors: one copy, not a round trip through Python floats.
            values = params
            if values.size != len(self.parameters):
                raise ModelError(f'expected {len(self.parameters)} parameter values '
                                 f'({", ".join(self.parameters)}), got {values.size}')
        else:
            values = list(np.ravel(np.asarray(params, dtype=float)))
            if len(values) != len(self.parameters):
                raise ModelError(f'expected {len(self.parameters)} parameter values '
                                 f'({", ".join(self.parameters)}), got {len(values)}')
        vector = np.array(values, dtype=float)
        if not np.isfinite(vector).all():
            raise ModelError(f'parameter values must be finite, got {vector}')
        return vector

    def as_dict(self, theta: Sequence[float]) -> Dict[str, float]:
        """Map a parameter vector back to ``{name: value}``."""
        return {name: float(value) for name, value in zip(self.parameters, theta)}

    def coefficients(self, params: ParameterValues) -> Coefficients:
        """Numeric ``N`` (per channel), ``D``, dead time and their Jacobians at ``params``."""
        flat = self.coefficient_array(params)
        channels, n_num = self._channels, self.num_degree + 1
        n_den, n_par = self.den_degree + 1, len(self.parameters)
        n_nums = channels * n_num
        values, jacobian = flat[:n_nums + n_den + 1], flat[n_nums + n_den + 1:]
        jacobian = jacobian.reshape(n_nums + n_den + 1, n_par).T
        return Coefficients(
            num=values[:n_nums].reshape(channels, n_num), den=values[n_nums:n_nums + n_den],
            delay=float(values[-1]),
            num_jacobian=jacobian[:, :n_nums].reshape(n_par, channels, n_num),
            den_jacobian=jacobian[:, n_nums:n_nums + n_den], delay_gradient=jacobian[:, -1])

    def coefficient_array(self, params: ParameterValues) -> np.ndarray:
        """
        Return the numbers behind :meth:`coefficients` as one flat array.

        First the coefficients: ``N`` channel by channel, then ``D`` (highest power first), then
        the dead time; then for each of them in that order its derivatives by the parameters.
        For callers that evaluate thousands of parameter vectors and need a few of them.

        Raises
        ------
        ModelError
            If a parameter value is not finite or a coefficient is undefined (division by zero).

        """
        if type(params) is np.ndarray and params.ndim == 1 and params.dtype == float and \
                params.size == len(self.parameters) and np.isfinite(params).all():
            # The estimator's own vectors (thousands per fit): read, never kept, not copied.
            theta = params
        else:
            theta = self.vector(params)
        with np.errstate(all='ignore'):
            flat = np.asarray(self._evaluate(*theta), dtype=float)
        if not np.isfinite(flat).all():
            raise ModelError(f'the model is undefined at {self.as_dict(theta)} '
                             '(division by zero in a coefficient)')
        return flat

    def channel(self, input_name: Optional[str] = None) -> int:
        """Row of :attr:`Coefficients.num` that belongs to ``input_name`` (default: the only)."""
        if input_name is None:
            if len(self.inputs) > 1:
                raise ModelError(f'the model has inputs {", ".join(self.inputs)}: say which one')
            return 0
        if input_name not in self.inputs:
            raise ModelError(f'unknown input {input_name!r}; the model has '
                             f'{", ".join(self.inputs)}')
        return self.inputs.index(input_name)

    def transfer_function(self, params: ParameterValues, input_name: Optional[str] = None
                          ) -> Tuple[np.ndarray, np.ndarray, float]:
        """``(num, den, delay)`` from ``input_name`` to the output, highest power first."""
        coefficients = self.coefficients(params)
        return coefficients.num[self.channel(input_name)], coefficients.den, coefficients.delay

    def input_channels(self, u) -> np.ndarray:
        """
        Return the channel signals (N x channels): the input columns, then the constant 1.

        ``u`` is 1-D for a single input or has one column per input, in :attr:`inputs` order.
        """
        columns = as_inputs(u, len(self.inputs))
        if self.constant_input:
            columns = np.column_stack([columns, np.ones(columns.shape[0])])
        return columns

    def simulate(self, params: ParameterValues, u, ts: float, *,
                 intersample: str = 'zoh', output_skew: float = 0.0) -> np.ndarray:
        """
        Exact response of the model to sampled input ``u`` (the reference, in closed loop).

        Parameters
        ----------
        params : mapping or sequence
            Parameter values by name, or a vector in :attr:`parameters` order.
        u : array_like
            Input samples at ``t_k = k*ts``, shape (N,) or (N, inputs); the system is at rest
            before ``t_0`` (a constant input of the equation starts at ``t_0``).
        ts : float
            Sample time in seconds.
        intersample : {'zoh', 'foh'}
            Input behaviour between samples.
        output_skew : float
            Seconds after ``t_k`` at which the outputs are wanted, ``0 <= output_skew < ts``
            (see :class:`~ctid_ros.core.data.Data`).

        Returns
        -------
        ndarray
            Output samples at ``t_k + output_skew``.

        """
        if intersample not in INTERSAMPLE:
            raise ModelError(f'intersample must be one of {INTERSAMPLE}, got {intersample!r}')
        if output_skew and not (np.isfinite(output_skew) and 0.0 < output_skew < ts):
            raise ModelError(f'output skew must lie in [0, ts), got {output_skew}')
        coefficients = self.coefficients(params)
        if coefficients.delay < 0.0:
            raise ModelError(f'the dead time is negative ({coefficients.delay:g} s) at '
                             f'{self.as_dict(self.vector(params))}: that is a time advance')
        if coefficients.den[0] == 0.0:
            raise ModelError(f'the leading denominator coefficient vanishes at '
                             f'{self.as_dict(self.vector(params))}: the model order drops')
        discrete = ContinuousFilter(coefficients.den).discretize(
            ts, coefficients.delay + skew_delay(ts, output_skew), intersample)
        channels = skew_extended(self.input_channels(u), output_skew)
        output = sum(discrete.outputs(channels[:, index], [num])[0]
                     for index, num in enumerate(coefficients.num))
        return output[1:] if output_skew else output

    def frequency_response(self, params: ParameterValues, omega,
                           input_name: Optional[str] = None) -> np.ndarray:
        """Complex ``G(j omega)`` from ``input_name`` (including the dead time) at ``omega``."""
        num, den, delay = self.transfer_function(params, input_name)
        s = 1j * np.asarray(omega, dtype=float)
        return np.polyval(num, s) / np.polyval(den, s) * np.exp(-delay * s)
