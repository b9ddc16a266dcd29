"""Extended-model correction: the fitted named effects as a deviation model, and physics first, RBF after.

Conventions (those of :mod:`gls_calibration.correction.setpoints`): a deviation model maps targets ``Q`` (M, 2)
in mm, gls frame, to a correction ``delta(Q)`` (M, 2) in mm, and the head is commanded through the
nominal inverse kinematics to ``K = Q + sum_i model_i(Q)``. Training deviations are
``delta = Q - P``: target minus measured landing ``P``, the measurement rigidly aligned onto the targets.

The physical model holds the nominal geometry, the effect values the discrepancy workflow fitted,
and the 2-D rigid motion ``C`` that carries the model's landing (gls frame) into the frame of the
measurement (the least-squares fit of the predicted landing onto ``P``; that frame is unobservable,
so it belongs to the model and not to any effect). Its landing of a command ``x`` is
``L(x) = C(land(inverse(x)))``.

* :meth:`PhysicalDeviationModel.measured_deviation` is ``Q - L(Q)``: the deviation the model says a
  plate marked through the nominal model shows. Minus the measured deviations it gives what the
  RBF is trained on.
* Calling the model gives ``K_phys(Q) - Q`` with ``L(K_phys) = Q`` (solved by fixed-point
  iteration): the command that makes the modelled head land on ``Q``. It equals
  ``measured_deviation`` to first order; unlike a data-driven model it also removes the second-order
  error ``(dL/dx - I) delta`` (about 1 % of the deviation for a 1 % gain error), which a first
  correction from measured deviations keeps. ``inverse=False`` gives the first-order form.

Physics + RBF: ``K = K_phys(Q) + rbf(Q)`` with the RBF trained on ``delta - measured_deviation``,
i.e. on minus the landing the physics does not explain, ``r = P - L``. Then
``true landing(K) ~= L(K_phys) - r(Q) + r(K) ~= Q`` up to terms in the (small) gradient of ``r``.

The discrepancy workflow assumes the training plate was marked through the nominal model (at
``z = 0``). Commands at the measured plate height, as the calibration procedure gives them, are a
smooth change of the same kind as a plate tilt, which the named effects and the RBF take up
(benchmarks/bench_physics_rbf.py commands that way). After an earlier calibration the plate was not
marked nominally: train the RBF alone then.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
import math
import time
from types import MappingProxyType
from typing import Any, Optional

import numpy as np

from gls_calibration.common.validation import as_finite_array, as_matching_points, as_points, require_key, require_type
from gls_calibration.discrepancy import MIN_POINTS, DiscrepancyResult, explain, fit_effects, fit_inliers
from gls_calibration.geometry.effect_table import EFFECT_TABLE
from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.geometry.optics import HeadEffects, PhysicalHead
from gls_calibration.models import rbf
from gls_calibration.registration.rigid import align_rigid_2d

_INVERSE_TOLERANCE_MM = 1e-9
_INVERSE_MAX_ITERATIONS = 30
# typical sizes of the rigid motion's parameters (rotation rad, translation mm), as the effect table
# gives its parameters' typical sizes: the scale of a finite-difference step
_RIGID_TYPICAL = (1e-3, 1.0, 1.0)
RESIDUAL_TYPES = ("ols_rbf", "thin_plate_spline")


def _geometry_from_dict(data: Any) -> HeadGeometry:
    if not isinstance(data, Mapping):
        raise ValueError(f"physical model geometry must be a mapping, got {type(data).__name__}")
    known = {f.name for f in fields(HeadGeometry)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"physical model geometry has unknown key(s) {', '.join(unknown)}")
    return HeadGeometry(**{key: float(value) for key, value in data.items()})


class PhysicalDeviationModel:
    """Deviation model from named effects: ``model(Q)`` (M, 2) -> correction (M, 2), mm.

    ``geometry``: nominal head (what the controller commands through); ``effects``: the fitted
    (and known) effects; ``rotation_rad``, ``translation_mm``: the rigid motion ``C`` from the
    model's landing (gls frame) to the measurement frame, ``C(p) = R p + t``; ``inverse``: the
    correction is the exact inverse of the model (default) or its first-order form
    ``measured_deviation``. See the module docstring for the signs.
    """

    def __init__(self, geometry: HeadGeometry, effects: HeadEffects | Mapping[str, Sequence[float]],
                 rotation_rad: float = 0.0, translation_mm: Sequence[float] = (0.0, 0.0), *,
                 inverse: bool = True) -> None:
        if not isinstance(geometry, HeadGeometry):
            raise ValueError(f"geometry must be a HeadGeometry, got {type(geometry).__name__}")
        self.geometry = geometry
        self.effects = effects if isinstance(effects, HeadEffects) else HeadEffects(effects)
        self.rotation_rad = float(as_finite_array(rotation_rad, "rotation_rad", ndim=0))
        translation = as_finite_array(translation_mm, "translation_mm", ndim=1)
        if translation.shape != (2,):
            raise ValueError(f"translation_mm must hold 2 values, got {translation.size}")
        self.translation_mm = translation
        if not isinstance(inverse, (bool, np.bool_)):
            raise ValueError(f"inverse must be a bool, got {inverse!r}")
        self.inverse = bool(inverse)
        self._head = PhysicalHead(geometry, self.effects)
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        self._rotation = np.array([[c, -s], [s, c]])

    @classmethod
    def from_discrepancy(cls, result: DiscrepancyResult, targets_xy, measured_xy, *,
                         inverse: bool = True) -> "PhysicalDeviationModel":
        """Return the model of a discrepancy result, aligned onto the measurement ``measured_xy`` of ``targets_xy``.

        The rigid motion is the least-squares fit of the model's landing onto the measured points
        (the exact inverse of the alignment the discrepancy fit applies to the measurement).
        """
        return cls.aligned(result.geometry, result.model_effects, targets_xy, measured_xy, inverse=inverse)

    @classmethod
    def aligned(cls, geometry: HeadGeometry, effects: HeadEffects, targets_xy, measured_xy, *,
                inverse: bool = True) -> "PhysicalDeviationModel":
        """Return the model of ``effects``, its landing of ``targets_xy`` rigidly fitted onto ``measured_xy``.

        Parameters
        ----------
        geometry : HeadGeometry
            The nominal head.
        effects : HeadEffects
            The effects of the model.
        targets_xy, measured_xy : array_like, shape (N, 2)
            The commanded targets (gls frame) and where they were measured, mm.
        inverse : bool, default True
            The correction is the exact inverse of the model.

        Returns
        -------
        PhysicalDeviationModel
            The model, its landing carried into the measurement's frame.

        Raises
        ------
        ValueError
            For mismatched or non-finite points.
        """
        targets_xy, measured_xy = as_matching_points(targets_xy, measured_xy, "targets_xy", "measured_xy", 2)
        unaligned = cls(geometry, effects, inverse=inverse)
        alignment, _ = align_rigid_2d(unaligned.landing(targets_xy), measured_xy)
        return cls(geometry, effects, alignment.rotation_rad, alignment.translation_mm, inverse=inverse)

    def parameter_vector(self) -> np.ndarray:
        """Return the parameters as one vector: the effects' values (stored order), rotation (rad), translation (mm)."""
        values = [value for parameters in self.effects.values.values() for value in parameters]
        return np.array(values + [self.rotation_rad, *self.translation_mm], dtype=float)

    def parameter_scales(self) -> np.ndarray:
        """Return the typical size of each parameter of :meth:`parameter_vector` (effect table; rigid motion)."""
        typical = [parameter.typical for name in self.effects.values for parameter in EFFECT_TABLE[name].parameters]
        return np.array(typical + list(_RIGID_TYPICAL), dtype=float)

    def with_parameters(self, vector) -> "PhysicalDeviationModel":
        """Return the same model (geometry, effect names, inverse) with the parameters ``vector``.

        Parameters
        ----------
        vector : array_like
            As :meth:`parameter_vector` orders them.

        Returns
        -------
        PhysicalDeviationModel
            The model with these parameters.

        Raises
        ------
        ValueError
            For a vector of another length or with non-finite values.
        """
        vector = as_finite_array(vector, "parameter vector", ndim=1)
        current = self.parameter_vector()
        if vector.shape != current.shape:
            raise ValueError(f"parameter vector must hold {current.size} values, got {vector.size}")
        effects, start = {}, 0
        for name, parameters in self.effects.values.items():
            effects[name] = tuple(float(value) for value in vector[start:start + len(parameters)])
            start += len(parameters)
        return PhysicalDeviationModel(self.geometry, HeadEffects(effects), float(vector[-3]), vector[-2:],
                                      inverse=self.inverse)

    def landing(self, commanded_xy) -> np.ndarray:
        """Where the modelled head lands (M, 2), measurement frame, when commanded to ``commanded_xy`` nominally."""
        commanded_xy = as_points(commanded_xy, "points", 2, min_length=0)
        if commanded_xy.shape[0] == 0:
            return np.empty((0, 2))
        joints = inverse(self.geometry, commanded_xy[:, 0], commanded_xy[:, 1])
        landed = self._head.land(joints.alpha_x, joints.alpha_y)[:, :2]
        return landed @ self._rotation.T + self.translation_mm

    def measured_deviation(self, points) -> np.ndarray:
        """``Q - landing(Q)`` (M, 2): the deviation a plate marked through the nominal model would show."""
        points = as_points(points, "points", 2, min_length=0)
        return points - self.landing(points)

    def __call__(self, points) -> np.ndarray:
        """Correction (M, 2) in mm at targets ``points`` (M, 2) in mm."""
        points = as_points(points, "points", 2, min_length=0)
        first_order = points - self.landing(points)
        if not self.inverse or points.shape[0] == 0:
            return first_order
        # Fixed point K <- K + (Q - L(K)): the landing's Jacobian is the identity within a few
        # per cent, so each step gains about two decimal places.
        commanded = points + first_order
        for _ in range(_INVERSE_MAX_ITERATIONS):
            miss = points - self.landing(commanded)
            commanded += miss
            if float(np.max(np.abs(miss))) <= _INVERSE_TOLERANCE_MM:
                break
        return commanded - points

    def to_dict(self) -> dict:
        """Plain-number description (YAML-ready) from which :meth:`from_dict` rebuilds the same model."""
        return {
            "type": "physical",
            "geometry": {f.name: float(getattr(self.geometry, f.name)) for f in fields(HeadGeometry)},
            "effects": {name: list(values) for name, values in self.effects.values.items()},
            "alignment": {"rotation_rad": self.rotation_rad, "translation_mm": self.translation_mm.tolist(),
                          "maps": "model landing (gls) -> measurement frame"},
            "inverse": self.inverse,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "PhysicalDeviationModel":
        """Rebuild a model written by :meth:`to_dict`."""
        require_type(data, "physical")
        effects = require_key(data, "effects")
        if not isinstance(effects, Mapping):
            raise ValueError(f"physical model effects must be a mapping, got {type(effects).__name__}")
        alignment = require_key(data, "alignment")
        if not isinstance(alignment, Mapping):
            raise ValueError(f"physical model alignment must be a mapping, got {type(alignment).__name__}")
        return cls(_geometry_from_dict(require_key(data, "geometry")), HeadEffects(dict(effects)),
                   require_key(alignment, "rotation_rad"), require_key(alignment, "translation_mm"),
                   inverse=data.get("inverse", True))

    def __repr__(self) -> str:
        """Show the non-zero effects, the rotation and whether the model is the inverse."""
        return (f"PhysicalDeviationModel(effects={self.effects.nonzero()!r}, "
                f"rotation_rad={self.rotation_rad:.3g}, inverse={self.inverse})")


class SumModel:
    """Several deviation models as one: ``model(Q) = sum_i part_i(Q)`` (e.g. physics + RBF)."""

    def __init__(self, models: Sequence[rbf.DeviationModel]) -> None:
        models = tuple(models)
        if not models:
            raise ValueError("a sum model needs at least one model")
        for index, model in enumerate(models):
            if not callable(model) or not hasattr(model, "to_dict"):
                raise ValueError(f"models[{index}] is not a deviation model (callable with to_dict)")
        self.models = models

    def __call__(self, points) -> np.ndarray:
        """Return the summed outputs (M, 2) in mm at ``points`` (M, 2) in mm."""
        points = as_points(points, "points", 2, min_length=0)
        total = np.zeros_like(points)
        for model in self.models:
            total += model(points)
        return total

    def to_dict(self) -> dict:
        """Plain-number description: the parts' descriptions in order."""
        return {"type": "sum", "models": [model.to_dict() for model in self.models]}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any],
                  part_from_dict: Callable[[Mapping[str, Any]], rbf.DeviationModel]) -> "SumModel":
        """Rebuild a sum written by :meth:`to_dict`, each part through ``part_from_dict``.

        ``part_from_dict`` is the registry's
        :func:`gls_calibration.models.deviation_models.model_from_dict`: a part may be of any stored
        type.
        """
        require_type(data, "sum")
        parts = require_key(data, "models")
        if not isinstance(parts, Sequence) or isinstance(parts, (str, bytes)):
            raise ValueError(f"sum model 'models' must be a list, got {type(parts).__name__}")
        return cls([part_from_dict(part) for part in parts])

    def __repr__(self) -> str:
        """Show the parts in order of application."""
        return f"SumModel({', '.join(repr(model) for model in self.models)})"


