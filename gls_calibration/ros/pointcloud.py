"""PointCloud2 <-> numpy, and the units at the message boundary.

A PointCloud2 maps onto a numpy structured array whose dtype carries the message's field names,
offsets, byte order and ``point_step`` (as the itemsize), so reading a cloud is a view over
``msg.data`` and writing one copies the points into the message once.

Clouds on the wire are in metres (REP 103), the core works in millimetres; :func:`cloud_to_msg` and
:func:`cloud_from_msg` are the only places that scale.
"""
from __future__ import annotations

import array
from collections.abc import Callable, Sequence

import numpy as np
import numpy.lib.recfunctions as recfunctions
import numpy.typing as npt
from builtin_interfaces.msg import Time
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header


# sensor_msgs/PointField datatype codes and the numpy types they stand for (byte order set later).
_POINT_FIELD_TYPES: dict[int, np.dtype] = {
    PointField.INT8: np.dtype("i1"),
    PointField.UINT8: np.dtype("u1"),
    PointField.INT16: np.dtype("i2"),
    PointField.UINT16: np.dtype("u2"),
    PointField.INT32: np.dtype("i4"),
    PointField.UINT32: np.dtype("u4"),
    PointField.FLOAT32: np.dtype("f4"),
    PointField.FLOAT64: np.dtype("f8"),
}
_POINT_FIELD_CODES: dict[tuple[str, int], int] = {
    (numpy_type.kind, numpy_type.itemsize): code for code, numpy_type in _POINT_FIELD_TYPES.items()}
_SUPPORTED_TYPE_NAMES = ", ".join(numpy_type.name for numpy_type in _POINT_FIELD_TYPES.values())
_XYZ = ("x", "y", "z")


def point_field_type_name(datatype: int) -> str:
    """Return the numpy name of a PointField datatype code (e.g. "float32"); "unknown <code>" for others."""
    numpy_type = _POINT_FIELD_TYPES.get(datatype)
    return numpy_type.name if numpy_type is not None else f"unknown {datatype}"


def xyzi_dtype() -> np.dtype:
    """Packed float32 x, y, z, intensity point (16 bytes): the package's default cloud layout."""
    return np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])


def _field_list(names: Sequence[str]) -> str:
    return ", ".join(names) if names else "none"


def _message_dtype(msg: PointCloud2) -> np.dtype:
    """Validate the layout of ``msg`` and return the dtype of one whole point (itemsize point_step)."""
    byte_order = ">" if msg.is_bigendian else "<"
    point_step = int(msg.point_step)
    names: list[str] = []
    formats: list[np.dtype] = []
    offsets: list[int] = []
    for field in msg.fields:
        if field.name in names:
            raise ValueError(f"PointCloud2 has field '{field.name}' more than once")
        if field.datatype not in _POINT_FIELD_TYPES:
            raise ValueError(f"PointCloud2 field '{field.name}' has unknown datatype {field.datatype}")
        if field.count < 1:
            raise ValueError(f"PointCloud2 field '{field.name}' has count {field.count}; expected at least 1")
        base = _POINT_FIELD_TYPES[field.datatype].newbyteorder(byte_order)
        end = field.offset + base.itemsize * field.count
        if end > point_step:
            raise ValueError(f"PointCloud2 field '{field.name}' ends at byte {end}, "
                             f"beyond point_step {point_step}")
        names.append(field.name)
        formats.append(base if field.count == 1 else np.dtype((base, (field.count,))))
        offsets.append(int(field.offset))
    width, height, row_step = int(msg.width), int(msg.height), int(msg.row_step)
    if width > 0 and point_step == 0:
        raise ValueError("PointCloud2 point_step is 0 but width is positive")
    if row_step < width * point_step:
        raise ValueError(f"PointCloud2 row_step {row_step} is smaller than "
                         f"width * point_step = {width * point_step}")
    data_length = memoryview(msg.data).nbytes
    if data_length != height * row_step:
        raise ValueError(f"PointCloud2 data length {data_length} does not match "
                         f"height * row_step = {height * row_step}")
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})


