"""Bad options of the command-line tools: exit 2 with a one-line message naming the problem, before any
work starts, and nothing written (gls-train, gls-sim-cell, gls-correct, gls-calibrate, gls-export)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from gls_calibration.cli import calibrate, export, sim_cell, train
from gls_calibration.cli.correct import main as correct_main
from gls_calibration.common.config_files import config_path
from gls_calibration.models.training import TrainingOptions
import test_offline_tools

calibration_file = test_offline_tools.calibration_file      # fixture: a TPS calibration over 190 mm


def files_in(folder: Path) -> list[str]:
    return sorted(str(path.relative_to(folder)) for path in folder.rglob("*"))


def measured_csv(folder: Path) -> Path:
    """12 measured fiducials, as test_train_tool.test_gls_train_unwritable_output_exits_2 writes them."""
    measured = folder / "measured.csv"
    grid = np.array([(x, y) for x in (-20.0, 0.0, 20.0, 40.0) for y in (-20.0, 0.0, 20.0)])
    measured.write_text("x_cmd,y_cmd,x_meas,y_meas\n" + "".join(f"{x},{y},{x * 1.001},{y}\n" for x, y in grid))
    return measured


@pytest.fixture
def no_training(monkeypatch):
    """Bad input must be refused before the training: fail the test if it starts."""
    def refuse(*args, **kwargs):
        raise AssertionError("the training ran")
    monkeypatch.setattr(train, "train_correction", refuse)


def exit_code(call) -> int:
    """The exit code of a tool's main(): its return value or argparse's SystemExit."""
    try:
        return call()
    except SystemExit as exit_:
        return exit_.code


# --- A: gls-train --out that is not a regular file ------------------------------------------------

@pytest.mark.parametrize("kind", ["device", "fifo", "directory", "symlink", "dot"])
def test_gls_train_refuses_an_output_that_is_not_a_regular_file_before_training(tmp_path, monkeypatch, capsys,
                                                                                no_training, kind):
    measured = measured_csv(tmp_path)
    out = {"device": Path("/dev/null"), "fifo": tmp_path / "pipe", "directory": tmp_path / "folder",
           "symlink": tmp_path / "link", "dot": Path(".")}[kind]
    if kind == "fifo":
        os.mkfifo(out)
    elif kind == "directory":
        out.mkdir()
    elif kind == "symlink":
        out.symlink_to(tmp_path / "elsewhere.yaml")
    monkeypatch.chdir(tmp_path)
    before = files_in(tmp_path)
    assert train.main(["--measured", str(measured), "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert "refused (outputs are written as regular files only)" in error and len(error.splitlines()) == 1, error
    assert files_in(tmp_path) == before
    assert not Path("/dev/null.report.md").exists()


@pytest.mark.parametrize("plane_z", ["490", "-26"])
def test_gls_train_refuses_a_plane_outside_the_focus_range_before_training(tmp_path, capsys, no_training, plane_z):
    # The calibration was written, and refused only when loaded (the plate cannot have been marked there).
    measured = measured_csv(tmp_path)
    before = files_in(tmp_path)
    assert train.main(["--measured", str(measured), "--out", str(tmp_path / "c.yaml"), "--plane-z", plane_z]) == 2
    assert (f"calibration plane z = {plane_z} mm lies outside the head's focus range (+-25 mm)"
            in capsys.readouterr().err)
    assert files_in(tmp_path) == before


def test_gls_train_refuses_a_report_path_that_is_not_a_regular_file(tmp_path, capsys, no_training):
    measured = measured_csv(tmp_path)
    (tmp_path / "c.yaml.report.md").mkdir()
    assert train.main(["--measured", str(measured), "--out", str(tmp_path / "c.yaml")]) == 2
    assert "c.yaml.report.md is not a regular file: refused" in capsys.readouterr().err
    assert not (tmp_path / "c.yaml").exists()


# --- D: gls-train --config --------------------------------------------------------------------------

@pytest.mark.parametrize("text", [
    "rbf_trainer:\n  ros__parameters:\n    spreads_mm: [5.0]\n    folds: 3\n",
    "/gls/rbf_trainer:\n  ros__parameters:\n    spreads_mm: [5.0]\n    folds: 3\n",
    "/**:\n  ros__parameters:\n    spreads_mm: [5.0]\n    folds: 3\n    grid: {per_side: 7}\n",
    # the node's own block wins over the one every node reads, as for the rbf_trainer node
    "/**:\n  ros__parameters:\n    spreads_mm: [9.0]\n    folds: 3\nrbf_trainer:\n  ros__parameters:\n"
    "    spreads_mm: [5.0]\n",
])
def test_gls_train_reads_the_trainer_parameters_by_wildcard_or_node_name(tmp_path, text):
    config = tmp_path / "trainer.yaml"
    config.write_text(text)
    options = train.training_options(config)
    assert (tuple(options.spreads_mm), options.folds) == ((5.0,), 3)
    assert options.mse_goals_mm2 == TrainingOptions().mse_goals_mm2


def test_gls_train_reads_the_package_parameter_file_as_the_node_does():
    assert train.training_options(config_path("gls.yaml")) == TrainingOptions()


@pytest.mark.parametrize("text, message", [
    ("x_cmd,y_cmd,x_meas,y_meas\n1,2,3,4\n", "expected a ROS parameter file '/**:' or 'rbf_trainer:'"),
    ("calibration_manager:\n  ros__parameters:\n    max_iterations: 2\n", "no trainer parameters found"),
    ("/**:\n  ros__parameters:\n    grid: {per_side: 7}\n", "no trainer parameters found"),
    ("rbf_trainer:\n  spreads_mm: [5.0]\n", "'rbf_trainer' must hold a mapping 'ros__parameters:'"),
    ("/**:\n  ros__parameters:\n    spread_mm: [5.0]\n", "unknown parameter(s) 'spread_mm' under '/**'"),
    ("rbf_trainer:\n  ros__parameters:\n    spreads_mm: [5.0]\n    grid: {per_side: 7}\n",
     "unknown parameter(s) 'grid.per_side' under 'rbf_trainer'"),
    ("rbf_trainer:\n  ros__parameters:\n    spreads_mm: []\n", "'spreads_mm' must be a non-empty list of numbers"),
    ("rbf_trainer:\n  ros__parameters:\n    folds: 1\n", "'folds' must be an integer >= 2"),
])
def test_gls_train_refuses_a_config_without_usable_trainer_parameters(tmp_path, capsys, no_training, text, message):
    measured = measured_csv(tmp_path)
    config = tmp_path / "trainer.yaml"
    config.write_text(text)
    before = files_in(tmp_path)
    assert train.main(["--measured", str(measured), "--out", str(tmp_path / "c.yaml"), "--config", str(config)]) == 2
    error = capsys.readouterr().err
    assert message in error and str(config) in error and len(error.splitlines()) == 1, error
    assert files_in(tmp_path) == before


# --- B: gls-sim-cell ---------------------------------------------------------------------------------

@pytest.fixture
def no_cell(monkeypatch):
    """Bad arguments must be refused before the cell starts: fail the test if rclpy is initialised."""
    def refuse(*args, **kwargs):
        raise AssertionError("the cell started")
    monkeypatch.setattr(sim_cell.rclpy, "init", refuse)


@pytest.mark.parametrize("options, message", [
    (["--seed", "-1"], "--seed must be between 0 and 2147483647, got -1"),
    (["--timeout", "nan"], "argument --timeout: must be a positive number of seconds, got 'nan'"),
    (["--timeout", "-5"], "argument --timeout: must be a positive number of seconds, got '-5'"),
    (["--timeout", "0"], "argument --timeout: must be a positive number of seconds, got '0'"),
    (["--iterations", "4"], "--iterations must be between 1 and 3 (the manager's max_iterations), got 4"),
    (["--iterations", "0"], "--iterations must be between 1 and 3"),
    (["--grid", "102"], "--grid must be between 3 and 101, got 102"),
    # --iterations against a max_iterations override of the manager
    (["--iterations", "3", "--ros-args", "-p", "max_iterations:=2"],
     "--iterations must be between 1 and 2 (the manager's max_iterations, set by -p max_iterations:=2), got 3"),
    (["--iterations", "3", "--ros-args", "--param", "max_iterations:=2"], "between 1 and 2"),
    # a node-prefixed rule beats the others, but rcl applies it only to a manager in the root namespace
    (["--iterations", "5", "--ros-args", "-p", "calibration_manager:max_iterations:=5"], "between 1 and 3"),
    (["--namespace", "/", "--iterations", "4", "--ros-args", "-p", "calibration_manager:max_iterations:=3",
      "-p", "max_iterations:=5"], "between 1 and 3 (the manager's max_iterations, set by -p calibration_manager:"),
    (["--ros-args", "-p", "max_iterations:=abc"],
     "--ros-args -p max_iterations:=abc: the manager's max_iterations must be an integer between 1 and 10, got 'abc'"),
    (["--ros-args", "-p", "max_iterations:=2.0"], "max_iterations must be an integer between 1 and 10, got '2.0'"),
    (["--ros-args", "-p", "max_iterations:=11"], "max_iterations must be an integer between 1 and 10, got '11'"),
    (["--ros-args", "-p", "max_iterations:=0"], "max_iterations must be an integer between 1 and 10, got '0'"),
])
def test_gls_sim_cell_refuses_bad_options_before_starting_or_creating_anything(tmp_path, capsys, no_cell,
                                                                               options, message):
    out = tmp_path / "cell"
    assert exit_code(lambda: sim_cell.main(["--out", str(out), *options])) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("below", ["", "s1"])
def test_gls_sim_cell_refuses_an_out_that_cannot_be_a_folder(tmp_path, capsys, no_cell, below):
    regular = tmp_path / "regfile"
    regular.write_text("keep")
    out = regular / below if below else regular
    assert exit_code(lambda: sim_cell.main(["--out", str(out)])) == 2
    error = capsys.readouterr().err
    assert (f"{regular} is not a folder" if below else f"--out {regular} exists and is not a folder") in error
    assert regular.read_text() == "keep" and files_in(tmp_path) == ["regfile"]


def test_gls_sim_cell_help_and_validation_agree_on_the_iterations(tmp_path, capsys):
    with pytest.raises(SystemExit):
        sim_cell.parse_args(["--help"])
    assert "1 to 3" in " ".join(capsys.readouterr().out.split())
    assert sim_cell.parse_args(["--out", str(tmp_path / "cell"), "--iterations", "3"]).iterations == 3
    assert not (tmp_path / "cell").exists()


# --- C: gls-correct and gls-calibrate --timeout ------------------------------------------------------

@pytest.mark.parametrize("timeout", ["-1", "nan", "inf", "0"])
def test_gls_correct_refuses_a_bad_timeout_before_asking_the_cell(tmp_path, capsys, monkeypatch, timeout):
    import gls_calibration.cli.correct as correct

    def refuse(*args, **kwargs):
        raise AssertionError("the service was asked")
    monkeypatch.setattr(correct, "correct_by_service", refuse)
    targets = tmp_path / "targets.csv"
    targets.write_text("x,y\n0,0\n")
    assert exit_code(lambda: correct_main([str(targets), "--out", str(tmp_path / "o.csv"), "--timeout", timeout])) == 2
    assert f"argument --timeout: must be a positive number of seconds, got '{timeout}'" in capsys.readouterr().err
    assert files_in(tmp_path) == ["targets.csv"]


def test_gls_correct_help_describes_namespace_and_timeout(capsys):
    assert exit_code(lambda: correct_main(["--help"])) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "namespace of the cell's correction node" in text
    assert "give up on the correction service after this (s, default 30" in text


def test_gls_calibrate_shares_the_timeout_check(capsys):
    assert exit_code(lambda: calibrate.main(["--timeout", "nan"])) == 2
    assert "argument --timeout: must be a positive number of seconds, got 'nan'" in capsys.readouterr().err


# --- E: gls-export --pitch ---------------------------------------------------------------------------

@pytest.mark.parametrize("pitch, heights, message", [
    ("0.01", ["0"], "table would have 361,038,001 points (limit 1,000,000"),
    ("0.05", ["0"], "table would have 14,447,601 points (limit 1,000,000"),
    ("0.5", ["0", "1", "2", "3", "4", "5", "6"], "table would have 1,016,127 points"),
    ("1e-300", ["0"], "table would have more than 10^24 points"),
])
def test_gls_export_refuses_a_table_too_large_before_allocating_it(tmp_path, capsys, monkeypatch,
                                                                   calibration_file, pitch, heights,  # noqa: F811
                                                                   message):
    def refuse(*args, **kwargs):
        raise AssertionError("the table was allocated")
    monkeypatch.setattr(export, "table_axes", refuse)
    out = tmp_path / "export"
    assert export.main(["--calibration", str(calibration_file), "--out", str(out), "--pitch", pitch,
                        "--z", *heights]) == 2
    error = capsys.readouterr().err
    assert message in error and "choose a larger --pitch" in error and len(error.splitlines()) == 1, error
    assert not out.exists()


def test_gls_export_refuses_a_pitch_that_leaves_no_cell_inside_the_field(tmp_path, capsys,
                                                                         calibration_file):  # noqa: F811
    out = tmp_path / "export"
    assert export.main(["--calibration", str(calibration_file), "--out", str(out), "--pitch", "1000"]) == 2
    error = capsys.readouterr().err
    assert ("--pitch 1000 mm leaves no table cell inside the calibrated field (190 x 190 mm)" in error
            and len(error.splitlines()) == 1), error
    assert not out.exists()


# --- F: gls-sim-cell --iterations against a max_iterations the ROS arguments set -------------------------

@pytest.mark.parametrize("ros, iterations", [
    (["-p", "max_iterations:=5"], "5"),
    (["--param", "max_iterations:=5"], "4"),
    (["-p", "max_iterations:=2", "-p", "max_iterations:=6"], "6"),     # the last rule wins, as for rcl
])
def test_gls_sim_cell_takes_the_iterations_a_max_iterations_override_allows(tmp_path, no_cell, ros, iterations):
    args = sim_cell.parse_args(["--out", str(tmp_path / "cell"), "--iterations", iterations, "--ros-args", *ros])
    assert args.iterations == int(iterations) and not (tmp_path / "cell").exists()


@pytest.mark.parametrize("options", [
    ["--iterations", "5", "--ros-args", "-p", "max_iterations:=5"],
    ["--iterations", "2", "--ros-args", "--param", "max_iterations:=2"],
    ["--namespace", "/", "--iterations", "4", "--ros-args", "-p", "calibration_manager:max_iterations:=4",
     "-p", "max_iterations:=2"],
    ["--iterations", "3", "--ros-args", "-p", "calibration_manager:max_iterations:=7"],
])
def test_gls_sim_cell_and_its_manager_read_the_same_max_iterations(tmp_path, options):
    # the manager started with the cell's ROS arguments, as main() gives them: its limit is the tool's
    from gls_calibration.nodes.calibration_manager import CalibrationManager
    args = sim_cell.parse_args(["--out", str(tmp_path / "cell"), *options])
    context = sim_cell.rclpy.Context()
    cell_arguments = sim_cell.ros_arguments(args, tmp_path / "store", tmp_path)
    sim_cell.rclpy.init(args=cell_arguments + ["--", *args.user_ros_arguments], context=context)
    try:
        manager = CalibrationManager(context=context, namespace=sim_cell.cell_namespace(args))
        assert manager.settings.max_iterations == sim_cell.iterations_limit(sim_cell.manager_parameter_override(
            args.user_ros_arguments, sim_cell.cell_namespace(args), "max_iterations"))
        manager.destroy_node()
    finally:
        context.try_shutdown()


def test_gls_sim_cell_help_names_the_max_iterations_override(capsys):
    with pytest.raises(SystemExit):
        sim_cell.parse_args(["--help"])
    assert "or N when '--ros-args -p max_iterations:=N' sets it" in " ".join(capsys.readouterr().out.split())


# --- G: one table of the trainer's parameters, read by the node and by gls-train --config --------------------

def trainer_config(folder: Path, line: str) -> Path:
    config = folder / "trainer.yaml"
    config.write_text(f"rbf_trainer:\n  ros__parameters:\n    {line}\n")
    return config


def start_trainer(config: Path):
    """The rbf_trainer node started with ``config`` as its parameter file (the cell's way); shut down by the caller."""
    from gls_calibration.nodes.rbf_trainer import RbfTrainerNode
    context = sim_cell.rclpy.Context()
    sim_cell.rclpy.init(args=["node", "--ros-args", "--params-file", str(config)], context=context)
    try:
        return RbfTrainerNode(context=context, namespace="")
    except Exception:
        context.try_shutdown()
        raise


def test_the_trainer_node_declares_the_table_of_its_parameters(ros_context):
    from gls_calibration.common.parameter_specs import FLOAT_LIMITS, INTEGER_LIMITS
    from gls_calibration.models.training import TRAINER_PARAMETERS
    from gls_calibration.nodes.rbf_trainer import RbfTrainerNode
    node = RbfTrainerNode(context=ros_context)
    try:
        declared = {name for name in node._parameters
                    if not name.startswith("head.") and name not in ("use_sim_time", "start_type_description_service")}
        assert declared == {spec.name for spec in TRAINER_PARAMETERS}
        for spec in TRAINER_PARAMETERS:
            descriptor = node.describe_parameter(spec.name)
            assert (descriptor.description, descriptor.read_only) == (spec.description, True), spec.name
            assert node.get_parameter(spec.name).value == spec.default, spec.name
            ranges = [(r.from_value, r.to_value) for r in (*descriptor.integer_range, *descriptor.floating_point_range)]
            assert ranges == ([spec.bounds] if spec.bounds else []), spec.name
            if spec.kind == "integer" and spec.bounds:
                assert descriptor.integer_range and spec.bounds[1] <= INTEGER_LIMITS[1]
            if spec.kind == "number" and spec.bounds:
                assert descriptor.floating_point_range and spec.bounds[1] <= FLOAT_LIMITS[1]
    finally:
        node.destroy_node()


@pytest.mark.parametrize("line, message", [
    ("seed: 2147483648", "trainer parameter 'seed' must be at most 2147483647, got 2147483648"),
    ("cv_block_mm: 1.7e+308", "trainer parameter 'cv_block_mm' must be at most 1e+308, got 1.7e+308"),
    ("cv_block_mm: .inf", "trainer parameter 'cv_block_mm' must be a finite number, got inf"),
    ("cv_block_mm: 5", "trainer parameter 'cv_block_mm' must be a floating-point number"),
    ("spreads_mm: [25, 35]", "trainer parameter 'spreads_mm' must be a list of floating-point numbers"),
    ("folds: 3\n    max_points: 2", "trainer parameter 'max_points' must be an integer >= 3, got 2"),
])
def test_gls_train_and_the_trainer_node_refuse_the_same_values(tmp_path, capsys, no_training, line, message):
    config = trainer_config(tmp_path, line)
    with pytest.raises(Exception):
        start_trainer(config)
    measured = measured_csv(tmp_path)
    assert train.main(["--measured", str(measured), "--out", str(tmp_path / "c.yaml"), "--config", str(config)]) == 2
    error = capsys.readouterr().err
    assert message in error and len(error.splitlines()) == 1, error
    assert not (tmp_path / "c.yaml").exists()


@pytest.mark.parametrize("line", ["tps_smoothings: []", "seed: 2147483647", "cv_block_mm: 1.0e+308"])
def test_gls_train_and_the_trainer_node_take_the_same_values(tmp_path, line):
    config = trainer_config(tmp_path, line)
    node = start_trainer(config)
    try:
        assert node.options == train.training_options(config)
    finally:
        context = node.context
        node.destroy_node()
        context.try_shutdown()


# --- node parameters a node refuses at start (issue 31, item 8): a message and exit 2, nothing spun ------

@pytest.mark.parametrize("rule, message", [
    # rcl keeps the parameter file's value for a rule of another type: gls-sim-cell checks the rule first
    ("grid.size_mm:=abc", "--ros-args -p grid.size_mm:=abc: the manager's grid.size_mm must be a finite "
                          "floating-point number (write 5.0 for 5), got 'abc'"),
    ("grid.ring_radii_mm:=[]", "the manager's grid.ring_radii_mm must be a non-empty list of finite floating-point "
                               "numbers, got []"),
    ("grid.per_side:=2", "the manager's grid.per_side must be between 3 and 101, got 2"),
    ("calibration_manager:sweep.placed_by_pose:=1", "the manager's sweep.placed_by_pose must be true or false, got 1"),
])
def test_gls_sim_cell_refuses_a_manager_parameter_rule_of_the_wrong_type(tmp_path, capsys, no_cell, rule, message):
    out = tmp_path / "cell"
    assert exit_code(lambda: sim_cell.main(["--namespace", "/", "--out", str(out), "--ros-args", "-p", rule])) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("rule, message", [
    ("grid.ring_radii_mm:=[2.7,2.5]", "ring_radii_mm must be one or more positive finite radii in increasing order"),
    ("head_direction:=[0.0,0.0,0.0]",
     "parameter head_direction: 3 finite numbers, not all zero, are needed, got [0.0, 0.0, 0.0]"),
    ("head_direction:=[1.0]", "parameter head_direction: 3 finite numbers, not all zero, are needed, got [1.0]"),
    ("scanner_to_gls.translation_mm:=[0.0,325.0]",
     "parameter scanner_to_gls.translation_mm: 3 finite numbers are needed, got [0.0, 325.0]"),
    # rcl drops these rules without a word (the files set them): the nodes check what they hold
    ("head_direction:=[]", "plate_pose: parameter head_direction: the rule -p head_direction:=[] was not applied"),
    ("effects.galvo_gain_x:=[]",
     "parameter effects.galvo_gain_x: the rule -p effects.galvo_gain_x:=[] was not applied"),
    ("head.working_distance_mm:=480.0", "parameter head.working_distance_mm: the rule -p "
                                        "head.working_distance_mm:=480.0 was not applied"),
])
def test_gls_sim_cell_refuses_a_node_parameter_at_start_with_exit_2(tmp_path, capsys, monkeypatch, rule, message):
    """A value of the right type that a node refuses when it is built: said, exit 2, no calibration."""
    def refuse(*args, **kwargs):
        raise AssertionError("the calibration started")
    monkeypatch.setattr(sim_cell, "run_calibration", refuse)
    out = tmp_path / "cell"
    assert sim_cell.main(["--out", str(out), "--no-reference-check", "--grid", "3", "--ros-args", "-p", rule]) == 2
    err = capsys.readouterr().err
    assert "gls-sim-cell: " in err and message in err, err


@pytest.mark.parametrize("module, rule, message", [
    ("calibration_manager", "grid.size_mm:=abc", "expecting type 'DOUBLE'"),
    ("calibration_manager", "grid.ring_radii_mm:=[]", "parameter grid.ring_radii_mm: a non-empty list"),
    ("plate_pose", "head_direction:=[0.0,0.0,0.0]", "parameter head_direction: 3 finite numbers, not all zero"),
    ("plate_pose", "head_direction:=[1.0]", "parameter head_direction: 3 finite numbers, not all zero"),
])
def test_a_node_console_script_refuses_a_bad_parameter_at_start_with_exit_2(tmp_path, capsys, module, rule, message):
    import importlib
    main = importlib.import_module(f"gls_calibration.nodes.{module}").main
    assert main(["node", "--ros-args", "-p", f"calibration_dir:={tmp_path}", "-p", rule]) == 2
    assert message in capsys.readouterr().err
