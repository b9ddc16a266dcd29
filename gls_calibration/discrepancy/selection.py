"""Selection: which candidate effects to name, one step at a time, scored by an information criterion.

Each step fits every remaining candidate together with the effects already named, names the one
that improves the criterion most (if by at least ``name_threshold``), drops effects named earlier
that the others now explain (backward pass), and lists the candidates indistinguishable from it.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np

from gls_calibration.discrepancy.fitting import Predictor, as_effects, check_inputs, fit
from gls_calibration.discrepancy.residual_statistics import (
    estimate_noise_floor, locate_residual, rms, structure_test)
from gls_calibration.discrepancy.results import (
    CandidateScore, DiscrepancyResult, EffectsFit, EffectStep, NoiseFloor, StructureTest)
from gls_calibration.effect_table import EFFECT_TABLE, EFFECTS
from gls_calibration.kinematics import HeadGeometry
from gls_calibration.optics import HeadEffects
from gls_calibration.registration import align_rigid_2d

CRITERIA = ("bic", "aic")
RIGID_PARAMETERS = 3     # rotation and translation of the measured frame
RIGID_NOTE = ("Rotation and translation between the measured frame and the gls frame are removed by a "
              "rigid alignment: they are not observable from these data and are never named as effects.")


@dataclass(frozen=True)
class Selection:
    """What every step of one selection shares: the data, the model so far, the thresholds."""

    predict: Predictor
    measured_xy: np.ndarray
    known: HeadEffects
    noise: NoiseFloor
    pool: tuple[str, ...]
    criterion: str
    name_threshold: float
    indistinguishable_within: float
    structure_alpha: float
    min_noise_mm: float

    @property
    def observations(self) -> int:
        """Number of scalar observations (2 per point)."""
        return 2 * len(self.measured_xy)

    def information(self, model: EffectsFit) -> float:
        """Information criterion of a fit on the Gaussian likelihood with sigma = noise sigma per axis."""
        penalty = math.log(self.observations) if self.criterion == "bic" else 2.0
        parameters = RIGID_PARAMETERS + len(model.vector)
        return model.rss_mm2 / self.noise.sigma_axis_mm ** 2 + penalty * parameters

    def fit(self, names: Sequence[str], initial: np.ndarray) -> EffectsFit:
        """Fit ``names`` from ``initial`` on top of the known effects."""
        return fit(self.predict, self.measured_xy, names, self.known, initial, self.noise.sigma_axis_mm)

    def extend(self, model: EffectsFit, name: str) -> EffectsFit:
        """Fit ``model``'s effects plus ``name`` (starting from the known value of ``name``)."""
        initial = np.concatenate([model.vector, np.asarray(self.known.get(name), dtype=float)])
        return self.fit(model.names + (name,), initial)

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
        if name == best or gain < selection.name_threshold:
            continue
        _, moved = align_rigid_2d(alternative.predicted_xy, model.predicted_xy)
        difference = rms(moved - model.predicted_xy)
        if best_gain - gain < selection.indistinguishable_within or (
                difference < selection.noise.noise_floor_mm and gain >= 0.5 * best_gain):
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
            worsening[name] = (selection.information(reduced) - selection.information(model), reduced)
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


def step(selection: Selection, current: EffectsFit, dropped: set[str],
         notes: list[str]) -> tuple[EffectStep | None, EffectsFit, str]:
    """One forward step from ``current``: the step named (or None), the new model and, if none, why."""
    remaining = [name for name in selection.pool if name not in current.names and name not in dropped]
    if not remaining:
        return None, current, "no candidate effect left"
    base_information = selection.information(current)
    fits = {name: selection.extend(current, name) for name in remaining}
    improvement = {name: base_information - selection.information(f) for name, f in fits.items()}
    best = max(improvement, key=improvement.get)
    if improvement[best] < selection.name_threshold:
        return None, current, (f"no candidate improves the {selection.criterion.upper()} by "
                               f"{selection.name_threshold:g} or more (best: {best}, {improvement[best]:.1f})")
    scores = score_candidates(selection, fits, improvement, fits[best])
    model, removed = prune(selection, best, fits[best], notes)
    dropped.update(removed)
    found = (rivals_after_pruning(selection, best, model) if removed
             else rivals(selection, best, model, fits, base_information))
    if found:
        notes.append(f"{best} is indistinguishable from {', '.join(found)} with these data (criterion within "
                     f"{selection.indistinguishable_within:g} or landing fields within the noise floor).")
    spec = EFFECT_TABLE[best]
    named = EffectStep(best, MappingProxyType(model.parameters(best)), MappingProxyType(model.uncertainty(best)),
                       MappingProxyType(dict(zip(spec.parameter_names, spec.units))), tuple(found),
                       float(improvement[best]), current.rms_mm, model.rms_mm, scores, tuple(removed))
    return named, model, ""


