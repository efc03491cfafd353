"""
PI and PID gains from an identified model, verified on it and across its uncertainty.

:func:`tune` designs by a stated method and then checks the loop the way a sceptical engineer
would (:mod:`~ctid_ros.design.margins`): on the estimate, and on parameter vectors drawn from
the estimate's covariance (seeded), so the margins come with the band the data allow.

The methods:

* ``'simc'``: Skogestad's SIMC rules (J. Process Control 13, 2003) for a first- or second-order
  plus dead time model (``k e^{-theta s}/((tau1 s + 1)(tau2 s + 1))``), integrating
  (``k e^{-theta s}/s``) or double integrating. A model of more real lags is first reduced by
  Skogestad's half rule (half of the largest lag left out goes to the next lag kept, half plus
  all smaller lags to the dead time). The rules are read off the numeric transfer function, not
  the parameter names, so any parameterisation of these structures qualifies. The target is the
  closed-loop time constant ``tc`` (default ``tc = theta``, SIMC's tight but robust choice:
  Ms about 1.6-1.7); a controller that runs every ``sample_time`` adds half of it to the dead
  time, for the design and for every verification. Series PID settings are converted to the
  parallel form, the derivative filtered with ``tf = Td/10`` (a lag that joins the dead time).
* ``'ms'``: a loop-shaping design on the exact continuous-time model with its dead time: the
  largest integral gain whose sensitivity peak stays below the target ``ms`` (default 1.6), as
  Astrom and Hagglund's MIGO; for PID over a few derivative times. Any stable or integrating
  model, also with zeros or complex poles.
* ``'auto'``: ``'simc'`` where the model is lags and dead time, else ``'ms'``.

Refused with :class:`~ctid_ros.errors.DesignError`: an open-loop unstable model; a
non-minimum-phase or complex-pole model for the SIMC rule; a PI for a double integrator (it
cannot stabilise it); a PID for a single lag by SIMC (its derivative acts on a second lag).
"""

from dataclasses import dataclass, field
import math
from typing import Dict, List, Mapping, Optional, Tuple

from ctid_ros.core.model import Model
from ctid_ros.design.margins import (closed_loop_step, Gains, json_number, loop_margins, Margins,
                                     Plant)
from ctid_ros.errors import ConfigError, DesignError, ModelError
import numpy as np

__all__ = ['CONTROLLERS', 'DEFAULT_MS', 'DERIVATIVE_FILTER', 'METHODS', 'Reduced', 'Tuning',
           'default_horizon', 'loop_shaping', 'parameter_draws', 'reduce', 'simc', 'step_band',
           'tune', 'tune_from_settings', 'with_hold']

CONTROLLERS = ('PI', 'PID')
METHODS = ('auto', 'simc', 'ms')
# Sensitivity peak aimed at by the loop-shaping design (SIMC with tc = theta gives 1.6-1.7).
DEFAULT_MS = 1.6
# Derivative filter: tf = Td / DERIVATIVE_FILTER.
DERIVATIVE_FILTER = 10.0
# Imaginary part, relative to the modulus, below which a pole counts as real.
_REAL = 1e-6
# Percentiles of the band over covariance draws (a 95 % band).
_BAND = (2.5, 97.5)
# Derivative times tried by the loop-shaping PID, in units of 1/omega_135.
_DERIVATIVE_TIMES = (0.1, 0.2, 0.35, 0.5, 0.75)
# Proportional gains tried by the loop-shaping design, up to the largest the Ms target allows.
_GAIN_STEPS = 40


