"""Result types of the discrepancy workflow: frozen records, JSON-ready through one dataclass helper."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from gls_calibration.common.files import to_plain
from gls_calibration.geometry.effect_table import UserEffect
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.geometry.optics import HeadEffects
from gls_calibration.registration.rigid import RigidAlignment2D


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
    vector: np.ndarray                 # flat parameters of ``names`` (effect table order)
    covariance: np.ndarray             # of ``vector``, sigma = noise sigma per axis
    effects: HeadEffects               # the whole model: fixed known effects plus the fitted ones
    predicted_xy: np.ndarray           # (N, 2) landing of the model, gls frame
    residual_xy: np.ndarray            # (N, 2) aligned measurement minus prediction
    alignment: RigidAlignment2D        # measured -> gls
    rss_mm2: float
    success: bool
    evaluations: int
    user_values: Mapping[str, tuple[float, ...]]     # fitted user effects (not in ``effects``)
    layout: Mapping[str, tuple[str, ...]]            # effect name -> its parameter names, in ``vector`` order
    chi2: float                                      # sum of (residual / sigma)^2 over both axes

    @property
    def rms_mm(self) -> float:
        """RMS of the 2-D residual vector."""
        return float(np.sqrt(self.rss_mm2 / len(self.residual_xy)))

    def parameters(self, name: str) -> dict[str, float]:
        """Fitted parameters of one effect, parameter name -> value."""
        start = self._start(name)
        return {p: float(self.vector[start + i]) for i, p in enumerate(self.layout[name])}

    def uncertainty(self, name: str) -> dict[str, float]:
        """One-sigma uncertainty of one effect's parameters."""
        start = self._start(name)
        diagonal = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return {p: float(diagonal[start + i]) for i, p in enumerate(self.layout[name])}

    def _start(self, name: str) -> int:
        if name not in self.names:
            raise ValueError(f"effect {name!r} was not fitted; fitted: {', '.join(self.names) or 'none'}")
        index = self.names.index(name)
        return sum(len(self.layout[n]) for n in self.names[:index])


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
        return to_plain(self)


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
        return to_plain(self)


