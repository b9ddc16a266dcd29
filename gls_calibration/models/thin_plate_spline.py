"""The thin-plate spline deviation model: exact (or smoothed) interpolation of the training corrections."""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Optional

import cv2
import numpy as np

from gls_calibration.common.validation import (as_matching_points, as_non_negative_number, as_points,
                                               require_key, require_type)
from gls_calibration.models import tps_tiles
from gls_calibration.models.evaluation_blocks import (BLOCK_ROWS, TILED_MIN_ROWS, SMALL_BATCH, TILES_LOCK, query_points,
                                                      rows_of_two, scratch)

_TINY = np.finfo(float).tiny   # r = 0 in the kernel: tiny * ln(tiny) is 0
# Offset added to every squared distance of a large batch, in units of 1 + max |c|^2 (mm^2): 64 float
# steps, several times the round-off of |p|^2 + |c|^2 - 2 p.c where p meets a centre, so r^2 stays
# positive without a clamping pass (rows that still fail are recomputed from plain differences). It
# moves the spline by ~1e-12 mm (the weights sum to zero; test_rbf checks against the formula).
_OFFSET_PER_SQUARED_MM = 64 * np.finfo(float).eps


def tps_kernel(squared_distance: np.ndarray) -> np.ndarray:
    """Thin-plate kernel ``r^2 ln r`` from ``r^2`` (0 at r = 0), evaluated in place."""
    squared_distance = np.maximum(squared_distance, 0.0, out=squared_distance)
    positive = squared_distance > 0.0
    logs = np.log(squared_distance, out=np.zeros_like(squared_distance), where=positive)
    squared_distance *= logs
    squared_distance *= 0.5
    return squared_distance


