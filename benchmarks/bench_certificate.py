"""The certificate's U proven in simulation: coverage of the TRUE landing error on the validation plate.

Per preset and seed: the reference check of the calibration's plan on the simulated reference plate
(``reference_plate_check``), then the calibrate flow through ``DirectCell`` (one iteration, validation
on a fresh plate half a pitch off the training grid), then U (``calibration.uncertainty``) from the
first plate, the trained model and the check -- nothing of the ground truth enters U. Each
validation fiducial's TRUE landing error (after the best rigid alignment of the whole true field,
as every figure of the package) is compared with U at its target. Prints per seed and pooled per
preset: coverage (fraction with |true error| <= U; target 0.92-0.985), median U, TRUE RMS and
median U / TRUE RMS (target <= 3), and the budget's contributions (per-axis k = 1 RMS over the field);
each for the budget as trained (what a calibration without a validation plate serves) and with the
validation floor (``uncertainty.with_validation_floor``: what the calibrate flow activates after its
validation plate), with the validation's MEASURED RMS and the per-axis term the floor added.

``--cost`` / ``--cost-ros``: what serving U costs (issue 30: at most 10 % more time), in process and
through the correction node in a process of its own; with and without U timed in alternating pairs,
the median of the per-pair ratios and its quartiles, of wall and of CPU time.

Run: PYTHONPATH=. .venv/bin/python benchmarks/bench_certificate.py [--presets careful paper_like]
     [--seeds 1 2 3 4 5] [--grid 19] [--physics-first]
     PYTHONPATH=. .venv/bin/python benchmarks/bench_certificate.py --cost --cost-ros [--pairs 41]
     (ROS_DOMAIN_ID defaults to 57 and discovery to localhost for the nodes it starts)
"""
from __future__ import annotations

import argparse
import asyncio
import dataclasses
import os
import statistics
import tempfile
import time
import timeit
from pathlib import Path

import numpy as np

from gls_calibration.calibration import procedure
from gls_calibration.calibration.record import build_record, calibrated_region, save_candidate
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.calibration.uncertainty import (CONTRIBUTIONS, VALIDATION_FLOOR, check_matches_run, run_budget,
                                                     with_validation_floor)
from gls_calibration.simulation.direct_cell import DirectCell
from gls_calibration.simulation.reference_plate import FIELD_PLATE, calibration_plan, chain_check, reference_plate_check
from gls_calibration.simulation.world import SimulatedCell, load_sim_config


def certify_once(preset: str, seed: int, grid: int, store_dir: Path, with_check: bool = True,
                 physics_first: bool = False) -> dict:
    """One calibration with validation and its certificate; per validation fiducial |true error| and U.

    ``physics_first``: the cell trains the named physical effects first and the RBF/TPS on what they
    leave (``training.train_correction``), as ``gls-sim-cell --physics-first``.
    """
    config = dataclasses.replace(load_sim_config(preset=preset), seed=seed)
    plan = calibration_plan()
    check = None
    if with_check:
        result = reference_plate_check(config, plan, seed=seed, design=FIELD_PLATE)
        check = chain_check(result, plan, config, seed, FIELD_PLATE)
    cell = DirectCell(SimulatedCell(config), CalibrationStore(store_dir), physics_first=physics_first)
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
    floored = with_validation_floor(budget, validation.metrics.full.rms_abs_mm, check,
                                    check_matches_run(check, first, settings))
    targets = validation.paired_targets_xy
    u = budget.grid.at(targets[:, 0], targets[:, 1])
    true_error = np.hypot(*validation.true_deviations.T)
    return {"u": u, "u_floored": floored.grid.at(targets[:, 0], targets[:, 1]), "true": true_error,
            "budget": budget, "floored": floored, "budget_s": budget_s, "method": outcome.models[0].method,
            "true_rms": float(np.sqrt(np.mean(true_error ** 2))), "post_rms": validation.metrics.full.rms_abs_mm}


