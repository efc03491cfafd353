"""
A simulated plant for tests and demonstrations: exact sampled simulation, no ROS.

:class:`PlantSimulator` steps a continuous-time transfer function written as for
:class:`ctid_ros.Model` (``'K*exp(-tau*s)/(T*s + 1)'`` with numeric parameter values) one
sample at a time, exactly for a zero-order-hold input, including a dead time that is not a
multiple of the sample time (the modified discretisation of :mod:`ctid_ros.core.simulation`
with a history of past inputs). Two kinds of feedback close the loop around the held
reference ``r``:

* ``controller`` such as ``'20 + 10/s'``: the controller runs in continuous time together with
  the plant, as one system: the closed-loop data then match exactly the model
  ``P K/(1 + P K)`` the estimator fits, at any sample rate. The plant input ``u`` of the loop
  is a second output of that system, and the loop feeds back the noise-free output. A dead
  time cannot be inside such a loop (it would not be rational).
* ``pi_gains=(kp, ki)``: a digital PI controller (:class:`DigitalPI`), as on a real robot: at
  every sample it reads the measured (noisy) output, computes the command and holds it until
  the next sample. The plant may have a dead time; the data are identified from the measured
  command ``u`` to ``y`` (direct closed-loop identification).

Measurement noise (Gaussian, seeded) is added to ``y`` only. The ROS node that publishes a
simulator's samples is :mod:`ctid_ros.ros.plant_node`.
"""

from collections import deque
from dataclasses import dataclass
import itertools
from typing import Iterator, Mapping, Optional, Sequence, Tuple

from ctid_ros.core.excitation import prbs
from ctid_ros.core.model import Model
from ctid_ros.core.simulation import ContinuousFilter
from ctid_ros.errors import ConfigError
import numpy as np

__all__ = ['DigitalPI', 'PlantSimulator', 'excitation']


@dataclass
class DigitalPI:
    """
    Discrete PI controller run every sample: ``u[k] = kp e[k] + ki Ts (e[0] + ... + e[k])``.

    The integral is the backward-Euler sum, so the command reacts to the error of the sample it
    was computed from, as a controller that reads the sensor and writes the actuator in one
    cycle.

    Attributes
    ----------
    kp, ki : float
        Proportional and integral gains.
    sample_time : float
        Controller period in seconds.
    integral : float
        State of the integrator (the integral term of the last command).

    """

    kp: float
    ki: float
    sample_time: float
    integral: float = 0.0

    def __call__(self, error: float) -> float:
        """Return the command for the control error of this sample."""
        self.integral += self.ki * self.sample_time * error
        return self.kp * error + self.integral