def time_follows_position(points_xy: np.ndarray, t: np.ndarray, threshold: float = 0.9) -> bool:
    """True when a plane in x, y explains more than ``threshold`` of the variance of the marking time."""
    design = np.column_stack([np.ones(len(points_xy)), points_xy])
    fitted = design @ np.linalg.lstsq(design, t, rcond=None)[0]
    variance = float(np.var(t))
    return variance > 0.0 and 1.0 - float(np.var(t - fitted)) / variance > threshold


def candidate_pool(candidates: Sequence[str] | None, t: np.ndarray | None) -> tuple[str, ...]:
    """The candidate effects (default: the whole table), thermal_drift left out without marking time."""
    pool = list(EFFECTS) if candidates is None else list(candidates)
    for name in pool:
        if name not in EFFECTS:
            raise ValueError(f"unknown effect {name!r}; known effects: {', '.join(EFFECTS)}")
    if t is None and "thermal_drift" in pool:
        pool.remove("thermal_drift")   # invisible without marking time
    return tuple(pool)


def explain(commanded_xy, measured_xy, geometry: HeadGeometry | None = None,
            known_effects: HeadEffects | Mapping | None = None, t=None, *,
            candidates: Sequence[str] | None = None, criterion: str = "bic", name_threshold: float = 10.0,
            indistinguishable_within: float = 6.0, structure_alpha: float = 1e-3, max_steps: int = 4,
            min_noise_mm: float = 1e-4) -> DiscrepancyResult:
    """Find and name the effects missing from the model that explain the measured deviations.

    ``commanded_xy`` (N, 2): nominal targets in the gls frame (mm); ``measured_xy`` (N, 2): measured
    mark positions in any frame a rigid motion away (mm); ``t`` (N,): marking time (s), optional
    (``thermal_drift`` is a candidate only with it). ``known_effects`` are already in the model and
    stay fixed unless named again (then refitted). ``candidates`` defaults to every effect of
    :data:`gls_calibration.effect_table.EFFECT_TABLE`. See :mod:`gls_calibration.discrepancy` for the
    method and thresholds.
    """
    commanded_xy, measured_xy, t = check_inputs(commanded_xy, measured_xy, t)
    geometry = geometry if geometry is not None else HeadGeometry()
    known = as_effects(known_effects)
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {', '.join(CRITERIA)}, got {criterion!r}")
    if max_steps < 0:
        raise ValueError(f"max_steps must be >= 0, got {max_steps}")
    pool = candidate_pool(candidates, t)

    predict = Predictor(geometry, commanded_xy, t)
    first = fit(predict, measured_xy, (), known, np.zeros(0), 1.0)
    noise = estimate_noise_floor(commanded_xy, first.residual_xy, t, min_sigma_mm=min_noise_mm)
    selection = Selection(predict, measured_xy, known, noise, pool, criterion, name_threshold,
                          indistinguishable_within, structure_alpha, min_noise_mm)
    structure_before = structure_test(commanded_xy, first.residual_xy, noise, t, alpha=structure_alpha,
                                      min_sigma_mm=min_noise_mm)

    steps: list[EffectStep] = []
    dropped: set[str] = set()
    notes = [RIGID_NOTE]
    if t is not None and time_follows_position(commanded_xy, t):
        notes.append("Marking time follows the position (row-wise order): a drift growing with time looks like "
                     "a static field effect here (thermal_drift is confounded with axis_skew, the gains and "
                     "mirror_distance). Mark in a shuffled or repeated order to tell them apart.")
    stop_reason = f"reached max_steps = {max_steps}" if max_steps else "max_steps = 0"
    current, structure = first, structure_before
    for _ in range(max_steps):
        if not structure.is_structure:
            stop_reason = (f"the residual is noise (F-test p = {structure.p_value:.3g} >= {structure_alpha:g}, "
                           f"RMS {current.rms_mm:.4f} mm vs noise floor {noise.noise_floor_mm:.4f} mm)")
            break
        named, current, why = step(selection, current, dropped, notes)
        if named is None:
            stop_reason = why
            break
        steps.append(named)
        structure = selection.structure(current)
    structure_after = selection.structure(current)
    if not steps:
        notes.append("No missing effect named: " + stop_reason + ".")
    uncertainty = {name: tuple(current.uncertainty(name).values()) for name in current.names}
    return DiscrepancyResult(
        geometry=geometry, known_effects=known, model_effects=current.effects,
        model_uncertainty=MappingProxyType(uncertainty), named_effects=current.names, steps=tuple(steps),
        rms_before_mm=first.rms_mm, rms_after_mm=current.rms_mm, noise=noise,
        structure_before=structure_before, structure_after=structure_after,
        location_before=locate_residual(commanded_xy, first.residual_xy, t, noise=noise),
        location_after=locate_residual(commanded_xy, current.residual_xy, t, noise=noise),
        alignment_before=first.alignment, alignment_after=current.alignment,
        commanded_xy=commanded_xy, residual_before_xy=first.residual_xy, residual_after_xy=current.residual_xy,
        t=t, criterion=criterion, stop_reason=stop_reason, notes=tuple(notes))
