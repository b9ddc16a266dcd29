"""The streaming acquisition against a robot and a scanner played by a separate process that imports
nothing of this package (test/_stream_peer.py: plain rclpy, PointCloud2 in metres, /tf, /tf_static,
the motion contract): the assembled sweep against closed form, and every kind of bad stream refused
with a message naming it."""
from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rclpy.parameter import Parameter
from std_msgs.msg import Empty

from gls_calibration.nodes.stream_acquisition import StreamAcquisitionNode
from gls_calibration.ros import conversions
from gls_calibration_msgs.srv import AcquireSweep

from ros_helpers import call_service, default_sigint, stop_process, wait_for

PEER = Path(__file__).with_name("_stream_peer.py")
RATE_HZ = 50.0
STEP_MM = 1.0
LENGTH_MM = 20.0
# the peer's plate (test/_stream_peer.py, in mm): flat at z 300, a ridge at z 290 for 2.25 < x < 6.25
LINE_X_MM = -10.0 + 0.5 * np.arange(41)
TOLERANCE_MM = 1e-4        # float32 metres carry about 3e-5 mm at 0.3 m


def _plate_z_mm(x_mm: np.ndarray) -> np.ndarray:
    return np.where((x_mm > 2.25) & (x_mm < 6.25), 290.0, 300.0)


def imported_modules(path: Path) -> set[str]:
    """Every module a Python file names in an import statement."""
    modules = set()
    for statement in ast.walk(ast.parse(path.read_text())):
        if isinstance(statement, ast.Import):
            modules.update(alias.name for alias in statement.names)
        elif isinstance(statement, ast.ImportFrom):
            modules.add(statement.module or "")
    return modules


def test_the_peer_imports_nothing_of_the_package():
    """Its imports name no module of the package (and at run time it asserts none got loaded)."""
    modules = imported_modules(PEER)
    ours = ("gls_calibration", "gls_calibration_msgs", "ros_helpers")
    assert "rclpy" in modules and not any(name.split(".")[0] in ours for name in modules)


@pytest.fixture
def peer_session(ros_context, add_node, tmp_path):
    """The acquisition node in-process, the peer in its own process running ``modes`` in turn."""
    processes = []

    def start(modes: list[str], *options: str):
        log = tmp_path / "peer.log"
        with log.open("w") as handle:
            process = subprocess.Popen([sys.executable, str(PEER), "--rate", str(RATE_HZ), "--modes", ",".join(modes),
                                        "--lifetime", "120", *options], stdout=handle, stderr=subprocess.STDOUT,
                                       preexec_fn=default_sigint)
        processes.append(process)
        node = add_node(StreamAcquisitionNode(context=ros_context, parameter_overrides=[
            Parameter("profile_rate_hz", value=RATE_HZ), Parameter("end_grace_s", value=0.5)]))
        client_node = add_node(__import__("rclpy").create_node("peer_test_client", namespace="gls",
                                                               context=ros_context))
        client = client_node.create_client(AcquireSweep, "scan/acquire")

        def acquire(direction: int = 1, orientation_deg: float = 0.0):
            request = AcquireSweep.Request(length_mm=LENGTH_MM, step_mm=STEP_MM, direction=direction,
                                           orientation_deg=orientation_deg, timeout_s=30.0)
            return call_service(client_node, client, request, timeout_s=40.0)
        return node, acquire, log
    yield start
    for process in processes:
        stop_process(process)


def _check_closed_form(response, rows: int, direction: int, orientation_deg: float) -> None:
    """Every point on the peer's plate where its line lay, rows a whole number of steps apart."""
    xyz, _ = conversions.cloud_arrays_from_msg(response.cloud)
    assert xyz.shape == (rows, LINE_X_MM.size, 3)
    np.testing.assert_allclose(xyz[..., 2], _plate_z_mm(xyz[..., 0]), atol=TOLERANCE_MM)
    turn = np.radians(orientation_deg)
    # the sensor's x (the line) and y (the travel) in the base frame
    line_axis, travel_axis = np.array([np.cos(turn), np.sin(turn)]), np.array([-np.sin(turn), np.cos(turn)])
    along_line = xyz[..., :2] @ line_axis
    travel = xyz[..., :2] @ travel_axis
    start_travel = 0.5 * LENGTH_MM * (np.array([0.0, 1.0]) @ travel_axis) - direction * 0.5 * LENGTH_MM
    np.testing.assert_allclose(along_line - along_line[:, :1],
                               np.broadcast_to(LINE_X_MM - LINE_X_MM[0], along_line.shape), atol=TOLERANCE_MM)
    steps = direction * (travel[:, 0] - start_travel) / STEP_MM
    np.testing.assert_allclose(steps, np.round(steps), atol=TOLERANCE_MM)
    assert np.all(np.diff(np.round(steps)) >= 1) and steps[0] == pytest.approx(0.0, abs=TOLERANCE_MM)
    np.testing.assert_allclose(travel, travel[:, :1] * np.ones_like(travel), atol=TOLERANCE_MM)


def test_sweeps_from_a_peer_process_match_closed_form_and_bad_streams_are_refused(peer_session):
    node, acquire, log = peer_session(["normal", "out_of_order", "late", "stale", "stops", "mm"],
                                      "--hand-eye-on-request")
    missing = acquire()     # the peer withholds the hand-eye: no line is commanded
    assert not missing.success
    # (robot_base -> gls is named among the frames received unless the peer took over 5 s to start)
    assert missing.message.startswith("no fixed transform from flange to scanner_optical on /tf_static within 5 s "
                                      "(fixed frames received: "), missing.message
    assert missing.message.endswith("; line not commanded"), missing.message
    hand_eye = node.create_publisher(Empty, "/peer/hand_eye", 10)
    wait_for(lambda: hand_eye.get_subscription_count() > 0, 20.0, what="the peer's /peer/hand_eye subscription")
    hand_eye.publish(Empty())

    good = acquire()
    assert good.success, f"{good.message}\npeer log:\n{log.read_text()}"
    assert good.placed_by_pose and good.cloud.header.frame_id == "robot_base"
    assert "21 profiles of 41 points" in good.message
    # the 3 streamed before the start and, of the 5 after the end, those that came before the sweep closed (>= 1)
    outside = int(re.search(r"; (\d+) profile\(s\) outside the motion not used", good.message).group(1))
    assert 4 <= outside <= 8, good.message
    _check_closed_form(good, 21, 1, 0.0)

    swapped = acquire(direction=-1, orientation_deg=90.0)
    assert swapped.success, swapped.message
    assert "1 out of order dropped" in swapped.message and "20 profiles of 41 points" in swapped.message
    _check_closed_form(swapped, 20, -1, 90.0)

    held_back = acquire()     # one profile of the line comes LATE_S (3 s) after the end: the sweep is taken without it
    assert held_back.success and "20 profiles of 41 points" in held_back.message, held_back.message
    assert "late" not in held_back.message
    _check_closed_form(held_back, 20, 1, 0.0)
    wait_for(lambda: node.late == 1, 10.0, what="the held-back profile counted as late")

    stale = acquire()
    assert stale.message.endswith("; 1 profile(s) of the previous sweep came after it was taken (late, not used)")
    assert not stale.success and "older than" in stale.message and "(limit 0.05 s)" in stale.message, stale.message

    stops = acquire()
    assert not stops.success
    assert "the profile stream stops" in stops.message and "before the motion ends" in stops.message

    millimetres = acquire()
    assert not millimetres.success and "not in metres (millimetres?)" in millimetres.message, millimetres.message
    assert node.session is None
