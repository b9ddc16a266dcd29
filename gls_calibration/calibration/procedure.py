"""The calibrate flow: plate run(s), deviations, training, validation; pure and awaitable.

The procedure does not know ROS. It awaits a ``Cell``: an object whose coroutine methods reach the
scanner, the galvo and the processing nodes (the calibration manager implements them with service
calls; ``simulation.direct_cell.DirectCell`` calls the simulated cell and the core directly).
Everything it decides -- where to mark, how to pair, what to train, when to stop -- lives here, so
the node stays thin.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
import inspect
import math
from pathlib import Path
import time
from typing import Any, Awaitable, Callable, Coroutine, Optional, Protocol, TypeVar

import numpy as np

from gls_calibration.calibration.outcome import CalibrationOutcome, Candidate, PlateRun, deviation_metrics
from gls_calibration.common.time_budget import StageClock
from gls_calibration.common.validation import as_positive_number
from gls_calibration.correction.setpoints import CorrectedSetpoints
from gls_calibration.fiducials import targets as grid
from gls_calibration.fiducials.measure import FiducialMeasurement
from gls_calibration.models.training import TrainedModel
from gls_calibration.registration.chain_map import ChainMap, chain_map_identity, correct_measurements
from gls_calibration.registration.rigid import RigidTransform, align_rigid_2d, pair_with_targets
from gls_calibration.registration.separation import SeparationSettings
from gls_calibration.registration.sweep_plan import (CellTimeModel, CombinedSweeps, SweepPass, combine_sweeps,
                                                     in_view, plan_label)
from gls_calibration.scan.plate_marks import existing_marks
from gls_calibration.scan.plate_pose import PlatePose, mean_plate_pose, pose_at_height


T = TypeVar("T")


class CalibrationError(RuntimeError):
    """The calibration cannot go on; the message says why. Nothing has been replaced.

    Parameters
    ----------
    message : str
        Why the calibration stopped.
    """


class Cell(Protocol):
    """What the procedure needs from the cell: the contract a cell integrator implements.

    Every method is a coroutine; a failure raises ``CalibrationError`` with a message saying what
    went wrong (the procedure lets it through, and the caller keeps the active calibration).
    Lengths in mm, angles in rad. Frames: ``scanner`` is the line scanner's frame in which clouds
    and plate poses are expressed; ``gls`` is the galvo head's frame (z towards the head) in which
    targets and corrections are expressed. A cloud is whatever ``acquire_sweep`` returns; the
    procedure only hands it back to ``estimate_plate_pose`` and ``measure_fiducials``, so a cell can
    keep it in its own form (the manager keeps the PointCloud2 message and forwards it untouched).
    """

    async def acquire_sweep(self, step_mm: float, direction: int = 1, orientation_deg: float = 0.0) -> Any:
        """Sweep the scanner over the plate and return the cloud in the scanner (base) frame.

        Profiles are ``step_mm`` apart, along the sensor's +y (``direction`` 1) or -y (-1), the
        sensor turned by ``orientation_deg`` (0, 45 or 90) about its viewing axis. The cloud is in the
        scanner (base) frame whatever the direction and orientation, placed by the robot's reported
        pose where the cell has one (see ``scan/sweep.py``).
        """

    async def acquire_standstill(self, profiles: int) -> Any:
        """Take ``profiles`` profiles with the robot standing still in the marking pose.

        ``profiles`` profiles taken with the robot standing still in the pose the marks are made
        from (no travel), as a cloud in the scanner (base) frame like ``acquire_sweep``'s: the plate
        height at marking (``settings.standstill_height``). Needs its own random draws on a simulated
        cell, never those of the sweeps.
        """

    async def estimate_plate_pose(self, cloud: Any) -> PlatePose:
        """Fit the plate plane to ``cloud`` (scanner frame, normal towards the head)."""

    async def measure_fiducials(self, cloud: Any, pose: PlatePose, expected_count: int,
                                ring_radii_mm: tuple[float, ...]) -> FiducialMeasurement:
        """Find the centres (scanner frame, mm) of the ring fiducials in ``cloud``.

        Centres (scanner frame, mm) of the ring fiducials found in ``cloud`` on the plate ``pose``;
        ``expected_count`` fiducials were marked (a hint, not a promise) with rings of ``ring_radii_mm``
        (the procedure's settings: the radii it marked with, the one owner).
        """

    async def correct(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> CorrectedSetpoints:
        """Return setpoints that land on the targets through the cell's loaded calibration.

        Targets are (x, y, z) (gls frame, mm); the nominal model serves when no calibration is
        loaded. ``within_limits`` flags the reachable ones.
        """

    async def mark(self, alpha_x: np.ndarray, alpha_y: np.ndarray, focus_shift: np.ndarray,
                   polyline_starts: np.ndarray) -> float:
        """Mark polylines given as mirror angles and focus shift; return the marking time (s).

        Mark polylines: mirror angles (rad) and focus shift (mm) per point, ``polyline_starts`` the
        index of each polyline's first point (starts with 0). Returns the marking time in seconds.
        """

    async def train(self, landed_xy: np.ndarray, corrections: np.ndarray) -> TrainedModel:
        """Train a model of the correction to add at a target from landed points and corrections.

        Landed points P (N, 2) and corrections K(Q) - K(P) (N, 2) are in the gls frame, mm; see
        ``training.train_correction``.
        """

    async def use_candidate(self, candidate: Candidate) -> None:
        """Make the cell correct through ``candidate`` (saved, not active) from now on.

        Its correction as it is, not its file read again.
        """

    async def reload_active(self) -> None:
        """Make the cell correct through the store's active calibration again.

        That is the nominal model when there is none. A failed run calls this to drop a candidate it
        loaded.
        """

    async def exchange_plate(self) -> None:
        """Put a clean plate in the cell (second iteration, validation).

        CalibrationError when the cell cannot.
        """

    async def true_marks(self) -> Optional[list[np.ndarray]]:
        """Return the polylines really marked on the current plate (simulation only).

        Simulation only: the polylines really marked on the current plate ((M, 3) each, gls frame,
        mm), in marking order; None on a real cell.
        """

    def start(self, step: Coroutine[Any, Any, T]) -> Awaitable[T]:
        """Begin ``step`` now, beside what the procedure awaits next; return what to await.

        Begin ``step`` (a coroutine of this cell) now, beside what the procedure awaits next, and
        return what to await for its result; the procedure measures a sweep while it scans the next.
        A cell that cannot run steps side by side returns ``step`` itself (it then runs when awaited).
        Not a coroutine: it only schedules.
        """

    def points_and_intensities(self, cloud: Any) -> tuple[np.ndarray, np.ndarray]:
        """Return the points (..., 3) mm and intensity (...) of a cloud from ``acquire_sweep``.

        Points are in any frame a rigid motion from the plate's; NaN marks no return. They serve the
        check that the plain plate carries no old marks. Not a coroutine: the cloud is here.
        """


ITERATIONS_LIMIT = 10    # most iterations max_iterations (and default_iterations) may allow: the manager's range
# Room a sweep needs at each end beyond the outermost ring: the first plate is marked through the
# uncalibrated model, whose field error reaches ~2 mm at the grid's corners (the seed paper; 2.1 mm
# in the simulated head), the grid's offset from the sweep's centre (~1 mm), and the ring fit's rays
# reach ~0.7 mm beyond the outer ring. A ring cut by the end of a sweep is found or lost by chance
# (2 mm were too little: 8 of 9 found on 3x3 grids, seeds 1, 7 and 8 of paper_like, 2026-12-02).
SWEEP_END_MARGIN_MM = 4.0


@dataclass(frozen=True)
class ProcedureSettings:
    """Settings of one calibration (mm unless named otherwise).

    Parameters
    ----------
    grid_per_side : int, default 19
        Fiducials per side of the training grid.
    grid_size_mm : float, default 190.0
        Span of the grid, mm.
    ring_radii_mm : tuple of float, default RING_RADII_MM
        Ring radii of a fiducial, increasing, mm (marked and sent with every measurement).
    plain_sweep_step_mm : float, default 1.0
        Profile step of the plain-plate sweeps, mm.
    plain_sweeps : int, default 2
        Plain-plate sweeps, their poses averaged: with ``standstill_height`` they give the tilt only;
        without it one sweep's height error sets the field's scale, and more sweeps average it.
    standstill_height : bool, default True
        Take the plate height from profiles taken standing at the marking pose ...
    standstill_profiles : int, default 20
        ... this many; positive.
    marked_sweep_step_mm : float, default 0.1
        Profile step of the marked-plate sweeps, mm.
    scanner_to_gls : RigidTransform, optional
        Scanner base frame -> gls frame (identity by default).
    tolerance_rms_mm : float, default 0.05
        A first plate within it is not trained on (unless forced), mm.
    min_found_fraction : float, default 0.9
        Least share of the fiducials to find.
    default_iterations, max_iterations : int, default 1, 3
        Iterations when none is asked for, and the most allowed (each marks and measures a fresh plate).
    validation_offset_half_pitch : bool, default True
        The validation grid sits half a pitch off the training grid.
    mark_check_sigmas : float, default 6.0
        Plain-plate points this far outside the texture (robust deviations) look like marks ...
    max_outlying_points : int, default 10
        ... and more of them than this mean the plate is not clean;
    mark_cluster_sigmas : float, default 4.0
        or points this far outside it ...
    max_cluster_points : int, default 8
        ... more than this many within one fiducial's extent (see ``plate_marks``).
    measurement_uncertainty_mm : float, default 0.005
        Least standard uncertainty of one fiducial centre, mm.
    max_cv_factor : float, default 20.0
        A CV RMS above this many uncertainties ...
    max_cv_fraction : float, default 0.5
        ... and above this fraction of the deviations' RMS: the model explains little.
    sweep_plan : tuple of SweepPass, default one "0+" pass
        The passes over the marked plate; several (reversed, sensor turned) let the separation remove
        what is fixed to the scanner frame or to one sweep's motion.
    profiles_placed_by_pose : bool, default True
        The cell places profiles by the robot's reported pose (else by time).
    cell_time : CellTimeModel, optional
        Sweep length and speed, robot moves.
    separation : SeparationSettings, optional
        None: the default for the placement (``sweep_plan.combine_sweeps``).
    chain_map : ChainMap, optional
        The lines' repeating robot error, removed from every sweep (None: off).

    Raises
    ------
    ValueError
        On the first bad field: ring radii not positive and increasing, a threshold not positive, a
        bad count, a sweep too short to cover the grid, iterations out of order.
    """

    grid_per_side: int = 19
    grid_size_mm: float = 190.0
    ring_radii_mm: tuple[float, float] = grid.RING_RADII_MM
    plain_sweep_step_mm: float = 1.0
    plain_sweeps: int = 2               # averaged: one sweep's path error tilts the plane (the height: stand-still)
    standstill_height: bool = True      # the plate height from profiles taken standing at the marking pose
    standstill_profiles: int = 20       # ... this many (the height of one is already ~2000 points)
    marked_sweep_step_mm: float = 0.1
    scanner_to_gls: RigidTransform = field(default_factory=lambda: RigidTransform(np.eye(3), np.zeros(3)))
    tolerance_rms_mm: float = 0.05
    min_found_fraction: float = 0.9
    default_iterations: int = 1
    max_iterations: int = 3             # each iteration marks and measures a fresh plate
    validation_offset_half_pitch: bool = True
    mark_check_sigmas: float = 6.0      # plain-plate points this far outside the texture look like marks...
    max_outlying_points: int = 10       # ...and more of them than this mean the plate is not clean;
    mark_cluster_sigmas: float = 4.0    # or points this far outside it...
    max_cluster_points: int = 8         # ...more than this many within one fiducial's extent (see plate_marks)
    # of one fiducial centre, at least (3-4 um RMS measured against the truth)
    measurement_uncertainty_mm: float = 0.005
    max_cv_factor: float = 20.0         # a CV RMS above this many uncertainties...
    max_cv_fraction: float = 0.5        # ...and above this fraction of the deviations' RMS: the model explains little

    # the marked plate is swept once per pass; several passes (reversed, sensor turned) let the
    # separation remove what is fixed to the scanner frame or to one sweep's motion
    sweep_plan: tuple[SweepPass, ...] = (SweepPass(),)
    profiles_placed_by_pose: bool = True    # the cell places profiles by the robot's reported pose
    cell_time: CellTimeModel = CellTimeModel()
    separation: Optional[SeparationSettings] = None   # None: the default for the placement (sweep_plan.combine_sweeps)
    chain_map: Optional[ChainMap] = None   # the lines' repeating robot error, removed from every sweep (None: off)

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        radii = np.asarray(self.ring_radii_mm, dtype=float)
        if radii.ndim != 1 or radii.size == 0 or not np.all(np.isfinite(radii)) or np.any(radii <= 0.0) \
                or np.any(np.diff(radii) <= 0.0):
            raise ValueError(f"ring_radii_mm must be one or more positive finite radii in increasing order, "
                             f"got {list(self.ring_radii_mm)}")
        for name in ("mark_check_sigmas", "mark_cluster_sigmas", "measurement_uncertainty_mm", "max_cv_factor",
                     "max_cv_fraction"):
            as_positive_number(getattr(self, name), name)
        if isinstance(self.standstill_profiles, bool) or not isinstance(self.standstill_profiles, int) \
                or self.standstill_profiles < 1:
            raise ValueError(f"standstill_profiles must be a positive integer, got {self.standstill_profiles!r}")
        for name in ("max_outlying_points", "max_cluster_points"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must not be negative, got {getattr(self, name)}")
        # finite: the error separation measures every sweep from its middle, half this length
        as_positive_number(self.cell_time.sweep_length_mm, "cell_time.sweep_length_mm")
        covered_mm = self.grid_size_mm + 2.0 * (float(radii[-1]) + SWEEP_END_MARGIN_MM)
        if self.cell_time.sweep_length_mm < covered_mm:
            raise ValueError(f"sweep length {self.cell_time.sweep_length_mm:g} mm cannot cover the grid: its "
                             f"{self.grid_size_mm:g} mm, the outer ring ({float(radii[-1]):g} mm) and "
                             f"{SWEEP_END_MARGIN_MM:g} mm at each end need {covered_mm:g} mm")
        if not 1 <= self.default_iterations <= self.max_iterations:
            raise ValueError(f"default_iterations must be between 1 and max_iterations ({self.max_iterations}), "
                             f"got {self.default_iterations}")

    def iterations_problem(self, iterations: int) -> str:
        """Why a requested iteration count (0: the default) is refused; empty string when it is fine."""
        if iterations == 0 or 1 <= iterations <= self.max_iterations:
            return ""
        return (f"iterations must be 0 (the default, {self.default_iterations}) or 1 to {self.max_iterations}, "
                f"got {iterations}")


def plane_height(pose: PlatePose, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Return the height z of the plate plane above (x, y) in the frame of ``pose``."""
    nx, ny, nz = pose.normal
    if abs(nz) < 1e-6:
        raise CalibrationError("the plate plane is parallel to the beam axis; check the scanner mounting")
    cx, cy, cz = pose.centre
    return cz - (nx * (x - cx) + ny * (y - cy)) / nz


def pose_in_frame(pose: PlatePose, transform: RigidTransform) -> PlatePose:
    """Return the plate pose expressed in the frame ``transform`` maps into."""
    rotation = transform.rotation @ pose.rotation
    return PlatePose(normal=rotation[:, 2].copy(), centre=transform.apply(pose.centre[None, :])[0],
                     rotation=rotation, flatness_rms_mm=pose.flatness_rms_mm,
                     inlier_count=pose.inlier_count, inlier_fraction=pose.inlier_fraction)


def true_fiducial_centres(ring_marks: list[np.ndarray], rings_per_fiducial: int) -> np.ndarray:
    """Centres (N, 3) of marked fiducials from their landed closed ring polylines, in marking order.

    A ring is commanded as points evenly spread in angle; the head's distortion is smooth on the
    scale of a ring, so the mean of the landed points (the repeated closing point left out) is
    where the ring's centre really is.
    """
    if len(ring_marks) % rings_per_fiducial:
        raise ValueError(f"{len(ring_marks)} ring marks do not make whole fiducials of {rings_per_fiducial} rings")
    means = np.array([np.asarray(ring, dtype=float)[:-1].mean(axis=0) for ring in ring_marks])
    return means.reshape(-1, rings_per_fiducial, means.shape[1]).mean(axis=1)


Progress = Callable[[str, float, str], None]


def check_clean_plate(points: np.ndarray, intensity: np.ndarray, settings: ProcedureSettings) -> None:
    """Raise CalibrationError when the plain-plate sweep shows marks beyond the plate's texture.

    Marks are many points far outside the texture, or a fiducial-sized cluster of them; the sweep
    is points (..., 3) mm and intensity (...).
    """
    evidence = existing_marks(intensity, settings.mark_check_sigmas, points=points,
                              cluster_sigmas=settings.mark_cluster_sigmas,
                              cluster_radius_mm=2.0 * max(settings.ring_radii_mm) + 0.5)
    if evidence.marked(settings.max_outlying_points, settings.max_cluster_points):
        raise CalibrationError(
            f"the plate already carries marks: {evidence.outlying_points} of {evidence.finite_points} points of "
            f"the plain-plate sweep lie beyond {evidence.sigmas:g} sigma of its texture (at most "
            f"{settings.max_outlying_points} allowed), {evidence.largest_cluster} beyond "
            f"{evidence.cluster_sigmas:g} sigma within {evidence.cluster_radius_mm:g} mm of one another (at most "
            f"{settings.max_cluster_points} allowed); exchange the plate, or give a plate region that avoids "
            "the old marks (force marks over them anyway)")


def centre_uncertainty_mm(run: PlateRun, settings: ProcedureSettings) -> float:
    """Return the standard uncertainty (mm, per axis) of one measured centre of ``run``.

    Standard uncertainty (mm, per axis) of one measured centre of ``run``: the RMS of the
    per-centre figures the measurement stated, never below ``settings.measurement_uncertainty_mm``.

    The floor stands for what the fits cannot see (robot path, plate height, timing); a plate that
    measures worse (speckle, faint marks) raises the figure above it.
    """
    floor = settings.measurement_uncertainty_mm
    sigma = None if run.sigma_mm is None else np.asarray(run.sigma_mm, dtype=float)
    if sigma is None or sigma.size == 0 or not np.all(np.isfinite(sigma)):
        return floor
    return max(floor, float(np.sqrt(np.mean(sigma ** 2))))


def check_model_explains(model: "TrainedModel", deviation_rms_mm: float, uncertainty_mm: float,
                         settings: ProcedureSettings) -> None:
    """Raise CalibrationError when the model cannot explain the measurement.

    That is: its cross-validated error is far above the measurement's uncertainty
    (``uncertainty_mm``, :func:`centre_uncertainty_mm`) and a large part of the deviations it was
    trained on.

    Both, because a sparse grid (3x3) leaves a CV error of ~0.6 mm on a 1.5 mm field and still
    helps, while new marks measured among old ones (the issue's case) leave 0.25 mm of 0.34 mm.
    """
    limit = max(settings.max_cv_factor * uncertainty_mm, settings.max_cv_fraction * deviation_rms_mm)
    if not model.cv_rms_mm <= limit:
        raise CalibrationError(
            f"the model cannot explain the measurement: CV RMS {model.cv_rms_mm:.4f} mm is over "
            f"{settings.max_cv_factor:g} x the per-fiducial uncertainty ({uncertainty_mm:.4f} mm) "
            f"and over {settings.max_cv_fraction:g} x the deviations' RMS ({deviation_rms_mm:.4f} mm); old marks "
            "or ambiguous pairings? Nothing activated")


def acceptance_problem(before_rms_mm: float, after_rms_mm: float, uncertainty_mm: float,
                       against: str = "this run's first plate") -> str:
    """Why a validated candidate must not replace the calibration in use (empty string: accept it).

    ``before_rms_mm``: the calibration in use, measured on ``against``; ``after``: the validation
    plate, marked through the candidate; both measured the same way, with a per-centre uncertainty of
    ``uncertainty_mm`` (the larger of the two plates').
    """
    if after_rms_mm + uncertainty_mm < before_rms_mm:
        return ""
    return (f"candidate rejected: validation {after_rms_mm:.4f} mm RMS is not better than the calibration in use "
            f"({before_rms_mm:.4f} mm RMS on {against}) by more than the measurement uncertainty "
            f"{uncertainty_mm:.4f} mm")


def combined_centres_gls(measurements: list[FiducialMeasurement], settings: ProcedureSettings, targets: np.ndarray,
                         pose_scanner: PlatePose) -> tuple[np.ndarray, CombinedSweeps]:
    """Combine the marked plate's centres (K, 3, gls frame) from every sweep of the plan.

    The combination is ``sweep_plan.combine_sweeps`` with the placement the settings say; with a
    ``settings.chain_map`` each sweep's centres lose their line's repeating error first.

    Parameters
    ----------
    measurements : list of FiducialMeasurement
        One per pass of ``settings.sweep_plan``, in its order (scanner base frame, mm).
    settings : ProcedureSettings
        The plan, placement, separation, chain map and ``scanner_to_gls``.
    targets : numpy.ndarray, shape (N, 3)
        The targets, gls frame, mm.
    pose_scanner : PlatePose
        The plate plane in the scanner base frame; the centres are put on it.

    Returns
    -------
    centres : numpy.ndarray, shape (K, 3)
        The centres, gls frame, mm.
    combined : CombinedSweeps
        The combination.

    Raises
    ------
    CalibrationError
        If the sweeps cannot be combined.
    """
    try:
        measurements = correct_measurements(settings.chain_map, measurements, settings.sweep_plan, pose_scanner)
        combined = combine_sweeps(measurements, settings.sweep_plan, targets, settings.scanner_to_gls,
                                  settings.profiles_placed_by_pose, settings.separation,
                                  sweep_length_mm=settings.cell_time.sweep_length_mm)
    except ValueError as error:
        raise CalibrationError(f"the sweeps of the marked plate cannot be combined: {error}") from None
    centres = np.column_stack([combined.centres_xy, plane_height(pose_scanner, *combined.centres_xy.T)])
    return settings.scanner_to_gls.apply(centres), combined


async def plate_height_at_marking(cell: Cell, settings: ProcedureSettings, pose_scanner: PlatePose) -> PlatePose:
    """Move ``pose_scanner`` to the plate height measured standing still at the marking pose.

    ``pose_scanner`` (from the sweeps) moved to the plate height measured standing still at the
    marking pose.

    Each sweep's path is off by the robot's repeatability; the mean of a few sweeps still leaves the
    height wrong by ~0.015 mm, and a height error dz scales the marked field by dz/d (a radial pattern
    that differs from plate to plate). Standing still, no path error enters, and the scanner sees the
    plate where the head held by the same robot marks it.
    """
    cloud = await cell.acquire_standstill(settings.standstill_profiles)
    points, _ = cell.points_and_intensities(cloud)
    try:
        return pose_at_height(pose_scanner, points)
    except ValueError as error:
        raise CalibrationError(f"the plate height at the marking pose cannot be measured: {error}") from None


async def measure_marked_plate(cell: Cell, settings: ProcedureSettings, pose_scanner: PlatePose,
                               expected_count: int, report: Progress, *,
                               targets_gls: Optional[np.ndarray] = None) -> list[FiducialMeasurement]:
    """Scan the marked plate by the sweep plan and measure each sweep while the next is scanned.

    The measurement of sweep k runs (``Cell.start``) while sweep k + 1 is acquired; its result is taken
    after that acquisition. A sweep with fewer than ``min_found_fraction`` of the fiducials in its view
    fails the run: of all ``expected_count`` at 0 and 90 deg; a 45 deg pass sees the middle band of
    the plate, and with ``targets_gls`` (N, 2+) it needs that share of the targets it is sure to see
    (``sweep_plan.in_view``; without them, of all). On any failure the measurement still running is
    awaited first, so that nothing of this run goes on behind its error.
    """
    plan = settings.sweep_plan
    in_view_count = {item: expected_count for item in plan}
    if targets_gls is not None:
        targets_b = settings.scanner_to_gls.inverse().apply(
            np.column_stack([np.asarray(targets_gls, dtype=float)[:, :2], np.zeros(len(targets_gls))]))
        in_view_count = {item: int(np.count_nonzero(in_view(item, targets_b[:, :2]))) for item in plan}
    measurements: list[FiducialMeasurement] = []

    async def take(item: SweepPass, pending: Awaitable[FiducialMeasurement]) -> None:
        found = await pending
        needed = fiducials_needed(settings, in_view_count[item])
        if len(found.centres) < needed:
            which = f" (sweep {item.label} of {plan_label(plan)})" if len(plan) > 1 else ""
            of = (f"{expected_count}" if in_view_count[item] == expected_count
                  else f"the {in_view_count[item]} in its view of {expected_count}")
            raise CalibrationError(f"found {len(found.centres)} of {of} fiducials; at least {needed} "
                                   f"({settings.min_found_fraction:.0%}) are needed{which}")
        measurements.append(found)

    running: Optional[tuple[SweepPass, Awaitable[FiducialMeasurement]]] = None
    try:
        for number, item in enumerate(plan):
            report("sweep_marked", 0.45 + 0.4 * number / len(plan),
                   f"scanning the marked plate ({number + 1} of {len(plan)}: {item.label})")
            cloud = await cell.acquire_sweep(settings.marked_sweep_step_mm, item.direction, item.orientation_deg)
            if running is not None:
                previous, running = running, None
                await take(*previous)
            report("measurement", 0.45 + 0.4 * (number + 0.5) / len(plan),
                   f"measuring the fiducials of sweep {number + 1} of {len(plan)}")
            running = (item, cell.start(cell.measure_fiducials(cloud, pose_scanner, expected_count,
                                                               settings.ring_radii_mm)))
        previous, running = running, None
        await take(*previous)
    finally:
        if running is not None:     # a failure while a measurement is pending
            if inspect.iscoroutine(running[1]):
                running[1].close()      # never begun (a cell that runs steps when awaited): nothing to wait for
            else:
                with contextlib.suppress(Exception):    # let it end before the error goes on
                    await running[1]
    return measurements


def fiducials_needed(settings: ProcedureSettings, expected_count: int) -> int:
    """Return the fewest fiducials a sweep (and the pairing) must find of ``expected_count`` marked."""
    return math.ceil(settings.min_found_fraction * expected_count)


async def scan_plate_pose(cell: Cell, settings: ProcedureSettings, report: Progress, *,
                          check_clean: bool, plate: str = "plain plate") -> PlatePose:
    """Scan the plate before marking and return its pose (scanner base frame), as every plate is scanned.

    ``settings.plain_sweeps`` sweeps at ``settings.plain_sweep_step_mm``, their poses averaged, then,
    with ``settings.standstill_height``, the height measured standing still at the marking pose
    (:func:`plate_height_at_marking`). ``report`` takes the plate's share of the progress (0 to 0.15).

    Parameters
    ----------
    cell : Cell
        The cell's steps.
    settings : ProcedureSettings
        The calibration's settings.
    report : callable
        ``report(stage, part, text)``, ``part`` the share of this plate's progress.
    check_clean : bool
        Refuse a plate whose first sweep shows marks (``check_clean_plate``); off where the plate
        carries rings on purpose (a reference plate) or marking over old marks is forced.
    plate : str, default "plain plate"
        What the progress messages call the plate.

    Returns
    -------
    PlatePose
        The plate plane in the scanner base frame.

    Raises
    ------
    CalibrationError
        When a cell step fails, the plate is not clean or the stand-still height cannot be measured.
    """
    poses = []
    for repeat in range(settings.plain_sweeps):
        report("sweep_plain", 0.1 * repeat / settings.plain_sweeps,
               f"scanning the {plate} ({repeat + 1} of {settings.plain_sweeps})")
        cloud = await cell.acquire_sweep(settings.plain_sweep_step_mm)
        if repeat == 0 and check_clean:
            check_clean_plate(*cell.points_and_intensities(cloud), settings)
        poses.append(await cell.estimate_plate_pose(cloud))
    pose_scanner = mean_plate_pose(poses)
    if settings.standstill_height:
        # part of scanning the plain plate: "plate_pose" follows once the pose is final
        report("sweep_plain", 0.1, f"profiling the {plate} standing at the marking pose "
               f"({settings.standstill_profiles} profiles)")
        pose_scanner = await plate_height_at_marking(cell, settings, pose_scanner)
    report("plate_pose", 0.15, f"plate flatness {pose_scanner.flatness_rms_mm:.4f} mm RMS")
    return pose_scanner


async def run_plate(cell: Cell, settings: ProcedureSettings, grid_xy: np.ndarray, progress: Progress,
                    span: tuple[float, float], want_truth: bool, allow_marked: bool = False) -> PlateRun:
    """Scan the plain plate, mark ``grid_xy`` through the active correction, scan, measure, pair.

    The plain plate must be clean (see ``plate_marks``) unless ``allow_marked``: measuring new
    marks among old ones pairs the wrong rings.
    """
    start, width = span

    def report(stage: str, part: float, text: str) -> None:
        progress(stage, start + width * part, text)

    pose_scanner = await scan_plate_pose(cell, settings, report, check_clean=not allow_marked)
    pose_gls = pose_in_frame(pose_scanner, settings.scanner_to_gls)

    targets = np.column_stack([grid_xy, plane_height(pose_gls, grid_xy[:, 0], grid_xy[:, 1])])
    rings = grid.rings_polylines(grid_xy, settings.ring_radii_mm)
    starts = np.cumsum([0] + [len(ring) for ring in rings[:-1]]).astype(np.uint32)
    ring_xy = np.vstack(rings)
    ring_z = plane_height(pose_gls, ring_xy[:, 0], ring_xy[:, 1])
    setpoints = await cell.correct(ring_xy[:, 0], ring_xy[:, 1], ring_z)
    if not np.all(setpoints.within_limits):
        count = int(np.count_nonzero(~setpoints.within_limits))
        raise CalibrationError(f"{count} ring point(s) lie beyond the mirror limits or the focus range; "
                               "reduce the grid size or check the plate pose")
    report("marking", 0.2, f"marking {len(grid_xy)} fiducials")
    marking_s = await cell.mark(setpoints.alpha_x, setpoints.alpha_y, setpoints.focus_shift, starts)

    plan, needed = settings.sweep_plan, fiducials_needed(settings, len(grid_xy))
    measurements = await measure_marked_plate(cell, settings, pose_scanner, len(grid_xy), report, targets_gls=grid_xy)
    report("measurement", 0.85, "combining the sweeps")
    centres_gls, combined = combined_centres_gls(measurements, settings, targets, pose_scanner)
    pairing = pair_with_targets(centres_gls, targets)
    if len(pairing.target_index) < needed:
        raise CalibrationError(f"paired {len(pairing.target_index)} of {len(grid_xy)} fiducials with their "
                               f"targets; at least {needed} are needed")
    measured = pairing.transform.apply(centres_gls[pairing.measured_index])
    paired_xy = grid_xy[pairing.target_index]
    deviations = paired_xy - measured[:, :2]
    # Commanding K(Q) landed at P, so K(Q) is the command that lands on P: the correction model is
    # trained at P with K(Q) - K(P) (Q - P with no calibration active). Trained at Q instead, it
    # would leave a second-order error of about grad(delta) . delta (~0.02 mm on a 2 mm field).
    commanded = await cell.correct(paired_xy[:, 0], paired_xy[:, 1], targets[pairing.target_index, 2])
    at_measured = await cell.correct(measured[:, 0], measured[:, 1], measured[:, 2])
    corrections = (np.column_stack([commanded.x, commanded.y])
                   - np.column_stack([at_measured.x, at_measured.y]))

    true_deviations = true_metrics = None
    if want_truth:
        marks = await cell.true_marks()
        if marks is not None:
            true_centres = true_fiducial_centres(marks[-len(rings):], len(settings.ring_radii_mm))
            # The calibration cannot see a rigid motion of the whole field, so the truth is
            # compared after the same kind of alignment as the measurement.
            every_true_deviation = grid_xy - align_rigid_2d(true_centres[:, :2], grid_xy)[1]
            true_metrics = deviation_metrics(grid_xy, every_true_deviation)
            true_deviations = every_true_deviation[pairing.target_index]
    report("deviations", 1.0, f"{len(deviations)} fiducials paired")
    separation = combined.separation
    return PlateRun(targets=targets, paired_targets_xy=paired_xy, deviations=deviations,
                    measured_gls=measured, corrections=corrections, true_deviations=true_deviations,
                    plate_pose_gls=pose_gls,
                    fiducials_found=len(combined.target_index), alignment=pairing.transform,
                    metrics=deviation_metrics(paired_xy, deviations), true_metrics=true_metrics,
                    sigma_mm=combined.sigma_mm[pairing.measured_index], sweep_plan=plan_label(plan),
                    chain_map=chain_map_identity(settings.chain_map),
                    cell_time_s=settings.cell_time.plate_s(settings.plain_sweeps + len(plan), marking_s),
                    scanner_error_rms_mm=separation.scanner_rms_mm if separation else math.nan,
                    motion_error_rms_mm=separation.motion_rms_mm if separation else math.nan)


def training_grid(settings: ProcedureSettings) -> np.ndarray:
    """Return the calibration grid's fiducial centres (N, 3), gls frame, mm (``grid_per_side``, ``grid_size_mm``)."""
    return grid.grid_targets(settings.grid_per_side, settings.grid_size_mm)


def validation_grid(settings: ProcedureSettings) -> np.ndarray:
    """Fiducials between the training ones (half a pitch off), so validation is not on training points."""
    training = training_grid(settings)
    if not settings.validation_offset_half_pitch:
        return training
    pitch = settings.grid_size_mm / (settings.grid_per_side - 1)
    return grid.grid_targets(settings.grid_per_side - 1, settings.grid_size_mm - pitch)


async def calibrate(cell: Cell, settings: ProcedureSettings, *, iterations: int, validate: bool, force: bool,
                    want_truth: bool, progress: Progress,
                    save_candidate: Callable[[list[PlateRun], list[TrainedModel]], Candidate],
                    active_calibration: bool = False,
                    certify: Optional[Callable[[Candidate, PlateRun], Candidate]] = None) -> CalibrationOutcome:
    """Run the calibrate flow; ``save_candidate`` stores a calibration without activating it.

    The cell is switched to the candidate for later iterations and validation; the caller activates
    it only when this returns without a ``rejection``, so a failure (``CalibrationError``) keeps the
    active one. The plain plate must be clean, the model must explain the measurement, and with
    validation the candidate must beat the calibration in use (``acceptance_problem``).

    With ``active_calibration`` the first plate's figure is self-consistency (the chain re-measures
    the positions that calibration was trained on, with the same repeating errors); so with
    validation it is marked on a further plate at the validation positions too, and the candidate is
    judged against that (``CalibrationOutcome.active_validation``).

    Parameters
    ----------
    cell : Cell
        The cell's steps (coroutines).
    settings : ProcedureSettings
        The calibration's settings.
    iterations : int
        Plates to train on; 0: ``settings.default_iterations``.
    validate : bool
        Mark and measure a validation plate through the candidate.
    force : bool
        Allow a marked plate and training within the tolerance.
    want_truth : bool
        Ask the cell for the ground truth (simulation only).
    progress : callable
        ``progress(stage: str, fraction: float, message: str) -> None``.
    save_candidate : callable
        ``save_candidate(runs, models) -> Candidate``: store a calibration without activating it.
    active_calibration : bool, default False
        The cell corrects through a trained calibration (not the nominal model) when the run starts.
    certify : callable, optional
        ``certify(candidate, validation) -> Candidate``: called once a validated candidate is
        accepted, returns the candidate to activate (``record.certified_candidate``: its U map raised
        to what the validation showed, as a new file).

    Returns
    -------
    CalibrationOutcome
        The plates, models, candidate and message; ``rejection`` set when the candidate must not be
        activated.

    Raises
    ------
    CalibrationError
        When the calibration cannot go on (a cell step fails, the plate is not clean, too few
        fiducials, a model that explains too little, ...); the message says why.
    """
    began = time.monotonic()
    clock = StageClock()
    progress = clock.wrap(progress)
    iterations = iterations or settings.default_iterations
    training_targets = training_grid(settings)
    compare_active = validate and active_calibration
    passes = iterations + (1 if validate else 0) + (1 if compare_active else 0)
    span = 1.0 / passes
    runs: list[PlateRun] = []
    models: list[TrainedModel] = []
    candidate: Optional[Candidate] = None
    for iteration in range(iterations):
        if iteration > 0:
            await cell.exchange_plate()
        run = await run_plate(cell, settings, training_targets, progress, (iteration * span, span * 0.9),
                              want_truth, allow_marked=force)
        runs.append(run)
        rms = run.metrics.full.rms_abs_mm
        if iteration == 0 and rms <= settings.tolerance_rms_mm and not force:
            return CalibrationOutcome(f"deviation RMS {rms:.4f} mm is within the tolerance of "
                                      f"{settings.tolerance_rms_mm} mm: nothing trained (use force to train)",
                                      tuple(runs), None, tuple(models), None, time.monotonic() - began,
                                      active_calibration=active_calibration, stage_times=clock.times())
        progress("training", (iteration + 0.9) * span, f"training on {len(run.deviations)} deviations")
        models.append(await cell.train(run.measured_gls[:, :2], run.corrections))
        check_model_explains(models[-1], rms, centre_uncertainty_mm(run, settings), settings)
        candidate = save_candidate(runs, models)
        await cell.use_candidate(candidate)

    validation = active_validation = None
    if validate:
        validation_xy = validation_grid(settings)
        await cell.exchange_plate()
        validation = await run_plate(cell, settings, validation_xy, progress,
                                     (iterations * span, span), want_truth, allow_marked=force)
        before, against = runs[0], "this run's first plate"
        if compare_active:
            # like with like: the calibration in use marked at the candidate's validation positions
            await cell.exchange_plate()
            await cell.reload_active()
            active_validation = await run_plate(cell, settings, validation_xy, progress,
                                                ((iterations + 1) * span, span), want_truth, allow_marked=force)
            await cell.use_candidate(candidate)
            before, against = active_validation, "the validation grid"
        rejected = acceptance_problem(before.metrics.full.rms_abs_mm, validation.metrics.full.rms_abs_mm,
                                      max(centre_uncertainty_mm(before, settings),
                                          centre_uncertainty_mm(validation, settings)), against)
        if rejected:
            rejected = f"{rejected}; {Path(candidate.path).name} stays in the history, inactive"
            progress("done", 1.0, rejected)
            return CalibrationOutcome(rejected, tuple(runs), validation, tuple(models), candidate,
                                      time.monotonic() - began, rejection=rejected,
                                      active_validation=active_validation, active_calibration=active_calibration,
                                      stage_times=clock.times())
        if certify is not None:
            candidate = certify(candidate, validation)
    progress("done", 1.0, "calibration finished")
    return CalibrationOutcome("calibrated", tuple(runs), validation, tuple(models), candidate,
                              time.monotonic() - began, active_validation=active_validation,
                              active_calibration=active_calibration, stage_times=clock.times())
