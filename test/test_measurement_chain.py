"""The simulated measurement chain: each error source moves what is measured by what it should."""
from dataclasses import replace
import json
import math

import numpy as np
import pytest
import yaml

from gls_calibration.calibration.procedure import ProcedureSettings
from gls_calibration.common.config_files import config_path
from gls_calibration.fiducials import targets
from gls_calibration.fiducials.measure import measure_fiducials
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.scan.plate_pose import estimate_plate_pose
from gls_calibration.scan.sweep import SWEEP_LENGTH_MM
from gls_calibration.simulation.head import TruthHead
from gls_calibration.simulation.measurement import (PRESET_CHAINS, MeasurementChain, lateral_linearity_shape,
                                                    measurement_from_mapping, smooth_process)
from gls_calibration.registration.sweep_plan import parse_plan, plan_label
from gls_calibration.simulation.plate import Plate, PlateSettings
from gls_calibration.simulation.scanner import LaserLineScanner, ScannerSettings
from gls_calibration.simulation.world import load_sim_config, sim_config_from_dict

QUIET = ScannerSettings(line_length_mm=60.0, z_noise_mm=0.0, linearity_mm=0.0, speckle=0.0, dropout_fraction=0.0,
                        path_repeatability_mm=0.0)
FLAT = PlateSettings(texture_std=0.0)
LENGTH = 60.0
# fiducials at these base-frame positions (x along the line, y along the travel); the default
# scanner maps base (x, y) to plate (x, START_Y - y), its start above plate y = START_Y
CENTRES_B = np.array([(x, y) for y in (12.0, 30.0, 48.0) for x in (-18.0, 0.0, 18.0)])
START_Y = 0.5 * SWEEP_LENGTH_MM


def chain(**values) -> MeasurementChain:
    return replace(MeasurementChain(), **values)


def marked_plate(plate_chain: MeasurementChain | None = None, settings: PlateSettings = FLAT) -> Plate:
    plate = Plate(settings, seed=4, chain=plate_chain)
    uv = np.column_stack([CENTRES_B[:, 0], START_Y - CENTRES_B[:, 1]])
    for ring in targets.rings_polylines(uv, (2.5, 2.7)):
        plate.add_mark_plate(ring)
    return plate


def centres_b(scanner_chain: MeasurementChain, plate: Plate | None = None, placement: str = "time",
              settings: ScannerSettings = QUIET, seed: int = 3) -> np.ndarray:
    """Measured centres (9, 2) in the base frame, in the order of CENTRES_B."""
    scanner = LaserLineScanner(settings, chain=scanner_chain)
    data = scanner.sweep_data(plate or marked_plate(), LENGTH, seed=seed)
    xyz = data.placed_by_pose() if placement == "pose" else data.placed_by_time()
    pose = estimate_plate_pose(xyz, head_direction=(0.0, 0.0, -1.0))
    found = measure_fiducials(xyz, data.intensity, pose, expected_count=9).centres[:, :2]
    order = np.argmin(np.linalg.norm(found[:, None, :] - CENTRES_B[None, :, :], axis=2), axis=0)
    assert len(found) == 9
    return found[order]


@pytest.fixture(scope="module")
def reference() -> np.ndarray:
    return centres_b(MeasurementChain())


def test_ideal_chain_measures_the_centres_exactly(reference):
    assert np.abs(reference - CENTRES_B).max() < 0.004


# ---------------------------------------------------------------- a. robot placement
def test_speed_scale_error_shrinks_the_sweep_unless_placed_by_pose(reference):
    scale = 2e-3
    measured = centres_b(chain(speed_scale_error=scale))
    # a feature at true travel s is seen when the robot has travelled s, placed at s / (1 + scale)
    expected = reference[:, 1] / (1.0 + scale) - reference[:, 1]
    assert np.allclose(measured[:, 1] - reference[:, 1], expected, atol=0.003)
    assert np.abs(measured[:, 1] - reference[:, 1]).max() > 0.08
    by_pose = centres_b(chain(speed_scale_error=scale), placement="pose")
    assert np.abs(by_pose - reference).max() < 0.003


