"""PointCloud2 <-> numpy conversions: bit-exact round trips, zero-copy views and malformed messages."""
from __future__ import annotations

import struct

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.time import Time as RclpyTime
from sensor_msgs.msg import PointCloud2, PointField

from gls_calibration.ros.conversions import (array_to_pointcloud2, pointcloud2_to_array, unstructured_xyz,
                                             xyz_intensity_arrays, xyzi_array, xyzi_dtype)

# A scanner-like layout with every awkward feature: a float64 field, small integer fields, a
# count-3 sub-array, holes between fields and trailing padding (point_step 48 > 41 bytes used).
RICH_DTYPE = np.dtype({
    "names": ["x", "y", "z", "intensity", "timestamp", "ring", "label", "normal"],
    "formats": ["<f4", "<f4", "<f4", "<f4", "<f8", "<u2", "i1", ("<f4", (3,))],
    "offsets": [0, 4, 8, 12, 16, 24, 26, 28],
    "itemsize": 48,
})
RICH_CODES = {"x": (PointField.FLOAT32, 1), "y": (PointField.FLOAT32, 1), "z": (PointField.FLOAT32, 1),
              "intensity": (PointField.FLOAT32, 1), "timestamp": (PointField.FLOAT64, 1),
              "ring": (PointField.UINT16, 1), "label": (PointField.INT8, 1),
              "normal": (PointField.FLOAT32, 3)}


def random_bits_cloud(shape: tuple[int, ...], dtype: np.dtype, seed: int) -> np.ndarray:
    """Cloud whose every byte is random: NaN payloads, infinities and padding bytes included."""
    rng = np.random.default_rng(seed)
    count = int(np.prod(shape))
    return np.frombuffer(rng.bytes(count * dtype.itemsize), dtype=dtype).reshape(shape).copy()


def field_bits(points: np.ndarray, name: str) -> np.ndarray:
    """Raw bits of one field in native byte order (byte swapping is exact, NaN payloads too)."""
    values = points[name]
    native = values.astype(values.dtype.newbyteorder("="))
    return np.ascontiguousarray(native).view(np.uint8)


def assert_fields_bitwise_equal(actual: np.ndarray, expected: np.ndarray) -> None:
    assert actual.shape == expected.shape
    assert actual.dtype.names == expected.dtype.names
    for name in expected.dtype.names:
        np.testing.assert_array_equal(field_bits(actual, name), field_bits(expected, name), err_msg=name)


def shares_message_buffer(points: np.ndarray, msg: PointCloud2) -> bool:
    return np.shares_memory(points, np.frombuffer(msg.data, dtype=np.uint8))


