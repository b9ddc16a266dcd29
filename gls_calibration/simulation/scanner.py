"""Simulated laser-line scanner swept over the plate by the robot.

Frames. The *base* frame B is the sensor's nominal pose at the start of a default sweep (the frame
the CAD mounting ``scanner_to_gls`` maps to the gls frame): x along the laser line (0 on the
sensor axis), y along the default travel, z along the viewing direction from the sensor towards the
plate (z is the measured distance, about 325 mm). Right-handed. The true mounting may differ by a
small unknown error (``mounting_error``, applied in B), and each sweep's path may be off by the
robot's repeatability (a constant per sweep) and wander along it (``MeasurementChain``).

Sweeps (the hooks of the error-separation work). ``direction`` +1 moves the sensor along its +y,
-1 along its -y (the sensor does not turn); ``orientation_deg`` 0, 45 or 90 turns the sensor about its
viewing axis (B's z) before the sweep, so a 90 deg sweep runs along B's x. Either way the sweep
covers ``length_mm`` centred on ``(0, length_mm / 2, 0)`` of B. The sweep's *start frame* is the
nominal sensor pose at its first profile (:meth:`LaserLineScanner.start_pose`, a 4x4 in B).

Profiles. Every profile holds W points ``x, y, z, intensity`` (float32) placed *by time* in the
start frame (y = direction * index * step, what a scanner without an encoder assumes: constant
nominal speed); the sensor itself measures y = 0. Invalid points (off the plate, out of range,
dropouts) are NaN in every field. Each profile also carries ``reported_pose`` (4x4, sensor -> B):
the pose the robot REPORTS at the profile's stamp (its encoder pose): it follows the robot's timing
(speed-scale error and speed ripple) but not the difference between reported and true pose, which
the robot cannot see: the per-sweep repeatability offset, the per-sweep path wander, and the
errors that repeat per programmed line (``robot_*`` of the measurement chain: a travel scale per
line, smooth along-travel, cross-track and height errors that are functions of where the sensor is
in the base frame, drawn once per robot from ``robot_seed``, one field per travel direction and
sensor orientation). A consumer places a profile by pose as ``reported_pose @ (x, 0, z, 1)`` of its
sensor-frame points.

Stand-still (:meth:`LaserLineScanner.standstill_data`): profiles taken with the robot standing still at
the marking pose, so no path error of a sweep enters; the scanner, held by the same flange as the
head, sees the plate moved by the head's marking-pose error. Its draws have a stream of their own.

Noise model: z noise (Gaussian), a smooth z linearity error across the line, and the measurement
chain (:mod:`gls_calibration.simulation.measurement`): placement errors of the robot, the lateral
linearity of the sensor, fan geometry (points on rays from the fan apex, so lateral position and
pitch follow the measured range), white and correlated speckle, saturation with blooming along the
line, quantisation to ``intensity_bits`` and random dropouts.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from scipy.ndimage import gaussian_filter, gaussian_filter1d

from gls_calibration.simulation.measurement import (MeasurementChain, lateral_linearity_shape, smooth_field,
                                                    smooth_process)
from gls_calibration.common.validation import as_finite_array, as_non_negative_number, as_positive_number
from gls_calibration.geometry.optics import plate_frame
from gls_calibration.registration.sweep_plan import ORIENTATIONS_DEG, ORIENTATIONS_TEXT
from gls_calibration.scan.sweep import SCANNER_STANDOFF_MM, SWEEP_LENGTH_MM, nominal_mounting, nominal_start_pose
from gls_calibration.simulation.plate import Plate

PROFILE_DTYPE = np.dtype([("x", np.float32), ("y", np.float32), ("z", np.float32), ("intensity", np.float32)])
_CHUNK_ROWS = 128
_PATH_STREAM = 2 ** 31 - 1      # random stream of the robot path error, apart from the chunk streams
_CHAIN_STREAM = 2 ** 31 - 2     # robot placement processes of one sweep
_SPECKLE_STREAM = 2 ** 31 - 3   # correlated speckle, one sub-stream per profile
_ROBOT_STREAM = 2 ** 31 - 4     # the robot's repeating errors, one sub-stream per line kind and component
_WANDER_STREAM = 2 ** 31 - 5    # the per-sweep along-travel wander (apart, so old sweeps stay the same)
_STANDSTILL_STREAM = 2 ** 31 - 6  # stand-still profiles: apart, so the sweeps' numbers stay the same
_ORIENTATION_STREAM = {0.0: 0, 90.0: 1, 45.0: 2}
"""Sub-stream of each orientation's repeating robot errors (0 and 90 as before 45 was added: the same draws)."""


