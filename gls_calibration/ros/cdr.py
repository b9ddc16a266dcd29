"""The streams' serialised messages read straight from their CDR bytes, without rclpy's message objects.

A subscription created with ``raw=True`` hands over the serialised message (the bytes the DDS layer
received: a 4-byte encapsulation header, then the message in CDR, plain XCDR1 as Fast DDS and
Cyclone DDS send ROS 2 messages, either byte order). Turning a 2 000-point ``PointCloud2`` into a
Python message object costs rclpy about as much as everything else done with the profile; read
here, the point data stays a view of the received bytes (``numpy.frombuffer``, no copy).

The readers return small immutable records (named tuples) that carry the attribute names of the ROS types
(``message.header.stamp.sec``, ``message.fields[i].offset``, ``message.transforms[i].transform.rotation.w``,
...), so what consumes a message (:class:`~gls_calibration.scan.bag_io.StreamAssembler`, which bag
replay feeds with rosbags' objects) runs the same code on them. Malformed bytes (cut short, an
unknown encapsulation, a string without its terminating NUL or not UTF-8, a sequence longer than
the message) raise ``ValueError`` naming the message type and the byte offset.
"""
from __future__ import annotations

import struct
from typing import NamedTuple

import numpy as np

NS_PER_S = 1_000_000_000
_ENCAPSULATION = {b"\x00\x00": ">", b"\x00\x01": "<"}    # CDR_BE, CDR_LE (plain CDR, XCDR1)
_HEADER_BYTES = 4


class Time(NamedTuple):
    """``builtin_interfaces/Time``."""

    sec: int
    nanosec: int


class Header(NamedTuple):
    """``std_msgs/Header``."""

    stamp: Time
    frame_id: str


class PointField(NamedTuple):
    """``sensor_msgs/PointField``."""

    name: str
    offset: int
    datatype: int
    count: int


class PointCloud2(NamedTuple):
    """``sensor_msgs/PointCloud2``; ``data`` is a read-only uint8 view of the received bytes."""

    header: Header
    height: int
    width: int
    fields: tuple
    is_bigendian: bool
    point_step: int
    row_step: int
    data: np.ndarray
    is_dense: bool


class Vector3(NamedTuple):
    """``geometry_msgs/Vector3``."""

    x: float
    y: float
    z: float


class Quaternion(NamedTuple):
    """``geometry_msgs/Quaternion``."""

    x: float
    y: float
    z: float
    w: float


class Transform(NamedTuple):
    """``geometry_msgs/Transform``."""

    translation: Vector3
    rotation: Quaternion


class TransformStamped(NamedTuple):
    """``geometry_msgs/TransformStamped``."""

    header: Header
    child_frame_id: str
    transform: Transform


class TFMessage(NamedTuple):
    """``tf2_msgs/TFMessage``."""

    transforms: tuple


class _Reader:
    """A cursor over one serialised message; alignment counts from the end of the encapsulation header."""

    __slots__ = ("raw", "at", "order", "kind", "_u32", "_header", "_field", "_steps", "_seven_f64")

    def __init__(self, raw, kind: str) -> None:
        if not isinstance(raw, (bytes, bytearray, memoryview)):
            raise ValueError(f"{kind}: expected the serialised message as bytes, got {type(raw).__name__}")
        self.raw = raw
        self.kind = kind
        if len(raw) < _HEADER_BYTES:
            raise ValueError(f"{kind}: {len(raw)} bytes are too few for a serialised message")
        order = _ENCAPSULATION.get(bytes(raw[:2]))
        if order is None:
            raise ValueError(f"{kind}: encapsulation 0x{bytes(raw[:2]).hex()} is not plain CDR (0x0000 or 0x0001)")
        self.order = order
        self.at = _HEADER_BYTES
        self._u32 = _STRUCTS[order]["I"]
        self._header = _STRUCTS[order]["iII"]
        self._field = _STRUCTS[order]["IBxxxI"]
        self._steps = _STRUCTS[order]["?xxxII"]
        self._seven_f64 = _STRUCTS[order]["7d"]

    def _need(self, size: int) -> None:
        if self.at + size > len(self.raw):
            raise ValueError(f"{self.kind}: the message ends at byte {len(self.raw)}, {size} more bytes needed "
                             f"at byte {self.at} (cut short?)")

    def align(self, size: int) -> None:
        self.at += (-(self.at - _HEADER_BYTES)) % size

    def unpack(self, layout: struct.Struct, alignment: int) -> tuple:
        self.align(alignment)
        self._need(layout.size)
        values = layout.unpack_from(self.raw, self.at)
        self.at += layout.size
        return values

    def u32(self) -> int:
        return self.unpack(self._u32, 4)[0]

    def u8(self) -> int:
        self._need(1)
        self.at += 1
        return self.raw[self.at - 1]

    def string_bytes(self, length: int) -> str:
        """Read the string of ``length`` bytes (its NUL included) at the cursor."""
        if length == 0:
            raise ValueError(f"{self.kind}: a string of length 0 at byte {self.at - 4} (no terminating NUL)")
        self._need(length)
        end = self.at + length - 1
        if self.raw[end] != 0:
            raise ValueError(f"{self.kind}: the string at byte {self.at - 4} does not end with NUL")
        try:
            text = bytes(self.raw[self.at:end]).decode("utf-8")
        except UnicodeDecodeError:
            raise ValueError(f"{self.kind}: the string at byte {self.at - 4} is not UTF-8") from None
        self.at = end + 1
        return text

    def string(self) -> str:
        return self.string_bytes(self.u32())

    def header(self) -> Header:
        """Read a ``std_msgs/Header`` (stamp, then the frame's name)."""
        sec, nanosec, length = self.unpack(self._header, 4)
        return Header(Time(sec, nanosec), self.string_bytes(length))

    def count(self, element_bytes: int) -> int:
        """Read a sequence's length, refused when its elements cannot fit in the rest of the message."""
        count = self.u32()
        if count * element_bytes > len(self.raw) - self.at:
            raise ValueError(f"{self.kind}: a sequence of {count} elements at byte {self.at - 4} is longer than "
                             f"the message ({len(self.raw)} bytes)")
        return count

    def end(self, message):
        """Return ``message`` once every byte but CDR padding was read."""
        if len(self.raw) - self.at > 3:
            raise ValueError(f"{self.kind}: {len(self.raw) - self.at} bytes left after the message")
        return message


