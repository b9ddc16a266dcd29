"""The sweep plan: parsing, cell time, and the calibrate flow combining reversed and turned sweeps."""
import asyncio
import dataclasses

import numpy as np
import pytest

from gls_calibration.calibration import procedure
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.fiducials.measure import FiducialMeasurement
from gls_calibration.registration.rigid import RigidTransform
from gls_calibration.registration.sweep_plan import (CellTimeModel, SweepPass, combine_sweeps, parse_plan,
                                                     plan_label)
from gls_calibration.scan.plate_pose import estimate_plate_pose
from gls_calibration.scan.sweep import nominal_start_pose, sweep_middle_mm
from gls_calibration.simulation.direct_cell import DirectCell
from gls_calibration.simulation.world import SimulatedCell, load_sim_config


def test_a_plan_reads_and_writes_back():
    plan = parse_plan(" 0+, 0-,90+ ,90-")
    assert plan == (SweepPass(1, 0.0), SweepPass(-1, 0.0), SweepPass(1, 90.0), SweepPass(-1, 90.0))
    assert plan_label(plan) == "0+,0-,90+,90-"


@pytest.mark.parametrize("text, message", [
    ("", "must be an orientation"),
    ("0", "must be an orientation"),
    ("x+", "is not a number"),
    ("30+", "orientation must be 0, 45 or 90"),
    ("0+,,90-", "must be an orientation"),
])
def test_a_bad_plan_is_refused_with_the_item_named(text, message):
    with pytest.raises(ValueError, match=message):
        parse_plan(text)


def test_the_cell_time_counts_sweeps_moves_and_marking():
    model = CellTimeModel(sweep_length_mm=200.0, sweep_speed_mm_s=20.0, robot_move_s=5.0)
    assert model.plate_s(8, marking_s=30.0) == pytest.approx(8 * (10.0 + 5.0) + 30.0)


def small_cell(tmp_path, preset, robot_repeats=True):
    config = load_sim_config(preset=preset)
    chain = config.measurement if robot_repeats else dataclasses.replace(
        config.measurement, robot_scale_error=0.0, robot_along_error_mm=0.0, robot_path_error_mm=0.0)
    config = dataclasses.replace(config, scanner=dataclasses.replace(config.scanner, line_length_mm=120.0),
                                 sweep_length_mm=110.0, scanner_to_gls=None, seed=3, measurement=chain)
    return DirectCell(SimulatedCell(config), CalibrationStore(tmp_path / "store"))


def measurement_error_rms(run):
    """RMS of MEASURED minus TRUE deviations, their common shift removed (mm)."""
    difference = run.deviations - run.true_deviations
    difference -= difference.mean(axis=0)
    return float(np.sqrt(np.mean(np.sum(difference ** 2, axis=1))))


def test_reversed_and_turned_sweeps_measure_the_plate_better_than_one(tmp_path):
    grid_xy = grid_targets(7, 90.0)
    errors, runs = {}, {}
    for label in ("0+", "0+,0-,90+,90-"):
        for repeats in (False, True):
            cell = small_cell(tmp_path / f"{label}{repeats}", "paper_like", robot_repeats=repeats)
            settings = cell.settings(grid_per_side=7, grid_size_mm=90.0, plain_sweeps=1, plain_sweep_step_mm=2.0,
                                     sweep_plan=parse_plan(label))
            runs[label, repeats] = asyncio.run(procedure.run_plate(cell, settings, grid_xy, lambda *_: None,
                                                                   (0.0, 1.0), True))
            errors[label, repeats] = measurement_error_rms(runs[label, repeats])
    # errors drawn anew per sweep and fixed to the scanner frame are separated ...
    assert errors["0+,0-,90+,90-", False] < 0.6 * errors["0+", False], errors
    # ... the robot's errors that repeat on every run of a line are not: the plan measures worse with them
    assert errors["0+,0-,90+,90-", True] > 1.5 * errors["0+,0-,90+,90-", False], errors
    runs = {label: runs[label, True] for label in ("0+", "0+,0-,90+,90-")}
    full = runs["0+,0-,90+,90-"]
    assert full.sweep_plan == "0+,0-,90+,90-" and full.fiducials_found == 49
    assert np.isfinite(full.scanner_error_rms_mm) and np.isfinite(full.motion_error_rms_mm)
    assert np.all(np.isfinite(full.sigma_mm)) and np.all(full.sigma_mm > 0)
    # three sweeps more cost three sweeps and robot moves more (the marking is the same)
    single = runs["0+"]
    sweep_s = settings.cell_time.sweep_length_mm / settings.cell_time.sweep_speed_mm_s   # the small cell's 110 mm
    assert full.cell_time_s - single.cell_time_s == pytest.approx(3 * (sweep_s + settings.cell_time.robot_move_s),
                                                                  rel=0.05)


