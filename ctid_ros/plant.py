"""
A simulated plant for tests and demonstrations: exact sampled simulation, published on ROS.

:class:`PlantSimulator` is ROS-free. It steps a continuous-time transfer function written as
for :class:`ctid_ros.Model` (``'K*exp(-tau*s)/(T*s + 1)'`` with numeric parameter values) one
sample at a time, exactly for a zero-order-hold input, including a dead time that is not a
multiple of the sample time (the modified discretisation of :mod:`ctid_ros.simulation` with a
history of past inputs). Two kinds of feedback close the loop around the held reference ``r``:

* ``controller`` such as ``'20 + 10/s'``: the controller runs in continuous time together with
  the plant, as one system: the closed-loop data then match exactly the model
  ``P K/(1 + P K)`` the estimator fits, at any sample rate. The plant input ``u`` of the loop
  is a second output of that system, and the loop feeds back the noise-free output. A dead
  time cannot be inside such a loop (it would not be rational).
* ``pi_gains=(kp, ki)``: a digital PI controller (:class:`DigitalPI`), as on a real robot: at
  every sample it reads the measured (noisy) output, computes the command and holds it until
  the next sample. The plant may have a dead time; the data are identified from the measured
  command ``u`` to ``y`` (direct closed-loop identification).

Measurement noise (Gaussian, seeded) is added to ``y`` only.

:class:`PlantNode` (``ctid_plant``) drives a simulator with a PRBS and publishes, per sample:

* ``message_type: float64``: ``std_msgs/Float64`` on ``input_topic`` (``u`` open loop, the
  reference ``r`` closed loop), ``output_topic`` (``y``) and, closed loop, ``control_topic``
  (the plant input ``u``). Float64 has no header: a subscriber stamps it on reception.
* ``message_type: point_stamped``: the same topics as ``geometry_msgs/PointStamped`` with the
  value in ``point.x`` and ``header.stamp`` = the simulated sample instant.
* ``message_type: joint_state``: one ``sensor_msgs/JointState`` on ``joint_state_topic`` with
  ``effort[0]`` = excitation (``u`` or ``r``), ``position[0]`` = ``y``, ``velocity[0]`` = plant
  input ``u`` and ``header.stamp`` = the simulated sample instant.

A wall timer (the node clock) checks at least every 10 ms how many sample instants
``start + k*sample_time`` have passed and publishes those samples, so timer jitter delays a
sample but never distorts the simulated data. ``start`` is a multiple of ``sample_time``, so
header stamps fall on the estimator's grid. Optionally the parameters jump to
``drift_values`` at ``drift_time`` seconds after the start (see :meth:`PlantSimulator.retune`).

Run it with ``ctid_plant --ros-args --params-file config/plant_sim.yaml``.
"""

from collections import deque
from dataclasses import dataclass
import itertools
import sys
from typing import Dict, Iterator, List, Mapping, Optional, Sequence, Tuple

from ctid_ros.errors import ConfigError
from ctid_ros.excitation import prbs
from ctid_ros.model import Model
from ctid_ros.node import parameter_value, run_node
from ctid_ros.simulation import ContinuousFilter
from geometry_msgs.msg import PointStamped
import numpy as np
import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64

NANOSECONDS = 1_000_000_000
MESSAGE_TYPES = ('float64', 'point_stamped', 'joint_state')


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


