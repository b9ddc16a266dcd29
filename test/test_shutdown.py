"""Stopping the cell cannot abort (issue 31, item 1).

A thread still inside compiled code when the interpreter finalises is ended by ``pthread_exit``, whose
unwinding through C++ frames aborts the process ("terminate called without an active exception",
exit 134). The stop order of ``runtime.NodeThreads.stop`` (no new work, runs canceled, owned threads
joined, executors shut down, nodes destroyed, then the context) must leave none.

Both tests run the cell in child processes (an abort must not take pytest with it) beside a busy
process that keeps one CPU loaded, as on the machine where the abort was seen.
"""
from __future__ import annotations

from pathlib import Path
import signal
import subprocess
import sys
import time

import threading

import pytest
from rclpy.node import Node

from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.runtime import NodeThreads

from gls_calibration_msgs.srv import Calibrate

from ros_helpers import call_service, default_sigint, wait_for_peer_service

CYCLES = 20
CELL_START_TIMEOUT_S = 60.0
CALIBRATE_TIMEOUT_S = 300.0
STOP_TIMEOUT_S = 20.0          # the stop itself takes 1-3 s on a loaded machine; 10 s was a hang
BUSY = "while True: pass"
# One plain sweep and one pass over the marked plate: the shortest calibration that trains a model. The
# time limits are widened: with the busy process beside other work a 2001-profile sweep has taken more
# than its default 36.7 s, and this test is about the stop, not the cell's speed.
# On the sweep-contract cell, to keep this test's cost: the split cell (gls-sim-cell's default) calibrates
# about 1.5-2x slower, and twenty cycles of it did not end within 15 min beside the busy process on a host
# at load 9 (the sweep-contract cell took 17 min there, its last calibrate also over 300 s). The stop
# under test is the shared NodeThreads/StopSignals path; the split cell's stop on SIGINT after a
# calibration is tested by test_cross_process.py.
FAST_ARGUMENTS = ["--sweep-contract", "--ros-args", "-p", "sweep.plain_repeats:=1", "-p", "sweep.plan:=0+",
                  "-p", "deadline_factor:=10.0"]
ABORT = "terminate called"

# The in-process cell (every node in one context, spun by NodeThreads, as gls-sim-cell and the tests'
# start_cell run it) started and stopped CYCLES times in one process.
IN_PROCESS = """
import sys, tempfile
from pathlib import Path
sys.path.insert(0, {test_dir!r})
from ros_helpers import running_cell
for cycle in range({cycles}):
    with tempfile.TemporaryDirectory() as folder:
        with running_cell(Path(folder)) as cell:
            assert cell.context.ok()
    print("stopped", cycle + 1, flush=True)
"""


def test_the_stop_joins_the_threads_a_node_owns_before_destroying_it(ros_context):
    node = GlsNode("owner", context=ros_context)
    threads = NodeThreads([node])
    release = threading.Event()
    worker = node.start_worker(lambda: release.wait(1.0), "slow-worker")
    assert worker is not None and worker.is_alive() and not worker.daemon
    destroyed = []
    original = node.destroy_node
    node.destroy_node = lambda: (destroyed.append(worker.is_alive()), original())[1]
    assert threads.stop() == []
    assert destroyed == [False]                      # the worker had ended when the node was destroyed
    assert not any(thread.is_alive() for thread in threads.threads)
    assert node.start_worker(lambda: None, "late") is None   # no new work once stopping
    assert threads.stop() == []                      # idempotent: nothing is destroyed twice
    assert destroyed == [False]


def test_a_thread_that_does_not_end_is_named_and_its_node_stays(ros_context):
    node = GlsNode("stuck_owner", context=ros_context)
    threads = NodeThreads([node])
    release = threading.Event()
    node.start_worker(release.wait, "stuck-worker")
    try:
        assert threads.stop(join_timeout_s=0.3) == ["stuck-worker"]
    finally:
        release.set()


@pytest.fixture
def busy_cpu():
    """One process spinning on a CPU while the test runs."""
    process = subprocess.Popen([sys.executable, "-c", BUSY])
    try:
        yield process
    finally:
        process.kill()
        process.wait()


@pytest.mark.slow
def test_the_in_process_cell_starts_and_stops_without_abort(busy_cpu, tmp_path):
    script = IN_PROCESS.format(test_dir=str(Path(__file__).parent), cycles=CYCLES)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=CYCLES * 30.0, cwd=tmp_path)
    assert ABORT not in done.stderr, done.stderr[-3000:]
    assert done.returncode == 0, f"exit {done.returncode}; stderr:\n{done.stderr[-3000:]}"
    assert done.stdout.split() == [word for cycle in range(CYCLES) for word in ("stopped", str(cycle + 1))]


def serve_calibrate_and_interrupt(node: Node, out: Path, log_path: Path) -> tuple[int, float]:
    """``gls-sim-cell --serve`` on a fast 3x3 cell, one calibration from ``node``, SIGINT as soon as
    it answers: (exit status, seconds from SIGINT to exit). A cell still running STOP_TIMEOUT_S after
    SIGINT is killed and reported as -SIGKILL."""
    with open(log_path, "w") as log:
        cell = subprocess.Popen([sys.executable, "-m", "gls_calibration.cli.sim_cell", "--serve", "--grid", "3",
                                 "--out", str(out), *FAST_ARGUMENTS], stdout=log, stderr=subprocess.STDOUT,
                                preexec_fn=default_sigint)
    calibrator = node.create_client(Calibrate, "calibrate")
    try:
        wait_for_peer_service(node, calibrator, cell, log_path, CELL_START_TIMEOUT_S)
        answer = call_service(node, calibrator, Calibrate.Request(validate=False, force=True), CALIBRATE_TIMEOUT_S)
        assert answer.success, f"{answer.message}; log:\n{log_path.read_text()[-3000:]}"
        assert answer.neurons > 0          # a model was trained: the correction node loads and prepares it
        cell.send_signal(signal.SIGINT)    # right after: the correction node is still preparing the model
        began = time.monotonic()
        try:
            cell.wait(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            cell.kill()
            cell.wait()
        return cell.returncode, time.monotonic() - began
    finally:
        node.destroy_client(calibrator)
        if cell.poll() is None:
            cell.kill()
            cell.wait()


@pytest.mark.slow
@pytest.mark.timeout(CYCLES * 90)
def test_the_served_cell_stops_on_sigint_right_after_a_calibration(ros_context, add_node, busy_cpu, tmp_path):
    """Exit status 130 (docs/tools.md: interrupted) every time: no abort (134), no hang."""
    node = add_node(Node("shutdown_test", namespace="gls", context=ros_context))
    statuses = []
    for cycle in range(CYCLES):
        log_path = tmp_path / f"cell_{cycle}.log"
        status, stop_s = serve_calibrate_and_interrupt(node, tmp_path / f"cell_{cycle}", log_path)
        statuses.append(status)
        log = log_path.read_text()
        assert ABORT not in log and status == 130, \
            f"cycle {cycle + 1}: exit {status} after {stop_s:.1f} s (statuses so far {statuses}); log:\n{log[-3000:]}"
