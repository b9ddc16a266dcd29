"""correction: serves ``correct_setpoints`` and ``correction/load`` (hot reload)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from gls_calibration.nodes import conversions
from gls_calibration.calibration_record import correction_from_record
from gls_calibration.correction import Correction
from gls_calibration.nodes.base import GlsNode, answers_errors, run_node
from gls_calibration.nodes.head_parameters import declare_head_geometry
from gls_calibration.persistence import CalibrationFileError, CalibrationStore
from gls_calibration_msgs.srv import CorrectSetpoints, LoadCalibration


class CorrectionNode(GlsNode):
    """Corrects setpoints with the loaded calibration; the nominal model when there is none."""

    def __init__(self, **kwargs) -> None:
        super().__init__("correction", **kwargs)
        self.geometry = declare_head_geometry(self)
        self.store = CalibrationStore(Path(self.declare("calibration_dir", "calibrations",
                                                        "folder of the calibration store")))
        self.correction: Optional[Correction] = Correction(self.geometry)
        self.file = ""
        self.problem = ""
        self._load("")
        self.create_service(CorrectSetpoints, "correct_setpoints", self.on_correct)
        self.create_service(LoadCalibration, "correction/load", self.on_load)

    def _load(self, file: str) -> str:
        """Load ``file`` (empty: the active calibration); on failure refuse corrections until a good load."""
        try:
            path = Path(file) if file else self.store.active_path()
        except CalibrationFileError as error:
            self.correction, self.file = None, str(self.store.pointer_path)
            self.problem = f"calibration store pointer is unusable: {error}"
            self.get_logger().error(self.problem)
            return self.problem
        if path is None:
            self.correction, self.file, self.problem = Correction(self.geometry), "", ""
            self.get_logger().info("no calibration in the store: nominal model")
            return "no calibration in the store: nominal model in use"
        try:
            record = self.store.load(path)
            correction = correction_from_record(record, self.geometry)
        except (CalibrationFileError, ValueError, OSError) as error:
            self.correction, self.file = None, str(path)
            self.problem = f"calibration file {path} is unusable: {error}"
            self.get_logger().error(self.problem)
            return self.problem
        self.correction, self.file, self.problem = correction, str(path), ""
        self.get_logger().info(f"calibration loaded from {path}")
        return f"calibration loaded from {path}"

    def on_load(self, request, response):
        """Hot reload."""
        response.message = self._load(request.file)
        response.success = not self.problem
        response.file = self.file
        return response

    @answers_errors(ValueError)
    def on_correct(self, request, response):
        """Correct the targets; ``success=false`` and a message naming the problem on bad input."""
        if self.correction is None:
            response.success = False
            response.message = f"corrections refused: {self.problem}"
            return response
        result = self.correction.correct(request.x, request.y, request.z if len(request.z) else None)
        conversions.setpoints_to_response(result, response)
        unreachable = int((~result.within_limits).sum())
        if unreachable:
            first = int((~result.within_limits).argmax())
            response.success = False
            response.message = (f"{unreachable} target(s) beyond the mirror limits or the focus range "
                                 f"(first at index {first}); see within_limits")
        else:
            response.success = True
            response.message = "corrected" if self.file else "no calibration loaded: nominal model"
        return response


def main(args=None) -> None:
    """Console script ``gls-correction``."""
    run_node(CorrectionNode, args)
