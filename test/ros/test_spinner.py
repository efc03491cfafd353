"""Spinner: callbacks run in its thread, and stop() leaves the executor free to shut down."""

import threading
import time

from ctid_ros.ros.spinner import Spinner
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor


def _spinning() -> bool:
    return any(thread.name == 'spinner_test' and thread.is_alive()
               for thread in threading.enumerate())


def _started(context):
    executor = SingleThreadedExecutor(context=context)
    node = rclpy.create_node('spinner_test', context=context)
    ticks = threading.Semaphore(0)
    node.create_timer(0.01, ticks.release)
    executor.add_node(node)
    spinner = Spinner(executor, 'spinner_test')
    spinner.start()
    return executor, node, spinner, ticks


@pytest.mark.ros
def test_stop_ends_the_thread_before_the_executor_shuts_down():
    context = Context()
    rclpy.init(context=context)
    executor, node, spinner, ticks = _started(context)
    try:
        for _ in range(3):
            assert ticks.acquire(timeout=10), 'the timer did not fire in the spinning thread'
        spinner.stop()
        assert not _spinning()
        assert executor.shutdown(timeout_sec=10)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.mark.ros
def test_the_thread_ends_when_its_context_is_shut_down():
    context = Context()
    rclpy.init(context=context)
    executor, node, spinner, ticks = _started(context)
    assert ticks.acquire(timeout=10)
    rclpy.try_shutdown(context=context)
    deadline = time.monotonic() + 10
    while _spinning() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _spinning(), 'the thread kept spinning on a context that was shut down'
    spinner.stop()
    executor.shutdown(timeout_sec=10)
    node.destroy_node()
