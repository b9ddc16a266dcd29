"""RBF-only against physics + RBF on the paper-like simulated cell, for 7x7, 11x11 and 19x19 fiducials.

Target (issue): physics + RBF with 7x7 fiducials at least as accurate as RBF-only with 19x19.

Every plate goes through the calibrate flow's own ``procedure.run_plate`` on a ``DirectCell`` (the
simulated cell without ROS): plain sweeps -> plate pose -> rings marked through the cell's active
correction on the measured plate plane -> marked sweep -> fiducials measured, paired, deviations
``Q - P``. Per grid over 190 mm one plate is run through the nominal model, and the SAME
measurements train every method: RBF at the landed points P (``training.train_correction``, as the
calibration trains), physics + RBF (``train_correction(physics_first=True)``), and for comparison
RBF at the targets Q (the published way) and the physics used to first order only
(``inverse=False``: ``K = Q + measured deviation``, like the RBF). Each correction then runs the
18x18 validation grid over 180 mm (half a pitch off the 19x19 one) on a fresh plate; the error is
the TRUE one (landed ring polylines -> centres -> rigid 2-D alignment onto the targets), over the
field and the central 150x150 mm, with the MEASURED RMS beside it. The first row of each grid is the
cell without correction. Common random numbers: every measurement plate (of every grid) gets the
same sweep draws (robot path error, noise), and so does every validation plate, so the rows differ
by grid and method only. The plate height a plate's sweeps measure moves the whole field's scale by
a few micrometres from draw to draw, as much as the methods differ here; other draws give other
figures at that level. Seeds are fixed (config/sim.yaml); training uses the trainer node's
defaults (``training.TrainingOptions``).

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_physics_rbf.py   (several minutes)
"""
from __future__ import annotations

import asyncio
import tempfile
import time

import numpy as np

from gls_calibration.calibration.procedure import run_plate
from gls_calibration.calibration.record import calibrated_region
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.correction.setpoints import Correction
from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.models import rbf
from gls_calibration.models.deviation_models import model_from_dict
from gls_calibration.models.physical_model import train_physics_then_rbf
from gls_calibration.models.training import TrainingOptions, train_correction
from gls_calibration.simulation.direct_cell import DirectCell
from gls_calibration.simulation.world import SimulatedCell, load_sim_config

GRIDS = (7, 11, 19)
SIZE_MM = 190.0
VALIDATION = grid_targets(18, 180.0)
MEASUREMENT_DRAWS = 0       # sweeps "taken before" each measurement plate: the same draws for every grid
VALIDATION_DRAWS = 1000     # ... and before each validation plate: the same draws for every row


def rms(vectors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(vectors ** 2, axis=1))))


def plate(cell: DirectCell, settings, grid_xy: np.ndarray, correction: Correction, sweeps_before: int):
    """One plate of the calibrate flow marked through ``correction`` on a fresh plate; its sweeps
    draw as if ``sweeps_before`` sweeps had been taken before."""
    cell.sim.exchange_plate()
    cell.sweeps = sweeps_before
    cell.marks.clear()
    cell.correction = correction
    return asyncio.run(run_plate(cell, settings, grid_xy, lambda *_: None, (0.0, 1.0), True))


def main() -> None:
    """Print the comparison table."""
    # the ideal measurement chain (the algorithmic floor), as the table of docs/method-and-results.md
    # (Algorithmic floor) was made
    config = load_sim_config(preset="ideal")
    geometry = config.geometry
    options = TrainingOptions()
    cell = DirectCell(SimulatedCell(config), CalibrationStore(tempfile.mkdtemp(prefix="gls-bench-store-")))
    header = (f"{'grid':6s} {'method':26s} {'named effects':58s} {'RMS 180':>8s} {'max 180':>8s} "
              f"{'RMS 150':>8s} {'max 150':>8s} {'meas RMS':>8s} {'train s':>8s}")
    print("TRUE error on the 18x18 validation grid over 180 mm (mm, after rigid 2-D alignment; 'meas RMS' "
          "is the MEASURED RMS of the same plate); paper-like cell (config/sim.yaml), procedure.run_plate "
          "on a DirectCell")
    print(header)
    print("-" * len(header))
    for per_side in GRIDS:
        settings = cell.settings(grid_per_side=per_side, grid_size_mm=SIZE_MM)
        region = calibrated_region(settings)
        began = time.perf_counter()
        run = plate(cell, settings, grid_targets(per_side, SIZE_MM), Correction(geometry), MEASUREMENT_DRAWS)
        measuring = time.perf_counter() - began
        targets, landed, deviations = run.paired_targets_xy, run.measured_gls[:, :2], run.deviations

        def timed(train):
            began = time.perf_counter()
            result = train()
            return result, time.perf_counter() - began

        rows = [("none (nominal model)", "", Correction(geometry), 0.0)]
        (model, selection), seconds = timed(lambda: rbf.select_model(targets, deviations, **options.select_kwargs()))
        rows.append((f"RBF at Q ({selection.method})", "published way", Correction(geometry, [model], region),
                     seconds))
        trained, seconds = timed(lambda: train_correction(landed, run.corrections, geometry, options=options))
        rows.append((f"RBF at P ({trained.method})", "this package, RBF only",
                     Correction(geometry, [model_from_dict(trained.model)], region), seconds))
        trained, seconds = timed(lambda: train_correction(landed, run.corrections, geometry, physics_first=True,
                                                          options=options))
        rows.append((trained.method, ", ".join(trained.named_effects) or "none",
                     Correction(geometry, [model_from_dict(trained.model)], region), seconds))
        # where the gain comes from: the same physics used to first order only (as the RBF is)
        (first_order, report), seconds = timed(lambda: train_physics_then_rbf(
            landed + run.corrections, run.corrections, geometry, inverse=False, **options.select_kwargs()))
        rows.append(("  same, physics 1st order", "(same)", Correction(geometry, [first_order], region), seconds))
        label = f"{per_side}x{per_side}"
        for method, named, correction, training in rows:
            validation = plate(cell, settings, VALIDATION, correction, VALIDATION_DRAWS)
            full = validation.true_metrics.full
            central = validation.true_metrics.field(150.0)
            print(f"{label:6s} {method:26s} {named:58s} {full.rms_abs_mm:8.4f} {full.max_abs_mm:8.4f} "
                  f"{central.rms_abs_mm:8.4f} {central.max_abs_mm:8.4f} {validation.metrics.full.rms_abs_mm:8.4f} "
                  f"{training:8.2f}", flush=True)
        print(f"{'':6s} ({len(targets)}/{per_side ** 2} fiducials paired; measurement error vs truth "
              f"{rms(deviations - run.true_deviations):.4f} mm RMS; physics left {report.residual_rms_mm:.4f} mm "
              f"RMS for the RBF, residual CV RMS {report.cv_rms_mm:.4f} mm; measuring {measuring:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