def cost_calibration():
    """The serving-cost case: a 19x19 thin-plate spline over the 190 mm field and its U map.

    Returns
    -------
    tuple
        (record without the ``uncertainty`` key, the U map as a record's mapping, the correction
        without U, the correction with U)
    """
    from gls_calibration.calibration.record_file import new_record
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
    budget = uncertainty_budget([TrainingData(xy, values, np.full(361, 0.004), model.to_dict())], region.to_dict(),
                                490.0, None, False)
    zeros = np.zeros(len(xy))
    record = new_record(head=HeadGeometry(), plate_pose={"normal": [0, 0, 1], "centre": [0, 0, 0],
                                                         "rotation": np.eye(3), "flatness_rms_mm": 0.0},
                        models=[model.to_dict()], calibrated_region={**region.to_dict(), "taper_mm": 10.0},
                        hyper_parameters={}, metrics={},
                        fiducials={"target_x": xy[:, 0], "target_y": xy[:, 1], "measured_x": xy[:, 0],
                                   "measured_y": xy[:, 1], "measured_z": zeros, "dx": zeros, "dy": zeros})
    return (record, budget.to_dict(), Correction(HeadGeometry(), [model], region),
            Correction(HeadGeometry(), [model], region, uncertainty=budget.grid))


def paired_ratios(without, with_u, pairs: int, cpu_clocks) -> dict:
    """Time ``without`` and ``with_u`` back to back ``pairs`` times (which goes first alternates);
    per pair the ratio with / without, of wall time and of CPU time (``cpu_clocks``: the clock of the
    process or thread that does the work of each, in seconds).

    A loaded host slows a pair's two halves alike, so the median of the per-pair ratios is steadier
    than a ratio of two separate medians or minima.

    Returns
    -------
    dict
        ``wall`` and ``cpu``: (median ratio, first and third quartile, 95 % confidence interval of the
        median); ``wall_s`` and ``cpu_s``: the median times without and with (s).
    """
    times = {clock: ([], []) for clock in ("wall", "cpu")}
    for index in range(pairs):
        for slot in ((0, 1) if index % 2 == 0 else (1, 0)):
            cpu_clock = cpu_clocks[slot]
            cpu_began, began = cpu_clock(), time.perf_counter()
            (without, with_u)[slot]()
            times["wall"][slot].append(time.perf_counter() - began)
            times["cpu"][slot].append(cpu_clock() - cpu_began)
    figures = {}
    for clock, (plain, certified) in times.items():
        ratios = sorted(b / a for a, b in zip(plain, certified))
        low, _, high = statistics.quantiles(ratios, n=4)
        # distribution-free 95 % confidence interval of the median: order statistics n/2 -+ 0.98 sqrt(n)
        rank = max(0, int((len(ratios) - 1.96 * len(ratios) ** 0.5) / 2))
        figures[clock] = (statistics.median(ratios), low, high, ratios[rank], ratios[-1 - rank])
        figures[f"{clock}_s"] = (statistics.median(plain), statistics.median(certified))
    return figures


def print_pairs(what: str, figures: dict, unit: float, unit_name: str, pairs: int,
                target: str = "ratio <= 1.10") -> None:
    """One line per measured case: median times and the median per-pair ratio (quartiles), wall and CPU."""
    parts = []
    for clock in ("wall", "cpu"):
        plain, certified = figures[f"{clock}_s"]
        ratio, low, high, ci_low, ci_high = figures[clock]
        parts.append(f"{clock} {plain / unit:.3g} -> {certified / unit:.3g} {unit_name}, ratio {ratio:.3f} "
                     f"(95 % CI {ci_low:.3f}-{ci_high:.3f}, quartiles {low:.3f}-{high:.3f})")
    print(f"{what}: {'; '.join(parts)}; {pairs} pairs; target {target}", flush=True)


