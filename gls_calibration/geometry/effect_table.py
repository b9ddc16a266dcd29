"""The one table of the head's named physical effects: parameters, units, typical magnitude, plausible range.

Every consumer reads this table: the ray trace (:mod:`gls_calibration.geometry.optics`, parameter order),
the discrepancy workflow (fit scales, observability probes, plausibility), the configuration files
and the simulation's node parameters (units in descriptions).

``typical`` is the size of a parameter for a head of this class (the fit measures its unknowns in
it; observability probes each effect with it). ``low``/``high`` bound what is physically plausible
for such a head (f = 490 mm working distance, 10 mm mirror spacing, ~190 mm field): a fitted value
outside them is not named by the discrepancy workflow. For the two thermal rates ``typical`` is the
change over the whole run (divided by the marking-time span at use), the range is per second.
"""
from __future__ import annotations

from dataclasses import dataclass
import importlib
from types import MappingProxyType
from typing import Callable, Mapping

import numpy as np

from gls_calibration.geometry.kinematics import HeadGeometry


@dataclass(frozen=True)
class ParameterSpec:
    """One parameter of an effect."""

    name: str
    unit: str
    typical: float            # typical magnitude for a head of this class
    low: float                # plausible range, inclusive
    high: float
    per_run: bool = False     # ``typical`` is a change over the whole run (a rate per second otherwise)

    def plausible(self, value: float) -> bool:
        """Return True when ``value`` lies in the plausible range."""
        return self.low <= value <= self.high


@dataclass(frozen=True)
class EffectSpec:
    """One named effect: its parameters in vector order and one sentence of physics.

    Parameters
    ----------
    name : str
        The effect's name (a key of the effect table).
    parameters : tuple of ParameterSpec
        Its parameters in the order of its parameter vector (name, unit, typical magnitude, plausible range).
    doc : str
        One sentence on the physics of the effect.
    """

    name: str
    parameters: tuple[ParameterSpec, ...]
    doc: str

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Parameter names in vector order."""
        return tuple(p.name for p in self.parameters)

    @property
    def units(self) -> tuple[str, ...]:
        """Return the unit of each parameter, in vector order."""
        return tuple(p.unit for p in self.parameters)


def _symmetric(name: str, unit: str, typical: float, bound: float, per_run: bool = False) -> ParameterSpec:
    return ParameterSpec(name, unit, typical, -bound, bound, per_run)


_TABLE = (
    EffectSpec("mirror_distance", (_symmetric("delta_e_mm", "mm", 1.0, 5.0),),
               "The Y mirror pivot sits delta_e further from the X mirror pivot than nominal "
               "(-e - delta_e, 0, d); only y carries e, so only y changes."),
    EffectSpec("working_distance", (_symmetric("delta_d_mm", "mm", 1.0, 10.0),),
               "The plate lies delta_d below the nominal work plane (z = -delta_d, farther from "
               "the head when > 0); the field grows radially in proportion."),
    EffectSpec("galvo_gain_x", (_symmetric("gain_error_x", "1", 1e-3, 0.05),),
               "The X galvo turns (1 + gain_error_x) times the commanded mechanical angle: x scales."),
    EffectSpec("galvo_gain_y", (_symmetric("gain_error_y", "1", 1e-3, 0.05),),
               "The Y galvo turns (1 + gain_error_y) times the commanded mechanical angle: y scales."),
    EffectSpec("galvo_offset_x", (_symmetric("offset_x_rad", "rad", 1e-3, 0.05),),
               "The X galvo's zero is off by offset_x_rad (added to the mechanical angle): mostly a shift in x."),
    EffectSpec("galvo_offset_y", (_symmetric("offset_y_rad", "rad", 1e-3, 0.05),),
               "The Y galvo's zero is off by offset_y_rad (added to the mechanical angle): mostly a shift in y."),
    EffectSpec("axis_skew", (_symmetric("skew_rad", "rad", 1e-3, 0.02),),
               "The X mirror's rotation axis is tilted by skew_rad about gls x, out of perpendicular to "
               "the Y mirror axis; the mirror normal at zero angle stays nominal. Turning the X mirror "
               "then also deflects the beam in y: a shear (y changes in proportion to x). Convention: "
               "only the axis tilts. A whole X galvo turned by s about the beam reaching it (axis and "
               "mirror together) fits as skew_rad = 2 s plus a 0.56 s rad galvo_offset_y (or beam_tilt "
               "tilt_a_rad 1.1 s) and a rigid shift."),
    EffectSpec("mirror_offset", (_symmetric("offset_x_mm", "mm", 0.5, 3.0), _symmetric("offset_y_mm", "mm", 0.5, 3.0)),
               "Each reflecting surface is displaced along its normal (towards the incoming beam when "
               "> 0) from its rotation axis, so the reflection point walks as the mirror turns."),
    EffectSpec("beam_tilt", (_symmetric("tilt_a_rad", "rad", 1e-3, 0.05), _symmetric("tilt_b_rad", "rad", 1e-3, 0.05)),
               "The incoming laser beam is tilted off +y by tilt_a_rad towards +x and tilt_b_rad towards "
               "+z; it still meets the Y mirror pivot."),
    EffectSpec("plate_tilt", (_symmetric("tilt_x_rad", "rad", 5e-3, 0.05), _symmetric("tilt_y_rad", "rad", 5e-3, 0.05)),
               "The plate plane is rotated by tilt_x_rad about gls x, then by tilt_y_rad about gls y "
               "(axes through the plate origin): a keystone-like distortion."),
    EffectSpec("radial_distortion", (_symmetric("k1_per_mm2", "1/mm^2", 1e-7, 1e-6),),
               "The landing point moves radially about the field centre in the plate plane, "
               "r -> r (1 + k1 r^2), as an uncorrected lens or window would do."),
    EffectSpec("thermal_drift", (_symmetric("gain_rate_per_s", "1/s", 1e-3, 5e-5, per_run=True),
                                 _symmetric("offset_rate_rad_per_s", "rad/s", 1e-3, 5e-5, per_run=True)),
               "Gain error and zero offset of both galvos grow linearly with marking time t: "
               "+gain_rate_per_s * t and +offset_rate_rad_per_s * t."),
)

#: Effect name -> its specification, in the ray trace's order.
EFFECT_TABLE: Mapping[str, EffectSpec] = MappingProxyType({spec.name: spec for spec in _TABLE})

#: Effect name -> parameter names in vector order (a view of :data:`EFFECT_TABLE`).
EFFECTS: Mapping[str, tuple[str, ...]] = MappingProxyType({name: spec.parameter_names
                                                           for name, spec in EFFECT_TABLE.items()})


# --------------------------------------------------------------------------------------------------
# effects an engineer adds without editing the package

@dataclass(frozen=True, eq=False)
class EffectContext:
    """What a user effect may depend on, for the N commanded points of one data set.

    Parameters
    ----------
    geometry : HeadGeometry
        The nominal head.
    commanded_xy : numpy.ndarray, shape (N, 2)
        Nominal targets in the gls frame, mm.
    alpha_x, alpha_y : numpy.ndarray, shape (N,)
        Commanded X and Y mirror angles (mechanical, rad; nominal inverse kinematics).
    t : numpy.ndarray, shape (N,), or None
        Marking time of each point, s, or None when unknown.
    """

    geometry: HeadGeometry       # nominal head
    commanded_xy: np.ndarray     # (N, 2) nominal targets, gls frame, mm
    alpha_x: np.ndarray          # (N,) commanded X mirror angle (mechanical, rad; nominal inverse kinematics)
    alpha_y: np.ndarray          # (N,) commanded Y mirror angle (rad)
    t: np.ndarray | None         # (N,) marking time, s, or None


@dataclass(frozen=True, eq=False)
class UserEffect:
    """An effect outside the library: its table entry and the in-plane deviation it causes.

    ``deviation(context, values)`` returns (N, 2) mm added to where the modelled head lands (gls
    frame) for the parameter values ``values`` (k,), in the order of ``spec.parameters``; it must be
    zero for zero values. The discrepancy workflow fits ``values`` like a library effect, measures
    them in ``typical`` units and names the effect only within ``[low, high]``.

    Parameters
    ----------
    spec : EffectSpec
        The effect's name, parameters (with units, typical magnitudes and ranges) and physics.
    deviation : callable
        ``deviation(context: EffectContext, values: numpy.ndarray (k,)) -> numpy.ndarray (N, 2)``, mm.
    """

    spec: EffectSpec
    deviation: Callable[[EffectContext, np.ndarray], np.ndarray]

    @property
    def name(self) -> str:
        """Return the effect's name."""
        return self.spec.name