def test_speed_ripple_moves_centres_along_the_sweep_by_the_drawn_process(reference):
    measured_chain = chain(speed_ripple_mm=0.05, speed_ripple_correlation_mm=30.0)
    scanner = LaserLineScanner(QUIET, chain=measured_chain)
    _, travel, _, _ = scanner._placement(3, 601, 0.1)
    ripple = travel - np.arange(601) * 0.1
    expected = -np.interp(reference[:, 1], np.arange(601) * 0.1, ripple)
    measured = centres_b(measured_chain)
    assert np.allclose(measured[:, 1] - reference[:, 1], expected, atol=0.004)
    assert np.abs(expected).max() > 0.01                       # the draw is not trivially small
    assert np.abs(centres_b(measured_chain, placement="pose") - reference).max() < 0.003
    assert np.allclose(measured[:, 0], reference[:, 0], atol=0.002)


def test_path_wander_moves_centres_across_and_the_encoder_does_not_see_it(reference):
    measured_chain = chain(path_wander_mm=0.05, path_wander_correlation_mm=30.0)
    scanner = LaserLineScanner(QUIET, chain=measured_chain)
    _, _, across, _ = scanner._placement(3, 601, 0.1)
    expected = -np.interp(reference[:, 1], np.arange(601) * 0.1, across)
    for placement in ("time", "pose"):
        measured = centres_b(measured_chain, placement=placement)
        assert np.allclose(measured[:, 0] - reference[:, 0], expected, atol=0.004)
    assert np.abs(expected).max() > 0.01


def test_placement_processes_are_drawn_anew_per_sweep_with_the_given_statistics():
    scanner = LaserLineScanner(QUIET, chain=chain(speed_ripple_mm=0.05, speed_ripple_correlation_mm=10.0))
    first = scanner._placement(1, 2001, 0.1)[0]
    second = scanner._placement(2, 2001, 0.1)[0]
    assert not np.allclose(first, second)
    draws = np.array([smooth_process(np.random.default_rng(seed), np.arange(0, 400, 0.5), 0.05, 10.0)
                      for seed in range(100)])
    assert draws.std() == pytest.approx(0.05, rel=0.05)
    lag = int(10.0 / 0.5)
    correlation = np.mean(draws[:, :-lag] * draws[:, lag:]) / draws.var()
    assert correlation == pytest.approx(math.exp(-0.5), abs=0.07)


# ---------------------------------------------------------------- b. lateral linearity
def test_lateral_linearity_moves_centres_along_the_line_by_the_fixed_shape(reference):
    measured = centres_b(chain(lateral_linearity_mm=0.065))
    expected = 0.065 * lateral_linearity_shape(reference[:, 0], 0.5 * QUIET.line_length_mm)
    assert np.allclose(measured[:, 0] - reference[:, 0], expected, atol=0.004)
    assert np.abs(expected).max() > 0.03
    # the same in every sweep: a property of the sensor
    assert np.allclose(centres_b(chain(lateral_linearity_mm=0.065), seed=9), measured, atol=0.002)
    assert np.abs(lateral_linearity_shape(np.linspace(-30, 30, 601), 30.0)).max() == pytest.approx(1.0, abs=1e-3)


# ---------------------------------------------------------------- c. fan geometry
def test_fan_geometry_puts_points_on_rays_from_the_apex(reference):
    noisy = replace(QUIET, z_noise_mm=0.05)
    scanner = LaserLineScanner(noisy, chain=chain(fan_geometry=1.0))
    xyz, _ = scanner.sweep_cloud(Plate(PlateSettings(delta_d_mm=20.0, texture_std=0.0)), 2.0)
    x, z = xyz[0, :, 0].astype(float), xyz[0, :, 2].astype(float)
    # lateral position follows the measured range along each pixel's ray
    assert np.allclose(x / z, scanner.line_x() / QUIET.standoff_mm, atol=1e-6)
    pitch = np.median(np.diff(x))
    assert pitch == pytest.approx(0.1 * np.mean(z) / QUIET.standoff_mm, rel=1e-3)
    assert np.mean(z) > QUIET.standoff_mm + 15.0
    # on a flat plate the rays still measure the marks where they are
    assert np.abs(centres_b(chain(fan_geometry=1.0)) - reference).max() < 0.004


