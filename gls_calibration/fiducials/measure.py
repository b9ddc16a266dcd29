"""Centres of the double-ring fiducials marked on the plate, measured in a laser-line scanner cloud.

What we know is used throughout: every fiducial is two concentric rings of known radii.

1. Image: an organized cloud (H, W, 3) maps straight to pixels (row = profile, column = point); an
   unorganized one is rasterised on the plate plane at ``pixel_size_mm`` (by default from the cloud's
   own point spacing, ``_point_spacing``: its step on a regular scan, else ``NO_LATTICE_PIXEL_MM``
   or finer), on a raster whose pixel
   centres follow the points of a regular scan (an affine lattice fitted to the points' phase;
   ``_scan_lattice``): there each point is one pixel's sample (nearest-pixel binning); a cloud
   without a lattice is splatted bilinearly (a weighted mean intensity per pixel) on a raster in the
   cloud's own x-y, mapped to the plate through the plane. Missing pixels are
   filled by normalised convolution. The
   polarity of the marks (darker or brighter than the steel) is given or found from the image.
2. Detection: normalised cross-correlation (``cv2.matchTemplate``) of the image with a template of
   the double ring drawn at the image's pixel pitch, local maxima above a threshold set by the
   spread of the correlation over bare steel. A ring is rotationally symmetric, so in-plane
   rotation does not matter; the template integrates the whole circumference, so speckle, faint
   marks and scratches that defeat edge detection (Canny + Hough) still leave a clear peak.
3. Sub-pixel centres: for each candidate the intensity is sampled along 256 rays laid out in plate
   millimetres (through a local pixel -> plane affine map fitted to the cloud, so tilted plates and
   unequal pixel pitches need no resampling). Each ray's profile is correlated with the radial
   profile of the double ring; the parabolic peak is an edge point. A ring model fitted to these
   radii (mean radius, centre offset and an elliptical second harmonic; least squares weighted by
   each ray's darkness contrast relative to the fiducial's other rays, ``_edge_weights``, one robust
   trimming round) moves the centre; the rays follow it (a coarse pass, then fine passes). The symmetric profile template makes each edge point unbiased by background
   level, linear shading and the rings' blur. These passes run on the high-passed log image; the
   last fit, which gives the centre, runs on the log image prewhitened by the noise spectrum of the
   plate's bare steel (``_prewhitening_kernel``), so that correlated speckle weighs less at the
   spatial frequencies where it is strong.
4. Quality per centre: the ring amplitude is measured on 24 angular sectors at the fitted circle;
   ``coverage`` is the share of sectors where the rings are seen, and rays of unseen sectors are
   left out of the final fit. The standard uncertainty per axis comes from the fit: the larger of a
   delete-one-sector jackknife of the edge points' ring fit (a fiducial's own local trouble) and a
   spectral estimate (edge noise correlated along the ring, whose power in the first harmonic, the
   centre, the residuals do not show; ``_spectral_covariance``), its variances raised towards the
   plate's typical one where they came out low by chance (``_moderated``), plus ``MODEL_SIGMA_MM``.
5. Status: candidates are rejected with a reason (``spurious``: coverage below ``SPURIOUS_COVERAGE``,
   no ring there; ``partial``: coverage below ``MIN_COVERAGE``;
   ``radius``: a ring's semi-axes (mean radius +- its second harmonic) off the nominal radius, which
   also turns down two rings close enough to merge into one detection; ``merged``: two fiducials
   closer still (about 0.1-0.3 mm), whose lines split along their offset and coincide across it
   (``merged_fiducials``); ``fit``: too few usable rays or an ill-posed fit;
   ``uncertain``: stated uncertainty above ``MAX_SIGMA_MM``; ``duplicate``: the same fiducial as a
   better candidate). Accepted centres are returned in plate coordinates and, via
   ``PlatePose.from_plane``, as 3-D points on the fitted plane.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import optimize, special
from scipy.spatial import cKDTree

from gls_calibration.common.robust import NORMAL_MAD_SCALE, robust_sigma
from gls_calibration.common.validation import as_finite_array
from gls_calibration.fiducials import merged_pairs as merged_fiducials
from gls_calibration.fiducials import sector_jackknife
from gls_calibration.fiducials.targets import RING_RADII_MM
from gls_calibration.scan.plate_pose import PlatePose

RAY_COUNT = 256
"""Rays per fiducial: about 1.5 rays per pixel of outer-ring circumference at 0.1 mm pixels."""

RADIAL_STEP_PX = 0.2
RADIUS_TOLERANCE_FRACTION = 0.12 / 2.7
"""Accepted error of a fitted ring's semi-axes, as a fraction of the fiducial's largest radius: an
uncalibrated head scales its marks by a few percent (gain and distortion), whatever their size."""
"""Sample spacing along a ray, in pixels."""

COARSE_MARGIN_PX = 4.0
"""How far (pixels) the first pass looks for the rings: the detection may be this far off."""

FINE_MARGIN_PX = 1.5
"""How far later passes look for the rings around the current circle."""

PASSES = 3
"""Coarse pass, fine pass on all rays, fine pass on the rays of sectors where the rings are seen."""

SECTORS = 24
"""Angular sectors for coverage (15 degrees each)."""

SECTOR_SEEN_FRACTION = 0.4
"""A sector sees the rings when its amplitude reaches this share of the fiducial's typical one."""

MIN_COVERAGE = 0.75
"""Accepted fiducials show their rings on at least this share of the circumference."""

SPURIOUS_COVERAGE = 0.3
"""Below this coverage a candidate is not a damaged ring but no ring at all (``spurious``)."""

MIN_VALID_RAY_FRACTION = 0.5
"""A fit needs this share of all rays usable."""

EDGE_WEIGHT_POWER = 2.0
"""A ray's weight in the ring fit grows as the square of its rings' contrast (``_edge_weights``): the
edge point's variance falls as the contrast's square, at equal noise."""

EDGE_WEIGHT_MAX = 2.0
"""Relative contrast beyond which a ray weighs no more: a speckle grain or a scratch that adds to a
ray's contrast does not take over the fit."""

MODEL_SIGMA_MM = 0.001
"""Uncertainty of the method itself, added in quadrature: its error on noise-free renders is a
fraction of this (interpolation and the template's line shape)."""

SPECTRUM_FIT_HARMONICS = (3, 12)
"""Harmonics of the ring's residuals (the fit leaves 3 and up) whose straight line gives the edge
noise's power at harmonics 0-2 (``_spectral_covariance``); 8 or 16 as the last changed the stated
uncertainties under speckle by about 3 %."""

SPECTRUM_SAMPLE_MIN_SHARE = 0.9
"""Candidates with at least this share of their rays used give the plate's spectrum shape (gaps blur
a periodogram)."""

MAX_SIGMA_MM = 0.010
"""Candidates whose stated uncertainty exceeds this (per axis) are rejected as ``uncertain``."""

MODERATION_MIN_REFERENCE = 10
"""Candidates a plate needs before their uncertainties are moderated towards its typical one."""

MERGED_FALSE_ALARM = 1e-5
"""Chance that one single fiducial is turned down as ``merged`` if the merged test's noise model
holds (``merged_fiducials.merged``): one good fiducial lost in about 280 plates of 361, while a
merged pair accepted puts a centre 50-100 um off. The null was measured (docs/fiducial-measurement.md, *Merged
detections*): no p below 7e-5 among 6 320 single fiducials of the benchmark's renders, none of
1 408 on the simulated cell turned down."""

MERGED_MIN_REFERENCE = 20
"""The merged test compares a candidate with the plate's other fiducials: it needs this many."""

DETECTION_SIGMAS = 4.0
"""Detection threshold on the correlation map, in robust standard deviations of bare steel."""

