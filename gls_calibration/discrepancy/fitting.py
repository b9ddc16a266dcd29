"""Effect fitting: the model's landing for the commanded targets, and least-squares fits of named effects.

The controller commands through the NOMINAL kinematics (``alpha = kinematics.inverse(geometry, Q)``);
the head lands them as :class:`gls_calibration.geometry.optics.PhysicalHead` with the effects of the model
says. The measurement is aligned rigidly onto the prediction inside every residual evaluation
(:func:`gls_calibration.registration.rigid.align_rigid_2d`), so no effect can absorb or be blamed for a
rotation or translation of the measured frame. Unknowns are measured in their typical size
(:data:`gls_calibration.geometry.effect_table.EFFECT_TABLE`), so one finite-difference step suits them all.
"""
from __future__ import annotations

from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np
from scipy import optimize

from gls_calibration.common.validation import as_finite_array, as_points
from gls_calibration.discrepancy.residual_statistics import MIN_POINTS, estimate_noise_floor
from gls_calibration.discrepancy.results import DiscrepancyResult, EffectsFit
from gls_calibration.geometry.effect_table import EFFECT_TABLE, EffectContext, EffectSpec, UserEffect
from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.geometry.optics import HeadEffects, PhysicalHead
from gls_calibration.registration.rigid import RigidAlignment2D, align_rigid_2d


class Predictor:
    """Landing (N, 2) of the commanded targets for given effects; commands go through the nominal model.

    Library effects go through the ray trace; user effects (:class:`gls_calibration.geometry.effect_table.UserEffect`)
    add their in-plane deviation to its landing.
    """

    def __init__(self, geometry: HeadGeometry, commanded_xy: np.ndarray, t: np.ndarray | None,
                 user_effects: Sequence[UserEffect] = ()) -> None:
        self.geometry = geometry
        self.commanded_xy = commanded_xy
        joints = inverse(geometry, commanded_xy[:, 0], commanded_xy[:, 1])
        self.alpha_x = joints.alpha_x
        self.alpha_y = joints.alpha_y
        self.t = t
        self.user_effects = {effect.name: effect for effect in user_effects}
        self.context = EffectContext(geometry, commanded_xy, self.alpha_x, self.alpha_y, t)
        self._checked: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None   # the angles, checked once

    def spec(self, name: str) -> EffectSpec:
        """Table entry of a library or user effect."""
        if name in self.user_effects:
            return self.user_effects[name].spec
        if name not in EFFECT_TABLE:
            known = ", ".join(list(EFFECT_TABLE) + list(self.user_effects))
            raise ValueError(f"unknown effect {name!r}; known effects: {known}")
        return EFFECT_TABLE[name]

    def __call__(self, effects: HeadEffects | Mapping[str, Sequence[float]],
                 user_values: Mapping[str, Sequence[float]] | None = None) -> np.ndarray:
        """Landing of the recorded angles with these effects (n, 2) mm, user effects added."""
        if self._checked is None:
            self._checked = PhysicalHead.checked_angles(self.alpha_x, self.alpha_y, self.t)
        landing = PhysicalHead(self.geometry, effects).land_checked(*self._checked)[:, :2]
        for name, values in (user_values or {}).items():
            change = np.asarray(self.user_effects[name].deviation(self.context, np.asarray(values, dtype=float)),
                                dtype=float)
            if change.shape != landing.shape or not np.all(np.isfinite(change)):
                raise ValueError(f"user effect {name!r} must return finite (N, 2) deviations for N = "
                                 f"{len(landing)} points, got shape {change.shape}")
            landing = landing + change
        return landing

    def subset(self, keep: np.ndarray) -> "Predictor":
        """Return the same predictor for the points ``keep`` (a boolean mask or indices)."""
        return Predictor(self.geometry, self.commanded_xy[keep], None if self.t is None else self.t[keep],
                         tuple(self.user_effects.values()))


def typical_scales(specs: Sequence[EffectSpec], t: np.ndarray | None) -> np.ndarray:
    """Typical size of each parameter of ``specs`` (flat, table order); per-run rates divided by the time span."""
    span = max(float(np.ptp(t)), 1.0) if t is not None and len(t) else 1.0
    return np.array([p.typical / span if p.per_run else p.typical for spec in specs for p in spec.parameters])


def aligned_residual(predicted_xy: np.ndarray, measured_xy: np.ndarray) -> tuple[RigidAlignment2D, np.ndarray]:
    """Return the rigid motion measured -> prediction and the residual ``aligned measurement - prediction``."""
    alignment, aligned = align_rigid_2d(measured_xy, predicted_xy)
    return alignment, aligned - predicted_xy