def _select_fields(point_dtype: np.dtype, field_names: Sequence[str] | None) -> np.dtype:
    """Dtype that keeps only ``field_names`` (in that order) at their offsets, itemsize unchanged."""
    available = point_dtype.names
    if field_names is None:
        return point_dtype
    if isinstance(field_names, str):
        raise ValueError(f"field_names must be a sequence of names, got the string {field_names!r}")
    seen: set[str] = set()
    for name in field_names:
        if name in seen:
            raise ValueError(f"field_names lists '{name}' more than once")
        seen.add(name)
        if name not in available:
            raise ValueError(f"PointCloud2 has no field '{name}' (fields: {_field_list(available)})")
    return np.dtype({
        "names": list(field_names),
        "formats": [point_dtype.fields[name][0] for name in field_names],
        "offsets": [point_dtype.fields[name][1] for name in field_names],
        "itemsize": point_dtype.itemsize,
    })


def _cloud_view(msg: PointCloud2, dtype: np.dtype) -> np.ndarray:
    """Zero-copy (height, width) view of msg.data; strides skip row padding."""
    height, width = int(msg.height), int(msg.width)
    return np.ndarray(shape=(height, width), dtype=dtype, buffer=msg.data, offset=0,
                      strides=(int(msg.row_step), dtype.itemsize))


def pointcloud2_to_array(msg: PointCloud2, field_names: Sequence[str] | None = ("x", "y", "z", "intensity"),
                         skip_nans: bool = False) -> np.ndarray:
    """Structured array of the points in ``msg``, holding only ``field_names`` (None: every field).

    Organized clouds (height > 1) give shape (height, width), others (width,). Without
    ``skip_nans`` the result is a zero-copy view over ``msg.data``: it keeps the message's byte
    order, offsets and point_step (the itemsize), and writing into it writes into the message.
    With ``skip_nans`` the points whose x, y or z is NaN are dropped and the result is a 1-D copy
    with the same dtype.
    Fields with count > 1 appear as sub-arrays. A malformed message raises ValueError.
    """
    point_dtype = _message_dtype(msg)
    selected = _cloud_view(msg, _select_fields(point_dtype, field_names))
    if skip_nans:
        missing = [name for name in _XYZ if name not in point_dtype.names]
        if missing:
            raise ValueError(f"skip_nans needs fields x, y and z; PointCloud2 has no field '{missing[0]}' "
                             f"(fields: {_field_list(point_dtype.names)})")
        coordinates = _cloud_view(msg, _select_fields(point_dtype, _XYZ))
        invalid = np.zeros(coordinates.shape, dtype=bool)
        for name in _XYZ:
            values = coordinates[name]
            # count > 1 coordinates are unusual; any NaN component invalidates the point.
            invalid |= np.isnan(values).reshape(coordinates.shape + (-1,)).any(axis=-1)
        # take() with indices copies whole points and beats boolean indexing of structured arrays.
        return selected.reshape(-1).take(np.flatnonzero(~invalid.reshape(-1)))
    if msg.height > 1:
        return selected
    return selected.reshape(-1)


def _field_code(name: str, field_type: np.dtype) -> tuple[int, int]:
    """Return the PointField datatype and count for one numpy field; ValueError if not carried."""
    base, shape = (field_type.subdtype if field_type.subdtype is not None else (field_type, ()))
    code = _POINT_FIELD_CODES.get((base.kind, base.itemsize))
    if code is None or base.fields is not None or len(shape) > 1:
        raise ValueError(f"field '{name}' has dtype {field_type}, which PointCloud2 cannot carry "
                         f"(supported: {_SUPPORTED_TYPE_NAMES}, optionally as 1-D sub-arrays)")
    return code, int(np.prod(shape, dtype=int))


def _is_dense(points: np.ndarray) -> bool:
    """Return True unless some point has a NaN x, y or z (clouds without x, y, z count as dense)."""
    if not all(name in points.dtype.names for name in _XYZ):
        return True
    return not any(np.isnan(points[name]).any() for name in _XYZ)


