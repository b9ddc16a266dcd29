"""The Gaussian RBF network trained by orthogonal least squares: the seed paper's model.

Centres are chosen by forward selection, as MATLAB's ``newrb`` does.
"""
from __future__ import annotations

from collections.abc import Mapping
import math
from typing import Any, Optional

import numpy as np

from gls_calibration.common.validation import (as_integer_at_least, as_matching_points, as_non_negative_number,
                                               as_points, as_positive_number, require_key, require_type)
from gls_calibration.models.evaluation_blocks import BLOCK_ROWS, SMALL_BATCH, query_points, rows_of_two, scratch


LN2 = math.log(2.0)


_USABLE_FRACTION = 1e-6      # squared-norm share a candidate must keep outside the chosen span


def sigma_from_spread(spread_mm: float) -> float:
    """Return the standard deviation of the Gaussian ``exp(-r^2 / (2 sigma^2))`` equal to a MATLAB-spread unit."""
    return as_positive_number(spread_mm, "spread_mm") / math.sqrt(2.0 * LN2)


def gaussian_design(points: np.ndarray, centres: np.ndarray, spread_mm: float) -> np.ndarray:
    """Return the outputs (N, K) of Gaussian units at ``centres`` for ``points`` (MATLAB spread convention)."""
    squared = np.sum((points[:, None, :] - centres[None, :, :]) ** 2, axis=2)
    return np.exp(-(LN2 / spread_mm ** 2) * squared)


def forward_selection(X: np.ndarray, Y: np.ndarray, spread_mm: float, mse_goal: float,
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

    Units are added until the training MSE (mean over points and both outputs) is <=
    ``mse_goal_mm2`` or ``max_neurons`` units are in; the weights of the chosen units and the bias
    are then solved by least squares. Selection also ends when no candidate is left that is not
    (numerically) in the span of the chosen ones; then ``training_mse_mm2`` stays above the goal.
    ``model(points)`` evaluates (M, 2) mm at (M, 2) mm. Attributes: ``centres`` (K, 2),
    ``weights`` (K, 2), ``bias`` (2,), ``spread_mm``, ``mse_goal_mm2``, ``max_neurons``,
    ``training_mse_mm2``.

    Parameters
    ----------
    X : array_like, shape (N, 2)
        Inputs (training points), mm.
    Y : array_like, shape (N, 2)
        Outputs (deviations), mm.
    spread_mm : float, default 35.0
        Spread of the Gaussian units, mm; positive.
    mse_goal_mm2 : float, default 0.0005
        Training MSE at which selection stops, mm^2; non-negative.
    max_neurons : int, optional
        Most units (default N); at least 1.

    Raises
    ------
    ValueError
        If X and Y are not finite (N, 2) arrays of one length, or a number is out of its range.

    Examples
    --------
    >>> from gls_calibration.fiducials.targets import grid_targets
    >>> points = grid_targets(5, 100.0)
    >>> network = OLSRBFNetwork(points, 0.001 * points[:, ::-1], spread_mm=40.0, mse_goal_mm2=1e-6)
    >>> bool(network.training_mse_mm2 <= 1e-6), network(np.array([[10.0, 20.0]])).shape
    (True, (1, 2))
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
        order, _ = forward_selection(X, Y, spread_mm, mse_goal_mm2, limit)
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
        """Return the number of Gaussian units (the bias not counted)."""
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
        if points.shape[0] <= SMALL_BATCH:
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
        buffer = scratch("exponent", min(BLOCK_ROWS, points.shape[0]), self.centres.shape[0])
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
        factors = scratch("factors", rows, count_x + self._unique_y.size)     # [x part | y part]
        partial = scratch("partial", rows, self._lattice.shape[1])
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
        centres = rows_of_two(require_key(data, "centres"), "centres")
        weights = rows_of_two(require_key(data, "weights"), "weights")
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
        """Show the spread, the MSE goal, the neuron count and the training MSE."""
        return (f"OLSRBFNetwork(spread_mm={self.spread_mm:g}, mse_goal_mm2={self.mse_goal_mm2:g}, "
                f"neurons={self.neuron_count}, training_mse_mm2={self.training_mse_mm2:.3g})")


def stop_count(history: np.ndarray, goal: float) -> int:
    """Return the units the constructor would keep for ``goal``: the first count whose MSE is <= goal."""
    reached = np.flatnonzero(history <= goal)
    return int(reached[0]) if reached.size else history.size - 1
