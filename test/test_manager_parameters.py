"""The calibration manager's parameters an operator can set (issue 31, item 7).

Through the node's own SetParameters service, as ``ros2 param set`` calls it: a settable parameter
applies from the next run, a change while a run is in progress or an invalid value is refused with a
message, a read-only one is refused and its description says why.
"""
from __future__ import annotations

import pytest
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.srv import DescribeParameters, GetParameters, SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from gls_calibration.nodes.calibration_manager import CalibrationManager
from gls_calibration.ros.manager_parameters import MANAGER_PARAMETERS, SETTABLE, manager_config
from gls_calibration_msgs.srv import Calibrate

from ros_helpers import call_service, wait_for
from test_nodes import TIMEOUT_S, client_node, start_manager

CALIBRATE_TIMEOUT_S = 300.0
FAST = {"sweep.plain_repeats": 1, "sweep.plan": "0+"}
ROS_OWN = {"use_sim_time", "start_type_description_service"}   # what rclpy declares on every node


class ParameterClient:
    """``ros2 param set/get/describe`` on the manager, from ``node``."""

    def __init__(self, node: Node, target: str = "calibration_manager") -> None:
        self.node = node
        self.setter = node.create_client(SetParameters, f"{target}/set_parameters")
        self.getter = node.create_client(GetParameters, f"{target}/get_parameters")
        self.describer = node.create_client(DescribeParameters, f"{target}/describe_parameters")

    def set(self, name: str, value):
        message = Parameter(name, value=value).to_parameter_msg()
        answer = call_service(self.node, self.setter, SetParameters.Request(parameters=[message]), TIMEOUT_S)
        return answer.results[0]

    def get(self, name: str):
        answer = call_service(self.node, self.getter, GetParameters.Request(names=[name]), TIMEOUT_S)
        return Parameter.from_parameter_msg(ParameterMsg(name=name, value=answer.values[0])).value

    def describe(self, name: str):
        return call_service(self.node, self.describer, DescribeParameters.Request(names=[name]),
                            TIMEOUT_S).descriptors[0]


def test_the_table_holds_every_parameter_the_manager_declares(ros_context, tmp_path):
    folders = {"calibration_dir": str(tmp_path / "store"), "report_dir": str(tmp_path / "reports")}
    manager = CalibrationManager(context=ros_context, parameter_overrides=[
        Parameter(name, value=value) for name, value in folders.items()])
    try:
        declared = set(manager._parameters) - ROS_OWN
        assert declared == {parameter.name for parameter in MANAGER_PARAMETERS}
        for parameter in MANAGER_PARAMETERS:
            descriptor = manager.describe_parameter(parameter.name)
            assert descriptor.read_only == (not parameter.settable), parameter.name
            assert descriptor.description == parameter.full_description
            if parameter.settable:
                assert descriptor.description.endswith("[settable: applies from the next calibration run]")
            else:
                assert "[read-only: " in descriptor.description and len(parameter.read_only_because) > 20
        # the defaults make the configuration a manager without a parameter file runs with
        defaults = manager_config({parameter.name: parameter.default for parameter in MANAGER_PARAMETERS} | folders)
        assert repr(defaults) == repr(manager.config)   # (numpy arrays inside: compared as text)
    finally:
        manager.destroy_node()


