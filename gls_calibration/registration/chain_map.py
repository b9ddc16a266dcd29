"""Chain map: the robot's repeating error along each programmed line, measured once and removed.

The robot places every profile by the pose it reports; the reported pose differs from the true one
by an error that REPEATS each time the arm runs the same programmed line in the same direction
(transmission error, compliance, kinematic parameter errors: issue 32). Averaging sweeps cannot
remove it, and the error separation (``registration/separation.py``) trusts the reported travel. It can be
measured: scan a plate with known centres (a certified grid plate; the simulated reference plate)
along the same programmed lines as the calibration (the same sweep plan, sweep length and start),
compare each sweep's measured centres with the known ones, and fit per line an error field that
depends only on where the sensor is along its travel.

Model of a centre of the reference plate, known at ``k`` in the plate's frame, measured at ``m`` in
the scanner base frame B by a sweep of line ``l`` (plate ``j``):

    m = R_j k + t_j + e_l(u) + noise

- ``R_j, t_j``: where plate ``j`` lies (a 2-D rigid motion; unknown, fitted);
- ``e_l(u) = (e_x(u), e_y(u))``: the line's error in B's x and y, a natural cubic spline in knot
  values over ``u``, the B coordinate along the line's travel (B's y for the sensor as mounted,
  B's x for the sensor turned 90 deg). The along-travel component holds the scale of the travel and
  the smooth transmission error, the across component the path's deviation; a rigid motion of the
  plate cannot mimic the along part (the plate's scale is certified), so the map keeps the scale.

A second-difference prior (``curvature_sigma_mm``) keeps the spline smooth where centres are sparse
and a weak ridge (``ridge_sigma_mm``) fixes what no plate motion tells apart: a common shift of
every line. The map is applied to every sweep of the calibration plate before the sweeps are
combined: ``m - e_l(u(m))`` (:meth:`ChainMap.correct_measurement`).

A chain map is a small YAML file (:func:`save_chain_map`, :func:`load_chain_map`)::

    chain_map:
      reference: "certified grid plate 19 x 19 at 10 mm, S/N 1234"
      sweeps_per_line: 2                  # sweeps of each line the map averages
      residual_rms_mm: [0.004, 0.005]     # per axis (B x, y) after the fit, k = 1
      lines:
        - line: "0+"                      # sweep_plan label: orientation (deg) and direction
          first_knot_mm: -100.0           # u of the first knot (B frame, mm)
          knot_spacing_mm: 10.0
          error_x_mm: [...]               # e_x at the knots
          error_y_mm: [...]               # e_y at the knots

The map is only valid for the lines it was measured on: same plan, sweep length and robot program.
Renew it when the robot or its program changes, and on a schedule (the repeating error drifts with
wear and temperature; see docs/method-and-results.md, "Chain map").

Example
-------
>>> import numpy as np
>>> line = LineMap("0+", -50.0, 10.0, np.zeros(11), np.linspace(-0.01, 0.01, 11))
>>> chain = ChainMap((line,), reference="synthetic", sweeps_per_line=1, residual_rms_mm=(0.001, 0.001))
>>> np.round(chain.error_mm("0+", np.array([[0.0, 50.0]])), 4).tolist()
[[0.0, 0.01]]
"""
from __future__ import annotations

from dataclasses import dataclass, replace
import hashlib
import json
import math
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np
from scipy.interpolate import CubicSpline
import yaml

from gls_calibration.common.config_files import read_config_file, require_exact_keys
from gls_calibration.common.files import atomic_write_text
from gls_calibration.registration.rigid import align_rigid_2d
from gls_calibration.registration.sweep_plan import SweepPass, parse_plan

MAX_KNOTS = 1000
"""Most knots one line may hold (a 10 m line at 10 mm): a bigger file is not a chain map."""

MAX_ERROR_MM = 5.0
"""Largest error a map may hold at a knot: a robot off by more is broken, not mapped."""


