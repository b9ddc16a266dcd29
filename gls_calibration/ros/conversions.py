"""Conversions between ROS messages and numpy: the one module of the package that touches messages.

Section "PointCloud2 <-> numpy": a PointCloud2 maps onto a numpy structured array whose dtype
carries the message's field names, offsets, byte order and ``point_step`` (as the itemsize), so
reading a cloud is a view over ``msg.data`` and writing one copies the points into the message once.

Section "Units at the message boundary": clouds on the wire are in metres (REP 103), the core works
in millimetres; :func:`cloud_to_msg` and :func:`cloud_from_msg` are the only places that scale.
"""
from __future__ import annotations

import array
from collections.abc import Sequence
from dataclasses import fields

import numpy as np
import numpy.lib.recfunctions as recfunctions
import numpy.typing as npt
from builtin_interfaces.msg import Time
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header
import yaml

from gls_calibration.correction.setpoints import CorrectedSetpoints
from gls_calibration.fiducials.measure import FiducialMeasurement
from gls_calibration.models.training import TrainedModel
from gls_calibration.scan.plate_pose import PlatePose
from gls_calibration_msgs.msg import PlatePose as PlatePoseMsg

# ---------------------------------------------------------------------------------------------
# PointCloud2 <-> numpy
# ---------------------------------------------------------------------------------------------

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
    """The numpy name of a PointField datatype code (e.g. "float32"); "unknown <code>" for others."""
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
    """PointField datatype and count for one numpy field, or ValueError if it cannot be carried."""
    base, shape = (field_type.subdtype if field_type.subdtype is not None else (field_type, ()))
    code = _POINT_FIELD_CODES.get((base.kind, base.itemsize))
    if code is None or base.fields is not None or len(shape) > 1:
        raise ValueError(f"field '{name}' has dtype {field_type}, which PointCloud2 cannot carry "
                         f"(supported: {_SUPPORTED_TYPE_NAMES}, optionally as 1-D sub-arrays)")
    return code, int(np.prod(shape, dtype=int))


def _is_dense(points: np.ndarray) -> bool:
    """True unless some point has a NaN x, y or z (clouds without x, y, z count as dense)."""
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
    for axis, name in enumerate(_XYZ):
        points[name] = xyz[..., axis]
    if intensity is None:
        points["intensity"] = 0.0
    else:
        intensity = np.asarray(intensity)
        if intensity.shape != xyz.shape[:-1]:
            raise ValueError(f"intensity must have shape {xyz.shape[:-1]} to match xyz, "
                             f"got {intensity.shape}")
        points["intensity"] = intensity
    return points


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
    """A PointCloud2 in metres (float32 x, y, z, intensity) of a structured cloud in mm."""
    _require_fields(points_mm, _XYZ + ("intensity",))
    wire = np.empty(points_mm.shape, dtype=xyzi_dtype())
    for name in _XYZ:   # float32 division is correctly rounded: as exact as float32 metres can be
        np.divide(points_mm[name], np.float32(MM_PER_M), out=wire[name], dtype=np.float32)
    wire["intensity"] = points_mm["intensity"]
    return array_to_pointcloud2(wire, frame_id=frame_id, stamp=stamp)


def cloud_from_msg(msg: PointCloud2, mm_per_unit: float = MM_PER_M) -> np.ndarray:
    """The float32 x, y, z, intensity cloud (mm, a copy) of a PointCloud2 in metres, or in the unit
    of which one is ``mm_per_unit`` mm (1.0 for a driver that publishes millimetres)."""
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


# ---------------------------------------------------------------------------------------------
# Calibration messages <-> core types
# ---------------------------------------------------------------------------------------------
# rclpy wants array.array (or lists) for unbounded sequence fields and hands array.array back;
# numpy views over those buffers avoid per-element Python objects both ways.