def split_values(predict: Predictor, names: Sequence[str], vector: np.ndarray,
                 known: HeadEffects) -> tuple[HeadEffects, dict[str, tuple[float, ...]]]:
    """Return the flat vector of ``names`` as library effects (on top of ``known``) and user-effect values."""
    library = dict(known.values)
    user: dict[str, tuple[float, ...]] = {}
    start = 0
    for name in names:
        count = len(predict.spec(name).parameters)
        values = tuple(float(v) for v in vector[start:start + count])
        (user if name in predict.user_effects else library)[name] = values
        start += count
    return HeadEffects(library), user


def fit(predict: Predictor, measured_xy: np.ndarray, names: Sequence[str], known: HeadEffects,
        initial: np.ndarray, sigma_axis_mm) -> EffectsFit:
    """Fit ``names`` (starting at ``initial``) on top of ``known``.

    ``sigma_axis_mm`` (a number or one value per point) is the per-axis noise the covariance and the
    chi-square refer to; per-point values also weight the fit.
    """
    names = tuple(names)
    specs = [predict.spec(name) for name in names]
    scales = typical_scales(specs, predict.t)
    sigma = np.asarray(sigma_axis_mm, dtype=float)
    weights = None if sigma.ndim == 0 else np.repeat(1.0 / sigma, 2)   # per point, both axes

    def residuals(u: np.ndarray) -> np.ndarray:
        predicted = predict(*split_values(predict, names, initial + scales * u, known))
        flat = aligned_residual(predicted, measured_xy)[1].ravel()
        return flat if weights is None else flat * weights

    if names:
        # unknowns in units of their typical size: one step size suits every parameter
        solution = optimize.least_squares(residuals, np.zeros(len(scales)), method="lm", diff_step=1e-5,
                                          xtol=1e-8, ftol=1e-8)
        vector = initial + scales * solution.x
        # covariance in the scaled unknowns (well conditioned), then back to parameter units
        jacobian = np.atleast_2d(solution.jac)
        factor = float(sigma) ** 2 if weights is None else 1.0
        covariance = factor * np.linalg.pinv(jacobian.T @ jacobian) * np.outer(scales, scales)
        success, evaluations = bool(solution.success), int(solution.nfev)
    else:
        vector, covariance, success, evaluations = np.zeros(0), np.zeros((0, 0)), True, 1
    return evaluate(predict, measured_xy, names, known, vector, sigma_axis_mm, covariance, success, evaluations)


def evaluate(predict: Predictor, measured_xy: np.ndarray, names: Sequence[str], known: HeadEffects,
             vector: np.ndarray, sigma_axis_mm, covariance: np.ndarray, success: bool = True,
             evaluations: int = 1) -> EffectsFit:
    """Return the fit record of ``names`` at ``vector`` (on top of ``known``): landing, aligned residual, chi-square."""
    names = tuple(names)
    sigma = np.asarray(sigma_axis_mm, dtype=float)
    effects, user = split_values(predict, names, vector, known)
    predicted = predict(effects, user)
    alignment, residual = aligned_residual(predicted, measured_xy)
    rss = float(np.sum(residual ** 2))
    chi2 = rss / float(sigma) ** 2 if sigma.ndim == 0 else float(np.sum((residual / sigma[:, None]) ** 2))
    layout = MappingProxyType({name: predict.spec(name).parameter_names for name in names})
    return EffectsFit(names, vector, covariance, effects, predicted, residual, alignment, rss, success, evaluations,
                      MappingProxyType(user), layout, chi2)


def linearised_extensions(predict: Predictor, measured_xy: np.ndarray, current: EffectsFit,
                          candidates: Sequence[str], known: HeadEffects, sigma_axis_mm) -> dict[str, EffectsFit]:
    """One Gauss-Newton step of ``current`` plus each candidate, evaluated exactly (``evaluations`` = 0).

    Cheap screening: the Jacobian columns (finite differences of the aligned, weighted residual in
    typical units) of the current effects are shared by all candidates. The chi-square at the step
    is that of a real model, so the gain it shows never overstates what a full fit finds near it.
    """
    sigma = np.asarray(sigma_axis_mm, dtype=float)
    weights = 1.0 / (np.full(len(measured_xy), float(sigma)) if sigma.ndim == 0 else sigma)

    def flat(names: tuple[str, ...], vector: np.ndarray) -> np.ndarray:
        predicted = predict(*split_values(predict, names, vector, known))
        return (aligned_residual(predicted, measured_xy)[1] * weights[:, None]).ravel()

    base = (current.residual_xy * weights[:, None]).ravel()
    names = tuple(current.names)
    scales = typical_scales([predict.spec(n) for n in names], predict.t)
    columns = []
    for i, scale in enumerate(scales):
        step = np.zeros(len(scales))
        step[i] = 1e-3 * scale
        columns.append((flat(names, current.vector + step) - base) / 1e-3)
    results = {}
    for name in candidates:
        extended = names + (name,)
        start = (np.zeros(len(predict.spec(name).parameters)) if name in predict.user_effects
                 else np.asarray(known.get(name), dtype=float))
        vector0 = np.concatenate([current.vector, start])
        own_scales = typical_scales([predict.spec(name)], predict.t)
        own = []
        for i, scale in enumerate(own_scales):
            step = np.zeros(len(vector0))
            step[len(scales) + i] = 1e-3 * scale
            own.append((flat(extended, vector0 + step) - base) / 1e-3)
        jacobian = np.column_stack(columns + own)
        # the residual is measured - model: moving the model by J du changes it by J du, so solve J du = -r
        du = np.linalg.lstsq(jacobian, -base, rcond=None)[0]
        all_scales = np.concatenate([scales, own_scales])
        covariance = np.linalg.pinv(jacobian.T @ jacobian) * np.outer(all_scales, all_scales)
        results[name] = evaluate(predict, measured_xy, extended, known, vector0 + all_scales * du, sigma_axis_mm,
                                 covariance, success=False, evaluations=0)
    return results