@dataclass(frozen=True)
class Reduced:
    """
    A model read as SIMC's ``k e^{-theta s} / (s^m (tau1 s + 1)(tau2 s + 1))``.

    Attributes
    ----------
    gain : float
        ``k``: the static gain, or the velocity (acceleration) gain of an integrating (double
        integrating) plant.
    lags : tuple of float
        ``(tau1,)`` or ``(tau1, tau2)`` kept, largest first; may be empty.
    delay : float
        Effective dead time ``theta`` (s), what the half rule moved into it included.
    integrators : int
        ``m``, 0 to 2.
    note : str
        How it was obtained (exactly, or by the half rule from which lags).

    """

    gain: float
    lags: Tuple[float, ...]
    delay: float
    integrators: int
    note: str

    def describe(self) -> str:
        """Return the reduced transfer function as text."""
        parts = ['s' if self.integrators == 1 else f's**{self.integrators}'] \
            if self.integrators else []
        parts += [f'({lag:.4g}*s + 1)' for lag in self.lags]
        below = '*'.join(parts) or '1'
        below = f'({below})' if len(parts) > 1 else below
        return f'{self.gain:.4g}*exp(-{self.delay:.4g}*s)/{below}'


def _lags_and_gain(plant: Plant) -> Tuple[float, List[float], int, List[str]]:
    """
    Return the static (velocity) gain, the real lags, the integrators and what else is there.

    ``what else``: words for zeros, complex or unstable poles (empty for SIMC's structures).
    """
    integrators = plant.integrators
    den = plant.den[:len(plant.den) - integrators]
    poles = np.roots(den) if den.size > 1 else np.zeros(0)
    objections = []
    zeros = plant.zeros
    unstable_zeros = zeros[zeros.real > 0]
    if unstable_zeros.size:
        objections.append('non-minimum-phase (zero at '
                          + ', '.join(f'{value:.4g}' for value in unstable_zeros) + ')')
    elif zeros.size:
        objections.append('zeros at ' + ', '.join(f'{value:.4g}' for value in zeros))
    complex_poles = poles[np.abs(poles.imag) > _REAL * np.abs(poles)]
    if complex_poles.size:
        objections.append('complex poles (' + ', '.join(f'{value:.4g}' for value in complex_poles)
                          + ')')
    lags = sorted((-1.0 / pole.real for pole in poles
                   if abs(pole.imag) <= _REAL * abs(pole) and pole.real < 0), reverse=True)
    gain = float(plant.num[-1] / den[-1]) if plant.num[-1] and den[-1] else 0.0
    return gain, lags, integrators, objections


def _check_stable(plant: Plant, model_text: str) -> None:
    """Refuse an open-loop unstable plant (a pole in the right half plane)."""
    poles = plant.poles
    scale = max(np.max(np.abs(poles), initial=0.0), 1.0)
    unstable = poles[poles.real > 1e-9 * scale]
    if unstable.size:
        raise DesignError(
            f'the model {model_text} is open-loop unstable (pole at '
            + ', '.join(f'{value:.4g}' for value in unstable) + '): the tuning rules and the '
            'loop-shaping design here start from a stable or integrating plant; stabilise it '
            'first (an inner loop) and identify that loop')
    if plant.integrators > 2:
        raise DesignError(f'the model {model_text} has {plant.integrators} integrators: no PI '
                          'or PID rule covers more than two')


def reduce(plant: Plant, controller: str = 'PI', model_text: str = 'model') -> Reduced:
    """
    Return the SIMC reading of ``plant`` for ``controller`` (exact, or by the half rule).

    Raises
    ------
    DesignError
        If the plant is unstable, non-minimum-phase, has zeros or complex poles, or has more
        than two integrators.

    """
    _check_stable(plant, model_text)
    gain, lags, integrators, objections = _lags_and_gain(plant)
    if objections:
        raise DesignError(f'the SIMC rule takes lags and a dead time only; the model '
                          f'{model_text} has {" and ".join(objections)}: use the loop-shaping '
                          "design (method 'ms')")
    if gain == 0.0:
        raise DesignError(f'the model {model_text} has zero gain: nothing to control')
    # Slots the rule keeps: tau1 (and tau2 for PID) minus those the integrators take.
    slots = max((2 if controller == 'PID' else 1) - integrators, 0)
    kept, rest = lags[:slots], lags[slots:]
    delay = plant.delay
    note = 'exact'
    if rest:
        half = rest[0] / 2.0
        if kept:
            kept[-1] += half
        delay += half + sum(rest[1:])
        note = (f'half rule: the lag {rest[0]:.4g} s split between '
                f'{"the lag kept and " if kept else ""}the dead time'
                + (f', the lags {", ".join(f"{lag:.4g}" for lag in rest[1:])} s added to it'
                   if rest[1:] else ''))
    return Reduced(gain, tuple(kept), delay, integrators, note)


