"""The calibration certificate (issue 30): U from a named budget, stored, served, and its coverage."""
from __future__ import annotations

import math

import numpy as np
import pytest

from gls_calibration.calibration.stated_accuracy import ChainCheck
from gls_calibration.calibration.uncertainty import (COVERAGE_FACTOR, CertificateSettings, TrainingData,
                                                     UncertaintyGrid, bilinear, uncertainty_budget)
from gls_calibration.models.linear_response import response_matrix
from gls_calibration.models.rbf import OLSRBFNetwork, ThinPlateSplineModel

REGION = {"x_min": -60.0, "x_max": 60.0, "y_min": -60.0, "y_max": 60.0, "plane_z_mm": 0.0}


def grid_data(seed: int = 3, per_side: int = 9, noise_mm: float = 0.004):
    rng = np.random.default_rng(seed)
    axis = np.linspace(-55.0, 55.0, per_side)
    xy = np.array([(x, y) for y in axis for x in axis]) + rng.normal(0.0, 0.2, (per_side ** 2, 2))
    field = np.column_stack([1e-3 * xy[:, 0] + 2e-5 * xy[:, 0] * xy[:, 1], -8e-4 * xy[:, 1] + 1e-5 * xy[:, 0] ** 2])
    return xy, field, field + rng.normal(0.0, noise_mm, field.shape)


@pytest.mark.parametrize("make", [lambda x, y: OLSRBFNetwork(x, y, 35.0, 1e-6),
                                  lambda x, y: ThinPlateSplineModel(x, y, 10.0),
                                  lambda x, y: ThinPlateSplineModel(x, y, 0.0)])
def test_response_matrix_reproduces_the_trained_model(make):
    xy, _, noisy = grid_data()
    model = make(xy, noisy)
    points = np.random.default_rng(1).uniform(-60.0, 60.0, (50, 2))
    response = response_matrix(model.to_dict(), xy, points)
    assert response.shape == (50, len(xy))
    np.testing.assert_allclose(response @ noisy, model(points), atol=1e-9)


def test_propagated_variance_matches_monte_carlo_refits():
    # the exact propagation against refits on noise alone (linear: f(Y + E) - f(Y) = f(E))
    xy, _, noisy = grid_data()
    model = ThinPlateSplineModel(xy, noisy, 10.0)
    points = np.array([[0.0, 0.0], [30.0, -20.0], [58.0, 58.0]])
    sigma = np.full(len(xy), 0.004)
    exact = (response_matrix(model.to_dict(), xy, points) ** 2) @ sigma ** 2
    rng = np.random.default_rng(7)
    draws = np.array([ThinPlateSplineModel(xy, rng.normal(0.0, 0.004, noisy.shape), 10.0)(points)[:, 0]
                      for _ in range(400)])
    np.testing.assert_allclose(draws.var(axis=0), exact, rtol=0.2)


def test_response_matrix_refuses_a_model_that_is_not_linear_in_its_data():
    with pytest.raises(ValueError, match="model type 'physical' is not linear in its training data"):
        response_matrix({"type": "physical"}, np.zeros((3, 2)), np.zeros((1, 2)))


def test_budget_names_every_contribution_and_expands_by_the_2d_factor():
    xy, _, noisy = grid_data()
    model = ThinPlateSplineModel(xy, noisy, 10.0)
    training = TrainingData(xy, noisy, np.full(len(xy), 0.004), model.to_dict())
    check = ChainCheck((0.01, 0.012), "0+", "pose", "plate A", 100)
    budget = uncertainty_budget([training], REGION, 490.0, check, True)
    names = [item.name for item in budget.contributions]
    assert names == ["measurement", "chain", "model", "plate_height"]
    assert COVERAGE_FACTOR == pytest.approx(2.4477, abs=1e-4)
    chain = budget.contribution("chain")
    assert chain.rms_mm == pytest.approx(math.sqrt((0.01 ** 2 + 0.012 ** 2) / 2 - 0.004 ** 2))
    assert "reference check" in chain.basis
    per_axis = np.sqrt(sum(item.max_mm ** 2 for item in budget.contributions))
    assert budget.u95_full_mm <= COVERAGE_FACTOR * per_axis + 1e-12
    assert budget.u95_full_mm >= budget.u95_central_mm > 0.0
    # without a matching check the chain term is assumed, never zero
    assumed = uncertainty_budget([training], REGION, 490.0, check, False).contribution("chain")
    assert assumed.rms_mm == pytest.approx(0.004) and assumed.basis.startswith("assumed")


