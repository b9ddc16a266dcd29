"""fiducial_measurement: serves ``fiducials/measure``, ring fiducial centres in a marked-plate scan."""
from __future__ import annotations

from gls_calibration.nodes import conversions
from gls_calibration.fiducials import measure_fiducials
from gls_calibration.nodes.base import GlsNode, answers_errors, run_node
from gls_calibration.targets import RING_RADII_MM
from gls_calibration_msgs.srv import MeasureFiducials


class FiducialMeasurementNode(GlsNode):
    """Thin wrapper over ``fiducials.measure_fiducials``."""

    def __init__(self, **kwargs) -> None:
        super().__init__("fiducial_measurement", **kwargs)
        # The same key as the manager's, from the same config/gls.yaml; a request's own radii win.
        self.ring_radii_mm = tuple(self.declare_numbers(
            "grid.ring_radii_mm", list(RING_RADII_MM), "radii of the rings of a fiducial (mm), for requests "
            "that carry none (the calibration manager sends the radii it marked with)"))
        self.pixel_size_mm = self.declare("pixel_size_mm", 0.1,
                                          "raster pixel for unorganized clouds (mm)", minimum=0.005, maximum=5.0)
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
