"""How much one reference check depends on its own draw: the check redrawn, its field's symmetric shear.

The stated accuracy adds one reference check of the chain to the measured figure
(``calibration/stated_accuracy.py``). The check's sweeps carry random errors of their own; this
benchmark measures the check ``--draws`` times on the same simulated cell (the same repeating robot
error, the same chain map with ``--chain-map``), draw 0 being the one ``gls-sim-cell`` and
``bench_stated_accuracy.py`` use (check seed = cell seed; draw d uses seed + 1000 d, plate and sweeps).
Per draw it prints the check's 2-D figure sqrt(sigma_x^2 + sigma_y^2), the symmetric shear s of its
residual field (least squares delta_x = s y, delta_y = s x over the plate, with a shift; per mm),
that shear's RMS and the figure without it; and, from one calibration of the same cell through
``DirectCell`` (one iteration, validation plate), the STATED / TRUE ratio each draw would give, and
the same for the check pooled over draws 0..d (each known centre's residual averaged over the draws,
the per-axis figure taken from that mean field as ``reference_plate_check`` takes it).

Why the shear: a symmetric shear of the marks cannot be told from the same cross-track slope in
every sweep of both orientations (each sweep's path yaw), so the separation leaves the marks with
the mean of the sweeps' random slopes; the check and the calibration each carry a draw of it.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_check_draws.py [--preset paper_like]
     [--seeds 3] [--draws 4] [--chain-map]
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import tempfile
from pathlib import Path

import numpy as np

from bench_honest_robot import calibrate_once
from gls_calibration.calibration.reference_check import residual_sigma_mm
from gls_calibration.calibration.procedure import ProcedureSettings, training_grid
from gls_calibration.calibration.stated_accuracy import stated_accuracy
from gls_calibration.discrepancy.residual_statistics import rms
from gls_calibration.registration.chain_map import chain_map_identity
from gls_calibration.simulation.reference_plate import (FIELD_PLATE, calibration_plan, chain_check,
                                                        measure_chain_map, reference_plate_check)
from gls_calibration.simulation.world import load_sim_config

# the shipped calibration grid: what the stated figure covers, and the check must reach
GRID = training_grid(ProcedureSettings())

DRAW_SEED_STEP = 1000
"""Check seed of draw d: cell seed + d x this (draw 0 is the check the cell uses)."""


def symmetric_shear(known_xy: np.ndarray, residuals: np.ndarray) -> tuple[float, np.ndarray]:
    """Least-squares s of residuals = shift + s (y, x) about the centres' mean, and that field (N, 2)."""
    centred = known_xy - known_xy.mean(axis=0)
    swapped = centred[:, ::-1]
    about = residuals - residuals.mean(axis=0)
    s = float(np.sum(about * swapped) / np.sum(swapped * swapped))
    return s, s * swapped


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="paper_like")
    parser.add_argument("--seeds", nargs="+", type=int, default=[3])
    parser.add_argument("--draws", type=int, default=4)
    parser.add_argument("--chain-map", action="store_true", help="measure a chain map first and apply it")
    args = parser.parse_args()
    if args.draws < 1:
        parser.error("--draws must be at least 1")
    plan = calibration_plan()
    print(f"{args.preset}, plan {plan.label}, check on {FIELD_PLATE.label}, chain map "
          f"{'on' if args.chain_map else 'off'}; mm, shear per mm")
    print(f"{'seed':>4s} {'draw':>4s} {'check':>8s} {'shear':>10s} {'its RMS':>8s} {'rest':>8s} {'STATED/TRUE':>11s}"
          f" {'pooled':>8s} {'its S/T':>7s}")
    for seed in args.seeds:
        config = dataclasses.replace(load_sim_config(preset=args.preset), seed=seed)
        chain_map = measure_chain_map(config, plan, seed=seed) if args.chain_map else None
        with tempfile.TemporaryDirectory() as folder:
            run = calibrate_once(args.preset, seed, True, None, Path(folder), chain_map=chain_map)
        print(f"{seed:4d} calibration: MEASURED {run['measured_rms']:.4f}, TRUE {run['true_rms']:.4f}", flush=True)
        residuals, knowns = [], []
        for draw in range(args.draws):
            check_seed = seed + DRAW_SEED_STEP * draw
            result = reference_plate_check(config, plan, seed=check_seed, design=FIELD_PLATE, chain_map=chain_map)
            shear, field = symmetric_shear(result.known_xy_mm, result.residuals_mm)
            check = chain_check(result, plan, config, check_seed, FIELD_PLATE, chain_map)
            stated = stated_accuracy(run["measured_rms"], check, plan=plan.label, placement=plan.placement,
                                     chain_map=chain_map_identity(chain_map), targets_xy_mm=GRID)
            # The check pooled over draws 0..d: each known centre's residual averaged over the draws,
            # then the per-axis standard deviation as chain_check takes it (pooled only while every
            # draw found the same known centres).
            residuals.append(result.residuals_mm)
            knowns.append(result.known_xy_mm)
            pooled_text = f"{'n/a':>8s} {'n/a':>7s}"
            if all(np.array_equal(known, knowns[0]) for known in knowns):
                mean = np.mean(residuals, axis=0)
                pooled_sigma = residual_sigma_mm(mean)
                pooled = stated_accuracy(run["measured_rms"], dataclasses.replace(check, sigma_mm=pooled_sigma),
                                         plan=plan.label, placement=plan.placement,
                                         chain_map=chain_map_identity(chain_map), targets_xy_mm=GRID)
                pooled_text = f"{math.hypot(*pooled_sigma):8.4f} {pooled.rms_mm / run['true_rms']:7.2f}"
            print(f"{seed:4d} {draw:4d} {math.hypot(*result.sigma_mm):8.4f} {shear:+10.2e} {rms(field):8.4f} "
                  f"{rms(result.residuals_mm - field):8.4f} {stated.rms_mm / run['true_rms']:11.2f} {pooled_text}",
                  flush=True)


if __name__ == "__main__":
    main()
