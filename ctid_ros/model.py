"""
Grey-box continuous-time transfer-function models.

A :class:`Model` is built from safe text (see :mod:`ctid_ros.expression`)::

    Model('1/(m*s**2 + d*s + k)')                 # mass-spring-damper, parameters m, d, k
    Model('K*exp(-tau*s)/(T*s + 1)')              # first order plus dead time
    Model('K/((T1*s + 1)*(T2*s + 1))')            # not affine in (K, T1, T2)
    Model('1/(J*s**2 + b*s)', controller='40 + 20/s')   # closed loop r -> y of P K/(1 + P K)

Every name other than ``s`` (and the constant ``pi``) is a parameter. ``model.parameters`` lists
them in order of first appearance in the plant expression. From the text the model derives the
coefficients of ``N(s, theta)`` and ``D(s, theta)``, their Jacobians with respect to ``theta``
(symbolically, then compiled to numpy), the dead time ``tau(theta)`` of an optional factor
``exp(-tau*s)``, and whether the structure is affine in ``theta`` (Condition 1 of the method).
"""

from dataclasses import dataclass
import keyword
from typing import Dict, Mapping, Optional, Sequence, Tuple, Union

from ctid_ros.errors import ModelError
from ctid_ros.expression import LAPLACE, MAX_DEGREE, parse_expression
from ctid_ros.simulation import ContinuousFilter, INTERSAMPLE
import numpy as np
import sympy as sp

ParameterValues = Union[Mapping[str, float], Sequence[float], np.ndarray]


@dataclass(frozen=True)
class Structure:
    """
    Numeric model structure at one parameter vector.

    Coefficient arrays are highest power of ``s`` first; Jacobians have one row per parameter.
    """

    num: np.ndarray
    den: np.ndarray
    delay: float
    num_jacobian: np.ndarray
    den_jacobian: np.ndarray
    delay_gradient: np.ndarray


def _split_delay(expression: sp.Expr, text: str) -> Tuple[sp.Expr, sp.Expr]:
    """Return ``(rational part, tau)`` with ``expression = rational * exp(-tau*s)``."""
    exponentials = [atom for atom in expression.atoms(sp.exp) if atom.has(LAPLACE)]
    if not exponentials:
        return expression, sp.Integer(0)
    if len(exponentials) > 1:
        raise ModelError(f'at most one dead-time factor exp(-tau*s) is allowed in {text!r}')
    factor = exponentials[0]
    argument = factor.args[0]
    slope = sp.cancel(argument / LAPLACE)
    if slope.has(LAPLACE):
        raise ModelError(f'exp({argument}) is not a dead time: its argument must be -tau*s with '
                         'tau independent of s')
    marker = sp.Dummy('delay')
    num, den = sp.fraction(sp.together(expression.subs(factor, marker)))
    if den.has(marker) or sp.Poly(num, marker).monoms() != [(1,)]:
        raise ModelError(f'the dead time exp({argument}) must multiply the whole transfer '
                         f'function (a factor), not appear in a sum or a power in {text!r}')
    tau = -slope
    if tau.is_number and tau < 0:
        raise ModelError(f'exp({argument}) is a time advance, not a dead time: write exp(-tau*s)')
    return sp.cancel(num / marker) / den, tau


def _polynomials(rational: sp.Expr, text: str) -> Tuple[sp.Poly, sp.Poly]:
    if any(atom.has(LAPLACE) for atom in rational.atoms(sp.exp)):
        raise ModelError(f'{text!r} has exp(...) of s outside a dead-time factor')
    if not rational.is_rational_function(LAPLACE):
        raise ModelError(f'{text!r} is not a rational function of s')
    num, den = sp.fraction(sp.together(rational))
    num_poly = sp.Poly(sp.expand(num), LAPLACE)
    den_poly = sp.Poly(sp.expand(den), LAPLACE)
    if den_poly.is_zero:
        raise ModelError(f'{text!r} has a zero denominator')
    return num_poly, den_poly


def _check_proper(num: sp.Poly, den: sp.Poly, text: str) -> None:
    if not num.is_zero and num.degree() > den.degree():
        raise ModelError(f'{text!r} is improper: numerator degree {num.degree()} exceeds '
                         f'denominator degree {den.degree()} (a physical plant cannot '
                         'differentiate its input)')


