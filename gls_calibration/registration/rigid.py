"""Registration of measured fiducial centres onto the nominal targets, and the deviations.

The measured centres come in the scanner's frame; the targets in the ``gls`` frame. Both lie on a
plane. :func:`pair_with_targets` finds which measured point belongs to which target and the rigid
transform measured -> gls; :func:`deviations` turns the registered points into the error field
(its metrics: :func:`gls_calibration.calibration.outcome.deviation_metrics`).

In-plane rotation convention: each plane gets 2-D axes ``u`` = its frame's x axis projected onto
the plane, ``v = n x u`` (the convention of :class:`gls_calibration.scan.plate_pose.PlatePose`). The
``+-max_rotation_deg`` prior bounds the angle between the measured ``u`` carried into the target
plane and the target ``u``. This prior is what tells a square grid from its 90 deg turns.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from gls_calibration.common.validation import as_finite_array, as_non_negative_number, as_points, as_positive_number


_VOTERS = 400  # at most this many measured points take part in the coarse search


@dataclass(frozen=True)
class RigidTransform:
    """Proper rigid motion ``p -> rotation @ p + translation`` (mm).

    Parameters
    ----------
    rotation : array_like, shape (3, 3)
        Rotation matrix.
    translation : array_like, shape (3,)
        Translation, mm.

    Raises
    ------
    ValueError
        If either is not finite or has the wrong shape.
    """

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        """Validate the rotation (3, 3) and translation (3,) and store them as arrays."""
        rotation = as_finite_array(self.rotation, "rotation", ndim=2)
        translation = as_finite_array(self.translation, "translation", ndim=1)
        if rotation.shape != (3, 3):
            raise ValueError(f"rotation must have shape (3, 3), got {rotation.shape}")
        if translation.shape != (3,):
            raise ValueError(f"translation must have shape (3,), got {translation.shape}")
        object.__setattr__(self, "rotation", rotation)
        object.__setattr__(self, "translation", translation)

    @classmethod
    def identity(cls) -> "RigidTransform":
        """Return the transform that leaves every point in place."""
        return cls(np.eye(3), np.zeros(3))

    def apply(self, points) -> np.ndarray:
        """Transform (N, 3) points (or one (3,) point)."""
        array = np.asarray(points, dtype=float)
        return array @ self.rotation.T + self.translation

    def inverse(self) -> "RigidTransform":
        """Return the transform that undoes this one."""
        return RigidTransform(self.rotation.T, -self.rotation.T @ self.translation)

    def as_matrix(self) -> np.ndarray:
        """Homogeneous 4x4 matrix."""
        matrix = np.eye(4)
        matrix[:3, :3] = self.rotation
        matrix[:3, 3] = self.translation
        return matrix


def fit_rigid(source, target, weights=None) -> RigidTransform:
    """Least-squares rigid transform (no scale) taking ``source`` (N, 3) onto ``target`` (N, 3).

    Kabsch/Umeyama: SVD of the weighted cross-covariance, with the sign of the last singular
    direction chosen so that the rotation is proper (det = +1) even for coplanar points.
    """
    source = as_points(source, "source", 3, min_length=3)
    target = as_points(target, "target", 3, min_length=3)
    if source.shape[0] != target.shape[0]:
        raise ValueError(f"source and target must have the same number of points, "
                         f"got {source.shape[0]} and {target.shape[0]}")
    if weights is None:
        weights = np.ones(source.shape[0])
    else:
        weights = as_finite_array(weights, "weights", ndim=1)
        if weights.shape[0] != source.shape[0]:
            raise ValueError(f"weights must have one value per point ({source.shape[0]}), got {weights.shape[0]}")
        if np.any(weights < 0.0) or weights.sum() <= 0.0:
            raise ValueError("weights must be non-negative with a positive sum")
    weights = weights / weights.sum()
    source_centre = weights @ source
    target_centre = weights @ target
    covariance = (target - target_centre).T @ ((source - source_centre) * weights[:, None])
    left, _, right_t = np.linalg.svd(covariance)
    sign = np.ones(3)
    sign[2] = np.sign(np.linalg.det(left @ right_t)) or 1.0
    rotation = (left * sign) @ right_t
    return RigidTransform(rotation, target_centre - rotation @ source_centre)


@dataclass(frozen=True)
class RigidAlignment2D:
    """In-plane rigid motion ``target = R(rotation_rad) @ source + translation_mm`` (no scale).

    Parameters
    ----------
    rotation_rad : float
        Rotation angle, rad (counter-clockwise).
    translation_mm : tuple of 2 float
        Translation, mm.
    """

    rotation_rad: float
    translation_mm: tuple[float, float]

    def apply(self, points_xy) -> np.ndarray:
        """Map (N, 2) points of the source frame into the target frame."""
        points = np.asarray(points_xy, dtype=float)
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        return points @ np.array([[c, s], [-s, c]]) + np.asarray(self.translation_mm)


def align_rigid_2d(source_xy: np.ndarray, target_xy: np.ndarray) -> tuple[RigidAlignment2D, np.ndarray]:
    """Least-squares rotation + translation (no scale) of ``source`` (N, 2) onto ``target``; it and ``source`` moved.

    The one 2-D rigid alignment of the package. Closed-form 2-D Kabsch: the optimal angle is atan2
    of the summed cross and dot products of the centred point sets (no SVD: it runs inside every
    residual evaluation of the discrepancy fits).

    Parameters
    ----------
    source_xy, target_xy : ndarray
        Paired points (N, 2), mm.

    Returns
    -------
    alignment : RigidAlignment2D
        Rotation (rad) and translation (mm) that take ``source_xy`` onto ``target_xy``.
    moved : ndarray
        ``source_xy`` moved by it (N, 2).

    Examples
    --------
    >>> source = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    >>> target = source @ np.array([[0.0, 1.0], [-1.0, 0.0]]) + [1.0, 2.0]
    >>> alignment, moved = align_rigid_2d(source, target)
    >>> print(round(alignment.rotation_rad, 6), np.allclose(moved, target))
    1.570796 True
    """
    source_xy = np.asarray(source_xy, dtype=float)
    target_xy = np.asarray(target_xy, dtype=float)
    source_mean = source_xy.mean(axis=0)
    target_mean = target_xy.mean(axis=0)
    s = source_xy - source_mean
    d = target_xy - target_mean
    angle = math.atan2(float(np.sum(s[:, 0] * d[:, 1] - s[:, 1] * d[:, 0])),
                       float(np.sum(s[:, 0] * d[:, 0] + s[:, 1] * d[:, 1])))
    c, sn = math.cos(angle), math.sin(angle)
    moved = np.empty_like(s)
    moved[:, 0] = c * s[:, 0] - sn * s[:, 1] + target_mean[0]
    moved[:, 1] = sn * s[:, 0] + c * s[:, 1] + target_mean[1]
    translation = target_mean - np.array([c * source_mean[0] - sn * source_mean[1],
                                          sn * source_mean[0] + c * source_mean[1]])
    return RigidAlignment2D(angle, (float(translation[0]), float(translation[1]))), moved


@dataclass(frozen=True)
class Pairing:
    """Result of :func:`pair_with_targets`.

    ``target_index[i]`` is paired with ``measured_index[i]`` (sorted by target). ``extra_measured``
    lists every measured point left unpaired, including ``duplicate_measured``: points that were
    the second (or later) candidate for an already paired target. ``rms_mm`` is the RMS 3-D distance
    of the pairs after ``transform`` (measured -> gls); ``gate_mm`` the pairing gate used.
    """

    target_index: np.ndarray
    measured_index: np.ndarray
    transform: RigidTransform
    missing_targets: np.ndarray
    extra_measured: np.ndarray
    duplicate_measured: np.ndarray
    rms_mm: float
    gate_mm: float


@dataclass(frozen=True)
class _PlaneFrame:
    centre: np.ndarray   # (3,)
    axes: np.ndarray     # (3, 3): rows u, v, n (right-handed)

    def to_plane(self, points: np.ndarray) -> np.ndarray:
        return (points - self.centre) @ self.axes[:2].T


def _plane_normal(points: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    centre = points.mean(axis=0)
    _, singular, right_t = np.linalg.svd(points - centre, full_matrices=False)
    if singular.size < 2 or singular[1] <= 1e-9 * max(singular[0], 1.0):
        raise ValueError(f"{name} are collinear; a plane cannot be fitted")
    return centre, right_t[2]


def _plane_frame(centre: np.ndarray, normal: np.ndarray) -> _PlaneFrame:
    # u = the frame's x axis projected on the plane; y axis if x is (nearly) along the normal.
    for axis in np.eye(3)[:2]:
        projected = axis - (axis @ normal) * normal
        length = np.linalg.norm(projected)
        if length > 0.3:
            u = projected / length
            return _PlaneFrame(centre, np.vstack([u, np.cross(normal, u), normal]))
    raise AssertionError("unreachable: x and y cannot both be along the normal")


def grid_pitch(targets_xy: np.ndarray) -> float:
    """Median nearest-neighbour spacing of the targets (mm)."""
    distances, _ = cKDTree(targets_xy).query(targets_xy, k=2)
    pitch = float(np.median(distances[:, 1]))
    if pitch <= 0.0:
        raise ValueError("targets contain coincident points; the grid pitch is zero")
    return pitch


class _TranslationVote:
    """2-D histogram of target-minus-measured differences; its peak is the translation most points agree on.

    Measured points are given relative to the origin of their plane coordinates, so rotating them
    keeps every difference inside a box fixed in advance (cells of one gate).
    """

    def __init__(self, target_2d: np.ndarray, measured_radius: float, gate: float) -> None:
        self.target_2d = target_2d
        self.gate = gate
        self.low = target_2d.min(axis=0) - measured_radius - gate
        self.shape = ((np.ptp(target_2d, axis=0) + 2.0 * measured_radius + 2.0 * gate) / gate).astype(np.int64) + 2

    def _cells(self, measured_2d: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
        """Every target-minus-measured difference along ``axis`` (N, K) and the cell it falls in."""
        differences = np.subtract.outer(self.target_2d[:, axis], measured_2d[:, axis])
        # one axis at a time and in place: 62 votes per pairing, and interleaved (N*K, 2) arrays
        # with their temporaries took 9x as long
        scaled = differences - self.low[axis]
        scaled *= 1.0 / self.gate
        return differences, scaled.astype(np.int64)

    def votes(self, measured_2d: np.ndarray) -> tuple[int, tuple[int, int]]:
        """Most differences in any 2x2-cell box (a cluster split by a cell edge still counts whole)."""
        index = self._cells(measured_2d, 0)[1]
        index *= self.shape[1]
        index += self._cells(measured_2d, 1)[1]
        counts = np.bincount(index.ravel(), minlength=self.shape[0] * self.shape[1]).reshape(self.shape)
        boxes = counts[:-1, :-1] + counts[1:, :-1] + counts[:-1, 1:] + counts[1:, 1:]
        best = np.unravel_index(int(np.argmax(boxes)), boxes.shape)
        return int(boxes[best]), (int(best[0]), int(best[1]))

    def shift(self, measured_2d: np.ndarray, box: tuple[int, int]) -> np.ndarray:
        """Median difference inside the winning box."""
        (along_x, cells_x), (along_y, cells_y) = self._cells(measured_2d, 0), self._cells(measured_2d, 1)
        inside = (cells_x >= box[0]) & (cells_x <= box[0] + 1) & (cells_y >= box[1]) & (cells_y <= box[1] + 1)
        return np.median(np.column_stack([along_x[inside], along_y[inside]]), axis=0)


def _voters(measured_2d: np.ndarray, count: int) -> np.ndarray:
    """At most ``count`` measured points, spread over the whole set (every k-th one).

    The whole extent matters: near the boundary a translation one grid pitch off loses votes,
    which is what singles out the right one.
    """
    stride = max(1, math.ceil(measured_2d.shape[0] / count))
    return measured_2d[::stride]


def _rotation_2d(angle: float) -> np.ndarray:
    cosine, sine = math.cos(angle), math.sin(angle)
    return np.array([[cosine, -sine], [sine, cosine]])


def _match(moved: np.ndarray, tree: cKDTree, gate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest target within the gate for each moved point; a target keeps only its closest point.

    Returns (target_index, measured_index, duplicate_measured), pairs sorted by target.
    """
    distance, nearest = tree.query(moved, k=1, distance_upper_bound=gate)
    candidates = np.flatnonzero(np.isfinite(distance))
    order = candidates[np.lexsort((distance[candidates], nearest[candidates]))]
    first = np.ones(order.size, dtype=bool)
    first[1:] = nearest[order[1:]] != nearest[order[:-1]]
    kept = order[first]
    return nearest[kept], kept, np.sort(order[~first])


