"""The CDR readers of the raw stream subscriptions against rclpy's own (de)serialisation."""
from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from builtin_interfaces.msg import Time
from geometry_msgs.msg import TransformStamped
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from gls_calibration.ros import cdr

NAMES = ["", "x", "robot_base", "scanner_optical", "ä_frame/ü", "a" * 37]


def random_header(rng: np.random.Generator) -> Header:
    return Header(stamp=Time(sec=int(rng.integers(-2**31, 2**31)), nanosec=int(rng.integers(0, 2**32))),
                  frame_id=str(rng.choice(NAMES)))


def random_cloud(rng: np.random.Generator) -> PointCloud2:
    fields = [PointField(name=str(rng.choice(NAMES)), offset=int(rng.integers(0, 2**32)),
                         datatype=int(rng.integers(0, 256)), count=int(rng.integers(0, 2**32)))
              for _ in range(int(rng.integers(0, 6)))]
    size = int(rng.integers(0, 200))
    return PointCloud2(header=random_header(rng), height=int(rng.integers(0, 2**32)),
                       width=int(rng.integers(0, 2**32)), fields=fields, is_bigendian=bool(rng.integers(0, 2)),
                       point_step=int(rng.integers(0, 2**32)), row_step=int(rng.integers(0, 2**32)),
                       data=rng.integers(0, 256, size).astype(np.uint8).tolist(), is_dense=bool(rng.integers(0, 2)))


def random_tf(rng: np.random.Generator) -> TFMessage:
    transforms = []
    for _ in range(int(rng.integers(0, 5))):
        transform = TransformStamped(header=random_header(rng), child_frame_id=str(rng.choice(NAMES)))
        t, q = transform.transform.translation, transform.transform.rotation
        t.x, t.y, t.z, q.x, q.y, q.z, q.w = (float(v) for v in rng.normal(0.0, 10.0 ** rng.uniform(-9, 9), 7))
        transforms.append(transform)
    return TFMessage(transforms=transforms)


def same_header(read: cdr.Header, message: Header) -> bool:
    return (read.stamp.sec, read.stamp.nanosec, read.frame_id) == (message.stamp.sec, message.stamp.nanosec,
                                                                   message.frame_id)


@pytest.mark.parametrize("seed", range(40))
def test_a_random_cloud_reads_as_rclpy_deserialises_it(seed):
    rng = np.random.default_rng(seed)
    raw = serialize_message(random_cloud(rng))
    expected = deserialize_message(raw, PointCloud2)
    read = cdr.read_pointcloud2(raw)
    assert same_header(read.header, expected.header)
    assert (read.height, read.width, read.is_bigendian, read.point_step, read.row_step, read.is_dense) == (
        expected.height, expected.width, expected.is_bigendian, expected.point_step, expected.row_step,
        expected.is_dense)
    assert [tuple(field) for field in read.fields] == [(f.name, f.offset, f.datatype, f.count) for f in expected.fields]
    assert read.data.dtype == np.uint8 and read.data.tobytes() == bytes(expected.data)
    assert cdr.header_stamp_ns(raw) == expected.header.stamp.sec * 10**9 + expected.header.stamp.nanosec


@pytest.mark.parametrize("seed", range(40))
def test_a_random_tf_message_reads_as_rclpy_deserialises_it(seed):
    rng = np.random.default_rng(seed)
    raw = serialize_message(random_tf(rng))
    expected = deserialize_message(raw, TFMessage)
    read = cdr.read_tf_message(raw)
    assert len(read.transforms) == len(expected.transforms)
    for mine, theirs in zip(read.transforms, expected.transforms):
        assert same_header(mine.header, theirs.header) and mine.child_frame_id == theirs.child_frame_id
        t, q = theirs.transform.translation, theirs.transform.rotation
        assert tuple(mine.transform.translation) + tuple(mine.transform.rotation) == (t.x, t.y, t.z, q.x, q.y, q.z,
                                                                                      q.w)


