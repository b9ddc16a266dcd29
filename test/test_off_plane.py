"""Off the calibration plane: correction through Q' on a head whose exit rays are straight.

The head of this test is independent of the correction code: commanded mechanical angles are
distorted nonlinearly (a radial and an asymmetric term, ~1 mm at the field's edge), and the spot
lands where the published closed form (``kinematics.forward``) puts that ray at the target's
height. Its rays are straight after the last mirror, so a correction learned on z = 0 is exactly
right along the ray through Q' and only approximately right at Q's own (x, y).
"""
import numpy as np
import pytest

from gls_calibration.correction.setpoints import CalibratedRegion, Correction
from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.geometry.kinematics import HeadGeometry, forward, inverse
from gls_calibration.models.rbf import ThinPlateSplineModel

GEOMETRY = HeadGeometry()


def true_landing(alpha_x, alpha_y, z):
    """Where the straight-ray head lands (mm) on the plane at height ``z`` for commanded angles (rad)."""
    radius2 = alpha_x ** 2 + alpha_y ** 2
    distorted_x = alpha_x * (1.0 + 0.4 * radius2) + 0.1 * alpha_y ** 2
    distorted_y = alpha_y * (1.0 + 0.3 * radius2) - 0.1 * alpha_x * alpha_y
    return np.column_stack(forward(GEOMETRY, distorted_x, distorted_y, z))


@pytest.fixture(scope="module")
def correction():
    # The calibration flow on z = 0: command the grid nominally, train at the landed points P on Q - P.
    targets = grid_targets(19, 190.0)
    joints = inverse(GEOMETRY, targets[:, 0], targets[:, 1])
    landed = true_landing(joints.alpha_x, joints.alpha_y, 0.0)
    assert 0.5 < np.max(np.linalg.norm(targets - landed, axis=1)) < 3.0        # a paper-like field
    model = ThinPlateSplineModel(landed, targets - landed)
    return Correction(GEOMETRY, [model], CalibratedRegion.from_points(targets, plane_z_mm=0.0))


def landing_errors(correction, z, through_q_prime=True):
    """|true landing - target| (mm) over a validation grid between the training targets at height z."""
    targets = grid_targets(18, 180.0)
    heights = np.full(len(targets), float(z))
    if through_q_prime:
        result = correction.correct(targets[:, 0], targets[:, 1], heights)
        alpha_x, alpha_y = result.alpha_x, result.alpha_y
    else:   # the old rule: the model evaluated at Q's own (x, y)
        dx, dy, _ = correction.deviation(targets[:, 0], targets[:, 1])
        joints = inverse(GEOMETRY, targets[:, 0] + dx, targets[:, 1] + dy, heights)
        alpha_x, alpha_y = joints.alpha_x, joints.alpha_y
    return np.linalg.norm(true_landing(alpha_x, alpha_y, z) - targets, axis=1)


def rms(values):
    return float(np.sqrt(np.mean(values ** 2)))


@pytest.mark.parametrize("z", [-25.0, -10.0, -5.0, 5.0, 10.0, 25.0])
def test_true_error_off_the_plane_stays_close_to_the_on_plane_error(correction, z):
    on_plane = rms(landing_errors(correction, 0.0))
    assert on_plane < 0.005
    off_plane = rms(landing_errors(correction, z))
    if abs(z) <= 10.0:
        assert off_plane <= 1.5 * on_plane, (z, off_plane, on_plane)
    assert off_plane <= 2.0 * on_plane, (z, off_plane, on_plane)


def test_evaluating_at_q_itself_is_worse_off_the_plane(correction):
    # Shows that the test can fail: the old rule misses by far more at +-10 mm on this head.
    for z in (-10.0, 10.0):
        assert rms(landing_errors(correction, z, through_q_prime=False)) > 3.0 * rms(landing_errors(correction, z))


def test_on_the_plane_the_rule_is_the_correction_at_q(correction):
    points = np.random.default_rng(0).uniform(-90.0, 90.0, (50, 2))
    result = correction.correct(points[:, 0], points[:, 1])
    dx, dy, _ = correction.deviation(points[:, 0], points[:, 1])
    np.testing.assert_allclose(result.x, points[:, 0] + dx, atol=1e-12)
    np.testing.assert_allclose(result.y, points[:, 1] + dy, atol=1e-12)


def test_the_focus_is_set_for_the_true_height(correction):
    result = correction.correct([40.0, -60.0], [30.0, 70.0], [10.0, -20.0])
    joints = inverse(GEOMETRY, result.x, result.y, np.array([10.0, -20.0]))
    np.testing.assert_allclose(result.focus_shift, joints.focus_shift, atol=1e-12)
    # The commanded point lies on the corrected ray at the target's height.
    np.testing.assert_allclose(np.column_stack(forward(GEOMETRY, result.alpha_x, result.alpha_y, [10.0, -20.0])),
                               np.column_stack([result.x, result.y]), atol=1e-9)