# ---------------------------------------------------------------- d. speckle, saturation, blooming
def test_correlated_speckle_has_the_given_contrast_and_correlation_length():
    settings = replace(QUIET, gain=1.0)
    scanner = LaserLineScanner(settings, chain=chain(speckle_contrast=0.1, speckle_correlation_mm=0.3))
    _, intensity = scanner.sweep_cloud(Plate(FLAT), 30.0, seed=1)
    ratio = intensity / 0.6 - 1.0
    assert np.std(ratio) == pytest.approx(0.1, rel=0.1)
    lag = 3                                     # 0.3 mm at 0.1 mm pitch, along the line and the travel
    for axis in (0, 1):
        a = np.moveaxis(ratio, axis, 0)
        correlation = np.mean(a[:-lag] * a[lag:]) / np.var(a)
        assert correlation == pytest.approx(math.exp(-0.5), abs=0.08)


def test_speckle_scatters_the_centres(reference):
    spread = np.abs(centres_b(chain(speckle_contrast=0.1, speckle_correlation_mm=0.1)) - reference)
    assert 0.001 < spread.max() < 0.03


def test_blooming_spills_saturated_light_into_dark_marks_without_moving_centres():
    plate = marked_plate(settings=PlateSettings())
    glaring = replace(QUIET, gain=2.5)              # the steel saturates, the marks' centres do not
    plain = LaserLineScanner(glaring).sweep_cloud(plate, LENGTH, seed=3)[1]
    bloomed = LaserLineScanner(glaring, chain=chain(blooming_mm=0.1)).sweep_cloud(plate, LENGTH, seed=3)[1]
    marks = plain < 0.9
    assert np.mean(bloomed[marks]) > np.mean(plain[marks]) + 0.05
    assert np.array_equal(bloomed[plain == 1.0], plain[plain == 1.0])
    bright = replace(QUIET, gain=1.7)               # saturated in places: the rings can still be found
    measured = centres_b(chain(blooming_mm=0.1), plate=plate, settings=bright)
    assert np.abs(measured - centres_b(MeasurementChain(), plate=plate, settings=bright)).max() < 0.003


# ---------------------------------------------------------------- e. marks
def test_mark_blobs_darken_where_rings_start_but_sit_on_the_path(reference):
    plate = marked_plate(chain(mark_blob_mm=0.1))
    start = np.array([[CENTRES_B[0, 0] + 2.5 - 0.12, START_Y - CENTRES_B[0, 1]]])   # beside the ring's start
    opposite = np.array([[CENTRES_B[0, 0] - 2.5 + 0.12, START_Y - CENTRES_B[0, 1]]])
    assert plate.mark_darkening(start)[0] > 0.3 and plate.mark_darkening(opposite)[0] < 0.05
    # a blob is centred on the path: it does not move the ring's centre (expected shift 0)
    measured = centres_b(MeasurementChain(), plate=plate)
    assert np.abs(measured - reference).max() < 0.002


def test_width_darkness_and_wander_of_marks_scatter_the_centres(reference):
    for marks in (chain(mark_width_variation=0.2, mark_darkness_variation=0.2, mark_variation_correlation_mm=1.0),
                  chain(mark_wander_mm=0.01, mark_wander_correlation_mm=1.0)):
        spread = np.abs(centres_b(MeasurementChain(), plate=marked_plate(marks)) - reference)
        assert 0.0015 < spread.max() < 0.03


def test_spot_blur_widens_the_line_and_lowers_its_peak():
    sigma = 0.1 / 2.3548
    plate = Plate(FLAT, chain=chain(spot_blur_mm=sigma))
    plate.add_mark_plate(np.array([[0.0, -5.0], [0.0, 5.0]]))
    darkening = plate.mark_darkening(np.column_stack([np.linspace(-0.3, 0.3, 601), np.zeros(601)]))
    assert darkening.max() == pytest.approx(1 / math.sqrt(2.0), rel=0.01)
    width = np.ptp(np.linspace(-0.3, 0.3, 601)[darkening >= darkening.max() / 2])
    assert width == pytest.approx(0.1 * math.sqrt(2.0), rel=0.03)


