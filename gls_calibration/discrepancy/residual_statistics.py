"""Residual statistics: the noise floor, the structure-or-noise test and where the residual lives.

All work on a residual field (N, 2) over the commanded points (N, 2), optionally with marking time
(N,). A smooth polynomial field (degree <= 5 in x, y, plus t, t*x, t*y) stands for what physical
effects can leave; what it cannot explain stands for noise.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.special import betainc

from gls_calibration.common.validation import as_finite_array, as_points
from gls_calibration.discrepancy.results import FloorEvidence, NoiseFloor, ResidualLocation, StructureTest

#: The fewest points the workflow accepts.
MIN_POINTS = 10


def f_survival(f_statistic: float, dof_model: int, dof_residual: int) -> float:
    """P(F > f) of the F distribution (scipy.special rather than scipy.stats: a quarter of the start-up)."""
    if f_statistic <= 0.0:
        return 1.0
    return float(betainc(0.5 * dof_residual, 0.5 * dof_model, dof_residual / (dof_residual + dof_model * f_statistic)))


def _normalised(points_xy: np.ndarray, t: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    centre = 0.5 * (points_xy.max(axis=0) + points_xy.min(axis=0))
    half = np.maximum(0.5 * (points_xy.max(axis=0) - points_xy.min(axis=0)), 1e-9)
    u = (points_xy - centre) / half
    tau = None
    if t is not None:
        span = max(float(np.ptp(t)), 1e-12)
        tau = 2.0 * (t - t.min()) / span - 1.0
    return u[:, 0], u[:, 1], tau


def smooth_basis(points_xy: np.ndarray, t: np.ndarray | None, degree: int, use_time: bool) -> np.ndarray:
    """Return the per-component design matrix: monomials x^i y^j (i + j <= degree), plus t, t*x, t*y."""
    u, v, tau = _normalised(points_xy, t)
    columns = [u ** i * v ** (total - i) for total in range(degree + 1) for i in range(total + 1)]
    if use_time and tau is not None:
        columns += [tau, tau * u, tau * v]
    return np.stack(columns, axis=1)


def smooth_degree(n_points: int, use_time: bool) -> tuple[int, bool]:
    """Return the highest degree (<= 5) whose basis keeps at most a third of the points per component."""
    for degree in range(5, 0, -1):
        terms = (degree + 1) * (degree + 2) // 2 + (3 if use_time else 0)
        if terms <= n_points / 3:
            return degree, use_time
    return 1, False


def _smooth_fit(points_xy: np.ndarray, residual_xy: np.ndarray, t: np.ndarray | None,
                degree: int | None = None, use_time: bool = True) -> tuple[float, int, int, bool]:
    """RSS of a smooth field fitted to the residual, its parameter count, degree and time use."""
    use_time = use_time and t is not None
    if degree is None:
        degree, use_time = smooth_degree(len(points_xy), use_time)
    basis = smooth_basis(points_xy, t, degree, use_time)
    coefficients, _, rank, _ = np.linalg.lstsq(basis, residual_xy, rcond=None)
    rss = float(np.sum((residual_xy - basis @ coefficients) ** 2))
    return rss, 2 * int(rank), degree, use_time


def estimate_noise_floor(points_xy, residual_xy, t=None, *, fitted_parameters: int = 0,
                         min_sigma_mm: float = 1e-4) -> NoiseFloor:
    """Noise of the residual field: what a smooth field (degree <= 5, plus time terms) cannot explain.

    Physical effects leave smooth residuals over the field; measurement noise does not. The
    residual sum of squares of the smooth fit over its degrees of freedom (minus ``fitted_parameters``
    already spent on the residual) estimates sigma^2 per axis without bias when the residual is pure
    noise and with little bias when it holds smooth structure. ``min_sigma_mm`` keeps noise-free data
    from giving a zero floor.
    """
    points_xy = as_points(points_xy, "points_xy", 2, min_length=MIN_POINTS)
    residual_xy = as_points(residual_xy, "residual_xy", 2, min_length=MIN_POINTS)
    t = None if t is None else as_finite_array(t, "t", ndim=1)
    rss, parameters, degree, uses_time = _smooth_fit(points_xy, residual_xy, t)
    dof = max(2 * len(points_xy) - parameters - int(fitted_parameters), 1)
    sigma = max(math.sqrt(rss / dof), float(min_sigma_mm))
    return NoiseFloor(sigma, math.sqrt(2.0) * sigma, degree, uses_time, dof)


def structure_test(points_xy, residual_xy, noise: NoiseFloor, t=None, *, fitted_parameters: int = 0,
                   alpha: float = 1e-3, min_sigma_mm: float = 1e-4) -> StructureTest:
    """F-test whether a smooth field explains the rigidly aligned residual better than nothing.

    F-test: does a smooth field explain the (rigidly aligned) residual better than nothing?

    The null model is the rigid alignment alone (3 parameters, already applied to the residual); the
    alternative is the smooth field of :func:`estimate_noise_floor`. The residual is structure when the
    p-value is below ``alpha``. The error variance never drops below the noise floor's minimum.
    """
    points_xy = np.asarray(points_xy, dtype=float)
    residual_xy = np.asarray(residual_xy, dtype=float)
    n = 2 * len(points_xy)
    rss0 = float(np.sum(residual_xy ** 2))
    rss1, parameters, _, _ = _smooth_fit(points_xy, residual_xy, None if t is None else np.asarray(t, float),
                                         noise.degree, noise.uses_time)
    dof_model = max(parameters - 3, 1)
    dof_residual = max(n - parameters - int(fitted_parameters), 1)
    variance = max(rss1 / dof_residual, min_sigma_mm ** 2)
    f_statistic = max(rss0 - rss1, 0.0) / dof_model / variance
    p_value = f_survival(f_statistic, dof_model, dof_residual)
    chi2_ratio = rss0 / (n * noise.sigma_axis_mm ** 2)
    return StructureTest(float(f_statistic), p_value, dof_model, dof_residual, float(chi2_ratio),
                         bool(p_value < alpha))


def rms(vectors: np.ndarray) -> float:
    """RMS of the 2-D vectors (N, 2): sqrt(mean(dx^2 + dy^2)); NaN when empty."""
    return float(np.sqrt(np.mean(np.sum(vectors ** 2, axis=1)))) if len(vectors) else float("nan")


def _profile(coordinate: np.ndarray, residual_xy: np.ndarray, bins: int) -> tuple[tuple[float, float], ...]:
    edges = np.linspace(coordinate.min(), coordinate.max(), bins + 1)
    index = np.clip(np.searchsorted(edges, coordinate, side="right") - 1, 0, bins - 1)
    profile = []
    for b in range(bins):
        members = index == b
        if np.any(members):
            profile.append((float(0.5 * (edges[b] + edges[b + 1])), rms(residual_xy[members])))
    return tuple(profile)


def locate_residual(points_xy, residual_xy, t=None, *, noise: NoiseFloor | FloorEvidence | None = None,
                    bins: int = 5) -> ResidualLocation:
    """Where the residual lives: centre vs edge, x vs y component, profiles along x, y and time.

    ``findings`` states in words what stands out (ratios above 1.5, a significant time trend),
    compared with the noise floor when ``noise`` is given.
    """
    points_xy = np.asarray(points_xy, dtype=float)
    residual_xy = np.asarray(residual_xy, dtype=float)
    centre = 0.5 * (points_xy.max(axis=0) + points_xy.min(axis=0))
    radius = np.hypot(*(points_xy - centre).T)
    inner = radius <= np.median(radius)
    rms_all = rms(residual_xy)
    rms_x = float(np.sqrt(np.mean(residual_xy[:, 0] ** 2)))
    rms_y = float(np.sqrt(np.mean(residual_xy[:, 1] ** 2)))
    rms_centre, rms_edge = rms(residual_xy[inner]), rms(residual_xy[~inner])
    time_profile: tuple[tuple[float, float], ...] = ()
    time_p = None
    findings = []
    if t is not None:
        t = np.asarray(t, dtype=float)
        time_profile = _profile(t, residual_xy, bins)
        degree, _ = smooth_degree(len(points_xy), True)
        rss_space, p_space, _, _ = _smooth_fit(points_xy, residual_xy, t, degree, use_time=False)
        rss_time, p_time, _, used = _smooth_fit(points_xy, residual_xy, t, degree, use_time=True)
        if used and p_time > p_space:
            dof = max(2 * len(points_xy) - p_time, 1)
            f = max(rss_space - rss_time, 0.0) / (p_time - p_space) / max(rss_time / dof, 1e-16)
            time_p = f_survival(f, p_time - p_space, dof)
        else:
            findings.append("marking time is a smooth function of position (e.g. raster order): a change over "
                            "time cannot be told from a change over the field here")
    if noise is not None and rms_all <= 1.1 * noise.noise_floor_mm:
        findings.append(f"residual RMS {rms_all:.4f} mm is at the {getattr(noise, 'source', 'residual')} noise floor "
                        f"({noise.noise_floor_mm:.4f} mm)")
    else:
        if rms_edge > 1.5 * rms_centre:
            findings.append(f"grows towards the edges (edge RMS {rms_edge:.4f} mm, centre {rms_centre:.4f} mm)")
        elif rms_centre > 1.5 * rms_edge:
            findings.append(f"largest in the centre (centre RMS {rms_centre:.4f} mm, edge {rms_edge:.4f} mm)")
        if rms_x > 1.5 * rms_y:
            findings.append(f"mostly along X (x RMS {rms_x:.4f} mm, y {rms_y:.4f} mm)")
        elif rms_y > 1.5 * rms_x:
            findings.append(f"mostly along Y (y RMS {rms_y:.4f} mm, x {rms_x:.4f} mm)")
        for axis, profile in (("x", _profile(points_xy[:, 0], residual_xy, bins)),
                              ("y", _profile(points_xy[:, 1], residual_xy, bins))):
            values = [value for _, value in profile]
            if len(values) >= 2 and max(values) > 2.0 * max(min(values), 1e-12):
                where = profile[int(np.argmax(values))][0]
                findings.append(f"varies along {axis}: largest near {axis} = {where:.1f} mm")
    if time_p is not None and time_p < 1e-3:
        findings.append(f"changes with marking time (F-test p = {time_p:.2g})")
    return ResidualLocation(rms_all, rms_x, rms_y, rms_centre, rms_edge,
                            _profile(points_xy[:, 0], residual_xy, bins),
                            _profile(points_xy[:, 1], residual_xy, bins),
                            time_profile, time_p, tuple(findings))
