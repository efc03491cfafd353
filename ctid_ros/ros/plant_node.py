"""
``ctid_plant``: a simulated plant published on ROS, for tests and demonstrations.

The simulation itself is :class:`ctid_ros.core.plant.PlantSimulator` (exact, ROS-free).

:class:`PlantNode` (``ctid_plant``) drives a simulator with a PRBS and publishes, per sample:

* ``message_type: float64``: ``std_msgs/Float64`` on ``input_topic`` (``u`` open loop, the
  reference ``r`` closed loop), ``output_topic`` (``y``) and, closed loop, ``control_topic``
  (the plant input ``u``). Float64 has no header: a subscriber stamps it on reception.
* ``message_type: point_stamped``: the same topics as ``geometry_msgs/PointStamped`` with the
  value in ``point.x`` and ``header.stamp`` = the simulated sample instant.
* ``message_type: joint_state``: one ``sensor_msgs/JointState`` on ``joint_state_topic`` with
  ``effort[0]`` = excitation (``u`` or ``r``), ``position[0]`` = ``y``, ``velocity[0]`` = plant
  input ``u`` and ``header.stamp`` = the simulated sample instant. With several
  ``joint_names`` the simulated joint is the last one (``position[<its name>]``), the others
  stand still at 0.

A wall timer (the node clock) checks at least every 10 ms how many sample instants
``start + k*sample_time`` have passed and publishes those samples, so timer jitter delays a
sample but never distorts the simulated data. ``start`` is a multiple of ``sample_time``, so
header stamps fall on the estimator's grid. Optionally the parameters jump to
``drift_values`` at ``drift_time`` seconds after the start (see
:meth:`~ctid_ros.core.plant.PlantSimulator.retune`).

Run it with ``ctid_plant --ros-args --params-file config/plant_sim.yaml``.
"""

import signal
import sys
import time
from typing import Any, Dict, List, Mapping, Optional

from ctid_ros.core.plant import excitation, PlantSimulator
from ctid_ros.errors import ConfigError, CtidError
from ctid_ros.ros.parameter_table import wrap_text
from ctid_ros.ros.parameters import parameter_value
from ctid_ros.ros.runner import run_node
from ctid_ros.streaming.contract import NANOSECONDS
from geometry_msgs.msg import PointStamped
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64

__all__ = ['MESSAGE_TYPES', 'PLANT_PARAMETERS', 'PlantNode', 'main', 'plant_usage',
           'run_samples']

MESSAGE_TYPES = ('float64', 'point_stamped', 'joint_state')
_DOUBLE_ARRAY = rclpy.Parameter.Type.DOUBLE_ARRAY
# (name, default, meaning) of every parameter of ctid_plant.
PLANT_PARAMETERS = (
    ('model', 'K*exp(-tau*s)/(T*s + 1)', 'Plant transfer function in s.'),
    ('parameter_names', ['K', 'T', 'tau'], 'Names of the values in parameter_values.'),
    ('parameter_values', [2.0, 0.5, 0.137], 'True parameter values of the simulation.'),
    ('controller', '', "Continuous controller closing the loop, e.g. '20 + 10/s'; '' = open "
     'loop.'),
    ('pi_gains', _DOUBLE_ARRAY, 'Digital PI [kp, ki] run every sample on the noisy '
     'measurement (instead of controller).'),
    ('sample_time', 0.005, 'Sample time (s) of the simulation and of the published samples.'),
    ('noise_std', 0.01, 'Standard deviation of the white noise added to the output.'),
    ('seed', 0, 'Seed of the noise.'),
    ('prbs_bits', 9, 'Bits of the PRBS excitation (period 2**bits - 1 steps).'),
    ('prbs_clock', 20, 'Samples each PRBS bit is held.'),
    ('amplitude', 1.0, 'Amplitude of the excitation.'),
    ('offset', 0.0, 'Offset of the excitation.'),
    ('message_type', 'float64', f'One of {", ".join(MESSAGE_TYPES)}.'),
    ('input_topic', 'u', 'Topic of the excitation (u open loop, the reference r closed loop).'),
    ('output_topic', 'y', 'Topic of the output y.'),
    ('control_topic', 'u_plant', 'Topic of the plant input u in closed loop.'),
    ('joint_state_topic', 'joint_states', 'Topic of the JointState (message_type '
     'joint_state).'),
    ('joint_names', ['joint'], 'Joint names of the JointState; the simulated joint is the last '
     'one, the others stand still.'),
    ('reliable', True, 'Reliable (true) or best-effort publishers.'),
    ('drift_time', -1.0, 'Seconds after the start at which the parameters jump to '
     'drift_values; negative = never.'),
    ('drift_values', _DOUBLE_ARRAY, 'Parameter values after drift_time.'),
)