def xyzi_cloud(shape: tuple[int, ...], seed: int, nan_fraction: float = 0.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xyz = rng.normal(scale=100.0, size=shape + (3,))
    xyz[rng.random(shape + (3,)) < nan_fraction] = np.nan
    return xyzi_array(xyz, rng.random(shape))


# --- round trips -------------------------------------------------------------------------------

@pytest.mark.parametrize("big_endian", [False, True])
@pytest.mark.parametrize("shape", [(257,), (7, 13), (0,)])
@pytest.mark.parametrize("dtype", [xyzi_dtype(), RICH_DTYPE], ids=["xyzi", "rich"])
def test_round_trip_is_bit_exact(dtype, shape, big_endian):
    points = random_bits_cloud(shape, dtype, seed=len(shape) * 10 + big_endian)
    msg = array_to_pointcloud2(points, "scanner", big_endian=big_endian)
    back = pointcloud2_to_array(msg, field_names=None)
    assert_fields_bitwise_equal(back, points)
    assert back.dtype.itemsize == msg.point_step == dtype.itemsize
    assert msg.is_bigendian == big_endian
    if not big_endian:
        # Little-endian wire data is the array's memory as is, padding bytes included.
        assert bytes(msg.data) == points.tobytes()


def test_message_layout_follows_the_dtype():
    points = random_bits_cloud((4, 6), RICH_DTYPE, seed=1)
    msg = array_to_pointcloud2(points)
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (4, 6, 48, 6 * 48)
    assert len(msg.data) == 4 * 6 * 48
    assert [field.name for field in msg.fields] == list(RICH_DTYPE.names)
    for field in msg.fields:
        assert (field.datatype, field.count) == RICH_CODES[field.name]
        assert field.offset == RICH_DTYPE.fields[field.name][1]


def test_big_endian_bytes_are_big_endian():
    points = xyzi_cloud((5,), seed=2)
    msg = array_to_pointcloud2(points, big_endian=True)
    first_x, = struct.unpack_from(">f", bytes(msg.data), 0)
    second_intensity, = struct.unpack_from(">f", bytes(msg.data), msg.point_step + 12)
    assert first_x == points["x"][0]
    assert second_intensity == points["intensity"][1]


def test_big_endian_input_written_little_endian():
    points = random_bits_cloud((9,), RICH_DTYPE.newbyteorder(">"), seed=3)
    msg = array_to_pointcloud2(points, big_endian=False)
    assert not msg.is_bigendian
    assert_fields_bitwise_equal(pointcloud2_to_array(msg, None), points)


def test_deserialized_message_round_trip():
    points = xyzi_cloud((6, 8), seed=4, nan_fraction=0.1)
    msg = array_to_pointcloud2(points, "scanner")
    received = deserialize_message(serialize_message(msg), PointCloud2)
    back = pointcloud2_to_array(received)
    assert back.tobytes() == points.tobytes()
    assert shares_message_buffer(back, received)


def test_single_row_array_comes_back_unorganized():
    points = xyzi_cloud((1, 10), seed=5)
    msg = array_to_pointcloud2(points)
    assert (msg.height, msg.width) == (1, 10)
    assert pointcloud2_to_array(msg).shape == (10,)


def test_header_and_density():
    dense = array_to_pointcloud2(xyzi_cloud((20,), seed=6), "plate", Time(sec=12, nanosec=34))
    assert dense.header.frame_id == "plate"
    assert (dense.header.stamp.sec, dense.header.stamp.nanosec) == (12, 34)
    assert dense.is_dense
    holes = array_to_pointcloud2(xyzi_cloud((20,), seed=6, nan_fraction=0.2),
                                 stamp=RclpyTime(seconds=5, nanoseconds=6))
    assert (holes.header.stamp.sec, holes.header.stamp.nanosec) == (5, 6)
    assert not holes.is_dense
    unstamped = array_to_pointcloud2(xyzi_cloud((3,), seed=6))
    assert (unstamped.header.stamp.sec, unstamped.header.stamp.nanosec) == (0, 0)


# --- reading: views, selection, NaNs, padding ----------------------------------------------------

def test_result_is_a_view_into_the_message():
    points = xyzi_cloud((3, 4), seed=7)
    msg = array_to_pointcloud2(points)
    view = pointcloud2_to_array(msg, ("z", "x"))
    assert view.dtype.names == ("z", "x")
    assert view.dtype.itemsize == 16
    assert shares_message_buffer(view, msg)
    np.testing.assert_array_equal(view["z"], points["z"])
    view["x"][1, 2] = 123.0        # documented: writing into the view writes into the message
    assert pointcloud2_to_array(msg)["x"][1, 2] == 123.0


def test_all_fields_when_field_names_is_none():
    points = random_bits_cloud((5,), RICH_DTYPE, seed=8)
    back = pointcloud2_to_array(array_to_pointcloud2(points), field_names=None)
    assert back.dtype.names == RICH_DTYPE.names
    assert back["normal"].shape == (5, 3)


def test_skip_nans_drops_points_with_a_nan_coordinate_only():
    points = xyzi_cloud((10, 12), seed=9)
    points["x"][0, 1] = np.nan
    points["y"][3, 4] = np.nan
    points["z"][9, 11] = np.nan
    points["intensity"][5, 5] = np.nan      # not a coordinate: the point stays
    msg = array_to_pointcloud2(points)
    kept = pointcloud2_to_array(msg, ("x", "intensity"), skip_nans=True)
    valid = ~(np.isnan(points["x"]) | np.isnan(points["y"]) | np.isnan(points["z"]))
    assert kept.shape == (120 - 3,)
    assert_fields_bitwise_equal(kept, pointcloud2_to_array(msg, ("x", "intensity"))[valid])
    assert not shares_message_buffer(kept, msg)


def test_row_padding_is_skipped_without_copying():
    points = xyzi_cloud((3, 5), seed=10)
    row_step = 5 * 16 + 12
    padded = np.full((3, row_step), 0xAB, dtype=np.uint8)
    padded[:, :80] = points.view(np.uint8).reshape(3, 80)
    packed = array_to_pointcloud2(points)
    msg = PointCloud2(header=packed.header, height=3, width=5, fields=packed.fields, is_bigendian=False,
                      point_step=16, row_step=row_step, data=padded.tobytes(), is_dense=True)
    view = pointcloud2_to_array(msg)
    assert view.tobytes() == points.tobytes()
    assert shares_message_buffer(view, msg)
    assert_fields_bitwise_equal(pointcloud2_to_array(msg, skip_nans=True), points.reshape(-1))


# --- helpers -----------------------------------------------------------------------------------

def test_xyzi_helpers_round_trip():
    rng = np.random.default_rng(11)
    xyz = rng.normal(size=(4, 6, 3)).astype(np.float32)
    intensity = rng.random((4, 6)).astype(np.float32)
    points = xyzi_array(xyz, intensity)
    assert points.dtype == xyzi_dtype() and points.dtype.itemsize == 16
    message = array_to_pointcloud2(points, big_endian=True)
    back_xyz, back_intensity = xyz_intensity_arrays(pointcloud2_to_array(message))
    assert back_xyz.dtype == np.float64 and back_xyz.shape == (4, 6, 3)
    np.testing.assert_array_equal(back_xyz, xyz)
    np.testing.assert_array_equal(back_intensity, intensity)
    np.testing.assert_array_equal(xyzi_array(xyz)["intensity"], 0.0)


def test_unstructured_xyz_view_when_layout_allows():
    points = xyzi_cloud((8,), seed=12)
    view = unstructured_xyz(points, dtype=None)
    assert view.shape == (8, 3) and np.shares_memory(view, points)
    np.testing.assert_array_equal(view[:, 2], points["z"])


# --- malformed messages and bad input -------------------------------------------------------------

def xyz_message(**overrides) -> PointCloud2:
    """A valid 2-point x, y, z message (point_step 12) with some attributes replaced."""
    fields = [PointField(name=name, offset=4 * index, datatype=PointField.FLOAT32, count=1)
              for index, name in enumerate("xyz")]
    values = dict(height=1, width=2, fields=fields, is_bigendian=False, point_step=12, row_step=24,
                  data=bytes(24), is_dense=True)
    values.update(overrides)
    return PointCloud2(**values)


def test_valid_xyz_message_reads():
    assert pointcloud2_to_array(xyz_message(), ("x", "y", "z")).shape == (2,)


@pytest.mark.parametrize(("overrides", "field_names", "message"), [
    ({}, ("x", "y", "z", "intensity"), r"^PointCloud2 has no field 'intensity' \(fields: x, y, z\)$"),
    ({"fields": []}, ("x",), r"^PointCloud2 has no field 'x' \(fields: none\)$"),
    ({"data": bytes(20)}, ("x",), r"^PointCloud2 data length 20 does not match height \* row_step = 24$"),
    ({"height": 2}, ("x",), r"^PointCloud2 data length 24 does not match height \* row_step = 48$"),
    ({"row_step": 10, "data": bytes(10)}, ("x",),
     r"^PointCloud2 row_step 10 is smaller than width \* point_step = 24$"),
    ({"fields": [PointField(name="x", offset=0, datatype=42, count=1)]}, ("x",),
     r"^PointCloud2 field 'x' has unknown datatype 42$"),
    ({"fields": [PointField(name="x", offset=0, datatype=PointField.FLOAT32, count=0)]}, ("x",),
     r"^PointCloud2 field 'x' has count 0; expected at least 1$"),
    ({"fields": [PointField(name="x", offset=8, datatype=PointField.FLOAT64, count=1)]}, ("x",),
     r"^PointCloud2 field 'x' ends at byte 16, beyond point_step 12$"),
    ({"fields": [PointField(name="n", offset=0, datatype=PointField.FLOAT32, count=4)]}, ("n",),
     r"^PointCloud2 field 'n' ends at byte 16, beyond point_step 12$"),
    ({"fields": [PointField(name="x", offset=0, datatype=PointField.FLOAT32, count=1)] * 2}, ("x",),
     r"^PointCloud2 has field 'x' more than once$"),
    ({"point_step": 0, "row_step": 0, "data": b"", "fields": []}, ("x",),
     r"^PointCloud2 point_step is 0 but width is positive$"),
    ({}, ("x", "x"), r"^field_names lists 'x' more than once$"),
    ({}, "x", r"^field_names must be a sequence of names, got the string 'x'$"),
])
def test_malformed_message_raises(overrides, field_names, message):
    with pytest.raises(ValueError, match=message):
        pointcloud2_to_array(xyz_message(**overrides), field_names)


def test_skip_nans_needs_coordinates():
    msg = xyz_message(fields=[PointField(name="x", offset=0, datatype=PointField.FLOAT32, count=1)])
    with pytest.raises(ValueError, match=r"^skip_nans needs fields x, y and z; PointCloud2 has no field 'y' "
                                         r"\(fields: x\)$"):
        pointcloud2_to_array(msg, ("x",), skip_nans=True)


@pytest.mark.parametrize(("points", "message"), [
    (np.zeros((4, 3), dtype=np.float32), r"^points must be a structured numpy array \(see xyzi_dtype\(\)\), "
                                         r"got float32$"),
    ([(1.0, 2.0, 3.0, 4.0)], r"^points must be a structured numpy array .*got list$"),
    (np.zeros((2, 2, 2), dtype=xyzi_dtype()), r"^points must have 1 or 2 dimensions, got shape \(2, 2, 2\)$"),
    (np.zeros(3, dtype=[("x", "<i8")]), r"^field 'x' has dtype int64, which PointCloud2 cannot carry"),
    (np.zeros(3, dtype=[("x", "<f2")]), r"^field 'x' has dtype float16, which PointCloud2 cannot carry"),
    (np.zeros(3, dtype=[("flag", "?")]), r"^field 'flag' has dtype bool, which PointCloud2 cannot carry"),
    (np.zeros(3, dtype=[("m", "<f4", (2, 2))]),
     r"^field 'm' has dtype \('<f4', \(2, 2\)\), which PointCloud2"),
    (np.zeros(3, dtype=[("p", [("a", "<f4")])]), r"^field 'p' has dtype .*, which PointCloud2 cannot carry"),
])
def test_array_to_pointcloud2_rejects_bad_input(points, message):
    with pytest.raises(ValueError, match=message):
        array_to_pointcloud2(points)


@pytest.mark.parametrize(("call", "message"), [
    (lambda: xyzi_array(np.zeros((5, 2))), r"^xyz must have shape \(\.\.\., 3\), got \(5, 2\)$"),
    (lambda: xyzi_array(np.zeros((5, 3)), np.zeros(4)), r"^intensity must have shape \(5,\) to match xyz, "
     r"got \(4,\)$"),
    (lambda: unstructured_xyz(np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4")])),
     r"^points has no field 'z' \(fields: x, y\)$"),
    (lambda: xyz_intensity_arrays(np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])),
     r"^points has no field 'intensity' \(fields: x, y, z\)$"),
    (lambda: unstructured_xyz(np.zeros((3, 3))), r"^points has no field 'x' \(fields: none\)$"),
])
def test_helpers_reject_bad_input(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_fiducial_uncertainties_and_rejections_survive_the_service_response():
    from gls_calibration.fiducials.measure import FiducialMeasurement
    from gls_calibration.ros.conversions import fiducials_from_response, fiducials_to_response
    from gls_calibration.scan.plate_pose import estimate_plate_pose
    from gls_calibration_msgs.srv import MeasureFiducials

    plane = np.column_stack([np.random.default_rng(3).uniform(-5, 5, (2000, 2)), np.zeros(2000)])
    pose = estimate_plate_pose(plane)
    centres = np.array([[1.0, 2.0, 0.0], [3.0, -1.0, 0.0]])
    measurement = FiducialMeasurement(
        centres=centres, centres_plane=pose.to_plane(centres), quality=np.array([0.001, 0.002]),
        radii=np.array([2.7, 2.71]), inner_radii=np.array([2.5, 2.49]), merged=0, rejected=1, missing=3,
        image_shape=(10, 10), pixel_pitch_mm=(0.1, 0.1), sigma_xy_mm=np.array([[0.002, 0.003], [0.004, 0.005]]),
        coverage=np.array([1.0, 0.8]), rejected_centres=np.array([[7.0, 7.0, 0.0]]), rejected_reasons=("partial",),
        rejected_sigma_xy_mm=np.array([[0.02, 0.02]]), rejected_coverage=np.array([0.5]))
    response = MeasureFiducials.Response()
    fiducials_to_response(measurement, response)
    back = deserialize_message(serialize_message(response), MeasureFiducials.Response)
    restored = fiducials_from_response(back, pose)
    assert np.allclose(restored.sigma_xy_mm, measurement.sigma_xy_mm)
    assert np.allclose(restored.coverage, measurement.coverage)
    assert np.allclose(restored.rejected_centres, measurement.rejected_centres)
    assert restored.rejected_reasons == ("partial",) and restored.rejected == 1
    assert restored.sigma_plane_mm.shape == (2, 2) and np.isnan(restored.sigma_plane_mm).all()


def test_marked_paths_split_into_their_polylines():
    from gls_calibration.ros.conversions import marked_polylines
    from gls_calibration_msgs.msg import MarkedPaths
    points = np.arange(15, dtype=float).reshape(5, 3)
    paths = MarkedPaths(x=points[:, 0].tolist(), y=points[:, 1].tolist(), z=points[:, 2].tolist(),
                        polyline_starts=[0, 2])
    polylines = marked_polylines(paths)
    assert [polyline.tolist() for polyline in polylines] == [points[:2].tolist(), points[2:].tolist()]
    assert marked_polylines(MarkedPaths()) == []
