"""The stored U map: the expanded uncertainty of a corrected target's landing on a regular grid.

U (mm) is a 95 % coverage RADIUS of the 2-D landing position relative to the best-fit rigid frame
of the field; ``COVERAGE_FACTOR`` = sqrt(-2 ln 0.05) = 2.448 expands the per-axis standard
uncertainty (an isotropic 2-D Gaussian's 95 % radius; k = 2 per axis would cover 86 %). The name
served and stored stays ``uncertainty_k2_mm``. The budget that fills the grid:
``gls_calibration.calibration.uncertainty``. Between nodes U is bilinear; outside the grid NaN.
"""
from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass
import math
from typing import Any, Mapping

import numpy as np

COVERAGE_PROBABILITY = 0.95
COVERAGE_FACTOR = math.sqrt(-2.0 * math.log(1.0 - COVERAGE_PROBABILITY))   # 2.4477
UNCERTAINTY_KEY = "uncertainty"
_TOLERANCE_MM = 1e-9     # a point this close outside the grid counts as on it


@dataclass(frozen=True)
class UncertaintyGrid:
    """U (k = 2.448, 95 % radius, mm) on the nodes ``x_mm`` (nx) x ``y_mm`` (ny), rows along y.

    Parameters
    ----------
    x_mm : array_like, shape (nx,)
        Node positions along x, gls frame, mm.
    y_mm : array_like, shape (ny,)
        Node positions along y, mm.
    u_k2_mm : array_like, shape (ny, nx)
        U at the nodes, mm.

    Raises
    ------
    ValueError
        If an axis is not 2 or more finite numbers increasing strictly, or ``u_k2_mm`` has not the
        shape (ny, nx), is not finite or holds negative values.

    Examples
    --------
    >>> grid = UncertaintyGrid([0.0, 10.0], [0.0, 10.0], [[0.01, 0.02], [0.03, 0.04]])
    >>> grid.at_point(5.0, 5.0), grid.at([0.0, 20.0], [10.0, 0.0]).tolist()
    (0.025, [0.03, nan])
    """

    x_mm: np.ndarray
    y_mm: np.ndarray
    u_k2_mm: np.ndarray     # (ny, nx)

    def __post_init__(self) -> None:
        """Validate the grid and keep what the one-target lookup needs (ValueError if bad)."""
        for name in ("x_mm", "y_mm", "u_k2_mm"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=float))
        check_grid(self.x_mm, self.y_mm, self.u_k2_mm, UNCERTAINTY_KEY)
        # plain lists for the one-target path (bisect on a list beats numpy per call)
        object.__setattr__(self, "_x_list", self.x_mm.tolist())
        object.__setattr__(self, "_y_list", self.y_mm.tolist())
        spacing = (np.diff(self.x_mm), np.diff(self.y_mm))
        object.__setattr__(self, "_uniform",
                           bool(all(np.allclose(step, step.mean(), rtol=1e-9, atol=0.0) for step in spacing)))
        # Python floats: numpy scalars would make every step of the one-target path ~10x slower
        object.__setattr__(self, "_scale", (float((self.x_mm.size - 1) / (self.x_mm[-1] - self.x_mm[0])),
                                            float((self.y_mm.size - 1) / (self.y_mm[-1] - self.y_mm[0]))))
        object.__setattr__(self, "_flat", np.ascontiguousarray(self.u_k2_mm).ravel())
        # Everything the one-target path needs in one tuple: one look-up per call instead of a dozen
        # (with min/max calls, they were most of its 1.2 us).
        xs, ys = self._x_list, self._y_list
        object.__setattr__(self, "_point", (
            xs[0] - _TOLERANCE_MM, xs[-1] + _TOLERANCE_MM, ys[0] - _TOLERANCE_MM, ys[-1] + _TOLERANCE_MM,
            xs[0], ys[0], *self._scale, len(xs) - 1.0, len(ys) - 1.0, len(xs) - 2, len(ys) - 2, len(xs),
            self._flat.tolist()))

    def _uniform_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear on nodes equally spaced (the grids the package writes): cell index by arithmetic."""
        xs, ys = self.x_mm, self.y_mm
        nx = xs.size
        fx = (x - xs[0]) * ((nx - 1) / (xs[-1] - xs[0]))
        fy = (y - ys[0]) * ((ys.size - 1) / (ys[-1] - ys[0]))
        np.clip(fx, 0.0, nx - 1, out=fx)
        np.clip(fy, 0.0, ys.size - 1, out=fy)
        i = np.minimum(fx.astype(np.intp), nx - 2)
        j = np.minimum(fy.astype(np.intp), ys.size - 2)
        fx -= i
        fy -= j
        index = j * nx + i
        flat = self._flat
        low = flat.take(index)
        low += fx * (flat.take(index + 1) - low)
        index += nx
        high = flat.take(index)
        high += fx * (flat.take(index + 1) - high)
        low += fy * (high - low)
        return low

    def at_point(self, x: float, y: float) -> float:
        """U at one point (the same value as :meth:`at`), in scalar arithmetic."""
        (x_low, x_high, y_low, y_high, x_first, y_first, scale_x, scale_y, end_x, end_y, last_x, last_y, nx,
         flat) = self._point
        if not (x_low <= x <= x_high and y_low <= y <= y_high):
            return math.nan
        if not self._uniform:
            return self._bisected_at(x, y)
        # the arithmetic of _uniform_at, step by step (the same floats); comparisons, not min/max calls
        fx = (x - x_first) * scale_x
        fx = 0.0 if fx < 0.0 else end_x if fx > end_x else fx
        fy = (y - y_first) * scale_y
        fy = 0.0 if fy < 0.0 else end_y if fy > end_y else fy
        i, j = int(fx), int(fy)
        if i > last_x:
            i = last_x
        if j > last_y:
            j = last_y
        tx = fx - i
        index = j * nx + i
        low = flat[index]
        bottom = low + tx * (flat[index + 1] - low)
        index += nx
        low = flat[index]
        top = low + tx * (flat[index + 1] - low)
        return bottom + (fy - j) * (top - bottom)

    def _bisected_at(self, x: float, y: float) -> float:
        """:meth:`at_point` inside the grid's box when the nodes are not equally spaced."""
        xs, ys = self._x_list, self._y_list
        last_x, last_y = len(xs) - 2, len(ys) - 2
        x, y = min(max(x, xs[0]), xs[-1]), min(max(y, ys[0]), ys[-1])
        i = min(max(bisect_right(xs, x) - 1, 0), last_x)
        j = min(max(bisect_right(ys, y) - 1, 0), last_y)
        tx, ty = (x - xs[i]) / (xs[i + 1] - xs[i]), (y - ys[j]) / (ys[j + 1] - ys[j])
        flat, index = self._point[-1], j * len(xs) + i      # U once, as the uniform path reads it
        low, high = flat[index], flat[index + len(xs)]
        bottom = low + tx * (flat[index + 1] - low)
        top = high + tx * (flat[index + len(xs) + 1] - high)
        return bottom + ty * (top - bottom)

    def at(self, x, y) -> np.ndarray:
        """U at points (x, y) by bilinear interpolation; NaN outside the grid (1e-9 mm tolerance)."""
        return bilinear(self.x_mm, self.y_mm, self.u_k2_mm, np.asarray(x, float), np.asarray(y, float))

    def inside_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Return U at points of the calibrated field, clamped to the grid's box (no NaN).

        The fast cell lookup serves when the nodes are equally spaced (the documented evaluator
        clamps the same way).
        """
        if self._uniform:
            return self._uniform_at(np.asarray(x, float), np.asarray(y, float))
        x = np.clip(np.asarray(x, float), self.x_mm[0], self.x_mm[-1])
        y = np.clip(np.asarray(y, float), self.y_mm[0], self.y_mm[-1])
        return bilinear(self.x_mm, self.y_mm, self.u_k2_mm, x, y)

    def field_figures(self, central_mm: float = 150.0) -> tuple[float, float, float]:
        """(largest U over the grid, largest U over the centred ``central_mm`` square, median U), mm."""
        gx, gy = np.meshgrid(self.x_mm, self.y_mm)
        centre_x, centre_y = 0.5 * (self.x_mm[0] + self.x_mm[-1]), 0.5 * (self.y_mm[0] + self.y_mm[-1])
        half = central_mm / 2.0 + 1e-9
        central = (np.abs(gx - centre_x) <= half) & (np.abs(gy - centre_y) <= half)
        u = self.u_k2_mm
        return float(u.max()), float(u[central].max()) if central.any() else math.nan, float(np.median(u))

    def to_dict(self) -> dict:
        """Plain form of the grid for the calibration file."""
        return {"coverage_probability": COVERAGE_PROBABILITY, "coverage_factor": COVERAGE_FACTOR,
                "x_mm": self.x_mm.tolist(), "y_mm": self.y_mm.tolist(), "u_k2_mm": self.u_k2_mm.tolist()}

    @classmethod
    def from_dict(cls, data: Any, key: str = UNCERTAINTY_KEY) -> "UncertaintyGrid":
        """Return the grid of a record's ``uncertainty`` mapping; ValueError naming ``key`` and the field."""
        if not isinstance(data, Mapping):
            raise ValueError(f"key '{key}' must be a mapping")
        for name in ("x_mm", "y_mm", "u_k2_mm"):
            if name not in data:
                raise ValueError(f"missing key '{key}.{name}'")
        try:
            x = np.asarray(data["x_mm"], dtype=float)
            y = np.asarray(data["y_mm"], dtype=float)
            u = np.asarray(data["u_k2_mm"], dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"key '{key}': x_mm, y_mm and u_k2_mm must be numbers") from None
        return cls(x, y, u)


