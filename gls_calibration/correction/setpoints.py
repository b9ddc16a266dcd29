"""Corrected galvo setpoints: nominal inverse kinematics applied to a model-corrected target.

The models were learned on one plane, the calibration plane ``z = plane_z_mm`` (gls frame). A
target ``Q = (x, y, z)`` is corrected through ``Q'``, the point where Q's nominal ray meets that
plane (seed section 2.3): ``K' = Q' + sum_i model_i(Q')`` on the plane, then ``K`` is the point
where the nominal ray through ``K'`` meets Q's own height ``z``, and the mirror angles and the focus
shift are the nominal inverse kinematics of ``K`` at ``z``. So the beam runs along the ray the
calibration found for Q' and is focused at Q's true height. Every model predicts the deviation
``delta = Q - P`` that was measured (the i-th one while the first i-1 corrections were already
commanded), so successive calibrations add up. On the plane (``z = plane_z_mm``) ``K = K'``; for a
deviation field linear in x, y the rule equals correcting Q at its own (x, y); for a nonlinear one
and a head whose rays are straight it is the right one (the rays' errors scale with the distance
from the head, not with x, y at the target's height).

Calibrated region: the axis-aligned box of the training targets. The targets form a rectangular
grid, whose convex hull is that box, and clamping to a box is exact and cheap. Outside it the
models are not trusted to extrapolate: they are evaluated at the nearest point of the box and the
correction fades to zero with a raised cosine over ``taper_mm`` beyond the boundary, so it stays
continuous, bounded by its values on the boundary, and finite however far away the point is.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, fields
import math
import os
import threading
from typing import Any, Optional

import numpy as np
from threadpoolctl import threadpool_limits

from gls_calibration.common.validation import (as_coordinate_arrays, as_finite_array, as_integer_at_least,
                                               as_non_negative_number, as_points)
from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.correction.uncertainty_grid import UncertaintyGrid
from gls_calibration.models.rbf import BLOCK_ROWS, TILED_MIN_ROWS, DeviationModel


_INSIDE_TOLERANCE_MM = 1e-9
#: Largest correction a usable calibration may predict anywhere in its calibrated field: half the
#: ~190 mm field. The effect table's plausible extremes stay below it (the largest, a 0.05 rad galvo
#: zero offset, moves the spot ~55 mm); a model predicting more is broken (e.g. weights of 1e308).
MAX_DEVIATION_MM = 100.0
FIELD_CHECK_SAMPLES = 41   # per side of the grid on which a loaded correction's field is checked
_SMALL_REQUEST = 16        # up to this many targets, U is looked up point by point


@dataclass(frozen=True)
class CalibratedRegion:
    """Axis-aligned box (mm, gls frame) on the calibration plane ``z = plane_z_mm`` where the models were trained.

    Parameters
    ----------
    x_min, x_max, y_min, y_max : float
        Bounds of the box, mm.
    plane_z_mm : float, default 0.0
        Height of the calibration plane in the gls frame, mm.

    Raises
    ------
    ValueError
        If a bound is not finite or the box is empty.
    """

    x_min: float
    x_max: float
    y_min: float
    y_max: float
    plane_z_mm: float = 0.0

    def __post_init__(self) -> None:
        """Validate the fields and store them normalised (ValueError on the first bad one)."""
        values = [float(getattr(self, name)) for name in ("x_min", "x_max", "y_min", "y_max", "plane_z_mm")]
        if not all(math.isfinite(value) for value in values):
            raise ValueError(f"calibrated region bounds must be finite, got {values}")
        if values[0] > values[1] or values[2] > values[3]:
            raise ValueError(f"calibrated region is empty: x [{values[0]}, {values[1]}], y [{values[2]}, {values[3]}]")
        for name, value in zip(("x_min", "x_max", "y_min", "y_max", "plane_z_mm"), values):
            object.__setattr__(self, name, value)

    @classmethod
    def from_points(cls, points, plane_z_mm: float = 0.0) -> "CalibratedRegion":
        """Bounding box of training targets (N, 2) on the plane ``z = plane_z_mm``."""
        points = as_points(points, "points", 2)
        low, high = points.min(axis=0), points.max(axis=0)
        return cls(float(low[0]), float(high[0]), float(low[1]), float(high[1]), plane_z_mm)

    def contains(self, x, y) -> np.ndarray:
        """Return True for points inside the box or on its boundary (1e-9 mm tolerance)."""
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        tolerance = _INSIDE_TOLERANCE_MM
        return ((x >= self.x_min - tolerance) & (x <= self.x_max + tolerance)
                & (y >= self.y_min - tolerance) & (y <= self.y_max + tolerance))

    def clamp(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Nearest point of the box."""
        return (np.clip(np.asarray(x, dtype=float), self.x_min, self.x_max),
                np.clip(np.asarray(y, dtype=float), self.y_min, self.y_max))

    def intersection(self, other: "CalibratedRegion") -> "CalibratedRegion":
        """Part covered by both boxes (ValueError if they do not overlap); the plane stays this one's."""
        return CalibratedRegion(max(self.x_min, other.x_min), min(self.x_max, other.x_max),
                                max(self.y_min, other.y_min), min(self.y_max, other.y_max), self.plane_z_mm)

    def to_dict(self) -> dict:
        """Plain-number description (YAML-ready)."""
        return {"type": "box", "x_min": self.x_min, "x_max": self.x_max, "y_min": self.y_min, "y_max": self.y_max,
                "plane_z_mm": self.plane_z_mm}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "CalibratedRegion":
        """Rebuild a region written by :meth:`to_dict`."""
        if not isinstance(data, Mapping) or data.get("type") != "box":
            raise ValueError(f"calibrated region must be a mapping with type 'box', got {data!r}")
        missing = [key for key in ("x_min", "x_max", "y_min", "y_max") if key not in data]
        if missing:
            raise ValueError(f"calibrated region lacks key(s) {', '.join(missing)}")
        # Files of format version 1 have no plane: their calibrations were learned at z = 0.
        return cls(data["x_min"], data["x_max"], data["y_min"], data["y_max"], data.get("plane_z_mm", 0.0))