def array_to_pointcloud2(points: np.ndarray, frame_id: str = "", stamp: Time | None = None, *,
                         big_endian: bool = False) -> PointCloud2:
    """PointCloud2 holding the structured array ``points`` (1-D: height 1; 2-D: organized).

    The point layout is the array's dtype as is: field offsets and itemsize (point_step) are kept,
    so padding survives a round trip bit for bit; only the byte order is set by ``big_endian``.
    ``stamp`` is a builtin_interfaces Time (or anything with ``to_msg()``, such as rclpy Time);
    None means zero. ``is_dense`` is False when some point has a NaN x, y or z.
    """
    if not isinstance(points, np.ndarray) or points.dtype.names is None:
        got = points.dtype if isinstance(points, np.ndarray) else type(points).__name__
        raise ValueError(f"points must be a structured numpy array (see xyzi_dtype()), got {got}")
    if points.ndim not in (1, 2):
        raise ValueError(f"points must have 1 or 2 dimensions, got shape {points.shape}")
    if points.dtype.itemsize == 0:
        raise ValueError("points has an empty dtype (itemsize 0)")
    byte_order = ">" if big_endian else "<"
    fields: list[PointField] = []
    formats: list[np.dtype] = []
    offsets: list[int] = []
    for name in points.dtype.names:
        field_type, offset = points.dtype.fields[name][:2]
        code, count = _field_code(name, field_type)
        fields.append(PointField(name=name, offset=int(offset), datatype=code, count=count))
        formats.append(field_type.newbyteorder(byte_order))
        offsets.append(int(offset))
    wire_dtype = np.dtype({"names": list(points.dtype.names), "formats": formats, "offsets": offsets,
                           "itemsize": points.dtype.itemsize})
    if points.dtype == wire_dtype:
        wire = np.ascontiguousarray(points)
    else:
        # Zeroed first so that padding bytes are deterministic after the byte-order conversion.
        wire = np.zeros(points.shape, dtype=wire_dtype)
        wire[...] = points
    data = array.array("B")
    data.frombytes(wire.reshape(-1).view(np.uint8))
    if stamp is None:
        stamp = Time()
    elif hasattr(stamp, "to_msg"):
        stamp = stamp.to_msg()
    height, width = (1, points.shape[0]) if points.ndim == 1 else points.shape
    # check_fields=True lets the data setter keep our array.array instead of copying it again.
    msg = PointCloud2(check_fields=True)
    msg.header = Header(stamp=stamp, frame_id=frame_id)
    msg.height = int(height)
    msg.width = int(width)
    msg.fields = fields
    msg.is_bigendian = bool(big_endian)
    msg.point_step = int(wire_dtype.itemsize)
    msg.row_step = int(wire_dtype.itemsize * width)
    msg.data = data
    msg.is_dense = _is_dense(points)
    return msg


def xyzi_array(xyz: np.ndarray, intensity: np.ndarray | None = None) -> np.ndarray:
    """Structured :func:`xyzi_dtype` array from xyz (..., 3) and intensity (...) (None: zeros)."""
    xyz = np.asarray(xyz)
    if xyz.ndim < 1 or xyz.shape[-1] != 3:
        raise ValueError(f"xyz must have shape (..., 3), got {xyz.shape}")
    points = np.empty(xyz.shape[:-1], dtype=xyzi_dtype())
    words = _words(points)      # x, y, z, intensity as the last axis: one strided copy, not one per field
    words[..., :3] = xyz
    if intensity is None:
        words[..., 3] = 0.0
    else:
        intensity = np.asarray(intensity)
        if intensity.shape != xyz.shape[:-1]:
            raise ValueError(f"intensity must have shape {xyz.shape[:-1]} to match xyz, "
                             f"got {intensity.shape}")
        words[..., 3] = intensity
    return points


def _words(points: np.ndarray) -> np.ndarray:
    """Return the float32 words of an :func:`xyzi_dtype` array, x, y, z, intensity along a last axis (a view)."""
    return points.reshape(-1).view(np.float32).reshape(points.shape + (4,))


def _require_fields(points: np.ndarray, names: Sequence[str]) -> None:
    available = points.dtype.names or ()
    for name in names:
        if name not in available:
            raise ValueError(f"points has no field '{name}' (fields: {_field_list(available)})")


def unstructured_xyz(points: np.ndarray, dtype: npt.DTypeLike | None = np.float64) -> np.ndarray:
    """(..., 3) array of the x, y, z fields of a structured array.

    With ``dtype=None`` the fields' own type is kept and the result is a view where numpy can make
    one; otherwise it is a native-order copy in ``dtype``.
    """
    _require_fields(points, _XYZ)
    return recfunctions.structured_to_unstructured(points[list(_XYZ)], dtype=dtype)


