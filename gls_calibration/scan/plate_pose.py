"""Pose of the marked steel plate from a laser-line scanner cloud.

Method: Open3D RANSAC (``segment_plane``) on a seeded random subsample of the finite points finds
the dominant plane quickly; a vectorised distance test then selects the inliers among *all* points
and a least-squares plane (smallest eigenvector of the inlier covariance, i.e. the SVD of the centred
inliers) is refitted to them, twice, so the result does not depend on the subsample.

The plate centre is the centroid of the inliers; it lies on the least-squares plane by construction.
The in-plane x axis is the scan's x axis projected onto the plane, so plate coordinates keep the
scanner's row/column orientation.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gls_calibration.common.validation import as_finite_array

MIN_PLATE_POINTS = 1000
"""Fewest finite points accepted: below this a 'dominant plane' means nothing."""

RANSAC_SUBSAMPLE = 100_000
"""Points handed to RANSAC; enough for a well-conditioned hypothesis, cheap on 4 M-point scans."""

LSQ_MAX_REFITS = 20
"""Most inlier selection + least-squares rounds on the full cloud after RANSAC.

The rounds stop when the inliers no longer change: the plane is then a function of the cloud alone,
not of the RANSAC hypothesis it started from (Open3D's RANSAC draws differently with the number of
OpenMP threads, which made repeated runs differ in the last digits).
"""


@dataclass(frozen=True)
class PlatePose:
    """Plane of the plate in the cloud's frame (mm).

    Parameters
    ----------
    normal : numpy.ndarray, shape (3,)
        Unit normal of the plate, pointing towards the head.
    centre : numpy.ndarray, shape (3,)
        A point of the plane, mm.
    rotation : numpy.ndarray, shape (3, 3)
        Maps plate coordinates to the cloud frame: its columns are the in-plane x axis, the in-plane
        y axis and ``normal``.
    flatness_rms_mm : float
        RMS distance of the inliers from the plane, mm.
    inlier_count : int
        Points within the fit's distance threshold.
    inlier_fraction : float
        Their fraction of the finite points.
    """

    normal: np.ndarray
    centre: np.ndarray
    rotation: np.ndarray
    flatness_rms_mm: float
    inlier_count: int
    inlier_fraction: float

    def to_plane(self, points) -> np.ndarray:
        """In-plane coordinates (..., 2) of points (..., 3) about the centre, normal offset dropped."""
        points = np.asarray(points, dtype=float)
        # Matrix-vector products per axis: a tall (N, 3) @ (3, 2) product can be very slow in OpenBLAS
        # on a busy machine, gemv is not.
        x_axis, y_axis = (np.ascontiguousarray(self.rotation[:, k]) for k in (0, 1))
        return np.stack([points @ x_axis - self.centre @ x_axis, points @ y_axis - self.centre @ y_axis],
                        axis=-1)

    def from_plane(self, uv) -> np.ndarray:
        """Points (..., 3) on the plane from in-plane coordinates (..., 2)."""
        uv = np.asarray(uv, dtype=float)
        return self.centre + uv[..., :1] * self.rotation[:, 0] + uv[..., 1:2] * self.rotation[:, 1]

    def distance(self, points) -> np.ndarray:
        """Signed distance (...) of points (..., 3) from the plane, positive towards the head."""
        points = np.asarray(points, dtype=float)
        return points @ self.normal - self.centre @ self.normal


def cloud_rows(points) -> np.ndarray:
    """View an (N, 3) or (H, W, 3) cloud as rows (M, 3); NaN rows stay (they fail every distance test)."""
    try:
        array = np.asarray(points, dtype=float)
    except (TypeError, ValueError) as error:
        raise ValueError(f"plate cloud must be numeric: {error}") from None
    if array.ndim not in (2, 3) or array.shape[-1] != 3:
        raise ValueError(f"plate cloud must have shape (N, 3) or (H, W, 3), got {array.shape}")
    return array.reshape(-1, 3)


def _least_squares_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Centroid, unit normal and RMS residual of the least-squares plane through points (N, 3)."""
    centroid = np.ones(len(points)) @ points / len(points)  # BLAS; several times faster than mean(axis=0)
    # The 3x3 covariance has the same eigenvectors as the SVD of the centred points, at a fraction of
    # the cost for millions of points; it is formed without materialising the centred copy.
    scatter = points.T @ points / len(points) - np.outer(centroid, centroid)
    values, vectors = np.linalg.eigh(scatter)
    return centroid, vectors[:, 0], float(np.sqrt(max(values[0], 0.0)))


