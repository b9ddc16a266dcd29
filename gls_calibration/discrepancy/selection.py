"""Selection: which candidate effects to name, one step at a time, scored by an information criterion.

Each step fits every remaining candidate together with the effects already named, names the one
that improves the criterion most (if by at least ``name_threshold``), drops effects named earlier
that the others now explain (backward pass), and lists the candidates indistinguishable from it.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
import math
from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np

from gls_calibration.discrepancy.fitting import (
    Predictor, aligned_residual, as_effects, check_inputs, fit, implausible_values, linearised_extensions,
    rigid_correlation)
from gls_calibration.discrepancy.noise_floor import floor_evidence, independent_noise
from gls_calibration.discrepancy.outliers import find_outliers
from gls_calibration.discrepancy.separability import SEPARABLE_AT, Separability, separability
from gls_calibration.discrepancy.verdict import against_floor, judge
from gls_calibration.discrepancy.residual_statistics import (
    estimate_noise_floor, locate_residual, rms, structure_test)
from gls_calibration.discrepancy.results import (
    CandidateScore, DiscrepancyResult, EffectsFit, EffectStep, Implausible, NoiseFloor, Outlier, StructureTest)
from gls_calibration.geometry.effect_table import EFFECTS, UserEffect, check_user_effect
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.geometry.optics import HeadEffects
from gls_calibration.registration.rigid import align_rigid_2d

CRITERIA = ("bic", "aic")
RIGID_PARAMETERS = 3     # rotation and translation of the measured frame
MIN_NOISE_MM = 1e-4      # lower bound of an estimated noise (explain's default)
FULL_FITS = 5            # candidates per step fitted fully after the linearised screening
RIGID_NOTE = ("Rotation and translation between the measured frame and the gls frame are removed by a "
              "rigid alignment: they are not observable from these data and are never named as effects.")


@dataclass(frozen=True)
class Selection:
    """What every step of one selection shares: the data, the model so far, the thresholds."""

    predict: Predictor
    measured_xy: np.ndarray
    known: HeadEffects
    noise: NoiseFloor                 # the residual-roughness estimate (structure test)
    sigma_axis_mm: object             # sigma of the fits: a number or one value per point
    inflation: float                  # the criterion divides chi-square by inflation^2 (>= 1)
    noise_floor_mm: float             # floor the rivals' field differences are compared with
    pool: tuple[str, ...]
    criterion: str
    name_threshold: float
    indistinguishable_within: float
    structure_alpha: float
    min_noise_mm: float

    @property
    def observations(self) -> int:
        """Return the number of scalar observations (2 per point)."""
        return 2 * len(self.measured_xy)

    def information(self, model: EffectsFit) -> float:
        """Information criterion of a fit on the Gaussian likelihood with the selection's sigma per axis."""
        penalty = math.log(self.observations) if self.criterion == "bic" else 2.0
        parameters = RIGID_PARAMETERS + len(model.vector)
        return model.chi2 / self.inflation ** 2 + penalty * parameters

    def fit(self, names: Sequence[str], initial: np.ndarray) -> EffectsFit:
        """Fit ``names`` from ``initial`` on top of the known effects."""
        return fit(self.predict, self.measured_xy, names, self.known, initial, self.sigma_axis_mm)

    def extend(self, model: EffectsFit, name: str) -> EffectsFit:
        """Fit ``model``'s effects plus ``name`` (starting from the known value of ``name``, zero for user effects)."""
        start = (np.zeros(len(self.predict.spec(name).parameters)) if name in self.predict.user_effects
                 else np.asarray(self.known.get(name), dtype=float))
        return self.fit(model.names + (name,), np.concatenate([model.vector, start]))

    def implausible(self, model: EffectsFit) -> list[str]:
        """Reasons ``model`` is physically implausible (empty when every value is in range)."""
        return implausible_values(self.predict, model)

    def reduce(self, model: EffectsFit, keep: Sequence[str]) -> EffectsFit:
        """Refit only ``keep`` of ``model``'s effects, starting from their values in ``model``."""
        start = np.array([value for n in keep for value in model.parameters(n).values()])
        return self.fit(tuple(keep), start)

    def structure(self, model: EffectsFit) -> StructureTest:
        """Structure-or-noise test of ``model``'s residual."""
        return structure_test(self.predict.commanded_xy, model.residual_xy, self.noise, self.predict.t,
                              fitted_parameters=len(model.vector), alpha=self.structure_alpha,
                              min_sigma_mm=self.min_noise_mm)