@dataclass(frozen=True, eq=False)
class DiscrepancyResult:
    """Outcome of :func:`explain`: named effects in the order added, gap per step, residual fields.

    Built by :func:`explain` only.

    Parameters
    ----------
    geometry : HeadGeometry
        The nominal head.
    known_effects : HeadEffects
        The effects the model held before.
    model_effects : HeadEffects
        Known effects plus the named ones, final joint fit.
    model_uncertainty : mapping of str to tuple of float
        1-sigma of the named effects in the final fit, in their units.
    named_effects : tuple of str
        The effects named, in the order added.
    steps : tuple of EffectStep
        One per named effect: its values, its rivals, the gap before and after.
    rms_before_mm, rms_after_mm : float
        RMS of the residual before any step and after the last, mm.
    noise : NoiseFloor
        The floor estimated from the residual.
    structure_before, structure_after : StructureTest
        Structure or noise, before and after.
    location_before, location_after : ResidualLocation
        Where in the field the residual lives, before and after.
    alignment_before, alignment_after : RigidAlignment2D
        The rigid motion profiled out, before and after.
    commanded_xy : numpy.ndarray, shape (N, 2)
        The commanded points the fits used, mm.
    residual_before_xy, residual_after_xy : numpy.ndarray, shape (N, 2)
        The residual fields, mm.
    t : numpy.ndarray, shape (N,), or None
        Marking time, s.
    criterion : str
        The selection criterion (e.g. ``"bic"``).
    stop_reason : str
        Why the search stopped.
    notes : tuple of str
        Notes for the report.
    floor : FloorEvidence
        The floor the verdict uses, and its source.
    outliers : tuple of Outlier
        Excluded from every fit.
    implausible : tuple of Implausible
        Fits outside the plausible ranges, not named.
    verdict : Verdict
        Explained or not, against the floor.
    rigid_correlation : mapping
        ``"effect.parameter"`` -> its correlation with rotation, translation_x and translation_y.
    user_effects : tuple of UserEffect
        Candidates from outside the library.
    user_values : mapping of str to tuple of float
        Named user effects, final joint fit.
    inliers : numpy.ndarray, shape (N_input,)
        bool: the input points the fits used.
    fitted_effects : tuple of str, optional
        Effects the final model holds (``model_effects``); ``named_effects`` are those the data tell
        apart from the rigid motion and from every other candidate (:mod:`.separability`).
    named_groups : tuple of tuple of str, optional
        Each a fitted effect and the candidates it cannot be told from.
    separability : tuple, optional
        One ``separability.Separability`` per fitted effect.
    """

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
    floor: FloorEvidence                       # the floor the verdict uses, and its source
    outliers: tuple[Outlier, ...]              # excluded from every fit
    implausible: tuple[Implausible, ...]       # fits outside the plausible ranges, not named
    verdict: Verdict
    rigid_correlation: Mapping[str, Mapping[str, float]]   # "effect.parameter" -> rotation/translation_x/_y
    user_effects: tuple[UserEffect, ...]       # candidates from outside the library
    user_values: Mapping[str, tuple[float, ...]]   # named user effects, final joint fit
    inliers: np.ndarray                        # (N_input,) bool: the points the fits used
    # Effects the final model holds (``model_effects``); ``named_effects`` are those of them the data
    # tell apart from the rigid motion and from every other candidate (:mod:`.separability`), each
    # of ``named_groups`` is a fitted effect and the candidates it cannot be told from.
    fitted_effects: tuple[str, ...] = ()
    named_groups: tuple[tuple[str, ...], ...] = ()
    separability: tuple = ()                   # one separability.Separability per fitted effect

    @property
    def noise_floor_mm(self) -> float:
        """RMS of the 2-D measurement noise: independent evidence when given, else estimated from the residual."""
        return self.floor.noise_floor_mm

    @property
    def gap_per_step_mm(self) -> tuple[float, ...]:
        """Residual RMS before any step, then after each step."""
        return (self.rms_before_mm,) + tuple(step.rms_after_mm for step in self.steps)

    def to_dict(self) -> dict:
        """JSON-ready summary (no per-point arrays)."""
        return {
            "named_effects": list(self.named_effects),
            "named_groups": [list(group) for group in self.named_groups],
            "fitted_effects": list(self.fitted_effects),
            "separability": [record.to_dict() for record in self.separability],
            "effects": [step.to_dict() for step in self.steps],
            "rms_before_mm": self.rms_before_mm,
            "rms_after_mm": self.rms_after_mm,
            "noise_floor_mm": self.noise_floor_mm,
            "noise_floor_source": self.floor.source,
            "noise_floor": to_plain(self.floor),
            "noise_sigma_axis_mm": self.floor.sigma_axis_mm,
            "residual_noise_estimate": to_plain(self.noise),
            "verdict": self.verdict.verdict,
            "unexplained_rms_mm": self.verdict.unexplained_rms_mm,
            "verdict_detail": to_plain(self.verdict),
            "outliers": [{"index": o.index, "size_mm": o.size_mm, "x_mm": o.position_mm[0], "y_mm": o.position_mm[1]}
                         for o in self.outliers],
            "implausible": to_plain(self.implausible),
            "rigid_correlation": to_plain(self.rigid_correlation),
            "user_effects": [to_plain(effect.spec) for effect in self.user_effects],
            "user_values": to_plain(self.user_values),
            "gap_per_step_mm": list(self.gap_per_step_mm),
            "criterion": self.criterion,
            "stop_reason": self.stop_reason,
            "notes": list(self.notes),
            "point_count": int(len(self.commanded_xy)),
            "uses_time": self.t is not None,
            "geometry": to_plain(self.geometry),
            "known_effects": to_plain(self.known_effects.values),
            "model_effects": to_plain(self.model_effects.values),
            "model_uncertainty": to_plain(self.model_uncertainty),
            "structure_before": to_plain(self.structure_before),
            "structure_after": to_plain(self.structure_after),
            "location_before": to_plain(self.location_before),
            "location_after": to_plain(self.location_after),
            "rigid_motion_before": to_plain(self.alignment_before),
            "rigid_motion_after": to_plain(self.alignment_after),
        }


@dataclass(frozen=True)
class FloorEvidence:
    """The noise floor the verdict compares with, where it came from, and the residual's cross-check."""

    source: str                    # repeats | per_point | stated | residual
    sigma_axis_mm: float           # per-axis noise of the data the fit uses (RMS over points)
    noise_floor_mm: float          # RMS of the 2-D noise vector, sqrt(2) * sigma_axis_mm
    residual_estimate_mm: float    # the residual-roughness estimate of the same floor (cross-check)
    repeats: int                   # measurements averaged per point (1 unless repeats)
    cross_check: str               # agreement or disagreement of the two, in words


@dataclass(frozen=True)
class Outlier:
    """A gross outlier excluded from every fit: its data index, size and position."""

    index: int                     # index into the input points (the CLI reports the CSV data row)
    size_mm: float                 # departure from the smooth field and from its neighbours
    position_mm: tuple[float, float]   # commanded target, gls frame


@dataclass(frozen=True)
class Implausible:
    """A candidate whose fit fell outside the physically plausible ranges: not named."""

    name: str
    parameters: Mapping[str, float]    # of the candidate, in that fit
    why: str
    step: int                          # 1-based step at which it was the best or a rival


@dataclass(frozen=True)
class Verdict:
    """Whether the gap is explained by the named effects, against the independent floor.

    Is the gap explained by the named effects, measured against the independent floor?
    """

    verdict: str                   # explained | unexplained_structure
    unexplained_rms_mm: float      # residual RMS above the floor, in quadrature; with below_floor the RMS
    # of the smooth structure the F-test found
    ratio_to_floor: float          # residual RMS / noise floor
    chi2_p_value: float            # residual consistent with the floor (chi-square test)
    pattern: str                   # the dominant pattern in words
    findings: tuple[str, ...]      # further observations
    below_floor: bool = False      # structure found although the residual RMS is not above the floor