def travel_direction(line: str) -> np.ndarray:
    """Return the unit vector (2,) in B x-y along which the coordinate of line ``line`` runs.

    The B axis the line (a sweep-plan label) travels along: y for the sensor as mounted, x for the
    sensor turned 90 deg; for the 45 deg line its travel with a positive y component,
    (-1, 1) / sqrt(2). Either travel direction of a line gives the same coordinate.
    """
    (item,) = parse_plan(line)
    if item.orientation_deg in (0.0, 90.0):
        return np.array([0.0, 1.0]) if item.orientation_deg == 0.0 else np.array([1.0, 0.0])
    angle = math.radians(item.orientation_deg)
    return np.array([-math.sin(angle), math.cos(angle)])


def travel_coordinate(line: str, xy_mm: np.ndarray) -> np.ndarray:
    """Return the coordinate (N,) of points ``xy_mm`` (N, 2+, B, mm) along :func:`travel_direction`."""
    return np.asarray(xy_mm, dtype=float)[:, :2] @ travel_direction(line)


@dataclass(frozen=True)
class LineMap:
    """The repeating error of one programmed line: ``e_x, e_y`` (mm, B frame) at knots along its travel.

    Knot ``i`` is at ``u = first_knot_mm + i * knot_spacing_mm`` along the travel (:func:`travel_coordinate`);
    between knots a natural cubic spline. ``error_mm`` evaluates it; outside the knots it refuses.
    """

    line: str
    first_knot_mm: float
    knot_spacing_mm: float
    error_x_mm: np.ndarray
    error_y_mm: np.ndarray

    def __post_init__(self) -> None:
        """Validate the fields and store them normalised (ValueError on the first bad one)."""
        if not isinstance(self.line, str):
            raise ValueError(f"chain_map line must be a sweep plan item such as 0+, got {self.line!r}")
        try:
            items = parse_plan(self.line)
        except ValueError as error:
            raise ValueError(f"chain_map line {self.line!r}: {error}") from None
        if len(items) != 1:
            raise ValueError(f"chain_map line must be one sweep plan item, got {self.line!r}")
        object.__setattr__(self, "line", items[0].label)
        where = f"chain_map line {self.line}"
        for name in ("first_knot_mm", "knot_spacing_mm"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"{where}: {name} must be a finite number, got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.knot_spacing_mm <= 0.0:
            raise ValueError(f"{where}: knot_spacing_mm must be positive, got {self.knot_spacing_mm!r}")
        arrays = []
        for name in ("error_x_mm", "error_y_mm"):
            raw = getattr(self, name)
            try:
                values = np.array(raw, dtype=float)
            except (TypeError, ValueError):
                raise ValueError(f"{where}: {name} must be a list of numbers") from None
            if values.ndim != 1 or not 4 <= values.size <= MAX_KNOTS:
                raise ValueError(f"{where}: {name} must be a list of 4 to {MAX_KNOTS} numbers")
            if not np.all(np.isfinite(values)) or np.any(np.abs(values) > MAX_ERROR_MM):
                raise ValueError(f"{where}: {name} must hold finite errors within +-{MAX_ERROR_MM:g} mm")
            values.setflags(write=False)
            object.__setattr__(self, name, values)
            arrays.append(values)
        if arrays[0].size != arrays[1].size:
            raise ValueError(f"{where}: error_x_mm and error_y_mm must have the same length "
                             f"({arrays[0].size} != {arrays[1].size})")

    @property
    def knots_mm(self) -> np.ndarray:
        """Positions of the knots along the line, mm."""
        return self.first_knot_mm + self.knot_spacing_mm * np.arange(self.error_x_mm.size)

    def error_mm(self, xy_mm: np.ndarray) -> np.ndarray:
        """Return the line's error (N, 2) (B x, y, mm) at points ``xy_mm`` (N, 2+) of B.

        ValueError for a point beyond the first or last knot: the map says nothing there.
        """
        xy = np.asarray(xy_mm, dtype=float)
        u = travel_coordinate(self.line, xy)
        knots = self.knots_mm
        tolerance = 1e-9 * self.knot_spacing_mm
        if not np.all(np.isfinite(u)) or np.any(u < knots[0] - tolerance) or np.any(u > knots[-1] + tolerance):
            raise ValueError(f"chain map of line {self.line} covers {knots[0]:g} to {knots[-1]:g} mm along its "
                             f"travel; a centre at {float(np.nanmax(np.abs(u))):g} mm lies outside (or is not finite)")
        spline = CubicSpline(knots, np.column_stack([self.error_x_mm, self.error_y_mm]), bc_type="natural")
        return spline(np.clip(u, knots[0], knots[-1]))

    def to_dict(self) -> dict:
        """Plain form of this line's map for the map file."""
        return {"line": self.line, "first_knot_mm": self.first_knot_mm, "knot_spacing_mm": self.knot_spacing_mm,
                "error_x_mm": [float(v) for v in self.error_x_mm], "error_y_mm": [float(v) for v in self.error_y_mm]}


@dataclass(frozen=True)
class ChainMap:
    """Repeating errors of the programmed lines (one :class:`LineMap` each).

    Parameters
    ----------
    lines : tuple of LineMap
        One map per line, each line once.
    reference : str
        Names the plate with known centres the map was measured on.
    sweeps_per_line : int
        Sweeps averaged per line; at least 1.
    residual_rms_mm : tuple of 2 float
        Per-axis RMS (B x, y) of the reference centres about the fit, mm; non-negative.

    Raises
    ------
    ValueError
        On the first bad field (no lines, a line mapped twice, an empty reference, bad counts or RMS).
    """

    lines: tuple[LineMap, ...]
    reference: str
    sweeps_per_line: int
    residual_rms_mm: tuple[float, float]

    def __post_init__(self) -> None:
        """Validate the fields and store them normalised (ValueError on the first bad one)."""
        lines = tuple(self.lines) if isinstance(self.lines, (list, tuple)) else None
        if not lines or not all(isinstance(line, LineMap) for line in lines):
            raise ValueError("chain_map.lines must hold one or more line maps")
        labels = [line.line for line in lines]
        if len(set(labels)) != len(labels):
            raise ValueError(f"chain_map.lines maps a line twice: {', '.join(labels)}")
        object.__setattr__(self, "lines", lines)
        if not isinstance(self.reference, str) or not self.reference.strip():
            raise ValueError("chain_map.reference must name the plate with known centres the map was measured on")
        if isinstance(self.sweeps_per_line, bool) or not isinstance(self.sweeps_per_line, int) \
                or self.sweeps_per_line < 1:
            raise ValueError(f"chain_map.sweeps_per_line must be an integer of at least 1, "
                             f"got {self.sweeps_per_line!r}")
        rms = tuple(self.residual_rms_mm) if isinstance(self.residual_rms_mm, (list, tuple)) else ()
        if len(rms) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                                    and v >= 0.0 for v in rms):
            raise ValueError(f"chain_map.residual_rms_mm must be two non-negative finite numbers, "
                             f"got {self.residual_rms_mm!r}")
        object.__setattr__(self, "residual_rms_mm", (float(rms[0]), float(rms[1])))

    @property
    def labels(self) -> tuple[str, ...]:
        """Return the programmed lines this map covers, in its order."""
        return tuple(line.line for line in self.lines)

    def line_map(self, line: str) -> LineMap:
        """Return the map of line ``line`` (a sweep-plan label); ValueError when the map has none."""
        label = parse_plan(line)[0].label
        for item in self.lines:
            if item.line == label:
                return item
        raise ValueError(f"the chain map has no line {label} (it maps {', '.join(self.labels)}); measure the "
                         "map with the calibration's sweep plan")

    def error_mm(self, line: str, xy_mm: np.ndarray) -> np.ndarray:
        """Error (N, 2) of line ``line`` at B points ``xy_mm`` (N, 2+): measured minus true."""
        return self.line_map(line).error_mm(xy_mm)

    def correct(self, line: str, centres_mm: np.ndarray) -> np.ndarray:
        """Centres (N, 2 or 3, B frame) of a sweep of ``line`` with the line's error removed (z kept)."""
        centres = np.array(centres_mm, dtype=float)
        if centres.ndim != 2 or centres.shape[1] not in (2, 3):
            raise ValueError(f"centres must have shape (N, 2) or (N, 3), got {centres.shape}")
        if len(centres):
            centres[:, :2] -= self.error_mm(line, centres)
        return centres

    def correct_measurement(self, found, item: SweepPass, pose) -> Any:
        """Correct a sweep ``item``'s ``FiducialMeasurement`` (B frame) on the plate ``pose``.

        A ``FiducialMeasurement`` of a sweep ``item`` with its centres corrected (B frame) and its
        plate coordinates recomputed on the plate ``pose`` (``PlatePose``).
        """
        centres = self.correct(item.label, found.centres)
        return replace(found, centres=centres, centres_plane=pose.to_plane(centres))

    @property
    def identity(self) -> str:
        """Return ``sha256:`` and 16 hex digits of the map's content.

        A reference check and a calibration record use it to say which map their sweeps were
        corrected with.
        """
        text = json.dumps(self.to_dict(), sort_keys=True)
        return "sha256:" + hashlib.sha256(text.encode()).hexdigest()[:16]

    def to_dict(self) -> dict:
        """Plain form of the whole map for the map file."""
        return {"reference": self.reference, "sweeps_per_line": self.sweeps_per_line,
                "residual_rms_mm": list(self.residual_rms_mm), "lines": [line.to_dict() for line in self.lines]}