@dataclass(frozen=True)
class CorrectedSetpoints:
    """Corrected command per point: target ``x``, ``y`` actually commanded (mm), joint setpoints and flags.

    Parameters
    ----------
    x, y : numpy.ndarray, shape (N,)
        The corrected target K actually commanded, gls frame, mm.
    alpha_x, alpha_y : numpy.ndarray, shape (N,)
        Mechanical mirror angles, rad.
    focus_shift : numpy.ndarray, shape (N,)
        Focus shift, mm.
    inside_calibrated_field : numpy.ndarray, shape (N,)
        bool: the target lies in the calibrated region.
    within_limits : numpy.ndarray, shape (N,)
        bool: the angles and focus are within the head's limits.
    uncertainty_k2_mm : numpy.ndarray, shape (N,), optional
        Expanded uncertainty (95 % radius, mm) of the landing, NaN outside the calibrated field or
        when the calibration holds no U grid; None only where a client rebuilt setpoints from an
        answer that had none.
    """

    x: np.ndarray
    y: np.ndarray
    alpha_x: np.ndarray
    alpha_y: np.ndarray
    focus_shift: np.ndarray
    inside_calibrated_field: np.ndarray
    within_limits: np.ndarray
    # expanded uncertainty (95 % radius, mm) of the landing, NaN outside the calibrated field or
    # when the calibration holds no U grid (``uncertainty_grid``); None only where a client
    # rebuilt setpoints from an answer that had none
    uncertainty_k2_mm: Optional[np.ndarray] = None


