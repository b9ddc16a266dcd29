"""Physical deviation model, sum model and physics-then-RBF training, on truth-head data."""
from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from gls_calibration.correction.setpoints import CalibratedRegion, Correction
from gls_calibration.discrepancy import align_rigid_2d
from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.geometry.optics import PhysicalHead
from gls_calibration.models import rbf
from gls_calibration.models.deviation_models import model_from_dict
from gls_calibration.models.physical_model import PhysicalDeviationModel, SumModel, train_physics_then_rbf

GEOMETRY = HeadGeometry()
# Two hidden effects of the paper-like size: X gain error and the plate tilt (keystone).
HIDDEN = {"galvo_gain_x": [0.0107], "plate_tilt": [0.0167, -0.01]}
VALIDATION = grid_targets(18, 180.0)     # half a pitch off the 19x19 training grid
SMALL_SEARCH = dict(spreads_mm=(35.0, 60.0), mse_goals_mm2=(0.0005,), tps_smoothings=(0.0, 100.0))


def truth_landing(commanded_xy: np.ndarray, effects=HIDDEN) -> np.ndarray:
    """Where the truth head lands (N, 2), gls frame, when commanded nominally to ``commanded_xy``."""
    joints = inverse(GEOMETRY, commanded_xy[:, 0], commanded_xy[:, 1])
    return PhysicalHead(GEOMETRY, effects).land(joints.alpha_x, joints.alpha_y)[:, :2]


def training_data(per_side: int, seed: int, effects=HIDDEN, noise_mm: float = 0.005):
    """Targets and deviations ``Q - P`` of a noisy measurement in a randomly moved frame."""
    rng = np.random.default_rng(seed)
    targets = grid_targets(per_side, 190.0)
    landed = truth_landing(targets, effects) + rng.normal(0.0, noise_mm, targets.shape)
    angle = rng.uniform(-math.pi, math.pi)
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    measured = landed @ rotation.T + rng.uniform(-50.0, 50.0, 2)
    _, aligned = align_rigid_2d(measured, targets)
    return targets, targets - aligned


def true_error_rms(model=None, effects=HIDDEN) -> float:
    """RMS (mm) of the true landing error on the validation grid, corrected by ``model``, after rigid alignment."""
    models = [] if model is None else [model]
    region = CalibratedRegion(-95.0, 95.0, -95.0, 95.0) if models else None
    setpoints = Correction(GEOMETRY, models, region).correct(VALIDATION[:, 0], VALIDATION[:, 1])
    commanded = np.column_stack([setpoints.x, setpoints.y])
    _, aligned = align_rigid_2d(truth_landing(commanded, effects), VALIDATION)
    return float(np.sqrt(np.mean(np.sum((VALIDATION - aligned) ** 2, axis=1))))


@pytest.fixture(scope="module")
def trained_7x7():
    targets, deviations = training_data(7, seed=7)
    model, report = train_physics_then_rbf(targets, deviations, GEOMETRY, **SMALL_SEARCH)
    return targets, deviations, model, report


def sample_points(seed: int = 3) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-95.0, 95.0, (50, 2))


def test_physical_model_round_trip_gives_equal_predictions(trained_7x7):
    physical = trained_7x7[3].physical_model
    copy = model_from_dict(yaml.safe_load(yaml.safe_dump(physical.to_dict())))
    assert isinstance(copy, PhysicalDeviationModel)
    np.testing.assert_allclose(copy(sample_points()), physical(sample_points()), rtol=0.0, atol=1e-12)
    first_order = PhysicalDeviationModel.from_dict({**physical.to_dict(), "inverse": False})
    np.testing.assert_allclose(first_order(sample_points()), physical.measured_deviation(sample_points()),
                               rtol=0.0, atol=1e-12)


def test_sum_model_round_trip_and_equals_the_sum_of_its_parts(trained_7x7):
    model = trained_7x7[2]
    assert isinstance(model, SumModel) and len(model.models) == 2
    points = sample_points()
    np.testing.assert_allclose(model(points), model.models[0](points) + model.models[1](points),
                               rtol=0.0, atol=1e-12)
    copy = model_from_dict(yaml.safe_load(yaml.safe_dump(model.to_dict())))
    assert [part.to_dict()["type"] for part in copy.models] == [part.to_dict()["type"] for part in model.models]
    np.testing.assert_allclose(copy(points), model(points), rtol=0.0, atol=1e-9)
    assert model(np.empty((0, 2))).shape == (0, 2)


