"""
A PID loop around a continuous-time plant with a dead time: stability, margins, step response.

Conventions (as python-control's ``margin`` and ``stability_margins``, with the dead time kept
exact instead of a Pade approximation):

* the plant is ``P(s) = N(s)/D(s) exp(-theta s)``, the controller the parallel filtered PID
  ``C(s) = kp + ki/s + kd s/(tf s + 1)`` (``tf = 0``: no derivative filter; the ros2_control
  PID's ``p``, ``i``, ``d``), negative feedback on the error ``e = r - y``;
* ``L = C P`` is the loop, ``S = 1/(1 + L)`` the sensitivity, ``T = L/(1 + L)`` the closed loop;
* every quantity is read on a dense logarithmic grid of ``L(j omega)`` (at least 1000 points a
  decade, refined until the phase of ``1 + L`` moves less than a radian between points) from
  three decades below the slowest corner to where ``|L|`` has fallen below 0.5;
* stability is the Nyquist criterion on that grid: ``Z = P + (m pi - 2 Delta) / (2 pi)``
  closed-loop poles in the right half plane, with ``P`` open-loop poles in the right half
  plane, ``m`` at the origin (plant integrators plus the controller's) and ``Delta`` the change
  of the argument of ``1 + L`` from ``0+`` to infinity (the contour passes the origin on the
  right);
* gain margin: the least factor by which the gain can grow before the loop is unstable, read
  where ``L`` crosses the negative real axis inside the unit circle (infinite if it never does);
  phase margin: ``180 + arg L`` in degrees at the gain crossovers ``|L| = 1``, the smallest;
  ``Ms = max |S|``; bandwidth: the lowest frequency where ``|T|`` falls below ``1/sqrt 2``.
"""

from dataclasses import dataclass
import math
from typing import Dict, Optional, Sequence, Tuple

from ctid_ros.core.model import Model
from ctid_ros.errors import ModelError
import numpy as np
from scipy import signal

__all__ = ['Gains', 'Margins', 'Plant', 'closed_loop_step', 'frequency_grid',
           'integral_absolute_error', 'json_number', 'loop_margins']

