"""``gls-train --bag BAG --out calibration.yaml``: the whole calibrate flow run again offline from a bag.

The bag's motions, in order, feed ``procedure.calibrate`` through a
:class:`~gls_calibration.calibration.replay_cell.ReplayCell`: per plate the plain sweeps, the stand-still profiles
(unless ``--no-standstill-height``), then the passes of the sweep plan; the last plate is the validation
plate with ``--validate``. The number of plates follows from the bag (it must hold whole plates).
Grid, plan, plain sweeps and stand-still height default to ``config/gls.yaml`` (what
``gls-sim-cell --record`` records with); the galvo head's mounting comes from the bag's ``/tf_static``
(robot base -> gls). Writes the calibration to ``--out`` and the calibrate flow's report (report.md,
summary.json, fiducials.csv, training.csv, plots) into ``<out>.report/``.
"""
from __future__ import annotations

import argparse
import asyncio
from dataclasses import replace
import math
from pathlib import Path
import sys
import tempfile

import numpy as np

from gls_calibration.calibration.outcome import summarise
from gls_calibration.calibration.procedure import CalibrationError, ProcedureSettings, calibrate
from gls_calibration.calibration.record import build_record, save_candidate
from gls_calibration.calibration.replay_cell import ReplayCell
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.common.files import atomic_write_text, require_regular_output
from gls_calibration.geometry.head_config import load_head_config
from gls_calibration.registration.rigid import RigidTransform
from gls_calibration.report.run_report import write_outcome_report
from gls_calibration.scan.bag_io import BagLayout, ReplayedSweep, read_recording

RECORDED_LENGTH_TOLERANCE_MM = 3.0
"""How far a recorded sweep's travel (first to last profile) may fall from ``sweep.length_mm``: up to a
profile step at either end (1 mm on a plain sweep) and 1 mm more; its middle then lies within 1.5 mm
of the one the error separation measures from."""


def plates_in(motion_count: int, settings: ProcedureSettings) -> int:
    """Count the plates a bag of ``motion_count`` motions holds.

    Plates a bag of ``motion_count`` motions (sweeps and stand-stills) holds; ValueError when it does not
    hold whole plates.
    """
    standstills = 1 if settings.standstill_height else 0
    per_plate = settings.plain_sweeps + standstills + len(settings.sweep_plan)
    if motion_count % per_plate:
        raise ValueError(f"the bag holds {motion_count} motion(s); a plate takes {per_plate} "
                         f"({settings.plain_sweeps} plain, {standstills} stand-still and {len(settings.sweep_plan)} "
                         "marked): check --grid, --sweep-plan, --plain-sweeps and --standstill-height against the "
                         "recording")
    return motion_count // per_plate


def recording_settings(grid: int | None, size_mm: float | None, sweep_plan: str | None,
                       plain_sweeps: int | None, standstill: bool | None = None) -> ProcedureSettings:
    """Return grid, plan, plain sweeps and stand-still height as given, else as gls.yaml has them.

    The sweep length is gls.yaml's (the recording's: the error separation measures from its middle).

    ValueError naming a bad one.
    """
    from gls_calibration.cli.sim_record import grid_per_side, grid_size_mm, standstill_height, sweep_length_mm
    from gls_calibration.registration.sweep_plan import CellTimeModel, parse_plan
    from gls_calibration.simulation.reference_plate import calibration_plan

    plan = calibration_plan()
    return ProcedureSettings(grid_per_side=grid if grid is not None else grid_per_side(),
                             grid_size_mm=size_mm if size_mm is not None else grid_size_mm(),
                             sweep_plan=parse_plan(sweep_plan) if sweep_plan is not None else plan.passes,
                             plain_sweeps=plain_sweeps if plain_sweeps is not None else plan.plain_sweeps,
                             standstill_height=standstill if standstill is not None else standstill_height(),
                             cell_time=CellTimeModel(sweep_length_mm=sweep_length_mm()))