def _register(measured: np.ndarray, targets: np.ndarray, target_tree: cKDTree,
              target_frame: _PlaneFrame, measured_frame: _PlaneFrame,
              max_rotation: float, gate: float, step: float, max_iterations: int):
    """Coarse in-plane search then gated ICP for one orientation of the measured plane."""
    target_2d = target_frame.to_plane(targets)
    measured_2d = measured_frame.to_plane(measured)
    voters = _voters(measured_2d, _VOTERS)
    vote = _TranslationVote(target_2d, float(np.max(np.linalg.norm(voters, axis=1))), gate)
    best_votes, best_angle, best_box = -1, 0.0, (0, 0)
    for angle in np.arange(-max_rotation, max_rotation + 0.5 * step, step):
        votes, box = vote.votes(voters @ _rotation_2d(angle).T)
        if votes > best_votes:
            best_votes, best_angle, best_box = votes, angle, box
    best_shift = vote.shift(voters @ _rotation_2d(best_angle).T, best_box)
    # Lift the 2-D solution to 3-D: measured plane axes -> rotated -> target plane axes.
    in_plane = np.eye(3)
    in_plane[:2, :2] = _rotation_2d(best_angle)
    rotation = target_frame.axes.T @ in_plane @ measured_frame.axes
    translation = (target_frame.centre + target_frame.axes[:2].T @ best_shift) - rotation @ measured_frame.centre
    transform = RigidTransform(rotation, translation)

    previous = None
    for _ in range(max_iterations):
        target_index, measured_index, duplicates = _match(transform.apply(measured), target_tree, gate)
        if target_index.size < 3:
            break
        key = (target_index.tobytes(), measured_index.tobytes())
        if key == previous:
            break
        previous = key
        transform = fit_rigid(measured[measured_index], targets[target_index])
    target_index, measured_index, duplicates = _match(transform.apply(measured), target_tree, gate)
    if target_index.size >= 3:
        residual = transform.apply(measured[measured_index]) - targets[target_index]
        rms = float(np.sqrt(np.mean(np.sum(residual ** 2, axis=1))))
    else:
        rms = math.inf
    return target_index, measured_index, duplicates, transform, rms