@dataclass(frozen=True, eq=False)
class PhysicsTrainingReport:
    """What :func:`train_physics_then_rbf` did: named effects, what the physics left, the RBF choice."""

    named_effects: tuple[str, ...]
    effects: Mapping[str, tuple[float, ...]]      # the physical model's effects (known plus named)
    deviation_rms_mm: float                       # RMS |delta| of the training deviations
    residual_rms_mm: float                        # RMS |delta - physical part| the RBF was trained on
    noise_floor_mm: float                         # estimated by the discrepancy workflow
    stop_reason: str
    physical_model: Optional[PhysicalDeviationModel]   # None when no effect was used (RBF only)
    residual_model: rbf.DeviationModel
    selection: rbf.ModelSelection
    discrepancy: DiscrepancyResult
    duration_s: float

    @property
    def uses_physics(self) -> bool:
        """Return True when the trained model holds a physical part."""
        return self.physical_model is not None

    @property
    def cv_rms_mm(self) -> float:
        """Cross-validated RMS of the residual model (mm)."""
        return float(self.selection.chosen.cv_rms_mm)

    @property
    def method(self) -> str:
        """``physics+<rbf method>``, or the RBF method alone when no effect was used."""
        return f"physics+{self.selection.method}" if self.uses_physics else self.selection.method

    def to_dict(self) -> dict:
        """Plain-number summary (YAML-ready)."""
        return {"method": self.method, "named_effects": list(self.named_effects),
                "effects": {name: list(values) for name, values in self.effects.items()},
                "deviation_rms_mm": self.deviation_rms_mm, "residual_rms_mm": self.residual_rms_mm,
                "noise_floor_mm": self.noise_floor_mm, "cv_rms_mm": self.cv_rms_mm,
                "stop_reason": self.stop_reason, "selection": self.selection.to_dict(),
                "duration_s": self.duration_s}


