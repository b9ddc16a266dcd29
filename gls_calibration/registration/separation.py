"""Error separation over repeated sweeps of one marked plate (reversal and redundancy).

Reversal and redundancy as in CMM self-calibration.

Each sweep measures the same fiducials in its own scanner frame: x along the laser line (lateral),
y along the travel. Between sweeps the plate stays put while the sensor is swept in the opposite
direction or turned (0 / 90 deg about its axis), so what is fixed to the scanner frame changes axis
or sign relative to the marks, and what is random changes from sweep to sweep. The model of a
centre i measured in sweep k (sweep frame, mm):

    p_ki = R_k m_i + t_k + (L(p_x), 0) + (W_k(p_y), S_k(p_y)) + noise

- ``m_i``: the true centre in the reference frame (sweep 0's frame, rid of its own errors);
- ``R_k, t_k``: the rigid placement of sweep k (sweep 0 defines the frame);
- ``L``: the scanner's lateral linearity shape, the same in every sweep. Its constant part is a
  placement. One scale must be trusted, since a scale of every measurement cannot be told from a
  scale of the plate (the gauge): with ``scale_from="line"`` (profiles placed by time) the
  sensor's lateral scale, so L has no linear part; with ``"travel"`` (profiles placed by the robot's
  reported pose) the travel, so S_k has no linear part and the lateral scale is estimated;
- ``W_k, S_k``: the motion of sweep k along its travel -- path wander across, and placement error
  along (speed scale and ripple when profiles are placed by time). Drawn anew each sweep. Their
  constant parts are the placement (W_k's linear part is a shear: the path not parallel to the
  line's normal; a rotation also moves the other axis).

``L``, ``W_k`` and ``S_k`` are piecewise-linear in knot values (hat functions). Knot values carry
a weak ridge (``*_prior_sigma_mm``): a shape the sweeps cannot see (one orientation only, say) stays
zero and the marks keep the plain average, so the separation never does worse than averaging.
The fit is a weighted linear least-squares problem in the marks, the placements' small increments
and the shapes (a few Gauss-Newton passes for the rotations). The per-centre uncertainty combines
the ring-fit sigma of each measurement with the spread of the repeated sweeps about the fit.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Optional, Sequence

import numpy as np
from scipy import linalg, sparse

from gls_calibration.common.validation import as_integer_at_least, as_positive_number
from gls_calibration.registration.rigid import align_rigid_2d

SIGMA_FLOOR_MM = 0.001
"""Smallest per-centre sigma used as a weight: a ring fit never knows a centre better than 1 um."""

SCALE_REFERENCES = ("travel", "line")
"""What sets the scale: the sensor's lateral scale, or the travel as the robot's encoders report it."""

SPREAD_PRIOR_DOF = 4.0
"""Degrees of freedom of the pooled spread that each centre's own few-sweep spread is shrunk towards."""


@dataclass(frozen=True)
class SeparationSettings:
    """Knot spacings of the shapes (mm), the ridge on them (mm), Gauss-Newton passes.

    The defaults suit profiles placed by the robot's reported pose (travel trusted, little along-track
    error left); :data:`TIME_PLACED` suits profiles placed by time at an assumed speed.

    Parameters
    ----------
    lateral_knot_spacing_mm : float, default 15.0
        Knot spacing of the scanner's lateral error shape, mm.
    motion_knot_spacing_mm : float, default 10.0
        Knot spacing of each sweep's motion error shape, mm.
    lateral_prior_sigma_mm : float, default 0.5
        Prior std of the lateral shape, mm.
    across_prior_sigma_mm : float, default 0.05
        Prior std of the path wander across the travel, per sweep, mm.
    along_prior_sigma_mm : float, default 0.002
        Prior std of the placement along the travel, per sweep, mm (small with a pose stream).
    default_sigma_mm : float, default 0.005
        Sigma of a centre without a ring-fit sigma, mm.
    passes : int, default 3
        Gauss-Newton passes; at least 1.
    scale_from : str, default "travel"
        ``"travel"``: trust the pose stream's travel; ``"line"``: the sensor's lateral scale.

    Raises
    ------
    ValueError
        On the first field that is not positive, or an unknown ``scale_from``.
    """

    lateral_knot_spacing_mm: float = 15.0
    motion_knot_spacing_mm: float = 10.0
    lateral_prior_sigma_mm: float = 0.5
    across_prior_sigma_mm: float = 0.05   # path wander across the travel, per sweep
    along_prior_sigma_mm: float = 0.002   # placement along the travel, per sweep: small with a pose stream
    default_sigma_mm: float = 0.005      # a centre without a ring-fit sigma
    passes: int = 3
    scale_from: str = "travel"           # "travel": trust the pose stream's travel; "line": the sensor's lateral scale

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        for name in ("lateral_knot_spacing_mm", "motion_knot_spacing_mm", "lateral_prior_sigma_mm",
                     "across_prior_sigma_mm", "along_prior_sigma_mm", "default_sigma_mm"):
            as_positive_number(getattr(self, name), f"separation {name}")
        as_integer_at_least(self.passes, "separation passes", 1)
        if self.scale_from not in SCALE_REFERENCES:
            raise ValueError(f"separation scale_from must be one of {', '.join(SCALE_REFERENCES)}, "
                             f"got {self.scale_from!r}")


