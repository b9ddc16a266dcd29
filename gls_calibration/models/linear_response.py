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

A physics-first model (``physical_model.train_physics_then_rbf``) is not linear in its data: the
named effects are a nonlinear least-squares fit. :func:`physics_response_matrix` linearises it at its
solution, with what training selected held fixed (the effects, the outliers the fit leaves out, the
RBF's hyper-parameters): the parameters ``theta`` (effects, then the rigid motion of the model's
landing) move by ``A dY``, ``A`` from the pseudo-inverse of the Jacobian ``J`` of the deviation the
model fits, and the RBF takes what they leave, ``(I - J A) dY``. The physics couples x and y, so
that response is (2M, 2N) over the flattened (x, y) pairs.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from gls_calibration.common.validation import as_points
from gls_calibration.discrepancy import fit_inliers
from gls_calibration.models.physical_model import physics_first_parts
from gls_calibration.models.rbf import gaussian_design, tps_kernel

LINEAR_TYPES = ("ols_rbf", "thin_plate_spline")
# finite-difference step of a physical parameter, in its typical size (the discrepancy fit's unit)
_PARAMETER_STEP = 1e-3


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


def physics_response_matrix(model: Mapping[str, Any], targets_xy, deviations, points) -> np.ndarray:
    """Return ``H`` (2M, 2N): the physics-first model's change at ``points`` per change of its training data.

    The model of :func:`gls_calibration.models.physical_model.train_physics_then_rbf`, trained on
    the deviations ``Y = Q - P`` (N, 2) at the targets ``Q``, linearised at its solution with the
    selection held (the effects it holds, the points the effect fit leaves out, the RBF's
    hyper-parameters) and ``Q`` fixed (the commanded targets carry no measurement error):
    ``d model(points).ravel() = H @ dY.ravel()``, both flattened as (x, y) pairs,
    ``H = J_p A + (H_rbf kron I_2) (I - J A)``. ``J`` (2N, K) is the Jacobian of the deviation the
    physics fits, ``Q - landing(Q)``, with respect to its K parameters (effects, rotation,
    translation); the effects are fitted on the inliers with the rigid motion profiled out
    (``A_effects``: their rows of ``pinv(J_inliers)``), the rigid motion on all points with the
    effects given (``pinv(J_rigid) (I - J_effects A_effects)``); unweighted, as the training fits.
    ``J_p`` (2M, K) is the Jacobian of the correction (the model's inverse) at ``points``, ``H_rbf``
    (M, N) the residual model's :func:`response_matrix` at the targets. Jacobians by central finite
    differences, steps of 1e-3 of each parameter's typical size.

    Parameters
    ----------
    model : mapping
        The physics-first model's ``to_dict()`` form (a ``sum`` of ``physical`` and ``ols_rbf`` or
        ``thin_plate_spline``).
    targets_xy : array_like (N, 2)
        The targets Q the model was trained at (mm).
    deviations : array_like (N, 2)
        The deviations ``Q - P`` it was trained on (mm).
    points : array_like (M, 2)
        Where to evaluate (mm).

    Returns
    -------
    numpy.ndarray, shape (2M, 2N)
        Row ``2 m + a`` is the response of output axis ``a`` at point ``m`` to the training values
        ``Y[i, b]`` in column ``2 i + b`` (dimensionless).

    Raises
    ------
    ValueError
        For a model that is not physics first, mismatched or non-finite data, or a residual
        spline whose centres are not ``targets_xy``.
    """
    physical, residual_model = physics_first_parts(model)
    targets = as_points(targets_xy, "targets_xy", 2)
    deviations = as_points(deviations, "deviations", 2)
    if deviations.shape != targets.shape:
        raise ValueError(f"deviations must have the shape of targets_xy {targets.shape}, got {deviations.shape}")
    points = as_points(points, "points", 2, min_length=0)
    count = len(targets)
    theta = physical.parameter_vector()
    steps = _PARAMETER_STEP * physical.parameter_scales()
    fitted_deviation = np.empty((2 * count, theta.size))     # J
    correction = np.empty((2 * len(points), theta.size))     # J_p
    for k, step in enumerate(steps):
        shift = np.zeros(theta.size)
        shift[k] = step
        plus, minus = physical.with_parameters(theta + shift), physical.with_parameters(theta - shift)
        fitted_deviation[:, k] = (plus.measured_deviation(targets) - minus.measured_deviation(targets)).ravel() \
            / (2.0 * step)
        correction[:, k] = (plus(points) - minus(points)).ravel() / (2.0 * step)
    effects = theta.size - 3
    inlier_rows = np.repeat(fit_inliers(targets, targets - deviations, physical.geometry), 2)
    gain = np.zeros((theta.size, 2 * count))                 # A: d theta = A dY
    gain[:effects, inlier_rows] = np.linalg.pinv(fitted_deviation[inlier_rows])[:effects]
    rigid = np.linalg.pinv(fitted_deviation[:, effects:])
    gain[effects:] = rigid - (rigid @ fitted_deviation[:, :effects]) @ gain[:effects]
    left = np.eye(2 * count) - fitted_deviation @ gain         # (I - J A): what the RBF is trained on
    residual = response_matrix(residual_model, targets, points)   # (M, N), both axes alike
    through_residual = (residual @ left.reshape(count, 2 * 2 * count)).reshape(2 * len(points), 2 * count)
    return correction @ gain + through_residual