def pair_with_targets(measured, targets, *, max_rotation_deg: float = 15.0, gate_mm: Optional[float] = None,
                      measured_normal=None, angle_step_deg: float = 1.0,
                      max_iterations: int = 30) -> Pairing:
    """Pair measured centres (K, 3, scanner frame) with targets (N, 3, gls frame) and register them.

    Both sets are planar. Each gets plane axes (see the module docstring); the in-plane rotation
    is searched over ``+-max_rotation_deg`` in ``angle_step_deg`` steps (half of 1 deg moves a
    point 134 mm from the centre by 1.2 mm, well inside the default gate), the translation for each
    angle by voting over all target-minus-measured differences; the best start is refined by
    gated ICP (nearest target within ``gate_mm`` by cKDTree, Kabsch fit, until the pairing stops
    changing).

    The side of the measured plane facing the head is unknown from the points alone. When
    ``measured_normal`` is given it decides; otherwise both sides are tried and the one with more
    pairs wins, a tie (a grid with a mirror symmetry cannot tell) going to the side whose normal has
    a non-negative z component, the convention of ``estimate_plate_pose(head_direction=(0, 0, 1))``.

    Parameters
    ----------
    measured : array_like, shape (K, 3)
        Measured centres, scanner frame, mm; at least 3.
    targets : array_like, shape (N, 3)
        Targets, gls frame, mm; at least 3.
    max_rotation_deg : float, default 15.0
        Largest in-plane rotation searched, degrees; non-negative.
    gate_mm : float, optional
        Pairing gate, mm; defaults to 0.4 x the grid pitch (median nearest-neighbour spacing).
    measured_normal : array_like, shape (3,), optional
        A direction in the measured frame pointing towards the head.
    angle_step_deg : float, default 1.0
        Step of the rotation search, degrees; positive.
    max_iterations : int, default 30
        Most ICP iterations.

    Returns
    -------
    Pairing
        Paired indices (sorted by target), the transform measured -> gls, the missing targets, the
        extra and duplicate measured points, the RMS distance of the pairs and the gate used.

    Raises
    ------
    ValueError
        If either set is not (M, 3) finite with at least 3 points or is collinear, the targets hold
        coincident points, a number is out of range, or ``measured_normal`` is not a non-zero 3-vector.

    Examples
    --------
    A 5 x 5 grid measured turned by 3 deg and shifted, its last two fiducials not found:

    >>> from gls_calibration.fiducials.targets import grid_targets
    >>> targets = np.column_stack([grid_targets(5, 40.0), np.zeros(25)])
    >>> angle = np.radians(3.0)
    >>> turn = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    >>> measured = (targets[:-2] - [1.0, 2.0, 0.0]) @ turn.T
    >>> pairing = pair_with_targets(measured, targets)
    >>> len(pairing.target_index), pairing.missing_targets.tolist(), pairing.transform.translation.round(6).tolist()
    (23, [23, 24], [1.0, 2.0, 0.0])
    """
    measured = as_points(measured, "measured", 3, min_length=3)
    targets = as_points(targets, "targets", 3, min_length=3)
    max_rotation = math.radians(as_non_negative_number(max_rotation_deg, "max_rotation_deg"))
    step = math.radians(as_positive_number(angle_step_deg, "angle_step_deg"))
    target_centre, target_normal = _plane_normal(targets, "targets")
    if target_normal[2] < 0.0:  # gls z points towards the head
        target_normal = -target_normal
    target_frame = _plane_frame(target_centre, target_normal)
    gate = (0.4 * grid_pitch(target_frame.to_plane(targets)) if gate_mm is None
            else as_positive_number(gate_mm, "gate_mm"))

    measured_centre, normal = _plane_normal(measured, "measured")
    if measured_normal is not None:
        hint = as_finite_array(measured_normal, "measured_normal", ndim=1)
        if hint.shape != (3,) or not np.any(hint):
            raise ValueError(f"measured_normal must be a non-zero 3-vector, got {hint!r}")
        sides = [normal if hint @ normal >= 0.0 else -normal]
    else:
        preferred = normal if normal[2] >= 0.0 else -normal
        sides = [preferred, -preferred]

    tree = cKDTree(targets)
    best = None
    most_pairs = min(measured.shape[0], targets.shape[0])
    for side in sides:
        if best is not None and best[0].size == most_pairs:
            break       # every point paired: the other side cannot pair more, and a tie keeps the first
        result = _register(measured, targets, tree, target_frame, _plane_frame(measured_centre, side),
                           max_rotation, gate, step, max_iterations)
        if best is None or result[0].size > best[0].size:
            best = result
    target_index, measured_index, duplicates, transform, rms = best
    missing = np.setdiff1d(np.arange(targets.shape[0]), target_index)
    extra = np.setdiff1d(np.arange(measured.shape[0]), measured_index)
    return Pairing(target_index, measured_index, transform, missing, extra, duplicates, rms, gate)


def deviations(targets, measured_in_gls) -> np.ndarray:
    """Deviation field ``delta = Q - P``: target minus where the mark landed (same shape, mm)."""
    targets = as_finite_array(targets, "targets", ndim=2)
    measured_in_gls = as_finite_array(measured_in_gls, "measured_in_gls", ndim=2)
    if targets.shape != measured_in_gls.shape:
        raise ValueError(f"targets and measured_in_gls must have the same shape, "
                         f"got {targets.shape} and {measured_in_gls.shape}")
    return targets - measured_in_gls