def _in_plane_x_axis(normal: np.ndarray) -> np.ndarray:
    """Return the scan's x axis projected onto the plane (the y axis if the normal is along x)."""
    for axis in (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
        projected = axis - (axis @ normal) * normal
        length = np.linalg.norm(projected)
        if length > 1e-6:
            return projected / length
    raise AssertionError("unreachable: x and y cannot both be parallel to a unit normal")


def estimate_plate_pose(points, *, distance_threshold_mm: float = 0.2, head_direction=(0.0, 0.0, 1.0),
                        seed: int = 0, min_inlier_fraction: float = 0.5,
                        ransac_iterations: int = 1000) -> PlatePose:
    """Fit the plate plane to a scanner cloud: (N, 3) or organized (H, W, 3), NaNs allowed (dropped).

    The first call in a process imports Open3D (about 1 s of CPU; see ``benchmarks/bench_startup.py``).

    Parameters
    ----------
    points : array_like
        The cloud (mm), (N, 3) or organized (H, W, 3).
    distance_threshold_mm : float
        Half-width of the inlier band about the plane.
    head_direction : array_like
        Which side the head is on: the normal is turned towards it.
    seed : int
        Fixes the subsample and Open3D's RANSAC.
    min_inlier_fraction : float
        Share of the finite points that must lie in the band.
    ransac_iterations : int
        RANSAC iterations before the least-squares refit on the inliers.

    Returns
    -------
    PlatePose
        Normal, centre (the inliers' centroid), in-plane rotation, flatness RMS and inlier counts.

    Raises
    ------
    ValueError
        Too few finite points, a bad option, or too few points in the band.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> xy = rng.uniform(-50.0, 50.0, (2000, 2))
    >>> pose = estimate_plate_pose(np.column_stack([xy, 5.0 + 0.01 * xy[:, 0]]))
    >>> print(np.round(pose.normal, 4), pose.inlier_fraction)
    [-0.01  0.    1.  ] 1.0
    """
    if not np.isfinite(distance_threshold_mm) or distance_threshold_mm <= 0.0:
        raise ValueError(f"distance_threshold_mm must be positive, got {distance_threshold_mm!r}")
    if not 0.0 < min_inlier_fraction <= 1.0:
        raise ValueError(f"min_inlier_fraction must be in (0, 1], got {min_inlier_fraction!r}")
    head = as_finite_array(head_direction, "head_direction", ndim=1)
    if head.shape != (3,) or np.linalg.norm(head) == 0.0:
        raise ValueError(f"head_direction must be a non-zero 3-vector, got {head.tolist()}")

    # Rows are not compressed to the finite ones: on 4 M points the copy costs more than the fit, and
    # a NaN row simply fails every inlier test below.
    cloud = cloud_rows(points)
    finite = np.isfinite(cloud @ np.ones(3))
    finite_count = int(np.count_nonzero(finite))
    if finite_count < MIN_PLATE_POINTS:
        raise ValueError(
            f"plate cloud has {finite_count} finite points; at least {MIN_PLATE_POINTS} are needed")

    rng = np.random.default_rng(seed)
    if finite_count <= RANSAC_SUBSAMPLE:
        sample = cloud[finite]
    else:
        # Drawing with replacement is much faster than without and a repeat is harmless to RANSAC.
        sample = cloud[rng.integers(0, len(cloud), int(RANSAC_SUBSAMPLE * len(cloud) / finite_count))]
        sample = sample[np.isfinite(sample @ np.ones(3))]
    # Imported here, not with the module: Open3D loads its plotting stack too, which every process
    # that imports PlatePose would otherwise pay at start-up.
    import open3d as o3d
    o3d.utility.random.seed(int(rng.integers(2**31 - 1)))
    o3d_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sample))
    (a, b, c, d), _ = o3d_cloud.segment_plane(distance_threshold=distance_threshold_mm, ransac_n=3,
                                              num_iterations=ransac_iterations)
    normal = np.array([a, b, c]) / np.linalg.norm([a, b, c])
    centre = -d * normal / np.linalg.norm([a, b, c])

    flatness = float("nan")
    chosen = None
    for _ in range(LSQ_MAX_REFITS):
        mask = np.abs(cloud @ normal - centre @ normal) <= distance_threshold_mm
        if chosen is not None and np.array_equal(mask, chosen):
            break       # the same inliers fit the same plane
        chosen = mask
        inliers = cloud[mask]
        if len(inliers) < 3:
            break
        centre, normal, flatness = _least_squares_plane(inliers)

    fraction = len(inliers) / finite_count
    if fraction < min_inlier_fraction:
        raise ValueError(f"no dominant plane: best plane holds {100 * fraction:.1f} % of the points "
                         f"(minimum {100 * min_inlier_fraction:.0f} %)")

    if normal @ head < 0.0:
        normal = -normal
    x_axis = _in_plane_x_axis(normal)
    rotation = np.column_stack([x_axis, np.cross(normal, x_axis), normal])
    return PlatePose(normal=normal, centre=centre, rotation=rotation,
                     flatness_rms_mm=flatness,
                     inlier_count=int(len(inliers)), inlier_fraction=float(fraction))


