"""The calibrate flow without ROS: ``procedure.calibrate`` and ``run_plate`` through ``DirectCell``.

The paper-like simulated head (config/sim.yaml) with a short scanner line and sweep (120 x 110 mm
around the head's centre), a 5x5 grid over 90 mm and one plain sweep at a coarse step: a few seconds
per plate. Accuracy figures here are TRUE (simulation ground truth) or MEASURED as named; the bounds
are loose, these tests check the flow's paths, not the accuracy.
"""
from __future__ import annotations

import asyncio
import dataclasses
from unittest import mock

import numpy as np
import pytest

from gls_calibration.calibration import procedure
from gls_calibration.calibration.record import build_record, save_candidate
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.registration.sweep_plan import CellTimeModel, parse_plan
from gls_calibration.simulation.direct_cell import DirectCell
from gls_calibration.simulation.world import SimulatedCell, load_sim_config

FAST = dict(grid_per_side=5, grid_size_mm=90.0, plain_sweeps=1, plain_sweep_step_mm=2.0)


def small_config():
    """config/sim.yaml with a 120 mm scanner line and a 110 mm sweep centred on the head (mounting
    recomputed), on the ideal measurement chain: these tests check the procedure, not the measurement."""
    config = load_sim_config(preset="ideal")
    return dataclasses.replace(config, scanner=dataclasses.replace(config.scanner, line_length_mm=120.0),
                               sweep_length_mm=110.0, scanner_to_gls=None)


def new_cell(tmp_path, cell_type=None) -> DirectCell:
    return (cell_type or DirectCell)(SimulatedCell(small_config()), CalibrationStore(tmp_path / "store"))


def run_calibrate(cell: DirectCell, settings: procedure.ProcedureSettings, *, iterations=1, validate=False,
                  force=False, stages=None) -> procedure.CalibrationOutcome:
    """``calibrate`` as the manager runs it: candidates saved inactive, the active one back on failure."""
    def save(runs, models):
        return save_candidate(cell.store, build_record(cell.sim.config.geometry, settings, runs, models, []),
                              cell.sim.config.geometry)

    def progress(stage, fraction, text):
        if stages is not None:
            stages.append((stage, fraction))

    async def flow():
        try:
            return await procedure.calibrate(cell, settings, iterations=iterations, validate=validate,
                                             force=force, want_truth=True, progress=progress,
                                             save_candidate=save,
                                             active_calibration=cell.store.active_path() is not None)
        except procedure.CalibrationError:
            await cell.reload_active()
            raise
    return asyncio.run(flow())


def nominal(cell: DirectCell) -> bool:
    """True when the cell corrects through the nominal model (no calibration loaded)."""
    return not cell.correction.models


def test_fiducials_found_counts_every_fiducial_some_pass_measured(tmp_path):
    """Report as found every fiducial with a measured centre, not the fewest of one sweep.

    A 45 deg pass sees the grid's middle band only: on a 5 x 5 grid over 96 mm of the small cell it
    misses the corners' fiducials, which the 0 and 90 deg passes see.
    """
    cell = new_cell(tmp_path)
    settings = cell.settings(**{**FAST, "grid_size_mm": 96.0}, sweep_plan=parse_plan("0+,90+,45+"))
    per_sweep = []
    combine = procedure.combine_sweeps

    def spy(measurements, *args, **kwargs):
        per_sweep.append([len(found.centres) for found in measurements])
        return combine(measurements, *args, **kwargs)

    with mock.patch.object(procedure, "combine_sweeps", spy):
        run = asyncio.run(procedure.run_plate(cell, settings, grid_targets(5, 96.0), lambda *_: None,
                                              (0.0, 1.0), True))
    assert per_sweep[0][:2] == [25, 25] and per_sweep[0][2] < 25, per_sweep
    assert run.fiducials_found == len(run.deviations) == 25


def test_run_plate_measures_the_uncorrected_field(tmp_path):
    cell = new_cell(tmp_path)
    settings = cell.settings(**FAST)
    grid_xy = grid_targets(5, 90.0)
    run = asyncio.run(procedure.run_plate(cell, settings, grid_xy, lambda *_: None, (0.0, 1.0), True))
    assert run.fiducials_found == 25 and len(run.deviations) == 25
    # The paper-like head deviates by about 0.3 mm RMS over these 90 mm (0.9 mm over 190 mm);
    # measured and TRUE agree to a few hundredths.
    assert 0.1 < run.metrics.full.rms_abs_mm < 1.0
    assert abs(run.metrics.full.rms_abs_mm - run.true_metrics.full.rms_abs_mm) < 0.05
    np.testing.assert_allclose(run.deviations, run.true_deviations, atol=0.1)
    # Nothing active: the corrections are Q - P, i.e. the measured deviations.
    np.testing.assert_allclose(run.corrections, run.deviations, atol=1e-6)
    assert len(cell.marks) == 2 * 25                      # two rings per fiducial


