"""The certificate's U proven in simulation: coverage of the TRUE landing error on the validation plate.

Per preset and seed: the reference check of the calibration's plan on the simulated reference plate
(``reference_plate_check``), then the calibrate flow through ``DirectCell`` (one iteration, validation
on a fresh plate half a pitch off the training grid), then U (``calibration.uncertainty``) from the
first plate, the trained model and the check -- nothing of the ground truth enters U. Each
validation fiducial's TRUE landing error (after the best rigid alignment of the whole true field,
as every figure of the package) is compared with U at its target. Prints per seed and pooled per
preset: coverage (fraction with |true error| <= U; target 0.92-0.985), median U, TRUE RMS and
median U / TRUE RMS (target <= 3), and the budget's contributions (per-axis k = 1 RMS over the field).

Run: PYTHONPATH=. .venv/bin/python benchmarks/bench_certificate.py [--presets careful paper_like]
     [--seeds 1 2 3 4 5] [--grid 19]
"""
from __future__ import annotations

import argparse
import asyncio
import dataclasses
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from gls_calibration.calibration import procedure
from gls_calibration.calibration.record import build_record, calibrated_region, save_candidate
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.calibration.uncertainty import CONTRIBUTIONS, run_budget
from gls_calibration.simulation.direct_cell import DirectCell
from gls_calibration.simulation.reference_plate import FIELD_PLATE, calibration_plan, chain_check, reference_plate_check
from gls_calibration.simulation.world import SimulatedCell, load_sim_config


def certify_once(preset: str, seed: int, grid: int, store_dir: Path, with_check: bool = True) -> dict:
    """One calibration with validation and its certificate; per validation fiducial |true error| and U."""
    config = dataclasses.replace(load_sim_config(preset=preset), seed=seed)
    plan = calibration_plan()
    check = None
    if with_check:
        result = reference_plate_check(config, plan, seed=seed, design=FIELD_PLATE)
        check = chain_check(result, plan, config, seed, FIELD_PLATE)
    cell = DirectCell(SimulatedCell(config), CalibrationStore(store_dir))
    settings = cell.settings(sweep_plan=plan.passes, plain_sweeps=plan.plain_sweeps, grid_per_side=grid,
                             plain_sweep_step_mm=plan.plain_step_mm, marked_sweep_step_mm=plan.marked_step_mm,
                             profiles_placed_by_pose=plan.placed_by_pose)

    def save(runs, models):
        return save_candidate(cell.store, build_record(config.geometry, settings, runs, models, []), config.geometry)

    outcome = asyncio.run(procedure.calibrate(cell, settings, iterations=1, validate=True, force=True,
                                              want_truth=True, progress=lambda *_: None, save_candidate=save))
    first = outcome.runs[0]
    region = calibrated_region(settings, float(np.mean(first.targets[:, 2]))).to_dict()
    began = time.perf_counter()
    budget = run_budget(outcome.runs, outcome.models, settings, region, config.geometry.working_distance_mm, check)
    budget_s = time.perf_counter() - began
    validation = outcome.validation
    targets = validation.paired_targets_xy
    u = budget.grid.at(targets[:, 0], targets[:, 1])
    true_error = np.hypot(*validation.true_deviations.T)
    return {"u": u, "true": true_error, "budget": budget, "budget_s": budget_s,
            "true_rms": float(np.sqrt(np.mean(true_error ** 2)))}