class PlantNode(Node):
    """Simulated plant publishing its excitation, input and output at every sample."""

    def __init__(self, **kwargs):
        super().__init__('ctid_plant', **kwargs)
        double_array = rclpy.Parameter.Type.DOUBLE_ARRAY
        self.declare_parameters('', [
            ('model', 'K*exp(-tau*s)/(T*s + 1)'), ('parameter_names', ['K', 'T', 'tau']),
            ('parameter_values', [2.0, 0.5, 0.137]), ('controller', ''),
            ('pi_gains', double_array),
            ('sample_time', 0.005), ('noise_std', 0.01), ('seed', 0),
            ('prbs_bits', 9), ('prbs_clock', 20), ('amplitude', 1.0), ('offset', 0.0),
            ('message_type', 'float64'), ('input_topic', 'u'), ('output_topic', 'y'),
            ('control_topic', 'u_plant'), ('joint_state_topic', 'joint_states'),
            ('reliable', True), ('drift_time', -1.0), ('drift_values', double_array)])
        value = self._value
        self._message_type = value('message_type')
        if self._message_type not in MESSAGE_TYPES:
            raise ConfigError(f'message_type must be one of {", ".join(MESSAGE_TYPES)}, got '
                              f'{self._message_type!r}')
        names = list(value('parameter_names'))
        self._params = dict(zip(names, value('parameter_values')))
        drift = value('drift_values')
        self._drift_time = value('drift_time')
        # A negative drift_time disables the drift, whatever drift_values say.
        self._drift = dict(zip(names, drift)) if drift and self._drift_time >= 0 else None
        self.simulator = PlantSimulator(value('model'), self._params, value('sample_time'),
                                        controller=value('controller'),
                                        pi_gains=value('pi_gains'),
                                        noise_std=value('noise_std'), seed=value('seed'))
        self._excitation = excitation(value('prbs_bits'), value('prbs_clock'),
                                      value('amplitude'), value('offset'))
        self._step_ns = round(self.simulator.sample_time * NANOSECONDS)
        # Deep: a starved timer catches up in a burst, which must not overflow the history.
        self._qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE
                               if value('reliable') else ReliabilityPolicy.BEST_EFFORT)
        self._topic_publishers: Dict[str, rclpy.publisher.Publisher] = {}
        self.create_publishers()
        self.restart()
        self._timer = self.create_timer(min(self.simulator.sample_time, 0.01), self._tick)

    def _value(self, name: str):
        return parameter_value(self, name, ())

    def create_publishers(self) -> None:
        """(Re)create the publishers, e.g. to test a subscriber against a publisher restart."""
        for publisher in self._topic_publishers.values():
            self.destroy_publisher(publisher)
        if self._message_type == 'joint_state':
            topics = {'joint_state': (JointState, self._value('joint_state_topic'))}
        else:
            kind = PointStamped if self._message_type == 'point_stamped' else Float64
            topics = {'input': (kind, self._value('input_topic')),
                      'output': (kind, self._value('output_topic'))}
            if self.simulator.closed_loop:
                topics['control'] = (kind, self._value('control_topic'))
        self._topic_publishers = {role: self.create_publisher(kind, topic, self._qos)
                                  for role, (kind, topic) in topics.items()}

    def subscription_counts(self) -> Dict[str, int]:
        """Return the number of matched subscriptions of each published topic."""
        return {publisher.topic_name: publisher.get_subscription_count()
                for publisher in self._topic_publishers.values()}

    def matched(self) -> bool:
        """Return True when every publisher has at least one subscriber."""
        return all(self.subscription_counts().values())

    @property
    def start_ns(self) -> int:
        """Return the stamp (node clock, ns) of sample 0: the simulation starts at rest there."""
        return self._start_ns

    def restart(self) -> None:
        """Count samples from zero, the next one due now (e.g. once subscribers matched)."""
        now = self.get_clock().now().nanoseconds
        self._start_ns = -(-now // self._step_ns) * self._step_ns
        self.published = 0

    def _tick(self) -> None:
        now = self.get_clock().now().nanoseconds
        while self._start_ns + self.published * self._step_ns <= now:
            stamp = self._start_ns + self.published * self._step_ns
            if self._drift and stamp - self._start_ns >= self._drift_time * NANOSECONDS:
                self.simulator.retune({**self._params, **self._drift})
                self._drift = None
            excitation_value = next(self._excitation)
            u, y = self.simulator.step(excitation_value)
            self._publish(stamp, excitation_value, u, y)
            self.published += 1

    def _publish(self, stamp: int, excitation_value: float, u: float, y: float) -> None:
        publishers = self._topic_publishers
        if 'joint_state' in publishers:
            message = JointState(name=['joint'], position=[y], velocity=[u],
                                 effort=[excitation_value])
            _set_stamp(message, stamp)
            publishers['joint_state'].publish(message)
            return
        for role, value in (('input', excitation_value), ('control', u), ('output', y)):
            if role in publishers:
                if self._message_type == 'point_stamped':
                    message = PointStamped()
                    message.point.x = value
                    _set_stamp(message, stamp)
                else:
                    message = Float64(data=value)
                publishers[role].publish(message)


def _set_stamp(message, stamp: int) -> None:
    message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp, NANOSECONDS)


def main(args: Optional[List[str]] = None) -> int:
    """Run the simulated plant until Ctrl-C or SIGTERM."""
    return run_node(PlantNode, 'ctid_plant', args)


if __name__ == '__main__':
    sys.exit(main())
