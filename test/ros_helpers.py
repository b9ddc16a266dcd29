"""Helpers for launch-free ROS tests (used with the fixtures in test/conftest.py).

Tests run their nodes in an executor spun by a background thread, so the test body itself may
block: it waits on futures and conditions with a timeout instead of spinning. Never call these
helpers from inside a ROS callback: a callback that waits for a service answer can starve the
executor that has to deliver it.

running_cell starts every node of the simulated cell in-process, as gls-sim-cell does, with its
parameter files and overrides (the ``start_cell`` fixture wraps it).
"""
from __future__ import annotations

import json
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import rclpy
from rclpy.client import Client
from rclpy.context import Context
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.task import Future

from gls_calibration.cli import sim_cell
from gls_calibration.ros.runtime import NodeThreads


def wait_for(condition: Callable[[], bool], timeout_s: float, *, what: str = "condition",
             interval_s: float = 0.005) -> None:
    """Poll ``condition`` until it returns True; raise TimeoutError naming ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() >= deadline:
            raise TimeoutError(f"{what} did not hold within {timeout_s} s")
        time.sleep(interval_s)


def call_service(node: Node, client: Client, request, timeout_s: float = 5.0, resend_after_s: float | None = None):
    """Call ``client`` asynchronously and return the response, or raise TimeoutError.

    The service must become available and answer within ``timeout_s`` each. If ``node`` is in a
    spinning executor (the ``executor`` fixture) the answer arrives through it; otherwise the node
    is spun here until the answer arrives. ``resend_after_s`` (idempotent services only): send the
    request again when unanswered that long, then after twice as long, and so on, as the package's
    clients do (a server in another process that has not yet discovered this client drops its answer).
    """
    name = node.resolve_service_name(client.srv_name)
    if not client.wait_for_service(timeout_sec=timeout_s):
        raise TimeoutError(f"service {name} is not available after {timeout_s} s")
    deadline = time.monotonic() + timeout_s
    answered, sent, wait_s = Future(), [], resend_after_s
    try:
        while not answered.done():
            future = client.call_async(request)
            future.add_done_callback(lambda done: answered.done() or answered.set_result(done))
            sent.append(future)
            remaining = deadline - time.monotonic()
            attempt_s = max(remaining if wait_s is None else min(remaining, wait_s), 1e-3)
            if node.executor is None:
                rclpy.spin_until_future_complete(node, answered, executor=SingleThreadedExecutor(context=node.context),
                                                 timeout_sec=attempt_s)
            else:
                try:
                    wait_for(answered.done, attempt_s, what=f"answer from {name}")
                except TimeoutError:
                    pass
            if not answered.done() and attempt_s >= remaining:
                raise TimeoutError(f"service {name} did not answer within {timeout_s} s")
            wait_s = None if wait_s is None else 2.0 * wait_s
        return answered.result().result()
    finally:
        for future in sent:
            if not future.done():
                client.remove_pending_request(future)


def wait_for_peer_service(node: Node, client: Client, process: subprocess.Popen, log_path: Path,
                          timeout_s: float) -> None:
    """Wait until another process serves ``client``'s service; AssertionError with the process's
    exit code and log when it does not within ``timeout_s`` (or exits first)."""
    deadline = time.monotonic() + timeout_s
    while not client.wait_for_service(timeout_sec=0.25):
        if process.poll() is not None or time.monotonic() >= deadline:
            service = node.resolve_service_name(client.srv_name)
            raise AssertionError(f"service {service} did not appear within {timeout_s} s; process exit code "
                                 f"{process.poll()}, log:\n{log_path.read_text()}")


def spin_in_background(executor: Executor) -> threading.Thread:
    """Start a daemon thread that spins ``executor`` until it is shut down."""
    thread = threading.Thread(target=executor.spin, name="ros-test-executor", daemon=True)
    thread.start()
    return thread


def default_sigint() -> None:
    """``preexec_fn`` of a ROS child process: SIGINT back to its default, so that the child's Python
    turns it into KeyboardInterrupt even when the test run itself ignores SIGINT (a background job)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


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


# --- the simulated cell in-process -------------------------------------------------------------

def parameter_text(value: Any) -> str:
    """A parameter value as ROS's ``-p name:=value`` reads it (YAML; JSON is YAML)."""
    return json.dumps(value)