def load_user_effect(reference: str) -> UserEffect:
    """Import ``module:function`` and call ``function()``, which returns a :class:`UserEffect`.

    The module is found on ``sys.path`` (e.g. the working directory or ``PYTHONPATH``).

    Parameters
    ----------
    reference : str
        ``"module:function"``.

    Returns
    -------
    UserEffect
        The effect the function returned, checked by :func:`check_user_effect`.

    Raises
    ------
    ValueError
        Naming the problem: a reference not of the form ``module:function``, an import failure, a
        missing function, a failure inside the function, a return value that is not a UserEffect,
        or a check of :func:`check_user_effect` that fails (e.g. a name clash with the library).
    """
    module_name, _, function_name = reference.partition(":")
    if not module_name or not function_name:
        raise ValueError(f"user effect {reference!r} must be given as module:function")
    try:
        module = importlib.import_module(module_name)
    except Exception as error:   # ImportError, or the module's own failure (SyntaxError, ...)
        raise ValueError(f"user effect {reference!r}: cannot import {module_name!r}: {error}") from None
    factory = getattr(module, function_name, None)
    if not callable(factory):
        raise ValueError(f"user effect {reference!r}: {module_name} has no function {function_name!r}")
    try:
        effect = factory()
    except Exception as error:   # the engineer's code: any failure is reported as bad input
        raise ValueError(f"user effect {reference!r}: {function_name}() failed: {error}") from None
    if not isinstance(effect, UserEffect):
        raise ValueError(f"user effect {reference!r} must return a UserEffect, got {type(effect).__name__}")
    check_user_effect(effect)
    return effect


def check_user_effect(effect: UserEffect) -> None:
    """Check that ``effect`` has a new name, parameters, ranges about 0 and a callable deviation.

    Parameters
    ----------
    effect : UserEffect
        The effect to check.

    Raises
    ------
    ValueError
        If its name clashes with a library effect, it has no parameters, a parameter's typical
        magnitude is not positive or its plausible range does not contain 0, or ``deviation`` is not callable.
    """
    spec = effect.spec
    if spec.name in EFFECT_TABLE:
        raise ValueError(f"user effect {spec.name!r} clashes with the library effect of that name")
    if not spec.parameters:
        raise ValueError(f"user effect {spec.name!r} has no parameters")
    for parameter in spec.parameters:
        if not (parameter.typical > 0.0 and parameter.low <= 0.0 <= parameter.high):
            raise ValueError(f"user effect {spec.name!r}, parameter {parameter.name!r}: typical must be > 0 and "
                             f"the plausible range must contain 0, got typical {parameter.typical!r}, "
                             f"range [{parameter.low!r}, {parameter.high!r}]")
    if not callable(effect.deviation):
        raise ValueError(f"user effect {spec.name!r}: deviation is not callable")
