"""The package as ROS users meet it: which calibration answers, run-time parameters, the calibrate
action with cancel (in-process; the cross-process checks are in test_cross_process.py)."""
from __future__ import annotations

from pathlib import Path
import time

import numpy as np
import pytest
import yaml
from action_msgs.msg import GoalStatus
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.action import ActionClient
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.time import Time
from sensor_msgs.msg import PointCloud2, PointField

from gls_calibration.calibration.record import record_identity
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.common.config_files import config_path
from gls_calibration.geometry import kinematics
from gls_calibration.nodes.correction import CorrectionNode
from gls_calibration.ros import rviz
from gls_calibration.ros.conversions import (array_to_pointcloud2, cloud_from_msg, cloud_to_msg, pointcloud2_to_array,
                                             time_to_msg, xyzi_array)
from gls_calibration.scan.bag_io import BagLayout
from gls_calibration.scan.cell_frames import load_cell_frames
from gls_calibration_msgs.action import Calibrate as CalibrateAction
from gls_calibration_msgs.srv import AcquireSweep, CorrectSetpoints, LoadCalibration

from ros_helpers import call_service, wait_for
from test_nodes import trained_record

NAMESPACE = "gls"
TIMEOUT_S = 10.0


def correct(node: Node, x, y) -> CorrectSetpoints.Response:
    client = node.create_client(CorrectSetpoints, "correct_setpoints")
    try:
        return call_service(node, client, CorrectSetpoints.Request(x=[float(v) for v in x], y=[float(v) for v in y]),
                            TIMEOUT_S)
    finally:
        node.destroy_client(client)


def set_parameters(node: Node, target: str, parameters: list[Parameter]):
    """Set parameters of the node ``target`` through its parameter services; the results."""
    client = AsyncParameterClient(node, target)
    assert client.wait_for_services(timeout_sec=TIMEOUT_S)
    future = client.set_parameters(parameters)
    wait_for(future.done, TIMEOUT_S, what=f"set_parameters on {target}")
    return future.result().results


def seconds(stamp) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def test_every_answer_names_the_calibration_that_gave_it(ros_context, add_node, tmp_path):
    store = CalibrationStore(tmp_path / "store")
    add_node(CorrectionNode(context=ros_context, parameter_overrides=[
        Parameter("calibration_dir", value=str(store.directory))]))
    node = add_node(Node("test_client", namespace=NAMESPACE, context=ros_context))
    nominal = correct(node, [0.0], [0.0])
    assert nominal.success and nominal.calibration_id == "nominal"
    assert seconds(nominal.calibration_created) == 0.0

    record, _ = trained_record()
    store.save(record, activate=True)
    client = node.create_client(LoadCalibration, "correction/load")
    assert call_service(node, client, LoadCalibration.Request(file=""), TIMEOUT_S).success
    answer = correct(node, [0.0], [0.0])
    content_hash, created = record_identity(record)
    assert answer.calibration_id == content_hash and len(content_hash) == 16
    assert seconds(answer.calibration_created) == pytest.approx(created.timestamp(), abs=1e-6)
    # A bad request still says who would have answered.
    refused = correct(node, [0.0, float("nan")], [0.0, 0.0])
    assert not refused.success and refused.calibration_id == content_hash


def test_a_head_parameter_change_reloads_the_correction(ros_context, add_node, tmp_path):
    add_node(CorrectionNode(context=ros_context, parameter_overrides=[
        Parameter("calibration_dir", value=str(tmp_path / "store"))]))
    node = add_node(Node("test_client", namespace=NAMESPACE, context=ros_context))
    x, y = np.array([30.0, -60.0]), np.array([10.0, 80.0])
    before = correct(node, x, y)
    results = set_parameters(node, "/gls/correction", [Parameter("head.working_distance_mm", value=400.0)])
    assert results[0].successful, results[0].reason
    after = correct(node, x, y)
    expected = kinematics.inverse(kinematics.HeadGeometry(working_distance_mm=400.0), x, y)
    np.testing.assert_allclose(np.asarray(after.alpha_x), expected.alpha_x, rtol=0, atol=1e-15)
    assert not np.allclose(np.asarray(after.alpha_x), np.asarray(before.alpha_x), rtol=0, atol=1e-6)
    # Out of range: refused, and the answers stay those of 400 mm.
    refused = set_parameters(node, "/gls/correction", [Parameter("head.working_distance_mm", value=-5.0)])
    assert not refused[0].successful
    np.testing.assert_array_equal(np.asarray(correct(node, x, y).alpha_x), np.asarray(after.alpha_x))
    # The store's folder cannot change at run time: refused, not ignored.
    read_only = set_parameters(node, "/gls/correction", [Parameter("calibration_dir", value=str(tmp_path))])
    assert not read_only[0].successful


