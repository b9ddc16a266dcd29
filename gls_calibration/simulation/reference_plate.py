"""Reference-plate check of the simulated measurement chain (the published set-up's §3.2, simulated).

A reference plate with known centres -- our own double-ring fiducials (radii 2.5 and 2.7 mm, the
calibration's), 13 x 11 at a 10 mm pitch (120 x 100 mm), as precise as a certified plate: its marks
carry none of the marking effects and it is neither warm nor warped -- is laid at several positions
in the field and scanned by the simulated robot and scanner with the whole measurement chain. Each
position's measured centres (gls frame through the CAD mounting) are paired with the known ones and
aligned by a best 2-D rigid motion (where a plate lies is unknown); the residuals give the standard
uncertainty per axis (k = 1, pooled over positions, the alignment's 3 degrees of freedom per position
taken out) and the bias per position (mean residual after ONE rigid alignment of all positions, what
a position-dependent error leaves).

Two measurement plans are compared: ``RAW_PLAN``, the paper's way (one sweep, profiles placed by
time at the nominal speed), and the plan the calibration uses (``CALIBRATION_PLAN`` unless given:
today one sweep placed by time; a plan may place profiles by the robot's reported pose and average
several sweeps in both directions and sensor orientations).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
import math

import numpy as np
from scipy.spatial import cKDTree

from gls_calibration import targets
from gls_calibration.fiducials import measure_fiducials
from gls_calibration.plate_pose import estimate_plate_pose
from gls_calibration.registration import align_rigid_2d
from gls_calibration.simulation.plate import Plate
from gls_calibration.simulation.world import SimConfig

RING_RADII_MM = (2.5, 2.7)
PATTERN = (13, 11)                  # rings along x, along y
PITCH_MM = 10.0
POSITIONS_MM = ((-40.0, -40.0), (0.0, 0.0), (40.0, 40.0))


@dataclass(frozen=True)
class MeasurementPlan:
    """How a plate is measured: profile placement (``time`` or ``pose``) and the sweeps
    ((direction +1/-1, sensor orientation 0/90 deg), ...) whose centres are averaged."""

    placement: str = "time"
    sweeps: tuple[tuple[int, float], ...] = ((1, 0.0),)

    def __post_init__(self) -> None:
        if self.placement not in ("time", "pose"):
            raise ValueError(f"plan placement must be 'time' or 'pose', got {self.placement!r}")
        if not self.sweeps:
            raise ValueError("a plan needs at least one sweep")
        for direction, orientation in self.sweeps:
            if direction not in (1, -1) or orientation not in (0.0, 90.0):
                raise ValueError(f"plan sweep ({direction}, {orientation}): direction must be +1 or -1 and "
                                 "orientation 0 or 90 deg")


RAW_PLAN = MeasurementPlan()
CALIBRATION_PLAN = MeasurementPlan()     # what the calibrate flow does today: one marked sweep by time


@dataclass(frozen=True)
class ReferencePlateResult:
    """Standard uncertainty (k = 1) and bias per axis (gls x, y), mm, of one plan."""

    sigma_mm: tuple[float, float]
    bias_mm: tuple[tuple[float, float], ...]    # per position
    found: int
    expected: int


def reference_pattern() -> np.ndarray:
    """Known centres (N, 2) of the reference pattern about its own centre, mm."""
    nx, ny = PATTERN
    u = (np.arange(nx) - 0.5 * (nx - 1)) * PITCH_MM
    v = (np.arange(ny) - 0.5 * (ny - 1)) * PITCH_MM
    return np.array([(a, b) for b in v for a in u])


def _reference_plate(config: SimConfig, offset_xy, seed) -> tuple[Plate, np.ndarray]:
    chain = replace(config.measurement, mark_width_variation=0.0, mark_darkness_variation=0.0,
                    mark_wander_mm=0.0, mark_blob_mm=0.0, spot_blur_mm=0.0, thermal_scale_ppm=0.0,
                    plate_warp_mm=0.0)
    plate = Plate(config.plate_settings, seed=seed, chain=chain)
    known_uv = reference_pattern() + np.asarray(offset_xy, dtype=float)
    for ring in targets.rings_polylines(known_uv, RING_RADII_MM):
        plate.add_mark_plate(ring)
    return plate, plate.from_plate(known_uv)


def measure_plate(config: SimConfig, plate: Plate, plan: MeasurementPlan, seed: int,
                  expected_count: int) -> np.ndarray:
    """Fiducial centres (M, 3) in the scanner base frame, averaged over the plan's sweeps.

    Centres seen in fewer than all sweeps are dropped."""
    scanner = config.make_scanner()
    per_sweep = []
    for number, (direction, orientation) in enumerate(plan.sweeps):
        data = scanner.sweep_data(plate, config.sweep_length_mm, step_mm=0.1, seed=seed * 1009 + number,
                                  direction=direction, orientation_deg=orientation)
        xyz = data.placed_by_pose() if plan.placement == "pose" else data.placed_by_time()
        pose = estimate_plate_pose(xyz, head_direction=(0.0, 0.0, -1.0))
        per_sweep.append(measure_fiducials(xyz, data.intensity, pose, ring_radii_mm=RING_RADII_MM,
                                           expected_count=expected_count).centres)
    reference = per_sweep[0]
    total, seen = reference.copy(), np.ones(len(reference), dtype=int)
    for centres in per_sweep[1:]:
        distance, nearest = cKDTree(centres).query(reference)
        close = distance < 1.0
        total[close] += centres[nearest[close]]
        seen[close] += 1
    keep = seen == len(per_sweep)
    return total[keep] / seen[keep, None]


def reference_plate_check(config: SimConfig, plan: MeasurementPlan = CALIBRATION_PLAN, seed: int = 1,
                          positions=POSITIONS_MM) -> ReferencePlateResult:
    """Scan the reference plate at ``positions`` (plate-centre offsets, mm) with ``plan``."""
    scanner = config.make_scanner()
    residuals, measured_all, known_all, found, expected = [], [], [], 0, 0
    for index, offset in enumerate(positions):
        plate, known = _reference_plate(config, offset, [seed, index])
        centres = scanner.to_gls(measure_plate(config, plate, plan, seed * 101 + index, len(known)))
        distance, nearest = cKDTree(known).query(centres)
        paired = distance < 0.5 * PITCH_MM
        measured, truth = centres[paired], known[nearest[paired]]
        found += int(paired.sum())
        expected += len(known)
        residuals.append(_aligned_residuals(measured, truth))
        measured_all.append(measured)
        known_all.append(truth)
    stacked = np.vstack(residuals)
    dof = len(stacked) - 1.5 * len(positions)
    sigma = tuple(float(math.sqrt(np.sum(stacked[:, axis] ** 2) / dof)) for axis in range(2))
    joint = _aligned_residuals(np.vstack(measured_all), np.vstack(known_all))
    bounds = np.cumsum([0] + [len(m) for m in measured_all])
    bias = tuple(tuple(float(v) for v in joint[a:b].mean(axis=0)) for a, b in zip(bounds[:-1], bounds[1:]))
    return ReferencePlateResult(sigma, bias, found, expected)


def _aligned_residuals(measured: np.ndarray, known: np.ndarray) -> np.ndarray:
    """In-plane residuals (N, 2) of measured centres after the best 2-D rigid motion onto the known ones."""
    return align_rigid_2d(measured[:, :2], known[:, :2])[1] - known[:, :2]
