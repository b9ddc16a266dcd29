"""The plate height at marking: TRUE error after calibration with and without the stand-still height.

Issue 31 item 5. Runs the calibrate flow (one iteration, validation plate) in one process through
``DirectCell`` -- the same core steps as the nodes, without ROS -- with the calibration manager's
plan from ``config/gls.yaml``, for each seed, with ``standstill_height`` on or off, and prints per
run, over the validation grid: TRUE RMS / max, MEASURED RMS, and the radial scale ``s`` of the TRUE
residual (least squares of delta = s * r, r from the grid's centre) with the RMS it accounts for.

Run: .venv/bin/python benchmarks/bench_standstill.py [--preset ideal] [--seeds 23 24 25 26 27] [--standstill on|off]
"""
from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from direct_runs import calibrate_validated, direct_cell, plan_settings
from gls_calibration.calibration import procedure
from gls_calibration.simulation.world import load_sim_config


def radial_scale(targets_xy: np.ndarray, deviations: np.ndarray) -> tuple[float, float]:
    """Least-squares scale s of deviations = s * r (r from the targets' centre) and the RMS |s r|."""
    r = targets_xy - targets_xy.mean(axis=0)
    scale = float(np.sum(deviations * r) / np.sum(r * r))
    return scale, abs(scale) * float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def calibrate_once(preset: str, seed: int, standstill: bool, store_dir: Path) -> procedure.PlateRun:
    cell = direct_cell(dataclasses.replace(load_sim_config(preset=preset), seed=seed), store_dir)
    return calibrate_validated(cell, plan_settings(cell, standstill_height=standstill)).validation


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="ideal")
    parser.add_argument("--seeds", nargs="+", type=int, default=[23, 24, 25, 26, 27])
    parser.add_argument("--standstill", choices=("on", "off"), default="on")
    args = parser.parse_args()
    print(f"preset {args.preset}, stand-still height {args.standstill}; validation grid, mm")
    print(f"{'seed':>4s} {'TRUE rms':>9s} {'TRUE max':>9s} {'MEAS rms':>9s} "
          f"{'scale':>10s} {'scale rms':>9s} {'wall s':>7s}")
    worst = 0.0
    for seed in args.seeds:
        began = time.perf_counter()
        with tempfile.TemporaryDirectory() as folder:
            run = calibrate_once(args.preset, seed, args.standstill == "on", Path(folder))
        scale, scale_rms = radial_scale(run.paired_targets_xy, run.true_deviations)
        true_rms = run.true_metrics.full.rms_abs_mm
        worst = max(worst, true_rms)
        print(f"{seed:4d} {true_rms:9.4f} {run.true_metrics.full.max_abs_mm:9.4f} {run.metrics.full.rms_abs_mm:9.4f} "
              f"{scale:10.2e} {scale_rms:9.4f} {time.perf_counter() - began:7.0f}", flush=True)
    print(f"worst TRUE RMS {worst:.4f} mm")


if __name__ == "__main__":
    main()
