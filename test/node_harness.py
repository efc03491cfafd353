"""
Launch-free ROS 2 test harness: nodes of one test on real DDS over loopback.

Each test has its own rclpy context, an executor thread per node and a unique namespace
(test/conftest.py gives every run its own domain, discovery limited to localhost). Shared by
the node, lifecycle and robustness tests.
"""

import itertools
import json
import subprocess
import sys
import threading
import time

from ctid_ros.ros.node import IdentificationNode
from ctid_ros.ros.plant_node import PlantNode
from ctid_ros.ros.spinner import Spinner
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray
import yaml

__all__ = ['Harness', 'NodeProcess', 'converge', 'keys', 'named', 'wait_for', 'write_params']

_COUNTER = itertools.count()


class _QuotingDumper(yaml.SafeDumper):
    """Quote every string: rcl's params parser reads a bare y (as in topic y) as a boolean."""


_QuotingDumper.add_representer(
    str, lambda dumper, text: dumper.represent_scalar('tag:yaml.org,2002:str', text, style="'"))


def write_params(path, namespace, parameters):
    """Write a ctid_node params file keyed by the node's fully qualified name."""
    key = f'{namespace}/ctid_node'
    path.write_text(yaml.dump({key: {'ros__parameters': parameters}}, Dumper=_QuotingDumper))
    return path


class Harness:
    """
    Nodes of one test, each spun by its own executor thread, and what the observer received.

    One single-threaded executor per node, as ``ctid_node`` runs in production: in one shared
    multi-threaded executor the plant's 200 Hz timer was starved for up to 2 s at a time.
    """

    def __init__(self, tmp_path):
        self.tmp_path = tmp_path
        self.namespace = f'/t{next(_COUNTER)}_{int(time.time() * 1000) % 100000}'
        self.context = Context()
        rclpy.init(context=self.context)
        self.estimates = []
        self.predictions = []
        self.processes = []
        self.statuses = []
        self._lock = threading.Lock()
        self._spinning = []
        # One client per (type, service), kept across calls: see call().
        self._clients = {}
        self.observer = self.spin(rclpy.create_node('observer', namespace=self.namespace,
                                                    context=self.context))

    def spin(self, node):
        executor = SingleThreadedExecutor(context=self.context)
        executor.add_node(node)
        spinner = Spinner(executor, node.get_name())
        spinner.start()
        self._spinning.append((executor, node, spinner))
        return node

    def plant(self, **parameters) -> PlantNode:
        overrides = [Parameter(name, value=value) for name, value in parameters.items()]
        return self.spin(PlantNode(context=self.context, namespace=self.namespace,
                                   parameter_overrides=overrides))

    def spawn_plant(self, **parameters) -> subprocess.Popen:
        """
        Run ctid_plant in its own process, as in a real system.

        Float64 samples are stamped when published: a plant sharing the test's interpreter lock
        with an estimate being computed would publish late and in bursts.
        """
        arguments = [sys.executable, '-m', 'ctid_ros.ros.plant_node', '--ros-args', '-r',
                     f'__ns:={self.namespace}', '--log-level', 'warn']
        for name, value in parameters.items():
            arguments += ['-p', f'{name}:={json.dumps(value)}']
        process = subprocess.Popen(arguments)
        self.processes.append(process)
        return process

    def identifier(self, **parameters) -> IdentificationNode:
        """Start ctid_node from a params file, as a user would."""
        path = write_params(self.tmp_path / 'params.yaml', self.namespace, parameters)
        node = IdentificationNode(context=self.context, namespace=self.namespace,
                                  cli_args=['--ros-args', '--params-file', str(path)])
        self.observe()
        return self.spin(node)

    def observe(self):
        """Record the estimates, predictions and statuses of this test's ctid_node."""
        prefix = f'{self.namespace}/ctid_node'
        self.observer.create_subscription(
            Float64MultiArray, f'{prefix}/estimate',
            lambda message: self._record(self.estimates, message), 10)
        self.observer.create_subscription(
            Float64MultiArray, f'{prefix}/prediction',
            lambda message: self._record(self.predictions, message), 10)
        self.observer.create_subscription(
            DiagnosticArray, '/diagnostics', lambda message: self._record(
                self.statuses, *[status for status in message.status
                                 if status.name == f'{prefix[1:]}: estimate']), 10)

    def _record(self, into, *messages):
        with self._lock:
            into.extend(messages)

    def latest(self, into):
        with self._lock:
            return into[-1] if into else None

    def call(self, service_type, name, request, timeout=60.0, repeatable=False):
        """
        Call a service and return its response.

        One client per service, kept: a new client's response reader may not be matched by
        the server when its first request arrives (DDS discovery runs both ways), and that
        response is then lost. A ``repeatable`` request (a query that changes nothing) is
        sent again every few seconds until it is answered.
        """
        client = self._clients.get((service_type, name))
        if client is None:
            client = self._clients[(service_type, name)] = \
                self.observer.create_client(service_type, name)
        assert client.wait_for_service(timeout_sec=timeout), f'no service {name}'
        deadline = time.monotonic() + timeout
        while True:
            future = client.call_async(request)
            give_up = min(deadline, time.monotonic() + 5.0) if repeatable else deadline
            while not future.done() and time.monotonic() < give_up:
                time.sleep(0.05)
            if future.done():
                return future.result()
            assert time.monotonic() < deadline, \
                f'timed out after {timeout} s: no answer from {name}'
            client.remove_pending_request(future)

    def close(self):
        for process in self.processes:
            process.terminate()
            process.wait(timeout=10)
        for executor, node, spinner in self._spinning:
            spinner.stop()
            executor.shutdown()
            node.destroy_node()
        rclpy.shutdown(context=self.context)


