"""The simulated cell split as a real one is: a robot and a line scanner streaming profiles.

The robot runs commanded straight lines of the flange, the scanner streams profiles; both are fed by
one simulation of each motion.

A line is commanded as the flange's start and end poses in the robot base frame (4x4, mm) and its
duration. The simulation turns it into the sensor's line through the cell's hand-eye
(``flange_to_sensor``) and computes the motion as :class:`~gls_calibration.simulation.direct_cell.DirectCell`
does (same draws for the same seed and sweep count): the profiles in the sensor's optical frame and
the sensor pose the robot REPORTS (its encoders) at each profile, from which the robot publishes the
flange pose. A line of no length is a stand-still at the marking pose. The simulated scanner takes
one profile every ``1 / profile_rate_hz`` s, so the step along the line is the speed over the rate.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from gls_calibration.registration.sweep_plan import ORIENTATIONS_DEG, ORIENTATIONS_TEXT
from gls_calibration.simulation.scanner import SweepData
from gls_calibration.simulation.world import SimulatedCell

NS_PER_S = 1_000_000_000
MM_PER_M = 1000.0
POSE_TOLERANCE_MM = 1e-6     # a commanded line must be one the simulation sweeps (its plan's lines)
STANDSTILL_LENGTH_MM = 1e-6  # a commanded line shorter than this is a stand-still
STEP_SNAP = 1e-6             # a line's steps within this of a whole number are that number (ns-stamped durations)
AFTER_PROFILES = 5           # profiles the scanner streams after a motion, the robot standing at its end


@dataclass(frozen=True)
class LineCommand:
    """A straight line of the flange: start and end poses (flange -> robot base, 4x4, mm), duration (s).

    Parameters
    ----------
    start_flange_mm, end_flange_mm : numpy.ndarray, shape (4, 4)
        Flange poses at the start and the end, mm.
    duration_s : float
        Duration of the motion, s.
    """

    start_flange_mm: np.ndarray
    end_flange_mm: np.ndarray
    duration_s: float


@dataclass(frozen=True)
class MotionRun:
    """One simulated motion: what the scanner streams and what the robot reports, stamped in ns.

    Parameters
    ----------
    start_ns, end_ns : int
        Stamps of the motion's start and end, ns.
    profile_stamps_ns : numpy.ndarray, shape (H,)
        The profiles' stamps, ns.
    profiles_m : numpy.ndarray, shape (H, W, 4)
        float32 x, y, z (m, optical frame, y = 0 on the line) and intensity.
    reported_flange_mm : numpy.ndarray, shape (H, 4, 4)
        The flange pose the robot reports at each profile's stamp, mm.
    data : SweepData
        The simulated sweep behind it.
    """

    start_ns: int
    end_ns: int
    profile_stamps_ns: np.ndarray
    profiles_m: np.ndarray
    reported_flange_mm: np.ndarray
    data: SweepData

    def flange_at(self, stamps_ns: np.ndarray) -> np.ndarray:
        """Return the reported flange poses (N, 4, 4) at ``stamps_ns``.

        Reported flange poses (N, 4, 4) at ``stamps_ns``: linear in time between the profiles' poses
        (slerp for the rotation), held before the first and after the last.
        """
        # Times from the motion's first profile: absolute ns (~1.8e18) as float64 keep only 256 ns, and the
        # poses would depend on when the motion ran (repeated simulated runs differed in the last digits).
        first = self.profile_stamps_ns[0]
        knots = (self.profile_stamps_ns - first).astype(float)
        times = np.clip((np.asarray(stamps_ns, dtype=np.int64) - first).astype(float), knots[0], knots[-1])
        poses = np.repeat(np.eye(4)[None], times.size, axis=0)
        for axis in range(3):
            poses[:, axis, 3] = np.interp(times, knots, self.reported_flange_mm[:, axis, 3])
        if knots.size == 1:
            poses[:, :3, :3] = self.reported_flange_mm[0, :3, :3]
        else:
            poses[:, :3, :3] = Slerp(knots, Rotation.from_matrix(self.reported_flange_mm[:, :3, :3]))(times).as_matrix()
        return poses

    @property
    def profile_period_ns(self) -> int:
        """Time between two profiles (ns); 0.1 s for a motion of one profile."""
        stamps = self.profile_stamps_ns
        return int(stamps[1] - stamps[0]) if stamps.size > 1 else NS_PER_S // 10

    @property
    def streamed_until_ns(self) -> int:
        """Stamp of the last profile the scanner streams for this motion (the last of :meth:`after_profiles`)."""
        return self.end_ns + self.profile_period_ns * AFTER_PROFILES

    def after_profiles(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the stamps (ns) and profiles the scanner streams after the motion's end.

        Stamps (ns) and profiles the scanner streams after the motion's end (the robot stands at its
        end: the last profile again), as a running sensor keeps streaming.
        """
        stamps = self.end_ns + self.profile_period_ns * np.arange(1, AFTER_PROFILES + 1, dtype=np.int64)
        return stamps, np.repeat(self.profiles_m[-1:], AFTER_PROFILES, axis=0)