def check_calibration_plane(geometry: HeadGeometry, plane_z_mm: float) -> None:
    """Check that the calibration plane, where the plate was marked and scanned, lies within the focus range.

    Parameters
    ----------
    geometry : HeadGeometry
        The nominal head.
    plane_z_mm : float
        Height of the calibration plane in the gls frame, mm.

    Raises
    ------
    ValueError
        If ``|plane_z_mm|`` exceeds ``geometry.focus_range_mm`` (or is NaN).
    """
    if not abs(plane_z_mm) <= geometry.focus_range_mm:
        raise ValueError(f"calibration plane z = {plane_z_mm:g} mm lies outside the head's focus range "
                         f"(+-{geometry.focus_range_mm:g} mm)")


def taper_weight(distance_mm: np.ndarray, taper_mm: float) -> np.ndarray:
    """Raised-cosine fade: 1 at the boundary, 0 from ``taper_mm`` beyond it (a step when taper is 0)."""
    distance_mm = np.asarray(distance_mm, dtype=float)
    if taper_mm == 0.0:
        return (distance_mm <= 0.0).astype(float)
    # Only points beyond the boundary need the cosine (it is exactly 1 at distance 0).
    weight = np.ones_like(distance_mm)
    beyond = distance_mm > 0.0
    if beyond.any():
        fraction = np.clip(distance_mm[beyond] / taper_mm, 0.0, 1.0)
        weight[beyond] = 0.5 * (1.0 + np.cos(math.pi * fraction))
    return weight


