"""What each step of the measurement contributes: the error of one plate's measured deviations.

Runs ``procedure.run_plate`` (scan the plain plate, mark the 19x19 grid through the nominal model,
scan the marked plate, measure, pair) on ``DirectCell`` for each way of measuring below and prints
the MEASURED minus TRUE deviations of the paired fiducials after their common shift is removed
(a shift of the whole plate is not a measurement error the calibration sees): RMS and max of the
2-D error, mm. The TRUE deviations are the simulated marks' own, aligned as the measurement is.

A repeating error of the robot's reported pose is measured again on every run of the same line, so
it is in this figure as in the calibration's TRUE error, but not in the validation plate's MEASURED
figure (see ``calibration/stated_accuracy.py``).

``--plans P [P ...]`` measures only the given plans, placed by pose (e.g. ``0+,90+,45+``).

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_measurement_steps.py
     [--preset paper_like] [--seeds 1 2 3] [--plans 0+,0-,90+,90- 0+,90+,45+]
"""
from __future__ import annotations

import argparse
import asyncio
import dataclasses
import statistics
import tempfile
from pathlib import Path

import numpy as np

from direct_runs import direct_cell, plan_settings
from gls_calibration.calibration import procedure
from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.registration.sweep_plan import parse_plan
from gls_calibration.simulation.world import load_sim_config

WAYS = (("one sweep placed by time (the paper's way)", "0+", False),
        ("one sweep placed by pose", "0+", True),
        ("0+,90+ by pose", "0+,90+", True),
        ("0+,0-,90+,90- by pose", "0+,0-,90+,90-", True),
        ("0+,90+,45+ by pose (config/gls.yaml)", "0+,90+,45+", True),
        ("0+,0-,90+,90- placed by time (no pose stream)", "0+,0-,90+,90-", False))
"""(label, passes over the marked plate, profiles placed by the reported pose)."""


def measurement_error(preset: str, seed: int, passes: str, by_pose: bool, store_dir: Path) -> tuple[float, float]:
    """RMS and max (mm) of one plate's MEASURED minus TRUE deviations, their common shift removed."""
    cell = direct_cell(dataclasses.replace(load_sim_config(preset=preset), seed=seed), store_dir,
                       placed_by_pose=by_pose)
    settings = plan_settings(cell, sweep_plan=parse_plan(passes), profiles_placed_by_pose=by_pose)
    run = asyncio.run(procedure.run_plate(cell, settings, grid_targets(19, 190.0), lambda *_: None, (0.0, 1.0),
                                          want_truth=True))
    error = run.deviations - run.true_deviations
    error -= error.mean(axis=0)
    length = np.hypot(error[:, 0], error[:, 1])
    return float(np.sqrt(np.mean(length ** 2))), float(length.max())


def main() -> None:
    """Print the table: one row per way of measuring and seed, then the medians."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="paper_like")
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3])
    parser.add_argument("--plans", nargs="+", metavar="PLAN", help="only these plans, placed by pose")
    args = parser.parse_args()
    ways = WAYS
    if args.plans:
        for plan in args.plans:
            try:
                parse_plan(plan)
            except ValueError as error:
                parser.error(f"--plans: {error}")
        ways = tuple((f"{plan} by pose", plan, True) for plan in args.plans)
    print(f"DirectCell, {args.preset}, one 19x19 plate marked through the nominal model; MEASURED - TRUE "
          "deviations, common shift removed, RMS / max of the 2-D error (mm)")
    for label, passes, by_pose in ways:
        rows = []
        for seed in args.seeds:
            with tempfile.TemporaryDirectory() as store:
                rows.append(measurement_error(args.preset, seed, passes, by_pose, Path(store)))
            print(f"  seed {seed}: {label}: {rows[-1][0]:.4f} / {rows[-1][1]:.4f}", flush=True)
        print(f"{label}: median {statistics.median(r[0] for r in rows):.4f} / "
              f"{statistics.median(r[1] for r in rows):.4f}", flush=True)


if __name__ == "__main__":
    main()
