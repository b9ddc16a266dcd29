"""The calibration certificate (issue 30): U from a named budget, stored, served, and its coverage."""
from __future__ import annotations

import math

import numpy as np
import pytest

from gls_calibration.calibration.stated_accuracy import ChainCheck
from gls_calibration.calibration.uncertainty import CertificateSettings, TrainingData, uncertainty_budget
from gls_calibration.correction.uncertainty_grid import COVERAGE_FACTOR, UncertaintyGrid, bilinear
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
    # without a matching check the chain term is assumed, never zero: what the plan removed, else one
    # centre's random part, flagged
    assumed = uncertainty_budget([training], REGION, 490.0, check, False, removed_chain_rms_mm=0.05)
    assert assumed.contribution("chain").rms_mm == pytest.approx(0.05 / math.sqrt(2.0))
    assert assumed.contribution("chain").basis.startswith("assumed")
    bare = uncertainty_budget([training], REGION, 490.0, check, False).contribution("chain")
    assert bare.rms_mm == pytest.approx(0.004) and "NOT supported" in bare.basis


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


# --- stored and served -----------------------------------------------------------------------------

def _stored(tmp_path, with_grid: bool = True, grid_override=None):
    """A 9x9 TPS calibration with its U map, saved to a store; (store, path, parsed record)."""
    from gls_calibration.calibration.record_file import new_record
    from gls_calibration.calibration.store import CalibrationStore
    from gls_calibration.geometry.kinematics import HeadGeometry

    xy, _, noisy = grid_data()
    model = ThinPlateSplineModel(xy, noisy, 10.0)
    region = {"type": "box", **REGION}
    budget = uncertainty_budget([TrainingData(xy, noisy, np.full(len(xy), 0.004), model.to_dict())],
                                REGION, 490.0, None, False)
    grid = budget.to_dict() if grid_override is None else grid_override
    zeros = np.zeros(len(xy))
    record = new_record(head=HeadGeometry(), plate_pose={"normal": [0, 0, 1], "centre": [0, 0, 0],
                                                         "rotation": np.eye(3), "flatness_rms_mm": 0.0},
                        models=[model.to_dict()], calibrated_region={**region, "taper_mm": 10.0},
                        hyper_parameters={}, metrics={},
                        fiducials={"target_x": xy[:, 0], "target_y": xy[:, 1], "measured_x": xy[:, 0],
                                   "measured_y": xy[:, 1], "measured_z": zeros, "dx": zeros, "dy": zeros},
                        uncertainty=grid if with_grid else None)
    store = CalibrationStore(tmp_path)
    return store, store.save(record), budget


def test_correction_serves_u_from_the_stored_grid_and_nan_outside(tmp_path):
    from gls_calibration.calibration.record import correction_from_record
    from gls_calibration.geometry.kinematics import HeadGeometry

    store, path, budget = _stored(tmp_path)
    correction = correction_from_record(store.load(path), HeadGeometry())
    x = np.array([0.0, 12.3, -59.0, 61.0, 200.0])
    y = np.array([0.0, -40.0, 59.0, 0.0, 0.0])
    answer = correction.correct(x, y, np.zeros(5))
    np.testing.assert_allclose(answer.uncertainty_k2_mm[:3], budget.grid.at(x[:3], y[:3]), rtol=1e-12)
    assert np.all(answer.uncertainty_k2_mm[:3] > 0.0)
    assert np.isnan(answer.uncertainty_k2_mm[3:]).all() and not answer.inside_calibrated_field[3:].any()
    for index in range(5):     # the one-target path answers the same
        one = correction.correct(x[index], y[index], 0.0).uncertainty_k2_mm[0]
        np.testing.assert_allclose(one, answer.uncertainty_k2_mm[index], rtol=1e-12, equal_nan=True)


def test_the_documented_evaluator_gives_the_served_u(tmp_path):
    import yaml

    from gls_calibration.calibration.record import correction_from_record
    from gls_calibration.geometry.kinematics import HeadGeometry
    from test_calibration_format import doc_evaluator

    store, path, _ = _stored(tmp_path)
    record = store.load(path).to_dict()
    rng = np.random.default_rng(4)
    x, y, z = rng.uniform(-70.0, 70.0, 300), rng.uniform(-70.0, 70.0, 300), rng.uniform(-20.0, 20.0, 300)
    served = correction_from_record(record, HeadGeometry()).correct(x, y, z).uncertainty_k2_mm
    documented = doc_evaluator()["uncertainty"](yaml.safe_load(yaml.safe_dump(record)), x, y, z)
    np.testing.assert_allclose(documented, served, rtol=0.0, atol=1e-9, equal_nan=True)
    assert np.isnan(served).any() and np.isfinite(served).any()