class ThinPlateSplineModel:
    """Smoothing thin-plate spline, stored as what evaluates it.

    ``f(p) = sum_i w_i phi(|p - c_i|) + a_0 + a_x x + a_y y`` with ``phi(r) = r^2 ln r`` (r in mm,
    ``phi(0) = 0``), one column per output. Fitting (the constructor) solves the usual system
    ``[[K + s I, P], [P^T, 0]] [w; a] = [Y; 0]`` with ``K_ij = phi(|x_i - x_j|)``, ``P = [1, x, y]``
    and ``s = smoothing``, the same system as
    ``scipy.interpolate.RBFInterpolator(kernel="thin_plate_spline")``. ``to_dict`` stores the
    centres, weights and affine part; :meth:`from_dict` never refits. Attributes: ``centres``
    (N, 2), ``weights`` (N, 2), ``affine`` (3, 2) rows [1, x, y], ``smoothing``.

    Parameters
    ----------
    X : array_like, shape (N, 2)
        Inputs (training points, the centres), mm; at least 3.
    Y : array_like, shape (N, 2)
        Outputs (deviations), mm.
    smoothing : float, default 0.0
        0 interpolates; larger values trade fit for smoothness, in mm^2 ln mm; non-negative.

    Raises
    ------
    ValueError
        If X and Y are not finite (N, 2) arrays of one length with N >= 3, ``smoothing`` is negative,
        or the system is singular (collinear or repeated points).

    Examples
    --------
    An affine field is reproduced exactly:

    >>> from gls_calibration.fiducials.targets import grid_targets
    >>> points = grid_targets(5, 100.0)
    >>> spline = ThinPlateSplineModel(points, 0.001 * points[:, ::-1])
    >>> spline(np.array([[10.0, 20.0]])).round(6)
    array([[0.02, 0.01]])
    """

    centres: np.ndarray
    weights: np.ndarray
    affine: np.ndarray
    smoothing: float

    def __init__(self, X, Y, smoothing: float = 0.0) -> None:
        X, Y = as_matching_points(X, Y, "X", "Y", 2, min_length=3)
        smoothing = as_non_negative_number(smoothing, "smoothing")
        count = X.shape[0]
        # The affine columns are centred and scaled for the solve (conditioning), then mapped back.
        shift = X.mean(axis=0)
        scale = max(float(np.max(np.abs(X - shift))), 1e-12)
        system = np.zeros((count + 3, count + 3))
        system[:count, :count] = tps_kernel(np.sum((X[:, None, :] - X[None, :, :]) ** 2, axis=2))
        system[:count, :count] += smoothing * np.eye(count)
        polynomial = np.column_stack([np.ones(count), (X - shift) / scale])
        system[:count, count:] = polynomial
        system[count:, :count] = polynomial.T
        right = np.zeros((count + 3, 2))
        right[:count] = Y
        try:
            solution = np.linalg.solve(system, right)
        except np.linalg.LinAlgError:
            raise ValueError("thin-plate spline system is singular (are the points collinear or repeated?)") from None
        scaled = solution[count:]
        affine = np.vstack([scaled[0] - (shift / scale) @ scaled[1:], scaled[1:] / scale])
        self._set(X, solution[:count], affine, smoothing)

    def _set(self, centres, weights, affine, smoothing: float) -> None:
        self.centres = np.ascontiguousarray(centres, dtype=float)
        self.weights = np.ascontiguousarray(weights, dtype=float)
        self.affine = np.ascontiguousarray(affine, dtype=float)
        self.smoothing = float(smoothing)
        # |p - c|^2 = [x, y, |p|^2, 1] . [-2 c_x, -2 c_y, 1, |c|^2 + offset]: one BLAS product per block.
        squared_norms = np.sum(self.centres ** 2, axis=1)
        offset = _OFFSET_PER_SQUARED_MM * (1.0 + float(np.max(squared_norms, initial=0.0)))
        self._expansion = np.vstack([-2.0 * self.centres.T, np.ones(self.centres.shape[0]), squared_norms + offset])
        # phi = 0.5 r^2 ln r^2: the 0.5 goes into the weights.
        self._half_weights = np.ascontiguousarray(0.5 * self.weights)
        self._centres_by_axis = np.ascontiguousarray(self.centres.T)
        self._tiles: Optional[list] = None      # [evaluator or None] once built (on the first large batch)

    def prepare(self) -> None:
        """Build the evaluator of large batches now rather than on the first large batch."""
        self._tiled()

    def _tiled(self) -> Optional[tps_tiles.TiledKernelSum]:
        """Return the tiled evaluator, built once on first use, or None where it failed its check.

        Building takes 60-150 ms, so loading a file stays fast; the check is of its accuracy.
        """
        if self._tiles is None:
            with TILES_LOCK:
                if self._tiles is None:
                    self._tiles = [tps_tiles.build(self.centres, self._half_weights)]
        return self._tiles[0]

    def at_point(self, x: float, y: float) -> tuple[float, float]:
        """Predicted deviation (mm) at one point (mm): the same value as ``model([[x, y]])``, faster."""
        differences = self._centres_by_axis - np.array([[x], [y]])
        differences *= differences
        squared = differences[0] + differences[1]
        np.maximum(squared, _TINY, out=squared)
        kernel = np.log(squared)
        kernel *= squared
        dx, dy = (kernel @ self._half_weights).tolist()
        affine = self.affine
        return (dx + affine[0, 0] + x * affine[1, 0] + y * affine[2, 0],
                dy + affine[0, 1] + x * affine[1, 1] + y * affine[2, 1])

    @property
    def neuron_count(self) -> int:
        """Return the number of kernel centres."""
        return self.centres.shape[0]

    def __call__(self, points) -> np.ndarray:
        """Return the predicted deviations at ``points``.

        Parameters
        ----------
        points : array_like, shape (M, 2)
            Where to evaluate, mm.

        Returns
        -------
        numpy.ndarray, shape (M, 2)
            The deviations, mm.

        Raises
        ------
        ValueError
            If ``points`` is not a finite (M, 2) array.
        """
        points = query_points(points)
        result = points @ self.affine[1:]
        result += self.affine[0]
        if points.shape[0] <= SMALL_BATCH:
            result += self._kernel_part(points)
            return result
        tiled = self._tiled() if points.shape[0] >= TILED_MIN_ROWS else None
        if tiled is not None:
            if tiled.covers(points):
                result += tiled(points)
                return result
            inside = tiled.inside(points)
            # Beyond the centres' box (never from Correction, which clamps to the calibrated region).
            result[inside] += tiled(points[inside])
            result[~inside] = self._blocks(points[~inside])
            return result
        return self._blocks(points, result)

    def _blocks(self, points: np.ndarray, result: Optional[np.ndarray] = None) -> np.ndarray:
        """Evaluate the spline (M, 2) at ``points`` (M, 2), summed exactly block by block.

        Added to ``result`` when given (its affine part).
        """
        if result is None:
            result = points @ self.affine[1:]
            result += self.affine[0]
        rows = min(BLOCK_ROWS, points.shape[0])
        augmented = scratch("augmented", rows, 4)
        augmented[:, 3] = 1.0
        squared_buffer = scratch("squared", rows, self.centres.shape[0])
        kernel_buffer = scratch("kernel", rows, self.centres.shape[0])
        with np.errstate(invalid="ignore"):          # a row that failed (NaN) is recomputed below
            for start in range(0, points.shape[0], BLOCK_ROWS):
                block = points[start:start + BLOCK_ROWS]
                count = block.shape[0]
                augmented[:count, :2] = block
                np.einsum("ij,ij->i", block, block, out=augmented[:count, 2])
                squared, kernel = squared_buffer[:count], kernel_buffer[:count]
                np.matmul(augmented[:count], self._expansion, out=squared)
                # OpenCV's vectorised logarithm: 1.4x numpy's on this machine, within 3e-16 relative.
                cv2.log(squared, kernel)
                kernel *= squared
                result[start:start + count] += kernel @ self._half_weights
        failed = ~np.isfinite(result).all(axis=1)
        if failed.any():
            result[failed] = points[failed] @ self.affine[1:] + self.affine[0] + self._kernel_part(points[failed])
        return result

    def _kernel_part(self, points: np.ndarray) -> np.ndarray:
        """``sum_i w_i phi(|p - c_i|)`` (M, 2) from plain differences: exact, for few points."""
        return tps_kernel(np.sum((points[:, None, :] - self.centres) ** 2, axis=2)) @ self.weights

    def to_dict(self) -> dict:
        """Plain-number description (YAML-ready) from which :meth:`from_dict` rebuilds the same spline."""
        return {"type": "thin_plate_spline", "kernel": "r^2 ln r", "smoothing": self.smoothing,
                "centres": self.centres.tolist(), "weights": self.weights.tolist(),
                "affine": self.affine.tolist()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "ThinPlateSplineModel":
        """Rebuild a spline written by :meth:`to_dict` (no refit).

        A spline of format version 1 (``points``, ``values``, ``smoothing``: its training data) is
        fitted once from that data.
        """
        require_type(data, "thin_plate_spline")
        if "centres" not in data and "points" in data:
            return cls(require_key(data, "points"), require_key(data, "values"),
                       smoothing=require_key(data, "smoothing"))
        centres = rows_of_two(require_key(data, "centres"), "centres")
        weights = rows_of_two(require_key(data, "weights"), "weights")
        if centres.shape != weights.shape:
            raise ValueError(f"centres and weights must have the same shape, got {centres.shape} and {weights.shape}")
        affine = as_points(require_key(data, "affine"), "affine", 2)
        if affine.shape != (3, 2):
            raise ValueError(f"affine must have shape (3, 2) (rows 1, x, y), got {affine.shape}")
        model = cls.__new__(cls)
        model._set(centres, weights, affine, as_non_negative_number(data.get("smoothing", 0.0), "smoothing"))
        return model

    def __repr__(self) -> str:
        """Show the centre count and the smoothing."""
        return f"ThinPlateSplineModel(centres={self.neuron_count}, smoothing={self.smoothing:g})"
