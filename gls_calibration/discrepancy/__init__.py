"""Discrepancy workflow: where the head disagrees with its model and which effect is missing.

Discrepancy workflow: where does the head disagree with its model, and which named effect is missing?

Given commanded targets ``Q`` (gls frame, mm) and measured mark positions ``M`` (any 2-D frame that is
a rigid motion away from gls, mm), the workflow

1. predicts the landing points with the current model: the controller commands through the NOMINAL
   kinematics (``alpha = kinematics.inverse(geometry, Q)``), the head lands them as the extended
   model :class:`gls_calibration.geometry.optics.PhysicalHead` (nominal geometry plus the effects known so far)
   says, plus the deviation of any user effect; only the in-plane x, y of the landing point are used;
2. aligns the measurement rigidly to the prediction (2-D Kabsch, closed form, no scale) and takes the
   residual field ``aligned M - prediction``. Rotation and translation of the measured frame are not
   observable and are never named as effects; the alignment is re-solved inside every residual
   evaluation of every fit, so no effect can absorb them or be blamed for them;
3. lists gross outliers (a point departing from a robust smooth fit with no neighbour departing
   alike) and leaves them out of everything that follows;
4. takes the noise floor from independent evidence: repeated measurements (``measured`` (R, N, 2)),
   per-point or stated ``sigma_mm``; the residual's roughness (what a smooth polynomial field, degree
   <= 5 in x, y plus t, t*x, t*y, leaves) is only a cross-check, and the floor itself when there is
   no evidence (the result says so). The same smooth fit gives the structure test: an F-test of the
   smooth field against the rigid alignment alone;
5. for every candidate effect (the table's and the user's) fits its parameters together with the
   effects already named (one Gauss-Newton step screens them, the five best are fitted fully with
   ``scipy.optimize.least_squares``) and scores it with an information criterion on the Gaussian
   likelihood: BIC = chi^2 + k ln(n) (or AIC with 2 k), n = 2 N observations, chi^2 on the floor's
   sigma, inflated by the current residual's roughness when that is larger (structure finer than a
   smooth field is not evidence for a library effect). The best PLAUSIBLE candidate (every value of
   the joint fit inside the table's ranges; others are listed as implausible) is named only if it
   improves the criterion by at least ``name_threshold`` (default 10, "very strong" on the
   Kass-Raftery scale). Candidates that are themselves significant and either within
   ``indistinguishable_within`` (default 6) of the best or whose fitted landing fields differ from
   the best's by less than the noise floor (RMS after rigid alignment) are reported as
   indistinguishable from it; a backward pass drops effects named earlier that the others explain;
6. repeats while smooth structure is left or the residual is above the independent floor, and no
   more than ``max_steps`` times;
7. names only what the data separate (:mod:`.separability`): a fitted effect whose field, once the
   rigid motion and the other fitted effects are profiled out, is below ``SEPARABLE_AT`` standard
   errors is not named; one that falls below it when some other candidate is also profiled out is
   named as a group with those candidates (``named_groups``); ``fitted_effects`` is what the model
   holds either way;
8. gives the verdict (:mod:`.verdict`): ``explained`` or ``unexplained_structure`` with the RMS above
   the floor and the dominant pattern in words. Nothing above the floor is called noise.

Files: :mod:`.results` (types), :mod:`.residual_statistics` (roughness, structure test, location),
:mod:`.noise_floor` (independent evidence), :mod:`.outliers`, :mod:`.fitting` (prediction, effect
fits, plausibility, correlation with the rigid motion), :mod:`.selection` (:func:`explain`),
:mod:`.verdict`, :mod:`.run_verdict` (the lines of a calibration run's report), :mod:`.observability`.
The effects, their units, typical sizes and plausible ranges come from
:data:`gls_calibration.geometry.effect_table.EFFECT_TABLE`; the rigid alignment is
:func:`gls_calibration.registration.rigid.align_rigid_2d`.

RMS figures are of the 2-D residual vector, ``sqrt(mean(dx^2 + dy^2))``; the noise floor is on the
same footing (``sqrt(2)`` times the per-axis sigma), so a residual that is pure noise has RMS close to
the noise floor.
"""
from __future__ import annotations

from gls_calibration.discrepancy.fitting import fit_effects, physical_prediction
from gls_calibration.discrepancy.noise_floor import NOISE_SOURCES, average_repeats
from gls_calibration.discrepancy.observability import ObservabilityReport, observability_report
from gls_calibration.discrepancy.residual_statistics import (
    MIN_POINTS, estimate_noise_floor, locate_residual, structure_test)
from gls_calibration.discrepancy.results import (
    CandidateScore, DiscrepancyResult, EffectsFit, EffectStep, FloorEvidence, Implausible, NoiseFloor, Outlier,
    ResidualLocation, StructureTest, Verdict)
from gls_calibration.discrepancy.run_verdict import run_verdict_lines
from gls_calibration.discrepancy.selection import CRITERIA, MIN_NOISE_MM, RIGID_NOTE, explain, fit_inliers
from gls_calibration.discrepancy.separability import SEPARABLE_AT, Separability, separability
from gls_calibration.discrepancy.verdict import naming_phrase, verdict_lines
from gls_calibration.registration.rigid import RigidAlignment2D, align_rigid_2d

__all__ = [
    "CRITERIA", "MIN_NOISE_MM", "MIN_POINTS", "NOISE_SOURCES", "RIGID_NOTE", "SEPARABLE_AT", "CandidateScore",
    "DiscrepancyResult", "EffectStep", "EffectsFit", "FloorEvidence", "Implausible", "NoiseFloor",
    "ObservabilityReport", "Outlier", "ResidualLocation", "RigidAlignment2D", "Separability", "StructureTest",
    "Verdict", "align_rigid_2d", "average_repeats", "estimate_noise_floor", "explain", "fit_effects",
    "fit_inliers", "locate_residual", "naming_phrase", "observability_report", "physical_prediction",
    "run_verdict_lines", "separability", "structure_test", "verdict_lines",
]