def float64_sequence(values: npt.ArrayLike) -> array.array:
    """An ``array('d')`` for a float64[] field (one copy, no per-element objects)."""
    sequence = array.array("d")
    sequence.frombytes(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    return sequence


def uint32_sequence(values: npt.ArrayLike) -> array.array:
    """An ``array('I')`` for a uint32[] field."""
    sequence = array.array("I")
    sequence.frombytes(np.ascontiguousarray(values, dtype=np.uint32).tobytes())
    return sequence


def flag_array(sequence) -> np.ndarray:
    """A bool array from a uint8[] flag field (0 = false, anything else = true)."""
    if isinstance(sequence, (array.array, bytes)):
        return np.frombuffer(sequence, dtype=np.uint8) != 0
    return np.asarray(sequence, dtype=np.uint8).reshape(-1) != 0


def float64_array(sequence) -> np.ndarray:
    """A float64 numpy array over a float64[] field's buffer (a copy when it is a list)."""
    if isinstance(sequence, array.array):
        return np.frombuffer(sequence, dtype=np.float64) if len(sequence) else np.empty(0)
    return np.asarray(sequence, dtype=np.float64)


def time_to_msg(seconds: float) -> Time:
    """A builtin_interfaces Time from seconds since the epoch (UTC)."""
    nanoseconds = int(round(seconds * 1e9))
    return Time(sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000)


def plate_pose_to_msg(pose: PlatePose) -> PlatePoseMsg:
    """``plate_pose.PlatePose`` -> ``gls_calibration_msgs/PlatePose``."""
    return PlatePoseMsg(normal=np.asarray(pose.normal, float), centre=np.asarray(pose.centre, float),
                        rotation=np.asarray(pose.rotation, float).reshape(9),
                        flatness_rms_mm=float(pose.flatness_rms_mm), inliers=int(pose.inlier_count))


def plate_pose_from_msg(msg: PlatePoseMsg) -> PlatePose:
    """``gls_calibration_msgs/PlatePose`` -> ``plate_pose.PlatePose`` (ValueError if not a rotation)."""
    rotation = np.asarray(msg.rotation, dtype=float).reshape(3, 3)
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6) or np.linalg.det(rotation) < 0:
        raise ValueError("plate pose rotation is not a proper rotation matrix")
    if not np.all(np.isfinite(msg.centre)):
        raise ValueError(f"plate pose centre must be finite, got {list(msg.centre)}")
    return PlatePose(normal=rotation[:, 2].copy(), centre=np.asarray(msg.centre, dtype=float),
                     rotation=rotation, flatness_rms_mm=float(msg.flatness_rms_mm),
                     inlier_count=int(msg.inliers), inlier_fraction=float("nan"))


def fiducials_to_response(measurement: FiducialMeasurement, response) -> None:
    """Fill a MeasureFiducials response from a ``fiducials.FiducialMeasurement``."""
    centres = np.asarray(measurement.centres, dtype=float).reshape(-1, 3)
    response.x, response.y, response.z = (float64_sequence(centres[:, axis]) for axis in range(3))
    response.quality = float64_sequence(measurement.quality)
    response.outer_radius = float64_sequence(measurement.radii)
    response.inner_radius = float64_sequence(measurement.inner_radii)
    response.merged = int(measurement.merged)
    response.rejected = int(measurement.rejected)
    response.missing = int(measurement.missing or 0)
    sigma = np.asarray(measurement.sigma_xy_mm, dtype=float).reshape(-1, 2)
    response.sigma_x, response.sigma_y = float64_sequence(sigma[:, 0]), float64_sequence(sigma[:, 1])
    response.coverage = float64_sequence(measurement.coverage)
    rejected = np.asarray(measurement.rejected_centres, dtype=float).reshape(-1, 3)
    response.rejected_x, response.rejected_y, response.rejected_z = (
        float64_sequence(rejected[:, axis]) for axis in range(3))
    response.rejected_reason = [str(reason) for reason in measurement.rejected_reasons]


