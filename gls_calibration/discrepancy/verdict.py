"""The verdict: whether the rest after the named effects stays at the noise floor, and where.

The verdict: does what is left after the named effects stay at the noise floor, and if not, where is it?

``explained`` needs the final residual to be consistent with the floor (chi-square test at
``alpha``, or an RMS within 10 % of the floor, which a slightly mis-stated sigma gives) AND no smooth
structure left (the F-test of :func:`.residual_statistics.structure_test`). Otherwise the verdict is
``unexplained_structure`` with the RMS above the floor (in quadrature; when the residual is not above
the floor but the F-test finds smooth structure, the RMS of that smooth field) and the dominant pattern in
words: local near (x, y), periodic along x or y with period P, growing with r, a smooth field, or
point-to-point scatter. Nothing above the floor is ever called noise.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.special import gammaincc
from scipy.spatial import cKDTree

from gls_calibration.discrepancy.residual_statistics import smooth_basis, smooth_degree, rms
from gls_calibration.discrepancy.results import (
    DiscrepancyResult, FloorEvidence, ResidualLocation, StructureTest, Verdict)

#: An RMS within this factor of the floor is consistent with it whatever the chi-square says.
CLOSE_TO_FLOOR = 1.1
_PERIODS = 160   # trial periods between 2.5 grid pitches and half the field span


def _pitch(points_xy: np.ndarray) -> float:
    distances, _ = cKDTree(points_xy).query(points_xy, k=2)
    return max(float(np.median(distances[:, 1])), 1e-9)


def periodic_pattern(points_xy: np.ndarray, residual_xy: np.ndarray) -> tuple[float, str, float, float]:
    """Best sinusoid along x or y: (fraction of the residual's variance it explains, axis, period mm, amplitude mm)."""
    pitch = _pitch(points_xy)
    best = (0.0, "x", math.nan, 0.0)
    total = float(np.sum((residual_xy - residual_xy.mean(axis=0)) ** 2))
    if total <= 0.0:
        return best
    for axis, coordinate in (("x", points_xy[:, 0]), ("y", points_xy[:, 1])):
        span = float(np.ptp(coordinate))
        if span < 5.0 * pitch:
            continue
        periods = np.geomspace(2.5 * pitch, 0.5 * span, _PERIODS)   # at least two periods in the field
        phase = 2.0 * np.pi * coordinate[None, :] / periods[:, None]            # (P, N)
        cos, sin = np.cos(phase), np.sin(phase)
        centred = residual_xy - residual_xy.mean(axis=0)
        explained = np.zeros(len(periods))
        amplitude = np.zeros(len(periods))
        for component in range(2):     # least squares of a, b in a cos + b sin per period (2x2 normal equations)
            y = centred[:, component]
            cc, ss, cs = np.sum(cos * cos, 1), np.sum(sin * sin, 1), np.sum(cos * sin, 1)
            cy, sy = cos @ y, sin @ y
            det = np.maximum(cc * ss - cs * cs, 1e-12)
            a = (ss * cy - cs * sy) / det
            b = (cc * sy - cs * cy) / det
            explained += a * cy + b * sy
            amplitude = np.maximum(amplitude, np.hypot(a, b))
        index = int(np.argmax(explained))
        fraction = float(explained[index]) / total
        if fraction > best[0]:
            best = (fraction, axis, float(periods[index]), float(amplitude[index]))
    return best


def local_pattern(points_xy: np.ndarray, residual_xy: np.ndarray) -> tuple[float, tuple[float, float], float]:
    """Share of the residual energy in the most compact hot spot: (share, centre (x, y) mm, radius mm)."""
    energy = np.sum(residual_xy ** 2, axis=1)
    neighbours = min(9, len(points_xy))
    _, nearest = cKDTree(points_xy).query(points_xy, k=neighbours)
    smoothed = energy[nearest].mean(axis=1)
    peak = int(np.argmax(smoothed))
    hot = smoothed >= 0.25 * smoothed[peak]
    # keep the connected patch around the peak: points within the hot set closest to it
    distance = np.hypot(*(points_xy - points_xy[peak]).T)
    radius = float(np.max(distance[hot])) if np.any(hot) else 0.0
    patch = hot & (distance <= radius)
    if patch.sum() > 0.2 * len(points_xy):
        return 0.0, (float(points_xy[peak, 0]), float(points_xy[peak, 1])), radius
    share = float(energy[patch].sum() / max(energy.sum(), 1e-300))
    centre = np.average(points_xy[patch], axis=0, weights=energy[patch] + 1e-300)
    return share, (float(centre[0]), float(centre[1])), radius


def smooth_share(points_xy: np.ndarray, residual_xy: np.ndarray) -> float:
    """Fraction of the residual's energy a smooth polynomial field (degree <= 5) explains."""
    degree, _ = smooth_degree(len(points_xy), False)
    basis = smooth_basis(points_xy, None, degree, False)
    fitted = basis @ np.linalg.lstsq(basis, residual_xy, rcond=None)[0]
    total = float(np.sum(residual_xy ** 2))
    return float(np.sum(fitted ** 2)) / total if total > 0.0 else 0.0


def dominant_pattern(points_xy: np.ndarray, residual_xy: np.ndarray, location: ResidualLocation,
                     structure: StructureTest) -> str:
    """Return the pattern that carries most of the residual, in words."""
    share, centre, radius = local_pattern(points_xy, residual_xy)
    if share >= 0.5:
        return (f"local near (x, y) = ({centre[0]:.0f}, {centre[1]:.0f}) mm within ~{radius:.0f} mm "
                f"({share:.0%} of the residual energy)")
    fraction, axis, period, amplitude = periodic_pattern(points_xy, residual_xy)
    if fraction >= 0.4:
        return (f"periodic along {axis} with period {period:.1f} mm (amplitude {amplitude:.3f} mm, "
                f"{fraction:.0%} of the residual variance)")
    if location.rms_edge_mm > 1.5 * location.rms_centre_mm:
        return (f"growing with r (edge RMS {location.rms_edge_mm:.4f} mm, centre {location.rms_centre_mm:.4f} mm)")
    smooth = smooth_share(points_xy, residual_xy)
    if smooth >= 0.5 or structure.is_structure:
        return (f"a smooth field over the whole plate ({smooth:.0%} of the residual energy, "
                f"{math.sqrt(smooth) * rms(residual_xy):.4f} mm RMS, is a polynomial of degree <= 5; "
                f"F-test p = {structure.p_value:.2g})")
    return ("point-to-point scatter with no spatial pattern: more scatter than the floor says "
            "(an unmodelled noise source, or an optimistic uncertainty)")


def against_floor(residual_xy: np.ndarray, floor: FloorEvidence, fitted_parameters: int, *,
                  alpha: float = 1e-3) -> tuple[bool, float, float]:
    """Is the residual consistent with the floor? (consistent, chi-square p-value, RMS / floor)."""
    ratio = rms(residual_xy) / floor.noise_floor_mm
    dof = max(2 * len(residual_xy) - 3 - fitted_parameters, 1)
    chi2 = float(np.sum(residual_xy ** 2)) / floor.sigma_axis_mm ** 2
    p_value = float(gammaincc(0.5 * dof, 0.5 * chi2))   # chi-square survival function
    return p_value >= alpha or ratio <= CLOSE_TO_FLOOR, p_value, ratio


def judge(points_xy: np.ndarray, residual_xy: np.ndarray, floor: FloorEvidence, structure: StructureTest,
          location: ResidualLocation, fitted_parameters: int, *, alpha: float = 1e-3) -> Verdict:
    """Return the verdict on the final residual against the floor."""
    residual_rms = rms(residual_xy)
    consistent, p_value, ratio = against_floor(residual_xy, floor, fitted_parameters, alpha=alpha)
    unexplained = math.sqrt(max(residual_rms ** 2 - floor.noise_floor_mm ** 2, 0.0))
    findings = tuple(location.findings)
    if consistent and not structure.is_structure:
        pattern = (f"none above the {floor.source} floor: residual RMS {residual_rms:.4f} mm vs floor "
                   f"{floor.noise_floor_mm:.4f} mm")
        return Verdict("explained", unexplained, ratio, p_value, pattern, findings)
    pattern = dominant_pattern(points_xy, residual_xy, location, structure)
    if unexplained > 0.0:
        return Verdict("unexplained_structure", unexplained, ratio, p_value, pattern, findings)
    # The residual is not above the floor, yet the F-test finds smooth structure in it (the floor is
    # pessimistic, or the structure is small): it is structure, not noise, and its size is the RMS of
    # the smooth field, not the (zero) excess over the floor.
    structured = math.sqrt(smooth_share(points_xy, residual_xy)) * residual_rms
    return Verdict("unexplained_structure", structured, ratio, p_value, pattern, findings, below_floor=True)


def unexplained_phrase(verdict: Verdict, floor: FloorEvidence) -> str:
    """Return what is left unexplained, in words consistent with the verdict's figure."""
    if verdict.below_floor:
        return (f"{verdict.unexplained_rms_mm:.4f} mm RMS of smooth structure (F-test) remains below the "
                f"{floor.source} noise floor")
    return f"{verdict.unexplained_rms_mm:.4f} mm RMS remains above the {floor.source} noise floor"


def naming_phrase(result: DiscrepancyResult) -> str:
    """Return the named effects and groups in words: ``a, b and one of c / d`` (``no effect`` when none).

    Parameters
    ----------
    result : DiscrepancyResult
        The workflow's result.

    Returns
    -------
    str
        The phrase.
    """
    parts = list(result.named_effects) + [f"one of {' / '.join(group)}" for group in result.named_groups]
    if not parts:
        return "no effect"
    return parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1]


