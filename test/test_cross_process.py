"""The simulated cell in another process (``gls-sim-cell --serve``), driven through its services.

The child inherits the session's ROS_DOMAIN_ID (see conftest.py), so only this test sees it.
"""
from __future__ import annotations

from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from visualization_msgs.msg import MarkerArray

from gls_calibration.calibration.record import record_identity
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.cli.client import RESEND_AFTER_S
from gls_calibration.geometry import kinematics
from gls_calibration_msgs.msg import CalibrationProgress
from gls_calibration_msgs.srv import Calibrate, CorrectSetpoints

from ros_helpers import call_service, default_sigint, stop_process, wait_for, wait_for_peer_service
from test_nodes import trained_record

CELL_START_TIMEOUT_S = 60.0          # interpreter start, imports, eight nodes, discovery on a busy machine
CALIBRATE_TIMEOUT_S = 300.0          # a 3x3 calibration takes well under a minute when the machine is idle
CALL_TIMEOUT_S = 20.0
STOP_TIMEOUT_S = 15.0


def start_serving_cell(out: Path, log_path: Path) -> subprocess.Popen:
    """``gls-sim-cell --serve`` on a 3x3 grid in another process, its store in ``out``/calibrations.

    ``--out`` is given relative to the child's working directory, as ``make sim`` gives it: a store
    opened by a relative directory once made every calibration fail after training. The default sweep
    plan of config/gls.yaml: a 3x3 grid needs every fiducial, and its turned pass lost a corner ring
    with the 200 mm sweep and the 0.12 mm radius tolerance (docs/method-and-results.md)."""
    with open(log_path, "w") as log:
        return subprocess.Popen([sys.executable, "-m", "gls_calibration.cli.sim_cell", "--serve", "--grid", "3",
                                 "--out", out.name], cwd=out.parent, stdout=log,
                                stderr=subprocess.STDOUT, preexec_fn=default_sigint)


def connect(node: Node, cell: subprocess.Popen, log_path: Path):
    """``node`` and its clients of the cell's correct_setpoints and calibrate, once both are served."""
    corrector = node.create_client(CorrectSetpoints, "correct_setpoints")
    calibrator = node.create_client(Calibrate, "calibrate")
    wait_for_peer_service(node, corrector, cell, log_path, CELL_START_TIMEOUT_S)
    wait_for_peer_service(node, calibrator, cell, log_path, CELL_START_TIMEOUT_S)
    return node, corrector, calibrator


