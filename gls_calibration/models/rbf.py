"""Deviation models: the OLS-trained Gaussian RBF network, a thin-plate spline, cross-validation.

A deviation model maps target positions ``Q`` (M, 2) in mm to deviations ``delta`` (M, 2) in mm:
it is built from training data in its constructor (like ``scipy.interpolate.RBFInterpolator``),
evaluated with ``model(points)`` and stored with ``to_dict()`` / ``from_dict`` (every stored type:
:mod:`gls_calibration.models.deviation_models`).

Spread convention (the one of MATLAB's ``newrb``, in which the published spread of 35 mm is
given): a unit's output is ``exp(-(sqrt(ln 2) r / spread)^2)``, i.e. 0.5 at ``r = spread``
(MATLAB writes the constant as 0.8326). In the ``exp(-r^2 / (2 sigma^2))`` form,
``sigma = spread / sqrt(2 ln 2) ~= 0.8493 spread``.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
import math
import threading
from typing import Any, Optional, Protocol

import cv2
import numpy as np

from gls_calibration.common.validation import (as_integer_at_least, as_matching_points, as_non_negative_number,
                                               as_points, as_positive_number, require_key, require_type)
from gls_calibration.models import tps_tiles

LN2 = math.log(2.0)
# Rows per block when evaluating many points (bounds memory, stays in cache). A row's result depends
# only on the block it falls in: batches split at multiples of it give bit-identical results.
BLOCK_ROWS = 512
_SMALL_BATCH = 64            # up to this many points, plain differences beat any set-up
# From this many points on, a thin-plate spline sums its kernels through its tiled evaluator
# (gls_calibration.models.tps_tiles; below, its fixed cost per tile outweighs the saving). The correction's
# worker threads never get fewer rows, so a target's value does not depend on how a request is shared.
TILED_MIN_ROWS = 8 * BLOCK_ROWS


_thread_scratch = threading.local()
# Serialises building splines' tiled evaluators (one module lock: a model stays picklable).
_TILES_LOCK = threading.Lock()


def _scratch(name: str, rows: int, columns: int) -> np.ndarray:
    """A (rows, columns) float work array of the calling thread, reused from call to call: a fresh
    array of a few MB is mapped and page-faulted anew each time (10 % of a large evaluation)."""
    size = rows * columns
    buffer = getattr(_thread_scratch, name, None)
    if buffer is None or buffer.size < size:
        buffer = np.empty(size)
        setattr(_thread_scratch, name, buffer)
    return buffer[:size].reshape(rows, columns)


def _query_points(points) -> np.ndarray:
    """``points`` as a finite (M, 2) float array; the full check (exact message) only when the quick one fails."""
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 2 or not np.isfinite(points).all():
        points = as_points(points, "points", 2, min_length=0)
    return points


_USABLE_FRACTION = 1e-6      # squared-norm share a candidate must keep outside the chosen span
_TINY = np.finfo(float).tiny
# Offset added to every squared distance of a large batch, in units of 1 + max |c|^2 (mm^2): 64 float
# steps, several times the round-off of |p|^2 + |c|^2 - 2 p.c where p meets a centre, so r^2 stays
# positive without a clamping pass (rows that still fail are recomputed from plain differences). It
# moves the spline by ~1e-12 mm (the weights sum to zero; test_rbf checks against the formula).
_OFFSET_PER_SQUARED_MM = 64 * np.finfo(float).eps


class DeviationModel(Protocol):
    """What the correction needs from a model."""

    def __call__(self, points) -> np.ndarray: ...

    def to_dict(self) -> dict: ...


def sigma_from_spread(spread_mm: float) -> float:
    """Standard deviation of the Gaussian ``exp(-r^2 / (2 sigma^2))`` equal to a MATLAB-spread unit."""
    return as_positive_number(spread_mm, "spread_mm") / math.sqrt(2.0 * LN2)


def gaussian_design(points: np.ndarray, centres: np.ndarray, spread_mm: float) -> np.ndarray:
    """Unit outputs (N, K) of Gaussian units at ``centres`` for ``points`` (MATLAB spread convention)."""
    squared = np.sum((points[:, None, :] - centres[None, :, :]) ** 2, axis=2)
    return np.exp(-(LN2 / spread_mm ** 2) * squared)


def _forward_selection(X: np.ndarray, Y: np.ndarray, spread_mm: float, mse_goal: float,
                       max_neurons: int) -> tuple[np.ndarray, np.ndarray]:
    """Orthogonal least squares forward selection (Chen, Cowan & Grant, 1991).

    The constant regressor enters first; then each step takes the candidate (a unit centred on a
    training input) with the largest error reduction ratio summed over the outputs, i.e. the share
    of the total output energy its orthogonalised regressor explains. All remaining candidates are
    orthogonalised against the chosen one at once (modified Gram-Schmidt as a rank-1 update); the
    chosen regressor itself is re-orthogonalised against the basis so far, which keeps the tracked
    residual equal to the least-squares one. A candidate keeping less than ``_USABLE_FRACTION`` of
    its squared norm outside the span so far is dropped: adding it would only make the weights
    ill-conditioned. Returns the chosen candidate indices in order and the training MSE (mean over
    points and outputs) after 0, 1, ... units.
    """
    count = X.shape[0]
    design = gaussian_design(X, X, spread_mm)
    original = np.einsum("ij,ij->j", design, design)
    basis = np.empty((count, min(max_neurons, count) + 1))
    basis[:, 0] = 1.0 / math.sqrt(count)               # the constant regressor, always first
    residual = Y - Y.mean(axis=0)
    candidates = design - design.mean(axis=0)
    usable = np.ones(count, dtype=bool)
    chosen: list[int] = []
    history = [float(np.mean(residual ** 2))]
    while history[-1] > mse_goal and len(chosen) < max_neurons:
        norms = np.einsum("ij,ij->j", candidates, candidates)
        usable &= norms > _USABLE_FRACTION * original
        energy = residual.T @ candidates                # (outputs, candidates)
        ratio = np.where(usable, np.sum(energy ** 2, axis=0) / np.where(usable, norms, 1.0), -np.inf)
        best = int(np.argmax(ratio))
        if not np.isfinite(ratio[best]) or ratio[best] <= 0.0:
            break
        known = basis[:, :len(chosen) + 1]
        unit = design[:, best].copy()
        for _ in range(2):                              # "twice is enough" re-orthogonalisation
            unit -= known @ (known.T @ unit)
        length = math.sqrt(unit @ unit)
        if length ** 2 <= _USABLE_FRACTION * original[best]:
            usable[best] = False
            continue
        unit /= length
        residual -= np.outer(unit, unit @ residual)
        candidates -= np.outer(unit, unit @ candidates)
        usable[best] = False
        chosen.append(best)
        basis[:, len(chosen)] = unit
        history.append(float(np.mean(residual ** 2)))
    return np.asarray(chosen, dtype=np.intp), np.asarray(history)


class OLSRBFNetwork:
    """Gaussian RBF network with an output bias, trained by OLS forward selection.

    ``OLSRBFNetwork(X, Y, spread_mm=35.0, mse_goal_mm2=0.0005, max_neurons=None)`` fits inputs
    X (N, 2) to outputs Y (N, 2) (mm): units are added until the training MSE (mean over points
    and both outputs) is <= ``mse_goal_mm2`` or ``max_neurons`` units (default N) are in; the
    weights of the chosen units and the bias are then solved by least squares. Selection also
    ends when no candidate is left that is not (numerically) in the span of the chosen ones; then
    ``training_mse_mm2`` stays above the goal. ``model(points)`` evaluates (M, 2). Attributes: ``centres`` (K, 2), ``weights`` (K, 2), ``bias`` (2,),
    ``spread_mm``, ``mse_goal_mm2``, ``max_neurons``, ``training_mse_mm2``.
    """

    centres: np.ndarray
    weights: np.ndarray
    bias: np.ndarray
    spread_mm: float
    mse_goal_mm2: float
    max_neurons: Optional[int]
    training_mse_mm2: float

    def __init__(self, X, Y, spread_mm: float = 35.0, mse_goal_mm2: float = 0.0005,
                 max_neurons: Optional[int] = None) -> None:
        X, Y = as_matching_points(X, Y, "X", "Y", 2)
        spread_mm = as_positive_number(spread_mm, "spread_mm")
        mse_goal_mm2 = as_non_negative_number(mse_goal_mm2, "mse_goal_mm2")
        if max_neurons is not None:
            max_neurons = as_integer_at_least(max_neurons, "max_neurons", 1)
        limit = X.shape[0] if max_neurons is None else min(max_neurons, X.shape[0])
        order, _ = _forward_selection(X, Y, spread_mm, mse_goal_mm2, limit)
        self._fit_weights(X, Y, order, spread_mm, mse_goal_mm2, max_neurons)

    @classmethod
    def _from_selection(cls, X: np.ndarray, Y: np.ndarray, order: np.ndarray, spread_mm: float,
                        mse_goal_mm2: float, max_neurons: Optional[int]) -> "OLSRBFNetwork":
        # Same result as the constructor when ``order`` is a prefix of the greedy path.
        model = cls.__new__(cls)
        model._fit_weights(X, Y, order, spread_mm, mse_goal_mm2, max_neurons)
        return model

    def _fit_weights(self, X: np.ndarray, Y: np.ndarray, order: np.ndarray, spread_mm: float,
                     mse_goal_mm2: float, max_neurons: Optional[int]) -> None:
        centres = X[order]
        design = np.column_stack([gaussian_design(X, centres, spread_mm), np.ones(X.shape[0])])
        solution = np.linalg.lstsq(design, Y, rcond=None)[0]
        self._set(centres, solution[:-1], solution[-1], spread_mm, mse_goal_mm2, max_neurons,
                  float(np.mean((design @ solution - Y) ** 2)))

    def _set(self, centres, weights, bias, spread_mm, mse_goal_mm2, max_neurons, training_mse_mm2) -> None:
        self.centres = np.ascontiguousarray(centres, dtype=float).reshape(-1, 2)
        self.weights = np.ascontiguousarray(weights, dtype=float).reshape(-1, 2)
        self.bias = np.asarray(bias, dtype=float).reshape(2)
        self.spread_mm = float(spread_mm)
        self.mse_goal_mm2 = float(mse_goal_mm2)
        self.max_neurons = max_neurons
        self.training_mse_mm2 = float(training_mse_mm2)
        self._prepare_evaluation()

    def _prepare_evaluation(self) -> None:
        self._scale = LN2 / self.spread_mm ** 2
        self._centre_columns = [np.ascontiguousarray(self.centres[:, k]) for k in range(2)]
        self._weight_columns = [np.ascontiguousarray(self.weights[:, k]) for k in range(2)]
        # Expansion a|x - c|^2 = a|x|^2 - 2a x.c + a|c|^2: the cross term is one BLAS product.
        self._expansion = np.vstack([-2.0 * self._scale * self.centres.T,
                                     self._scale * np.sum(self.centres ** 2, axis=1)])
        # Centres on a lattice (training targets of a grid) let each Gaussian factor into an x and
        # a y part: exp over M x (Ux + Uy) values and a small product instead of M x K exps.
        # Measured break-even (100 000 points): worth it when K > 25 + 0.09 Ux Uy.
        unique_x, index_x = np.unique(self.centres[:, 0], return_inverse=True)
        unique_y, index_y = np.unique(self.centres[:, 1], return_inverse=True)
        self._separable = self.centres.shape[0] > 25 + 0.09 * unique_x.size * unique_y.size
        if self._separable:
            lattice = np.zeros((unique_y.size, 2, unique_x.size))
            np.add.at(lattice, (index_y, slice(None), index_x), self.weights)
            self._unique_x, self._unique_y = unique_x, unique_y
            self._lattice = lattice.reshape(unique_y.size, 2 * unique_x.size)
            self._sum_over_x = np.kron(np.eye(2), np.ones((unique_x.size, 1)))

    @property
    def neuron_count(self) -> int:
        """Number of Gaussian units (the bias not counted)."""
        return self.centres.shape[0]

    def __call__(self, points) -> np.ndarray:
        """Predicted deviations (M, 2) in mm at ``points`` (M, 2) in mm."""
        points = _query_points(points)
        if points.shape[0] <= _SMALL_BATCH:
            squared = np.sum((points[:, None, :] - self.centres) ** 2, axis=2)
            return np.exp(-self._scale * squared) @ self.weights + self.bias
        # Blocks with reused buffers: fresh multi-megabyte temporaries cost more than the maths.
        result = np.empty((points.shape[0], 2))
        evaluate = self._separable_blocks if self._separable else self._expanded_blocks
        evaluate(points, result)
        result += self.bias
        return result

    def at_point(self, x: float, y: float) -> tuple[float, float]:
        """Predicted deviation (mm) at one point (mm): the same value as ``model([[x, y]])``, faster."""
        squared = np.square(self._centre_columns[0] - x)
        squared += np.square(self._centre_columns[1] - y)
        squared *= -self._scale
        units = np.exp(squared, out=squared)
        return (float(units @ self._weight_columns[0]) + float(self.bias[0]),
                float(units @ self._weight_columns[1]) + float(self.bias[1]))

    def _expanded_blocks(self, points: np.ndarray, result: np.ndarray) -> None:
        buffer = _scratch("exponent", min(BLOCK_ROWS, points.shape[0]), self.centres.shape[0])
        squared_norms = self._scale * np.einsum("ij,ij->i", points, points)
        for start in range(0, points.shape[0], BLOCK_ROWS):
            block = points[start:start + BLOCK_ROWS]
            exponent = buffer[:block.shape[0]]
            np.matmul(block, self._expansion[:2], out=exponent)
            exponent += self._expansion[2]
            exponent += squared_norms[start:start + BLOCK_ROWS, None]
            # Round-off can make |x - c|^2 slightly negative; a unit never exceeds 1.
            np.minimum(np.negative(exponent, out=exponent), 0.0, out=exponent)
            np.exp(exponent, out=exponent)
            np.matmul(exponent, self.weights, out=result[start:start + BLOCK_ROWS])

    def _separable_blocks(self, points: np.ndarray, result: np.ndarray) -> None:
        rows = min(BLOCK_ROWS, points.shape[0])
        count_x = self._unique_x.size
        factors = _scratch("factors", rows, count_x + self._unique_y.size)     # [x part | y part]
        partial = _scratch("partial", rows, self._lattice.shape[1])
        for start in range(0, points.shape[0], BLOCK_ROWS):
            block = points[start:start + BLOCK_ROWS]
            count = block.shape[0]
            both = factors[:count]
            np.subtract(block[:, 0, None], self._unique_x, out=both[:, :count_x])
            np.subtract(block[:, 1, None], self._unique_y, out=both[:, count_x:])
            np.square(both, out=both)
            both *= -self._scale
            np.exp(both, out=both)
            # Weights summed over y per x node, then weighted by the x factor and summed over x
            # (the last sum as a product with a 0/1 matrix: faster than a reduction over a short axis).
            product = partial[:count]
            np.matmul(both[:, count_x:], self._lattice, out=product)
            product_3d = product.reshape(count, 2, count_x)
            product_3d *= both[:, None, :count_x]
            np.matmul(product, self._sum_over_x, out=result[start:start + BLOCK_ROWS])

    def to_dict(self) -> dict:
        """Plain-number description (YAML-ready) from which :meth:`from_dict` rebuilds the same model."""
        return {
            "type": "ols_rbf",
            "spread_convention": "matlab_newrb",
            "spread_mm": self.spread_mm,
            "mse_goal_mm2": self.mse_goal_mm2,
            "max_neurons": self.max_neurons,
            "training_mse_mm2": self.training_mse_mm2,
            "centres": self.centres.tolist(),
            "weights": self.weights.tolist(),
            "bias": self.bias.tolist(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "OLSRBFNetwork":
        """Rebuild a network written by :meth:`to_dict`."""
        require_type(data, "ols_rbf")
        centres = _rows_of_two(require_key(data, "centres"), "centres")
        weights = _rows_of_two(require_key(data, "weights"), "weights")
        if centres.shape != weights.shape:
            raise ValueError(f"centres and weights must have the same shape, got {centres.shape} and {weights.shape}")
        bias = as_points([require_key(data, "bias")], "bias", 2)[0]
        max_neurons = data.get("max_neurons")
        model = cls.__new__(cls)
        model._set(centres, weights, bias, as_positive_number(require_key(data, "spread_mm"), "spread_mm"),
                   as_non_negative_number(data.get("mse_goal_mm2", 0.0), "mse_goal_mm2"),
                   None if max_neurons is None else as_integer_at_least(max_neurons, "max_neurons", 1),
                   float(data.get("training_mse_mm2", math.nan)))
        return model

    def __repr__(self) -> str:
        return (f"OLSRBFNetwork(spread_mm={self.spread_mm:g}, mse_goal_mm2={self.mse_goal_mm2:g}, "
                f"neurons={self.neuron_count}, training_mse_mm2={self.training_mse_mm2:.3g})")


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
    and ``s = smoothing`` (0 interpolates; larger values trade fit for smoothness, in mm^2 ln mm),
    the same system as ``scipy.interpolate.RBFInterpolator(kernel="thin_plate_spline")``.
    ``to_dict`` stores the centres, weights and affine part; :meth:`from_dict` never refits.
    Attributes: ``centres`` (N, 2), ``weights`` (N, 2), ``affine`` (3, 2) rows [1, x, y], ``smoothing``.
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
        """The tiled evaluator, built once on first use (60-150 ms; loading a file stays fast), or None
        where it failed its accuracy check."""
        if self._tiles is None:
            with _TILES_LOCK:
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
        """Number of kernel centres."""
        return self.centres.shape[0]

    def __call__(self, points) -> np.ndarray:
        """Predicted deviations (M, 2) in mm at ``points`` (M, 2) in mm."""
        points = _query_points(points)
        result = points @ self.affine[1:]
        result += self.affine[0]
        if points.shape[0] <= _SMALL_BATCH:
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
        """The spline (M, 2) at ``points`` (M, 2) summed exactly block by block (added to ``result``
        when given: its affine part)."""
        if result is None:
            result = points @ self.affine[1:]
            result += self.affine[0]
        rows = min(BLOCK_ROWS, points.shape[0])
        augmented = _scratch("augmented", rows, 4)
        augmented[:, 3] = 1.0
        squared_buffer = _scratch("squared", rows, self.centres.shape[0])
        kernel_buffer = _scratch("kernel", rows, self.centres.shape[0])
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
            return cls(require_key(data, "points"), require_key(data, "values"), smoothing=require_key(data, "smoothing"))
        centres = _rows_of_two(require_key(data, "centres"), "centres")
        weights = _rows_of_two(require_key(data, "weights"), "weights")
        if centres.shape != weights.shape:
            raise ValueError(f"centres and weights must have the same shape, got {centres.shape} and {weights.shape}")
        affine = as_points(require_key(data, "affine"), "affine", 2)
        if affine.shape != (3, 2):
            raise ValueError(f"affine must have shape (3, 2) (rows 1, x, y), got {affine.shape}")
        model = cls.__new__(cls)
        model._set(centres, weights, affine, as_non_negative_number(data.get("smoothing", 0.0), "smoothing"))
        return model

    def __repr__(self) -> str:
        return f"ThinPlateSplineModel(centres={self.neuron_count}, smoothing={self.smoothing:g})"


def _rows_of_two(values: Any, name: str) -> np.ndarray:
    """(K, 2) points; an empty list (a network of the bias alone, as YAML writes it) gives (0, 2)."""
    if isinstance(values, (list, tuple)) and len(values) == 0:
        return np.empty((0, 2))
    return as_points(values, name, 2, min_length=0)


@dataclass(frozen=True)
class CrossValidation:
    """K-fold cross-validation: RMS Euclidean held-out residual, per fold and overall (mm)."""

    rms_mm: float
    fold_rms_mm: tuple[float, ...]
    residuals: np.ndarray        # (N, 2) held-out residual Y - prediction, in input order


def _fold_indices(count: int, folds: int, seed, points: Optional[np.ndarray] = None,
                  block_mm: Optional[float] = None) -> list[np.ndarray]:
    """Seeded folds: points at random, or whole square blocks of ``block_mm`` (spatially blocked).

    When measurement errors are correlated between neighbours, a random split leaves a held-out
    point's correlated neighbours in training, and the CV error favours models that follow the
    measurement error; holding out whole blocks wider than that correlation keeps the CV honest.
    """
    folds = as_integer_at_least(folds, "folds", 2)
    if count < folds:
        raise ValueError(f"cannot split {count} point(s) into {folds} folds")
    rng = np.random.default_rng(seed)
    if block_mm is None:
        return np.array_split(rng.permutation(count), folds)
    block_mm = as_positive_number(block_mm, "block_mm")
    cells = np.floor((points - points.min(axis=0)) / block_mm).astype(np.int64)
    _, block = np.unique(cells, axis=0, return_inverse=True)
    block = block.ravel()
    if block.max() + 1 < folds:
        raise ValueError(f"{block.max() + 1} block(s) of {block_mm:g} mm cannot make {folds} folds")
    sizes = np.zeros(folds, dtype=int)
    members: list[list[int]] = [[] for _ in range(folds)]
    for label in rng.permutation(block.max() + 1):    # each block to the smallest fold so far
        smallest = int(np.argmin(sizes))
        chosen = np.flatnonzero(block == label)
        members[smallest].extend(chosen.tolist())
        sizes[smallest] += chosen.size
    return [np.sort(np.asarray(fold, dtype=int)) for fold in members]


def _summarise(residuals: np.ndarray, split: list[np.ndarray]) -> CrossValidation:
    squared = np.sum(residuals ** 2, axis=1)
    return CrossValidation(float(np.sqrt(squared.mean())),
                           tuple(float(np.sqrt(squared[fold].mean())) for fold in split), residuals)


def cross_validate(make_model: Callable[[np.ndarray, np.ndarray], DeviationModel], X, Y,
                   folds: int = 5, seed=0, block_mm: Optional[float] = None) -> CrossValidation:
    """K-fold cross-validation of ``make_model(X_train, Y_train)`` on a seeded random split
    (``block_mm``: whole square blocks held out together)."""
    X, Y = as_matching_points(X, Y, "X", "Y", 2)
    split = _fold_indices(X.shape[0], folds, seed, X, block_mm)
    residuals = np.empty_like(Y)
    for held_out in split:
        training = np.setdiff1d(np.arange(X.shape[0]), held_out)
        model = make_model(X[training], Y[training])
        residuals[held_out] = Y[held_out] - model(X[held_out])
    return _summarise(residuals, split)


@dataclass(frozen=True)
class CandidateScore:
    """One model configuration and its cross-validated error."""

    method: str                   # "ols_rbf" or "thin_plate_spline"
    parameters: Mapping[str, float]
    cv_rms_mm: float
    fold_rms_mm: tuple[float, ...]


@dataclass(frozen=True)
class ModelSelection:
    """Every candidate's cross-validated error and the chosen one (refitted on all data)."""

    candidates: tuple[CandidateScore, ...]
    chosen: CandidateScore
    folds: int
    seed: int

    @property
    def method(self) -> str:
        """Name of the chosen method."""
        return self.chosen.method

    def to_dict(self) -> dict:
        """Plain-number description (YAML-ready)."""
        def entry(score: CandidateScore) -> dict:
            return {"method": score.method, "parameters": dict(score.parameters),
                    "cv_rms_mm": score.cv_rms_mm, "fold_rms_mm": list(score.fold_rms_mm)}
        return {"method": self.method, "chosen": entry(self.chosen), "folds": self.folds, "seed": self.seed,
                "candidates": [entry(score) for score in self.candidates]}