def test_a_header_and_big_endian_cdr_read():
    header = Header(stamp=Time(sec=7, nanosec=123), frame_id="robot_base")
    raw = serialize_message(header)
    assert cdr.read_header(raw) == cdr.Header(cdr.Time(7, 123), "robot_base")
    # the same header written big-endian (encapsulation 0x0000), as a big-endian host sends it
    body = (7).to_bytes(4, "big") + (123).to_bytes(4, "big") + (11).to_bytes(4, "big") + b"robot_base\x00"
    assert cdr.read_header(b"\x00\x00\x00\x00" + body) == cdr.Header(cdr.Time(7, 123), "robot_base")


def test_a_cloud_reads_its_points_without_copying_them():
    points = np.arange(32, dtype=np.float32)
    message = PointCloud2(height=1, width=8, point_step=16, row_step=128, data=points.view(np.uint8).tolist())
    raw = serialize_message(message)
    read = cdr.read_pointcloud2(raw)
    assert np.array_equal(read.data.view(np.float32), points)
    assert not read.data.flags.owndata and not read.data.flags.writeable


@pytest.mark.parametrize("reader, message", [
    (cdr.read_pointcloud2, random_cloud(np.random.default_rng(1))),
    (cdr.read_tf_message, random_tf(np.random.default_rng(3))),
    (cdr.read_header, random_header(np.random.default_rng(2)))])
def test_malformed_bytes_raise_value_error_not_a_crash(reader, message):
    raw = serialize_message(message)
    for cut in range(len(raw) - 3):     # cut short anywhere (up to 3 bytes of final padding may go)
        with pytest.raises(ValueError):
            reader(raw[:cut])
    rng = np.random.default_rng(0)
    for _ in range(300):                # random damage: a ValueError or a message, never another exception
        damaged = bytearray(raw)
        damaged[4 + int(rng.integers(0, len(raw) - 4))] = int(rng.integers(0, 256))
        try:
            reader(bytes(damaged))
        except ValueError:
            pass
    with pytest.raises(ValueError, match=r"encapsulation 0x0007 is not plain CDR"):
        reader(b"\x00\x07\x00\x00" + raw[4:])
    with pytest.raises(ValueError, match=r"expected the serialised message as bytes, got str"):
        reader("not bytes")
    with pytest.raises(ValueError, match=r"bytes left after the message"):
        reader(raw + bytes(8))


def test_exact_messages_of_malformed_strings_and_sequences():
    header = serialize_message(Header(stamp=Time(sec=1, nanosec=2), frame_id="ab"))
    assert header[12:16] == b"\x03\x00\x00\x00"
    with pytest.raises(ValueError, match=r"^Header: the string at byte 12 does not end with NUL$"):
        cdr.read_header(header[:-1] + b"x")
    with pytest.raises(ValueError, match=r"^Header: the string at byte 12 is not UTF-8$"):
        cdr.read_header(header[:16] + b"\xff\xfe\x00")
    with pytest.raises(ValueError, match=r"^Header: a string of length 0 at byte 12 \(no terminating NUL\)$"):
        cdr.read_header(header[:12] + bytes(4))
    tf = serialize_message(TFMessage())
    with pytest.raises(ValueError, match=r"^TFMessage: a sequence of 1000000 elements at byte 4 is longer than the "
                                         r"message \(8 bytes\)$"):
        cdr.read_tf_message(tf[:4] + (1000000).to_bytes(4, "little"))
    with pytest.raises(ValueError, match=r"^Header: 3 bytes are too few for a serialised message$"):
        cdr.read_header(b"\x00\x01\x00")


