"""Kill each node of the cell during the step that uses it: the calibration fails fast, keeps the
active calibration byte for byte, and the next calibration succeeds once the node is restarted.

The manager, scan acquisition and plate pose run in this process (ros_helpers.running_cell); the
scanner, galvo, fiducial measurement, trainer and correction nodes run in processes of their own
(their console scripts with the cell's parameters), so that they can be killed with SIGKILL.
To be sure the request is in flight when the node dies, the victim is first frozen (SIGSTOP) at a
stage before the one that uses it, then killed once that stage has begun.
The answer is timed from the SIGKILL; the limit (10 s) is the issue's.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from std_srvs.srv import Trigger

from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.nodes.calibration_manager import CalibrationManager
from gls_calibration.nodes.plate_pose import PlatePoseNode
from gls_calibration.nodes.scan_acquisition import ScanAcquisitionNode
from gls_calibration_msgs.msg import CalibrationProgress
from gls_calibration_msgs.srv import (Calibrate, CorrectSetpoints, GetMarkedPaths, MeasureFiducials, StartSweep,
                                      TrainCorrection)

from ros_helpers import cell_ros_arguments, running_cell, stop_process, wait_for, wait_for_peer_service

pytestmark = pytest.mark.slow

ANSWER_AFTER_KILL_S = 10.0       # the limit
START_TIMEOUT_S = 90.0           # a node process on a busy machine: interpreter, imports, discovery
CALIBRATE_TIMEOUT_S = 300.0
CALL_TIMEOUT_S = 20.0
EXCHANGE_ATTEMPTS, EXCHANGE_TIMEOUT_S = 4, 5.0
GRID = 3
# One plain sweep per run: the test is about faults, not accuracy. A 3x3 grid recalibrated on the
# paper_like measurement chain leaves a CV error above half its deviations: the "model cannot
# explain the measurement" check is made inert here (it has its own tests). One pass over the marked
# plate for the same reason (the sweep plan has its own tests).
PARAMETERS = {"sweep.plain_repeats": 1, "max_cv_fraction": 100.0, "sweep.plan": "0+"}


@dataclass(frozen=True)
class Victim:
    script: str              # console script of the node
    service: tuple           # (type, name) of a service it serves: up when this answers
    freeze_at: str           # progress stage at which it is frozen (None: never)
    kill_at: str             # stage at which it is killed...
    kill_after_s: float      # ...this long after the stage began
    named: str               # what the failure message must name


VICTIMS = {
    "scanner": Victim("gls-sim-scanner", (StartSweep, "scanner/start_sweep"), None, "sweep_marked", 0.3,
                      "scanner/start_sweep"),
    "galvo": Victim("gls-sim-galvo", (GetMarkedPaths, "sim/marked_paths"), "plate_pose", "marking", 0.2,
                    "galvo/mark"),
    "measurement": Victim("gls-fiducial-measurement", (MeasureFiducials, "fiducials/measure"), "sweep_marked",
                          "measurement", 0.2, "fiducials/measure"),
    "trainer": Victim("gls-rbf-trainer", (TrainCorrection, "rbf/train"), "measurement", "training", 0.2,
                      "rbf/train"),
    # Its first use (the ring points) follows the plate_pose stage at once and is quick: frozen earlier.
    "correction": Victim("gls-correction", (CorrectSetpoints, "correct_setpoints"), "sweep_plain", "plate_pose",
                         0.0, "correct_setpoints"),
}


class Cell:
    """The in-process part of the cell, the victim processes, and a progress listener."""

    def __init__(self, running, ros_args: list[str], log_dir: Path) -> None:
        self.running = running
        self.node = running.client_node
        self.ros_args = ros_args
        self.log_dir = log_dir
        self.processes: dict[str, subprocess.Popen] = {}
        self.stages: list[tuple[str, float]] = []
        self.lock = threading.Lock()
        self.node.create_subscription(CalibrationProgress, "calibration/progress", self._on_progress, 100)

    def _on_progress(self, message) -> None:
        with self.lock:
            self.stages.append((message.stage, time.monotonic()))

    def seen(self, stage: str) -> bool:
        with self.lock:
            return any(name == stage for name, _ in self.stages)

    def log(self, name: str) -> Path:
        return self.log_dir / f"{name}.log"

    def start(self, name: str) -> None:
        script = Path(sys.executable).with_name(VICTIMS[name].script)
        with open(self.log(name), "a") as log:
            self.processes[name] = subprocess.Popen([str(script), *self.ros_args], stdout=log,
                                                    stderr=subprocess.STDOUT)

    def wait_up(self, name: str) -> None:
        srv_type, service = VICTIMS[name].service
        client = self.node.create_client(srv_type, service)
        try:
            wait_for_peer_service(self.node, client, self.processes[name], self.log(name), START_TIMEOUT_S)
        finally:
            self.node.destroy_client(client)

    def call(self, srv_type, name: str, request, timeout_s: float = CALL_TIMEOUT_S):
        return self.running.call(srv_type, name, request, timeout_s)

    def calibrate_async(self):
        with self.lock:
            self.stages.clear()
        client = self.node.create_client(Calibrate, "calibrate")
        assert client.wait_for_service(timeout_sec=CALL_TIMEOUT_S)
        return client.call_async(Calibrate.Request(iterations=1, validate=False, force=True))

    def calibrate(self) -> Calibrate.Response:
        # The operator loads a fresh plate before each calibration. A galvo that has just restarted may
        # drop its first answer (as the nodes' own calls expect, see request_ids); loading a clean plate
        # twice leaves a clean plate, so the request is sent again.
        for attempt in range(EXCHANGE_ATTEMPTS):
            try:
                exchanged = self.call(Trigger, "sim/exchange_plate", Trigger.Request(), EXCHANGE_TIMEOUT_S)
                break
            except TimeoutError:
                if attempt == EXCHANGE_ATTEMPTS - 1:
                    raise
        assert exchanged.success, exchanged.message
        return self.call(Calibrate, "calibrate", Calibrate.Request(iterations=1, validate=False, force=True),
                         CALIBRATE_TIMEOUT_S)


def active_bytes(store_dir: Path) -> tuple[bytes, bytes]:
    """The pointer file and the calibration it names, as bytes."""
    path = CalibrationStore(store_dir).active_path()
    return (store_dir / "active.yaml").read_bytes(), path.read_bytes()


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    directory = tmp_path_factory.mktemp("kill")
    ros_args = cell_ros_arguments(directory / "calibrations", directory / "reports", grid=GRID,
                                  parameters=PARAMETERS)
    with running_cell(directory, grid=GRID, parameters=PARAMETERS,
                      node_types=(ScanAcquisitionNode, PlatePoseNode, CalibrationManager)) as running:
        cell = Cell(running, ros_args, directory)
        try:
            for name in VICTIMS:
                cell.start(name)
            for name in VICTIMS:
                cell.wait_up(name)
            first = cell.calibrate()
            assert first.success, first.message
            yield cell
        finally:
            for process in cell.processes.values():
                stop_process(process)


def kill_during_step(cell: Cell, name: str) -> tuple[Calibrate.Response, float]:
    """Start a calibration, kill the victim during the step that uses it (frozen before, if it has a
    freeze stage), start it again; the run's answer and how long after the kill it came."""
    victim = VICTIMS[name]
    exchanged = cell.call(Trigger, "sim/exchange_plate", Trigger.Request())
    assert exchanged.success, exchanged.message
    process = cell.processes[name]
    future = cell.calibrate_async()
    if victim.freeze_at:
        wait_for(lambda: cell.seen(victim.freeze_at) or future.done(), CALIBRATE_TIMEOUT_S,
                 what=f"stage {victim.freeze_at}")
        os.kill(process.pid, signal.SIGSTOP)
    wait_for(lambda: cell.seen(victim.kill_at) or future.done(), CALIBRATE_TIMEOUT_S,
             what=f"stage {victim.kill_at}")
    assert not future.done(), f"the run ended before {name} was killed: {future.result().message}"
    time.sleep(victim.kill_after_s)
    process.kill()
    killed = time.monotonic()
    process.wait(timeout=10.0)
    wait_for(future.done, ANSWER_AFTER_KILL_S + 5.0, what="the answer to calibrate")
    answered_after_s = time.monotonic() - killed
    # Started again before anything is asserted, so that one failure does not take the next cases along.
    cell.start(name)
    cell.wait_up(name)
    return future.result(), answered_after_s