def test_the_cell_reports_diagnostics_and_accepts_no_parameter_it_would_ignore(start_cell):
    cell = start_cell(grid=3)
    statuses: dict[str, DiagnosticStatus] = {}

    def keep(array: DiagnosticArray) -> None:
        for status in array.status:
            statuses[status.name] = status
    cell.client_node.create_subscription(DiagnosticArray, "/diagnostics", keep, 10)
    wait_for(lambda: {"gls/calibration_manager", "gls/correction"} <= set(statuses), 5.0,
             what="/diagnostics from the manager and the correction node (1 Hz)")
    manager = {value.key: value.value for value in statuses["gls/calibration_manager"].values}
    assert manager["state"] == "idle" and manager["active_calibration_id"] == "nominal"
    assert manager["last_measured_rms_mm"] == "nan"
    correction = {value.key: value.value for value in statuses["gls/correction"].values}
    assert correction["state"] == "serving" and correction["active_calibration_id"] == "nominal"
    assert statuses["gls/correction"].level == DiagnosticStatus.OK

    for name, node in cell.nodes.items():
        if name == "cell_test_client":
            continue
        for parameter_name in node.list_parameters([], 0).names:
            if parameter_name == "use_sim_time":     # rclpy's own
                continue
            descriptor = node.describe_parameter(parameter_name)
            dynamic = parameter_name in node.dynamic_parameters
            assert descriptor.read_only != dynamic, f"{name}: {parameter_name} read_only={descriptor.read_only}"


# --- the calibrate action ----------------------------------------------------------------------------

def store_bytes(store_dir: Path) -> dict[str, bytes]:
    return {str(path.relative_to(store_dir)): path.read_bytes() for path in sorted(store_dir.rglob("*"))
            if path.is_file()}


class GoalWatcher:
    """Sends one goal of the calibrate action and keeps its feedback."""

    def __init__(self, client: ActionClient, goal) -> None:
        self.stages: list[str] = []
        self.sent = client.send_goal_async(goal, feedback_callback=lambda m: self.stages.append(m.feedback.stage))

    def handle(self):
        wait_for(self.sent.done, TIMEOUT_S, what="the goal's acceptance")
        return self.sent.result()


def test_a_canceled_calibration_keeps_the_active_one_and_a_new_goal_is_accepted(start_cell, tmp_path):
    store = CalibrationStore(tmp_path / "calibrations")
    record, _ = trained_record()
    active = store.save(record, activate=True)
    before = store_bytes(store.directory)
    cell = start_cell(grid=3)
    client = ActionClient(cell.client_node, CalibrateAction, "calibrate")
    assert client.wait_for_server(timeout_sec=TIMEOUT_S)

    # Canceled once the model is trained: the candidate exists in the history, but is never active.
    first = GoalWatcher(client, CalibrateAction.Goal(validate=True, force=True))
    handle = first.handle()
    assert handle.accepted
    wait_for(lambda: "training" in first.stages, 240.0, what="the training stage")
    handle.cancel_goal_async()
    result = handle.get_result_async()
    wait_for(result.done, 240.0, what="the canceled result")
    assert result.result().status == GoalStatus.STATUS_CANCELED
    assert not result.result().result.success
    assert "canceled" in result.result().result.message
    assert first.stages[-1] == "training"          # stopped after the step it was in
    after = store_bytes(store.directory)
    assert {name: data for name, data in after.items() if name in before} == before   # byte for byte
    assert len(after) == len(before) + 1           # the candidate, kept in the history only
    assert store.active_path() == active
    answer = correct(cell.client_node, [0.0], [0.0])
    assert answer.success and answer.calibration_id == record_identity(record)[0]

    # A new goal is accepted (and canceled at its first step).
    second = GoalWatcher(client, CalibrateAction.Goal())
    handle = second.handle()
    assert handle.accepted
    handle.cancel_goal_async()
    result = handle.get_result_async()
    wait_for(result.done, 120.0, what="the second canceled result")
    assert result.result().status == GoalStatus.STATUS_CANCELED
    assert store.active_path() == active and store_bytes(store.directory) == after