def rivals(selection: Selection, best: str, model: EffectsFit, alternatives: Mapping[str, EffectsFit],
           base_information: float) -> list[str]:
    """Candidates that explain (nearly) what ``best`` explains in ``model``.

    A rival is itself significant and either close in the criterion or gains at least half as much
    with a landing field that differs from the best's by less than the noise floor.
    """
    best_gain = base_information - selection.information(model)
    found = []
    for name, alternative in sorted(alternatives.items(), key=lambda item: selection.information(item[1])):
        gain = base_information - selection.information(alternative)
        if name == best or gain < selection.name_threshold or selection.implausible(alternative):
            continue
        _, moved = align_rigid_2d(alternative.predicted_xy, model.predicted_xy)
        difference = rms(moved - model.predicted_xy)
        if best_gain - gain < selection.indistinguishable_within or (
                difference < selection.noise_floor_mm and gain >= 0.5 * best_gain):
            found.append(name)
    return found


def score_candidates(selection: Selection, fits: Mapping[str, EffectsFit], improvement: Mapping[str, float],
                     best_fit: EffectsFit) -> tuple[CandidateScore, ...]:
    """Every candidate of one step, best first, with its distance to the best candidate's landing field."""
    scores = []
    for name, candidate in sorted(fits.items(), key=lambda item: -improvement[item[0]]):
        _, moved = align_rigid_2d(candidate.predicted_xy, best_fit.predicted_xy)
        scores.append(CandidateScore(name, MappingProxyType(candidate.parameters(name)),
                                     MappingProxyType(candidate.uncertainty(name)), selection.information(candidate),
                                     float(improvement[name]), candidate.rms_mm,
                                     rms(moved - best_fit.predicted_xy)))
    return tuple(scores)


def prune(selection: Selection, best: str, model: EffectsFit, notes: list[str]) -> tuple[EffectsFit, list[str]]:
    """Backward pass: drop effects named earlier that the others now explain.

    Forward selection can pick a look-alike of two effects first; an earlier effect goes when
    keeping it is not strongly supported (the criterion worsens by less than ``name_threshold``).
    """
    removed: list[str] = []
    while len(model.names) > 1:
        worsening = {}
        for name in model.names[:-1]:
            reduced = selection.reduce(model, [n for n in model.names if n != name])
            if not selection.implausible(reduced):
                worsening[name] = (selection.information(reduced) - selection.information(model), reduced)
        if not worsening:
            break
        weakest = min(worsening, key=lambda name: worsening[name][0])
        if worsening[weakest][0] >= selection.name_threshold:
            break
        removed.append(weakest)
        model = worsening[weakest][1]
        notes.append(f"{weakest} was dropped after {best} was added: the other named effects explain it "
                     f"({selection.criterion.upper()} worsens by only {worsening[weakest][0]:.1f} without it).")
    return model, removed


def rivals_after_pruning(selection: Selection, best: str, model: EffectsFit) -> list[str]:
    """Rivals of ``best`` in the pruned model: every other candidate in its place."""
    base = selection.reduce(model, [n for n in model.names if n != best])
    alternatives = {name: selection.extend(base, name) for name in selection.pool if name not in model.names}
    return rivals(selection, best, model, alternatives, selection.information(base))


def screen(selection: Selection, current: EffectsFit, remaining: Sequence[str],
           base_information: float) -> dict[str, EffectsFit]:
    """Screen every remaining candidate added to ``current``: a step each, full fits for the best.

    Every remaining candidate added to ``current``: one Gauss-Newton step for all, a full fit for the
    ``FULL_FITS`` whose step drops the chi-square most unless even that cannot pay for its parameters
    (a drop below half its penalty). For the others the step stands: its chi-square is that of a real
    model, so it never overstates their gain.
    """
    steps = linearised_extensions(selection.predict, selection.measured_xy, current, remaining, selection.known,
                                  selection.sigma_axis_mm)
    penalty = math.log(selection.observations) if selection.criterion == "bic" else 2.0
    drop = {name: (current.chi2 - steps[name].chi2) / selection.inflation ** 2 for name in remaining}
    leaders = sorted(remaining, key=lambda name: -drop[name])[:FULL_FITS]
    fits = {}
    for name in remaining:
        hopeless = drop[name] < 0.5 * penalty * len(selection.predict.spec(name).parameters)
        fits[name] = selection.extend(current, name) if name in leaders and not hopeless else steps[name]
    return fits