def _rms(vectors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(vectors ** 2, axis=1))))


def train_physics_then_rbf(targets_xy, deviations, geometry: Optional[HeadGeometry] = None, *,
                           known_effects: HeadEffects | Mapping | None = None,
                           candidates: Optional[Sequence[str]] = None, inverse: bool = True,
                           **select_kwargs: Any) -> tuple[rbf.DeviationModel, PhysicsTrainingReport]:
    """Physics first, RBF on what is left: a :class:`SumModel` of the physical model and the RBF/TPS.

    ``targets_xy`` (N, 2) and ``deviations`` (N, 2) ``delta = Q - P`` in mm (a plate marked through
    the nominal model); ``geometry`` the nominal head (default: the published one). The discrepancy
    workflow (:func:`gls_calibration.discrepancy.explain` on ``Q`` and ``P = Q - delta``, with
    ``known_effects`` and ``candidates``) names the effects; :func:`rbf.select_model`
    (``select_kwargs``) fits the deviations the physical model leaves. When no effect is named and
    none is known, the result is the plain RBF-only model of the deviations.
    """
    began = time.perf_counter()
    targets_xy, deviations = as_matching_points(targets_xy, deviations, "targets_xy", "deviations", 2,
                                                min_length=MIN_POINTS)
    geometry = geometry if geometry is not None else HeadGeometry()
    measured = targets_xy - deviations
    result = explain(targets_xy, measured, geometry, known_effects, candidates=candidates)
    physical = None
    residual = deviations
    if result.model_effects.nonzero():
        physical = PhysicalDeviationModel.from_discrepancy(result, targets_xy, measured, inverse=inverse)
        residual = deviations - physical.measured_deviation(targets_xy)
    residual_model, selection = rbf.select_model(targets_xy, residual, **select_kwargs)
    model = residual_model if physical is None else SumModel([physical, residual_model])
    report = PhysicsTrainingReport(
        named_effects=tuple(result.fitted_effects),   # what the physical part holds, groups included
        effects=MappingProxyType(dict(result.model_effects.nonzero())),
        deviation_rms_mm=_rms(deviations), residual_rms_mm=_rms(residual),
        noise_floor_mm=float(result.noise_floor_mm), stop_reason=result.stop_reason,
        physical_model=physical, residual_model=residual_model, selection=selection, discrepancy=result,
        duration_s=time.perf_counter() - began)
    return model, report


