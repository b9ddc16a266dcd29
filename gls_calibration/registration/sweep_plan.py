"""The sweep plan of the marked plate, its cell time, and the combination of its sweeps.

A plan is a sequence of passes (direction +1/-1 along the sensor's y, sensor turned 0, 45 or 90 deg
about its viewing axis). Every sweep's fiducials are paired with the targets, expressed in that
sweep's sensor axes, and :func:`separation.separate` removes what is fixed to the scanner frame or
to one sweep's motion; what is left is averaged. Clouds are in the scanner base frame (see
``scan/sweep.py``), so a turned or reversed sweep measures the same marks in the same frame.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from gls_calibration.fiducials.measure import FiducialMeasurement
from gls_calibration.registration.rigid import RigidTransform, pair_with_targets
from gls_calibration.registration.separation import TIME_PLACED, Separation, SeparationSettings, separate
from gls_calibration.scan.sweep import SWEEP_LENGTH_MM, nominal_start_pose, sweep_middle_mm

ORIENTATIONS_DEG = (0.0, 45.0, 90.0)
"""Turns of the sensor a pass may take, degrees. At 0 and 90 the sweep covers the whole grid; the
diagonal pass covers its middle band (:func:`in_view`) and is what makes a symmetric shear of the
marks observable apart from the sweeps' path yaw (docs/method-and-results.md, the 45 deg pass)."""

ORIENTATIONS_TEXT = ", ".join(f"{value:g}" for value in ORIENTATIONS_DEG[:-1]) + f" or {ORIENTATIONS_DEG[-1]:g}"
"""``ORIENTATIONS_DEG`` as the error messages name it: ``0, 45 or 90``."""


@dataclass(frozen=True)
class SweepPass:
    """One sweep of the marked plate: travel direction (+1/-1) and sensor orientation (deg).

    Parameters
    ----------
    direction : int, default 1
        +1 or -1.
    orientation_deg : float, default 0.0
        0, 45 or 90, degrees.

    Raises
    ------
    ValueError
        If either is not one of its allowed values.
    """

    direction: int = 1
    orientation_deg: float = 0.0

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        if self.direction not in (1, -1):
            raise ValueError(f"sweep plan direction must be +1 or -1, got {self.direction!r}")
        if self.orientation_deg not in ORIENTATIONS_DEG:
            raise ValueError(f"sweep plan orientation must be {ORIENTATIONS_TEXT} deg, got {self.orientation_deg!r}")

    @property
    def label(self) -> str:
        """Short name of the pass, such as ``90-`` (orientation, direction)."""
        return f"{self.orientation_deg:g}{'+' if self.direction > 0 else '-'}"


def parse_plan(text: str) -> tuple[SweepPass, ...]:
    """Parse passes from a comma-separated list such as ``"0+,0-,90+,90-"`` (orientation deg, direction).

    Parameters
    ----------
    text : str
        The plan.

    Returns
    -------
    tuple of SweepPass
        The passes in order.

    Raises
    ------
    ValueError
        If an item is not an orientation (0, 45 or 90) followed by + or -, or the plan is empty.

    Examples
    --------
    >>> passes = parse_plan("0+, 90-")
    >>> [(item.direction, item.orientation_deg) for item in passes]
    [(1, 0.0), (-1, 90.0)]
    >>> plan_label(passes)
    '0+,90-'
    """
    passes = []
    for item in (part.strip() for part in str(text).split(",")):
        if len(item) < 2 or item[-1] not in "+-":
            raise ValueError(f"sweep plan item {item!r} must be an orientation ({ORIENTATIONS_TEXT}) followed by "
                             "+ or -, e.g. 0+,0-,90+,90-")
        try:
            orientation = float(item[:-1])
        except ValueError:
            raise ValueError(f"sweep plan item {item!r}: orientation {item[:-1]!r} is not a number") from None
        passes.append(SweepPass(1 if item[-1] == "+" else -1, orientation))
    if not passes:
        raise ValueError("the sweep plan needs at least one pass")
    return tuple(passes)


