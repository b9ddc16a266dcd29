"""A second calibration judged like with like (issue 31 item 4).

In a served paper_like cell with a calibration active, a second calibrate measured the ACTIVE
calibration on the run's first plate (its own training positions: self-consistency, the chain
re-measures the repeating errors it learned) and the CANDIDATE on the validation grid, and rejected
the candidate. Now the active calibration is marked on the validation grid too and the two are
compared there. The flow is driven here with plate runs of given figures (the figures of an earlier
paper_like seed-1 run, ``benchmarks/bench_recalibration.py``), so the decision is checked exactly.
"""
from __future__ import annotations

import asyncio
import math
from types import SimpleNamespace

import numpy as np
import pytest

from gls_calibration.calibration import procedure
from gls_calibration.calibration.outcome import INDEPENDENT, Candidate, deviation_metrics, summarise
from gls_calibration.calibration.stated_accuracy import SELF_CONSISTENCY
from gls_calibration.registration.rigid import RigidTransform
from gls_calibration.report.run_report import figure_kind_lines
from gls_calibration.scan.plate_pose import PlatePose

SETTINGS = procedure.ProcedureSettings(grid_per_side=5, grid_size_mm=90.0)
TRAINING = procedure.grid.grid_targets(5, 90.0)
# measured RMS (mm) of a plate by (calibration marking it, positions)
FIGURES = {("active", "training"): 0.0068, ("candidate", "validation"): 0.0082, ("active", "validation"): 0.0216}


def plate(grid_xy: np.ndarray, rms_mm: float) -> procedure.PlateRun:
    """A plate run whose deviations all have the length ``rms_mm`` (so its RMS is ``rms_mm``)."""
    count = len(grid_xy)
    deviations = np.column_stack([np.full(count, rms_mm), np.zeros(count)])
    targets = np.column_stack([grid_xy, np.zeros(count)])
    pose = PlatePose(np.array([0.0, 0.0, 1.0]), np.zeros(3), np.eye(3), 0.01, 1000, 1.0)
    metrics = deviation_metrics(grid_xy, deviations)
    return procedure.PlateRun(targets=targets, paired_targets_xy=grid_xy, deviations=deviations,
                              measured_gls=targets, corrections=deviations, true_deviations=deviations,
                              plate_pose_gls=pose, fiducials_found=count,
                              alignment=RigidTransform(np.eye(3), np.zeros(3)), metrics=metrics,
                              true_metrics=metrics, sigma_mm=np.full(count, 0.002), cell_time_s=100.0)


class FiguresCell:
    """Just enough of a cell for ``calibrate``: it records what it was asked and which calibration
    corrects (``loaded``); the plate runs come from ``FIGURES`` (see ``fake_run_plate``)."""

    def __init__(self, figures):
        self.figures, self.loaded, self.calls = figures, "active", []

    async def exchange_plate(self):
        self.calls.append("exchange")

    async def reload_active(self):
        self.loaded = "active"
        self.calls.append("reload_active")

    async def use_candidate(self, candidate):
        self.loaded = "candidate"
        self.calls.append("load_candidate")

    async def train(self, landed_xy, corrections):
        return SimpleNamespace(cv_rms_mm=0.001, neurons=5, method="thin_plate_spline")


@pytest.fixture
def figures_flow(monkeypatch):
    async def fake_run_plate(cell, settings, grid_xy, progress, span, want_truth, allow_marked=False):
        positions = "training" if np.array_equal(grid_xy, TRAINING) else "validation"
        cell.calls.append(f"plate {cell.loaded} {positions}")
        return plate(grid_xy, cell.figures[(cell.loaded, positions)])
    monkeypatch.setattr(procedure, "run_plate", fake_run_plate)

    def run(figures, active_calibration):
        cell = FiguresCell(figures)
        # force: a calibrated cell measures within the tolerance, the operator forced the run
        outcome = asyncio.run(procedure.calibrate(
            cell, SETTINGS, iterations=1, validate=True, force=True, want_truth=True, progress=lambda *_: None,
            save_candidate=lambda runs, models: Candidate("/store/candidate.json", None),
            active_calibration=active_calibration))
        return cell, outcome
    return run


def test_the_old_rule_rejects_a_candidate_measured_against_self_consistency(figures_flow):
    _, outcome = figures_flow(FIGURES, active_calibration=False)
    assert outcome.rejection.startswith(
        "candidate rejected: validation 0.0082 mm RMS is not better than the calibration in use "
        "(0.0068 mm RMS on this run's first plate)")
    assert outcome.active_validation is None


def test_the_active_calibration_is_marked_on_the_validation_grid_and_compared_there(figures_flow):
    cell, outcome = figures_flow(FIGURES, active_calibration=True)
    assert outcome.rejection == "" and outcome.message == "calibrated"
    assert cell.calls == ["plate active training", "load_candidate", "exchange", "plate candidate validation",
                          "exchange", "reload_active", "plate active validation", "load_candidate"]
    summary = summarise(outcome)
    assert (summary.pre_kind, summary.post_kind, summary.active_post_kind) == (SELF_CONSISTENCY, INDEPENDENT,
                                                                               INDEPENDENT)
    assert summary.active_post_rms_mm == pytest.approx(0.0216)
    assert summary.true_active_post_rms_mm == pytest.approx(0.0216)
    assert summary.post_rms_mm == pytest.approx(0.0082)
    assert summary.accepted_against == "active calibration on the validation grid"
    lines = figure_kind_lines(summary)
    assert lines[0] == ("first plate (`pre_rms_mm` 0.0068 mm): SELF-CONSISTENCY (the calibration in use "
                        "re-measured at the positions it was trained on)")
    assert lines[1] == "candidate on the validation grid (`post_rms_mm` 0.0082 mm): INDEPENDENT"
    assert lines[2] == "calibration in use on the validation grid (`active_post_rms_mm` 0.0216 mm): INDEPENDENT"
    assert summary.to_dict()["accepted_against"] == "active calibration on the validation grid"
    assert summary.cell_time_s == pytest.approx(300.0)      # the third plate counts in the cell time


def test_a_candidate_no_better_on_the_validation_grid_is_still_rejected(figures_flow):
    _, outcome = figures_flow({**FIGURES, ("active", "validation"): 0.0100}, active_calibration=True)
    assert outcome.rejection.startswith(
        "candidate rejected: validation 0.0082 mm RMS is not better than the calibration in use "
        "(0.0100 mm RMS on the validation grid) by more than the measurement uncertainty 0.0050 mm")
    assert outcome.active_validation.metrics.full.rms_abs_mm == pytest.approx(0.0100)


def test_a_first_calibration_has_independent_figures_and_no_active_comparison(figures_flow):
    nominal = {("active", "training"): 0.85, ("candidate", "validation"): 0.0082}
    cell, outcome = figures_flow(nominal, active_calibration=False)
    summary = summarise(outcome)
    assert outcome.rejection == "" and "plate active validation" not in cell.calls
    assert (summary.pre_kind, summary.post_kind, summary.active_post_kind) == (INDEPENDENT, INDEPENDENT, "")
    assert math.isnan(summary.active_post_rms_mm) and summary.accepted_against == "first plate"