def physics_first_parts(model: Mapping[str, Any]) -> tuple[PhysicalDeviationModel, Mapping[str, Any]]:
    """Return the physical part and the residual model's description of a physics-first model's description.

    Parameters
    ----------
    model : mapping
        A ``sum`` model's ``to_dict()`` form as :func:`train_physics_then_rbf` makes it: a ``physical``
        part, then an ``ols_rbf`` or ``thin_plate_spline`` part.

    Returns
    -------
    tuple
        (the physical part as a :class:`PhysicalDeviationModel`, the residual part's mapping).

    Raises
    ------
    ValueError
        For another type or other parts.
    """
    require_type(model, "sum")
    parts = require_key(model, "models")
    kinds = ([part.get("type") if isinstance(part, Mapping) else type(part).__name__ for part in parts]
             if isinstance(parts, Sequence) and not isinstance(parts, (str, bytes)) else None)
    if kinds is None or len(kinds) != 2 or kinds[0] != "physical" or kinds[1] not in RESIDUAL_TYPES:
        raise ValueError(f"a physics-first model is the sum of a physical model and one of "
                         f"{', '.join(RESIDUAL_TYPES)}, got parts {kinds}")
    return PhysicalDeviationModel.from_dict(parts[0]), parts[1]


def refit_physics_then_rbf(model: Mapping[str, Any], targets_xy, deviations,
                           refit_residual: Callable[[np.ndarray, np.ndarray], rbf.DeviationModel]) -> SumModel:
    """Refit a physics-first model on other data with its structure held: the same effects and RBF settings.

    What :func:`train_physics_then_rbf` does with the selection held fixed: the effects the model
    holds are fitted again (from their values in ``model``, least squares on the points the
    discrepancy workflow keeps, the rigid motion profiled out), the rigid motion of the model's landing
    onto the measurement is fitted on all points, and the residual model is refitted by
    ``refit_residual`` on what the physics leaves.

    Parameters
    ----------
    model : mapping
        The physics-first model's description (see :func:`physics_first_parts`).
    targets_xy, deviations : array_like, shape (N, 2)
        The targets Q and the deviations ``Q - P`` to fit, mm.
    refit_residual : callable
        ``(targets (N, 2), residual (N, 2)) -> model`` with the residual model's hyper-parameters.

    Returns
    -------
    SumModel
        The refitted physical model plus the refitted residual model.

    Raises
    ------
    ValueError
        For a model that is not physics first, mismatched points or too few of them.
    """
    physical, _ = physics_first_parts(model)
    targets_xy, deviations = as_matching_points(targets_xy, deviations, "targets_xy", "deviations", 2,
                                                min_length=MIN_POINTS)
    measured = targets_xy - deviations
    inliers = fit_inliers(targets_xy, measured, physical.geometry)
    # sigma only scales the fit's covariance: the fit is unweighted, as in train_physics_then_rbf
    fitted = fit_effects(targets_xy[inliers], measured[inliers], physical.geometry, tuple(physical.effects.values),
                         known_effects=physical.effects, sigma_axis_mm=1.0)
    refitted = PhysicalDeviationModel.aligned(physical.geometry, fitted.effects, targets_xy, measured,
                                              inverse=physical.inverse)
    return SumModel([refitted, refit_residual(targets_xy, deviations - refitted.measured_deviation(targets_xy))])