_STRUCTS = {order: {layout: struct.Struct(order + layout) for layout in ("I", "iII", "IBxxxI", "?xxxII", "7d")}
            for order in "<>"}


def read_pointcloud2(raw) -> PointCloud2:
    """Read a serialised ``sensor_msgs/PointCloud2``; its point data is a view of ``raw``.

    Parameters
    ----------
    raw : bytes
        The serialised message, as a ``raw=True`` subscription hands it over.

    Returns
    -------
    PointCloud2
        The message's fields; ``data`` a read-only ``uint8`` array over ``raw`` (no copy).

    Raises
    ------
    ValueError
        Naming the problem and its byte offset when ``raw`` is not a serialised PointCloud2.
    """
    reader = _Reader(raw, "PointCloud2")
    header = reader.header()
    height, width = reader.u32(), reader.u32()
    fields = []
    for _ in range(reader.count(17)):     # a field: name (4 + 1 bytes at least), offset, datatype, count
        name = reader.string()
        fields.append(PointField(name, *reader.unpack(reader._field, 4)))
    is_bigendian, point_step, row_step = reader.unpack(reader._steps, 4)    # the flag is 4-aligned: after a u32
    size = reader.count(1)
    data = np.frombuffer(raw, dtype=np.uint8, count=size, offset=reader.at)
    reader.at += size
    is_dense = bool(reader.u8())
    return reader.end(PointCloud2(header, height, width, tuple(fields), is_bigendian, point_step, row_step, data,
                                  is_dense))


def read_tf_message(raw) -> TFMessage:
    """Read a serialised ``tf2_msgs/TFMessage``.

    Parameters
    ----------
    raw : bytes
        The serialised message, as a ``raw=True`` subscription hands it over.

    Returns
    -------
    TFMessage
        Its transforms (stamped, parent and child frame, translation in metres, quaternion x, y, z, w).

    Raises
    ------
    ValueError
        Naming the problem and its byte offset when ``raw`` is not a serialised TFMessage.
    """
    reader = _Reader(raw, "TFMessage")
    transforms = []
    for _ in range(reader.count(74)):
        header = reader.header()
        child = reader.string()
        tx, ty, tz, qx, qy, qz, qw = reader.unpack(reader._seven_f64, 8)
        transforms.append(TransformStamped(header, child, Transform(Vector3(tx, ty, tz), Quaternion(qx, qy, qz, qw))))
    return reader.end(TFMessage(tuple(transforms)))


def read_header(raw) -> Header:
    """Read a serialised ``std_msgs/Header``.

    Parameters
    ----------
    raw : bytes
        The serialised message.

    Returns
    -------
    Header
        Its stamp and frame.

    Raises
    ------
    ValueError
        Naming the problem and its byte offset when ``raw`` is not a serialised Header.
    """
    reader = _Reader(raw, "Header")
    return reader.end(reader.header())


def header_stamp_ns(raw) -> int:
    """Return the stamp (integer ns) of a serialised message that begins with a ``std_msgs/Header``.

    Parameters
    ----------
    raw : bytes
        The serialised message (``PointCloud2``, ``Header``, ...).

    Returns
    -------
    int
        ``header.stamp`` in nanoseconds.

    Raises
    ------
    ValueError
        When ``raw`` is too short or not plain CDR.
    """
    reader = _Reader(raw, "message")
    sec, nanosec, _ = reader.unpack(reader._header, 4)
    return sec * NS_PER_S + nanosec