def simc(reduced: Reduced, controller: str = 'PI', tc: Optional[float] = None) -> Gains:
    """
    Return SIMC's PI or PID gains (parallel form) for a reduced model.

    Parameters
    ----------
    reduced : Reduced
        The model as :func:`reduce` read it for ``controller``.
    controller : {'PI', 'PID'}
        Controller type.
    tc : float, optional
        Closed-loop time constant (s); default the effective dead time.

    Raises
    ------
    DesignError
        For a PI on a double integrator, a PID without a second lag to act on, or no dead time
        and no ``tc``.

    """
    theta, k, m = reduced.delay, reduced.gain, reduced.integrators
    if tc is None:
        tc = theta
    if not tc > 0.0:
        raise DesignError('the model has no dead time, so SIMC has no default speed: give the '
                          'closed-loop time constant (target tc=SECONDS)')
    total = tc + theta
    if controller == 'PI':
        if m == 2:
            raise DesignError('a PI controller cannot stabilise a double integrator '
                              '(the loop keeps -180 degrees of phase): ask for a PID')
        if m == 1:
            kc, ti = 1.0 / (k * total), 4.0 * total
        elif not reduced.lags:
            # A pure dead time: the limit tau1 -> 0 of the rule, an integral controller.
            return Gains(0.0, float(1.0 / (k * total)))
        else:
            tau1 = reduced.lags[0]
            kc, ti = tau1 / (k * total), min(tau1, 4.0 * total)
        return Gains(float(kc), float(kc / ti))
    if m == 1 and not reduced.lags:
        raise DesignError('SIMC gives an integrating plant without a lag a PI (the '
                          "derivative acts on a lag): ask for 'PI'")
    if m == 0 and len(reduced.lags) < 2:
        raise DesignError("SIMC's derivative acts on a second lag and the model has one "
                          "(a first-order plus dead time): ask for 'PI'")
    # The derivative filter is one more small lag: it joins the dead time (half rule), and
    # the settings are computed again with it (once: it is a tenth of Td).
    settings = _series_pid(reduced, tc, theta)
    lag = settings[2] / (1.0 + settings[2] / settings[1]) / DERIVATIVE_FILTER
    kc, ti, td = _series_pid(reduced, tc + (lag if tc == theta else 0.0), theta + lag)
    # Series (interacting) settings to the parallel form.
    factor = 1.0 + td / ti
    kp, ti_parallel, td_parallel = kc * factor, ti + td, td / factor
    return Gains(float(kp), float(kp / ti_parallel), float(kp * td_parallel), float(lag))


def _series_pid(reduced: Reduced, tc: float, theta: float) -> Tuple[float, float, float]:
    """Return SIMC's series ``(Kc, tau_I, tau_D)`` for dead time ``theta``."""
    k, total = reduced.gain, tc + theta
    if reduced.integrators == 2:
        return 1.0 / (4.0 * k * total ** 2), 4.0 * total, 4.0 * total
    if reduced.integrators == 1:
        return 1.0 / (k * total), 4.0 * total, reduced.lags[0]
    tau1, tau2 = reduced.lags
    return tau1 / (k * total), min(tau1, 4.0 * total), tau2


def _design_grid(plant: Plant) -> np.ndarray:
    """Return the grid (rad/s) the loop-shaping design evaluates Ms on: 300 points a decade."""
    corners = plant.corners()
    corners = corners[np.isfinite(corners) & (corners > 0)]
    low, high = (corners.min(), corners.max()) if corners.size else (1.0, 1.0)
    low, high = math.log10(low) - 3.0, math.log10(high) + 2.5
    return np.logspace(low, high, int(300 * (high - low)) + 1)


