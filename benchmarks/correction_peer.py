"""A correction node in a child process with a trained calibration, and a client node here (for benchmarks)."""
from __future__ import annotations

from contextlib import contextmanager
import os
from pathlib import Path
import signal
import subprocess
import sys
import tempfile
import threading
from typing import Iterator

import numpy as np
import rclpy

from gls_calibration.calibration.procedure import ProcedureSettings
from gls_calibration.calibration.record import calibrated_region, correction_from_record
from gls_calibration.calibration.record_file import new_record
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.correction.setpoints import Correction
from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.models.rbf import OLSRBFNetwork
from gls_calibration.ros.dds import use_fast_liveliness
from gls_calibration.ros.runtime import NodeThreads


def synthetic_calibration(directory: Path) -> None:
    """A store whose active calibration is an OLS network on a smooth 0.85 mm field."""
    targets = grid_targets(19, 190.0)
    x, y = targets.T / 95.0
    field = np.column_stack([0.9 * x + 0.3 * x * y ** 2, 0.3 * y - 0.2 * x ** 2])
    model = OLSRBFNetwork(targets, field, 35.0, 0.0005)
    zeros = np.zeros(len(targets))
    record = new_record(
        head=HeadGeometry(), plate_pose={"normal": [0, 0, 1], "centre": [0, 0, 0], "rotation": np.eye(3),
                                         "flatness_rms_mm": 0.0},
        models=[model.to_dict()], calibrated_region=calibrated_region(ProcedureSettings()).to_dict(),
        hyper_parameters={}, metrics={}, fiducials={"target_x": targets[:, 0], "target_y": targets[:, 1],
                                                    "measured_x": targets[:, 0], "measured_y": targets[:, 1],
                                                    "measured_z": zeros, "dx": field[:, 0], "dy": field[:, 1]})
    CalibrationStore(directory).save(record)


def rss_bytes(pid: int) -> int:
    """Resident set size of process ``pid`` (Linux /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"no VmRSS for process {pid}")


def call(client, request, timeout_s: float = 120.0):
    """The answer to ``request`` (the client's node is spun by another thread); RuntimeError after
    ``timeout_s`` (a benchmark must fail, not hang)."""
    # Blocking on an event, not polling: a polling client took CPU from the server it measured.
    answered = threading.Event()
    future = client.call_async(request)
    future.add_done_callback(lambda _: answered.set())
    if not answered.wait(timeout_s):
        raise RuntimeError(f"no answer from {client.srv_name} within {timeout_s} s")
    return future.result()


def stop_process(process: subprocess.Popen) -> None:
    """Ctrl-C for a node's process (it leaves the DDS graph cleanly); killed when not gone within 10 s."""
    process.send_signal(signal.SIGINT)
    try:
        process.wait(timeout=10)
    except subprocess.TimeoutExpired:
        process.kill()


@contextmanager
def correction_peer(client_names: tuple[str, ...] = ("bench_client",), *parameters: str) -> Iterator[tuple]:
    """(child process, client nodes, the Correction it serves), all stopped afterwards; ``parameters``
    (``name:=value``) go to the correction node."""
    os.environ.setdefault("ROS_DOMAIN_ID", str(np.random.default_rng().integers(101, 200)))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    use_fast_liveliness()
    with tempfile.TemporaryDirectory() as store:
        synthetic_calibration(Path(store))
        expected: Correction = correction_from_record(CalibrationStore(store).load_active(), HeadGeometry())
        child = subprocess.Popen(
            [sys.executable, "-c", "from gls_calibration.nodes.correction import main; main()",
             "--ros-args", "-p", f"calibration_dir:={store}", "--log-level", "warn",
             *(argument for parameter in parameters for argument in ("-p", parameter))])
        rclpy.init()
        nodes = [rclpy.create_node(name, namespace="gls") for name in client_names]
        threads = NodeThreads(nodes)
        try:
            yield child, nodes, expected
        finally:
            threads.stop()
            rclpy.shutdown()
            stop_process(child)