class Correction:
    """Setpoint correction from a sequence of deviation models (applied additively).

    Without models the correction is the nominal kinematics and no point counts as inside the
    calibrated field.

    Parameters
    ----------
    geometry : HeadGeometry
        The nominal head.
    models : sequence of DeviationModel, optional
        Callables ``(M, 2) -> (M, 2)`` mm (e.g. :class:`gls_calibration.models.rbf.OLSRBFNetwork`).
    calibrated_region : CalibratedRegion, optional
        Where the models were trained; required when there is at least one model.
    taper_mm : float, default 10.0
        Width of the raised-cosine fade of the correction beyond the calibrated region, mm;
        non-negative (0: a step).
    uncertainty : UncertaintyGrid, optional
        The calibration's U map; each answer carries U at Q' (NaN outside the calibrated field, and
        everywhere without a map). Dropped without models.

    Raises
    ------
    ValueError
        If ``geometry`` is not a HeadGeometry, a model is not callable, models come without a region,
        the region or ``uncertainty`` has the wrong type, the calibration plane lies outside the focus
        range, or ``taper_mm`` is negative.

    Examples
    --------
    A model that moves every point by 0.1 mm in x and y, trained on a 200 x 200 mm box:

    >>> from gls_calibration.geometry.kinematics import HeadGeometry
    >>> region = CalibratedRegion(-100.0, 100.0, -100.0, 100.0)
    >>> correction = Correction(HeadGeometry(), [lambda points: np.full((len(points), 2), 0.1)], region)
    >>> answer = correction.correct([0.0, 50.0], [0.0, 150.0])
    >>> answer.x.tolist(), answer.y.tolist(), answer.inside_calibrated_field.tolist()
    ([0.1, 50.0], [0.1, 150.0], [True, False])
    """

    def __init__(self, geometry: HeadGeometry, models: Sequence[DeviationModel] = (),
                 calibrated_region: Optional[CalibratedRegion] = None, taper_mm: float = 10.0,
                 uncertainty: Optional[UncertaintyGrid] = None) -> None:
        if not isinstance(geometry, HeadGeometry):
            raise ValueError(f"geometry must be a HeadGeometry, got {type(geometry).__name__}")
        models = tuple(models)
        for index, model in enumerate(models):
            if not callable(model):
                raise ValueError(f"models[{index}] is not callable")
        if models and calibrated_region is None:
            raise ValueError("calibrated_region is required when models are given")
        if calibrated_region is not None and not isinstance(calibrated_region, CalibratedRegion):
            raise ValueError(f"calibrated_region must be a CalibratedRegion, got {type(calibrated_region).__name__}")
        if calibrated_region is not None:
            check_calibration_plane(geometry, calibrated_region.plane_z_mm)
        self.geometry = geometry
        self.models = models
        self.calibrated_region = calibrated_region
        self.taper_mm = as_non_negative_number(taper_mm, "taper_mm")
        if uncertainty is not None and not isinstance(uncertainty, UncertaintyGrid):
            raise ValueError(f"uncertainty must be an UncertaintyGrid, got {type(uncertainty).__name__}")
        self.uncertainty = uncertainty if models else None     # U describes these models only

    def with_model(self, model: DeviationModel, region: Optional[CalibratedRegion] = None) -> "Correction":
        """Return a new correction with ``model`` added after the existing ones.

        The region becomes the overlap of the current one and ``region`` (either may be absent,
        not both when this is the first model). The U map describes the old models only: it is dropped.
        """
        if region is None:
            combined = self.calibrated_region
        elif self.calibrated_region is None:
            combined = region
        else:
            combined = self.calibrated_region.intersection(region)
        return Correction(self.geometry, self.models + (model,), combined, self.taper_mm)

    def prepare(self) -> None:
        """Build what the models evaluate large requests with now, not on the first large request.

        For a spline that is its tiles (60-150 ms). Safe to call from another thread while this
        correction serves.
        """
        for model in self.models:
            prepare = getattr(model, "prepare", None)
            if prepare is not None:
                prepare()

    def deviation(self, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the summed, clamped and tapered model correction (dx, dy) in mm and the inside flags."""
        x, y, _ = as_coordinate_arrays(x, y)
        if not self.models:
            zeros = np.zeros_like(x)
            return zeros, zeros.copy(), np.zeros(x.shape, dtype=bool)
        return self._deviation(x, y)[:3]

    def _deviation(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
        """:meth:`deviation` of validated arrays with models, and the clamped points it evaluated."""
        region = self.calibrated_region
        inside = region.contains(x, y)
        clamped_x, clamped_y = region.clamp(x, y)
        weight = taper_weight(np.hypot(x - clamped_x, y - clamped_y), self.taper_mm)
        points = np.column_stack([clamped_x, clamped_y])
        total = np.zeros_like(points)
        for model in self.models:
            total += as_finite_array(model(points), "model output", ndim=2)
        return weight * total[:, 0], weight * total[:, 1], inside, clamped_x, clamped_y

    def check_field(self, samples_per_side: int = FIELD_CHECK_SAMPLES) -> None:
        """Raise ValueError unless the summed correction is finite and within ``MAX_DEVIATION_MM``.

        It is evaluated on a grid over the calibrated region (its edges included; outside it the
        correction is the edge's, tapered). Called when a calibration is loaded, so that a broken
        model is refused then and not on every later request.
        """
        if not self.models:
            return
        region = self.calibrated_region
        xs = np.linspace(region.x_min, region.x_max, samples_per_side)
        ys = np.linspace(region.y_min, region.y_max, samples_per_side)
        grid_x, grid_y = np.meshgrid(xs, ys)
        total = np.zeros((grid_x.size, 2))
        points = np.column_stack([grid_x.ravel(), grid_y.ravel()])
        with np.errstate(all="ignore"):   # overflow is what is checked for
            for model in self.models:
                output = np.asarray(model(points), dtype=float)
                if output.shape != total.shape:
                    raise ValueError(f"a model of the correction returns shape {output.shape} for "
                                     f"{len(points)} points; ({len(points)}, 2) is expected")
                total += output
            size = np.hypot(total[:, 0], total[:, 1])
        bad = ~np.isfinite(size) | (size > MAX_DEVIATION_MM)
        if bad.any():
            first = int(np.argmax(bad))
            raise ValueError(f"the correction is unusable: at {int(np.count_nonzero(bad))} of {len(size)} points of "
                             f"its calibrated field it is not finite or exceeds {MAX_DEVIATION_MM:g} mm "
                             f"(first at x = {points[first, 0]:.1f}, y = {points[first, 1]:.1f} mm: "
                             f"{size[first]:.3g} mm)")

    def correct(self, x, y, z=None, workers: Optional[int] = None) -> CorrectedSetpoints:
        """Corrected setpoints for targets (x, y[, z]) in mm (gls frame); z defaults to the work plane.

        Through Q' on the calibration plane (see the module docstring); without models the nominal
        kinematics of Q. ``workers``: threads that share a large request (None: every CPU this
        process may use; 1: none). The targets are split at multiples of the models' evaluation
        block, so the answer is bit-identical whatever the number of workers. Once a request has been
        shared, BLAS runs on one thread in this process (the workers are the parallelism).

        Parameters
        ----------
        x, y : array_like
            Targets (mm, gls frame).
        z : array_like, optional
            Target heights (mm); None: the work plane.
        workers : int, optional
            Threads that share a large request.

        Returns
        -------
        CorrectedSetpoints
            Corrected targets K (mm), mirror angles (rad), focus shift (mm) and per target whether it
            lies in the calibrated field and within the head's limits.

        Raises
        ------
        ValueError
            Coordinates that are not finite, do not match, or a height at the head.

        Examples
        --------
        >>> from gls_calibration.geometry.kinematics import HeadGeometry
        >>> answer = Correction(HeadGeometry()).correct([10.0], [20.0])     # no model: the nominal head
        >>> print(answer.x, answer.y, answer.inside_calibrated_field, answer.within_limits)
        [10.] [20.] [False] [ True]
        """
        single = _single_target(x, y, z)
        if single is not None and self.models:
            if abs(single[2]) >= self.geometry.working_distance_mm:     # scalar test: this path is hot
                self._check_heights(np.array([single[2]]))
            return self._correct_one(*single)
        x, y, z = as_coordinate_arrays(x, y, z)
        self._check_heights(z)
        parts = _worker_slices(x.size, available_workers() if workers is None else
                               as_integer_at_least(workers, "workers", 1))
        if len(parts) == 1:
            return self._correct_many(x, y, z)
        pieces = list(_pool(len(parts)).map(lambda part: self._correct_many(x[part], y[part], z[part]), parts))
        return CorrectedSetpoints(*(np.concatenate([getattr(piece, field.name) for piece in pieces])
                                    for field in fields(CorrectedSetpoints)))

    def _check_heights(self, z: np.ndarray) -> None:
        """Raise ValueError unless every height is within +- the working distance.

        No ray reaches a point at or above the mirrors, and nothing as far below the plane as the
        head is above it is a target.
        """
        limit = self.geometry.working_distance_mm
        outside = np.abs(z) >= limit
        if outside.any():
            first = int(np.argmax(outside))
            raise ValueError(f"z must lie within +-{limit:g} mm (the head's working distance): "
                             f"{int(np.count_nonzero(outside))} target(s) outside, first z = {z[first]:g} mm "
                             f"at index {first}")

    def _correct_many(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> CorrectedSetpoints:
        """:meth:`correct` for validated 1-D arrays, in this thread."""
        # The height itself must lie in the focus range too, not only the focus shift it needs.
        height_ok = np.abs(z) <= self.geometry.focus_range_mm
        if not self.models:
            joints = inverse(self.geometry, x, y, z)
            return CorrectedSetpoints(x, y, joints.alpha_x, joints.alpha_y, joints.focus_shift,
                                      np.zeros(x.shape, dtype=bool), joints.within_limits & height_ok,
                                      np.full(x.shape, np.nan))
        plane_z = self.calibrated_region.plane_z_mm
        on_plane_x, on_plane_y = transfer_along_ray(self.geometry, x, y, z, plane_z)
        delta_x, delta_y, inside, clamped_x, clamped_y = self._deviation(on_plane_x, on_plane_y)
        commanded_x, commanded_y = transfer_along_ray(self.geometry, on_plane_x + delta_x, on_plane_y + delta_y,
                                                      plane_z, z)
        joints = inverse(self.geometry, commanded_x, commanded_y, z)
        if self.uncertainty is None:
            uncertainty = np.full(x.shape, np.nan)
        else:
            # at the clamped point (the grid spans the region), NaN where Q' is outside
            grid = self.uncertainty
            if x.size <= _SMALL_REQUEST:     # numpy's per-call cost outweighs a few scalar lookups
                uncertainty = np.array([grid.at_point(px, py) if flag else math.nan
                                        for px, py, flag in zip(on_plane_x.tolist(), on_plane_y.tolist(), inside)])
            else:
                uncertainty = grid.inside_at(clamped_x, clamped_y)
                uncertainty[~inside] = np.nan
        return CorrectedSetpoints(commanded_x, commanded_y, joints.alpha_x, joints.alpha_y, joints.focus_shift,
                                  inside, joints.within_limits & height_ok, uncertainty)

    def _correct_one(self, x: float, y: float, z: float) -> CorrectedSetpoints:
        """:meth:`correct` for one target in scalar arithmetic (same formulas; numpy per call costs ~1 us)."""
        geometry, region = self.geometry, self.calibrated_region
        d, e, plane_z = geometry.working_distance_mm, geometry.mirror_distance_mm, region.plane_z_mm

        def transfer(px: float, py: float, z_from: float, z_to: float) -> tuple[float, float]:
            ratio = (d - z_to) / (d - z_from)
            slant = math.hypot(d - z_from, px)
            return px * ratio, py * ((e + slant * ratio) / (e + slant))

        on_plane_x, on_plane_y = transfer(x, y, z, plane_z)
        clamped_x = min(max(on_plane_x, region.x_min), region.x_max)
        clamped_y = min(max(on_plane_y, region.y_min), region.y_max)
        distance = math.hypot(on_plane_x - clamped_x, on_plane_y - clamped_y)
        weight = float(taper_weight(distance, self.taper_mm)) if distance > 0.0 else 1.0
        delta_x = delta_y = 0.0
        for model in self.models:
            if hasattr(model, "at_point"):
                model_x, model_y = model.at_point(clamped_x, clamped_y)
            else:
                model_x, model_y = as_finite_array(model(np.array([[clamped_x, clamped_y]])), "model output",
                                                   ndim=2)[0]
            delta_x += model_x
            delta_y += model_y
        if not (math.isfinite(delta_x) and math.isfinite(delta_y)):
            raise ValueError("model output contains NaN or infinite value(s)")
        commanded_x, commanded_y = transfer(on_plane_x + weight * delta_x, on_plane_y + weight * delta_y, plane_z, z)
        height = d - z
        slant = math.hypot(height, commanded_x)
        alpha_x = 0.5 * math.atan2(commanded_x, height)
        alpha_y = 0.5 * math.atan2(commanded_y, e + slant)
        focus_shift = math.hypot(e + slant, commanded_y) - (e + height)
        limit = geometry.mirror_limit_rad
        within = (abs(alpha_x) <= limit and abs(alpha_y) <= limit and abs(focus_shift) <= geometry.focus_range_mm
                  and abs(z) <= geometry.focus_range_mm)
        tolerance = _INSIDE_TOLERANCE_MM
        inside = (region.x_min - tolerance <= on_plane_x <= region.x_max + tolerance
                  and region.y_min - tolerance <= on_plane_y <= region.y_max + tolerance)
        grid = self.uncertainty
        uncertainty = grid.at_point(on_plane_x, on_plane_y) if grid is not None and inside else math.nan
        return CorrectedSetpoints(np.array([commanded_x]), np.array([commanded_y]), np.array([alpha_x]),
                                  np.array([alpha_y]), np.array([focus_shift]), np.array([inside]),
                                  np.array([within]), np.array([uncertainty]))


# Below this a thread's hand-over costs more than it saves; and no part may fall below the size from
# which a spline changes its evaluator (a target's value must not depend on the sharing).
_MIN_ROWS_PER_WORKER = max(8 * BLOCK_ROWS, TILED_MIN_ROWS)
_pool_lock = threading.Lock()
_shared_pool: list[tuple[int, ThreadPoolExecutor]] = []    # (threads, pool): one, replaced by a larger one


def available_workers() -> int:
    """Count the CPUs this process may run on (default workers of :meth:`Correction.correct`)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:           # not on Linux
        return max(1, os.cpu_count() or 1)


def _worker_slices(count: int, workers: int) -> list[slice]:
    """Cut ``count`` targets into contiguous parts for up to ``workers`` threads.

    Contiguous parts of ``count`` targets for up to ``workers`` threads, cut at multiples of BLOCK_ROWS,
    none shorter than ``_MIN_ROWS_PER_WORKER`` (a short last part joins the one before it).
    """
    workers = max(1, min(workers, count // _MIN_ROWS_PER_WORKER))
    if workers == 1:
        return [slice(0, count)]
    size = -(-count // workers)
    size = -(-size // BLOCK_ROWS) * BLOCK_ROWS
    starts = list(range(0, count, size))
    if count - starts[-1] < _MIN_ROWS_PER_WORKER:
        starts.pop()
    return [slice(start, end) for start, end in zip(starts, starts[1:] + [count])]


def _pool(workers: int) -> ThreadPoolExecutor:
    """Return a shared pool of at least ``workers`` threads (started once, not per request).

    From its start on, BLAS runs on one thread in this process.
    """
    with _pool_lock:
        if not _shared_pool or _shared_pool[0][0] < workers:
            # The workers are the parallelism: under each of them a threaded BLAS would start threads of
            # its own on the same CPUs (2 workers, threaded OpenBLAS: 60-66 ms per 100 000 targets at
            # twice the CPU time; BLAS on one thread: 32-37 ms). Kept, like the pool, for good.
            threadpool_limits(limits=1, user_api="blas")
            # The smaller pool is dropped, not shut down: a caller may still be handing it parts (its
            # idle threads end when it is collected).
            _shared_pool[:] = [(workers, ThreadPoolExecutor(workers, thread_name_prefix="correction"))]
        return _shared_pool[0][1]


def _single_target(x, y, z) -> Optional[tuple[float, float, float]]:
    """(x, y, z) as floats when the request is one finite target (z absent or one value), else None."""
    try:
        if len(x) != 1 or len(y) != 1 or (z is not None and len(z) > 1):
            return None
        values = (float(x[0]), float(y[0]), float(z[0]) if z is not None and len(z) else 0.0)
    except (TypeError, ValueError, IndexError):
        return None           # scalars, nested or odd input: the general path validates and reports
    if isinstance(x[0], (bool, np.bool_)) or not all(math.isfinite(value) for value in values):
        return None
    return values


def transfer_along_ray(geometry: HeadGeometry, x, y, z_from, z_to) -> tuple[np.ndarray, np.ndarray]:
    """Where the nominal ray through (x, y, ``z_from``) meets the plane ``z = z_to`` (mm).

    Beyond the X mirror the nominal ray is straight: x scales with the height below the mirror
    ``h = d - z``, the slant ``hypot(h, x)`` too, and ``y / (e + slant)`` (tan of the Y angle) is
    constant along it. Where both heights are equal everywhere, (x, y) themselves (the formulas give
    exactly them: every ratio is 1.0).
    """
    z_from, z_to = _uniform_to_scalar(z_from), _uniform_to_scalar(z_to)
    if np.all(z_from == z_to):
        return np.array(x, dtype=float), np.array(y, dtype=float)
    height_from = geometry.working_distance_mm - z_from
    ratio = (geometry.working_distance_mm - z_to) / height_from
    slant = np.hypot(height_from, x)
    e = geometry.mirror_distance_mm
    return x * ratio, y * ((e + slant * ratio) / (e + slant))


def _uniform_to_scalar(z) -> np.ndarray:
    """``z`` as a float array; a 0-d one when all its values are equal (the same arithmetic, fewer passes)."""
    z = np.asarray(z, dtype=float)
    if z.ndim and z.size and np.all(z == z.flat[0]):
        return np.asarray(z.flat[0])
    return z