def pose_matrix(xyz_mm, rpy_rad) -> np.ndarray:
    """4x4 transform from a translation (mm) and roll, pitch, yaw (rad, fixed axes x, y, z)."""
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler("xyz", as_finite_array(rpy_rad, "rpy_rad", ndim=1)).as_matrix()
    matrix[:3, 3] = as_finite_array(xyz_mm, "xyz_mm", ndim=1)
    return matrix


@dataclass(frozen=True)
class ScannerSettings:
    """Laser-line scanner and sweep settings (mm, s)."""

    standoff_mm: float = SCANNER_STANDOFF_MM
    line_length_mm: float = 210.0
    point_spacing_mm: float = 0.1
    step_mm: float = 0.1
    speed_mm_s: float = 15.0
    depth_min_mm: float = 225.0
    depth_max_mm: float = 425.0
    z_noise_mm: float = 0.015
    linearity_mm: float = 0.065
    gain: float = 1.3
    speckle: float = 0.05
    intensity_bits: int = 10
    dropout_fraction: float = 0.002
    path_repeatability_mm: float = 0.05

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        for name in ("standoff_mm", "line_length_mm", "point_spacing_mm", "step_mm", "speed_mm_s",
                     "depth_max_mm", "gain"):
            as_positive_number(getattr(self, name), f"scanner {name}")
        for name in ("depth_min_mm", "z_noise_mm", "linearity_mm", "speckle", "path_repeatability_mm"):
            as_non_negative_number(getattr(self, name), f"scanner {name}")
        if self.depth_min_mm >= self.depth_max_mm:
            raise ValueError(f"scanner depth_min_mm ({self.depth_min_mm}) must be below "
                             f"depth_max_mm ({self.depth_max_mm})")
        if not 0.0 <= self.dropout_fraction < 1.0:
            raise ValueError(f"scanner dropout_fraction must be in [0, 1), got {self.dropout_fraction!r}")
        if not (isinstance(self.intensity_bits, int) and 1 <= self.intensity_bits <= 24):
            raise ValueError(f"scanner intensity_bits must be an integer in [1, 24], got {self.intensity_bits!r}")


@dataclass(frozen=True)
class Profile:
    """One scan line: its index in the sweep, its time stamp (s) and W points (structured float32).

    Parameters
    ----------
    index : int
        The profile's index in the sweep.
    stamp_s : float
        Its time stamp, s.
    points : numpy.ndarray, shape (W,)
        Structured float32 points (x, y, z, intensity).
    reported_pose : numpy.ndarray, shape (4, 4), optional
        Sensor -> base frame B, mm, as the robot's encoder reports it.
    """

    index: int
    stamp_s: float
    points: np.ndarray
    reported_pose: np.ndarray = None    # 4x4 sensor -> base frame B, as the robot's encoder reports it


@dataclass(frozen=True)
class SweepData:
    """A whole sweep: profiles placed by time (start frame), intensity, stamps, reported poses."""

    xyz: np.ndarray               # (H, W, 3) float32, placed by time in the start frame
    intensity: np.ndarray         # (H, W) float32
    stamps_s: np.ndarray          # (H,) s from the first profile
    reported_poses: np.ndarray    # (H, 4, 4) sensor -> B, the encoder's
    start_pose: np.ndarray        # (4, 4) nominal start frame -> B
    direction: int
    orientation_deg: float
    step_mm: float

    def sensor_points(self) -> np.ndarray:
        """(H, W, 3) points in each profile's own sensor frame (y = 0)."""
        xyz = self.xyz.astype(float)
        xyz[..., 1] -= self.direction * self.step_mm * np.arange(xyz.shape[0])[:, None]
        return xyz

    def placed_by_time(self) -> np.ndarray:
        """(H, W, 3) in the base frame B, profiles placed by time at the nominal speed."""
        return _apply(self.start_pose, self.xyz.astype(float))

    def placed_by_pose(self) -> np.ndarray:
        """(H, W, 3) in the base frame B, each profile placed by its reported (encoder) pose."""
        points = self.sensor_points()
        return (np.einsum("hij,hwj->hwi", self.reported_poses[:, :3, :3], points)
                + self.reported_poses[:, None, :3, 3])


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]


