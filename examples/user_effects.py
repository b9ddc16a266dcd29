"""A user effect for ``gls-discrepancy --effects user_effects:encoder_nonlinearity_x``.

The signature every user effect follows: a function without arguments returning a
:class:`gls_calibration.geometry.effect_table.UserEffect`, i.e. an
:class:`~gls_calibration.geometry.effect_table.EffectSpec` (name, parameters with unit, typical magnitude and
plausible range, one sentence of physics) and ``deviation(context, values) -> (N, 2) mm``: how far
the landing point moves in the plane for the parameter values, zero for zero values. ``context``
carries the nominal geometry, the commanded targets (N, 2, mm), the commanded mirror angles
``alpha_x``, ``alpha_y`` (N,, rad) and the marking time ``t`` (or None).
"""
from __future__ import annotations

import numpy as np

from gls_calibration.geometry.effect_table import EffectContext, EffectSpec, ParameterSpec, UserEffect
from gls_calibration.geometry.optics import PhysicalHead

#: Period of the X encoder's error in mechanical angle (rad): about 40 mm on the plate at 490 mm.
PERIOD_RAD = 0.04


def encoder_deviation(context: EffectContext, values: np.ndarray) -> np.ndarray:
    """The X mirror turns to alpha + A sin(2 pi alpha / P) instead of alpha: where the spot moves (N, 2) mm."""
    head = PhysicalHead(context.geometry)
    amplitude_rad = values[0]
    turned = context.alpha_x + amplitude_rad * np.sin(2.0 * np.pi * context.alpha_x / PERIOD_RAD)
    return (head.land(turned, context.alpha_y, context.t)[:, :2]
            - head.land(context.alpha_x, context.alpha_y, context.t)[:, :2])


def encoder_nonlinearity_x() -> UserEffect:
    """Periodic error of the X galvo's angle encoder (amplitude in rad of mechanical angle)."""
    spec = EffectSpec(
        "encoder_nonlinearity_x",
        (ParameterSpec("amplitude_rad", "rad", typical=1e-4, low=-2e-3, high=2e-3),),
        "The X galvo's angle encoder reads a periodic error: the mirror turns to "
        "alpha + amplitude_rad * sin(2 pi alpha / 0.04 rad) when alpha is commanded.")
    return UserEffect(spec, encoder_deviation)