def require_recorded_length(sweeps: list[ReplayedSweep], length_mm: float) -> None:
    """Refuse a recording whose sweeps are not ``length_mm`` long (stand-stills skipped).

    The error separation measures every pass from the sweeps' middle, ``length_mm`` / 2 along the
    travel: a bag swept with another length (recorded with another ``sweep.length_mm``) would be
    combined about the wrong point.

    Parameters
    ----------
    sweeps : list of ReplayedSweep
        The bag's motions in order.
    length_mm : float
        ``sweep.length_mm`` the replay runs with.

    Raises
    ------
    ValueError
        Naming the first sweep whose travel differs by more than ``RECORDED_LENGTH_TOLERANCE_MM``.
    """
    for number, sweep in enumerate(sweeps):
        if sweep.standstill:
            continue
        travel = sweep.travel_mm
        if abs(travel - length_mm) > RECORDED_LENGTH_TOLERANCE_MM:
            raise ValueError(f"motion {number} of the bag travels {travel:.1f} mm, sweep.length_mm of "
                             f"config/gls.yaml is {length_mm:g} mm: the error separation measures every pass "
                             "from the sweeps' middle; set sweep.length_mm to the recording's length")


def train_from_bag(args: argparse.Namespace, settings: ProcedureSettings) -> int:
    """Run the calibration from ``args.bag``; exit 0, 1 if the calibration failed, 2 on bad input.

    ``settings``: grid, plan and plain sweeps of the recording (the mounting is taken from the bag).
    """
    report_dir = args.out.with_name(args.out.name + ".report")
    try:
        require_regular_output(args.out)
        if report_dir.exists():
            raise ValueError(f"{report_dir}: exists already (the report folder of --out)")
        geometry, _ = load_head_config(args.head)
        given = {"scan_topic": args.scan_topic, "base_frame": args.base_frame, "sensor_frame": args.sensor_frame}
        layout = BagLayout(**{name: value for name, value in given.items() if value is not None})
        sweeps, gls_in_base = read_recording(args.bag, layout)
        require_recorded_length(sweeps, settings.cell_time.sweep_length_mm)
        scanner_to_gls = np.linalg.inv(gls_in_base)
        settings = replace(settings, scanner_to_gls=RigidTransform(scanner_to_gls[:3, :3], scanner_to_gls[:3, 3]),
                           profiles_placed_by_pose=True)
        plates = plates_in(len(sweeps), settings)
        iterations = plates - (1 if args.validate else 0)
        if iterations < 1:
            raise ValueError(f"the bag holds {plates} plate(s): nothing to train on besides the validation plate")
        message = settings.iterations_problem(iterations)
        if message:
            raise ValueError(message)
    except (ValueError, OSError) as error:
        print(f"gls-train: {error}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix=f".{args.out.name}.", dir=args.out.parent) as scratch:
        cell = ReplayCell(sweeps, geometry, CalibrationStore(Path(scratch) / "store"),
                          physics_first=args.physics_first, training=args.training)

        def save(runs, models):
            return save_candidate(cell.store, build_record(geometry, settings, runs, models, []), geometry)

        try:
            outcome = asyncio.run(calibrate(cell, settings, iterations=iterations, validate=args.validate,
                                            force=args.force, want_truth=False, progress=lambda *parts: None,
                                            save_candidate=save))
        except CalibrationError as error:
            print(f"gls-train: calibration from {args.bag} failed: {error}", file=sys.stderr)
            return 1
        unused = len(sweeps) - cell.taken
        if outcome.candidate is None:
            print(f"gls-train: nothing trained: {outcome.message}", file=sys.stderr)
            return 1
        summary = replace(summarise(outcome, None, "pose"), calibration_file=str(args.out))
        staged = Path(scratch) / "report"
        staged.mkdir()
        write_outcome_report(staged, outcome, summary)
        text = Path(outcome.candidate.path).read_text(encoding="utf-8")
        try:
            atomic_write_text(args.out, text)
            staged.rename(report_dir)
        except (OSError, ValueError) as error:
            print(f"gls-train: cannot write {args.out}: {getattr(error, 'strerror', None) or error}", file=sys.stderr)
            return 2
    rms = summary.post_rms_mm if math.isfinite(summary.post_rms_mm) else summary.pre_rms_mm
    which = "after (validation plate)" if math.isfinite(summary.post_rms_mm) else "before"
    print(f"{outcome.message}; measured RMS {which} {rms:.4f} mm; {len(sweeps)} sweep(s) of {args.bag}"
          + (f" ({unused} not needed)" if unused else ""))
    print(f"calibration written to {args.out}; report {report_dir / 'report.md'}")
    if outcome.rejection:
        print(f"gls-train: the validation rejects the calibration: {outcome.rejection}", file=sys.stderr)
        return 1
    return 0
