"""A second, independent model of a scanned marked plate (issue 31 item 2), sharing no code with
``test/rendering.py``.

The detector was developed on ``rendering.py``'s plates (Gaussian-free exact pixel coverage of sharp
lines, log-normal speckle from filtered noise, uniform mark darkness, a perfect scan grid). This
module models the same physics differently, so that a detector tuned to one renderer shows it:

- **Points**: a laser-line scanner's profiles (scan lines along x, ``line_pitch_mm`` apart in y),
  each line displaced across itself by its own random jitter and starting at its own random phase
  along x, points ``point_pitch_mm`` apart along it with a little along-line jitter. No two lines
  share a lattice, so the cloud has no regular grid to follow.
- **Line profile**: each ring line is flat-topped with soft edges (a raised-cosine taper), its full
  width at half depth ``line_width_mm``; a point samples the profile at its own position (no
  pixel-area integration).
- **Mark darkness** varies along the marking path: each ring's depth follows a smooth random
  function of the angle (a marking laser's power and speed are not constant).
- **Speckle** is a sum of random phasors: a complex field built from random-phase plane waves whose
  spatial frequencies fill a disc (the scanner's aperture, grain size ``speckle_grain_mm``), so its
  intensity is fully developed (exponential) speckle; a share ``speckle_contrast`` of the returned
  light carries it, the rest is diffuse, which sets the contrast (standard deviation / mean).

``render_independent_plate`` returns an ``(N, 4)`` cloud ``x, y, z, intensity`` in mm (``in_metres``
for the same cloud with x, y, z in metres) and the true centres ``(K, 3)`` in the scanner frame.
"""
from __future__ import annotations

import numpy as np
from scipy import fft
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

STEEL_COUNTS = 1000.0
"""Intensity of bare steel (arbitrary units)."""

PLATE_SPAN_MM = 190.0
"""First to last centre of the 19x19 grid."""

SPECKLE_TILE_PX = 2048
"""Side of the periodic speckle field's sample grid; at a third of a grain per sample it repeats only
every few hundred grains, far beyond a fiducial."""


def grid_centres_mm(per_side: int, span_mm: float | None = None, seed: int = 0) -> np.ndarray:
    """Plate-plane centres (K, 2) of a per_side x per_side grid at the 19x19 plate's pitch (span
    ``span_mm``, default ``(per_side - 1) * 190 / 18``), each moved by a random sub-point offset of up
    to 0.04 mm so no centre sits on a scan point."""
    pitch_mm = PLATE_SPAN_MM / 18
    span_mm = (per_side - 1) * pitch_mm if span_mm is None else span_mm
    axis = np.linspace(-span_mm / 2, span_mm / 2, per_side)
    u, v = np.meshgrid(axis, axis)
    centres = np.column_stack([u.ravel(), v.ravel()])
    return centres + np.random.default_rng(seed + 7).uniform(-0.04, 0.04, centres.shape)


