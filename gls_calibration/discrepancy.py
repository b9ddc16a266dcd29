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

RMS figures are of the 2-D residual vector, ``sqrt(mean(dx^2 + dy^2))``; the noise floor is on the
same footing (``sqrt(2)`` times the per-axis sigma), so a residual that is pure noise has RMS close to
the noise floor.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np
from scipy import optimize, stats
from scipy.linalg import subspace_angles

from gls_calibration.kinematics import HeadGeometry, inverse
from gls_calibration.optics import EFFECTS, PARAMETER_UNITS, HeadEffects, PhysicalHead
from gls_calibration.validation import as_finite_array, as_points

#: Typical size of each parameter for a head of this class; the fit scales its unknowns by it and
#: :func:`observability_report` probes each effect with it. The two thermal rates are per run
#: (divided by the marking-time span at use).
NOMINAL_MAGNITUDES: dict[str, float] = {
    "delta_e_mm": 1.0,
    "delta_d_mm": 1.0,
    "gain_error_x": 1e-3,
    "gain_error_y": 1e-3,
    "offset_x_rad": 1e-3,
    "offset_y_rad": 1e-3,
    "skew_rad": 1e-3,
    "offset_x_mm": 0.5,
    "offset_y_mm": 0.5,
    "tilt_a_rad": 1e-3,
    "tilt_b_rad": 1e-3,
    "tilt_x_rad": 5e-3,
    "tilt_y_rad": 5e-3,
    "k1_per_mm2": 1e-7,
    "gain_rate_per_s": 1e-3,          # gain change over the whole run
    "offset_rate_rad_per_s": 1e-3,    # offset change over the whole run
}
_PER_RUN = ("gain_rate_per_s", "offset_rate_rad_per_s")

CRITERIA = ("bic", "aic")
MIN_POINTS = 10
RIGID_NOTE = ("Rotation and translation between the measured frame and the gls frame are removed by a "
              "rigid alignment: they are not observable from these data and are never named as effects.")


# --------------------------------------------------------------------------------------------------
# result types

@dataclass(frozen=True)
class RigidAlignment2D:
    """In-plane rigid motion ``gls = R(rotation_rad) @ measured + translation_mm`` (no scale)."""

    rotation_rad: float
    translation_mm: tuple[float, float]

    def apply(self, points_xy) -> np.ndarray:
        """Map (N, 2) points of the measured frame into the gls frame."""
        points = np.asarray(points_xy, dtype=float)
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        return points @ np.array([[c, s], [-s, c]]) + np.asarray(self.translation_mm)


@dataclass(frozen=True)
class NoiseFloor:
    """Measurement noise estimated from the residual's departure from a smooth field."""

    sigma_axis_mm: float      # per-axis standard deviation
    noise_floor_mm: float     # RMS of the 2-D noise vector, sqrt(2) * sigma_axis_mm
    degree: int               # polynomial degree of the smooth field
    uses_time: bool           # t, t*x, t*y terms included
    dof: int                  # residual degrees of freedom of the smooth fit


@dataclass(frozen=True)
class StructureTest:
    """Is the residual structure or noise? F-test of a smooth field against rigid alignment only."""

    f_statistic: float
    p_value: float
    dof_model: int
    dof_residual: int
    chi2_ratio: float          # residual RMS^2 / noise floor^2 (about 1 for noise)
    is_structure: bool