# ---------------------------------------------------------------- f. plate to plate
def test_marking_pose_error_is_drawn_per_plate_and_moves_the_landed_field():
    geometry = HeadGeometry()
    plate = Plate(FLAT, chain=chain(marking_height_mm=0.05, marking_tilt_rad=1e-4, straight_rays=1.0))
    draws = []
    for seed in range(60):
        plate.load_clean(seed)
        draws.append(plate.marking_pose_error)
    draws = np.array(draws)
    assert draws[:, 0].std() == pytest.approx(0.05, rel=0.3) and draws[:, 1].std() == pytest.approx(1e-4, rel=0.3)
    head = TruthHead(geometry, plate=plate)
    alpha = np.linspace(-0.08, 0.08, 9)
    plate.marking_pose_error = (0.0, 0.0, 0.0)
    flat = head.land(alpha, 0.5 * alpha)
    plate.marking_pose_error = (0.5, 0.0, 0.0)
    raised = head.land(alpha, 0.5 * alpha)
    # 0.5 mm closer to the head: the field shrinks by about 0.5 / 490
    ratio = np.linalg.norm(raised[:, :2], axis=1)[alpha != 0] / np.linalg.norm(flat[:, :2], axis=1)[alpha != 0]
    assert np.allclose(ratio, 1.0 - 0.5 / 490.0, atol=2e-5)


def test_thermal_scale_shrinks_the_marks_of_each_plate():
    plate = Plate(FLAT, seed=2, chain=chain(thermal_scale_ppm=50.0))
    assert plate.thermal_scale != 0.0 and abs(plate.thermal_scale) < 4 * 50e-6
    plate.add_mark(np.array([[10.0, 20.0, 0.0], [30.0, -40.0, 0.0]]))
    assert np.allclose(plate.marks[0], np.array([[10.0, 20.0], [30.0, -40.0]]) * (1.0 + plate.thermal_scale))


def test_plate_warp_raises_the_surface_for_the_scanner_and_the_beam():
    plate = Plate(FLAT, seed=5, chain=chain(plate_warp_mm=0.1))
    corners = plate.warp(np.array([[125.0, 125.0], [125.0, -125.0], [-125.0, 125.0], [0.0, 125.0]]))
    assert np.abs(corners).max() <= 0.1 + 1e-9 and np.abs(corners).max() > 0.05
    uv = np.array([[100.0, 50.0]])
    plate.add_mark(plate.from_plate(uv))
    height = plate.warp(uv)[0]
    assert np.allclose(plate.marks[0], uv * (1.0 - height / plate.beam_distance_mm))
    flat = LaserLineScanner(QUIET).sweep_cloud(Plate(FLAT, seed=5), 2.0)[0][..., 2]
    warped = LaserLineScanner(QUIET).sweep_cloud(plate, 2.0)[0][..., 2]
    expected = plate.warp(np.column_stack([LaserLineScanner(QUIET).line_x(), np.full(601, START_Y)]))
    # the surface is closer to the scanner where it is raised
    assert np.allclose(flat[0] - warped[0], expected, atol=1e-4)


# ---------------------------------------------------------------- g. straight rays
@pytest.mark.parametrize("offset_mm", [10.0, -10.0])
def test_a_target_off_the_calibration_plane_lands_on_the_straight_ray(offset_mm):
    geometry = HeadGeometry()
    k1, delta_d = 5.9e-7, 0.8
    head = TruthHead(geometry, {"radial_distortion": [k1], "working_distance": [delta_d]})
    alpha_x, alpha_y = np.array([0.06, -0.04, 0.02]), np.array([0.03, 0.05, -0.07])
    landed = head.land(alpha_x, alpha_y, plane_offset_mm=offset_mm)
    # independent: the published closed form gives the undistorted ray after the X mirror; its exit
    # point (0, e tan(theta_y), d); the lens moves the landing on the calibration plane radially
    d, e = geometry.working_distance_mm, geometry.mirror_distance_mm
    theta_x, theta_y = 2 * alpha_x, 2 * alpha_y
    z0 = -delta_d
    x0 = (d - z0) * np.tan(theta_x)
    y0 = (e + (d - z0) / np.cos(theta_x)) * np.tan(theta_y)
    scale = 1.0 + k1 * (x0 ** 2 + y0 ** 2)
    distorted = np.column_stack([x0 * scale, y0 * scale, np.full(3, z0)])
    exit_point = np.column_stack([np.zeros(3), e * np.tan(theta_y), np.full(3, d)])
    z = z0 + offset_mm
    expected = exit_point + (distorted - exit_point) * (d - z) / (d - z0)
    assert np.allclose(landed, expected, atol=1e-6)
    # the old model (distortion in the plane at every height) would be off by micrometres
    assert np.abs(head.land(alpha_x, alpha_y) - distorted).max() < 1e-6


