"""Assembly of laser-line profiles into one organized cloud per sweep.

A laser-line scanner measures 2-D profiles in its own moving frame. Each profile is placed

- *by pose* when the robot reports the sensor's pose as a stamped stream (its encoders): the pose
  interpolated at the profile's stamp (linear in position, slerp in rotation) maps the profile's
  points into the scanner base frame. Speed error and ripple then cost nothing; what the encoders
  cannot see (the path's structural wander) remains;
- *by time* otherwise (a driver without a pose stream): the sweep's nominal motion, a straight line
  at constant speed, moves the points by ``direction * speed * (stamp - first stamp)`` in the
  sweep's start frame, which the sweep's nominal start pose maps into the base frame. Speed error
  and ripple of the robot go straight into the cloud.

The base frame B is the sensor's nominal pose at the start of a default sweep (forward, not turned);
a sweep of length L covers L centred on (0, L/2, 0) of B, travelling along the sensor's +y
(``direction`` +1) or -y (-1), with the sensor turned by ``orientation_deg`` about its viewing axis.
Rows of the result are profiles in time order, columns the points of a profile; profiles shorter
than the widest are padded with NaN points.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Optional

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

XYZI_FIELDS = ("x", "y", "z", "intensity")
XYZI_DTYPE = np.dtype([(name, np.float32) for name in XYZI_FIELDS])
"""A kept profile's and an assembled cloud's points: x, y, z, intensity, float32, packed."""


@dataclass(frozen=True)
class ProfileRules:
    """What a profile must be to join a running sweep: the one owner of these limits.

    Parameters
    ----------
    field_type : str
        numpy name of the type the sensor declares for x, y, z and intensity (default "float32", what
        the package's drivers publish). A profile whose fields declare another type is dropped.
    big_endian : bool
        Byte order the sensor declares (default False: little-endian, every ROS 2 platform). A profile
        with the other ``is_bigendian`` flag is dropped.
    max_points : int
        Most points of one profile (default 4096); a wider profile is dropped, the sweep goes on.
    stamp_window_factor : float
        A sweep's profiles are stamped within (profiles - 1) step / speed of each other; the window
        that holds them is this many times longer (default 1.5: room for a robot slower than
        commanded) ...
    stamp_window_margin_s : float
        ... plus this (default 1.0 s). A profile stamped outside it (zero, far in the future, another
        sweep's) is not of the sweep.
    count_slack : int
        Profiles by which a scanner's announced count may differ from length / step + 1 (default 1:
        the driver's rounding) before the mismatch is reported.
    """

    field_type: str = "float32"
    big_endian: bool = False
    max_points: int = 4096
    stamp_window_factor: float = 1.5
    stamp_window_margin_s: float = 1.0
    count_slack: int = 1

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        if self.field_type not in ("float32", "float64"):
            raise ValueError(f"profile field type must be float32 or float64, got {self.field_type!r}")
        if self.max_points < 1 or self.count_slack < 0:
            raise ValueError(f"max_points must be at least 1 and count_slack at least 0, got {self.max_points} "
                             f"and {self.count_slack}")
        if not (math.isfinite(self.stamp_window_factor) and self.stamp_window_factor >= 1.0
                and math.isfinite(self.stamp_window_margin_s) and self.stamp_window_margin_s >= 0.0):
            raise ValueError("the stamp window needs a finite factor of at least 1 and a finite margin of at "
                             f"least 0 s, got {self.stamp_window_factor} and {self.stamp_window_margin_s} s")

    def describe(self) -> str:
        """Return the declared format in words, e.g. 'float32, little-endian'."""
        return f"{self.field_type}, {'big' if self.big_endian else 'little'}-endian"

    def format_problem(self, field_types: dict[str, str], big_endian: bool) -> str:
        """Say why a profile's fields are not in the sensor's declared format (empty if they are).

        Why a profile whose fields declare ``field_types`` (name -> numpy type name) and byte order
        ``big_endian`` is not in the sensor's declared format (empty when it is; a missing field is
        for :func:`profile_problem`).
        """
        if bool(big_endian) != self.big_endian:
            return f"byte order {'big' if big_endian else 'little'}-endian, the sensor declares {self.describe()}"
        other = {name: kind for name, kind in field_types.items() if name in XYZI_FIELDS and kind != self.field_type}
        if other:
            listed = ", ".join(f"{name} {kind}" for name, kind in other.items())
            return f"fields {listed}, the sensor declares {self.describe()}"
        return ""

    def announcement_problem(self, announced: int, length_mm: float, step_mm: float) -> str:
        """Say why an announced profile count contradicts a sweep's length and step (empty if not).

        Why a scanner's announced profile count contradicts a sweep's length and step (empty when
        it does not, or when either is 0: left to the driver): floor(L / s) + 1 profiles, within
        ``count_slack``.
        """
        if length_mm <= 0.0 or step_mm <= 0.0:
            return ""
        expected = math.floor(length_mm / step_mm + 1e-9) + 1
        if abs(int(announced) - expected) <= self.count_slack:
            return ""
        return (f"the scanner announced {announced} profiles for {length_mm:g} mm every {step_mm:g} mm, which "
                f"gives {expected}")

    def stamp_window_s(self, profiles: int, step_mm: float, speed_mm_s: float) -> float:
        """Length (s) of the time window that holds every profile of a sweep of ``profiles`` profiles."""
        span = max(profiles - 1, 0) * step_mm / speed_mm_s if speed_mm_s > 0.0 else math.inf
        return self.stamp_window_factor * span + self.stamp_window_margin_s if math.isfinite(span) else math.inf


@dataclass(frozen=True)
class SweepMotion:
    """Straight sweep at constant speed: unit direction in the scanner frame, speed (mm/s).

    Parameters
    ----------
    direction : tuple of 3 float
        Unit direction of travel in the scanner frame.
    speed_mm_s : float
        Speed, mm/s; positive.

    Raises
    ------
    ValueError
        If ``direction`` is not a unit vector or the speed is not positive and finite.
    """

    direction: tuple[float, float, float]
    speed_mm_s: float

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        norm = float(np.linalg.norm(self.direction))
        if not np.isfinite(norm) or abs(norm - 1.0) > 1e-6:
            raise ValueError(f"sweep direction must be a unit vector, got {self.direction}")
        if not np.isfinite(self.speed_mm_s) or self.speed_mm_s <= 0.0:
            raise ValueError(f"sweep speed must be positive, got {self.speed_mm_s} mm/s")


def profile_problem(stamp_s: float, profile: np.ndarray) -> str:
    """Why one profile cannot be part of a sweep (empty string when it can).

    Each of x, y, z, intensity must be one number per point (count 1); the stamp must be finite and
    not negative; the coordinates must not be infinite, and at least one point must be finite (a
    missing return is a NaN point, a profile of NaN points carries nothing).
    """
    if not np.isfinite(stamp_s) or stamp_s < 0.0:
        return f"profile stamp {stamp_s!r} s is not a finite non-negative time"
    names = profile.dtype.names or ()
    missing = [name for name in XYZI_FIELDS if name not in names]
    if missing:
        return f"profile has no field {', '.join(missing)} (fields: {', '.join(names) or 'none'})"
    for name in XYZI_FIELDS:
        if profile.dtype[name].shape != ():
            return f"profile field {name} has count {int(np.prod(profile.dtype[name].shape))}; 1 is expected"
    if profile.size == 0:
        return "profile has no points"
    # In the profile's own precision, one field at a time (no float64 copy of the profile).
    coordinates = [np.asarray(profile[name]).reshape(-1) for name in ("x", "y", "z")]
    if any(np.isinf(values).any() for values in coordinates):
        return "profile has infinite coordinates"
    finite = np.isfinite(coordinates[0]) & np.isfinite(coordinates[1]) & np.isfinite(coordinates[2])
    if not finite.any():
        return "profile has no finite point"
    if not any(np.any(values[finite]) for values in coordinates):
        return "profile has every point at the sensor's origin (0, 0, 0): not a measurement"
    return ""


def median_point_distance(xyz: np.ndarray) -> float:
    """Return the median distance of the finite points from the sensor's origin.

    A profile's unit shows in it: a line scanner sees its plate tens to hundreds of mm away.

    Parameters
    ----------
    xyz : numpy.ndarray, shape (N, 3)
        Points in the sensor frame, any unit.

    Returns
    -------
    float
        The median distance, in the points' unit; NaN when none is finite.

    Examples
    --------
    >>> median_point_distance(np.array([[0.0, 0.0, 0.2], [0.0, 0.3, 0.4], [np.nan, 0.0, 0.0]]))
    0.35
    """
    xyz = np.asarray(xyz, dtype=float)
    squared = np.einsum("...i,...i->...", xyz, xyz)     # linalg.norm, several times faster on (N, 3)
    squared = squared[np.isfinite(squared)].ravel()
    if not squared.size:
        return math.nan
    # np.median's value without its sort of every distance: the middle one or two of the squared distances
    # (the root keeps their order), their roots averaged as np.median averages them
    middle = squared.size // 2
    if squared.size % 2:
        return float(np.sqrt(np.partition(squared, middle)[middle]))
    low, high = np.sqrt(np.partition(squared, (middle - 1, middle))[middle - 1:middle + 1])
    return float((low + high) / 2.0)


# The unit check of a profile: at most this many of its points, evenly spaced, decide it when their median
# distance lies well inside the limits (by UNIT_CHECK_MARGIN); otherwise every point decides.
UNIT_CHECK_POINTS = 128
UNIT_CHECK_MARGIN = 4.0


def unit_check_distance(xyz: np.ndarray, low: float, high: float) -> float:
    """Return the median point distance that decides whether a profile lies within ``[low, high]``.

    A unit check only tells metres from millimetres (a factor of 1000), so a bounded, evenly spaced
    subsample gives the same verdict as every point: every k-th point, at most ``UNIT_CHECK_POINTS``
    of them, its finite points' median (:func:`median_point_distance`) returned when it lies within
    ``[low * UNIT_CHECK_MARGIN, high / UNIT_CHECK_MARGIN]``. Otherwise (near or beyond a limit, or no
    finite point sampled) every point's median is returned, the exact value a message names. Only a
    profile whose sampled points' median lies that well inside while the median of all its points
    lies outside could be judged otherwise than by every point: more than half of its points beyond a
    limit and more than half of the sampled ones a factor of ``UNIT_CHECK_MARGIN`` inside it.

    Parameters
    ----------
    xyz : numpy.ndarray, shape (N, 3)
        Points in the sensor frame, any unit.
    low : float
        Lowest median distance that passes, in the points' unit (0 for none).
    high : float
        Highest median distance that passes, in the points' unit.

    Returns
    -------
    float
        A median distance on the same side of the limits as every point's (that median itself unless
        the subsample's lies well inside); NaN when no point is finite.

    Examples
    --------
    >>> xyz = np.column_stack([np.linspace(-0.1, 0.1, 1000), np.zeros(1000), np.full(1000, 0.3)])
    >>> 0.3 <= unit_check_distance(xyz, 0.0, 10.0) <= 0.32
    True
    >>> round(unit_check_distance(xyz * 1000.0, 0.0, 10.0), 4) == round(median_point_distance(xyz * 1000.0), 4)
    True
    """
    xyz = np.asarray(xyz)
    if xyz.ndim == 2 and xyz.shape[0] > UNIT_CHECK_POINTS:
        sampled = median_point_distance(xyz[::-(-xyz.shape[0] // UNIT_CHECK_POINTS)])
        if low * UNIT_CHECK_MARGIN <= sampled <= high / UNIT_CHECK_MARGIN:     # False for NaN
            return sampled
    return median_point_distance(xyz)


SWEEP_LENGTH_MM = 210.0
"""Default length of a sweep, mm: the 190 mm grid, its 2.7 mm outer rings and
``procedure.SWEEP_END_MARGIN_MM`` at each end need 203.4 mm; 210 mm is also the simulated
scanner's line, so the 0 and 90 deg passes cover the same square (the 200 mm sweep cut corner
rings: 8 of 9 found on 3x3 grids)."""


SCANNER_STANDOFF_MM = 325.0
"""Nominal distance of the line scanner above the work plane, mm (the default mounting's and the
simulated scanner's; a real cell states its own in ``scanner_to_gls.translation_mm``)."""


def nominal_mounting(length_mm: float = SWEEP_LENGTH_MM,
                     standoff_mm: float = SCANNER_STANDOFF_MM) -> tuple[list[float], list[float]]:
    """Return the CAD mounting (sweep start frame -> gls frame) of a scanner that sweeps the gls field.

    The one owner of the head's pose at a sweep's start: the scanner looks straight down from
    ``standoff_mm`` (turned half a turn about x, so its z points at the plate) and its sweeps' middle
    (:func:`sweep_middle_mm`) lies over the gls origin. ``config/gls.yaml``, ``config/sim.yaml`` and
    ``config/cell_frames.yaml`` write the same pose for the default sweep (test_head_pose).

    Parameters
    ----------
    length_mm : float, default SWEEP_LENGTH_MM
        Length of the sweeps, mm.
    standoff_mm : float, default SCANNER_STANDOFF_MM
        Height of the scanner above the gls plane, mm.

    Returns
    -------
    translation_mm : list of 3 float
        The start frame's origin in the gls frame, mm.
    rpy_rad : list of 3 float
        Roll, pitch, yaw about the fixed axes x, y, z, rad.

    Examples
    --------
    >>> nominal_mounting(200.0, 300.0)
    ([0.0, 100.0, 300.0], [3.141592653589793, 0.0, 0.0])
    """
    middle = sweep_middle_mm(length_mm)
    return [float(middle[0]), float(middle[1]), float(standoff_mm)], [math.pi, 0.0, 0.0]


def stamp_window_s(profiles: int, step_mm: float, speed_mm_s: float, rules: ProfileRules = ProfileRules()) -> float:
    """Length (s) of the time window that holds every profile of a sweep (see :class:`ProfileRules`)."""
    return rules.stamp_window_s(profiles, step_mm, speed_mm_s)


def sweep_middle_mm(length_mm: float) -> np.ndarray:
    """Return the middle (2,) of every nominal sweep of ``length_mm`` in the base frame's x-y, mm.

    Every pass of a plan, forward or back and turned or not, runs through this point: the sensor is
    turned about it (:func:`nominal_start_pose`), so a point's coordinate along the sensor's line is
    measured from here.

    Parameters
    ----------
    length_mm : float
        Length of the sweeps, mm.

    Returns
    -------
    numpy.ndarray, shape (2,)
        The middle's x and y in the base frame, mm.

    Examples
    --------
    >>> sweep_middle_mm(200.0).tolist()
    [0.0, 100.0]
    """
    return np.array([0.0, 0.5 * float(length_mm)])


def nominal_start_pose(length_mm: float, direction: int = 1, orientation_deg: float = 0.0) -> np.ndarray:
    """Return the sensor's 4x4 pose (start frame -> base frame, mm) at the first profile of a sweep.

    Parameters
    ----------
    length_mm : float
        Length of the sweep, mm.
    direction : int, default 1
        +1 or -1: the sweep travels along the sensor's +y or -y.
    orientation_deg : float, default 0.0
        Turn of the sensor about its viewing axis, degrees.

    Returns
    -------
    numpy.ndarray, shape (4, 4)
        The pose; the sweep's middle lies at y = length_mm / 2 of the base frame.

    Raises
    ------
    ValueError
        If ``direction`` is not +1 or -1.

    Examples
    --------
    >>> nominal_start_pose(100.0, direction=-1)[:3, 3]
    array([  0., 100.,   0.])
    """
    if direction not in (1, -1):
        raise ValueError(f"sweep direction must be +1 or -1, got {direction!r}")
    angle = math.radians(orientation_deg)
    cos, sin = round(math.cos(angle), 15), round(math.sin(angle), 15)
    pose = np.eye(4)
    pose[:3, :3] = [[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = (np.append(sweep_middle_mm(length_mm), 0.0)
                   - pose[:3, :3] @ np.array([0.0, direction * 0.5 * length_mm, 0.0]))
    return pose


class PoseTrack:
    """Stamped sensor poses (sensor -> base frame, mm) reported by the robot during one sweep.

    Parameters
    ----------
    max_poses : int
        Most poses kept (bounded memory); later ones are ignored.
    """

    def __init__(self, max_poses: int) -> None:
        self.max_poses = max_poses
        self._stamps: list[float] = []
        self._positions: list[tuple[float, float, float]] = []
        self._quaternions: list[tuple[float, float, float, float]] = []

    def __len__(self) -> int:
        """Return the number of poses kept."""
        return len(self._stamps)

    def add(self, stamp_s: float, position_mm, quaternion_xyzw) -> bool:
        """Keep one reported pose; False (ignored) when over the bound or not finite."""
        values = np.concatenate([[stamp_s], np.asarray(position_mm, float), np.asarray(quaternion_xyzw, float)])
        if len(self._stamps) >= self.max_poses or values.shape != (8,) or not np.all(np.isfinite(values)) \
                or np.linalg.norm(values[4:]) < 1e-9:
            return False
        self._stamps.append(float(stamp_s))
        self._positions.append(tuple(values[1:4]))
        self._quaternions.append(tuple(values[4:]))
        return True

    def covers(self, stamps_s: np.ndarray, tolerance_s: float = 1e-6) -> bool:
        """Return True when every stamp lies within the reported poses' time span."""
        if len(self._stamps) < 2:
            return len(self._stamps) == 1 and bool(np.all(np.abs(stamps_s - self._stamps[0]) <= tolerance_s))
        return bool(stamps_s.min() >= min(self._stamps) - tolerance_s
                    and stamps_s.max() <= max(self._stamps) + tolerance_s)

    def at(self, stamps_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotations (n, 3, 3) and positions (n, 3) interpolated at ``stamps_s`` (inside the span)."""
        order = np.argsort(self._stamps, kind="stable")
        stamps = np.asarray(self._stamps)[order]
        keep = np.concatenate([[True], np.diff(stamps) > 0.0])     # one pose per stamp
        stamps = stamps[keep]
        positions = np.asarray(self._positions)[order][keep]
        rotations = Rotation.from_quat(np.asarray(self._quaternions)[order][keep])
        if stamps.size == 1:
            count = len(stamps_s)
            return np.repeat(rotations.as_matrix(), count, axis=0), np.repeat(positions, count, axis=0)
        clipped = np.clip(stamps_s, stamps[0], stamps[-1])
        moved = np.column_stack([np.interp(clipped, stamps, positions[:, axis]) for axis in range(3)])
        return Slerp(stamps, rotations)(clipped).as_matrix(), moved


class SweepCollector:
    """Collects the profiles of one sweep with a bound on their number (bounded memory).

    Profiles that well-formed junk could slip in among the sweep's are told apart at the end
    (:meth:`members`): the sweep is the largest set of profiles with one wire layout (field types,
    byte order) whose stamps fit in the sweep's time window; the others are not assembled.

    Parameters
    ----------
    max_profiles : int
        Most profiles kept; more truncate the sweep (counted in ``dropped``).
    max_points_per_profile : int
        Most points of one profile; a wider one is dropped (counted in ``too_wide``).

    Raises
    ------
    ValueError
        If either bound is below 1.
    """

    def __init__(self, max_profiles: int, max_points_per_profile: int) -> None:
        if max_profiles < 1 or max_points_per_profile < 1:
            raise ValueError("max_profiles and max_points_per_profile must be at least 1")
        self.max_profiles = max_profiles
        self.max_points = max_points_per_profile
        self._stamps: list[float] = []
        self._profiles: list[np.ndarray] = []
        self._layouts: list[object] = []
        self.dropped = 0        # over max_profiles: the sweep is truncated
        self.too_wide = 0       # over max_points_per_profile: dropped, the sweep goes on

    def __len__(self) -> int:
        """Return the number of profiles kept."""
        return len(self._profiles)

    def add(self, stamp_s: float, profile: np.ndarray, layout: object = None) -> bool:
        """Keep a copy of one profile (structured x, y, z, intensity); False when over a bound.

        ``layout`` (hashable) names the profile's wire layout; profiles of another layout than most
        of the sweep's are not assembled. ValueError (nothing kept) for a profile that cannot be
        placed: see :func:`profile_problem`.
        """
        problem = profile_problem(stamp_s, profile)
        if problem:
            raise ValueError(problem)
        if profile.size > self.max_points:
            self.too_wide += 1
            return False
        if len(self._profiles) >= self.max_profiles:
            self.dropped += 1
            return False
        if profile.dtype == XYZI_DTYPE:
            # the wire's own layout: copied as plain float32 (a structured copy is 10x slower)
            flat = profile.reshape(-1).view(np.float32).copy().view(XYZI_DTYPE)
        else:
            flat = np.empty(profile.size, dtype=XYZI_DTYPE)
            for name in XYZI_FIELDS:
                flat[name] = profile[name].reshape(-1)
        self._stamps.append(float(stamp_s))
        self._profiles.append(flat)
        self._layouts.append(layout)
        return True

    def members(self, window_s: float = math.inf) -> np.ndarray:
        """Return a boolean mask of the kept profiles that form the sweep.

        Boolean mask of the kept profiles that form the sweep: the most common layout, and of
        those the most that fit in one time window of ``window_s`` (see :func:`stamp_window_s`).
        """
        mask = np.zeros(len(self._profiles), dtype=bool)
        if not self._profiles:
            return mask
        layouts = {}
        for layout in self._layouts:
            layouts[layout] = layouts.get(layout, 0) + 1
        common = max(layouts, key=layouts.get)       # ties: the layout that came first
        same = np.array([layout == common for layout in self._layouts])
        stamps = np.asarray(self._stamps)
        ordered = np.sort(stamps[same])
        ends = np.searchsorted(ordered, ordered + window_s, side="right")
        first = int(np.argmax(ends - np.arange(len(ordered))))
        return same & (stamps >= ordered[first]) & (stamps <= ordered[first] + window_s)

    def stamps_s(self, members: np.ndarray) -> np.ndarray:
        """Return the stamps (s) of the profiles ``members`` selects, in arrival order."""
        return np.asarray(self._stamps, dtype=float)[np.asarray(members, dtype=bool)]

    def first_stamp_s(self, members: np.ndarray) -> float:
        """Return the earliest stamp (s) of the profiles ``members`` selects."""
        return float(np.min(self.stamps_s(members)))

    def assemble(self, motion: SweepMotion, start_pose: Optional[np.ndarray] = None,
                 poses: Optional[PoseTrack] = None, members: Optional[np.ndarray] = None) -> tuple[np.ndarray, bool]:
        """Return the organized (profiles, points) structured cloud in the base frame, and whether by pose.

        Placed by ``poses`` when they cover every profile's stamp, else by ``motion`` in the start
        frame mapped by ``start_pose`` (4x4, start frame -> base frame; None: the identity).
        ``members`` (a mask from :meth:`members`) selects the profiles; default: all kept.
        """
        chosen = np.ones(len(self._profiles), dtype=bool) if members is None else np.asarray(members, dtype=bool)
        if not chosen.any():
            raise ValueError("no profiles were received in this sweep")
        order = np.flatnonzero(chosen)[np.argsort(np.asarray(self._stamps)[chosen], kind="stable")]
        stamps = np.asarray(self._stamps)[order]
        by_pose = poses is not None and poses.covers(stamps)
        if by_pose:
            rotations, translations = poses.at(stamps)
        else:
            pose = np.eye(4) if start_pose is None else np.asarray(start_pose, dtype=float)
            rotations = np.repeat(pose[None, :3, :3], len(order), axis=0)
            travel = np.outer(stamps - stamps[0], np.asarray(motion.direction) * motion.speed_mm_s)
            translations = travel @ pose[:3, :3].T + pose[:3, 3]
        width = max(self._profiles[index].size for index in order)
        # every row is written below, a narrower one padded with NaN points (np.full of a structured
        # NaN costs more than the placement)
        cloud = np.empty((len(order), width), dtype=XYZI_DTYPE)
        rows = cloud.view(np.float32).reshape(len(order), width, 4)     # x, y, z, intensity of each point
        # Each row as one affine product into reused float64 buffers: the point (x, y, z, 1) times
        # [R^T; t] gives (x', y', z', 0), written as one contiguous row; the intensity is copied after.
        # About 9 us a row of 2 000 points against 60 us for a fresh float64 copy, a product, a sum and
        # four field writes.
        homogeneous, placed = np.empty((width, 4)), np.empty((width, 4))
        affine = np.zeros((len(order), 4, 4))
        affine[:, :3, :3] = np.swapaxes(rotations, 1, 2)
        affine[:, 3, :3] = translations
        for row, index in enumerate(order):
            profile = self._profiles[index].view(np.float32).reshape(-1, 4)
            size = profile.shape[0]
            np.copyto(homogeneous[:size], profile)
            homogeneous[:size, 3] = 1.0
            np.matmul(homogeneous[:size], affine[row], out=placed[:size])
            rows[row, :size] = placed[:size]
            rows[row, :size, 3] = profile[:, 3]
            rows[row, size:] = np.nan
        return cloud, by_pose
