"""The simulated cell in another process (``gls-sim-cell --serve``), driven through its services.

The child inherits the session's ROS_DOMAIN_ID (see conftest.py), so only this test sees it.
"""
from __future__ import annotations

import signal
import subprocess
import sys

import numpy as np
import pytest
from rclpy.node import Node

from gls_calibration import kinematics
from gls_calibration.persistence import CalibrationStore
from gls_calibration_msgs.srv import Calibrate, CorrectSetpoints

from ros_helpers import call_service, stop_process, wait_for_peer_service

CELL_START_TIMEOUT_S = 60.0          # interpreter start, imports, eight nodes, discovery on a busy machine
CALIBRATE_TIMEOUT_S = 300.0          # a 3x3 calibration takes well under a minute when the machine is idle
CALL_TIMEOUT_S = 20.0
STOP_TIMEOUT_S = 15.0


@pytest.mark.slow
def test_serving_cell_calibrates_on_request_from_another_process(ros_context, add_node, tmp_path):
    out = tmp_path / "cell"
    log_path = tmp_path / "sim_cell.log"
    with open(log_path, "w") as log:
        cell = subprocess.Popen([sys.executable, "-m", "gls_calibration.cli.sim_cell", "--serve", "--grid", "3",
                                 "--out", str(out)], stdout=log, stderr=subprocess.STDOUT)
    try:
        node = add_node(Node("cross_process_test", namespace="gls", context=ros_context))
        corrector = node.create_client(CorrectSetpoints, "correct_setpoints")
        calibrator = node.create_client(Calibrate, "calibrate")
        wait_for_peer_service(node, corrector, cell, log_path, CELL_START_TIMEOUT_S)
        wait_for_peer_service(node, calibrator, cell, log_path, CELL_START_TIMEOUT_S)

        x, y = np.array([0.0, 40.0, -80.0]), np.array([0.0, -60.0, 30.0])
        nominal = call_service(node, corrector, CorrectSetpoints.Request(x=x, y=y), CALL_TIMEOUT_S)
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

        corrected = call_service(node, corrector, CorrectSetpoints.Request(x=x, y=y), CALL_TIMEOUT_S)
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
