"""Service and streaming figures of the ROS layer (medians; real DDS transport).

1. ``correct_setpoints`` across processes: the correction node runs in a child process with a
   trained calibration; this process calls it with one target and with 100 000 targets.
2. A full 0.1 mm sweep of the simulated scanner streamed as profiles on ``scan/points`` and
   assembled by ``scan_acquisition`` (in one process): time and whether every profile arrived.

Run: .venv/bin/python benchmarks/bench_services.py
"""
from __future__ import annotations

import os
from pathlib import Path
import signal
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import rclpy

from gls_calibration.calibration_record import calibrated_region
from gls_calibration.nodes.conversions import float64_sequence
from gls_calibration.kinematics import HeadGeometry
from gls_calibration.nodes.base import NodeThreads
from gls_calibration.persistence import CalibrationStore, new_record
from gls_calibration.procedure import ProcedureSettings
from gls_calibration.rbf import OLSRBFNetwork
from gls_calibration.targets import grid_targets
from gls_calibration_msgs.srv import AcquireSweep, CorrectSetpoints


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


def timed_calls(client, request, count: int) -> list[float]:
    """Round-trip times (s) of ``count`` calls, each awaited before the next."""
    times = []
    for _ in range(count):
        began = time.perf_counter()
        future = client.call_async(request)
        while not future.done():
            time.sleep(0.0001)
        response = future.result()
        times.append(time.perf_counter() - began)
        assert response.success, response.message
    return times


def bench_correct_setpoints(domain: str) -> None:
    """Round trip of correct_setpoints to a correction node in another process."""
    with tempfile.TemporaryDirectory() as store:
        synthetic_calibration(Path(store))
        child = subprocess.Popen(
            [sys.executable, "-c", "from gls_calibration.nodes.correction import main; main()",
             "--ros-args", "-p", f"calibration_dir:={store}", "--log-level", "warn"],
            env={**os.environ, "ROS_DOMAIN_ID": domain})
        try:
            rclpy.init()
            node = rclpy.create_node("bench_client", namespace="gls")
            threads = NodeThreads([node])
            client = node.create_client(CorrectSetpoints, "correct_setpoints")
            if not client.wait_for_service(timeout_sec=30.0):
                raise RuntimeError("the correction node did not come up")
            rng = np.random.default_rng(0)
            one = CorrectSetpoints.Request(x=[10.0], y=[-20.0])
            many_xy = rng.uniform(-95.0, 95.0, (100_000, 2))
            many = CorrectSetpoints.Request(x=float64_sequence(many_xy[:, 0]), y=float64_sequence(many_xy[:, 1]))
            timed_calls(client, one, 20)  # warm-up: discovery, first allocations
            single = timed_calls(client, one, 300)
            bulk = timed_calls(client, many, 15)
            print(f"correct_setpoints, 1 target, across processes:        median {1e3 * statistics.median(single):7.3f} ms "
                  f"(p90 {1e3 * np.percentile(single, 90):.3f} ms; target <= 2 ms)")
            print(f"correct_setpoints, 100 000 targets, across processes: median {1e3 * statistics.median(bulk):7.1f} ms "
                  f"(target <= 100 ms)")
            threads.stop()
            rclpy.shutdown()
        finally:
            child.send_signal(signal.SIGINT)
            try:
                child.wait(timeout=10)
            except subprocess.TimeoutExpired:
                child.kill()


def bench_sweep_stream() -> None:
    """One full 200 mm sweep at 0.1 mm streamed as profiles and assembled."""
    from gls_calibration.nodes.scan_acquisition import ScanAcquisitionNode
    from gls_calibration.nodes.sim_galvo import SimGalvoNode
    from gls_calibration.nodes.sim_scanner import SimScannerNode
    rclpy.init(args=["--ros-args", "--log-level", "warn"])
    client_node = rclpy.create_node("bench_sweep_client", namespace="gls")
    threads = NodeThreads([SimGalvoNode(), SimScannerNode(), ScanAcquisitionNode(), client_node])
    client = client_node.create_client(AcquireSweep, "scan/acquire")
    client.wait_for_service(timeout_sec=10.0)
    durations = []
    for _ in range(3):
        began = time.perf_counter()
        future = client.call_async(AcquireSweep.Request(step_mm=0.1))
        while not future.done():
            time.sleep(0.001)
        durations.append(time.perf_counter() - began)
        response = future.result()
        assert response.success, response.message
    cloud = response.cloud
    print(f"sweep 200 mm at 0.1 mm streamed as profiles: {cloud.height} profiles x {cloud.width} points "
          f"({cloud.height * cloud.width / 1e6:.1f} M points), none lost; median {statistics.median(durations):.2f} s "
          f"generate + publish + assemble")
    threads.stop()
    rclpy.shutdown()


if __name__ == "__main__":
    domain = os.environ.setdefault("ROS_DOMAIN_ID", str(np.random.default_rng().integers(101, 200)))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    bench_correct_setpoints(domain)
    bench_sweep_stream()
