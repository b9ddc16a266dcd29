"""The calibration manager's explain_deviations service: the discrepancy workflow on a stored
calibration's measured fiducials, answered as success=false with a message on a bad file."""
from __future__ import annotations

import json

import numpy as np
import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter

from gls_calibration.calibration.procedure import ProcedureSettings
from gls_calibration.calibration.record import calibrated_region
from gls_calibration.calibration.record_file import new_record
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.geometry.optics import PhysicalHead
from gls_calibration.nodes.calibration_manager import CalibrationManager
from gls_calibration_msgs.srv import ExplainDeviations
from ros_helpers import call_service

GEOMETRY = HeadGeometry()


def store_with_hidden_gain_error(directory, seed: int = 3) -> None:
    """An active calibration whose fiducials come from a head with a hidden 0.5 % X gain error."""
    rng = np.random.default_rng(seed)
    targets = grid_targets(19, 190.0)
    setpoints = inverse(GEOMETRY, targets[:, 0], targets[:, 1])
    landed = PhysicalHead(GEOMETRY, {"galvo_gain_x": (0.005,)}).land(setpoints.alpha_x, setpoints.alpha_y)
    measured = landed[:, :2] + rng.normal(0.0, 0.003, targets.shape)
    zeros = np.zeros(len(targets))
    record = new_record(
        head=GEOMETRY, plate_pose={"normal": [0, 0, 1], "centre": [0, 0, 0], "rotation": np.eye(3),
                                   "flatness_rms_mm": 0.01},
        models=[], calibrated_region=calibrated_region(ProcedureSettings()).to_dict(), hyper_parameters={},
        metrics={}, fiducials={"target_x": targets[:, 0], "target_y": targets[:, 1], "measured_x": measured[:, 0],
                               "measured_y": measured[:, 1], "measured_z": zeros,
                               "dx": targets[:, 0] - measured[:, 0], "dy": targets[:, 1] - measured[:, 1]})
    CalibrationStore(directory).save(record)


def test_explain_deviations_names_the_hidden_effect_and_refuses_a_bad_file(add_node, ros_context, tmp_path):
    store_with_hidden_gain_error(tmp_path / "store")
    add_node(CalibrationManager(context=ros_context, parameter_overrides=[
        Parameter("calibration_dir", value=str(tmp_path / "store")),
        Parameter("report_dir", value=str(tmp_path / "reports"))]))
    client_node = add_node(Node("explain_client", context=ros_context))
    client = client_node.create_client(ExplainDeviations, "/gls/explain_deviations")

    answer = call_service(client_node, client, ExplainDeviations.Request(), timeout_s=30.0)
    assert answer.success, answer.message
    assert list(answer.named_effects) == ["galvo_gain_x"]
    assert answer.rms_before_mm > 0.1
    assert answer.rms_after_mm < 1.5 * answer.noise_floor_mm
    report = json.loads(answer.report_json)
    assert report["named_effects"] == ["galvo_gain_x"]
    assert report["effects"][0]["parameters"]["gain_error_x"] == pytest.approx(0.005, rel=0.05)

    missing = call_service(client_node, client, ExplainDeviations.Request(calibration_file=str(tmp_path / "nope.yaml")),
                           timeout_s=10.0)
    assert not missing.success
    assert "nope.yaml" in missing.message and "outside the calibration directory" in missing.message
    # no existence oracle: a file that exists outside the store gets the same answer (issue 31)
    existing = tmp_path / "there.yaml"
    existing.write_text("active: x\n")
    there = call_service(client_node, client, ExplainDeviations.Request(calibration_file=str(existing)),
                         timeout_s=10.0)
    assert not there.success
    assert there.message.replace(str(existing), "PATH") == missing.message.replace(str(tmp_path / "nope.yaml"), "PATH")
    inside = call_service(client_node, client, ExplainDeviations.Request(calibration_file="nope.yaml"), timeout_s=10.0)
    assert not inside.success and "cannot read file" in inside.message