def fiducials_from_response(response, pose: PlatePose) -> FiducialMeasurement:
    """A ``fiducials.FiducialMeasurement`` from a MeasureFiducials response and the pose it used."""
    centres = np.column_stack([float64_array(response.x), float64_array(response.y), float64_array(response.z)])
    return FiducialMeasurement(
        centres=centres, centres_plane=pose.to_plane(centres) if len(centres) else np.empty((0, 2)),
        quality=float64_array(response.quality), radii=float64_array(response.outer_radius),
        inner_radii=float64_array(response.inner_radius), merged=int(response.merged),
        rejected=int(response.rejected), missing=int(response.missing), image_shape=(0, 0),
        pixel_pitch_mm=(float("nan"), float("nan")),
        sigma_xy_mm=np.column_stack([float64_array(response.sigma_x), float64_array(response.sigma_y)]),
        sigma_plane_mm=None, coverage=float64_array(response.coverage),
        rejected_centres=np.column_stack([float64_array(response.rejected_x), float64_array(response.rejected_y),
                                          float64_array(response.rejected_z)]),
        rejected_reasons=tuple(str(reason) for reason in response.rejected_reason))


SETPOINT_FLAGS = ("inside_calibrated_field", "within_limits")   # uint8[] fields, 1 = true
OPTIONAL_SETPOINT_FIELDS = ("uncertainty_k2_mm",)     # filled where the message type has them (issue 30)


def start_setpoints_response(response) -> dict[str, array.array]:
    """Empty the array fields of a CorrectSetpoints response and return them by ``CorrectedSetpoints``
    field name, to be extended chunk by chunk (``append_setpoints``): nothing of the whole answer's
    size is allocated, concatenated or converted at once while the interpreter lock is held."""
    sequences = {}
    for field in fields(CorrectedSetpoints):
        if field.name in OPTIONAL_SETPOINT_FIELDS and not hasattr(response, field.name):
            continue     # message definitions built before the field existed
        setattr(response, field.name, array.array("B" if field.name in SETPOINT_FLAGS else "d"))
        sequences[field.name] = getattr(response, field.name)   # the setter copies: extend the stored one
    return sequences


def append_setpoints(sequences: dict[str, array.array], part: CorrectedSetpoints) -> None:
    """Append a ``CorrectedSetpoints`` (flags as 0/1) to the arrays of ``start_setpoints_response``."""
    for name, sequence in sequences.items():
        dtype = np.uint8 if name in SETPOINT_FLAGS else np.float64
        values = getattr(part, name)
        if values is None:           # setpoints made without an uncertainty: NaN, as a calibration without a map
            values = np.full(len(part.x), np.nan)
        sequence.frombytes(np.ascontiguousarray(values, dtype=dtype).tobytes())


def setpoints_to_response(result, response) -> None:
    """Fill a CorrectSetpoints response from a ``correction.CorrectedSetpoints``."""
    append_setpoints(start_setpoints_response(response), result)


def setpoints_from_response(response) -> CorrectedSetpoints:
    """A ``correction.CorrectedSetpoints`` from a CorrectSetpoints response."""
    return CorrectedSetpoints(x=float64_array(response.x), y=float64_array(response.y),
                              alpha_x=float64_array(response.alpha_x), alpha_y=float64_array(response.alpha_y),
                              focus_shift=float64_array(response.focus_shift),
                              inside_calibrated_field=flag_array(response.inside_calibrated_field),
                              within_limits=flag_array(response.within_limits),
                              uncertainty_k2_mm=float64_array(response.uncertainty_k2_mm)
                              if hasattr(response, "uncertainty_k2_mm") else None)


def trained_model_from_response(response) -> TrainedModel:
    """A ``training.TrainedModel`` from a TrainCorrection response (ValueError on a bad model)."""
    model = yaml.safe_load(response.model_yaml)
    if not isinstance(model, dict) or "type" not in model:
        raise ValueError("the trainer answered with a model that is not a mapping with a 'type'")
    return TrainedModel(model=model, method=response.method, neurons=int(response.neurons),
                        spread_mm=float(response.spread_mm), cv_rms_mm=float(response.cv_rms_mm))