def test_within_tolerance_nothing_is_trained_or_saved(tmp_path):
    cell = new_cell(tmp_path)
    outcome = run_calibrate(cell, cell.settings(**FAST, tolerance_rms_mm=5.0), validate=True)
    assert "within the tolerance of 5.0 mm: nothing trained" in outcome.message
    assert outcome.candidate is None and outcome.models == () and outcome.validation is None
    assert len(outcome.runs) == 1
    assert cell.store.history() == [] and cell.store.active_path() is None
    assert nominal(cell)


def test_force_trains_even_within_tolerance(tmp_path):
    cell = new_cell(tmp_path)
    outcome = run_calibrate(cell, cell.settings(**FAST, tolerance_rms_mm=5.0), force=True)
    assert outcome.candidate is not None and len(outcome.models) == 1


def test_too_few_fiducials_fail_before_anything_is_saved(tmp_path):
    # The 120 x 110 mm scan sees only the centre of a 3x3 grid over 190 mm.
    cell = new_cell(tmp_path)
    with pytest.raises(procedure.CalibrationError, match=r"found \d of 9 fiducials; at least 9 \(90%\) are needed"):
        # (settings that claim a sweep long enough for the grid: a shorter one is refused first)
        run_calibrate(cell, cell.settings(**{**FAST, "grid_per_side": 3, "grid_size_mm": 190.0,
                                             "cell_time": CellTimeModel(sweep_length_mm=210.0)}))
    assert cell.store.history() == [] and nominal(cell)


def test_targets_beyond_the_mirror_limits_fail_before_marking(tmp_path):
    cell = new_cell(tmp_path)
    with pytest.raises(procedure.CalibrationError,
                       match=r"\d+ ring point\(s\) lie beyond the mirror limits or the focus range"):
        # (a sweep long enough for the grid: a shorter one is refused first, by the settings)
        run_calibrate(cell, cell.settings(**{**FAST, "grid_size_mm": 900.0,
                                             "cell_time": CellTimeModel(sweep_length_mm=920.0)}))
    assert cell.marks == [] and cell.sim.head.log == []     # nothing was marked
    assert cell.store.history() == []


def test_two_iterations_and_validation_leave_a_saved_inactive_candidate(tmp_path):
    cell = new_cell(tmp_path)
    stages = []
    outcome = run_calibrate(cell, cell.settings(**FAST), iterations=2, validate=True, stages=stages)
    assert outcome.message == "calibrated" and len(outcome.runs) == 2 and len(outcome.models) == 2
    first, second = outcome.runs
    # The second plate is marked through the first correction: MEASURED error well below the first.
    assert second.metrics.full.rms_abs_mm < first.metrics.full.rms_abs_mm / 5
    # ... and its training data are the corrections still to add, not the raw deviations again.
    assert np.sqrt(np.mean(np.sum(second.corrections ** 2, axis=1))) < first.metrics.full.rms_abs_mm / 5
    validation = outcome.validation
    assert len(validation.targets) == 16                 # 4x4 between the training fiducials
    assert validation.true_metrics.full.rms_abs_mm < first.true_metrics.full.rms_abs_mm / 5
    # A candidate per iteration, saved but not activated (the caller activates the last one).
    history = cell.store.history()
    assert len(history) == 2 and cell.store.active_path() is None
    assert str(history[-1]) == outcome.candidate.path
    assert len(outcome.candidate.correction.models) == 2
    assert cell.store.load(outcome.candidate.path)["models"] == [model.model for model in outcome.models]
    # Progress runs forward from 0 to 1 through every stage.
    fractions = [fraction for _, fraction in stages]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert stages[-1][0] == "done"
    # The time budget: every stage the flow reported but the last has a wall time, and they add up to
    # the run's duration up to what came before the first message and after the last one.
    wall = outcome.stage_times.wall_s
    assert set(wall) == {stage for stage, _ in stages[:-1]} and all(value >= 0.0 for value in wall.values())
    assert sum(wall.values()) <= outcome.duration_s <= sum(wall.values()) + 1.0
    assert 0.0 <= outcome.stage_times.last_sweep_to_result_s <= wall["measurement"] + wall["deviations"] + 1.0


class NoPlateChanger(DirectCell):
    """A cell without a plate changer: a second plate cannot be loaded."""

    async def exchange_plate(self) -> None:
        raise procedure.CalibrationError("no plate exchange in this cell")


def test_a_failure_after_training_never_activates_the_candidate(tmp_path):
    cell = new_cell(tmp_path, NoPlateChanger)
    with pytest.raises(procedure.CalibrationError, match="no plate exchange in this cell"):
        run_calibrate(cell, cell.settings(**FAST), validate=True)
    store = cell.store
    assert len(store.history()) == 1 and store.active_path() is None     # saved as a candidate only
    assert nominal(cell)                                                 # the active (nominal) one is back