class SimulatedLineMotion:
    """Runs commanded lines on a :class:`SimulatedCell` (its plate, scanner and robot errors).

    Parameters
    ----------
    sim : SimulatedCell
        The simulated cell.
    flange_to_sensor : numpy.ndarray, shape (4, 4)
        The hand-eye, sensor -> flange, mm.
    profile_rate_hz : float
        The scanner's profile rate, Hz; positive.

    Raises
    ------
    ValueError
        If ``profile_rate_hz`` is not positive.
    """

    def __init__(self, sim: SimulatedCell, flange_to_sensor: np.ndarray, profile_rate_hz: float) -> None:
        if not (np.isfinite(profile_rate_hz) and profile_rate_hz > 0.0):
            raise ValueError(f"profile_rate_hz must be positive, got {profile_rate_hz!r}")
        self.sim = sim
        self.flange_to_sensor = np.asarray(flange_to_sensor, dtype=float)
        self.profile_rate_hz = float(profile_rate_hz)
        self.sweeps = 0
        self.standstills = 0

    def run(self, command: LineCommand, start_ns: int) -> MotionRun:
        """Simulate ``command`` starting at ``start_ns``; ValueError for a line the simulation cannot run."""
        if not (np.isfinite(command.duration_s) and command.duration_s > 0.0):
            raise ValueError(f"a line needs a positive duration, got {command.duration_s!r} s")
        start = command.start_flange_mm @ self.flange_to_sensor
        end = command.end_flange_mm @ self.flange_to_sensor
        if not np.allclose(start[:3, :3], end[:3, :3], atol=1e-9):
            raise ValueError("the sensor turns during the line: the simulation runs lines of fixed orientation")
        travel = end[:3, 3] - start[:3, 3]
        length = float(np.linalg.norm(travel))
        seed = self.sim.config.seed * 100003
        if length < STANDSTILL_LENGTH_MM:
            data = self._standstill(command, start, seed)
        else:
            data = self._sweep(command, start, travel, length, seed)
        return self._stamped(data, start_ns)

    def _standstill(self, command: LineCommand, start: np.ndarray, seed: int) -> SweepData:
        expected = np.eye(4)
        expected[1, 3] = 0.5 * self.sim.config.sweep_length_mm
        if not np.allclose(start, expected, atol=POSE_TOLERANCE_MM):
            raise ValueError("a stand-still is simulated at the marking pose, sensor at "
                             f"{expected[:3, 3].tolist()} mm, "
                             f"orientation 0; commanded at {start[:3, 3].tolist()} mm")
        profiles = int(round(command.duration_s * self.profile_rate_hz)) + 1
        self.standstills += 1
        return self.sim.standstill_data(profiles, seed=seed + self.standstills)

    def _sweep(self, command: LineCommand, start: np.ndarray, travel: np.ndarray, length: float,
               seed: int) -> SweepData:
        along = start[:3, :3].T @ travel / length            # the travel in the sensor's frame: +-y
        direction = int(round(along[1]))
        turn = float(np.degrees(np.arctan2(start[1, 0], start[0, 0])))
        orientation = min(ORIENTATIONS_DEG, key=lambda value: abs(value - turn))
        scanner = self.sim.scanner
        if direction not in (1, -1) or not np.allclose(start, scanner.start_pose(length, direction, orientation),
                                                       atol=POSE_TOLERANCE_MM):
            raise ValueError("the simulation sweeps the lines of its sweep plan only (sensor along its y, orientation "
                             f"{ORIENTATIONS_TEXT} deg, centred on the plate); this line is not one of them")
        speed = length / command.duration_s
        step = speed / self.profile_rate_hz
        steps = round(length / step)
        if abs(length / step - steps) < STEP_SNAP:   # a duration in whole ns: the step of the intended count
            step = length / steps
        self.sweeps += 1
        return scanner.sweep_data(self.sim.plate, length, speed, step,
                                  seed=seed + self.sweeps, direction=direction, orientation_deg=orientation)

    def _stamped(self, data: SweepData, start_ns: int) -> MotionRun:
        sensor_mm = data.sensor_points()
        sensor_mm[..., 1] = np.where(np.isfinite(sensor_mm[..., 1]), 0.0, np.nan)   # a line sensor measures y = 0
        profiles_m = np.concatenate([sensor_mm / MM_PER_M, data.intensity[..., None]], axis=-1).astype(np.float32)
        rows = profiles_m.shape[0]
        stamps = int(start_ns) + np.round(np.arange(rows) * (NS_PER_S / self.profile_rate_hz)).astype(np.int64)
        flange = data.reported_poses @ np.linalg.inv(self.flange_to_sensor)
        return MotionRun(int(stamps[0]), int(stamps[-1]), stamps, profiles_m, flange, data)