class PlantSimulator:
    """
    Exact sample-by-sample simulation of a continuous-time plant, open or closed loop.

    Parameters
    ----------
    model : str
        Plant transfer function in ``s`` (syntax of :class:`ctid_ros.Model`).
    params : mapping
        Value of every model parameter.
    sample_time : float
        Seconds between samples; the excitation is held (ZOH) in between.
    controller : str
        Known controller ``K(s)`` with numeric coefficients, e.g. ``'20 + 10/s'``, simulated in
        continuous time with the plant; empty for none. The plant may then have no dead time.
    pi_gains : (float, float), optional
        Gains ``(kp, ki)`` of a :class:`DigitalPI` that closes the loop at the sample time on
        the measured output; the plant must be strictly proper. Not with ``controller``.
    noise_std : float
        Standard deviation of white Gaussian noise added to the measured output.
    seed : int
        Seed of the noise generator.

    """

    def __init__(self, model: str, params: Mapping[str, float], sample_time: float, *,
                 controller: str = '', pi_gains: Optional[Sequence[float]] = None,
                 noise_std: float = 0.0, seed: int = 0):
        if pi_gains and (controller or len(pi_gains) != 2):
            raise ConfigError(f'pi_gains must be two gains (kp, ki) and exclude a continuous '
                              f'controller; got {list(pi_gains)} with controller {controller!r}')
        self.sample_time = float(sample_time)
        self.noise_std = float(noise_std)
        self._plant = Model(model)
        self._loop = Model(model, controller) if controller else self._plant
        self._pi = DigitalPI(*pi_gains, self.sample_time) if pi_gains else None
        self._rng = np.random.default_rng(seed)
        self._state: Optional[np.ndarray] = None
        self._history: deque = deque([0.0])
        self.retune(params)
        if self._pi is not None and self._outputs[0][1] != 0.0:
            raise ConfigError(f'a digital controller needs a strictly proper plant (the output '
                              f'cannot react to the command it is computed from): {model}')

    @property
    def closed_loop(self) -> bool:
        """Return True when a controller closes the loop."""
        return self._loop is not self._plant or self._pi is not None

    @property
    def parameters(self) -> Tuple[str, ...]:
        """Return the plant parameter names."""
        return self._plant.parameters

    def retune(self, params: Mapping[str, float]) -> None:
        """
        Change the plant parameters, now or in mid-run (parameter drift).

        The state of the realisation is carried over as its phase variables ``s^j/D(s) r``, so
        the output stays continuous when only the denominator's lower coefficients or the gain
        change; the input history is kept.
        """
        num, den, delay = self._loop.transfer_function(params)
        numerators = [num]
        if self._loop is not self._plant:
            # u/r = K/(1 + P K) = (P K/(1 + P K)) * Dp/Np: the loop numerator is Np*Nk.
            plant_num, plant_den, _ = self._plant.transfer_function(params)
            controller_num, _ = np.polydiv(num, plant_num)
            numerators.append(np.polymul(plant_den, controller_num))
        realisation = ContinuousFilter(den)
        discrete = realisation.discretize(self.sample_time, delay, 'zoh')
        phase = self._phase_map(realisation)
        if self._state is not None and self._state.size == realisation.order:
            self._state = np.linalg.solve(phase, self._phase @ self._state)
        else:
            self._state = np.zeros(realisation.order)
        self._phase = phase
        self._discrete = discrete
        self._outputs = [realisation.output_map(numerator) for numerator in numerators]
        oldest = max(-offset for offset, _ in itertools.chain(discrete.drive, discrete.feed))
        history = list(self._history)[-(oldest + 1):]
        self._history = deque([0.0] * (oldest + 1 - len(history)) + history, maxlen=oldest + 1)

    @staticmethod
    def _phase_map(realisation: ContinuousFilter) -> np.ndarray:
        order = realisation.order
        rows = [realisation.output_map(np.eye(order)[order - 1 - power])[0]
                for power in range(order)]
        return np.array(rows).reshape(order, order)

    def _input(self, offset: int) -> float:
        return self._history[offset - 1]

    def step(self, value: float) -> Tuple[float, float]:
        """
        Apply ``value`` (``u`` open loop, ``r`` closed loop) from this sample instant on.

        Returns
        -------
        (float, float)
            The plant input ``u`` and the measured (noisy) output ``y`` at this instant.

        """
        noise = self.noise_std * float(self._rng.standard_normal())
        if self._pi is None:
            self._history.append(float(value))
            held = sum(weight * self._input(offset) for (offset, _), weight in
                       self._discrete.feed.items())
            outputs = [float(row @ self._state) + feed * held for row, feed in self._outputs]
            u, y = (outputs[1] if self.closed_loop else float(value)), outputs[0] + noise
        else:
            # No feedthrough (checked): y now does not depend on the command being computed.
            y = float(self._outputs[0][0] @ self._state) + noise
            u = self._pi(float(value) - y)
            self._history.append(u)
        forcing = sum(vector * self._input(offset) for (offset, _), vector in
                      self._discrete.drive.items())
        self._state = self._discrete.transition @ self._state + forcing
        return u, y


def excitation(bits: int, clock: int, amplitude: float = 1.0,
               offset: float = 0.0) -> Iterator[float]:
    """Return an endless PRBS(bits, clock) of levels ``offset +- amplitude``."""
    return itertools.cycle((offset + amplitude * prbs(bits, clock)).tolist())