def xyz_intensity_arrays(points: np.ndarray, dtype: npt.DTypeLike = np.float64
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Plain xyz (..., 3) and intensity (...) arrays (copies in ``dtype``) of a structured cloud."""
    _require_fields(points, _XYZ + ("intensity",))
    return unstructured_xyz(points, dtype), points["intensity"].astype(dtype)


# ---------------------------------------------------------------------------------------------
# Units at the message boundary
# ---------------------------------------------------------------------------------------------

MM_PER_M = 1000.0


def cloud_to_msg(points_mm: np.ndarray, frame_id: str, stamp: Time | None = None) -> PointCloud2:
    """Return a PointCloud2 in metres (float32 x, y, z, intensity) of a structured cloud in mm."""
    _require_fields(points_mm, _XYZ + ("intensity",))
    wire = np.empty(points_mm.shape, dtype=xyzi_dtype())
    # float32 division is correctly rounded: as exact as float32 metres can be
    if points_mm.dtype == xyzi_dtype():     # the package's own layout: the three fields in one strided division
        source, words = _words(np.ascontiguousarray(points_mm)), _words(wire)
        np.divide(source[..., :3], np.float32(MM_PER_M), out=words[..., :3], dtype=np.float32)
        words[..., 3] = source[..., 3]
    else:
        for name in _XYZ:
            np.divide(points_mm[name], np.float32(MM_PER_M), out=wire[name], dtype=np.float32)
        wire["intensity"] = points_mm["intensity"]
    return array_to_pointcloud2(wire, frame_id=frame_id, stamp=stamp)


def xyzi_cloud_to_msg(xyz_mm: np.ndarray, intensity: np.ndarray, frame_id: str, stamp: Time | None = None
                      ) -> PointCloud2:
    """Return ``cloud_to_msg(xyzi_array(xyz_mm, intensity), frame_id, stamp)``, written straight into the message.

    The same message, byte for byte, without the two intermediate clouds: the float32 metres are
    computed in the message's own buffer (a sweep of 2 000 x 2 000 points is 64 MB a copy).

    Parameters
    ----------
    xyz_mm : numpy.ndarray, shape (..., 3)
        Points, mm (1-D or 2-D grid of points: height 1 or organized).
    intensity : numpy.ndarray, shape (...)
        Intensity of each point.
    frame_id : str
        The cloud's frame.
    stamp : builtin_interfaces.msg.Time, optional
        Its stamp (None: zero).

    Returns
    -------
    sensor_msgs.msg.PointCloud2
        float32 x, y, z (m), intensity.

    Raises
    ------
    ValueError
        If ``xyz_mm`` is not (..., 3) of 1 or 2 dimensions of points or ``intensity`` does not match it.
    """
    xyz_mm, intensity = np.asarray(xyz_mm), np.asarray(intensity)
    if xyz_mm.ndim not in (2, 3) or xyz_mm.shape[-1] != 3:
        raise ValueError(f"xyz must have shape (W, 3) or (H, W, 3), got {xyz_mm.shape}")
    if intensity.shape != xyz_mm.shape[:-1]:
        raise ValueError(f"intensity must have shape {xyz_mm.shape[:-1]} to match xyz, got {intensity.shape}")
    msg, words = _xyzi_msg((1, xyz_mm.shape[0]) if xyz_mm.ndim == 2 else xyz_mm.shape[:2], frame_id, stamp)
    words = words.reshape(xyz_mm.shape[:-1] + (4,))
    # cast to float32 as xyzi_array casts, then divided in float32 as cloud_to_msg divides: one pass
    np.divide(xyz_mm, np.float32(MM_PER_M), out=words[..., :3], dtype=np.float32, casting="unsafe")
    words[..., 3] = intensity
    # a float is NaN in float32 metres exactly when it is NaN in xyz_mm (read contiguous, not strided)
    msg.is_dense = not bool(np.isnan(xyz_mm if xyz_mm.dtype.kind == "f" else words[..., :3]).any())
    return msg


# Rows a block of xyzi_blocks_to_msg holds: few enough that its float64 buffers (~64 B a point) stay in cache.
ROWS_PER_BLOCK = 32


def xyzi_blocks_to_msg(height: int, width: int, place_rows: Callable[[int, np.ndarray, np.ndarray], None],
                       frame_id: str, stamp: Time | None = None) -> PointCloud2:
    """Return the message :func:`xyzi_cloud_to_msg` builds of an organized cloud given a block of rows at a time.

    ``place_rows(first, out, intensity_out)`` writes the points (float64, mm) of rows ``first`` to
    ``first + len(out) - 1`` into ``out`` and their intensities into ``intensity_out``; each block
    goes straight into the message, so the cloud's float64 arrays (a sweep of 2 000 x 2 000 points is
    96 MB of points) are never made, with a few calls for all its rows (a dozen calls per row were
    most of the cost for a sweep of narrow profiles). The same element-wise casts and divisions, so
    the message is byte for byte the one :func:`xyzi_cloud_to_msg` gives for the rows stacked.

    Parameters
    ----------
    height, width : int
        Rows and points per row.
    place_rows : callable
        ``place_rows(first: int, out: numpy.ndarray of shape (B, width, 3), intensity_out: numpy.ndarray
        of shape (B, width)) -> None``, B at most ``ROWS_PER_BLOCK``.
    frame_id : str
        The cloud's frame.
    stamp : builtin_interfaces.msg.Time, optional
        Its stamp (None: zero).

    Returns
    -------
    sensor_msgs.msg.PointCloud2
        float32 x, y, z (m), intensity, organized (height x width).

    Raises
    ------
    ValueError
        If ``height`` or ``width`` is negative.
    """
    if height < 0 or width < 0:
        raise ValueError(f"height and width must not be negative, got {height} x {width}")
    msg, words = _xyzi_msg((height, width), frame_id, stamp)
    words = words.reshape(height, width, 4)
    xyz_mm = np.empty((min(height, ROWS_PER_BLOCK), width, 3))
    dense = True
    scale = np.float32(MM_PER_M)
    for first in range(0, height, ROWS_PER_BLOCK):
        rows = min(ROWS_PER_BLOCK, height - first)
        block = xyz_mm[:rows]
        place_rows(first, block, words[first:first + rows, :, 3])
        for axis in range(3):
            np.divide(block[:, :, axis], scale, out=words[first:first + rows, :, axis], dtype=np.float32,
                      casting="unsafe")
        dense = dense and not bool(np.isnan(block).any())
    msg.is_dense = dense
    return msg


def _xyzi_msg(shape: tuple[int, int], frame_id: str, stamp: Time | None) -> tuple[PointCloud2, np.ndarray]:
    """Return a float32 x, y, z, intensity PointCloud2 of ``shape`` (height, width) and its data as float32 words.

    The data is a fresh buffer the caller fills (through the words, (height * width * 4,)); ``is_dense``
    is left for the caller to set.
    """
    height, width = shape
    point = xyzi_dtype()
    data = array.array("B", bytes(point.itemsize)) * (int(height) * int(width))
    msg = PointCloud2(check_fields=True)
    msg.header = Header(stamp=Time() if stamp is None else stamp, frame_id=frame_id)
    msg.height = int(height)
    msg.width = int(width)
    msg.fields = [PointField(name=name, offset=int(point.fields[name][1]), datatype=PointField.FLOAT32, count=1)
                  for name in point.names]
    msg.is_bigendian = False
    msg.point_step = int(point.itemsize)
    msg.row_step = int(point.itemsize * width)
    msg.data = data
    return msg, np.frombuffer(data, dtype=np.float32)


def cloud_from_msg(msg: PointCloud2, mm_per_unit: float = MM_PER_M) -> np.ndarray:
    """Return the float32 x, y, z, intensity cloud (mm, a copy) of a PointCloud2.

    The PointCloud2 is in metres, or in the unit of which one is ``mm_per_unit`` mm (1.0 for a
    driver that publishes millimetres).
    """
    view = pointcloud2_to_array(msg)
    _require_fields(view, _XYZ + ("intensity",))
    points = np.empty(view.shape, dtype=xyzi_dtype())
    with np.errstate(over="ignore"):   # a value beyond float32 becomes inf, which the caller refuses
        for name in _XYZ:
            np.multiply(view[name], np.float32(mm_per_unit), out=points[name], dtype=np.float32)
    points["intensity"] = view["intensity"]
    return points


def cloud_arrays_from_msg(msg: PointCloud2) -> tuple[np.ndarray, np.ndarray]:
    """float64 xyz (H, W, 3) or (N, 3) in mm and intensity of a PointCloud2 (x, y, z in metres, intensity)."""
    xyz, intensity = xyz_intensity_arrays(pointcloud2_to_array(msg))
    xyz *= MM_PER_M
    return xyz, intensity
