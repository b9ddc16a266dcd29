"""Synthetic laser-line scans of a marked plate, for the vision tests and benchmarks.

The scanner frame has x along a profile (columns), y along the travel (rows) and z up towards the
scanner. The plate is a plane through ``offset_mm`` tilted by ``tilt_rad`` (about x, then y); marks
are double rings drawn in plate coordinates. Each pixel's intensity is the mean reflectance over its
footprint, computed by supersampling with an exact 1-D coverage of the ring line per sub-sample, so
ring centres are meaningful well below a pixel.
"""
from __future__ import annotations

import numpy as np

BACKGROUND = 180.0
MARK = 60.0


def plate_frame(tilt_rad=(0.0, 0.0), offset_mm=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (columns: plate x, plate y, normal) and origin of the plate in the scanner frame."""
    tx, ty = tilt_rad
    rot_x = np.array([[1, 0, 0], [0, np.cos(tx), -np.sin(tx)], [0, np.sin(tx), np.cos(tx)]])
    rot_y = np.array([[np.cos(ty), 0, np.sin(ty)], [0, 1, 0], [-np.sin(ty), 0, np.cos(ty)]])
    return rot_y @ rot_x, np.asarray(offset_mm, dtype=float)


def plate_to_scanner(uv, tilt_rad=(0.0, 0.0), offset_mm=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Scanner-frame points (N, 3) of plate coordinates (N, 2)."""
    rotation, origin = plate_frame(tilt_rad, offset_mm)
    return origin + np.asarray(uv, dtype=float) @ rotation[:, :2].T


def _scanner_to_plate_uv(x, y, rotation, origin):
    """Plate coordinates of the plate surface point seen at scanner (x, y), and its height z."""
    x, y = np.broadcast_arrays(x, y)
    normal = rotation[:, 2]
    z = origin[2] - (normal[0] * (x - origin[0]) + normal[1] * (y - origin[1])) / normal[2]
    rel = np.stack([x - origin[0], y - origin[1], z - origin[2]], axis=-1)
    return rel @ rotation[:, 0], rel @ rotation[:, 1], z


def _band_coverage(distance, half_width, half_step):
    """Share of [distance - half_step, distance + half_step] inside [-half_width, half_width]."""
    low = np.maximum(distance - half_step, -half_width)
    high = np.minimum(distance + half_step, half_width)
    return np.clip(high - low, 0.0, None) / (2 * half_step)


def render_plate_scan(centres_plane_mm, *, tilt_rad=(0.0, 0.0), offset_mm=(0.0, 0.0, 0.0),
                      pixel_mm=0.1, row_pixel_mm=None, size_mm=(60.0, 60.0),
                      ring_radii_mm=(2.5, 2.7), line_width_mm=0.1, noise=0.0, speckle=0.0,
                      range_noise_mm=0.0, dropout_fraction=0.0, supersampling=6,
                      marks_darker=True, seed=0) -> tuple[np.ndarray, np.ndarray]:
    """Render an organized scan: xyz (H, W, 3) in mm and intensity (H, W).

    The scan covers ``size_mm`` (x, y) centred on the scanner origin with ``pixel_mm`` between points
    of a profile and ``row_pixel_mm`` (default: the same) between profiles. ``noise`` is additive
    Gaussian intensity noise (intensity units, background 180, marks 60), ``speckle`` the relative
    standard deviation of a multiplicative gamma speckle, ``range_noise_mm`` Gaussian noise on z,
    ``dropout_fraction`` the share of points lost (NaN in xyz and intensity).
    """
    rng = np.random.default_rng(seed)
    row_pixel_mm = pixel_mm if row_pixel_mm is None else row_pixel_mm
    width = int(round(size_mm[0] / pixel_mm))
    height = int(round(size_mm[1] / row_pixel_mm))
    xs = (np.arange(width) - (width - 1) / 2) * pixel_mm
    ys = (np.arange(height) - (height - 1) / 2) * row_pixel_mm
    rotation, origin = plate_frame(tilt_rad, offset_mm)
    x_grid, y_grid = np.meshgrid(xs, ys)
    _, _, z = _scanner_to_plate_uv(x_grid, y_grid, rotation, origin)

    darkness = np.zeros((height, width))
    r_outer = max(ring_radii_mm) + line_width_mm + 2 * max(pixel_mm, row_pixel_mm)
    sub = (np.arange(supersampling) + 0.5) / supersampling - 0.5
    # 1-D coverage across the line for each sub-sample, with the sub-sample's mean extent as half step.
    half_step = 0.5 * np.hypot(pixel_mm, row_pixel_mm) / supersampling / np.sqrt(2)
    for centre in np.atleast_2d(np.asarray(centres_plane_mm, dtype=float)):
        centre_xyz = plate_to_scanner(centre[None], tilt_rad, offset_mm)[0]
        # Windows are generous (plate tilt is small) and rendered only around each fiducial.
        cols = np.nonzero(np.abs(xs - centre_xyz[0]) <= 1.1 * r_outer)[0]
        rows = np.nonzero(np.abs(ys - centre_xyz[1]) <= 1.1 * r_outer)[0]
        if cols.size == 0 or rows.size == 0:
            continue
        sx = xs[cols][None, :, None, None] + sub[None, None, None, :] * pixel_mm
        sy = ys[rows][:, None, None, None] + sub[None, None, :, None] * row_pixel_mm
        u, v, _ = _scanner_to_plate_uv(sx, sy, rotation, origin)
        radius = np.hypot(u - centre[0], v - centre[1])
        cover = sum(_band_coverage(radius - r, line_width_mm / 2, half_step) for r in ring_radii_mm)
        darkness[np.ix_(rows, cols)] += cover.mean(axis=(2, 3))
    darkness = np.clip(darkness, 0.0, 1.0)

    contrast = (MARK - BACKGROUND) if marks_darker else (BACKGROUND - MARK) / 2
    intensity = BACKGROUND + contrast * darkness
    if speckle > 0:
        intensity = intensity * rng.gamma(1 / speckle**2, speckle**2, intensity.shape)
    if noise > 0:
        intensity = intensity + rng.normal(0.0, noise, intensity.shape)
    if range_noise_mm > 0:
        z = z + rng.normal(0.0, range_noise_mm, z.shape)
    xyz = np.stack([x_grid, y_grid, z], axis=-1)
    if dropout_fraction > 0:
        lost = rng.random((height, width)) < dropout_fraction
        xyz[lost] = np.nan
        intensity[lost] = np.nan
    return xyz, intensity
