"""The certificate's validation floor: U raised to what the validation plate and the reference check show.

The chain term of U is one draw of the reference check; the validation plate carries the
calibration's own draw of the chain's random error. ``with_validation_floor`` raises U uniformly so
that the 2-D RMS it implies reaches the validation's RMS in quadrature with the check; the calibrate
flow stores a raised map as a new candidate (``record.certified_candidate``).
"""
from __future__ import annotations

import asyncio
import dataclasses
import math

import numpy as np
import pytest

from gls_calibration.calibration.stated_accuracy import ChainCheck, centres_extent_mm, placement_name
from gls_calibration.calibration.uncertainty import (VALIDATION_FLOOR, TrainingData, uncertainty_budget,
                                                     with_validation_floor, with_validation_floor_stored)
from gls_calibration.correction.uncertainty_grid import UncertaintyGrid
from gls_calibration.models.rbf import ThinPlateSplineModel
from test_certificate import REGION, grid_data

CHECK = ChainCheck((0.002, 0.003), "0+", "pose", "plate A", 100)


def budget():
    xy, _, noisy = grid_data()
    model = ThinPlateSplineModel(xy, noisy, 10.0)
    return uncertainty_budget([TrainingData(xy, noisy, np.full(len(xy), 0.004), model.to_dict())], REGION, 490.0,
                              CHECK, True)


def implied_rms_2d(grid: UncertaintyGrid, coverage_factor: float) -> float:
    """The 2-D RMS error a U grid implies: sqrt(2 mean(u^2)), u = U / coverage factor per axis."""
    return math.sqrt(2.0 * float(np.mean(np.square(grid.u_k2_mm / coverage_factor))))


def test_a_validation_above_the_budget_raises_u_uniformly_to_it():
    trained = budget()
    post_rms = 0.05      # far above what the budget implies (about 0.01 mm)
    assert implied_rms_2d(trained.grid, trained.coverage_factor) < post_rms
    raised = with_validation_floor(trained, post_rms, CHECK, True)
    floor = math.sqrt(post_rms ** 2 + 0.002 ** 2 + 0.003 ** 2)
    assert implied_rms_2d(raised.grid, raised.coverage_factor) == pytest.approx(floor, rel=1e-12)
    # one per-axis variance added at every node: the budget's shape over the field is kept
    before = np.square(trained.grid.u_k2_mm / trained.coverage_factor)
    added = np.square(raised.grid.u_k2_mm / raised.coverage_factor) - before
    np.testing.assert_allclose(added, added.flat[0], rtol=1e-9)
    line = raised.contributions[-1]
    assert line.name == VALIDATION_FLOOR and line.rms_mm == pytest.approx(math.sqrt(added.flat[0]))
    assert "0.0500 mm RMS" in line.basis and "0.0020 / 0.0030" in line.basis
    assert [item.name for item in raised.contributions[:-1]] == [item.name for item in trained.contributions]
    assert raised.u95_full_mm == pytest.approx(raised.grid.u_k2_mm.max())
    assert raised.u95_median_mm > trained.u95_median_mm and raised.u95_central_mm > trained.u95_central_mm


@pytest.mark.parametrize("post_rms, check, matches", [
    (0.0, CHECK, True),                 # the budget already implies more than validation and check
    (0.05, None, True),                 # no check: nothing independent to add the validation to
    (0.05, CHECK, False),               # a check of another plan, placement or chain map
    (math.nan, CHECK, True),            # not validated
])
def test_the_budget_stays_as_trained_where_there_is_no_floor_above_it(post_rms, check, matches):
    trained = budget()
    assert with_validation_floor(trained, post_rms, check, matches) is trained
    assert with_validation_floor_stored(trained.to_dict(), post_rms, check, matches) is None


def test_a_negative_validation_figure_is_refused():
    with pytest.raises(ValueError, match=r"^post_rms_mm must be non-negative, got -0\.01$"):
        with_validation_floor(budget(), -0.01, CHECK, True)


def test_the_stored_mapping_is_raised_as_the_budget_is():
    trained = budget()
    raised = with_validation_floor(trained, 0.05, CHECK, True)
    stored = with_validation_floor_stored(trained.to_dict(), 0.05, CHECK, True)
    assert stored == raised.to_dict()
    np.testing.assert_allclose(UncertaintyGrid.from_dict(stored).u_k2_mm, raised.grid.u_k2_mm)
    with pytest.raises(ValueError, match="missing key 'uncertainty.u_k2_mm'"):
        with_validation_floor_stored({"x_mm": [0.0, 1.0], "y_mm": [0.0, 1.0]}, 0.05, CHECK, True)