# ---------------------------------------------------------------- presets and bad input
def test_presets_and_their_relations():
    assert all(value == 0.0 for key, value in vars(PRESET_CHAINS["ideal"]).items() if key != "straight_rays")
    paper, careful = PRESET_CHAINS["paper_like"], PRESET_CHAINS["careful"]
    for key in ("speed_scale_error", "speed_ripple_mm", "path_wander_mm", "marking_height_mm", "marking_tilt_rad"):
        assert getattr(careful, key) == pytest.approx(getattr(paper, key) / 3.0)
    assert paper.lateral_linearity_mm == 0.065          # the datasheet's linearity
    assert load_sim_config().measurement_preset == "paper_like"
    assert load_sim_config(preset="ideal").measurement == PRESET_CHAINS["ideal"]


@pytest.mark.parametrize("block, preset, message", [
    ({"preset": "noisy"}, None, "unknown measurement preset 'noisy'"),
    ({}, "perfect", "unknown measurement preset 'perfect'"),
    ({"preset": "custom", "speed_ripple_mm": -0.1, "speed_ripple_correlation_mm": 5.0}, None,
     "measurement.speed_ripple_mm must be non-negative"),
    ({"preset": "custom", "path_wander_mm": 0.1, "path_wander_correlation_mm": -5.0}, None,
     "measurement.path_wander_correlation_mm must be non-negative"),
    ({"preset": "custom", "path_wander_mm": 0.1}, None, "measurement.path_wander_correlation_mm must be positive"),
    ({"preset": "paper_like", "lateral_linearity_mm": 0.2}, None,
     "measurement.lateral_linearity_mm = 0.2 conflicts with preset 'paper_like'"),
    ({"lateral_linearity_mm": 0.065}, "ideal",
     "measurement.lateral_linearity_mm = 0.065 conflicts with preset 'ideal'"),
    ({"preset": "custom", "speckel": 0.1}, None, "unknown measurement parameter"),
    ({"preset": "custom", "fan_geometry": 0.5}, None, "measurement.fan_geometry is a switch"),
    ({"preset": "custom", "marking_height_mm": 0.05}, None,
     "measurement.marking_height_mm needs measurement.straight_rays"),
])
def test_bad_measurement_blocks_are_refused_naming_the_key(block, preset, message):
    with pytest.raises(ValueError, match=message):
        sim_config_from_dict({"measurement": block}, preset)


def test_custom_and_agreeing_explicit_keys_are_accepted():
    name, custom = measurement_from_mapping({"preset": "custom", "lateral_linearity_mm": 0.03})
    assert name == "custom" and custom == MeasurementChain(lateral_linearity_mm=0.03)
    name, paper = measurement_from_mapping({"preset": "paper_like", "lateral_linearity_mm": 0.065})
    assert paper == PRESET_CHAINS["paper_like"]


# ---------------------------------------------------------------- sweep plans: direction, orientation, reported pose
def plan_centres(scanner_chain: MeasurementChain, direction: int, orientation: float, placement: str) -> np.ndarray:
    scanner = LaserLineScanner(replace(QUIET, line_length_mm=LENGTH), chain=scanner_chain)
    data = scanner.sweep_data(marked_plate(), LENGTH, seed=3, direction=direction, orientation_deg=orientation)
    xyz = data.placed_by_pose() if placement == "pose" else data.placed_by_time()
    pose = estimate_plate_pose(xyz, head_direction=(0.0, 0.0, -1.0))
    found = measure_fiducials(xyz, data.intensity, pose, expected_count=9).centres[:, :2]
    assert len(found) == 9
    return found[np.argmin(np.linalg.norm(found[:, None, :] - CENTRES_B[None, :, :], axis=2), axis=0)]


