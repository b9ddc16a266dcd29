"""The plate as an image (step 1 of :mod:`gls_calibration.fiducials.measure`).

The plate as an image: an organized cloud as it is, an unorganized one rasterised on the plate plane
(step 1 of :mod:`gls_calibration.fiducials.measure`).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree

from gls_calibration.fiducials.targets import RING_RADII_MM
from gls_calibration.fiducials.sector_jackknife import well_conditioned
from gls_calibration.scan.plate_pose import PlatePose


HIGH_PASS_SIGMA_PX = 1.5
"""Gaussian (pixels) subtracted from the log image: ring lines are about one pixel wide, speckle grains
of laser-marked steel 1-2 pixels correlated; this kept the most line signal over speckle in the
vision benchmark (1.5 / 2 / 3 px compared)."""

LINE_HALF_WIDTH_MM = 0.05
"""Half the width of a marked ring line (the paper's 0.1 mm lines): how far a line's own darkness
reaches beyond its radius."""

NO_LATTICE_PIXEL_MM = 2 * LINE_HALF_WIDTH_MM / HIGH_PASS_SIGMA_PX
"""Raster pixel (mm, 0.067) of a cloud without a lattice whose points are coarser: the finest at which
the high pass's blur (``HIGH_PASS_SIGMA_PX``) still spans a line's width. Measured on the independent
renderer's 19x19 plates (issue 31, jittered scan lines): 0.05 mm lost 19 of 361 fiducials under 0.3
speckle (the blur subtracts the line's own darkness), 0.1 mm at 0.15 mm point pitch 13 (holes between
points, 6-8 um RMS); 0.067 mm found all 361 in each of the issue's conditions, 0.5-4.9 um RMS per axis
(docs/fiducial-measurement.md, *Plates from two renderers*)."""

MIN_NORMAL_Z_FOR_CLOUD_RASTER = 0.7
"""A cloud without a lattice is rasterised in its own x-y (``rasterised_image``) when the plate's
normal is within about 45 deg of the cloud's z; steeper, on the plate's plane."""

LATTICE_TILE_PX = 125.0
"""Tile size (pixels) in the search for an unorganized cloud's scan lattice (``_scan_lattice``): tile
centres this far apart tell phase gradients apart up to 1 / 125 = 0.008 px per px, more than the
search's range of +-0.003, so no gradient is taken for another."""

PHASE_TILE_PX = 32
"""Tile size (pixels) over which a lattice cloud's local phase against the raster is averaged
(``_local_phase``): about a thousand points, a phase to a few thousandths of a pixel."""

SEAM_FREE_PHASE_PX = 0.25
"""A lattice cloud whose tiles all lie within this phase (px) of the raster is rounded as it is: a
point then moves to another pixel only if the scan's own jitter exceeds a quarter pixel."""

PHASE_MIN_TILE_POINTS = 16
"""A tile whose sampled points are fewer gives no phase of its own (``_local_phase``)."""

PHASE_MIN_COHERENCE = 0.5
"""A tile whose phasors' mean length is below this has no clear phase (the lattice test's
concentration, ``_scan_lattice``)."""

PHASE_SAMPLE_STRIDE = 4
"""Every this-many-th point of a lattice cloud gives the tiles' phases (``_local_phase``): a quarter of
a tile's thousand points still holds its phase to about 0.01 px; the trigonometry of every point
was most of the raster's time."""

LATTICE_SAMPLE_POINTS = 50_000
"""Points of an unorganized cloud (a regular stride through it) that the lattice search and the
raster's orientation are taken from: about 200 per tile are plenty for a phase."""

SPACING_PATCH_POINTS = 120
"""Side (in points) of the patch of an unorganized cloud whose neighbour distances give its point
spacing (``_point_spacing``): about 14 000 points, whose median distances hold to 0.1 %."""

SPACING_CONE_RATIO = 2.0
"""A neighbour counts as one along a raster axis when its offset along that axis is at least this
many times its offset across it (within about 27 deg of the axis)."""

MAX_PIXEL_RADIUS_FRACTION = 0.2
"""A pixel taken from the cloud's own point spacing must be below this share of the smallest ring
radius (0.5 mm for 2.5 mm rings, a raster too coarse to see the rings): beyond, the spacing is
taken for a units mistake and refused."""

FINITE_BLOCK_POINTS = 32_768
"""Points whose finiteness is checked at a time (``_finite_points``): their coordinates, 0.8 MB,
stay in the cache for the check of each axis."""

FILL_BOX_SIZES = (3, 5, 9, 17, 33)
"""Box sizes (pixels) tried in turn to fill a missing pixel from its valid neighbours; beyond the last,
the image's median."""


class PointsByPixel:
    """A lattice cloud's points looked up by pixel: ``[rows, cols]`` gives their xyz (NaN where none).

    What an organized cloud's (H, W, 3) array gives, without building it: only the pixels that the
    local affines read are looked up.
    """

    def __init__(self, points: np.ndarray, point_of_pixel: np.ndarray) -> None:
        self.points = points                    # (N, 3)
        self.point_of_pixel = point_of_pixel    # (H, W) int, -1 where no point
        self.shape = point_of_pixel.shape + (3,)

    def __getitem__(self, index) -> np.ndarray:
        """Return the points (..., 3) at ``index`` into the pixels (NaN where a pixel has none)."""
        which = self.point_of_pixel[index]
        found = self.points[np.maximum(which, 0)]
        found[which < 0] = np.nan
        return found

    def dense(self) -> np.ndarray:
        """Return every pixel's point, (H, W, 3)."""
        return self[...]


@dataclass(frozen=True)
class _PlateImage:
    """Intensity image with a per-pixel plane position.

    The organized cloud's point (through the plate pose) or uv = raster_origin + raster_matrix @
    (col, row).
    """

    intensity: np.ndarray          # (H, W) float32, marks dark, no NaN
    cloud_xyz: np.ndarray | PointsByPixel | None   # (H, W, 3) the cloud's point per pixel, NaN allowed
    raster_origin: np.ndarray | None  # (2,) plane coordinates of pixel (0, 0) (rasterised clouds)
    pitch: tuple[float, float]     # (row, column) pixel pitch in mm
    raster_matrix: np.ndarray | None = None   # (2, 2) uv = raster_origin + raster_matrix @ (col, row)
    pose: PlatePose | None = None  # plane coordinates of ``cloud_xyz``


def _fill_missing(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill invalid pixels with the mean of the valid ones in the smallest box holding any.

    The boxes are ``FILL_BOX_SIZES`` around each pixel (borders reflected as
    ``cv2.BORDER_REFLECT``); beyond the largest, the median of the valid pixels fills in.
    """
    if valid.all():
        return image
    filled = image.astype(np.float32)
    values = np.where(valid, filled, np.float32(0.0))
    reach = FILL_BOX_SIZES[-1] // 2
    rows, cols = np.nonzero(~valid)
    # The chessboard distance to the nearest valid pixel names the box each missing pixel needs
    # (a copy reflected beyond the border is never nearer than the pixel it copies), so every
    # missing pixel is read once, and those beyond the largest box not at all.
    needed = cv2.distanceTransform((~valid).astype(np.uint8), cv2.DIST_C, 3)[rows, cols]
    row_of = np.pad(np.arange(valid.shape[0]), reach, mode="symmetric")     # reflected row per padded row
    col_of = np.pad(np.arange(valid.shape[1]), reach, mode="symmetric")
    tables = None
    smaller = 0
    for size in FILL_BOX_SIZES:
        half = size // 2
        members = (needed > smaller) & (needed <= half)
        smaller = half
        box_rows, box_cols = rows[members], cols[members]
        if len(box_rows) == 0:
            continue
        if len(box_rows) * size * size <= valid.size:
            # Few pixels for this size: read their boxes (cheaper than any pass over the image).
            offsets = np.arange(-half, half + 1)
            rows_in_box = row_of[box_rows[:, None] + reach + offsets][:, :, None]
            cols_in_box = col_of[box_cols[:, None] + reach + offsets][:, None, :]
            counts = np.count_nonzero(valid[rows_in_box, cols_in_box], axis=(1, 2))
            sums = values[rows_in_box, cols_in_box].sum(axis=(1, 2), dtype=np.float64)
        else:
            # Many: box sums from summed-area tables of the reflected image, built once.
            if tables is None:
                tables = [cv2.integral(cv2.copyMakeBorder(table, reach, reach, reach, reach, cv2.BORDER_REFLECT),
                                       sdepth=depth)
                          for table, depth in ((values, cv2.CV_64F), (valid.astype(np.uint8), cv2.CV_32S))]
            low_r, high_r = box_rows + reach - half, box_rows + reach + half + 1
            low_c, high_c = box_cols + reach - half, box_cols + reach + half + 1
            sums, counts = (table[high_r, high_c] - table[low_r, high_c] - table[high_r, low_c]
                            + table[low_r, low_c] for table in tables)
        filled[box_rows, box_cols] = sums / counts
    far = needed > reach
    if far.any():
        filled[rows[far], cols[far]] = np.median(image[valid])
    return filled


def _finite_points(xyz: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    """Mask (intensity's shape) of the points whose coordinates (xyz (..., 3)) and intensity are finite."""
    # Column by column (a third of the time of isfinite(xyz).all(axis=-1)), in blocks of
    # ``FINITE_BLOCK_POINTS`` points: the three strided passes over a block read it from the cache,
    # not the whole cloud from memory three times (half the time on a 2060x2060 scan).
    finite, points = np.isfinite(intensity).reshape(-1), xyz.reshape(-1, 3)
    for start in range(0, len(finite), FINITE_BLOCK_POINTS):
        block = slice(start, start + FINITE_BLOCK_POINTS)
        for axis in range(3):
            finite[block] &= np.isfinite(points[block, axis])
    return finite.reshape(intensity.shape)


def _median_spacing(lines_uv: np.ndarray, axis: int) -> float:
    """Return the median distance (mm) between neighbouring pixels' plane positions along ``axis``.

    Median distance (mm) between neighbouring pixels' plane positions ``lines_uv`` (..., 2) along
    image axis ``axis``.
    """
    with np.errstate(invalid="ignore", over="ignore"):     # missing or absurd points drop out below
        steps = np.diff(lines_uv, axis=axis)
        lengths = np.hypot(steps[..., 0], steps[..., 1]).ravel()
    lengths = lengths[np.isfinite(lengths)]
    if lengths.size == 0:
        raise ValueError("organized cloud has no two neighbouring finite points")
    return float(np.median(lengths, overwrite_input=True))     # partitioned in place: our own copy


def organized_image(xyz: np.ndarray, intensity: np.ndarray, pose: PlatePose) -> _PlateImage:
    """Image of an organized cloud: one pixel per point."""
    valid = _finite_points(xyz, intensity)
    if np.count_nonzero(valid) == 0:
        raise ValueError("intensity image has no finite pixels")
    # Every 8th line across each axis is plenty for a median: the plane coordinates of the whole
    # cloud are never needed (the local affines take those of their windows).
    pitch = (_median_spacing(pose.to_plane(xyz[:, ::8]), 0), _median_spacing(pose.to_plane(xyz[::8]), 1))
    return _PlateImage(_fill_missing(intensity, valid), xyz, None, pitch, pose=pose)


def _scan_lattice(uv: np.ndarray, pixel_size_mm: float) -> tuple[np.ndarray, np.ndarray, bool]:
    """Return the raster for an unorganized cloud: ``(to_pixel (2, 2), shift (2,), on_lattice)``.

    Raster for an unorganized cloud: ``(to_pixel (2, 2), shift (2,), on_lattice)`` with pixel
    (col, row) = to_pixel @ uv + shift, pixel centres on the points of a regular scan where it has
    them (``on_lattice`` True).

    Points midway between pixel centres are averaged 2x2 by the splatting, and a raster whose phase
    against the scan drifts across the plate (tilt shears the scan's grid on the plane) blurs and
    shifts the thin ring lines by different amounts in different places (measured: 2.4 um RMS where
    the phase is within 0.1 px, 5 um at 0.1-0.3 px). The scan's phase against the raster is modelled
    as linear in uv per axis (an affine lattice): a coarse search of its gradient over tiles of
    ``LATTICE_TILE_PX``, then a least-squares refinement. A cloud without a lattice (phase concentration
    below 0.5) keeps the plain raster at ``pixel_size_mm``.
    """
    step = max(1, len(uv) // LATTICE_SAMPLE_POINTS)
    sample = uv[::step] / pixel_size_mm                                          # pixel units
    low, span = sample.min(axis=0), np.maximum(np.ptp(sample, axis=0), 1e-9)
    tiles = int(np.clip(np.ceil(span.max() / LATTICE_TILE_PX), 4, 64))          # per side
    cell = np.minimum(((sample - low) / span * tiles).astype(int), tiles - 1)
    tile = cell[:, 0] * tiles + cell[:, 1]
    counts = np.bincount(tile, minlength=tiles**2)
    filled = counts > 0
    centres = np.stack([np.bincount(tile, weights=sample[:, k], minlength=tiles**2)
                        for k in range(2)], -1)[filled] / counts[filled, None]
    middle = centres.mean(axis=0)
    centres = centres - middle
    # Phase drift per pixel: up to 6 px over 2000 px, in steps that turn the plate's ends by 0.2 px.
    gradients = np.arange(-30, 31) * 1e-4
    to_pixel, shift = np.eye(2), np.zeros(2)
    for axis in range(2):
        phasor = np.exp(2j * np.pi * sample[:, axis])
        tile_sums = (np.bincount(tile, weights=phasor.real, minlength=tiles**2)
                     + 1j * np.bincount(tile, weights=phasor.imag, minlength=tiles**2))[filled]
        # Coarse: the gradient (px of phase per px) that best lines the tiles' phasors up.
        # score[a, b] = |sum_t tile_sums_t exp(-2 pi i (g_a u_t + g_b v_t))|: one matrix product.
        along_u = np.exp(-2j * np.pi * np.outer(gradients, centres[:, 0]))
        along_v = np.exp(-2j * np.pi * np.outer(gradients, centres[:, 1]))
        score = np.abs((along_u * tile_sums) @ along_v.T)
        best = np.unravel_index(np.argmax(score), score.shape)
        gradient = np.array([gradients[best[0]], gradients[best[1]]])
        # Fine: least squares on the tiles' residual phases, weighted by their phasor sums' length.
        aligned = tile_sums * np.exp(-2j * np.pi * centres @ gradient)
        residual = np.angle(aligned * np.exp(-1j * np.angle(aligned.sum()))) / (2 * np.pi)   # about 0: no wrap
        design = np.column_stack([np.ones(len(centres)), centres])
        weight = np.abs(tile_sums)
        fit = np.linalg.lstsq(design * weight[:, None], residual * weight, rcond=None)[0]
        gradient = gradient + fit[1:]
        mean_phasor = np.exp(2j * np.pi * (sample[:, axis] - (sample - middle) @ gradient)).mean()
        if abs(mean_phasor) < 0.5:
            return np.eye(2) / pixel_size_mm, np.zeros(2), False
        to_pixel[axis] -= gradient
        shift[axis] = middle @ gradient - np.angle(mean_phasor) / (2 * np.pi)
    return to_pixel / pixel_size_mm, shift, True


def _local_phase(column: np.ndarray, row: np.ndarray) -> list[np.ndarray | None]:
    """Return each point's phase (px) against the raster per axis, or None where rounding needs none.

    The phase of the points' columns (rows) against the nearest integer, averaged as phasors over
    tiles of ``PHASE_TILE_PX`` (from every ``PHASE_SAMPLE_STRIDE``-th point) and unwrapped across the
    tiles, so that a drift of whole pixels stays continuous. Subtracted before rounding, each point's
    tile's phase keeps each scan line on one raster line where the lattice is regular only locally
    (neighbouring tiles differ by hundredths of a pixel, far from the half pixel at which a point would
    change its pixel). A tile with few points or no clear phase (the plate's edge, a hole, noise) takes
    its nearest clear tile's, so that it cannot unwrap its row by a whole pixel. Where every tile lies
    within ``SEAM_FREE_PHASE_PX`` of the raster (an affine lattice followed the scan), plain rounding is
    already seam-free: None, and no work per point.
    """
    first_column, first_row = np.floor(column.min() / PHASE_TILE_PX), np.floor(row.min() / PHASE_TILE_PX)
    sample = slice(None, None, PHASE_SAMPLE_STRIDE)

    def tiles_of(select) -> tuple[np.ndarray, np.ndarray]:
        tile_column = (column[select] // PHASE_TILE_PX - first_column).astype(np.int64)
        tile_row = (row[select] // PHASE_TILE_PX - first_row).astype(np.int64)
        return tile_row, tile_column

    sampled_row, sampled_column = tiles_of(sample)
    shape = (int(row.max() // PHASE_TILE_PX - first_row) + 1, int(column.max() // PHASE_TILE_PX - first_column) + 1)
    sampled_tile = sampled_row * shape[1] + sampled_column
    counts = np.bincount(sampled_tile, minlength=shape[0] * shape[1]).reshape(shape)
    phases, tile = [], None
    for coordinate in (column, row):
        angle = 2 * np.pi * coordinate[sample]
        phasor = (np.bincount(sampled_tile, weights=np.cos(angle), minlength=counts.size)
                  + 1j * np.bincount(sampled_tile, weights=np.sin(angle), minlength=counts.size)).reshape(shape)
        clear = (counts >= PHASE_MIN_TILE_POINTS) & (np.abs(phasor) >= PHASE_MIN_COHERENCE * counts)
        if not clear.any():
            phases.append(None)
            continue
        nearest = tuple(distance_transform_edt(~clear, return_distances=False, return_indices=True))
        turns = np.angle(phasor[nearest])
        turns[:, 0] = np.unwrap(turns[:, 0])
        turns = np.unwrap(turns, axis=1) / (2 * np.pi)
        turns -= np.round(np.median(turns[clear]))
        if np.abs(turns).max() < SEAM_FREE_PHASE_PX:
            phases.append(None)
            continue
        if tile is None:
            tile_row, tile_column = tiles_of(slice(None))
            tile = tile_row * shape[1] + tile_column
        phases.append(turns.ravel()[tile])
    return phases


def _point_spacing(xyz: np.ndarray, keep: np.ndarray, pose: PlatePose, turn: np.ndarray,
                   footprint_mm2: float) -> tuple[float, float, float]:
    """Point spacing (mm) of an unorganized cloud on the plate: ``(along, across, per_point)``.

    ``along`` and ``across`` are the median distances from a point to its nearest neighbour in the
    positive direction of each raster axis (the plane turned by ``turn``), over a patch of about
    ``SPACING_PATCH_POINTS`` squared points at the middle of the cloud: a scan's step along its
    lines and between them, exactly, whatever the points' order in the cloud. ``per_point`` is the
    square root of the plate area per point (``footprint_mm2`` over the finite points), the spacing
    of points that lie on no lines.
    """
    finite = xyz[keep] if not keep.all() else xyz
    per_point = float(np.sqrt(footprint_mm2 / max(len(finite), 1)))
    step = max(1, len(finite) // LATTICE_SAMPLE_POINTS)
    middle = np.median(finite[::step], axis=0)
    # A square of the cloud's x-y about its middle: the plate's scale there, up to its tilt.
    half = SPACING_PATCH_POINTS / 2 * per_point / max(abs(float(pose.normal[2])), 0.1)
    # The band in x first, then y among its points only: half the passes over the whole cloud.
    near = np.flatnonzero(np.abs(finite[:, 0] - middle[0]) < half)
    near = near[np.abs(finite[near, 1] - middle[1]) < half]
    patch = pose.to_plane(finite[near]) @ turn.T
    if len(patch) < 16:
        return per_point, per_point, per_point
    _, neighbour = cKDTree(patch).query(patch, k=9)
    offsets = patch[neighbour[:, 1:]] - patch[:, None, :]
    spacing = []
    for axis in range(2):
        along, across = offsets[..., axis], np.abs(offsets[..., 1 - axis])
        nearest = np.where((along > 0) & (along >= SPACING_CONE_RATIO * across), along, np.inf).min(axis=1)
        nearest = nearest[np.isfinite(nearest)]
        spacing.append(float(np.median(nearest)) if len(nearest) else per_point)
    return spacing[0], spacing[1], per_point


def _edge_turn(points: np.ndarray) -> np.ndarray:
    """Return the rotation (2, 2) aligning the minimum-area rectangle of ``points`` with the axes.

    Rotation (2, 2) that turns 2-D ``points`` (N, 2) so that the edges of their minimum-area
    rectangle lie along the axes (by at most 45 deg).
    """
    with np.errstate(over="ignore", invalid="ignore"):     # absurd coordinates fail the size check later
        edge_deg = cv2.minAreaRect(points.astype(np.float32))[2]
    turn_rad = np.deg2rad((edge_deg + 45.0) % 90.0 - 45.0)
    return np.array([[np.cos(turn_rad), np.sin(turn_rad)], [-np.sin(turn_rad), np.cos(turn_rad)]])   # by -turn


def rasterised_image(xyz: np.ndarray, intensity: np.ndarray, pose: PlatePose,
                     pixel_size_mm: float | None, smallest_radius_mm: float = RING_RADII_MM[0]) -> _PlateImage:
    """Image of an unorganized cloud: mean intensity of the points falling in each plane pixel.

    ``pixel_size_mm`` None takes the pixel from the cloud's own point spacing (``_point_spacing``):
    the larger of its steps along and across the scan lines, so that every pixel holds a point,
    where the raster follows a regular scan; otherwise the larger side of the plate area per point
    split in the same ratio (points off any lattice, ``_scan_lattice``). ValueError when that pixel
    is at least ``MAX_PIXEL_RADIUS_FRACTION`` of ``smallest_radius_mm`` (a cloud in other units).
    """
    keep = _finite_points(xyz, intensity)
    if not keep.any():
        raise ValueError("cloud has no finite point with a finite intensity")
    step = max(1, len(xyz) // LATTICE_SAMPLE_POINTS)
    sample = xyz[::step][keep[::step]]
    sample = sample if len(sample) else xyz[keep]
    sample_uv = pose.to_plane(sample)
    # Raster axes along the edges of the cloud's minimum-area rectangle: a cloud turned in its plane
    # (into a robot's frame, say) keeps a tight image, and a regular scan's lines come out along the
    # raster, where _scan_lattice can follow them.
    turn = _edge_turn(sample_uv)
    if pixel_size_mm is None:
        with np.errstate(over="ignore", invalid="ignore"):      # absurd coordinates: refused below
            footprint_mm2 = float(np.prod(cv2.minAreaRect(sample_uv.astype(np.float32))[1]))
        along, across, per_point = _point_spacing(xyz, keep, pose, turn, footprint_mm2)
        pixel_size_mm = max(along, across)
        if not (np.isfinite(pixel_size_mm) and 0 < pixel_size_mm < MAX_PIXEL_RADIUS_FRACTION * smallest_radius_mm):
            raise ValueError(f"the cloud's point spacing ({pixel_size_mm:.3g} mm) is not between 0 and "
                             f"{MAX_PIXEL_RADIUS_FRACTION * smallest_radius_mm:.3g} mm for rings of "
                             f"{smallest_radius_mm:g} mm; check the cloud's units (mm) or give pixel_size_mm")
        to_pixel, shift, on_lattice = _scan_lattice(sample_uv @ turn.T, pixel_size_mm)
        if not on_lattice:
            # No lattice: the points sample the lines at random phases and splatting blurs them by
            # about a pixel, so the raster is finer than a coarse scan (most of its pixels then hold
            # no point and are filled from their neighbours), down to NO_LATTICE_PIXEL_MM. Finer
            # clouds keep their own spacing, from the area per point (a step to the nearest
            # neighbour is short where points lie at random).
            spacing_mm = per_point * float(np.sqrt(max(along, across) / min(along, across)))
            pixel_size_mm = min(spacing_mm, NO_LATTICE_PIXEL_MM)
            to_pixel = np.eye(2) / pixel_size_mm
    else:
        to_pixel, shift, on_lattice = _scan_lattice(sample_uv @ turn.T, pixel_size_mm)
    to_pixel = to_pixel @ turn
    # Pixel coordinates straight from the cloud, column = xyz @ in_plane[:, 0] + offset[0] (gemv): the
    # plane coordinates of the whole cloud are never needed.
    in_plane = pose.rotation[:, :2] @ to_pixel.T            # (3, 2)
    in_cloud_xy = not on_lattice and abs(pose.normal[2]) >= MIN_NORMAL_Z_FOR_CLOUD_RASTER
    if in_cloud_xy:
        # No lattice to follow, but the points may still lie one per cell of the scanner's grid (a
        # jittered scan), which the cloud's x-y carries undistorted and the tilted plate foreshortens
        # (~100 ppm at 1.3 deg). Splatting's error depends on the raster's phase against those cells:
        # on the plate's plane that phase drifts slowly across the plate and stretches it (measured:
        # 41 ppm, 4 um at its edge); on the cloud's x-y it stays put. So the raster lies in x-y, along
        # the edges of the cloud's footprint there, and maps to the plate through the plane (affine).
        to_pixel_xy = _edge_turn(sample[:, :2]) / pixel_size_mm
        in_plane = np.vstack([to_pixel_xy.T, np.zeros((1, 2))])            # pixel = to_pixel_xy @ (x, y)
        to_pixel = to_pixel_xy @ pose.rotation[:2, :2]     # points on the plane: (x, y) = centre + R uv
        shift = np.zeros(2)
    offset = shift - pose.centre @ in_plane
    column = xyz @ np.ascontiguousarray(in_plane[:, 0])
    row = xyz @ np.ascontiguousarray(in_plane[:, 1])
    values = intensity
    if not keep.all():      # no copy of a whole cloud for nothing
        column, row, values = column[keep], row[keep], intensity[keep]
    # Move by whole pixels only (the lattice's phase stays), one pixel of margin.
    offset = offset + 1.0 - np.floor([column.min() + offset[0], row.min() + offset[1]])
    column += offset[0]
    row += offset[1]
    # The image's size before any cast to integers (a cloud in metres or absurd coordinates would wrap).
    width, height = float(column.max()) + 2.0, float(row.max()) + 2.0
    if not (width * height <= 10_000 * 10_000):         # also NaN
        raise ValueError(f"rasterised plate image would have {height:.3g}x{width:.3g} pixels; "
                         f"check pixel_size_mm ({pixel_size_mm}) and the cloud's units (mm)")
    if on_lattice:
        # Each point is one pixel's sample, at its centre up to the scan's jitter: nearest-pixel binning
        # takes it as it is (two bincounts where splatting takes eight), against the lattice's local
        # phase (an affine lattice drifts a pixel across a plate whose scan is not quite regular, which
        # would give every raster line a seam where its points jump to the next scan line).
        corner_column, corner_row = (np.rint(coordinate if phase is None else coordinate - phase).astype(np.int64)
                                     for coordinate, phase in zip((column, row), _local_phase(column, row)))
        corner_column -= corner_column.min() - 1
        corner_row -= corner_row.min() - 1
    else:
        corner_column, corner_row = column.astype(np.int64), row.astype(np.int64)    # >= 1: the floor
        fraction_column, fraction_row = column - corner_column, row - corner_row
    width, height = int(corner_column.max()) + 2, int(corner_row.max()) + 2
    base = corner_row
    base *= width
    base += corner_column                   # in place: every fresh array of a whole cloud costs
    if on_lattice:
        sums = np.bincount(base, weights=values, minlength=width * height)
        weights = np.bincount(base, minlength=width * height)
    else:
        # Bilinear splatting: every point spreads over its four nearest pixels. Off a lattice, nearest-
        # pixel binning would shift whole regions by up to half a pixel where the scan and raster are
        # out of phase; splatting keeps the marks' sub-pixel position.
        rest_column, rest_row = 1.0 - fraction_column, 1.0 - fraction_row
        size = width * height
        weight = np.empty(len(base))
        for step, column_weight, row_weight in ((0, rest_column, rest_row), (1, fraction_column, rest_row),
                                                (width, rest_column, fraction_row),
                                                (width + 1, fraction_column, fraction_row)):
            # Binned at the corner pixel, then moved by ``step``: no index array per neighbour. The
            # corner's own bins start the sums (as added to zeros, without the pass over them).
            np.multiply(column_weight, row_weight, out=weight)
            if step == 0:
                weights = np.bincount(base, weights=weight, minlength=size)
            else:
                weights[step:] += np.bincount(base, weights=weight, minlength=size)[:size - step]
            weight *= values
            if step == 0:
                sums = np.bincount(base, weights=weight, minlength=size)
            else:
                sums[step:] += np.bincount(base, weights=weight, minlength=size)[:size - step]
    covered = weights > 1e-3
    mean = np.divide(sums, weights, out=sums, where=covered).reshape(height, width)   # 0 where not covered
    if on_lattice:
        # Binning put each point on its lattice pixel, not where its coordinates say: a smooth
        # displacement below half a pixel (a robot's uneven travel in a flattened sweep) would vanish
        # (measured: 0.03 mm lost to 0.01 mm RMS). Each pixel keeps its point's coordinates, and the
        # image is measured as the organized cloud it is (local affines through the real points).
        # A pixel that two points share (rare: the local phase keeps scan lines apart) takes the last
        # one's coordinates; its intensity is their mean.
        point_of_pixel = np.full(height * width, -1, dtype=np.int64)
        point_of_pixel[base] = np.arange(len(base))
        points = xyz if keep.all() else xyz[keep]
        image = _fill_missing(mean, covered.reshape(height, width))
        return _PlateImage(image, PointsByPixel(points, point_of_pixel.reshape(height, width)), None,
                           (pixel_size_mm, pixel_size_mm), pose=pose)
    image = _fill_missing(mean, covered.reshape(height, width))
    to_plane = np.linalg.inv(to_pixel)
    shift = offset + pose.centre @ in_plane         # pixel = to_pixel @ uv + shift
    # (row, column) pitch on the plate: the nominal one, or through the plane for a raster in x-y.
    pitch = ((float(np.linalg.norm(to_plane[:, 1])), float(np.linalg.norm(to_plane[:, 0]))) if in_cloud_xy
             else (pixel_size_mm, pixel_size_mm))
    return _PlateImage(image, None, -to_plane @ shift, pitch, to_plane)


def local_affines(plate: _PlateImage, centres_px: np.ndarray, half_px: int):
    """Per candidate: plane offset (M, 2) and 2x2 Jacobian (M, 2, 2) with uv = offset + J @ (col, row)."""
    count = len(centres_px)
    if plate.cloud_xyz is None:
        jacobian = np.broadcast_to(plate.raster_matrix, (count, 2, 2)).copy()
        return np.broadcast_to(plate.raster_origin, (count, 2)).copy(), jacobian, np.ones(count, bool)
    # Least-squares affine fit of the cloud's plane coordinates over a window around each candidate:
    # smoother than interpolating four noisy neighbours, and it carries tilt and pitch.
    height, width = plate.intensity.shape
    # Every third pixel of the window: plenty for six affine parameters, nine times cheaper.
    offsets_1d = np.arange(-half_px, half_px + 1, 3)
    base = np.rint(centres_px).astype(np.int64)
    cols = base[:, 0, None, None] + offsets_1d[None, None, :]
    rows = base[:, 1, None, None] + offsets_1d[None, :, None]
    cols, rows = np.broadcast_arrays(cols, rows)
    inside = (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
    uv = plate.pose.to_plane(plate.cloud_xyz[np.clip(rows, 0, height - 1), np.clip(cols, 0, width - 1)])
    weight = (inside & np.isfinite(uv).all(axis=-1)).astype(float)
    uv = np.where(weight[..., None] > 0, uv, 0.0)
    # Design matrix relative to the candidate pixel for conditioning.
    design = np.stack([np.ones_like(cols, dtype=float), (cols - base[:, 0, None, None]).astype(float),
                       (rows - base[:, 1, None, None]).astype(float)], axis=-1).reshape(count, -1, 3)
    weight = weight.reshape(count, -1)
    uv = uv.reshape(count, -1, 2)
    weighted = design * weight[..., None]
    normal_matrix = np.matmul(weighted.transpose(0, 2, 1), design)
    right = np.matmul(weighted.transpose(0, 2, 1), uv)
    # Enough pixels, and not all on one line (a window missing all but a row of its points).
    usable = (weight.sum(axis=1) >= 10) & well_conditioned(normal_matrix, 1e10)
    normal_matrix[~usable] = np.eye(3)
    solution = np.linalg.solve(normal_matrix, right)            # (M, 3, 2)
    jacobian = np.ascontiguousarray(np.transpose(solution[:, 1:, :], (0, 2, 1)))   # (M, 2 [u,v], 2 [col,row])
    offset = solution[:, 0, :] - np.einsum("mij,mj->mi", jacobian, base.astype(float))
    usable &= np.isfinite(offset).all(axis=1) & np.isfinite(jacobian).all(axis=(1, 2))
    usable[usable] &= np.linalg.cond(jacobian[usable]) < 1e6
    if not usable.all():
        # A window without a usable fit (points missing or absurd) borrows its nearest usable
        # neighbour's map, so that its candidate is still placed (and turned down as ``fit``).
        if usable.any():
            nearest = np.flatnonzero(usable)[cKDTree(centres_px[usable]).query(centres_px[~usable])[1]]
            offset[~usable], jacobian[~usable] = offset[nearest], jacobian[nearest]
        else:
            offset[~usable], jacobian[~usable] = 0.0, np.diag(plate.pitch[::-1])
    return offset, jacobian, usable