# Points per decade of the frequency grid, before refinement.
_DENSITY = 1000
# Largest change (rad) of the argument of 1 + L between grid points that the count trusts.
_PHASE_STEP = 1.0
# |L| below which the loop is taken as ended (its argument stays within a quarter turn of 0).
_ENDED = 0.5
# Relative size below which a root counts as zero (an integrator) or a real part as zero.
_ROOT_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Gains:
    """
    A parallel PID controller ``kp + ki/s + kd s/(tf s + 1)``.

    Attributes
    ----------
    kp, ki, kd : float
        Proportional, integral (1/s) and derivative (s) gains, as ros2_control's ``p``, ``i``
        and ``d`` of an error in the plant's output units.
    tf : float
        Time constant (s) of the derivative's first-order filter; 0 with ``kd = 0``.

    """

    kp: float
    ki: float
    kd: float = 0.0
    tf: float = 0.0

    @property
    def kind(self) -> str:
        """Return ``'PID'`` with a derivative gain, else ``'PI'``."""
        return 'PID' if self.kd else 'PI'

    def transfer_function(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return ``(num, den)`` of ``C(s)``, highest power first."""
        tf = self.tf
        if not self.ki:
            # No integrator, no pole at the origin to cancel.
            if not self.kd:
                return np.array([self.kp]), np.array([1.0])
            return np.array([self.kp * tf + self.kd, self.kp]), np.array([tf, 1.0])
        if not self.kd:
            return np.array([self.kp, self.ki]), np.array([1.0, 0.0])
        return (np.array([self.kp * tf + self.kd, self.kp + self.ki * tf, self.ki]),
                np.array([tf, 1.0, 0.0]))

    def response(self, omega: np.ndarray) -> np.ndarray:
        """Return ``C(j omega)``."""
        s = 1j * np.asarray(omega, dtype=float)
        derivative = self.kd * s / (self.tf * s + 1.0) if self.kd else 0.0
        return self.kp + (self.ki / s if self.ki else 0.0) + derivative

    def to_dict(self) -> Dict[str, float]:
        """Return ``{"kp", "ki"}``, with ``"kd"`` and ``"tf"`` for a PID."""
        gains = {'kp': float(self.kp), 'ki': float(self.ki)}
        if self.kd:
            gains.update(kd=float(self.kd), tf=float(self.tf))
        return gains


@dataclass(frozen=True)
class Plant:
    """
    A single-input plant ``num(s)/den(s) exp(-delay s)`` with numeric coefficients.

    Attributes
    ----------
    num, den : ndarray
        Coefficients, highest power first; leading zeros of ``num`` removed.
    delay : float
        Dead time in seconds (>= 0).

    """

    num: np.ndarray
    den: np.ndarray
    delay: float

    @classmethod
    def from_model(cls, model: Model, params) -> 'Plant':
        """
        Return the plant of ``model`` at ``params`` (the plant of a closed-loop model).

        Raises
        ------
        ModelError
            For a model with several inputs, a constant input or an undefined or improper
            transfer function at ``params``.

        """
        if model.controller is not None:
            model = Model(model.expression, inputs=model.inputs, output=model.output)
        if len(model.inputs) != 1 or model.constant_input:
            raise ModelError(f'a loop is designed for one input and no constant term; the model '
                             f'{model.expression} has inputs {", ".join(model.inputs)}'
                             + (' and a constant term' if model.constant_input else ''))
        num, den, delay = model.transfer_function(params)
        return cls.of(num, den, delay)

    @classmethod
    def of(cls, num: Sequence[float], den: Sequence[float], delay: float = 0.0) -> 'Plant':
        """Return the plant with these coefficients; the dead time is clipped at 0."""
        num = np.trim_zeros(np.atleast_1d(np.asarray(num, dtype=float)), 'f')
        den = np.trim_zeros(np.atleast_1d(np.asarray(den, dtype=float)), 'f')
        if not num.size or not den.size:
            raise ModelError('the transfer function is zero or has no denominator')
        if num.size > den.size:
            raise ModelError('the transfer function is improper (more zeros than poles)')
        return cls(num, den, max(float(delay), 0.0))

    def response(self, omega: np.ndarray) -> np.ndarray:
        """Return ``P(j omega)`` with the dead time."""
        s = 1j * np.asarray(omega, dtype=float)
        return np.polyval(self.num, s) / np.polyval(self.den, s) * np.exp(-self.delay * s)

    @property
    def poles(self) -> np.ndarray:
        """Return the roots of ``den``."""
        return np.roots(self.den)

    @property
    def zeros(self) -> np.ndarray:
        """Return the roots of ``num``."""
        return np.roots(self.num)

    @property
    def integrators(self) -> int:
        """Return the number of poles at the origin (trailing zero coefficients of ``den``)."""
        scale = np.max(np.abs(self.den))
        count = 0
        for value in self.den[::-1]:
            if abs(value) > _ROOT_TOLERANCE * scale:
                break
            count += 1
        return count

    def corners(self) -> np.ndarray:
        """Return the magnitudes of the nonzero poles and zeros and ``1/delay`` (rad/s)."""
        roots = np.abs(np.concatenate([self.poles, self.zeros]))
        corners = list(roots[roots > _ROOT_TOLERANCE * max(roots.max(initial=1.0), 1.0)])
        if self.delay > 0.0:
            corners.append(1.0 / self.delay)
        return np.array(corners)


def _unstable_poles(den: np.ndarray) -> int:
    """Return the number of roots of ``den`` with a positive real part (not at the origin)."""
    roots = np.roots(den)
    scale = max(np.max(np.abs(roots), initial=0.0), 1.0)
    return int(np.sum(roots.real > _ROOT_TOLERANCE * scale))


@dataclass(frozen=True)
class Margins:
    """
    Stability and robustness of one loop (conventions in the module docstring).

    Attributes
    ----------
    stable : bool
        No closed-loop pole in the closed right half plane.
    gain_db : float
        Gain margin in dB; ``inf`` if ``L`` never crosses the negative real axis inside the
        unit circle.
    phase_deg : float
        Phase margin in degrees; ``inf`` without a gain crossover.
    ms : float
        Peak of the sensitivity ``max |S(j omega)|``.
    crossover : float
        Lowest gain-crossover frequency (rad/s); NaN without one.
    bandwidth : float
        Closed-loop bandwidth (rad/s): lowest frequency where ``|T|`` falls below
        ``1/sqrt 2``; NaN if it starts below.
    unstable_poles : int
        Closed-loop poles in the right half plane (0 when stable).

    """

    stable: bool
    gain_db: float
    phase_deg: float
    ms: float
    crossover: float
    bandwidth: float
    unstable_poles: int

    def to_dict(self) -> Dict[str, Optional[float]]:
        """Return the margins as JSON numbers: infinite or undefined ones as null."""
        return {'gain_db': json_number(self.gain_db), 'phase_deg': json_number(self.phase_deg),
                'ms': json_number(self.ms), 'crossover': json_number(self.crossover),
                'bandwidth': json_number(self.bandwidth), 'stable': bool(self.stable)}


def json_number(value: Optional[float]) -> Optional[float]:
    """Return ``value`` as a float for JSON, or None if it is None, infinite or NaN."""
    return float(value) if value is not None and np.isfinite(value) else None


def _loop_polynomials(plant: Plant, gains: Gains) -> Tuple[np.ndarray, np.ndarray]:
    """Return the rational part of ``L = C P`` as ``(num, den)``."""
    num, den = gains.transfer_function()
    return np.polymul(plant.num, num), np.polymul(plant.den, den)


def frequency_grid(plant: Plant, gains: Gains) -> np.ndarray:
    """
    Return the grid (rad/s) the loop is read on (see the module docstring).

    Three decades below the slowest corner of plant and controller to the frequency, past the
    fastest corner and ten times ``1/delay``, where ``|L|`` has fallen below 0.5 (at most six
    more decades); :data:`_DENSITY` points a decade, doubled (twice at most) until the argument
    of ``1 + L`` moves less than a radian between points.
    """
    corners = list(plant.corners())
    if gains.kp and gains.ki:
        corners.append(abs(gains.ki / gains.kp))
    if gains.kd and gains.tf:
        corners.append(1.0 / gains.tf)
    corners = [value for value in corners if np.isfinite(value) and value > 0.0] or [1.0]
    low = math.log10(min(corners)) - 3.0
    high = math.log10(max(corners)) + 2.0
    for _ in range(6):
        if np.abs(plant.response([10.0 ** high]) * gains.response([10.0 ** high]))[0] < _ENDED:
            break
        high += 1.0
    density = _DENSITY
    for _ in range(3):
        omega = np.logspace(low, high, int(density * (high - low)) + 1)
        phase = np.unwrap(np.angle(1.0 + plant.response(omega) * gains.response(omega)))
        if np.max(np.abs(np.diff(phase))) < _PHASE_STEP:
            break
        density *= 2
    return omega


def _crossings(values: np.ndarray) -> np.ndarray:
    """Return indices ``i`` where ``values`` changes sign between ``i`` and ``i + 1``."""
    sign = values >= 0.0
    return np.flatnonzero(sign[:-1] != sign[1:])


def _interpolated(omega: np.ndarray, values: np.ndarray, index: int, level: np.ndarray
                  ) -> Tuple[float, float]:
    """Return the log-interpolated frequency where ``level`` is zero and ``values`` there."""
    a, b = level[index], level[index + 1]
    weight = a / (a - b)
    frequency = omega[index] * (omega[index + 1] / omega[index]) ** weight
    return float(frequency), float(values[index] + weight * (values[index + 1] - values[index]))


def loop_margins(plant: Plant, gains: Gains, omega: Optional[np.ndarray] = None) -> Margins:
    """
    Return the stability, margins, Ms and bandwidth of ``gains`` on ``plant``.

    Parameters
    ----------
    plant : Plant
        The plant with its dead time.
    gains : Gains
        The controller.
    omega : ndarray, optional
        Grid (rad/s); default :func:`frequency_grid`.

    Returns
    -------
    Margins
        See the module docstring for the conventions.

    """
    if omega is None:
        omega = frequency_grid(plant, gains)
    loop = plant.response(omega) * gains.response(omega)
    num, den = _loop_polynomials(plant, gains)
    integrators = plant.integrators + (1 if gains.ki else 0)
    open_unstable = _unstable_poles(plant.den)
    closed = _unstable_count(loop, num, den, integrators, open_unstable)
    magnitude = np.abs(loop)
    # The phase of L: the rational part unwrapped, the dead time exact (never wrapped).
    rational = np.polyval(num, 1j * omega) / np.polyval(den, 1j * omega)
    phase = np.degrees(np.unwrap(np.angle(rational)) - omega * plant.delay)
    phase_margin, crossover = np.inf, np.nan
    for index in _crossings(np.log(magnitude)):
        frequency, angle = _interpolated(omega, phase, index, np.log(magnitude))
        margin = (angle + 180.0) % 360.0
        margin = margin - 360.0 if margin > 180.0 else margin
        if margin < phase_margin:
            phase_margin = margin
        if not np.isfinite(crossover):
            crossover = frequency
    gain_margin = np.inf
    for index in _crossings(loop.imag):
        _, real = _interpolated(omega, loop.real, index, loop.imag)
        if -1.0 < real < 0.0:
            gain_margin = min(gain_margin, -1.0 / real)
    sensitivity = np.abs(1.0 / (1.0 + loop))
    closed_loop = np.abs(loop / (1.0 + loop))
    below = np.flatnonzero(closed_loop < 1.0 / math.sqrt(2.0))
    bandwidth = float(omega[below[0]]) if below.size and below[0] > 0 else np.nan
    return Margins(stable=closed == 0, gain_db=float(20.0 * np.log10(gain_margin)),
                   phase_deg=float(phase_margin), ms=float(np.max(sensitivity)),
                   crossover=float(crossover), bandwidth=bandwidth, unstable_poles=closed)


def _unstable_count(loop: np.ndarray, num: np.ndarray, den: np.ndarray, integrators: int,
                    open_unstable: int) -> int:
    """Return the closed-loop poles in the right half plane by the Nyquist criterion."""
    phase = np.unwrap(np.angle(1.0 + loop))
    # The argument of 1 + L as omega -> 0+: that of c / (j omega)^m, c = lim s^m L(s).
    if integrators:
        low = num[np.flatnonzero(num)[-1]] / den[len(den) - 1 - integrators]
        start = np.angle(low) - integrators * np.pi / 2.0
    else:
        start = np.angle(1.0 + num[-1] / den[-1])
    start = start + 2.0 * np.pi * np.round((phase[0] - start) / (2.0 * np.pi))
    # Beyond the grid |L| < 0.5: the argument ends on the whole turn nearest its last value.
    end = 2.0 * np.pi * np.round(phase[-1] / (2.0 * np.pi))
    change = end - start
    count = open_unstable + (integrators * np.pi - 2.0 * change) / (2.0 * np.pi)
    return max(int(round(count)), 0)


def integral_absolute_error(times: np.ndarray, output: np.ndarray, reference: float = 1.0
                            ) -> float:
    """Return ``integral |r - y| dt`` by the trapezoidal rule."""
    return float(np.trapezoid(np.abs(reference - output), times))


def closed_loop_step(plant: Plant, gains: Gains, horizon: float, steps: int = 4000
                     ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Simulate the loop's response to a unit reference step from rest.

    Plant and controller are discretised exactly for a held input at a step ``h`` (the
    controller's error held over each step, the plant's command likewise), the dead time is a
    whole number of steps (``h`` chosen so that it is, down to a quarter of ``horizon/steps``),
    and the loop ``u = C (r - y)`` is the discrete closed loop run by
    :func:`scipy.signal.lfilter`: exact as ``h`` goes to zero, within a few tenths of a
    percent at the default 4000 steps.

    Parameters
    ----------
    plant : Plant
        The plant.
    gains : Gains
        The controller.
    horizon : float
        Seconds to simulate.
    steps : int
        Steps over ``horizon`` (more where the dead time asks for a finer step, at most 4x).

    Returns
    -------
    times, output, command : ndarray
        Instants (s), plant output ``y`` and controller output ``u``.

    """
    step = horizon / steps
    delay_steps = 0
    if plant.delay > 0.0:
        # A dead time below a step shortens the step, to a quarter of it at most.
        step = min(step, max(plant.delay, step / 4))
        delay_steps = max(int(round(plant.delay / step)), 1)
        step = plant.delay / delay_steps
    count = int(math.ceil(horizon / step)) + 1
    plant_num, plant_den, _ = signal.cont2discrete((plant.num, plant.den), step, method='zoh')
    controller_num, controller_den, _ = signal.cont2discrete(gains.transfer_function(), step,
                                                             method='zoh')
    # Polynomials in z^-1: T = Bc Bp z^-d / (Ac Ap + Bc Bp z^-d), U/R = Bc Ap / (same).
    forward = np.concatenate([np.zeros(delay_steps),
                              np.polymul(np.ravel(controller_num), np.ravel(plant_num))])
    loop = np.polymul(np.ravel(controller_den), np.ravel(plant_den))
    size = max(forward.size, loop.size)
    forward = np.pad(forward, (0, size - forward.size))
    characteristic = np.pad(loop, (0, size - loop.size)) + forward
    reference = np.ones(count)
    output = signal.lfilter(forward, characteristic, reference)
    command = signal.lfilter(np.polymul(np.ravel(controller_num), np.ravel(plant_den)),
                             characteristic, reference)
    return step * np.arange(count), output, command
