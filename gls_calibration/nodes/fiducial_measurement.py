"""fiducial_measurement: serves ``fiducials/measure``, ring fiducial centres in a marked-plate scan."""
from __future__ import annotations

from gls_calibration.fiducials.measure import measure_fiducials
from gls_calibration.fiducials.targets import RING_RADII_MM
from gls_calibration.ros import conversions
from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.runtime import run_node
from gls_calibration.ros.service_errors import answers_errors
from gls_calibration_msgs.srv import MeasureFiducials


MIN_PIXEL_MM = 0.005
"""A given raster pixel below this makes a plate image of tens of thousands of pixels a side."""


class FiducialMeasurementNode(GlsNode):
    """Thin wrapper over ``fiducials.measure_fiducials``."""

    def __init__(self, **kwargs) -> None:
        super().__init__("fiducial_measurement", **kwargs)
        # The same key as the manager's, from the same config/gls.yaml; a request's own radii win.
        self.ring_radii_mm = tuple(self.declare_numbers(
            "grid.ring_radii_mm", list(RING_RADII_MM), "radii of the rings of a fiducial (mm), for requests "
            "that carry none (the calibration manager sends the radii it marked with)"))
        # 0 (the default): from the cloud's own point spacing, as gls-measure does without --pixel
        pixel_mm = self.declare("pixel_size_mm", 0.0, "raster pixel for unorganized clouds (mm); 0: from the "
                                "cloud's own point spacing", minimum=0.0, maximum=5.0)
        if 0.0 < pixel_mm < MIN_PIXEL_MM:
            raise ValueError(f"parameter pixel_size_mm must be 0 (from the point spacing) or at least "
                             f"{MIN_PIXEL_MM:g} mm, got {pixel_mm:g}")
        self.pixel_size_mm = pixel_mm or None
        self.marks_darker = self.declare("marks_darker", True, "marks are darker than the plain plate")
        self.create_service(MeasureFiducials, "fiducials/measure", self.on_measure)

    @answers_errors(ValueError)
    def on_measure(self, request, response):
        """Measure; ``success=false`` with the reason when nothing usable is found."""
        xyz, intensity = conversions.cloud_arrays_from_msg(request.cloud)
        pose = conversions.plate_pose_from_msg(request.pose)
        radii = tuple(request.ring_radii_mm) or self.ring_radii_mm
        measurement = measure_fiducials(
            xyz, intensity, pose, ring_radii_mm=radii, pixel_size_mm=self.pixel_size_mm,
            expected_count=request.expected_count or None, marks_darker=self.marks_darker)
        conversions.fiducials_to_response(measurement, response)
        if measurement.extra:
            # The response has no field for a surplus (missing is then 0), so say it here.
            self.get_logger().warning(
                f"{len(measurement.centres)} fiducials found, {measurement.extra} more than the "
                f"{request.expected_count} expected: check expected_count or the scan for spurious rings")
        response.success = True
        response.message = f"{len(measurement.centres)} fiducials found"
        return response


def main(args=None) -> int:
    """Console script ``gls-fiducial-measurement``."""
    return run_node(FiducialMeasurementNode, args)