@dataclass(frozen=True)
class Shape:
    """A piecewise-linear error shape: values (mm) at knots (mm) of one sweep-frame coordinate."""

    knots_mm: np.ndarray
    values_mm: np.ndarray

    def __call__(self, coordinate_mm) -> np.ndarray:
        """Return the error at ``coordinate_mm`` along the travel, mm (linear between knots)."""
        return np.interp(np.asarray(coordinate_mm, dtype=float), self.knots_mm, self.values_mm)


@dataclass(frozen=True)
class Separation:
    """Centres rid of scanner-frame and motion errors, with what was removed (mm).

    ``centres_mm`` (N, 2) are in sweep 0's frame; ``sigma_mm`` (N,) is the combined standard
    uncertainty per axis of each centre (the larger of ``ring_sigma_mm``, from the ring fits, and
    ``spread_sigma_mm``, from the scatter of the sweeps about the fit; NaN where seen once).
    ``sweeps_seen`` (N,) counts the sweeps that found each fiducial. ``placements`` (K, 3) hold
    each sweep's rotation (rad) and translation (mm) from the reference frame. ``lateral`` is the
    scanner's lateral linearity shape; ``motion_across``/``motion_along`` one shape per sweep.
    ``scanner_rms_mm`` and ``motion_rms_mm`` are the RMS of the removed errors over all
    measurements, ``residual_rms_mm`` the RMS of what the model leaves.
    """

    centres_mm: np.ndarray
    sigma_mm: np.ndarray
    ring_sigma_mm: np.ndarray
    spread_sigma_mm: np.ndarray
    sweeps_seen: np.ndarray
    placements: np.ndarray
    lateral: Shape
    motion_across: tuple[Shape, ...]
    motion_along: tuple[Shape, ...]
    scanner_rms_mm: float
    motion_rms_mm: float
    residual_rms_mm: float


TIME_PLACED = SeparationSettings(scale_from="line", along_prior_sigma_mm=0.05)
"""Profiles placed by time: speed scale and ripple per sweep, the sensor's lateral scale trusted.

A shape common to every sweep's along-track error cannot be told from the lateral linearity (both
move the marks by a separable c(x), c(y)); the prior then decides, so repeated noise leaks into that
pattern more than with a pose stream (measured in test_separation.py).
"""


def _rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def _knots(values: np.ndarray, spacing: float) -> np.ndarray:
    low, high = float(values.min()), float(values.max())
    count = max(3, int(math.ceil((high - low) / spacing)) + 1)
    return np.linspace(low - 1e-6, high + 1e-6, count)


