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


_STRUCTS = {order: {layout: struct.Struct(order + layout) for layout in ("I", "iI", "iII", "IBxxxI", "?xxxII", "7d")}
            for order in "<>"}
_STAMP_AT = _HEADER_BYTES       # header.stamp: sec, nanosec, then the frame's name from byte 12
_FRAME_AT = _STAMP_AT + 8
_BYTES = (bytes, bytearray, memoryview)


class _CloudLayout(NamedTuple):
    """What a cloud's bytes from the frame's name to the point data said, to read the next cloud of that layout."""

    encapsulation: bytes
    prefix: bytes            # the bytes from _FRAME_AT to data_at
    data_at: int
    stamp: struct.Struct
    cloud: PointCloud2       # the cloud read; its stamp, data and is_dense are the next cloud's own


class _TfLayout(NamedTuple):
    """What a one-transform TFMessage's bytes but its stamp and numbers said, to read the next of that layout."""

    encapsulation: bytes     # the encapsulation and the transforms' count (one)
    prefix: bytes            # the bytes from _TF_FRAME_AT to data_at: the frames' names and padding
    data_at: int             # where the translation and rotation begin
    stamp: struct.Struct
    numbers: struct.Struct
    frame_id: str
    child_frame_id: str


_TF_FRAME_AT = _FRAME_AT + 4    # a TFMessage: its count, then the first transform's header
# The layout of the last cloud read in full (a stream's profiles share it): a cloud whose bytes from the
# encapsulation to its data are the same but for the stamp reads as that one, so only the stamp, the data and
# is_dense are read (the full read is a function of exactly those bytes). Replaced whole (one assignment), so
# threads reading clouds side by side at worst read in full.
_last_cloud_layout: "_CloudLayout | None" = None
# The same for the last one-transform TFMessage read in full (a robot's flange poses share it).
_last_tf_layout: "_TfLayout | None" = None


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
    global _last_cloud_layout
    layout = _last_cloud_layout
    if layout is not None and isinstance(raw, _BYTES):
        cloud, data_at = layout.cloud, layout.data_at
        size = cloud.data.size
        end = data_at + size
        if (0 <= len(raw) - end - 1 <= 3 and raw[:2] == layout.encapsulation
                and raw[_FRAME_AT:data_at] == layout.prefix):
            sec, nanosec = layout.stamp.unpack_from(raw, _STAMP_AT)
            return PointCloud2(Header(Time(sec, nanosec), cloud.header.frame_id), cloud.height, cloud.width,
                               cloud.fields, cloud.is_bigendian, cloud.point_step, cloud.row_step,
                               np.frombuffer(raw, dtype=np.uint8, count=size, offset=data_at), bool(raw[end]))
    reader = _Reader(raw, "PointCloud2")
    header = reader.header()
    height, width = reader.u32(), reader.u32()
    fields = []
    for _ in range(reader.count(17)):     # a field: name (4 + 1 bytes at least), offset, datatype, count
        name = reader.string()
        fields.append(PointField(name, *reader.unpack(reader._field, 4)))
    is_bigendian, point_step, row_step = reader.unpack(reader._steps, 4)    # the flag is 4-aligned: after a u32
    size = reader.count(1)
    data_at = reader.at
    data = np.frombuffer(raw, dtype=np.uint8, count=size, offset=data_at)
    reader.at += size
    is_dense = bool(reader.u8())
    cloud = reader.end(PointCloud2(header, height, width, tuple(fields), is_bigendian, point_step, row_step, data,
                                   is_dense))
    _last_cloud_layout = _CloudLayout(bytes(raw[:2]), bytes(raw[_FRAME_AT:data_at]), data_at,
                                      _STRUCTS[reader.order]["iI"], cloud)
    return cloud


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
    global _last_tf_layout
    layout = _last_tf_layout
    if layout is not None and isinstance(raw, _BYTES):
        numbers_at = layout.data_at
        if (0 <= len(raw) - numbers_at - 56 <= 3 and raw[:_STAMP_AT + 4] == layout.encapsulation
                and raw[_TF_FRAME_AT:numbers_at] == layout.prefix):
            sec, nanosec = layout.stamp.unpack_from(raw, _TF_FRAME_AT - 8)
            tx, ty, tz, qx, qy, qz, qw = layout.numbers.unpack_from(raw, numbers_at)
            return TFMessage((TransformStamped(Header(Time(sec, nanosec), layout.frame_id), layout.child_frame_id,
                                               Transform(Vector3(tx, ty, tz), Quaternion(qx, qy, qz, qw))),))
    reader = _Reader(raw, "TFMessage")
    transforms = []
    for _ in range(reader.count(74)):
        header = reader.header()
        child = reader.string()
        tx, ty, tz, qx, qy, qz, qw = reader.unpack(reader._seven_f64, 8)
        transforms.append(TransformStamped(header, child, Transform(Vector3(tx, ty, tz), Quaternion(qx, qy, qz, qw))))
    message = reader.end(TFMessage(tuple(transforms)))
    if len(transforms) == 1:
        numbers_at = reader.at - 56
        _last_tf_layout = _TfLayout(bytes(raw[:_STAMP_AT + 4]), bytes(raw[_TF_FRAME_AT:numbers_at]), numbers_at,
                                    _STRUCTS[reader.order]["iI"], reader._seven_f64, header.frame_id, child)
    return message


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
    if isinstance(raw, _BYTES) and len(raw) >= _FRAME_AT + 4:     # what the reader below needs: read at once
        order = _ENCAPSULATION.get(bytes(raw[:2]))
        if order is not None:
            sec, nanosec = _STRUCTS[order]["iI"].unpack_from(raw, _STAMP_AT)
            return sec * NS_PER_S + nanosec
    reader = _Reader(raw, "message")
    sec, nanosec, _ = reader.unpack(reader._header, 4)
    return sec * NS_PER_S + nanosec
