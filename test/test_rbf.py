"""Tests of the OLS RBF network, the thin-plate spline model, cross-validation and model selection."""
import math

import numpy as np
import pytest

from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.models import model_selection, rbf
from gls_calibration.models.deviation_models import load_model_yaml, model_from_dict, save_model_yaml
from gls_calibration.models.rbf import (CrossValidation, OLSRBFNetwork, ThinPlateSplineModel, cross_validate,
                                        select_model)

GRID = grid_targets()


def distortion_field(points):
    """Smooth synthetic galvo distortion: polynomial terms up to cubic and a radial term, X larger than Y.

    Normalised to 0.85 mm RMS of |delta| over the 19x19 grid; zero at the centre.
    """
    def raw(p):
        s, t = p[:, 0] / 95.0, p[:, 1] / 95.0
        r2 = s * s + t * t
        dx = 0.55 * s + 0.25 * s * t + 0.35 * s ** 3 - 0.15 * s * t * t + 0.30 * s * r2 + 0.1 * (s * s - t * t)
        dy = 0.30 * t - 0.20 * s * s + 0.15 * t ** 3 + 0.10 * s * t + 0.18 * t * r2
        return np.column_stack([dx, dy])
    scale = 0.85 / math.sqrt(np.mean(np.sum(raw(GRID) ** 2, axis=1)))
    return scale * raw(np.asarray(points, dtype=float))


def noisy_samples(seed=0, noise=0.02):
    rng = np.random.default_rng(seed)
    return GRID, distortion_field(GRID) + rng.normal(0.0, noise, GRID.shape)


def dense_points(count=81, half=95.0):
    axis = np.linspace(-half, half, count)
    return np.column_stack([grid.ravel() for grid in np.meshgrid(axis, axis)])


def rms(values):
    return math.sqrt(np.mean(np.sum(values ** 2, axis=1)))


def test_constant_field_is_reproduced_exactly_by_the_bias_alone():
    X = grid_targets(7, 60.0)
    network = OLSRBFNetwork(X, np.tile([0.25, -0.5], (len(X), 1)))
    assert network.neuron_count == 0
    np.testing.assert_allclose(network(dense_points(11, 200.0)), np.tile([0.25, -0.5], (121, 1)), atol=1e-12)


def test_field_made_of_gaussian_units_is_fitted_exactly():
    X = grid_targets(11, 100.0)
    units = np.array([[-30.0, 20.0], [10.0, -40.0], [40.0, 40.0]])
    weights = np.array([[0.4, -0.2], [-0.3, 0.1], [0.2, 0.5]])
    truth = OLSRBFNetwork.from_dict({"type": "ols_rbf", "spread_mm": 35.0, "centres": units.tolist(),
                                     "weights": weights.tolist(), "bias": [0.05, -0.02]})
    network = OLSRBFNetwork(X, truth(X), spread_mm=35.0, mse_goal_mm2=1e-20)
    assert network.neuron_count <= len(X)
    assert {tuple(c) for c in units} <= {tuple(c) for c in network.centres[:3]}   # found first
    query = dense_points(41, 50.0)
    np.testing.assert_allclose(network(query), truth(query), atol=1e-8)


def test_spread_follows_the_matlab_convention():
    unit = OLSRBFNetwork.from_dict({"type": "ols_rbf", "spread_mm": 35.0, "centres": [[1.0, 2.0]],
                                    "weights": [[1.0, 2.0]], "bias": [0.0, 0.0]})
    np.testing.assert_allclose(unit(np.array([[1.0, 37.0]])), [[0.5, 1.0]], rtol=1e-14)
    np.testing.assert_allclose(unit(np.array([[1.0, 2.0]])), [[1.0, 2.0]], rtol=1e-14)


def test_training_stops_at_the_mse_goal():
    X, Y = noisy_samples(1)
    network = OLSRBFNetwork(X, Y, spread_mm=35.0, mse_goal_mm2=0.0005)
    assert 0 < network.neuron_count <= len(X)
    assert network.training_mse_mm2 <= 0.0005
    one_fewer = OLSRBFNetwork(X, Y, spread_mm=35.0, mse_goal_mm2=0.0005, max_neurons=network.neuron_count - 1)
    assert one_fewer.neuron_count == network.neuron_count - 1
    assert one_fewer.training_mse_mm2 > 0.0005
    np.testing.assert_array_equal(one_fewer.centres, network.centres[:-1])     # greedy: same path


def test_max_neurons_bounds_the_network():
    X, Y = noisy_samples(2)
    network = OLSRBFNetwork(X, Y, spread_mm=35.0, mse_goal_mm2=0.0, max_neurons=5)
    assert network.neuron_count == 5 and network.weights.shape == (5, 2)