def step(selection: Selection, current: EffectsFit, dropped: set[str], notes: list[str],
         implausible: dict[str, Implausible], number: int) -> tuple[EffectStep | None, EffectsFit, str]:
    """One forward step from ``current``: the step named (or None), the new model and, if none, why.

    A candidate whose joint fit puts any value outside its plausible range is not named; it is
    recorded in ``implausible`` (first occurrence per effect) when it would otherwise have counted.
    """
    remaining = [name for name in selection.pool if name not in current.names and name not in dropped]
    if not remaining:
        return None, current, "no candidate effect left"
    base_information = selection.information(current)
    fits = screen(selection, current, remaining, base_information)
    improvement = {name: base_information - selection.information(f) for name, f in fits.items()}
    plausible = {}
    for name, candidate in fits.items():
        reasons = selection.implausible(candidate)
        if not reasons:
            plausible[name] = candidate
        elif improvement[name] >= selection.name_threshold and name not in implausible:
            implausible[name] = Implausible(name, MappingProxyType(candidate.parameters(name)), "; ".join(reasons),
                                            number)
    if not plausible:
        return None, current, "every candidate's fit is physically implausible"
    best = max(plausible, key=improvement.get)
    if improvement[best] < selection.name_threshold:
        return None, current, (f"no plausible candidate improves the {selection.criterion.upper()} by "
                               f"{selection.name_threshold:g} or more (best: {best}, {improvement[best]:.1f})")
    scores = score_candidates(selection, fits, improvement, fits[best])
    model, removed = prune(selection, best, fits[best], notes)
    dropped.update(removed)
    found = (rivals_after_pruning(selection, best, model) if removed
             else rivals(selection, best, model, fits, base_information))
    if found:
        notes.append(f"{best} is indistinguishable from {', '.join(found)} with these data (criterion within "
                     f"{selection.indistinguishable_within:g} or landing fields within the noise floor).")
    spec = selection.predict.spec(best)
    named = EffectStep(best, MappingProxyType(model.parameters(best)), MappingProxyType(model.uncertainty(best)),
                       MappingProxyType(dict(zip(spec.parameter_names, spec.units))), tuple(found),
                       float(improvement[best]), current.rms_mm, model.rms_mm, scores, tuple(removed))
    return named, model, ""


def time_follows_position(points_xy: np.ndarray, t: np.ndarray, threshold: float = 0.9) -> bool:
    """Return True when a plane in x, y explains more than ``threshold`` of the variance of the marking time."""
    design = np.column_stack([np.ones(len(points_xy)), points_xy])
    fitted = design @ np.linalg.lstsq(design, t, rcond=None)[0]
    variance = float(np.var(t))
    return variance > 0.0 and 1.0 - float(np.var(t - fitted)) / variance > threshold


def candidate_pool(candidates: Sequence[str] | None, t: np.ndarray | None,
                   user_effects: Sequence[UserEffect] = ()) -> tuple[str, ...]:
    """Return the candidate effects (default: the whole table and user effects); thermal_drift needs time."""
    user = [effect.name for effect in user_effects]
    if len(set(user)) != len(user):
        raise ValueError(f"user effect names must be unique, got {user}")
    known = list(EFFECTS) + user
    pool = known if candidates is None else list(candidates)
    for name in pool:
        if name not in known:
            raise ValueError(f"unknown effect {name!r}; known effects: {', '.join(known)}")
    if t is None and "thermal_drift" in pool:
        pool.remove("thermal_drift")   # invisible without marking time
    return tuple(pool)


def _outliers(predict: Predictor, measured_xy: np.ndarray, known: HeadEffects,
              min_noise_mm: float) -> tuple[Outlier, ...]:
    """Gross outliers of the residual against the known model (see :mod:`.outliers`)."""
    _, residual = aligned_residual(predict(known), measured_xy)
    mask, size = find_outliers(predict.commanded_xy, residual, min_sigma_mm=min_noise_mm)
    return tuple(Outlier(int(i), float(size[i]), (float(predict.commanded_xy[i, 0]), float(predict.commanded_xy[i, 1])))
                 for i in np.flatnonzero(mask))


