"""Placing profiles by the robot's reported pose, and by time as the fallback."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gls_calibration.scan.sweep import PoseTrack, SweepCollector, SweepMotion, XYZI_FIELDS, nominal_start_pose

SPEED = 15.0
STEP = 0.5


def profile(x, z):
    points = np.zeros(len(x), dtype=[(name, np.float32) for name in XYZI_FIELDS])
    points["x"], points["z"], points["intensity"] = x, z, 0.5
    return points


def true_travel(stamps):
    """Travel (mm) of a robot with a 0.3 % speed error and a ripple: what placing by time gets wrong."""
    return 1.003 * SPEED * stamps + 0.05 * np.sin(2 * np.pi * stamps * SPEED / 15.0)


def collect(rng, count=200, pose_every=1, orientation_deg=0.0, direction=1, tilt_rad=0.0):
    """A sweep of ``count`` profiles with its reported poses; returns the collector, poses, truth."""
    stamps = np.arange(count) * STEP / SPEED + 0.013
    start = nominal_start_pose(count * STEP, direction, orientation_deg)
    collector, poses = SweepCollector(1000, 100), PoseTrack(1000)
    x = np.linspace(-50, 50, 11)
    truth = []
    for index, stamp in enumerate(stamps):
        rotation = start[:3, :3] @ Rotation.from_rotvec([tilt_rad * math.sin(index / 30.0), 0, 0]).as_matrix()
        position = start[:3, 3] + start[:3, :3] @ np.array([0.0, direction * true_travel(stamp - stamps[0]), 0.0])
        z = 325.0 + rng.normal(0, 0.01, x.size)
        collector.add(stamp, profile(x, z))
        if index % pose_every == 0 or index == count - 1:
            poses.add(stamp, position, Rotation.from_matrix(rotation).as_quat())
        truth.append(np.column_stack([x, np.zeros_like(x), z]) @ rotation.T + position)
    return collector, poses, np.array(truth)


def xyz(cloud):
    return np.stack([cloud[name] for name in ("x", "y", "z")], axis=-1).astype(float)


@pytest.mark.parametrize("orientation_deg, direction", [(0.0, 1), (0.0, -1), (90.0, 1), (90.0, -1)])
def test_profiles_placed_by_pose_land_where_they_were_taken(orientation_deg, direction):
    collector, poses, truth = collect(np.random.default_rng(1), orientation_deg=orientation_deg,
                                      direction=direction, tilt_rad=1e-3)
    cloud, by_pose = collector.assemble(SweepMotion((0.0, float(direction), 0.0), SPEED),
                                        nominal_start_pose(100.0, direction, orientation_deg), poses)
    assert by_pose
    assert np.max(np.abs(xyz(cloud) - truth)) < 1e-3          # float32 storage only


def test_placing_by_time_carries_the_robots_speed_error():
    collector, poses, truth = collect(np.random.default_rng(2))
    cloud, by_pose = collector.assemble(SweepMotion((0.0, 1.0, 0.0), SPEED), nominal_start_pose(100.0))
    assert not by_pose
    error = np.abs(xyz(cloud) - truth)[..., 1]
    assert 0.25 < error.max() < 0.4                            # 0.3 % of 100 mm plus the ripple


def test_poses_are_interpolated_between_reports():
    collector, poses, truth = collect(np.random.default_rng(3), pose_every=4)
    cloud, by_pose = collector.assemble(SweepMotion((0.0, 1.0, 0.0), SPEED), None, poses)
    assert by_pose
    # four profiles between reports: the ripple's curvature is all that linear interpolation misses
    assert np.max(np.abs(xyz(cloud) - truth)) < 0.01


def test_a_pose_stream_that_does_not_cover_the_sweep_falls_back_to_time():
    collector, _, truth = collect(np.random.default_rng(4))
    partial = PoseTrack(10)
    partial.add(0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    partial.add(1.0, [0.0, 15.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    cloud, by_pose = collector.assemble(SweepMotion((0.0, 1.0, 0.0), SPEED), None, partial)
    assert not by_pose


def test_the_nominal_start_pose_of_reversed_and_turned_sweeps_covers_the_same_stretch():
    for direction in (1, -1):
        for orientation in (0.0, 90.0):
            pose = nominal_start_pose(200.0, direction, orientation)
            start = pose[:3, 3]
            end = start + pose[:3, :3] @ np.array([0.0, direction * 200.0, 0.0])
            assert np.allclose((start + end) / 2, [0.0, 100.0, 0.0])
    assert np.allclose(nominal_start_pose(200.0), np.eye(4))
    with pytest.raises(ValueError, match="direction must be"):
        nominal_start_pose(200.0, 0)


def test_the_pose_track_refuses_bad_poses_and_keeps_its_bound():
    track = PoseTrack(2)
    assert not track.add(0.0, [np.nan, 0, 0], [0, 0, 0, 1])
    assert not track.add(0.0, [0, 0, 0], [0, 0, 0, 0])
    assert track.add(0.0, [0, 0, 0], [0, 0, 0, 1]) and track.add(1.0, [0, 1, 0], [0, 0, 0, 1])
    assert not track.add(2.0, [0, 2, 0], [0, 0, 0, 1])
    assert len(track) == 2


def test_junk_profiles_are_kept_apart_by_layout_and_time_window_and_wide_ones_dropped():
    # Issue 31 item 8: well-formed junk joined the sweep (2 006 rows instead of 2 001), its stamps
    # switched placement to time, and five over-wide profiles failed the whole sweep.
    from gls_calibration.scan.sweep import profile_problem, stamp_window_s
    count = 40
    collector = SweepCollector(1000, 20)
    x = np.linspace(-50, 50, 11)
    stamps = 100.0 + np.arange(count) * STEP / SPEED
    for index, stamp in enumerate(stamps):
        collector.add(stamp, profile(x, np.full(x.size, 325.0 + index)), layout="float32-le")
        if index == 7:
            collector.add(stamps[3], profile(x, np.full(x.size, 1.0)), layout="float64-le")   # another layout
            collector.add(stamps[4], profile(x, np.full(x.size, 2.0)), layout="float32-be")
            collector.add(0.0, profile(x, np.full(x.size, 3.0)), layout="float32-le")          # stamp zero
            collector.add(4e9, profile(x, np.full(x.size, 4.0)), layout="float32-le")          # far future
            for _ in range(5):
                assert not collector.add(stamps[5], profile(np.linspace(-50, 50, 21), np.full(21, 5.0)),
                                         layout="float32-le")                                  # too wide
    assert collector.too_wide == 5 and collector.dropped == 0
    window = stamp_window_s(count, STEP, SPEED)
    assert window == pytest.approx(1.5 * (count - 1) * STEP / SPEED + 1.0)
    members = collector.members(window)
    assert len(collector) == count + 4 and int(members.sum()) == count
    poses = PoseTrack(1000)
    for stamp in stamps:
        poses.add(stamp, (0.0, SPEED * (stamp - stamps[0]), 0.0), (0.0, 0.0, 0.0, 1.0))
    cloud, by_pose = collector.assemble(SweepMotion((0.0, 1.0, 0.0), SPEED), None, poses, members)
    assert by_pose and cloud.shape == (count, x.size)
    np.testing.assert_array_equal(cloud["z"][:, 0], 325.0 + np.arange(count))     # only the sweep's, in order
    assert collector.first_stamp_s(members) == stamps[0]
    # a profile of zeros is no measurement at all
    assert "sensor's origin" in profile_problem(1.0, profile(np.zeros(x.size), np.zeros(x.size)))


def test_profile_rules_drop_what_the_sensor_did_not_declare_and_refuse_bad_limits():
    from gls_calibration.scan.sweep import ProfileRules
    rules = ProfileRules()
    float32 = {name: "float32" for name in ("x", "y", "z", "intensity")}
    assert rules.format_problem(float32 | {"ring": "uint16"}, False) == ""     # other fields are free
    assert rules.format_problem(float32, True) == ("byte order big-endian, the sensor declares float32, "
                                                   "little-endian")
    assert rules.format_problem(float32 | {"z": "float64"}, False) == ("fields z float64, the sensor declares "
                                                                       "float32, little-endian")
    assert ProfileRules(field_type="float64", big_endian=True).format_problem(
        {name: "float64" for name in float32}, True) == ""
    assert rules.stamp_window_s(201, 0.15, 15.0) == pytest.approx(1.5 * 2.0 + 1.0)
    for bad in (dict(field_type="int8"), dict(max_points=0), dict(stamp_window_factor=0.5),
                dict(stamp_window_margin_s=math.nan)):
        with pytest.raises(ValueError):
            ProfileRules(**bad)


def test_an_announced_count_is_checked_against_length_and_step_within_the_slack():
    from gls_calibration.scan.sweep import ProfileRules
    rules = ProfileRules()
    assert rules.announcement_problem(2001, 200.0, 0.1) == ""          # floor(200 / 0.1) + 1
    assert rules.announcement_problem(2000, 200.0, 0.1) == ""          # a driver that rounds the other way
    assert rules.announcement_problem(20, 0.0, 0.15) == ""             # length left to the driver
    assert rules.announcement_problem(20, 30.0, 0.15) == ("the scanner announced 20 profiles for 30 mm every "
                                                          "0.15 mm, which gives 201")