class PlantNode(Node):
    """Simulated plant publishing its excitation, input and output at every sample."""

    def __init__(self, **kwargs):
        super().__init__('ctid_plant', **kwargs)
        try:
            self._configure()
        except BaseException:
            # Never returned to a caller that could destroy it: its handles end here, or they
            # would keep the context and its DDS threads alive into the process's exit.
            self.destroy_node()
            raise

    def _configure(self) -> None:
        """Declare and read the parameters, build the simulator, publishers and timer."""
        self.declare_parameters('', [(name, default) for name, default, _ in PLANT_PARAMETERS])
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
        # Samples to publish at most (None: no end).
        self.limit: Optional[int] = None
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
        while self._start_ns + self.published * self._step_ns <= now and \
                (self.limit is None or self.published < self.limit):
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
            names = list(self._value('joint_names')) or ['joint']
            still = [0.0] * (len(names) - 1)
            message = JointState(name=names, position=still + [y], velocity=still + [u],
                                 effort=still + [excitation_value])
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


def run_samples(params_file: str, overrides: Mapping[str, Any], samples: int,
                subscribers: Mapping[str, int], events: Any, startup_timeout: float = 60.0
                ) -> None:
    """
    Run ``ctid_plant`` in this process for ``samples`` samples, e.g. as a child process.

    Nothing is published before every topic has the expected number of matched subscribers,
    so all of them see the plant start at rest.

    Parameters
    ----------
    params_file : str
        The plant's params file.
    overrides : mapping
        Parameters set over the file's, e.g. ``{'drift_time': 4.0}``.
    samples : int
        Samples to publish before returning.
    subscribers : mapping of str to int
        Matched subscriptions to wait for, by absolute topic.
    events : queue
        Gets ``('started', start_ns)``, then ``('finished', published)``, or
        ``('error', text)`` instead.
    startup_timeout : float
        Seconds to wait for the subscribers.

    """
    # The parent stops this process (terminate) when it is interrupted; Ctrl-C reaches every
    # process of the terminal's group, and must not end this one with a traceback.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = PlantNode(cli_args=['--ros-args', '--params-file', params_file],
                         parameter_overrides=[Parameter(name, value=value)
                                              for name, value in overrides.items()])
    except CtidError as error:
        events.put(('error', str(error)))
        rclpy.shutdown()
        return
    try:
        deadline = time.monotonic() + startup_timeout
        while any(node.subscription_counts().get(topic, 0) < count
                  for topic, count in subscribers.items()):
            if time.monotonic() > deadline:
                events.put(('error', f'subscribers after {startup_timeout:g} s: '
                                     f'{node.subscription_counts()}, expected {subscribers}'))
                return
            time.sleep(0.01)
        # Exactly ``samples``: a late timer tick catches up on several at once.
        node.limit = samples
        node.restart()
        events.put(('started', node.start_ns))
        while node.published < samples:
            rclpy.spin_once(node, timeout_sec=0.01)
        events.put(('finished', node.published))
    finally:
        node.destroy_node()
        rclpy.shutdown()


def plant_usage() -> str:
    """Return the ``ctid_plant --help`` text: how to run it and every parameter."""
    lines = ['usage: ctid_plant [-h] [--ros-args [--params-file FILE] [-p NAME:=VALUE]...]', '',
             wrap_text('Simulate a plant exactly (zero-order hold, fractional dead time) under '
                       'a PRBS, open loop or with a controller, and publish its excitation, '
                       'input and output at every sample.', ''), '',
             'example:', '  ctid_plant --ros-args --params-file config/plant_sim.yaml', '',
             'parameters:']
    for name, default, meaning in PLANT_PARAMETERS:
        shown = '[]' if isinstance(default, rclpy.Parameter.Type) else repr(default)
        lines += [f'  {name} (default {shown})', wrap_text(meaning, '      ')]
    return '\n'.join(lines)


def main(args: Optional[List[str]] = None) -> int:
    """Run the simulated plant until Ctrl-C or SIGTERM."""
    return run_node(PlantNode, 'ctid_plant', args, plant_usage)


if __name__ == '__main__':
    sys.exit(main())