def _hats(coordinate: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """(n, len(knots)) linear-interpolation weights of ``coordinate`` on ``knots``."""
    index = np.clip(np.searchsorted(knots, coordinate) - 1, 0, len(knots) - 2)
    fraction = np.clip((coordinate - knots[index]) / (knots[index + 1] - knots[index]), 0.0, 1.0)
    basis = np.zeros((coordinate.size, knots.size))
    rows = np.arange(coordinate.size)
    basis[rows, index] = 1.0 - fraction
    basis[rows, index + 1] = fraction
    return basis


def _without(knots: np.ndarray, degree: int) -> np.ndarray:
    """Orthonormal basis of knot values with no polynomial part up to ``degree`` (0: constant, 1: line)."""
    excluded = np.vander(knots - knots.mean(), degree + 1, increasing=True)
    left, _, _ = np.linalg.svd(excluded, full_matrices=True)
    return left[:, degree + 1:]


def _checked_sweeps(centres: Sequence, sigmas: Optional[Sequence], default_sigma: float):
    if len(centres) < 1:
        raise ValueError("error separation needs at least one sweep")
    points = []
    for k, sweep in enumerate(centres):
        array = np.asarray(sweep, dtype=float)
        if array.ndim != 2 or array.shape[1] != 2:
            raise ValueError(f"sweep {k} centres must have shape (N, 2), got {array.shape}")
        if np.any(np.isinf(array)):
            raise ValueError(f"sweep {k} centres contain infinite values (NaN marks a fiducial not found)")
        points.append(array)
    count = points[0].shape[0]
    if any(array.shape[0] != count for array in points):
        raise ValueError("every sweep must list the same fiducials (one row each, NaN where not found)")
    stacked = np.stack(points)                                    # (K, N, 2)
    if sigmas is None:
        sigma = np.full(stacked.shape[:2], default_sigma)
    else:
        if len(sigmas) != len(points):
            raise ValueError(f"sigmas must hold one array per sweep ({len(points)}), got {len(sigmas)}")
        sigma = np.stack([np.broadcast_to(np.asarray(s, dtype=float), (count,)) for s in sigmas])
        finite = np.isfinite(sigma)
        if np.any(sigma[finite] < 0.0):
            raise ValueError("sigmas must be non-negative")
        sigma = np.where(finite, sigma, default_sigma)
    valid = np.all(np.isfinite(stacked), axis=2)
    if not valid[0].any() or valid[0].sum() < 3:
        raise ValueError("the reference sweep (sweep 0) must have found at least 3 fiducials")
    return stacked, np.maximum(sigma, SIGMA_FLOOR_MM), valid


def separate(centres: Sequence, sigmas: Optional[Sequence] = None,
             settings: SeparationSettings = SeparationSettings()) -> Separation:
    """Separate scanner-frame and motion errors from the marks over repeated sweeps.

    ``centres``: one (N, 2) array per sweep, the centres measured in that sweep's frame (x along
    the line, y along the travel, mm), row i the same fiducial in every sweep, NaN where not found.
    ``sigmas``: one (N,) array per sweep of ring-fit standard uncertainties (mm), or None.
    """
    points, sigma, valid = _checked_sweeps(centres, sigmas, settings.default_sigma_mm)
    sweeps, count = valid.shape
    placements = np.zeros((sweeps, 3))
    for k in range(1, sweeps):
        both = valid[0] & valid[k]
        if both.sum() < 3:
            raise ValueError(f"sweep {k} shares fewer than 3 fiducials with sweep 0")
        rigid, _ = align_rigid_2d(points[0][both], points[k][both])
        placements[k] = (rigid.rotation_rad, *rigid.translation_mm)
    seen = valid.sum(axis=0)
    marks = np.full((count, 2), np.nan)
    sweep_of, mark_of = np.nonzero(valid)
    observed = points[sweep_of, mark_of]                          # (n, 2) sweep-frame positions
    weight = 1.0 / sigma[sweep_of, mark_of]

    # shapes: lateral without constant and line (placement, gauge); motion across and along
    # without constant (the placement); a line across is a shear of the path, not a rotation
    lateral_knots = _knots(observed[:, 0], settings.lateral_knot_spacing_mm)
    trust_line = settings.scale_from == "line"
    lateral_free = _without(lateral_knots, 1 if trust_line else 0)
    if not np.any(np.abs(np.sin(placements[:, 0])) > 0.5):
        # every sweep sees the marks along the same line axis: the lateral shape is the marks' own
        # shape to these sweeps (not observable), so it is not estimated
        lateral_free = lateral_free[:, :0]
    lateral_basis = _hats(observed[:, 0], lateral_knots) @ lateral_free
    motion_knots, motion_blocks = [], []
    for k in range(sweeps):
        mine = sweep_of == k
        knots = _knots(observed[mine, 1], settings.motion_knot_spacing_mm)
        hats = _hats(observed[mine, 1], knots)
        motion_knots.append(knots)
        along_free = _without(knots, 0 if trust_line else 1)
        motion_blocks.append((mine, hats @ _without(knots, 0), hats @ along_free, _without(knots, 0), along_free))

    seen_index = np.flatnonzero(seen > 0)
    column_of_mark = -np.ones(count, dtype=int)
    column_of_mark[seen_index] = np.arange(seen_index.size)
    n_marks = 2 * seen_index.size
    n_place = 3 * (sweeps - 1)
    n_lateral = lateral_free.shape[1]
    motion_sizes = [(block[1].shape[1], block[2].shape[1]) for block in motion_blocks]
    n_motion = sum(a + b for a, b in motion_sizes)
    unknowns = n_marks + n_place + n_lateral + n_motion
    rows = observed.shape[0]
    # the prior on the shapes: a common shape of every sweep's motion cannot be told from a lateral
    # linearity shape (both shift the marks by a separable c(x), c(y)); a looser prior on the
    # lateral shape puts such a common part there, where the sensor's fixed error belongs
    ridge = [np.full(n_lateral, settings.lateral_prior_sigma_mm ** -2)]
    for n_across, n_along in motion_sizes:
        ridge += [np.full(n_across, settings.across_prior_sigma_mm ** -2),
                  np.full(n_along, settings.along_prior_sigma_mm ** -2)]
    ridge = np.concatenate(ridge)

    reference = None
    for _ in range(settings.passes):
        rotations = np.stack([_rotation(angle) for angle in placements[:, 0]])   # (K, 2, 2)
        back = np.transpose(rotations[sweep_of], (0, 2, 1))                       # R_k^T per row
        aligned = np.einsum("nij,nj->ni", back, observed - placements[sweep_of, 1:])
        if reference is None:
            reference = _weighted_mean(aligned, weight, mark_of, count)
        # the design's columns after the marks' (placements, shapes); a row's one mark column is built
        # straight into the sparse matrix below
        design = np.zeros((2 * rows, unknowns - n_marks))
        x_rows, y_rows = np.arange(0, 2 * rows, 2), np.arange(1, 2 * rows, 2)
        moving = sweep_of > 0
        base = 3 * (sweep_of[moving] - 1)
        start = reference[mark_of[moving]]
        # R(d) m ~ m + d J m: J m = (-m_y, m_x)
        design[x_rows[moving], base] = -start[:, 1]
        design[y_rows[moving], base] = start[:, 0]
        design[x_rows[moving], base + 1] = 1.0
        design[y_rows[moving], base + 2] = 1.0
        # an error along sweep axis a shows in the reference frame as column a of R_k^T
        column = n_place
        design[x_rows, column:column + n_lateral] = back[:, 0, 0, None] * lateral_basis
        design[y_rows, column:column + n_lateral] = back[:, 1, 0, None] * lateral_basis
        column += n_lateral
        for (mine, across, along, _, _), (n_across, n_along) in zip(motion_blocks, motion_sizes):
            where = np.flatnonzero(mine)
            design[x_rows[where], column:column + n_across] = back[mine, 0, 0, None] * across
            design[y_rows[where], column:column + n_across] = back[mine, 1, 0, None] * across
            column += n_across
            design[x_rows[where], column:column + n_along] = back[mine, 0, 1, None] * along
            design[y_rows[where], column:column + n_along] = back[mine, 1, 1, None] * along
            column += n_along
        row_weight = np.repeat(weight, 2)
        mark_column = np.empty(2 * rows, dtype=np.int64)
        mark_column[x_rows] = 2 * column_of_mark[mark_of]
        mark_column[y_rows] = 2 * column_of_mark[mark_of] + 1
        weighted = _weighted_design(mark_column, design, row_weight, unknowns)
        normal = (weighted.T @ weighted).toarray()
        shapes_at = np.arange(n_marks + n_place, unknowns)
        normal[shapes_at, shapes_at] += ridge
        solution = linalg.solve(normal, weighted.T @ (aligned.reshape(-1) * row_weight), assume_a="pos")

        marks[seen_index] = solution[:n_marks].reshape(-1, 2)
        increments = solution[n_marks:n_marks + n_place].reshape(-1, 3)
        for k in range(1, sweeps):
            angle, shift = increments[k - 1, 0], increments[k - 1, 1:]
            placements[k, 1:] += rotations[k] @ shift
            placements[k, 0] += angle
        reference = marks
    shapes = solution[n_marks + n_place:]
    lateral = Shape(lateral_knots, lateral_free @ shapes[:n_lateral])
    across_shapes, along_shapes = [], []
    offset = n_lateral
    for knots, (_, _, _, across_free, along_free), (n_across, n_along) in zip(motion_knots, motion_blocks,
                                                                              motion_sizes):
        across_shapes.append(Shape(knots, across_free @ shapes[offset:offset + n_across]))
        offset += n_across
        along_shapes.append(Shape(knots, along_free @ shapes[offset:offset + n_along]))
        offset += n_along

    scanner_error = np.column_stack([lateral(observed[:, 0]), np.zeros(rows)])
    motion_error = np.zeros((rows, 2))
    for k in range(sweeps):
        mine = sweep_of == k
        motion_error[mine, 0] = across_shapes[k](observed[mine, 1])
        motion_error[mine, 1] = along_shapes[k](observed[mine, 1])
    rotations = np.stack([_rotation(angle) for angle in placements[:, 0]])
    predicted = (np.einsum("nij,nj->ni", rotations[sweep_of], marks[mark_of]) + placements[sweep_of, 1:]
                 + scanner_error + motion_error)
    residual = observed - predicted
    ring_sigma, spread_sigma = _uncertainties(residual, sigma[sweep_of, mark_of], mark_of, count, seen)
    combined = np.fmax(ring_sigma, spread_sigma)
    return Separation(
        centres_mm=marks, sigma_mm=combined, ring_sigma_mm=ring_sigma, spread_sigma_mm=spread_sigma,
        sweeps_seen=seen, placements=placements, lateral=lateral, motion_across=tuple(across_shapes),
        motion_along=tuple(along_shapes), scanner_rms_mm=_rms(scanner_error), motion_rms_mm=_rms(motion_error),
        residual_rms_mm=_rms(residual))


def _weighted_design(mark_column: np.ndarray, rest: np.ndarray, row_weight: np.ndarray,
                     unknowns: int) -> sparse.csr_matrix:
    """Return the row-weighted design as a CSR matrix, the one ``csr_matrix`` makes of the dense design.

    Each row holds a 1 in its mark's column (``mark_column``, all before the others) and ``rest`` in
    the columns after the marks. The same entries, in the same order, without the dense design of
    every mark's column (99 % zeros) and the search of it for its nonzeros.
    """
    rows, n_marks = rest.shape[0], unknowns - rest.shape[1]
    rest = rest * row_weight[:, None]
    rest_rows, rest_columns = np.nonzero(rest)         # row-major: within a row, by column
    indptr = np.zeros(rows + 1, dtype=np.int64)
    indptr[1:] = np.cumsum(np.bincount(rest_rows, minlength=rows) + 1)
    data = np.empty(indptr[-1])
    indices = np.empty(indptr[-1], dtype=np.int64)
    first = indptr[:-1]                                # a row's mark entry, then its other entries
    data[first] = row_weight                           # 1.0 * weight, as the dense design's product
    indices[first] = mark_column
    others = np.arange(rest_rows.size) + rest_rows + 1
    data[others] = rest[rest_rows, rest_columns]
    indices[others] = rest_columns + n_marks
    return sparse.csr_matrix((data, indices, indptr), shape=(rows, unknowns))


def _rms(vectors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(vectors ** 2, axis=1)))) if len(vectors) else 0.0