def serving_cost(repeats: int = 15) -> None:
    """Correction time with the U map against without it (the same 19x19 TPS calibration), in process:
    one batch of 100 000 targets and 2 000 single-target calls; best of ``repeats``."""
    from gls_calibration.calibration.uncertainty import TrainingData, uncertainty_budget
    from gls_calibration.correction.setpoints import CalibratedRegion, Correction
    from gls_calibration.fiducials.targets import grid_targets
    from gls_calibration.geometry.kinematics import HeadGeometry
    from gls_calibration.models.rbf import ThinPlateSplineModel

    rng = np.random.default_rng(0)
    xy = grid_targets(19, 190.0) + rng.normal(0.0, 0.3, (361, 2))
    values = 1e-3 * xy[:, ::-1] + rng.normal(0.0, 0.004, xy.shape)
    model = ThinPlateSplineModel(xy, values, 10.0)
    region = CalibratedRegion(-97.7, 97.7, -97.7, 97.7)
    grid = uncertainty_budget([TrainingData(xy, values, np.full(361, 0.004), model.to_dict())], region.to_dict(),
                              490.0, None, False).grid
    plain, certified = Correction(HeadGeometry(), [model], region), Correction(HeadGeometry(), [model], region,
                                                                               uncertainty=grid)
    x, y, z = rng.uniform(-100.0, 100.0, 100_000), rng.uniform(-100.0, 100.0, 100_000), rng.uniform(-5, 5, 100_000)

    def paired(call_plain, call_certified) -> tuple[float, float]:
        # interleaved, best of each: a loaded host slows both alike
        times: list[list[float]] = [[], []]
        for _ in range(repeats):
            for slot, call in enumerate((call_plain, call_certified)):
                began = time.perf_counter()
                call()
                times[slot].append(time.perf_counter() - began)
        return min(times[0]), min(times[1])

    for correction in (plain, certified):
        correction.correct(x, y, z, workers=1)     # tiles built before timing
    batch = paired(lambda: plain.correct(x, y, z, workers=1), lambda: certified.correct(x, y, z, workers=1))
    one = [(x[i:i + 1], y[i:i + 1], z[i:i + 1]) for i in range(2000)]     # as a service passes one target
    single = paired(lambda: [plain.correct(*target) for target in one],
                    lambda: [certified.correct(*target) for target in one])
    lookup = paired(lambda: None, lambda: grid.inside_at(np.clip(x, -97.7, 97.7), np.clip(y, -97.7, 97.7)))[1]
    print(f"U lookup alone for 100000 targets {lookup * 1e3:.1f} ms ({lookup / batch[0]:.1%} of the plain batch)")
    print(f"serving cost, in process: batch of 100000 {batch[0] * 1e3:.1f} -> {batch[1] * 1e3:.1f} ms "
          f"(ratio {batch[1] / batch[0]:.3f}); 2000 single targets {single[0] * 1e3:.1f} -> {single[1] * 1e3:.1f} ms "
          f"(ratio {single[1] / single[0]:.3f}); target <= 1.10", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["careful", "paper_like"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3, 4, 5])
    parser.add_argument("--grid", type=int, default=19)
    parser.add_argument("--no-check", action="store_true", help="no reference check: the chain term is assumed")
    parser.add_argument("--cost", action="store_true", help="only the serving cost of U (no calibration)")
    args = parser.parse_args()
    if args.cost:
        serving_cost()
        return
    print(f"grid {args.grid}x{args.grid}, plan {calibration_plan().label}, validation {args.grid - 1}x{args.grid - 1} "
          f"half a pitch off; reference check {'none' if args.no_check else FIELD_PLATE.label}; mm")
    print(f"{'preset':11s} {'seed':>4s} {'coverage':>8s} {'median U':>8s} {'TRUE rms':>8s} {'U/TRUE':>6s} "
          + " ".join(f"{name:>12s}" for name in CONTRIBUTIONS) + f" {'budget s':>8s}")
    for preset in args.presets:
        pooled_u, pooled_true, ratios = [], [], []
        for seed in args.seeds:
            with tempfile.TemporaryDirectory() as folder:
                row = certify_once(preset, seed, args.grid, Path(folder), not args.no_check)
            covered = float(np.mean(row["true"] <= row["u"]))
            median_u = float(np.median(row["u"]))
            ratios.append(median_u / row["true_rms"])
            pooled_u.append(row["u"])
            pooled_true.append(row["true"])
            parts = " ".join(f"{row['budget'].contribution(name).rms_mm:12.4f}" for name in CONTRIBUTIONS)
            print(f"{preset:11s} {seed:4d} {covered:8.3f} {median_u:8.4f} {row['true_rms']:8.4f} {ratios[-1]:6.2f} "
                  f"{parts} {row['budget_s']:8.2f}", flush=True)
        u, true = np.concatenate(pooled_u), np.concatenate(pooled_true)
        true_rms = float(np.sqrt(np.mean(true ** 2)))
        print(f"{preset:11s} pooled coverage {np.mean(true <= u):.3f} over {u.size} fiducials (target 0.92-0.985); "
              f"median U {np.median(u):.4f} mm, TRUE RMS {true_rms:.4f} mm, median U / TRUE RMS "
              f"{np.median(u) / true_rms:.2f} (target <= 3); per-seed U/TRUE median {statistics.median(ratios):.2f}",
              flush=True)


if __name__ == "__main__":
    main()
