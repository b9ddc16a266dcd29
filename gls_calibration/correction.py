"""Corrected galvo setpoints: nominal inverse kinematics applied to a model-corrected target.

For a desired point ``Q`` the head is commanded to ``K = Q + sum_i model_i(Q)``: every model
predicts the deviation ``delta = Q - P`` that was measured (the i-th one while the first i-1
corrections were already commanded), so successive calibrations add up.

Calibrated region: the axis-aligned box of the training targets. The targets form a rectangular
grid, whose convex hull is that box, and clamping to a box is exact and cheap. Outside it the
models are not trusted to extrapolate: they are evaluated at the nearest point of the box and the
correction fades to zero with a raised cosine over ``taper_mm`` beyond the boundary, so it stays
continuous, bounded by its values on the boundary, and finite however far away the point is.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
import math
from typing import Any, Optional

import numpy as np

from gls_calibration.kinematics import HeadGeometry, inverse
from gls_calibration.rbf import DeviationModel
from gls_calibration.validation import as_coordinate_arrays, as_finite_array, as_non_negative_number, as_points


@dataclass(frozen=True)
class CalibratedRegion:
    """Axis-aligned box (mm, gls frame) where the deviation models were trained."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float

    def __post_init__(self) -> None:
        values = [float(getattr(self, name)) for name in ("x_min", "x_max", "y_min", "y_max")]
        if not all(math.isfinite(value) for value in values):
            raise ValueError(f"calibrated region bounds must be finite, got {values}")
        if values[0] > values[1] or values[2] > values[3]:
            raise ValueError(f"calibrated region is empty: x [{values[0]}, {values[1]}], y [{values[2]}, {values[3]}]")
        for name, value in zip(("x_min", "x_max", "y_min", "y_max"), values):
            object.__setattr__(self, name, value)

    @classmethod
    def from_points(cls, points) -> "CalibratedRegion":
        """Bounding box of training targets (N, 2)."""
        points = as_points(points, "points", 2)
        low, high = points.min(axis=0), points.max(axis=0)
        return cls(float(low[0]), float(high[0]), float(low[1]), float(high[1]))

    def contains(self, x, y) -> np.ndarray:
        """True for points inside the box or on its boundary (1e-9 mm tolerance)."""
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        tolerance = 1e-9
        return ((x >= self.x_min - tolerance) & (x <= self.x_max + tolerance)
                & (y >= self.y_min - tolerance) & (y <= self.y_max + tolerance))

    def clamp(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Nearest point of the box."""
        return (np.clip(np.asarray(x, dtype=float), self.x_min, self.x_max),
                np.clip(np.asarray(y, dtype=float), self.y_min, self.y_max))

    def intersection(self, other: "CalibratedRegion") -> "CalibratedRegion":
        """Part covered by both boxes (ValueError if they do not overlap)."""
        return CalibratedRegion(max(self.x_min, other.x_min), min(self.x_max, other.x_max),
                                max(self.y_min, other.y_min), min(self.y_max, other.y_max))

    def to_dict(self) -> dict:
        """Plain-number description (YAML-ready)."""
        return {"type": "box", "x_min": self.x_min, "x_max": self.x_max, "y_min": self.y_min, "y_max": self.y_max}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "CalibratedRegion":
        """Rebuild a region written by :meth:`to_dict`."""
        if not isinstance(data, Mapping) or data.get("type") != "box":
            raise ValueError(f"calibrated region must be a mapping with type 'box', got {data!r}")
        missing = [key for key in ("x_min", "x_max", "y_min", "y_max") if key not in data]
        if missing:
            raise ValueError(f"calibrated region lacks key(s) {', '.join(missing)}")
        return cls(data["x_min"], data["x_max"], data["y_min"], data["y_max"])


@dataclass(frozen=True)
class CorrectedSetpoints:
    """Corrected command per point: target ``x``, ``y`` actually commanded (mm), joint setpoints and flags."""

    x: np.ndarray
    y: np.ndarray
    alpha_x: np.ndarray
    alpha_y: np.ndarray
    focus_shift: np.ndarray
    inside_calibrated_field: np.ndarray
    within_limits: np.ndarray


def taper_weight(distance_mm: np.ndarray, taper_mm: float) -> np.ndarray:
    """Raised-cosine fade: 1 at the boundary, 0 from ``taper_mm`` beyond it (a step when taper is 0)."""
    distance_mm = np.asarray(distance_mm, dtype=float)
    if taper_mm == 0.0:
        return (distance_mm <= 0.0).astype(float)
    fraction = np.clip(distance_mm / taper_mm, 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(math.pi * fraction))


class Correction:
    """Setpoint correction from a sequence of deviation models (applied additively).

    ``models`` are callables ``(M, 2) -> (M, 2)`` (e.g. :class:`gls_calibration.rbf.OLSRBFNetwork`);
    ``calibrated_region`` is required when there is at least one model. Without models the
    correction is the nominal kinematics and no point counts as inside the calibrated field.
    """

    def __init__(self, geometry: HeadGeometry, models: Sequence[DeviationModel] = (),
                 calibrated_region: Optional[CalibratedRegion] = None, taper_mm: float = 10.0) -> None:
        if not isinstance(geometry, HeadGeometry):
            raise ValueError(f"geometry must be a HeadGeometry, got {type(geometry).__name__}")
        models = tuple(models)
        for index, model in enumerate(models):
            if not callable(model):
                raise ValueError(f"models[{index}] is not callable")
        if models and calibrated_region is None:
            raise ValueError("calibrated_region is required when models are given")
        if calibrated_region is not None and not isinstance(calibrated_region, CalibratedRegion):
            raise ValueError(f"calibrated_region must be a CalibratedRegion, got {type(calibrated_region).__name__}")
        self.geometry = geometry
        self.models = models
        self.calibrated_region = calibrated_region
        self.taper_mm = as_non_negative_number(taper_mm, "taper_mm")

    def with_model(self, model: DeviationModel, region: Optional[CalibratedRegion] = None) -> "Correction":
        """A new correction with ``model`` added after the existing ones.

        The region becomes the overlap of the current one and ``region`` (either may be absent,
        not both when this is the first model).
        """
        if region is None:
            combined = self.calibrated_region
        elif self.calibrated_region is None:
            combined = region
        else:
            combined = self.calibrated_region.intersection(region)
        return Correction(self.geometry, self.models + (model,), combined, self.taper_mm)

    def deviation(self, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Summed, clamped and tapered model correction (dx, dy) in mm and the inside flags."""
        x, y, _ = as_coordinate_arrays(x, y)
        if not self.models:
            zeros = np.zeros_like(x)
            return zeros, zeros.copy(), np.zeros(x.shape, dtype=bool)
        region = self.calibrated_region
        inside = region.contains(x, y)
        clamped_x, clamped_y = region.clamp(x, y)
        weight = taper_weight(np.hypot(x - clamped_x, y - clamped_y), self.taper_mm)
        points = np.column_stack([clamped_x, clamped_y])
        total = np.zeros_like(points)
        for model in self.models:
            total += as_finite_array(model(points), "model output", ndim=2)
        return weight * total[:, 0], weight * total[:, 1], inside

    def correct(self, x, y, z=None) -> CorrectedSetpoints:
        """Corrected setpoints for targets (x, y[, z]) in mm (gls frame); z defaults to the work plane."""
        x, y, z = as_coordinate_arrays(x, y, z)
        delta_x, delta_y, inside = self.deviation(x, y)
        commanded_x, commanded_y = x + delta_x, y + delta_y
        joints = inverse(self.geometry, commanded_x, commanded_y, z)
        # The height itself must lie in the focus range too, not only the focus shift it needs.
        within = joints.within_limits & (np.abs(z) <= self.geometry.focus_range_mm)
        return CorrectedSetpoints(commanded_x, commanded_y, joints.alpha_x, joints.alpha_y, joints.focus_shift,
                                  inside, within)
