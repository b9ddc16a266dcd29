"""Service and streaming figures of the ROS layer (medians; real DDS transport).

1. ``correct_setpoints`` with the calibration the DEFAULT main job produces (``gls-sim-cell`` with no
   option is run first, unless ``--calibration FILE`` names one): the correction node runs in a
   child process; this process calls it with one target and with 100 000 targets, and calls an
   echo service in another child process that answers the same request with the same response
   arrays (no correction), so the ratio is what the correction adds to the transport.
2. In-process: ``Correction.correct()`` for one target and for 100 000 targets, and loading the
   calibration file (parse + validate + build the correction, as the node's load does).
3. A full 0.1 mm sweep of the simulated scanner streamed as profiles on ``scan/points`` and
   assembled by ``scan_acquisition`` (in one process): time and whether every profile arrived.

Run: .venv/bin/python benchmarks/bench_services.py [--calibration FILE] [--skip-sweep]
"""
from __future__ import annotations

import argparse
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
import os
from pathlib import Path
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import rclpy

from gls_calibration.calibration.record import correction_from_record
from gls_calibration.calibration.record_file import head_geometry, load_record
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.ros.conversions import float64_sequence
from gls_calibration.ros.runtime import NodeThreads
from gls_calibration_msgs.srv import AcquireSweep, CorrectSetpoints

from correction_peer import call

# An echo of CorrectSetpoints: the response carries the same arrays as the correction's, filled
# from the request without computing anything.
ECHO_NODE = """
import numpy as np
from gls_calibration.correction.setpoints import CorrectedSetpoints
from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.conversions import setpoints_to_response
from gls_calibration.ros.runtime import run_node
from gls_calibration_msgs.srv import CorrectSetpoints

class Echo(GlsNode):
    def __init__(self, **kwargs):
        super().__init__("echo", **kwargs)
        self.create_service(CorrectSetpoints, "echo_setpoints", self.on_call)
        # the same without the uncertainty column (left empty): the answer as it was before issue 30
        self.create_service(CorrectSetpoints, "echo_setpoints_without_u", self.on_call_without_u)

    def on_call(self, request, response):
        x, y = np.asarray(request.x, dtype=float), np.asarray(request.y, dtype=float)
        flags = np.ones(x.size, dtype=bool)
        setpoints_to_response(CorrectedSetpoints(x, y, x, y, x, flags, flags), response)
        response.success = True
        return response

    def on_call_without_u(self, request, response):
        self.on_call(request, response)
        response.uncertainty_k2_mm = []
        return response

run_node(Echo)
"""


CORRECTION_NODE = "from gls_calibration.nodes.correction import main; main()"


def node_process(code: str, environment: Mapping[str, str], *ros_arguments: str) -> subprocess.Popen:
    """A node script ``code`` run by this Python in a child process (log level warn)."""
    return subprocess.Popen([sys.executable, "-c", code, "--ros-args", "--log-level", "warn", *ros_arguments],
                            env=dict(environment))


def correction_process(store: str, environment: Mapping[str, str], namespace: str = "") -> subprocess.Popen:
    """The correction node (and its batch companion) serving the active calibration of ``store``,
    in ``namespace`` (default: the package's)."""
    remap = ["-r", f"__ns:={namespace}"] if namespace else []
    return node_process(CORRECTION_NODE, environment, "-p", f"calibration_dir:={store}", *remap)


def stop_processes(children: list[subprocess.Popen]) -> None:
    """Interrupt the child processes, then kill those still running after 10 s."""
    for child in children:
        child.send_signal(signal.SIGINT)
    for child in children:
        try:
            child.wait(timeout=10)
        except subprocess.TimeoutExpired:
            child.kill()


@contextmanager
def service_clients(services: Mapping[str, str], node_name: str = "bench_client") -> Iterator[dict]:
    """CorrectSetpoints clients by name for the service names given, once every service is up; a
    client node in the ``gls`` namespace spun by a thread of its own (rclpy initialised here)."""
    rclpy.init()
    try:
        node = rclpy.create_node(node_name, namespace="gls")
        threads = NodeThreads([node])
        try:
            clients = {name: node.create_client(CorrectSetpoints, service) for name, service in services.items()}
            for client in clients.values():
                if not client.wait_for_service(timeout_sec=60.0):
                    raise RuntimeError(f"{client.srv_name} did not come up")
            yield clients
        finally:
            threads.stop()
    finally:
        rclpy.shutdown()


def default_main_job_calibration(directory: Path) -> Path:
    """Run ``gls-sim-cell`` with its defaults; the active calibration of the store in its report folder."""
    tool = shutil.which("gls-sim-cell", path=str(Path(sys.executable).parent)) or "gls-sim-cell"
    began = time.perf_counter()
    subprocess.run([tool, "--out", str(directory)], check=True, stdout=subprocess.DEVNULL)
    print(f"default main job (gls-sim-cell, no option) ran in {time.perf_counter() - began:.1f} s")
    return CalibrationStore(directory / "calibrations").active_path()


