"""Grid-plate self-calibration measured against today's plan and the chain map (issue 32 item 3).

Per preset and seed one simulated cell (``DirectCell``, the plan of ``config/gls.yaml``) marks its
19 x 19 plate through ``procedure.run_plate`` (no calibration active) and the marks' recovered
positions are compared with where they truly landed (TRUE: RMS / max of the vector error after the
best rigid motion, as the calibration's TRUE figures), for:

- ``today``: the plan's 4 passes combined by the separation (``procedure.combined_centres_gls``);
- ``map``: the same on a twin cell (same seed: the same marks and robot) with the chain map of the
  plan's lines (``reference_plate.measure_chain_map``, 2 sweeps a line);
- ``self-cal``: views of the same marked plate at whole grid-pitch shifts solved by
  ``registration/self_calibration.py``, the symmetric linear part from one sweep per pass type of the
  certified plate (``reference_plate.FIELD_PLATE``). Two ways to shift (``LaserLineScanner.sweep_data``
  ``line_offset_mm``): ``moved`` -- the plate moved in its fixture (the robot runs its programmed
  lines; Ye et al.'s design), ``program`` -- the programmed lines shifted, the plate left in place
  (no fixture change; the robot's error is a function of where the arm is, so it stays with the
  base frame). Two designs: ``A`` 0+, 0- at shifts (0,0), (0,1) and 90+, 90- at (0,0), (1,0) (8
  sweeps); ``B`` A plus (0,3) and (3,0) (12 sweeps). Each solved with a free field per node (the
exact algorithm) and with a separable field (``-sep``: per pass type a function of the node column
plus one of the node row). ``A-mean``: design A's views simply averaged (no separation).

Cell time (``ProcedureSettings().cell_time``): today's marked plate has 4 sweeps; a design's extra is
its sweeps beyond those 4 (plus, for ``moved``, a fixture change per distinct plate position, not
modelled); the reference's linear part costs one certified-plate sweep per pass type, the map 8.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_self_calibration.py [--presets paper_like]
     [--seeds 1 2 3] [--robot on|off] [--sweep-noise on|off]
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

from bench_honest_robot import cell_config
from direct_runs import direct_cell, plan_settings
from gls_calibration.calibration import procedure
from gls_calibration.calibration.reference_check import plate_plane
from gls_calibration.fiducials import targets
from gls_calibration.fiducials.measure import measure_fiducials
from gls_calibration.registration.rigid import align_rigid_2d, pair_with_targets
from gls_calibration.registration.self_calibration import GridView, affine_basis, self_calibrate
from gls_calibration.registration.sweep_plan import parse_plan, SweepPass
from gls_calibration.simulation.plate import Plate
from gls_calibration.simulation.reference_plate import (FIELD_PLATE, RING_RADII_MM, calibration_plan,
                                                        measure_chain_map, reference_pattern)

#: Per-sweep noise of a centre, mm, (along travel, across): the preset's random along-travel wander
#: (``robot_along_wander_mm`` 0.01) with the ring fit, and its path wander (``path_wander_mm`` 0.08).
SIGMA_ALONG_MM, SIGMA_ACROSS_MM = 0.012, 0.08
#: A mark is used only if its node lies this far inside the sweep's covered rectangle: ring radius
#: 2.7 mm plus the marks' landing deviation (up to ~2 mm on ``paper_like``).
EDGE_MARGIN_MM = 4.8
#: A centre pairs with the nearest target within this distance (half the pitch of 10.6 mm, less margin).
PAIR_GATE_MM = 4.0
DESIGNS = {"A": {"0+": ((0, 0), (0, 1)), "0-": ((0, 0), (0, 1)), "90+": ((0, 0), (1, 0)), "90-": ((0, 0), (1, 0))},
           "B": {"0+": ((0, 0), (0, 1), (0, 3)), "0-": ((0, 0), (0, 1), (0, 3)),
                 "90+": ((0, 0), (1, 0), (3, 0)), "90-": ((0, 0), (1, 0), (3, 0))}}
PASSES = {item.label: item for item in parse_plan("0+,0-,90+,90-")}


def true_error(recovered_xy: np.ndarray, true_xy: np.ndarray) -> tuple[float, float]:
    """RMS and max of the vector error after the best rigid motion of ``recovered_xy`` onto ``true_xy``, mm."""
    moved = align_rigid_2d(recovered_xy, true_xy)[1]
    length = np.hypot(*(moved - true_xy).T)
    return float(np.sqrt(np.mean(length ** 2))), float(length.max())


def grid_index(xy: np.ndarray, grid_xy: np.ndarray) -> np.ndarray:
    """Index into ``grid_xy`` of each point of ``xy`` (the target it was paired with)."""
    return np.argmin(np.linalg.norm(xy[:, None, :] - grid_xy[None, :, :], axis=2), axis=1)


def plate_run(cell, settings, grid_xy):
    """Mark and measure one plate as the calibration does; return the run and the true centres (N, 2)."""
    run = asyncio.run(procedure.run_plate(cell, settings, grid_xy, lambda *_: None, (0.0, 1.0), True))
    truth = procedure.true_fiducial_centres(cell.marks, len(settings.ring_radii_mm))[:, :2]
    return run, truth


def covered(item: SweepPass, offset_b: np.ndarray, node_b: np.ndarray, length_mm: float, line_mm: float):
    """Which nodes (B x-y) lie inside the sweep's covered rectangle by ``EDGE_MARGIN_MM``."""
    centre = np.array([0.0, 0.5 * length_mm]) + offset_b
    half = np.array([0.5 * line_mm, 0.5 * length_mm])
    if item.orientation_deg == 90.0:
        half = half[::-1]
    return np.all(np.abs(node_b - centre) <= half - EDGE_MARGIN_MM, axis=1)