@dataclass(frozen=True)
class ResidualLocation:
    """Where in the field the residual lives (all RMS of the 2-D residual vector unless _x/_y)."""

    rms_mm: float
    rms_x_mm: float
    rms_y_mm: float
    rms_centre_mm: float       # points within the median radius
    rms_edge_mm: float         # points beyond it
    x_profile: tuple[tuple[float, float], ...]     # (bin centre x mm, RMS mm)
    y_profile: tuple[tuple[float, float], ...]
    time_profile: tuple[tuple[float, float], ...]  # (bin centre t s, RMS mm); empty without t
    time_p_value: float | None                     # F-test of t, t*x, t*y terms; None without t
    findings: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class EffectsFit:
    """Least-squares fit of named effects (rigid alignment profiled out) to the measured positions."""

    names: tuple[str, ...]
    vector: np.ndarray                 # flat parameters of ``names`` (optics order)
    covariance: np.ndarray             # of ``vector``, sigma = noise sigma per axis
    effects: HeadEffects               # the whole model: fixed known effects plus the fitted ones
    predicted_xy: np.ndarray           # (N, 2) landing of the model, gls frame
    residual_xy: np.ndarray            # (N, 2) aligned measurement minus prediction
    alignment: RigidAlignment2D        # measured -> gls
    rss_mm2: float
    success: bool
    evaluations: int

    @property
    def rms_mm(self) -> float:
        """RMS of the 2-D residual vector."""
        return float(np.sqrt(self.rss_mm2 / len(self.residual_xy)))

    def parameters(self, name: str) -> dict[str, float]:
        """Fitted parameters of one effect, parameter name -> value."""
        start = self._start(name)
        return {p: float(self.vector[start + i]) for i, p in enumerate(EFFECTS[name])}

    def uncertainty(self, name: str) -> dict[str, float]:
        """One-sigma uncertainty of one effect's parameters."""
        start = self._start(name)
        diagonal = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return {p: float(diagonal[start + i]) for i, p in enumerate(EFFECTS[name])}

    def _start(self, name: str) -> int:
        if name not in self.names:
            raise ValueError(f"effect {name!r} was not fitted; fitted: {', '.join(self.names) or 'none'}")
        index = self.names.index(name)
        return sum(len(EFFECTS[n]) for n in self.names[:index])


@dataclass(frozen=True)
class CandidateScore:
    """One candidate effect at one step."""

    name: str
    parameters: Mapping[str, float]
    uncertainty: Mapping[str, float]
    criterion: float               # information criterion of the model with this candidate added
    improvement: float             # criterion without it minus with it (> 0: better)
    rms_after_mm: float
    field_difference_mm: float     # RMS difference to the best candidate's landing field, aligned

    def to_dict(self) -> dict:
        """JSON-ready mapping."""
        return {"name": self.name, "parameters": dict(self.parameters), "uncertainty": dict(self.uncertainty),
                "criterion": self.criterion, "improvement": self.improvement,
                "rms_after_mm": self.rms_after_mm, "field_difference_mm": self.field_difference_mm}


@dataclass(frozen=True)
class EffectStep:
    """One named effect: its values when it was added, its rivals, and the gap before and after."""

    name: str
    parameters: Mapping[str, float]
    uncertainty: Mapping[str, float]
    units: Mapping[str, str]
    indistinguishable_from: tuple[str, ...]
    improvement: float
    rms_before_mm: float
    rms_after_mm: float
    candidates: tuple[CandidateScore, ...]
    removed: tuple[str, ...] = ()      # effects named earlier that this one made redundant

    def to_dict(self) -> dict:
        """JSON-ready mapping."""
        return {"name": self.name, "parameters": dict(self.parameters), "uncertainty": dict(self.uncertainty),
                "units": dict(self.units), "indistinguishable_from": list(self.indistinguishable_from),
                "improvement": self.improvement, "rms_before_mm": self.rms_before_mm,
                "rms_after_mm": self.rms_after_mm, "removed": list(self.removed),
                "candidates": [c.to_dict() for c in self.candidates]}


