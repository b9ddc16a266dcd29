"""plate_pose: serves ``plate_pose/estimate``, the plate plane fitted to a cloud."""
from __future__ import annotations

import math

from gls_calibration.ros import conversions
from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.runtime import run_node
from gls_calibration.ros.service_errors import answers_errors
from gls_calibration.scan.plate_pose import estimate_plate_pose
from gls_calibration_msgs.srv import EstimatePlatePose


class PlatePoseNode(GlsNode):
    """Thin wrapper over ``plate_pose.estimate_plate_pose``."""

    def __init__(self, **kwargs) -> None:
        super().__init__("plate_pose", **kwargs)
        self.distance_threshold_mm = self.declare(
            "distance_threshold_mm", 0.2, "RANSAC inlier distance to the plane (mm)", minimum=1e-4)
        self.head_direction = head_direction(self.declare(
            "head_direction", [0.0, 0.0, -1.0],
            "direction towards the galvo head in the scan frame (the normal is oriented along it)"))
        self.seed = self.declare("seed", 0, "seed of the RANSAC sampling", minimum=0)
        self.create_service(EstimatePlatePose, "plate_pose/estimate", self.on_estimate)

    @answers_errors(ValueError)
    def on_estimate(self, request, response):
        """Fit the plane; ``success=false`` with the reason on bad clouds."""
        xyz, _ = conversions.cloud_arrays_from_msg(request.cloud)
        pose = estimate_plate_pose(xyz, distance_threshold_mm=self.distance_threshold_mm,
                                   head_direction=tuple(self.head_direction), seed=self.seed)
        response.success = True
        response.message = f"plane fitted to {pose.inlier_count} points, flatness {pose.flatness_rms_mm:.4f} mm RMS"
        response.pose = conversions.plate_pose_to_msg(pose)
        return response


def head_direction(value) -> tuple[float, float, float]:
    """Return the ``head_direction`` parameter's value as 3 floats; ValueError if unusable.

    ValueError unless 3 finite numbers, not all zero: a zero direction orients no normal. Checked at
    start, not at the first request.
    """
    items = list(value) if isinstance(value, (list, tuple)) or hasattr(value, "tolist") else []
    numbers = [float(item) for item in items
               if isinstance(item, (int, float)) and not isinstance(item, bool) and math.isfinite(float(item))]
    if len(items) != 3 or len(numbers) != 3 or not any(numbers):
        raise ValueError(f"parameter head_direction: 3 finite numbers, not all zero, are needed, got {value!r}")
    return numbers[0], numbers[1], numbers[2]


def main(args=None) -> int:
    """Console script ``gls-plate-pose``."""
    return run_node(PlatePoseNode, args)
