"""Effect fitting: the model's landing for the commanded targets, and least-squares fits of named effects.

The controller commands through the NOMINAL kinematics (``alpha = kinematics.inverse(geometry, Q)``);
the head lands them as :class:`gls_calibration.optics.PhysicalHead` with the effects of the model
says. The measurement is aligned rigidly onto the prediction inside every residual evaluation
(:func:`gls_calibration.registration.align_rigid_2d`), so no effect can absorb or be blamed for a
rotation or translation of the measured frame. Unknowns are measured in their typical size
(:data:`gls_calibration.effect_table.EFFECT_TABLE`), so one finite-difference step suits them all.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
from scipy import optimize

from gls_calibration.discrepancy.residual_statistics import MIN_POINTS, estimate_noise_floor
from gls_calibration.discrepancy.results import DiscrepancyResult, EffectsFit
from gls_calibration.effect_table import EFFECT_TABLE
from gls_calibration.kinematics import HeadGeometry, inverse
from gls_calibration.optics import HeadEffects, PhysicalHead
from gls_calibration.registration import RigidAlignment2D, align_rigid_2d
from gls_calibration.validation import as_finite_array, as_points


class Predictor:
    """Landing (N, 2) of the commanded targets for given effects; commands go through the nominal model."""

    def __init__(self, geometry: HeadGeometry, commanded_xy: np.ndarray, t: np.ndarray | None) -> None:
        self.geometry = geometry
        self.commanded_xy = commanded_xy
        joints = inverse(geometry, commanded_xy[:, 0], commanded_xy[:, 1])
        self.alpha_x = joints.alpha_x
        self.alpha_y = joints.alpha_y
        self.t = t

    def __call__(self, effects: HeadEffects | Mapping[str, Sequence[float]]) -> np.ndarray:
        return PhysicalHead(self.geometry, effects).land(self.alpha_x, self.alpha_y, self.t)[:, :2]


def typical_scales(names: Sequence[str], t: np.ndarray | None) -> np.ndarray:
    """Typical size of each parameter of ``names`` (flat, table order); per-run rates divided by the time span."""
    span = max(float(np.ptp(t)), 1.0) if t is not None and len(t) else 1.0
    return np.array([p.typical / span if p.per_run else p.typical
                     for name in names for p in EFFECT_TABLE[name].parameters])


def aligned_residual(predicted_xy: np.ndarray, measured_xy: np.ndarray) -> tuple[RigidAlignment2D, np.ndarray]:
    """The rigid motion measured -> prediction and the residual ``aligned measurement - prediction``."""
    alignment, aligned = align_rigid_2d(measured_xy, predicted_xy)
    return alignment, aligned - predicted_xy


def fit(predict: Predictor, measured_xy: np.ndarray, names: Sequence[str], known: HeadEffects,
        initial: np.ndarray, sigma_axis_mm: float) -> EffectsFit:
    """Fit ``names`` (starting at ``initial``) on top of ``known``; covariance for ``sigma_axis_mm`` per axis."""
    names = tuple(names)
    scales = typical_scales(names, predict.t)
    base = dict(known.values)

    def model(vector: np.ndarray) -> HeadEffects:
        values = dict(base)
        values.update(HeadEffects.from_vector(names, vector).values)
        return HeadEffects(values)

    def residuals(u: np.ndarray) -> np.ndarray:
        predicted = predict(model(initial + scales * u))
        return aligned_residual(predicted, measured_xy)[1].ravel()

    if names:
        # unknowns in units of their typical size: one step size suits every parameter
        solution = optimize.least_squares(residuals, np.zeros(len(scales)), method="lm", diff_step=1e-5,
                                          xtol=1e-10, ftol=1e-10)
        vector = initial + scales * solution.x
        # covariance in the scaled unknowns (well conditioned), then back to parameter units
        jacobian = np.atleast_2d(solution.jac)
        covariance = sigma_axis_mm ** 2 * np.linalg.pinv(jacobian.T @ jacobian) * np.outer(scales, scales)
        success, evaluations = bool(solution.success), int(solution.nfev)
    else:
        vector, covariance, success, evaluations = np.zeros(0), np.zeros((0, 0)), True, 1
    effects = model(vector) if names else known
    predicted = predict(effects)
    alignment, residual = aligned_residual(predicted, measured_xy)
    return EffectsFit(names, vector, covariance, effects, predicted, residual, alignment,
                      float(np.sum(residual ** 2)), success, evaluations)


def check_inputs(commanded_xy, measured_xy, t) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Validated (N, 2) commanded and measured points and optional (N,) marking time."""
    commanded_xy = as_points(commanded_xy, "commanded_xy", 2, min_length=MIN_POINTS)
    measured_xy = as_points(measured_xy, "measured_xy", 2, min_length=MIN_POINTS)
    if measured_xy.shape != commanded_xy.shape:
        raise ValueError(f"measured_xy must have the shape of commanded_xy {commanded_xy.shape}, "
                         f"got {measured_xy.shape}")
    if t is not None:
        t = as_finite_array(t, "t", ndim=1)
        if t.shape[0] != commanded_xy.shape[0]:
            raise ValueError(f"t must hold one marking time per point ({commanded_xy.shape[0]}), got {t.shape[0]}")
    return commanded_xy, measured_xy, t


def as_effects(known_effects) -> HeadEffects:
    """``known_effects`` (None, a mapping or HeadEffects) as HeadEffects."""
    if known_effects is None:
        return HeadEffects()
    return known_effects if isinstance(known_effects, HeadEffects) else HeadEffects(known_effects)


def fit_effects(commanded_xy, measured_xy, geometry: HeadGeometry, names: Sequence[str],
                known_effects: HeadEffects | Mapping | None = None, t=None, *,
                sigma_axis_mm: float | None = None) -> EffectsFit:
    """Fit the parameters of the named effects (on top of ``known_effects``) to the measured positions.

    Starts from the known value of each named effect (zero when unknown); the fitted values replace
    them. The rigid motion of the measured frame is solved in closed form inside every evaluation.
    ``sigma_axis_mm`` scales the covariance (default: the noise floor estimated from the data).
    """
    commanded_xy, measured_xy, t = check_inputs(commanded_xy, measured_xy, t)
    names = tuple(names)
    if len(set(names)) != len(names):
        raise ValueError(f"effect names must be unique, got {list(names)}")
    known = as_effects(known_effects)
    initial = known.to_vector(names)   # also rejects unknown names
    predict = Predictor(geometry, commanded_xy, t)
    if sigma_axis_mm is None:
        _, residual = aligned_residual(predict(known), measured_xy)
        sigma_axis_mm = estimate_noise_floor(commanded_xy, residual, t).sigma_axis_mm
    return fit(predict, measured_xy, names, known, initial, sigma_axis_mm)


def physical_prediction(result: DiscrepancyResult, commanded_xy, t=None) -> np.ndarray:
    """Landing points (N, 2), gls frame, of the extended model (known plus named effects) for targets.

    Measured positions aligned to the gls frame minus this are the deviations that are left for a
    data-driven correction (the RBF) after the physics.
    """
    commanded_xy = as_points(commanded_xy, "commanded_xy", 2)
    if t is not None:
        t = as_finite_array(t, "t", ndim=1)
        if t.shape[0] != commanded_xy.shape[0]:
            raise ValueError(f"t must hold one marking time per point ({commanded_xy.shape[0]}), got {t.shape[0]}")
    return Predictor(result.geometry, commanded_xy, t)(result.model_effects)