def _found(centres: np.ndarray) -> FiducialMeasurement:
    """A sweep's centres (N, 3) as the fiducial measurement states them, sigma 1 um."""
    pose = estimate_plate_pose(np.column_stack([np.random.default_rng(3).uniform(-100, 100, (2000, 2)),
                                                np.zeros(2000)]))
    count = len(centres)
    return FiducialMeasurement(centres=centres, centres_plane=pose.to_plane(centres), quality=np.full(count, 0.001),
                               radii=np.full(count, 2.7), inner_radii=np.full(count, 2.5), merged=0, rejected=0,
                               missing=0, image_shape=(10, 10), pixel_pitch_mm=(0.1, 0.1),
                               sigma_xy_mm=np.full((count, 2), 0.001))


@pytest.mark.parametrize("plan", ["0+,0-,90+,90-", "0+,90+,45+"])
def test_the_lateral_error_is_taken_where_it_lies_on_the_sensors_line(plan):
    """The scanner's lateral linearity error is a function of the position on its laser line, measured
    from the sweep's middle, about which every pass turns the sensor (``sweep_middle_mm``); every pass
    sees it there, so the turned passes separate it from the marks. Measured from another origin, a
    turned pass reads the same place of the line at another coordinate, and the marks keep the error."""
    length_mm = 200.0
    side = np.linspace(-90.0, 90.0, 13)
    marks = np.array([(x, 100.0 + y, 0.0) for y in side for x in side])       # B frame, around the middle
    rng = np.random.default_rng(11)

    def lateral_error_mm(u):
        return 0.03 * np.sin(u / 25.0) + 0.02 * np.cos(u / 11.0)              # no polynomial: not a placement

    passes = parse_plan(plan)
    measurements = []
    for item in passes:
        line = nominal_start_pose(length_mm, item.direction, item.orientation_deg)[:2, 0]   # the laser line in B
        u = (marks[:, :2] - sweep_middle_mm(length_mm)) @ line
        seen = np.abs(u) <= 100.0                                                # the sensor's 200 mm line
        measured = marks[seen].copy()
        measured[:, :2] += lateral_error_mm(u[seen])[:, None] * line + rng.normal(0.0, 0.001, (seen.sum(), 2))
        measurements.append(_found(measured))

    def error_rms(sweep_length_mm):
        combined = combine_sweeps(measurements, passes, marks, RigidTransform.identity(), True,
                                  sweep_length_mm=sweep_length_mm)
        error = combined.centres_xy - marks[combined.target_index, :2]
        error -= error.mean(axis=0)
        return float(np.sqrt(np.mean(np.sum(error ** 2, axis=1))))

    assert error_rms(length_mm) < 0.004
    assert error_rms(0.5 * length_mm) > 2.0 * error_rms(length_mm)      # a middle 50 mm off: part of it stays


@pytest.mark.parametrize("length", [float("nan"), float("inf"), 0.0, -200.0])
def test_a_sweep_length_that_has_no_middle_is_refused(length):
    """The separation measures every sweep from half its length: NaN or infinity would be passed on."""
    with pytest.raises(ValueError, match=r"^cell_time\.sweep_length_mm must be a positive finite number, got "):
        procedure.ProcedureSettings(cell_time=CellTimeModel(sweep_length_mm=length))


@pytest.mark.parametrize("text", [".nan", ".inf", "0", "-200.0"])
def test_gls_yaml_sweep_length_is_checked_where_the_tools_read_it(tmp_path, monkeypatch, text):
    from gls_calibration.cli import sim_record

    (tmp_path / "gls.yaml").write_text(f"calibration_manager:\n  ros__parameters:\n    sweep:\n"
                                       f"      length_mm: {text}\n")
    monkeypatch.setattr(sim_record, "config_path", lambda name: tmp_path / name)
    with pytest.raises(ValueError, match=r"^sweep\.length_mm of config/gls\.yaml must be a positive finite number"):
        sim_record.sweep_length_mm()
