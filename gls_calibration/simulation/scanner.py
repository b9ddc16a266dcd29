"""Simulated laser-line scanner swept over the plate by the robot.

Scanner frame (the sensor's pose at the start of a sweep): x along the laser line (0 on the
sensor axis), y along the travel direction (the distance travelled), z along the viewing
direction from the sensor towards the plate, so z is the measured distance (about 325 mm).
Right-handed. Every profile holds W points ``x, y, z, intensity`` (float32) at a fixed spacing
along the line; invalid points (off the plate, out of range, dropouts) are NaN in every field.

The scanner's pose relative to the head comes from CAD (``scanner_to_gls``, 4x4); the true
mounting may differ by a small unknown error (``mounting_error``, applied in the scanner frame),
and each sweep's path may be off by the robot's repeatability. Measurement rays are modelled
parallel to z (the fan angle of the line is neglected).

Noise model: z noise (Gaussian), a smooth linearity error across the line, intensity =
reflectivity * gain * speckle (multiplicative Gaussian, clipped at 0), saturation at 1.0 then
quantisation to ``intensity_bits``, and random dropouts.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from gls_calibration.simulation.plate import Plate
from gls_calibration.validation import as_finite_array, as_non_negative_number, as_positive_number

PROFILE_DTYPE = np.dtype([("x", np.float32), ("y", np.float32), ("z", np.float32), ("intensity", np.float32)])
_CHUNK_ROWS = 128
_PATH_STREAM = 2 ** 31 - 1      # random stream of the robot path error, apart from the chunk streams


def pose_matrix(xyz_mm, rpy_rad) -> np.ndarray:
    """4x4 transform from a translation (mm) and roll, pitch, yaw (rad, fixed axes x, y, z)."""
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler("xyz", as_finite_array(rpy_rad, "rpy_rad", ndim=1)).as_matrix()
    matrix[:3, 3] = as_finite_array(xyz_mm, "xyz_mm", ndim=1)
    return matrix


@dataclass(frozen=True)
class ScannerSettings:
    """Laser-line scanner and sweep settings (mm, s)."""

    standoff_mm: float = 325.0
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
        for name in ("standoff_mm", "line_length_mm", "point_spacing_mm", "step_mm", "speed_mm_s",
                     "depth_max_mm", "gain"):
            as_positive_number(getattr(self, name), f"scanner {name}")
        for name in ("depth_min_mm", "z_noise_mm", "linearity_mm", "speckle", "path_repeatability_mm"):
            as_non_negative_number(getattr(self, name), f"scanner {name}")
        if self.depth_min_mm >= self.depth_max_mm:
            raise ValueError(f"scanner depth_min_mm ({self.depth_min_mm}) must be below depth_max_mm ({self.depth_max_mm})")
        if not 0.0 <= self.dropout_fraction < 1.0:
            raise ValueError(f"scanner dropout_fraction must be in [0, 1), got {self.dropout_fraction!r}")
        if not (isinstance(self.intensity_bits, int) and 1 <= self.intensity_bits <= 24):
            raise ValueError(f"scanner intensity_bits must be an integer in [1, 24], got {self.intensity_bits!r}")


@dataclass(frozen=True)
class Profile:
    """One scan line: its index in the sweep, its time stamp (s) and W points (structured float32)."""

    index: int
    stamp_s: float
    points: np.ndarray


class LaserLineScanner:
    """Generates the profiles a laser-line scanner records while swept over a plate."""

    def __init__(self, settings: ScannerSettings | None = None, scanner_to_gls=None, mounting_error=None) -> None:
        self.settings = settings if settings is not None else ScannerSettings()
        if scanner_to_gls is None:
            # looking straight down from the standoff, travelling towards -y of the head
            scanner_to_gls = pose_matrix([0.0, 100.0, self.settings.standoff_mm], [math.pi, 0.0, 0.0])
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

    def _path_error(self, seed: int) -> np.ndarray:
        bound = self.settings.path_repeatability_mm
        return np.random.default_rng([seed, _PATH_STREAM]).uniform(-bound, bound, 3)

    def _rows(self, plate: Plate, first: int, count: int, step: float, path_error: np.ndarray,
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Measured xyz (count, W, 3) and intensity (count, W) of profiles first .. first + count - 1."""
        s = self.settings
        x = self.line_x()
        y = (first + np.arange(count)) * step
        rotation = self.true_scanner_to_gls[:3, :3]
        translation = self.true_scanner_to_gls[:3, 3]
        # the plate plane in the true scanner frame; the ray from (x, y, 0) + error along z meets it at
        # z = z0 + zx x + zy y, an affine map, and so are the plate coordinates of the hit point
        normal = rotation.T @ plate.normal
        origin = rotation.T @ (plate.origin - translation)
        if abs(normal[2]) < 1e-6:
            raise ValueError("the scanner looks along the plate; no profile can be measured")
        z0 = normal @ (origin - path_error) / normal[2]
        zx, zy = -normal[0] / normal[2], -normal[1] / normal[2]
        depth = z0 + zx * x[None, :] + zy * y[:, None]
        hit_origin = rotation @ (path_error + np.array([0.0, 0.0, z0])) + translation
        hit_x = rotation @ np.array([1.0, 0.0, zx])
        hit_y = rotation @ np.array([0.0, 1.0, zy])
        uv0, uvx, uvy = plate.to_plate(hit_origin), hit_x @ plate.rotation[:, :2], hit_y @ plate.rotation[:, :2]
        uv = uv0 + x[None, :, None] * uvx + y[:, None, None] * uvy
        reflectivity = plate.reflectivity(uv)

        shape = depth.shape
        z = depth + s.z_noise_mm * rng.standard_normal(shape) + self._linearity(x)[None, :]
        speckle = np.maximum(1.0 + s.speckle * rng.standard_normal(shape, dtype=np.float32), 0.0)
        levels = float(2 ** s.intensity_bits - 1)
        intensity = np.round(np.clip(reflectivity * np.float32(s.gain) * speckle, 0.0, 1.0) * levels) / levels
        invalid = (~np.isfinite(reflectivity) | (rng.random(shape, dtype=np.float32) < s.dropout_fraction)
                   | (depth < s.depth_min_mm) | (depth > s.depth_max_mm))
        xyz = np.empty(shape + (3,), dtype=np.float32)
        xyz[..., 0] = x[None, :]
        xyz[..., 1] = y[:, None]
        xyz[..., 2] = z
        xyz[invalid] = np.nan
        intensity = intensity.astype(np.float32)
        intensity[invalid] = np.nan
        return xyz, intensity

    def _linearity(self, x: np.ndarray) -> np.ndarray:
        """Smooth systematic z error across the line, peak ``linearity_mm``."""
        half = 0.5 * self.settings.line_length_mm
        return self.settings.linearity_mm * np.sin(1.5 * np.pi * x / half)

    def _chunks(self, plate, length_mm, speed_mm_s, step_mm, seed):
        rows, speed, step = self.sweep_parameters(length_mm, speed_mm_s, step_mm)
        path_error = self._path_error(seed)
        for number, first in enumerate(range(0, rows, _CHUNK_ROWS)):
            count = min(_CHUNK_ROWS, rows - first)
            rng = np.random.default_rng([seed, number])
            xyz, intensity = self._rows(plate, first, count, step, path_error, rng)
            yield first, step / speed, xyz, intensity

    def sweep(self, plate: Plate, length_mm: float = 200.0, speed_mm_s: float | None = None,
              step_mm: float | None = None, seed: int = 0) -> Iterator[Profile]:
        """Profiles of one sweep over ``length_mm`` at ``speed_mm_s``, one every ``step_mm``, in order."""
        for first, period, xyz, intensity in self._chunks(plate, length_mm, speed_mm_s, step_mm, seed):
            for row in range(xyz.shape[0]):
                points = np.empty(xyz.shape[1], dtype=PROFILE_DTYPE)
                points["x"], points["y"], points["z"] = xyz[row, :, 0], xyz[row, :, 1], xyz[row, :, 2]
                points["intensity"] = intensity[row]
                yield Profile(first + row, (first + row) * period, points)

    def sweep_cloud(self, plate: Plate, length_mm: float = 200.0, speed_mm_s: float | None = None,
                    step_mm: float | None = None, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """The whole sweep as an organized cloud: xyz (H, W, 3) and intensity (H, W), float32, scanner frame.

        Same numbers as :meth:`sweep` with the same arguments.
        """
        parts = list(self._chunks(plate, length_mm, speed_mm_s, step_mm, seed))
        return (np.concatenate([part[2] for part in parts]), np.concatenate([part[3] for part in parts]))

    def to_gls(self, points) -> np.ndarray:
        """Scanner-frame points (..., 3) to the gls frame with the CAD mounting (what a calibration knows)."""
        points = np.asarray(points, dtype=float)
        return points @ self.scanner_to_gls[:3, :3].T + self.scanner_to_gls[:3, 3]
