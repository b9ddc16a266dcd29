"""Assembly of laser-line profiles into one organized cloud per sweep.

A laser-line scanner measures 2-D profiles in its own moving frame; the sweep's known motion (a
straight line at constant speed) places each profile: its points move by ``direction * speed *
(stamp - first stamp)``. Rows of the result are profiles in time order, columns the points of a
profile; profiles shorter than the widest are padded with NaN points.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

XYZI_FIELDS = ("x", "y", "z", "intensity")


@dataclass(frozen=True)
class SweepMotion:
    """Straight sweep at constant speed: unit direction in the scanner frame, speed (mm/s)."""

    direction: tuple[float, float, float]
    speed_mm_s: float

    def __post_init__(self) -> None:
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
    coordinates = np.stack([np.asarray(profile[name], dtype=np.float64).reshape(-1) for name in ("x", "y", "z")])
    if np.isinf(coordinates).any():
        return "profile has infinite coordinates"
    if not np.isfinite(coordinates).all(axis=0).any():
        return "profile has no finite point"
    return ""


class SweepCollector:
    """Collects the profiles of one sweep with a bound on their number (bounded memory)."""

    def __init__(self, max_profiles: int, max_points_per_profile: int) -> None:
        if max_profiles < 1 or max_points_per_profile < 1:
            raise ValueError("max_profiles and max_points_per_profile must be at least 1")
        self.max_profiles = max_profiles
        self.max_points = max_points_per_profile
        self._stamps: list[float] = []
        self._profiles: list[np.ndarray] = []
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._profiles)

    def add(self, stamp_s: float, profile: np.ndarray) -> bool:
        """Keep a copy of one profile (structured x, y, z, intensity); False when over a bound.

        ValueError (nothing kept) for a profile that cannot be placed: see :func:`profile_problem`.
        """
        problem = profile_problem(stamp_s, profile)
        if problem:
            raise ValueError(problem)
        if len(self._profiles) >= self.max_profiles or profile.size > self.max_points:
            self.dropped += 1
            return False
        flat = np.empty(profile.size, dtype=[(name, np.float32) for name in XYZI_FIELDS])
        for name in XYZI_FIELDS:
            flat[name] = profile[name].reshape(-1)
        self._stamps.append(float(stamp_s))
        self._profiles.append(flat)
        return True

    def assemble(self, motion: SweepMotion) -> np.ndarray:
        """The organized (profiles, points) structured cloud in the frame of the first profile."""
        if not self._profiles:
            raise ValueError("no profiles were received in this sweep")
        order = np.argsort(np.asarray(self._stamps), kind="stable")
        stamps = np.asarray(self._stamps)[order]
        width = max(profile.size for profile in self._profiles)
        cloud = np.full((len(order), width), np.nan,
                        dtype=[(name, np.float32) for name in XYZI_FIELDS])
        offsets = np.outer(stamps - stamps[0], np.asarray(motion.direction) * motion.speed_mm_s)
        for row, index in enumerate(order):
            profile = self._profiles[index]
            for axis, name in enumerate(("x", "y", "z")):
                cloud[name][row, :profile.size] = profile[name] + offsets[row, axis]
            cloud["intensity"][row, :profile.size] = profile["intensity"]
        return cloud
