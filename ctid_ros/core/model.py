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
import math
from typing import Callable, Dict, Mapping, Optional, Sequence, Tuple, Union

from ctid_ros.core import model_cache
from ctid_ros.core.data import as_inputs
from ctid_ros.core.limits import check_model_text_length
from ctid_ros.core.simulation import (all_finite, ContinuousFilter, INTERSAMPLE, skew_delay,
                                      skew_extended)
from ctid_ros.errors import ModelError
import numpy as np

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
    """
    Return the attributes of the model of these texts (an error is raised each time).

    Stored on disk once derived and read back from there (:mod:`ctid_ros.core.model_cache`),
    so that a new process builds a known model without sympy.
    """
    key = (expression, controller, inputs, output)
    attributes = model_cache.load(key)
    if attributes is None:
        model = Model.__new__(Model)
        model._derive(expression, controller, inputs=inputs, output=output)
        attributes = dict(vars(model))
        model_cache.store(key, attributes)
    return attributes


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
        # A text too long for the parser is refused before sympy's import (a third of a second,
        # 34 MiB): a hostile parameter costs nothing. The controller's first, as derive says it.
        if controller is not None:
            try:
                check_model_text_length(controller)
            except ModelError as error:
                raise ModelError(f'controller: {error}') from None
        check_model_text_length(expression)
        # Imported here: sympy loads only for a model not yet derived.
        from ctid_ros.core.derivation import derive

        self.__dict__.update(derive(expression, controller, inputs=inputs, output=output))

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
        # Imported here: the parser brings sympy, which a model read from the store does not need.
        from ctid_ros.core.expression import tokenize

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
        # The estimator's own vectors (thousands per fit): read, never kept, not copied. A sum
        # (of Python floats, without numpy's dispatch) is finite if every value is (a finite
        # sum overflowing takes the full check).
        floats = self._floats
        theta = None
        if type(params) is np.ndarray and params.ndim == 1 and params.dtype == float and \
                params.size == len(self.parameters):
            values = params.tolist()
            if math.isfinite(sum(values)):
                theta = params
        if theta is None:
            theta = self.vector(params)
            values = theta.tolist()
        # Python floats where the program can take them (the same values, without numpy's
        # dispatch per operation); numpy scalars where a value becomes infinite or NaN.
        flat = floats(values) if floats is not None else None
        if flat is None:
            with np.errstate(all='ignore'):
                flat = np.asarray(self._evaluate(*theta), dtype=float)
        if not all_finite(flat):
            raise ModelError(f'the model is undefined at {self.as_dict(theta)} '
                             '(division by zero in a coefficient)')
        return flat

    @functools.cached_property
    def _floats(self) -> Optional[Callable[[Sequence[float]], Optional[np.ndarray]]]:
        # The program's float evaluation (None for a compiled function outside the program's
        # forms): looked up once, not per evaluation.
        evaluate = self._evaluate
        return evaluate.floats if isinstance(evaluate, model_cache.CoefficientProgram) else None

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