def plan_label(passes: Sequence[SweepPass]) -> str:
    """Return the plan as ``parse_plan`` reads it.

    Parameters
    ----------
    passes : sequence of SweepPass
        The passes.

    Returns
    -------
    str
        Comma-separated labels, e.g. ``"0+,0-,90+,90-"``.
    """
    return ",".join(item.label for item in passes)


def in_view(item: SweepPass, points_xy_mm: np.ndarray) -> np.ndarray:
    """Return which points a pass is sure to see: those inside its footprint's guaranteed square.

    The plan's 0 and 90 deg passes must each cover every point, so the sensor's footprint holds the
    points' bounding square in both; a pass turned by another angle holds at least that square
    turned with it, about the same centre. At 0 and 90 deg every point is in view.

    Parameters
    ----------
    item : SweepPass
        The pass.
    points_xy_mm : numpy.ndarray, shape (N, 2)
        The points (targets) in the scanner base frame's x-y, mm.

    Returns
    -------
    numpy.ndarray, shape (N,)
        True where the point lies inside the turned square (1 um of slack).

    Examples
    --------
    >>> corners = np.array([[-90.0, -90.0], [90.0, 90.0], [0.0, 0.0], [90.0, 0.0]])
    >>> in_view(SweepPass(1, 45.0), corners).tolist()
    [False, False, True, True]
    """
    points = np.asarray(points_xy_mm, dtype=float)[:, :2]
    low, high = points.min(axis=0), points.max(axis=0)
    half = 0.5 * float(np.max(high - low)) + 1e-3
    axes = nominal_start_pose(0.0, item.direction, item.orientation_deg)[:2, :2]
    local = (points - 0.5 * (low + high)) @ axes
    return np.all(np.abs(local) <= half, axis=1)


@dataclass(frozen=True)
class CellTimeModel:
    """What one plate costs in cell time besides marking: sweeps at the scanner's speed, robot moves.

    Parameters
    ----------
    sweep_length_mm : float, default SWEEP_LENGTH_MM
        Length of one sweep, mm (210).
    sweep_speed_mm_s : float, default 15.0
        The scanner's travel speed, mm/s.
    robot_move_s : float, default 4.0
        Moving back to a sweep's start (and turning the sensor) between sweeps, s.
    """

    sweep_length_mm: float = SWEEP_LENGTH_MM
    sweep_speed_mm_s: float = 15.0
    robot_move_s: float = 4.0          # back to a sweep's start (and turning the sensor) between sweeps

    def plate_s(self, sweeps: int, marking_s: float) -> float:
        """Cell time of one plate: ``sweeps`` sweeps (plain and marked), the moves, the marking."""
        return sweeps * (self.sweep_length_mm / self.sweep_speed_mm_s + self.robot_move_s) + marking_s


@dataclass(frozen=True)
class CombinedSweeps:
    """The marked plate's centres from every sweep of a plan (scanner base frame, mm).

    Parameters
    ----------
    centres_xy : numpy.ndarray, shape (K, 2)
        Centres in the base frame's plane (the caller puts them on the plate plane), mm.
    sigma_mm : numpy.ndarray, shape (K,)
        Standard uncertainty per axis of each (ring fit and sweep spread; NaN when unknown), mm.
    target_index : numpy.ndarray, shape (K,)
        The target each belongs to.
    separation : Separation or None
        The separation of the scanner-frame errors; None for a single sweep.
    """

    centres_xy: np.ndarray
    sigma_mm: np.ndarray
    target_index: np.ndarray
    separation: Optional[Separation]


def _ring_sigma(found: FiducialMeasurement) -> np.ndarray:
    """Per-centre sigma (K,) from the ring fit when the measurement states one, else NaN."""
    sigma = getattr(found, "sigma_xy_mm", None)
    if sigma is None:
        return np.full(len(found.centres), np.nan)
    return np.sqrt(np.mean(np.asarray(sigma, dtype=float) ** 2, axis=1))