def fit_inliers(commanded_xy, measured_xy, geometry: HeadGeometry | None = None,
                known_effects: HeadEffects | Mapping | None = None, *,
                min_noise_mm: float = MIN_NOISE_MM) -> np.ndarray:
    """Return the points :func:`explain` fits (no time, no user effects): True except its gross outliers.

    Parameters
    ----------
    commanded_xy : array_like, shape (N, 2)
        Nominal targets in the gls frame, mm.
    measured_xy : array_like, shape (N, 2)
        Measured mark positions in any frame a rigid motion away, mm.
    geometry : HeadGeometry, optional
        The nominal head; the default one when None.
    known_effects : HeadEffects or mapping, optional
        Effects already in the model.
    min_noise_mm : float, default MIN_NOISE_MM
        Lower bound of the estimated noise, mm (``explain``'s ``min_noise_mm``).

    Returns
    -------
    numpy.ndarray of bool, shape (N,)
        False for the points ``explain`` leaves out of every fit.

    Raises
    ------
    ValueError
        For bad points (shapes, too few, not finite) or bad ``known_effects``.
    """
    commanded_xy, measured_xy, _ = check_inputs(commanded_xy, measured_xy, None)
    predict = Predictor(geometry if geometry is not None else HeadGeometry(), commanded_xy, None)
    inliers = np.ones(len(commanded_xy), dtype=bool)
    inliers[[o.index for o in _outliers(predict, measured_xy, as_effects(known_effects), min_noise_mm)]] = False
    return inliers


