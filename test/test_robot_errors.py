"""The simulated robot reports its pose as a real arm does: errors that repeat per programmed line.

The difference between the reported (encoder) pose and the true one has a repeating part -- a
function of where the arm is, the same on every run of the same line and direction -- and a part
drawn anew for every sweep. These tests check both parts through ``LaserLineScanner._placement``
(reported travel, true travel, across, height) and through what a sweep placed by pose measures.
"""
from dataclasses import replace

import numpy as np
import pytest

from gls_calibration.simulation.measurement import (FIELD_HALF_SPAN_MM, PRESET_CHAINS, ROBOT_REPEATING_LIMIT_MM,
                                                    MeasurementChain, smooth_field)
from gls_calibration.simulation.scanner import LaserLineScanner, ScannerSettings
from gls_calibration.simulation.world import load_sim_config, sim_config_from_dict

QUIET = ScannerSettings(line_length_mm=60.0, z_noise_mm=0.0, linearity_mm=0.0, speckle=0.0, dropout_fraction=0.0,
                        path_repeatability_mm=0.0)
ROWS, STEP = 2001, 0.1
REPEATING = MeasurementChain(robot_scale_error=2e-4, robot_along_error_mm=0.05, robot_along_correlation_mm=20.0,
                             robot_path_error_mm=0.03, robot_path_correlation_mm=30.0)


def error_of(scanner: LaserLineScanner, seed: int, direction: int = 1, orientation: float = 0.0, step: float = STEP):
    """(true - reported travel, across, height) of one sweep (mm), and the reported travel."""
    rows = int(round((ROWS - 1) * STEP / step)) + 1
    reported, true, across, height = scanner._placement(seed, rows, step, direction=direction,
                                                        orientation_deg=orientation)
    return true - reported, across, height, reported


def test_the_repeating_part_is_the_same_on_every_run_of_a_line():
    scanner = LaserLineScanner(QUIET, chain=REPEATING, robot_seed=4)
    first, second = error_of(scanner, seed=1), error_of(scanner, seed=2)
    for one, other in zip(first[:3], second[:3]):
        assert np.abs(one).max() > 0.01                    # not trivially small
        assert np.allclose(one, other, atol=1e-12)         # nothing per sweep in this chain
    # a new robot (another cell seed) has another field
    other_robot = error_of(LaserLineScanner(QUIET, chain=REPEATING, robot_seed=5), seed=1)
    assert np.abs(other_robot[0] - first[0]).max() > 0.01


def test_it_is_a_function_of_where_the_arm_is_not_of_the_sweep_step():
    scanner = LaserLineScanner(QUIET, chain=REPEATING, robot_seed=4)
    fine, coarse = error_of(scanner, seed=1), error_of(scanner, seed=2, step=0.5)
    # the coarse sweep's profiles stand where every fifth fine profile stands
    for one, other in zip(fine[:3], coarse[:3]):
        assert np.allclose(one[::5], other, atol=1e-12)


def test_each_direction_and_orientation_has_its_own_error():
    scanner = LaserLineScanner(QUIET, chain=REPEATING, robot_seed=4)
    forward = error_of(scanner, seed=1)[0]
    backward = error_of(scanner, seed=1, direction=-1)[0][::-1]       # the same positions, run backwards
    turned = error_of(scanner, seed=1, orientation=90.0)[0]
    assert np.abs(forward - backward).max() > 0.01 and np.abs(forward - turned).max() > 0.01


def test_the_per_sweep_part_is_drawn_anew_and_the_repeating_part_stays():
    chain = replace(REPEATING, path_wander_mm=0.02, path_wander_correlation_mm=20.0, robot_along_wander_mm=0.01)
    scanner = LaserLineScanner(QUIET, chain=chain, robot_seed=4)
    repeating = error_of(LaserLineScanner(QUIET, chain=REPEATING, robot_seed=4), seed=1)
    runs = [error_of(scanner, seed) for seed in range(1, 41)]
    along = np.array([run[0] for run in runs])
    across = np.array([run[1] for run in runs])
    # the average over many runs converges to the repeating part, not to zero
    assert np.sqrt(np.mean((along.mean(axis=0) - repeating[0]) ** 2)) < 0.004
    assert np.sqrt(np.mean((across.mean(axis=0) - repeating[1]) ** 2)) < 0.008
    # and the spread about it is the per-sweep part's size
    assert np.std(along - repeating[0]) == pytest.approx(0.01, rel=0.35)
    assert np.std(across - repeating[1]) == pytest.approx(0.02, rel=0.35)