def check_grid(x: np.ndarray, y: np.ndarray, u: np.ndarray, key: str) -> None:
    """Raise ValueError naming ``key`` unless the axes and U form a valid grid.

    The axes must be increasing finite lists of 2+ nodes and U a finite non-negative (ny, nx)
    array.
    """
    for name, axis in (("x_mm", x), ("y_mm", y)):
        if axis.ndim != 1 or axis.size < 2 or not np.all(np.isfinite(axis)):
            raise ValueError(f"key '{key}.{name}' must be a list of 2 or more finite numbers")
        if np.any(np.diff(axis) <= 0.0):
            raise ValueError(f"key '{key}.{name}' must increase strictly (monotonic axis)")
    if u.shape != (y.size, x.size):
        raise ValueError(f"key '{key}.u_k2_mm' must have shape ({y.size}, {x.size}) (rows along y), got {u.shape}")
    if not np.all(np.isfinite(u)):
        raise ValueError(f"key '{key}.u_k2_mm' holds NaN or infinite values")
    if np.any(u < 0.0):
        raise ValueError(f"key '{key}.u_k2_mm' holds negative values")


def bilinear(x_nodes: np.ndarray, y_nodes: np.ndarray, values: np.ndarray, x: np.ndarray,
             y: np.ndarray) -> np.ndarray:
    """``values`` (ny, nx) interpolated bilinearly at (x, y); NaN outside the nodes' box."""
    tolerance = 1e-9
    inside = (x >= x_nodes[0] - tolerance) & (x <= x_nodes[-1] + tolerance) \
        & (y >= y_nodes[0] - tolerance) & (y <= y_nodes[-1] + tolerance)
    xc = np.clip(x, x_nodes[0], x_nodes[-1])
    yc = np.clip(y, y_nodes[0], y_nodes[-1])
    i = np.clip(np.searchsorted(x_nodes, xc, side="right") - 1, 0, x_nodes.size - 2)
    j = np.clip(np.searchsorted(y_nodes, yc, side="right") - 1, 0, y_nodes.size - 2)
    tx = (xc - x_nodes[i]) / (x_nodes[i + 1] - x_nodes[i])
    ty = (yc - y_nodes[j]) / (y_nodes[j + 1] - y_nodes[j])
    result = (values[j, i] * (1.0 - tx) * (1.0 - ty) + values[j, i + 1] * tx * (1.0 - ty)
              + values[j + 1, i] * (1.0 - tx) * ty + values[j + 1, i + 1] * tx * ty)
    return np.where(inside, result, np.nan)
