"""Conversions between the package's service messages and the core's types (arrays, dataclasses).

With :mod:`gls_calibration.ros.pointcloud` (clouds and their units, whose names it also offers) the
only modules of the package that touch messages.
"""
from __future__ import annotations

import array
from dataclasses import fields

import numpy as np
import numpy.typing as npt
from builtin_interfaces.msg import Time
import yaml

from gls_calibration.common.bounded_yaml import SAFE_LOADER
from gls_calibration.correction.setpoints import CorrectedSetpoints
from gls_calibration.fiducials.measure import FiducialMeasurement
from gls_calibration.models.training import TrainedModel
from gls_calibration.ros.pointcloud import (MM_PER_M, array_to_pointcloud2, cloud_arrays_from_msg,
                                            cloud_from_msg, cloud_to_msg, point_field_type_name,
                                            pointcloud2_to_array, unstructured_xyz, xyz_intensity_arrays,
                                            xyzi_array, xyzi_dtype)
from gls_calibration.scan.plate_pose import PlatePose
from gls_calibration_msgs.msg import PlatePose as PlatePoseMsg

# The cloud conversions (first line) are offered here too: a node imports one module for its messages.
__all__ = ["MM_PER_M", "array_to_pointcloud2", "cloud_arrays_from_msg", "cloud_from_msg", "cloud_to_msg",
           "point_field_type_name", "pointcloud2_to_array", "unstructured_xyz", "xyz_intensity_arrays",
           "xyzi_array", "xyzi_dtype",
           "float64_sequence", "uint32_sequence", "flag_array", "float64_array", "time_to_msg",
           "plate_pose_to_msg", "plate_pose_from_msg", "fiducials_to_response", "fiducials_from_response",
           "SETPOINT_FLAGS", "OPTIONAL_SETPOINT_FIELDS", "start_setpoints_response", "append_setpoints",
           "setpoints_to_response", "setpoints_from_response", "trained_model_from_response"]

# ---------------------------------------------------------------------------------------------
# Calibration messages <-> core types
# ---------------------------------------------------------------------------------------------
# rclpy wants array.array (or lists) for unbounded sequence fields and hands array.array back;
# numpy views over those buffers avoid per-element Python objects both ways.


def float64_sequence(values: npt.ArrayLike) -> array.array:
    """Return an ``array('d')`` for a float64[] field (one copy, no per-element objects)."""
    sequence = array.array("d")
    sequence.frombytes(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    return sequence


def uint32_sequence(values: npt.ArrayLike) -> array.array:
    """Return an ``array('I')`` for a uint32[] field."""
    sequence = array.array("I")
    sequence.frombytes(np.ascontiguousarray(values, dtype=np.uint32).tobytes())
    return sequence


def flag_array(sequence) -> np.ndarray:
    """Return a bool array from a uint8[] flag field (0 = false, anything else = true)."""
    if isinstance(sequence, (array.array, bytes)):
        return np.frombuffer(sequence, dtype=np.uint8) != 0
    return np.asarray(sequence, dtype=np.uint8).reshape(-1) != 0


def float64_array(sequence) -> np.ndarray:
    """Return a float64 numpy array over a float64[] field's buffer (a copy when it is a list)."""
    if isinstance(sequence, array.array):
        return np.frombuffer(sequence, dtype=np.float64) if len(sequence) else np.empty(0)
    return np.asarray(sequence, dtype=np.float64)


def marked_polylines(paths) -> list[np.ndarray]:
    """Split a ``MarkedPaths`` message into its polylines, each (K, 3) x, y, z in mm; [] when it holds none."""
    points = np.column_stack([float64_array(paths.x), float64_array(paths.y), float64_array(paths.z)])
    if not len(points):
        return []
    return np.split(points, np.asarray(paths.polyline_starts[1:], dtype=int))


def time_to_msg(seconds: float) -> Time:
    """Return a builtin_interfaces Time from seconds since the epoch (UTC)."""
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
    """Return a ``fiducials.FiducialMeasurement`` from a MeasureFiducials response and the pose it used."""
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
    """Empty the array fields of a CorrectSetpoints response and return them by field name.

    The field names are those of ``CorrectedSetpoints``; the fields are extended chunk by chunk
    (``append_setpoints``): nothing of the whole answer's size is allocated, concatenated or
    converted at once while the interpreter lock is held.
    """
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
    """Return a ``correction.CorrectedSetpoints`` from a CorrectSetpoints response."""
    return CorrectedSetpoints(x=float64_array(response.x), y=float64_array(response.y),
                              alpha_x=float64_array(response.alpha_x), alpha_y=float64_array(response.alpha_y),
                              focus_shift=float64_array(response.focus_shift),
                              inside_calibrated_field=flag_array(response.inside_calibrated_field),
                              within_limits=flag_array(response.within_limits),
                              uncertainty_k2_mm=float64_array(response.uncertainty_k2_mm)
                              if hasattr(response, "uncertainty_k2_mm") else None)


def trained_model_from_response(response) -> TrainedModel:
    """Return a ``training.TrainedModel`` from a TrainCorrection response (ValueError on a bad model)."""
    model = yaml.load(response.model_yaml, Loader=SAFE_LOADER)     # libyaml's parser: the same values, faster
    if not isinstance(model, dict) or "type" not in model:
        raise ValueError("the trainer answered with a model that is not a mapping with a 'type'")
    return TrainedModel(model=model, method=response.method, neurons=int(response.neurons),
                        spread_mm=float(response.spread_mm), cv_rms_mm=float(response.cv_rms_mm))