def _phase_frequency(plant: Plant, omega: np.ndarray, degrees: float) -> Optional[float]:
    """
    Return the lowest frequency where the plant's phase falls below ``degrees``, or None.

    The phase of ``sign(k) P``, starting at ``-90 m`` degrees for ``m`` integrators.
    """
    rational = np.polyval(plant.num, 1j * omega) / np.polyval(plant.den, 1j * omega)
    phase = np.degrees(np.unwrap(np.angle(rational * _sign(plant))) - omega * plant.delay)
    phase = phase - 360.0 * np.round((phase[0] + 90.0 * plant.integrators) / 360.0)
    below = np.flatnonzero(phase < degrees)
    return float(omega[below[0]]) if below.size else None


def loop_shaping(plant: Plant, controller: str = 'PI', ms: float = DEFAULT_MS,
                 model_text: str = 'model') -> Gains:
    """
    Return the gains of the largest integral gain whose sensitivity peak stays below ``ms``.

    For every proportional gain (up to the largest a P controller keeps within ``ms``) the
    integral gain is raised geometrically until ``max |S|`` exceeds ``ms``, then bisected;
    the pair with the largest integral gain whose closed loop is stable wins. A PID tries
    ``kd = kp Td`` for a few ``Td`` (fractions of ``1/omega_135``, where the plant's phase
    reaches -135 degrees) with ``tf = Td/10``.

    Raises
    ------
    DesignError
        For an unstable plant, a double integrator, or when no gains meet ``ms``.

    """
    _check_stable(plant, model_text)
    if not ms > 1.0:
        raise DesignError(f'the sensitivity peak target must exceed 1, got {ms:g}')
    if plant.integrators == 2:
        raise DesignError('the loop-shaping design starts from a proportional loop, which a '
                          "double integrator does not have: use the SIMC rule (method 'simc')")
    omega = _design_grid(plant)
    # Designed for the plant of positive gain; the gains take the plant's sign.
    sign = _sign(plant)
    response = sign * plant.response(omega)
    s = 1j * omega
    reference = _phase_frequency(plant, omega, -135.0) or float(omega[-1] / 100.0)
    times = (0.0,) if controller == 'PI' else tuple(value / reference
                                                    for value in _DERIVATIVE_TIMES)
    best: Optional[Tuple[float, Gains]] = None
    for td in times:
        def peak(kp: float, ki: float) -> float:
            derivative = kp * td * s / (td / DERIVATIVE_FILTER * s + 1.0) if td else 0.0
            loop = response * (kp + ki / s + derivative)
            return float(np.max(np.abs(1.0 / (1.0 + loop))))

        kp_max = _largest(lambda kp: peak(kp, 0.0) <= ms, 1e-6 / abs(response[0]))
        if kp_max is None:
            continue
        for kp in np.linspace(kp_max / _GAIN_STEPS, kp_max, _GAIN_STEPS):
            ki = _largest(lambda value, kp=kp: peak(kp, value) <= ms,
                          1e-6 * kp * reference)
            if ki is None:
                continue
            gains = Gains(sign * float(kp), sign * ki, sign * float(kp * td),
                          td / DERIVATIVE_FILTER) if td else Gains(sign * float(kp), sign * ki)
            if best is None or ki > best[0]:
                margins = loop_margins(plant, gains)
                if margins.stable:
                    best = (ki, gains)
    if best is None:
        raise DesignError(f'no {controller} keeps the sensitivity peak of {model_text} below '
                          f'{ms:g}; allow a larger Ms (target ms=...)')
    return best[1]


def _sign(plant: Plant) -> float:
    """Return the sign of the plant's static (velocity) gain."""
    den = plant.den[:len(plant.den) - plant.integrators]
    num = plant.num[np.flatnonzero(plant.num)[-1]]
    return 1.0 if num * den[-1] > 0 else -1.0