def test_model_term_grows_with_the_distance_to_the_nearest_fiducial():
    xy, _, noisy = grid_data(noise_mm=0.001)
    rough = noisy + 0.02 * np.sin(xy[:, [1, 0]] / 9.0)     # structure between fiducials the model misses
    training = TrainingData(xy, rough, np.full(len(xy), 0.001), ThinPlateSplineModel(xy, rough, 0.0).to_dict())
    budget = uncertainty_budget([training], REGION, 490.0, None, False, CertificateSettings(grid_step_mm=1.0))
    assert budget.contribution("model").max_mm > 0.002
    at_fiducial = budget.grid.at(xy[40:41, 0], xy[40:41, 1])[0]
    between = budget.grid.at(xy[40:41, 0] + 0.5 * budget.pitch_mm, xy[40:41, 1] + 0.5 * budget.pitch_mm)[0]
    assert between > at_fiducial


@pytest.mark.parametrize("change, message", [
    (lambda t: TrainingData(t.landed_xy[:5], t.corrections[:5], t.sigma_mm[:5], t.model),
     "training data must hold at least 10 points, got 5"),
    (lambda t: TrainingData(t.landed_xy, t.corrections, np.zeros(len(t.sigma_mm)), t.model),
     "sigma_mm must be positive for every centre"),
    (lambda t: TrainingData(t.landed_xy, np.full_like(t.corrections, np.nan), t.sigma_mm, t.model),
     "training data holds NaN or infinite values"),
])
def test_budget_refuses_bad_training_data(change, message):
    xy, _, noisy = grid_data()
    training = TrainingData(xy, noisy, np.full(len(xy), 0.004), ThinPlateSplineModel(xy, noisy, 10.0).to_dict())
    with pytest.raises(ValueError, match=message):
        uncertainty_budget([change(training)], REGION, 490.0, None, False)
    with pytest.raises(ValueError, match="needs at least one trained model"):
        uncertainty_budget([], REGION, 490.0, None, False)


@pytest.mark.parametrize("x, y, u, message", [
    ([0.0, 1.0], [0.0, 1.0], [[0.0, 1.0], [float("nan"), 1.0]], "key 'uncertainty.u_k2_mm' holds NaN"),
    ([0.0, 1.0], [0.0, 1.0], [[0.0, -1.0], [1.0, 1.0]], "key 'uncertainty.u_k2_mm' holds negative values"),
    ([1.0, 0.0], [0.0, 1.0], [[0.0, 1.0], [1.0, 1.0]], r"key 'uncertainty.x_mm' must increase strictly"),
    ([0.0, 1.0], [0.0, 1.0, 2.0], [[0.0, 1.0], [1.0, 1.0]], r"key 'uncertainty.u_k2_mm' must have shape \(3, 2\)"),
])
def test_grid_refuses_bad_values_naming_the_key(x, y, u, message):
    with pytest.raises(ValueError, match=message):
        UncertaintyGrid.from_dict({"x_mm": x, "y_mm": y, "u_k2_mm": u})


def test_bilinear_is_exact_on_a_plane_and_nan_outside():
    x, y = np.linspace(-2.0, 2.0, 5), np.linspace(-1.0, 3.0, 9)
    values = 1.0 + 2.0 * x[None, :] + 3.0 * y[:, None]
    points = np.random.default_rng(0).uniform(-1.9, 1.9, (20, 2))
    np.testing.assert_allclose(bilinear(x, y, values, points[:, 0], points[:, 1] + 1.0),
                               1.0 + 2.0 * points[:, 0] + 3.0 * (points[:, 1] + 1.0), atol=1e-12)
    assert np.isnan(bilinear(x, y, values, np.array([2.1]), np.array([0.0]))).all()
