"""The head's pose at a sweep's start has one owner (``scan.sweep.nominal_mounting``) that every file follows."""
import numpy as np
import yaml

from gls_calibration.common.config_files import config_path
from gls_calibration.ros.head_parameters import SCANNER_TO_GLS_DEFAULTS
from gls_calibration.scan.cell_frames import load_cell_frames
from gls_calibration.scan.sweep import SCANNER_STANDOFF_MM, SWEEP_LENGTH_MM, nominal_mounting, nominal_start_pose
from gls_calibration.simulation.scanner import LaserLineScanner, pose_matrix
from gls_calibration.simulation.world import SimConfig, load_sim_config


def _parameters(name):
    return yaml.safe_load(config_path(name).read_text())["/**"]["ros__parameters"]


def test_the_owner_puts_the_sweeps_middle_over_the_gls_origin():
    translation_mm, rpy_rad = nominal_mounting(150.0, 300.0)
    mounting = pose_matrix(translation_mm, rpy_rad)
    start = nominal_start_pose(150.0)
    middle_in_gls = mounting @ start @ np.array([0.0, 75.0, 0.0, 1.0])   # half-way along the sweep
    np.testing.assert_allclose(middle_in_gls[:3], [0.0, 0.0, 300.0], atol=1e-12)
    np.testing.assert_allclose(mounting[:3, :3] @ [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], atol=1e-12)  # looks down


def test_gls_yaml_and_the_manager_default_are_the_owners_pose_of_the_default_sweep():
    gls = _parameters("gls.yaml")
    assert gls["sweep"]["length_mm"] == SWEEP_LENGTH_MM
    expected = nominal_mounting(SWEEP_LENGTH_MM, SCANNER_STANDOFF_MM)
    assert [gls["scanner_to_gls"]["translation_mm"], gls["scanner_to_gls"]["rpy_rad"]] == list(expected)
    assert [SCANNER_TO_GLS_DEFAULTS["scanner_to_gls.translation_mm"],
            SCANNER_TO_GLS_DEFAULTS["scanner_to_gls.rpy_rad"]] == list(expected)


def test_the_simulated_cell_and_the_cell_frames_hold_the_same_pose():
    config = load_sim_config()
    expected = pose_matrix(*nominal_mounting(config.sweep_length_mm, config.scanner.standoff_mm))
    np.testing.assert_allclose(config.scanner_to_gls, expected, atol=1e-12)
    # cell_frames.yaml holds the gls frame in the robot base (the first sweep's start frame): the inverse
    np.testing.assert_allclose(np.linalg.inv(load_cell_frames().base_to_gls), expected, atol=1e-9)
    np.testing.assert_allclose(SimConfig().scanner_to_gls, pose_matrix(*nominal_mounting()), atol=0.0)
    np.testing.assert_allclose(LaserLineScanner().scanner_to_gls, pose_matrix(*nominal_mounting()), atol=0.0)