def test_field_statistics_over_many_robots():
    values = np.array([smooth_field(np.random.default_rng(seed), 0.05, 20.0)(np.array([[0.0, 0.0], [20.0, 0.0],
                                                                                       [0.0, 20.0]]))
                       for seed in range(300)])
    assert values.std() == pytest.approx(0.05, rel=0.1)
    # Gaussian autocorrelation exp(-d^2 / 2 L^2) at d = L, in x and in y alike
    for lag in (1, 2):
        assert np.mean(values[:, 0] * values[:, lag]) / values[:, 0].var() == pytest.approx(np.exp(-0.5), abs=0.1)
    with pytest.raises(ValueError, match="outside the simulated robot's field"):
        smooth_field(np.random.default_rng(1), 0.05, 20.0)(np.array([[FIELD_HALF_SPAN_MM, 0.0]]))
    scales = [LaserLineScanner(QUIET, chain=REPEATING, robot_seed=seed)._robot_field(3, 1, 0.0) for seed in range(400)]
    assert np.std(scales) == pytest.approx(2e-4, rel=0.12)


def test_placement_by_pose_no_longer_removes_the_travel_error():
    """Placing by the reported pose removes the timing errors, not the repeating reported-vs-true error."""
    from gls_calibration.simulation.plate import Plate, PlateSettings
    scanner = LaserLineScanner(QUIET, chain=REPEATING, robot_seed=4)
    data = scanner.sweep_data(Plate(PlateSettings(texture_std=0.0)), 200.0, seed=3)
    reported_travel = data.reported_poses[:, 1, 3] - data.reported_poses[0, 1, 3]
    along = error_of(scanner, seed=3)[0]
    # the encoder travel is the nominal one (no timing error in this chain) ...
    assert np.allclose(reported_travel, np.arange(ROWS) * STEP, atol=1e-9)
    # ... while the sensor truly stands off it by the repeating error
    assert np.abs(along).max() > 0.02


def test_presets_carry_the_robot_and_careful_a_third_of_it():
    paper, careful = PRESET_CHAINS["paper_like"], PRESET_CHAINS["careful"]
    assert paper.robot_repeats and not PRESET_CHAINS["ideal"].robot_repeats
    for key in ("robot_scale_error", "robot_along_error_mm", "robot_path_error_mm", "robot_along_wander_mm"):
        assert getattr(paper, key) > 0.0
        assert getattr(careful, key) == pytest.approx(getattr(paper, key) / 3.0)
    assert careful.robot_along_correlation_mm == paper.robot_along_correlation_mm
    # one robot per simulated cell: the calibration's sweeps and the reference check share it
    config = load_sim_config(preset="paper_like")
    first, second = config.make_scanner(), config.make_scanner()
    assert first.robot_seed == second.robot_seed == config.seed
    points = np.array([[0.0, 10.0], [0.0, 150.0], [-60.0, 100.0]])
    for component in (0, 1, 2):
        assert np.array_equal(first._robot_field(component, 1, 0.0)(points),
                              second._robot_field(component, 1, 0.0)(points))


@pytest.mark.parametrize("block, message", [
    ({"robot_along_error_mm": -0.01, "robot_along_correlation_mm": 20.0},
     "measurement.robot_along_error_mm must be non-negative"),
    ({"robot_path_error_mm": float("nan"), "robot_path_correlation_mm": 20.0},
     "measurement.robot_path_error_mm must be a finite number"),
    ({"robot_along_error_mm": 0.05}, "measurement.robot_along_correlation_mm must be positive"),
    ({"robot_along_wander_mm": 0.05}, "measurement.path_wander_correlation_mm must be positive"),
    ({"robot_scale_error": -1e-4}, "measurement.robot_scale_error must be non-negative"),
    ({"robot_along_error_mm": 0.08, "robot_along_correlation_mm": 20.0, "robot_path_error_mm": 0.06,
      "robot_path_correlation_mm": 20.0}, "add up to 0.1 mm, above 0.09 mm"),
    ({"robot_scale_error": 1e-3}, "measurement.robot_scale_error"),
])
def test_bad_robot_parameters_are_refused_naming_the_key(block, message):
    with pytest.raises(ValueError, match=message):
        sim_config_from_dict({"measurement": {"preset": "custom", **block}})


def test_the_limit_is_the_top_of_the_published_band():
    assert ROBOT_REPEATING_LIMIT_MM == pytest.approx(0.09)
    # at the limit it is accepted, just above it refused
    sim_config_from_dict({"measurement": {"preset": "custom", "robot_along_error_mm": 0.09,
                                          "robot_along_correlation_mm": 20.0}})


def test_sim_cell_refuses_a_robot_too_large_before_writing(tmp_path, capsys):
    from gls_calibration.cli import sim_cell
    config = tmp_path / "sim.yaml"
    config.write_text("/**:\n  ros__parameters:\n    measurement: {preset: custom, robot_path_error_mm: 0.5, "
                      "robot_path_correlation_mm: 30.0}\n")
    for extra in ([], ["--reference-plate"]):
        with pytest.raises(SystemExit) as exit_info:
            sim_cell.main(["--sim-config", str(config), *extra, "--out", str(tmp_path / "out")])
        assert exit_info.value.code == 2
        assert "measurement.robot_path_error_mm" in capsys.readouterr().err
        assert not (tmp_path / "out").exists()