def _weighted_mean(values: np.ndarray, weight: np.ndarray, index: np.ndarray, count: int) -> np.ndarray:
    w = weight ** 2
    total = np.bincount(index, w, minlength=count)
    mean = np.column_stack([np.bincount(index, w * values[:, axis], minlength=count) for axis in range(2)])
    with np.errstate(invalid="ignore", divide="ignore"):
        return mean / total[:, None]


def _uncertainties(residual: np.ndarray, sigma: np.ndarray, index: np.ndarray, count: int, seen: np.ndarray):
    """Per-axis standard uncertainty of each centre: from the ring fits, and from the sweeps' spread.

    The spread of 2-4 sweeps is itself uncertain; each centre's spread variance is shrunk towards
    the pooled one (``SPREAD_PRIOR_DOF`` degrees of freedom) before it is used as a weight.
    """
    inverse = np.bincount(index, 1.0 / sigma ** 2, minlength=count)
    with np.errstate(divide="ignore"):
        ring = np.where(seen > 0, 1.0 / np.sqrt(np.maximum(inverse, 1e-300)), np.nan)
    squared = np.bincount(index, 0.5 * np.sum(residual ** 2, axis=1), minlength=count)  # per axis
    dof = np.maximum(seen - 1, 0).astype(float)
    spread = np.full(count, np.nan)
    repeated = dof > 0
    if repeated.any():
        pooled = squared[repeated].sum() / dof[repeated].sum()
        variance = (squared[repeated] + SPREAD_PRIOR_DOF * pooled) / (dof[repeated] + SPREAD_PRIOR_DOF)
        spread[repeated] = np.sqrt(variance / seen[repeated])
    return ring, spread