def combine_sweeps(measurements: Sequence[FiducialMeasurement], passes: Sequence[SweepPass], targets_gls: np.ndarray,
                   scanner_to_gls: RigidTransform, placed_by_pose: bool,
                   settings: Optional[SeparationSettings] = None, *, sweep_length_mm: float) -> CombinedSweeps:
    """Pair every sweep's centres with the targets and separate the scanner-frame errors.

    Parameters
    ----------
    measurements : sequence of FiducialMeasurement
        One per pass, scanner base frame, mm.
    passes : sequence of SweepPass
        The sweep plan.
    targets_gls : numpy.ndarray, shape (N, 3)
        The targets, gls frame, mm.
    scanner_to_gls : RigidTransform
        Scanner base frame -> gls frame.
    placed_by_pose : bool
        Whether the profiles were placed by the robot's reported pose (else by time).
    settings : SeparationSettings, optional
        Defaults to the separation for profiles placed by pose, or by time
        (``separation.TIME_PLACED``) when ``placed_by_pose`` is false.
    sweep_length_mm : float
        Length of the sweeps, mm: they are turned about their middle (``sweep.sweep_middle_mm``),
        from which a centre's coordinate along the sensor's line is measured.

    Returns
    -------
    CombinedSweeps
        The centres in the reference sweep's frame (the sweep that saw the most), with sigmas and targets.

    Raises
    ------
    ValueError
        If there is no measurement or the counts of measurements and passes differ, or a pairing
        rejects its input (see :func:`pair_with_targets`).
    """
    if len(measurements) != len(passes) or not measurements:
        raise ValueError(f"{len(measurements)} measurement(s) for a plan of {len(passes)} pass(es)")
    count = len(targets_gls)
    if len(measurements) == 1:
        found = measurements[0]
        pairing = pair_with_targets(scanner_to_gls.apply(found.centres), targets_gls)
        return CombinedSweeps(found.centres[pairing.measured_index, :2], _ring_sigma(found)[pairing.measured_index],
                              pairing.target_index, None)
    # Coordinates from the sweeps' common middle: there each sweep's x is the position on the sensor's
    # line, where the scanner's lateral linearity shape is the same in every sweep (from B's origin,
    # the 90 deg sweeps' x was 100 mm off the 0 deg sweeps' for the same place on the line).
    middle = sweep_middle_mm(sweep_length_mm)
    tables, sigmas = [], []
    for found, item in zip(measurements, passes):
        pairing = pair_with_targets(scanner_to_gls.apply(found.centres), targets_gls)
        axes = nominal_start_pose(0.0, item.direction, item.orientation_deg)[:2, :2]
        table = np.full((count, 2), np.nan)
        # the sweep's own axes: x along its line, y along its travel (B's axes turned by the orientation)
        table[pairing.target_index] = (found.centres[pairing.measured_index, :2] - middle) @ axes
        sigma = np.full(count, np.nan)
        sigma[pairing.target_index] = _ring_sigma(found)[pairing.measured_index]
        tables.append(table)
        sigmas.append(sigma)
    # the reference sweep must see the most fiducials: the separation works in its frame
    order = sorted(range(len(tables)), key=lambda k: -int(np.all(np.isfinite(tables[k]), axis=1).sum()))
    reference = order[0]
    if settings is None:
        settings = SeparationSettings() if placed_by_pose else TIME_PLACED
    result = separate([tables[k] for k in order], [sigmas[k] for k in order], settings)
    seen = result.sweeps_seen > 0
    axes = nominal_start_pose(0.0, passes[reference].direction, passes[reference].orientation_deg)[:2, :2]
    return CombinedSweeps(result.centres_mm[seen] @ axes.T + middle, result.sigma_mm[seen], np.flatnonzero(seen),
                          result)
