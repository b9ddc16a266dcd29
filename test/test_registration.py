"""Tests of rigid fitting, measured-to-target pairing and deviations."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.registration.rigid import RigidTransform, deviations, fit_rigid, pair_with_targets

PITCH = 190.0 / 18


def planar_targets(per_side=19, size=190.0):
    grid = grid_targets(per_side, size)
    return np.column_stack([grid, np.zeros(len(grid))])


def scanner_from_gls(in_plane_deg, tilt_y_deg, tilt_x_deg, translation):
    """gls -> scanner transform whose scanner x axis, projected on the plate, is turned by in_plane_deg."""
    scanner_to_gls = Rotation.from_euler("ZYX", [in_plane_deg, tilt_y_deg, tilt_x_deg], degrees=True).as_matrix()
    return RigidTransform(scanner_to_gls, np.asarray(translation, dtype=float)).inverse()


def test_fit_rigid_recovers_a_random_motion_and_ignores_point_order():
    rng = np.random.default_rng(1)
    source = rng.normal(0.0, 50.0, (40, 3))
    truth = RigidTransform(Rotation.random(random_state=2).as_matrix(), rng.normal(0.0, 100.0, 3))
    target = truth.apply(source)
    fitted = fit_rigid(source, target)
    np.testing.assert_allclose(fitted.rotation, truth.rotation, atol=1e-9)
    np.testing.assert_allclose(fitted.translation, truth.translation, atol=1e-9)
    order = rng.permutation(40)
    shuffled = fit_rigid(source[order], target[order])
    np.testing.assert_allclose(shuffled.as_matrix(), fitted.as_matrix(), atol=1e-9)


def test_fit_rigid_returns_a_proper_rotation_for_coplanar_points():
    rng = np.random.default_rng(3)
    source = planar_targets(5, 40.0)
    truth = RigidTransform(Rotation.random(random_state=4).as_matrix(), rng.normal(0.0, 10.0, 3))
    fitted = fit_rigid(source, truth.apply(source) + rng.normal(0.0, 1e-3, source.shape))
    assert np.linalg.det(fitted.rotation) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(fitted.rotation, truth.rotation, atol=1e-4)


def test_fit_rigid_weights_switch_off_outliers():
    rng = np.random.default_rng(5)
    source = rng.normal(0.0, 30.0, (20, 3))
    truth = RigidTransform(Rotation.random(random_state=6).as_matrix(), np.array([1.0, 2.0, 3.0]))
    target = truth.apply(source)
    target[:3] += 50.0
    weights = np.ones(20)
    weights[:3] = 0.0
    np.testing.assert_allclose(fit_rigid(source, target, weights).as_matrix(), truth.as_matrix(), atol=1e-9)


def test_rigid_transform_inverse_and_matrix_agree():
    transform = RigidTransform(Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix(), [1.0, -2.0, 3.0])
    points = np.random.default_rng(7).normal(size=(5, 3))
    np.testing.assert_allclose(transform.inverse().apply(transform.apply(points)), points, atol=1e-12)
    homogeneous = np.column_stack([points, np.ones(5)]) @ transform.as_matrix().T
    np.testing.assert_allclose(homogeneous[:, :3], transform.apply(points), atol=1e-12)


@pytest.mark.parametrize("source, target, message", [
    (np.zeros((4, 3)), np.zeros((5, 3)), "source and target must have the same number of points"),
    (np.zeros((2, 3)), np.zeros((2, 3)), "source must hold at least 3 point"),
    (np.full((4, 3), np.nan), np.zeros((4, 3)), "source contains 12 NaN"),
    (np.zeros((4, 2)), np.zeros((4, 2)), r"source must have shape \(N, 3\)"),
])
def test_fit_rigid_rejects_bad_input(source, target, message):
    with pytest.raises(ValueError, match=message):
        fit_rigid(source, target)


def measured_scene(seed, in_plane_deg, tilt_y_deg, tilt_x_deg, targets=None, missing=7, extras=5):
    """Measured centres in the scanner frame: distorted, noisy, some missing, some spurious, one duplicate."""
    rng = np.random.default_rng(seed)
    targets = planar_targets() if targets is None else targets
    count = len(targets)
    landed = targets.copy()
    landed[:, 0] -= 0.8 * (targets[:, 0] / 95.0) ** 3 + 0.3 * targets[:, 0] / 95.0
    landed[:, 1] -= 0.4 * targets[:, 1] / 95.0
    landed[:, :2] += rng.normal(0.0, 0.02, (count, 2))
    kept = np.sort(rng.choice(count, count - missing, replace=False))
    # Spurious detections halfway between targets, out of any gate.
    spurious = targets[rng.choice(count, extras, replace=False)] + np.array([0.5 * PITCH, 0.5 * PITCH, 0.0])
    duplicate = landed[kept[10]] + np.array([0.6, -0.3, 0.0])
    points_gls = np.vstack([landed[kept], spurious, duplicate])
    to_scanner = scanner_from_gls(in_plane_deg, tilt_y_deg, tilt_x_deg, rng.uniform(-500.0, 500.0, 3))
    order = rng.permutation(len(points_gls))                       # detection order is arbitrary
    measured = to_scanner.apply(points_gls)[order]
    source_of = np.argsort(order)                                  # position of each gls row in measured
    truth = {
        "pairs": dict(zip(kept, source_of[:len(kept)])),
        "missing": np.setdiff1d(np.arange(count), kept),
        "spurious": np.sort(source_of[len(kept):len(kept) + extras]),
        "duplicate": source_of[-1],
        "scanner_to_gls": to_scanner.inverse(),
        "normal_in_scanner": to_scanner.rotation[:, 2],
    }
    return measured, targets, truth


def check_pairing(pairing, truth):
    assert dict(zip(pairing.target_index.tolist(), pairing.measured_index.tolist())) == {
        int(k): int(v) for k, v in truth["pairs"].items()}
    np.testing.assert_array_equal(pairing.missing_targets, truth["missing"])
    assert set(truth["spurious"]) | {truth["duplicate"]} == set(pairing.extra_measured.tolist())
    assert pairing.duplicate_measured.tolist() == [truth["duplicate"]]
    # The recovered motion is the true one up to the effect of the distortion (well under 0.1 deg).
    relative = pairing.transform.rotation @ truth["scanner_to_gls"].rotation.T
    assert math.degrees(Rotation.from_matrix(relative).magnitude()) < 0.1
    assert pairing.rms_mm < 1.0          # the distortion field, not a mismatch


@pytest.mark.parametrize("seed, in_plane, tilt_y, tilt_x", [
    (10, 14.0, 25.0, -40.0), (11, -14.5, -50.0, 10.0), (12, 3.0, 0.0, 0.0), (13, -7.0, 70.0, 60.0)])
def test_pairing_recovers_correspondences_under_rotation_tilt_and_translation(seed, in_plane, tilt_y, tilt_x):
    measured, targets, truth = measured_scene(seed, in_plane, tilt_y, tilt_x)
    pairing = pair_with_targets(measured, targets)
    assert pairing.gate_mm == pytest.approx(0.4 * PITCH)
    check_pairing(pairing, truth)


def test_pairing_of_a_plate_seen_from_below_needs_the_normal_hint_on_a_symmetric_grid():
    measured, targets, truth = measured_scene(20, 9.0, 20.0, 170.0)
    pairing = pair_with_targets(measured, targets, measured_normal=truth["normal_in_scanner"])
    check_pairing(pairing, truth)


def test_pairing_picks_the_plate_side_with_more_pairs_on_an_asymmetric_layout():
    grid = planar_targets()
    # Remove the top-right block of targets: the layout has no mirror symmetry any more.
    asymmetric = grid[~((grid[:, 0] > 40.0) & (grid[:, 1] > 40.0))]
    measured, targets, truth = measured_scene(21, -11.0, 30.0, 160.0, targets=asymmetric)
    check_pairing(pair_with_targets(measured, targets), truth)


def test_pairing_outside_the_rotation_prior_fails_to_pair_everything():
    measured, targets, truth = measured_scene(22, 40.0, 0.0, 0.0)
    pairing = pair_with_targets(measured, targets, max_rotation_deg=15.0)
    assert pairing.target_index.size < len(truth["pairs"])


@pytest.mark.parametrize("kwargs, message", [
    ({"gate_mm": 0.0}, "gate_mm must be a positive finite number"),
    ({"max_rotation_deg": -1.0}, "max_rotation_deg must be a non-negative finite number"),
    ({"measured_normal": (0.0, 0.0, 0.0)}, "measured_normal must be a non-zero 3-vector"),
])
def test_pairing_rejects_bad_options(kwargs, message):
    targets = planar_targets(3, 10.0)
    with pytest.raises(ValueError, match=message):
        pair_with_targets(targets, targets, **kwargs)


def test_pairing_rejects_collinear_points():
    line = np.column_stack([np.arange(5.0), np.zeros(5), np.zeros(5)])
    with pytest.raises(ValueError, match="measured are collinear"):
        pair_with_targets(line, planar_targets(3, 10.0))


def test_deviations_are_target_minus_measured():
    targets = planar_targets(3, 10.0)
    measured = targets + np.array([0.1, -0.2, 0.0])
    np.testing.assert_allclose(deviations(targets, measured), np.tile([-0.1, 0.2, 0.0], (9, 1)))
    with pytest.raises(ValueError, match="targets and measured_in_gls must have the same shape"):
        deviations(targets, measured[:5])


def test_a_pairing_of_every_point_is_not_tried_on_the_other_side(monkeypatch):
    """The other side of the plane is registered only when the first leaves a point unpaired."""
    from gls_calibration.registration import rigid

    targets = np.column_stack([grid_targets(5, 40.0), np.zeros(25)])
    calls = []
    original = rigid._register

    def counting(*args):
        calls.append(args[4].axes[2].copy())
        return original(*args)
    monkeypatch.setattr(rigid, "_register", counting)
    complete = pair_with_targets(targets[:-2] + [1.0, 2.0, 0.0], targets)
    assert len(calls) == 1 and len(complete.target_index) == 23
    calls.clear()
    stray = np.vstack([targets[:-2], [[500.0, 500.0, 0.0]]])      # a point no target is near
    pair_with_targets(stray, targets)
    assert len(calls) == 2 and calls[0] @ calls[1] < 0.0
