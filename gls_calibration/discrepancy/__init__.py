"""Discrepancy workflow: where does the head disagree with its model, and which named effect is missing?

Given commanded targets ``Q`` (gls frame, mm) and measured mark positions ``M`` (any 2-D frame that is
a rigid motion away from gls, mm), the workflow

1. predicts the landing points with the current model: the controller commands through the NOMINAL
   kinematics (``alpha = kinematics.inverse(geometry, Q)``), the head lands them as the extended
   model :class:`gls_calibration.optics.PhysicalHead` (nominal geometry plus the effects known so far)
   says; only the in-plane x, y of the landing point are used;
2. aligns the measurement rigidly to the prediction (2-D Kabsch, closed form, no scale) and takes the
   residual field ``aligned M - prediction``. Rotation and translation of the measured frame are not
   observable and are never named as effects; the alignment is re-solved inside every residual
   evaluation of every fit, so no effect can absorb them or be blamed for them;
3. estimates the measurement noise floor from the data: a smooth polynomial field (degree <= 5 in x, y,
   plus t, t*x, t*y when marking time is given) is fitted to the residual, and what it leaves is taken
   as noise (unbiased with the residual degrees of freedom). The same fit gives the structure test:
   an F-test of the smooth field against the rigid alignment alone;
4. for every candidate effect of the library fits its parameters together with the effects already
   named (``scipy.optimize.least_squares`` on the aligned residual) and scores it with an information
   criterion on the Gaussian likelihood with sigma = noise floor: BIC = RSS / sigma^2 + k ln(n) (or AIC
   with 2 k), n = 2 N observations. The best candidate is named only if it improves the criterion by at
   least ``name_threshold`` (default 10, "very strong" on the Kass-Raftery scale). Candidates that are
   themselves significant and either within ``indistinguishable_within`` (default 6) of the best or whose
   fitted landing fields differ from the best's by less than the noise floor (RMS after rigid alignment)
   are reported as indistinguishable from it;
5. adds the best to the model and repeats until the residual is noise (F-test p >= ``structure_alpha``)
   or no candidate is significant.

Files: :mod:`.results` (types), :mod:`.residual_statistics` (noise floor, structure test, location),
:mod:`.fitting` (prediction, effect fits), :mod:`.selection` (:func:`explain`), :mod:`.observability`.
The effects, their units, typical sizes and plausible ranges come from
:data:`gls_calibration.effect_table.EFFECT_TABLE`; the rigid alignment is
:func:`gls_calibration.registration.align_rigid_2d`.

RMS figures are of the 2-D residual vector, ``sqrt(mean(dx^2 + dy^2))``; the noise floor is on the
same footing (``sqrt(2)`` times the per-axis sigma), so a residual that is pure noise has RMS close to
the noise floor.
"""
from __future__ import annotations

from gls_calibration.discrepancy.fitting import fit_effects, physical_prediction
from gls_calibration.discrepancy.observability import ObservabilityReport, observability_report
from gls_calibration.discrepancy.residual_statistics import (
    MIN_POINTS, estimate_noise_floor, locate_residual, structure_test)
from gls_calibration.discrepancy.noise_floor import NOISE_SOURCES, average_repeats
from gls_calibration.discrepancy.results import (
    CandidateScore, DiscrepancyResult, EffectsFit, EffectStep, FloorEvidence, Implausible, NoiseFloor, Outlier,
    ResidualLocation, StructureTest, Verdict)
from gls_calibration.discrepancy.run_verdict import run_verdict_lines
from gls_calibration.discrepancy.selection import CRITERIA, RIGID_NOTE, explain
from gls_calibration.discrepancy.verdict import verdict_lines
from gls_calibration.registration import RigidAlignment2D, align_rigid_2d

__all__ = [
    "CRITERIA", "MIN_POINTS", "NOISE_SOURCES", "RIGID_NOTE", "CandidateScore", "DiscrepancyResult", "EffectStep",
    "EffectsFit", "FloorEvidence", "Implausible", "NoiseFloor", "ObservabilityReport", "Outlier", "ResidualLocation",
    "RigidAlignment2D", "StructureTest", "Verdict", "align_rigid_2d", "average_repeats", "estimate_noise_floor",
    "explain", "fit_effects", "locate_residual", "observability_report", "physical_prediction", "run_verdict_lines",
    "structure_test", "verdict_lines",
]