def test_predictions_are_invariant_to_translating_inputs_and_queries_together():
    X, Y = noisy_samples(3)
    shift = np.array([1234.5, -678.25])
    query = np.random.default_rng(4).uniform(-95.0, 95.0, (500, 2))
    original = OLSRBFNetwork(X, Y)
    shifted = OLSRBFNetwork(X + shift, Y)
    np.testing.assert_allclose(shifted.centres - shift, original.centres, atol=1e-9)
    np.testing.assert_allclose(shifted(query + shift), original(query), atol=1e-9)


def test_batch_and_single_point_evaluation_agree():
    X, Y = noisy_samples(5)
    query = np.random.default_rng(6).uniform(-120.0, 120.0, (3000, 2))
    forms = set()
    for goal in (0.001, 0.0002):        # few units (expanded form) and many (separable form)
        network = OLSRBFNetwork(X, Y, spread_mm=30.0, mse_goal_mm2=goal)
        forms.add(network._separable)
        batch = network(query)
        singles = np.vstack([network(point[None, :]) for point in query[:50]])
        np.testing.assert_allclose(singles, batch[:50], atol=1e-12)
        design = np.exp(-math.log(2.0) * np.sum((query[:, None] - network.centres) ** 2, axis=2) / 30.0 ** 2)
        np.testing.assert_allclose(batch, design @ network.weights + network.bias, atol=1e-12)
    assert forms == {True, False}


def test_save_and_load_give_identical_predictions(tmp_path):
    X, Y = noisy_samples(7)
    query = dense_points(31)
    for model in (OLSRBFNetwork(X, Y), ThinPlateSplineModel(X, Y, smoothing=100.0)):
        path = tmp_path / f"{model.to_dict()['type']}.yaml"
        save_model_yaml(path, model)
        loaded = load_model_yaml(path)
        assert type(loaded) is type(model)
        np.testing.assert_array_equal(loaded(query), model(query))
        assert model_from_dict(model.to_dict()).to_dict() == model.to_dict()


def test_a_network_of_the_bias_alone_survives_a_yaml_round_trip(tmp_path):
    X = GRID
    Y = np.tile([0.01, -0.02], (X.shape[0], 1))     # constant: the bias meets the goal, no unit is added
    network = OLSRBFNetwork(X, Y)
    assert network.neuron_count == 0
    save_model_yaml(tmp_path / "bias.yaml", network)
    loaded = load_model_yaml(tmp_path / "bias.yaml")
    assert loaded.neuron_count == 0
    np.testing.assert_allclose(loaded(dense_points(5)), network(dense_points(5)), atol=1e-15)


def test_thin_plate_spline_interpolates_without_smoothing_and_smooths_with_it():
    X, Y = noisy_samples(8)
    exact = ThinPlateSplineModel(X, Y)
    np.testing.assert_allclose(exact(X), Y, atol=1e-8)
    smooth = ThinPlateSplineModel(X, Y, smoothing=1000.0)
    assert rms(smooth(X) - Y) > 1e-3
    assert smooth(dense_points(5)).shape == (25, 2)


def test_thin_plate_spline_solves_the_same_system_as_scipy():
    from scipy.interpolate import RBFInterpolator
    X, Y = noisy_samples(13)
    query = dense_points(41, 120.0)
    for smoothing in (0.0, 300.0):
        reference = RBFInterpolator(X, Y, kernel="thin_plate_spline", smoothing=smoothing)(query)
        np.testing.assert_allclose(ThinPlateSplineModel(X, Y, smoothing)(query), reference, atol=1e-9)


@pytest.mark.parametrize("offset", ["default", 0.0])
def test_thin_plate_spline_blocks_agree_with_the_kernel_formula_at_and_between_centres(monkeypatch, offset):
    # Large batches take the blocked path (BLAS distances, OpenCV logarithm, an offset that keeps
    # r^2 positive); at a centre itself phi(0) = 0 must still hold. Without the offset, round-off
    # makes r^2 zero or negative at the centres: those rows must be recomputed, not returned as NaN.
    if offset != "default":
        monkeypatch.setattr("gls_calibration.models.thin_plate_spline._OFFSET_PER_SQUARED_MM", offset)
    X, Y = noisy_samples(14)
    spline = ThinPlateSplineModel(X, Y)
    query = np.vstack([X, np.random.default_rng(15).uniform(-120.0, 120.0, (2000, 2))])
    squared = np.sum((query[:, None, :] - spline.centres) ** 2, axis=2)
    phi = 0.5 * squared * np.log(np.where(squared > 0.0, squared, 1.0))
    expected = phi @ spline.weights + spline.affine[0] + query @ spline.affine[1:]
    # 5e-12 mm: the round-off of the expanded distances is ~2e-12 here, the offset's share 1e-12.
    np.testing.assert_allclose(spline(query), expected, rtol=0.0, atol=5e-12)
    np.testing.assert_allclose(spline(X), Y, rtol=0.0, atol=1e-9)