class NodeProcess:
    """ctid_node in a process of its own, driven and observed from the test's harness."""

    def __init__(self, ros, parameters):
        self.ros = ros
        self.name = f'{ros.namespace}/ctid_node'
        params = write_params(ros.tmp_path / 'node.yaml', ros.namespace, parameters)
        # A file, not a pipe: a pipe nobody reads would block the node once full.
        self.log = ros.tmp_path / 'node.log'
        with open(self.log, 'w') as log:
            self.process = subprocess.Popen(
                [sys.executable, '-m', 'ctid_ros.ros.node', '--ros-args', '-r',
                 f'__ns:={ros.namespace}', '--params-file', str(params)],
                stdout=log, stderr=subprocess.STDOUT)

    def call(self, service_type, service, request, repeatable=False):
        return self.ros.call(service_type, f'{self.name}/{service}', request, timeout=60.0,
                             repeatable=repeatable)

    def change(self, transition_id, label=''):
        """Request a transition through ~/change_state; return whether it succeeded."""
        request = ChangeState.Request(transition=Transition(id=transition_id, label=label))
        return self.call(ChangeState, 'change_state', request).success

    def state(self):
        return self.call(GetState, 'get_state', GetState.Request(),
                         repeatable=True).current_state.label

    def stop(self, number):
        """Send signal ``number``; return the seconds to the exit, the status and the log."""
        started = time.monotonic()
        self.process.send_signal(number)
        try:
            self.process.wait(timeout=60.0)
        finally:
            if self.process.poll() is None:
                self.process.kill()
        elapsed = time.monotonic() - started
        return elapsed, self.process.returncode, self.log.read_text()


def wait_for(predicate, timeout, what):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, \
            f'timed out after {timeout} s: {what() if callable(what) else what}'
        time.sleep(0.05)


def named(message: Float64MultiArray):
    names = message.layout.dim[0].label.split(',')
    assert message.layout.dim[0].size == message.layout.dim[0].stride == len(names)
    return dict(zip(names, message.data))


def keys(status: DiagnosticStatus):
    return {pair.key: pair.value for pair in status.values}


def converge(ros, truth, tolerance, timeout):
    """Wait for an estimate within tolerance of the truth; return it (or fail with the last)."""
    def close_enough():
        message = ros.latest(ros.estimates)
        return message is not None and all(
            abs(named(message)[name] - value) <= tolerance[name] for name, value in truth.items())
    wait_for(close_enough, timeout, lambda: f'estimates {[named(m) for m in ros.estimates]}')
    return named(ros.latest(ros.estimates))