@dataclass(frozen=True, eq=False)
class DiscrepancyResult:
    """Outcome of :func:`explain`: named effects in the order added, gap per step, residual fields."""

    geometry: HeadGeometry
    known_effects: HeadEffects
    model_effects: HeadEffects                 # known effects plus the named ones, final joint fit
    model_uncertainty: Mapping[str, tuple[float, ...]]   # 1-sigma of the named effects in the final fit
    named_effects: tuple[str, ...]
    steps: tuple[EffectStep, ...]
    rms_before_mm: float
    rms_after_mm: float
    noise: NoiseFloor
    structure_before: StructureTest
    structure_after: StructureTest
    location_before: ResidualLocation
    location_after: ResidualLocation
    alignment_before: RigidAlignment2D
    alignment_after: RigidAlignment2D
    commanded_xy: np.ndarray
    residual_before_xy: np.ndarray
    residual_after_xy: np.ndarray
    t: np.ndarray | None
    criterion: str
    stop_reason: str
    notes: tuple[str, ...]

    @property
    def noise_floor_mm(self) -> float:
        """RMS of the 2-D measurement noise estimated from the data."""
        return self.noise.noise_floor_mm

    @property
    def gap_per_step_mm(self) -> tuple[float, ...]:
        """Residual RMS before any step, then after each step."""
        return (self.rms_before_mm,) + tuple(step.rms_after_mm for step in self.steps)

    def to_dict(self) -> dict:
        """JSON-ready summary (no per-point arrays)."""
        def structure(test: StructureTest) -> dict:
            return {"f_statistic": test.f_statistic, "p_value": test.p_value, "dof_model": test.dof_model,
                    "dof_residual": test.dof_residual, "chi2_ratio": test.chi2_ratio,
                    "is_structure": test.is_structure}

        def location(loc: ResidualLocation) -> dict:
            return {"rms_mm": loc.rms_mm, "rms_x_mm": loc.rms_x_mm, "rms_y_mm": loc.rms_y_mm,
                    "rms_centre_mm": loc.rms_centre_mm, "rms_edge_mm": loc.rms_edge_mm,
                    "x_profile": [list(p) for p in loc.x_profile], "y_profile": [list(p) for p in loc.y_profile],
                    "time_profile": [list(p) for p in loc.time_profile], "time_p_value": loc.time_p_value,
                    "findings": list(loc.findings)}

        def alignment(a: RigidAlignment2D) -> dict:
            return {"rotation_rad": a.rotation_rad, "translation_mm": list(a.translation_mm)}

        g = self.geometry
        return {
            "named_effects": list(self.named_effects),
            "effects": [step.to_dict() for step in self.steps],
            "rms_before_mm": self.rms_before_mm,
            "rms_after_mm": self.rms_after_mm,
            "noise_floor_mm": self.noise_floor_mm,
            "noise_sigma_axis_mm": self.noise.sigma_axis_mm,
            "gap_per_step_mm": list(self.gap_per_step_mm),
            "criterion": self.criterion,
            "stop_reason": self.stop_reason,
            "notes": list(self.notes),
            "point_count": int(len(self.commanded_xy)),
            "uses_time": self.t is not None,
            "geometry": {"working_distance_mm": g.working_distance_mm, "mirror_distance_mm": g.mirror_distance_mm,
                         "mirror_limit_rad": g.mirror_limit_rad, "focus_range_mm": g.focus_range_mm},
            "known_effects": {k: list(v) for k, v in self.known_effects.values.items()},
            "model_effects": {k: list(v) for k, v in self.model_effects.values.items()},
            "model_uncertainty": {k: list(v) for k, v in self.model_uncertainty.items()},
            "structure_before": structure(self.structure_before),
            "structure_after": structure(self.structure_after),
            "location_before": location(self.location_before),
            "location_after": location(self.location_after),
            "rigid_motion_before": alignment(self.alignment_before),
            "rigid_motion_after": alignment(self.alignment_after),
        }


# --------------------------------------------------------------------------------------------------
# alignment, noise floor, structure, location