def test_the_calibrate_flow_activates_the_candidate_certify_returns(tmp_path):
    """``certify`` runs once, after the validation, and its candidate is the one the outcome names.

    On this small cell the model's term (5x5 fiducials) puts the budget above the real validation and
    check: the candidate stays as it is; a validation figure of 0.05 mm puts the floor above it, and
    the raised map is a second file, the first staying in the history, inactive.
    """
    from gls_calibration.calibration import procedure
    from gls_calibration.calibration.outcome import summarise
    from gls_calibration.calibration.record import build_record, certified_candidate, save_candidate
    from gls_calibration.calibration.uncertainty import check_matches_run
    from gls_calibration.correction.uncertainty_grid import UNCERTAINTY_KEY
    from gls_calibration.registration.sweep_plan import plan_label
    from test_procedure import FAST, new_cell

    cell = new_cell(tmp_path)
    settings = cell.settings(**FAST)
    geometry = cell.sim.config.geometry
    check = ChainCheck((0.002, 0.002), plan_label(settings.sweep_plan),
                       placement_name(settings.profiles_placed_by_pose), "plate A", 100,
                       extent_mm=centres_extent_mm(procedure.training_grid(settings)))
    # a plate that ends inside the validation's outer targets does not check them
    smaller = dataclasses.replace(check, extent_mm=centres_extent_mm(0.8 * procedure.validation_grid(settings)))
    calls, unchanged = [], []

    def save(runs, models):
        assert check_matches_run(check, runs[0], settings)
        return save_candidate(cell.store, build_record(geometry, settings, runs, models, [], check), geometry)

    def certify(candidate, validation):
        calls.append(candidate)
        matches = check_matches_run(check, validation, settings)
        assert not check_matches_run(smaller, validation, settings)
        as_validated = certified_candidate(cell.store, candidate, geometry, validation.metrics.full.rms_abs_mm,
                                           check, matches)
        unchanged.append(as_validated is candidate)
        return certified_candidate(cell.store, candidate, geometry, 0.05, check, matches)

    outcome = asyncio.run(procedure.calibrate(cell, settings, iterations=1, validate=True, force=True,
                                              want_truth=True, progress=lambda *_: None, save_candidate=save,
                                              certify=certify))
    assert len(calls) == 1 and unchanged == [True]
    assert outcome.candidate.path != calls[0].path
    assert len(cell.store.history()) == 2          # the first candidate stays, inactive
    first = calls[0].record[UNCERTAINTY_KEY]
    stored = outcome.candidate.record[UNCERTAINTY_KEY]
    assert [line["name"] for line in stored["budget"]] == [line["name"] for line in first["budget"]] + [
        VALIDATION_FLOOR]
    floor = math.hypot(0.05, 0.002, 0.002)
    grid = outcome.candidate.correction.uncertainty
    assert implied_rms_2d(grid, stored["coverage_factor"]) == pytest.approx(floor, rel=1e-9)
    assert cell.store.load(outcome.candidate.path)[UNCERTAINTY_KEY] == stored
    summary = summarise(outcome, check)
    assert summary.certificate_u95_median_mm == pytest.approx(stored["u95_median_mm"])
    assert stored["budget"][-1]["rms_mm"] > 0.0
    assert summary.certificate_validation_mm == pytest.approx(stored["budget"][-1]["rms_mm"])
    # without validation there is nothing to raise it to: certify is not called
    calls.clear()
    unvalidated = asyncio.run(procedure.calibrate(cell, settings, iterations=1, validate=False, force=True,
                                                  want_truth=True, progress=lambda *_: None, save_candidate=save,
                                                  certify=certify))
    assert calls == [] and math.isnan(summarise(unvalidated, check).certificate_validation_mm)


def test_a_raised_certificate_that_cannot_be_written_fails_the_run_and_activates_nothing(tmp_path, monkeypatch):
    from gls_calibration.calibration import procedure
    from gls_calibration.calibration.record import build_record, certified_candidate, save_candidate
    from test_procedure import FAST, new_cell

    cell = new_cell(tmp_path)
    settings = cell.settings(**FAST)
    geometry = cell.sim.config.geometry
    check = ChainCheck((0.002, 0.002), "0+", "pose", "plate A", 100)

    def save(runs, models):
        return save_candidate(cell.store, build_record(geometry, settings, runs, models, [], check), geometry)

    def certify(candidate, validation):
        def full_disk(*args, **kwargs):
            raise OSError(28, "No space left on device")
        monkeypatch.setattr(cell.store, "save", full_disk)
        return certified_candidate(cell.store, candidate, geometry, 0.05, check, True)

    with pytest.raises(OSError, match="No space left on device"):
        asyncio.run(procedure.calibrate(cell, settings, iterations=1, validate=True, force=True, want_truth=True,
                                        progress=lambda *_: None, save_candidate=save, certify=certify))
    assert cell.store.active_path() is None and len(cell.store.history()) == 1