def view_centres(sim, settings, plate, item, shift, pitch, grid_xy, moved, seed, pose):
    """One sweep of ``plate`` with the line moved by ``shift`` pitches; centres (N, 2, gls) and seen."""
    mounting = settings.scanner_to_gls
    offset_b = (mounting.rotation.T @ np.array([shift[0] * pitch, shift[1] * pitch, 0.0]))[:2]
    data = sim.scanner.sweep_data(plate, sim.config.sweep_length_mm, step_mm=settings.marked_sweep_step_mm,
                                  seed=seed, direction=item.direction, orientation_deg=item.orientation_deg,
                                  line_offset_mm=None if not any(shift) else offset_b, plate_moved=moved and any(shift))
    xyz = data.placed_by_pose()
    pose = plate_plane(xyz) if pose is None else pose
    found = measure_fiducials(xyz, data.intensity, pose, ring_radii_mm=settings.ring_radii_mm,
                              expected_count=len(grid_xy))
    # paired with the nearest target: the shift is known, and a vote over the translation can take a
    # view that misses a row for one shifted by a pitch
    centres_gls = mounting.apply(found.centres)[:, :2]
    index = grid_index(centres_gls, grid_xy)
    near = np.linalg.norm(centres_gls - grid_xy[index], axis=1) < PAIR_GATE_MM
    centres = np.zeros((len(grid_xy), 2))
    seen = np.zeros(len(grid_xy), bool)
    centres[index[near]] = centres_gls[near]
    seen[index[near]] = True
    node_b = ((np.column_stack([grid_xy, np.zeros(len(grid_xy))]) - mounting.translation) @ mounting.rotation)[:, :2]
    seen &= covered(item, offset_b, node_b, sim.config.sweep_length_mm, sim.scanner.settings.line_length_mm)
    return centres, seen, pose


def reference_linear(config, settings, design, seed):
    """The chain's symmetric linear error per pass type on the certified plate, weighted as the design's views."""
    chain = dataclasses.replace(config.measurement, mark_width_variation=0.0, mark_darkness_variation=0.0,
                                mark_wander_mm=0.0, mark_blob_mm=0.0, spot_blur_mm=0.0, thermal_scale_ppm=0.0,
                                plate_warp_mm=0.0)
    plate = Plate(config.plate_settings, seed=[7907, seed], chain=chain)
    known_uv = reference_pattern(FIELD_PLATE)
    for ring in targets.rings_polylines(known_uv, RING_RADII_MM):
        plate.add_mark_plate(ring)
    known_gls = plate.from_plate(known_uv)
    scanner = config.make_scanner()
    mounting = settings.scanner_to_gls
    nodes = np.rint((known_uv - known_uv.min(axis=0)) / FIELD_PLATE.pitch_mm).astype(int)
    basis = affine_basis(nodes, FIELD_PLATE.pitch_mm)
    total, weight, pose = np.zeros((2, 2)), 0, None
    for number, (label, shifts) in enumerate(design.items()):
        item = PASSES[label]
        data = scanner.sweep_data(plate, config.sweep_length_mm, step_mm=settings.marked_sweep_step_mm,
                                  seed=(7907 + seed) * 1009 + number, direction=item.direction,
                                  orientation_deg=item.orientation_deg)
        xyz = data.placed_by_pose()
        pose = plate_plane(xyz) if pose is None else pose
        found = measure_fiducials(xyz, data.intensity, pose, ring_radii_mm=RING_RADII_MM,
                                  expected_count=len(known_gls))
        pairing = pair_with_targets(mounting.apply(found.centres), known_gls)
        measured = mounting.apply(found.centres[pairing.measured_index])[:, :2]
        difference = np.full((len(known_gls), 2), np.nan)
        difference[pairing.target_index] = measured - known_gls[pairing.target_index, :2]
        rows = np.repeat(np.isfinite(difference[:, 0]), 2)
        c = np.linalg.lstsq(basis[rows], difference.ravel()[rows], rcond=None)[0]
        total += len(shifts) * np.array([[c[3], c[5]], [c[5], c[4]]])
        weight += len(shifts)
    return total / weight