NO_CHAIN_MAP = "none"
"""The identity recorded when no chain map corrected the sweeps."""


def chain_map_identity(chain_map: Optional[ChainMap]) -> str:
    """Return ``chain_map.identity``, or :data:`NO_CHAIN_MAP` for None.

    Parameters
    ----------
    chain_map : ChainMap or None
        The map.

    Returns
    -------
    str
        ``sha256:`` and 16 hex digits of the map's content, or :data:`NO_CHAIN_MAP`.
    """
    return NO_CHAIN_MAP if chain_map is None else chain_map.identity


def correct_measurements(chain_map: Optional[ChainMap], measurements: Sequence, passes: Sequence[SweepPass],
                         pose) -> list:
    """Remove from every sweep's measurement the map of its line.

    Parameters
    ----------
    chain_map : ChainMap or None
        The map; None leaves the measurements unchanged.
    measurements : sequence of FiducialMeasurement
        One per sweep, in the order of ``passes`` (B frame, mm).
    passes : sequence of SweepPass
        The sweep plan.
    pose : PlatePose
        The plate, on which the plate coordinates are recomputed.

    Returns
    -------
    list of FiducialMeasurement
        The measurements with corrected centres.

    Raises
    ------
    ValueError
        If ``chain_map`` is neither a ChainMap nor None, the counts of measurements and passes differ,
        or a line is not mapped.
    """
    if chain_map is None:
        return list(measurements)
    if not isinstance(chain_map, ChainMap):
        raise ValueError(f"chain_map must be a ChainMap or None, got {type(chain_map).__name__}")
    if len(measurements) != len(passes):
        raise ValueError(f"{len(measurements)} measurement(s) for a plan of {len(passes)} pass(es)")
    return [chain_map.correct_measurement(found, item, pose) for found, item in zip(measurements, passes)]