def _plate_axes(tilt_deg: float, tilt_azimuth_deg: float) -> np.ndarray:
    """Columns: the plate's in-plane axes and normal in the scanner frame, the plate tipped by
    ``tilt_deg`` about the in-plane axis at ``tilt_azimuth_deg`` from x (Rodrigues' formula)."""
    azimuth = np.deg2rad(tilt_azimuth_deg)
    k = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
    angle = np.deg2rad(tilt_deg)
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def _scan_points(half_extent_mm: float, point_pitch_mm: float, line_pitch_mm: float,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Scanner x, y of every point: lines along x with per-line jitter across and phase along."""
    lines = np.arange(-half_extent_mm, half_extent_mm, line_pitch_mm)
    line_y = lines + rng.normal(0.0, 0.12 * line_pitch_mm, lines.size)
    phase = rng.uniform(0.0, point_pitch_mm, lines.size)
    along = np.arange(-half_extent_mm, half_extent_mm, point_pitch_mm)
    x = along[None, :] + phase[:, None] + rng.normal(0.0, 0.03 * point_pitch_mm, (lines.size, along.size))
    y = np.broadcast_to(line_y[:, None], x.shape)
    return x.ravel(), np.array(y).ravel()


def _flat_top_depth(distance_mm: np.ndarray, line_width_mm: float) -> np.ndarray:
    """Depth 0-1 across a line: 1 on a flat core, raised-cosine edges of 40 % of the width each side,
    0.5 at +-line_width_mm / 2 (the full width at half depth)."""
    edge = 0.4 * line_width_mm
    core = line_width_mm / 2 - edge / 2
    beyond = np.clip((np.abs(distance_mm) - core) / edge, 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * beyond))


def _speckle_field(grain_mm: float, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Complex speckle field (unit mean intensity) on a periodic grid and its sample step (mm): a sum of
    unit phasors of random phase, one per spatial frequency inside the aperture's disc (cut-off
    1 / grain_mm); its squared modulus is fully developed (exponential) speckle."""
    step_mm = grain_mm / 4
    frequency = fft.fftfreq(SPECKLE_TILE_PX, d=step_mm)
    inside = np.hypot(*np.meshgrid(frequency, frequency)) <= 1.0 / grain_mm
    phasors = np.where(inside, np.exp(2j * np.pi * rng.random(inside.shape)), 0.0)
    field = fft.ifft2(phasors, workers=1)
    return field / np.sqrt(np.mean(np.abs(field) ** 2)), step_mm


def render_independent_plate(per_side: int = 5, *, point_pitch_mm: float = 0.1, line_pitch_mm: float | None = None,
                             ring_radii_mm=(2.5, 2.7), line_width_mm: float = 0.1, mark_ratio: float = 0.4,
                             darkness_variation: float = 0.2, speckle_contrast: float = 0.0,
                             speckle_grain_mm: float = 0.2, noise_fraction: float = 0.01,
                             tilt_deg: float = 1.0, tilt_azimuth_deg: float = 30.0,
                             offset_mm=(0.4, -0.3, 150.0), margin_mm: float = 6.0,
                             seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Render a scanned plate: ``(cloud (N, 4) x, y, z, intensity in mm, true centres (K, 3) mm)``.

    ``mark_ratio`` is the mean reflectance of a line's core relative to bare steel (0.85: marks
    darken the steel to 85 %); ``darkness_variation`` the relative amplitude of the darkness's
    change along each ring's path; ``speckle_contrast`` the standard deviation / mean of the speckle;
    ``noise_fraction`` additive detector noise relative to the steel's intensity; ``tilt_deg`` the
    plate's tilt about an in-plane axis at ``tilt_azimuth_deg``; ``offset_mm`` where the plate's
    centre lies. Points cover the grid plus ``margin_mm`` beyond its outer rings.
    """
    rng = np.random.default_rng(seed)
    line_pitch_mm = point_pitch_mm if line_pitch_mm is None else line_pitch_mm
    centres_uv = grid_centres_mm(per_side, seed=seed)
    axes = _plate_axes(tilt_deg, tilt_azimuth_deg)
    origin = np.asarray(offset_mm, dtype=float)
    half_extent = float(np.abs(centres_uv).max()) + max(ring_radii_mm) + margin_mm
    x, y = _scan_points(half_extent, point_pitch_mm, line_pitch_mm, rng)
    x, y = x + origin[0], y + origin[1]
    # Where each scanner ray (along z) meets the plate plane, and that point's plate coordinates.
    normal = axes[:, 2]
    z = origin[2] - (normal[0] * (x - origin[0]) + normal[1] * (y - origin[1])) / normal[2]
    relative = np.column_stack([x - origin[0], y - origin[1], z - origin[2]])
    uv = relative @ axes[:, :2]

    # Each point's nearest fiducial (the grid's pitch keeps every other one far beyond its rings).
    _, nearest = cKDTree(centres_uv).query(uv)
    offset_uv = uv - centres_uv[nearest]
    radius = np.hypot(offset_uv[:, 0], offset_uv[:, 1])
    angle = np.arctan2(offset_uv[:, 1], offset_uv[:, 0])
    variation = rng.normal(0.0, darkness_variation / np.sqrt(3), (len(centres_uv), len(ring_radii_mm), 3))
    phases = rng.uniform(0.0, 2 * np.pi, variation.shape)
    depth = np.zeros(len(x))
    for ring, ring_radius in enumerate(ring_radii_mm):
        close = np.abs(radius - ring_radius) < line_width_mm
        coefficients = np.stack([variation[nearest[close], ring], phases[nearest[close], ring]], axis=-1)
        along = np.ones(int(close.sum()))
        for order in range(3):
            along += coefficients[:, order, 0] * np.cos((order + 1) * angle[close] + coefficients[:, order, 1])
        depth[close] = np.maximum(depth[close], np.clip(along, 0.0, None)
                                  * _flat_top_depth(radius[close] - ring_radius, line_width_mm))
    reflectance = 1.0 - (1.0 - mark_ratio) * np.clip(depth, 0.0, 1.0 / max(1.0 - mark_ratio, 1e-9))
    # Slow illumination fall-off across the field, as a line laser's fan gives.
    shading = 1.0 - 0.04 * ((x - origin[0]) ** 2 + (y - origin[1]) ** 2) / half_extent**2
    intensity = STEEL_COUNTS * shading * np.clip(reflectance, 0.0, None)
    if speckle_contrast > 0:
        field, step_mm = _speckle_field(speckle_grain_mm, rng)
        coordinates = np.stack([uv[:, 1] / step_mm, uv[:, 0] / step_mm]) % SPECKLE_TILE_PX
        # The field (not its intensity) is interpolated between samples, then squared at each point.
        amplitude = (map_coordinates(field.real, coordinates, order=1, mode="grid-wrap")
                     + 1j * map_coordinates(field.imag, coordinates, order=1, mode="grid-wrap"))
        speckle = np.abs(amplitude) ** 2
        speckle /= speckle.mean()
        intensity = intensity * ((1.0 - speckle_contrast) + speckle_contrast * speckle)
    if noise_fraction > 0:
        intensity = intensity + rng.normal(0.0, noise_fraction * STEEL_COUNTS, intensity.shape)
    truth = origin + np.column_stack([centres_uv, np.zeros(len(centres_uv))]) @ axes.T
    cloud = np.column_stack([x, y, z, intensity])
    return cloud, truth


def in_metres(cloud_mm: np.ndarray) -> np.ndarray:
    """The same cloud with x, y, z in metres (intensity unchanged), as most ROS and PCL exports give."""
    cloud = np.array(cloud_mm, dtype=float, copy=True)
    cloud[:, :3] /= 1000.0
    return cloud


CONDITIONS = {
    "pitch_0.07": dict(point_pitch_mm=0.07),
    "pitch_0.1": dict(point_pitch_mm=0.1),
    "pitch_0.15": dict(point_pitch_mm=0.15),
    "speckle_0.3": dict(speckle_contrast=0.3),
    "marks_85pct": dict(mark_ratio=0.85),
    "tilt_3deg": dict(tilt_deg=3.0),
}
"""The issue's conditions as keywords of ``render_independent_plate`` (0.1 mm pitch unless named)."""