def test_thin_plate_spline_loads_without_refitting(monkeypatch):
    X, Y = noisy_samples(14)
    spline = ThinPlateSplineModel(X, Y, smoothing=10.0)
    description = spline.to_dict()
    assert {"centres", "weights", "affine"} <= set(description) and "values" not in description
    monkeypatch.setattr(np.linalg, "solve", lambda *a, **k: pytest.fail("loading refitted the spline"))
    loaded = model_from_dict(description)
    query = dense_points(23)
    np.testing.assert_array_equal(loaded(query), spline(query))
    singles = np.vstack([loaded(point[None, :]) for point in query[:20]])   # the small-batch path
    np.testing.assert_allclose(singles, spline(query[:20]), atol=1e-12)


def test_a_version_1_spline_of_training_data_still_loads():
    X, Y = noisy_samples(15)
    old = {"type": "thin_plate_spline", "smoothing": 10.0, "points": X.tolist(), "values": Y.tolist()}
    np.testing.assert_allclose(model_from_dict(old)(X), ThinPlateSplineModel(X, Y, 10.0)(X), atol=1e-12)


def test_selected_model_meets_the_accuracy_target_on_a_dense_held_out_grid():
    X, Y = noisy_samples(9)
    initial = rms(distortion_field(X))
    assert initial == pytest.approx(0.85)
    model, report = select_model(X, Y)
    query = dense_points(96, 94.0)               # between and away from the training targets
    residual = rms(model(query) - distortion_field(query))
    assert residual <= 0.03
    assert len(report.candidates) == 6 * 3 + 6
    assert report.chosen.cv_rms_mm == min(score.cv_rms_mm for score in report.candidates)
    assert report.method == report.chosen.method
    assert report.to_dict()["chosen"]["cv_rms_mm"] == report.chosen.cv_rms_mm


def test_published_settings_also_beat_the_target():
    X, Y = noisy_samples(10)
    query = dense_points(96, 94.0)
    assert rms(OLSRBFNetwork(X, Y, 35.0, 0.0005)(query) - distortion_field(query)) <= 0.03


def test_cross_validation_is_seeded_and_consistent():
    X, Y = noisy_samples(11)

    def make(x, y):
        return OLSRBFNetwork(x, y, 35.0, 0.0005)

    first = cross_validate(make, X, Y, folds=4, seed=3)
    assert isinstance(first, CrossValidation)
    assert first.residuals.shape == (361, 2) and len(first.fold_rms_mm) == 4
    assert first.rms_mm == pytest.approx(rms(first.residuals))
    assert cross_validate(make, X, Y, folds=4, seed=3).rms_mm == first.rms_mm
    assert cross_validate(make, X, Y, folds=4, seed=4).rms_mm != first.rms_mm
    constant = cross_validate(lambda x, y: OLSRBFNetwork(x, y), X, np.ones_like(Y), folds=3)
    assert constant.rms_mm < 1e-12


def test_selection_by_cross_validation_prefers_the_truth_like_candidate():
    # Data from a spline with heavy noise: an interpolating candidate must lose to a smoothing one.
    X, Y = noisy_samples(12, noise=0.2)
    model, report = select_model(X, Y, spreads_mm=(), tps_smoothings=(0.0, 1000.0))
    assert report.chosen.parameters == {"smoothing": 1000.0}
    assert model.smoothing == 1000.0 and model.centres.shape == (361, 2)        # refitted on all data


@pytest.mark.parametrize("X, Y, kwargs, message", [
    (np.empty((0, 2)), np.empty((0, 2)), {}, "X must hold at least 1 point"),
    ([[0.0, np.nan]], [[0.0, 0.0]], {}, "X contains 1 NaN or infinite value"),
    ([[0.0, 0.0]], [[0.0, np.inf]], {}, "Y contains 1 NaN or infinite value"),
    ([[0.0, 0.0], [1.0, 1.0]], [[0.0, 0.0]], {}, "X and Y must have the same number of points, got 2 and 1"),
    ([[0.0, 0.0, 0.0]], [[0.0, 0.0]], {}, r"X must have shape \(N, 2\)"),
    ([[0.0, 0.0]], [[0.0, 0.0]], {"spread_mm": 0.0}, "spread_mm must be a positive finite number, got 0.0"),
    ([[0.0, 0.0]], [[0.0, 0.0]], {"spread_mm": -3}, "spread_mm must be a positive finite number, got -3"),
    ([[0.0, 0.0]], [[0.0, 0.0]], {"mse_goal_mm2": -1e-3},
     "mse_goal_mm2 must be a non-negative finite number, got -0.001"),
    ([[0.0, 0.0]], [[0.0, 0.0]], {"max_neurons": 0}, "max_neurons must be an integer >= 1, got 0"),
])
def test_network_rejects_bad_input(X, Y, kwargs, message):
    with pytest.raises(ValueError, match=message):
        OLSRBFNetwork(X, Y, **kwargs)


