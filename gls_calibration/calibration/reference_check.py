"""A reference check measured: a plate with known centres scanned as the calibration scans its plate.

The stated accuracy (:mod:`gls_calibration.calibration.stated_accuracy`) rests on a check of the
measurement chain against known centres. Here is how such a check is measured, the same steps for a
simulated reference plate and for a certified plate scanned in a real cell:

0. :func:`read_certified_centres`: the known centres, a CSV (``x``, ``y``[, ``z``], mm, gls frame);
1. :func:`measure_reference_plate` (sweeps in hand: a bag, the simulation) or
   :func:`scan_reference_check` (a ``procedure.Cell`` driven through the scan): the plate plane
   from the plain sweeps (averaged as the calibration averages them), the fiducials of every pass
   of the sweep plan, the passes combined by the calibration's own error separation
   (``procedure.combined_centres_gls``, the chain map applied when the settings hold one) and
   paired with the known centres as the calibration pairs its targets (:func:`paired_centres`);
2. :func:`chain_sigma_mm`: per placement of the plate, the paired centres aligned onto the known ones
   by the best 2-D rigid motion (where a plate lies is not known to the micrometre), the residuals
   pooled over placements, the per-axis standard deviation with each alignment's 3 degrees of
   freedom taken out (1.5 per axis; :func:`residual_sigma_mm`).

Example
-------
>>> known = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [10.0, 10.0, 0.0]])
>>> measured = known + np.array([[0.002, 0.0, 0.0], [-0.002, 0.0, 0.0], [-0.002, 0.0, 0.0], [0.002, 0.0, 0.0]])
>>> sigma, residuals = chain_sigma_mm([measured], [known])
>>> round(sigma[0], 4), residuals.shape
(0.0025, (4, 2))
"""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from gls_calibration.calibration import procedure
from gls_calibration.calibration.procedure import ProcedureSettings, combined_centres_gls
from gls_calibration.calibration.stated_accuracy import (ChainCheck, centres_extent_mm, placement_name,
                                                         sides_short_of)
from gls_calibration.fiducials.measure import FiducialMeasurement, measure_fiducials
from gls_calibration.registration.chain_map import chain_map_identity
from gls_calibration.registration.rigid import align_rigid_2d, pair_with_targets
from gls_calibration.registration.sweep_plan import plan_label
from gls_calibration.scan.plate_pose import PlatePose, estimate_plate_pose, mean_plate_pose

MIN_CERTIFIED = 3
"""Centres a rigid alignment needs, and then some: fewer certified centres are refused."""

HEAD_DIRECTION = (0.0, 0.0, -1.0)
"""Where the head looks from the plate in the scanner's base frame, as the calibration's cells take
it (``core_cell``): it tells the plate's upper face from its lower one."""


def plate_plane(xyz_mm: np.ndarray) -> PlatePose:
    """Return the plate plane of one sweep's points (any shape (..., 3), mm) as the calibration fits it.

    Parameters
    ----------
    xyz_mm : numpy.ndarray, shape (..., 3)
        Points in the scanner base frame, mm; NaN for no return.

    Returns
    -------
    PlatePose
        The fitted plane.

    Raises
    ------
    ValueError
        If no plane can be fitted (too few points).
    """
    return estimate_plate_pose(np.asarray(xyz_mm).reshape(-1, 3), head_direction=HEAD_DIRECTION)


