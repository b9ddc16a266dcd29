"""A second calibration on a cell whose calibration is active: which figure is compared with which.

Issue 31 item 4. Runs the calibrate flow twice in one process through ``DirectCell`` (the same core
steps as the nodes, without ROS), with the calibration manager's plan from ``config/gls.yaml``:
the first calibration (validated) is activated, a fresh plate is loaded, and a second calibration
(forced, validated) runs through it. Prints, MEASURED by the cell's chain and TRUE from the
simulation's ground truth (RMS, mm):

- the active calibration on the run's first plate (its own training positions: SELF-CONSISTENCY);
- the candidate on the validation grid (INDEPENDENT positions);
- the active calibration on the validation grid (INDEPENDENT positions, the new comparison);

and the verdict of the old rule (candidate on the validation grid against the active calibration
on the first plate) and of the new one (both on the validation grid).

Run: .venv/bin/python benchmarks/bench_recalibration.py [--preset paper_like] [--seed 1]
"""
from __future__ import annotations

import argparse
import asyncio
import dataclasses
import tempfile
import time
from pathlib import Path

from gls_calibration.calibration import procedure
from gls_calibration.calibration.outcome import summarise
from direct_runs import calibrate_validated, direct_cell, plan_settings
from gls_calibration.simulation.world import load_sim_config


def figures(run: procedure.PlateRun) -> str:
    return f"{run.metrics.full.rms_abs_mm:.4f} measured / {run.true_metrics.full.rms_abs_mm:.4f} true"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="paper_like")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    config = dataclasses.replace(load_sim_config(preset=args.preset), seed=args.seed)
    began = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder:
        cell = direct_cell(config, Path(folder))
        settings = plan_settings(cell)
        first = calibrate_validated(cell, settings)
        print(f"{args.preset} seed {args.seed}, first calibration: {first.message}; candidate on the validation grid "
              f"{figures(first.validation)} mm RMS")
        cell.store.activate(first.candidate.path)
        cell.reload_active_now()
        asyncio.run(cell.exchange_plate())
        second = calibrate_validated(cell, settings)
    summary = summarise(second)
    uncertainty = max(procedure.centre_uncertainty_mm(second.runs[0], settings),
                      procedure.centre_uncertainty_mm(second.validation, settings))
    old_rule = procedure.acceptance_problem(second.runs[0].metrics.full.rms_abs_mm,
                                            second.validation.metrics.full.rms_abs_mm, uncertainty)
    print("second calibration, RMS mm:")
    print(f"  active calibration on its first plate ({summary.pre_kind}): {figures(second.runs[0])}")
    print(f"  candidate on the validation grid ({summary.post_kind}): {figures(second.validation)}")
    print(f"  active calibration on the validation grid ({summary.active_post_kind}): "
          f"{figures(second.active_validation)}")
    print(f"  old rule (validation vs first plate): {'rejected' if old_rule else 'accepted'}")
    print(f"  new rule (judged against: {summary.accepted_against}): "
          f"{'rejected: ' + second.rejection if second.rejection else 'accepted'}")
    print(f"wall time {time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
