"""What the cell measures, what is true, and what it states, on a robot whose pose errors repeat.

Runs the calibrate flow (one iteration, validation plate) in one process through ``DirectCell`` --
the same core steps as the nodes, without ROS -- with the calibration manager's plan from
``config/gls.yaml``, for each preset and seed, and prints per run and per preset (median, worst):

- MEASURED: RMS / max of the validation plate's deviations, measured by the cell's own chain;
- TRUE: RMS / max of the validation plate's true landing errors (simulation ground truth);
- MEASURED/TRUE: how far the cell's own figure understates the truth.

``--robot off`` zeroes the robot's repeating errors of the preset (the preset as it was before they
existed, for the "no loss" comparison); ``--along-prior MM`` sets the separation's along-track prior
(the robot's along-track accuracy; default: the code's default).

``--sweep-plan PLAN`` replaces the plan's passes over the marked plates (and the lines of the chain
map) by PLAN, e.g. ``0+,90+,45+``; ``--plain-sweeps N`` the plan's number of plain-plate sweeps.

``--chain-map`` runs every calibration twice on the same cell: without and with a chain map
(``registration/chain_map.py``), measured before the calibration on the certified plate over the whole field
(``reference_plate.FIELD_PLATE``) along the calibration's lines, ``--map-repeats`` sweeps per line
(default 2), and prints the figures side by side with the map's cell time.

Run: .venv/bin/python benchmarks/bench_honest_robot.py [--presets paper_like careful] [--seeds 1 2 3 4 5]
     [--chain-map [--map-repeats 2]] [--sweep-plan PLAN] [--plain-sweeps N]
"""
from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
from pathlib import Path

from direct_runs import calibrate_validated, direct_cell, plan_settings
from gls_calibration.calibration import procedure
from gls_calibration.registration.chain_map import ChainMap
from gls_calibration.registration.separation import SeparationSettings
from gls_calibration.registration.sweep_plan import SweepPass, parse_plan, plan_label
from gls_calibration.simulation.reference_plate import FIELD_PLATE, calibration_plan, measure_chain_map
from gls_calibration.simulation.world import load_sim_config

ROBOT_OFF = dict(robot_scale_error=0.0, robot_along_error_mm=0.0, robot_path_error_mm=0.0, robot_along_wander_mm=0.0)


def cell_config(preset: str, seed: int, robot: bool):
    """The simulated cell of ``preset`` and ``seed``, the robot's repeating errors off unless ``robot``."""
    config = load_sim_config(preset=preset)
    chain = config.measurement if robot else dataclasses.replace(config.measurement, **ROBOT_OFF)
    return dataclasses.replace(config, seed=seed, measurement=chain)


def map_cell_time_s(repeats: int, plan=None) -> float:
    """Cell time of a chain map: ``repeats`` sweeps of every line of the plan (default: config/gls.yaml's)."""
    timing = procedure.ProcedureSettings().cell_time
    return repeats * len((plan or calibration_plan()).passes) * timing.plate_s(1, 0.0)