def test_physics_names_the_hidden_effects_and_leaves_noise(trained_7x7):
    _, _, _, report = trained_7x7
    assert {"galvo_gain_x", "plate_tilt"} <= set(report.named_effects)
    assert report.method.startswith("physics+")
    assert report.deviation_rms_mm > 0.3
    assert report.residual_rms_mm < 0.02          # what the RBF gets: noise of 0.005 mm per axis and little else


def test_physical_part_reproduces_the_measured_deviations(trained_7x7):
    targets, deviations, _, report = trained_7x7
    physical = report.physical_model
    gap = deviations - physical.measured_deviation(targets)
    assert np.sqrt(np.mean(np.sum(gap ** 2, axis=1))) < 0.02
    # the exact inverse agrees with the first-order form up to second-order terms
    difference = physical(targets) - physical.measured_deviation(targets)
    assert 1e-4 < np.max(np.abs(difference)) < 0.1


def test_inverse_makes_the_modelled_landing_hit_the_target(trained_7x7):
    physical = trained_7x7[3].physical_model
    points = sample_points()
    np.testing.assert_allclose(physical.landing(points + physical(points)), points, rtol=0.0, atol=1e-8)


def test_correcting_with_the_model_reduces_the_true_error(trained_7x7):
    model, report = trained_7x7[2], trained_7x7[3]
    uncorrected = true_error_rms()
    assert uncorrected > 0.3
    assert true_error_rms(report.physical_model) < 0.05 * uncorrected
    assert true_error_rms(model) < 0.01
    # the opposite sign doubles the error instead
    wrong = PhysicalDeviationModel.from_dict({**report.physical_model.to_dict(), "inverse": False})
    assert true_error_rms(lambda points: -wrong(points)) > 1.5 * uncorrected


def test_physics_rbf_on_7x7_is_at_least_as_accurate_as_rbf_only_on_19x19(trained_7x7):
    model_7x7 = trained_7x7[2]
    targets, deviations = training_data(19, seed=19)
    rbf_19x19, _ = rbf.select_model(targets, deviations, **SMALL_SEARCH)
    assert true_error_rms(model_7x7) <= true_error_rms(rbf_19x19)


def test_without_a_named_effect_it_is_rbf_only():
    targets, deviations = training_data(7, seed=5, effects={})
    model, report = train_physics_then_rbf(targets, deviations, GEOMETRY, **SMALL_SEARCH)
    reference, _ = rbf.select_model(targets, deviations, **SMALL_SEARCH)
    assert report.named_effects == () and not report.uses_physics
    assert report.method == report.selection.method
    assert model.to_dict() == reference.to_dict()


@pytest.mark.parametrize("data, message", [
    ({"type": "physical", "effects": {}, "alignment": {"rotation_rad": 0.0, "translation_mm": [0.0, 0.0]}},
     "model description lacks key 'geometry'"),
    ({"type": "physical", "geometry": {"lens": 1.0}, "effects": {},
      "alignment": {"rotation_rad": 0.0, "translation_mm": [0.0, 0.0]}},
     "physical model geometry has unknown key\\(s\\) lens"),
    ({"type": "physical", "geometry": {}, "effects": {"wobble": [1.0]},
      "alignment": {"rotation_rad": 0.0, "translation_mm": [0.0, 0.0]}},
     "unknown effect 'wobble'"),
    ({"type": "physical", "geometry": {}, "effects": {},
      "alignment": {"rotation_rad": 0.0, "translation_mm": [0.0]}},
     "translation_mm must hold 2 values, got 1"),
    ({"type": "sum", "models": []}, "a sum model needs at least one model"),
    ({"type": "sum", "models": "ols_rbf"}, "sum model 'models' must be a list, got str"),
    ({"type": "sum", "models": [{"type": "spline3"}]}, "unknown model type 'spline3'"),
])
def test_bad_descriptions_are_refused(data, message):
    with pytest.raises(ValueError, match=message):
        model_from_dict(data)


def test_bad_training_input_is_refused():
    targets = grid_targets(3, 190.0)
    with pytest.raises(ValueError, match="targets_xy must hold at least 10 point\\(s\\), got 9"):
        train_physics_then_rbf(targets, np.zeros_like(targets))
    targets = grid_targets(4, 190.0)
    with pytest.raises(ValueError, match="targets_xy and deviations must have the same number of points"):
        train_physics_then_rbf(targets, np.zeros((15, 2)))