def test_an_older_file_without_the_grid_serves_nan_and_warns_once(tmp_path, caplog):
    import logging

    from gls_calibration.calibration import record as record_module
    from gls_calibration.calibration.record import correction_from_record
    from gls_calibration.geometry.kinematics import HeadGeometry

    record_module._warned.clear()
    store, path, _ = _stored(tmp_path, with_grid=False)
    with caplog.at_level(logging.WARNING, logger=record_module.__name__):
        first = correction_from_record(store.load(path), HeadGeometry())
        correction_from_record(store.load(path), HeadGeometry())
    warnings = [entry for entry in caplog.records if "without an uncertainty map" in entry.getMessage()]
    assert len(warnings) == 1
    answer = first.correct([0.0, 10.0], [0.0, 5.0], [0.0, 0.0])
    assert np.isnan(answer.uncertainty_k2_mm).all() and answer.inside_calibrated_field.all()


@pytest.mark.parametrize("change, message", [
    (lambda g: g["u_k2_mm"][3].__setitem__(2, -0.01), "key 'uncertainty.u_k2_mm' holds negative values"),
    (lambda g: g["x_mm"].reverse(), "key 'uncertainty.x_mm' must increase strictly"),
    (lambda g: g["y_mm"].__setitem__(1, g["y_mm"][0]), "key 'uncertainty.y_mm' must increase strictly"),
    (lambda g: g["u_k2_mm"][0].__setitem__(0, float("nan")), "key 'uncertainty.u_k2_mm' holds NaN"),
])
def test_a_bad_grid_is_refused_at_load_naming_the_key(tmp_path, change, message):
    import yaml

    from gls_calibration.calibration.record_file import CalibrationFileError, validate_record

    store, path, budget = _stored(tmp_path)
    record = store.load(path).to_dict()      # a plain copy to break
    change(record["uncertainty"])
    with pytest.raises(CalibrationFileError, match=message):
        validate_record(record, path)
    path.write_text(yaml.safe_dump(record))     # the file itself, as the nodes load it
    with pytest.raises(CalibrationFileError, match="key 'uncertainty"):
        store.load(path)


# --- in the calibrate flow and the report ----------------------------------------------------------

