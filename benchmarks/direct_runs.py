"""The calibrate flow on ``DirectCell`` as the benchmarks run it: one cell, the plan's settings, one run.

``DirectCell`` runs the core steps of the nodes without ROS. The benchmarks that compare plans,
presets or chain maps all need the same three things, owned here once: a cell with a store
(:func:`direct_cell`), the procedure settings of the calibration plan of ``config/gls.yaml`` with
what a benchmark varies (:func:`plan_settings`), and one forced, validated calibration with the
truth, saved as the manager saves it (:func:`calibrate_validated`).
"""
from __future__ import annotations

import asyncio
from pathlib import Path

from gls_calibration.calibration import procedure
from gls_calibration.calibration.record import build_record, record_models, save_candidate
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.simulation.direct_cell import DirectCell
from gls_calibration.simulation.reference_plate import calibration_plan
from gls_calibration.simulation.world import SimConfig, SimulatedCell


def direct_cell(config: SimConfig, store_dir: Path, *, placed_by_pose: bool = True) -> DirectCell:
    """Return the simulated cell of ``config`` with a calibration store in ``store_dir``."""
    return DirectCell(SimulatedCell(config), CalibrationStore(store_dir), placed_by_pose=placed_by_pose)


def plan_settings(cell: DirectCell, **overrides) -> procedure.ProcedureSettings:
    """Return the settings of the calibration plan (``config/gls.yaml``) on ``cell``, then ``overrides``.

    The plan gives the passes, plain sweeps, both profile steps and the placement; a benchmark
    overrides what it varies (``sweep_plan``, ``plain_sweeps``, ``chain_map``, ...).
    """
    plan = calibration_plan()
    values = dict(sweep_plan=plan.passes, plain_sweeps=plan.plain_sweeps, plain_sweep_step_mm=plan.plain_step_mm,
                  marked_sweep_step_mm=plan.marked_step_mm, profiles_placed_by_pose=plan.placed_by_pose)
    values.update(overrides)
    return cell.settings(**values)


def calibrate_validated(cell: DirectCell, settings: procedure.ProcedureSettings) -> procedure.CalibrationOutcome:
    """Run one forced calibration (one iteration) with its validation plate and the truth.

    As the manager runs it: the candidate holds the active calibration's models (when one is active)
    and the new one, trained through them.
    """
    geometry = cell.sim.config.geometry
    active = cell.store.active_path()
    existing = record_models(cell.store.load(active)) if active else []

    def save(runs, models):
        return save_candidate(cell.store, build_record(geometry, settings, runs, models, existing), geometry)
    return asyncio.run(procedure.calibrate(cell, settings, iterations=1, validate=True, force=True, want_truth=True,
                                           progress=lambda *_: None, save_candidate=save,
                                           active_calibration=active is not None))