def test_clouds_of_one_layout_read_as_rclpy_deserialises_each():
    """The second and later clouds of a layout (read from the stamp, data and is_dense only) read as the first."""
    rng = np.random.default_rng(7)
    base = random_cloud(rng)
    base.data = rng.integers(0, 256, 64).astype(np.uint8).tolist()
    variants = []
    for sec, nanosec, dense, fill in ((5, 6, True, 1), (-7, 2**32 - 1, False, 2), (5, 6, True, 3)):
        cloud = deserialize_message(serialize_message(base), PointCloud2)
        cloud.header.stamp = Time(sec=sec, nanosec=nanosec)
        cloud.is_dense, cloud.data = dense, [fill] * 64
        variants.append(cloud)
    other = deserialize_message(serialize_message(base), PointCloud2)
    other.header.frame_id = base.header.frame_id + "z"         # another layout between two of the first
    variants.insert(2, other)
    raws = [serialize_message(cloud) for cloud in variants]
    raws.append(bytearray(raws[0]))
    raws.append(memoryview(raws[1]))
    for raw in raws + raws:
        expected = deserialize_message(bytes(raw), PointCloud2)
        read = cdr.read_pointcloud2(raw)
        assert same_header(read.header, expected.header)
        assert (read.height, read.width, read.is_bigendian, read.point_step, read.row_step, read.is_dense) == (
            expected.height, expected.width, expected.is_bigendian, expected.point_step, expected.row_step,
            expected.is_dense)
        assert [tuple(field) for field in read.fields] == [(f.name, f.offset, f.datatype, f.count)
                                                           for f in expected.fields]
        assert read.data.tobytes() == bytes(expected.data)
        assert cdr.header_stamp_ns(raw) == expected.header.stamp.sec * 10**9 + expected.header.stamp.nanosec
    # damaged clouds of the layout just read are refused as after a cloud of another layout (read in full)
    raw = raws[0]
    for damaged in (raw[:len(raw) - 5], raw[:len(raw) - 9], raw + bytes(4), b"\x00\x07" + raw[2:],
                    raw[:12] + b"\xff\xff\xff\x00" + raw[16:]):
        messages = []
        for first in (raws[2], raw):
            cdr.read_pointcloud2(first)
            with pytest.raises(ValueError) as error:
                cdr.read_pointcloud2(damaged)
            messages.append(str(error.value))
        assert messages[0] == messages[1]


def test_flange_poses_of_one_layout_read_as_rclpy_deserialises_each():
    """One-transform TF messages after the first of their frames (read from the stamp and numbers only)."""
    rng = np.random.default_rng(11)
    messages = []
    for parent, child in (("robot_base", "flange"), ("robot_base", "flange"), ("robot_base", "flange2"),
                          ("robot_base", "flange"), ("", "x"), ("", "x")):
        message = random_tf(rng)
        while len(message.transforms) != 1:
            message = random_tf(rng)
        message.transforms[0].header.frame_id, message.transforms[0].child_frame_id = parent, child
        messages.append(message)
    raws = [serialize_message(message) for message in messages]
    raws += [bytearray(raws[0]), memoryview(raws[1]), serialize_message(random_tf(np.random.default_rng(3)))]
    for raw in raws + raws:
        expected = deserialize_message(bytes(raw), TFMessage)
        read = cdr.read_tf_message(raw)
        assert len(read.transforms) == len(expected.transforms)
        for mine, theirs in zip(read.transforms, expected.transforms):
            assert same_header(mine.header, theirs.header) and mine.child_frame_id == theirs.child_frame_id
            t, q = theirs.transform.translation, theirs.transform.rotation
            assert tuple(mine.transform.translation) + tuple(mine.transform.rotation) == (t.x, t.y, t.z, q.x, q.y,
                                                                                          q.z, q.w)
    # damaged messages of the layout just read are refused as after a message of another layout (read in full)
    raw = raws[0]
    for damaged in (raw[:len(raw) - 1], raw[:len(raw) - 8], raw + bytes(4), b"\x00\x07" + raw[2:],
                    raw[:16] + b"\xff\xff\xff\x00" + raw[20:]):
        messages = []
        for first in (raws[2], raw):
            cdr.read_tf_message(first)
            with pytest.raises(ValueError) as error:
                cdr.read_tf_message(damaged)
            messages.append(str(error.value))
        assert messages[0] == messages[1]