def align_rigid_2d(source_xy: np.ndarray, target_xy: np.ndarray) -> tuple[RigidAlignment2D, np.ndarray]:
    """Least-squares rotation + translation (no scale) of ``source`` onto ``target``; returns it and ``source`` moved.

    Closed-form 2-D Kabsch: the optimal angle is atan2 of the summed cross and dot products of the
    centred point sets.
    """
    source_mean = source_xy.mean(axis=0)
    target_mean = target_xy.mean(axis=0)
    s = source_xy - source_mean
    d = target_xy - target_mean
    angle = math.atan2(float(np.sum(s[:, 0] * d[:, 1] - s[:, 1] * d[:, 0])),
                       float(np.sum(s[:, 0] * d[:, 0] + s[:, 1] * d[:, 1])))
    c, sn = math.cos(angle), math.sin(angle)
    moved = np.empty_like(s)
    moved[:, 0] = c * s[:, 0] - sn * s[:, 1] + target_mean[0]
    moved[:, 1] = sn * s[:, 0] + c * s[:, 1] + target_mean[1]
    translation = target_mean - np.array([c * source_mean[0] - sn * source_mean[1],
                                          sn * source_mean[0] + c * source_mean[1]])
    return RigidAlignment2D(angle, (float(translation[0]), float(translation[1]))), moved