class LaserLineScanner:
    """Generates the profiles a laser-line scanner records while swept over a plate."""

    def __init__(self, settings: ScannerSettings | None = None, scanner_to_gls=None, mounting_error=None,
                 chain: MeasurementChain | None = None, robot_seed: int = 0) -> None:
        self.settings = settings if settings is not None else ScannerSettings()
        self.chain = chain if chain is not None else MeasurementChain()
        if isinstance(robot_seed, bool) or not isinstance(robot_seed, int) or robot_seed < 0:
            raise ValueError(f"robot_seed must be a non-negative integer, got {robot_seed!r}")
        self.robot_seed = robot_seed
        self._robot_fields: dict[tuple, object] = {}
        if scanner_to_gls is None:
            # looking straight down from the standoff, travelling towards -y of the head
            scanner_to_gls = pose_matrix(*nominal_mounting(SWEEP_LENGTH_MM, self.settings.standoff_mm))
        self.scanner_to_gls = self._check_pose(scanner_to_gls, "scanner_to_gls")
        self.mounting_error = self._check_pose(np.eye(4) if mounting_error is None else mounting_error,
                                               "mounting_error")
        self.true_scanner_to_gls = self.scanner_to_gls @ self.mounting_error

    @staticmethod
    def _check_pose(matrix, name: str) -> np.ndarray:
        matrix = as_finite_array(matrix, name, ndim=2)
        if matrix.shape != (4, 4):
            raise ValueError(f"{name} must be a 4x4 transform, got shape {matrix.shape}")
        rotation = matrix[:3, :3]
        if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-9) or np.linalg.det(rotation) < 0:
            raise ValueError(f"{name} must hold a proper rotation")
        return matrix.copy()

    def line_x(self) -> np.ndarray:
        """Point positions along the laser line (W,), mm, centred on the sensor axis."""
        s = self.settings
        count = int(math.floor(s.line_length_mm / s.point_spacing_mm + 1e-9)) + 1
        return (np.arange(count) - 0.5 * (count - 1)) * s.point_spacing_mm

    def sweep_parameters(self, length_mm, speed_mm_s=None, step_mm=None) -> tuple[int, float, float]:
        """Profile count, speed and step of a sweep (None: the settings' defaults); ValueError if not positive."""
        length = as_positive_number(length_mm, "length_mm")
        speed = as_positive_number(self.settings.speed_mm_s if speed_mm_s is None else speed_mm_s, "speed_mm_s")
        step = as_positive_number(self.settings.step_mm if step_mm is None else step_mm, "step_mm")
        return int(math.floor(length / step + 1e-9)) + 1, speed, step

    def start_pose(self, length_mm: float, direction: int = 1, orientation_deg: float = 0.0) -> np.ndarray:
        """Nominal sensor pose at the first profile of a sweep (4x4, start frame -> B)."""
        return nominal_start_pose(length_mm, direction, orientation_deg)

    def _path_error(self, seed: int) -> np.ndarray:
        bound = self.settings.path_repeatability_mm
        return np.random.default_rng([seed, _PATH_STREAM]).uniform(-bound, bound, 3)

    def _robot_field(self, component: int, direction: int, orientation_deg: float):
        """Return the robot's repeating error ``component`` for this direction and orientation.

        Components: 0 along, 1 across, 2 height; 3 the line's scale (a number). Drawn once and kept.
        """
        key = (component, direction, orientation_deg)
        if key not in self._robot_fields:
            c = self.chain
            rng = np.random.default_rng([self.robot_seed, _ROBOT_STREAM, component, direction + 1,
                                         _ORIENTATION_STREAM[orientation_deg]])
            if component == 3:
                self._robot_fields[key] = float(c.robot_scale_error * rng.standard_normal())
            elif component == 0:
                self._robot_fields[key] = smooth_field(rng, c.robot_along_error_mm, c.robot_along_correlation_mm)
            else:
                self._robot_fields[key] = smooth_field(rng, c.robot_path_error_mm, c.robot_path_correlation_mm)
        return self._robot_fields[key]

    def _placement(self, seed: int, rows: int, step: float, start: np.ndarray | None = None, direction: int = 1,
                   orientation_deg: float = 0.0, field_shift_mm: np.ndarray | None = None,
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Return the reported travel, true travel, across and height deviation (rows,) of one sweep (mm).

        The reported travel is the robot's timing (what its encoders see); the true travel, across and
        height add what the robot cannot see: per-sweep wander and the errors that repeat per line,
        evaluated where the sensor is in the base frame (less ``field_shift_mm``, B x-y, when given).
        """
        c = self.chain
        nominal = np.arange(rows) * step
        if start is None:
            start = self.start_pose((rows - 1) * step, direction, orientation_deg)
        rng = np.random.default_rng([seed, _CHAIN_STREAM])
        ripple = smooth_process(rng, nominal, c.speed_ripple_mm, c.speed_ripple_correlation_mm)
        across = smooth_process(rng, nominal, c.path_wander_mm, c.path_wander_correlation_mm)
        height = smooth_process(rng, nominal, c.path_wander_mm, c.path_wander_correlation_mm)
        reported = nominal * (1.0 + c.speed_scale_error) + ripple
        true = reported.copy()
        if c.robot_along_wander_mm:
            true += smooth_process(np.random.default_rng([seed, _WANDER_STREAM]), nominal, c.robot_along_wander_mm,
                                   c.path_wander_correlation_mm)
        if c.robot_repeats:
            where = (start[:3, 3] + np.outer(direction * reported, start[:3, 1]))[:, :2]
            if field_shift_mm is not None:
                where = where - field_shift_mm
            true += (self._robot_field(3, direction, orientation_deg) * reported
                     + self._robot_field(0, direction, orientation_deg)(where))
            across = across + self._robot_field(1, direction, orientation_deg)(where)
            height = height + self._robot_field(2, direction, orientation_deg)(where)
        return reported, true, across, height

    def _correlated_speckle(self, seed: int, first: int, count: int, width: int, step: float) -> np.ndarray:
        """Multiplicative speckle (count, width) of rows first .. first + count - 1, continuous across chunks."""
        c = self.chain
        sigma_rows = c.speckle_correlation_mm / math.sqrt(2.0) / step
        sigma_cols = c.speckle_correlation_mm / math.sqrt(2.0) / self.settings.point_spacing_mm
        margin = int(math.ceil(4.0 * sigma_rows)) + 1
        noise = np.stack([np.random.default_rng([seed, _SPECKLE_STREAM, row + 2 ** 20]).standard_normal(width)
                          for row in range(first - margin, first + count + margin)])
        field = gaussian_filter(noise, (sigma_rows, sigma_cols), mode="nearest")[margin:margin + count]
        norm = _kernel_norm(sigma_rows) * _kernel_norm(sigma_cols)
        return np.maximum(1.0 + c.speckle_contrast / norm * field, 0.0)

    def _rows(self, plate: Plate, first: int, count: int, step: float, path_error: np.ndarray,
              placement, direction: int, orientation_deg: float, start: np.ndarray, seed: int,
              rng: np.random.Generator, plane: tuple[np.ndarray, np.ndarray] | None = None,
              ) -> tuple[np.ndarray, np.ndarray]:
        """Measured xyz (count, W, 3), placed by time in the start frame, and intensity (count, W).

        ``plane`` (normal, origin in gls) replaces the plate's plane where the rays end (the stand-still
        acquisition: the plate as the robot-held head sees it in its marking pose).
        """
        s, c = self.settings, self.chain
        x = self.line_x()
        rows = slice(first, first + count)
        _, travel, across, height = (part[rows] for part in placement)
        turn = start[:3, :3]
        # true sensor origin of each profile in B; ray origins and directions of each point
        local = np.column_stack([across, direction * travel, height])
        sensor = start[:3, 3] + local @ turn.T + path_error
        if c.fan_geometry:
            tangent = x / s.standoff_mm
            ray_origin = np.zeros((x.size, 3))
            ray_direction = np.column_stack([tangent, np.zeros_like(x), np.ones_like(x)])
        else:
            tangent = None
            ray_origin = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
            ray_direction = np.tile([0.0, 0.0, 1.0], (x.size, 1))
        ray_origin, ray_direction = ray_origin @ turn.T, ray_direction @ turn.T
        rotation = self.true_scanner_to_gls[:3, :3]
        translation = self.true_scanner_to_gls[:3, 3]
        plane_normal, plane_origin = (plate.normal, plate.origin) if plane is None else plane
        normal = rotation.T @ plane_normal
        origin = rotation.T @ (plane_origin - translation)
        facing = ray_direction @ normal                                    # (W,)
        if np.any(np.abs(facing) < 1e-6):
            raise ValueError("the scanner looks along the plate; no profile can be measured")
        origins = sensor[:, None, :] + ray_origin[None, :, :]               # (count, W, 3)
        depth = ((origin - origins) @ normal) / facing
        hits = origins + depth[..., None] * ray_direction
        uv = plate.to_plate(hits @ rotation.T + translation)
        warp = plate.warp(uv)
        if warp is not None:
            # the surface stands off the plane along its normal: one correction step is plenty
            depth = depth + warp / facing
            hits = origins + depth[..., None] * ray_direction
            uv = plate.to_plate(hits @ rotation.T + translation)
        reflectivity = plate.reflectivity(uv)

        shape = depth.shape
        noise = s.z_noise_mm * rng.standard_normal(shape)
        z = depth + noise + self._linearity(x)[None, :]
        speckle = np.maximum(1.0 + s.speckle * rng.standard_normal(shape, dtype=np.float32), 0.0)
        raw = reflectivity * np.float32(s.gain) * speckle
        if c.speckle_contrast and step > 0.0:
            raw = raw * self._correlated_speckle(seed, first, count, x.size, step).astype(np.float32)
        if c.blooming_mm:
            # saturated light spills along the line into the neighbouring pixels
            excess = np.nan_to_num(np.maximum(raw - 1.0, 0.0))
            raw = raw + gaussian_filter1d(excess, c.blooming_mm / s.point_spacing_mm, axis=1, mode="constant")
        levels = float(2 ** s.intensity_bits - 1)
        intensity = np.round(np.clip(raw, 0.0, 1.0) * levels) / levels
        invalid = (~np.isfinite(reflectivity) | (rng.random(shape, dtype=np.float32) < s.dropout_fraction)
                   | (depth < s.depth_min_mm) | (depth > s.depth_max_mm))
        lateral = c.lateral_linearity_mm * lateral_linearity_shape(x, 0.5 * s.line_length_mm)
        xyz = np.empty(shape + (3,), dtype=np.float32)
        # the sensor reports the point on its pixel's ray at the measured range
        xyz[..., 0] = (x[None, :] if tangent is None else (depth + noise) * tangent[None, :]) + lateral[None, :]
        xyz[..., 1] = (direction * step * np.arange(first, first + count))[:, None]
        xyz[..., 2] = z
        xyz[invalid] = np.nan
        intensity = intensity.astype(np.float32)
        intensity[invalid] = np.nan
        return xyz, intensity

    def _linearity(self, x: np.ndarray) -> np.ndarray:
        """Smooth systematic z error across the line, peak ``linearity_mm``."""
        half = 0.5 * self.settings.line_length_mm
        return self.settings.linearity_mm * np.sin(1.5 * np.pi * x / half)

    def _shifted_start(self, length_mm: float, direction: int, orientation_deg: float, line_offset_mm) -> np.ndarray:
        """Return the sweep's start pose, moved by ``line_offset_mm`` (B x-y) when given."""
        start = self.start_pose(float(length_mm), direction, orientation_deg)
        if line_offset_mm is not None:
            start[:2, 3] += line_offset_mm
        return start

    def _chunks(self, plate, length_mm, speed_mm_s, step_mm, seed, direction=1, orientation_deg=0.0,
                line_offset_mm=None, plate_moved=False):
        rows, speed, step = self.sweep_parameters(length_mm, speed_mm_s, step_mm)
        if direction not in (1, -1):
            raise ValueError(f"direction must be +1 or -1, got {direction!r}")
        if orientation_deg not in ORIENTATIONS_DEG:
            raise ValueError(f"orientation_deg must be {ORIENTATIONS_TEXT}, got {orientation_deg!r}")
        path_error = self._path_error(seed)
        start = self._shifted_start(length_mm, direction, orientation_deg, line_offset_mm)
        placement = self._placement(seed, rows, step, start, direction, orientation_deg,
                                    line_offset_mm if plate_moved else None)
        for number, first in enumerate(range(0, rows, _CHUNK_ROWS)):
            count = min(_CHUNK_ROWS, rows - first)
            rng = np.random.default_rng([seed, number])
            xyz, intensity = self._rows(plate, first, count, step, path_error, placement, direction,
                                        orientation_deg, start, seed, rng)
            reported = np.repeat(start[None], count, axis=0)
            reported[:, :3, 3] += (direction * placement[0][first:first + count])[:, None] * start[:3, 1]
            yield first, step / speed, xyz, intensity, reported

    def standstill_data(self, plate: Plate, profiles: int, seed: int = 0, position_mm=(0.0, 0.5 * SWEEP_LENGTH_MM, 0.0),
                        marking_pose_error: tuple[float, float, float] = (0.0, 0.0, 0.0),
                        period_s: float | None = None) -> SweepData:
        """Take ``profiles`` profiles with the robot standing still at the marking pose.

        ``profiles`` profiles taken with the robot standing still at the marking pose (see :class:`SweepData`;
        ``step_mm`` 0, every reported pose the same).

        The sensor stands at ``position_mm`` of B, orientation 0. No travel, so none of the robot's
        path errors (repeatability offset, wander, the errors repeating per line) enters; what the
        robot-held head's marking pose is off by (``marking_pose_error``: height towards the head,
        tilts about gls x and y, as ``Plate.marking_pose_error``) the scanner, held by the same
        flange, sees as the plate moved: it measures the plate where the head marks it. Noise, range
        linearity, speckle and dropouts as in a sweep; a random stream of its own (``seed``). One
        profile every ``period_s`` (None: the settings' step over their speed).
        """
        if isinstance(profiles, bool) or not isinstance(profiles, (int, np.integer)) or profiles < 1:
            raise ValueError(f"profiles must be a positive integer, got {profiles!r}")
        profiles = int(profiles)
        position = as_finite_array(position_mm, "position_mm", ndim=1)
        if position.shape != (3,):
            raise ValueError(f"position_mm must be a 3-vector, got {position.tolist()}")
        height, tilt_x, tilt_y = (float(value) for value in marking_pose_error)
        base_tilt_x, base_tilt_y = plate.settings.tilt_x_rad, plate.settings.tilt_y_rad
        rotation, origin = plate_frame(base_tilt_x + tilt_x, base_tilt_y + tilt_y, plate.settings.delta_d_mm - height)
        start = np.eye(4)
        start[:3, 3] = position
        still = np.zeros(profiles)
        placement = (still, still, still, still)
        rng = np.random.default_rng([seed, _STANDSTILL_STREAM])
        # the step only sizes the correlated speckle, which a sensor standing still does not resample: off
        xyz, intensity = self._rows(plate, 0, profiles, 0.0, np.zeros(3), placement, 1, 0.0, start, seed, rng,
                                    plane=(rotation[:, 2].copy(), origin))
        period_s = (self.settings.step_mm / self.settings.speed_mm_s if period_s is None
                    else as_positive_number(period_s, "period_s"))
        return SweepData(xyz, intensity, np.arange(profiles) * period_s, np.repeat(start[None], profiles, axis=0),
                         start, 1, 0.0, 0.0)

    def standstill(self, plate: Plate, profiles: int, seed: int = 0, position_mm=(0.0, 0.5 * SWEEP_LENGTH_MM, 0.0),
                   marking_pose_error: tuple[float, float, float] = (0.0, 0.0, 0.0),
                   period_s: float | None = None) -> Iterator[Profile]:
        """Yield the profiles of :meth:`standstill_data` one by one.

        In the sensor frame, y = 0; the reported pose is where the sensor stands.
        """
        data = self.standstill_data(plate, profiles, seed, position_mm, marking_pose_error, period_s)
        for row in range(data.xyz.shape[0]):
            points = np.empty(data.xyz.shape[1], dtype=PROFILE_DTYPE)
            points["x"], points["y"], points["z"] = data.xyz[row, :, 0], data.xyz[row, :, 1], data.xyz[row, :, 2]
            points["intensity"] = data.intensity[row]
            yield Profile(row, float(data.stamps_s[row]), points, data.reported_poses[row])

    def sweep(self, plate: Plate, length_mm: float = SWEEP_LENGTH_MM, speed_mm_s: float | None = None,
              step_mm: float | None = None, seed: int = 0, direction: int = 1,
              orientation_deg: float = 0.0) -> Iterator[Profile]:
        """Profiles of one sweep over ``length_mm`` at ``speed_mm_s``, one every ``step_mm``, in order."""
        for first, period, xyz, intensity, reported in self._chunks(plate, length_mm, speed_mm_s, step_mm, seed,
                                                                    direction, orientation_deg):
            for row in range(xyz.shape[0]):
                points = np.empty(xyz.shape[1], dtype=PROFILE_DTYPE)
                points["x"], points["y"], points["z"] = xyz[row, :, 0], xyz[row, :, 1], xyz[row, :, 2]
                points["intensity"] = intensity[row]
                yield Profile(first + row, (first + row) * period, points, reported[row])

    def sweep_cloud(self, plate: Plate, length_mm: float = SWEEP_LENGTH_MM, speed_mm_s: float | None = None,
                    step_mm: float | None = None, seed: int = 0, direction: int = 1,
                    orientation_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Return the whole sweep as an organized cloud placed by time.

        xyz (H, W, 3) and intensity (H, W), float32, in the sweep's start frame (B for the default
        sweep). Same numbers as :meth:`sweep`.
        """
        data = self.sweep_data(plate, length_mm, speed_mm_s, step_mm, seed, direction, orientation_deg)
        return data.xyz, data.intensity

    def sweep_data(self, plate: Plate, length_mm: float = SWEEP_LENGTH_MM, speed_mm_s: float | None = None,
                   step_mm: float | None = None, seed: int = 0, direction: int = 1,
                   orientation_deg: float = 0.0, *, line_offset_mm=None, plate_moved: bool = False) -> SweepData:
        """Return the whole sweep with its stamps and reported poses (see :class:`SweepData`).

        ``line_offset_mm`` (B x, y; None: the plan's line) moves the programmed line: the sensor
        sweeps a line shifted by it and the robot reports it there. The robot's repeating error is a
        function of where the arm is, so it is evaluated on the shifted line, unless ``plate_moved``:
        then the offset stands for the plate moved by ``-line_offset_mm`` in its fixture under the
        plan's own line (the arm runs its unshifted line, the field is evaluated there; the plate's
        marks are met where a shifted line would meet them). Grid-plate self-calibration
        (``registration/self_calibration.py``) measures with both.
        """
        if line_offset_mm is not None:
            line_offset_mm = as_finite_array(line_offset_mm, "line_offset_mm", ndim=1)
            if line_offset_mm.shape != (2,):
                raise ValueError(f"line_offset_mm must be two numbers (B x, y), got {line_offset_mm.tolist()}")
        elif plate_moved:
            raise ValueError("plate_moved needs line_offset_mm")
        parts = list(self._chunks(plate, length_mm, speed_mm_s, step_mm, seed, direction, orientation_deg,
                                  line_offset_mm, plate_moved))
        rows = sum(part[2].shape[0] for part in parts)
        _, speed, step = self.sweep_parameters(length_mm, speed_mm_s, step_mm)
        return SweepData(np.concatenate([part[2] for part in parts]), np.concatenate([part[3] for part in parts]),
                         np.arange(rows) * step / speed, np.concatenate([part[4] for part in parts]),
                         self._shifted_start(length_mm, direction, orientation_deg, line_offset_mm), direction,
                         float(orientation_deg), step)

    def to_gls(self, points) -> np.ndarray:
        """Base-frame points (..., 3) to the gls frame with the CAD mounting (what a calibration knows)."""
        points = np.asarray(points, dtype=float)
        return points @ self.scanner_to_gls[:3, :3].T + self.scanner_to_gls[:3, 3]


def _kernel_norm(sigma: float) -> float:
    """Root sum of squares of the discrete Gaussian kernel (unit-variance scaling of filtered noise)."""
    if sigma <= 0.0:
        return 1.0
    size = 2 * int(math.ceil(4.0 * sigma)) + 1
    impulse = np.zeros(size)
    impulse[size // 2] = 1.0
    return math.sqrt(float(np.sum(gaussian_filter1d(impulse, sigma, mode="constant") ** 2)))