def calibrate_once(preset: str, seed: int, robot: bool, separation: SeparationSettings | None, store_dir: Path,
                   chain_map: ChainMap | None = None, sweep_plan: tuple[SweepPass, ...] | None = None,
                   plain_sweeps: int | None = None) -> dict:
    cell = direct_cell(cell_config(preset, seed, robot), store_dir)
    varied = dict(sweep_plan=sweep_plan, plain_sweeps=plain_sweeps, separation=separation)
    given = {key: value for key, value in varied.items() if value is not None}    # None: the plan's own
    settings = plan_settings(cell, chain_map=chain_map, **given)
    began = time.perf_counter()
    outcome = calibrate_validated(cell, settings)
    validation = outcome.validation
    return {"measured_rms": validation.metrics.full.rms_abs_mm, "measured_max": validation.metrics.full.max_abs_mm,
            "true_rms": validation.true_metrics.full.rms_abs_mm, "true_max": validation.true_metrics.full.max_abs_mm,
            "pre_rms": outcome.runs[0].metrics.full.rms_abs_mm, "wall_s": time.perf_counter() - began}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["paper_like"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3, 4, 5])
    parser.add_argument("--robot", choices=("on", "off"), default="on")
    parser.add_argument("--along-prior", type=float, default=None, help="separation along_prior_sigma_mm")
    parser.add_argument("--chain-map", action="store_true", help="also calibrate with a chain map; both side by side")
    parser.add_argument("--map-repeats", type=int, default=2, help="sweeps per line of the chain map (default 2)")
    parser.add_argument("--sweep-plan", default=None, metavar="PLAN",
                        help="passes over the marked plates instead of config/gls.yaml's, e.g. 0+,90+,45+")
    parser.add_argument("--plain-sweeps", type=int, default=None, metavar="N",
                        help="plain-plate sweeps instead of config/gls.yaml's sweep.plain_repeats")
    args = parser.parse_args()
    if args.plain_sweeps is not None and args.plain_sweeps < 1:
        parser.error("--plain-sweeps must be at least 1")
    if args.sweep_plan is not None:
        try:
            args.sweep_plan = parse_plan(args.sweep_plan)      # parsed once: the passes from here on
        except ValueError as error:
            parser.error(f"--sweep-plan: {error}")
    if args.map_repeats < 1:
        parser.error("--map-repeats must be at least 1")
    separation = None if args.along_prior is None else SeparationSettings(along_prior_sigma_mm=args.along_prior)
    along_prior_mm = SeparationSettings().along_prior_sigma_mm if args.along_prior is None else args.along_prior
    plan = calibration_plan()
    plain_sweeps = plan.plain_sweeps if args.plain_sweeps is None else args.plain_sweeps
    print(f"plan {plan_label(args.sweep_plan or plan.passes)}, {plain_sweeps} plain sweep(s); "
          f"robot repeating errors {args.robot}; along prior {along_prior_mm} mm")
    if args.chain_map:
        compare_chain_map(args, separation)
        return
    print(f"{'preset':11s} {'seed':>4s} {'pre':>7s} {'MEAS rms':>9s} {'MEAS max':>9s} {'TRUE rms':>9s} "
          f"{'TRUE max':>9s} {'TRUE/MEAS':>9s} {'wall s':>7s}")
    for preset in args.presets:
        rows = []
        for seed in args.seeds:
            with tempfile.TemporaryDirectory() as folder:
                row = calibrate_once(preset, seed, args.robot == "on", separation, Path(folder),
                                     sweep_plan=args.sweep_plan, plain_sweeps=args.plain_sweeps)
            rows.append(row)
            print(f"{preset:11s} {seed:4d} {row['pre_rms']:7.4f} {row['measured_rms']:9.4f} {row['measured_max']:9.4f} "
                  f"{row['true_rms']:9.4f} {row['true_max']:9.4f} {row['true_rms'] / row['measured_rms']:9.2f} "
                  f"{row['wall_s']:7.1f}", flush=True)
        for label, pick in (("median", statistics.median), ("worst", max)):
            print(f"{preset:11s} {label:>6s} {'':5s} {pick(r['measured_rms'] for r in rows):9.4f} "
                  f"{pick(r['measured_max'] for r in rows):9.4f} {pick(r['true_rms'] for r in rows):9.4f} "
                  f"{pick(r['true_max'] for r in rows):9.4f}")


def compare_chain_map(args: argparse.Namespace, separation: SeparationSettings | None) -> None:
    """TRUE and MEASURED without and with a chain map, per preset and seed, and their medians."""
    plan = calibration_plan()
    if args.sweep_plan is not None:
        plan = dataclasses.replace(plan, passes=args.sweep_plan)
    print(f"chain map: {FIELD_PLATE.label}, {args.map_repeats} sweep(s) per line of {plan.label}, "
          f"cell time {map_cell_time_s(args.map_repeats, plan):.0f} s; mm")
    print(f"{'preset':11s} {'seed':>4s} {'MEAS w/o':>9s} {'MEAS map':>9s} {'TRUE w/o':>9s} {'TRUE map':>9s} "
          f"{'TMAX w/o':>9s} {'TMAX map':>9s} {'map fit x/y':>13s}")
    keys = ("measured_rms", "measured_rms_map", "true_rms", "true_rms_map", "true_max", "true_max_map")
    for preset in args.presets:
        rows = []
        for seed in args.seeds:
            config = cell_config(preset, seed, args.robot == "on")
            chain_map = measure_chain_map(config, plan, seed=seed, repeats=args.map_repeats)
            row = {}
            for suffix, used in (("", None), ("_map", chain_map)):
                with tempfile.TemporaryDirectory() as folder:
                    result = calibrate_once(preset, seed, args.robot == "on", separation, Path(folder), used,
                                            args.sweep_plan, args.plain_sweeps)
                row.update({f"{key}{suffix}": value for key, value in result.items()})
            rows.append(row)
            fit = chain_map.residual_rms_mm
            print(f"{preset:11s} {seed:4d} " + " ".join(f"{row[key]:9.4f}" for key in keys)
                  + f" {fit[0]:6.4f}/{fit[1]:6.4f}", flush=True)
        for label, pick in (("median", statistics.median), ("worst", max)):
            print(f"{preset:11s} {label:>6s} " + " ".join(f"{pick(r[key] for r in rows):9.4f}" for key in keys),
                  flush=True)


if __name__ == "__main__":
    main()