def timed_calls(client, request, count: int) -> list[float]:
    """Round-trip times (s) of ``count`` calls, each awaited before the next (RuntimeError when an
    answer does not come within 60 s: a benchmark must fail, not spin for ever)."""
    times = []
    for _ in range(count):
        began = time.perf_counter()
        response = call(client, request, timeout_s=60.0)
        times.append(time.perf_counter() - began)
        assert response.success, response.message
    return times


def describe(calibration: Path) -> str:
    record = load_record(calibration)
    models = ", ".join(f"{model['type']} ({len(model.get('centres', []))} centres)" for model in record["models"])
    return f"{calibration} [{models}]"


def timed(function, count: int) -> tuple[float, float]:
    """Median wall time and mean CPU time of this process (s) per call of ``function``.

    On a machine shared with other work the wall time includes waiting for a core; the CPU time
    does not (it still includes the cache and core sharing)."""
    walls = []
    cpu_began = time.process_time()
    for _ in range(count):
        began = time.perf_counter()
        function()
        walls.append(time.perf_counter() - began)
    return statistics.median(walls), (time.process_time() - cpu_began) / count


def bench_in_process(calibration: Path) -> None:
    """Correction.correct() and loading, in this process."""
    def load():
        record = load_record(calibration)
        return correction_from_record(record, head_geometry(record))

    correction = load()
    many = np.random.default_rng(0).uniform(-95.0, 95.0, (100_000, 2))
    correction.correct([10.0], [-20.0])
    one_wall, one_cpu = timed(lambda: correction.correct([10.0], [-20.0]), 3000)
    bulk_wall, bulk_cpu = timed(lambda: correction.correct(many[:, 0], many[:, 1]), 15)
    load_wall, load_cpu = timed(load, 15)
    print(f"in-process Correction.correct(), 1 target:        median {1e6 * one_wall:7.1f} us wall, "
          f"{1e6 * one_cpu:.1f} us CPU (target <= 15 us)")
    print(f"in-process Correction.correct(), 100 000 targets: median {1e3 * bulk_wall:7.1f} ms wall, "
          f"{1e3 * bulk_cpu:.1f} ms CPU (target <= 60 ms)")
    print(f"loading the calibration file (parse, validate, build): median {1e3 * load_wall:5.1f} ms wall, "
          f"{1e3 * load_cpu:.1f} ms CPU (target <= 50 ms)")


def bench_correct_setpoints(domain: str, calibration: Path) -> None:
    """Round trips of correct_setpoints and of an echo with the same arrays, both in other processes."""
    environment = {**os.environ, "ROS_DOMAIN_ID": domain}
    with tempfile.TemporaryDirectory() as store:
        CalibrationStore(store).save(load_record(calibration))
        children = [correction_process(store, environment), node_process(ECHO_NODE, environment)]
        try:
            with service_clients({"correction": "correct_setpoints", "echo": "echo_setpoints"}) as clients:
                rng = np.random.default_rng(0)
                one = CorrectSetpoints.Request(x=[10.0], y=[-20.0])
                many_xy = rng.uniform(-95.0, 95.0, (100_000, 2))
                many = CorrectSetpoints.Request(x=float64_sequence(many_xy[:, 0]), y=float64_sequence(many_xy[:, 1]))
                medians = {}
                for name, client in clients.items():
                    timed_calls(client, one, 20)  # warm-up: discovery, first allocations
                # Interleaved rounds, so both services see the same machine load.
                single = {name: [] for name in clients}
                bulk = {name: [] for name in clients}
                for _ in range(5):
                    for name, client in clients.items():
                        single[name] += timed_calls(client, one, 60)
                        bulk[name] += timed_calls(client, many, 3)
                for name in clients:
                    medians[name] = (statistics.median(single[name]), statistics.median(bulk[name]))
                (one_c, bulk_c), (one_e, bulk_e) = medians["correction"], medians["echo"]
                print(f"correct_setpoints, 1 target, across processes:        median {1e3 * one_c:7.3f} ms; echo "
                      f"{1e3 * one_e:.3f} ms; ratio {one_c / one_e:.2f} (target <= 1.3)")
                print(f"correct_setpoints, 100 000 targets, across processes: median {1e3 * bulk_c:7.1f} ms; echo "
                      f"{1e3 * bulk_e:.1f} ms; ratio {bulk_c / bulk_e:.2f} (target <= 2)")
        finally:
            stop_processes(children)


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
    parser = argparse.ArgumentParser(description="service and streaming benchmarks")
    parser.add_argument("--calibration", type=Path, help="calibration file (default: run the default main job)")
    parser.add_argument("--skip-sweep", action="store_true", help="only the correction figures")
    arguments = parser.parse_args()
    domain = os.environ.setdefault("ROS_DOMAIN_ID", str(np.random.default_rng().integers(101, 200)))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    with tempfile.TemporaryDirectory() as scratch:
        calibration = arguments.calibration or default_main_job_calibration(Path(scratch) / "main_job")
        print(f"calibration: {describe(calibration)}")
        bench_in_process(calibration)
        bench_correct_setpoints(domain, calibration)
    if not arguments.skip_sweep:
        bench_sweep_stream()
