"""The direct simulated cell recording what a real cell's drivers would stream into a rosbag2 bag.

Each sweep, and each stand-still acquisition (profiles taken with the robot standing at the marking
pose: a motion without travel), becomes, in the bag (:mod:`gls_calibration.scan.bag_io`): its motion's
start and end stamps, one PointCloud2 per profile in the scanner's optical frame in metres, and the
flange pose the robot reports (encoder pose, robot base -> flange) on ``/tf`` at each profile's stamp.
The robot base frame of the recording is the simulation's scanner base frame B (see
:mod:`gls_calibration.simulation.scanner`), so the calibration flow sees the same clouds live and on
replay. What the cell itself measures is placed from exactly the messages it writes (float32 metres; TF
in metres and quaternions), so that a replay can be compared with the live run: the cell measures what a
subscriber to its own streams assembles (:class:`~gls_calibration.scan.bag_io.StreamAssembler`, fed
every message as it is written), the same code a replay runs on the bag.
"""
from __future__ import annotations

import math

import numpy as np

from gls_calibration.calibration.core_cell import Cloud, refusing
from gls_calibration.fiducials.measure import FiducialMeasurement
from gls_calibration.scan.bag_io import NS_PER_S, MM_PER_M, BagRecorder, ReplayLimits, StreamAssembler
from gls_calibration.scan.plate_pose import PlatePose
from gls_calibration.simulation.direct_cell import DirectCell
from gls_calibration.simulation.scanner import pose_matrix

SIM_FLANGE_TO_SENSOR = pose_matrix([40.0, 0.0, 180.0], [0.0, 0.0, math.pi / 2])
"""The simulated hand-eye mounting (scanner optical frame -> flange, mm): 180 mm below the flange,
40 mm off its axis, turned a quarter turn, so that replay exercises a real chain."""
SWEEP_GAP_NS = NS_PER_S       # the robot's time between two sweeps (repositioning), nothing streamed
STREAM_AFTER_PROFILES = 5     # profiles the scanner streams after each motion's end (outside the sweep)
FIRST_STAMP_NS = 1_700_000_000 * NS_PER_S    # a fixed epoch, so that recordings are reproducible


class RecordingCell(DirectCell):
    """:class:`DirectCell` whose sweeps are written to ``recorder`` as they are acquired.

    ``live_poses`` and ``live_measurements`` keep what the calibration flow measured, in order, for a
    comparison with a replay of the bag.

    Parameters
    ----------
    *args, **kwargs
        As for :class:`DirectCell`.
    recorder : BagRecorder
        The open bag the sweeps are written to.

    Raises
    ------
    ValueError
        If the cell does not place profiles by the robot's pose (a replay does).
    """

    def __init__(self, *args, recorder: BagRecorder, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        if not self.placed_by_pose:
            raise ValueError("a recording cell places profiles by the robot's pose, as a replay does")
        self.recorder = recorder
        self.stream = StreamAssembler(recorder.layout, ReplayLimits(), "live stream")
        recorder.tap = self.stream.add
        self.live_poses: list[PlatePose] = []
        self.live_measurements: list[FiducialMeasurement] = []

    async def acquire_sweep(self, step_mm: float, direction: int = 1, orientation_deg: float = 0.0) -> Cloud:
        """Simulate a sweep as DirectCell does and record it."""
        self.sweeps += 1
        data = refusing(self.sim.sweep_data, step_mm=step_mm, seed=self.sim.config.seed * 100003 + self.sweeps,
                        direction=direction, orientation_deg=orientation_deg)
        return self._record(data)

    async def acquire_standstill(self, profiles: int) -> Cloud:
        """Simulate profiles standing still as DirectCell does and record them."""
        self.standstills += 1     # the same draws as DirectCell's
        data = refusing(self.sim.standstill_data, profiles, seed=self.sim.config.seed * 100003 + self.standstills)
        return self._record(data)

    def _record(self, data) -> Cloud:
        """Write one motion's stream and assemble it as a subscriber would.

        The stream holds the profiles, the flange poses and the motion's start and end.
        """
        sensor_mm = data.sensor_points()
        sensor_mm[..., 1] = np.where(np.isfinite(sensor_mm[..., 1]), 0.0, np.nan)   # a line sensor measures y = 0
        profiles_m = np.concatenate([sensor_mm / MM_PER_M, data.intensity[..., None]], axis=-1).astype(np.float32)
        start_ns = max(self.recorder.clock_ns + SWEEP_GAP_NS, FIRST_STAMP_NS)
        stamps_ns = start_ns + np.round(data.stamps_s * NS_PER_S).astype(np.int64)
        base_to_flange = data.reported_poses @ np.linalg.inv(SIM_FLANGE_TO_SENSOR)
        self.recorder.write_sweep(int(stamps_ns[0]), int(stamps_ns[-1]), stamps_ns, profiles_m, stamps_ns,
                                  base_to_flange)
        # the scanner keeps streaming for a moment after the robot stopped: not part of the sweep
        period_ns = int(stamps_ns[1] - stamps_ns[0]) if len(stamps_ns) > 1 else SWEEP_GAP_NS // 10
        after = int(stamps_ns[-1]) + period_ns * np.arange(1, STREAM_AFTER_PROFILES + 1)
        self.recorder.write_stream(after, np.repeat(profiles_m[-1:], after.size, axis=0), after,
                                   np.repeat(base_to_flange[-1:], after.size, axis=0))
        sweep = refusing(self.stream.take_last_sweep)
        return sweep.xyz_mm, sweep.intensity

    async def estimate_plate_pose(self, cloud: Cloud) -> PlatePose:
        """Plate pose as CoreCell, kept to compare with the replay."""
        pose = await super().estimate_plate_pose(cloud)
        self.live_poses.append(pose)
        return pose

    async def measure_fiducials(self, cloud: Cloud, pose: PlatePose, expected_count: int,
                                ring_radii_mm) -> FiducialMeasurement:
        """Fiducial centres as CoreCell, kept to compare with the replay."""
        found = await super().measure_fiducials(cloud, pose, expected_count, ring_radii_mm)
        self.live_measurements.append(found)
        return found


def base_to_gls(config) -> np.ndarray:
    """Return the galvo head's frame in the recording's robot base frame (mm).

    Parameters
    ----------
    config : SimConfig
        The simulated cell; its ``scanner_to_gls`` (the CAD mounting) is inverted.

    Returns
    -------
    numpy.ndarray, shape (4, 4)
        gls -> robot base, mm.
    """
    return np.linalg.inv(config.scanner_to_gls)
