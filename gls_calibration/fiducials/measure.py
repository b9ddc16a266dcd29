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
   trimming round) moves the centre; the rays follow it (a coarse pass on every second ray at 0.3 px
   steps, then fine passes on all 256 at 0.2 px). The symmetric profile template makes each edge
   point unbiased by background level, linear shading and the rings' blur. These passes run on the
   high-passed log image; the last fit, which gives the centre, runs on the log image prewhitened by
   the noise spectrum of the plate's bare steel (``prewhitening_kernel``), so that correlated speckle
   weighs less at the spatial frequencies where it is strong.
4. Quality per centre: the ring amplitude is measured on 24 angular sectors at the fitted circle;
   ``coverage`` is the share of sectors where the rings are seen, and rays of unseen sectors are
   left out of the final fit. The standard uncertainty per axis comes from the fit: the larger of a
   delete-one-sector jackknife of the edge points' ring fit (a fiducial's own local trouble) and a
   spectral estimate (edge noise correlated along the ring, whose power in the first harmonic, the
   centre, the residuals do not show; ``_spectral_covariance``), its variances raised towards the
   plate's typical one where they came out low by chance (``moderated_covariance``), plus ``MODEL_SIGMA_MM``.
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
from scipy.spatial import cKDTree

from gls_calibration.common.validation import as_finite_array
from gls_calibration.fiducials import merged_pairs as merged_fiducials
from gls_calibration.fiducials.centre_uncertainty import MODEL_SIGMA_MM, moderated_covariance, plane_to_cloud_sigma
from gls_calibration.fiducials.detection import (PREWHITENING_KERNEL_PX, detect_rings, log_intensity_image,
                                                 prewhitening_kernel, refinement_image)
from gls_calibration.fiducials.raster import LINE_HALF_WIDTH_MM, local_affines, organized_image, rasterised_image
from gls_calibration.fiducials.ring_fit import refine_ring_centres
from gls_calibration.fiducials.targets import RING_RADII_MM
from gls_calibration.scan.plate_pose import PlatePose


RADIUS_TOLERANCE_FRACTION = 0.16 / 2.7
"""Accepted error of a fitted ring's semi-axes, as a fraction of the fiducial's largest radius: an
uncalibrated head scales its marks by a few percent (gain and distortion), whatever their size. The
simulated paper-like head (2.1 mm field error) scales the corner rings of a 190 mm grid by up to 3 %
and makes them 1-2 % elliptical: semi-axes up to 0.123 mm off, beyond the former 0.12 mm (a corner
fiducial lost on 3x3 grids); 0.16 mm leaves a head 30 % more distorted room. Two fiducials 0.2-0.5 mm
apart, one detection, are still turned down (``merged``, ``partial``, ``radius`` or ``uncertain``)."""

MIN_COVERAGE = 0.75
"""Accepted fiducials show their rings on at least this share of the circumference."""

SPURIOUS_COVERAGE = 0.3
"""Below this coverage a candidate is not a damaged ring but no ring at all (``spurious``)."""

MAX_SIGMA_MM = 0.010
"""Candidates whose stated uncertainty exceeds this (per axis) are rejected as ``uncertain``."""

MERGED_FALSE_ALARM = 1e-5
"""Chance that one single fiducial is turned down as ``merged`` if the merged test's noise model
holds (``merged_fiducials.merged``): one good fiducial lost in about 280 plates of 361, while a
merged pair accepted puts a centre 50-100 um off. The null was measured (docs/fiducial-measurement.md, *Merged
detections*): no p below 7e-5 among 6 320 single fiducials of the benchmark's renders, none of
1 408 on the simulated cell turned down."""

MERGED_MIN_REFERENCE = 20
"""The merged test compares a candidate with the plate's other fiducials: it needs this many."""

RING_CLEARANCE_MM = 0.5
"""Margin beyond the outer ring that the noise spectrum's bare-steel tiles keep from every candidate."""

STATUS_OK = "ok"