def _largest(feasible, start: float, factor: float = 1.5, limit: int = 120) -> Optional[float]:
    """
    Return (about) the largest value ``feasible`` accepts, ladder from ``start`` then bisection.

    None if ``start`` itself is refused; the last rung if no rung is refused.
    """
    if not feasible(start):
        return None
    good = start
    bad = None
    for _ in range(limit):
        trial = good * factor
        if not feasible(trial):
            bad = trial
            break
        good = trial
    if bad is None:
        return good
    for _ in range(30):
        middle = math.sqrt(good * bad)
        if feasible(middle):
            good = middle
        else:
            bad = middle
        if bad / good < 1.001:
            break
    return good


def parameter_draws(model: Model, params: Mapping[str, float], covariance: np.ndarray,
                    count: int, seed: int = 0) -> List[Dict[str, float]]:
    """
    Return ``count`` parameter sets drawn from the normal distribution of the estimate.

    Parameters without a finite variance (held at a bound) keep their value. Seeded.
    """
    theta = model.vector(params)
    covariance = np.asarray(covariance, dtype=float)
    free = np.isfinite(np.diag(covariance)) if covariance.size else np.zeros(theta.size, bool)
    if not np.any(free) or count < 1:
        return []
    rng = np.random.default_rng(seed)
    sub = covariance[np.ix_(free, free)]
    if not np.all(np.isfinite(sub)):
        return []
    draws = rng.multivariate_normal(theta[free], sub, size=count, method='eigh')
    result = []
    for row in draws:
        vector = theta.copy()
        vector[free] = row
        result.append(model.as_dict(vector))
    return result


@dataclass(frozen=True)
class Tuning:
    """
    The result of :func:`tune`.

    Attributes
    ----------
    controller : {'PI', 'PID'}
        Controller type.
    gains : Gains
        Parallel gains ``kp``, ``ki`` (1/s), ``kd`` (s), derivative filter ``tf`` (s).
    method : str
        The method and what it rested on, in words (the rule, the reduced model, the target).
    target : dict
        ``{'tc': seconds}`` (SIMC) or ``{'ms': peak}`` (loop shaping).
    margins : Margins
        Of the controller on the identified model.
    band : dict
        ``{name: (low, high)}``: 95 % of the covariance draws' gain_db, phase_deg, ms and
        bandwidth (an infinite margin counts as large).
    draws : int
        Covariance draws the band is made of.
    unstable_draws : int
        Draws whose closed loop is unstable.
    warnings : list of str
        What a user should know (unstable draws, a weak margin).
    model, params, covariance
        The identified model the design used, for :func:`step_band`.
    hold : float
        Half the controller's sample time (s), added to the model's dead time wherever the
        loop is verified (the hold's delay); 0 for a continuous controller.

    """

    controller: str
    gains: Gains
    method: str
    target: Dict[str, float]
    margins: Margins
    band: Dict[str, Tuple[Optional[float], Optional[float]]]
    draws: int
    unstable_draws: int
    warnings: List[str] = field(default_factory=list)
    model: Optional[Model] = None
    params: Dict[str, float] = field(default_factory=dict)
    covariance: Optional[np.ndarray] = None
    hold: float = 0.0

    def to_dict(self, joint: str = 'joint1') -> dict:
        """
        Return the ``ctid tune --json`` object.

        ``gains``, ``margins`` (nominal, with ``band``), ``method``, ``target``, ``draws``,
        ``unstable_draws``, ``warnings`` and ``ros2_control``: the params YAML for ``joint``.
        """
        margins = self.margins.to_dict()
        margins['band'] = {name: [json_number(low), json_number(high)]
                           for name, (low, high) in self.band.items()}
        return {'controller': self.controller, 'gains': self.gains.to_dict(),
                'margins': margins, 'method': self.method, 'target': dict(self.target),
                'draws': self.draws, 'unstable_draws': self.unstable_draws,
                'warnings': list(self.warnings), 'ros2_control': self.ros2_control_yaml(joint)}

    def ros2_control_params(self, joint: str = 'joint1',
                            controller_name: str = 'pid_controller') -> dict:
        """
        Return params for ros2_controllers' ``pid_controller``: ``gains.<joint>.p/i/d``.

        ``i`` and ``d`` are the parallel gains (``u = p e + i int e dt + d de/dt``, as
        control_toolbox's PID); its derivative is not filtered, so ``tf`` is not included.
        """
        gains = {'p': float(self.gains.kp), 'i': float(self.gains.ki),
                 'd': float(self.gains.kd)}
        return {controller_name: {'ros__parameters': {
            'dof_names': [joint], 'gains': {joint: gains}}}}

    def ros2_control_yaml(self, joint: str = 'joint1',
                          controller_name: str = 'pid_controller') -> str:
        """Return :meth:`ros2_control_params` as YAML text, with the method as a comment."""
        import yaml

        header = (f'# {self.controller} from ctid tune: {self.method}\n'
                  f'# margins on the identified model: {_margin_text(self.margins)}\n')
        return header + yaml.safe_dump(self.ros2_control_params(joint, controller_name),
                                       sort_keys=False, default_flow_style=False)