# --- SI units and frames at the message boundary -------------------------------------------------------

def test_clouds_go_out_in_metres_and_come_back_in_millimetres():
    rng = np.random.default_rng(3)
    points_mm = xyzi_array(rng.uniform(-100.0, 400.0, (40, 3)), rng.random(40))
    message = cloud_to_msg(points_mm, "scanner", time_to_msg(12.5))
    wire = pointcloud2_to_array(message)
    assert [field.name for field in message.fields] == ["x", "y", "z", "intensity"]
    assert all(field.datatype == PointField.FLOAT32 for field in message.fields)
    np.testing.assert_allclose(wire["x"], points_mm["x"] / 1000.0, rtol=1e-6)
    assert (message.header.frame_id, message.header.stamp.sec, message.header.stamp.nanosec) == \
        ("scanner", 12, 500_000_000)
    back = cloud_from_msg(message)
    for name in ("x", "y", "z"):
        np.testing.assert_allclose(back[name], points_mm[name], rtol=0, atol=1e-4)
    # A driver publishing millimetres: one parameter (scan_acquisition's profile_unit) says so.
    in_mm = array_to_pointcloud2(points_mm, "scanner_sensor")
    np.testing.assert_array_equal(cloud_from_msg(in_mm, mm_per_unit=1.0)["z"], points_mm["z"])


def test_scan_points_are_in_metres_and_the_sweep_is_stamped_with_its_first_profile(start_cell):
    cell = start_cell(grid=3)
    profiles: list[PointCloud2] = []
    cell.client_node.create_subscription(
        PointCloud2, "scan/points", profiles.append,
        QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE))
    wait_for(lambda: cell.client_node.count_publishers("scan/points") > 0, TIMEOUT_S, what="the scanner")
    time.sleep(0.5)        # discovery both ways before the sweep starts
    response = cell.call(AcquireSweep, "scan/acquire", AcquireSweep.Request(step_mm=2.0), timeout_s=120.0)
    assert response.success, response.message
    wait_for(lambda: len(profiles) >= response.cloud.height, TIMEOUT_S, what="every profile")
    first = pointcloud2_to_array(profiles[0])
    assert profiles[0].header.frame_id == "scanner_sensor"
    z = first["z"][np.isfinite(first["z"])]
    assert z.size and np.all((0.25 < z) & (z < 0.40)), z[:5]              # ~325 mm, in metres
    assert float(np.nanmax(np.abs(first["x"]))) < 0.2                   # a line of ~250 mm
    assert response.cloud.header.frame_id == "scanner"
    stamps = [Time.from_msg(profile.header.stamp).nanoseconds for profile in profiles]
    assert Time.from_msg(response.cloud.header.stamp).nanoseconds == min(stamps) > 0
    cloud = pointcloud2_to_array(response.cloud)
    assert 0.25 < float(np.nanmedian(cloud["z"])) < 0.40


# --- RViz ----------------------------------------------------------------------------------------------

def test_the_rviz_config_shows_the_calibration_topics_transient_local():
    document = yaml.safe_load(config_path("gls_calibration.rviz").read_text())
    manager = document["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == rviz.FRAME_ID
    displays = {display["Class"]: display for display in manager["Displays"]}
    for display_class, topic in (("rviz_default_plugins/Pose", "/gls/calibration/plate_pose"),
                                 ("rviz_default_plugins/MarkerArray", "/gls/calibration/markers")):
        assert displays[display_class]["Topic"]["Value"] == topic
        assert displays[display_class]["Topic"]["Durability Policy"] == "Transient Local"
    assert set(displays["rviz_default_plugins/MarkerArray"]["Namespaces"]) == {
        "fiducials", "deviation_before", "validation_fiducials", "deviation_after"}
    # the streaming cell: the profiles as the driver streams them, placed through TF, which connects
    # their frame to the fixed one: sensor -> flange (/tf_static), flange -> base (the robot's /tf),
    # base -> gls (/tf_static), all named by the cell frames file
    assert "rviz_default_plugins/TF" in displays
    assert displays["rviz_default_plugins/PointCloud2"]["Topic"]["Value"] == BagLayout().scan_topic
    frames = load_cell_frames()
    assert frames.gls == rviz.FRAME_ID
    assert len({frames.sensor, frames.flange, frames.base, frames.gls}) == 4   # one tree, rooted at the base
