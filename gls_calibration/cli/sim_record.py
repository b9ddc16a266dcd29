"""``gls-sim-cell --record DIR``: one calibration of the simulated cell, recorded as a rosbag2 bag.

Runs in-process on the direct cell (:class:`~gls_calibration.simulation.recording_cell.RecordingCell`,
no ROS graph): the same procedure, core steps and simulated cell as the node graph, with the command
line's seed, grid, iterations, measurement preset and sweep plan, and the grid size, sweeps and
stand-still height of ``config/gls.yaml``. Every sweep is written to DIR as a real cell's drivers would stream it (see
:mod:`gls_calibration.scan.bag_io`); replay it with ``gls-measure --bag DIR``.
"""
from __future__ import annotations

import argparse
import asyncio
from dataclasses import replace
import sys

from gls_calibration.calibration.procedure import CalibrationError, ProcedureSettings, calibrate
from gls_calibration.calibration.record import build_record, save_candidate
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.common.config_files import config_path, read_config_file
from gls_calibration.common.validation import as_positive_number
from gls_calibration.geometry.head_config import parameters_block
from gls_calibration.registration.sweep_plan import CellTimeModel
from gls_calibration.scan.bag_io import BagRecorder
from gls_calibration.simulation.recording_cell import SIM_FLANGE_TO_SENSOR, RecordingCell, base_to_gls
from gls_calibration.simulation.world import SimulatedCell


def _grid_value(key: str, default):
    def parse(document):
        grid = parameters_block(document).get("grid") or {}
        return grid.get(key, default)
    return read_config_file(config_path("gls.yaml"), "parameter file", parse)


def _sweep_value(key: str, default):
    def parse(document):
        sweep = parameters_block(document).get("sweep") or {}
        return sweep.get(key, default)
    return read_config_file(config_path("gls.yaml"), "parameter file", parse)


def standstill_height() -> bool:
    """``sweep.standstill_height`` of config/gls.yaml (the procedure's default when the file leaves it out)."""
    value = _sweep_value("standstill_height", ProcedureSettings.standstill_height)
    if not isinstance(value, bool):
        raise ValueError(f"sweep.standstill_height of config/gls.yaml must be true or false, got {value!r}")
    return value


def grid_size_mm() -> float:
    """``grid.size_mm`` of config/gls.yaml (the procedure's default when the file leaves it out)."""
    return float(_grid_value("size_mm", ProcedureSettings.grid_size_mm))


def sweep_length_mm() -> float:
    """``sweep.length_mm`` of config/gls.yaml (the cell-time model's default when the file leaves it out).

    The recorded sweeps' length: they turn the sensor about their middle, from which the error separation
    measures a centre's place on the laser line.
    """
    value = _sweep_value("length_mm", CellTimeModel.sweep_length_mm)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"sweep.length_mm of config/gls.yaml must be a number, got {value!r}")
    return as_positive_number(value, "sweep.length_mm of config/gls.yaml")


def grid_per_side() -> int:
    """``grid.per_side`` of config/gls.yaml (the procedure's default when the file leaves it out)."""
    return int(_grid_value("per_side", ProcedureSettings.grid_per_side))


def run_recording(args: argparse.Namespace) -> int:
    """Calibrate the direct simulated cell once, recording to ``args.record``; return an exit code.

    Exit 0 on success, 1 when the calibration failed (the bag is kept: it shows what happened), 2
    when nothing could be recorded.
    """
    config = replace(args.sim, seed=args.seed)
    plan = args.reference_plan
    try:
        recorder = BagRecorder(args.record, SIM_FLANGE_TO_SENSOR, base_to_gls(config), storage=args.record_storage)
    except (ValueError, OSError) as error:
        print(f"gls-sim-cell: --record: {error}", file=sys.stderr)
        return 2
    failure = ""
    with recorder:
        cell = RecordingCell(SimulatedCell(config), CalibrationStore(args.out / "calibrations"), recorder=recorder,
                             physics_first=args.physics_first)
        settings = cell.settings(grid_per_side=args.grid, grid_size_mm=grid_size_mm(), sweep_plan=plan.passes,
                                 plain_sweeps=plan.plain_sweeps, plain_sweep_step_mm=plan.plain_step_mm,
                                 marked_sweep_step_mm=plan.marked_step_mm, standstill_height=standstill_height())

        def save(runs, models):
            return save_candidate(cell.store, build_record(config.geometry, settings, runs, models, []),
                                  config.geometry)

        def progress(stage: str, part: float, text: str) -> None:
            print(f"[{part:4.0%}] {text}", file=sys.stderr, flush=True)

        try:
            outcome = asyncio.run(calibrate(cell, settings, iterations=args.iterations, validate=not args.no_validate,
                                            force=args.force, want_truth=True, progress=progress,
                                            save_candidate=save))
        except CalibrationError as error:
            failure = str(error)
    print(f"recorded {cell.sweeps} sweep(s) and {cell.standstills} stand-still(s) to {args.record} "
          f"({args.record_storage})")
    if failure:
        print(f"calibration failed: {failure}", file=sys.stderr)
        return 1
    print(outcome.message)
    return 0