@dataclass(frozen=True)
class ReferenceSweep:
    """One sweep of a plate with known centres.

    Parameters
    ----------
    line : str
        The sweep's line (sweep-plan label, e.g. ``"0+"``).
    plate : int
        Which plate placement it saw: sweeps of one placement share the plate's unknown pose.
    known_xy_mm : numpy.ndarray, shape (M, 2)
        The known centres in the plate's own frame, mm.
    measured_xy_mm : numpy.ndarray, shape (M, 2) or (M, 3)
        Where the sweep measured them, B frame, mm.
    """

    line: str
    plate: int
    known_xy_mm: np.ndarray
    measured_xy_mm: np.ndarray


@dataclass(frozen=True)
class ChainMapFit:
    """How the map is fitted: knots, reach, smoothness prior, ridge and measurement sigma.

    Parameters
    ----------
    knot_spacing_mm : float, default 10.0
        Knot spacing along a line, mm; positive.
    margin_mm : float, default 10.0
        The knots' reach beyond the measured centres, mm; non-negative.
    curvature_sigma_mm : float, default 0.02
        Smoothness prior: std of a second difference of knot values, mm; positive.
    ridge_sigma_mm : float, default 0.2
        The ridge fixing a common shift of every line, mm; positive.
    centre_sigma_mm : float, default 0.005
        The per-centre measurement sigma that weighs the data, mm; positive.

    Raises
    ------
    ValueError
        On the first field that is not a finite number in its range.
    """

    knot_spacing_mm: float = 10.0
    margin_mm: float = 10.0
    curvature_sigma_mm: float = 0.02
    ridge_sigma_mm: float = 0.2
    centre_sigma_mm: float = 0.005

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        for name in ("knot_spacing_mm", "curvature_sigma_mm", "ridge_sigma_mm", "centre_sigma_mm"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value <= 0.0:
                raise ValueError(f"chain map fit {name} must be a positive finite number, got {value!r}")
        value = self.margin_mm
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0.0:
            raise ValueError(f"chain map fit margin_mm must be a non-negative finite number, got {value!r}")


def _spline_basis(knots: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(N, K) values of the natural cubic spline through unit knot values: the map is linear in them."""
    return CubicSpline(knots, np.eye(knots.size), bc_type="natural")(u)


def _checked_sweeps(sweeps: Sequence[ReferenceSweep]) -> list[tuple[str, int, np.ndarray, np.ndarray]]:
    if not isinstance(sweeps, (list, tuple)) or not sweeps:
        raise ValueError("a chain map needs one or more reference sweeps")
    checked = []
    for number, sweep in enumerate(sweeps):
        if not isinstance(sweep, ReferenceSweep):
            raise ValueError(f"reference sweep {number} must be a ReferenceSweep, got {type(sweep).__name__}")
        try:
            items = parse_plan(sweep.line) if isinstance(sweep.line, str) else ()
        except ValueError:
            items = ()
        if len(items) != 1:
            raise ValueError(f"reference sweep {number}: line must be one sweep plan item such as 0+, "
                             f"got {sweep.line!r}")
        label = items[0].label
        if isinstance(sweep.plate, bool) or not isinstance(sweep.plate, int) or sweep.plate < 0:
            raise ValueError(f"reference sweep {number}: plate must be a non-negative integer, got {sweep.plate!r}")
        known = np.asarray(sweep.known_xy_mm, dtype=float)
        measured = np.asarray(sweep.measured_xy_mm, dtype=float)
        if known.ndim != 2 or known.shape[1] != 2 or measured.ndim != 2 or measured.shape[1] < 2 \
                or len(known) != len(measured):
            raise ValueError(f"reference sweep {number}: known_xy_mm (M, 2) and measured_xy_mm (M, 2+) must pair "
                             f"up, got {known.shape} and {measured.shape}")
        if len(known) < 3:
            raise ValueError(f"reference sweep {number}: at least 3 centres are needed, got {len(known)}")
        if not (np.all(np.isfinite(known)) and np.all(np.isfinite(measured[:, :2]))):
            raise ValueError(f"reference sweep {number}: centres must be finite")
        checked.append((label, sweep.plate, known, measured[:, :2]))
    return checked


def fit_chain_map(sweeps: Sequence[ReferenceSweep], reference: str, fit: ChainMapFit = ChainMapFit()) -> ChainMap:
    """Fit the repeating error of every line that ``sweeps`` ran (see the module docstring).

    Parameters
    ----------
    sweeps : sequence of ReferenceSweep
        Sweeps of one or more placements of a plate with known centres, each paired with its known
        centres; several sweeps of the same line are averaged by the fit.
    reference : str
        The plate (and its certificate) the map was measured on; stored in the map.
    fit : ChainMapFit
        Knot spacing and priors.

    Returns
    -------
    ChainMap
        One :class:`LineMap` per line, knots covering that line's centres plus ``fit.margin_mm``.

    Raises
    ------
    ValueError
        For malformed sweeps, or when the placements' poses and the lines' maps cannot be told
        apart (the least-squares system is not finite).
    """
    checked = _checked_sweeps(sweeps)
    labels = sorted({label for label, *_ in checked})
    plates = sorted({plate for _, plate, *_ in checked})
    if not isinstance(reference, str) or not reference.strip():
        raise ValueError("chain map reference must name the plate with known centres")
    # Each plate's pose: a first rigid alignment of its known centres onto the mean of what its sweeps
    # measured; the fit then solves for small increments (translation, rotation) about it.
    poses = {}
    for plate in plates:
        known = np.vstack([k for _, p, k, _ in checked if p == plate])
        measured = np.vstack([m for _, p, _, m in checked if p == plate])
        alignment, _ = align_rigid_2d(known, measured)
        poses[plate] = alignment
    knots = {}
    for label in labels:
        u = np.concatenate([travel_coordinate(label, m) for lab, _, _, m in checked if lab == label])
        h = fit.knot_spacing_mm
        first = math.floor((u.min() - fit.margin_mm) / h) * h
        count = int(math.ceil((u.max() + fit.margin_mm - first) / h)) + 1
        if count > MAX_KNOTS:
            raise ValueError(f"line {label} spans {u.max() - u.min():g} mm: more than {MAX_KNOTS} knots")
        knots[label] = first + h * np.arange(max(count, 4))
    # unknowns: per plate (dx, dy, dtheta), then per line 2 x K knot values (x block, then y block)
    column = {}
    size = 3 * len(plates)
    for label in labels:
        column[label] = size
        size += 2 * knots[label].size
    rows, rhs = [], []
    sigma = fit.centre_sigma_mm
    for label, plate, known, measured in checked:
        predicted = poses[plate].apply(known)
        residual = measured - predicted
        about = predicted - poses[plate].apply(np.zeros((1, 2)))
        basis = _spline_basis(knots[label], travel_coordinate(label, measured))
        k = knots[label].size
        p = 3 * plates.index(plate)
        for component in (0, 1):
            block = np.zeros((len(known), size))
            block[:, p + component] = 1.0
            # small rotation about the plate's own origin: (-y, x) * dtheta
            block[:, p + 2] = -about[:, 1] if component == 0 else about[:, 0]
            start = column[label] + component * k
            block[:, start:start + k] = basis
            rows.append(block / sigma)
            rhs.append(residual[:, component] / sigma)
    for label in labels:
        k = knots[label].size
        second = np.diff(np.eye(k), n=2, axis=0)
        for component in (0, 1):
            start = column[label] + component * k
            block = np.zeros((k - 2, size))
            block[:, start:start + k] = second
            rows.append(block / fit.curvature_sigma_mm)
            rhs.append(np.zeros(k - 2))
            ridge = np.zeros((k, size))
            ridge[:, start:start + k] = np.eye(k)
            rows.append(ridge / fit.ridge_sigma_mm)
            rhs.append(np.zeros(k))
    design, target = np.vstack(rows), np.concatenate(rhs)
    solution, *_ = np.linalg.lstsq(design, target, rcond=None)
    if not np.all(np.isfinite(solution)):
        raise ValueError("the chain map fit did not converge to finite values; check the reference sweeps")
    line_maps = []
    for label in labels:
        k = knots[label].size
        start = column[label]
        line_maps.append(LineMap(label, float(knots[label][0]), fit.knot_spacing_mm,
                                 solution[start:start + k], solution[start + k:start + 2 * k]))
    # the data rows come first, per sweep an x block then a y block
    data_rows = 2 * sum(len(known) for _, _, known, _ in checked)
    residuals = (target[:data_rows] - design[:data_rows] @ solution) * sigma
    x_parts, y_parts, offset = [], [], 0
    for _, _, known, _ in checked:
        n = len(known)
        x_parts.append(residuals[offset:offset + n])
        y_parts.append(residuals[offset + n:offset + 2 * n])
        offset += 2 * n
    rms = tuple(float(np.sqrt(np.mean(np.concatenate(parts) ** 2))) for parts in (x_parts, y_parts))
    counts = [sum(1 for lab, *_ in checked if lab == label) for label in labels]
    return ChainMap(tuple(line_maps), reference=reference, sweeps_per_line=min(counts), residual_rms_mm=rms)


def chain_map_from_mapping(document: Any) -> ChainMap:
    """Return a :class:`ChainMap` from the parsed file (``{chain_map: {...}}``); ValueError naming the key."""
    if not isinstance(document, Mapping) or not isinstance(document.get("chain_map"), Mapping):
        raise ValueError("a chain map file holds one mapping 'chain_map'")
    block = dict(document["chain_map"])
    keys = ("reference", "sweeps_per_line", "residual_rms_mm", "lines")
    require_exact_keys(block, keys, "chain_map")
    lines = block["lines"]
    if not isinstance(lines, list) or not lines:
        raise ValueError("chain_map.lines must be a list of one or more line maps")
    line_keys = ("line", "first_knot_mm", "knot_spacing_mm", "error_x_mm", "error_y_mm")
    parsed = []
    for number, line in enumerate(lines):
        if not isinstance(line, Mapping):
            raise ValueError(f"chain_map.lines[{number}] must be a mapping")
        require_exact_keys(line, line_keys, f"chain_map.lines[{number}]")
        for key in ("error_x_mm", "error_y_mm"):
            if not isinstance(line[key], list) or not all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) for v in line[key]):
                raise ValueError(f"chain_map.lines[{number}].{key} must be a list of numbers")
        parsed.append(LineMap(**dict(line)))
    return ChainMap(tuple(parsed), block["reference"], block["sweeps_per_line"], block["residual_rms_mm"])


def load_chain_map(path: str | Path) -> ChainMap:
    """Read and validate a chain map file.

    Parameters
    ----------
    path : str or pathlib.Path
        The YAML file (one mapping ``chain_map``).

    Returns
    -------
    ChainMap
        The validated map.

    Raises
    ------
    ValueError
        Naming the file and the key, for an unreadable file or YAML or a bad value.
    """
    return read_config_file(path, "chain map file", chain_map_from_mapping)


def save_chain_map(path: str | Path, chain_map: ChainMap) -> None:
    """Write ``chain_map`` atomically as a chain map file.

    Parameters
    ----------
    path : str or pathlib.Path
        The YAML file to write.
    chain_map : ChainMap
        The map.

    Raises
    ------
    ValueError
        If ``chain_map`` is not a ChainMap.
    """
    if not isinstance(chain_map, ChainMap):
        raise ValueError(f"save_chain_map needs a ChainMap, got {type(chain_map).__name__}")
    atomic_write_text(path, yaml.safe_dump({"chain_map": chain_map.to_dict()}, sort_keys=False))