@pytest.mark.parametrize("direction, orientation", [(1, 0.0), (-1, 0.0), (1, 90.0), (-1, 90.0), (1, 45.0),
                                                    (-1, 45.0)])
def test_every_direction_and_orientation_measures_the_plate_in_the_base_frame(direction, orientation):
    measured = plan_centres(MeasurementChain(), direction, orientation, "time")
    assert np.abs(measured - CENTRES_B).max() < 0.005


def test_scanner_frame_errors_change_sign_or_axis_with_the_sweep():
    scale = chain(speed_scale_error=2e-3)
    forward = plan_centres(scale, 1, 0.0, "time") - CENTRES_B
    backward = plan_centres(scale, -1, 0.0, "time") - CENTRES_B
    # the along-sweep scale acts about each sweep's start: opposite ends for opposite directions
    assert np.allclose(forward[:, 1], -2e-3 * CENTRES_B[:, 1], atol=0.004)
    assert np.allclose(backward[:, 1], 2e-3 * (LENGTH - CENTRES_B[:, 1]), atol=0.004)
    linear = chain(lateral_linearity_mm=0.065)
    turned = plan_centres(linear, 1, 90.0, "time") - CENTRES_B
    # turned by 90 deg, the line runs along base y: the lateral error moves y, not x
    assert np.abs(turned[:, 0]).max() < 0.004 and np.abs(turned[:, 1]).max() > 0.02
    diagonal = plan_centres(linear, 1, 45.0, "time") - CENTRES_B
    # at 45 deg along the line (1, 1) / sqrt(2): the lateral error moves x and y alike, nothing across
    assert np.abs(diagonal[:, 0] - diagonal[:, 1]).max() < 0.006 and np.abs(diagonal).max() > 0.015
    for direction, orientation in ((1, 0.0), (-1, 0.0), (1, 90.0), (-1, 90.0)):
        assert np.abs(plan_centres(scale, direction, orientation, "pose") - CENTRES_B).max() < 0.005


def test_reported_poses_follow_the_true_travel_and_profiles_carry_them():
    measured_chain = chain(speed_scale_error=1e-3, speed_ripple_mm=0.05, speed_ripple_correlation_mm=10.0,
                           path_wander_mm=0.05, path_wander_correlation_mm=10.0)
    scanner = LaserLineScanner(QUIET, chain=measured_chain)
    data = scanner.sweep_data(Plate(FLAT), 20.0, seed=7, direction=-1, orientation_deg=90.0)
    _, travel, _, _ = scanner._placement(7, 201, 0.1)
    start = scanner.start_pose(20.0, -1, 90.0)
    assert np.allclose(start[:3, 3], [0.0, 0.0, 0.0] + np.array([0.0, 10.0, 0.0]) + np.array([-10.0, 0.0, 0.0]))
    # sensor y is base -x at 90 deg; moving along sensor -y means base +x
    assert np.allclose(data.reported_poses[:, :3, 3] - start[:3, 3], np.column_stack(
        [travel, np.zeros(201), np.zeros(201)]), atol=1e-9)
    profiles = list(scanner.sweep(Plate(FLAT), 20.0, seed=7, direction=-1, orientation_deg=90.0))
    assert np.allclose(profiles[50].reported_pose, data.reported_poses[50])
    assert np.allclose(profiles[50].points["y"], -50 * 0.1, atol=1e-5)
    with pytest.raises(ValueError, match="orientation_deg must be 0, 45 or 90"):
        scanner.sweep_data(Plate(FLAT), 20.0, orientation_deg=30.0)
    with pytest.raises(ValueError, match="direction must be"):
        scanner.sweep_data(Plate(FLAT), 20.0, direction=2)


