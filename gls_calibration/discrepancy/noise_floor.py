"""The noise floor from independent evidence: repeated measurements, per-point uncertainties, a stated value.

The residual's own roughness (:func:`.residual_statistics.estimate_noise_floor`) is only a
cross-check: structure the library cannot explain raises it, so it cannot tell structure from noise.
In order of preference the floor comes from

- ``repeats``: the same plate measured R times (``measured`` of shape (R, N, 2)); each repeat is
  aligned rigidly onto their mean, the scatter about the mean gives the per-axis sigma, and the fit
  uses the mean (sigma / sqrt(R));
- ``per_point``: one per-axis standard uncertainty per point (``sigma_mm`` of shape (N,));
- ``stated``: one per-axis standard uncertainty for every point (``sigma_mm`` a number);
- ``residual``: none of these; the floor is the residual estimate, and the report says so.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from gls_calibration.common.validation import as_finite_array
from gls_calibration.discrepancy.results import FloorEvidence, NoiseFloor
from gls_calibration.registration.rigid import align_rigid_2d

NOISE_SOURCES = ("repeats", "per_point", "stated", "residual")
#: The residual estimate and the independent floor disagree when their ratio leaves [1/x, x].
DISAGREEMENT_RATIO = 1.3
#: Per-axis scatter of repeats (mm) at or below which they count as identical (copies, not repeats).
NO_SCATTER_MM = 1e-9


@dataclass(frozen=True, eq=False)
class IndependentNoise:
    """The data the fit uses and the per-axis sigma of each of its points."""

    measured_xy: np.ndarray          # (N, 2): the measurement, or the mean of the repeats
    sigma_axis_mm: np.ndarray | None  # (N,) per-axis sigma of each point of ``measured_xy``; None: no evidence
    source: str
    repeats: int


def average_repeats(measured) -> tuple[np.ndarray, float]:
    """Mean (N, 2) of R rigidly aligned repeats (R, N, 2) and the per-axis sigma of ONE measurement.

    Every repeat is aligned onto the current mean (twice: the first mean is that of the raw repeats);
    sigma^2 = sum of squared departures from the mean / (2 N (R - 1) - 3 (R - 1)).
    Repeats without scatter (identical up to a rigid motion, sigma <= ``NO_SCATTER_MM``) carry no
    evidence of the noise: ValueError, rather than a zero floor nothing can be compared with.
    """
    stack = as_finite_array(measured, "measured_xy", ndim=3)
    repeats, points = stack.shape[0], stack.shape[1]
    if repeats < 2 or stack.shape[2] != 2:
        raise ValueError(f"repeated measurements must have the shape (R >= 2, N, 2), got {stack.shape}")
    aligned = stack.copy()
    for _ in range(2):
        mean = aligned.mean(axis=0)
        aligned = np.stack([align_rigid_2d(repeat, mean)[1] for repeat in stack])
    mean = aligned.mean(axis=0)
    dof = max(2 * points * (repeats - 1) - 3 * (repeats - 1), 1)
    sigma = math.sqrt(float(np.sum((aligned - mean) ** 2)) / dof)
    if not sigma > NO_SCATTER_MM:
        raise ValueError(f"repeats show no scatter: the noise floor cannot be estimated from them (the {repeats} "
                         f"repeats are identical up to a rigid motion, per-axis scatter {sigma:.3g} mm; "
                         f"give one set without the repeat column and state the uncertainty: "
                         f"--sigma or a sigma column)")
    return mean, sigma


def independent_noise(measured, sigma_mm=None) -> IndependentNoise:
    """Sort out the evidence: repeats first, then per-point, then stated sigma; else none."""
    array = np.asarray(measured, dtype=float)
    if array.ndim == 3:
        mean, sigma = average_repeats(array)
        count = array.shape[0]
        return IndependentNoise(mean, np.full(len(mean), sigma / math.sqrt(count)), "repeats", count)
    if sigma_mm is None:
        return IndependentNoise(array, None, "residual", 1)
    sigma = as_finite_array(sigma_mm, "sigma_mm")
    if np.any(sigma <= 0.0):
        raise ValueError("sigma_mm must be > 0 (mm, per axis)")
    if sigma.ndim == 0:
        return IndependentNoise(array, np.full(len(array), float(sigma)), "stated", 1)
    if sigma.shape != (len(array),):
        raise ValueError(f"sigma_mm must be a number or hold one value per point ({len(array)}), "
                         f"got shape {sigma.shape}")
    return IndependentNoise(array, sigma, "per_point", 1)


def floor_evidence(evidence: IndependentNoise, residual_estimate: NoiseFloor) -> FloorEvidence:
    """Return the floor the verdict uses and the cross-check against the residual's roughness."""
    estimate = residual_estimate.noise_floor_mm
    if evidence.sigma_axis_mm is None:
        return FloorEvidence("residual", residual_estimate.sigma_axis_mm, estimate, estimate, 1,
                             "no independent evidence (repeats, per-point sigma or a stated sigma): the floor is "
                             "estimated from the residual itself, so structure finer than a smooth field would be "
                             "counted in it; give --sigma or a sigma column to test it")
    sigma = float(np.sqrt(np.mean(evidence.sigma_axis_mm ** 2)))
    floor = math.sqrt(2.0) * sigma
    ratio = estimate / floor
    if ratio > DISAGREEMENT_RATIO:
        text = (f"disagreement: the residual's roughness ({estimate:.4f} mm) is {ratio:.2f}x the {evidence.source} "
                f"floor ({floor:.4f} mm): the residual holds structure finer than a smooth field, or more scatter "
                f"than the evidence says; it is not counted as noise")
    elif ratio < 1.0 / DISAGREEMENT_RATIO:
        text = (f"disagreement: the residual's roughness ({estimate:.4f} mm) is only {ratio:.2f}x the "
                f"{evidence.source} floor ({floor:.4f} mm): the stated uncertainty may be pessimistic")
    else:
        text = f"agrees: the residual's roughness ({estimate:.4f} mm) is {ratio:.2f}x the {evidence.source} floor"
    return FloorEvidence(evidence.source, sigma, floor, estimate, evidence.repeats, text)