MIN_DETECTION_SCORE = 0.12
"""Lowest normalised correlation accepted as a candidate whatever the steel looks like."""

HIGH_PASS_SIGMA_PX = 1.5
"""Gaussian (pixels) subtracted from the log image: ring lines are about one pixel wide, speckle grains
of laser-marked steel 1-2 pixels correlated; this kept the most line signal over speckle in the
vision benchmark (1.5 / 2 / 3 px compared)."""

PREWHITENING_TILE_PX = 32
"""Side (pixels) of the bare-steel tiles whose averaged periodogram is the noise spectrum the centre
fit is prewhitened by (``_prewhitening_kernel``): 1/32 cycle per pixel resolves speckle correlated
over 1-2 pixels, and a 19x19 plate at 0.1 mm holds about 1 100 such tiles clear of its rings."""

PREWHITENING_KERNEL_PX = 11
"""Side (pixels) of the prewhitening filter (the spectrum's inverse square root, truncated): it
spans the speckle's correlation several times over and stays cheap (``cv2.filter2D``)."""

PREWHITENING_MIN_TILES = 16
"""Bare-steel tiles needed for a noise spectrum; with fewer the centre fit keeps the high-passed image."""

PREWHITENING_FLOOR = 1e-3
"""Floor added to the noise spectrum, as a share of its mean: no frequency is boosted by more than
about 1 / sqrt(floor), so spectral bins the periodogram put near zero by chance stay bounded."""

FIT_PASSES = 1
"""Passes of the centre fit on the prewhitened image, from the high-passed image's result: that
start is within about 20 um, where the ring model's first-order centre is exact to well below 1 nm
(a second pass changed the 19x19 speckle plate's RMS by 0.04 um)."""

RING_CLEARANCE_MM = 0.5
"""Margin beyond the outer ring that the noise spectrum's bare-steel tiles keep from every candidate."""

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
"""A cloud without a lattice is rasterised in its own x-y (``_rasterised_image``) when the plate's
normal is within about 45 deg of the cloud's z; steeper, on the plate's plane."""

LATTICE_TILE_PX = 125.0
"""Tile size (pixels) in the search for an unorganized cloud's scan lattice (``_scan_lattice``): tile
centres this far apart tell phase gradients apart up to 1 / 125 = 0.008 px per px, more than the
search's range of +-0.003, so no gradient is taken for another."""

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

FILL_BOX_SIZES = (3, 5, 9, 17, 33)
"""Box sizes (pixels) tried in turn to fill a missing pixel from its valid neighbours; beyond the last,
the image's median."""

STATUS_OK = "ok"


@dataclass(frozen=True)
class FiducialMeasurement:
    """Measured fiducial centres (mm) with their uncertainties, and the candidates turned down.

    ``centres`` (K, 3) lie on the fitted plate plane in the cloud's frame, ``centres_plane`` (K, 2)
    are the same points in plate coordinates (``PlatePose.to_plane``). ``quality`` (K,) is the RMS
    residual of the edge points about the fitted circle in mm, ``radii`` (K,) the fitted outer-ring
    radius and ``inner_radii`` (K,) the fitted inner-ring radius. ``sigma_xy_mm`` (K, 2) is the
    standard uncertainty (k = 1) of each centre along the cloud frame's x and y axes,
    ``sigma_plane_mm`` (K, 2) the same along the plate axes, ``coverage`` (K,) the share of the
    circumference where the rings were seen (0-1). ``merged`` counts duplicate candidates of an
    accepted fiducial (reason ``duplicate``; two fiducials merged into one detection are rejected
    with the reason ``merged`` instead), ``rejected`` all candidates turned down; those are listed in
    ``rejected_centres`` (J, 3) with ``rejected_reasons`` (J,), ``rejected_sigma_xy_mm`` (J, 2)
    and ``rejected_coverage`` (J,).
    ``missing`` (int) is ``max(0, expected_count - K)``, the expected fiducials not found; never negative.
    ``extra`` (int) is ``max(0, K - expected_count)``, the fiducials found beyond the expected count.
    Both are None when no count was expected; ``extra`` also when unknown (rebuilt from a message).
    ``image_shape`` is (rows, columns) of the analysed image and
    ``pixel_pitch_mm`` its (row, column) pitch. Arrays not given (a result rebuilt from a message)
    default to NaN of the right shape, the rejected list to empty.
    """

    centres: np.ndarray
    centres_plane: np.ndarray
    quality: np.ndarray
    radii: np.ndarray
    inner_radii: np.ndarray
    merged: int
    rejected: int
    missing: int | None
    image_shape: tuple[int, int]
    pixel_pitch_mm: tuple[float, float]
    sigma_xy_mm: np.ndarray | None = None
    sigma_plane_mm: np.ndarray | None = None
    coverage: np.ndarray | None = None
    rejected_centres: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    rejected_reasons: tuple[str, ...] = ()
    rejected_sigma_xy_mm: np.ndarray = field(default_factory=lambda: np.empty((0, 2)))
    rejected_coverage: np.ndarray = field(default_factory=lambda: np.empty(0))
    extra: int | None = None    # defaulted: the service response carries ``missing`` only

    def __post_init__(self) -> None:
        count = len(np.asarray(self.centres).reshape(-1, 3))
        for name, shape in (("sigma_xy_mm", (count, 2)), ("sigma_plane_mm", (count, 2)), ("coverage", (count,))):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(shape, np.nan))


@dataclass(frozen=True)
class _PlateImage:
    """Intensity image with a per-pixel plane position: the organized cloud's point (through the plate
    pose) or uv = raster_origin + raster_matrix @ (col, row)."""

    intensity: np.ndarray          # (H, W) float32, marks dark, no NaN
    cloud_xyz: np.ndarray | None   # (H, W, 3) the organized cloud's point per pixel, NaN allowed
    raster_origin: np.ndarray | None  # (2,) plane coordinates of pixel (0, 0) (rasterised clouds)
    pitch: tuple[float, float]     # (row, column) pixel pitch in mm
    raster_matrix: np.ndarray | None = None   # (2, 2) uv = raster_origin + raster_matrix @ (col, row)
    pose: PlatePose | None = None  # plane coordinates of ``cloud_xyz``