def test_a_small_calibration_reports_its_certificate_and_coverage_that_can_fail(tmp_path):
    import csv

    from gls_calibration.calibration.outcome import summarise
    from gls_calibration.report.certificate import coverage
    from gls_calibration.report.run_report import write_outcome_report
    from test_procedure import FAST, new_cell, run_calibrate

    cell = new_cell(tmp_path)
    outcome = run_calibrate(cell, cell.settings(**FAST), validate=True, force=True)
    summary = summarise(outcome)
    grid = outcome.candidate.correction.uncertainty
    assert grid is not None and summary.certificate_u95_full_mm >= summary.certificate_u95_central_mm > 0.0
    validation = outcome.validation
    u = grid.at(validation.paired_targets_xy[:, 0], validation.paired_targets_xy[:, 1])
    assert summary.certificate_coverage == pytest.approx(coverage(u, validation.true_deviations))
    # the check can fail: a U five times too small leaves most true errors outside it
    assert coverage(0.2 * u, validation.true_deviations) < 0.9
    assert "assumed" in summary.certificate_reference or "none" in summary.certificate_reference

    write_outcome_report(tmp_path / "report", outcome, summary)
    text = (tmp_path / "report" / "report.md").read_text()
    assert "## Certificate" in text and "| measurement |" in text and "uncertainty_map.png" in text
    with (tmp_path / "report" / "validation.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert list(rows[0]) == ["x_mm", "y_mm", "true_dx_mm", "true_dy_mm", "u_k2_mm"]
    assert len(rows) == len(validation.paired_targets_xy)
    np.testing.assert_allclose([float(row["u_k2_mm"]) for row in rows], u)


def test_a_physics_first_calibration_stores_and_serves_its_certificate(tmp_path, caplog):
    from gls_calibration.calibration.store import CalibrationStore
    from gls_calibration.simulation.direct_cell import DirectCell
    from gls_calibration.simulation.world import SimulatedCell
    from test_procedure import FAST, run_calibrate, small_config

    cell = DirectCell(SimulatedCell(small_config()), CalibrationStore(tmp_path / "store"), physics_first=True)
    with caplog.at_level("WARNING"):
        outcome = run_calibrate(cell, cell.settings(**FAST), validate=True, force=True)
    assert outcome.models[0].method.startswith("physics+") and outcome.candidate.record["models"][0]["type"] == "sum"
    assert "no uncertainty map" not in caplog.text
    grid = outcome.candidate.correction.uncertainty
    assert grid is not None and "uncertainty" in outcome.candidate.record
    targets = outcome.validation.paired_targets_xy
    served = outcome.candidate.correction.correct(targets[:, 0], targets[:, 1]).uncertainty_k2_mm
    assert np.all(np.isfinite(served)) and np.all(served > 0.0)


# --- served by the correction node ---------------------------------------------------------------

def test_both_correction_services_answer_u_and_a_bad_grid_keeps_the_served_calibration(ros_context, add_node,
                                                                                       tmp_path):
    import yaml
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from gls_calibration.calibration.record import correction_from_record
    from gls_calibration.geometry.kinematics import HeadGeometry
    from gls_calibration.nodes.correction import CorrectionNode
    from gls_calibration_msgs.srv import CorrectSetpoints, LoadCalibration
    from ros_helpers import call_service

    if "uncertainty_k2_mm" not in CorrectSetpoints.Response.get_fields_and_field_types():
        pytest.skip("gls_calibration_msgs was built before issue 30: rebuild msg_defs (make setup)")
    store, path, _ = _stored(tmp_path / "store")
    add_node(CorrectionNode(context=ros_context, parameter_overrides=[
        Parameter("calibration_dir", value=str(tmp_path / "store"))]))
    node = add_node(Node("certificate_client", namespace="gls", context=ros_context))
    x, y = np.array([0.0, 20.0, -55.0, 80.0]), np.array([0.0, -30.0, 50.0, 0.0])
    expected = correction_from_record(store.load(path), HeadGeometry()).correct(x, y).uncertainty_k2_mm
    for service in ("correct_setpoints", "correct_setpoints_batch"):
        response = call_service(node, node.create_client(CorrectSetpoints, service),
                                CorrectSetpoints.Request(x=x.tolist(), y=y.tolist()), 10.0)
        assert response.success, response.message
        np.testing.assert_allclose(np.asarray(response.uncertainty_k2_mm), expected, rtol=1e-12, equal_nan=True)
        assert np.isfinite(response.uncertainty_k2_mm[:3]).all() and math.isnan(response.uncertainty_k2_mm[3])

    record = store.load(path).to_dict()      # a plain copy to break
    record["uncertainty"]["x_mm"].reverse()
    path.write_text(yaml.safe_dump(record))
    answer = call_service(node, node.create_client(LoadCalibration, "correction/load"),
                          LoadCalibration.Request(file=str(path)), 10.0)
    assert not answer.success and "uncertainty.x_mm" in answer.message, answer.message
    kept = call_service(node, node.create_client(CorrectSetpoints, "correct_setpoints"),
                        CorrectSetpoints.Request(x=x.tolist(), y=y.tolist()), 10.0)
    np.testing.assert_allclose(np.asarray(kept.uncertainty_k2_mm), expected, rtol=1e-12, equal_nan=True)


def test_gls_export_and_gls_correct_write_the_uncertainty_column(tmp_path):
    from gls_calibration.calibration.record import correction_from_record
    from gls_calibration.cli.correct import main as correct_main
    from gls_calibration.cli.export import main as export_main
    from gls_calibration.geometry.kinematics import HeadGeometry

    store, path, _ = _stored(tmp_path / "store")
    correction = correction_from_record(store.load(path), HeadGeometry())
    targets = tmp_path / "targets.csv"
    targets.write_text("x,y\n0,0\n20,-30\n80,0\n")
    assert correct_main(["--calibration", str(path), str(targets), "--out", str(tmp_path / "out.csv")]) == 0
    table = np.genfromtxt(tmp_path / "out.csv", delimiter=",", names=True)
    np.testing.assert_allclose(table["uncertainty_k2_mm"],
                               correction.correct([0, 20, 80], [0, -30, 0]).uncertainty_k2_mm,
                               rtol=1e-12, equal_nan=True)
    assert export_main(["--calibration", str(path), "--out", str(tmp_path / "export"), "--pitch", "20"]) == 0
    exported = np.genfromtxt(tmp_path / "export" / "table.csv", delimiter=",", names=True)
    expected = correction.correct(exported["x"], exported["y"], exported["z"]).uncertainty_k2_mm
    np.testing.assert_allclose(exported["uncertainty_k2_mm"], expected, rtol=1e-12, equal_nan=True)
    assert np.isfinite(exported["uncertainty_k2_mm"]).any()


# --- physics first: the physical fit linearised at its solution ----------------------------------

def physics_first_data(effects, seed: int, outlier: bool):
    """13x13 targets and deviations ``Q - P`` of a simulated head with ``effects``, a smooth bump the
    physics cannot explain, 4 um noise and, with ``outlier``, one gross outlier (point 17)."""
    from gls_calibration.fiducials.targets import grid_targets
    from gls_calibration.geometry.kinematics import HeadGeometry, inverse
    from gls_calibration.geometry.optics import PhysicalHead

    rng = np.random.default_rng(seed)
    targets = grid_targets(13, 190.0)
    joints = inverse(HeadGeometry(), targets[:, 0], targets[:, 1])
    landed = PhysicalHead(HeadGeometry(), effects).land(joints.alpha_x, joints.alpha_y)[:, :2]
    landed += rng.normal(0.0, 0.004, landed.shape)
    landed[:, 0] += 0.02 * np.exp(-((targets[:, 0] - 30.0) ** 2 + (targets[:, 1] + 20.0) ** 2) / 2000.0)
    if outlier:
        landed[17] += (0.15, -0.1)
    return targets, targets - landed


# Two simulated heads: a gain and plate tilt (the spline takes the rest), and a Y gain, mirror offsets and a
# working distance with one gross outlier the effect fit leaves out (the OLS network takes the rest).
HEADS = [({"galvo_gain_x": [0.0107], "plate_tilt": [0.0167, -0.01]}, 5, False, "thin_plate_spline"),
         ({"galvo_gain_y": [-0.006], "mirror_offset": [0.8, -0.5], "working_distance": [2.0]}, 6, True, "ols_rbf")]


@pytest.mark.parametrize("effects, seed, outlier, residual_type", HEADS)
def test_physics_first_response_matches_finite_difference_refits_of_the_real_training(effects, seed, outlier,
                                                                                      residual_type):
    from gls_calibration.models.linear_response import physics_response_matrix
    from gls_calibration.models.physical_model import train_physics_then_rbf

    targets, deviations = physics_first_data(effects, seed, outlier)
    model, report = train_physics_then_rbf(targets, deviations)
    described = model.to_dict()
    assert report.uses_physics and described["models"][1]["type"] == residual_type
    assert bool(report.discrepancy.outliers) == outlier
    points = np.random.default_rng(2).uniform(-95.0, 95.0, (40, 2))
    response = physics_response_matrix(described, targets, deviations, points)
    assert response.shape == (80, 2 * len(targets))
    rng = np.random.default_rng(9)
    changes = {"noise": rng.normal(0.0, 1e-4, deviations.shape),
               "smooth": 1e-4 * np.column_stack([targets[:, 0] / 95.0, targets[:, 0] * targets[:, 1] / 95.0 ** 2]),
               "point 17": np.zeros_like(deviations)}
    changes["point 17"][17, 0] = 1e-3      # the outlier, when there is one: the physics must not move
    for name, change in changes.items():
        refit, refit_report = train_physics_then_rbf(targets, deviations + change)
        again = refit.to_dict()
        # the same selection (effects, units, spread or smoothing): only then is a refit a derivative
        assert refit_report.named_effects == report.named_effects, name
        for key in ("type", "spread_mm", "smoothing"):
            assert again["models"][1].get(key) == described["models"][1].get(key), name
        np.testing.assert_array_equal(again["models"][1]["centres"], described["models"][1]["centres"])
        moved = (refit(points) - model(points)).ravel()
        predicted = response @ change.ravel()
        assert np.linalg.norm(predicted - moved) <= 0.01 * np.linalg.norm(moved), name


def test_physics_first_budget_gives_a_finite_map_with_every_contribution():
    from gls_calibration.models.physical_model import train_physics_then_rbf

    effects, seed, outlier, _ = HEADS[0]
    targets, deviations = physics_first_data(effects, seed, outlier)
    model, _ = train_physics_then_rbf(targets, deviations)
    # trained as train_correction trains it: at the landed points P = Q - Y on the corrections Y
    training = TrainingData(targets - deviations, deviations, np.full(len(targets), 0.004), model.to_dict())
    budget = uncertainty_budget([training], {**REGION, "x_min": -95.0, "x_max": 95.0, "y_min": -95.0,
                                             "y_max": 95.0}, 490.0, None, False)
    assert np.all(np.isfinite(budget.grid.u_k2_mm)) and np.all(budget.grid.u_k2_mm > 0.0)
    measurement = budget.contribution("measurement")
    assert measurement.basis == "per-centre sigma through the model (physics first: linearised at its solution)"
    # 169 centres of 4 um: the fitted model averages them (below one centre's sigma in the field)
    assert 0.0 < measurement.rms_mm < 0.004
    assert budget.contribution("model").rms_mm > 0.0


def test_a_physics_first_training_that_names_no_effect_is_certified_where_it_was_trained():
    from gls_calibration.calibration.uncertainty import trained_at
    from gls_calibration.models.physical_model import train_physics_then_rbf

    from gls_calibration.fiducials.targets import grid_targets

    targets = grid_targets(13, 190.0)        # a nominal head with a narrow bump, measured with 4 um noise
    deviations = np.random.default_rng(4).normal(0.0, 0.004, targets.shape)
    deviations[:, 0] += 0.02 * np.exp(-((targets[:, 0] - 30.0) ** 2 + (targets[:, 1] + 20.0) ** 2) / 300.0)
    model, report = train_physics_then_rbf(targets, deviations)
    assert not report.uses_physics       # a plain spline, trained at the targets Q = P + Y
    assert model.to_dict()["type"] == "thin_plate_spline"
    landed = targets - deviations
    assert trained_at(model.to_dict(), landed, deviations) is not landed
    np.testing.assert_allclose(trained_at(model.to_dict(), landed, deviations), targets, atol=1e-12)
    budget = uncertainty_budget([TrainingData(landed, deviations, np.full(len(landed), 0.004), model.to_dict())],
                                REGION, 490.0, None, False)
    assert np.all(np.isfinite(budget.grid.u_k2_mm))
    with pytest.raises(ValueError, match="ols_rbf: its centres are neither the landed points nor the targets given"):
        trained_at({"type": "ols_rbf", "centres": [[500.0, 500.0]]}, landed, deviations)


def test_physics_response_and_budget_refuse_what_they_do_not_cover():
    from gls_calibration.models.linear_response import physics_response_matrix
    from gls_calibration.models.physical_model import train_physics_then_rbf

    xy, _, noisy = grid_data()
    with pytest.raises(ValueError, match=r"a physics-first model is the sum of a physical model and one of ols_rbf, "
                                         r"thin_plate_spline, got parts \[\]"):
        physics_response_matrix({"type": "sum", "models": []}, xy, noisy, xy)
    with pytest.raises(ValueError, match="model type must be 'sum', got 'thin_plate_spline'"):
        physics_response_matrix(ThinPlateSplineModel(xy, noisy, 10.0).to_dict(), xy, noisy, xy)
    effects, seed, outlier, _ = HEADS[0]
    targets, deviations = physics_first_data(effects, seed, outlier)
    described = train_physics_then_rbf(targets, deviations)[0].to_dict()
    with pytest.raises(ValueError, match=r"deviations must have the shape of targets_xy \(169, 2\), got \(168, 2\)"):
        physics_response_matrix(described, targets, deviations[:-1], xy)
    training = TrainingData(xy, noisy, np.full(len(xy), 0.004), {"type": "physical"})
    with pytest.raises(ValueError, match="the certificate covers OLS RBF networks, thin-plate splines and "
                                         "physics-first sums trained on the corrections, not a model of type "
                                         "'physical'"):
        uncertainty_budget([training], REGION, 490.0, None, False)
