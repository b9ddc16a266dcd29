"""Accuracy against cell time: which measurement plans buy accuracy, on a robot whose errors repeat.

Runs the calibrate flow (one iteration, validation plate) through ``DirectCell`` -- the core steps
of the nodes, without ROS -- for each plan and seed and prints the TRUE and MEASURED RMS on the
validation grid and the cell time of the whole calibration (training and validation plate: sweeps
at the configured speed, robot moves, marking; ``sweep_plan.CellTimeModel``). A plan is the number
of plain-plate sweeps and the passes over the marked plate; the stand-still plate height is on in
every plan. ``--chain-map`` also runs each plan with a chain map of its own lines, measured once
before (its cell time printed apart: it is renewed on a schedule, not per calibration).

The sweep speed is not varied: the simulated robot's errors do not depend on its speed (its
ripple and wander are functions of the distance travelled), so a faster sweep would look free here
and the figure would describe the simulator, not a cell.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_cell_time.py [--preset paper_like]
     [--seeds 1 2 3] [--chain-map [--map-only]] [--plan PLAIN:PASSES ...]
"""
from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
from pathlib import Path

from direct_runs import calibrate_validated, direct_cell, plan_settings
from gls_calibration.calibration import procedure
from gls_calibration.registration.sweep_plan import parse_plan, plan_label
from gls_calibration.simulation.reference_plate import calibration_plan, measure_chain_map
from gls_calibration.simulation.world import load_sim_config

PLANS = ((4, "0+,0-,90+,90-"), (1, "0+,0-,90+,90-"), (2, "0+,90+"), (1, "0+,90+"), (1, "0+"), (4, "0+,90+,45+"),
         (1, "0+,90+,45+"))
"""(plain sweeps, passes over the marked plate); (4, "0+,90+,45+") is config/gls.yaml's."""


def calibrate(preset: str, seed: int, plain_sweeps: int, passes: str, chain_map, store_dir: Path) -> dict:
    cell = direct_cell(dataclasses.replace(load_sim_config(preset=preset), seed=seed), store_dir)
    outcome = calibrate_validated(cell, plan_settings(cell, sweep_plan=parse_plan(passes), plain_sweeps=plain_sweeps,
                                                      profiles_placed_by_pose=True, chain_map=chain_map))
    validation = outcome.validation
    return {"true_rms": validation.true_metrics.full.rms_abs_mm, "true_max": validation.true_metrics.full.max_abs_mm,
            "measured_rms": validation.metrics.full.rms_abs_mm,
            "cell_time_s": sum(run.cell_time_s for run in outcome.runs) + validation.cell_time_s}


def map_for(preset: str, seed: int, passes: str):
    """The chain map of ``passes``' lines on the cell of ``preset`` and ``seed``, and its cell time (s)."""
    config = dataclasses.replace(load_sim_config(preset=preset), seed=seed)
    plan = dataclasses.replace(calibration_plan(), passes=parse_plan(passes))
    timing = procedure.ProcedureSettings().cell_time
    repeats = 2
    return (measure_chain_map(config, plan, seed=seed, repeats=repeats),
            repeats * len(plan.passes) * timing.plate_s(1, 0.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="paper_like")
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3])
    parser.add_argument("--chain-map", action="store_true", help="also run each plan with a chain map of its lines")
    parser.add_argument("--map-only", action="store_true", help="with --chain-map: only the runs with the map")
    parser.add_argument("--plan", action="append", metavar="PLAIN:PASSES",
                        help="a plan to run, e.g. 1:0+,0-,90+,90- (repeatable; default: the table's seven)")
    args = parser.parse_args()
    plans = PLANS
    if args.plan:
        try:
            plans = tuple((int(text.split(":", 1)[0]), plan_label(parse_plan(text.split(":", 1)[1])))
                          for text in args.plan)
        except (ValueError, IndexError) as error:
            parser.error(f"--plan must be PLAIN:PASSES such as 1:0+,90+ ({error})")
    if args.map_only and not args.chain_map:
        parser.error("--map-only needs --chain-map")
    print(f"DirectCell, {args.preset}, 19x19, 1 iteration + validation plate, stand-still height; TRUE and "
          "MEASURED RMS on the validation grid (mm), cell time of the whole calibration (s)")
    print(f"{'plain':>5} {'passes':>14} {'map':>4} {'seed':>4} {'TRUE':>8} {'TRUE max':>8} {'MEASURED':>9} "
          f"{'cell s':>7} {'map s':>6}")
    for plain, passes in plans:
        for with_map in ((True,) if args.map_only else (False, True)) if args.chain_map else (False,):
            rows = []
            for seed in args.seeds:
                chain_map, map_s = map_for(args.preset, seed, passes) if with_map else (None, 0.0)
                with tempfile.TemporaryDirectory() as store:
                    row = calibrate(args.preset, seed, plain, passes, chain_map, Path(store))
                rows.append(row)
                print(f"{plain:>5} {passes:>14} {'yes' if with_map else 'no':>4} {seed:>4} {row['true_rms']:>8.4f} "
                      f"{row['true_max']:>8.3f} {row['measured_rms']:>9.4f} {row['cell_time_s']:>7.0f} "
                      f"{map_s:>6.0f}", flush=True)
            print(f"{plain:>5} {passes:>14} {'yes' if with_map else 'no':>4} {'med':>4} "
                  f"{statistics.median(r['true_rms'] for r in rows):>8.4f} "
                  f"{statistics.median(r['true_max'] for r in rows):>8.3f} "
                  f"{statistics.median(r['measured_rms'] for r in rows):>9.4f} "
                  f"{statistics.median(r['cell_time_s'] for r in rows):>7.0f}", flush=True)


if __name__ == "__main__":
    main()