# ---------------------------------------------------------------- reference-plate check and the command line
def test_reference_plate_check_on_ideal_is_within_a_hundredth():
    from gls_calibration.simulation.reference_plate import RAW_PLAN, reference_plate_check
    result = reference_plate_check(load_sim_config(preset="ideal"), RAW_PLAN, seed=1, positions=((0.0, 0.0),))
    assert result.found == result.expected == 143
    assert max(result.sigma_mm) < 0.01


@pytest.mark.slow
def test_reference_plate_check_on_paper_like_is_like_the_papers():
    from gls_calibration.simulation.reference_plate import RAW_PLAN, reference_plate_check
    result = reference_plate_check(load_sim_config(preset="paper_like"), RAW_PLAN, seed=1)
    assert all(0.05 <= sigma <= 0.09 for sigma in result.sigma_mm), result.sigma_mm


def test_reference_plate_calibration_plan_is_the_calibration_managers(tmp_path):
    from gls_calibration.simulation.reference_plate import calibration_plan
    sweep = yaml.safe_load(config_path("gls.yaml").read_text())["/**"]["ros__parameters"]["sweep"]
    plan = calibration_plan()
    assert plan.label == plan_label(parse_plan(sweep["plan"])) and len(plan.passes) > 1
    assert plan.placed_by_pose is sweep["placed_by_pose"] and plan.plain_sweeps == sweep["plain_repeats"]
    assert (plan.plain_step_mm, plan.marked_step_mm) == (sweep["plain_step_mm"], sweep["marked_step_mm"])
    steps = tmp_path / "steps.yaml"
    steps.write_text("/**:\n  ros__parameters:\n    sweep: {plain_step_mm: 2.0, marked_step_mm: 0.07}\n")
    stepped = calibration_plan(steps)
    assert (stepped.plain_step_mm, stepped.marked_step_mm) == (2.0, 0.07)
    negative = tmp_path / "negative.yaml"
    negative.write_text("/**:\n  ros__parameters:\n    sweep: {marked_step_mm: -0.1}\n")
    with pytest.raises(ValueError, match=r"negative.yaml: marked_step_mm must be a positive finite number"):
        calibration_plan(negative)
    bare = tmp_path / "bare.yaml"
    bare.write_text("/**:\n  ros__parameters:\n    grid: {per_side: 5}\n")
    defaults = ProcedureSettings()
    assert calibration_plan(bare) == replace(plan, passes=defaults.sweep_plan, plain_sweeps=defaults.plain_sweeps,
                                             placed_by_pose=defaults.profiles_placed_by_pose,
                                             plain_step_mm=defaults.plain_sweep_step_mm,
                                             marked_step_mm=defaults.marked_sweep_step_mm)
    bad = tmp_path / "bad.yaml"
    bad.write_text("/**:\n  ros__parameters:\n    sweep: {plan: '0+,30-'}\n")
    with pytest.raises(ValueError, match=r"bad.yaml: sweep plan orientation must be 0, 45 or 90 deg, got 30.0"):
        calibration_plan(bad)


def test_sim_cell_reference_plate_measures_with_the_calibrations_plan(tmp_path, monkeypatch):
    from gls_calibration.cli import sim_cell
    from gls_calibration.simulation import reference_plate
    plans = []

    def check(config, plan, seed=1, positions=reference_plate.POSITIONS_MM):
        plans.append(plan)
        sigma = (0.05, 0.06) if plan == reference_plate.RAW_PLAN else (0.01, 0.02)
        return reference_plate.ReferencePlateResult(sigma, ((0.0, 0.0),), 143, 143)

    monkeypatch.setattr(reference_plate, "reference_plate_check", check)
    assert sim_cell.main(["--reference-plate", "--measurement", "ideal", "--out", str(tmp_path / "a")]) == 0
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    calibration = reference_plate.calibration_plan()
    assert plans == [reference_plate.RAW_PLAN, replace(calibration, placed_by_pose=True)]
    assert summary["reference_plate_raw_sigma_mm"] == [0.05, 0.06]
    assert summary["reference_plate_sigma_mm"] == [0.01, 0.02]
    assert summary["reference_plate_plan"]["sweep_plan"] == calibration.label
    assert summary["reference_plate_plan"]["placement"] == "pose"
    assert summary["reference_plate_raw_plan"] == {"sweep_plan": "0+", "placement": "time", "plain_sweeps": 0}
    # the cell's own overrides of the plan reach the check as they reach the manager
    plans.clear()
    assert sim_cell.main(["--reference-plate", "--measurement", "ideal", "--sweep-plan", "0+,90-", "--placement",
                          "time", "--out", str(tmp_path / "b")]) == 0
    assert plans[1] == replace(calibration, passes=parse_plan("0+,90-"), placed_by_pose=False)
    assert json.loads((tmp_path / "b" / "summary.json").read_text())["reference_plate_plan"]["sweep_plan"] == "0+,90-"


