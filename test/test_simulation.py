"""Tests of the simulated cell: truth head, plate, laser-line scanner and configuration."""
import math
from dataclasses import replace

import numpy as np
import pytest

from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.geometry.optics import PhysicalHead
from gls_calibration.scan.sweep import SWEEP_LENGTH_MM
from gls_calibration.simulation.head import TruthHead
from gls_calibration.simulation.plate import Plate, PlateSettings
from gls_calibration.simulation.scanner import LaserLineScanner, ScannerSettings, pose_matrix
from gls_calibration.simulation.world import SimConfig, SimulatedCell, load_sim_config, sim_config_from_dict

GEOMETRY = HeadGeometry()
QUIET = ScannerSettings(z_noise_mm=0.0, linearity_mm=0.0, speckle=0.0, dropout_fraction=0.0,
                        path_repeatability_mm=0.0)


def grid(per_side: int = 19, size: float = 190.0) -> np.ndarray:
    offsets = np.linspace(-size / 2, size / 2, per_side)
    x, y = np.meshgrid(offsets, offsets)
    return np.column_stack([x.ravel(), y.ravel()])


def ring(centre, radius: float, count: int = 720) -> np.ndarray:
    angles = np.linspace(0.0, 2.0 * math.pi, count + 1)
    return np.asarray(centre) + radius * np.column_stack([np.cos(angles), np.sin(angles)])


