"""Issue 31 item 8: a node started with the package's parameter files and a ``-p`` rule that rcl drops
without a word (another type than the file's, ``[]``, a parameter two files set) stops at start with
exit 2 and a message naming the parameter, instead of running with the file's value."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from gls_calibration.common.config_files import config_path
from gls_calibration.ros.parameter_rules import parameter_rules, rule_applied

START_LIMIT_S = 60.0     # a node that starts instead of refusing is stopped here and the test fails


@pytest.mark.parametrize("text, held, applied", [
    ("abc", 190.0, False), ("190.0", 190.0, True), ("1.9e2", 190.0, True), ("150.0", 190.0, False),
    ("[]", [2.5, 2.7], False), ("[]", None, True), ("[2.5, 2.7]", [2.5, 2.7], True), ("[2.5]", [2.5, 2.7], False),
    ("[1e3, .inf]", [1000.0, float("inf")], True), ("abc", [2.5], False),
    ("true", True, True), ("1", True, False), ("abc", 3, False), ("0x10", 16, True),
    ("m", "m", True), ("'mm'", "mm", True), ("mm", "m", False), ("[.nan]", [float("nan")], True),
])
def test_a_rule_is_applied_only_when_the_node_holds_its_value(text, held, applied):
    assert rule_applied(text, held) is applied


def test_rules_are_read_only_from_the_ros_arguments():
    argv = ["node", "-p", "a:=1", "--ros-args", "-p", "b:=2", "--param", "c:=3", "-r", "x:=y", "--", "-p", "d:=4"]
    assert parameter_rules(argv) == ["b:=2", "c:=3"]


def files(*names: str) -> list[str]:
    return [argument for name in names for argument in ("--params-file", str(config_path(name)))]


@pytest.mark.parametrize("module, parameter_files, rule", [
    ("calibration_manager", ("head.yaml", "gls.yaml"), "grid.size_mm:=abc"),
    ("calibration_manager", ("head.yaml", "gls.yaml"), "grid.ring_radii_mm:=[]"),
    ("fiducial_measurement", ("gls.yaml",), "grid.ring_radii_mm:=[]"),
    ("plate_pose", ("gls.yaml",), "head_direction:=[]"),
    ("correction", ("head.yaml", "sim.yaml"), "head.working_distance_mm:=480.0"),    # set by both files
    ("sim_scanner", ("sim.yaml",), "effects.galvo_gain_x:=[]"),
    ("sim_galvo", ("sim.yaml",), "seed:=abc"),
])
def test_a_node_refuses_a_rule_that_rcl_dropped_with_exit_2(tmp_path, module, parameter_files, rule):
    command = [sys.executable, "-c", f"import sys; from gls_calibration.nodes.{module} import main; sys.exit(main())",
               "--ros-args", *files(*parameter_files), "-p", f"calibration_dir:={tmp_path}", "-p", rule]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=START_LIMIT_S, env=os.environ.copy())
    except subprocess.TimeoutExpired:
        pytest.fail(f"{module} started with -p {rule} (the rule was dropped) instead of refusing it")
    name = rule.partition(":=")[0]
    assert done.returncode == 2, done.stderr
    assert f"parameter {name}: the rule -p {rule} was not applied" in done.stderr, done.stderr


def test_a_node_takes_rules_of_the_right_type_over_the_parameter_files(tmp_path):
    from gls_calibration.nodes.calibration_manager import CalibrationManager
    from gls_calibration.ros.parameter_rules import unapplied_rule_problem
    import rclpy
    from rclpy.context import Context
    rules = ["-p", f"calibration_dir:={tmp_path}", "-p", "grid.size_mm:=150.0", "-p", "grid.ring_radii_mm:=[2.0, 2.2]",
             "-p", "sweep.placed_by_pose:=false", "-p", "other_node:grid.size_mm:=abc"]
    argv = ["node", "--ros-args", *files("head.yaml", "gls.yaml"), *rules]
    context = Context()
    rclpy.init(args=argv, context=context)
    try:
        node = CalibrationManager(context=context)
        try:
            assert node.get_parameter("grid.size_mm").value == 150.0
            assert unapplied_rule_problem(node, argv) == ""
        finally:
            node.destroy_node()
    finally:
        context.try_shutdown()