def measure_reference_plate(plain_xyz_mm: Iterable[np.ndarray], passes: Iterable[tuple[np.ndarray, np.ndarray]],
                            settings: ProcedureSettings, known_gls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Measure a plate with known centres as the calibration measures its marked plate.

    Parameters
    ----------
    plain_xyz_mm : iterable of numpy.ndarray, shape (..., 3)
        The points of each plain sweep (scanner base frame, mm); may be empty, then the plane comes
        from the first pass.
    passes : iterable of (numpy.ndarray, numpy.ndarray)
        Points (..., 3) and intensities (...) of each pass of ``settings.sweep_plan``, in its order;
        taken one at a time (a generator keeps one sweep in memory).
    settings : ProcedureSettings
        Plan, placement, separation, ring radii, chain map and ``scanner_to_gls``.
    known_gls : numpy.ndarray, shape (N, 3)
        The known centres, gls frame, mm, where the plate nominally lies.

    Returns
    -------
    measured : numpy.ndarray, shape (M, 3)
        The measured centres paired with known ones, gls frame, mm.
    known : numpy.ndarray, shape (M, 3)
        The known centres they pair with, in the same order.

    Raises
    ------
    ValueError
        If the number of passes is not the plan's, or no plane can be fitted.
    CalibrationError
        If the sweeps cannot be combined.
    """
    known_gls = np.asarray(known_gls, dtype=float)
    poses = [plate_plane(xyz) for xyz in plain_xyz_mm]
    pose = mean_plate_pose(poses) if poses else None
    measurements = []
    for xyz, intensity in passes:
        if pose is None:
            pose = plate_plane(xyz)
        measurements.append(measure_fiducials(xyz, intensity, pose, ring_radii_mm=settings.ring_radii_mm,
                                              expected_count=len(known_gls)))
    if len(measurements) != len(settings.sweep_plan):
        raise ValueError(f"the sweep plan has {len(settings.sweep_plan)} pass(es), {len(measurements)} "
                         "sweep(s) were given")
    return paired_centres(measurements, settings, known_gls, pose)


def paired_centres(measurements: list[FiducialMeasurement], settings: ProcedureSettings, known_gls: np.ndarray,
                   pose_scanner: PlatePose) -> tuple[np.ndarray, np.ndarray]:
    """Combine the passes' centres as the calibration combines them and pair them with the known centres.

    Parameters
    ----------
    measurements : list of FiducialMeasurement
        One per pass of ``settings.sweep_plan``, in its order (scanner base frame, mm).
    settings : ProcedureSettings
        Plan, placement, separation, chain map and ``scanner_to_gls``.
    known_gls : numpy.ndarray, shape (N, 3)
        The known centres, gls frame, mm.
    pose_scanner : PlatePose
        The plate plane in the scanner base frame.

    Returns
    -------
    measured : numpy.ndarray, shape (M, 3)
        The measured centres paired with known ones, gls frame, mm.
    known : numpy.ndarray, shape (M, 3)
        The known centres they pair with, in the same order.

    Raises
    ------
    CalibrationError
        If the sweeps cannot be combined.
    """
    centres_gls, _combined = combined_centres_gls(measurements, settings, known_gls, pose_scanner)
    pairing = pair_with_targets(centres_gls, known_gls)
    return centres_gls[pairing.measured_index], known_gls[pairing.target_index]


def chain_check(measured: np.ndarray, known: np.ndarray, settings: ProcedureSettings,
                reference: str) -> tuple[ChainCheck, np.ndarray]:
    """Return the reference check of one placement's paired centres and their aligned residuals.

    Parameters
    ----------
    measured, known : numpy.ndarray, shape (M, 2 or 3)
        The paired centres (:func:`paired_centres`), mm.
    settings : ProcedureSettings
        The plan, the placement (``profiles_placed_by_pose``) and the chain map they were measured with.
    reference : str
        Names the plate and its certificate.

    Returns
    -------
    check : ChainCheck
        The check (``chain_sigma_mm``), its plan, placement and chain map those of ``settings``, its
        extent that of the paired known centres (as :func:`certified_reach` judges them before a scan).
    residuals_mm : numpy.ndarray, shape (M, 2)
        Measured minus known after the best rigid motion, mm.

    Raises
    ------
    ValueError
        If fewer than 3 centres pair or ``reference`` is blank.
    """
    sigma, residuals = chain_sigma_mm([measured], [known])
    check = ChainCheck(sigma_mm=sigma, plan=plan_label(settings.sweep_plan),
                       placement=placement_name(settings.profiles_placed_by_pose), reference=reference.strip(),
                       centres=len(measured), chain_map=chain_map_identity(settings.chain_map),
                       extent_mm=centres_extent_mm(known))
    return check, residuals


async def scan_reference_check(cell: procedure.Cell, settings: ProcedureSettings, known_gls: np.ndarray,
                               reference: str, progress: procedure.Progress) -> ChainCheck:
    """Scan a plate with known centres through ``cell`` as a calibration scans its marked plate; its check.

    The same steps as ``procedure.run_plate`` without the marking: the plate pose from the plain
    sweeps and, with ``settings.standstill_height``, the stand-still height
    (``procedure.scan_plate_pose``; the plate carries rings, so no clean-plate check), the passes of
    the sweep plan measured while the next is scanned (``procedure.measure_marked_plate``), combined
    and paired with the known centres (:func:`paired_centres`), then :func:`chain_check`.

    Parameters
    ----------
    cell : procedure.Cell
        The cell's steps.
    settings : ProcedureSettings
        The settings the calibrations run with (plan, placement, chain map, ``scanner_to_gls``, ...).
    known_gls : numpy.ndarray, shape (N, 3)
        The certified centres, gls frame, mm, where the plate nominally lies
        (:func:`read_certified_centres`).
    reference : str
        Names the plate and its certificate (the check's ``reference``).
    progress : callable
        ``progress(stage: str, fraction: float, message: str) -> None``.

    Returns
    -------
    ChainCheck
        The check, to save with ``stated_accuracy.save_chain_check``.

    Raises
    ------
    ValueError
        If ``known_gls`` is not (N, 3) finite with at least ``MIN_CERTIFIED`` rows, or ``reference`` is blank.
    CalibrationError
        When a cell step fails, a sweep finds too few rings, or fewer than
        ``procedure.fiducials_needed`` of the known centres pair with measured ones.
    """
    known_gls = np.asarray(known_gls, dtype=float)
    if known_gls.ndim != 2 or known_gls.shape[1] != 3 or len(known_gls) < MIN_CERTIFIED \
            or not np.all(np.isfinite(known_gls)):
        raise ValueError(f"known_gls must be (N, 3) finite centres, N at least {MIN_CERTIFIED}, "
                         f"got shape {known_gls.shape}")
    if not isinstance(reference, str) or not reference.strip():
        raise ValueError("reference must name the plate and its certificate")
    pose_scanner = await procedure.scan_plate_pose(cell, settings, progress, check_clean=False,
                                                   plate="reference plate")
    measurements = await procedure.measure_marked_plate(cell, settings, pose_scanner, len(known_gls), progress,
                                                        targets_gls=known_gls)
    progress("measurement", 0.85, "combining the sweeps")
    measured, known = paired_centres(measurements, settings, known_gls, pose_scanner)
    needed = procedure.fiducials_needed(settings, len(known_gls))
    if len(measured) < needed:
        raise procedure.CalibrationError(f"paired {len(measured)} of {len(known_gls)} certified centres with "
                                         f"measured ones; at least {needed} are needed")
    check, _residuals = chain_check(measured, known, settings, reference)
    progress("done", 1.0, f"reference check: sigma x {check.sigma_mm[0]:.4f} mm, y {check.sigma_mm[1]:.4f} mm "
             f"from {check.centres} of {len(known_gls)} certified centres")
    return check


def certified_reach(known_gls: np.ndarray, settings: ProcedureSettings) -> str:
    """Return why the certified centres cannot check the calibration grid of ``settings``; ``""`` when they can.

    A check states a figure only for targets its known centres reach (``stated_accuracy.check_mismatch``):
    centres ending short of the grid's outer fiducials make a check that no calibration on that
    grid can state its accuracy from.

    Parameters
    ----------
    known_gls : numpy.ndarray, shape (N, 2 or 3)
        The certified centres, gls frame, mm.
    settings : ProcedureSettings
        The calibrations' grid (``grid_per_side``, ``grid_size_mm``).

    Returns
    -------
    str
        The sides the centres end short at and both extents; empty when they reach the grid.
    """
    reached = centres_extent_mm(known_gls)
    needed = centres_extent_mm(procedure.training_grid(settings))
    short = sides_short_of(reached, needed)
    if not short:
        return ""
    return (f"the certified centres span x {reached[0]:.1f}..{reached[1]:.1f}, y {reached[2]:.1f}..{reached[3]:.1f} mm "
            f"and end short of the calibration grid (x {needed[0]:.1f}..{needed[1]:.1f}, y {needed[2]:.1f}.."
            f"{needed[3]:.1f} mm) at {', '.join(short)}: a check on them would state no accuracy for that grid")


def read_certified_centres(path: str | Path) -> np.ndarray:
    """Return the certified centres (N, 3), mm, of a CSV with columns ``x``, ``y`` and optionally ``z``.

    Parameters
    ----------
    path : str or pathlib.Path
        The CSV file.

    Returns
    -------
    numpy.ndarray, shape (N, 3)
        The centres; z is 0 where the file has no ``z`` column.

    Raises
    ------
    ValueError
        If the file cannot be read, lacks a column, holds a value that is not a finite number, holds
        the same centre twice or fewer than ``MIN_CERTIFIED`` rows.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: cannot be read: {getattr(error, 'strerror', None) or error}") from None
    reader = csv.DictReader(io.StringIO(text))
    columns = [name.strip() for name in (reader.fieldnames or [])]
    missing = [name for name in ("x", "y") if name not in columns]
    if missing:
        raise ValueError(f"{path}: the header names no column {', '.join(missing)} "
                         f"(found: {', '.join(columns) or 'none'})")
    reader.fieldnames = columns
    rows = []
    for line, row in enumerate(reader, start=2):
        values = []
        for name in ("x", "y", "z"):
            if name == "z" and "z" not in columns:
                values.append(0.0)
                continue
            try:
                value = float(row[name])
            except (TypeError, ValueError):
                raise ValueError(f"{path}, line {line}: {name} is not a number: {row[name]!r}") from None
            if not math.isfinite(value):
                raise ValueError(f"{path}, line {line}: {name} is not finite: {row[name]!r}")
            values.append(value)
        rows.append(values)
    if len(rows) < MIN_CERTIFIED:
        raise ValueError(f"{path}: {len(rows)} certified centre(s); at least {MIN_CERTIFIED} are needed")
    centres = np.array(rows)
    if len(np.unique(centres[:, :2], axis=0)) != len(centres):
        raise ValueError(f"{path}: a certified centre (x, y) is listed twice")
    return centres


def aligned_residuals(measured: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Return in-plane residuals (N, 2) of measured centres after the best 2-D rigid motion onto the known ones.

    Parameters
    ----------
    measured, known : numpy.ndarray, shape (N, 2 or 3)
        Paired centres, mm (only x and y are used).

    Returns
    -------
    numpy.ndarray, shape (N, 2)
        Aligned measured minus known, mm.
    """
    return align_rigid_2d(measured[:, :2], known[:, :2])[1] - known[:, :2]


def chain_sigma_mm(measured: Sequence[np.ndarray], known: Sequence[np.ndarray]
                   ) -> tuple[tuple[float, float], np.ndarray]:
    """Return the chain's per-axis standard deviation (k = 1, mm) from paired centres of placements.

    Parameters
    ----------
    measured, known : sequence of numpy.ndarray, shape (N_i, 2 or 3)
        Per placement of the plate, the measured centres and the known ones they pair with, mm.

    Returns
    -------
    sigma_mm : tuple of 2 float
        Per-axis standard deviation of the residuals, each placement's rigid motion taken out (its 3
        degrees of freedom, 1.5 per axis).
    residuals_mm : numpy.ndarray, shape (sum N_i, 2)
        The aligned residuals, placements stacked in order.

    Raises
    ------
    ValueError
        If the placements do not pair up or leave no degree of freedom.
    """
    if len(measured) != len(known) or not len(measured):
        raise ValueError(f"measured and known centres must come in the same number of placements (at least "
                         f"one), got {len(measured)} and {len(known)}")
    if any(len(m) != len(k) or len(m) < 3 for m, k in zip(measured, known)):
        raise ValueError("every placement needs at least 3 paired centres, measured and known of the same count")
    stacked = np.vstack([aligned_residuals(np.asarray(m, float), np.asarray(k, float))
                         for m, k in zip(measured, known)])
    return residual_sigma_mm(stacked, len(measured)), stacked


def residual_sigma_mm(residuals_mm: np.ndarray, placements: int = 1) -> tuple[float, float]:
    """Return the per-axis standard deviation (k = 1, mm) of rigidly aligned residuals.

    Parameters
    ----------
    residuals_mm : numpy.ndarray, shape (N, 2)
        Residuals after each placement's best 2-D rigid motion, placements stacked.
    placements : int, default 1
        Placements aligned apart: each took 3 degrees of freedom (1.5 per axis).

    Returns
    -------
    tuple of 2 float
        sqrt(sum of squares / (N - 1.5 placements)) per axis.
    """
    dof = len(residuals_mm) - 1.5 * placements
    return tuple(float(math.sqrt(np.sum(residuals_mm[:, axis] ** 2) / dof)) for axis in range(2))
