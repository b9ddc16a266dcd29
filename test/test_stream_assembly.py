"""The stream path's cheaper steps give what the plain ones gave: CDR records, bulk TF, the metres check."""
from __future__ import annotations

import math
import os

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.serialization import deserialize_message, serialize_message
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from gls_calibration.ros import cdr, conversions
from gls_calibration.ros.stream_topics import time_msg, transform_msg
from gls_calibration.scan.bag_io import BagLayout, StreamAssembler, _add_transform
from gls_calibration.scan.sweep import UNIT_CHECK_POINTS, median_point_distance, unit_check_distance
from gls_calibration.scan.tf_buffer import TfBuffer

LAYOUT = BagLayout()
PERIOD_NS = 1_000_000_000 // 150
TF_PERIOD_NS = 1_000_000_000 // 250


def stream(rng: np.random.Generator, profiles: int = 60, points: int = 50) -> list[tuple[str, bytes, type]]:
    """A sweep's serialised messages in arrival order: fixed frames, start, poses and profiles, end."""
    start, end = 10 * PERIOD_NS, 10 * PERIOD_NS + profiles * PERIOD_NS
    hand_eye = np.eye(4)
    hand_eye[:3, 3] = (40.0, 0.0, 180.0)
    messages = [(LAYOUT.tf_static_topic, TFMessage(transforms=[
        transform_msg(LAYOUT.flange_frame, LAYOUT.sensor_frame, hand_eye, 0)])),
        (LAYOUT.motion_start_topic, Header(stamp=time_msg(start), frame_id=LAYOUT.base_frame))]
    events = [(int(t), 0) for t in range(start - 2 * TF_PERIOD_NS, end + 3 * TF_PERIOD_NS, TF_PERIOD_NS)]
    events += [(start + PERIOD_NS // 3 + row * PERIOD_NS, 1) for row in range(profiles)]
    for stamp, kind in sorted(events):
        if kind == 0:
            pose = np.eye(4)
            pose[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, 0.01, 3)).as_matrix()
            pose[:3, 3] = (500.0, 1e-8 * stamp, 400.0) + rng.normal(0.0, 0.01, 3)
            messages.append((LAYOUT.tf_topic, TFMessage(transforms=[
                transform_msg(LAYOUT.base_frame, LAYOUT.flange_frame, pose, stamp)])))
        else:
            xyz = np.column_stack([np.linspace(-0.06, 0.06, points), np.zeros(points),
                                   0.3 + rng.normal(0.0, 1e-4, points)])
            xyz[rng.uniform(size=points) < 0.1] = np.nan
            messages.append((LAYOUT.scan_topic, conversions.array_to_pointcloud2(
                conversions.xyzi_array(xyz, rng.uniform(size=points)), LAYOUT.sensor_frame, time_msg(stamp))))
    messages.append((LAYOUT.motion_end_topic, Header(stamp=time_msg(end), frame_id=LAYOUT.base_frame)))
    return [(topic, serialize_message(message), type(message)) for topic, message in messages]


def read_raw(topic: str, raw: bytes):
    if topic == LAYOUT.scan_topic:
        return cdr.read_pointcloud2(raw)
    if topic in (LAYOUT.tf_topic, LAYOUT.tf_static_topic):
        return cdr.read_tf_message(raw)
    return cdr.read_header(raw)


def test_a_sweep_from_cdr_records_is_the_sweep_from_rclpy_messages():
    messages = stream(np.random.default_rng(0))
    from_objects, from_bytes = StreamAssembler(LAYOUT), StreamAssembler(LAYOUT)
    for topic, raw, kind in messages:
        from_objects.add(topic, deserialize_message(raw, kind))
        from_bytes.add(topic, read_raw(topic, raw))
    expected, sweep = from_objects.take_last_sweep(), from_bytes.take_last_sweep()
    assert sweep.xyz_mm.shape == (60, 50, 3) and np.isfinite(sweep.xyz_mm).any()
    for name in ("xyz_mm", "intensity", "stamps_ns"):
        assert np.array_equal(getattr(sweep, name), getattr(expected, name), equal_nan=True), name


def test_flange_poses_added_in_bulk_are_those_added_one_at_a_time():
    messages = stream(np.random.default_rng(1))
    assembler, one_by_one = StreamAssembler(LAYOUT), TfBuffer()
    for topic, raw, kind in messages:
        message = deserialize_message(raw, kind)
        assembler.add(topic, message)
        if topic in (LAYOUT.tf_topic, LAYOUT.tf_static_topic):
            for transform in message.transforms:
                _add_transform(one_by_one, transform, static=topic == LAYOUT.tf_static_topic)
    rng = np.random.default_rng(2)
    stamps = np.sort(rng.integers(10 * PERIOD_NS, 70 * PERIOD_NS, 500))
    for target, source in ((LAYOUT.base_frame, LAYOUT.sensor_frame), (LAYOUT.flange_frame, LAYOUT.base_frame)):
        bulk = assembler.buffer.try_lookup_many(target, source, stamps, 4_000_000)
        single = one_by_one.try_lookup_many(target, source, stamps, 4_000_000)
        assert np.array_equal(bulk[0], single[0], equal_nan=True) and bulk[1] == single[1]


def test_bulk_insertion_keeps_the_order_and_the_errors_of_single_ones():
    rng = np.random.default_rng(3)
    stamps = np.array([5, 3, 3, 9, 1, 9, 7], dtype=np.int64)      # out of order and repeated
    poses = np.tile(np.eye(4), (stamps.size, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(0.0, 0.3, (stamps.size, 3))).as_matrix()
    poses[:, :3, 3] = rng.normal(0.0, 100.0, (stamps.size, 3))
    bulk, single = TfBuffer(), TfBuffer()
    bulk.set_transforms("a", "b", stamps[:3], poses[:3])
    bulk.set_transforms("a", "b", stamps[3:], poses[3:])
    for stamp, pose in zip(stamps, poses):
        single.set_transform("a", "b", int(stamp), pose)
    lookups = np.arange(1, 10)
    assert np.array_equal(bulk.try_lookup_many("a", "b", lookups, 10)[0],
                          single.try_lookup_many("a", "b", lookups, 10)[0], equal_nan=True)
    bad = poses.copy()
    bad[4, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"^the transform a -> c at 1 ns is not a finite 4x4 pose$"):
        bulk.set_transforms("a", "c", stamps, bad)
    assert bulk.try_lookup_many("a", "c", [5], 0)[1] == [None]       # the samples before the bad one were added
    bad[4] = poses[4]
    bad[2, :3, :3] *= 1.01
    with pytest.raises(ValueError, match=r"^the transform a -> d at 3 ns does not hold a proper rotation"):
        bulk.set_transforms("a", "d", stamps, bad)
    with pytest.raises(ValueError, match=r"^frame b has two parents: a and e$"):
        bulk.set_transforms("e", "b", stamps, poses)
    with pytest.raises(ValueError, match=r"^a transform needs two different frame names, got 'a' -> 'a'$"):
        bulk.set_transforms("a", "a", stamps, poses)


def test_a_bad_flange_pose_is_refused_with_the_message_of_a_single_addition():
    messages = stream(np.random.default_rng(4), profiles=10)
    tf_at = [index for index, (topic, _, _) in enumerate(messages) if topic == LAYOUT.tf_topic]
    topic, raw, kind = messages[tf_at[5]]
    broken = deserialize_message(raw, kind)
    rotation = broken.transforms[0].transform.rotation
    rotation.x = rotation.y = rotation.z = rotation.w = 0.0
    assembler = StreamAssembler(LAYOUT)
    for index, (topic, raw, kind) in enumerate(messages):
        assembler.add(topic, broken if index == tf_at[5] else deserialize_message(raw, kind))
    with pytest.raises(ValueError, match="zero norm quaternion"):
        assembler.take_last_sweep()


@pytest.mark.parametrize("seed", range(5))
def test_the_median_distance_is_numpys_median(seed):
    rng = np.random.default_rng(seed)
    for size in range(0, 80):
        xyz = rng.normal(0.0, 10.0 ** rng.uniform(-3, 3), (size, 3))
        xyz[rng.uniform(size=size) < 0.2, int(rng.integers(0, 3))] = rng.choice([np.nan, np.inf, -np.inf])
        distance = np.sqrt(np.einsum("...i,...i->...", xyz, xyz))      # the distances as the function computes them
        distance = distance[np.isfinite(distance)]
        expected = float(np.median(distance)) if distance.size else math.nan
        got = median_point_distance(xyz)
        assert got == expected or (math.isnan(got) and math.isnan(expected)), (size, got, expected)


@pytest.mark.parametrize("seed", range(5))
def test_the_unit_check_gives_the_verdict_of_every_point(seed):
    """The subsampled unit check passes and fails the profiles every point's median passes and fails.

    Where it fails a profile, it returns every point's median (the number its message names).
    """
    rng = np.random.default_rng(seed)
    limits = [(0.0, 10.0), (10.0, 10000.0)]
    for size in [0, 1, 5, UNIT_CHECK_POINTS, UNIT_CHECK_POINTS + 1, 300, 2101, 4096]:
        for scale in (1e-4, 1e-3, 0.3, 2.0, 5.0, 30.0, 300.0, 3000.0, 5e4):
            xyz = rng.normal(0.0, 0.2, (size, 3)) * scale
            xyz[:, 2] += scale * rng.uniform(0.5, 1.5)
            xyz[rng.uniform(size=size) < rng.choice([0.0, 0.3, 0.9]), int(rng.integers(0, 3))] = np.nan
            exact = median_point_distance(xyz)
            for low, high in limits:
                got = unit_check_distance(xyz, low, high)
                passes = math.isnan(exact) or low <= exact <= high
                assert (math.isnan(got) or low <= got <= high) == passes, (size, scale, low, high, got, exact)
                if not passes or size <= UNIT_CHECK_POINTS:
                    assert got == exact or (math.isnan(got) and math.isnan(exact)), (size, scale, got, exact)


def test_the_unit_check_samples_points_well_inside_the_limits_only():
    """A profile's sampled median decides only well inside the limits; near one every point decides."""
    xyz = np.column_stack([np.zeros(2101), np.zeros(2101), np.linspace(0.2, 0.4, 2101)])
    assert unit_check_distance(xyz, 0.0, 10.0) != median_point_distance(xyz)     # sampled: (0.3 - half a step)
    assert abs(unit_check_distance(xyz, 0.0, 10.0) - 0.3) < 1e-3
    assert unit_check_distance(xyz, 0.0, 1.0) == median_point_distance(xyz)       # within 4x of the limit
    assert unit_check_distance(xyz, 0.1, 10.0) == median_point_distance(xyz)
    xyz[::17] = np.nan                   # every sampled point: the whole profile decides
    assert unit_check_distance(xyz, 0.0, 10.0) == median_point_distance(xyz)


@pytest.fixture
def acquisition_node():
    from gls_calibration.nodes.stream_acquisition import Session, StreamAcquisitionNode

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = Context()
    rclpy.init(context=context)
    node = StreamAcquisitionNode(context=context, namespace=f"cdr_test_{os.getpid()}")
    try:
        yield node, Session
    finally:
        node.destroy_node()
        context.try_shutdown()


def test_malformed_stream_bytes_are_a_problem_of_the_sweep_not_a_crash(acquisition_node):
    node, session_type = acquisition_node
    node._profile(b"\x00\x01")          # between sweeps: logged, nothing else
    node._tf(b"garbage")
    node.session = session = session_type(StreamAssembler(node.layout, node.limits, "stream"))
    good, cut = (serialize_message(conversions.array_to_pointcloud2(conversions.xyzi_array(
        np.array([[0.0, 0.0, 0.3], [0.01, 0.0, 0.3]]), np.ones(2)), node.frames.sensor, time_msg(stamp)))
        for stamp in (5, 3))
    node._profile(cut[:40])     # its stamp readable, the rest not
    node._tf(b"\x00\x05\x00\x00\x00\x00\x00\x00")
    node._profile(good)
    assert session.problems == [
        f"a profile on {node.layout.scan_topic}: PointCloud2: the message ends at byte 40, 4 more bytes needed "
        "at byte 40 (cut short?)",
        "a message on /tf: TFMessage: encapsulation 0x0005 is not plain CDR (0x0000 or 0x0001)"]
    assert session.profiles == 2 and len(session.assembler.profiles) == 1


def reference_cloud_msg(xyz_mm: np.ndarray, intensity: np.ndarray, frame_id: str, stamp) -> PointCloud2:
    """The answer as it was built before: a float32 cloud in mm field by field, then divided field by field."""
    points = np.empty(xyz_mm.shape[:-1], dtype=conversions.xyzi_dtype())
    for axis, name in enumerate("xyz"):
        points[name] = xyz_mm[..., axis]
    points["intensity"] = intensity
    wire = np.empty(points.shape, dtype=conversions.xyzi_dtype())
    for name in "xyz":
        np.divide(points[name], np.float32(1000.0), out=wire[name], dtype=np.float32)
    wire["intensity"] = points["intensity"]
    return conversions.array_to_pointcloud2(wire, frame_id=frame_id, stamp=stamp)


@pytest.mark.parametrize("shape", [(7,), (3, 5), (0,), (2, 0), (1, 1), (40, 33)])
@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
@pytest.mark.parametrize("dtype, nan", [("float64", True), ("float64", False), ("float32", True),
                                        ("float32", False), ("int64", False)])
def test_the_answer_cloud_is_the_one_built_field_by_field(shape, dtype, nan):
    from gls_calibration.ros.pointcloud import xyzi_cloud_to_msg

    rng = np.random.default_rng(len(shape) * 100 + shape[0])
    xyz = rng.normal(0.0, 300.0, shape + (3,))
    if nan:
        xyz.reshape(-1)[::7] = np.nan
    xyz.reshape(-1)[3::11] *= 1e40 if dtype == "float64" else 1.0      # beyond float32: inf, not NaN
    xyz = xyz.astype(dtype)
    intensity = rng.uniform(size=shape)
    expected = reference_cloud_msg(xyz, intensity, "robot_base", time_msg(12345))
    assert xyzi_cloud_to_msg(xyz, intensity, "robot_base", time_msg(12345)) == expected
    assert conversions.cloud_to_msg(conversions.xyzi_array(xyz, intensity), "robot_base", time_msg(12345)) == expected
    with pytest.raises(ValueError, match=r"^intensity must have shape \(2, 3\) to match xyz, got \(3, 2\)$"):
        xyzi_cloud_to_msg(np.zeros((2, 3, 3)), np.zeros((3, 2)), "robot_base")
    with pytest.raises(ValueError, match=r"^xyz must have shape \(W, 3\) or \(H, W, 3\), got \(3,\)$"):
        xyzi_cloud_to_msg(np.zeros(3), np.zeros(()), "robot_base")


class _Handle:
    """A subscription handle as another rclpy might have it: no take_message, or one of other arguments."""

    def __init__(self, take=None) -> None:
        if take is not None:
            self.take_message = take

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None


@pytest.mark.parametrize("take", [None, lambda message_type: None])
def test_take_waiting_leaves_the_queue_to_the_executor_on_another_rclpy(take):
    from types import SimpleNamespace

    from gls_calibration.ros.base import take_waiting

    subscription = SimpleNamespace(handle=_Handle(take), msg_type=PointCloud2, raw=True)
    assert list(take_waiting(subscription, 10)) == []


def test_take_waiting_stops_at_the_limit_and_at_an_empty_queue():
    from types import SimpleNamespace

    from gls_calibration.ros.base import take_waiting

    queue = [(b"a", None), (b"b", None), (b"c", None)]
    subscription = SimpleNamespace(handle=_Handle(lambda message_type, raw: queue.pop(0) if queue else None),
                                   msg_type=PointCloud2, raw=True)
    assert list(take_waiting(subscription, 2)) == [b"a", b"b"]
    assert list(take_waiting(subscription, 5)) == [b"c"]


def placed_as_before(assembler: StreamAssembler, start: int, end: int):
    """The sweep's points as the assembly placed them before the row-by-row placement: one array, then one sum."""
    inside = [(stamp, points) for stamp, points in assembler.profiles if start <= stamp <= end]
    stamps = np.array([stamp for stamp, _ in inside], dtype=np.int64)
    poses = assembler.buffer.lookup_many(LAYOUT.base_frame, LAYOUT.sensor_frame, stamps, max_age_ns=50_000_000)
    to_base_mm = np.swapaxes(poses[:, :3, :3], 1, 2) * 1000.0
    xyz = np.empty((len(inside), inside[0][1].shape[0], 3))
    intensity = np.empty(xyz.shape[:2])
    for row, (_, points_m) in enumerate(inside):
        points_m = np.asarray(points_m, dtype=np.float64)     # as profile_points gave every profile on arrival
        np.matmul(points_m[:, :3], to_base_mm[row], out=xyz[row])
        intensity[row] = points_m[:, 3]
    xyz += poses[:, None, :3, 3]
    return xyz, intensity, stamps


@pytest.mark.parametrize("seed, nan, raw", [(20, True, True), (21, False, True), (22, True, False)])
def test_the_answer_placed_row_by_row_is_the_sweep_placed_whole(seed, nan, raw):
    """``take_last_placement`` rows into the message: the sweep's points bit for bit, the message byte for byte.

    From CDR records (the profiles kept as float32 views of the bytes) and from rclpy's messages (float64 copies).
    """
    from gls_calibration.ros.pointcloud import xyzi_blocks_to_msg, xyzi_cloud_to_msg

    messages = stream(np.random.default_rng(seed), profiles=40, points=30)
    assembler = StreamAssembler(LAYOUT)
    for topic, raw, kind in messages:
        message = deserialize_message(raw, kind)
        if topic == LAYOUT.scan_topic and not nan:
            cloud = conversions.pointcloud2_to_array(message)
            for name in ("x", "y", "z"):
                cloud[name] = np.nan_to_num(cloud[name], nan=0.25)
            message = conversions.array_to_pointcloud2(cloud, LAYOUT.sensor_frame, message.header.stamp)
        assembler.add(topic, read_raw(topic, serialize_message(message)) if raw else message)
    kinds = {points.dtype for _, points in assembler.profiles}
    assert kinds == {np.dtype(np.float32) if raw else np.dtype(np.float64)}
    start, end = assembler.starts[-1], assembler.ends[-1]
    xyz, intensity, stamps = placed_as_before(assembler, start, end)
    later = [stamp for stamp, _ in assembler.profiles if stamp > end]
    placement = assembler.take_last_placement()
    assert [stamp for stamp, _ in assembler.profiles] == later      # dropped up to the end, as take_last_sweep
    sweep = placement.sweep()
    assert placement.shape == (40, 30) and np.array_equal(placement.stamps_ns, stamps)
    assert np.array_equal(sweep.xyz_mm, xyz, equal_nan=True) and np.array_equal(sweep.intensity, intensity)
    assert bool(np.isnan(xyz).any()) == nan
    expected = xyzi_cloud_to_msg(xyz, intensity, "robot_base", time_msg(int(stamps[0])))
    # the live answer's path: blocks of rows (40 rows: a full block and a partial one), the same bytes
    blocks = xyzi_blocks_to_msg(*placement.shape, placement.place_rows, "robot_base", time_msg(int(stamps[0])))
    assert blocks == expected and bytes(blocks.data) == bytes(expected.data) and blocks.is_dense == (not nan)
    assert xyzi_blocks_to_msg(0, 30, placement.place_rows, "robot_base") == xyzi_cloud_to_msg(
        np.zeros((0, 30, 3)), np.zeros((0, 30)), "robot_base")
    with pytest.raises(ValueError, match=r"^height and width must not be negative, got -1 x 30$"):
        xyzi_blocks_to_msg(-1, 30, placement.place_rows, "robot_base")


@pytest.mark.parametrize("session, queued, sleeps", [(True, 2, 1), (False, 2, 0), (True, 3, 0)])
def test_a_stream_callback_takes_again_after_the_coalescing_wait_only_during_a_sweep(
        monkeypatch, session, queued, sleeps):
    """The queue emptied during a sweep: one wait of ``COALESCE_S``, then what came meanwhile; else no wait."""
    from types import SimpleNamespace

    from gls_calibration.nodes import stream_acquisition

    queue = [(f"m{index}".encode(), None) for index in range(queued)]
    waits = []

    def sleep(seconds):
        waits.append(seconds)
        queue.append((b"meanwhile", None))

    monkeypatch.setattr(stream_acquisition, "TAKE_AT_ONCE", 3)
    monkeypatch.setattr(stream_acquisition.time, "sleep", sleep)
    subscription = SimpleNamespace(handle=_Handle(lambda message_type, raw: queue.pop(0) if queue else None),
                                   msg_type=PointCloud2, raw=True)
    node = SimpleNamespace(session=object() if session else None)
    handled = []
    stream_acquisition.StreamAcquisitionNode._take(node, subscription, handled.append)
    assert waits == [stream_acquisition.COALESCE_S] * sleeps
    assert handled == [f"m{index}".encode() for index in range(queued)] + [b"meanwhile"] * sleeps
    assert queue == []
