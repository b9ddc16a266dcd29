"""Helpers for launch-free ROS tests (used with the fixtures in test/conftest.py).

Tests run their nodes in an executor spun by a background thread, so the test body itself may
block: it waits on futures and conditions with a timeout instead of spinning. Never call these
helpers from inside a ROS callback: a callback that waits for a service answer can starve the
executor that has to deliver it.
"""
from __future__ import annotations

import signal
import subprocess
import threading
import time
from collections.abc import Callable

import rclpy
from rclpy.client import Client
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node


def wait_for(condition: Callable[[], bool], timeout_s: float, *, what: str = "condition",
             interval_s: float = 0.005) -> None:
    """Poll ``condition`` until it returns True; raise TimeoutError naming ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() >= deadline:
            raise TimeoutError(f"{what} did not hold within {timeout_s} s")
        time.sleep(interval_s)


def call_service(node: Node, client: Client, request, timeout_s: float = 5.0):
    """Call ``client`` asynchronously and return the response, or raise TimeoutError.

    The service must become available and answer within ``timeout_s`` each. If ``node`` is in a
    spinning executor (the ``executor`` fixture) the answer arrives through it; otherwise the node
    is spun here until the answer arrives.
    """
    name = node.resolve_service_name(client.srv_name)
    if not client.wait_for_service(timeout_sec=timeout_s):
        raise TimeoutError(f"service {name} is not available after {timeout_s} s")
    future = client.call_async(request)
    if node.executor is None:
        rclpy.spin_until_future_complete(node, future, executor=SingleThreadedExecutor(context=node.context),
                                         timeout_sec=timeout_s)
    else:
        try:
            wait_for(future.done, timeout_s, what=f"answer from {name}")
        except TimeoutError:
            pass
    if not future.done():
        client.remove_pending_request(future)
        raise TimeoutError(f"service {name} did not answer within {timeout_s} s")
    return future.result()


def spin_in_background(executor: Executor) -> threading.Thread:
    """Start a daemon thread that spins ``executor`` until it is shut down."""
    thread = threading.Thread(target=executor.spin, name="ros-test-executor", daemon=True)
    thread.start()
    return thread


def stop_process(process: subprocess.Popen, timeout_s: float = 5.0) -> int:
    """Stop a ROS process with SIGINT (rclpy's clean shutdown), escalating to SIGKILL; return its code."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=timeout_s)
    return process.returncode