def self_calibration_rows(cell, settings, grid_xy, truth, seed, reference):
    """TRUE RMS / max of the self-calibrated marks for every design and way of shifting."""
    pitch = settings.grid_size_mm / (settings.grid_per_side - 1)
    nodes = np.rint((grid_xy - grid_xy.min(axis=0)) / pitch).astype(int)
    rows = {}
    for moved in (True, False):
        pose = None
        views: dict = {}
        for number, (label, shifts) in enumerate(DESIGNS["B"].items()):
            for index, shift in enumerate(shifts):
                centres, seen, pose = view_centres(cell.sim, settings, cell.sim.plate, PASSES[label], shift, pitch,
                                                   grid_xy, moved, seed * 100003 + 50000 + 10 * number + index
                                                   + (0 if moved else 5000), pose)
                sigma = ((SIGMA_ACROSS_MM, SIGMA_ALONG_MM) if PASSES[label].orientation_deg == 0.0
                         else (SIGMA_ALONG_MM, SIGMA_ACROSS_MM))
                views[(label, shift)] = GridView(centres, seen, shift, label, sigma)
        for name, design in DESIGNS.items():
            chosen = [views[(label, shift)] for label, shifts in design.items() for shift in shifts]
            for model, suffix in (("nodes", ""), ("separable", "-sep")):
                result = self_calibrate(nodes, chosen, pitch, linear_correction=reference[name], field_model=model)
                rows[f"{name}-{'moved' if moved else 'program'}{suffix}"] = true_error(result.marks_mm, truth)
            if name == "A" and moved:
                mean = np.array([view.centres_mm for view in chosen])
                seen = np.array([view.seen for view in chosen])
                average = (mean * seen[..., None]).sum(axis=0) / seen.sum(axis=0)[:, None]
                rows["A-mean"] = true_error(average, truth)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["paper_like"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3])
    parser.add_argument("--robot", choices=("on", "off"), default="on")
    parser.add_argument("--sweep-noise", choices=("on", "off"), default="on",
                        help="off: no per-sweep random path error (path_wander_mm, robot_along_wander_mm): a diagnosis")
    args = parser.parse_args()
    timing = procedure.ProcedureSettings().cell_time
    sweep_s = timing.plate_s(1, 0.0)
    print(f"robot repeating errors {args.robot}; per-sweep path noise {args.sweep_noise}; 2026-11-28; "
          f"one sweep and move {sweep_s:.1f} s; TRUE RMS / max of "
          "the marks' recovered positions after the best rigid motion, mm")
    for name, design in DESIGNS.items():
        views = sum(len(shifts) for shifts in design.values())
        print(f"design {name}: {views} sweeps, {views - 4} beyond today's 4: +{(views - 4) * sweep_s:.0f} s; "
              f"reference linear part {len(design)} certified sweeps: {len(design) * sweep_s:.0f} s; "
              f"plate positions {len({s for shifts in design.values() for s in shifts})}")
    print(f"chain map: 8 certified sweeps, {8 * sweep_s:.0f} s")
    columns = ("today", "map", "A-mean", "A-moved", "A-moved-sep", "B-moved", "B-moved-sep", "B-program",
               "B-program-sep")
    print(f"{'preset':11s} {'seed':>4s} " + " ".join(f"{c:>15s}" for c in columns) + "  wall s")
    for preset in args.presets:
        table = []
        for seed in args.seeds:
            began = time.perf_counter()
            config = cell_config(preset, seed, args.robot == "on")
            if args.sweep_noise == "off":
                config = dataclasses.replace(config, measurement=dataclasses.replace(
                    config.measurement, path_wander_mm=0.0, robot_along_wander_mm=0.0))
            with tempfile.TemporaryDirectory() as folder:
                cell = direct_cell(config, Path(folder) / "a")
                settings = plan_settings(cell)
                grid_xy = targets.grid_targets(settings.grid_per_side, settings.grid_size_mm)
                run, truth = plate_run(cell, settings, grid_xy)
                row = {"today": true_error(run.measured_gls[:, :2], truth[grid_index(run.paired_targets_xy, grid_xy)])}
                chain_map = measure_chain_map(config, calibration_plan(), seed=seed, repeats=2)
                twin = direct_cell(config, Path(folder) / "b")
                run_map, truth_map = plate_run(twin, plan_settings(twin, chain_map=chain_map), grid_xy)
                row["map"] = true_error(run_map.measured_gls[:, :2],
                                        truth_map[grid_index(run_map.paired_targets_xy, grid_xy)])
                reference = {name: reference_linear(config, settings, design, seed) for name, design in DESIGNS.items()}
                row.update(self_calibration_rows(cell, settings, grid_xy, truth, seed, reference))
            table.append(row)
            print(f"{preset:11s} {seed:4d} " + " ".join(f"{row[c][0]:7.4f}/{row[c][1]:7.4f}" for c in columns)
                  + f"  {time.perf_counter() - began:6.0f}", flush=True)
        print(f"{preset:11s} {'median':>4s} " + " ".join(
            f"{statistics.median(r[c][0] for r in table):7.4f}/{statistics.median(r[c][1] for r in table):7.4f}"
            for c in columns))
        print(f"{preset:11s} {'ratio':>4s} " + " ".join(
            f"{statistics.median(r[c][0] / r['today'][0] for r in table):15.2f}" for c in columns)
            + "  (median over seeds of RMS / today's RMS)")


if __name__ == "__main__":
    main()