def test_evaluation_rejects_bad_points():
    network = OLSRBFNetwork(grid_targets(3, 10.0), np.zeros((9, 2)))
    with pytest.raises(ValueError, match="points contains 1 NaN or infinite value"):
        network(np.array([[0.0, np.nan]]))
    with pytest.raises(ValueError, match=r"points must have shape \(N, 2\)"):
        network(np.zeros((3, 3)))


def test_thin_plate_spline_rejects_negative_smoothing():
    with pytest.raises(ValueError, match="smoothing must be a non-negative finite number"):
        ThinPlateSplineModel(GRID, np.zeros_like(GRID), smoothing=-1.0)


@pytest.mark.parametrize("count, folds, message", [
    (10, 1, "folds must be an integer >= 2, got 1"),
    (3, 5, "cannot split 3 point\\(s\\) into 5 folds"),
])
def test_cross_validation_rejects_bad_folds(count, folds, message):
    X = np.random.default_rng(0).normal(size=(count, 2))
    with pytest.raises(ValueError, match=message):
        cross_validate(lambda x, y: OLSRBFNetwork(x, y), X, X, folds=folds)
    with pytest.raises(ValueError, match=message):
        select_model(X, X, folds=folds)


def test_model_from_dict_rejects_unknown_types():
    with pytest.raises(ValueError,
                       match="unknown model type 'spline3'; known types: ols_rbf, physical, sum, thin_plate_spline"):
        model_from_dict({"type": "spline3"})
    with pytest.raises(ValueError, match="model description lacks key 'centres'"):
        model_from_dict({"type": "ols_rbf", "spread_mm": 35.0})


def test_blocked_folds_hold_out_whole_blocks_and_balance_the_folds():
    axis = np.linspace(-90.0, 90.0, 19)
    points = np.column_stack([value.ravel() for value in np.meshgrid(axis, axis)])
    split = model_selection._fold_indices(len(points), 5, 0, points, block_mm=40.0)
    assert sorted(np.concatenate(split).tolist()) == list(range(len(points)))
    block = np.floor((points - points.min(axis=0)) / 40.0)
    for fold in split:
        others = np.setdiff1d(np.arange(len(points)), fold)
        # no block is split between a fold and the rest
        held = {tuple(b) for b in block[fold]}
        assert not held & {tuple(b) for b in block[others]}
    sizes = [len(fold) for fold in split]
    assert max(sizes) - min(sizes) <= 40          # at most about one block apart
    with pytest.raises(ValueError, match="cannot make 5 folds"):
        model_selection._fold_indices(len(points), 5, 0, points, block_mm=500.0)


def test_blocked_cv_is_not_fooled_by_errors_correlated_between_neighbours():
    # a smooth field measured with an error correlated over ~20 mm: a random split rewards a model
    # that follows the error (its neighbours are in training), blocks wider than that do not
    rng = np.random.default_rng(3)
    axis = np.linspace(-90.0, 90.0, 19)
    points = np.column_stack([value.ravel() for value in np.meshgrid(axis, axis)])
    truth = np.column_stack([0.5 * np.sin(points[:, 0] / 70.0), 0.4 * np.cos(points[:, 1] / 60.0)])
    waves = rng.normal(size=(12, 2)) / 15.0
    phases = rng.uniform(0, 2 * np.pi, 12)
    error = np.column_stack([sum(0.02 * np.sin(points @ w + p) for w, p in zip(waves[:6], phases[:6])),
                             sum(0.02 * np.sin(points @ w + p) for w, p in zip(waves[6:], phases[6:]))])
    measured = truth + error + rng.normal(0, 0.003, truth.shape)

    def tps(smoothing):
        return lambda x, y: rbf.ThinPlateSplineModel(x, y, smoothing)
    random_cv = rbf.cross_validate(tps(0.0), points, measured, 5, 0).rms_mm
    blocked_cv = rbf.cross_validate(tps(0.0), points, measured, 5, 0, block_mm=40.0).rms_mm
    assert blocked_cv > 1.5 * random_cv     # the random split's figure is the optimistic one