def _numeric_controller(text: str) -> Tuple[sp.Poly, sp.Poly]:
    expression, symbols = parse_expression(text)
    if symbols:
        names = ', '.join(str(symbol) for symbol in symbols)
        raise ModelError(f'controller {text!r} must have numeric coefficients; it has '
                         f'parameter(s) {names}')
    rational, tau = _split_delay(expression, text)
    if tau != 0:
        raise ModelError(f'controller {text!r} may not contain a dead time')
    num, den = _polynomials(rational, text)
    if num.is_zero:
        raise ModelError(f'controller {text!r} is identically zero')
    return num, den


def _coefficients(poly: sp.Poly, degree: int) -> list:
    coefficients = poly.all_coeffs() if not poly.is_zero else [sp.Integer(0)]
    return [sp.Integer(0)] * (degree + 1 - len(coefficients)) + coefficients


class Model:
    """
    Continuous-time grey-box transfer-function model ``G(s, theta)``.

    Parameters
    ----------
    expression : str
        Plant transfer function in ``s``; every other name is a parameter. At most one
        dead-time factor ``exp(-tau*s)`` (``tau`` may be a parameter or a number).
    controller : str, optional
        Known controller ``K(s)`` with numeric coefficients, e.g. ``'4 + 2/s'``. The model then
        describes the closed loop from reference ``r`` to output ``y``,
        ``P K / (1 + P K)``, while the parameters stay those of the plant ``P``.

    Raises
    ------
    ModelError
        If either text is unsafe, malformed, improper, or has a dead time that is not a factor.

    """

    def __init__(self, expression: str, controller: Optional[str] = None):
        if controller is not None and not isinstance(controller, str):
            raise ModelError(f'controller must be a string, got {type(controller).__name__}')
        self.expression = expression
        self.controller = controller if controller and controller.strip() else None
        parsed, symbols = parse_expression(expression)
        for symbol in symbols:
            if keyword.iskeyword(symbol.name):
                raise ModelError(f'parameter name {symbol.name!r} is a reserved word')
        rational, tau = _split_delay(parsed, expression)
        num, den = _polynomials(rational, expression)
        _check_proper(num, den, expression)
        if self.controller is not None:
            if tau != 0:
                raise ModelError(
                    'a dead time inside a closed loop makes P K/(1 + P K) irrational; identify '
                    'the plant open loop from its measured input u instead')
            k_num, k_den = _numeric_controller(self.controller)
            degree = max(num.degree() + k_num.degree(), den.degree() + k_den.degree())
            if degree > MAX_DEGREE:
                raise ModelError(f'the closed loop of {expression!r} with {self.controller!r} '
                                 f'has degree {degree} in s; the limit is {MAX_DEGREE}')
            num, den = num * k_num, den * k_den + num * k_num
            _check_proper(num, den, f'closed loop of {expression!r} with {self.controller!r}')
        self._symbols = symbols
        self.parameters: Tuple[str, ...] = tuple(symbol.name for symbol in symbols)
        if not self.parameters:
            raise ModelError(f'{expression!r} has no parameters to estimate')
        self._build(num, den, tau)

    def _build(self, num: sp.Poly, den: sp.Poly, tau: sp.Expr) -> None:
        self.num_degree = 0 if num.is_zero else num.degree()
        self.den_degree = den.degree()
        num_coefficients = _coefficients(num, self.num_degree)
        den_coefficients = _coefficients(den, self.den_degree)
        self._symbolic_num = num_coefficients
        self._symbolic_den = den_coefficients
        self._symbolic_delay = tau
        symbols = self._symbols
        jacobian = [[sp.diff(c, p) for p in symbols]
                    for c in num_coefficients + den_coefficients + [tau]]
        absent = [p.name for i, p in enumerate(symbols) if all(row[i] == 0 for row in jacobian)]
        if absent:
            raise ModelError(f'parameter(s) {", ".join(absent)} cancel out of the transfer '
                             'function, so no data can determine them; remove them')
        self.is_affine = all(not entry.has(*symbols) for row in jacobian for entry in row)
        self.has_delay = tau != 0
        self.delay_is_estimated = bool(tau.free_symbols)
        flat = num_coefficients + den_coefficients + [tau] + [e for row in jacobian for e in row]
        self._evaluate = sp.lambdify(symbols, flat, modules='numpy', dummify=True, cse=True)

    def __repr__(self) -> str:
        controller = f', controller={self.controller!r}' if self.controller else ''
        return f'Model({self.expression!r}{controller})'

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
        else:
            values = list(np.ravel(np.asarray(params, dtype=float)))
            if len(values) != len(self.parameters):
                raise ModelError(f'expected {len(self.parameters)} parameter values '
                                 f'({", ".join(self.parameters)}), got {len(values)}')
        vector = np.asarray(values, dtype=float)
        if not np.all(np.isfinite(vector)):
            raise ModelError(f'parameter values must be finite, got {vector}')
        return vector

    def as_dict(self, theta: Sequence[float]) -> Dict[str, float]:
        """Map a parameter vector back to ``{name: value}``."""
        return {name: float(value) for name, value in zip(self.parameters, theta)}

    def structure(self, params: ParameterValues) -> Structure:
        """Numeric ``N``, ``D``, dead time and their Jacobians at ``params``."""
        theta = self.vector(params)
        with np.errstate(all='ignore'):
            flat = np.asarray(self._evaluate(*theta), dtype=float)
        n_num, n_den, n_par = self.num_degree + 1, self.den_degree + 1, theta.size
        values, jacobian = flat[:n_num + n_den + 1], flat[n_num + n_den + 1:]
        jacobian = jacobian.reshape(n_num + n_den + 1, n_par).T
        if not np.all(np.isfinite(flat)):
            raise ModelError(f'the model is undefined at {self.as_dict(theta)} '
                             '(division by zero in a coefficient)')
        return Structure(
            num=values[:n_num], den=values[n_num:n_num + n_den], delay=float(values[-1]),
            num_jacobian=jacobian[:, :n_num], den_jacobian=jacobian[:, n_num:n_num + n_den],
            delay_gradient=jacobian[:, -1])

    def transfer_function(self, params: ParameterValues) -> Tuple[np.ndarray, np.ndarray, float]:
        """``(num, den, delay)`` with numeric coefficients (highest power first)."""
        structure = self.structure(params)
        return structure.num, structure.den, structure.delay

    def simulate(self, params: ParameterValues, u, ts: float, *,
                 intersample: str = 'zoh') -> np.ndarray:
        """
        Exact response of the model to sampled input ``u`` (the reference, in closed loop).

        Parameters
        ----------
        params : mapping or sequence
            Parameter values by name, or a vector in :attr:`parameters` order.
        u : array_like
            Input samples at ``t_k = k*ts``; the system is at rest before ``t_0``.
        ts : float
            Sample time in seconds.
        intersample : {'zoh', 'foh'}
            Input behaviour between samples.

        Returns
        -------
        ndarray
            Output samples at ``t_k``.

        """
        from ctid_ros.data import as_signal

        if intersample not in INTERSAMPLE:
            raise ModelError(f'intersample must be one of {INTERSAMPLE}, got {intersample!r}')
        num, den, delay = self.transfer_function(params)
        if delay < 0.0:
            raise ModelError(f'the dead time is negative ({delay:g} s) at '
                             f'{self.as_dict(self.vector(params))}: that is a time advance')
        if den[0] == 0.0:
            raise ModelError(f'the leading denominator coefficient vanishes at '
                             f'{self.as_dict(self.vector(params))}: the model order drops')
        discrete = ContinuousFilter(den).discretize(ts, delay, intersample)
        return discrete.outputs(as_signal(u, 'u'), [num])[0]

    def frequency_response(self, params: ParameterValues, omega) -> np.ndarray:
        """Complex ``G(j omega)`` (including the dead time) at angular frequencies ``omega``."""
        num, den, delay = self.transfer_function(params)
        s = 1j * np.asarray(omega, dtype=float)
        return np.polyval(num, s) / np.polyval(den, s) * np.exp(-delay * s)