def _margin_text(margins: Margins) -> str:
    gain = 'inf' if not np.isfinite(margins.gain_db) else f'{margins.gain_db:.1f}'
    phase = 'inf' if not np.isfinite(margins.phase_deg) else f'{margins.phase_deg:.0f}'
    return f'gain {gain} dB, phase {phase} deg, Ms {margins.ms:.2f}'


def _target(target, method: str) -> Dict[str, float]:
    """Check ``target``: None, ``{'tc': s}`` for SIMC or ``{'ms': peak}`` for loop shaping."""
    if target is None:
        return {}
    if not isinstance(target, Mapping) or len(target) != 1:
        raise ConfigError(f'target must be {{"tc": seconds}} or {{"ms": peak}}, got {target!r}')
    (name, value), = target.items()
    if name not in ('tc', 'ms'):
        raise ConfigError(f"target must name tc (SIMC's closed-loop time constant, s) or ms "
                          f'(the sensitivity peak of the loop-shaping design), got {name!r}')
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f'target {name} must be a number, got {value!r}') from None
    if not (np.isfinite(value) and value > (1.0 if name == 'ms' else 0.0)):
        raise ConfigError(f'target {name} must be ' + ('above 1' if name == 'ms' else
                                                       'positive seconds') + f', got {value:g}')
    wanted = {'tc': 'simc', 'ms': 'ms'}[name]
    if method not in ('auto', wanted):
        raise ConfigError(f"target {name} belongs to method '{wanted}', not '{method}'")
    return {name: value}