def verdict_lines(result: DiscrepancyResult) -> list[str]:
    """Return the verdict in a few Markdown lines, for the discrepancy report and the calibration run's report.

    Parameters
    ----------
    result : DiscrepancyResult
        The workflow's result.

    Returns
    -------
    list of str
        The verdict (explained or not, against which floor), then notes on the floor, outliers,
        groups and implausible fits.
    """
    verdict, floor = result.verdict, result.floor
    named = naming_phrase(result)
    if verdict.verdict == "explained":
        lines = [f"**Verdict: explained.** With {named} named, the residual is {result.rms_after_mm:.4f} mm RMS "
                 f"against a {floor.source} noise floor of {floor.noise_floor_mm:.4f} mm "
                 f"(ratio {verdict.ratio_to_floor:.2f})."]
    else:
        lines = [f"**Verdict: unexplained structure.** With {named} named, {unexplained_phrase(verdict, floor)} "
                 f"(residual {result.rms_after_mm:.4f} mm vs floor "
                 f"{floor.noise_floor_mm:.4f} mm, {verdict.ratio_to_floor:.2f}x) that no effect of the library"
                 + (" or the user effects" if result.user_effects else "")
                 + (" explains within the steps allowed (the search stopped at max_steps; more steps may explain more)."
                    if result.stop_reason.startswith("reached max_steps") else " explains."),
                 f"Dominant pattern: {verdict.pattern}."]
        if verdict.below_floor:
            lines.append("The residual is smaller than the stated noise floor, yet not noise: a smooth field explains "
                         "part of it beyond chance, so the floor is pessimistic or the structure is small.")
    if floor.source == "residual":
        lines.append("The floor was estimated from the residual itself (no repeats, per-point sigma or stated sigma): "
                     "structure finer than a smooth field would be counted in it, so this verdict cannot rule it out.")
    else:
        lines.append(f"Cross-check of the floor: {floor.cross_check}.")
    if result.outliers:
        lines.append(f"{len(result.outliers)} gross outlier(s) were excluded from every fit and are listed.")
    if result.named_groups:
        lines.append("A group is named when its effects move the marks alike at this noise: with any one of them "
                     "fitted the others add less than the separability threshold (see the notes); the data say "
                     "one of them, not which.")
    if result.implausible:
        lines.append("Not named because the fit was physically implausible: "
                     + ", ".join(i.name for i in result.implausible) + ".")
    return lines