@dataclass(frozen=True)
class FiducialMeasurement:
    """Measured fiducial centres (mm) with their uncertainties, and the candidates turned down.

    Arrays not given (a result rebuilt from a message) default to NaN of the right shape, the
    rejected list to empty.

    Parameters
    ----------
    centres : numpy.ndarray, shape (K, 3)
        Centres on the fitted plate plane in the cloud's frame, mm.
    centres_plane : numpy.ndarray, shape (K, 2)
        The same points in plate coordinates (``PlatePose.to_plane``), mm.
    quality : numpy.ndarray, shape (K,)
        RMS residual of the edge points about the fitted circle, mm.
    radii, inner_radii : numpy.ndarray, shape (K,)
        Fitted outer-ring and inner-ring radius, mm.
    merged : int
        Duplicate candidates of an accepted fiducial (reason ``duplicate``; two fiducials merged into
        one detection are rejected with the reason ``merged`` instead).
    rejected : int
        All candidates turned down.
    missing : int or None
        ``max(0, expected_count - K)``, the expected fiducials not found; None when no count was expected.
    image_shape : tuple of 2 int
        (rows, columns) of the analysed image.
    pixel_pitch_mm : tuple of 2 float
        Its (row, column) pitch, mm.
    sigma_xy_mm : numpy.ndarray, shape (K, 2), optional
        Standard uncertainty (k = 1) of each centre along the cloud frame's x and y axes, mm.
    sigma_plane_mm : numpy.ndarray, shape (K, 2), optional
        The same along the plate axes, mm.
    coverage : numpy.ndarray, shape (K,), optional
        Share of the circumference where the rings were seen (0-1).
    rejected_centres : numpy.ndarray, shape (J, 3), optional
        The candidates turned down, mm.
    rejected_reasons : tuple of str, length J, optional
        Why each was turned down.
    rejected_sigma_xy_mm : numpy.ndarray, shape (J, 2), optional
        Their standard uncertainties, mm.
    rejected_coverage : numpy.ndarray, shape (J,), optional
        Their ring coverage (0-1).
    extra : int or None, optional
        ``max(0, K - expected_count)``, the fiducials found beyond the expected count; None when no
        count was expected or unknown (rebuilt from a message).
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
        """Fill the per-centre sigmas and coverage left as None with NaN."""
        count = len(np.asarray(self.centres).reshape(-1, 3))
        for name, shape in (("sigma_xy_mm", (count, 2)), ("sigma_plane_mm", (count, 2)), ("coverage", (count,))):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(shape, np.nan))


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
    """Return the half-width (mm) about the mid-ring of the pixels the pair signature is fitted on.

    Half-width (mm) about the mid-ring of the pixels the pair signature is fitted on: the rings,
    their lines and the prewhitening filter's reach beyond them.
    """
    spread = float(np.ptp(radii_nominal)) / 2
    return spread + LINE_HALF_WIDTH_MM + (PREWHITENING_KERNEL_PX // 2) * max(pitch)


def measure_fiducials(xyz, intensity, pose: PlatePose, *, ring_radii_mm=RING_RADII_MM,
                      pixel_size_mm: float | None = None, expected_count: int | None = None,
                      marks_darker: bool | None = True, radius_tolerance_mm: float | None = None,
                      allow_empty: bool = False) -> FiducialMeasurement:
    """Measure the double-ring fiducials of a plate scan; see the module docstring for the method.

    ``xyz`` is organized (H, W, 3) with ``intensity`` (H, W), or unorganized (N, 3) with (N,); NaNs
    are allowed. ``pose`` is the plate pose from ``estimate_plate_pose``. ``pixel_size_mm`` is the
    raster pitch for unorganized clouds; None takes it from the cloud's own point spacing
    (``rasterised_image``). ``marks_darker`` None finds the polarity from the image.
    A candidate is accepted when both semi-axes of every fitted ring are within ``radius_tolerance_mm``
    of its nominal radius (None: :data:`RADIUS_TOLERANCE_FRACTION` of the largest radius, 0.12 mm for
    the published 2.7 mm ring: an uncalibrated scanner marks rings a few percent too large, 2.78 mm
    for 2.7 mm on the simulated defective cell, and a larger ring by as many percent) and its
    quality checks pass (module docstring,
    step 5).

    Parameters
    ----------
    xyz : array_like
        The marked plate's cloud (mm, scanner frame): organized (H, W, 3) or unorganized (N, 3).
    intensity : array_like
        Its intensity, (H, W) or (N,).
    pose : PlatePose
        The plate's plane in the same frame.
    ring_radii_mm : sequence of float
        Radii the rings were marked with (the fiducial design).
    pixel_size_mm : float, optional
        Raster pitch of an unorganized cloud.
    expected_count : int, optional
        Fiducials marked (a hint for the report of missing ones).
    marks_darker : bool or None
        Polarity of the marks; None finds it.
    radius_tolerance_mm : float, optional
        Accepted error of a fitted ring's semi-axes.
    allow_empty : bool
        Return an empty measurement instead of raising when nothing is accepted.

    Returns
    -------
    FiducialMeasurement
        Accepted centres on the plane (mm), their standard uncertainty per axis, ring radii,
        coverage and quality, and every rejected candidate with its reason.

    Raises
    ------
    ValueError
        Bad input, or no fiducial accepted (unless ``allow_empty``).

    Examples
    --------
    A plate rendered with two rings, measured (the tests render plates with speckle, blur, tilt and
    scanner noise, and by independent renderers, ``test/rendering*.py``):

    >>> from gls_calibration.scan.plate_pose import PlatePose
    >>> u = np.arange(-8.0, 8.0, 0.05)
    >>> x, y = np.meshgrid(u, u)
    >>> distance = np.hypot(x - 0.3, y + 0.2)
    >>> dark = np.exp(-0.5 * ((distance - 2.5) / 0.05) ** 2) + np.exp(-0.5 * ((distance - 2.7) / 0.05) ** 2)
    >>> cloud = np.dstack([x, y, np.zeros_like(x)])
    >>> pose = PlatePose(normal=np.array([0.0, 0.0, 1.0]), centre=np.zeros(3), rotation=np.eye(3),
    ...                  flatness_rms_mm=0.0, inlier_count=x.size, inlier_fraction=1.0)
    >>> found = measure_fiducials(cloud, 1.0 - 0.6 * dark, pose, expected_count=1)
    >>> print(np.round(found.centres_plane, 3), np.round(found.sigma_plane_mm, 4))
    [[ 0.3 -0.2]] [[0.001 0.001]]
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
        plate = organized_image(xyz, intensity, pose)
    elif xyz.ndim == 2 and xyz.shape[1] == 3 and intensity.shape == xyz.shape[:1]:
        plate = rasterised_image(xyz, intensity, pose, pixel_size_mm, float(radii_nominal[0]))
    else:
        raise ValueError("xyz must be (H, W, 3) with intensity (H, W), or (N, 3) with intensity (N,); "
                         f"got {xyz.shape} and {intensity.shape}")

    log_intensity = log_intensity_image(plate.intensity)
    whitened = refinement_image(log_intensity)
    height, width = whitened.shape
    candidates, _, marks_darker = detect_rings(whitened, plate.pitch, radii_nominal, marks_darker, expected_count)
    image = whitened if marks_darker else -whitened
    pitch = min(plate.pitch)
    if len(candidates):
        half_px = int(np.ceil((radii_nominal[-1] + 0.5) / pitch))
        offset, jacobian, affine_ok = local_affines(plate, candidates, half_px)
        start_uv = offset + np.einsum("mij,mj->mi", jacobian, candidates)
        kernel = prewhitening_kernel(log_intensity, candidates,
                                     (radii_nominal[-1] + RING_CLEARANCE_MM) / min(plate.pitch))
        fit_image = None if kernel is None else cv2.filter2D(
            log_intensity, cv2.CV_32F, kernel if marks_darker else -kernel, borderType=cv2.BORDER_REFLECT)
        fit = refine_ring_centres(image, start_uv, offset, jacobian, radii_nominal, pitch, fit_image)
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
    covariance = moderated_covariance(fit["covariance"], fit["dof"], reference) + MODEL_SIGMA_MM**2 * np.eye(2)
    sigma_plane = np.sqrt(np.stack([covariance[:, 0, 0], covariance[:, 1, 1]], axis=-1))
    sigma_xy = plane_to_cloud_sigma(covariance, pose)
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