def tune(estimate, controller: str = 'PI', method: str = 'auto',
         target: Optional[Mapping[str, float]] = None, *, sample_time: Optional[float] = None,
         draws: int = 200, seed: int = 0) -> Tuning:
    """
    Design a PI or PID controller from an identified model and verify it.

    Parameters
    ----------
    estimate : Estimate
        The identified model (``model``, ``params``, ``covariance``); of a closed-loop model the
        plant is used.
    controller : {'PI', 'PID'}
        Controller type.
    method : {'auto', 'simc', 'ms'}
        Design method (module docstring); ``'auto'``: SIMC for lags and dead time, else
        loop shaping.
    target : dict, optional
        ``{'tc': seconds}``: SIMC's closed-loop time constant (default the effective dead
        time); ``{'ms': peak}``: the loop-shaping design's sensitivity peak (default 1.6).
        Naming a target picks its method under ``'auto'``.
    sample_time : float, optional
        Period of the digital controller: half of it (the hold's delay) is added to the
        model's dead time, for the design and wherever the loop is verified. Default: a
        continuous controller.
    draws : int
        Covariance draws for the band (0: none).
    seed : int
        Seed of the draws.

    Returns
    -------
    Tuning
        Gains, method, margins on the model and their band over the draws.

    Raises
    ------
    ConfigError
        For an unknown controller, method or target.
    DesignError
        For a model the method cannot design for (module docstring), or when the loop is not
        stable on the identified model itself.

    """
    if controller not in CONTROLLERS:
        raise ConfigError(f'controller must be one of {", ".join(CONTROLLERS)}, got '
                          f'{controller!r}')
    if method not in METHODS:
        raise ConfigError(f'method must be one of {", ".join(METHODS)}, got {method!r}')
    goal = _target(target, method)
    if sample_time is not None and not (np.isfinite(sample_time) and sample_time > 0):
        raise ConfigError(f'sample_time must be positive seconds, got {sample_time!r}')
    model, params = estimate.model, dict(estimate.params)
    text = model.expression
    hold = 0.5 * sample_time if sample_time else 0.0
    try:
        plant = with_hold(model, params, hold)
    except ModelError as error:
        raise DesignError(str(error)) from None
    if method == 'auto':
        method = 'ms' if 'ms' in goal else 'simc' if 'tc' in goal else _automatic(plant)
    if method == 'simc':
        reduced = reduce(plant, controller, text)
        tc = goal.get('tc', reduced.delay)
        gains = simc(reduced, controller, tc)
        goal = {'tc': float(tc)}
        held = f'; dead time + half the {sample_time:g} s sample time' if hold else ''
        default = '' if 'tc' in (target or {}) else ' (= the effective dead time)'
        description = (f'SIMC {controller} (Skogestad 2003) on {reduced.describe()} '
                       f'({reduced.note}{held}), tc = {tc:.4g} s{default}')
    else:
        ms = goal.get('ms', DEFAULT_MS)
        gains = loop_shaping(plant, controller, ms, text)
        goal = {'ms': float(ms)}
        held = f' plus half the {sample_time:g} s sample time' if hold else ''
        description = (f'loop shaping {controller}: the largest integral gain with Ms <= '
                       f'{ms:g} on the exact model {text} with its dead time{held} (MIGO)')
    margins = loop_margins(plant, gains)
    if not margins.stable:
        raise DesignError(f'the {controller} designed by {description} does not stabilise the '
                          f'identified model ({margins.unstable_poles} closed-loop poles in the '
                          'right half plane); choose a slower target')
    band, count, unstable = _band(model, params, estimate.covariance, gains, draws, seed, hold)
    notes = []
    if unstable:
        notes.append(f'{unstable} of {count} covariance draws give an unstable loop: the model '
                     'is not known well enough for this speed; choose a slower target or '
                     'identify on richer data')
    if margins.ms > 2.0:
        notes.append(f'Ms {margins.ms:.2f} on the identified model: above 2, little robustness')
    return Tuning(controller, gains, description, goal, margins, band, count, unstable, notes,
                  model, params, np.asarray(estimate.covariance, dtype=float), hold)


def with_hold(model: Model, params: Mapping[str, float], hold: float = 0.0) -> Plant:
    """Return the plant of ``model`` at ``params`` with ``hold`` seconds more dead time."""
    plant = Plant.from_model(model, params)
    return Plant(plant.num, plant.den, plant.delay + hold) if hold else plant


def _automatic(plant: Plant) -> str:
    """Return 'simc' for lags and a dead time (integrators allowed), else 'ms'."""
    _, _, integrators, objections = _lags_and_gain(plant)
    return 'ms' if objections and integrators < 2 else 'simc'


def _band(model: Model, params: Mapping[str, float], covariance: np.ndarray, gains: Gains,
          count: int, seed: int, hold: float
          ) -> Tuple[Dict[str, Tuple[Optional[float], Optional[float]]], int, int]:
    """Return the 95 % band of the margins over covariance draws, the draws, the unstable."""
    rows = []
    unstable = 0
    for values in parameter_draws(model, params, covariance, count, seed):
        try:
            margins = loop_margins(with_hold(model, values, hold), gains)
        except ModelError:
            continue
        if not margins.stable:
            unstable += 1
            rows.append((-np.inf, -np.inf, np.inf, np.nan))
            continue
        rows.append((margins.gain_db, margins.phase_deg, margins.ms, margins.bandwidth))
    if not rows:
        return {}, 0, 0
    table = np.array(rows, dtype=float)
    band = {}
    for index, name in enumerate(('gain_db', 'phase_deg', 'ms', 'bandwidth')):
        column = table[:, index]
        column = column[~np.isnan(column)]
        if not column.size:
            continue
        # An infinite margin (no crossing) is larger than any finite one: percentiles of the
        # ranks keep it so, and report it as None.
        low, high = (_percentile(column, value) for value in _BAND)
        band[name] = (low, high)
    return band, len(rows), unstable


