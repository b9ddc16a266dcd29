"""Synthetic laser-line scans of a marked plate, for the vision tests and benchmarks.

The scanner frame has x along a profile (columns), y along the travel (rows) and z up towards the
scanner. The plate is a plane through ``offset_mm`` tilted by ``tilt_rad`` (about x, then y); marks
are double rings drawn in plate coordinates. Each pixel's intensity is the mean reflectance over its
footprint, computed by supersampling with an exact 1-D coverage of the ring line per sub-sample, so
ring centres are meaningful well below a pixel.

Real laser-marked stainless steel is harder than clean renders: ``speckle_corr_px`` makes the
speckle spatially correlated (log-normal, Gaussian correlation of that many pixels), ``mark_ratio``
sets how much the marks darken (or, above 1, brighten) the steel, ``scratches`` draws straight
lines of the same kind of reflectance change across the plate and ``erased`` removes an arc of
chosen fiducials' rings (a half-erased or partly worn mark).
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
                      marks_darker=True, seed=0, speckle_corr_px=0.0, mark_ratio=None,
                      scratches=(), erased=None, jitter_px=0.0) -> tuple[np.ndarray, np.ndarray]:
    """Render an organized scan: xyz (H, W, 3) in mm and intensity (H, W).

    The scan covers ``size_mm`` (x, y) centred on the scanner origin with ``pixel_mm`` between points
    of a profile and ``row_pixel_mm`` (default: the same) between profiles. ``noise`` is additive
    Gaussian intensity noise (intensity units, background 180, marks 60), ``speckle`` the relative
    standard deviation of a multiplicative gamma speckle, ``range_noise_mm`` Gaussian noise on z,
    ``dropout_fraction`` the share of points lost (NaN in xyz and intensity).
    ``speckle_corr_px`` > 0 makes the speckle correlated: a log-normal factor with relative standard
    deviation ``speckle`` from white noise smoothed by a Gaussian of that sigma (pixels).
    ``mark_ratio`` (e.g. 0.85) is the reflectance of a fully marked pixel relative to the steel and
    overrides ``marks_darker``. ``scratches`` is a sequence of ((x0, y0), (x1, y1), width_mm, ratio)
    line segments in scanner x, y (mm). ``erased`` maps a fiducial index to (start, stop) plate
    angles (rad) over which its rings are missing. ``jitter_px`` > 0 moves every point by a uniform
    random offset of up to that many pixels in x and y before it is rendered (an irregular cloud;
    0.5 leaves no trace of the grid).
    """
    rng = np.random.default_rng(seed)
    row_pixel_mm = pixel_mm if row_pixel_mm is None else row_pixel_mm
    width = int(round(size_mm[0] / pixel_mm))
    height = int(round(size_mm[1] / row_pixel_mm))
    xs = (np.arange(width) - (width - 1) / 2) * pixel_mm
    ys = (np.arange(height) - (height - 1) / 2) * row_pixel_mm
    rotation, origin = plate_frame(tilt_rad, offset_mm)
    x_grid, y_grid = np.meshgrid(xs, ys)
    if jitter_px > 0:
        shake = np.random.default_rng(seed + 1).uniform(-jitter_px, jitter_px, (2, height, width))
        x_grid = x_grid + shake[0] * pixel_mm
        y_grid = y_grid + shake[1] * row_pixel_mm
    _, _, z = _scanner_to_plate_uv(x_grid, y_grid, rotation, origin)

    darkness = np.zeros((height, width))
    r_outer = max(ring_radii_mm) + line_width_mm + 2 * max(pixel_mm, row_pixel_mm)
    sub = (np.arange(supersampling) + 0.5) / supersampling - 0.5
    # 1-D coverage across the line for each sub-sample, with the sub-sample's mean extent as half step.
    half_step = 0.5 * np.hypot(pixel_mm, row_pixel_mm) / supersampling / np.sqrt(2)
    for index, centre in enumerate(np.atleast_2d(np.asarray(centres_plane_mm, dtype=float))):
        centre_xyz = plate_to_scanner(centre[None], tilt_rad, offset_mm)[0]
        # Windows are generous (plate tilt is small) and rendered only around each fiducial.
        cols = np.nonzero(np.abs(xs - centre_xyz[0]) <= 1.1 * r_outer)[0]
        rows = np.nonzero(np.abs(ys - centre_xyz[1]) <= 1.1 * r_outer)[0]
        if cols.size == 0 or rows.size == 0:
            continue
        sx = x_grid[np.ix_(rows, cols)][:, :, None, None] + sub[None, None, None, :] * pixel_mm
        sy = y_grid[np.ix_(rows, cols)][:, :, None, None] + sub[None, None, :, None] * row_pixel_mm
        u, v, _ = _scanner_to_plate_uv(sx, sy, rotation, origin)
        radius = np.hypot(u - centre[0], v - centre[1])
        cover = sum(_band_coverage(radius - r, line_width_mm / 2, half_step) for r in ring_radii_mm)
        gap = (erased or {}).get(index)
        if gap is not None:
            angle = np.mod(np.arctan2(v - centre[1], u - centre[0]) - gap[0], 2 * np.pi)
            cover = np.where(angle < np.mod(gap[1] - gap[0], 2 * np.pi), 0.0, cover)
        darkness[np.ix_(rows, cols)] += cover.mean(axis=(2, 3))
    darkness = np.clip(darkness, 0.0, 1.0)

    if mark_ratio is not None:
        contrast = BACKGROUND * (mark_ratio - 1.0)
    else:
        contrast = (MARK - BACKGROUND) if marks_darker else (BACKGROUND - MARK) / 2
    intensity = BACKGROUND + contrast * darkness
    for (x0, y0), (x1, y1), width, ratio in scratches:
        # Distance of every pixel centre to the segment, anti-aliased over one pixel.
        along = np.array([x1 - x0, y1 - y0], dtype=float)
        t = np.clip(((x_grid - x0) * along[0] + (y_grid - y0) * along[1]) / (along @ along), 0.0, 1.0)
        distance = np.hypot(x_grid - x0 - t * along[0], y_grid - y0 - t * along[1])
        cover = np.clip((width / 2 - distance) / pixel_mm + 0.5, 0.0, 1.0)
        intensity = intensity * (1.0 + (ratio - 1.0) * cover)
    if speckle > 0 and speckle_corr_px > 0:
        field = _smoothed_unit_noise(rng, intensity.shape, speckle_corr_px)
        spread = np.sqrt(np.log1p(speckle**2))
        intensity = intensity * np.exp(spread * field - spread**2 / 2)
    elif speckle > 0:
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


def _smoothed_unit_noise(rng, shape, sigma_px: float) -> np.ndarray:
    """White Gaussian noise smoothed by a Gaussian of ``sigma_px`` and scaled back to unit variance."""
    from scipy import ndimage

    field = ndimage.gaussian_filter(rng.standard_normal(shape), sigma_px, mode="wrap")
    return field / field.std()


# ------------------------------------------------------------------ conditions of a real marked plate
GRID_PITCH_MM = 190.0 / 18
"""Pitch of the 19x19 calibration grid (190 mm span)."""

BASE_SCAN = dict(noise=2.0, tilt_rad=(0.012, -0.02), offset_mm=(0.35, -0.25, 4.0))
"""What every condition shares: 1 % intensity noise, a plate tilted by about 1.3 deg, off centre."""


def _scratches(per_side: int) -> tuple:
    """Three dark, shallow scratches crossing rings of the grid (scanner x, y in mm)."""
    half = (per_side - 1) / 2 * GRID_PITCH_MM + 3.0
    return (((-half, -half + 2.4), (half, half - 1.1), 0.15, 0.55),
            ((-half, 2.6), (half, 2.9), 0.12, 0.6),
            ((-2.5, -half), (-2.7, half), 0.2, 1.4))


def vision_conditions(per_side: int) -> dict:
    """Named scan conditions of issue 11: render keyword arguments plus how the cloud is handed over.

    Each value has ``scan`` (``render_plate_scan`` keywords on top of ``BASE_SCAN``), ``rotation_deg``
    (in-plane rotation of the grid), ``organized``, ``cloud_turn_deg`` (the whole cloud turned about
    the scanner's z axis, as a cloud handed over in a robot's frame) and ``marks_darker`` (what a
    caller would pass: None lets the measurement find out).
    """
    def condition(rotation_deg=0.0, organized=True, cloud_turn_deg=0.0, **scan):
        return dict(scan=dict(BASE_SCAN, **scan), rotation_deg=rotation_deg, organized=organized,
                    cloud_turn_deg=cloud_turn_deg)

    return {
        "clean": condition(noise=0.0),
        "speckle_0.3": condition(speckle=0.3, speckle_corr_px=1.5),
        "speckle_0.3_corr2": condition(speckle=0.3, speckle_corr_px=2.0),
        "marks_85pct": condition(mark_ratio=0.85),
        "marks_85pct_speckle_0.1": condition(mark_ratio=0.85, speckle=0.1, speckle_corr_px=1.5),
        "marks_bright": condition(mark_ratio=1.3),
        "scratches": condition(scratches=_scratches(per_side)),
        "pitch_0.07": condition(pixel_mm=0.07),
        "pitch_0.15": condition(pixel_mm=0.15),
        "pitch_0.07x0.15": condition(pixel_mm=0.07, row_pixel_mm=0.15),
        "unorganized": condition(organized=False),
        "rotation_15deg": condition(rotation_deg=15.0),
        "rotation_-15deg": condition(rotation_deg=-15.0),
        "tilt_3deg": condition(tilt_rad=(0.04, -0.035), offset_mm=(0.35, -0.25, 4.0)),
        "dropouts_1pct": condition(dropout_fraction=0.01, range_noise_mm=0.01),
        "unorganized_speckle_dropouts": condition(organized=False, speckle=0.3, speckle_corr_px=1.5,
                                                  dropout_fraction=0.01),
        # Points anywhere in their cell: no grid left for the raster to follow (the plain raster).
        "unorganized_irregular": condition(organized=False, jitter_px=0.5),
        # The scan's lines no longer along the cloud's axes.
        "unorganized_turned_20deg": condition(organized=False, cloud_turn_deg=20.0),
    }


def grid_truth(per_side: int, rotation_deg: float = 0.0, seed: int = 0) -> np.ndarray:
    """Row-major grid of plate positions at ``GRID_PITCH_MM``, rotated in plane, with random offsets
    of up to half a 0.1 mm pixel (so centres do not sit on pixel centres)."""
    axis = (np.arange(per_side) - (per_side - 1) / 2) * GRID_PITCH_MM
    grid = np.array([(u, v) for v in axis for u in axis]).reshape(-1, 2)
    angle = np.deg2rad(rotation_deg)
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    return grid @ rotation.T + np.random.default_rng(seed).uniform(-0.05, 0.05, grid.shape)


def scan_size_mm(per_side: int, rotation_deg: float = 0.0) -> tuple[float, float]:
    """Scan extent covering a rotated grid with a margin of 5 mm beyond the rings."""
    half = (per_side - 1) / 2 * GRID_PITCH_MM
    extent = 2 * half * (abs(np.cos(np.deg2rad(rotation_deg))) + abs(np.sin(np.deg2rad(rotation_deg))))
    side = float(np.ceil(extent / 2 + 2.7 + 5.0) * 2)
    return side, side


def render_condition(name: str, per_side: int, seed: int = 0, supersampling: int = 4):
    """Render one named condition: (xyz, intensity, truth_xyz, condition dict); xyz/intensity are
    flattened and shuffled for unorganized conditions. ``truth_xyz`` are the true centres (scanner)."""
    condition = vision_conditions(per_side)[name]
    truth_uv = grid_truth(per_side, condition["rotation_deg"], seed)
    scan = dict(condition["scan"], size_mm=scan_size_mm(per_side, condition["rotation_deg"]),
                supersampling=supersampling, seed=seed)
    xyz, intensity = render_plate_scan(truth_uv, **scan)
    if not condition["organized"]:
        order = np.random.default_rng(seed + 100).permutation(intensity.size)
        xyz, intensity = xyz.reshape(-1, 3)[order], intensity.reshape(-1)[order]
    truth = plate_to_scanner(truth_uv, scan["tilt_rad"], scan["offset_mm"])
    if condition["cloud_turn_deg"]:
        turn = np.deg2rad(condition["cloud_turn_deg"])
        about_z = np.array([[np.cos(turn), -np.sin(turn), 0.0], [np.sin(turn), np.cos(turn), 0.0], [0.0, 0.0, 1.0]])
        xyz, truth = xyz @ about_z.T, truth @ about_z.T
    return xyz, intensity, truth, condition