def _normalised(points_xy: np.ndarray, t: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    centre = 0.5 * (points_xy.max(axis=0) + points_xy.min(axis=0))
    half = np.maximum(0.5 * (points_xy.max(axis=0) - points_xy.min(axis=0)), 1e-9)
    u = (points_xy - centre) / half
    tau = None
    if t is not None:
        span = max(float(np.ptp(t)), 1e-12)
        tau = 2.0 * (t - t.min()) / span - 1.0
    return u[:, 0], u[:, 1], tau


def _smooth_basis(points_xy: np.ndarray, t: np.ndarray | None, degree: int, use_time: bool) -> np.ndarray:
    """Per-component design matrix: monomials x^i y^j (i + j <= degree), plus t, t*x, t*y."""
    u, v, tau = _normalised(points_xy, t)
    columns = [u ** i * v ** (total - i) for total in range(degree + 1) for i in range(total + 1)]
    if use_time and tau is not None:
        columns += [tau, tau * u, tau * v]
    return np.stack(columns, axis=1)


def _smooth_degree(n_points: int, use_time: bool) -> tuple[int, bool]:
    """Highest degree (<= 5) whose basis keeps at most a third of the points per component."""
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
        degree, use_time = _smooth_degree(len(points_xy), use_time)
    basis = _smooth_basis(points_xy, t, degree, use_time)
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
    """F-test: does a smooth field explain the (rigidly aligned) residual better than nothing?

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
    p_value = float(stats.f.sf(f_statistic, dof_model, dof_residual))
    chi2_ratio = rss0 / (n * noise.sigma_axis_mm ** 2)
    return StructureTest(float(f_statistic), p_value, dof_model, dof_residual, float(chi2_ratio),
                         bool(p_value < alpha))


def _rms(vectors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(vectors ** 2, axis=1)))) if len(vectors) else float("nan")


def _profile(coordinate: np.ndarray, residual_xy: np.ndarray, bins: int) -> tuple[tuple[float, float], ...]:
    edges = np.linspace(coordinate.min(), coordinate.max(), bins + 1)
    index = np.clip(np.searchsorted(edges, coordinate, side="right") - 1, 0, bins - 1)
    profile = []
    for b in range(bins):
        members = index == b
        if np.any(members):
            profile.append((float(0.5 * (edges[b] + edges[b + 1])), _rms(residual_xy[members])))
    return tuple(profile)


def locate_residual(points_xy, residual_xy, t=None, *, noise: NoiseFloor | None = None,
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
    rms = _rms(residual_xy)
    rms_x = float(np.sqrt(np.mean(residual_xy[:, 0] ** 2)))
    rms_y = float(np.sqrt(np.mean(residual_xy[:, 1] ** 2)))
    rms_centre, rms_edge = _rms(residual_xy[inner]), _rms(residual_xy[~inner])
    time_profile: tuple[tuple[float, float], ...] = ()
    time_p = None
    findings = []
    if t is not None:
        t = np.asarray(t, dtype=float)
        time_profile = _profile(t, residual_xy, bins)
        degree, _ = _smooth_degree(len(points_xy), True)
        rss_space, p_space, _, _ = _smooth_fit(points_xy, residual_xy, t, degree, use_time=False)
        rss_time, p_time, _, used = _smooth_fit(points_xy, residual_xy, t, degree, use_time=True)
        if used and p_time > p_space:
            dof = max(2 * len(points_xy) - p_time, 1)
            f = max(rss_space - rss_time, 0.0) / (p_time - p_space) / max(rss_time / dof, 1e-16)
            time_p = float(stats.f.sf(f, p_time - p_space, dof))
        else:
            findings.append("marking time is a smooth function of position (e.g. raster order): a change over "
                            "time cannot be told from a change over the field here")
    if noise is not None and rms <= 1.5 * noise.noise_floor_mm:
        findings.append(f"residual RMS {rms:.4f} mm is at the noise floor ({noise.noise_floor_mm:.4f} mm)")
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
    return ResidualLocation(rms, rms_x, rms_y, rms_centre, rms_edge,
                            _profile(points_xy[:, 0], residual_xy, bins),
                            _profile(points_xy[:, 1], residual_xy, bins),
                            time_profile, time_p, tuple(findings))


# --------------------------------------------------------------------------------------------------
# model prediction and effect fitting

class _Predictor:
    """Landing (N, 2) of the commanded targets for given effects; commands go through the nominal model."""

    def __init__(self, geometry: HeadGeometry, commanded_xy: np.ndarray, t: np.ndarray | None) -> None:
        self.geometry = geometry
        joints = inverse(geometry, commanded_xy[:, 0], commanded_xy[:, 1])
        self.alpha_x = joints.alpha_x
        self.alpha_y = joints.alpha_y
        self.t = t

    def __call__(self, effects: HeadEffects | Mapping[str, Sequence[float]]) -> np.ndarray:
        return PhysicalHead(self.geometry, effects).land(self.alpha_x, self.alpha_y, self.t)[:, :2]


def _scales(names: Sequence[str], t: np.ndarray | None) -> np.ndarray:
    span = max(float(np.ptp(t)), 1.0) if t is not None and len(t) else 1.0
    scales = []
    for name in names:
        for parameter in EFFECTS[name]:
            value = NOMINAL_MAGNITUDES[parameter]
            scales.append(value / span if parameter in _PER_RUN else value)
    return np.array(scales)


def _residual(predicted_xy: np.ndarray, measured_xy: np.ndarray) -> tuple[RigidAlignment2D, np.ndarray]:
    alignment, aligned = align_rigid_2d(measured_xy, predicted_xy)
    return alignment, aligned - predicted_xy


def _fit(predict: _Predictor, measured_xy: np.ndarray, names: Sequence[str], known: HeadEffects,
         initial: np.ndarray, sigma_axis_mm: float) -> EffectsFit:
    names = tuple(names)
    scales = _scales(names, predict.t)
    base = dict(known.values)

    def model(vector: np.ndarray) -> HeadEffects:
        values = dict(base)
        values.update(HeadEffects.from_vector(names, vector).values)
        return HeadEffects(values)

    def residuals(u: np.ndarray) -> np.ndarray:
        predicted = predict(model(initial + scales * u))
        return _residual(predicted, measured_xy)[1].ravel()

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
    alignment, residual = _residual(predicted, measured_xy)
    return EffectsFit(names, vector, covariance, effects, predicted, residual, alignment,
                      float(np.sum(residual ** 2)), success, evaluations)


def _check_inputs(commanded_xy, measured_xy, t) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
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


def _as_effects(known_effects) -> HeadEffects:
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
    commanded_xy, measured_xy, t = _check_inputs(commanded_xy, measured_xy, t)
    names = tuple(names)
    if len(set(names)) != len(names):
        raise ValueError(f"effect names must be unique, got {list(names)}")
    known = _as_effects(known_effects)
    initial = known.to_vector(names)   # also rejects unknown names
    predict = _Predictor(geometry, commanded_xy, t)
    if sigma_axis_mm is None:
        _, residual = _residual(predict(known), measured_xy)
        sigma_axis_mm = estimate_noise_floor(commanded_xy, residual, t).sigma_axis_mm
    return _fit(predict, measured_xy, names, known, initial, sigma_axis_mm)


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
    return _Predictor(result.geometry, commanded_xy, t)(result.model_effects)


def _time_follows_position(points_xy: np.ndarray, t: np.ndarray, threshold: float = 0.9) -> bool:
    """True when a plane in x, y explains more than ``threshold`` of the variance of the marking time."""
    design = np.column_stack([np.ones(len(points_xy)), points_xy])
    fitted = design @ np.linalg.lstsq(design, t, rcond=None)[0]
    variance = float(np.var(t))
    return variance > 0.0 and 1.0 - float(np.var(t - fitted)) / variance > threshold


def _criterion(rss: float, parameters: int, n: int, sigma: float, criterion: str) -> float:
    penalty = math.log(n) if criterion == "bic" else 2.0
    return rss / sigma ** 2 + penalty * parameters


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
    :data:`gls_calibration.optics.EFFECTS`. See the module docstring for the method and thresholds.
    """
    commanded_xy, measured_xy, t = _check_inputs(commanded_xy, measured_xy, t)
    geometry = geometry if geometry is not None else HeadGeometry()
    known = _as_effects(known_effects)
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {', '.join(CRITERIA)}, got {criterion!r}")
    if max_steps < 0:
        raise ValueError(f"max_steps must be >= 0, got {max_steps}")
    pool = list(EFFECTS) if candidates is None else list(candidates)
    for name in pool:
        if name not in EFFECTS:
            raise ValueError(f"unknown effect {name!r}; known effects: {', '.join(EFFECTS)}")
    if t is None and "thermal_drift" in pool:
        pool.remove("thermal_drift")   # invisible without marking time

    predict = _Predictor(geometry, commanded_xy, t)
    n = 2 * len(commanded_xy)
    current = _fit(predict, measured_xy, (), known, np.zeros(0), 1.0)
    noise = estimate_noise_floor(commanded_xy, current.residual_xy, t, min_sigma_mm=min_noise_mm)
    sigma = noise.sigma_axis_mm
    first = current
    structure_before = structure_test(commanded_xy, current.residual_xy, noise, t, alpha=structure_alpha,
                                      min_sigma_mm=min_noise_mm)
    rigid = 3

    def information(fit: EffectsFit) -> float:
        return _criterion(fit.rss_mm2, rigid + len(fit.vector), n, sigma, criterion)

    def rivals_of(best: str, model: EffectsFit, alternatives: Mapping[str, EffectsFit],
                  base_information: float) -> list[str]:
        # a rival explains (nearly) what the best explains: close in the criterion, or most of the
        # improvement with a landing field that differs from the best's by less than the noise
        best_gain = base_information - information(model)
        rivals = []
        for name, fit in sorted(alternatives.items(), key=lambda item: information(item[1])):
            gain = base_information - information(fit)
            if name == best or gain < name_threshold:
                continue
            _, moved = align_rigid_2d(fit.predicted_xy, model.predicted_xy)
            difference = _rms(moved - model.predicted_xy)
            if best_gain - gain < indistinguishable_within or (
                    difference < noise.noise_floor_mm and gain >= 0.5 * best_gain):
                rivals.append(name)
        return rivals

    steps: list[EffectStep] = []
    dropped: set[str] = set()
    notes = [RIGID_NOTE]
    if t is not None and _time_follows_position(commanded_xy, t):
        notes.append("Marking time follows the position (row-wise order): a drift growing with time looks like "
                     "a static field effect here (thermal_drift is confounded with axis_skew, the gains and "
                     "mirror_distance). Mark in a shuffled or repeated order to tell them apart.")
    stop_reason = f"reached max_steps = {max_steps}"
    structure = structure_before
    for _ in range(max_steps):
        if not structure.is_structure:
            stop_reason = (f"the residual is noise (F-test p = {structure.p_value:.3g} >= {structure_alpha:g}, "
                           f"RMS {current.rms_mm:.4f} mm vs noise floor {noise.noise_floor_mm:.4f} mm)")
            break
        remaining = [name for name in pool if name not in current.names and name not in dropped]
        if not remaining:
            stop_reason = "no candidate effect left"
            break
        base_information = information(current)
        fits = {}
        for name in remaining:
            names = current.names + (name,)
            initial = np.concatenate([current.vector, np.asarray(known.get(name), dtype=float)])
            fits[name] = _fit(predict, measured_xy, names, known, initial, sigma)
        improvement = {name: base_information - information(fit) for name, fit in fits.items()}
        best = max(improvement, key=improvement.get)
        if improvement[best] < name_threshold:
            stop_reason = (f"no candidate improves the {criterion.upper()} by {name_threshold:g} or more "
                           f"(best: {best}, {improvement[best]:.1f})")
            break
        best_fit = fits[best]
        scores = []
        for name, fit in sorted(fits.items(), key=lambda item: -improvement[item[0]]):
            _, moved = align_rigid_2d(fit.predicted_xy, best_fit.predicted_xy)
            scores.append(CandidateScore(name, MappingProxyType(fit.parameters(name)),
                                         MappingProxyType(fit.uncertainty(name)), information(fit),
                                         float(improvement[name]), fit.rms_mm, _rms(moved - best_fit.predicted_xy)))
        # backward pass: an effect named earlier may now be explained by the others (forward selection
        # can pick a look-alike of two effects first); drop it when keeping it is not strongly supported
        removed: list[str] = []
        while len(best_fit.names) > 1:
            worsening = {}
            for name in best_fit.names[:-1]:
                keep = [n for n in best_fit.names if n != name]
                start = np.array([value for n in keep for value in best_fit.parameters(n).values()])
                reduced = _fit(predict, measured_xy, keep, known, start, sigma)
                worsening[name] = (information(reduced) - information(best_fit), reduced)
            weakest = min(worsening, key=lambda name: worsening[name][0])
            if worsening[weakest][0] >= name_threshold:
                break
            removed.append(weakest)
            dropped.add(weakest)
            best_fit = worsening[weakest][1]
            notes.append(f"{weakest} was dropped after {best} was added: the other named effects explain it "
                         f"({criterion.upper()} worsens by only {worsening[weakest][0]:.1f} without it).")
        # rivals: other effects that could take the named one's place in the (pruned) model
        if removed:
            base_names = tuple(n for n in best_fit.names if n != best)
            start = np.array([value for n in base_names for value in best_fit.parameters(n).values()])
            base_fit = _fit(predict, measured_xy, base_names, known, start, sigma)
            alternatives = {}
            for name in pool:
                if name in best_fit.names:
                    continue
                initial = np.concatenate([base_fit.vector, np.asarray(known.get(name), dtype=float)])
                alternatives[name] = _fit(predict, measured_xy, base_names + (name,), known, initial, sigma)
            rivals = rivals_of(best, best_fit, alternatives, information(base_fit))
        else:
            rivals = rivals_of(best, best_fit, fits, base_information)
        steps.append(EffectStep(best, MappingProxyType(best_fit.parameters(best)),
                                MappingProxyType(best_fit.uncertainty(best)),
                                MappingProxyType(dict(zip(EFFECTS[best], PARAMETER_UNITS[best]))),
                                tuple(rivals), float(improvement[best]), current.rms_mm, best_fit.rms_mm,
                                tuple(scores), tuple(removed)))
        if rivals:
            notes.append(f"{best} is indistinguishable from {', '.join(rivals)} with these data "
                         f"(criterion within {indistinguishable_within:g} or landing fields within the noise floor).")
        current = best_fit
        structure = structure_test(commanded_xy, current.residual_xy, noise, t, fitted_parameters=len(current.vector),
                                   alpha=structure_alpha, min_sigma_mm=min_noise_mm)
    else:
        if max_steps == 0:
            stop_reason = "max_steps = 0"
    structure_after = structure_test(commanded_xy, current.residual_xy, noise, t, fitted_parameters=len(current.vector),
                                     alpha=structure_alpha, min_sigma_mm=min_noise_mm)
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


# --------------------------------------------------------------------------------------------------
# observability

@dataclass(frozen=True, eq=False)
class ObservabilityReport:
    """How much of each effect survives rigid alignment, and how alike the effects look afterwards."""

    effects: tuple[str, ...]
    parameters: tuple[tuple[str, str, float, float, float], ...]  # (effect, parameter, magnitude, rms raw, rms aligned) mm
    similarity: np.ndarray     # (E, E) cosine of the smallest principal angle between aligned field spans

    def confusable_pairs(self, threshold: float = 0.95) -> list[tuple[str, str, float]]:
        """Pairs of different effects whose aligned fields are nearly parallel (similarity >= threshold)."""
        pairs = []
        for i, a in enumerate(self.effects):
            for j in range(i + 1, len(self.effects)):
                if self.similarity[i, j] >= threshold:
                    pairs.append((a, self.effects[j], float(self.similarity[i, j])))
        return pairs

    def summary(self, visible_fraction: float = 0.2) -> str:
        """Plain-text table plus the effects that are mostly a rigid motion and the confusable pairs."""
        lines = ["effect              parameter               magnitude   raw RMS mm  aligned RMS mm  kept"]
        hidden = []
        for effect, parameter, magnitude, raw, aligned in self.parameters:
            kept = aligned / raw if raw > 0 else 0.0
            lines.append(f"{effect:19s} {parameter:23s} {magnitude:9.3g}  {raw:10.4f}  {aligned:14.4f}  {kept:5.0%}")
            if kept < visible_fraction:
                hidden.append(f"{effect}.{parameter} ({kept:.0%} kept)")
        if hidden:
            lines.append("mostly a rigid motion: " + ", ".join(hidden))
        for a, b, similarity in self.confusable_pairs():
            lines.append(f"confusable: {a} ~ {b} (similarity {similarity:.3f})")
        return "\n".join(lines)


def observability_report(geometry: HeadGeometry | None = None, *, per_side: int = 19, size_mm: float = 190.0,
                         duration_s: float = 360.0,
                         magnitudes: Mapping[str, float] | None = None) -> ObservabilityReport:
    """For each effect at its nominal magnitude: field change on the grid before and after rigid alignment.

    The similarity of two effects is the cosine of the smallest principal angle between the spans of
    their (linearised, rigidly aligned) landing fields: 1 means some combination of one effect's
    parameters moves the marks exactly like some combination of the other's.
    Marking time runs linearly over ``duration_s`` in grid order (for ``thermal_drift``).
    """
    geometry = geometry if geometry is not None else HeadGeometry()
    magnitudes = {**NOMINAL_MAGNITUDES, **(magnitudes or {})}
    axis = np.linspace(-0.5 * size_mm, 0.5 * size_mm, per_side)
    grid_x, grid_y = np.meshgrid(axis, axis)
    targets = np.column_stack([grid_x.ravel(), grid_y.ravel()])
    t = np.linspace(0.0, duration_s, len(targets))
    predict = _Predictor(geometry, targets, t)
    base = predict(HeadEffects())
    scales = {name: _scales([name], t) for name in EFFECTS}
    rows, spans = [], {}
    for name, parameters in EFFECTS.items():
        columns = []
        for i, parameter in enumerate(parameters):
            magnitude = magnitudes[parameter] if parameter not in _PER_RUN else scales[name][i]
            vector = np.zeros(len(parameters))
            vector[i] = magnitude
            change = predict(HeadEffects({name: vector})) - base
            _, moved = align_rigid_2d(base + change, base)
            aligned = moved - base   # what the rigid alignment cannot remove
            rows.append((name, parameter, float(magnitude), _rms(change), _rms(aligned)))
            columns.append(aligned.ravel())
        spans[name] = np.column_stack(columns)
    names = tuple(EFFECTS)
    similarity = np.eye(len(names))
    for i, a in enumerate(names):
        for j in range(i + 1, len(names)):
            value = float(np.cos(np.min(subspace_angles(spans[a], spans[b := names[j]]))))
            similarity[i, j] = similarity[j, i] = value
    return ObservabilityReport(names, tuple(rows), similarity)