def _percentile(values: np.ndarray, percent: float) -> Optional[float]:
    """Return the percentile (nearest rank) of ``values``, infinite ones included; None for inf."""
    ordered = np.sort(values)
    index = int(np.clip(round(percent / 100.0 * (ordered.size - 1)), 0, ordered.size - 1))
    return json_number(ordered[index])


def step_band(tuning: Tuning, horizon: Optional[float] = None, draws: int = 40,
              seed: int = 0) -> Tuple[np.ndarray, np.ndarray, Optional[np.ndarray], np.ndarray]:
    """
    Return the closed-loop unit step response on the model and its 95 % band over draws.

    Returns
    -------
    times, nominal : ndarray
        Seconds and the output on the identified model.
    band : ndarray or None
        ``(2, len(times))``: 2.5 and 97.5 percentiles over the stable draws (None without).
    command : ndarray
        The controller output on the identified model.

    """
    plant = with_hold(tuning.model, tuning.params, tuning.hold)
    if horizon is None:
        horizon = default_horizon(tuning.margins, plant)
    times, nominal, command = closed_loop_step(plant, tuning.gains, horizon)
    outputs = []
    for values in parameter_draws(tuning.model, tuning.params, tuning.covariance, draws, seed):
        try:
            draw = with_hold(tuning.model, values, tuning.hold)
        except ModelError:
            continue
        if not loop_margins(draw, tuning.gains).stable:
            continue
        _, output, _ = closed_loop_step(draw, tuning.gains, horizon, steps=times.size - 1)
        outputs.append(np.interp(times, np.linspace(0.0, horizon, output.size), output))
    band = np.percentile(outputs, _BAND, axis=0) if outputs else None
    return times, nominal, band, command


def default_horizon(margins: Margins, plant: Plant) -> float:
    """Return the seconds a step response is shown for: 12 / crossover, at least 6 dead times."""
    crossover = margins.crossover if np.isfinite(margins.crossover) else margins.bandwidth
    horizon = 12.0 / crossover if np.isfinite(crossover) and crossover > 0 else 10.0
    return float(max(horizon, 6.0 * plant.delay))


def tune_from_settings(estimate, settings: Mapping[str, object]) -> Tuning:
    """
    Tune from a ``tune:`` params mapping, for the node and the replay.

    ``settings``: ``controller`` (``PI``/``PID``, default PI), ``method`` (default auto),
    ``tc`` or ``ms`` (the target), ``sample_time``, ``draws``, ``seed``. Unknown keys are a
    :class:`~ctid_ros.errors.ConfigError`.
    """
    known = {'controller', 'method', 'tc', 'ms', 'sample_time', 'draws', 'seed', 'joint'}
    unknown = sorted(set(settings) - known)
    if unknown:
        raise ConfigError(f'tune: unknown keys {", ".join(map(str, unknown))}; known: '
                          f'{", ".join(sorted(known))}')
    targets = {name: settings[name] for name in ('tc', 'ms') if name in settings}
    if len(targets) > 1:
        raise ConfigError('tune: give tc (SIMC) or ms (loop shaping), not both')
    return tune(estimate, str(settings.get('controller', 'PI')),
                str(settings.get('method', 'auto')), targets or None,
                sample_time=settings.get('sample_time'), draws=int(settings.get('draws', 200)),
                seed=int(settings.get('seed', 0)))