def test_the_simulated_check_records_where_its_known_centres_lie():
    from gls_calibration.simulation import reference_plate
    config = load_sim_config(preset="ideal")
    plan = reference_plate.calibration_plan()
    known = reference_plate.reference_pattern(reference_plate.FIELD_PLATE) + [0.3, -0.2]
    result = reference_plate.ReferencePlateResult((0.01, 0.02), ((0.0, 0.0),), len(known), len(known), known)
    check = reference_plate.chain_check(result, plan, config, 1, reference_plate.FIELD_PLATE)
    assert check.extent_mm == pytest.approx((-94.7, 95.3, -95.2, 94.8))
    # a result that kept no centres makes a check that states nothing (stated_accuracy.check_mismatch)
    bare = reference_plate.chain_check(replace(result, known_xy_mm=None), plan, config, 1)
    assert bare.extent_mm is None


@pytest.mark.slow
def test_reference_plate_with_the_calibrations_plan_beats_one_sweep_and_sees_the_repeating_robot():
    from gls_calibration.simulation.reference_plate import RAW_PLAN, calibration_plan, reference_plate_check
    config = load_sim_config(preset="paper_like")
    assert config.measurement.robot_repeats
    no_repeats = replace(config, measurement=replace(config.measurement, robot_scale_error=0.0,
                                                     robot_along_error_mm=0.0, robot_path_error_mm=0.0))
    raw = reference_plate_check(no_repeats, RAW_PLAN, seed=2, positions=((0.0, 0.0),))
    planned = reference_plate_check(no_repeats, calibration_plan(), seed=2, positions=((0.0, 0.0),))
    assert planned.found == planned.expected == 143
    # with errors drawn anew per sweep, separating four reversed and turned sweeps placed by pose
    # leaves a fraction of one sweep by time ...
    assert max(planned.sigma_mm) < 0.4 * min(raw.sigma_mm), (planned.sigma_mm, raw.sigma_mm)
    # ... but an error that repeats on every run of a line is not averaged away, and the check,
    # measured against known centres, sees it (what the cell's own plate cannot)
    repeating = reference_plate_check(config, calibration_plan(), seed=2, positions=((0.0, 0.0),))
    assert min(repeating.sigma_mm) > 1.5 * max(planned.sigma_mm), (repeating.sigma_mm, planned.sigma_mm)


@pytest.mark.parametrize("arguments, message", [
    (["--measurement", "noisy"], "unknown measurement preset 'noisy'"),
    (["--reference-plate", "--measurement", "loud"], "unknown measurement preset 'loud'"),
])
def test_sim_cell_refuses_bad_measurement_input_before_writing(tmp_path, capsys, arguments, message):
    from gls_calibration.cli import sim_cell
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exit_info:
        sim_cell.main(arguments + ["--out", str(out)])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not out.exists()


def test_sim_cell_refuses_a_conflicting_sim_config(tmp_path, capsys):
    from gls_calibration.cli import sim_cell
    config = tmp_path / "sim.yaml"
    config.write_text("/**:\n  ros__parameters:\n    measurement: {preset: careful, plate_warp_mm: 1.0}\n")
    with pytest.raises(SystemExit) as exit_info:
        sim_cell.main(["--sim-config", str(config), "--reference-plate", "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    assert "measurement.plate_warp_mm = 1.0 conflicts with preset 'careful'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