# The galvo is frozen when the plate_pose stage's progress reaches this process. On a busy machine
# that message can come after the manager's marking request was answered (a 3x3 grid marks in
# milliseconds); the run then fails later, on the scanner's read of the marks from the dead galvo,
# and the step under test was never reached. Such an attempt is made again.
TOO_LATE = {"galvo": "sim/marked_paths"}
ATTEMPTS = 3


@pytest.mark.parametrize("name", list(VICTIMS))
def test_a_killed_node_fails_the_run_fast_and_keeps_the_active_calibration(cell, name):
    victim = VICTIMS[name]
    store_dir = cell.running.calibration_dir
    before = active_bytes(store_dir)
    for attempt in range(ATTEMPTS):
        response, answered_after_s = kill_during_step(cell, name)
        assert not response.success
        assert answered_after_s <= ANSWER_AFTER_KILL_S, f"answered {answered_after_s:.1f} s after the kill"
        assert active_bytes(store_dir) == before
        if name not in TOO_LATE or TOO_LATE[name] not in response.message:
            break
    assert victim.named in response.message, response.message

    again = cell.calibrate()
    assert again.success, f"{again.message}; {name} log:\n{cell.log(name).read_text()[-3000:]}"
    assert CalibrationStore(store_dir).active_path() == Path(again.calibration_file)