def implausible_values(predict: Predictor, model: EffectsFit) -> list[str]:
    """Why ``model`` is not physically plausible: each fitted value outside its effect's plausible range."""
    reasons = []
    for name in model.names:
        spec = predict.spec(name)
        for parameter, value in zip(spec.parameters, model.parameters(name).values()):
            if not parameter.plausible(value):
                reasons.append(f"{name}.{parameter.name} = {value:.4g} {parameter.unit} is outside the plausible "
                               f"range [{parameter.low:g}, {parameter.high:g}] {parameter.unit}")
    return reasons


def rigid_correlation(predict: Predictor, model: EffectsFit, sigma_axis_mm) -> dict[str, dict[str, float]]:
    """Correlation of each fitted parameter with the rigid motion (rotation, translation x, y).

    The fit profiles the rigid motion out; here the full Jacobian (effects and rigid motion, finite
    differences in typical units) is inverted once at the solution. A value near +-1 means the
    parameter is mostly a rotation or shift of the whole field.
    """
    if not model.names:
        return {}
    specs = [predict.spec(name) for name in model.names]
    scales = typical_scales(specs, predict.t)
    base = model.predicted_xy
    columns = []
    for i, scale in enumerate(scales):
        step = np.zeros_like(model.vector)
        step[i] = 1e-3 * scale
        moved = predict(*split_values(predict, model.names, model.vector + step, model.effects))
        columns.append(((moved - base) / 1e-3).ravel())
    centred = base - base.mean(axis=0)
    columns.append(np.column_stack([-centred[:, 1], centred[:, 0]]).ravel())      # rotation (rad)
    columns.append(np.tile([1.0, 0.0], len(base)))                                 # translation x (mm)
    columns.append(np.tile([0.0, 1.0], len(base)))                                 # translation y (mm)
    jacobian = np.column_stack(columns)
    sigma = np.asarray(sigma_axis_mm, dtype=float)
    if sigma.ndim:
        jacobian = jacobian / np.repeat(sigma, 2)[:, None]
    covariance = np.linalg.pinv(jacobian.T @ jacobian)
    deviation = np.sqrt(np.clip(np.diag(covariance), 1e-300, None))
    correlation = covariance / np.outer(deviation, deviation)
    labels = [f"{name}.{p}" for name in model.names for p in model.layout[name]]
    rigid = len(labels)
    return {label: {"rotation": float(correlation[i, rigid]), "translation_x": float(correlation[i, rigid + 1]),
                    "translation_y": float(correlation[i, rigid + 2])} for i, label in enumerate(labels)}


def check_inputs(commanded_xy, measured_xy, t) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Return validated (N, 2) commanded and measured points and optional (N,) marking time."""
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

    Parameters
    ----------
    commanded_xy : array_like, shape (N, 2)
        Nominal targets in the gls frame, mm.
    measured_xy : array_like, shape (N, 2)
        Measured mark positions in any frame a rigid motion away, mm.
    geometry : HeadGeometry
        The nominal head.
    names : sequence of str
        The effects to fit (unique names of the effect table).
    known_effects : HeadEffects or mapping, optional
        Effects already in the model; the named ones start from their values here.
    t : array_like, shape (N,), optional
        Marking time, s.
    sigma_axis_mm : float or array_like (N,), optional
        Per-axis noise, mm: a number scales the covariance only, per-point values also weight the fit.

    Returns
    -------
    EffectsFit
        The fitted values, their covariance, the landing, the aligned residual and the chi-square.

    Raises
    ------
    ValueError
        For bad points or times, repeated or unknown effect names, or bad ``known_effects``.
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
    return Predictor(result.geometry, commanded_xy, t, result.user_effects)(result.model_effects, result.user_values)