def _fill_missing(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill invalid pixels with the mean of the valid ones in the smallest box of ``FILL_BOX_SIZES``
    around them holding any (borders reflected as ``cv2.BORDER_REFLECT``); beyond the largest, the
    median of the valid pixels."""
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
    finite = np.isfinite(intensity)
    for axis in range(3):           # column by column: a third of the time of isfinite(xyz).all(axis=-1)
        finite &= np.isfinite(xyz[..., axis])
    return finite


def _median_spacing(lines_uv: np.ndarray, axis: int) -> float:
    """Median distance (mm) between neighbouring pixels' plane positions ``lines_uv`` (..., 2) along
    image axis ``axis``."""
    with np.errstate(invalid="ignore", over="ignore"):     # missing or absurd points drop out below
        steps = np.diff(lines_uv, axis=axis)
        lengths = np.hypot(steps[..., 0], steps[..., 1]).ravel()
    lengths = lengths[np.isfinite(lengths)]
    if lengths.size == 0:
        raise ValueError("organized cloud has no two neighbouring finite points")
    return float(np.median(lengths))


def _organized_image(xyz: np.ndarray, intensity: np.ndarray, pose: PlatePose) -> _PlateImage:
    """Image of an organized cloud: one pixel per point."""
    valid = _finite_points(xyz, intensity)
    if np.count_nonzero(valid) == 0:
        raise ValueError("intensity image has no finite pixels")
    # Every 8th line across each axis is plenty for a median: the plane coordinates of the whole
    # cloud are never needed (the local affines take those of their windows).
    pitch = (_median_spacing(pose.to_plane(xyz[:, ::8]), 0), _median_spacing(pose.to_plane(xyz[::8]), 1))
    return _PlateImage(_fill_missing(intensity, valid), xyz, None, pitch, pose=pose)


def _scan_lattice(uv: np.ndarray, pixel_size_mm: float) -> tuple[np.ndarray, np.ndarray, bool]:
    """Raster for an unorganized cloud: ``(to_pixel (2, 2), shift (2,), on_lattice)`` with pixel
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
    near = (np.abs(finite[:, 0] - middle[0]) < half) & (np.abs(finite[:, 1] - middle[1]) < half)
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
    """Rotation (2, 2) that turns 2-D ``points`` (N, 2) so that the edges of their minimum-area
    rectangle lie along the axes (by at most 45 deg)."""
    with np.errstate(over="ignore", invalid="ignore"):     # absurd coordinates fail the size check later
        edge_deg = cv2.minAreaRect(points.astype(np.float32))[2]
    turn_rad = np.deg2rad((edge_deg + 45.0) % 90.0 - 45.0)
    return np.array([[np.cos(turn_rad), np.sin(turn_rad)], [-np.sin(turn_rad), np.cos(turn_rad)]])   # by -turn


def _rasterised_image(xyz: np.ndarray, intensity: np.ndarray, pose: PlatePose,
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
        # takes it as it is (two bincounts where splatting takes eight).
        corner_column, corner_row = np.rint(column).astype(np.int64), np.rint(row).astype(np.int64)
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
        sums, weights, weight = np.zeros(size), np.zeros(size), np.empty(len(base))
        for step, column_weight, row_weight in ((0, rest_column, rest_row), (1, fraction_column, rest_row),
                                                (width, rest_column, fraction_row),
                                                (width + 1, fraction_column, fraction_row)):
            # Binned at the corner pixel, then moved by ``step``: no index array per neighbour.
            np.multiply(column_weight, row_weight, out=weight)
            weights[step:] += np.bincount(base, weights=weight, minlength=size)[:size - step]
            weight *= values
            sums[step:] += np.bincount(base, weights=weight, minlength=size)[:size - step]
    covered = weights > 1e-3
    mean = np.divide(sums, weights, out=sums, where=covered).reshape(height, width)   # 0 where not covered
    image = _fill_missing(mean, covered.reshape(height, width))
    to_plane = np.linalg.inv(to_pixel)
    shift = offset + pose.centre @ in_plane         # pixel = to_pixel @ uv + shift
    # (row, column) pitch on the plate: the nominal one, or through the plane for a raster in x-y.
    pitch = ((float(np.linalg.norm(to_plane[:, 1])), float(np.linalg.norm(to_plane[:, 0]))) if in_cloud_xy
             else (pixel_size_mm, pixel_size_mm))
    return _PlateImage(image, None, -to_plane @ shift, pitch, to_plane)


def _local_affines(plate: _PlateImage, centres_px: np.ndarray, half_px: int):
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
    with np.errstate(divide="ignore", invalid="ignore"):    # a singular window's condition is inf
        usable = (weight.sum(axis=1) >= 10) & (np.linalg.cond(normal_matrix) < 1e10)
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


def _sample_bicubic(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Bicubic samples (``cv2.INTER_CUBIC``) of ``image`` at float32 (column, row) positions (M, ...);
    NaN outside."""
    count = len(map_x)
    shape = map_x.shape
    map_x, map_y = map_x.reshape(count, -1), map_y.reshape(count, -1)
    # cv2.remap limits every image side to SHRT_MAX: one row per candidate, in blocks of rows.
    block = 16_384
    samples = np.empty(map_x.shape, np.float32)
    for start in range(0, count, block):
        rows = slice(start, start + block)
        samples[rows] = cv2.remap(image, map_x[rows], map_y[rows], interpolation=cv2.INTER_CUBIC,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return samples.reshape(shape)


def _log_intensity(intensity: np.ndarray) -> np.ndarray:
    """Log intensity (H, W) float32: speckle is multiplicative, so it becomes additive and equal on
    steel and marks. Intensities below 1 % of the typical one are clipped there."""
    # Every 4th pixel per axis gives the median to ~0.1 % at a 16th of the cost.
    floor = 0.01 * max(float(np.median(intensity[::4, ::4])), 1e-12)
    return np.log(np.maximum(intensity, floor)).astype(np.float32)


def _refinement_image(log_intensity: np.ndarray) -> np.ndarray:
    """Whitened image for detection and ring tracking: the log intensity minus its Gaussian blur of
    ``HIGH_PASS_SIGMA_PX`` (removes shading and the coarse part of correlated speckle, keeps the
    thin ring lines)."""
    return log_intensity - cv2.GaussianBlur(log_intensity, (0, 0), HIGH_PASS_SIGMA_PX)


def _prewhitening_kernel(log_intensity: np.ndarray, candidates_px: np.ndarray,
                         clear_radius_px: float) -> np.ndarray | None:
    """Filter (K, K) float32 that whitens the noise of bare steel, or None without enough of it.

    The noise spectrum is the mean periodogram (Hann window, each tile's mean removed) of the
    ``PREWHITENING_TILE_PX`` tiles of ``log_intensity`` that no candidate's disc of
    ``clear_radius_px`` (candidates as (column, row) pixels) touches, plus ``PREWHITENING_FLOOR``
    of its mean; the filter is its inverse square root without the mean, truncated to
    ``PREWHITENING_KERNEL_PX``. Correlated speckle puts most of its power at low spatial
    frequencies, one-pixel ring lines spread theirs up to the pixel pitch: after the filter every
    frequency carries the same noise, so the edge fit weighs each by its signal-to-noise ratio
    (a prewhitening matched filter). With white noise the filter is a mild high pass.
    """
    tile = PREWHITENING_TILE_PX
    height, width = log_intensity.shape
    rows, cols = height // tile, width // tile
    if rows * cols < PREWHITENING_MIN_TILES:
        return None
    covered = np.zeros((height, width), np.uint8)
    for column, row in np.rint(candidates_px).astype(int):
        cv2.circle(covered, (int(column), int(row)), int(np.ceil(clear_radius_px)), 1, -1)
    touched = covered[:rows * tile, :cols * tile].reshape(rows, tile, cols, tile).any(axis=(1, 3))
    tiles = log_intensity[:rows * tile, :cols * tile].reshape(rows, tile, cols, tile).swapaxes(1, 2)[~touched]
    if len(tiles) < PREWHITENING_MIN_TILES:
        return None
    window = np.outer(np.hanning(tile), np.hanning(tile)).astype(np.float32)
    spectrum = np.mean(np.abs(np.fft.rfft2((tiles - tiles.mean(axis=(1, 2), keepdims=True)) * window)) ** 2,
                       axis=0)
    mean_power = float(spectrum.mean())
    if not np.isfinite(mean_power) or mean_power <= 0:
        return None   # noiseless steel: nothing to whiten
    gain = 1.0 / np.sqrt(spectrum + PREWHITENING_FLOOR * mean_power)
    gain[0, 0] = 0.0
    kernel = np.fft.fftshift(np.fft.irfft2(gain, s=(tile, tile)))
    half = PREWHITENING_KERNEL_PX // 2
    kernel = kernel[tile // 2 - half:tile // 2 + half + 1, tile // 2 - half:tile // 2 + half + 1]
    kernel = kernel - kernel.mean()
    return (kernel / np.sqrt(np.sum(kernel**2))).astype(np.float32)


def _ring_template(pitch: tuple[float, float], radii: np.ndarray, line_sigma_mm: float) -> np.ndarray:
    """Darkness template of the rings (rows, cols) at the given (row, column) pitch, negated: dark
    rings correlate positively. Gaussian lines of ``line_sigma_mm`` tolerate blur and tilt."""
    half = radii[-1] + 3 * line_sigma_mm
    rows = np.arange(-np.ceil(half / pitch[0]), np.ceil(half / pitch[0]) + 1) * pitch[0]
    cols = np.arange(-np.ceil(half / pitch[1]), np.ceil(half / pitch[1]) + 1) * pitch[1]
    radius = np.hypot(*np.meshgrid(cols, rows))
    darkness = sum(np.exp(-0.5 * ((radius - r) / line_sigma_mm) ** 2) for r in radii)
    return (-darkness).astype(np.float32)


def _correlation_peaks(score: np.ndarray, distance_px: float, threshold: float) -> np.ndarray:
    """(column, row) of local maxima of ``score`` above ``threshold``, at least ``distance_px`` apart."""
    size = 2 * int(np.ceil(distance_px)) + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    peaks = (score >= cv2.dilate(score, kernel)) & (score > threshold)
    rows, cols = np.nonzero(peaks)
    # Plateaus give several equal maxima: keep one per neighbourhood, strongest first.
    order = np.argsort(-score[rows, cols], kind="stable")
    points = np.column_stack([cols, rows])[order].astype(float)
    if len(points) == 0:
        return points
    tree = cKDTree(points)
    taken = np.zeros(len(points), bool)
    keep = []
    for index in range(len(points)):
        if not taken[index]:
            keep.append(index)
            taken[tree.query_ball_point(points[index], distance_px)] = True
    return points[keep]


def _detection_image(image: np.ndarray, pitch: tuple[float, float]):
    """Image binned to about 0.2 mm pixels for detection (integer factors per axis) and the factors."""
    factor_rows = max(1, int(round(0.2 / pitch[0])))
    factor_cols = max(1, int(round(0.2 / pitch[1])))
    if factor_rows == factor_cols == 1:
        return image, (1, 1)
    height, width = image.shape[0] // factor_rows, image.shape[1] // factor_cols
    binned = image[:height * factor_rows, :width * factor_cols].reshape(
        height, factor_rows, width, factor_cols).mean(axis=(1, 3))
    return binned.astype(np.float32), (factor_rows, factor_cols)


def _detect(image: np.ndarray, pitch: tuple[float, float], radii: np.ndarray, marks_darker: bool | None,
            expected_count: int | None):
    """Candidate centres (M, 2) as (column, row) pixels of ``image``, their scores, and the polarity."""
    binned, (factor_rows, factor_cols) = _detection_image(image, pitch)
    binned_pitch = (pitch[0] * factor_rows, pitch[1] * factor_cols)
    template = _ring_template(binned_pitch, radii, max(0.6 * max(binned_pitch), 0.06))
    # Zero padding (the whitened image's mean) lets rings that touch the scan's border be found; the
    # fit then sees how much of them is there (coverage).
    pad_rows, pad_cols = (template.shape[0] - 1) // 2, (template.shape[1] - 1) // 2
    binned = cv2.copyMakeBorder(binned, pad_rows, pad_rows, pad_cols, pad_cols, cv2.BORDER_CONSTANT, value=0.0)
    score = cv2.matchTemplate(binned, template, cv2.TM_CCOEFF_NORMED)
    score = np.nan_to_num(score, nan=0.0)
    # Bare steel sets the spread of the correlation; marks cover a small share of the plate.
    sample = score[::2, ::2]
    median = float(np.median(sample))
    spread = robust_sigma(sample - median)
    threshold = max(MIN_DETECTION_SCORE, median + DETECTION_SIGMAS * spread,
                    -median + DETECTION_SIGMAS * spread)
    distance_px = radii[-1] / max(binned_pitch)
    if marks_darker is None:
        # The polarity whose strongest peaks stand out more: bright marks correlate negatively.
        top = max(expected_count or 0, 4)
        strength = []
        for sign in (1.0, -1.0):
            values = _correlation_peaks(sign * score, distance_px, threshold)
            scores = np.sort(sign * score[values[:, 1].astype(int), values[:, 0].astype(int)])[::-1][:top] \
                if len(values) else np.zeros(0)
            strength.append(float(np.sum(scores)))
        marks_darker = strength[0] >= strength[1]
    signed = score if marks_darker else -score
    peaks = _correlation_peaks(signed, distance_px, threshold)
    if expected_count:
        peaks = peaks[:max(2 * expected_count, expected_count + 20)]
    values = signed[peaks[:, 1].astype(int), peaks[:, 0].astype(int)] if len(peaks) else np.empty(0)
    offset = np.array([(template.shape[1] - 1) / 2 - pad_cols, (template.shape[0] - 1) / 2 - pad_rows])
    binned_centre = peaks + offset
    # Binned pixel k covers full pixels k*f .. k*f + f - 1: centre at k*f + (f - 1) / 2.
    centres = binned_centre * np.array([factor_cols, factor_rows]) + np.array(
        [(factor_cols - 1) / 2, (factor_rows - 1) / 2])
    return centres, values, marks_darker


def _profile_template(step: float, offsets: np.ndarray, line_sigma_mm: float) -> np.ndarray:
    """Radial profile of dark lines at ``offsets`` (mm from the template centre), zero mean, negated."""
    half = float(np.max(np.abs(offsets))) + 3 * line_sigma_mm
    positions = np.arange(-np.ceil(half / step), np.ceil(half / step) + 1) * step
    darkness = sum(np.exp(-0.5 * ((positions - offset) / line_sigma_mm) ** 2) for offset in offsets)
    template = -darkness
    return (template - template.mean()).astype(np.float32)


def _correlate_rows(profiles: np.ndarray, template: np.ndarray) -> np.ndarray:
    """Correlation of every profile (..., S) with a centred odd-length template, same length."""
    shape = profiles.shape
    flat = np.ascontiguousarray(profiles.reshape(-1, shape[-1]), dtype=np.float32)
    out = np.empty_like(flat)
    # cv2.filter2D correlates (no flip) with the anchor at the kernel centre; limited to 32767 rows.
    block = 32_000
    for start in range(0, len(flat), block):
        out[start:start + block] = cv2.filter2D(flat[start:start + block], cv2.CV_32F, template[None, :],
                                                borderType=cv2.BORDER_REPLICATE)
    return out.reshape(shape)


def _peak(score: np.ndarray, low: np.ndarray, width: int):
    """Sub-sample argmax of ``score`` (M, A, S) within sample indices [low, low + width) per candidate.

    ``low`` (M,) must keep the window and one neighbour on each side inside the profile. Returns
    the fractional index (M, A) and whether the maximum is interior (a real peak, not an end)."""
    index = low[:, None, None] + np.arange(width)[None, None, :]                   # (M, 1, W)
    window = np.take_along_axis(score, np.broadcast_to(index, score.shape[:2] + (width,)), -1)
    best = np.argmax(window, axis=-1)
    interior = (best > 0) & (best < width - 1)
    at = low[:, None] + best
    left = np.take_along_axis(score, (at - 1)[..., None], -1)[..., 0]
    centre = np.take_along_axis(score, at[..., None], -1)[..., 0]
    right = np.take_along_axis(score, (at + 1)[..., None], -1)[..., 0]
    curvature = left - 2 * centre + right
    delta = np.where(curvature < 0, 0.5 * (left - right) / np.where(curvature < 0, curvature, -1.0), 0.0)
    return at + np.clip(delta, -0.5, 0.5), interior & (curvature < 0)


def _harmonic_design(angles: np.ndarray) -> np.ndarray:
    """Radial model of a ring seen from near its centre: r(theta) = R + a cos + b sin + c cos 2 + d sin 2.

    (a, b) is the centre's offset from the ray origin (first order, exact at the fixed point of the
    passes); the second harmonic takes up ellipticity (tilt, unequal pixel pitch, an uncalibrated
    scanner's distortion) so that it neither enters the residuals nor the uncertainty."""
    return np.stack([np.ones_like(angles), np.cos(angles), np.sin(angles), np.cos(2 * angles),
                     np.sin(2 * angles)], axis=-1)


def _row_nanquantile(values: np.ndarray, quantile: float) -> np.ndarray:
    """Per row of ``values`` (M, N) the ``quantile`` (0-1, linear interpolation) of its finite entries,
    NaN for a row without any: ``np.nanpercentile`` along rows, with one sort for all rows instead of
    numpy's loop over the rows that hold a NaN."""
    ordered = np.sort(np.where(np.isfinite(values), values, np.nan), axis=1)      # NaN sorts last
    last = np.isfinite(values).sum(axis=1) - 1
    position = np.maximum(last, 0) * quantile
    low = np.floor(position).astype(int)
    high = np.minimum(low + 1, np.maximum(last, 0))
    rows = np.arange(len(values))
    lower, upper = ordered[rows, low], ordered[rows, high]
    return np.where(last >= 0, lower + (upper - lower) * (position - low), np.nan)


def _fit_ring(edge_radius: np.ndarray, design: np.ndarray, usable: np.ndarray, strength: np.ndarray | None = None):
    """Weighted least-squares fit of the radial model to edge radii (M, A) over the ``usable`` rays,
    each weighted by its ``strength`` (M, A; default 1), with one 3-sigma trimming round.

    Returns the centre shift (M, 2), mean radius (M,), the fitted radius along every ray (M, A),
    residuals (M, A), rays used (M, A) and fit_ok (M,).
    """
    used = usable.copy()
    parameters = design.shape[-1]
    for trimming in range(2):
        w = used * (1.0 if strength is None else strength)
        normal_matrix = np.einsum("ai,ma,aj->mij", design, w, design)
        right = np.einsum("ai,ma->mi", design, w * edge_radius)
        well_posed = np.linalg.cond(normal_matrix) < 1e10
        normal_matrix[~well_posed] = np.eye(parameters)
        solution = np.linalg.solve(normal_matrix, right[..., None])[..., 0]
        residual = edge_radius - solution @ design.T
        if trimming == 0:
            # Rays hit by speckle, a scratch or a neighbour's mark: beyond 3 robust sigmas.
            mad = _row_nanquantile(np.where(used, np.abs(residual), np.nan), 0.5)
            limit = np.maximum(3.0 * NORMAL_MAD_SCALE * np.nan_to_num(mad, nan=0.0), 1e-6)
            used = used & (np.abs(residual) <= limit[:, None])
    fit_ok = well_posed & (used.sum(axis=1) >= 16)
    return solution[:, 1:3], solution[:, 0], edge_radius - residual, residual, used, fit_ok


def _edge_weights(peak_score: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Weight (M, A) of every ray's edge point in the ring fit: its darkness contrast (the profile's
    correlation with the rings at the edge) over the candidate's median one, to the power
    ``EDGE_WEIGHT_POWER``, at most ``EDGE_WEIGHT_MAX``.

    A ray's edge error grows as its rings' contrast falls (marks fainter along the path, a line
    sampled between points), so rays are weighed by how clearly they see the rings, relative to the
    same fiducial's other rays rather than against a fixed threshold."""
    median = _row_nanquantile(np.where(usable, peak_score, np.nan), 0.5)
    relative = peak_score / np.where(median > 0, median, np.inf)[:, None]
    return np.clip(relative, 0.0, EDGE_WEIGHT_MAX) ** EDGE_WEIGHT_POWER


def _sector_sums(values: np.ndarray, sector_of_ray: np.ndarray) -> np.ndarray:
    """Sums of ``values`` (M, A, ...) over the rays of each sector (M, SECTORS, ...); the rays of a
    sector are contiguous and ``sector_of_ray`` is sorted, so this is one ``reduceat``."""
    starts = np.searchsorted(sector_of_ray, np.arange(SECTORS))
    return np.add.reduceat(values, starts, axis=1)


def _centre_covariance(design: np.ndarray, residual: np.ndarray, used: np.ndarray,
                       sector_of_ray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (M, 2, 2) of the fitted centre (plate axes, mm^2) from the radial residuals, and its
    degrees of freedom (M,): per candidate the larger (by trace) of two estimates, each blind to
    what the other sees.

    - The delete-one-sector jackknife of the linearised circle fit (dof: sectors used - 1) follows a
      fiducial's own trouble, a scratch or a speckle grain on a few sectors.
    - The spectral estimate (``_spectral_covariance``) follows noise correlated around the whole ring,
      whose share in the first harmonic (the centre) no sector sees.
    """
    count, rays = residual.shape
    parameters = design.shape[-1]
    u = np.asarray(used, dtype=float)       # the fit's weight per ray, 0 where unused
    full_design = np.broadcast_to(design, (count, rays, parameters))
    sector_normal = _sector_sums(np.einsum("mai,ma,maj->maij", full_design, u, full_design), sector_of_ray)
    sector_score = _sector_sums(full_design * (u * np.where(u > 0, residual, 0.0))[..., None], sector_of_ray)
    jackknife, groups = sector_jackknife(sector_normal, sector_score, _sector_sums(u, sector_of_ray) > 0,
                                          total_right=np.zeros((count, parameters)))
    jackknife = jackknife[:, 1:3, 1:3]
    spectral, spectral_dof = _spectral_covariance(design, residual, used)
    larger = np.trace(jackknife, axis1=1, axis2=2) >= np.trace(spectral, axis1=1, axis2=2)
    return (np.where(larger[:, None, None], jackknife, spectral),
            np.where(larger, groups - 1.0, spectral_dof))


def _spectral_covariance(design: np.ndarray, residual: np.ndarray, used: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (M, 2, 2) of the fitted centre from the edge noise's spectrum around the ring, and
    its degrees of freedom (M,).

    The edge errors of neighbouring rays are correlated (speckle grains span several rays), and their
    power falls with the harmonic number; the centre is the first harmonic, which the fit takes out of
    the residuals along with harmonics 0 and 2. So the spectrum's shape is pooled over the plate's
    well-seen candidates (residual periodograms, each over its own residual variance), fitted by a
    straight line over ``SPECTRUM_FIT_HARMONICS`` and extended by it to harmonics 0-2; each candidate
    scales it by its own residual variance s^2. With the rays' covariance C the circulant of that
    spectrum, the fit's covariance is the sandwich B^-1 (W X)^T C (W X) B^-1 (X the design, W the
    used rays, B = X^T W X). Degrees of freedom: the used rays over the noise's integrated
    correlation (the spectrum at harmonic 0 over its mean).
    """
    count, rays = residual.shape
    weight = np.asarray(used, dtype=float)      # the fit's weight per ray, 0 where unused
    kept = np.where(weight > 0, residual, 0.0)
    share = (weight > 0).mean(axis=1)
    variance = (weight * kept**2).sum(axis=1) / np.maximum(weight.sum(axis=1), 1e-12)
    periodogram = np.abs(np.fft.rfft(kept, axis=1)) ** 2 / rays                    # harmonics 0..A/2
    sample = (share >= SPECTRUM_SAMPLE_MIN_SHARE) & (variance > 0)
    if np.count_nonzero(sample) < MODERATION_MIN_REFERENCE:
        sample = variance > 0
    if not sample.any():
        return np.zeros((count, 2, 2)), np.full(count, 2.0)
    shape = (periodogram[sample] / (variance[sample] * share[sample])[:, None]).mean(axis=0)
    first, last = SPECTRUM_FIT_HARMONICS
    band = np.arange(first, last + 1)
    line = np.polyfit(band, shape[band], 1)
    shape[:first] = np.maximum(np.polyval(line, np.arange(first)), 0.0)
    weighted = weight[..., None] * design                                               # (M, A, P)
    correlated = np.fft.irfft(np.fft.rfft(weighted, axis=1) * shape[None, :, None], n=rays, axis=1)
    transposed = np.swapaxes(weighted, 1, 2)                                            # (M, P, A)
    meat = variance[:, None, None] * (transposed @ correlated)
    normal = transposed @ design
    normal[~(np.linalg.cond(normal) < 1e10)] = np.eye(design.shape[-1])
    inverse = np.linalg.inv(normal)
    covariance = inverse @ meat @ inverse
    # The mean over all A harmonics of the symmetric spectrum, from its half.
    full_mean = (2.0 * shape.sum() - shape[0] - shape[-1]) / rays
    correlation_time = max(shape[0] / max(full_mean, 1e-12), 1.0)
    return covariance[:, 1:3, 1:3], np.maximum(weight.sum(axis=1) / correlation_time, 2.0)


def _moderated(covariance: np.ndarray, dof: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Centre covariances (M, 2, 2) with each axis' variance raised to its empirical-Bayes
    posterior, never lowered.

    A variance estimated from ~24 sectors (``dof`` (M,) degrees of freedom) comes out well below the
    true one now and then, so in units of the stated uncertainty the errors of a plate are
    heavy-tailed (Student t, not normal). The fiducials of one plate share most of their noise:
    per plate axis, each variance is combined with the plate's typical one as in moderated
    statistics (Smyth 2004): the prior's degrees of freedom d0 and variance s0^2 by the method of
    moments on the log variances of the ``reference`` candidates, posterior (d s^2 + d0 s0^2) /
    (d + d0). Only raised: a fiducial with a genuinely larger uncertainty (scratched, partly seen)
    keeps its own. Fewer than ``MODERATION_MIN_REFERENCE`` references: unchanged.
    """
    usable = reference & (dof >= 2) & np.all(np.diagonal(covariance, axis1=1, axis2=2) > 0, axis=1)
    if np.count_nonzero(usable) < MODERATION_MIN_REFERENCE:
        return covariance
    half = dof[usable] / 2.0
    factors = np.ones((len(covariance), 2))
    for axis in range(2):
        variance = covariance[:, axis, axis]
        # log s^2 - E[log chi2_d / d] is centred on the log of the prior's scale (both have digammas)
        centred = np.log(variance[usable]) - special.digamma(half) + np.log(half)
        excess = np.var(centred, ddof=1) - np.mean(special.polygamma(1, half))
        if excess > 0:
            prior_dof = 2.0 * optimize.brentq(lambda x: special.polygamma(1, x) - excess, 1e-8, 1e8)
            prior = np.exp(np.mean(centred) + special.digamma(prior_dof / 2) - np.log(prior_dof / 2))
            posterior = (dof * variance + prior_dof * prior) / np.maximum(dof + prior_dof, 1e-12)
        else:   # no spread beyond the sampling's: one variance for the whole plate
            posterior = np.full(len(variance), np.exp(np.mean(centred)))
        with np.errstate(divide="ignore", invalid="ignore"):
            factors[:, axis] = np.where(variance > 0, np.maximum(posterior / variance, 1.0), 1.0)
    scale = np.sqrt(factors)
    return covariance * scale[:, :, None] * scale[:, None, :]


def _second_harmonic(radius_per_ray: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """cos 2theta and sin 2theta amplitudes (M, 2) of radii (M, A) at equally spaced ray ``angles`` (A,)."""
    return np.stack([radius_per_ray @ np.cos(2 * angles), radius_per_ray @ np.sin(2 * angles)], -1) * (
        2.0 / len(angles))


def _refine(image: np.ndarray, centres_uv: np.ndarray, offset: np.ndarray, jacobian: np.ndarray,
            radii_nominal: np.ndarray, pitch_mm: float, fit_image: np.ndarray | None = None) -> dict:
    """Sub-pixel double-ring fit per candidate (see the module docstring, step 3 and 4).

    ``PASSES`` passes on ``image`` follow the rings and give the coverage and the rings' radii; with
    a ``fit_image`` (the prewhitened image), ``FIT_PASSES`` more passes on it, over the sectors seen,
    give the centres and their covariance.
    Returns centres (M, 2), covariance (M, 2, 2) with its degrees of freedom (M,), per-ring radii
    (M, R), edge RMS (M,), coverage (M,), ellipticity (M,), the last fit's mean radius (M,) and
    elliptical second harmonic (M, 2), and fit_ok (M,).
    """
    count = len(centres_uv)
    mid = float(np.mean(radii_nominal))
    offsets = radii_nominal - mid
    line_sigma = max(0.9 * pitch_mm, 0.05)
    step = RADIAL_STEP_PX * pitch_mm
    pair_template = _profile_template(step, offsets, line_sigma)
    half = (len(pair_template) - 1) / 2 * step
    angles = np.linspace(0.0, 2 * np.pi, RAY_COUNT, endpoint=False)
    directions = np.stack([np.cos(angles), np.sin(angles)], axis=-1)         # (A, 2)
    design = _harmonic_design(angles)                                        # (A, 5)
    sector_of_ray = (np.arange(RAY_COUNT) * SECTORS) // RAY_COUNT
    inverse = np.linalg.inv(jacobian)
    centres = centres_uv.copy()
    visible = np.ones((count, RAY_COUNT), bool)
    fit_ok = np.ones(count, bool)
    coverage = np.zeros(count)
    schedule = [image] * PASSES + ([fit_image] * FIT_PASSES if fit_image is not None else [])
    tracked = None
    for refinement, pass_image in enumerate(schedule):
        fitting_only = refinement >= PASSES
        if fitting_only and refinement == PASSES:
            # What the rings' tracking found is kept: radii and coverage are measured on the
            # high-passed image, whose line shape the templates describe.
            tracked = dict(profiles=profiles, used=used, at=at, sampled_at=sampled_at, radial=radial)
        margin = (COARSE_MARGIN_PX if refinement == 0 else FINE_MARGIN_PX) * pitch_mm
        reach = half + (margin if refinement == 0 else 2 * margin) + step
        radial = (mid + np.arange(-np.ceil(reach / step), np.ceil(reach / step) + 1) * step).astype(np.float32)
        profiles = _ray_profiles(pass_image, centres, offset, inverse, directions, radial)
        finite = np.isfinite(profiles)
        inside = finite.all(axis=2)
        profiles = np.where(finite, profiles, np.float32(0.0))
        score = _correlate_rows(profiles, pair_template)
        # Search window (indices along the ray): +- margin about the nominal mid radius, then about
        # the last fitted one (rings of the wrong size stay in view and fail the radius check).
        centre_radius = np.full(count, mid) if refinement == 0 else np.clip(radius, mid - margin, mid + margin)
        width = int(np.floor(2 * margin / step)) + 1
        low = np.clip(np.ceil((centre_radius - margin - radial[0]) / step).astype(int), 1, len(radial) - width - 1)
        index, peak_ok = _peak(score, low, width)
        edge = radial[0] + index * step
        ray_ok = inside & peak_ok & (visible if refinement >= 2 else True)
        strength = _edge_weights(np.take_along_axis(score, np.rint(index).astype(int)[..., None], -1)[..., 0],
                                 ray_ok)
        shift, radius, at, residual, used, ok = _fit_ring(edge, design, ray_ok, strength)
        ok &= ray_ok.mean(axis=1) >= MIN_VALID_RAY_FRACTION * (coverage if refinement >= 2 else 1.0)
        fit_ok = ok if refinement == 0 else fit_ok & ok
        if fitting_only:
            centres = np.where(fit_ok[:, None], centres + shift, centres)
            continue
        # Ring amplitude of every ray at the fitted circle: erased arcs read about zero there.
        position = np.clip(np.rint((at - radial[0]) / step).astype(int), 0, len(radial) - 1)
        amplitude = np.where(inside, np.take_along_axis(score, position[..., None], -1)[..., 0], np.nan)
        sector_sum = _sector_sums(np.where(np.isfinite(amplitude), amplitude, 0.0), sector_of_ray)
        sector_n = _sector_sums(np.isfinite(amplitude).astype(float), sector_of_ray)
        with np.errstate(invalid="ignore", divide="ignore"):
            sector = np.where(sector_n > 0, sector_sum / sector_n, np.nan)
        reference = _row_nanquantile(sector, 0.75)
        seen = np.nan_to_num(sector) > SECTOR_SEEN_FRACTION * np.where(reference > 0, reference, np.inf)[:, None]
        coverage = seen.mean(axis=1)
        visible = seen[:, sector_of_ray]
        sampled_at = centres
        centres = np.where(fit_ok[:, None], centres + shift, centres)
    final_residual, final_used, final_weight = residual, used, used * strength
    # The fitted ring about the final centre: mean radius and elliptical second harmonic.
    mid_radius = radius
    harmonic = _second_harmonic(at, angles)
    if tracked is not None:
        profiles, used, at, sampled_at, radial = (
            tracked[key] for key in ("profiles", "used", "at", "sampled_at", "radial"))
    # Second harmonic of the tracked ring (half the difference of its axes): a ring on the plate is a
    # circle, so this is small; the envelope of two offset rings (a merged detection) is not.
    ellipticity = np.hypot(*_second_harmonic(at, angles).T)
    covariance, dof = _centre_covariance(design, final_residual, final_weight, sector_of_ray)

    # Each ring's radius about the final centre: darkness centroid in a window of +- half the ring
    # gap around its expected position on every used ray (a check of the ring sizes, not the centre).
    ring_radii = np.full((count, len(radii_nominal)), np.nan)
    gap = float(np.min(np.diff(radii_nominal))) if len(radii_nominal) > 1 else 4 * pitch_mm
    outside = np.abs(radial - mid) > half + margin
    background = np.median(profiles[:, :, outside], axis=2) if outside.any() else np.zeros(profiles.shape[:2])
    darkness = np.clip(background[..., None] - profiles, 0.0, None)
    at = at.astype(np.float32)
    for ring, ring_offset in enumerate(offsets):
        expected = (at + np.float32(ring_offset))[..., None]
        window = np.clip((np.float32(gap / 2) - np.abs(radial - expected)) / np.float32(step) + np.float32(0.5),
                         0.0, 1.0)
        weight = darkness * window
        total = weight.sum(axis=2)
        centroid = (weight * radial).sum(axis=2) / np.where(total > 0, total, 1.0)
        points = sampled_at[:, None, :] + centroid[..., None] * directions
        distance = np.linalg.norm(points - centres[:, None, :], axis=-1)
        good = used & (total > 0)
        counts = good.sum(axis=1)
        ring_radii[:, ring] = np.where(counts > 0, np.where(good, distance, 0.0).sum(axis=1)
                                       / np.maximum(counts, 1), np.nan)
    rms = np.sqrt((np.where(final_used, final_residual, 0.0) ** 2).sum(axis=1) / np.maximum(final_used.sum(axis=1), 1))
    return dict(centres=centres, covariance=covariance, dof=dof, radii=ring_radii, rms=rms, coverage=coverage,
                ellipticity=ellipticity, mid_radius=mid_radius, harmonic=harmonic,
                fit_ok=fit_ok & np.isfinite(ring_radii).all(axis=1))


def _ray_profiles(image: np.ndarray, centres: np.ndarray, offset: np.ndarray, inverse: np.ndarray,
                  directions: np.ndarray, radial: np.ndarray) -> np.ndarray:
    """Image samples along rays (M, A, S) laid out in plate mm from ``centres``; NaN outside.

    Rays map to pixels through each candidate's inverse affine map (pixel = J^-1 (uv - offset))."""
    start = np.einsum("mij,mj->mi", inverse, centres - offset).astype(np.float32)      # (M, 2)
    heading = np.einsum("mij,aj->mai", inverse, directions).astype(np.float32)          # (M, A, 2)
    map_x = start[:, None, None, 0] + heading[..., 0, None] * radial                    # (M, A, S)
    map_y = start[:, None, None, 1] + heading[..., 1, None] * radial
    return _sample_bicubic(image, map_x, map_y)


def _duplicates(centres: np.ndarray, sigma: np.ndarray, distance: float) -> np.ndarray:
    """Mask of centres within ``distance`` of a centre with a smaller uncertainty (kept: False)."""
    order = np.argsort(sigma, kind="stable")
    tree = cKDTree(centres)
    taken = np.zeros(len(centres), bool)
    duplicate = np.zeros(len(centres), bool)
    for index in order:
        if taken[index]:
            duplicate[index] = True
            continue
        taken[tree.query_ball_point(centres[index], distance)] = True
    return duplicate


def _signature_band_mm(radii_nominal: np.ndarray, pitch: tuple[float, float]) -> float:
    """Half-width (mm) about the mid-ring of the pixels the pair signature is fitted on: the rings,
    their lines and the prewhitening filter's reach beyond them."""
    spread = float(np.ptp(radii_nominal)) / 2
    return spread + LINE_HALF_WIDTH_MM + (PREWHITENING_KERNEL_PX // 2) * max(pitch)


def _plane_to_cloud_sigma(covariance: np.ndarray, pose: PlatePose) -> np.ndarray:
    """Per-axis standard uncertainty (M, 2) along the cloud's x and y of plate-axis covariances."""
    in_plane = np.asarray(pose.rotation, dtype=float)[:, :2]
    cloud = np.einsum("ij,mjk,lk->mil", in_plane, covariance, in_plane)
    return np.sqrt(np.stack([cloud[:, 0, 0], cloud[:, 1, 1]], axis=-1))


def measure_fiducials(xyz, intensity, pose: PlatePose, *, ring_radii_mm=RING_RADII_MM,
                      pixel_size_mm: float | None = None, expected_count: int | None = None,
                      marks_darker: bool | None = True, radius_tolerance_mm: float | None = None,
                      allow_empty: bool = False) -> FiducialMeasurement:
    """Measure the double-ring fiducials of a plate scan; see the module docstring for the method.

    ``xyz`` is organized (H, W, 3) with ``intensity`` (H, W), or unorganized (N, 3) with (N,); NaNs
    are allowed. ``pose`` is the plate pose from ``estimate_plate_pose``. ``pixel_size_mm`` is the
    raster pitch for unorganized clouds; None takes it from the cloud's own point spacing
    (``_rasterised_image``). ``marks_darker`` None finds the polarity from the image.
    A candidate is accepted when both semi-axes of every fitted ring are within ``radius_tolerance_mm``
    of its nominal radius (None: :data:`RADIUS_TOLERANCE_FRACTION` of the largest radius, 0.12 mm for
    the published 2.7 mm ring: an uncalibrated scanner marks rings a few percent too large, 2.78 mm
    for 2.7 mm on the simulated defective cell, and a larger ring by as many percent) and its
    quality checks pass (module docstring,
    step 5). Raises ValueError when no
    fiducial is accepted, unless ``allow_empty``.
    """
    radii_nominal = np.array(sorted(float(r) for r in as_finite_array(ring_radii_mm, "ring_radii_mm", ndim=1)))
    if radii_nominal.size == 0 or radii_nominal[0] <= 0 or len(set(radii_nominal)) != len(radii_nominal):
        raise ValueError(f"ring_radii_mm must be distinct positive radii, got {list(ring_radii_mm)}")
    if pixel_size_mm is not None and (not np.isfinite(pixel_size_mm) or pixel_size_mm <= 0):
        raise ValueError(f"pixel_size_mm must be positive, got {pixel_size_mm!r}")
    if expected_count is not None and expected_count < 0:
        raise ValueError(f"expected_count must be non-negative, got {expected_count}")
    try:
        xyz = np.asarray(xyz, dtype=float)
        intensity = np.asarray(intensity, dtype=float)
    except (TypeError, ValueError) as error:
        raise ValueError(f"xyz and intensity must be numeric: {error}") from None
    if xyz.ndim == 3 and xyz.shape[2] == 3 and intensity.shape == xyz.shape[:2]:
        plate = _organized_image(xyz, intensity, pose)
    elif xyz.ndim == 2 and xyz.shape[1] == 3 and intensity.shape == xyz.shape[:1]:
        plate = _rasterised_image(xyz, intensity, pose, pixel_size_mm, float(radii_nominal[0]))
    else:
        raise ValueError("xyz must be (H, W, 3) with intensity (H, W), or (N, 3) with intensity (N,); "
                         f"got {xyz.shape} and {intensity.shape}")

    log_intensity = _log_intensity(plate.intensity)
    whitened = _refinement_image(log_intensity)
    height, width = whitened.shape
    candidates, _, marks_darker = _detect(whitened, plate.pitch, radii_nominal, marks_darker, expected_count)
    image = whitened if marks_darker else -whitened
    pitch = min(plate.pitch)
    if len(candidates):
        half_px = int(np.ceil((radii_nominal[-1] + 0.5) / pitch))
        offset, jacobian, affine_ok = _local_affines(plate, candidates, half_px)
        start_uv = offset + np.einsum("mij,mj->mi", jacobian, candidates)
        kernel = _prewhitening_kernel(log_intensity, candidates,
                                      (radii_nominal[-1] + RING_CLEARANCE_MM) / min(plate.pitch))
        fit_image = None if kernel is None else cv2.filter2D(
            log_intensity, cv2.CV_32F, kernel if marks_darker else -kernel, borderType=cv2.BORDER_REFLECT)
        fit = _refine(image, start_uv, offset, jacobian, radii_nominal, pitch, fit_image)
    else:
        affine_ok = np.zeros(0, bool)
        offset, jacobian, fit_image = np.empty((0, 2)), np.empty((0, 2, 2)), None
        fit = dict(centres=np.empty((0, 2)), covariance=np.empty((0, 2, 2)), dof=np.zeros(0, int),
                   radii=np.empty((0, len(radii_nominal))), rms=np.empty(0), coverage=np.empty(0),
                   ellipticity=np.empty(0), mid_radius=np.empty(0), harmonic=np.empty((0, 2)),
                   fit_ok=np.zeros(0, bool))
    centres_uv = fit["centres"]
    # Both semi-axes of every ring (mean radius +- the second harmonic) within the tolerance: an
    # uncalibrated scanner's anisotropic scale keeps them there, the envelope of two offset rings
    # (a merged detection) does not.
    if radius_tolerance_mm is None:
        radius_tolerance_mm = RADIUS_TOLERANCE_FRACTION * float(radii_nominal[-1])
    radius_ok = np.all(np.abs(fit["radii"] - radii_nominal) + fit["ellipticity"][:, None] <= radius_tolerance_mm,
                       axis=1)
    reference = fit["fit_ok"] & (fit["coverage"] >= MIN_COVERAGE) & radius_ok
    covariance = _moderated(fit["covariance"], fit["dof"], reference) + MODEL_SIGMA_MM**2 * np.eye(2)
    sigma_plane = np.sqrt(np.stack([covariance[:, 0, 0], covariance[:, 1, 1]], axis=-1))
    sigma_xy = _plane_to_cloud_sigma(covariance, pose)
    reasons = np.full(len(candidates), STATUS_OK, dtype=object)
    # The first failing check names the reason, most basic first.
    checks = (("fit", fit["fit_ok"] & affine_ok), ("spurious", fit["coverage"] >= SPURIOUS_COVERAGE),
              ("partial", fit["coverage"] >= MIN_COVERAGE),
              ("radius", radius_ok), ("uncertain", sigma_plane.max(axis=1, initial=0.0) <= MAX_SIGMA_MM))
    for reason, passed in reversed(checks):
        reasons[~passed] = reason
    # Two fiducials close enough to pass as one (ring radii and shape within the tolerances above):
    # their lines split along the offset and coincide across it (``merged_fiducials``).
    signature, signature_covariance, signature_groups = merged_fiducials.pair_signature(
        image if fit_image is None else fit_image, centres_uv, offset, jacobian, fit["mid_radius"],
        fit["harmonic"], reasons == STATUS_OK, plate.pitch, _signature_band_mm(radii_nominal, plate.pitch))
    merged = merged_fiducials.merged(signature, signature_covariance, signature_groups, reasons == STATUS_OK,
                                     MERGED_FALSE_ALARM, MERGED_MIN_REFERENCE)
    reasons[merged & np.isin(reasons, (STATUS_OK, "uncertain"))] = "merged"
    accepted = np.nonzero(reasons == STATUS_OK)[0]
    duplicate = _duplicates(centres_uv[accepted], sigma_plane[accepted].max(axis=1, initial=0.0),
                            radii_nominal[-1])
    reasons[accepted[duplicate]] = "duplicate"
    kept = accepted[~duplicate]
    if len(kept):
        # Failed candidates of an accepted fiducial are its duplicates, whatever else went wrong.
        near = cKDTree(centres_uv[kept]).query(centres_uv, distance_upper_bound=radii_nominal[-1])[0]
        reasons[(reasons != STATUS_OK) & np.isfinite(near)] = "duplicate"
    turned_down = np.nonzero(reasons != STATUS_OK)[0]
    if len(kept) == 0 and not allow_empty:
        raise ValueError(f"no fiducials found in a {width}x{height} image "
                         f"({len(candidates)} candidate(s) rejected: "
                         f"{', '.join(sorted(set(reasons[turned_down].tolist()))) or 'none detected'})")
    # Row-major order in plate coordinates (v, then u) for reproducible output.
    kept = kept[np.lexsort((centres_uv[kept, 0], centres_uv[kept, 1]))]
    return FiducialMeasurement(
        centres=pose.from_plane(centres_uv[kept]).reshape(-1, 3), centres_plane=centres_uv[kept],
        quality=fit["rms"][kept], radii=fit["radii"][kept, -1], inner_radii=fit["radii"][kept, 0],
        merged=int(np.count_nonzero(reasons == "duplicate")), rejected=int(len(turned_down)),
        # Split so neither count goes negative: a shortfall and a surplus mean different things.
        missing=None if expected_count is None else max(0, int(expected_count) - len(kept)),
        extra=None if expected_count is None else max(0, len(kept) - int(expected_count)),
        image_shape=(height, width), pixel_pitch_mm=plate.pitch,
        sigma_xy_mm=sigma_xy[kept], sigma_plane_mm=sigma_plane[kept], coverage=fit["coverage"][kept],
        rejected_centres=pose.from_plane(centres_uv[turned_down]).reshape(-1, 3),
        rejected_reasons=tuple(reasons[turned_down].tolist()),
        rejected_sigma_xy_mm=sigma_xy[turned_down], rejected_coverage=fit["coverage"][turned_down])