@pytest.mark.slow
def test_serving_cell_calibrates_on_request_from_another_process(ros_context, add_node, tmp_path):
    out = tmp_path / "cell"
    log_path = tmp_path / "sim_cell.log"
    cell = start_serving_cell(out, log_path)
    try:
        node, corrector, calibrator = connect(add_node(Node("cross_process_test", namespace="gls",
                                                            context=ros_context)), cell, log_path)

        x, y = np.array([0.0, 40.0, -80.0]), np.array([0.0, -60.0, 30.0])
        nominal = call_service(node, corrector, CorrectSetpoints.Request(x=x, y=y), CALL_TIMEOUT_S, RESEND_AFTER_S)
        assert nominal.success, nominal.message
        assert "nominal" in nominal.message
        expected = kinematics.inverse(kinematics.HeadGeometry(), x, y)
        np.testing.assert_allclose(np.asarray(nominal.alpha_x), expected.alpha_x, rtol=0, atol=1e-15)
        np.testing.assert_allclose(np.asarray(nominal.alpha_y), expected.alpha_y, rtol=0, atol=1e-15)
        assert list(nominal.inside_calibrated_field) == [False, False, False]

        response = call_service(node, calibrator, Calibrate.Request(), CALIBRATE_TIMEOUT_S)
        assert response.success, f"{response.message}; log:\n{log_path.read_text()[-3000:]}"
        assert (response.fiducials_expected, response.fiducials_found) == (9, 9)
        assert response.pre_rms_mm > 0.3
        # --serve keeps its store in the output folder, and the new calibration is the active one.
        assert CalibrationStore(out / "calibrations").active_path() == \
            (out / "calibrations" / "history" / response.calibration_file.rsplit("/", 1)[-1])

        corrected = call_service(node, corrector, CorrectSetpoints.Request(x=x, y=y), CALL_TIMEOUT_S, RESEND_AFTER_S)
        assert corrected.success, corrected.message
        assert corrected.message == "corrected"
        assert list(corrected.inside_calibrated_field) == [True, True, True]
        assert not np.allclose(np.asarray(corrected.alpha_x), expected.alpha_x, rtol=0, atol=1e-7)

        # The operator tool gls-correct, a third process, gets the same answers as a CSV.
        targets_csv, result_csv = tmp_path / "targets.csv", tmp_path / "corrected.csv"
        targets_csv.write_text("x,y\n" + "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(x, y)))
        tool = subprocess.run([sys.executable, "-m", "gls_calibration.cli.correct", str(targets_csv),
                               "--out", str(result_csv)], capture_output=True, text=True, timeout=60)
        assert tool.returncode == 0, tool.stderr
        rows = np.genfromtxt(result_csv, delimiter=",", names=True)
        np.testing.assert_allclose(rows["alpha_x_rad"], np.asarray(corrected.alpha_x), rtol=0, atol=1e-15)
        assert rows["inside_calibrated_field"].tolist() == [1, 1, 1]
    finally:
        exit_code = stop_process(cell, STOP_TIMEOUT_S)
    # SIGINT is how an operator stops --serve: it must end the process without the SIGKILL fallback
    # (gls-sim-cell answers an interrupt with exit code 130).
    assert exit_code != -signal.SIGKILL, f"gls-sim-cell ignored SIGINT; log:\n{log_path.read_text()[-3000:]}"
    assert exit_code == 130, f"gls-sim-cell exited with {exit_code}; log:\n{log_path.read_text()[-3000:]}"


@pytest.mark.slow
def test_correct_setpoints_serves_only_the_active_calibration_throughout_a_run(ros_context, add_node, tmp_path):
    """Another process asks for corrections all through a calibration: every answer comes from the
    calibration active before the run until the new one is activated at the end. Then the operator
    tool gls-calibrate, interrupted with Ctrl-C, cancels its goal and exits cleanly."""
    out = tmp_path / "cell"
    store = CalibrationStore(out / "calibrations")
    record, _ = trained_record()
    store.save(record, activate=True)
    previous_id = record_identity(record)[0]
    log_path = tmp_path / "sim_cell.log"
    cell = start_serving_cell(out, log_path)
    try:
        node, corrector, calibrator = connect(add_node(Node("active_only_test", namespace="gls",
                                                            context=ros_context)), cell, log_path)
        stages: list[tuple[float, str]] = []
        node.create_subscription(CalibrationProgress, "calibration/progress",
                                 lambda message: stages.append((time.monotonic(), message.stage)), 100)
        wait_for(lambda: node.count_publishers("calibration/progress") > 0, CALL_TIMEOUT_S,
                 what="the progress publisher")

        answers: list[tuple[float, str]] = []
        stop = threading.Event()

        def poll() -> None:
            request = CorrectSetpoints.Request(x=[0.0, 20.0], y=[0.0, -30.0])
            while not stop.is_set():
                answer = call_service(node, corrector, request, CALL_TIMEOUT_S, RESEND_AFTER_S)
                assert answer.success, answer.message
                answers.append((time.monotonic(), answer.calibration_id))
                time.sleep(0.05)
        poller = threading.Thread(target=poll, daemon=True)
        poller.start()
        try:
            response = call_service(node, calibrator, Calibrate.Request(validate=True, force=True),
                                    CALIBRATE_TIMEOUT_S)
        finally:
            stop.set()
            poller.join(timeout=CALL_TIMEOUT_S)
        assert response.success, f"{response.message}; log:\n{log_path.read_text()[-3000:]}"
        new_id = record_identity(store.load(Path(response.calibration_file)))[0]
        assert new_id != previous_id
        final = call_service(node, corrector, CorrectSetpoints.Request(x=[0.0], y=[0.0]), CALL_TIMEOUT_S,
                             RESEND_AFTER_S)
        assert final.calibration_id == new_id

        # A late RViz gets the last calibration: plate pose and markers are transient-local (metres).
        late = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        poses, markers = [], []
        node.create_subscription(PoseStamped, "calibration/plate_pose", poses.append, late)
        node.create_subscription(MarkerArray, "calibration/markers", markers.append, late)
        wait_for(lambda: poses and markers, CALL_TIMEOUT_S, what="the latched plate pose and markers")
        assert poses[0].header.frame_id == "gls" and abs(poses[0].pose.position.z) < 0.05
        namespaces = [marker.ns for marker in markers[0].markers]
        assert namespaces.count("deviation_before") == 9 and namespaces.count("deviation_after") == 4
        assert {"fiducials", "validation_fiducials"} <= set(namespaces)

        ids = [calibration_id for _, calibration_id in answers]
        assert set(ids) <= {previous_id, new_id}, set(ids)
        switched = ids.index(new_id) if new_id in ids else len(ids)
        assert ids == [previous_id] * switched + [new_id] * (len(ids) - switched)
        # Validation marks through the candidate after training; meanwhile, others get the old one.
        trained_at = min(at for at, stage in stages if stage == "training")
        validation_measured_at = max(at for at, stage in stages if stage == "measurement")
        during_validation = [calibration_id for at, calibration_id in answers
                             if trained_at < at < validation_measured_at]
        assert len(during_validation) >= 5, (len(during_validation), stages)
        assert set(during_validation) == {previous_id}

        # gls-calibrate interrupted: the goal is canceled, the tool exits 130 with a message.
        tool_log = tmp_path / "gls_calibrate.log"
        with open(tool_log, "w") as stream:
            tool = subprocess.Popen([sys.executable, "-m", "gls_calibration.cli.calibrate", "--force"],
                                    stdout=stream, stderr=subprocess.STDOUT,
                                    preexec_fn=default_sigint)
        try:
            wait_for(lambda: "sweep_plain" in tool_log.read_text() or tool.poll() is not None, CALIBRATE_TIMEOUT_S,
                     what="gls-calibrate showing its first stage")
            tool.send_signal(signal.SIGINT)
            tool.wait(timeout=CALIBRATE_TIMEOUT_S)
        finally:
            stop_process(tool, STOP_TIMEOUT_S)
        text = tool_log.read_text()
        assert tool.returncode == 130, text
        assert "action /gls/calibrate" in text and "canceled" in text and "Traceback" not in text, text
        assert store.active_path() == Path(response.calibration_file)
        again = call_service(node, corrector, CorrectSetpoints.Request(x=[0.0], y=[0.0]), CALL_TIMEOUT_S,
                             RESEND_AFTER_S)
        assert again.calibration_id == new_id
    finally:
        exit_code = stop_process(cell, STOP_TIMEOUT_S)
    assert exit_code == 130, f"gls-sim-cell exited with {exit_code}; log:\n{log_path.read_text()[-3000:]}"