def mean_plate_pose(poses: list[PlatePose]) -> PlatePose:
    """Return the average of poses of one plate measured in several sweeps.

    Each sweep's path is off by the robot's repeatability; averaging N sweeps divides that error
    of the plate height (and so of the field's scale, dr/r = dz/d) by sqrt(N).

    Parameters
    ----------
    poses : list of PlatePose
        The poses of one plate, in one frame.

    Returns
    -------
    PlatePose
        Mean normal (renormalised) and centre; mean flatness and inlier fraction, summed inlier count.

    Raises
    ------
    ValueError
        If ``poses`` is empty.
    """
    if not poses:
        raise ValueError("mean_plate_pose needs at least one pose")
    normal = np.mean([pose.normal for pose in poses], axis=0)
    normal /= np.linalg.norm(normal)
    centre = np.mean([pose.centre for pose in poses], axis=0)
    x_axis = _in_plane_x_axis(normal)
    rotation = np.column_stack([x_axis, np.cross(normal, x_axis), normal])
    return PlatePose(normal=normal, centre=centre, rotation=rotation,
                     flatness_rms_mm=float(np.mean([pose.flatness_rms_mm for pose in poses])),
                     inlier_count=int(sum(pose.inlier_count for pose in poses)),
                     inlier_fraction=float(np.mean([pose.inlier_fraction for pose in poses])))


MIN_HEIGHT_POINTS = 100
"""Fewest finite points of a stand-still acquisition that set the plate height."""


def pose_at_height(pose: PlatePose, points, *, distance_threshold_mm: float = 0.2) -> PlatePose:
    """Move ``pose`` along its normal so that its plane runs through ``points``.

    Profiles taken without travel cover one line of the plate: they fix the height well (thousands of
    points) but not the tilt across the line, which the sweeps' pose keeps. The height is the mean
    signed distance of the points within ``distance_threshold_mm`` of their median distance.

    Parameters
    ----------
    pose : PlatePose
        The pose whose tilt is kept.
    points : array_like, shape (N, 3) or (H, W, 3)
        Profiles taken standing still, in the pose's frame, mm; NaNs are dropped.
    distance_threshold_mm : float, default 0.2
        Points farther than this from the median distance are left out, mm; positive.

    Returns
    -------
    PlatePose
        ``pose`` with its centre moved along its normal.

    Raises
    ------
    ValueError
        If ``distance_threshold_mm`` is not positive or fewer than ``MIN_HEIGHT_POINTS`` points are finite.
    """
    if not np.isfinite(distance_threshold_mm) or distance_threshold_mm <= 0.0:
        raise ValueError(f"distance_threshold_mm must be positive, got {distance_threshold_mm!r}")
    cloud = cloud_rows(points)
    cloud = cloud[np.isfinite(cloud @ np.ones(3))]
    if len(cloud) < MIN_HEIGHT_POINTS:
        raise ValueError(f"the stand-still profiles hold {len(cloud)} finite points; at least "
                         f"{MIN_HEIGHT_POINTS} are needed for the plate height")
    distance = pose.distance(cloud)
    middle = float(np.median(distance))
    near = np.abs(distance - middle) <= distance_threshold_mm
    height = float(np.mean(distance[near]))
    return PlatePose(normal=pose.normal.copy(), centre=pose.centre + height * pose.normal,
                     rotation=pose.rotation.copy(), flatness_rms_mm=pose.flatness_rms_mm,
                     inlier_count=pose.inlier_count, inlier_fraction=pose.inlier_fraction)