def rigid_2d(points: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """``points`` moved by the least-squares rotation + translation onto ``targets`` (2-D)."""
    p0, q0 = points.mean(axis=0), targets.mean(axis=0)
    u, _, vt = np.linalg.svd((points - p0).T @ (targets - q0))
    rotation = vt.T @ np.diag([1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
    return (points - p0) @ rotation.T + q0


def mark_xy(head: TruthHead, polyline_xy: np.ndarray) -> np.ndarray:
    setpoints = inverse(GEOMETRY, polyline_xy[:, 0], polyline_xy[:, 1])
    return head.mark(setpoints.alpha_x, setpoints.alpha_y)


# ---------------------------------------------------------------- truth head
def test_zero_defect_truth_lands_on_the_targets():
    head = TruthHead(GEOMETRY)
    targets = grid()
    landed = mark_xy(head, targets)
    assert np.abs(landed[:, :2] - targets).max() < 1e-6
    assert np.abs(landed[:, 2]).max() < 1e-9


def test_marking_records_order_and_time():
    head = TruthHead(GEOMETRY, mark_speed_mm_s=500.0, jump_time_s=0.01)
    lengths = []
    for radius in (2.5, 2.7, 10.0):
        polyline = ring((5.0, -3.0), radius)
        lengths.append(np.sum(np.hypot(*np.diff(polyline, axis=0).T)))
        mark_xy(head, polyline)
    assert [record.index for record in head.log] == [0, 1, 2]
    expected_end = 0.0
    for record, length in zip(head.log, lengths):
        assert record.start_s == pytest.approx(expected_end + 0.01)
        assert record.end_s - record.start_s == pytest.approx(length / 500.0, rel=1e-6)
        expected_end = record.end_s
        assert record.vertex_count == 721
    assert head.clock_s == pytest.approx(expected_end)
    head.reset_clock()
    assert head.clock_s == 0.0 and head.log == []


def test_thermal_drift_makes_later_marks_deviate_more():
    head = TruthHead(GEOMETRY, {"thermal_drift": (1e-5, 1e-6)}, jump_time_s=10.0)
    target = np.array([[80.0, 60.0]])
    first = mark_xy(head, target)
    second = mark_xy(head, target)
    setpoints = inverse(GEOMETRY, target[:, 0], target[:, 1])
    nominal = PhysicalHead(GEOMETRY).land(setpoints.alpha_x, setpoints.alpha_y)
    assert 0.0 < np.linalg.norm(first - nominal) < np.linalg.norm(second - nominal)


def test_truth_head_marks_onto_its_plate():
    plate = Plate(PlateSettings(tilt_x_rad=0.02, tilt_y_rad=-0.01, delta_d_mm=1.0), seed=2)
    head = TruthHead(GEOMETRY, {"galvo_gain_x": 0.01}, plate=plate)
    assert head.effects.get("plate_tilt") == (0.02, -0.01)
    assert head.effects.get("working_distance") == (1.0,)
    landed = mark_xy(head, ring((40.0, -70.0), 2.7))
    assert np.abs((landed - plate.origin) @ plate.normal).max() < 1e-9
    assert len(plate.marks) == 1 and head.log[0].plate_id == plate.plate_id
    assert np.allclose(plate.from_plate(plate.marks[0]), landed, atol=1e-9)


def test_truth_head_rejects_effects_that_contradict_the_plate():
    plate = Plate(PlateSettings(tilt_x_rad=0.02))
    with pytest.raises(ValueError, match="effect 'plate_tilt' = .* contradicts the plate pose"):
        TruthHead(GEOMETRY, {"plate_tilt": (0.01, 0.0)}, plate=plate)


def test_truth_head_rejects_bad_settings():
    with pytest.raises(ValueError, match="mark_speed_mm_s must be positive"):
        TruthHead(GEOMETRY, mark_speed_mm_s=-500.0)
    with pytest.raises(ValueError, match="unknown effect 'lens_wobble'"):
        TruthHead(GEOMETRY, {"lens_wobble": 1.0})
    with pytest.raises(ValueError, match=r"polyline 0 must have shape \(M, 2\)"):
        TruthHead(GEOMETRY).mark_polylines([np.zeros((4, 3))])


# ---------------------------------------------------------------- plate
def test_marks_darken_the_plate_with_the_documented_profile():
    settings = PlateSettings(texture_std=0.0, line_width_fwhm_mm=0.1, mark_depth=0.7)
    plate = Plate(settings)
    plate.add_mark_plate(np.array([[-5.0, 0.0], [5.0, 0.0]]))
    samples = np.array([[0.0, 0.0], [1.0, 0.05], [2.0, -0.05], [0.0, 1.0], [200.0, 0.0]])
    values = plate.reflectivity(samples)
    assert values[0] == pytest.approx(0.6 * 0.3, rel=1e-3)
    # half maximum at FWHM / 2 (within the sigma / 4 resampling of the path)
    assert values[1] == pytest.approx(0.6 * (1 - 0.35), rel=5e-3)
    assert values[2] == pytest.approx(values[1], rel=5e-3)
    assert values[3] == pytest.approx(0.6, rel=1e-6)
    assert np.isnan(values[4])                                      # off the 250 mm plate


def test_brightening_marks_and_texture():
    plate = Plate(PlateSettings(mark_depth=-0.5), seed=4)
    plate.add_mark_plate(np.array([[0.0, -3.0], [0.0, 3.0]]))
    on, off = plate.reflectivity(np.array([[0.0, 0.0], [3.0, 0.0]]))
    assert on > off
    image = Plate(PlateSettings(), seed=4).render(pixel_mm=0.5, extent_mm=100.0)
    assert 0.01 < np.std(image) < 0.03 and abs(np.mean(image) - 0.6) < 0.01


def test_clean_plate_clears_marks_and_gets_a_new_id():
    plate = Plate(seed=1)
    plate.add_mark_plate(ring((0.0, 0.0), 2.5))
    first_id = plate.plate_id
    marked = plate.reflectivity(np.array([[2.5, 0.0]]))
    new_id = plate.load_clean(seed=2)
    assert new_id == plate.plate_id != first_id
    assert plate.marks == ()
    assert plate.reflectivity(np.array([[2.5, 0.0]]))[0] > marked[0] + 0.3


def test_plate_ids_count_the_plates_of_one_fixture_not_of_the_process():
    """The simulated scanner rebuilds the galvo's plate from its id: an id that counted every plate the
    process had made gave an in-process cell other draws after other tests had run."""
    config = load_sim_config(preset="paper_like")
    cells = [SimulatedCell(config) for _ in range(2)]
    assert [cell.plate.plate_id for cell in cells] == [0, 0]
    assert [cell.exchange_plate() for cell in cells] == [1, 1]
    assert cells[0].exchange_plate() == 2
    mark = np.column_stack([ring((10.0, -5.0), 2.5), np.zeros(721)])
    cells[1].plate.add_mark(mark)
    copy = config.make_plate()
    assert config.load_plate(copy, 1, [mark]) == 1
    assert copy.marking_pose_error == cells[1].plate.marking_pose_error != cells[0].plate.marking_pose_error
    probe = np.array([[12.5, -5.0], [10.0, -2.5], [30.0, 30.0]])
    assert np.array_equal(copy.reflectivity(probe), cells[1].plate.reflectivity(probe))


# ---------------------------------------------------------------- scanner
def test_sweep_profile_count_spacing_and_stamps():
    scanner = LaserLineScanner(ScannerSettings(line_length_mm=50.0, step_mm=0.2, speed_mm_s=15.0))
    profiles = list(scanner.sweep(Plate(), length_mm=20.0, seed=3))
    assert len(profiles) == 101
    assert [p.index for p in profiles] == list(range(101))
    assert profiles[10].stamp_s == pytest.approx(10 * 0.2 / 15.0)
    points = profiles[7].points
    assert points.dtype.names == ("x", "y", "z", "intensity") and points["x"].dtype == np.float32
    assert points.size == 501
    valid = np.isfinite(points["x"])
    assert valid.sum() > 490
    assert np.allclose(points["x"][valid], scanner.line_x()[valid], atol=1e-5)
    assert np.allclose(np.diff(scanner.line_x()), 0.1)
    assert np.nanmax(np.abs(points["y"] - 1.4)) < 1e-5
    # the iterator and the fast path give the same numbers
    xyz, intensity = scanner.sweep_cloud(Plate(), length_mm=20.0, seed=3)
    assert xyz.shape == (101, 501, 3) and intensity.shape == (101, 501)
    assert np.array_equal(xyz[7], np.stack([points["x"], points["y"], points["z"]], axis=-1), equal_nan=True)
    assert np.array_equal(intensity[7], points["intensity"], equal_nan=True)


def test_sweep_measures_the_plate_plane_in_the_gls_frame():
    plate = Plate(PlateSettings(tilt_x_rad=0.01, tilt_y_rad=0.02, delta_d_mm=2.0))
    scanner = LaserLineScanner(QUIET)
    xyz, _ = scanner.sweep_cloud(plate, length_mm=SWEEP_LENGTH_MM, step_mm=2.0)      # the default mounting's
    assert 320.0 < np.nanmean(xyz[..., 2]) < 331.0
    gls = scanner.to_gls(xyz.reshape(-1, 3).astype(float))
    gls = gls[np.all(np.isfinite(gls), axis=1)]
    assert np.abs((gls - plate.origin) @ plate.normal).max() < 1e-3      # float32 rounding only
    assert gls[:, 1].min() < -99.0 and gls[:, 1].max() > 99.0


def test_noise_levels_and_dropouts_roughly_as_configured():
    settings = ScannerSettings(line_length_mm=40.0, linearity_mm=0.0, z_noise_mm=0.015,
                               speckle=0.05, dropout_fraction=0.01)
    xyz, intensity = LaserLineScanner(settings).sweep_cloud(Plate(PlateSettings(texture_std=0.0)),
                                                            length_mm=40.0, seed=5)
    z = xyz[..., 2].astype(float)
    finite = np.isfinite(z)
    rows, cols = np.nonzero(finite)
    design = np.column_stack([np.ones(rows.size), rows, cols])
    residual = z[finite] - design @ np.linalg.lstsq(design, z[finite], rcond=None)[0]
    assert np.std(residual) == pytest.approx(0.015, rel=0.1)
    assert np.mean(~finite) == pytest.approx(0.01, rel=0.2)
    values = intensity[finite]
    assert np.mean(values) == pytest.approx(0.6 * 1.3, rel=0.02)
    assert np.std(values) / np.mean(values) == pytest.approx(0.05, rel=0.2)
    assert len(np.unique(values)) < 1024               # quantised to 10 bits


def test_linearity_error_is_systematic_across_the_line():
    settings = replace(QUIET, linearity_mm=0.065)
    xyz, _ = LaserLineScanner(settings).sweep_cloud(Plate(), length_mm=10.0)
    across = xyz[..., 2].mean(axis=0) - 325.0
    assert np.nanmax(np.abs(across)) == pytest.approx(0.065, rel=0.05)
    assert np.allclose(xyz[0, :, 2], xyz[-1, :, 2], atol=1e-4)


def test_intensity_is_darker_on_the_marks_and_saturates():
    plate = Plate(PlateSettings(tilt_x_rad=0.005))
    head = TruthHead(GEOMETRY, plate=plate)
    landed = mark_xy(head, ring((0.0, 95.0), 2.7, 2000))
    centre = landed[:-1].mean(axis=0)          # the tilted plate moves the ring a little
    scanner = LaserLineScanner(ScannerSettings(gain=1.3, dropout_fraction=0.0, path_repeatability_mm=0.0))
    xyz, intensity = scanner.sweep_cloud(plate, length_mm=10.0, seed=1)
    gls = scanner.to_gls(xyz.astype(float))
    radius = np.hypot(gls[..., 0] - centre[0], gls[..., 1] - centre[1])
    ring_radius = np.hypot(*(landed[:, :2] - centre[:2]).T).mean()
    on_ring = np.abs(radius - ring_radius) < 0.02
    away = np.abs(radius - ring_radius) > 0.5
    assert on_ring.sum() > 20
    assert np.mean(intensity[on_ring]) < 0.5 * np.mean(intensity[away])
    bright = LaserLineScanner(ScannerSettings(gain=3.0)).sweep_cloud(plate, length_mm=2.0)[1]
    assert np.nanmax(bright) == 1.0 and np.mean(bright[np.isfinite(bright)] == 1.0) > 0.5


def test_mounting_error_moves_the_measured_cloud():
    plate = Plate()
    nominal = LaserLineScanner(QUIET)
    error = pose_matrix([0.3, -0.2, 0.4], [0.001, -0.0015, 0.002])
    mounted = LaserLineScanner(QUIET, mounting_error=error)
    z_nominal = nominal.sweep_cloud(plate, length_mm=20.0)[0][..., 2]
    z_mounted = mounted.sweep_cloud(plate, length_mm=20.0)[0][..., 2]
    difference = np.nanmean(z_mounted - z_nominal)
    assert 0.2 < abs(difference) < 0.8
    assert np.allclose(mounted.true_scanner_to_gls, nominal.scanner_to_gls @ error)


def test_scanner_rejects_bad_parameters():
    scanner = LaserLineScanner()
    with pytest.raises(ValueError, match="speed_mm_s must be a positive finite number, got -15.0"):
        next(scanner.sweep(Plate(), speed_mm_s=-15.0))
    with pytest.raises(ValueError, match="step_mm must be a positive finite number, got 0.0"):
        scanner.sweep_cloud(Plate(), step_mm=0.0)
    with pytest.raises(ValueError, match="length_mm must be a positive finite number"):
        scanner.sweep_cloud(Plate(), length_mm=-1.0)
    with pytest.raises(ValueError, match="scanner point_spacing_mm must be a positive finite number"):
        ScannerSettings(point_spacing_mm=0.0)
    with pytest.raises(ValueError, match="scanner dropout_fraction must be in"):
        ScannerSettings(dropout_fraction=1.5)
    with pytest.raises(ValueError, match="scanner_to_gls must be a 4x4 transform"):
        LaserLineScanner(scanner_to_gls=np.eye(3))


# ---------------------------------------------------------------- configuration
def test_default_configuration_loads_and_builds_a_cell():
    config = load_sim_config()
    assert config.geometry == GEOMETRY
    assert config.scanner.speed_mm_s == 15.0 and config.scanner.step_mm == 0.1
    cell = SimulatedCell(config)
    assert cell.head.effects == config.effects
    assert np.allclose(cell.plate.normal, cell.head.physical.plate_normal)
    old_id = cell.plate.plate_id
    assert cell.exchange_plate() != old_id


def test_paper_like_default_deviations():
    """Commanded on the plate's plane through the nominal model, as a calibration does."""
    cell = SimulatedCell(load_sim_config())
    targets = grid()
    normal, origin = cell.plate.normal, cell.plate.origin
    z = origin[2] - (normal[0] * (targets[:, 0] - origin[0]) + normal[1] * (targets[:, 1] - origin[1])) / normal[2]
    setpoints = inverse(cell.config.geometry, targets[:, 0], targets[:, 1], z)
    landed = cell.head.mark(setpoints.alpha_x, setpoints.alpha_y)[:, :2]
    deviation = rigid_2d(landed, targets) - targets
    size = np.linalg.norm(deviation, axis=1)
    assert np.sqrt(np.mean(size ** 2)) == pytest.approx(0.85, abs=0.1)
    assert size.max() == pytest.approx(2.1, abs=0.2)
    rms_x, rms_y = np.sqrt(np.mean(deviation ** 2, axis=0))
    assert rms_x == pytest.approx(0.8, abs=0.1) and rms_y == pytest.approx(0.3, abs=0.1)
    centre = np.hypot(*targets.T) < 30.0
    assert size[centre].mean() < 0.5 * size.mean()


def minimal(**blocks) -> dict:
    return {"/**": {"ros__parameters": blocks}}


def test_configuration_rejects_bad_values(tmp_path):
    with pytest.raises(ValueError, match="unknown effect 'lens_wobble'"):
        sim_config_from_dict(minimal(effects={"lens_wobble": [1.0]}))
    with pytest.raises(ValueError, match="scanner speed_mm_s must be a positive finite number, got -15.0"):
        sim_config_from_dict(minimal(scanner={"speed_mm_s": -15.0}))
    with pytest.raises(ValueError, match="scanner step_mm must be a positive finite number, got 0.0"):
        sim_config_from_dict(minimal(scanner={"step_mm": 0.0}))
    with pytest.raises(ValueError, match="scanner point_spacing_mm must be a positive finite number"):
        sim_config_from_dict(minimal(scanner={"point_spacing_mm": -0.1}))
    with pytest.raises(ValueError, match="unknown scanner parameter.*'scanner.pixel_mm'"):
        sim_config_from_dict(minimal(scanner={"pixel_mm": 0.1}))
    with pytest.raises(ValueError, match="mark_speed_mm_s must be positive"):
        sim_config_from_dict(minimal(marking={"mark_speed_mm_s": 0.0}))
    with pytest.raises(ValueError, match="not 'head.effects'"):
        sim_config_from_dict(minimal(head={"effects": {"galvo_gain_x": [0.01]}}))
    path = tmp_path / "sim.yaml"
    path.write_text("/**:\n  ros__parameters:\n    effects:\n      lens_wobble: [1.0]\n")
    with pytest.raises(ValueError, match=f"{path}: unknown effect 'lens_wobble'"):
        load_sim_config(path)
    assert isinstance(sim_config_from_dict(minimal()), SimConfig)


# ---------------------------------------------------------------- scanned marks, measured with the core
def measured_against_truth(per_side: int, size_mm: float) -> tuple[float, int]:
    """Mark a double-ring grid with the default (defective) cell on the ``ideal`` measurement chain
    (the algorithmic floor), sweep, measure with the core.

    Returns the RMS (mm) of measured centres against the true landed centres after a rigid
    alignment (no calibration involved), and the number of centres found.
    """
    from scipy.spatial import cKDTree

    from gls_calibration.fiducials.measure import measure_fiducials
    from gls_calibration.registration.rigid import fit_rigid
    from gls_calibration.scan.plate_pose import estimate_plate_pose

    config = load_sim_config(preset="ideal")
    span = size_mm + 20.0
    config = replace(config, scanner=replace(config.scanner, line_length_mm=span), sweep_length_mm=span,
                     scanner_to_gls=pose_matrix([0.0, span / 2, 325.0], [math.pi, 0.0, 0.0]))
    cell = SimulatedCell(config)
    truth = []
    for centre in grid(per_side, size_mm):
        landed = cell.mark_cartesian([ring(centre, radius) for radius in (2.5, 2.7)])
        truth.append(np.concatenate([polyline[:-1] for polyline in landed]).mean(axis=0))
    truth = np.array(truth)
    xyz, intensity = cell.sweep_cloud(seed=2)
    pose = estimate_plate_pose(xyz, head_direction=(0.0, 0.0, -1.0))   # the head is on the sensor side
    measurement = measure_fiducials(xyz, intensity, pose, expected_count=per_side ** 2)
    distance, nearest = cKDTree(truth).query(cell.scanner.to_gls(measurement.centres))
    assert distance.max() < 1.5          # the CAD mounting is off by about a millimetre at most
    transform = fit_rigid(measurement.centres, truth[nearest])
    residual = transform.apply(measurement.centres) - truth[nearest]
    return float(np.sqrt(np.mean(np.sum(residual ** 2, axis=1)))), len(measurement.centres)


def test_scanned_marks_recover_the_true_landing_points_small_grid():
    rms, found = measured_against_truth(5, 40.0)
    assert found == 25
    assert rms <= 0.02


@pytest.mark.slow
def test_scanned_marks_recover_the_true_landing_points_full_grid():
    rms, found = measured_against_truth(19, 190.0)
    assert found == 361
    assert rms <= 0.02


def _line_motion_run(start_ns: int):
    from scipy.spatial.transform import Rotation
    from gls_calibration.simulation.line_motion import MotionRun
    rows = 200
    stamps = start_ns + np.round(np.arange(rows) * (1e9 / 150.0)).astype(np.int64)
    poses = np.repeat(np.eye(4)[None], rows, axis=0)
    poses[:, 1, 3] = np.linspace(0.0, 20.0, rows)
    poses[:, :3, :3] = Rotation.from_rotvec(np.outer(np.linspace(0.0, 1e-3, rows), [0.0, 0.0, 1.0])).as_matrix()
    return MotionRun(int(stamps[0]), int(stamps[-1]), stamps, np.zeros((rows, 2, 4), np.float32), poses, None)


def test_reported_poses_do_not_depend_on_when_the_motion_ran():
    # A TF sample's pose at a given time into the motion is the same whenever the motion ran: absolute ns
    # (~1.8e18) as float64 keep only 256 ns, which made repeated simulated runs differ in the last digits
    # (3e-6 mm here before the fix).
    offsets = np.round(np.arange(-5, 700) * (1e9 / 250.0)).astype(np.int64)
    first, later = _line_motion_run(1_795_000_000_000_000_123), _line_motion_run(1_795_000_003_123_456_789)
    np.testing.assert_array_equal(first.flange_at(first.start_ns + offsets), later.flange_at(later.start_ns + offsets))
