"""Separability: whether the data tell a fitted effect from the rigid motion and the others.

Separability: can the data tell a fitted effect from the rigid motion and from the other candidates?

A fitted effect is named only when the part of its field that survives the rigid alignment and the
other named effects is large against its standard error at the noise the fit used. For an effect E
with fitted change ``v`` (its value minus the known one) and whitened Jacobian columns ``J_E``
(landing change per parameter divided by the per-axis sigma), with ``P`` the projection onto the
complement of the columns ``B`` of the rigid motion (rotation, translation x, y) and of the other
named effects, the statistic is the Wald statistic's square root

    z_E = sqrt(v' (J_E' P J_E) v),

i.e. the projected size of the fitted field over its standard error (for one parameter:
``|v| / se(v)``). With ``z_E < SEPARABLE_AT`` the effect is not separable from B. For every other
candidate C the same statistic with C's columns added to B says whether E is separable from C; the
candidates it is not separable from form its group: the data say "one of these", not which one.
The Jacobian is linearised at the final fit (finite differences in each parameter's typical size).
"""
from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np

from gls_calibration.discrepancy.fitting import Predictor, typical_scales
from gls_calibration.discrepancy.results import EffectsFit
from gls_calibration.geometry.optics import HeadEffects

#: A fitted effect is separable when its projected size is at least this many standard errors
#: (two-sided p ~ 6e-5 for one parameter: a dozen candidates over a few steps stay below 1e-3 in all).
SEPARABLE_AT = 4.0
_STEP = 1e-3   # finite-difference step, in typical units


@dataclass(frozen=True)
class Separability:
    """How well the data tell one fitted effect from the rigid motion and from the other candidates."""

    name: str
    z: float                           # projected size / standard error, rigid motion and other named effects out
    z_rigid: float                     # the same with only the rigid motion out
    group: tuple[str, ...]             # the effect, then the candidates it cannot be told from
    z_with: Mapping[str, float]        # z with each of those candidates' columns also profiled out
    separable_from_rigid: bool

    @property
    def named_alone(self) -> bool:
        """Separable from the rigid motion, the other named effects and every candidate."""
        return self.separable_from_rigid and len(self.group) == 1

    def to_dict(self) -> dict:
        """JSON-ready mapping."""
        return {"name": self.name, "z": self.z, "z_rigid": self.z_rigid, "group": list(self.group),
                "z_with": dict(self.z_with), "separable_from_rigid": self.separable_from_rigid}


def _columns(predict: Predictor, model: EffectsFit, name: str, scales: np.ndarray) -> np.ndarray:
    """Landing change (2N, k) per typical unit of each parameter of ``name``, about the final model."""
    base = model.predicted_xy
    user = {n: np.asarray(v, dtype=float) for n, v in model.user_values.items()}
    columns = []
    for i, scale in enumerate(scales):
        if name in predict.user_effects:
            values = np.array(user.get(name, np.zeros(len(scales))), dtype=float)
            values[i] += _STEP * scale
            moved = predict(model.effects, {**user, name: values})
        else:
            values = np.array(model.effects.get(name), dtype=float)
            values[i] += _STEP * scale
            moved = predict(model.effects.replace(**{name: tuple(values)}), user)
        columns.append(((moved - base) / _STEP).ravel())
    return np.column_stack(columns)


def _rigid_columns(base_xy: np.ndarray) -> np.ndarray:
    centred = base_xy - base_xy.mean(axis=0)
    return np.column_stack([np.column_stack([-centred[:, 1], centred[:, 0]]).ravel(),
                            np.tile([1.0, 0.0], len(base_xy)), np.tile([0.0, 1.0], len(base_xy))])


def _z(effect: np.ndarray, values: np.ndarray, others: np.ndarray) -> float:
    """sqrt(v' (J' P J) v) with P the projection onto the complement of ``others``' span."""
    basis, singular, _ = np.linalg.svd(others, full_matrices=False)
    basis = basis[:, singular > singular[0] * 1e-10]
    field = effect @ values
    projected = field - basis @ (basis.T @ field)
    return float(np.linalg.norm(projected))


def separability(predict: Predictor, model: EffectsFit, known: HeadEffects, pool: Sequence[str], sigma_axis_mm,
                 *, threshold: float = SEPARABLE_AT) -> tuple[Separability, ...]:
    """Return the :class:`Separability` of each effect of ``model`` (in its order).

    :class:`Separability` of each effect of ``model`` (in its order) against the rigid motion, the
    other named effects and every candidate of ``pool``.

    ``sigma_axis_mm`` is the per-axis noise (a number or one per point) the standard errors refer to.
    """
    if not model.names:
        return ()
    sigma = np.asarray(sigma_axis_mm, dtype=float)
    weights = np.repeat(1.0 / np.broadcast_to(sigma, (len(model.predicted_xy),)), 2)
    names = tuple(dict.fromkeys(tuple(model.names) + tuple(pool)))
    scales = {name: typical_scales([predict.spec(name)], predict.t) for name in names}
    whitened = {name: _columns(predict, model, name, scales[name]) * weights[:, None] for name in names}
    rigid = _rigid_columns(model.predicted_xy) * weights[:, None]
    records = []
    for name in model.names:
        start = np.array(known.get(name), dtype=float) if name not in predict.user_effects else 0.0
        change = (np.array(list(model.parameters(name).values())) - start) / scales[name]
        others = np.column_stack([rigid] + [whitened[n] for n in model.names if n != name])
        z = _z(whitened[name], change, others)
        z_rigid = _z(whitened[name], change, rigid)
        z_with = {}
        for candidate in names:
            if candidate == name:
                continue
            if candidate in model.names:
                # a named effect: separable from it alone (the others are not in the way)
                value = _z(whitened[name], change, np.column_stack([rigid, whitened[candidate]]))
            else:
                value = _z(whitened[name], change, np.column_stack([others, whitened[candidate]]))
            if value < threshold:
                z_with[candidate] = value
        if z < threshold and not any(c in model.names for c in z_with):
            # not separable from the other named effects together, from none of them alone: all of them
            z_with.update({n: z for n in model.names if n != name})
        group = (name,) + tuple(sorted(z_with, key=z_with.get))
        records.append(Separability(name, z, z_rigid, group, MappingProxyType(z_with), z_rigid >= threshold))
    return tuple(records)