def test_read_only_and_invalid_values_are_refused_with_a_message(ros_context, add_node, tmp_path):
    add_node(CalibrationManager(context=ros_context, parameter_overrides=[
        Parameter("calibration_dir", value=str(tmp_path / "store")),
        Parameter("report_dir", value=str(tmp_path / "reports"))]))
    manager = ParameterClient(client_node(ros_context, add_node))

    refused = manager.set("calibration_dir", "elsewhere")
    assert not refused.successful and "read-only" in refused.reason
    why = manager.describe("calibration_dir")
    assert why.read_only and "[read-only: the correction node serves the active calibration" in why.description
    assert manager.get("calibration_dir") == str(tmp_path / "store")
    assert not manager.set("head.working_distance_mm", 300.0).successful

    for name, value, reason in [
            ("grid.ring_radii_mm", [2.7, 2.5], "grid.ring_radii_mm not changed: ring_radii_mm must be one or more "
                                               "positive finite radii in increasing order, got [2.7, 2.5]"),
            ("sweep.plan", "0+,45*", "sweep.plan not changed: parameter sweep.plan: sweep plan item '45*' must be"),
            ("scanner_to_gls.rpy_rad", [0.0, 0.0], "scanner_to_gls.rpy_rad not changed: parameter "
                                                   "scanner_to_gls.rpy_rad: 3 finite numbers are needed"),
            ("default_iterations", 5, "default_iterations not changed: default_iterations must be between 1 and "
                                      "max_iterations (3), got 5")]:
        before = manager.get(name)
        answer = manager.set(name, value)
        assert not answer.successful and answer.reason.startswith(reason), (name, answer.reason)
        assert manager.get(name) == before
    # ROS's own checks come first: the range, the type
    out_of_range = manager.set("grid.per_side", 200)
    assert not out_of_range.successful and out_of_range.reason
    wrong_type = manager.set("grid.size_mm", "abc")
    assert not wrong_type.successful and wrong_type.reason
    assert manager.get("grid.per_side") == 19 and manager.get("grid.size_mm") == 190.0


def test_a_change_during_a_run_is_refused_and_accepted_after_it(ros_context, add_node, tmp_path):
    scanner = start_manager(ros_context, add_node, tmp_path, sweep_timeout_s=4.0, store_dir=tmp_path / "store")
    node = client_node(ros_context, add_node)
    manager = ParameterClient(node)
    calibrator = node.create_client(Calibrate, "calibrate")
    assert calibrator.wait_for_service(timeout_sec=TIMEOUT_S)
    run = calibrator.call_async(Calibrate.Request())
    wait_for(lambda: len(scanner.requests) == 1, TIMEOUT_S, what="the calibration starting a sweep")

    during = manager.set("grid.per_side", 5)
    assert not run.done()
    assert not during.successful
    assert during.reason == ("grid.per_side not changed: a calibration is running and keeps the settings it "
                             "started with; set it again once the run has ended")
    assert manager.get("grid.per_side") == 19

    wait_for(run.done, 4.0 + TIMEOUT_S, what="the run ending (its silent scanner fails it)")
    assert not run.result().success
    after = manager.set("grid.per_side", 5)
    assert after.successful, after.reason
    assert manager.get("grid.per_side") == 5


@pytest.mark.slow
def test_a_setting_changed_between_runs_applies_to_the_next_run(start_cell):
    cell = start_cell(grid=3, parameters=FAST)
    manager = ParameterClient(cell.client_node)
    first = cell.call(Calibrate, "calibrate", Calibrate.Request(force=True, validate=False), CALIBRATE_TIMEOUT_S)
    assert first.success, first.message
    assert first.fiducials_expected == 9 and first.neurons > 0

    # A 4x4 grid, and a tolerance the measured deviation is within: the next run measures 16 fiducials
    # and trains nothing (with the first run's settings it would have trained on 9).
    for name, value in [("grid.per_side", 4), ("tolerance_rms_mm", 10.0), ("rviz.arrow_scale", 20.0)]:
        assert name in SETTABLE
        answer = manager.set(name, value)
        assert answer.successful, answer.reason
    fresh = cell.call(Trigger, "sim/exchange_plate", Trigger.Request(), TIMEOUT_S)   # the first plate is marked
    assert fresh.success, fresh.message
    second = cell.call(Calibrate, "calibrate", Calibrate.Request(validate=False), CALIBRATE_TIMEOUT_S)
    assert second.fiducials_expected == 16, second.message
    assert second.success and second.neurons == 0, second.message
    assert cell.nodes["calibration_manager"].arrow_scale == 20.0