def select_model(X, Y, spreads_mm: Sequence[float] = (20.0, 25.0, 30.0, 35.0, 45.0, 60.0),
                 mse_goals_mm2: Sequence[float] = (0.0002, 0.0005, 0.001),
                 tps_smoothings: Sequence[float] = (0.0, 10.0, 100.0, 300.0, 1000.0, 3000.0),
                 folds: int = 5, seed: int = 0,
                 max_neurons: Optional[int] = None,
                 block_mm: Optional[float] = None) -> tuple[DeviationModel, ModelSelection]:
    """Choose among OLS RBF networks (spread x MSE goal) and thin-plate splines by K-fold CV error.

    Every candidate is scored on the same seeded folds; the lowest CV RMS wins and is refitted
    on all data. The greedy OLS path does not depend on the MSE goal (only where it stops), so
    one selection per spread and fold, run to the smallest goal, serves every goal. ``block_mm``
    holds out whole square blocks of that side together (spatially blocked CV, see ``_fold_indices``).
    """
    X, Y = as_matching_points(X, Y, "X", "Y", 2)
    split = _fold_indices(X.shape[0], folds, seed, X, block_mm)
    spreads = [as_positive_number(value, "spreads_mm") for value in spreads_mm]
    goals = sorted(as_non_negative_number(value, "mse_goals_mm2") for value in mse_goals_mm2)
    smoothings = [as_non_negative_number(value, "tps_smoothings") for value in tps_smoothings]
    if max_neurons is not None:
        max_neurons = as_integer_at_least(max_neurons, "max_neurons", 1)
    if not spreads and not smoothings:
        raise ValueError("select_model needs at least one candidate (spreads_mm or tps_smoothings)")
    if spreads and not goals:
        raise ValueError("mse_goals_mm2 must hold at least one value when spreads_mm is given")

    scores: list[CandidateScore] = []
    trainings = [np.setdiff1d(np.arange(X.shape[0]), held_out) for held_out in split]
    for spread in spreads:
        residuals = {goal: np.empty_like(Y) for goal in goals}
        for training, held_out in zip(trainings, split):
            limit = training.size if max_neurons is None else min(max_neurons, training.size)
            order, history = _forward_selection(X[training], Y[training], spread, goals[0], limit)
            for goal in goals:
                model = OLSRBFNetwork._from_selection(X[training], Y[training], order[:_stop_count(history, goal)],
                                                      spread, goal, max_neurons)
                residuals[goal][held_out] = Y[held_out] - model(X[held_out])
        for goal in goals:
            summary = _summarise(residuals[goal], split)
            scores.append(CandidateScore("ols_rbf", {"spread_mm": spread, "mse_goal_mm2": goal},
                                         summary.rms_mm, summary.fold_rms_mm))
    for smoothing in smoothings:
        summary = cross_validate(lambda x, y: ThinPlateSplineModel(x, y, smoothing), X, Y, folds, seed, block_mm)
        scores.append(CandidateScore("thin_plate_spline", {"smoothing": smoothing},
                                     summary.rms_mm, summary.fold_rms_mm))

    chosen = min(scores, key=lambda score: score.cv_rms_mm)
    if chosen.method == "ols_rbf":
        model: DeviationModel = OLSRBFNetwork(X, Y, chosen.parameters["spread_mm"],
                                              chosen.parameters["mse_goal_mm2"], max_neurons)
    else:
        model = ThinPlateSplineModel(X, Y, chosen.parameters["smoothing"])
    return model, ModelSelection(tuple(scores), chosen, len(split), seed)


def _stop_count(history: np.ndarray, goal: float) -> int:
    """Units the constructor would keep for ``goal``: the first count whose MSE is <= goal."""
    reached = np.flatnonzero(history <= goal)
    return int(reached[0]) if reached.size else history.size - 1