def cell_ros_arguments(calibration_dir: Path, report_dir: Path, *, grid: int = 3, seed: int = 1,
                       sim_config: Path | None = None, parameters: Mapping[str, Any] | None = None) -> list[str]:
    """``--ros-args`` of the simulated cell as gls-sim-cell builds them, plus ``parameters`` for every node.

    A name in ``parameters`` replaces gls-sim-cell's own ``-p`` override of that name (the config
    files stay underneath).
    """
    # Through gls-sim-cell's own command line, so that options it adds later get their defaults.
    command_line = ["--grid", str(grid), "--seed", str(seed)]
    if sim_config is not None:
        command_line += ["--sim-config", str(sim_config)]
    cell_args = sim_cell.parse_args(command_line)
    ros_args = sim_cell.ros_arguments(cell_args, calibration_dir, report_dir)
    # One pass over the marked plate unless a test says otherwise: these cells test the nodes, and one
    # pass takes a third of the default plan's time; the plan has its own tests (test_sweep_plan.py,
    # and test_cross_process.py serves a 3x3 cell with the default plan).
    parameters = {"sweep.plan": "0+"} | dict(parameters or {})
    kept: list[str] = []
    index = 0
    while index < len(ros_args):
        if ros_args[index] == "-p" and ros_args[index + 1].split(":=", 1)[0] in parameters:
            index += 2
            continue
        kept.append(ros_args[index])
        index += 1
    for name, value in parameters.items():
        kept += ["-p", f"{name}:={parameter_text(value)}"]
    return kept


@dataclass
class RunningCell:
    """Every node of the simulated cell in one context, each spun by its own thread, and a client node."""

    context: Context
    nodes: dict[str, Node]
    client_node: Node
    calibration_dir: Path
    report_dir: Path

    def call(self, srv_type: type, name: str, request, timeout_s: float):
        """Call the cell's service ``name`` (relative to the ``gls`` namespace) from the client node."""
        client = self.client_node.create_client(srv_type, name)
        try:
            return call_service(self.client_node, client, request, timeout_s)
        finally:
            self.client_node.destroy_client(client)


@contextmanager
def running_cell(directory: Path, *, grid: int = 3, seed: int = 1, sim_config: Path | None = None,
                 parameters: Mapping[str, Any] | None = None,
                 node_parameters: Mapping[str, Mapping[str, Any]] | None = None,
                 node_types: Sequence[type] = sim_cell.NODE_TYPES) -> Iterator[RunningCell]:
    """Start ``node_types`` (default: every node of gls-sim-cell) in a fresh context, spun as
    gls-sim-cell spins them; stop them and shut the context down afterwards.

    The store and the reports go to ``directory``/calibrations and ``directory``/reports.
    ``parameters`` apply to every node (command-line ``-p``); ``node_parameters`` maps a node name
    (e.g. ``"fiducial_measurement"``) to overrides for that node only.
    """
    calibration_dir, report_dir = directory / "calibrations", directory / "reports"
    report_dir.mkdir(parents=True, exist_ok=True)
    context = Context()
    rclpy.init(args=cell_ros_arguments(calibration_dir, report_dir, grid=grid, seed=seed,
                                       sim_config=sim_config, parameters=parameters), context=context)
    nodes: dict[str, Node] = {}
    threads = None
    try:
        for node_type in node_types:
            name = _node_name(node_type)
            overrides = [Parameter(key, value=value)
                         for key, value in (node_parameters or {}).get(name, {}).items()]
            nodes[name] = node_type(context=context, parameter_overrides=overrides)
        client_node = rclpy.create_node("cell_test_client", namespace="gls", context=context)
        nodes["cell_test_client"] = client_node
        threads = NodeThreads(list(nodes.values()))
        yield RunningCell(context, nodes, client_node, calibration_dir, report_dir)
    finally:
        if threads is not None:
            threads.stop()
        else:
            for node in nodes.values():
                node.destroy_node()
        context.try_shutdown()


def _node_name(node_type: type) -> str:
    """The ROS name a node class of the package gives itself (its module's name, by convention)."""
    return node_type.__module__.rsplit(".", 1)[-1]
