"""Where the round trip of 100 000 targets goes: request in, handler, answer out (medians, ms).

Each server runs in a child process and writes the monotonic clock (shared by all processes of the
machine) at the start and end of its handler into the answer's ``message``; this client stamps the
call and the arrival of the answer. Servers: an echo that answers at once, echoes that sleep before
answering (``--sleeps-ms``), and the correction node with the given calibration (one chunk for the
whole request). Each server gets a fresh pair of processes, so one run shows one transport mode.

Run: .venv/bin/python benchmarks/bench_transport_timeline.py [--calibration FILE] [--runs 2] [--sleeps-ms 4 16]
(without --calibration, the default main job runs first, as in bench_services.py)
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path
import subprocess
import sys
import tempfile
import time

import numpy as np
import rclpy

from gls_calibration.calibration.record_file import load_record
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.ros.conversions import float64_sequence
from gls_calibration.ros.runtime import NodeThreads
from gls_calibration_msgs.srv import CorrectSetpoints

from bench_services import default_main_job_calibration
from correction_peer import call, stop_process

# Both servers answer on correct_setpoints; argv[1] is the echo's sleep in ms (the correction node
# gets none). The stamps travel in the answer's message.
STAMPED_ECHO = """
import sys, time
import numpy as np
from gls_calibration.correction.setpoints import CorrectedSetpoints
from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.conversions import setpoints_to_response
from gls_calibration.ros.runtime import run_node
from gls_calibration_msgs.srv import CorrectSetpoints
SLEEP_S = float(sys.argv[1]) / 1000.0

class Echo(GlsNode):
    def __init__(self, **kwargs):
        super().__init__("echo", **kwargs)
        self.create_service(CorrectSetpoints, "correct_setpoints", self.on_call)

    def on_call(self, request, response):
        began = time.perf_counter()
        time.sleep(SLEEP_S)
        x, y = np.asarray(request.x, dtype=float), np.asarray(request.y, dtype=float)
        flags = np.ones(x.size, dtype=bool)
        setpoints_to_response(CorrectedSetpoints(x, y, x, y, x, flags, flags), response)
        response.success, response.message = True, f"{began!r} {time.perf_counter()!r}"
        return response

run_node(Echo, sys.argv[2:])
"""

STAMPED_CORRECTION = """
import sys, time
from gls_calibration.nodes import correction

answer = correction.CorrectionNode.answer

async def stamped(self, worker, request, response):
    began = time.perf_counter()
    response = await answer(self, worker, request, response)
    response.message = f"{began!r} {time.perf_counter()!r}"
    return response

correction.CorrectionNode.answer = stamped
correction.main(sys.argv[1:])
"""


def timeline(command: list[str], calls: int, warm_up: int) -> np.ndarray:
    """Medians (ms) of request in, handler, answer out and round trip over ``calls`` calls of
    100 000 targets to the server ``command`` starts (after ``warm_up`` calls)."""
    os.environ["ROS_DOMAIN_ID"] = str(np.random.default_rng().integers(101, 200))
    server = subprocess.Popen(command)
    try:
        rclpy.init()
        node = rclpy.create_node("timeline_client", namespace="gls")
        threads = NodeThreads([node])
        client = node.create_client(CorrectSetpoints, "correct_setpoints")
        if not client.wait_for_service(timeout_sec=60.0):
            raise RuntimeError("correct_setpoints did not come up")
        targets = np.random.default_rng(0).uniform(-95.0, 95.0, (100_000, 2))
        request = CorrectSetpoints.Request(x=float64_sequence(targets[:, 0]), y=float64_sequence(targets[:, 1]))
        rows = []
        for index in range(warm_up + calls):
            sent = time.perf_counter()
            response = call(client, request, timeout_s=60.0)
            arrived = time.perf_counter()
            began, ended = map(float, response.message.split()[:2])
            if index >= warm_up:
                rows.append((began - sent, ended - began, arrived - ended, arrived - sent))
        threads.stop()
        return 1e3 * np.median(np.array(rows), axis=0)
    finally:
        rclpy.try_shutdown()
        stop_process(server)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="request / handler / answer times of 100 000 targets")
    parser.add_argument("--calibration", type=Path,
                        help="calibration file the node serves (default: run the default main job)")
    parser.add_argument("--runs", type=int, default=2, help="fresh process pairs per server")
    parser.add_argument("--sleeps-ms", type=float, nargs="*", default=[4.0, 16.0], help="echoes that sleep first")
    parser.add_argument("--calls", type=int, default=50)
    arguments = parser.parse_args()
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    with tempfile.TemporaryDirectory() as store:
        calibration = arguments.calibration or default_main_job_calibration(Path(store) / "main_job")
        CalibrationStore(Path(store) / "served").save(load_record(calibration))
        servers = [("echo, answers at once", [sys.executable, "-c", STAMPED_ECHO, "0"])]
        servers += [(f"echo, sleeps {sleep:g} ms", [sys.executable, "-c", STAMPED_ECHO, str(sleep)])
                    for sleep in arguments.sleeps_ms]
        servers.append(("correction node, one chunk", [
            sys.executable, "-c", STAMPED_CORRECTION, "--ros-args", "-p", f"calibration_dir:={Path(store) / 'served'}",
            "-p", "chunk_targets:=1000000", "--log-level", "warn"]))
        print(f"{'server':30s} {'run':>3s} {'in':>6s} {'handler':>8s} {'out':>6s} {'round trip':>11s}  (medians, ms)")
        for run in range(arguments.runs):
            for name, command in servers:
                if "echo" in name:
                    command = command + ["--ros-args", "--log-level", "warn"]
                inbound, handler, outbound, total = timeline(command, arguments.calls, warm_up=10)
                print(f"{name:30s} {run + 1:3d} {inbound:6.1f} {handler:8.1f} {outbound:6.1f} {total:11.1f}",
                      flush=True)