def explain(commanded_xy, measured_xy, geometry: HeadGeometry | None = None,
            known_effects: HeadEffects | Mapping | None = None, t=None, *,
            sigma_mm=None, user_effects: Sequence[UserEffect] = (),
            candidates: Sequence[str] | None = None, criterion: str = "bic", name_threshold: float = 10.0,
            indistinguishable_within: float = 6.0, structure_alpha: float = 1e-3, max_steps: int = 6,
            min_noise_mm: float = MIN_NOISE_MM, reject_outliers: bool = True) -> DiscrepancyResult:
    """Find and name the effects missing from the model that explain the measured deviations.

    Without repeats or ``sigma_mm`` the floor is estimated from the residual and the result says
    so. Gross outliers are excluded from every fit and listed (``reject_outliers``). See
    :mod:`gls_calibration.discrepancy` for the method and thresholds.

    Parameters
    ----------
    commanded_xy : array_like, shape (N, 2)
        Nominal targets in the gls frame, mm.
    measured_xy : array_like, shape (N, 2) or (R, N, 2)
        Measured mark positions in any frame a rigid motion away, mm; (R, N, 2) for R repeated
        measurements of the same plate.
    geometry : HeadGeometry, optional
        The nominal head; the default one when None.
    known_effects : HeadEffects or mapping, optional
        Effects already in the model; they stay fixed unless named again (then refitted).
    t : array_like, shape (N,), optional
        Marking time, s (``thermal_drift`` is a candidate only with it).
    sigma_mm : float or array_like, shape (N,), optional
        Per-axis standard uncertainty of each measured point, mm, stated (a number) or per point;
        ignored with repeats.
    user_effects : sequence of UserEffect, optional
        They join the candidates.
    candidates : sequence of str, optional
        Effect names to try; defaults to every effect of
        :data:`gls_calibration.geometry.effect_table.EFFECT_TABLE` and the user effects.
    criterion : str, default "bic"
        The selection criterion, one of ``CRITERIA``.
    name_threshold : float, default 10.0
        Criterion gain an effect needs to be named.
    indistinguishable_within : float, default 6.0
        Criterion difference within which two candidates cannot be told apart.
    structure_alpha : float, default 1e-3
        Significance level of the structure test.
    max_steps : int, default 6
        Most effects named; non-negative.
    min_noise_mm : float, default 1e-4
        Lower bound of the estimated noise, mm.
    reject_outliers : bool, default True
        Exclude gross outliers from every fit.

    Returns
    -------
    DiscrepancyResult
        The named effects, the steps, the residual fields, the noise floor and the verdict.

    Raises
    ------
    ValueError
        For bad points or times (shapes, too few, not finite), a bad sigma, an unknown criterion or
        effect name, bad ``known_effects``, a negative ``max_steps``, user effect names that repeat
        or a user effect that fails :func:`~gls_calibration.geometry.effect_table.check_user_effect`.

    Examples
    --------
    A head whose X galvo gains 0.4 %, measured with 3 um noise:

    >>> from gls_calibration.fiducials.targets import grid_targets
    >>> from gls_calibration.geometry.kinematics import HeadGeometry, inverse
    >>> from gls_calibration.geometry.optics import PhysicalHead
    >>> targets = grid_targets(7, 180.0)
    >>> angles = inverse(HeadGeometry(), targets[:, 0], targets[:, 1])
    >>> landed = PhysicalHead(effects={"galvo_gain_x": 0.004}).land(angles.alpha_x, angles.alpha_y)[:, :2]
    >>> landed += np.random.default_rng(0).normal(0.0, 0.003, landed.shape)
    >>> result = explain(targets, landed, sigma_mm=0.003)
    >>> result.named_effects, result.verdict.verdict
    (('galvo_gain_x',), 'explained')
    """
    evidence = independent_noise(measured_xy, sigma_mm)
    commanded_xy, measured, t = check_inputs(commanded_xy, evidence.measured_xy, t)
    geometry = geometry if geometry is not None else HeadGeometry()
    known = as_effects(known_effects)
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {', '.join(CRITERIA)}, got {criterion!r}")
    if max_steps < 0:
        raise ValueError(f"max_steps must be >= 0, got {max_steps}")
    for effect in user_effects:
        check_user_effect(effect)
    pool = candidate_pool(candidates, t, user_effects)

    full = Predictor(geometry, commanded_xy, t, user_effects)
    outliers = _outliers(full, measured, known, min_noise_mm) if reject_outliers else ()
    inliers = np.ones(len(commanded_xy), dtype=bool)
    inliers[[o.index for o in outliers]] = False
    predict = full.subset(inliers) if outliers else full
    points, measured = predict.commanded_xy, measured[inliers]
    t = predict.t
    sigma_points = None if evidence.sigma_axis_mm is None else evidence.sigma_axis_mm[inliers]
    evidence = replace(evidence, measured_xy=measured, sigma_axis_mm=sigma_points)

    first = fit(predict, measured, (), known, np.zeros(0), 1.0)
    noise = estimate_noise_floor(points, first.residual_xy, t, min_sigma_mm=min_noise_mm)
    floor = floor_evidence(evidence, noise)
    # the criterion's sigma: the independent one, but never below the roughness of the current residual
    # (re-estimated at every step), so that structure finer than a smooth field is not taken as evidence
    # for a library effect; without independent evidence, the roughness of the first residual (fixed)
    sigma = noise.sigma_axis_mm if sigma_points is None else sigma_points
    first = fit(predict, measured, (), known, np.zeros(0), sigma)    # its chi-square on that sigma
    selection = Selection(predict, measured, known, noise, sigma, 1.0,
                          max(noise.noise_floor_mm, floor.noise_floor_mm),
                          pool, criterion, name_threshold, indistinguishable_within, structure_alpha, min_noise_mm)
    structure_before = structure_test(points, first.residual_xy, noise, t, alpha=structure_alpha,
                                      min_sigma_mm=min_noise_mm)

    steps: list[EffectStep] = []
    dropped: set[str] = set()
    implausible: dict[str, Implausible] = {}
    notes = [RIGID_NOTE]
    if outliers:
        notes.append(f"{len(outliers)} gross outlier(s) excluded from every fit: "
                     + ", ".join(f"#{o.index} ({o.size_mm:.3f} mm at {o.position_mm[0]:.1f}, {o.position_mm[1]:.1f})"
                                 for o in outliers) + ".")
    if t is not None and time_follows_position(points, t):
        notes.append("Marking time follows the position (row-wise order): a drift growing with time looks like "
                     "a static field effect here (thermal_drift is confounded with axis_skew, the gains and "
                     "mirror_distance). Mark in a shuffled or repeated order to tell them apart.")
    stop_reason = f"reached max_steps = {max_steps}" if max_steps else "max_steps = 0"
    current, structure = first, structure_before
    for number in range(1, max_steps + 1):
        # with independent evidence, structure that is not smooth (above the floor) is still worth a step
        at_floor = sigma_points is None or against_floor(current.residual_xy, floor, len(current.vector),
                                                         alpha=structure_alpha)[0]
        if not structure.is_structure and at_floor:
            stop_reason = (f"no smooth structure is left (F-test p = {structure.p_value:.3g} >= {structure_alpha:g}; "
                           f"RMS {current.rms_mm:.4f} mm, {floor.source} floor {floor.noise_floor_mm:.4f} mm)")
            break
        if sigma_points is not None:
            roughness = estimate_noise_floor(points, current.residual_xy, t, fitted_parameters=len(current.vector),
                                             min_sigma_mm=min_noise_mm).sigma_axis_mm
            selection = replace(selection, inflation=max(1.0, roughness / floor.sigma_axis_mm))
        named, current, why = step(selection, current, dropped, notes, implausible, number)
        if named is None:
            stop_reason = why
            break
        steps.append(named)
        structure = selection.structure(current)
    structure_after = selection.structure(current)
    # an effect implausible at one step but named at a later one is named, not "not named"
    implausible = {name: entry for name, entry in implausible.items() if name not in current.names}
    if not steps:
        notes.append("No missing effect named: " + stop_reason + ".")
    if implausible:
        notes.append("Not named, physically implausible: "
                     + "; ".join(f"{i.name} ({i.why})" for i in implausible.values()) + ".")
    if floor.source != "residual" or "disagreement" in floor.cross_check:
        notes.append(f"Noise floor ({floor.source}): {floor.cross_check}.")
    else:
        notes.append(f"Noise floor: {floor.cross_check}.")
    location_before = locate_residual(points, first.residual_xy, t, noise=floor)
    location_after = locate_residual(points, current.residual_xy, t, noise=floor)
    verdict = judge(points, current.residual_xy, floor, structure_after, location_after, len(current.vector),
                    alpha=structure_alpha)
    uncertainty = {name: tuple(current.uncertainty(name).values()) for name in current.names}
    # Name only what the data separate from the rigid motion and the other candidates (issue 31)
    separable = separability(predict, current, known, pool,
                             np.asarray(selection.sigma_axis_mm, dtype=float) * selection.inflation)
    named, groups = naming(separable, notes)
    return DiscrepancyResult(
        geometry=geometry, known_effects=known, model_effects=current.effects,
        model_uncertainty=MappingProxyType(uncertainty), named_effects=named, steps=tuple(steps),
        rms_before_mm=first.rms_mm, rms_after_mm=current.rms_mm, noise=noise,
        structure_before=structure_before, structure_after=structure_after,
        location_before=location_before, location_after=location_after,
        alignment_before=first.alignment, alignment_after=current.alignment,
        commanded_xy=points, residual_before_xy=first.residual_xy, residual_after_xy=current.residual_xy,
        t=t, criterion=criterion, stop_reason=stop_reason, notes=tuple(notes),
        floor=floor, outliers=outliers, implausible=tuple(implausible.values()), verdict=verdict,
        rigid_correlation=MappingProxyType(rigid_correlation(predict, current, sigma)),
        user_effects=tuple(user_effects), user_values=current.user_values, inliers=inliers,
        fitted_effects=current.names, named_groups=groups, separability=separable)


def naming(records: Sequence[Separability], notes: list[str]) -> tuple[tuple[str, ...], tuple[tuple[str, ...], ...]]:
    """Named effects and named groups from the separability of the fitted ones; notes say why not alone."""
    named, groups, seen = [], [], set()
    for record in records:
        if not record.separable_from_rigid:
            notes.append(f"{record.name} is fitted but not named: what survives the rigid alignment is "
                         f"{record.z_rigid:.1f} standard errors (< {SEPARABLE_AT:g}), i.e. the data cannot tell it "
                         "from a rotation or shift of the measured frame.")
        elif record.named_alone:
            named.append(record.name)
        elif frozenset(record.group) not in seen:
            seen.add(frozenset(record.group))
            groups.append(record.group)
            notes.append(f"{record.name} is named only as a group with {', '.join(record.group[1:])}: with any of them "
                         f"also fitted, its size is below {SEPARABLE_AT:g} standard errors ("
                         + ", ".join(f"{n} {z:.1f}" for n, z in record.z_with.items())
                         + "); the data say one of them, not which.")
    return tuple(named), tuple(groups)
