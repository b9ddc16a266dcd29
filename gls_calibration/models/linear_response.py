"""The trained models' response to their training data: the fit is linear in it.

With the hyper-parameters fixed (an OLS RBF network's chosen centres and spread, a thin-plate
spline's smoothing), the weights are a linear solve of the training outputs ``Y`` (N, 2), so the
model at points ``p`` (M, 2) is ``H(p) @ Y`` with one (M, N) matrix ``H`` for both outputs. ``H``
carries any noise of ``Y`` into the model exactly: the covariance of ``f(p)`` from independent
per-point errors of standard deviation ``sigma_i`` (per axis) is ``sum_i H[p, i]^2 sigma_i^2`` per axis.

Exact propagation (this module) rather than Monte-Carlo refits: it costs one solve instead of
dozens, and it has no sampling error (a 50-draw Monte-Carlo variance is off by ~20 %).
The OLS forward selection itself depends on ``Y``; it is held fixed here (the chosen centres),
as it is in any refit of the stored model with its hyper-parameters.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from gls_calibration.common.validation import as_points
from gls_calibration.models.rbf import gaussian_design, tps_kernel

LINEAR_TYPES = ("ols_rbf", "thin_plate_spline")


def response_matrix(model: Mapping[str, Any], training_xy, points) -> np.ndarray:
    """Return ``H`` (M, N) with ``model(points) == H @ Y`` for the training data ``Y`` at ``training_xy``.

    Parameters
    ----------
    model : mapping
        A model's ``to_dict()`` form, type ``ols_rbf`` or ``thin_plate_spline``.
    training_xy : array_like (N, 2)
        Where the model was trained (mm).
    points : array_like (M, 2)
        Where to evaluate (mm).

    Returns
    -------
    numpy.ndarray, shape (M, N)
        The model's exact linear response at ``points`` to its training data (dimensionless).

    Raises
    ------
    ValueError
        For another model type, or a spline whose centres are not ``training_xy``.
    """
    training = as_points(training_xy, "training_xy", 2)
    points = as_points(points, "points", 2, min_length=0)
    kind = model.get("type")
    if kind == "ols_rbf":
        centres = np.asarray(model["centres"], dtype=float).reshape(-1, 2)
        spread = float(model["spread_mm"])
        design = np.column_stack([gaussian_design(training, centres, spread), np.ones(len(training))])
        at_points = np.column_stack([gaussian_design(points, centres, spread), np.ones(len(points))])
        # lstsq's minimum-norm solution is pinv(design) @ Y
        return at_points @ np.linalg.pinv(design)
    if kind == "thin_plate_spline":
        centres = np.asarray(model["centres"], dtype=float).reshape(-1, 2)
        if centres.shape != training.shape or not np.allclose(centres, training, rtol=0.0, atol=1e-9):
            raise ValueError("thin_plate_spline: its centres are not the training points given")
        count = len(training)
        shift = training.mean(axis=0)
        scale = max(float(np.max(np.abs(training - shift))), 1e-12)
        system = np.zeros((count + 3, count + 3))
        system[:count, :count] = tps_kernel(np.sum((training[:, None, :] - training[None, :, :]) ** 2, axis=2))
        system[:count, :count] += float(model.get("smoothing", 0.0)) * np.eye(count)
        polynomial = np.column_stack([np.ones(count), (training - shift) / scale])
        system[:count, count:] = polynomial
        system[count:, :count] = polynomial.T
        unit_outputs = np.zeros((count + 3, count))
        unit_outputs[:count] = np.eye(count)
        solution = np.linalg.solve(system, unit_outputs)      # [w; a] per unit output
        kernel = tps_kernel(np.sum((points[:, None, :] - training[None, :, :]) ** 2, axis=2))
        return kernel @ solution[:count] + np.column_stack([np.ones(len(points)), (points - shift) / scale]) \
            @ solution[count:]
    raise ValueError(f"model type {kind!r} is not linear in its training data (known: {', '.join(LINEAR_TYPES)})")
