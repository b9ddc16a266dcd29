"""Observability: how much of each effect survives the rigid alignment, and which effects look alike."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
from scipy.linalg import subspace_angles

from gls_calibration.discrepancy.fitting import Predictor, typical_scales
from gls_calibration.discrepancy.residual_statistics import rms
from gls_calibration.geometry.effect_table import EFFECT_TABLE, EFFECTS
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.geometry.optics import HeadEffects
from gls_calibration.registration.rigid import align_rigid_2d


@dataclass(frozen=True, eq=False)
class ObservabilityReport:
    """How much of each effect survives rigid alignment, and how alike the effects look afterwards."""

    effects: tuple[str, ...]
    # (effect, parameter, magnitude, rms raw, rms aligned) mm
    parameters: tuple[tuple[str, str, float, float, float], ...]
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
    magnitudes = {**{p.name: p.typical for spec in EFFECT_TABLE.values() for p in spec.parameters},
                  **(magnitudes or {})}
    axis = np.linspace(-0.5 * size_mm, 0.5 * size_mm, per_side)
    grid_x, grid_y = np.meshgrid(axis, axis)
    targets = np.column_stack([grid_x.ravel(), grid_y.ravel()])
    t = np.linspace(0.0, duration_s, len(targets))
    predict = Predictor(geometry, targets, t)
    base = predict(HeadEffects())
    scales = {name: typical_scales([spec], t) for name, spec in EFFECT_TABLE.items()}
    rows, spans = [], {}
    for name, parameters in EFFECTS.items():
        columns = []
        for i, parameter in enumerate(parameters):
            magnitude = scales[name][i] if EFFECT_TABLE[name].parameters[i].per_run else magnitudes[parameter]
            vector = np.zeros(len(parameters))
            vector[i] = magnitude
            change = predict(HeadEffects({name: vector})) - base
            _, moved = align_rigid_2d(base + change, base)
            aligned = moved - base   # what the rigid alignment cannot remove
            rows.append((name, parameter, float(magnitude), rms(change), rms(aligned)))
            columns.append(aligned.ravel())
        spans[name] = np.column_stack(columns)
    names = tuple(EFFECTS)
    similarity = np.eye(len(names))
    for i, a in enumerate(names):
        for j in range(i + 1, len(names)):
            value = float(np.cos(np.min(subspace_angles(spans[a], spans[names[j]]))))
            similarity[i, j] = similarity[j, i] = value
    return ObservabilityReport(names, tuple(rows), similarity)