def serving_cost(pairs: int = 41) -> None:
    """Correction time with the U map against without it (the same 19x19 TPS calibration), in process
    and in this thread: one batch of 100 000 targets, and blocks of 2 000 single-target calls."""
    loading_cost(max(7, pairs // 10))     # first: what else this process holds slows its garbage collection
    _, _, plain, certified = cost_calibration()
    rng = np.random.default_rng(1)
    x, y, z = rng.uniform(-100.0, 100.0, 100_000), rng.uniform(-100.0, 100.0, 100_000), rng.uniform(-5, 5, 100_000)
    for correction in (plain, certified):
        correction.correct(x, y, z, workers=1)     # tiles built before timing
    clamped = np.clip(x, -97.7, 97.7), np.clip(y, -97.7, 97.7)
    lookup = statistics.median(timeit.repeat(lambda: certified.uncertainty.inside_at(*clamped), number=1, repeat=21))
    one_lookup = min(timeit.repeat(lambda: certified.uncertainty.at_point(12.3, -40.1), number=2000, repeat=7)) / 2000
    batch = paired_ratios(lambda: plain.correct(x, y, z, workers=1), lambda: certified.correct(x, y, z, workers=1),
                          pairs, (time.thread_time, time.thread_time))
    one = [(x[i:i + 1], y[i:i + 1], z[i:i + 1]) for i in range(2000)]     # as a service passes one target
    single = paired_ratios(lambda: [plain.correct(*target) for target in one],
                           lambda: [certified.correct(*target) for target in one], pairs,
                           (time.thread_time, time.thread_time))
    print(f"U lookup alone: 100 000 targets {lookup * 1e3:.2f} ms ({lookup / batch['wall_s'][0]:.1%} of the plain "
          f"batch); one target {one_lookup * 1e6:.2f} us "
          f"({one_lookup * 2000 / single['wall_s'][0]:.1%} of a plain call)")
    print_pairs("in process, batch of 100 000", batch, 1e-3, "ms", pairs)
    print_pairs("in process, 2 000 single-target calls", single, 1e-3, "ms", pairs)


def loading_cost(pairs: int) -> None:
    """Loading the calibration file (parse, validate, build the correction, as the node does) with and
    without its U map: once per (re)load, not per request."""
    import logging

    from gls_calibration.calibration.record import correction_from_record
    from gls_calibration.calibration.record_file import head_geometry, load_record
    from gls_calibration.calibration.store import CalibrationStore

    def load(path):
        record = load_record(path)
        return correction_from_record(record, head_geometry(record))

    record, grid, _, _ = cost_calibration()
    logging.getLogger("gls_calibration").setLevel(logging.ERROR)     # the no-map warning, once per load
    with tempfile.TemporaryDirectory() as without_u, tempfile.TemporaryDirectory() as with_u:
        paths = CalibrationStore(without_u).save(record), CalibrationStore(with_u).save({**record, "uncertainty": grid})
        figures = paired_ratios(lambda: load(paths[0]), lambda: load(paths[1]), pairs,
                                (time.process_time, time.process_time))
    print_pairs("loading the calibration file", figures, 1e-3, "ms", pairs, "<= 50 ms with the map (bench_services)")


def process_cpu_clock(pid: int):
    """A function giving the CPU time (s) of process ``pid`` so far, all its threads (Linux)."""
    clock_id = ((~pid) << 3) | 2     # the kernel's CPU clock of a whole process (clock_getcpuclockid)
    return lambda: time.clock_gettime(clock_id)


# The correction node as it answered before issue 30: the same code, the uncertainty array left empty.
NODE_BEFORE_U = """
from gls_calibration.nodes import correction
from gls_calibration.ros import conversions

start = conversions.start_setpoints_response


def without_u_column(response):
    sequences = start(response)
    sequences.pop("uncertainty_k2_mm", None)
    return sequences


conversions.start_setpoints_response = without_u_column
correction.main()
"""


def serving_cost_ros(pairs: int = 41, block: int = 40) -> None:
    """The same through the correction node in processes of their own, each in a namespace of its own.

    Three nodes: ``with`` serves the calibration with its U map; ``without`` the same file without
    the ``uncertainty`` key (U answered as NaN: the lookup is what differs); ``before`` that file with
    the answer's uncertainty array left empty, as before issue 30 (the lookup and the array differ).
    Both services (``correct_setpoints``, ``correct_setpoints_batch``), 1 and 100 000 targets. Besides,
    what the one more float64 array costs the transport alone (an echo with and without it).
    """
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_services import ECHO_NODE, correction_process, node_process, service_clients, stop_processes, \
        timed_calls
    from correction_peer import call
    from gls_calibration.calibration.store import CalibrationStore
    from gls_calibration.ros.conversions import float64_sequence
    from gls_calibration_msgs.srv import CorrectSetpoints

    os.environ.setdefault("ROS_DOMAIN_ID", "57")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    record, grid, _, _ = cost_calibration()
    rng = np.random.default_rng(1)
    x, y, z = rng.uniform(-95.0, 95.0, 100_000), rng.uniform(-95.0, 95.0, 100_000), rng.uniform(-5, 5, 100_000)
    requests = {"1 target": (CorrectSetpoints.Request(x=[10.0], y=[-20.0], z=[1.0]), block),
                "100 000 targets": (CorrectSetpoints.Request(x=float64_sequence(x), y=float64_sequence(y),
                                                             z=float64_sequence(z)), 1)}
    with tempfile.TemporaryDirectory() as without_u, tempfile.TemporaryDirectory() as with_u:
        CalibrationStore(without_u).save(record)
        CalibrationStore(with_u).save({**record, "uncertainty": grid})
        environment = dict(os.environ)
        children = {"before": node_process(NODE_BEFORE_U, environment, "-p", f"calibration_dir:={without_u}",
                                           "-r", "__ns:=/cost_before"),
                    "without": correction_process(without_u, environment, "/cost_without"),
                    "with": correction_process(with_u, environment, "/cost_with"),
                    "echo": node_process(ECHO_NODE, environment)}
        try:
            services = {f"{side} {service}": f"/cost_{side}/{service}" for side in ("before", "without", "with")
                        for service in ("correct_setpoints", "correct_setpoints_batch")}
            services |= {"echo without": "echo_setpoints_without_u", "echo with": "echo_setpoints"}
            with service_clients(services, "cost_client") as clients:
                for client in clients.values():
                    timed_calls(client, requests["1 target"][0], 20)     # warm-up: discovery, first allocations
                    timed_calls(client, requests["100 000 targets"][0], 2)
                for service in ("correct_setpoints", "correct_setpoints_batch"):
                    answers = {side: np.asarray(call(clients[f"{side} {service}"], requests["100 000 targets"][0])
                                                .uncertainty_k2_mm) for side in ("before", "without", "with")}
                    print(f"{service}, 100 000 targets, U answered: before {answers['before'].size} values; without "
                          f"the map {np.isnan(answers['without']).mean():.0%} NaN; with it "
                          f"{np.isfinite(answers['with']).mean():.1%} finite (NaN outside the calibrated field)")
                clocks = {name: process_cpu_clock(child.pid) for name, child in children.items()}
                cases = [(f"{service}, with / {base}", f"{base} {service}", f"with {service}")
                         for service in ("correct_setpoints", "correct_setpoints_batch")
                         for base in ("without", "before")]
                cases.append(("transport only (echo with / without the U array)", "echo without", "echo with"))
                for what, plain, certified in cases:
                    cpu = tuple(clocks[name.split()[0]] for name in (plain, certified))
                    for label, (request, count) in requests.items():
                        figures = paired_ratios(lambda: timed_calls(clients[plain], request, count),
                                                lambda: timed_calls(clients[certified], request, count), pairs, cpu)
                        blocks = f" (blocks of {count} calls)" if count > 1 else ""
                        print_pairs(f"out of process, {what}, {label}{blocks}", figures, 1e-3 * count,
                                    "ms per call", pairs)
        finally:
            stop_processes(list(children.values()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["careful", "paper_like"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3, 4, 5])
    parser.add_argument("--grid", type=int, default=19)
    parser.add_argument("--no-check", action="store_true", help="no reference check: the chain term is assumed")
    parser.add_argument("--physics-first", action="store_true",
                        help="train the named physical effects first, the RBF/TPS on what they leave")
    parser.add_argument("--cost", action="store_true", help="only the serving cost of U, in process (no calibration)")
    parser.add_argument("--cost-ros", action="store_true",
                        help="only the serving cost of U through the correction node in its own process")
    parser.add_argument("--pairs", type=int, default=41, help="with/without pairs per cost figure")
    args = parser.parse_args()
    if args.cost or args.cost_ros:
        print(f"host load (1, 5, 15 min): {' '.join(f'{load:.2f}' for load in os.getloadavg())}", flush=True)
        if args.cost:
            serving_cost(args.pairs)
        if args.cost_ros:
            serving_cost_ros(args.pairs)
        return
    print(f"grid {args.grid}x{args.grid}, plan {calibration_plan().label}, validation {args.grid - 1}x{args.grid - 1} "
          f"half a pitch off; reference check {'none' if args.no_check else FIELD_PLATE.label}; "
          f"{'physics first' if args.physics_first else 'RBF/TPS alone'}; mm; host load (1, 5, 15 min) "
          f"{' '.join(f'{load:.2f}' for load in os.getloadavg())}", flush=True)
    print("per seed: the budget as trained, then with the validation floor (``with_validation_floor``: U raised to "
          "the validation's RMS in quadrature with the check where the budget is below it; column 'validation' "
          "its per-axis term, 0 where not raised)")
    print(f"{'preset':11s} {'seed':>4s} {'coverage':>8s} {'median U':>8s} {'TRUE rms':>8s} {'U/TRUE':>6s} "
          + " ".join(f"{name:>12s}" for name in CONTRIBUTIONS) + f" {'budget s':>8s} | {'MEASURED':>8s} "
          f"{'floored':>7s} {'median U':>8s} {'U/TRUE':>6s} {VALIDATION_FLOOR:>10s} method")
    for preset in args.presets:
        pooled = {"u": [], "u_floored": [], "true": []}
        ratios, floored_ratios = [], []
        for seed in args.seeds:
            with tempfile.TemporaryDirectory() as folder:
                row = certify_once(preset, seed, args.grid, Path(folder), not args.no_check, args.physics_first)
            for key in pooled:
                pooled[key].append(row[key])
            medians = [float(np.median(row[key])) for key in ("u", "u_floored")]
            ratios.append(medians[0] / row["true_rms"])
            floored_ratios.append(medians[1] / row["true_rms"])
            parts = " ".join(f"{row['budget'].contribution(name).rms_mm:12.4f}" for name in CONTRIBUTIONS)
            names = [item.name for item in row["floored"].contributions]
            added = row["floored"].contribution(VALIDATION_FLOOR).rms_mm if VALIDATION_FLOOR in names else 0.0
            print(f"{preset:11s} {seed:4d} {np.mean(row['true'] <= row['u']):8.3f} {medians[0]:8.4f} "
                  f"{row['true_rms']:8.4f} {ratios[-1]:6.2f} {parts} {row['budget_s']:8.2f} | {row['post_rms']:8.4f} "
                  f"{np.mean(row['true'] <= row['u_floored']):7.3f} {medians[1]:8.4f} {floored_ratios[-1]:6.2f} "
                  f"{added:10.4f} {row['method']}", flush=True)
        true = np.concatenate(pooled["true"])
        true_rms = float(np.sqrt(np.mean(true ** 2)))
        for label, key, per_seed in (("as trained", "u", ratios), ("validation floor", "u_floored", floored_ratios)):
            u = np.concatenate(pooled[key])
            print(f"{preset:11s} {label}: pooled coverage {np.mean(true <= u):.3f} over {u.size} fiducials (target "
                  f"0.92-0.985); median U {np.median(u):.4f} mm, TRUE RMS {true_rms:.4f} mm, median U / TRUE RMS "
                  f"{np.median(u) / true_rms:.2f} (target <= 3); per-seed U/TRUE median "
                  f"{statistics.median(per_seed):.2f}",
                  flush=True)


if __name__ == "__main__":
    main()
