"""RBF-only against physics + RBF on the paper-like simulated cell, for 7x7, 11x11 and 19x19 fiducials.

Target (issue): physics + RBF with 7x7 fiducials at least as accurate as RBF-only with 19x19.

Per grid over 190 mm: a clean plate is scanned (plane), the double rings are marked through the
nominal model on the measured plate plane (z from the plain sweep, as the calibration
procedure commands), the plate is scanned at 0.1 mm and the fiducials measured, paired and turned
into deviations ``Q - P`` -- once, and the SAME measurements train both (a) RBF-only
(``rbf.select_model``) and (b) physics + RBF (``physical_model.train_physics_then_rbf``). RBF-only
is trained twice: at the targets Q (the published way, ``K = Q + delta(Q)`` to first order) and at
the landed points P (what the calibration procedure does: commanding Q landed at P, so Q - P is
exactly the correction for a target at P). Each
correction then marks a dense validation grid (18x18 over 180 mm, half a pitch off the 19x19 one)
on a fresh plate, and the error is taken from the TRUTH: landed ring polylines -> centres -> best
rigid 2-D alignment to the targets -> ``deviation_metrics`` over the field and the central 150x150 mm.
The first row of each grid is the cell without correction; the last uses the same physics to first
order only (``inverse=False``: ``K = Q + measured deviation``, like the RBF), which shows how much
of the gain is the exact inverse of the physical model. Seeds are fixed (config/sim.yaml).

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_physics_rbf.py   (about a minute)
"""
from __future__ import annotations

import time

import numpy as np

from gls_calibration import rbf
from gls_calibration.calibration_record import calibrated_region
from gls_calibration.correction import Correction
from gls_calibration.fiducials import measure_fiducials
from gls_calibration.kinematics import inverse
from gls_calibration.physical_model import train_physics_then_rbf
from gls_calibration.plate_pose import estimate_plate_pose
from gls_calibration.procedure import ProcedureSettings, true_fiducial_centres
from gls_calibration.registration import align_rigid_2d, deviation_metrics, pair_with_targets
from gls_calibration.simulation.world import SimulatedCell, load_sim_config
from gls_calibration.targets import grid_targets, rings_polylines

GRIDS = (7, 11, 19)
SIZE_MM = 190.0
RADII_MM = (2.5, 2.7)
VALIDATION = grid_targets(18, 180.0)


class PlatePlane:
    """Height z(x, y) (gls frame) of the plate plane measured on the plain sweep, CAD mounting."""

    def __init__(self, cell: SimulatedCell) -> None:
        xyz, _ = cell.sweep_cloud(step_mm=1.0)
        self.pose = estimate_plate_pose(xyz.reshape(-1, 3), head_direction=(0.0, 0.0, -1.0))
        self.centre = cell.scanner.to_gls(self.pose.centre)
        self.normal = cell.scanner.to_gls(self.pose.centre + self.pose.normal) - self.centre

    def z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        n, c = self.normal, self.centre
        return c[2] - (n[0] * (x - c[0]) + n[1] * (y - c[1])) / n[2]


def measure_deviations(cell: SimulatedCell, grid_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, PlatePlane]:
    """Mark ``grid_xy`` nominally on a clean plate, scan and measure: paired targets, landed points, true deviations, plane.

    As the calibration procedure does, every target is commanded on the measured plate plane.
    """
    cell.exchange_plate()
    plane = PlatePlane(cell)
    targets = np.column_stack([grid_xy, plane.z(grid_xy[:, 0], grid_xy[:, 1])])
    landed = []
    for ring in rings_polylines(grid_xy, RADII_MM):
        joints = inverse(cell.config.geometry, ring[:, 0], ring[:, 1], plane.z(ring[:, 0], ring[:, 1]))
        landed.append(cell.head.mark(joints.alpha_x, joints.alpha_y))
    xyz, intensity = cell.sweep_cloud()
    found = measure_fiducials(xyz, intensity, plane.pose, ring_radii_mm=RADII_MM, expected_count=len(grid_xy))
    centres_gls = cell.scanner.to_gls(found.centres)
    pairing = pair_with_targets(centres_gls, targets)
    measured = pairing.transform.apply(centres_gls[pairing.measured_index])
    paired = grid_xy[pairing.target_index]
    true_centres = true_fiducial_centres(landed, len(RADII_MM))[:, :2]
    true_deviations = grid_xy - align_rigid_2d(true_centres, grid_xy)[1]
    return paired, measured[:, :2], true_deviations[pairing.target_index], plane


