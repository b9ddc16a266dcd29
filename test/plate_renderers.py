"""The issue 31 item 2 conditions rendered by both plate renderers, as clouds a user would hand over.

``render(renderer, condition, per_side, seed)`` gives ``(cloud (N, 4) x, y, z, intensity in mm,
true centres (K, 3))`` from ``test/rendering.py`` (``"project"``: its organized scan flattened to a
list of points, as a ``.pcd`` export carries it) or ``test/rendering_independent.py``
(``"independent"``). Both render each named condition of ``CONDITIONS`` on top of their own base
scan (about 1 % intensity noise, a plate tilted by 1-1.3 deg and off centre).
"""
from __future__ import annotations

import numpy as np

import rendering
import rendering_independent

RENDERERS = ("project", "independent")
CONDITIONS = tuple(rendering_independent.CONDITIONS)
"""Point pitch 0.07 / 0.1 / 0.15 mm, correlated speckle of contrast 0.3, marks darkening the steel to
85 %, a 3 deg tilt (issue 31 item 2)."""

_PROJECT = {
    "pitch_0.07": dict(pixel_mm=0.07),
    "pitch_0.1": dict(pixel_mm=0.1),
    "pitch_0.15": dict(pixel_mm=0.15),
    "speckle_0.3": dict(speckle=0.3, speckle_corr_px=1.5),
    "marks_85pct": dict(mark_ratio=0.85),
    "tilt_3deg": dict(tilt_rad=(0.04, -0.035)),
}
"""The same conditions in ``rendering.render_plate_scan``'s keywords (as its ``vision_conditions``)."""


def render(renderer: str, condition: str, per_side: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Cloud (N, 4) in mm and true centres (K, 3) of one condition from one renderer."""
    if renderer == "independent":
        return rendering_independent.render_independent_plate(
            per_side, seed=seed, **rendering_independent.CONDITIONS[condition])
    if renderer != "project":
        raise ValueError(f"unknown renderer {renderer!r}")
    scan = dict(rendering.BASE_SCAN, **_PROJECT[condition])
    truth_uv = rendering.grid_truth(per_side, seed=seed)
    xyz, intensity = rendering.render_plate_scan(truth_uv, size_mm=rendering.scan_size_mm(per_side),
                                                 supersampling=4, seed=seed, **scan)
    truth = rendering.plate_to_scanner(truth_uv, scan["tilt_rad"], scan["offset_mm"])
    cloud = np.column_stack([xyz.reshape(-1, 3), intensity.reshape(-1)])
    return cloud[np.random.default_rng(seed + 100).permutation(len(cloud))], truth
