"""Shared pytest fixtures for launch-free ROS tests (rclpy's own test style).

Isolation: each pytest session picks one ROS domain at random in 1..100 (unless ROS_DOMAIN_ID is
already set, which then wins) so that concurrent test runs on this machine do not see each other's
nodes, and restricts discovery to localhost. The choice is made here, at import time, because rcl
reads the variables when a context is initialised; child processes inherit them through the
environment. The domain in use is printed in the pytest header.

Fixtures:
    ros_context  a fresh, initialised rclpy Context per test, shut down afterwards.
    executor     a MultiThreadedExecutor on that context, spun by a background thread.
    add_node     add_node(node) -> node: put a node into the executor; it is destroyed after the test.
    start_cell   start_cell(**options) -> RunningCell: every node of the simulated cell in a context of
                 its own, initialised with the cell's parameter files (see ros_helpers.running_cell);
                 stopped after the test.
Helpers for the test bodies (call_service, wait_for, stop_process) live in test/ros_helpers.py.
"""
from __future__ import annotations

import os
import random
from collections.abc import Callable, Iterator
from contextlib import ExitStack

import pytest

if "ROS_DOMAIN_ID" not in os.environ:
    # Not a data draw: isolation only, so deliberately unseeded (different for concurrent sessions).
    os.environ["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(1, 100))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
# As `make test` sets it (before numpy loads OpenBLAS), so that `python -m pytest` runs alike.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
from gls_calibration.ros.dds import use_fast_liveliness  # noqa: E402
use_fast_liveliness()  # as every node process does: a killed node leaves the graph within 1.5 s

try:
    import rclpy  # noqa: E402  (after the environment is set)
except ImportError as error:  # not the set-up venv: say what to run instead of failing in every test
    raise pytest.UsageError(f"{error}: run `make setup`, then `.venv/bin/python -m pytest` "
                            "(or `make test`)") from None
from rclpy.context import Context  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402

from ros_helpers import RunningCell, running_cell, spin_in_background  # noqa: E402

EXECUTOR_STOP_TIMEOUT_S = 5.0


def pytest_report_header(config) -> str:
    """Show which ROS domain this session uses (helps when a ROS test interferes with another run)."""
    return (f"ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']}, "
            f"ROS_AUTOMATIC_DISCOVERY_RANGE={os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE']}")


@pytest.fixture
def ros_context() -> Iterator[Context]:
    """A fresh initialised rclpy Context, shut down after the test."""
    context = Context()
    rclpy.init(context=context)
    try:
        yield context
    finally:
        context.try_shutdown()


@pytest.fixture
def executor(ros_context: Context) -> Iterator[MultiThreadedExecutor]:
    """A MultiThreadedExecutor spinning in a background thread; its nodes are destroyed afterwards."""
    executor = MultiThreadedExecutor(context=ros_context)
    thread = spin_in_background(executor)
    try:
        yield executor
    finally:
        nodes = executor.get_nodes()
        executor.shutdown(timeout_sec=EXECUTOR_STOP_TIMEOUT_S)
        thread.join(timeout=EXECUTOR_STOP_TIMEOUT_S)
        for node in nodes:
            node.destroy_node()
        assert not thread.is_alive(), "the executor thread did not stop"


@pytest.fixture
def add_node(executor: MultiThreadedExecutor) -> Callable[[Node], Node]:
    """add_node(node) -> node: spin ``node`` and its companions (``with_companions``) in the test's
    executor (destroyed after the test)."""
    from gls_calibration.ros.runtime import with_companions  # imports rclpy: after the environment is set

    def add(node: Node) -> Node:
        for member in with_companions(node):
            executor.add_node(member)
        return node
    return add


@pytest.fixture
def start_cell(tmp_path) -> Iterator[Callable[..., RunningCell]]:
    """start_cell(**options) -> RunningCell: the simulated cell in-process, in ``tmp_path`` (stopped afterwards)."""
    with ExitStack() as stack:
        def start(**options) -> RunningCell:
            return stack.enter_context(running_cell(tmp_path, **options))
        yield start