def true_validation(cell: SimulatedCell, correction: Correction, plane: PlatePlane) -> dict:
    """Mark the validation rings through ``correction`` on a fresh plate; metrics of the true deviations."""
    cell.exchange_plate()
    landed = []
    for ring in rings_polylines(VALIDATION, RADII_MM):
        setpoints = correction.correct(ring[:, 0], ring[:, 1], plane.z(ring[:, 0], ring[:, 1]))
        landed.append(cell.head.mark(setpoints.alpha_x, setpoints.alpha_y))
    centres = true_fiducial_centres(landed, len(RADII_MM))[:, :2]
    return deviation_metrics(VALIDATION, VALIDATION - align_rigid_2d(centres, VALIDATION)[1], (None, 150.0))


def rms(vectors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(vectors ** 2, axis=1))))


def main() -> None:
    """Print the comparison table."""
    config = load_sim_config()
    cell = SimulatedCell(config)
    geometry = config.geometry
    header = (f"{'grid':6s} {'method':26s} {'named effects':58s} {'RMS 180':>8s} {'max 180':>8s} "
              f"{'RMS 150':>8s} {'max 150':>8s} {'train s':>8s}")
    print("True error on the 18x18 validation grid over 180 mm (mm, after rigid 2-D alignment); "
          "paper-like cell (config/sim.yaml)")
    print(header)
    print("-" * len(header))
    for per_side in GRIDS:
        grid_xy = grid_targets(per_side, SIZE_MM)
        began = time.perf_counter()
        targets, landed, true_deviations, plane = measure_deviations(cell, grid_xy)
        deviations = targets - landed
        measuring = time.perf_counter() - began
        noise = rms(deviations - true_deviations)
        region = calibrated_region(ProcedureSettings(grid_per_side=per_side, grid_size_mm=SIZE_MM,
                                                     ring_radii_mm=RADII_MM))
        rows = [("none (nominal model)", "", Correction(geometry), 0.0)]
        began = time.perf_counter()
        model, selection = rbf.select_model(targets, deviations)
        rows.append((f"RBF at Q ({selection.method})", "published way", Correction(geometry, [model], region),
                     time.perf_counter() - began))
        # as the calibration procedure trains: at the landed points P, the correction Q - P
        began = time.perf_counter()
        model, selection = rbf.select_model(landed, deviations)
        rows.append((f"RBF at P ({selection.method})", "this package, RBF only",
                     Correction(geometry, [model], region), time.perf_counter() - began))
        began = time.perf_counter()
        model, report = train_physics_then_rbf(targets, deviations, geometry)
        rows.append((report.method, ", ".join(report.named_effects) or "none",
                     Correction(geometry, [model], region), time.perf_counter() - began))
        # where the gain comes from: the same physics used to first order only (as the RBF is)
        began = time.perf_counter()
        first_order, _ = train_physics_then_rbf(targets, deviations, geometry, inverse=False)
        rows.append(("  same, physics 1st order", "(same)", Correction(geometry, [first_order], region),
                     time.perf_counter() - began))
        label = f"{per_side}x{per_side}"
        for method, named, correction, training in rows:
            metrics = true_validation(cell, correction, plane)
            full, central = metrics["full"], metrics["150x150"]
            print(f"{label:6s} {method:26s} {named:58s} {full['rms_abs_mm']:8.4f} {full['max_abs_mm']:8.4f} "
                  f"{central['rms_abs_mm']:8.4f} {central['max_abs_mm']:8.4f} {training:8.2f}", flush=True)
        print(f"{'':6s} ({len(targets)}/{len(grid_xy)} fiducials paired; measurement error vs truth "
              f"{noise:.4f} mm RMS; physics left {report.residual_rms_mm:.4f} mm RMS for the RBF, "
              f"residual CV RMS {report.cv_rms_mm:.4f} mm; measuring {measuring:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
